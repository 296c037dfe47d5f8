//! Publication and grants: the manifest of the current model, every version published to the
//! workers, a new best model announced to the cars that follow "best", and the grant rounds
//! that give the workers the episodes the next update still needs (`grants.rs` decides them).

use super::link::LinkError;
use super::pending::PendingEval;
use super::state::Run;
use policy::exchange::PolicyVersion;
use policy::folder::Manifest;
use std::sync::Arc;
use std::time::Instant;

impl Run<'_> {
    /// The manifest of the current model, with `training`'s figures.
    pub(super) fn manifest(&self, training: serde_json::Value) -> Manifest {
        Manifest {
            format: "paddock-model-1".into(),
            policy_version: self.algo.version(),
            parent: self.parent.clone(),
            weights_sha256: String::new(),
            obs_size: self.spec.obs_size,
            observation: self.spec.observation.clone(),
            training,
        }
    }

    /// Make the current model the one workers act with.
    pub(super) fn publish(&mut self) -> Result<(), LinkError> {
        let p = PolicyVersion {
            version: self.algo.version(),
            model: Arc::new(self.algo.model().clone()),
            metadata: self.metadata.clone(),
        };
        let manifest = self.manifest(serde_json::json!({"run": self.spec.name}));
        self.link.publish(&p, &manifest, &self.signer)
    }

    /// Announce the evaluated checkpoint `p` as the new best model (with its `manifest`).
    pub(super) fn publish_best(&mut self, p: &PendingEval, manifest: &Manifest) -> Result<(), LinkError> {
        let best =
            PolicyVersion { version: p.version, model: Arc::new(p.model.clone()), metadata: self.metadata.clone() };
        self.link.best(&best, manifest, &self.signer)
    }

    /// Flow control: grant what the next update still needs (see `grants.rs`); nothing while
    /// a check that may stop the run goes first (the workers run it before any episodes).
    /// Each grant says which versions' checks are closed, so that a worker still running a
    /// verification that can no longer matter (another world's missed) drops it.
    pub(super) fn grant(&mut self, workers: &[String]) -> Result<(), LinkError> {
        if self.stop_reason.is_some() || self.check_goes_first() {
            return Ok(());
        }
        let shortfall = self.want.saturating_sub(self.buffer.len() as u64);
        match self.grants.due(self.algo.version(), shortfall, workers, Instant::now()) {
            Some(mut credit) => {
                credit.checks_closed_through = self.checks_closed_through();
                self.link.grant(&credit)
            }
            None => Ok(()),
        }
    }

    /// The newest version whose checks are all closed: below the evaluation under way, else
    /// the last one closed (checkpoints are evaluated in the order they were written, each
    /// once, and a verification is its evaluation's sequel).
    pub(super) fn checks_closed_through(&self) -> u64 {
        match &self.evals.pending {
            Some(p) => p.version.saturating_sub(1),
            None => self.evals.evaluated_version.unwrap_or(0),
        }
    }
}
