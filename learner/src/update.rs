//! What every algorithm's update has in common, PPO's or SAC's, alone or in a group: why one
//! is refused ([`Refused`]), the state a learner's next update starts from ([`LearnerState`],
//! what a learner joining a team takes over) and a state that does not fit ([`StateMismatch`]).

use crate::group::GroupError;

/// Everything that makes a learner's next update what it will be, but a replay memory: the
/// version, the weights and the optimisers' moments, as named tensors (`pi`, `v`,
/// `adam.pi.m`, …; a step count as one number). A learner joining a team takes it over before
/// its first update, so the team's members stay identical bit for bit.
#[derive(Clone, Debug, PartialEq)]
pub struct LearnerState {
    /// Policy version.
    pub version: u64,
    /// Named tensors.
    pub tensors: Vec<(String, Vec<f32>)>,
}

/// A state that does not fit this learner's model and optimisers (nothing was changed).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{0}")]
pub struct StateMismatch(pub String);

/// Why an update was refused. The weights and the optimiser state are as they were before it.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum Refused {
    /// Fewer samples than one minibatch.
    #[error("{samples} samples: fewer than one minibatch of {batch}")]
    TooFewSamples {
        /// Samples in the batch.
        samples: usize,
        /// The minibatch size.
        batch: usize,
    },
    /// A loss or gradient that is not a number.
    #[error(
        "non-finite loss or gradient at gradient step {step} (loss {loss}): update refused, weights kept at version {version}"
    )]
    NonFinite {
        /// The gradient step (from 0).
        step: usize,
        /// Its loss.
        loss: f64,
        /// The version kept.
        version: u64,
    },
    /// The GPU failed (the device was lost, a buffer too big for it).
    #[error("the GPU failed: {error}; weights kept at version {version}")]
    Device {
        /// What failed.
        error: String,
        /// The version kept.
        version: u64,
    },
    /// The learner group failed (a member lost, a share that does not fit).
    #[error("the learner group failed: {error}; weights kept at version {version}")]
    Group {
        /// What failed.
        error: GroupError,
        /// The version kept.
        version: u64,
    },
}

impl Refused {
    /// The group failed, not the numbers: the update can be made again without it.
    pub fn is_group(&self) -> bool {
        matches!(self, Refused::Group { .. })
    }
}
