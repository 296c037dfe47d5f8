//! DeepRacer's sim-trace CSV (§4.1 of the reference): the 19 columns of simapp 6, in order,
//! values written as Python's `str()` would, so `deepracer-utils` and existing notebooks
//! read Paddock's traces unchanged.

use crate::env::StepOutcome;
use crate::params::RewardParams;
use policy::Action;
use std::io::Write;
use tracks::{P2, Track};

/// The header line of simapp 6.0's `training-simtrace/<N>-iteration.csv`.
pub const HEADER: &str = "episode,steps,X,Y,yaw,steer,throttle,action,reward,done,all_wheels_on_track,progress,closest_waypoint,track_len,tstamp,episode_status,pause_duration,obstacle_crash_counter,wall_clock";

/// Which action was taken: a discrete index, or a continuous pair.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ActionTaken {
    /// Index into the discrete action list.
    Index(usize),
    /// Continuous action, written `[steer speed]` as DeepRacer does.
    Continuous(Action),
}

/// Writes sim-trace rows.
pub struct SimTraceWriter<W: Write> {
    out: W,
}

/// Python's `str(float)` for the values DeepRacer writes: shortest round-trip repr, always
/// with a decimal point or exponent.
fn py_float(v: f64) -> String {
    if v.is_nan() {
        "nan".into()
    } else if v.is_infinite() {
        if v > 0.0 { "inf".into() } else { "-inf".into() }
    } else {
        format!("{v:?}")
    }
}

fn py_bool(b: bool) -> &'static str {
    if b { "True" } else { "False" }
}

impl<W: Write> SimTraceWriter<W> {
    /// Start a file: writes the header.
    pub fn new(mut out: W) -> std::io::Result<SimTraceWriter<W>> {
        writeln!(out, "{HEADER}")?;
        Ok(SimTraceWriter { out })
    }

    /// One step's row. `episode` is the episode counter (evaluation: the trial).
    pub fn row(
        &mut self,
        episode: u64,
        track: &Track,
        p: &RewardParams,
        action: ActionTaken,
        o: &StepOutcome,
        wall_clock: f64,
    ) -> std::io::Result<()> {
        let [prev, next] = p.closest_waypoints;
        let wp = track.waypoints();
        let here = P2::new(p.x, p.y);
        let closest = if (wp[next] - here).norm() < (wp[prev] - here).norm() { next } else { prev };
        let action = match action {
            ActionTaken::Index(i) => i.to_string(),
            ActionTaken::Continuous(a) => format!("[{} {}]", py_float(a.steering_angle), py_float(a.speed)),
        };
        writeln!(
            self.out,
            "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}",
            episode,
            py_float(p.steps),
            py_float(p.x),
            py_float(p.y),
            py_float(p.heading),
            py_float(p.steering_angle),
            py_float(p.speed),
            action,
            py_float(o.reward),
            py_bool(o.done),
            py_bool(p.all_wheels_on_track),
            py_float(o.progress),
            closest,
            py_float(p.track_length),
            py_float(p.sim_time),
            o.status.label(),
            py_float(0.0),
            0,
            py_float(wall_clock),
        )
    }

    /// Flush and return the writer.
    pub fn finish(mut self) -> std::io::Result<W> {
        self.out.flush()?;
        Ok(self.out)
    }
}
