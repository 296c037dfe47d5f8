//! The policy gate: every policy a sim agent receives over the network is checked before the
//! agent acts with it, the car's check first (signed by a key the agent trusts, over exactly
//! these weights, metadata and manifest), then the job's (its sizes, version and actions), on
//! a thread of its own so that checking a large model never holds up the environments.
//!
//! The keys: those the agent is given (`--trust FILE`, and `models.pub` in the credentials
//! folder). An agent given none pins, per job, the key that signed the job's first valid
//! policy (trust on first use, as ssh does with host keys) and takes no other key's policies
//! for that job from then on. An unsigned policy is always refused. The signature is checked
//! before the weights are parsed: nothing unsigned reaches the model decoder.

use anyhow::Context;
use policy::exchange::PolicyVersion;
use policy::signature::TrustedKeys;
use protocol::exchange::{self as wire, JobView};
use protocol::{Actions, DecodeError, PolicyUpdate};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::mpsc::{Receiver, SyncSender, TrySendError, sync_channel};

/// Which keys an agent trusts.
#[derive(Clone, Debug)]
pub enum Trust {
    /// These keys and no other.
    Keys(TrustedKeys),
    /// Per job, the first key that signs a valid policy.
    FirstUse,
}

/// The keys an agent trusts: the `--trust` files and, with a credentials folder, its
/// `models.pub` (when the folder has one); [`Trust::FirstUse`] when that makes none.
pub fn trust(files: &[PathBuf], certs: Option<&Path>) -> anyhow::Result<Trust> {
    let mut files = files.to_vec();
    if let Some(p) = certs.map(|d| d.join(protocol::secure::MODEL_PUB_FILE)).filter(|p| p.exists()) {
        files.push(p);
    }
    if files.is_empty() {
        return Ok(Trust::FirstUse);
    }
    let keys = TrustedKeys::load(&files).context("--trust")?;
    tracing::info!(
        "policies are taken only when signed by {}",
        files.iter().map(|f| f.display().to_string()).collect::<Vec<_>>().join(", ")
    );
    Ok(Trust::Keys(keys))
}

/// What a policy must fit: the job it is for.
#[derive(Clone, Debug)]
pub struct GateJob {
    /// The job's id.
    pub job_id: String,
    /// Its observation size.
    pub obs_size: usize,
    /// Its worlds.
    pub worlds: Vec<String>,
    /// Its action space's shape.
    pub actions: Actions,
}

/// A policy that passed, with the name of the key that signed it.
pub struct Passed {
    /// The policy.
    pub policy: PolicyVersion,
    /// The trusted key's name (its file, or "first use").
    pub key: String,
}

/// The check, without the thread (the gate runs it; tests call it directly).
#[derive(Debug)]
pub struct Checker {
    trust: Trust,
    /// Under [`Trust::FirstUse`]: each job's pinned key, the oldest first.
    pins: Vec<(String, TrustedKeys)>,
}

/// Jobs whose first-use keys are remembered (the oldest is forgotten past this).
const MAX_PINS: usize = 64;

impl Checker {
    /// A checker trusting `trust`.
    pub fn new(trust: Trust) -> Checker {
        Checker { trust, pins: Vec::new() }
    }

    /// Check one policy for `job`; the reason when it is refused (signature refusals start
    /// with "signature:").
    pub fn check(&mut self, job: &GateJob, u: PolicyUpdate) -> Result<Passed, DecodeError> {
        let refuse = |e: policy::signature::SignatureError| DecodeError::Invalid(format!("signature: {e}"));
        if u.job_id != job.job_id {
            return Err(DecodeError::Invalid(format!("a policy for job {:?}, not {:?}", u.job_id, job.job_id)));
        }
        // Checked over the message's own bytes: nothing copied, nothing parsed before.
        let Some(sig) = wire::policy_signature(&u)? else {
            return Err(refuse(policy::signature::SignatureError::Refused("the model is not signed".into())));
        };
        let verify = |t: &TrustedKeys| {
            t.verify(&sig, &u.weights, &u.model_metadata_json, &u.manifest_json).map(str::to_string).map_err(refuse)
        };
        let pinned = self.pins.iter().find(|(j, _)| *j == job.job_id).map(|(_, t)| t);
        let (key, pin) = match (&self.trust, pinned) {
            (Trust::Keys(t), _) | (Trust::FirstUse, Some(t)) => (verify(t)?, None),
            (Trust::FirstUse, None) => {
                let mut t = TrustedKeys::default();
                t.add_hex("first use", &sig.public_key).map_err(refuse)?;
                verify(&t)?;
                ("first use".to_string(), Some((t, sig.public_key.clone())))
            }
        };
        let view = JobView { job_id: &job.job_id, obs_size: job.obs_size, worlds: &job.worlds, actions: job.actions };
        let policy = wire::policy_from_wire(u, &view)?;
        if let Some((t, hex)) = pin {
            tracing::warn!(
                job = %job.job_id,
                "no key to trust was given (--trust FILE, or models.pub with --certs DIR): trusting key {hex}, \
                 which signed this job's first policy, and no other for this job"
            );
            if self.pins.len() >= MAX_PINS {
                self.pins.remove(0);
            }
            self.pins.push((job.job_id.clone(), t));
        }
        Ok(Passed { policy, key })
    }
}

impl std::fmt::Debug for Passed {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "v{} signed by {}", self.policy.version, self.key)
    }
}

/// A policy's verdict, for the job it came for.
#[derive(Debug)]
pub struct Verdict {
    /// The job.
    pub job_id: String,
    /// The policy, or why it was refused.
    pub result: Result<Passed, DecodeError>,
}

/// Policies waiting for the gate's thread; more are refused as "busy" (the agent asks again
/// for the latest when it needs one).
const QUEUE: usize = 4;

/// The [`Checker`] on a thread of its own.
pub struct PolicyGate {
    tx: SyncSender<(Arc<GateJob>, PolicyUpdate)>,
    rx: Receiver<Verdict>,
}

impl PolicyGate {
    /// Start the gate's thread.
    pub fn start(trust: Trust) -> std::io::Result<PolicyGate> {
        let (tx, work) = sync_channel::<(Arc<GateJob>, PolicyUpdate)>(QUEUE);
        let (done, rx) = std::sync::mpsc::channel();
        let mut checker = Checker::new(trust);
        std::thread::Builder::new().name("policy-gate".into()).spawn(move || {
            while let Ok((job, u)) = work.recv() {
                let result = checker.check(&job, u);
                if done.send(Verdict { job_id: job.job_id.clone(), result }).is_err() {
                    break;
                }
            }
        })?;
        Ok(PolicyGate { tx, rx })
    }

    /// Hand a policy to the gate; refused at once when the gate is busy.
    pub fn offer(&self, job: &Arc<GateJob>, u: PolicyUpdate) -> Result<(), DecodeError> {
        match self.tx.try_send((job.clone(), u)) {
            Ok(()) => Ok(()),
            Err(TrySendError::Full(_)) => {
                Err(DecodeError::Invalid(format!("the policy check is busy ({QUEUE} policies waiting)")))
            }
            Err(TrySendError::Disconnected(_)) => Err(DecodeError::Invalid("the policy check has stopped".into())),
        }
    }

    /// A verdict, if one is ready.
    pub fn next(&self) -> Option<Verdict> {
        self.rx.try_recv().ok()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use policy::signature::Signer;
    use policy::{ActorCritic, Manifest, ModelMetadata};
    use rand::SeedableRng;

    fn job() -> GateJob {
        GateJob { job_id: "j".into(), obs_size: 10, worlds: vec!["reinvent_base".into()], actions: actions() }
    }

    fn metadata() -> ModelMetadata {
        ModelMetadata::default_state_vector()
    }

    fn actions() -> Actions {
        Actions::of(&metadata().action_space)
    }

    /// A policy update for job `j`, version `v`, signed by `signer` (or not).
    fn update(v: u64, signer: Option<&Signer>) -> PolicyUpdate {
        let meta = metadata();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(v);
        let model = ActorCritic::new(&meta, 10, &mut rng);
        let p = PolicyVersion { version: v, model: Arc::new(model), metadata: Arc::new(meta) };
        let manifest = Manifest {
            format: "paddock-model-1".into(),
            policy_version: v,
            parent: None,
            weights_sha256: String::new(),
            obs_size: 10,
            observation: serde_json::json!({}),
            training: serde_json::json!({}),
        };
        wire::policy_to_wire("j", &p, &manifest, signer)
    }

    fn refusal(c: &mut Checker, u: PolicyUpdate) -> String {
        c.check(&job(), u).map(|p| p.key).unwrap_err().to_string()
    }

    /// Issue 35: only policies signed by a trusted key pass.
    #[test]
    fn only_policies_signed_by_a_trusted_key_pass() {
        let learner = Signer::from_seed([1; 32]);
        let thief = Signer::from_seed([2; 32]);
        let mut trust = TrustedKeys::default();
        trust.add("models.pub", &learner);
        let mut c = Checker::new(Trust::Keys(trust));
        assert_eq!(c.check(&job(), update(3, Some(&learner))).unwrap().key, "models.pub");
        assert!(refusal(&mut c, update(4, None)).contains("signature: the model is not signed"));
        assert!(refusal(&mut c, update(4, Some(&thief))).contains("which is not trusted"));
        // The learner's signature over other weights.
        let mut tampered = update(5, Some(&learner));
        tampered.signature_json = update(6, Some(&learner)).signature_json;
        assert!(refusal(&mut c, tampered).contains("changed after signing"));
        // Signed, but not for this job's shape: the job's checks still hold.
        let mut other = update(7, Some(&learner));
        other.job_id = "k".into();
        assert!(refusal(&mut c, other).contains("not \"j\""));
    }

    /// Issue 35: without keys the first signer of a job is pinned.
    #[test]
    fn without_keys_the_first_signer_of_a_job_is_pinned() {
        let learner = Signer::from_seed([1; 32]);
        let thief = Signer::from_seed([2; 32]);
        let mut c = Checker::new(Trust::FirstUse);
        assert!(refusal(&mut c, update(1, None)).contains("not signed"));
        // A signature that does not hold pins nothing.
        let mut bad = update(1, Some(&thief));
        bad.signature_json = update(2, Some(&thief)).signature_json;
        assert!(refusal(&mut c, bad).contains("changed after signing"));
        assert_eq!(c.check(&job(), update(2, Some(&learner))).unwrap().key, "first use");
        assert!(refusal(&mut c, update(3, Some(&thief))).contains("which is not trusted"));
        assert!(c.check(&job(), update(4, Some(&learner))).is_ok());
    }

    /// Issue 35: the gate checks on its own thread and says when it is busy.
    #[test]
    fn the_gate_checks_on_its_own_thread_and_says_when_it_is_busy() {
        let learner = Signer::from_seed([1; 32]);
        let gate = PolicyGate::start(Trust::FirstUse).unwrap();
        let j = Arc::new(job());
        gate.offer(&j, update(1, Some(&learner))).unwrap();
        gate.offer(&j, update(2, None)).unwrap();
        let mut verdicts = Vec::new();
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(20);
        while verdicts.len() < 2 {
            assert!(std::time::Instant::now() < deadline, "no verdicts");
            match gate.next() {
                Some(v) => verdicts.push(v),
                None => std::thread::sleep(std::time::Duration::from_millis(5)),
            }
        }
        assert_eq!(verdicts[0].result.as_ref().unwrap().policy.version, 1);
        assert!(verdicts[1].result.as_ref().unwrap_err().to_string().contains("not signed"));
        // More than the queue holds at once: the rest are refused as busy, never blocked on.
        // Each takes the check a checksum of 4 MB (some milliseconds), handing one over a copy
        // (a fraction of that): the queue fills.
        let mut big = update(9, None);
        big.weights = vec![7; 4 << 20];
        let sig = learner.sign(&big.weights, &big.model_metadata_json, &big.manifest_json);
        big.signature_json = serde_json::to_string(&sig).unwrap();
        let busy = (0..64).filter_map(|_| gate.offer(&j, big.clone()).err()).count();
        assert!(busy >= 16, "a flood is turned away: {busy} of 64 refused");
    }
}
