//! The wire: Zenoh key expressions, message schemas (`proto/paddock.proto`, protobuf via
//! prost) and their encoding. The only crate that knows how anything crosses a process
//! boundary; the roles are thin shells over it and the libraries.
//!
//! Decoding never panics: a message that does not decode, is over [`MAX_MESSAGE_BYTES`], or
//! carries another [`PROTOCOL_VERSION`] is an error the caller counts and drops.
//!
//! # Key expressions
//!
//! Every key starts with [`keys::ROOT`] (`paddock/v1`). The first column names the function
//! or constant in [`keys`] that makes the key; a second name there is its wildcard twin (`*`,
//! or `**` for experience), which subscribers use. The coordinator's tick is 500 ms.
//!
//! | [`keys`] | key under `paddock/v1` | payload | who publishes |
//! |---|---|---|---|
//! | `agent_alive`, `AGENTS_ALIVE` | `alive/agent/{agent}` | liveliness token | sim agent |
//! | `learner_alive`, `LEARNERS_ALIVE` | `alive/learner/{learner}` | liveliness token | learner |
//! | `COORDINATOR_ALIVE` | `alive/coordinator` | liveliness token | coordinator |
//! | `car_alive`, `ALL_CARS_ALIVE` | `alive/car/{car}` | liveliness token | on-car agent (`deploy`) |
//! | `agent_info` | `agent/{agent}/info` | [`AgentInfo`] (queryable) | sim agent |
//! | `assignment` | `assign/{agent}` | [`Assignment`] (re-sent every tick) | coordinator |
//! | `JOBS` | `jobs` | [`AssignmentTable`] per running job (every tick) | coordinator |
//! | `CONTROL` | `control` | [`JobRequest`] → [`JobReply`] (queryable) | coordinator |
//! | `REVOKED` | `revoked` | the cluster CA's X.509 CRL, DER ([`revocation`]; re-sent every 10 s, and queryable) | coordinator |
//! | `job_spec`, `JOB_SPECS` | `job/{job}/spec` | [`Job`] (queryable; fetched once per job) | coordinator |
//! | `experience`, `experience_all` | `job/{job}/experience/{agent}` | [`ExperienceBatch`] | sim agent |
//! | `camera`, `cameras` | `job/{job}/camera/{agent}` | [`CameraFrame`] (camera jobs, ≤ 1 a second; for watchers) | sim agent |
//! | `eval_report`, `eval_reports` | `job/{job}/eval/report/{agent}` | [`EvalReport`] | sim agent |
//! | `agent_report`, `ALL_REPORTS` | `job/{job}/report/{agent}` | [`AgentReport`] (a failure) | sim agent |
//! | `credit` | `job/{job}/credit` | [`Credit`] (re-sent every second during a grant round; says through which version the checks are closed) | learner |
//! | `eval_request` | `job/{job}/eval/request/{agent}` | [`EvalRequest`] | learner |
//! | `policy` | `job/{job}/policy` | [`PolicyUpdate`] (publication and "latest" queryable) | learner |
//! | `best` | `job/{job}/best` | [`PolicyUpdate`] of the best model (publication and queryable) | learner |
//! | `promote` | `job/{job}/promote` | [`JobPromote`] → [`JobReply`] (queryable) | learner |
//! | `learner_status`, `ALL_LEARNER_STATUS` | `job/{job}/learner` | [`LearnerStatus`] (every update and second) | learner |
//! | `team_plan` | `job/{job}/team/plan` | [`TeamPlan`] (one per update) | a learner team's leader |
//! | `team_share`, `team_shares` | `job/{job}/team/share/{learner}` | [`GradShare`] | every team member |
//! | `team_join`, `team_joins` | `job/{job}/team/join/{learner}` | [`TeamJoin`] (every 500 ms) | a learner that follows |
//! | `team_memory` | `job/{job}/team/memory` | [`TeamMemory`] (SAC's replay memory in parts, for a joiner) | a learner team's leader |
//! | `car_status`, `ALL_CAR_STATUS` | `car/{car}/status` | [`CarStatus`] (once a second) | on-car agent |
//! | `car_control` | `car/{car}/control` | [`CarControl`] (the e-stop) | a person (`coordinator cars`) |
//! | `car_assign` | `car/{car}/assign` | [`CarAssign`] (the job to follow, its model) | an organiser (the console) |
//!
//! [`keys`] also has helpers: `job_of` (the job id in a key), `last` (a key's last chunk) and
//! `is_valid_name` (what a name in a key may hold). The car's own ROS 2 topics are outside
//! `paddock/v1`, under the bridge's namespace ([`ros::CarKeys`]):
//!
//! | key | payload | who publishes |
//! |---|---|---|
//! | `{ns}/sensor_fusion_pkg/sensor_msg` | the car's `EvoSensorMsg`, CDR ([`ros`]) | the car (zenoh-bridge-ros2dds) |
//! | `{ns}/deepracer_navigation_pkg/auto_drive` | `ServoCtrlMsg`, CDR ([`ros`]) | on-car agent |
//!
//! # Modules
//!
//! [`exchange`] (the learner's and workers' values on the wire, each checked against its
//! job), [`job`] (the job, its stop conditions and the coordinator's record of it), [`net`] (sessions, `NetCli`, typed
//! put/subscribe/query that count drops), [`secure`] (roles, certificates, access control,
//! logging), [`ros`] (the car's ROS 2 messages), [`exit`] (the exit codes of every binary).

use prost::Message;

#[allow(missing_docs, clippy::all)]
mod generated {
    include!(concat!(env!("OUT_DIR"), "/paddock.v1.rs"));
}

pub use generated::*;

pub mod exchange;
pub mod exit;
pub mod job;
pub mod join;
pub mod net;
pub mod revocation;
pub mod ros;
pub mod secure;
pub mod service;

/// The version every message carries; others are dropped.
pub const PROTOCOL_VERSION: u32 = 3;
/// The largest message accepted (a SHALLOW camera model is ≈47 MB for both towers).
pub const MAX_MESSAGE_BYTES: usize = 256 << 20;

/// Key expressions.
pub mod keys {
    /// Every key starts with this.
    pub const ROOT: &str = "paddock/v1";

    /// A sim agent's liveliness token.
    pub fn agent_alive(agent: &str) -> String {
        format!("{ROOT}/alive/agent/{agent}")
    }
    /// All sim agents' liveliness tokens.
    pub const AGENTS_ALIVE: &str = "paddock/v1/alive/agent/*";
    /// A learner's liveliness token.
    pub fn learner_alive(learner: &str) -> String {
        format!("{ROOT}/alive/learner/{learner}")
    }
    /// All learners' tokens.
    pub const LEARNERS_ALIVE: &str = "paddock/v1/alive/learner/*";
    /// The coordinator's token.
    pub const COORDINATOR_ALIVE: &str = "paddock/v1/alive/coordinator";
    /// A sim agent's info queryable.
    pub fn agent_info(agent: &str) -> String {
        format!("{ROOT}/agent/{agent}/info")
    }
    /// A sim agent's assignment.
    pub fn assignment(agent: &str) -> String {
        format!("{ROOT}/assign/{agent}")
    }
    /// The running jobs' tables.
    pub const JOBS: &str = "paddock/v1/jobs";
    /// Experience of a job from one agent.
    pub fn experience(job: &str, agent: &str) -> String {
        format!("{ROOT}/job/{job}/experience/{agent}")
    }
    /// A job's grants.
    pub fn credit(job: &str) -> String {
        format!("{ROOT}/job/{job}/credit")
    }
    /// Evaluation requests to one agent.
    pub fn eval_request(job: &str, agent: &str) -> String {
        format!("{ROOT}/job/{job}/eval/request/{agent}")
    }
    /// Evaluation reports from one agent.
    pub fn eval_report(job: &str, agent: &str) -> String {
        format!("{ROOT}/job/{job}/eval/report/{agent}")
    }
    /// Every agent's evaluation reports for a job.
    pub fn eval_reports(job: &str) -> String {
        format!("{ROOT}/job/{job}/eval/report/*")
    }
    /// All experience of a job.
    pub fn experience_all(job: &str) -> String {
        format!("{ROOT}/job/{job}/experience/**")
    }
    /// A job's policy publications and "latest model" queryable.
    pub fn policy(job: &str) -> String {
        format!("{ROOT}/job/{job}/policy")
    }
    /// A job's best model so far (publication and queryable), signed like every model.
    pub fn best(job: &str) -> String {
        format!("{ROOT}/job/{job}/best")
    }
    /// A job's promotion queryable (the learner answers: the version cars following "best" drive).
    pub fn promote(job: &str) -> String {
        format!("{ROOT}/job/{job}/promote")
    }
    /// A car's liveliness token.
    pub fn car_alive(car: &str) -> String {
        format!("{ROOT}/alive/car/{car}")
    }
    /// Every car's liveliness token.
    pub const ALL_CARS_ALIVE: &str = "paddock/v1/alive/car/*";
    /// A car's status (once a second).
    pub fn car_status(car: &str) -> String {
        format!("{ROOT}/car/{car}/status")
    }
    /// Every car's status.
    pub const ALL_CAR_STATUS: &str = "paddock/v1/car/*/status";
    /// A car's assignment (the job whose models it follows).
    pub fn car_assign(car: &str) -> String {
        format!("{ROOT}/car/{car}/assign")
    }
    /// A car's control (the e-stop).
    pub fn car_control(car: &str) -> String {
        format!("{ROOT}/car/{car}/control")
    }
    /// A job's learner status.
    pub fn learner_status(job: &str) -> String {
        format!("{ROOT}/job/{job}/learner")
    }
    /// A job's document (the coordinator's queryable).
    pub fn job_spec(job: &str) -> String {
        format!("{ROOT}/job/{job}/spec")
    }
    /// Every job's document.
    pub const JOB_SPECS: &str = "paddock/v1/job/*/spec";
    /// The job id in a key under `{ROOT}/job/`.
    pub fn job_of(key: &str) -> Option<&str> {
        key.strip_prefix("paddock/v1/job/").and_then(|r| r.split('/').next())
    }
    /// A job's team plans (learner leader to members).
    pub fn team_plan(job: &str) -> String {
        format!("{ROOT}/job/{job}/team/plan")
    }
    /// A job's team memory parts (learner leader to joiners).
    pub fn team_memory(job: &str) -> String {
        format!("{ROOT}/job/{job}/team/memory")
    }
    /// One learner's gradient shares for a job.
    pub fn team_share(job: &str, learner: &str) -> String {
        format!("{ROOT}/job/{job}/team/share/{learner}")
    }
    /// Every learner's gradient shares for a job.
    pub fn team_shares(job: &str) -> String {
        format!("{ROOT}/job/{job}/team/share/*")
    }
    /// One learner's wish to take part in a job's updates.
    pub fn team_join(job: &str, learner: &str) -> String {
        format!("{ROOT}/job/{job}/team/join/{learner}")
    }
    /// Every learner's wish to take part.
    pub fn team_joins(job: &str) -> String {
        format!("{ROOT}/job/{job}/team/join/*")
    }
    /// The coordinator's job-control queryable.
    pub const CONTROL: &str = "paddock/v1/control";
    /// The cluster's certificate revocation list (DER X.509 CRL signed by the cluster's CA):
    /// the coordinator publishes it and answers queries for it.
    pub const REVOKED: &str = "paddock/v1/revoked";
    /// What one of an agent's cars sees (camera jobs), for watchers.
    pub fn camera(job: &str, agent: &str) -> String {
        format!("{ROOT}/job/{job}/camera/{agent}")
    }
    /// Every agent's camera frames of a job.
    pub fn cameras(job: &str) -> String {
        format!("{ROOT}/job/{job}/camera/*")
    }
    /// An agent's failure report for a job.
    pub fn agent_report(job: &str, agent: &str) -> String {
        format!("{ROOT}/job/{job}/report/{agent}")
    }
    /// Every job's failure reports.
    pub const ALL_REPORTS: &str = "paddock/v1/job/*/report/*";
    /// Every job's learner status.
    pub const ALL_LEARNER_STATUS: &str = "paddock/v1/job/*/learner";

    /// The last chunk of a key (an agent id from a token key, say).
    pub fn last(key: &str) -> &str {
        key.rsplit('/').next().unwrap_or(key)
    }

    /// A name safe in a key expression: letters, digits, `-`, `_`, `.`.
    pub fn is_valid_name(s: &str) -> bool {
        !s.is_empty() && s.len() <= 128 && s.chars().all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
    }
}

/// Why a message was dropped.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum DecodeError {
    /// Over the size limit.
    #[error("message of {0} bytes is over the {MAX_MESSAGE_BYTES}-byte limit")]
    TooLarge(usize),
    /// Not a valid encoding of the expected message.
    #[error("malformed message: {0}")]
    Malformed(String),
    /// Another protocol version.
    #[error("protocol version {0}, expected {PROTOCOL_VERSION}")]
    Version(u32),
    /// Well-formed but inconsistent (e.g. column lengths disagree).
    #[error("invalid message: {0}")]
    Invalid(String),
}

/// Messages that carry a protocol version.
pub trait Versioned: Message + Default {
    /// The version field.
    fn version(&self) -> u32;
}

macro_rules! versioned {
    ($($t:ty),*) => {$(impl Versioned for $t { fn version(&self) -> u32 { self.protocol_version } })*};
}
versioned!(
    CameraFrame,
    AgentInfo,
    Assignment,
    AssignmentTable,
    ExperienceBatch,
    PolicyUpdate,
    LearnerStatus,
    JobRequest,
    JobReply,
    AgentReport,
    Credit,
    EvalRequest,
    EvalReport,
    TeamPlan,
    GradShare,
    TeamJoin,
    TeamMemory,
    Job,
    CarStatus,
    CarControl,
    CarAssign,
    JobPromote,
    JoinRequest,
    JoinReply
);

/// Encode a message.
pub fn encode<M: Message>(m: &M) -> Vec<u8> {
    m.encode_to_vec()
}

/// Decode a message, checking size and version. Never panics.
pub fn decode<M: Versioned>(bytes: &[u8]) -> Result<M, DecodeError> {
    if bytes.len() > MAX_MESSAGE_BYTES {
        return Err(DecodeError::TooLarge(bytes.len()));
    }
    let m = M::decode(bytes).map_err(|e| DecodeError::Malformed(e.to_string()))?;
    if m.version() != PROTOCOL_VERSION {
        return Err(DecodeError::Version(m.version()));
    }
    Ok(m)
}

/// Choices as the wire's two columns (discrete indices, continuous pairs).
pub fn choices_to_wire(choices: &[policy::Choice]) -> (Vec<u32>, Vec<f32>) {
    let mut discrete = Vec::new();
    let mut continuous = Vec::new();
    for c in choices {
        match c {
            policy::Choice::Discrete(i) => discrete.push(*i as u32),
            policy::Choice::Continuous(x) => continuous.extend_from_slice(x),
        }
    }
    (discrete, continuous)
}

/// Steps' sim-trace fields on the wire (`None` when none were recorded).
pub fn trace_to_wire(trace: &[policy::StepTrace]) -> Option<StepTraces> {
    if trace.is_empty() {
        return None;
    }
    let col = |f: &dyn Fn(&policy::StepTrace) -> f64| trace.iter().map(f).collect::<Vec<f64>>();
    let colf = |f: &dyn Fn(&policy::StepTrace) -> f32| trace.iter().map(f).collect::<Vec<f32>>();
    Some(StepTraces {
        x: col(&|s| s.x),
        y: col(&|s| s.y),
        yaw: colf(&|s| s.yaw),
        steer: colf(&|s| s.steer),
        throttle: colf(&|s| s.throttle),
        progress: colf(&|s| s.progress),
        closest_waypoint: trace.iter().map(|s| s.closest_waypoint).collect(),
        all_wheels_on_track: trace.iter().map(|s| s.all_wheels_on_track).collect(),
        status: trace.iter().map(|s| s.status.code()).collect(),
        tstamp: col(&|s| s.tstamp),
        pause_duration: colf(&|s| s.pause_duration),
        wall_clock: col(&|s| s.wall_clock),
    })
}

/// Steps' sim-trace fields back: none, or one of each per step, every number finite and in
/// range (positions within ±10 km, angles and speeds within ±10⁴, progress within
/// [`limits::PROGRESS`], known statuses, times not negative).
pub fn trace_from_wire(w: Option<StepTraces>, steps: usize) -> Result<Vec<policy::StepTrace>, DecodeError> {
    let Some(w) = w else { return Ok(Vec::new()) };
    let bad = |m: String| Err(DecodeError::Invalid(m));
    let lens = [
        w.x.len(),
        w.y.len(),
        w.yaw.len(),
        w.steer.len(),
        w.throttle.len(),
        w.progress.len(),
        w.closest_waypoint.len(),
        w.all_wheels_on_track.len(),
        w.status.len(),
        w.tstamp.len(),
        w.pause_duration.len(),
        w.wall_clock.len(),
    ];
    if lens.iter().any(|&l| l != steps) {
        return bad(format!("sim-trace columns of {lens:?} rows for {steps} steps"));
    }
    let within = |v: f64, limit: f64| v.is_finite() && v.abs() <= limit;
    if !w.x.iter().chain(&w.y).all(|&v| within(v, 1e4)) {
        return bad("sim-trace position not finite or beyond ±10 km".into());
    }
    if !w.yaw.iter().chain(&w.steer).chain(&w.throttle).all(|&v| within(v as f64, 1e4)) {
        return bad("sim-trace heading, steering or speed not finite or beyond ±1e4".into());
    }
    if !w.progress.iter().all(|&p| p.is_finite() && limits::PROGRESS.contains(&(p as f64))) {
        return bad("sim-trace progress outside [-100, 100]".into());
    }
    if !w.tstamp.iter().chain(&w.wall_clock).all(|&t| t.is_finite() && (0.0..=1e12).contains(&t))
        || !w.pause_duration.iter().all(|&t| t.is_finite() && (0.0..=1e4).contains(&t))
    {
        return bad("sim-trace times not finite or negative".into());
    }
    if let Some(c) = w.closest_waypoint.iter().find(|&&c| c as u64 > exchange::SANITY_LIMIT) {
        return bad(format!("sim-trace waypoint {c} beyond {}", exchange::SANITY_LIMIT));
    }
    let mut out = Vec::with_capacity(steps);
    for i in 0..steps {
        let Some(status) = policy::EpisodeStatus::from_code(w.status[i]) else {
            return bad(format!("sim-trace status code {} unknown", w.status[i]));
        };
        out.push(policy::StepTrace {
            x: w.x[i],
            y: w.y[i],
            yaw: w.yaw[i],
            steer: w.steer[i],
            throttle: w.throttle[i],
            progress: w.progress[i],
            closest_waypoint: w.closest_waypoint[i],
            all_wheels_on_track: w.all_wheels_on_track[i],
            status,
            tstamp: w.tstamp[i],
            pause_duration: w.pause_duration[i],
            wall_clock: w.wall_clock[i],
        });
    }
    Ok(out)
}

/// The wire's two action columns back as `n` choices of the job's action space.
pub fn choices_from_wire(
    discrete: &[u32],
    continuous: &[f32],
    n: usize,
    actions: Actions,
) -> Result<Vec<policy::Choice>, DecodeError> {
    let bad = |m: String| Err(DecodeError::Invalid(m));
    if !discrete.is_empty() || continuous.is_empty() {
        if discrete.len() != n {
            return bad(format!("{} discrete actions for {n} steps", discrete.len()));
        }
        let Actions::Discrete(count) = actions else {
            return bad("discrete actions for a continuous action space".into());
        };
        if let Some(a) = discrete.iter().find(|a| **a as usize >= count) {
            return bad(format!("discrete action {a} outside the action space of {count} actions"));
        }
        Ok(discrete.iter().map(|&a| policy::Choice::Discrete(a as usize)).collect())
    } else {
        if actions != Actions::Continuous {
            return bad("continuous actions for a discrete action space".into());
        }
        if continuous.len() != 2 * n {
            return bad(format!("{} continuous action values for {n} steps", continuous.len()));
        }
        // Negated so that NaN is refused too.
        #[allow(clippy::neg_cmp_op_on_partial_ord)]
        if let Some(a) = continuous.iter().find(|a| !(a.abs() <= limits::CONTINUOUS_ACTION)) {
            return bad(format!("continuous action {a} outside ±{}", limits::CONTINUOUS_ACTION));
        }
        Ok(continuous.chunks(2).map(|c| policy::Choice::Continuous([c[0], c[1]])).collect())
    }
}

/// A `policy::Trajectory` on the wire.
pub fn trajectory_to_wire(t: &policy::Trajectory, obs_size: usize) -> Trajectory {
    let (discrete, continuous) = choices_to_wire(&t.choices);
    // Camera frames are grey levels: a byte each instead of four, exactly the same numbers.
    let bytes = t.obs.iter().map(|&v| u8::try_from(v as u32).ok().filter(|b| f32::from(*b).to_bits() == v.to_bits()));
    let obs_u8: Option<Vec<u8>> = bytes.collect();
    let (obs, obs_u8) = match obs_u8 {
        Some(b) if !b.is_empty() => (Vec::new(), b),
        _ => (t.obs.clone(), Vec::new()),
    };
    Trajectory {
        env: t.env,
        episode: t.episode,
        policy_version: t.policy_version,
        obs_size: obs_size as u32,
        obs,
        obs_u8,
        discrete_actions: discrete,
        continuous_actions: continuous,
        logp: t.logp.clone(),
        values: t.values.clone(),
        rewards: t.rewards.clone(),
        done: t.done,
        progress: t.progress,
        lap_complete: t.lap_complete,
        world: t.world.clone(),
        trace: trace_to_wire(&t.trace),
        track_len: t.track_len,
    }
}

/// What a trajectory's actions must be: indices below the count, or two numbers per step.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Actions {
    /// A discrete space of this many actions.
    Discrete(usize),
    /// A continuous space (the network's two unit outputs, sampled).
    Continuous,
}

impl Actions {
    /// The kind of a model's action space.
    pub fn of(space: &policy::ActionSpace) -> Actions {
        match space {
            policy::ActionSpace::Discrete(a) => Actions::Discrete(a.len()),
            policy::ActionSpace::Continuous { .. } => Actions::Continuous,
        }
    }
}

/// Bounds on the numbers a trajectory may carry: beyond them a message is refused, not trained on.
pub mod limits {
    /// |reward| per step: `reward validate`'s range.
    pub const REWARD: f32 = 1e5;
    /// |observation|, |value estimate| and |log-probability|.
    pub const VALUE: f32 = 1e7;
    /// |a| of a continuous action in the network's unit space (samples from the Gaussian may
    /// leave [-1, 1]; this far out they are nonsense).
    pub const CONTINUOUS_ACTION: f32 = 1e3;
    /// Progress (%) as DeepRacer's `compute_current_prog` gives it: a car that backs over its
    /// start line has a little below 0 (−1 % a hundredth of the track behind it), never
    /// below −100 %, never above 100 % (a millesimal rounding allowed).
    pub const PROGRESS: std::ops::RangeInclusive<f64> = -100.0..=100.001;
}

/// A wire trajectory back, checked for consistent lengths and finite numbers.
pub fn trajectory_from_wire(
    w: Trajectory,
    obs_size: usize,
    actions: Actions,
) -> Result<policy::Trajectory, DecodeError> {
    let mut w = w;
    let n = w.rewards.len();
    let bad = |m: String| Err(DecodeError::Invalid(m));
    if !w.obs_u8.is_empty() {
        if !w.obs.is_empty() {
            return bad("observations both as floats and as bytes".into());
        }
        w.obs = w.obs_u8.iter().map(|&b| f32::from(b)).collect();
    }
    if w.obs_size as usize != obs_size {
        return bad(format!("observation size {}, the job's model takes {obs_size}", w.obs_size));
    }
    if w.obs.len() != n * obs_size || w.logp.len() != n || w.values.len() != n {
        return bad(format!(
            "column lengths disagree ({} steps, {} obs values, {} logp, {} values)",
            n,
            w.obs.len(),
            w.logp.len(),
            w.values.len()
        ));
    }
    let choices = choices_from_wire(&w.discrete_actions, &w.continuous_actions, n, actions)?;
    let trace = trace_from_wire(w.trace, n)?;
    if !(w.track_len.is_finite() && (0.0..=1e5).contains(&w.track_len)) {
        return bad(format!("track length {} out of range", w.track_len));
    }
    if !(w.obs.iter().chain(&w.logp).chain(&w.values).chain(&w.rewards).all(|x| x.is_finite())
        && w.progress.is_finite())
    {
        return bad("non-finite numbers".into());
    }
    if let Some(r) = w.rewards.iter().find(|r| r.abs() > limits::REWARD) {
        return bad(format!("reward {r} outside ±{} (the range `reward validate` allows)", limits::REWARD));
    }
    if let Some(v) = w.values.iter().chain(&w.obs).find(|v| v.abs() > limits::VALUE) {
        return bad(format!("observation or value estimate {v} outside ±{}", limits::VALUE));
    }
    if let Some(l) = w.logp.iter().find(|l| l.abs() > limits::VALUE || (actions != Actions::Continuous && **l > 0.0)) {
        return bad(format!("log-probability {l} out of range"));
    }
    if !limits::PROGRESS.contains(&w.progress) {
        return bad(format!("progress {} outside [-100, 100]", w.progress));
    }
    if !keys::is_valid_name(&w.world) {
        return bad(format!("world name {:?} is not a valid name", w.world));
    }
    Ok(policy::Trajectory {
        world: w.world,
        env: w.env,
        episode: w.episode,
        policy_version: w.policy_version,
        obs: w.obs,
        choices,
        logp: w.logp,
        values: w.values,
        rewards: w.rewards,
        done: w.done,
        progress: w.progress,
        lap_complete: w.lap_complete,
        track_len: w.track_len,
        trace,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue 8: camera observations travel as bytes and come back exactly.
    #[test]
    fn camera_observations_travel_as_bytes_and_come_back_exactly() {
        let t = |obs: Vec<f32>| policy::Trajectory {
            world: "reinvent_wood".into(),
            obs,
            choices: vec![policy::Choice::Discrete(1); 2],
            logp: vec![-1.0; 2],
            values: vec![0.5; 2],
            rewards: vec![1.0; 2],
            done: true,
            ..Default::default()
        };
        let grey = t(vec![0.0, 17.0, 255.0, 128.0, 3.0, 254.0]);
        let w = trajectory_to_wire(&grey, 3);
        assert!(w.obs.is_empty() && w.obs_u8 == [0, 17, 255, 128, 3, 254], "{w:?}");
        assert_eq!(trajectory_from_wire(w.clone(), 3, Actions::Discrete(5)).unwrap().obs, grey.obs);
        // Anything else stays four bytes a value, bits and all.
        for other in [
            vec![0.0, 17.5, 255.0, 128.0, 3.0, 254.0],
            vec![0.0, 17.0, 256.0, 128.0, 3.0, 254.0],
            vec![0.0, 17.0, -1.0, 128.0, 3.0, 254.0],
            vec![-0.0, 17.0, 255.0, 128.0, 3.0, 254.0],
        ] {
            let w = trajectory_to_wire(&t(other.clone()), 3);
            assert!(w.obs_u8.is_empty(), "{other:?}");
            let back = trajectory_from_wire(w, 3, Actions::Discrete(5)).unwrap().obs;
            assert_eq!(
                back.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                other.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
            );
        }
        // Bytes that do not fit the steps, or both encodings at once, are refused.
        let mut short = w.clone();
        short.obs_u8.pop();
        assert!(trajectory_from_wire(short, 3, Actions::Discrete(5)).is_err());
        let mut both = w;
        both.obs = vec![1.0; 6];
        assert!(trajectory_from_wire(both, 3, Actions::Discrete(5)).is_err());
    }

    #[test]
    fn round_trip_and_refusals() {
        let t = policy::Trajectory {
            world: "reinvent_wood".into(),
            env: 2,
            episode: 9,
            policy_version: 4,
            obs: vec![0.5; 6],
            choices: vec![policy::Choice::Discrete(1), policy::Choice::Discrete(3)],
            logp: vec![-1.0, -2.0],
            values: vec![0.1, 0.2],
            rewards: vec![1.0, 0.5],
            done: true,
            progress: 42.0,
            lap_complete: false,
            ..Default::default()
        };
        let batch = ExperienceBatch {
            protocol_version: PROTOCOL_VERSION,
            job_id: "j".into(),
            agent_id: "a".into(),
            seq: 3,
            trajectories: vec![trajectory_to_wire(&t, 3)],
            env_steps: 2,
            seconds: 0.1,
            credit_version: 4,
            credit_round: 1,
        };
        let bytes = encode(&batch);
        let back: ExperienceBatch = decode(&bytes).unwrap();
        assert_eq!(trajectory_from_wire(back.trajectories[0].clone(), 3, D).unwrap(), t);
        // Garbage, truncation, another version, wrong sizes: errors, never panics.
        assert!(matches!(decode::<ExperienceBatch>(&[0xff, 0xff, 0xff]), Err(DecodeError::Malformed(_))));
        assert!(decode::<ExperienceBatch>(&bytes[..bytes.len() / 2]).is_err());
        let other = ExperienceBatch { protocol_version: 99, ..batch.clone() };
        assert_eq!(decode::<ExperienceBatch>(&encode(&other)).unwrap_err(), DecodeError::Version(99));
        assert!(matches!(decode::<ExperienceBatch>(&vec![0u8; MAX_MESSAGE_BYTES + 1]), Err(DecodeError::TooLarge(_))));
        assert!(matches!(trajectory_from_wire(batch.trajectories[0].clone(), 4, D), Err(DecodeError::Invalid(_))));
        let mut short = batch.trajectories[0].clone();
        short.logp.pop();
        assert!(matches!(trajectory_from_wire(short, 3, D), Err(DecodeError::Invalid(_))));
        let mut nan = batch.trajectories[0].clone();
        nan.rewards[0] = f32::NAN;
        assert!(matches!(trajectory_from_wire(nan, 3, D), Err(DecodeError::Invalid(_))));
    }

    const D: Actions = Actions::Discrete(4);

    /// Issue 10: a batch that decodes but does not fit the job (an action index of 99 in a space of
    /// 10 would kill the learner) is refused, one reason per row.
    #[test]
    fn trajectories_that_do_not_fit_the_job_are_refused() {
        let t = Trajectory {
            obs_size: 1,
            obs: vec![0.5, 0.5],
            discrete_actions: vec![1, 3],
            logp: vec![-1.0, -2.0],
            values: vec![0.1, 0.2],
            rewards: vec![1.0, 0.5],
            progress: 42.0,
            world: "reinvent_wood".into(),
            ..Default::default()
        };
        assert!(trajectory_from_wire(t.clone(), 1, D).is_ok());
        let cont = Trajectory { discrete_actions: vec![], continuous_actions: vec![0.5, -0.5, 2.0, 0.0], ..t.clone() };
        assert!(trajectory_from_wire(cont.clone(), 1, Actions::Continuous).is_ok());
        let rows: &[(&str, Trajectory, Actions)] = &[
            ("discrete action 99", Trajectory { discrete_actions: vec![1, 99], ..t.clone() }, Actions::Discrete(10)),
            ("discrete action 3", t.clone(), Actions::Discrete(3)),
            ("discrete actions for a continuous", t.clone(), Actions::Continuous),
            ("continuous actions for a discrete", cont.clone(), D),
            (
                "continuous action inf",
                Trajectory { continuous_actions: vec![0.5, f32::INFINITY, 0.0, 0.0], ..cont.clone() },
                Actions::Continuous,
            ),
            (
                "continuous action 5000",
                Trajectory { continuous_actions: vec![0.5, 5e3, 0.0, 0.0], ..cont.clone() },
                Actions::Continuous,
            ),
            ("reward 1000000", Trajectory { rewards: vec![1.0, 1e6], ..t.clone() }, D),
            ("reward -1000000", Trajectory { rewards: vec![-1e6, 1.0], ..t.clone() }, D),
            ("value estimate 100000000", Trajectory { values: vec![1e8, 1.0], ..t.clone() }, D),
            ("log-probability 0.5", Trajectory { logp: vec![0.5, -1.0], ..t.clone() }, D),
            ("progress 140", Trajectory { progress: 140.0, ..t.clone() }, D),
            ("progress -101", Trajectory { progress: -101.0, ..t.clone() }, D),
        ];
        // A car that backed over its start line: DeepRacer's progress is a little below 0.
        assert!(trajectory_from_wire(Trajectory { progress: -1.0, ..t.clone() }, 1, D).is_ok());
        for (why, w, actions) in rows {
            match trajectory_from_wire(w.clone(), 1, *actions) {
                Err(DecodeError::Invalid(m)) => assert!(m.contains(why.split(' ').next_back().unwrap()), "{why}: {m}"),
                other => panic!("{why}: {other:?}"),
            }
        }
    }

    #[test]
    fn keys_are_well_formed() {
        assert_eq!(keys::experience("job1", "a1"), "paddock/v1/job/job1/experience/a1");
        assert_eq!(keys::last(&keys::agent_alive("host-1.2")), "host-1.2");
        assert!(keys::is_valid_name("job-7_a.b") && !keys::is_valid_name("a/b") && !keys::is_valid_name("*"));
    }
}
