//! DeepRacer's sim-trace CSV for a driven lap (`coordinator drive --simtrace`): the rows of
//! [`policy::simtrace`], from each step's [`StepOutcome`].

use crate::env::StepOutcome;
use policy::Action;
use policy::simtrace::{HEADER, Row, py_float, write_row};
use std::io::Write;

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
        track_len: f64,
        action: ActionTaken,
        o: &StepOutcome,
        wall_clock: f64,
    ) -> std::io::Result<()> {
        let action = match action {
            ActionTaken::Index(i) => i.to_string(),
            ActionTaken::Continuous(a) => format!("[{} {}]", py_float(a.steering_angle), py_float(a.speed)),
        };
        let t = policy::StepTrace { wall_clock, ..o.trace };
        let row = Row { episode, step: o.steps, trace: &t, action: &action, reward: o.reward, done: o.done, track_len };
        write_row(&mut self.out, &row)
    }

    /// Flush and return the writer.
    pub fn finish(mut self) -> std::io::Result<W> {
        self.out.flush()?;
        Ok(self.out)
    }
}
