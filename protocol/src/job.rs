//! The job document: a job spec with every file it names read in, as the coordinator stores
//! it (JSON in its database) and serves it once per job to learners and agents (the `Job`
//! protobuf message on `job/<id>/spec`). Everything the learner needs is here, so that it
//! needs no simulator.

use serde::{Deserialize, Serialize};

/// When a job stops (whichever comes first).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct StopSpec {
    /// Wall-clock minutes from the job's start.
    pub minutes: f64,
    /// Episodes trained on.
    pub max_episodes: u64,
    /// Mean progress (%) over the last `window` episodes.
    pub target_progress: Option<f64>,
    /// Mean episode reward over the last `window` episodes.
    pub target_reward: Option<f64>,
    /// Episodes in the window.
    pub window: u64,
    /// Compute budget: environment steps across all agents.
    pub env_steps_budget: Option<u64>,
    /// Stop once evaluations complete this many laps (of `eval_trials`, on every world)...
    pub target_laps: Option<u32>,
    /// ...in this many consecutive evaluations.
    pub target_evals: u32,
    /// Stop at a plateau: this many evaluations in a row without improving the best mean
    /// progress by a point (0: report plateaus, do not stop).
    pub plateau_evals: u32,
    /// Stop when evaluation progress collapses after a peak (the best model is kept).
    pub stop_on_collapse: bool,
}

impl Default for StopSpec {
    fn default() -> Self {
        StopSpec {
            minutes: 10.0,
            max_episodes: 1_000_000,
            target_progress: None,
            target_reward: None,
            window: 20,
            env_steps_budget: None,
            target_laps: None,
            target_evals: 1,
            plateau_evals: 0,
            stop_on_collapse: false,
        }
    }
}

/// A job with its files inlined.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JobDoc {
    /// The job's id (a key-expression-safe name).
    pub id: String,
    /// Worlds to train on.
    pub worlds: Vec<String>,
    /// The reward's file name (or `builtin:NAME`).
    pub reward_name: String,
    /// The reward's Python source (or `builtin:NAME`).
    pub reward_source: String,
    /// `model_metadata.json` text.
    pub model_metadata_json: String,
    /// `hyperparameters.json` text.
    pub hyperparameters_json: String,
    /// The simulator configuration (TOML).
    pub sim_config_toml: String,
    /// The run folder, on the learner's machine.
    pub out: String,
    /// A model folder to start from, on the learner's machine.
    pub clone_from: Option<String>,
    /// Random seed.
    pub seed: u64,
    /// Environments per sim agent.
    pub envs_per_agent: u32,
    /// Experience older than this many policy versions is dropped.
    pub max_policy_lag: u64,
    /// Stop conditions.
    pub stop: StopSpec,
    /// Evaluation trials per checkpoint (per world).
    pub eval_trials: u32,
    /// The model's observation length (from the model's sensors and the simulator
    /// configuration), so that the learner needs no simulator to know it.
    pub obs_size: u64,
    /// The simulator's observation settings (JSON), for the model's manifest.
    pub observation_json: String,
    /// The worlds' tracks as lines, for the learner's logs (MCAP) and reports.
    #[serde(default)]
    pub tracks: Vec<policy::TrackLines>,
}

/// A job on the wire.
pub fn to_wire(d: &JobDoc) -> crate::Job {
    let s = &d.stop;
    crate::Job {
        protocol_version: crate::PROTOCOL_VERSION,
        id: d.id.clone(),
        worlds: d.worlds.clone(),
        reward_name: d.reward_name.clone(),
        reward_source: d.reward_source.clone(),
        model_metadata_json: d.model_metadata_json.clone(),
        hyperparameters_json: d.hyperparameters_json.clone(),
        sim_config_toml: d.sim_config_toml.clone(),
        out: d.out.clone(),
        clone_from: d.clone_from.clone(),
        seed: d.seed,
        envs_per_agent: d.envs_per_agent,
        max_policy_lag: d.max_policy_lag,
        stop: Some(crate::JobStop {
            minutes: s.minutes,
            max_episodes: s.max_episodes,
            target_progress: s.target_progress,
            target_reward: s.target_reward,
            window: s.window,
            env_steps_budget: s.env_steps_budget,
            target_laps: s.target_laps,
            target_evals: s.target_evals,
            plateau_evals: s.plateau_evals,
            stop_on_collapse: s.stop_on_collapse,
        }),
        eval_trials: d.eval_trials,
        obs_size: d.obs_size,
        observation_json: d.observation_json.clone(),
        tracks: d
            .tracks
            .iter()
            .map(|t| {
                let flat = |l: &[[f64; 2]]| l.iter().flatten().copied().collect::<Vec<f64>>();
                crate::TrackLines {
                    world: t.world.clone(),
                    length: t.length,
                    centre: flat(&t.centre),
                    inner: flat(&t.inner),
                    outer: flat(&t.outer),
                }
            })
            .collect(),
    }
}

/// A job's track lines back: one per job world at most, points in pairs, finite, within
/// ±10 km, at most 100,000 per line.
fn tracks_from_wire(
    id: &str,
    worlds: &[String],
    w: Vec<crate::TrackLines>,
) -> Result<Vec<policy::TrackLines>, crate::DecodeError> {
    let mut out = Vec::with_capacity(w.len());
    for t in w {
        let lines = [&t.centre, &t.inner, &t.outer];
        let fits = worlds.contains(&t.world)
            && !out.iter().any(|o: &policy::TrackLines| o.world == t.world)
            && t.length.is_finite()
            && t.length > 0.0
            && lines
                .iter()
                .all(|l| l.len() % 2 == 0 && l.len() <= 200_000 && l.iter().all(|v| v.is_finite() && v.abs() <= 1e4));
        if !fits {
            return Err(crate::DecodeError::Invalid(format!(
                "job {id}: the lines of track {:?} (a job world, once, finite points in pairs)",
                t.world
            )));
        }
        let pairs = |l: &[f64]| l.chunks(2).map(|c| [c[0], c[1]]).collect::<Vec<[f64; 2]>>();
        out.push(policy::TrackLines {
            world: t.world,
            length: t.length,
            centre: pairs(&t.centre),
            inner: pairs(&t.inner),
            outer: pairs(&t.outer),
        });
    }
    Ok(out)
}

/// A job back: the one asked for (`id`), with a name, worlds and sizes that make sense.
pub fn from_wire(j: crate::Job, id: &str) -> Result<JobDoc, crate::DecodeError> {
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
    let Some(s) = j.stop else { return bad(format!("job {id} has no stop conditions")) };
    if !(s.minutes.is_finite() && s.minutes > 0.0) {
        return bad(format!("job {id}: stop after {} minutes", s.minutes));
    }
    let tracks = tracks_from_wire(&j.id, &j.worlds, j.tracks)?;
    Ok(JobDoc {
        tracks,
        id: j.id,
        worlds: j.worlds,
        reward_name: j.reward_name,
        reward_source: j.reward_source,
        model_metadata_json: j.model_metadata_json,
        hyperparameters_json: j.hyperparameters_json,
        sim_config_toml: j.sim_config_toml,
        out: j.out,
        clone_from: j.clone_from,
        seed: j.seed,
        envs_per_agent: j.envs_per_agent,
        max_policy_lag: j.max_policy_lag,
        stop: StopSpec {
            minutes: s.minutes,
            max_episodes: s.max_episodes,
            target_progress: s.target_progress,
            target_reward: s.target_reward,
            window: s.window,
            env_steps_budget: s.env_steps_budget,
            target_laps: s.target_laps,
            target_evals: s.target_evals,
            plateau_evals: s.plateau_evals,
            stop_on_collapse: s.stop_on_collapse,
        },
        eval_trials: j.eval_trials,
        obs_size: j.obs_size,
        observation_json: j.observation_json,
    })
}

/// Fetch job `id` from the coordinator (once per job: callers keep it). `None` when no
/// coordinator answered in time or the answer did not fit (counted in `drops`).
pub fn fetch(
    session: &zenoh::Session,
    id: &str,
    timeout: std::time::Duration,
    drops: &crate::net::DropCounters,
) -> Option<JobDoc> {
    let replies = crate::net::query::<crate::Job>(session, &crate::keys::job_spec(id), None, timeout, drops).ok()?;
    let mut found = None;
    for j in replies {
        match from_wire(j, id) {
            Ok(d) => found = Some(d),
            Err(e) => {
                drops.refuse(&format!("the document of job {id}"), &e);
            }
        }
    }
    found
}

#[cfg(test)]
mod tests {
    use super::*;

    fn doc() -> JobDoc {
        JobDoc {
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
            stop: StopSpec { target_laps: Some(3), target_progress: Some(80.0), ..StopSpec::default() },
            eval_trials: 3,
            obs_size: 27,
            observation_json: "{}".into(),
            tracks: vec![policy::TrackLines {
                world: "reinvent_wood".into(),
                length: 17.7,
                centre: vec![[0.0, 0.0], [1.0, 0.5]],
                inner: vec![[0.0, 0.5]],
                outer: vec![[0.0, -0.5]],
            }],
        }
    }

    #[test]
    fn issue_8_the_job_travels_as_protobuf_and_comes_back_whole() {
        let d = doc();
        let bytes = crate::encode(&to_wire(&d));
        assert_eq!(from_wire(crate::decode(&bytes).unwrap(), "job1").unwrap(), d);
        // Another job than asked for, no worlds, nonsense sizes: refused.
        assert!(from_wire(to_wire(&d), "job2").is_err());
        for f in [
            |j: &mut crate::Job| j.worlds.clear(),
            |j: &mut crate::Job| j.obs_size = 0,
            |j: &mut crate::Job| j.stop = None,
            |j: &mut crate::Job| j.stop.as_mut().unwrap().minutes = f64::NAN,
            |j: &mut crate::Job| j.worlds.push("../etc".into()),
            |j: &mut crate::Job| j.tracks[0].world = "reinvent_base".into(),
            |j: &mut crate::Job| j.tracks[0].centre.push(1.0),
            |j: &mut crate::Job| j.tracks[0].inner[0] = f64::NAN,
        ] {
            let mut j = to_wire(&d);
            f(&mut j);
            assert!(from_wire(j, "job1").is_err());
        }
    }
}
