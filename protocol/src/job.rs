//! The job: a job spec with every file it names read in. One type, the [`Job`] message: `job
//! start` sends it, the coordinator keeps it in its [`JobRecord`]s (protobuf in its
//! database) and serves it once per job to learners and agents on `job/<id>/spec`.
//! Everything the learner needs is here, so that it needs no simulator.
//!
//! Messages that cross the network are checked against the job asked for ([`check`]); a job
//! spec's `[stop]` table deserializes straight into [`JobStop`] with [`default_stop`]'s
//! values for the keys it leaves out.

pub use crate::{AgentWork, Job, JobRecord, JobState, JobStop};
use std::sync::LazyLock;

/// Evaluations in a row that must lap everywhere before a lap target verifies a checkpoint,
/// when the user names none: the second version that laps everywhere laps tracks it never
/// saw far more often than the first (docs/benchmarks.md, "Twenty trials a world").
pub const TARGET_EVALS: u32 = 2;

/// The stop conditions a job has when its spec names none: ten minutes, or a million
/// episodes, whichever comes first.
pub fn default_stop() -> JobStop {
    JobStop {
        minutes: 10.0,
        max_episodes: 1_000_000,
        target_progress: None,
        target_reward: None,
        window: 20,
        env_steps_budget: None,
        target_laps: None,
        target_evals: TARGET_EVALS,
        plateau_evals: 0,
        stop_on_collapse: false,
        verify_trials: 10,
    }
}

impl Job {
    /// The job's stop conditions ([`default_stop`] for a job that carries none; [`check`]
    /// refuses such a job from the network).
    pub fn stop(&self) -> JobStop {
        self.stop.unwrap_or_else(default_stop)
    }

    /// The worlds' track lines, as the learner's logs take them.
    pub fn track_lines(&self) -> Vec<policy::TrackLines> {
        let pairs = |l: &[f64]| l.chunks_exact(2).map(|c| [c[0], c[1]]).collect::<Vec<[f64; 2]>>();
        self.tracks
            .iter()
            .map(|t| policy::TrackLines {
                world: t.world.clone(),
                length: t.length,
                centre: pairs(&t.centre),
                inner: pairs(&t.inner),
                outer: pairs(&t.outer),
            })
            .collect()
    }
}

/// A track's lines as the job carries them (x-y pairs, flattened).
pub fn track_lines_to_wire(t: &policy::TrackLines) -> crate::TrackLines {
    let flat = |l: &[[f64; 2]]| l.iter().flatten().copied().collect::<Vec<f64>>();
    crate::TrackLines {
        world: t.world.clone(),
        length: t.length,
        centre: flat(&t.centre),
        inner: flat(&t.inner),
        outer: flat(&t.outer),
    }
}

/// A job from the network: the one asked for (`id`), with a name, worlds, sizes, stop
/// conditions and track lines that make sense (one per job world at most, points in pairs,
/// finite, within ±10 km, at most 100,000 per line).
pub fn check(j: &Job, id: &str) -> Result<(), crate::DecodeError> {
    let bad = |m: String| Err(crate::DecodeError::Invalid(m));
    if j.id != id || !crate::keys::is_valid_name(&j.id) {
        return bad(format!("job {:?} where {id:?} was asked for", j.id));
    }
    if j.worlds.is_empty() || j.worlds.len() > 64 || j.worlds.iter().any(|w| !crate::keys::is_valid_name(w)) {
        return bad(format!("job {id}: worlds {:?}", j.worlds));
    }
    if j.obs_size == 0 || j.obs_size > 1 << 24 || j.envs_per_agent > 4096 {
        return bad(format!(
            "job {id}: observation size {} or {} environments per agent",
            j.obs_size, j.envs_per_agent
        ));
    }
    let Some(s) = &j.stop else { return bad(format!("job {id} has no stop conditions")) };
    if !(s.minutes.is_finite() && s.minutes > 0.0) {
        return bad(format!("job {id}: stop after {} minutes", s.minutes));
    }
    if u64::from(s.verify_trials) > crate::exchange::SANITY_LIMIT {
        return bad(format!("job {id}: {} verification trials per world", s.verify_trials));
    }
    for (i, t) in j.tracks.iter().enumerate() {
        let lines = [&t.centre, &t.inner, &t.outer];
        let fits = j.worlds.contains(&t.world)
            && !j.tracks[..i].iter().any(|o| o.world == t.world)
            && t.length.is_finite()
            && t.length > 0.0
            && lines
                .iter()
                .all(|l| l.len() % 2 == 0 && l.len() <= 200_000 && l.iter().all(|v| v.is_finite() && v.abs() <= 1e4));
        if !fits {
            return bad(format!(
                "job {id}: the lines of track {:?} (a job world, once, finite points in pairs)",
                t.world
            ));
        }
    }
    Ok(())
}

/// Fetch job `id` from the coordinator (once per job: callers keep it). `None` when no
/// coordinator answered in time or the answer did not fit (counted in `drops`).
pub fn fetch(
    session: &zenoh::Session,
    id: &str,
    timeout: std::time::Duration,
    drops: &crate::net::DropCounters,
) -> Option<Job> {
    let replies = crate::net::query::<Job>(session, &crate::keys::job_spec(id), None, timeout, drops).ok()?;
    let mut found = None;
    for j in replies {
        match check(&j, id) {
            Ok(()) => found = Some(j),
            Err(e) => {
                drops.refuse(&format!("the document of job {id}"), &e);
            }
        }
    }
    found
}

/// A job state as JSON shows it: `running`, `stopping`, `finished`, `failed`.
pub fn state_name<S: serde::Serializer>(state: &i32, s: S) -> Result<S::Ok, S::Error> {
    s.serialize_str(JobState::try_from(*state).unwrap_or(JobState::Unspecified).name())
}

impl JobState {
    /// The state's name in text and JSON.
    pub fn name(self) -> &'static str {
        match self {
            JobState::Unspecified => "unknown",
            JobState::Running => "running",
            JobState::Stopping => "stopping",
            JobState::Finished => "finished",
            JobState::Failed => "failed",
        }
    }

    /// Running, or stopping (its final evaluation runs on the agents).
    pub fn is_active(self) -> bool {
        matches!(self, JobState::Running | JobState::Stopping)
    }
}

/// Seconds since the Unix epoch.
pub fn now_unix() -> f64 {
    use std::time::{SystemTime, UNIX_EPOCH};
    SystemTime::now().duration_since(UNIX_EPOCH).map(|d| d.as_secs_f64()).unwrap_or(0.0)
}

impl JobRecord {
    /// A job starting now: running, nothing assigned yet.
    pub fn start(job: Job) -> JobRecord {
        JobRecord { job: Some(job), state: JobState::Running as i32, started: now_unix(), ..Default::default() }
    }

    /// The job (a record always has one: [`decode_record`] refuses one without).
    pub fn job(&self) -> &Job {
        static NONE: LazyLock<Job> = LazyLock::new(Job::default);
        self.job.as_ref().unwrap_or(&NONE)
    }

    /// The job's id.
    pub fn id(&self) -> &str {
        &self.job().id
    }

    /// Log an event (and trace it); the log keeps its last 1,500 to 2,000 lines.
    pub fn event(&mut self, line: String) {
        tracing::info!(job = %self.id(), "{line}");
        let t = now_unix() - self.started;
        self.log.push(format!("[{t:>8.1}s] {line}"));
        if self.log.len() > 2000 {
            self.log.drain(..500);
        }
    }
}

/// A record back from the coordinator's database: it decodes, holds a job of this protocol
/// version and a known state.
pub fn decode_record(bytes: &[u8]) -> Result<JobRecord, crate::DecodeError> {
    use prost::Message;
    let r = JobRecord::decode(bytes).map_err(|e| crate::DecodeError::Malformed(e.to_string()))?;
    match &r.job {
        None => Err(crate::DecodeError::Invalid("a job record without its job".into())),
        Some(j) if j.protocol_version != crate::PROTOCOL_VERSION => {
            Err(crate::DecodeError::Version(j.protocol_version))
        }
        Some(_) if matches!(JobState::try_from(r.state), Err(_) | Ok(JobState::Unspecified)) => {
            Err(crate::DecodeError::Invalid(format!("job state {}", r.state)))
        }
        Some(_) => Ok(r),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn job() -> Job {
        Job {
            protocol_version: crate::PROTOCOL_VERSION,
            id: "job1".into(),
            worlds: vec!["reinvent_wood".into()],
            reward_name: "reward.py".into(),
            reward_source: "def reward_function(params):\n    return 1.0\n".into(),
            model_metadata_json: "{}".into(),
            hyperparameters_json: "{}".into(),
            sim_config_toml: "".into(),
            out: "run".into(),
            clone_from: Some("old/model".into()),
            seed: 3,
            envs_per_agent: 8,
            max_policy_lag: 2,
            stop: Some(JobStop { target_laps: Some(3), target_progress: Some(80.0), ..default_stop() }),
            eval_trials: 3,
            obs_size: 27,
            tracks: vec![track_lines_to_wire(&policy::TrackLines {
                world: "reinvent_wood".into(),
                length: 17.7,
                centre: vec![[0.0, 0.0], [1.0, 0.5]],
                inner: vec![[0.0, 0.5]],
                outer: vec![[0.0, -0.5]],
            })],
            adaptive: true,
            schedule_floor: 0.5,
            reversed: true,
            agents: 2,
            owner: "rita".into(),
        }
    }

    /// Issue 8: the job travels as protobuf and comes back whole.
    #[test]
    fn the_job_travels_as_protobuf_and_comes_back_whole() {
        let j = job();
        let back: Job = crate::decode(&crate::encode(&j)).unwrap();
        assert_eq!(back, j);
        check(&back, "job1").unwrap();
        assert_eq!(back.track_lines()[0].centre, vec![[0.0, 0.0], [1.0, 0.5]]);
        // Another job than asked for, no worlds, nonsense sizes: refused.
        assert!(check(&j, "job2").is_err());
        for f in [
            |j: &mut Job| j.worlds.clear(),
            |j: &mut Job| j.obs_size = 0,
            |j: &mut Job| j.stop = None,
            |j: &mut Job| j.stop.as_mut().unwrap().minutes = f64::NAN,
            |j: &mut Job| j.stop.as_mut().unwrap().verify_trials = u32::MAX,
            |j: &mut Job| j.worlds.push("../etc".into()),
            |j: &mut Job| j.tracks[0].world = "reinvent_base".into(),
            |j: &mut Job| j.tracks.push(j.tracks[0].clone()),
            |j: &mut Job| j.tracks[0].centre.push(1.0),
            |j: &mut Job| j.tracks[0].inner[0] = f64::NAN,
        ] {
            let mut bad = job();
            f(&mut bad);
            assert!(check(&bad, "job1").is_err(), "{bad:?}");
        }
    }

    /// Issue 29: a job record is one protobuf message and its JSON names the state.
    #[test]
    fn a_job_record_is_one_protobuf_message_and_its_json_names_the_state() {
        use prost::Message;
        let mut r = JobRecord::start(job());
        r.assignments.insert("a1".into(), AgentWork { worlds: vec!["reinvent_wood".into()], offset: 0, generation: 3 });
        r.event("started".into());
        assert_eq!(decode_record(&r.encode_to_vec()).unwrap(), r);
        let v = serde_json::to_value(&r).unwrap();
        assert_eq!(v["state"], "running");
        assert_eq!(v["job"]["stop"]["target_laps"], 3);
        assert_eq!(v["assignments"]["a1"]["generation"], 3);
        // A record without its job, of another version or in no known state: refused.
        for f in [
            |r: &mut JobRecord| r.job = None,
            |r: &mut JobRecord| r.job.as_mut().unwrap().protocol_version = 1,
            |r: &mut JobRecord| r.state = 0,
            |r: &mut JobRecord| r.state = 9,
        ] {
            let mut bad = r.clone();
            f(&mut bad);
            assert!(decode_record(&bad.encode_to_vec()).is_err(), "{bad:?}");
        }
        assert!(decode_record(b"\xff\xff").is_err());
    }

    /// Issue 29: a stop table is the stop message.
    #[test]
    fn a_stop_table_is_the_stop_message() {
        // Keys left out take the defaults; unknown keys are refused by name.
        let s: JobStop = serde_json::from_str(r#"{"max_episodes": 60, "target_laps": 3}"#).unwrap();
        assert_eq!(s, JobStop { max_episodes: 60, target_laps: Some(3), ..default_stop() });
        let e = serde_json::from_str::<JobStop>(r#"{"minute": 3}"#).unwrap_err().to_string();
        assert!(e.contains("minute"), "{e}");
        assert_eq!(Job::default().stop(), default_stop());
    }
}
