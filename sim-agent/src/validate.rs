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
#[derive(Clone, Debug, PartialEq)]
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

/// Call `reward` on sampled states of `track` (its floor `surface`) in `race`. Actions come
/// from `space` (all discrete actions, or the corners and middle of a continuous range).
pub fn validate_reward(
    reward: &mut RewardFn,
    track: &Track,
    surface: tracks::Surface,
    space: &ActionSpace,
    positions: usize,
    race: &RaceConfig,
) -> Result<ValidationReport, RewardError> {
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
                let r = match reward {
                    RewardFn::Builtin(b) => b.reward(&params, &line)?,
                    RewardFn::Python(py) => py.call(0, 0, track, &params)?,
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
    Ok(ValidationReport {
        calls,
        min,
        mean: sum / calls.max(1) as f64,
        max,
        mean_by_kind: SAMPLE_KINDS.iter().zip(by_kind).map(|(n, (s, c))| (*n, s / c.max(1) as f64)).collect(),
        rewards,
    })
}
