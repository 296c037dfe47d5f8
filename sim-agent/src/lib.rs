//! The simulator, a plain library: no transport, testable without a network.
//!
//! - [`car`]: the rapier car.
//! - [`handling`]: its measured handling per surface against the simple models.
//! - [`camera`]: the front camera, rendered with wgpu (GPU or lavapipe), batched.
//! - [`env`](mod@env): one environment, DeepRacer's step loop and episode rules.
//! - [`params`]: reward `params` from a pose.
//! - [`reward`] and [`python`]: built-in and Python reward functions.
//! - [`obs`]: the state vector and lidar.
//! - [`lidar`]: DeepRacer's simulated LiDAR against the race's objects, and its input filters.
//! - [`objects`]: a race's obstacles and bot cars in one environment, and the crash rule.
//! - [`vec_env`]: many environments on all cores.
//! - [`rollout`]: a policy acting in them (trajectories), and evaluation trials.
//! - [`worker`]: the learner's peer: granted episodes and evaluation trials, over any link.
//! - [`driver`]: a scripted pure-pursuit driver.
//! - [`simtrace`]: DeepRacer's sim-trace CSV, for the community's analysis notebooks.
//! - [`validate`]: DeepRacer's "Validate" for reward files, and more.
//! - [`config`]: the configuration struct and its loader.
//! - [`race`]: the race type and DeepRacer's obstacle and bot keys (`[race]`, `run.env`).
//!
//! Architecture invariant: nothing here opens a socket or names the wire. The `sim-agent`
//! binary's network role (`serve.rs`) is a thin shell over this library and `protocol`.

pub mod camera;
pub mod car;
pub mod config;
pub mod driver;
pub mod env;
pub mod handling;
pub use gpu::icd;
pub mod lidar;
pub mod objects;
pub mod obs;
pub mod params;
pub mod python;
pub mod race;
pub mod race_line;
pub mod reward;
pub mod reward_check;
pub mod rollout;
pub mod simtrace;
pub mod validate;
pub mod vec_env;
pub mod worker;

pub use config::SimConfig;
pub use env::{Env, EnvError, EnvSpec, EpisodeStatus, EvalRules, Mode, StepOutcome};
pub use reward::{BuiltinReward, RewardError, RewardFn};
pub use vec_env::VecEnv;

/// A world's track as lines, driven in `direction`, for logs written where no simulator runs.
pub fn track_lines(w: &tracks::World, direction: tracks::Direction) -> policy::TrackLines {
    let t = w.track(direction);
    let pts = |l: &[tracks::P2]| l.iter().map(|p| [p.x, p.y]).collect::<Vec<[f64; 2]>>();
    policy::TrackLines {
        world: w.name.clone(),
        length: t.length(),
        centre: pts(t.waypoints()),
        inner: pts(t.inner().points()),
        outer: pts(t.outer().points()),
    }
}

impl Env {
    /// The reward of the step [`Env::advance`] just ran, by any reward function (Python
    /// rewards use slot 0); 0 on the `prepare` step.
    pub fn reward_with(&self, reward: &mut RewardFn) -> Result<f64, RewardError> {
        if !self.needs_reward() {
            return Ok(0.0);
        }
        match reward {
            RewardFn::Builtin(b) => b.reward(self.params(), self.line()),
            RewardFn::Python(py) => py.call(0, self.episode(), self.track(), self.params()),
        }
    }

    /// One step with any reward function.
    pub fn step_with(&mut self, action: policy::Action, reward: &mut RewardFn) -> Result<StepOutcome, RewardError> {
        self.advance(action);
        let r = self.reward_with(reward)?;
        Ok(self.finish(r))
    }
}
