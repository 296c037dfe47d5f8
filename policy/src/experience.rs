//! Experience: what acting produces and learning consumes. Every trajectory carries the
//! policy version that acted, so staleness can be measured and bounded.

use crate::model::Choice;

/// One episode (or a segment of one) from one environment, stored column-wise.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct Trajectory {
    /// The world it was driven on (a built-in world name).
    pub world: String,
    /// The environment (agent-local index).
    pub env: u32,
    /// That environment's episode counter.
    pub episode: u64,
    /// The policy version that chose these actions.
    pub policy_version: u64,
    /// Observations, `len × obs_size`, row-major.
    pub obs: Vec<f32>,
    /// What the policy chose.
    pub choices: Vec<Choice>,
    /// log π(choice | obs) at acting time (the behaviour log-probabilities).
    pub logp: Vec<f32>,
    /// V(obs) at acting time.
    pub values: Vec<f32>,
    /// Rewards.
    pub rewards: Vec<f32>,
    /// The episode ended at the last step (otherwise the segment was cut).
    pub done: bool,
    /// Progress (%) when the trajectory ended.
    pub progress: f64,
    /// A lap was completed.
    pub lap_complete: bool,
}

impl Trajectory {
    /// Steps in the trajectory.
    pub fn len(&self) -> usize {
        self.rewards.len()
    }

    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.rewards.is_empty()
    }
}
