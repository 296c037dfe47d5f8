//! The seam between a training run and its algorithm. The run (`run/`) publishes,
//! grants, gathers, checkpoints and evaluates the same way for every algorithm; what differs
//! is here: how an iteration's episodes become a new policy version, whether experience from
//! an older version is still usable (PPO: within `max_policy_lag`; SAC: always, it is
//! off-policy), and what a checkpoint keeps beyond the model (SAC's critics and replay memory).
//!
//! [`Shared`] is what a learner team needs of an algorithm to share its updates: every member
//! makes the update from the leader's plan (the iteration's episodes and a seed) as one
//! member of a [`Reducer`] group, and a joiner first takes over the leader's
//! [`LearnerState`] (and SAC's replay memory, as bytes). [`Team`] is the team itself, as its
//! leader's run sees it.
//!
//! The algorithms know nothing of this module: each makes its update and reports its own
//! figures ([`PpoStats`], [`SacStats`]); here they become one [`UpdateStats`], and the traits
//! are implemented for [`Ppo`] and [`SacTrainer`] from their own methods.

use crate::group::{Alone, Reducer};
use crate::ppo::{Ppo, PpoStats};
use crate::sac::{SacStats, SacTrainer};
use crate::update::{LearnerState, Refused, StateMismatch};
use policy::{ActorCritic, FileError, Trajectory};
use std::path::Path;

/// What one update did, in its algorithm's own figures.
#[derive(Clone, Debug, PartialEq)]
pub enum UpdateStats {
    /// PPO's update.
    Ppo(PpoStats),
    /// SAC's iteration.
    Sac(SacStats),
}

impl UpdateStats {
    /// Samples trained on.
    pub fn samples(&self) -> usize {
        match self {
            UpdateStats::Ppo(s) => s.samples,
            UpdateStats::Sac(s) => s.samples,
        }
    }

    /// Gradient steps taken.
    pub fn gradient_steps(&self) -> usize {
        match self {
            UpdateStats::Ppo(s) => s.gradient_steps,
            UpdateStats::Sac(s) => s.gradient_steps,
        }
    }

    /// Policy version after the update.
    pub fn policy_version(&self) -> u64 {
        match self {
            UpdateStats::Ppo(s) => s.policy_version,
            UpdateStats::Sac(s) => s.policy_version,
        }
    }
}

/// The learners that share a run's updates, as their leader (the learner running the
/// training run) sees them. Members join and leave between updates; a member lost
/// during an update makes the team's attempt fail, and the leader makes that update again
/// with whoever is left.
pub trait Team {
    /// This iteration's update, made with the members there are (alone when there are none).
    fn update(&mut self, algo: &mut dyn Shared, trajs: &[Trajectory]) -> Result<UpdateStats, Refused>;
    /// Learners in the team besides its leader.
    fn members(&mut self) -> usize {
        0
    }
}

/// An algorithm whose updates a learner team shares ([`Team`]).
pub trait Shared {
    /// The policy version the next update starts from.
    fn version(&self) -> u64;
    /// The learning rate the next update uses.
    fn lr(&self) -> f64;
    /// Set it (a member takes the plan's).
    fn set_lr(&mut self, lr: f64);
    /// The seed of the next update (the leader draws it and sends it in the plan).
    fn draw_seed(&mut self) -> u64;
    /// The update every member makes from a plan: `trajs` and `seed`, as one member of
    /// `group`. A refused update leaves the weights and optimisers as they were.
    fn update_planned(
        &mut self,
        trajs: &[Trajectory],
        seed: u64,
        group: &mut dyn Reducer,
    ) -> Result<UpdateStats, Refused>;
    /// The update made by a learner alone.
    fn update_alone(&mut self, trajs: &[Trajectory]) -> Result<UpdateStats, Refused> {
        let seed = self.draw_seed();
        self.update_planned(trajs, seed, &mut Alone)
    }
    /// The leader makes alone the update its team's attempt failed at (a member lost midway).
    fn update_again(&mut self, trajs: &[Trajectory]) -> Result<UpdateStats, Refused> {
        self.update_alone(trajs)
    }
    /// What a joiner takes over.
    fn state(&self) -> LearnerState;
    /// What a joiner takes over beyond [`Shared::state`], as bytes: SAC's replay memory
    /// (`None`: nothing).
    fn memory(&self) -> Option<Vec<u8>> {
        None
    }
    /// Take over a member's state and memory. Refused, with nothing changed, unless both fit.
    fn restore(&mut self, state: LearnerState, memory: Option<&[u8]>) -> Result<(), StateMismatch>;
}

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
    fn save_state(&self, _dir: &Path) -> Result<(), FileError> {
        Ok(())
    }
    /// Write what a resumed run continues with beyond the checkpoint into the run folder
    /// `root`, when the run ends (SAC's replay memory; nothing for PPO).
    fn save_memory(&self, _root: &Path) -> Result<(), FileError> {
        Ok(())
    }
    /// Write into the run folder `root`, at a checkpoint, what a run resumed after a crash
    /// needs beyond the checkpoint (SAC: the transitions stored since the last one).
    fn save_memory_part(&mut self, _root: &Path) -> Result<(), FileError> {
        Ok(())
    }
}

impl Shared for Ppo {
    fn version(&self) -> u64 {
        self.version
    }
    fn lr(&self) -> f64 {
        Ppo::lr(self)
    }
    fn set_lr(&mut self, lr: f64) {
        Ppo::set_lr(self, lr)
    }
    fn draw_seed(&mut self) -> u64 {
        Ppo::draw_seed(self)
    }
    fn update_planned(
        &mut self,
        trajs: &[Trajectory],
        seed: u64,
        group: &mut dyn Reducer,
    ) -> Result<UpdateStats, Refused> {
        Ppo::update_planned(self, trajs, seed, group).map(UpdateStats::Ppo)
    }
    fn update_alone(&mut self, trajs: &[Trajectory]) -> Result<UpdateStats, Refused> {
        Ppo::update(self, trajs).map(UpdateStats::Ppo)
    }
    fn state(&self) -> LearnerState {
        Ppo::state(self)
    }
    fn restore(&mut self, state: LearnerState, memory: Option<&[u8]>) -> Result<(), StateMismatch> {
        if memory.is_some() {
            return Err(StateMismatch("PPO keeps no replay memory, and this state comes with one".into()));
        }
        Ppo::restore(self, state)
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
            None => Ppo::update(self, trajs).map(UpdateStats::Ppo),
        }
    }
}

impl Shared for SacTrainer {
    fn version(&self) -> u64 {
        SacTrainer::version(self)
    }
    fn lr(&self) -> f64 {
        SacTrainer::lr(self)
    }
    fn set_lr(&mut self, lr: f64) {
        SacTrainer::set_lr(self, lr)
    }
    fn draw_seed(&mut self) -> u64 {
        SacTrainer::draw_seed(self)
    }
    fn update_planned(
        &mut self,
        trajs: &[Trajectory],
        seed: u64,
        group: &mut dyn Reducer,
    ) -> Result<UpdateStats, Refused> {
        SacTrainer::update_planned(self, trajs, seed, group).map(UpdateStats::Sac)
    }
    fn update_alone(&mut self, trajs: &[Trajectory]) -> Result<UpdateStats, Refused> {
        SacTrainer::update_alone(self, trajs).map(UpdateStats::Sac)
    }
    fn update_again(&mut self, trajs: &[Trajectory]) -> Result<UpdateStats, Refused> {
        SacTrainer::update_again(self, trajs).map(UpdateStats::Sac)
    }
    fn state(&self) -> LearnerState {
        SacTrainer::state(self)
    }
    fn memory(&self) -> Option<Vec<u8>> {
        SacTrainer::memory(self)
    }
    fn restore(&mut self, state: LearnerState, memory: Option<&[u8]>) -> Result<(), StateMismatch> {
        SacTrainer::restore(self, state, memory)
    }
}

impl Algorithm for SacTrainer {
    fn name(&self) -> &'static str {
        "sac"
    }

    fn version(&self) -> u64 {
        SacTrainer::version(self)
    }

    fn model(&self) -> &ActorCritic {
        SacTrainer::model(self)
    }

    fn set_lr(&mut self, lr: f64) {
        SacTrainer::set_lr(self, lr)
    }

    fn off_policy(&self) -> bool {
        true
    }

    fn update(&mut self, trajs: &[Trajectory], team: Option<&mut dyn Team>) -> Result<UpdateStats, Refused> {
        match team {
            Some(team) => team.update(self, trajs),
            None => SacTrainer::update_alone(self, trajs).map(UpdateStats::Sac),
        }
    }

    fn save_state(&self, dir: &Path) -> Result<(), FileError> {
        SacTrainer::save_state(self, dir)
    }

    fn save_memory(&self, root: &Path) -> Result<(), FileError> {
        SacTrainer::save_memory(self, root)
    }

    fn save_memory_part(&mut self, root: &Path) -> Result<(), FileError> {
        SacTrainer::save_memory_part(self, root)
    }
}
