//! A model folder's evaluation: trials from the start line with the most likely action at
//! every step, on each world, under DeepRacer's evaluation rules (resets, off-track and crash
//! penalties). `coordinator evaluate` prints it; the console keeps it on the model's page.

use anyhow::{Context, Result, bail};
use policy::folder;
use sim_agent::obs::obs_dim;
use sim_agent::race::RaceConfig;
use sim_agent::rollout::{EvalPlan, TrialResult, evaluate_groups};
use sim_agent::{EnvSpec, EvalRules, SimConfig};
use std::path::Path;
use std::sync::Arc;

/// What to evaluate a model on.
#[derive(Clone, Debug)]
pub struct Request {
    /// The worlds, their trials run side by side.
    pub worlds: Vec<tracks::World>,
    /// Drive the tracks the other way round.
    pub reversed: bool,
    /// Trials a world, side by side.
    pub trials: usize,
    /// The environments' seed.
    pub seed: u64,
    /// The race (its objects or bots).
    pub race: RaceConfig,
    /// Resets and penalties.
    pub rules: EvalRules,
    /// Keep each step's pose and what the car saw (the first trial's frames, camera models).
    pub record: bool,
    /// Recording, keep every trial's frames (a live race replays each lap).
    pub all_frames: bool,
}

/// One world's trials.
pub struct WorldTrials {
    /// The world's name.
    pub world: String,
    /// Each trial, in order.
    pub trials: Vec<TrialResult>,
}

/// What was evaluated: the model's policy version, and each world's trials.
pub struct Evaluation {
    /// The policy version of the model folder.
    pub policy_version: u64,
    /// Per world.
    pub worlds: Vec<WorldTrials>,
}

/// Evaluate the model folder `model_dir`.
pub fn run(model_dir: &Path, req: &Request) -> Result<Evaluation> {
    let f = folder::load(model_dir)?;
    let cfg = SimConfig {
        race: req.race.clone(),
        observation: serde_json::from_value(f.manifest.observation.clone())
            .with_context(|| format!("{}: manifest.json's observation settings", model_dir.display()))?,
        record_trace: req.record,
        ..SimConfig::default()
    };
    if obs_dim(&cfg.observation) != f.manifest.obs_size {
        bail!(
            "{}: the observation settings give {} inputs, the model takes {}",
            model_dir.display(),
            obs_dim(&cfg.observation),
            f.manifest.obs_size
        );
    }
    let cfg = Arc::new(cfg);
    let threads = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
    let model = Arc::new(f.model.clone());
    let direction = if req.reversed { tracks::Direction::Reversed } else { tracks::Direction::Forward };
    // Every world's trials side by side, in one batch: each trial is the same as on its
    // world alone, and the batch fills the cores better than the worlds in turn.
    let plan = EvalPlan {
        rules: req.rules.clone(),
        count: req.trials,
        seed: req.seed,
        threads,
        all_frames: req.all_frames,
        spread: true,
        give_up_after_misses: None,
    };
    let groups: Vec<(EnvSpec, EvalPlan)> =
        req.worlds.iter().map(|w| (EnvSpec::from_world(w, direction), plan.clone())).collect();
    let ran = evaluate_groups(&model, &f.metadata.action_space, &groups, &cfg, None, &mut || true)?;
    let worlds =
        req.worlds.iter().zip(ran).map(|(w, g)| WorldTrials { world: w.name.clone(), trials: g.trials }).collect();
    Ok(Evaluation { policy_version: f.manifest.policy_version, worlds })
}
