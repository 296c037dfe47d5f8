//! How a run reaches the outside: its workers through a [`Link`] (what arrives is an
//! [`Inbound`]; a link names the learner [`Team`] the updates are shared with, when there is
//! one), and whoever hears about its iterations and evaluations ([`Observer`]).

use super::status::RunStatus;
use crate::algorithm::Team;
use crate::record::{EvalRecord, IterationRecord};
use policy::exchange::{Credit, EvalReport, EvalRequest, Experience, PolicyVersion};
use policy::folder::Manifest;
use policy::signature::Signer;
use std::time::Duration;

/// What a link failed at.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct LinkError(pub String);

/// What arrives from the workers (and from whoever may stop the run).
#[derive(Clone, Debug)]
pub enum Inbound {
    /// Episodes.
    Experience(Experience),
    /// Evaluation trials.
    Eval(EvalReport),
    /// Stop gracefully (final evaluation, checkpoint and best model), for this reason.
    Stop(String),
    /// A worker cannot go on; the run fails with its message.
    Failed {
        /// The worker.
        worker: String,
        /// Its error, traceback included.
        error: String,
    },
}

/// How the run reaches its workers.
pub trait Link {
    /// Make `policy` the one workers act with (every version is published).
    fn publish(&mut self, policy: &PolicyVersion, manifest: &Manifest, signer: &Signer) -> Result<(), LinkError>;
    /// A new best model (after the evaluation that made it best): cars following "best"
    /// drive it. Default: nothing (no car listens in one process).
    fn best(&mut self, _policy: &PolicyVersion, _manifest: &Manifest, _signer: &Signer) -> Result<(), LinkError> {
        Ok(())
    }
    /// Announce a grant (called again every second: it must be idempotent).
    fn grant(&mut self, credit: &Credit) -> Result<(), LinkError>;
    /// Ask a worker for evaluation trials.
    fn request_eval(&mut self, req: &EvalRequest) -> Result<(), LinkError>;
    /// The next message, waiting at most `timeout`.
    fn next(&mut self, timeout: Duration) -> Result<Option<Inbound>, LinkError>;
    /// The run's figures (after every update and every second).
    fn status(&mut self, status: &RunStatus) -> Result<(), LinkError>;
    /// The workers alive now.
    fn workers(&mut self) -> Vec<String>;
    /// The learners this run's updates are shared with (DD-PPO); `None`: this one alone.
    fn team(&mut self) -> Option<&mut dyn Team> {
        None
    }
}

/// Hears about iterations and evaluations (a terminal, a log). Default: nothing.
pub trait Observer {
    /// After every update.
    fn iteration(&mut self, _it: &IterationRecord) {}
    /// After every complete evaluation (all worlds).
    fn evaluation(&mut self, _e: &EvalRecord) {}
}

/// An observer that says nothing.
pub struct Quiet;
impl Observer for Quiet {}
