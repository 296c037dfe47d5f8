//! DeepRacer console's "Validate" for reward files, and more: call the reward function on
//! states sampled along a track — on the centre line, near each border, off the track,
//! facing backwards — and report the range of rewards or the first failure. In a race with
//! objects the states have them (placed as the race's first episode places them), so a
//! reward reading `objects_*` is called as training will call it.

use crate::car::{CarParams, wheel_points_at};
use crate::objects::Traffic;
use crate::params::{EpisodeClock, Pose, compute_params};
use crate::race::RaceConfig;
use crate::race_line::LineCell;
use crate::reward::{RewardError, RewardFn};
use policy::{Action, ActionSpace};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use tracks::Track;

/// What a passing validation saw.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ValidationReport {
    /// Number of calls made.
    pub calls: usize,
    /// Smallest reward.
    pub min: f64,
    /// Mean reward.
    pub mean: f64,
    /// Largest reward.
    pub max: f64,
    /// Mean reward per kind of state, in [`SAMPLE_KINDS`] order.
    pub mean_by_kind: Vec<(&'static str, f64)>,
    /// Every call's reward, in the order made (the same states every run).
    pub rewards: Vec<f64>,
}

/// The kinds of state sampled, by lateral offset (fraction of the half width) and heading.
pub const SAMPLE_KINDS: [&str; 5] =
    ["centre line", "near the left border", "near the right border", "off track", "facing backwards"];

/// Where a reward is validated: the track and its floor, the race, the actions (all discrete
/// actions, or the corners and middle of a continuous range) and how many places along the
/// track are sampled.
#[derive(Clone, Copy, Debug)]
pub struct Sampling<'a> {
    /// The track.
    pub track: &'a Track,
    /// Its floor.
    pub surface: tracks::Surface,
    /// The model's actions.
    pub space: &'a ActionSpace,
    /// Places sampled along the track.
    pub positions: usize,
    /// The race (its objects are placed as its first episode places them).
    pub race: &'a RaceConfig,
}

/// Call `reward` on sampled states of `track` (its floor `surface`) in `race`. Actions come
/// from `space` (all discrete actions, or the corners and middle of a continuous range). The
/// first failed call is the error.
pub fn validate_reward(
    reward: &mut RewardFn,
    track: &Track,
    surface: tracks::Surface,
    space: &ActionSpace,
    positions: usize,
    race: &RaceConfig,
) -> Result<ValidationReport, RewardError> {
    let at = Sampling { track, surface, space, positions, race };
    let (report, mut failures) = sample(reward, at, true)?;
    match failures.pop() {
        Some(e) => Err(e),
        None => Ok(report),
    }
}

/// [`validate_reward`] that goes on after a failed call: the report of the calls that
/// returned a reward, and every failed call. A call that runs out of time ends the calls (the
/// next would take the whole limit too).
pub fn validate_reward_all(
    reward: &mut RewardFn,
    at: Sampling<'_>,
) -> Result<(ValidationReport, Vec<RewardError>), RewardError> {
    sample(reward, at, false)
}

/// The sampled calls, up to the first failure when `stop_at_first`; an error only for what
/// stops every call (the race's objects).
fn sample(
    reward: &mut RewardFn,
    at: Sampling<'_>,
    stop_at_first: bool,
) -> Result<(ValidationReport, Vec<RewardError>), RewardError> {
    let Sampling { track, surface, space, positions, race } = at;
    let mut failures = Vec::new();
    let car = CarParams::default();
    let line = LineCell::new(std::sync::Arc::new(track.clone()), car.clone(), surface);
    let mut traffic =
        Traffic::new(track, race, "the race").map_err(|msg| RewardError::Load { origin: "the race".into(), msg })?;
    if let Some(t) = traffic.as_mut() {
        t.reset(track, &mut ChaCha8Rng::seed_from_u64(1));
    }
    let actions: Vec<Action> = match space {
        ActionSpace::Discrete(a) => a.clone(),
        ActionSpace::Continuous { steering_angle: (sl, sh), speed: (vl, vh) } => {
            let mid = |a: f64, b: f64| (a + b) / 2.0;
            vec![
                Action { steering_angle: *sl, speed: *vl },
                Action { steering_angle: mid(*sl, *sh), speed: mid(*vl, *vh) },
                Action { steering_angle: *sh, speed: *vh },
            ]
        }
    };
    let (mut sum, mut min, mut max, mut calls) = (0.0, f64::MAX, f64::MIN, 0usize);
    let mut rewards = Vec::new();
    let mut by_kind = [(0.0f64, 0usize); 5];
    let len = track.length();
    for i in 0..positions {
        let along = len * (i as f64 + 0.5) / positions as f64;
        let (c, dir) = track.pose_at(along);
        let q = track.query(c);
        let half = q.track_width / 2.0;
        let normal = (-dir.sin(), dir.cos()); // left of the driving direction
        // (lateral offset in m, heading offset in rad) per kind.
        let kinds =
            [(0.0, 0.0), (0.8 * half, 0.15), (-0.8 * half, -0.15), (half + 0.35, 0.0), (0.0, std::f64::consts::PI)];
        for (k, &(offset, dyaw)) in kinds.iter().enumerate() {
            for (j, &action) in actions.iter().enumerate() {
                let yaw = dir + dyaw;
                // Put the reference point (0.14 m ahead) at the sampled place.
                let fx = c.x + offset * normal.0;
                let fy = c.y + offset * normal.1;
                let pose = Pose {
                    x: fx - crate::params::FRONT_OFFSET * yaw.cos(),
                    y: fy - crate::params::FRONT_OFFSET * yaw.sin(),
                    yaw,
                };
                let wheels = wheel_points_at(&car, pose.x, pose.y, pose.yaw);
                let progress_here = 100.0 * along / len;
                let clock = EpisodeClock {
                    start_ndist: 0.0,
                    prev_progress: (progress_here - 0.5).max(0.0),
                    steps: 2 + (i * actions.len() + j) as u64,
                    sim_time: 0.0,
                };
                let mut params = compute_params(track, &pose, &wheels, action, &clock);
                params.sim_time = params.steps / 15.0;
                if let Some(t) = &traffic {
                    let at = tracks::P2::new(pose.x, pose.y);
                    let contact = t.contact(track, at, pose.yaw, params.progress.rem_euclid(100.0));
                    t.fill_params(track, &pose, contact, &mut params);
                }
                let called = match reward {
                    RewardFn::Builtin(b) => b.reward(&params, &line),
                    RewardFn::Python(py) => py.call(0, 0, track, &params),
                };
                let r = match called {
                    Ok(r) => r,
                    Err(e) => {
                        // A call out of time took the whole limit: the next would too.
                        let out_of_time = matches!(e, RewardError::TimedOut { .. });
                        failures.push(e);
                        if stop_at_first || out_of_time {
                            return Ok((report(calls, (sum, min, max), by_kind, rewards), failures));
                        }
                        continue;
                    }
                };
                calls += 1;
                rewards.push(r);
                sum += r;
                min = min.min(r);
                max = max.max(r);
                by_kind[k].0 += r;
                by_kind[k].1 += 1;
            }
        }
    }
    Ok((report(calls, (sum, min, max), by_kind, rewards), failures))
}

/// The report of `calls` rewards: their sum, smallest and largest; by kind of state.
fn report(
    calls: usize,
    (sum, min, max): (f64, f64, f64),
    by_kind: [(f64, usize); 5],
    rewards: Vec<f64>,
) -> ValidationReport {
    ValidationReport {
        calls,
        min: if calls == 0 { 0.0 } else { min },
        mean: sum / calls.max(1) as f64,
        max: if calls == 0 { 0.0 } else { max },
        mean_by_kind: SAMPLE_KINDS.iter().zip(by_kind).map(|(n, (s, c))| (*n, s / c.max(1) as f64)).collect(),
        rewards,
    }
}
