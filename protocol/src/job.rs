//! The job document: a job spec with every file it names read in, as the coordinator stores
//! it and sends it to the learner (JSON inside [`crate::AssignmentTable::job_json`]).
//! Everything the learner needs is here, so that it needs no simulator.

use serde::{Deserialize, Serialize};

/// When a job stops (whichever comes first).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct StopSpec {
    /// Wall-clock minutes from the job's start.
    pub minutes: f64,
    /// Episodes trained on.
    pub max_episodes: u64,
    /// Mean progress (%) over the last `window` episodes.
    pub target_progress: Option<f64>,
    /// Mean episode reward over the last `window` episodes.
    pub target_reward: Option<f64>,
    /// Episodes in the window.
    pub window: u64,
    /// Compute budget: environment steps across all agents.
    pub env_steps_budget: Option<u64>,
    /// Stop once evaluations complete this many laps (of `eval_trials`, on every world)...
    pub target_laps: Option<u32>,
    /// ...in this many consecutive evaluations.
    pub target_evals: u32,
}

impl Default for StopSpec {
    fn default() -> Self {
        StopSpec {
            minutes: 10.0,
            max_episodes: 1_000_000,
            target_progress: None,
            target_reward: None,
            window: 20,
            env_steps_budget: None,
            target_laps: None,
            target_evals: 1,
        }
    }
}

/// A job with its files inlined.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JobDoc {
    /// The job's id (a key-expression-safe name).
    pub id: String,
    /// Worlds to train on.
    pub worlds: Vec<String>,
    /// The reward's file name (or `builtin:NAME`).
    pub reward_name: String,
    /// The reward's Python source (or `builtin:NAME`).
    pub reward_source: String,
    /// `model_metadata.json` text.
    pub model_metadata_json: String,
    /// `hyperparameters.json` text.
    pub hyperparameters_json: String,
    /// The simulator configuration (TOML).
    pub sim_config_toml: String,
    /// The run folder, on the learner's machine.
    pub out: String,
    /// A model folder to start from, on the learner's machine.
    pub clone_from: Option<String>,
    /// Random seed.
    pub seed: u64,
    /// Environments per sim agent.
    pub envs_per_agent: u32,
    /// Experience older than this many policy versions is dropped.
    pub max_policy_lag: u64,
    /// Stop conditions.
    pub stop: StopSpec,
    /// Evaluation trials per checkpoint (per world).
    pub eval_trials: u32,
    /// The model's observation length (from the model's sensors and the simulator
    /// configuration), so that the learner needs no simulator to know it.
    pub obs_size: u64,
    /// The simulator's observation settings (JSON), for the model's manifest.
    pub observation_json: String,
}
