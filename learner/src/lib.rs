//! The learner, a plain library: PPO on faer, DeepRacer's hyperparameters, checkpoints.
//!
//! - [`hyperparams`]: `hyperparameters.json`, read unchanged.
//! - [`ppo`]: GAE, the clipped surrogate, the value loss, their gradients, the update.
//! - [`checkpoints`]: run folders, atomic checkpoints, best/last records.
//! - [`record`]: the run's logs: DeepRacer's sim-trace and metrics JSON (DRfC's layout), MCAP.
//! - [`run`]: one training run (flow control, updates, evaluations on the workers,
//!   checkpoints, stop rules) over any [`run::Link`]: in-process channels or Zenoh.
//! - [`trend`]: when to stop: plateaus and collapses of evaluation progress.
//!
//! Architecture invariant: no simulator and no transport here. Experience and evaluation
//! results arrive as [`policy::exchange`] values through a [`run::Link`], from a worker in the
//! same process or from the network; the learner package does not depend on `sim-agent`.

pub mod checkpoints;
pub mod hyperparams;
pub mod ppo;
pub mod record;
pub mod run;
pub mod trend;

pub use hyperparams::{Hyperparameters, LossType};
pub use ppo::{Alone, GroupError, Ppo, Reducer, StateMismatch, UpdateStats};
