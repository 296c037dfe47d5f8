//! What a run is given ([`RunSpec`], with how it opens its folder, [`Start`]) and what it
//! gives back: how it ended ([`Summary`]), or why it could not go on ([`RunFailure`]).

use super::link::LinkError;
use super::stop::StopRules;
use crate::checkpoints::{CheckpointRecord, RunError};
use crate::hyperparams::Hyperparameters;
use crate::update::LearnerState;
use faer::Par;
use policy::ModelMetadata;
use std::path::PathBuf;

/// Why a run could not go on.
#[derive(Debug, thiserror::Error)]
pub enum RunFailure {
    /// The run folder.
    #[error(transparent)]
    Run(#[from] RunError),
    /// A model folder (resume, clone, checkpoint).
    #[error(transparent)]
    Model(#[from] policy::ModelError),
    /// The inputs disagree (resume with another model, say).
    #[error("{0}")]
    Inputs(String),
    /// The transport.
    #[error("link: {0}")]
    Link(#[from] LinkError),
    /// A worker failed (a reward that raised, say): its message, traceback included.
    #[error("worker {worker} failed: {error}")]
    Worker {
        /// The worker.
        worker: String,
        /// What it said.
        error: String,
    },
}

/// How the run folder is opened.
#[derive(Clone, Debug, PartialEq)]
pub enum Start {
    /// A new folder (refused if it holds a run); fresh weights, or the given model folder's
    /// (transfer learning).
    New {
        /// Start from this model folder's weights.
        clone_from: Option<PathBuf>,
    },
    /// Delete the folder and start afresh.
    Force,
    /// Continue from the folder's last checkpoint (refused if there is none).
    Resume,
    /// Continue if the folder holds a run, else start anew (a learner restarted mid-job).
    ResumeOrNew {
        /// Start from this model folder's weights when new.
        clone_from: Option<PathBuf>,
    },
}

/// Everything a run needs to know.
#[derive(Clone)]
pub struct RunSpec {
    /// Names the run in logs and manifests (a job id, or the world).
    pub name: String,
    /// The model's metadata.
    pub metadata: ModelMetadata,
    /// PPO settings.
    pub hyper: Hyperparameters,
    /// Observation length.
    pub obs_size: usize,
    /// The observation settings, for the manifest (the simulator's, as JSON).
    pub observation: serde_json::Value,
    /// The simulator configuration's text, kept in the run folder as `sim.toml`.
    pub sim_toml: String,
    /// The worlds trained on; evaluations run on each.
    pub worlds: Vec<String>,
    /// The run folder.
    pub out: PathBuf,
    /// How to open it.
    pub start: Start,
    /// Seed for fresh weights, minibatch order and evaluation noise.
    pub seed: u64,
    /// Episodes older than this many versions are dropped (and counted).
    pub max_policy_lag: u64,
    /// Evaluation trials per world per checkpoint.
    pub eval_trials: u32,
    /// Seconds between evaluations (and checkpoints).
    pub eval_seconds: f64,
    /// When to stop.
    pub stop: StopRules,
    /// The workers share this machine's cores (`coordinator train`, and `up`'s learner): an
    /// update waits while an evaluation that may stop the run (one chaining a verification)
    /// or a verification is under way, so that its trials run on every core and the run
    /// stops as soon as they hold. A learner on a machine of its own trains on.
    pub checks_first: bool,
    /// Cores for the update (the camera networks split over them; the MLP does not).
    pub par: Par,
    /// The GPU PPO's update runs on, when it trains alone (`crate::device::open`); `None`:
    /// faer on the CPU.
    pub gpu: Option<std::sync::Arc<gpu::Gpu>>,
    /// A learner team member taking the run over from a leader that went away: its state
    /// (the team's, as of the last update, and SAC's replay memory as bytes), used when it is
    /// newer than the run folder's.
    pub adopt: Option<(LearnerState, Option<Vec<u8>>)>,
    /// The key that signs every published model and model folder (PKCS#8 PEM); `None`: the
    /// run folder's `signing.key`, made on first use (its `signing.pub` is what cars trust).
    pub signing_key: Option<PathBuf>,
    /// The worlds' tracks as lines, drawn in the MCAP log (a world without lines is logged
    /// without its track).
    pub tracks: Vec<policy::TrackLines>,
}

/// How a run ended.
#[derive(Clone, Debug)]
pub struct Summary {
    /// Why it stopped.
    pub stop_reason: String,
    /// Updates made (in this process).
    pub iterations: u64,
    /// Episodes trained on.
    pub episodes: u64,
    /// Episodes received.
    pub episodes_received: u64,
    /// Episodes dropped as stale.
    pub dropped_stale: u64,
    /// Environment steps received.
    pub env_steps: u64,
    /// Seconds.
    pub seconds: f64,
    /// The best checkpoint (the verified one when a verification held).
    pub best: Option<CheckpointRecord>,
    /// The checkpoint that held its verification, and what it did.
    pub verified: Option<String>,
    /// The final policy version.
    pub policy_version: u64,
    /// The run folder.
    pub run_dir: PathBuf,
    /// Writes to the run folder that failed, and the last one's error.
    pub write_failures: (u64, String),
}
