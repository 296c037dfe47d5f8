//! A model's evaluations, started from its page or the API and run in the console's process
//! by `coordinator::evaluation` (as `coordinator evaluate` runs them). Each is kept in the
//! model's folder as `evaluations/ID.json` (written whole: `running`, then `done` or
//! `failed`), with the first trial's camera frames as `ID-frames.png`.
//!
//! Per trial it keeps DeepRacer's columns (time, progress, status, resets, off-tracks and their
//! penalty, crashes and theirs) and, for the fastest trial, the path driven with its speed.

use crate::models::FieldError;
use crate::store::Store;
use serde_json::{Value, json};
use sim_agent::EvalRules;
use sim_agent::race::RaceConfig;
use std::path::{Path, PathBuf};

/// A checked request.
pub struct Checked {
    /// The record as first written (status `running`).
    pub record: Value,
    /// What to run.
    pub request: coordinator::evaluation::Request,
}

fn problem(field: &str, message: impl Into<String>) -> FieldError {
    FieldError { field: field.into(), message: message.into(), line: None }
}

/// The fields an evaluation takes.
pub const FIELDS: [&str; 8] =
    ["name", "track", "reversed", "trials", "race", "max_resets", "off_track_penalty", "crash_penalty"];

/// Check `POST …/evaluations`: `{"name"?, "track", "reversed"?, "trials"? (1–20, default 3),
/// "race"? (the simulator's race table), "max_resets"? (default 100), "off_track_penalty"? (s),
/// "crash_penalty"? (s)}`.
pub fn check(body: &Value, id: &str, now: f64) -> Result<Checked, Vec<FieldError>> {
    let mut errors = Vec::new();
    let Value::Object(map) = body else { return Err(vec![problem("", "expected a JSON object with a track")]) };
    for key in map.keys().filter(|k| !FIELDS.contains(&k.as_str())) {
        errors.push(problem(key, format!("unknown field; expected one of {}", FIELDS.join(", "))));
    }
    let name = match map.get("name") {
        None | Some(Value::Null) => id.to_string(),
        Some(Value::String(s)) => {
            if let Some(p) = crate::store::name_problem(s) {
                errors.push(problem("name", p));
            }
            s.clone()
        }
        Some(_) => {
            errors.push(problem("name", "expected a string"));
            String::new()
        }
    };
    let world = match map.get("track").and_then(Value::as_str) {
        Some(t) => tracks::world(t).map_err(|e| errors.push(problem("track", e.to_string()))).ok(),
        None => {
            errors.push(problem("track", "required: a track's name (GET /api/v1/tracks)"));
            None
        }
    };
    let reversed = match map.get("reversed") {
        None | Some(Value::Null) => false,
        Some(Value::Bool(b)) => *b,
        Some(_) => {
            errors.push(problem("reversed", "expected true or false"));
            false
        }
    };
    let number = |field: &str, default: f64, lo: f64, hi: f64, errors: &mut Vec<FieldError>| -> f64 {
        match map.get(field) {
            None | Some(Value::Null) => default,
            Some(v) => match v.as_f64() {
                Some(x) if (lo..=hi).contains(&x) => x,
                _ => {
                    errors.push(problem(field, format!("expected a number from {lo} to {hi}, not {v}")));
                    default
                }
            },
        }
    };
    let defaults = EvalRules::default();
    let trials = number("trials", 3.0, 1.0, 20.0, &mut errors);
    if trials.fract() != 0.0 {
        errors.push(problem("trials", "expected a whole number of trials"));
    }
    let max_resets = number("max_resets", 100.0, 0.0, 1000.0, &mut errors) as u32;
    let off_track = number("off_track_penalty", defaults.penalty_s, 0.0, 60.0, &mut errors);
    let crash = number("crash_penalty", defaults.collision_penalty_s, 0.0, 60.0, &mut errors);
    let race = match map.get("race") {
        None | Some(Value::Null) => RaceConfig::default(),
        Some(v) => race_table(v).unwrap_or_else(|e| {
            errors.push(problem("race", e));
            RaceConfig::default()
        }),
    };
    if !errors.is_empty() {
        return Err(errors);
    }
    let world = world.expect("checked");
    let rules = EvalRules { max_resets, penalty_s: off_track, collision_penalty_s: crash, time_limit_s: None };
    let record = json!({
        "id": id, "name": name, "created": now, "status": "running",
        "track": world.name, "reversed": reversed, "trials": trials as usize,
        "race_type": serde_json::to_value(race.race_type).unwrap_or(Value::Null),
        "race": serde_json::to_value(&race).unwrap_or(Value::Null),
        "max_resets": max_resets, "off_track_penalty": off_track, "crash_penalty": crash,
    });
    let request = coordinator::evaluation::Request {
        worlds: vec![world],
        reversed,
        trials: trials as usize,
        seed: now as u64,
        race,
        rules,
        record: true,
        all_frames: false,
    };
    Ok(Checked { record, request })
}

/// The simulator's race table (`race_type`, objects, bots) from JSON, or why not.
pub fn race_table(v: &Value) -> Result<RaceConfig, String> {
    use serde::Deserialize;
    toml::Value::try_from(v)
        .map_err(|e| e.to_string())
        .and_then(|t| RaceConfig::deserialize(t).map_err(|e| e.to_string()))
        .map_err(|e| e.trim().to_string())
}

/// The folder of a model's evaluations.
pub fn dir(store: &Store, model: &str) -> Result<PathBuf, crate::store::StoreError> {
    Ok(store.dir(model)?.join("evaluations"))
}

fn write_whole(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let tmp = path.with_extension("tmp");
    std::fs::write(&tmp, bytes)?;
    std::fs::rename(&tmp, path)
}

/// Write a record (whole).
pub fn save(dir: &Path, record: &Value) -> std::io::Result<()> {
    std::fs::create_dir_all(dir)?;
    let id = record["id"].as_str().unwrap_or("evaluation");
    write_whole(&dir.join(format!("{id}.json")), serde_json::to_string_pretty(record).expect("JSON").as_bytes())
}

/// Run a checked evaluation of the model folder `model_dir` and store its outcome (blocking).
pub fn run(dir: &Path, model_dir: &Path, mut checked: Checked) {
    let control_hz = sim_agent::SimConfig::default().control_hz;
    let rules = checked.request.rules.clone();
    match coordinator::evaluation::run(model_dir, &checked.request) {
        Ok(done) => {
            let w = done.worlds.into_iter().next().expect("one world");
            let mut rows = Vec::new();
            for (i, t) in w.trials.iter().enumerate() {
                let time = t.lap_time.unwrap_or(t.steps as f64 / control_hz);
                rows.push(json!({
                    "trial": i + 1, "time_s": time, "progress": t.progress, "status": t.status.label(),
                    "resets": t.off_track + t.crashes, "off_tracks": t.off_track,
                    "off_track_penalty_s": f64::from(t.off_track) * rules.penalty_s,
                    "crashes": t.crashes, "crash_penalty_s": f64::from(t.crashes) * rules.collision_penalty_s,
                    "lap_time_s": t.lap_time,
                }));
            }
            // The fastest lap; without one, the trial that got furthest.
            let best = (0..w.trials.len()).min_by(|&a, &b| {
                let key = |i: usize| (w.trials[i].lap_time.unwrap_or(f64::INFINITY), -w.trials[i].progress);
                key(a).partial_cmp(&key(b)).unwrap_or(std::cmp::Ordering::Equal)
            });
            let path: Vec<[f64; 3]> = best
                .map(|i| w.trials[i].log.trace.iter().map(|s| [s.x, s.y, f64::from(s.throttle)]).collect())
                .unwrap_or_default();
            let frames = w.trials.first().map(|t| t.log.frames.as_slice()).unwrap_or(&[]);
            let id = checked.record["id"].as_str().unwrap_or("evaluation").to_string();
            let has_frames = !frames.is_empty() && strip(frames, &dir.join(format!("{id}-frames.png"))).is_ok();
            let r = &mut checked.record;
            r["status"] = json!("done");
            r["policy_version"] = json!(done.policy_version);
            r["results"] = json!(rows);
            r["best_lap_s"] = json!(w.trials.iter().filter_map(|t| t.lap_time).min_by(f64::total_cmp));
            r["laps"] = json!(w.trials.iter().filter(|t| t.lap_time.is_some()).count());
            r["fastest_trial"] = json!(best.map(|i| i + 1));
            r["path"] = json!(path);
            r["frames"] = json!(has_frames);
        }
        Err(e) => {
            checked.record["status"] = json!("failed");
            checked.record["error"] = json!(format!("{e:#}"));
        }
    }
    // Its time counts against the quotas.
    checked.record["finished"] = json!(protocol::job::now_unix());
    if let Err(e) = save(dir, &checked.record) {
        tracing::error!("{}: the evaluation's record was not written: {e}", dir.display());
    }
}

/// Up to 12 of the frames, evenly spread, side by side as one grey PNG.
fn strip(frames: &[policy::exchange::Frame], out: &Path) -> image::ImageResult<()> {
    let n = frames.len().min(12);
    let (w, h) = (frames[0].width, frames[0].height);
    let mut img = image::GrayImage::new(w * n as u32, h);
    for k in 0..n {
        let f = &frames[k * frames.len() / n];
        if f.gray.len() != (w * h) as usize {
            continue;
        }
        for y in 0..h {
            for x in 0..w {
                img.put_pixel(k as u32 * w + x, y, image::Luma([f.gray[(y * w + x) as usize]]));
            }
        }
    }
    img.save(out)
}

/// A model's evaluations, newest first (without their paths); one still `running` in a
/// console that has since restarted is `interrupted`.
pub fn list(dir: &Path, running: &std::collections::BTreeSet<String>) -> Vec<Value> {
    let mut out: Vec<Value> = std::fs::read_dir(dir)
        .into_iter()
        .flatten()
        .flatten()
        .filter(|e| e.path().extension().is_some_and(|x| x == "json"))
        .filter_map(|e| std::fs::read_to_string(e.path()).ok())
        .filter_map(|t| serde_json::from_str::<Value>(&t).ok())
        .map(|mut v| {
            if v["status"] == "running" && !running.contains(v["id"].as_str().unwrap_or("")) {
                v["status"] = json!("interrupted");
            }
            if let Some(o) = v.as_object_mut() {
                o.remove("path");
            }
            v
        })
        .collect();
    out.sort_by(|a, b| b["created"].as_f64().unwrap_or(0.0).total_cmp(&a["created"].as_f64().unwrap_or(0.0)));
    out
}

/// One evaluation, path included.
pub fn get(dir: &Path, id: &str) -> Option<Value> {
    if crate::store::name_problem(id).is_some() {
        return None;
    }
    std::fs::read_to_string(dir.join(format!("{id}.json"))).ok().and_then(|t| serde_json::from_str(&t).ok())
}
