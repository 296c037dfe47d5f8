//! Reward functions: DeepRacer Python files run unmodified by embedded CPython
//! ([`crate::python`]), and built-in Rust rewards for speed.
//!
//! Whatever computes it, a reward is checked as DeepRacer's simapp checks it
//! (`RewardFunctionError`): a number, finite, within ±1e5. Anything else stops the run
//! with the step's params; it never reaches training.

use crate::params::RewardParams;
use crate::python::PythonReward;
use crate::race_line::LineCell;
use std::path::Path;

/// DeepRacer's bound on a reward's magnitude.
pub const REWARD_LIMIT: f64 = 1e5;

/// Built-in rewards, in Rust.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BuiltinReward {
    /// DeepRacer's sample "follow the centre line" (markers at 10/25/50 % of the width).
    CenterLine,
    /// DeepRacer's sample "stay inside the two borders".
    StayInside,
    /// DeepRacer's object-avoidance sample (the developer guide's Example 4: inside the
    /// borders, and penalised 0.8 m or nearer behind the next object in its lane) with the
    /// distance it means: along the track from the car to the next object, where the sample
    /// reads `objects_distance[next]`, the object's distance from waypoint 0. Without
    /// objects, nothing is penalised.
    ObjectAvoidance,
    /// Follow the racing line at its speeds, with progress ([`crate::race_line`]).
    RaceLine,
    /// Paddock's own for object avoidance and head-to-bot: 1 a step on the track, less the
    /// nearer the car's centre stands across from the next object's within 2.5 m ahead (and
    /// from the one it is passing, up to 0.5 m past it), so the signal comes while a swerve
    /// still helps; 0.001 off the track or crashed. At most 1 a step.
    Clearance,
}

/// [`BuiltinReward::Clearance`]: how far ahead an object starts to count (m)…
const CLEARANCE_AHEAD: f64 = 2.5;
/// …how far behind the car's reference point it still counts (m: the car is beside it)…
const CLEARANCE_BESIDE: f64 = 0.5;
/// …and the centre-to-centre distance across the track that clears it (half a box, 0.2 m,
/// half the car, 0.098 m, and a margin).
const CLEARANCE_ACROSS: f64 = 0.35;

impl BuiltinReward {
    /// All built-ins with their names.
    pub const ALL: [(BuiltinReward, &'static str); 5] = [
        (BuiltinReward::CenterLine, "center_line"),
        (BuiltinReward::StayInside, "stay_inside"),
        (BuiltinReward::ObjectAvoidance, "object_avoidance"),
        (BuiltinReward::RaceLine, "race_line"),
        (BuiltinReward::Clearance, "clearance"),
    ];

    /// The built-in's name.
    pub fn name(self) -> &'static str {
        BuiltinReward::ALL.iter().find(|(b, _)| *b == self).map(|(_, n)| *n).unwrap_or("?")
    }

    /// Evaluate for one step's params, on the track whose racing line `line` holds (only
    /// `race_line` reads it), checked as DeepRacer checks a reward.
    #[inline]
    pub fn reward(self, p: &RewardParams, line: &LineCell) -> Result<f64, RewardError> {
        let r = match self {
            BuiltinReward::RaceLine => line.get()?.reward(p),
            b => b.plain(p),
        };
        check_reward(r, p)
    }

    /// This built-in as a DeepRacer reward file: the same arithmetic in Python, so a file
    /// that `reward export` writes gives the rewards the built-in gives. `race_line` carries
    /// its track's lines ([`crate::race_line::python_source`]), so it has none here.
    pub fn python_source(self) -> Option<&'static str> {
        Some(match self {
            BuiltinReward::CenterLine => PY_CENTER_LINE,
            BuiltinReward::StayInside => PY_STAY_INSIDE,
            BuiltinReward::ObjectAvoidance => PY_OBJECT_AVOIDANCE,
            BuiltinReward::Clearance => PY_CLEARANCE,
            BuiltinReward::RaceLine => return None,
        })
    }

    /// The rewards that read nothing but the params.
    fn plain(self, p: &RewardParams) -> f64 {
        match self {
            BuiltinReward::CenterLine => {
                let w = p.track_width;
                let d = p.distance_from_center;
                if d <= 0.1 * w {
                    1.0
                } else if d <= 0.25 * w {
                    0.5
                } else if d <= 0.5 * w {
                    0.1
                } else {
                    1e-3
                }
            }
            BuiltinReward::StayInside => {
                if p.all_wheels_on_track && (0.5 * p.track_width - p.distance_from_center) >= 0.05 { 1.0 } else { 1e-3 }
            }
            BuiltinReward::ObjectAvoidance => {
                let lane = BuiltinReward::StayInside.plain(p);
                let o = &p.objects;
                let next = o.closest_objects[1];
                let mut avoid = 1.0;
                if let (Some(&d), Some(&left)) = (o.objects_distance.get(next), o.objects_left_of_center.get(next))
                    && left == p.is_left_of_center
                {
                    let gap = (d - p.projection_distance).rem_euclid(p.track_length);
                    if (0.5..0.8).contains(&gap) {
                        avoid *= 0.5;
                    } else if (0.3..0.5).contains(&gap) {
                        avoid *= 0.2;
                    } else if gap < 0.3 {
                        avoid = 1e-3;
                    }
                }
                1e-3 + lane + 4.0 * avoid
            }
            BuiltinReward::Clearance => {
                if !p.all_wheels_on_track || p.is_crashed {
                    return 1e-3;
                }
                let o = &p.objects;
                let side = |left: bool, d: f64| if left { d } else { -d };
                let car = side(p.is_left_of_center, p.distance_from_center);
                // 1 when clear across of object `i`, less by `weight` × the share not cleared.
                let cleared = |i: usize, weight: f64| {
                    let across = (car - side(o.objects_left_of_center[i], o.objects_distance_from_center[i])).abs();
                    1.0 - weight * (1.0 - (across / CLEARANCE_ACROSS).min(1.0))
                };
                let mut r = 1.0;
                let [prev, next] = o.closest_objects;
                if next < o.objects_distance.len() {
                    let ahead = (o.objects_distance[next] - p.projection_distance).rem_euclid(p.track_length);
                    if ahead < CLEARANCE_AHEAD {
                        r *= cleared(next, 1.0 - ahead / CLEARANCE_AHEAD);
                    }
                }
                // With one object both are it: at most one of the two holds on any lap over 3 m.
                if prev < o.objects_distance.len() {
                    let behind = (p.projection_distance - o.objects_distance[prev]).rem_euclid(p.track_length);
                    if behind < CLEARANCE_BESIDE {
                        r *= cleared(prev, 1.0);
                    }
                }
                r.max(1e-3)
            }
            BuiltinReward::RaceLine => unreachable!("race_line reads its line"),
        }
    }
}

const PY_CENTER_LINE: &str = r#""""Paddock's built-in center_line reward (DeepRacer's sample "follow the centre line")."""


def reward_function(params):
    w = params['track_width']
    d = params['distance_from_center']
    if d <= 0.1 * w:
        return 1.0
    if d <= 0.25 * w:
        return 0.5
    if d <= 0.5 * w:
        return 0.1
    return 1e-3
"#;

const PY_STAY_INSIDE: &str = r#""""Paddock's built-in stay_inside reward (DeepRacer's sample "stay inside the two borders")."""


def reward_function(params):
    if params['all_wheels_on_track'] and (0.5 * params['track_width'] - params['distance_from_center']) >= 0.05:
        return 1.0
    return 1e-3
"#;

const PY_OBJECT_AVOIDANCE: &str = r#""""Paddock's built-in object_avoidance reward: DeepRacer's object-avoidance sample (inside
the borders, penalised 0.8 m or nearer behind the next object in the car's lane), the
distance to that object measured along the track from the car."""


def reward_function(params):
    if params['all_wheels_on_track'] and (0.5 * params['track_width'] - params['distance_from_center']) >= 0.05:
        lane = 1.0
    else:
        lane = 1e-3
    avoid = 1.0
    nxt = params['closest_objects'][1]
    distances = params['objects_distance']
    left = params['objects_left_of_center']
    if nxt < len(distances) and nxt < len(left) and left[nxt] == params['is_left_of_center']:
        gap = (distances[nxt] - params['projection_distance']) % params['track_length']
        if 0.5 <= gap < 0.8:
            avoid *= 0.5
        elif 0.3 <= gap < 0.5:
            avoid *= 0.2
        elif gap < 0.3:
            avoid = 1e-3
    return 1e-3 + lane + 4.0 * avoid
"#;

const PY_CLEARANCE: &str = r#""""Paddock's built-in clearance reward for object avoidance and head-to-bot: 1 a step on the
track, less the nearer the car's centre stands across from the next object's within 2.5 m ahead
(and from the one it is passing, up to 0.5 m past it); 0.001 off the track or crashed."""

AHEAD = 2.5
BESIDE = 0.5
ACROSS = 0.35


def reward_function(params):
    if not params['all_wheels_on_track'] or params['is_crashed']:
        return 1e-3

    def side(left, d):
        return d if left else -d

    car = side(params['is_left_of_center'], params['distance_from_center'])
    left = params['objects_left_of_center']
    across_of = params['objects_distance_from_center']
    distances = params['objects_distance']

    def cleared(i, weight):
        across = abs(car - side(left[i], across_of[i]))
        return 1.0 - weight * (1.0 - min(across / ACROSS, 1.0))

    r = 1.0
    prev, nxt = params['closest_objects']
    if nxt < len(distances):
        ahead = (distances[nxt] - params['projection_distance']) % params['track_length']
        if ahead < AHEAD:
            r *= cleared(nxt, 1.0 - ahead / AHEAD)
    if prev < len(distances):
        behind = (params['projection_distance'] - distances[prev]) % params['track_length']
        if behind < BESIDE:
            r *= cleared(prev, 1.0)
    return max(r, 1e-3)
"#;

/// A reward function of either kind.
pub enum RewardFn {
    /// Computed in Rust, in parallel with the physics.
    Builtin(BuiltinReward),
    /// A DeepRacer `reward_function(params)` in Python.
    Python(Box<PythonReward>),
}

impl RewardFn {
    /// `builtin:NAME` (or a bare built-in name) selects a built-in; anything else is a Python file.
    pub fn from_spec(spec: &str) -> Result<RewardFn, RewardError> {
        let name = spec.strip_prefix("builtin:").unwrap_or(spec);
        if let Some((b, _)) = BuiltinReward::ALL.iter().find(|(_, n)| *n == name) {
            return Ok(RewardFn::Builtin(*b));
        }
        if spec.starts_with("builtin:") {
            let known: Vec<&str> = BuiltinReward::ALL.iter().map(|(_, n)| *n).collect();
            return Err(RewardError::Load {
                origin: spec.into(),
                msg: format!("no built-in reward '{name}'; known: {}", known.join(", ")),
            });
        }
        Ok(RewardFn::Python(Box::new(PythonReward::load(Path::new(spec))?)))
    }

    /// The Python reward file `path` whose text, `text`, was read already (its folder goes on
    /// `sys.path`, as for [`RewardFn::from_spec`]).
    pub fn from_file_text(path: &Path, text: &str) -> Result<RewardFn, RewardError> {
        Ok(RewardFn::Python(Box::new(PythonReward::load_text(path, text)?)))
    }

    /// A reward from a job's text: `builtin:NAME`, or the source of a Python reward file
    /// named `name` (compiled in memory; tracebacks name `name`).
    pub fn from_source(name: &str, source: &str) -> Result<RewardFn, RewardError> {
        if source.starts_with("builtin:") {
            return RewardFn::from_spec(source);
        }
        Ok(RewardFn::Python(Box::new(PythonReward::from_source(source, name)?)))
    }

    /// Let each call of a Python reward take at most `limit` (built-ins need no limit).
    pub fn with_time_limit(mut self, limit: std::time::Duration) -> RewardFn {
        if let RewardFn::Python(p) = &mut self {
            p.time_limit(limit);
        }
        self
    }

    /// A short description for logs.
    pub fn describe(&self) -> String {
        match self {
            RewardFn::Builtin(b) => format!("built-in {}", b.name()),
            RewardFn::Python(p) => format!("python {}", p.path().display()),
        }
    }
}

/// Why a reward could not be computed. The run stops on any of these.
#[derive(Debug, thiserror::Error)]
pub enum RewardError {
    /// The reward file could not be read or compiled, or lacks `reward_function`.
    #[error("{origin}: {msg}")]
    Load {
        /// The file.
        origin: String,
        /// What went wrong (with the traceback for Python errors).
        msg: String,
    },
    /// `reward_function` raised.
    #[error("reward function raised an exception at step {step}:\n{traceback}\nparams: {params}")]
    Raised {
        /// The step (`params['steps']`).
        step: f64,
        /// Python's formatted traceback.
        traceback: String,
        /// The params of that step, as JSON (waypoints left out).
        params: String,
    },
    /// `reward_function` did not return within the time limit.
    #[error(
        "{file}: reward_function did not return within the time limit of {limit:?} at step {step} (stopped with RewardTimeLimit):\n{traceback}\nparams: {params}"
    )]
    TimedOut {
        /// The reward file.
        file: String,
        /// The step.
        step: f64,
        /// The limit.
        limit: std::time::Duration,
        /// Where the code was when it was stopped.
        traceback: String,
        /// The params of that step, as JSON.
        params: String,
    },
    /// `reward_function` returned something that is not an acceptable reward.
    #[error("reward function returned {value} at step {step}: {why}\nparams: {params}")]
    BadValue {
        /// The step.
        step: f64,
        /// What it returned (Python repr or the number).
        value: String,
        /// Why it is refused.
        why: String,
        /// The params of that step, as JSON.
        params: String,
    },
}

/// Check a returned number as DeepRacer does.
pub fn check_reward(value: f64, params: &RewardParams) -> Result<f64, RewardError> {
    let why = if value.is_nan() {
        "NaN is not a reward"
    } else if value.is_infinite() {
        "an infinite reward is not allowed"
    } else if value.abs() > REWARD_LIMIT {
        "outside DeepRacer's limit of [-1e5, 1e5]"
    } else {
        return Ok(value);
    };
    Err(RewardError::BadValue {
        step: params.steps,
        value: format!("{value}"),
        why: why.into(),
        params: params_json(params),
    })
}

/// Params as compact JSON for error reports.
pub fn params_json(params: &RewardParams) -> String {
    serde_json::to_string(params).unwrap_or_else(|e| format!("<unprintable params: {e}>"))
}
