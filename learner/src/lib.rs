//! The learner, a plain library: PPO and SAC on faer, DeepRacer's hyperparameters, checkpoints.
//!
//! The modules are layers; each uses only those above it in this list:
//!
//! - [`hyperparams`]: `hyperparameters.json`, read unchanged. [`trend`]: plateaus and
//!   collapses of evaluation progress. [`checkpoints`]: run folders, atomic checkpoints,
//!   best/last records. [`device`]: `--device auto|cpu|gpu`, and the GPU's Adam step.
//! - [`group`]: a group of learners that trains as one (a learner team's exchange): the
//!   [`Reducer`], [`Alone`], [`GroupError`], factored gradients.
//! - [`update`]: what every algorithm's update shares: [`Refused`], [`update::LearnerState`],
//!   [`StateMismatch`].
//! - [`ppo`] and [`sac`]: the two algorithms, each with its own figures, neither using the
//!   other.
//! - [`algorithm`]: what a run and a learner team need of an algorithm ([`algorithm::Algorithm`],
//!   [`algorithm::Shared`], [`algorithm::Team`]), implemented for PPO and SAC; [`UpdateStats`].
//! - [`record`]: the run's logs: `metrics.jsonl`'s records, DeepRacer's sim-trace and metrics
//!   JSON (DRfC's layout), MCAP.
//! - [`run`]: one training run (flow control, updates, evaluations on the workers,
//!   checkpoints, stop rules) over any [`run::Link`]: in-process channels or Zenoh.
//!
//! Architecture invariant: no simulator and no transport here. Experience and evaluation
//! results arrive as [`policy::exchange`] values through a [`run::Link`], from a worker in the
//! same process or from the network; the learner package does not depend on `sim-agent`.

pub mod algorithm;
pub mod checkpoints;
pub mod device;
pub mod group;
pub mod hyperparams;
pub mod ppo;
pub mod record;
pub mod run;
pub mod sac;
pub mod trend;
pub mod update;

pub use algorithm::UpdateStats;
pub use gpu::DeviceChoice;
pub use group::{Alone, GroupError, Reducer};
pub use hyperparams::{Hyperparameters, LossType, LrSchedule};
pub use ppo::Ppo;
pub use update::{Refused, StateMismatch};

/// Run this process's parallel network maths on `threads` threads (default: one per core):
/// sizes rayon's global pool, which `faer` and the conv, Adam and gradient loops run on.
/// `Par::rayon(n)` splits work `n` ways but runs it on the pool it is called from, so without
/// this a learner told to use 2 threads would run its optimiser on every core of the machine.
/// Call it before any parallel work. Returns the threads the maths runs on: the pool's size,
/// which a later call leaves as it is (with a warning).
pub fn use_threads(threads: Option<usize>) -> usize {
    let threads = threads.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get())).max(1);
    let built =
        rayon::ThreadPoolBuilder::new().num_threads(threads).thread_name(|i| format!("maths-{i}")).build_global();
    if built.is_err() {
        tracing::warn!(threads, pool = rayon::current_num_threads(), "the maths thread pool was already built");
    }
    rayon::current_num_threads()
}
