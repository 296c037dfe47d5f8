//! The racing line as a reward (`builtin:race_line`) and as an action space
//! (`--action-space-from-line`).
//!
//! The line is [`tracks::raceline::race_line`] through the track in its driving order, kept
//! [`MARGIN`] from both borders; its speeds are the fastest the car's limits on the surface
//! allow, as the simulator measures them ([`crate::handling::limits`]). A step's reward, with
//! all wheels on the track (1e-3 otherwise), is the sum of
//! - closeness to the line: `(1 − d / (w/2))²`, `d` the distance to the line, `w` the width;
//! - speed against the line's at the nearest point `v*`: `(1 − |v − v*| / v*)²`;
//! - pace: progress per step against the line's (its lap at 15 steps a second), capped at 2;
//! - at a finished lap, ten times the line's steps over the lap's, capped at 2;
//!
//! plus 1e-3. [`python_source`] writes the same arithmetic as a DeepRacer reward file with
//! both directions' lines in it, so `reward export` gives rewards equal to the built-in's.

use crate::car::CarParams;
use crate::params::RewardParams;
use crate::reward::RewardError;
use policy::Action;
use std::sync::{Arc, OnceLock};
use tracks::raceline::{Limits, LineError, Profile, curvature, race_line, speed_profile};
use tracks::{P2, Surface, Track};

/// Distance (m) the line keeps from both borders: the car's half-width and room to spare.
pub const MARGIN: f64 = 0.15;
/// DeepRacer's control rate, which the pace term counts the line's lap in.
pub const STEPS_PER_SECOND: f64 = 15.0;
/// The lowest speed target (DeepRacer's slowest action).
const MIN_TARGET: f64 = 0.1;

/// A racing line with its speeds, in driving order (a loop's closing point not repeated).
#[derive(Clone, Debug, PartialEq)]
pub struct LinePlan {
    /// The points.
    pub points: Vec<P2>,
    /// The fastest speed at each point (m/s).
    pub speed: Vec<f64>,
    /// Seconds round the line.
    pub lap_time: f64,
    /// Whether the line is a loop.
    pub closed: bool,
}

impl LinePlan {
    /// The line of `track` in its driving order for a car of `car` on `surface`.
    pub fn new(track: &Track, car: &CarParams, surface: Surface) -> Result<LinePlan, LineError> {
        let line = race_line(&track.rows(), MARGIN)?;
        Ok(LinePlan::along(&line.points, line.closed, &crate::handling::limits(car, surface)))
    }

    /// The plan along `points` (a loop's first point repeated last when `closed`) for a car
    /// of `limits`.
    pub fn along(points: &[P2], closed: bool, limits: &Limits) -> LinePlan {
        LinePlan::from_profile(points, closed, &speed_profile(points, closed, limits))
    }

    /// The plan along `points` whose speeds `profile` (`speed_profile` of the same points)
    /// already holds.
    pub fn from_profile(points: &[P2], closed: bool, profile: &Profile) -> LinePlan {
        let n = if closed { points.len().saturating_sub(1) } else { points.len() };
        LinePlan {
            points: points[..n].to_vec(),
            speed: profile.speed[..n].to_vec(),
            lap_time: profile.lap_time,
            closed,
        }
    }

    /// The reward of one step (see the module's docs).
    pub fn reward(&self, p: &RewardParams) -> f64 {
        if !p.all_wheels_on_track {
            return 1e-3;
        }
        let n = self.points.len();
        let (x, y) = (p.x, p.y);
        let (mut i, mut best) = (0, f64::INFINITY);
        for (k, q) in self.points.iter().enumerate() {
            let (dx, dy) = (q.x - x, q.y - y);
            let d = dx * dx + dy * dy;
            if d < best {
                best = d;
                i = k;
            }
        }
        let (prev, next) =
            if self.closed { ((i + n - 1) % n, (i + 1) % n) } else { (i.saturating_sub(1), (i + 1).min(n - 1)) };
        let pts = &self.points;
        let dist = segment_distance(x, y, pts[prev], pts[i]).min(segment_distance(x, y, pts[i], pts[next]));
        let half = 0.5 * p.track_width;
        let on_line = (1.0 - dist / half).max(0.0);
        let target = self.speed[i].max(MIN_TARGET);
        let on_pace = (1.0 - (p.speed - target).abs() / target).max(0.0);
        let line_steps = self.lap_time * STEPS_PER_SECOND;
        let pace = if p.steps > 0.0 { (p.progress / 100.0 * line_steps / p.steps).min(2.0) } else { 0.0 };
        let mut reward = 1e-3 + on_line * on_line + on_pace * on_pace + pace;
        if p.progress >= 100.0 && p.steps > 0.0 {
            reward += 10.0 * (line_steps / p.steps).min(2.0);
        }
        reward
    }

    /// A discrete action space of `n` actions for this line: the steering (the kinematic
    /// bicycle's for the line's curvature, + = left) and speed at each point, weighted by
    /// the time spent there, grouped into `n` by k-means; sorted by steering, then speed.
    pub fn action_space(&self, car: &CarParams, n: usize, max_steer: f64, max_speed: f64) -> Vec<Action> {
        let m = self.points.len();
        let pts = &self.points;
        let mut samples = Vec::with_capacity(m);
        for i in 0..m {
            let k = if self.closed || (i > 0 && i + 1 < m) {
                curvature(pts[(i + m - 1) % m], pts[i], pts[(i + 1) % m])
            } else {
                0.0
            };
            let steer = (car.wheelbase * k).atan().to_degrees().clamp(-max_steer, max_steer);
            let speed = self.speed[i].clamp(MIN_TARGET, max_speed);
            let j = if self.closed { (i + 1) % m } else { (i + 1).min(m - 1) };
            let weight = (pts[j] - pts[i]).norm() / speed;
            samples.push(([steer / max_steer, speed / max_speed], weight.max(1e-6)));
        }
        let centres = kmeans(&samples, n.max(1).min(m));
        let mut actions: Vec<Action> = centres
            .iter()
            .map(|c| Action {
                steering_angle: (c[0] * max_steer * 10.0).round() / 10.0,
                speed: (c[1] * max_speed * 100.0).round() / 100.0,
            })
            .collect();
        actions.sort_by(|a, b| a.steering_angle.total_cmp(&b.steering_angle).then(a.speed.total_cmp(&b.speed)));
        actions.dedup();
        actions
    }
}

/// Distance from (x, y) to the segment a–b (written as the Python file writes it).
fn segment_distance(x: f64, y: f64, a: P2, b: P2) -> f64 {
    let (ex, ey) = (b.x - a.x, b.y - a.y);
    let ll = ex * ex + ey * ey;
    let t = if ll > 0.0 { (((x - a.x) * ex + (y - a.y) * ey) / ll).clamp(0.0, 1.0) } else { 0.0 };
    let (dx, dy) = (x - (a.x + t * ex), y - (a.y + t * ey));
    (dx * dx + dy * dy).sqrt()
}

/// Weighted k-means (Lloyd's) of 2-D samples, started from `k` samples spread along the
/// steering order; deterministic.
fn kmeans(samples: &[([f64; 2], f64)], k: usize) -> Vec<[f64; 2]> {
    let mut order: Vec<usize> = (0..samples.len()).collect();
    order.sort_by(|&a, &b| {
        samples[a].0[0].total_cmp(&samples[b].0[0]).then(samples[a].0[1].total_cmp(&samples[b].0[1]))
    });
    let mut centres: Vec<[f64; 2]> = (0..k).map(|c| samples[order[(2 * c + 1) * samples.len() / (2 * k)]].0).collect();
    for _ in 0..100 {
        let mut sums = vec![([0.0f64; 2], 0.0f64); k];
        for (s, w) in samples {
            let c = nearest(&centres, s);
            sums[c].0[0] += w * s[0];
            sums[c].0[1] += w * s[1];
            sums[c].1 += w;
        }
        let mut moved = 0.0f64;
        for (c, (sum, w)) in centres.iter_mut().zip(sums) {
            if w > 0.0 {
                let next = [sum[0] / w, sum[1] / w];
                moved = moved.max((next[0] - c[0]).abs() + (next[1] - c[1]).abs());
                *c = next;
            }
        }
        if moved < 1e-9 {
            break;
        }
    }
    centres
}

fn nearest(centres: &[[f64; 2]], s: &[f64; 2]) -> usize {
    let d = |c: &[f64; 2]| (c[0] - s[0]).powi(2) + (c[1] - s[1]).powi(2);
    (0..centres.len()).min_by(|&a, &b| d(&centres[a]).total_cmp(&d(&centres[b]))).unwrap_or(0)
}

/// An environment's line, worked out at its first use and kept.
#[derive(Debug)]
pub struct LineCell {
    track: Arc<Track>,
    car: CarParams,
    surface: Surface,
    cell: OnceLock<Result<LinePlan, String>>,
}

impl LineCell {
    /// The line of `track` for `car` on `surface`, not yet computed.
    pub fn new(track: Arc<Track>, car: CarParams, surface: Surface) -> LineCell {
        LineCell { track, car, surface, cell: OnceLock::new() }
    }

    /// The line, computed on the first call.
    pub fn get(&self) -> Result<&LinePlan, RewardError> {
        self.cell
            .get_or_init(|| LinePlan::new(&self.track, &self.car, self.surface).map_err(|e| e.to_string()))
            .as_ref()
            .map_err(|msg| RewardError::Load {
                origin: "builtin:race_line".into(),
                msg: format!("{}: no racing line: {msg}", self.track.name()),
            })
    }
}

/// A DeepRacer reward file computing `builtin:race_line` for `world` with the lines of
/// both directions written in (`forward`, `reversed`), picked by `params['is_reversed']`.
pub fn python_source(world: &str, surface: Surface, forward: &LinePlan, reversed: &LinePlan) -> String {
    let line = |plan: &LinePlan| -> String {
        let mut s = format!("({:?}, {}, [\n", plan.lap_time, if plan.closed { "True" } else { "False" });
        for (p, v) in plan.points.iter().zip(&plan.speed) {
            s.push_str(&format!("    [{:?}, {:?}, {:?}],\n", p.x, p.y, v));
        }
        s.push_str("])");
        s
    };
    format!(
        r#""""Paddock's built-in race_line reward for {world} ({surface}), written by
`coordinator reward export builtin:race_line --world {world}`.

With all wheels on the track, the reward is 1e-3 plus: closeness to the racing line,
(1 - d / (w/2))^2; the speed against the line's at the nearest point v*,
(1 - |v - v*| / v*)^2; pace, progress per step against the line's lap at {sps} steps a
second, at most 2; and at a finished lap ten times the line's steps over the lap's, at
most 2. Off the track it is 1e-3. LINES holds (lap seconds, loop, [[x, y, speed], ...])
for each direction: the line keeps {margin} m from both borders, its speeds the fastest the
simulated car's grip, top speed, acceleration and braking allow.
"""
import math

STEPS_PER_SECOND = {sps:?}
MIN_TARGET = {min:?}

FORWARD = {fwd}

REVERSED = {rev}

LINES = {{False: FORWARD, True: REVERSED}}


def _segment_distance(x, y, a, b):
    ex = b[0] - a[0]
    ey = b[1] - a[1]
    ll = ex * ex + ey * ey
    t = 0.0
    if ll > 0.0:
        t = min(max(((x - a[0]) * ex + (y - a[1]) * ey) / ll, 0.0), 1.0)
    dx = x - (a[0] + t * ex)
    dy = y - (a[1] + t * ey)
    return math.sqrt(dx * dx + dy * dy)


def reward_function(params):
    if not params['all_wheels_on_track']:
        return 1e-3
    lap_time, closed, line = LINES[bool(params['is_reversed'])]
    x = params['x']
    y = params['y']
    n = len(line)
    i = 0
    best = math.inf
    for k in range(n):
        dx = line[k][0] - x
        dy = line[k][1] - y
        d = dx * dx + dy * dy
        if d < best:
            best = d
            i = k
    if closed:
        prev, nxt = (i + n - 1) % n, (i + 1) % n
    else:
        prev, nxt = max(i - 1, 0), min(i + 1, n - 1)
    dist = min(_segment_distance(x, y, line[prev], line[i]), _segment_distance(x, y, line[i], line[nxt]))
    half = 0.5 * params['track_width']
    on_line = max(1.0 - dist / half, 0.0)
    target = max(line[i][2], MIN_TARGET)
    on_pace = max(1.0 - abs(params['speed'] - target) / target, 0.0)
    line_steps = lap_time * STEPS_PER_SECOND
    steps = params['steps']
    pace = min(params['progress'] / 100.0 * line_steps / steps, 2.0) if steps > 0 else 0.0
    reward = 1e-3 + on_line * on_line + on_pace * on_pace + pace
    if params['progress'] >= 100.0 and steps > 0:
        reward += 10.0 * min(line_steps / steps, 2.0)
    return float(reward)
"#,
        surface = surface.name(),
        sps = STEPS_PER_SECOND,
        margin = MARGIN,
        min = MIN_TARGET,
        fwd = line(forward),
        rev = line(reversed),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Env, EnvSpec, Mode, SimConfig};
    use tracks::Direction;

    fn reinvent() -> (Env, CarParams) {
        let world = tracks::world("reinvent_base").unwrap();
        let spec = EnvSpec::from_world(&world, Direction::Forward);
        let mut env = Env::new(spec, Arc::new(SimConfig::default()), Mode::Training, 1, 0.0).unwrap();
        env.advance(Action { steering_angle: 0.0, speed: 1.0 });
        (env, SimConfig::default().car)
    }

    /// Issue 34: the race line reward is highest on the line at its speed and pace.
    #[test]
    fn the_race_line_reward_is_highest_on_the_line_at_its_speed_and_pace() {
        let (env, _) = reinvent();
        let plan = env.line().get().unwrap();
        let i = plan.points.len() / 3;
        let mut p = env.params().clone();
        (p.x, p.y, p.speed, p.all_wheels_on_track) = (plan.points[i].x, plan.points[i].y, plan.speed[i], true);
        (p.progress, p.steps) = (10.0, 0.1 * plan.lap_time * STEPS_PER_SECOND);
        let best = plan.reward(&p);
        assert!((best - (1e-3 + 1.0 + 1.0 + 1.0)).abs() < 1e-9, "on the line, at its speed and pace: {best}");
        // A step away from the line, off its speed, behind its pace: each costs.
        let normal = (plan.points[i + 1] - plan.points[i - 1]).normalize();
        let mut off = p.clone();
        (off.x, off.y) = (p.x - 0.2 * normal.y, p.y + 0.2 * normal.x);
        let mut slow = p.clone();
        slow.speed = 0.5 * plan.speed[i];
        let mut behind = p.clone();
        behind.steps *= 2.0;
        for (what, q) in [("off the line", off), ("slow", slow), ("behind pace", behind)] {
            let r = plan.reward(&q);
            assert!(r < best - 0.2, "{what}: {r} against {best}");
        }
        let mut out = p.clone();
        out.all_wheels_on_track = false;
        assert_eq!(plan.reward(&out), 1e-3);
        // A finished lap at the line's pace earns ten times its pace more.
        let mut lap = p.clone();
        (lap.progress, lap.steps) = (100.0, plan.lap_time * STEPS_PER_SECOND);
        assert!((plan.reward(&lap) - (best + 10.0)).abs() < 1e-9);
    }

    /// Issue 34: the action space from the line covers its straights and its tightest turn.
    #[test]
    fn the_action_space_from_the_line_covers_its_straights_and_its_tightest_turn() {
        let (env, car) = reinvent();
        let plan = env.line().get().unwrap();
        let actions = plan.action_space(&car, 7, 30.0, 4.0);
        assert_eq!(actions.len(), 7, "{actions:?}");
        assert!(actions.windows(2).all(|w| w[0].steering_angle <= w[1].steering_angle), "{actions:?}");
        assert!(actions.iter().all(|a| a.steering_angle.abs() <= 30.0 && (0.1..=4.0).contains(&a.speed)));
        assert!(actions.iter().any(|a| a.steering_angle.abs() < 2.0 && a.speed > 3.5), "a fast straight: {actions:?}");
        // reinvent_base runs anticlockwise: its turns are to the left and slower.
        let tightest = actions.last().unwrap();
        assert!(tightest.steering_angle > 5.0 && tightest.speed < 3.5, "{actions:?}");
        assert_eq!(plan.action_space(&car, 7, 30.0, 4.0), actions, "deterministic");
        assert!(plan.action_space(&car, 3, 30.0, 2.0).iter().all(|a| a.speed <= 2.0));
    }
}
