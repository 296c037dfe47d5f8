//! The seam between a training run and its algorithm. [`crate::run::run`] publishes,
//! grants, gathers, checkpoints and evaluates the same way for every algorithm; what differs
//! is here: how an iteration's episodes become a new policy version, whether experience from
//! an older version is still usable (PPO: within `max_policy_lag`; SAC: always, it is
//! off-policy), and what a checkpoint keeps beyond the model (SAC's critics and replay memory).

use crate::ppo::{Ppo, Refused, UpdateStats};
use crate::run::Team;
use policy::{ActorCritic, Trajectory};
use std::path::Path;

/// What a training run needs of its algorithm.
pub trait Algorithm {
    /// DeepRacer's name for it (`training_algorithm`).
    fn name(&self) -> &'static str;
    /// The policy version workers act with (+1 per accepted update).
    fn version(&self) -> u64;
    /// The model published, evaluated and saved.
    fn model(&self) -> &ActorCritic;
    /// Set the learning rate the next update uses (the run's schedule).
    fn set_lr(&mut self, lr: f64);
    /// Off-policy: every episode is usable whatever version acted, and the next round of
    /// episodes is granted while an update runs.
    fn off_policy(&self) -> bool;
    /// One iteration on these episodes (with the learner team, when there is one).
    fn update(&mut self, trajs: &[Trajectory], team: Option<&mut dyn Team>) -> Result<UpdateStats, Refused>;
    /// Write what a checkpoint keeps beyond the model into its folder `dir` (nothing for PPO).
    fn save_state(&self, _dir: &Path) -> Result<(), String> {
        Ok(())
    }
    /// Write what a resumed run continues with beyond the checkpoint into the run folder
    /// `root`, when the run ends (SAC's replay memory; nothing for PPO).
    fn save_memory(&self, _root: &Path) -> Result<(), String> {
        Ok(())
    }
}

impl Algorithm for Ppo {
    fn name(&self) -> &'static str {
        "clipped_ppo"
    }

    fn version(&self) -> u64 {
        self.version
    }

    fn model(&self) -> &ActorCritic {
        &self.model
    }

    fn set_lr(&mut self, lr: f64) {
        Ppo::set_lr(self, lr)
    }

    fn off_policy(&self) -> bool {
        false
    }

    fn update(&mut self, trajs: &[Trajectory], team: Option<&mut dyn Team>) -> Result<UpdateStats, Refused> {
        match team {
            Some(team) => team.update(self, trajs),
            None => Ppo::update(self, trajs),
        }
    }
}
