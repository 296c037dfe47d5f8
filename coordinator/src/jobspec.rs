//! Job spec files (`JOB.toml`): parsed with errors that name the field, every file they
//! point at read in, and turned into the [`Job`] the coordinator stores.
//!
//! ```toml
//! worlds = ["reinvent_carpet", "reinvent_concrete"]   # required
//! reversed = false                   # optional: drive every world the other way round
//! agents = 4                         # optional: the most sim agents it takes (default: all)
//! owner = "rita"                     # optional: who made it (waiting jobs take turns by owner)
//! reward = "reward_function.py"      # DeepRacer's file as it is, or "builtin:center_line"
//! model_metadata = "model_metadata.json"   # optional, DeepRacer's file
//! hyperparameters = "hyperparameters.json" # optional, DeepRacer's file
//! clone_from = "runs/first/model"    # optional: start from a model (path on the learner)
//! out = "runs/carpet-concrete"       # run folder on the learner's machine
//! [stop]
//! minutes = 10
//! target_progress = 95
//! [schedule]                         # optional
//! adaptive = true    # environments move to the weakest worlds (default: with 3 worlds or more)
//! floor = 0.5        # each world keeps at least this fraction of an even share
//! ```

use anyhow::{Context, Result, bail};
use learner::Hyperparameters;
use policy::ModelMetadata;
use protocol::Job;
use protocol::job::{JobStop, default_stop};
use serde::Deserialize;
use sim_agent::SimConfig;
use std::path::Path;

/// The file's fields.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct JobSpec {
    /// Optional name (the job id is derived from it).
    pub name: Option<String>,
    /// Worlds to train on.
    pub worlds: Vec<String>,
    /// Drive every world the other way round (DeepRacer's `is_reversed`; DRoA's other
    /// direction).
    #[serde(default)]
    pub reversed: bool,
    /// The most sim agents the job takes (default: every agent there is).
    pub agents: Option<u32>,
    /// Who made it (a console's user): waiting jobs take turns by owner.
    #[serde(default)]
    pub owner: String,
    /// Reward file or `builtin:NAME`.
    #[serde(default = "default_reward")]
    pub reward: String,
    /// `model_metadata.json`.
    pub model_metadata: Option<String>,
    /// `hyperparameters.json`.
    pub hyperparameters: Option<String>,
    /// A model folder to start from (on the learner's machine).
    pub clone_from: Option<String>,
    /// The run folder (on the learner's machine).
    pub out: Option<String>,
    /// Random seed.
    #[serde(default = "one")]
    pub seed: u64,
    /// Environments per sim agent.
    #[serde(default = "sixteen")]
    pub envs_per_agent: u32,
    /// Experience older than this many policy versions is dropped.
    #[serde(default = "four")]
    pub max_policy_lag: u64,
    /// Evaluation trials per checkpoint.
    #[serde(default = "three")]
    pub eval_trials: u32,
    /// Stop conditions.
    #[serde(default = "default_stop")]
    pub stop: JobStop,
    /// Simulator configuration (any key of config/default.toml).
    #[serde(default)]
    pub sim: Option<toml::Table>,
    /// How the coordinator spreads the environments over the worlds.
    #[serde(default)]
    pub schedule: ScheduleSpec,
}

/// `[schedule]`.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScheduleSpec {
    /// Move environments to the worlds the last evaluations found weakest (default: on for
    /// jobs of three worlds or more).
    pub adaptive: Option<bool>,
    /// The fraction of an even share each world keeps (default 0.5).
    pub floor: Option<f64>,
}

/// The floor of a world's share when `[schedule] floor` is not given.
pub const DEFAULT_FLOOR: f64 = 0.5;

fn default_reward() -> String {
    "builtin:center_line".into()
}
fn one() -> u64 {
    1
}
fn sixteen() -> u32 {
    16
}
fn four() -> u64 {
    4
}
fn three() -> u32 {
    3
}

/// The spec's optional `name` (used for the job id), if the file parses.
pub fn name_of(text: &str) -> Option<String> {
    toml::from_str::<JobSpec>(text).ok().and_then(|s| s.name)
}

/// Read a spec file and everything it names; `id` is the job id to give it.
pub fn load(path: &Path, id: &str) -> Result<Job> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    parse(&text, path.parent().unwrap_or(Path::new(".")), &path.display().to_string(), id)
}

/// Parse spec text; relative file names resolve against `base`.
pub fn parse(text: &str, base: &Path, origin: &str, id: &str) -> Result<Job> {
    let spec: JobSpec = toml::from_str(text).map_err(|e| anyhow::anyhow!("{origin}: {e}"))?;
    if spec.worlds.is_empty() {
        bail!("{origin}: field 'worlds' is empty; name at least one world");
    }
    for w in &spec.worlds {
        tracks::world(w).map_err(|e| anyhow::anyhow!("{origin}: field 'worlds': {e}"))?;
    }
    let read = |field: &str, name: &str| -> Result<String> {
        let p = base.join(name);
        std::fs::read_to_string(&p).map_err(|e| anyhow::anyhow!("{origin}: field '{field}': {}: {e}", p.display()))
    };
    let (reward_name, reward_source) = if spec.reward.starts_with("builtin:") {
        (spec.reward.clone(), spec.reward.clone())
    } else {
        let name = Path::new(&spec.reward).file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        (name, read("reward", &spec.reward)?)
    };
    let model_metadata_json = match &spec.model_metadata {
        Some(f) => {
            let t = read("model_metadata", f)?;
            ModelMetadata::parse(&t, &base.join(f).display().to_string())?;
            t
        }
        None => ModelMetadata::default_state_vector().to_json(),
    };
    let hyperparameters_json = match &spec.hyperparameters {
        Some(f) => {
            let t = read("hyperparameters", f)?;
            Hyperparameters::parse(&t, &base.join(f).display().to_string())?;
            t
        }
        None => Hyperparameters::default().to_json(),
    };
    let mut sim: SimConfig = match &spec.sim {
        Some(t) => SimConfig::deserialize(toml::Value::Table(t.clone()))
            .map_err(|e| anyhow::anyhow!("{origin}: field 'sim': {e}"))?,
        None => SimConfig::default(),
    };
    let meta = ModelMetadata::parse(&model_metadata_json, "model_metadata.json")?;
    sim.observation.set_sensors(&meta).map_err(|e| anyhow::anyhow!("{origin}: model_metadata: {e}"))?;
    let floor = spec.schedule.floor.unwrap_or(DEFAULT_FLOOR);
    if !(0.0..=1.0).contains(&floor) {
        bail!("{origin}: field 'schedule.floor' must be a fraction from 0 to 1, not {floor}");
    }
    if spec.stop.minutes <= 0.0 || !spec.stop.minutes.is_finite() {
        bail!("{origin}: field 'stop.minutes' must be a positive number of minutes");
    }
    if spec.owner.chars().count() > 64 || spec.owner.chars().any(char::is_control) {
        bail!("{origin}: field 'owner' must be a name of at most 64 characters");
    }
    if spec.agents == Some(0) {
        bail!("{origin}: field 'agents' must be at least 1 (leave it out for every agent there is)");
    }
    let direction = if spec.reversed { tracks::Direction::Reversed } else { tracks::Direction::Forward };
    let tracks = spec
        .worlds
        .iter()
        .map(|w| Ok(protocol::job::track_lines_to_wire(&sim_agent::track_lines(&tracks::world(w)?, direction))))
        .collect::<Result<Vec<_>>>()?;
    Ok(Job {
        protocol_version: protocol::PROTOCOL_VERSION,
        id: id.to_string(),
        tracks,
        reward_name,
        reward_source,
        model_metadata_json,
        hyperparameters_json,
        sim_config_toml: toml::to_string(&sim)?,
        out: spec.out.unwrap_or_else(|| format!("runs/{id}")),
        clone_from: spec.clone_from,
        seed: spec.seed,
        envs_per_agent: spec.envs_per_agent.max(1),
        max_policy_lag: spec.max_policy_lag,
        stop: Some(spec.stop),
        eval_trials: spec.eval_trials.max(1),
        obs_size: sim_agent::obs::obs_dim(&sim.observation) as u64,
        adaptive: spec.schedule.adaptive.unwrap_or(spec.worlds.len() >= 3),
        schedule_floor: floor,
        reversed: spec.reversed,
        agents: spec.agents.unwrap_or(0),
        owner: spec.owner,
        worlds: spec.worlds,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn errors_name_the_field() {
        let dir = std::env::temp_dir();
        for (text, want) in [
            ("worlds = []", "field 'worlds' is empty"),
            ("worlds = [\"no_such_world\"]", "no built-in world named 'no_such_world'"),
            ("worlds = [\"reinvent_wood\"]\nrewrd = \"x.py\"", "rewrd"),
            ("worlds = [\"reinvent_wood\"]\nreward = \"missing.py\"", "field 'reward'"),
            ("worlds = [\"reinvent_wood\"]\n[stop]\nminutes = -1", "stop.minutes"),
            ("worlds = [\"reinvent_wood\"]\n[stop]\nminute = 3", "minute"),
            ("worlds = [\"reinvent_wood\"]\n[schedule]\nfloor = 1.5", "field 'schedule.floor' must be a fraction"),
            ("worlds = [\"reinvent_wood\"]\n[schedule]\nadaptiv = true", "adaptiv"),
            ("worlds = [\"reinvent_wood\"]\n[sim]\ncontrol_hz = \"fast\"", "field 'sim'"),
            ("worlds = \"reinvent_wood\"", "worlds"),
            ("worlds = [\"reinvent_wood\"]\nagents = 0", "field 'agents' must be at least 1"),
            ("worlds = [\"reinvent_wood\"]\nreversed = \"yes\"", "reversed"),
        ] {
            let e = parse(text, &dir, "job.toml", "j").unwrap_err().to_string();
            assert!(e.contains("job.toml") && e.contains(want), "{text}: {e}");
        }
        let ok =
            parse("worlds = [\"reinvent_carpet\", \"reinvent_concrete\"]\n[stop]\nminutes = 2", &dir, "job.toml", "j")
                .unwrap();
        assert_eq!(ok.worlds.len(), 2);
        assert_eq!(ok.reward_source, "builtin:center_line");
        assert_eq!(ok.out, "runs/j");
    }

    /// Issue 51: `reversed` drives every world the other way round, its lines (for the
    /// learner's logs) reversed too; `agents` caps the agents the job takes.
    #[test]
    fn reversed_and_agents_reach_the_job() {
        let dir = std::env::temp_dir();
        let plain = parse("worlds = [\"reinvent_base\"]", &dir, "job.toml", "j").unwrap();
        assert_eq!((plain.reversed, plain.agents), (false, 0));
        let other = parse("worlds = [\"reinvent_base\"]\nreversed = true\nagents = 3", &dir, "job.toml", "j").unwrap();
        assert_eq!((other.reversed, other.agents), (true, 3));
        let (a, b) = (&plain.tracks[0].centre, &other.tracks[0].centre);
        assert_eq!(a.len(), b.len());
        assert_ne!(a[2..4], b[2..4], "the reversed centre line runs the other way");
    }

    /// Issue 34: the adaptive schedule is on for three worlds or more unless turned off.
    #[test]
    fn the_adaptive_schedule_is_on_for_three_worlds_or_more_unless_turned_off() {
        let dir = std::env::temp_dir();
        let three = "worlds = [\"reinvent_base\", \"reinvent_wood\", \"reinvent_carpet\"]\n";
        let two = "worlds = [\"reinvent_base\", \"reinvent_wood\"]\n";
        for (text, adaptive, floor) in [
            (three.to_string(), true, DEFAULT_FLOOR),
            (two.to_string(), false, DEFAULT_FLOOR),
            (format!("{three}[schedule]\nadaptive = false\n"), false, DEFAULT_FLOOR),
            (format!("{two}[schedule]\nadaptive = true\nfloor = 0.2\n"), true, 0.2),
        ] {
            let doc = parse(&text, &dir, "job.toml", "j").unwrap();
            assert_eq!((doc.adaptive, doc.schedule_floor), (adaptive, floor), "{text}");
        }
    }

    /// Issue 29: every stop key is read into the job.
    #[test]
    fn every_stop_key_is_read_into_the_job() {
        let dir = std::env::temp_dir();
        let text = "worlds = [\"reinvent_base\"]\n[stop]\nminutes = 0.1\nmax_episodes = 60\nenv_steps_budget = 15000\n\
                    target_progress = 25\ntarget_reward = 15\nwindow = 7\ntarget_laps = 3\ntarget_evals = 2\n\
                    plateau_evals = 4\nstop_on_collapse = true\nverify_trials = 5\n";
        let doc = parse(text, &dir, "job.toml", "j").unwrap();
        let want = JobStop {
            minutes: 0.1,
            max_episodes: 60,
            target_progress: Some(25.0),
            target_reward: Some(15.0),
            window: 7,
            env_steps_budget: Some(15000),
            target_laps: Some(3),
            target_evals: 2,
            plateau_evals: 4,
            stop_on_collapse: true,
            verify_trials: 5,
        };
        assert_eq!(doc.stop, Some(want));
    }
}
