//! A new model from the API's JSON (`POST /api/v1/models`): every field checked, every
//! problem listed with its field (not just the first), the reward file validated as
//! `coordinator reward validate` validates it, and the job spec made by the CLI's own parser
//! (`coordinator::jobspec`) from the files as stored.

use crate::store::{ModelRecord, NewFiles, description_problem, name_problem};
use policy::ModelMetadata;
use serde_json::Value;
use sim_agent::reward_check::{self, RewardInput, Severity};
use sim_agent::validate::Sampling;
use std::time::Duration;

/// One problem with a request: the field (a JSON path such as `tracks[1]`), what was
/// expected, and for a reward file the line.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct FieldError {
    /// The field.
    pub field: String,
    /// What is wrong and what was expected.
    pub message: String,
    /// The reward file's line, when the problem is on one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub line: Option<usize>,
}

fn problem(field: &str, message: impl Into<String>) -> FieldError {
    FieldError { field: field.into(), message: message.into(), line: None }
}

/// A reward the console was given: `builtin:NAME`, or a Python file's text (which tracebacks
/// call `reward_function.py`, its name in the model's folder).
pub fn reward_input(reward: &str) -> RewardInput<'_> {
    if reward.starts_with("builtin:") {
        RewardInput::Builtin(reward)
    } else {
        RewardInput::Source { name: "reward_function.py", text: reward }
    }
}

/// `training_algorithm` as `model_metadata.json` writes it.
pub fn algorithm_name(a: policy::TrainingAlgorithm) -> &'static str {
    match a {
        policy::TrainingAlgorithm::ClippedPpo => "clipped_ppo",
        policy::TrainingAlgorithm::Sac => "sac",
    }
}

/// The most agents a model may ask for (the roster's default agent slots).
pub const MAX_AGENTS: u64 = 64;

/// DeepRacer's limit on a reward file (its editor's and API's).
pub const MAX_REWARD_CHARS: usize = 140_000;

/// The fields `POST /api/v1/models` takes.
pub const FIELDS: [&str; 11] = [
    "name",
    "description",
    "tracks",
    "reversed",
    "agents",
    "reward_function",
    "model_metadata",
    "hyperparameters",
    "stop",
    "race",
    "clone_from",
];

/// The stop when the request names none: the verified model (3 of 3 laps in two evaluations
/// in a row, then 10 trials a world without a failure), or 10 minutes, DeepRacer's shortest run.
pub fn default_stop() -> toml::Table {
    let mut t = toml::Table::new();
    t.insert("minutes".into(), toml::Value::Float(10.0));
    t.insert("target_laps".into(), toml::Value::Integer(3));
    t.insert("target_evals".into(), toml::Value::Integer(protocol::job::TARGET_EVALS.into()));
    t.insert("verify_trials".into(), toml::Value::Integer(10));
    t
}

/// A request that passed every check: the files to store and what the job spec adds.
pub struct Checked {
    /// The model's files and record.
    pub files: NewFiles,
    /// The simulator's `race` table, when the request set one.
    pub race: Option<toml::Table>,
    /// The model folder to start from (a clone's).
    pub clone_from: Option<std::path::PathBuf>,
}

/// What a clone starts from: the model's metadata and its model folder, or why it cannot.
pub type CloneSource<'a> = &'a dyn Fn(&str) -> Result<(ModelMetadata, std::path::PathBuf), String>;

/// Check a request, running the reward file on the first track (blocking: CPython).
pub fn check(
    body: &Value,
    now: f64,
    job_id: impl FnOnce(&str) -> String,
    clone_source: CloneSource<'_>,
) -> Result<Checked, Vec<FieldError>> {
    let mut errors = Vec::new();
    let Value::Object(map) = body else {
        return Err(vec![problem("", "expected a JSON object with the fields name, tracks and reward_function")]);
    };
    for key in map.keys().filter(|k| !FIELDS.contains(&k.as_str())) {
        errors.push(problem(key, format!("unknown field; expected one of {}", FIELDS.join(", "))));
    }
    let string = |field: &str, errors: &mut Vec<FieldError>| -> Option<String> {
        match map.get(field) {
            None | Some(Value::Null) => None,
            Some(Value::String(s)) => Some(s.clone()),
            Some(other) => {
                errors.push(problem(field, format!("expected a string, not {}", kind(other))));
                None
            }
        }
    };
    let name = string("name", &mut errors).unwrap_or_default();
    if let Some(p) = name_problem(&name) {
        errors.push(problem("name", p));
    }
    let description = string("description", &mut errors).unwrap_or_default();
    if let Some(p) = description_problem(&description) {
        errors.push(problem("description", p));
    }
    let mut worlds = Vec::new();
    match map.get("tracks") {
        Some(Value::Array(a)) if !a.is_empty() => {
            for (i, t) in a.iter().enumerate() {
                let field = format!("tracks[{i}]");
                match t.as_str().map(tracks::world) {
                    Some(Ok(w)) => worlds.push(w),
                    Some(Err(e)) => errors.push(problem(&field, e.to_string())),
                    None => errors.push(problem(&field, format!("expected a track's name, not {}", kind(t)))),
                }
            }
        }
        Some(Value::Array(_)) => errors.push(problem("tracks", "name at least one track")),
        None | Some(Value::Null) => {
            errors.push(problem("tracks", "required: a list of track names (GET /api/v1/tracks)"))
        }
        Some(other) => errors.push(problem("tracks", format!("expected a list of track names, not {}", kind(other)))),
    }
    let reversed = match map.get("reversed") {
        None | Some(Value::Null) => false,
        Some(Value::Bool(b)) => *b,
        Some(other) => {
            errors.push(problem("reversed", format!("expected true or false, not {}", kind(other))));
            false
        }
    };
    let agents = match map.get("agents") {
        None | Some(Value::Null) => None,
        Some(v) => match v.as_u64() {
            Some(n @ 1..=MAX_AGENTS) => Some(n as u32),
            _ => {
                errors.push(problem(
                    "agents",
                    format!("expected a whole number from 1 to {MAX_AGENTS}, or null for every agent"),
                ));
                None
            }
        },
    };
    let file = |field: &str, errors: &mut Vec<FieldError>| -> Option<String> {
        match map.get(field) {
            None | Some(Value::Null) => None,
            Some(v @ Value::Object(_)) => Some(serde_json::to_string_pretty(v).expect("JSON serialises")),
            Some(other) => {
                errors
                    .push(problem(field, format!("expected a JSON object (the file's content), not {}", kind(other))));
                None
            }
        }
    };
    let metadata_text = file("model_metadata", &mut errors);
    let metadata = match &metadata_text {
        Some(t) => ModelMetadata::parse(t, "model_metadata")
            .map_err(|e| errors.push(problem("model_metadata", e.to_string())))
            .ok(),
        None => ModelMetadata::for_sensor("camera"),
    };
    let hyper_text = file("hyperparameters", &mut errors);
    if let Some(t) = &hyper_text
        && let Err(e) = learner::Hyperparameters::parse(t, "hyperparameters")
    {
        errors.push(problem("hyperparameters", e.to_string()));
    }
    let table = |field: &str, errors: &mut Vec<FieldError>| -> Option<toml::Table> {
        match map.get(field) {
            None | Some(Value::Null) => None,
            Some(v @ Value::Object(_)) => match toml::Value::try_from(v) {
                Ok(toml::Value::Table(t)) => Some(t),
                Ok(_) => None,
                Err(e) => {
                    errors.push(problem(field, format!("not a table of settings: {e}")));
                    None
                }
            },
            Some(other) => {
                errors.push(problem(field, format!("expected a JSON object, not {}", kind(other))));
                None
            }
        }
    };
    let stop = table("stop", &mut errors).unwrap_or_else(default_stop);
    {
        use serde::Deserialize;
        match protocol::job::JobStop::deserialize(toml::Value::Table(stop.clone())) {
            Ok(s) if !(s.minutes > 0.0 && s.minutes.is_finite()) => errors
                .push(problem("stop", format!("'minutes' must be a positive number of minutes, not {}", s.minutes))),
            Ok(_) => {}
            Err(e) => errors.push(problem("stop", e.to_string().trim().to_string())),
        }
    }
    let clone_of = string("clone_from", &mut errors);
    let mut clone_from = None;
    if let Some(from) = &clone_of {
        match clone_source(from) {
            Ok((theirs, dir)) => {
                if let Some(ours) = &metadata {
                    for p in clone_problems(&theirs, ours) {
                        errors.push(problem("clone_from", format!("{from}: {p}")));
                    }
                }
                clone_from = Some(dir);
            }
            Err(e) => errors.push(problem("clone_from", e)),
        }
    }
    let race = table("race", &mut errors);
    if let Some(r) = &race {
        use serde::Deserialize;
        if let Err(e) = sim_agent::race::RaceConfig::deserialize(toml::Value::Table(r.clone())) {
            errors.push(problem("race", e.to_string().trim().to_string()));
        }
    }
    let reward = string("reward_function", &mut errors).unwrap_or_default();
    let mut reward_source = None;
    if reward.trim().is_empty() {
        errors.push(problem("reward_function", "required: a Python reward file's text, or builtin:NAME"));
    } else if reward.chars().count() > MAX_REWARD_CHARS {
        errors.push(problem("reward_function", format!("at most {MAX_REWARD_CHARS} characters (DeepRacer's limit)")));
    } else if let Some(world) = worlds.first() {
        if !reward.starts_with("builtin:") {
            reward_source = Some(reward.clone());
        }
        errors.extend(reward_errors(reward_input(&reward), world, reversed, metadata.as_ref()));
    }
    if !errors.is_empty() {
        return Err(errors);
    }
    let metadata = metadata.expect("checked above");
    let record = ModelRecord {
        job_id: job_id(&name),
        name,
        description,
        created: now,
        tracks: worlds.iter().map(|w| w.name.clone()).collect(),
        reversed,
        agents,
        algorithm: algorithm_name(metadata.training_algorithm).into(),
        sensors: metadata.sensor.iter().map(|s| s.name().to_string()).collect(),
        reward: if reward_source.is_some() { "reward_function.py".into() } else { reward },
        stop,
        clone_of,
        owner: None,
    };
    Ok(Checked {
        files: NewFiles {
            record,
            reward_source,
            model_metadata: metadata_text.unwrap_or_else(|| metadata.to_json()),
            hyperparameters: hyper_text.unwrap_or_else(|| learner::Hyperparameters::default().to_json()),
        },
        race,
        clone_from,
    })
}

/// DeepRacer's locks on a clone: the same algorithm, action-space type (and size, discrete),
/// and sensors as the model it starts from.
pub fn clone_problems(theirs: &ModelMetadata, ours: &ModelMetadata) -> Vec<String> {
    use policy::ActionSpace::{Continuous, Discrete};
    let mut out = Vec::new();
    if theirs.training_algorithm != ours.training_algorithm {
        out.push("a clone keeps its model's training algorithm".to_string());
    }
    match (&theirs.action_space, &ours.action_space) {
        (Discrete(a), Discrete(b)) if a.len() != b.len() => {
            out.push(format!("a clone keeps the number of actions: {} here, {} in the model", b.len(), a.len()))
        }
        (Discrete(_), Continuous { .. }) | (Continuous { .. }, Discrete(_)) => {
            out.push("a clone keeps its model's action-space type (continuous or discrete)".to_string())
        }
        _ => {}
    }
    if theirs.sensor != ours.sensor {
        out.push("a clone keeps its model's sensors".to_string());
    }
    out
}

/// The reward file's errors (warnings are DeepRacer's refusals, which Paddock runs: not errors).
fn reward_errors(
    input: RewardInput<'_>,
    world: &tracks::World,
    reversed: bool,
    metadata: Option<&ModelMetadata>,
) -> Vec<FieldError> {
    let v = match validate(input, world, reversed, metadata) {
        Ok(v) => v,
        Err(e) => return vec![problem("reward_function", e)],
    };
    v.findings
        .iter()
        .filter(|f| f.severity == Severity::Error)
        .map(|f| FieldError { field: "reward_function".into(), message: f.message.clone(), line: f.line })
        .collect()
}

/// Validate a reward on `world` (driven the other way round when `reversed`) as `coordinator
/// reward validate` does (60 places, the simulator's time limit a call, the model's actions or
/// DeepRacer's widest).
pub fn validate(
    input: RewardInput<'_>,
    world: &tracks::World,
    reversed: bool,
    metadata: Option<&ModelMetadata>,
) -> Result<reward_check::Validation, String> {
    let track = world.track(if reversed { tracks::Direction::Reversed } else { tracks::Direction::Forward });
    let space = metadata
        .map(|m| m.action_space.clone())
        .unwrap_or(policy::ActionSpace::Continuous { steering_angle: (-30.0, 30.0), speed: (0.5, 4.0) });
    let race = sim_agent::race::RaceConfig::default();
    let at = Sampling { track: &track, surface: world.surface, space: &space, positions: 60, race: &race };
    let limit = sim_agent::SimConfig::default().reward_time_limit().min(Duration::from_secs(5));
    reward_check::validate(input, at, limit)
}

/// The job spec of a stored model (`job.toml`), as `coordinator job start` takes it; files
/// by their names in the model's folder, the run folder `run_dir`.
pub fn job_spec(checked: &Checked, run_dir: &std::path::Path) -> String {
    use toml::Value;
    let r = &checked.files.record;
    let mut t = toml::Table::new();
    t.insert("name".into(), Value::String(r.name.clone()));
    t.insert("worlds".into(), Value::Array(r.tracks.iter().cloned().map(Value::String).collect()));
    if r.reversed {
        t.insert("reversed".into(), Value::Boolean(true));
    }
    if let Some(n) = r.agents {
        t.insert("agents".into(), Value::Integer(n.into()));
    }
    if let Some(o) = &r.owner {
        t.insert("owner".into(), Value::String(o.clone()));
    }
    t.insert("reward".into(), Value::String(r.reward.clone()));
    t.insert("model_metadata".into(), Value::String("model_metadata.json".into()));
    t.insert("hyperparameters".into(), Value::String("hyperparameters.json".into()));
    t.insert("out".into(), Value::String(run_dir.display().to_string()));
    t.insert("stop".into(), Value::Table(r.stop.clone()));
    if let Some(from) = &checked.clone_from {
        t.insert("clone_from".into(), Value::String(from.display().to_string()));
    }
    if let Some(race) = &checked.race {
        let mut sim = toml::Table::new();
        sim.insert("race".into(), Value::Table(race.clone()));
        t.insert("sim".into(), Value::Table(sim));
    }
    format!(
        "# Written by Paddock's console; `coordinator job start` takes this file as it is.\n{}",
        toml::to_string(&t).expect("a table serialises")
    )
}

/// A job spec's error as a field error: the spec's field names the request's.
pub fn spec_error(e: &anyhow::Error) -> FieldError {
    let text = format!("{e:#}");
    let field = if text.contains("field 'stop") || text.contains("stop.") {
        "stop"
    } else if text.contains("field 'sim'") {
        "race"
    } else if text.contains("model_metadata") {
        "model_metadata"
    } else if text.contains("hyperparameters") {
        "hyperparameters"
    } else {
        "job"
    };
    problem(field, text)
}

fn kind(v: &Value) -> &'static str {
    match v {
        Value::Null => "null",
        Value::Bool(_) => "a boolean",
        Value::Number(_) => "a number",
        Value::String(_) => "a string",
        Value::Array(_) => "a list",
        Value::Object(_) => "an object",
    }
}
