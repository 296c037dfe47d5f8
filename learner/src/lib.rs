//! The learner, a plain library: PPO on faer, DeepRacer's hyperparameters, checkpoints.
//!
//! - [`hyperparams`]: `hyperparameters.json`, read unchanged.
//! - [`ppo`]: GAE, the clipped surrogate, the value loss, their gradients, the update.
//! - [`checkpoints`]: run folders, atomic checkpoints, best/last records.
//!
//! Architecture invariant: no simulator and no transport here. Experience arrives as
//! [`policy::Trajectory`] values, from the same process or (later) from the network.

pub mod checkpoints;
pub mod hyperparams;
pub mod ppo;

pub use hyperparams::{Hyperparameters, LossType};
pub use ppo::{Ppo, UpdateStats};
