//! Experience: what acting produces and learning consumes. Every trajectory carries the
//! policy version that acted, so staleness can be measured and bounded, and (when the job
//! records) each step's sim-trace fields, so the learner can write DeepRacer's logs without
//! a simulator of its own.

use crate::model::Choice;

/// One episode (or a segment of one) from one environment, stored column-wise.
#[derive(Clone, Debug, PartialEq, Default)]
pub struct Trajectory {
    /// The world it was driven on (a built-in world name).
    pub world: String,
    /// The environment (agent-local index).
    pub env: u32,
    /// That environment's episode counter.
    pub episode: u64,
    /// The policy version that chose these actions.
    pub policy_version: u64,
    /// Observations, `len × obs_size`, row-major.
    pub obs: Vec<f32>,
    /// What the policy chose.
    pub choices: Vec<Choice>,
    /// log π(choice | obs) at acting time (the behaviour log-probabilities).
    pub logp: Vec<f32>,
    /// V(obs) at acting time, where the acting computed it: a sim agent on the CPU acts with
    /// the policy tower alone and sends 0 (PPO's update computes the values as it begins).
    pub values: Vec<f32>,
    /// Rewards.
    pub rewards: Vec<f32>,
    /// The episode ended at the last step (otherwise the segment was cut).
    pub done: bool,
    /// Progress (%) when the trajectory ended.
    pub progress: f64,
    /// A lap was completed.
    pub lap_complete: bool,
    /// Length of the track driven (m); DeepRacer's `track_len` column.
    pub track_len: f64,
    /// Per step, what DeepRacer's sim-trace row holds beyond the action and reward; empty
    /// when the job does not record.
    pub trace: Vec<StepTrace>,
}

/// DeepRacer's `episode_status` values (the sim-trace labels).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum EpisodeStatus {
    /// The first step of an episode.
    #[default]
    Prepare,
    /// Driving.
    InProgress,
    /// All four wheels off the road.
    OffTrack,
    /// Progress fell for too many steps in a row.
    Reversed,
    /// The car stopped moving.
    Immobilized,
    /// Progress reached 100.
    LapComplete,
    /// The race's time limit ran out.
    TimeUp,
    /// Evaluation: the car waits out a reset's time penalty, held where it was put back.
    Pause,
    /// A car corner inside an obstacle, or inside a bot the car ran into from behind.
    Crashed,
}

impl EpisodeStatus {
    /// Every status, in code order ([`EpisodeStatus::code`]).
    pub const ALL: [EpisodeStatus; 9] = [
        EpisodeStatus::Prepare,
        EpisodeStatus::InProgress,
        EpisodeStatus::OffTrack,
        EpisodeStatus::Reversed,
        EpisodeStatus::Immobilized,
        EpisodeStatus::LapComplete,
        EpisodeStatus::TimeUp,
        EpisodeStatus::Pause,
        EpisodeStatus::Crashed,
    ];

    /// The label DeepRacer's sim-trace writes.
    pub fn label(self) -> &'static str {
        match self {
            EpisodeStatus::Prepare => "prepare",
            EpisodeStatus::InProgress => "in_progress",
            EpisodeStatus::OffTrack => "off_track",
            EpisodeStatus::Reversed => "reversed",
            EpisodeStatus::Immobilized => "immobilized",
            EpisodeStatus::LapComplete => "lap_complete",
            EpisodeStatus::TimeUp => "time_up",
            EpisodeStatus::Pause => "pause",
            EpisodeStatus::Crashed => "crashed",
        }
    }

    /// The label DeepRacer's metrics JSON writes (`"Lap complete"`, `"Off track"`, …).
    pub fn metrics_label(self) -> &'static str {
        match self {
            EpisodeStatus::Prepare => "Prepare",
            EpisodeStatus::InProgress => "In progress",
            EpisodeStatus::OffTrack => "Off track",
            EpisodeStatus::Reversed => "Reversed",
            EpisodeStatus::Immobilized => "Immobilized",
            EpisodeStatus::LapComplete => "Lap complete",
            EpisodeStatus::TimeUp => "Time Up",
            EpisodeStatus::Pause => "Pause",
            EpisodeStatus::Crashed => "Crashed",
        }
    }

    /// A small number for the wire.
    pub fn code(self) -> u32 {
        EpisodeStatus::ALL.iter().position(|s| *s == self).expect("listed") as u32
    }

    /// The status with this code, if any.
    pub fn from_code(code: u32) -> Option<EpisodeStatus> {
        EpisodeStatus::ALL.get(code as usize).copied()
    }
}

/// One step's sim-trace fields (simapp's `markov/metrics/constants.py::StepMetrics`), apart
/// from the episode counter, the action and the reward, which the trajectory holds.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StepTrace {
    /// The car's reference point, x (m) (`X`).
    pub x: f64,
    /// The car's reference point, y (m) (`Y`).
    pub y: f64,
    /// Heading (degrees) (`yaw`).
    pub yaw: f32,
    /// Commanded steering (degrees) (`steer`).
    pub steer: f32,
    /// Commanded speed (m/s) (`throttle`).
    pub throttle: f32,
    /// Progress (%) after the step.
    pub progress: f32,
    /// The nearer of the two closest waypoints (`closest_waypoint`).
    pub closest_waypoint: u32,
    /// `all_wheels_on_track`.
    pub all_wheels_on_track: bool,
    /// `episode_status`.
    pub status: EpisodeStatus,
    /// Simulation time since the episode started (s) (`tstamp`).
    pub tstamp: f64,
    /// Penalty seconds still to serve (`pause_duration`).
    pub pause_duration: f32,
    /// Unix time when the step was taken (`wall_clock`).
    pub wall_clock: f64,
}

impl Trajectory {
    /// Steps in the trajectory.
    pub fn len(&self) -> usize {
        self.rewards.len()
    }

    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.rewards.is_empty()
    }

    /// The bytes its columns hold on the heap (what keeping it costs).
    pub fn heap_bytes(&self) -> usize {
        use std::mem::size_of;
        self.world.capacity()
            + size_of::<f32>()
                * (self.obs.capacity() + self.logp.capacity() + self.values.capacity() + self.rewards.capacity())
            + size_of::<Choice>() * self.choices.capacity()
            + size_of::<StepTrace>() * self.trace.capacity()
    }
}

/// A world's track as lines (centre, inner and outer borders, in the driving direction), for
/// logs and charts drawn where no simulator runs (the learner's MCAP, reports).
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TrackLines {
    /// The world's name.
    pub world: String,
    /// Centre-line length (m).
    pub length: f64,
    /// Centre line (the waypoints), x–y in metres.
    pub centre: Vec<[f64; 2]>,
    /// Inner border.
    pub inner: Vec<[f64; 2]>,
    /// Outer border.
    pub outer: Vec<[f64; 2]>,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue 54: what keeping an episode costs counts its observations, the largest column,
    /// and its trace; an empty one costs nothing.
    #[test]
    fn an_episodes_heap_bytes_count_its_observations_and_trace() {
        assert_eq!(Trajectory::default().heap_bytes(), 0);
        let (n, obs) = (200, 19_200);
        let t = Trajectory {
            obs: vec![0.0; n * obs],
            rewards: vec![0.0; n],
            trace: vec![StepTrace::default(); n],
            ..Trajectory::default()
        };
        let least = 4 * n * obs + 4 * n + n * std::mem::size_of::<StepTrace>();
        assert_eq!(t.heap_bytes(), least);
    }
}
