//! DeepRacer's sim-trace CSV (simapp's `markov/metrics/constants.py::StepMetrics`): the 19
//! columns of simapp 6, in order, values written as Python's `str()` writes them, so
//! `deepracer-utils` and existing notebooks read Paddock's traces unchanged. The simulator
//! (`coordinator drive`) and the learner (training and evaluation logs) both write through
//! this module.

use crate::experience::{StepTrace, Trajectory};
use crate::metadata::ActionSpace;
use crate::model::Choice;
use std::io::Write;

/// Seconds since the Unix epoch: the `wall_clock` column (Python's `time.time()`), and the
/// learner's log timestamps.
pub fn unix_now() -> f64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs_f64()).unwrap_or(0.0)
}

/// The header line of simapp 6's `training-simtrace/<N>-iteration.csv`.
pub const HEADER: &str = "episode,steps,X,Y,yaw,steer,throttle,action,reward,done,all_wheels_on_track,progress,closest_waypoint,track_len,tstamp,episode_status,pause_duration,obstacle_crash_counter,wall_clock";

/// Python's `str(float)`: the shortest repr that reads back, always with a decimal point or
/// an exponent.
pub fn py_float(v: f64) -> String {
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

/// The `action` column: the discrete index, or `[steer speed]` in the model's units for a
/// continuous space, as DeepRacer writes them.
pub fn action_text(choice: &Choice, space: &ActionSpace) -> String {
    match choice {
        Choice::Discrete(i) => i.to_string(),
        Choice::Continuous(_) => {
            let a = choice.to_action(space);
            format!("[{} {}]", py_float(a.steering_angle), py_float(a.speed))
        }
    }
}

/// One row of a simtrace CSV: a step and what it was worth.
#[derive(Clone, Copy, Debug)]
pub struct Row<'a> {
    /// DeepRacer's episode column (training: the worker's episode counter; evaluation: the
    /// trial).
    pub episode: u64,
    /// The step, from 1.
    pub step: u64,
    /// Where the car was and what it did.
    pub trace: &'a StepTrace,
    /// The action as DeepRacer writes it (an index, or `[steering speed]`).
    pub action: &'a str,
    /// The step's reward.
    pub reward: f64,
    /// The episode's last step.
    pub done: bool,
    /// The track's length (m).
    pub track_len: f64,
}

/// Write `row` as DeepRacer's simapp writes it.
pub fn write_row(out: &mut impl Write, row: &Row<'_>) -> std::io::Result<()> {
    let Row { episode, step, trace: t, action, reward, done, track_len } = *row;
    writeln!(
        out,
        "{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{},{}",
        episode,
        py_float(step as f64),
        py_float(t.x),
        py_float(t.y),
        py_float(t.yaw as f64),
        py_float(t.steer as f64),
        py_float(t.throttle as f64),
        action,
        py_float(reward),
        py_bool(done),
        py_bool(t.all_wheels_on_track),
        py_float(t.progress as f64),
        t.closest_waypoint,
        py_float(track_len),
        py_float(t.tstamp),
        t.status.label(),
        py_float(t.pause_duration as f64),
        0,
        py_float(t.wall_clock),
    )
}

/// Every recorded step of a trajectory (nothing when it carries no trace).
pub fn write_trajectory(
    out: &mut impl Write,
    episode: u64,
    t: &Trajectory,
    space: &ActionSpace,
) -> std::io::Result<()> {
    let n = t.trace.len();
    for (i, ((s, c), r)) in t.trace.iter().zip(&t.choices).zip(&t.rewards).enumerate() {
        let done = t.done && i + 1 == n;
        let action = action_text(c, space);
        let row = Row {
            episode,
            step: i as u64 + 1,
            trace: s,
            action: &action,
            reward: *r as f64,
            done,
            track_len: t.track_len,
        };
        write_row(out, &row)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rows_are_written_as_python_writes_them() {
        let t = StepTrace {
            x: 0.20775390119932716,
            y: -2.1729670099725897,
            yaw: 180.0,
            steer: 15.0,
            throttle: 1.5,
            progress: 0.25,
            closest_waypoint: 0,
            all_wheels_on_track: true,
            status: crate::EpisodeStatus::Prepare,
            tstamp: 36.721000000000004,
            pause_duration: 0.0,
            wall_clock: 1772822267.7927284,
        };
        let mut out = Vec::new();
        let row =
            Row { episode: 0, step: 1, trace: &t, action: "8", reward: 0.0, done: false, track_len: 59.99785047027138 };
        write_row(&mut out, &row).unwrap();
        assert_eq!(
            String::from_utf8(out).unwrap(),
            "0,1.0,0.20775390119932716,-2.1729670099725897,180.0,15.0,1.5,8,0.0,False,True,0.25,0,59.99785047027138,36.721000000000004,prepare,0.0,0,1772822267.7927284\n"
        );
        assert_eq!(HEADER.split(',').count(), 19);
    }
}
