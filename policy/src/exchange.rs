//! What the learner and the sim workers say to each other, as plain values.
//!
//! The training run (in `learner`) and the sim worker (in `sim-agent`) are peers: neither
//! depends on the other, and both speak this vocabulary. In one process the values travel
//! over channels; across machines the `protocol` crate maps them onto its protobuf messages.
//! Nothing here knows a transport.
//!
//! Flow control: the learner grants each worker a number of episodes to *start* with a policy
//! version ([`Credit`]). A worker that has spent its grant waits (or runs evaluations) until
//! the next grant, so it never simulates what the learner will not use.

use crate::experience::Trajectory;
use crate::metadata::ModelMetadata;
use crate::model::ActorCritic;
use std::collections::BTreeMap;
use std::sync::Arc;

/// A policy version, ready to act with.
#[derive(Clone)]
pub struct PolicyVersion {
    /// The version (+1 per accepted update).
    pub version: u64,
    /// The model.
    pub model: Arc<ActorCritic>,
    /// Its metadata (action space, sensors).
    pub metadata: Arc<ModelMetadata>,
}

/// Episodes each worker may start with `version`, in grant `round` (a round is re-issued
/// when a worker went away before delivering its share).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Credit {
    /// The policy version the episodes are for.
    pub version: u64,
    /// Grant round: increases with every grant of a run, whatever the version, and a later
    /// run (a restarted learner) starts above its predecessor's.
    pub round: u64,
    /// Worker id → episodes granted in this round.
    pub episodes: BTreeMap<String, u64>,
    /// The learner has closed every evaluation and verification of the policy versions up to
    /// this one (0: none said): trials of them still queued or running are wasted, and a
    /// worker drops them.
    pub checks_closed_through: u64,
}

/// Experience from one worker: complete episodes, and what producing them cost.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Experience {
    /// The worker.
    pub worker: String,
    /// Per worker, from 1: the learner drops duplicates.
    pub seq: u64,
    /// The grant these episodes were produced under (version, round).
    pub credit: (u64, u64),
    /// Complete episodes (each tagged with its world and the version that acted).
    pub trajectories: Vec<Trajectory>,
    /// Environment steps simulated for this batch.
    pub env_steps: u64,
    /// Wall time it took (s).
    pub seconds: f64,
    /// What one of the worker's cars sees now (camera jobs, at most once a second), for
    /// people watching the job; not training data, and not sent to the learner.
    pub frame: Option<Frame>,
}

/// A camera frame, grey levels row by row.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Frame {
    /// The world the car drives.
    pub world: String,
    /// Width (pixels).
    pub width: u32,
    /// Height (pixels).
    pub height: u32,
    /// `width × height` grey levels.
    pub gray: Vec<u8>,
    /// The policy version driving.
    pub policy_version: u64,
    /// The episode's step it was seen at, before acting (0: a live frame).
    pub step: u64,
}

/// Run evaluation trials of one policy version on one world (DeepRacer's evaluation worker:
/// every trial from the start line, most likely action at every step).
#[derive(Clone, Debug, PartialEq)]
pub struct EvalRequest {
    /// Request id (unique within the run).
    pub id: u64,
    /// Who should run it.
    pub worker: String,
    /// The policy version to evaluate.
    pub version: u64,
    /// The world (a built-in world name).
    pub world: String,
    /// Trials.
    pub trials: u32,
    /// Seed of the trials' actuator noise.
    pub seed: u64,
    /// The verification to run at once, on the same version and world, when these trials lap
    /// enough: the learner would ask for it as soon as every world's evaluation is in, and
    /// running it here saves that round trip (a round of episodes and an update).
    pub then_verify: Option<ChainedVerify>,
}

/// A verification chained to an evaluation ([`EvalRequest::then_verify`]): its own request id,
/// trials and noise; run when the evaluation lapped `laps` of its trials or more.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ChainedVerify {
    /// The verification's request id (its report answers this id).
    pub id: u64,
    /// Trials.
    pub trials: u32,
    /// Seed of the trials' actuator noise.
    pub seed: u64,
    /// Laps the evaluation's trials must make for the verification to run.
    pub laps: u32,
}

impl EvalRequest {
    /// The verification chained to this evaluation, as a request of its own (`None` without
    /// one, or when `trials` did not lap enough for it).
    pub fn chained(&self, trials: &[Trial]) -> Option<EvalRequest> {
        let v = self.then_verify?;
        (summarise(trials).2 >= v.laps as usize).then(|| EvalRequest {
            id: v.id,
            worker: self.worker.clone(),
            version: self.version,
            world: self.world.clone(),
            trials: v.trials,
            seed: v.seed,
            then_verify: None,
        })
    }
}

/// One evaluation trial.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Trial {
    /// Progress reached (%).
    pub progress: f64,
    /// Lap time if the lap was completed (s, penalties included).
    pub lap_time: Option<f64>,
    /// Times the car left the track.
    pub off_track: u32,
    /// Times the car crashed into an obstacle or a bot.
    pub crashes: u32,
    /// Bots the car overtook (per bot, the times it went past it less the times the bot went
    /// past the car, when more), in a race with bots.
    pub overtakes: Option<u32>,
    /// The trial's reward: its steps' summed (whether or not the job records).
    pub reward: f64,
    /// Steps taken.
    pub steps: u64,
    /// How the trial ended (DeepRacer's status label).
    pub status: String,
    /// Per step (when the job records): what the policy chose, the reward and the
    /// sim-trace fields, for DeepRacer's evaluation sim-trace. Empty otherwise.
    pub choices: Vec<crate::Choice>,
    /// Rewards, one per step of `choices`.
    pub rewards: Vec<f32>,
    /// The sim-trace fields, one per step of `choices`.
    pub trace: Vec<crate::StepTrace>,
    /// Length of the track driven (m); DeepRacer's `track_len` column.
    pub track_len: f64,
    /// Camera jobs that record: what the car saw in this trial, every second step (the first
    /// trial of a request only), for the MCAP log.
    pub frames: Vec<Frame>,
}

/// The answer to an [`EvalRequest`].
#[derive(Clone, Debug, PartialEq)]
pub struct EvalReport {
    /// The request's id.
    pub id: u64,
    /// The worker that ran it.
    pub worker: String,
    /// The version evaluated.
    pub version: u64,
    /// The world.
    pub world: String,
    /// The trials, or why they could not run.
    pub trials: Result<Vec<Trial>, String>,
}

/// Laps of `trials` trials that keep the share of `laps` in `of` (3 of 3 → every trial; 2 of
/// 3 → 7 of 10), never more than there are: what a verification needs, on the learner that
/// judges it and on the worker that runs it.
pub fn laps_needed(laps: usize, of: usize, trials: usize) -> usize {
    let share = laps.min(of) as f64 / of.max(1) as f64;
    ((share * trials as f64) - 1e-9).ceil().clamp(0.0, trials as f64) as usize
}

/// Mean progress, mean lap time (when every trial completed), laps completed.
pub fn summarise(trials: &[Trial]) -> (f64, Option<f64>, usize) {
    let n = trials.len().max(1) as f64;
    let progress = trials.iter().map(|t| t.progress).sum::<f64>() / n;
    let laps = trials.iter().filter(|t| t.lap_time.is_some()).count();
    let lap = (laps == trials.len() && laps > 0).then(|| trials.iter().filter_map(|t| t.lap_time).sum::<f64>() / n);
    (progress, lap, laps)
}
