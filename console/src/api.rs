//! The JSON API under `/api/v1/` (documented in `openapi.json`, served at
//! `/api/v1/openapi.json`). The pages use it; so can any program with the token.
//!
//! Bad requests get 400 with every invalid field (`{"error", "errors": [{"field",
//! "message", "line"?}]}`), unknown models 404, a name taken 409; each refusal is counted.

use crate::hub::Hub;
use crate::models::{self, FieldError};
use crate::store::{ModelRecord, Store, StoreError};
use axum::body::Bytes;
use axum::extract::{Path, State};
use axum::http::{StatusCode, header};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use protocol::job_reply::Body;
use protocol::job_request::Kind;
use protocol::{JobReply, JobState};
use serde_json::{Value, json};
use std::sync::Arc;
use std::time::Duration;

/// What every handler shares.
#[derive(Clone)]
pub struct App {
    /// The data folder.
    pub store: Store,
    /// The Zenoh side.
    pub hub: Hub,
    /// The token, the users and their sessions.
    pub gate: Arc<crate::auth::Gate>,
    /// Served over TLS (cookies are marked Secure).
    pub https: bool,
    /// The evaluations running in this process (their ids).
    pub running: Arc<std::sync::Mutex<std::collections::BTreeSet<String>>>,
    /// The races.
    pub races: crate::races::Races,
    /// Race entries evaluated at once: one permit each.
    pub race_slots: Arc<tokio::sync::Semaphore>,
    /// Live races replay at this many simulator seconds a second.
    pub live_speed: f64,
}

/// The middleware on a model's routes (`/models/NAME…`, `/api/v1/models/NAME…`): a model
/// that is not the requester's is refused (403, naming the role that would do), to see it
/// unless they are a facilitator or an admin, to change it unless they are an admin.
pub async fn ownership(State(app): State<App>, req: axum::extract::Request, next: axum::middleware::Next) -> Response {
    // The open routes (the login's) carry no principal, and name no model.
    let Some(p) = req.extensions().get::<crate::auth::Principal>().cloned() else { return next.run(req).await };
    let path = req.uri().path();
    // The name as the route's `{name}` reads it: percent-decoded (`rita%2D1` is `rita-1`).
    let name = path
        .strip_prefix("/api/v1/models/")
        .or_else(|| path.strip_prefix("/models/"))
        .and_then(|rest| rest.split('/').next())
        .map(|n| percent_encoding::percent_decode_str(n).decode_utf8().map(|d| d.into_owned()));
    let name = match name {
        Some(Ok(n)) => Some(n).filter(|n| !crate::store::RESERVED.contains(&n.as_str())),
        Some(Err(_)) => {
            crate::counters::refused("an unknown model");
            return error(StatusCode::NOT_FOUND, "no such model");
        }
        None => None,
    };
    if let Some(rec) = name.and_then(|n| app.store.get(&n).ok()) {
        let owner = rec.owner.as_deref();
        let reading = matches!(*req.method(), axum::http::Method::GET | axum::http::Method::HEAD);
        if !p.may_see(owner) {
            crate::counters::refused("another user's model");
            return error(
                StatusCode::FORBIDDEN,
                &format!("model '{}' is another user's: seeing it needs the facilitator role", rec.name),
            );
        }
        if !reading && !p.may_change(owner) {
            crate::counters::refused("another user's model");
            return error(
                StatusCode::FORBIDDEN,
                &format!("model '{}' is another user's: changing it needs the admin role", rec.name),
            );
        }
    }
    next.run(req).await
}

/// The models `p` may see.
pub fn visible_models(app: &App, p: &crate::auth::Principal) -> Vec<ModelRecord> {
    app.store.list().into_iter().filter(|r| p.may_see(r.owner.as_deref())).collect()
}

/// A JSON error answer: `{"error": message}`.
pub fn error(code: StatusCode, message: &str) -> Response {
    (code, axum::Json(json!({"error": message}))).into_response()
}

/// 400 with every invalid field.
pub fn invalid(errors: &[FieldError]) -> Response {
    crate::counters::refused("invalid fields");
    let summary: Vec<String> = errors.iter().map(|e| format!("{}: {}", e.field, e.message)).collect();
    (StatusCode::BAD_REQUEST, axum::Json(json!({"error": summary.join("; "), "errors": errors}))).into_response()
}

fn store_error(e: StoreError) -> Response {
    match e {
        StoreError::NotFound(_) => {
            crate::counters::refused("an unknown model");
            error(StatusCode::NOT_FOUND, &e.to_string())
        }
        StoreError::Taken(_) => {
            crate::counters::refused("a model name taken");
            error(StatusCode::CONFLICT, &e.to_string())
        }
        StoreError::Io { .. } => {
            tracing::error!("{e}");
            error(StatusCode::INTERNAL_SERVER_ERROR, &e.to_string())
        }
    }
}

fn json_body(body: &Bytes) -> Result<Value, FieldError> {
    serde_json::from_slice(body).map_err(|e| FieldError {
        field: String::new(),
        message: format!("the body is not JSON: {e}"),
        line: None,
    })
}

/// A model's status from its job's state: `training`, `stopping`, `ready`, `failed`, or
/// `unknown` (the coordinator has not listed the job: it is starting, or its database is gone).
pub fn status_of(state: Option<JobState>, rec: &ModelRecord, store: &Store) -> &'static str {
    match state {
        Some(JobState::Running) => "training",
        Some(JobState::Stopping) => "stopping",
        Some(JobState::Finished) => "ready",
        Some(JobState::Failed) => "failed",
        _ => match store.dir(&rec.name) {
            Ok(d) if d.join("run/model/manifest.json").exists() => "ready",
            _ => "unknown",
        },
    }
}

/// The best lap of a model's evaluations (s): the fastest mean lap of an evaluation whose
/// every trial finished.
pub fn best_lap(store: &Store, name: &str) -> Option<f64> {
    let text = std::fs::read_to_string(store.dir(name).ok()?.join("run/evaluations.jsonl")).ok()?;
    text.lines()
        .filter_map(|l| serde_json::from_str::<Value>(l).ok())
        .filter_map(|v| v["lap_time"].as_f64())
        .min_by(f64::total_cmp)
}

fn model_json(app: &App, rec: &ModelRecord, state: Option<JobState>) -> Value {
    json!({
        "name": rec.name,
        "description": rec.description,
        "status": status_of(state, rec, &app.store),
        "job_id": rec.job_id,
        "algorithm": rec.algorithm,
        "sensors": rec.sensors,
        "tracks": rec.tracks,
        "reversed": rec.reversed,
        "agents": rec.agents,
        "owner": rec.owner,
        // Its place among the jobs waiting their turn (0: not waiting).
        "queued": app.hub.job(&rec.job_id).map_or(0, |j| j.queued),
        "reward": rec.reward,
        "stop": rec.stop,
        "created": rec.created,
        "best_lap_s": best_lap(&app.store, &rec.name),
    })
}

/// `GET /api/v1/health`: the coordinator's answer, refusals counted.
pub async fn health(State(app): State<App>) -> Response {
    let (listed, error) = {
        let s = app.hub.seen.lock().expect("hub state");
        (s.listed.map(|t| t.elapsed().as_secs_f64()), s.error.clone())
    };
    axum::Json(
        json!({"coordinator_listed_s_ago": listed, "coordinator_error": error, "refused": crate::counters::all()}),
    )
    .into_response()
}

/// `GET /api/v1/tracks`.
pub async fn tracks() -> Response {
    let list: Vec<Value> = tracks::worlds()
        .iter()
        .map(|w| {
            let t = w.track(tracks::Direction::Forward);
            // DRoA's direction names: which way round the track's own order drives.
            let forward = if t.is_ccw() { "counterclockwise" } else { "clockwise" };
            json!({"name": w.name, "surface": w.surface.name(), "length_m": t.length(), "forward": forward,
                   "picture": format!("/api/v1/tracks/{}/picture.svg", w.name)})
        })
        .collect();
    axum::Json(list).into_response()
}

/// `GET /api/v1/tracks/NAME/picture.svg`: the track drawn from its own lines.
pub async fn track_picture(Path(name): Path<String>) -> Response {
    match tracks::world(&name) {
        Ok(w) => ([(header::CONTENT_TYPE, "image/svg+xml")], crate::pictures::track_svg(&w)).into_response(),
        Err(e) => {
            crate::counters::refused("an unknown track");
            error(StatusCode::NOT_FOUND, &e.to_string())
        }
    }
}

/// `GET /api/v1/tracks/NAME/race_line?actions=N&reversed=B`: the track's racing line (`[x, y,
/// speed]` a point, its lap time) for DeepRacer's car on the track's surface, driven the other
/// way round when `reversed=true`, and N discrete actions that drive it
/// (`--action-space-from-line`'s), 10 by default.
pub async fn race_line(
    Path(name): Path<String>,
    axum::extract::Query(q): axum::extract::Query<std::collections::HashMap<String, String>>,
) -> Response {
    let n = match q.get("actions").map(|a| a.parse::<usize>()) {
        None => 10,
        Some(Ok(n)) if (2..=30).contains(&n) => n,
        _ => {
            return invalid(&[field(
                "actions",
                "expected a number of actions from 2 to 30 (DeepRacer's range)".into(),
            )]);
        }
    };
    let direction = match q.get("reversed").map(String::as_str) {
        None | Some("false") => tracks::Direction::Forward,
        Some("true") => tracks::Direction::Reversed,
        Some(_) => return invalid(&[field("reversed", "expected true or false".into())]),
    };
    let world = match tracks::world(&name) {
        Ok(w) => w,
        Err(e) => {
            crate::counters::refused("an unknown track");
            return error(StatusCode::NOT_FOUND, &e.to_string());
        }
    };
    let made = tokio::task::spawn_blocking(move || {
        let car = sim_agent::SimConfig::default().car;
        sim_agent::race_line::LinePlan::new(&world.track(direction), &car, world.surface).map(|plan| {
            let actions = plan.action_space(&car, n, 30.0, 4.0);
            let points: Vec<[f64; 3]> = plan.points.iter().zip(&plan.speed).map(|(p, v)| [p.x, p.y, *v]).collect();
            let svg = crate::pictures::lap_svg(&world, &points, "speed (m/s)");
            json!({"track": world.name, "lap_time_s": plan.lap_time, "points": points, "svg": svg,
                   "actions": actions.iter().map(|a| json!({"steering_angle": a.steering_angle, "speed": a.speed})).collect::<Vec<_>>()})
        })
    })
    .await;
    match made {
        Ok(Ok(v)) => axum::Json(v).into_response(),
        Ok(Err(e)) => error(StatusCode::UNPROCESSABLE_ENTITY, &format!("{name}: no racing line: {e}")),
        Err(e) => error(StatusCode::INTERNAL_SERVER_ERROR, &e.to_string()),
    }
}

/// `POST /api/v1/rewards/dry_run` `{"reward_function", "track"?}`: the reward along one lap of
/// Paddock's scripted driver, `[x, y, reward]` a step, and the lap drawn on the track coloured by
/// reward (blue low, red high). A file with errors gets the validation's answer instead (400).
pub async fn dry_run(body: Bytes) -> Response {
    let v = match json_body(&body) {
        Ok(v) => v,
        Err(f) => return invalid(&[f]),
    };
    let mut errors = Vec::new();
    let source = match v.get("reward_function").and_then(Value::as_str) {
        Some(s) if s.chars().count() <= models::MAX_REWARD_CHARS => s.to_string(),
        _ => {
            errors
                .push(field("reward_function", "required: the reward file's text (at most 140,000 characters)".into()));
            String::new()
        }
    };
    let track = v.get("track").and_then(Value::as_str).unwrap_or("reinvent_base");
    let world = tracks::world(track).map_err(|e| errors.push(field("track", e.to_string()))).ok();
    let reversed = reversed_field(&v, &mut errors);
    if !errors.is_empty() {
        return invalid(&errors);
    }
    let world = world.expect("checked");
    let done = tokio::task::spawn_blocking(move || -> Result<Value, Vec<FieldError>> {
        let input = models::reward_input(&source);
        let checked = models::validate(input, &world, reversed, None).map_err(|e| vec![field("reward_function", e)])?;
        if !checked.ok() {
            return Err(checked
                .findings
                .iter()
                .filter(|f| f.severity == sim_agent::reward_check::Severity::Error)
                .map(|f| FieldError { field: "reward_function".into(), message: f.message.clone(), line: f.line })
                .collect());
        }
        let cfg = std::sync::Arc::new(sim_agent::SimConfig::default());
        let mut reward = if source.starts_with("builtin:") {
            sim_agent::RewardFn::from_spec(&source)
        } else {
            sim_agent::RewardFn::from_file_text(std::path::Path::new("reward_function.py"), &source)
        }
        .map_err(|e| vec![field("reward_function", e.to_string())])?
        .with_time_limit(cfg.reward_time_limit());
        let direction = if reversed { tracks::Direction::Reversed } else { tracks::Direction::Forward };
        let (points, status) = sim_agent::driver::lap_rewards(&world, direction, &mut reward, cfg)
            .map_err(|e| vec![field("reward_function", e.to_string())])?;
        let total: f64 = points.iter().map(|p| p[2]).sum();
        Ok(json!({"track": world.name, "status": status.label(), "steps": points.len(), "total_reward": total,
                  "svg": crate::pictures::lap_svg(&world, &points, "reward"), "points": points}))
    })
    .await;
    match done {
        Ok(Ok(v)) => axum::Json(v).into_response(),
        Ok(Err(e)) => invalid(&e),
        Err(e) => error(StatusCode::INTERNAL_SERVER_ERROR, &e.to_string()),
    }
}

/// `POST /api/v1/rewards/validate` `{"reward_function", "track"?, "model_metadata"?}`.
pub async fn validate_reward(body: Bytes) -> Response {
    let v = match json_body(&body) {
        Ok(v) => v,
        Err(f) => return invalid(&[f]),
    };
    let mut errors = Vec::new();
    let source = match v.get("reward_function") {
        Some(Value::String(s)) if s.chars().count() <= models::MAX_REWARD_CHARS => s.clone(),
        Some(Value::String(_)) => {
            errors.push(field("reward_function", format!("at most {} characters", models::MAX_REWARD_CHARS)));
            String::new()
        }
        _ => {
            errors.push(field("reward_function", "required: the reward file's text".into()));
            String::new()
        }
    };
    let track = v.get("track").and_then(Value::as_str).unwrap_or("reinvent_base");
    let world = tracks::world(track).map_err(|e| errors.push(field("track", e.to_string()))).ok();
    let reversed = reversed_field(&v, &mut errors);
    let metadata = match v.get("model_metadata") {
        None | Some(Value::Null) => None,
        Some(m) => policy::ModelMetadata::parse(&m.to_string(), "model_metadata")
            .map_err(|e| errors.push(field("model_metadata", e.to_string())))
            .ok(),
    };
    if !errors.is_empty() {
        return invalid(&errors);
    }
    let world = world.expect("checked");
    let done = tokio::task::spawn_blocking(move || {
        let input = models::reward_input(&source);
        models::validate(input, &world, reversed, metadata.as_ref()).map(|v| v.to_json())
    })
    .await;
    match done {
        Ok(Ok(v)) => axum::Json(v).into_response(),
        Ok(Err(e)) => error(StatusCode::INTERNAL_SERVER_ERROR, &e),
        Err(e) => error(StatusCode::INTERNAL_SERVER_ERROR, &format!("the validation failed: {e}")),
    }
}

/// A request's optional `"reversed"`: false when absent, an error unless a boolean.
fn reversed_field(v: &Value, errors: &mut Vec<FieldError>) -> bool {
    match v.get("reversed") {
        None | Some(Value::Null) => false,
        Some(Value::Bool(b)) => *b,
        Some(_) => {
            errors.push(field("reversed", "expected true or false".into()));
            false
        }
    }
}

fn field(name: &str, message: String) -> FieldError {
    FieldError { field: name.into(), message, line: None }
}

/// `GET /api/v1/models`.
pub async fn list_models(
    State(app): State<App>,
    axum::Extension(p): axum::Extension<crate::auth::Principal>,
) -> Response {
    let list: Vec<Value> = visible_models(&app, &p)
        .iter()
        .map(|r| model_json(&app, r, app.hub.job(&r.job_id).map(|j| j.state())))
        .collect();
    axum::Json(list).into_response()
}

/// `POST /api/v1/models`: check, store, start the job; 201 with the model.
pub async fn create_model(
    State(app): State<App>,
    axum::Extension(p): axum::Extension<crate::auth::Principal>,
    body: Bytes,
) -> Response {
    let v = match json_body(&body) {
        Ok(v) => v,
        Err(f) => return invalid(&[f]),
    };
    if let Some(name) = v.get("name").and_then(Value::as_str)
        && let Ok(r) = app.store.get(name)
    {
        return store_error(StoreError::Taken(r.name));
    }
    // A model spends a model and its stop's minutes (10 when it names none), of its maker's
    // quota and the instance's.
    let minutes = v
        .get("stop")
        .and_then(|s| s.get("minutes"))
        .and_then(Value::as_f64)
        .unwrap_or_else(|| crate::quota::stop_minutes(&models::default_stop()));
    let ask = crate::quota::Ask { models: 1, minutes: Some(minutes) };
    if let Err(r) = crate::quota::check_off_thread(&app, &p, ask).await {
        return r.into_response();
    }
    let store = app.store.clone();
    let made = tokio::task::spawn_blocking(move || -> Result<(ModelRecord, protocol::Job), Created> {
        let now = protocol::job::now_unix();
        let source = |from: &str| -> Result<(policy::ModelMetadata, std::path::PathBuf), String> {
            let rec = store.get(from).map_err(|e| e.to_string())?;
            if !p.may_see(rec.owner.as_deref()) {
                return Err(format!("model '{from}' is another user's: cloning it needs the facilitator role"));
            }
            let dir = store.dir(&rec.name).map_err(|e| e.to_string())?;
            let model = dir.join("run/model");
            if !model.join("manifest.json").exists() {
                return Err(format!("model '{from}' has no trained model yet"));
            }
            let text = std::fs::read_to_string(dir.join("model_metadata.json")).map_err(|e| e.to_string())?;
            let meta = policy::ModelMetadata::parse(&text, "model_metadata.json").map_err(|e| e.to_string())?;
            Ok((meta, model))
        };
        let job_id = |name: &str| format!("{name}-{}", (now * 1000.0) as u64 % 100_000_000);
        let mut checked = models::check(&v, now, job_id, &source).map_err(Created::Invalid)?;
        checked.files.record.owner = p.user.clone();
        let record = checked.files.record.clone();
        let run = store.dir(&record.name)?.join("run");
        let job = store.create(&checked.files, |tmp| -> Result<protocol::Job, Created> {
            let spec = tmp.join("job.toml");
            std::fs::write(&spec, models::job_spec(&checked, &run))
                .map_err(|e| Created::Store(StoreError::Io { path: spec.display().to_string(), msg: e.to_string() }))?;
            coordinator::jobspec::load(&spec, &record.job_id)
                .map_err(|e| Created::Invalid(vec![models::spec_error(&e)]))
        })?;
        Ok((record, job))
    })
    .await;
    let (record, job) = match made {
        Ok(Ok(m)) => m,
        Ok(Err(Created::Store(e))) => return store_error(e),
        Ok(Err(Created::Invalid(e))) => return invalid(&e),
        Err(e) => return error(StatusCode::INTERNAL_SERVER_ERROR, &format!("creating the model failed: {e}")),
    };
    match app.hub.request(Kind::StartJob(job), Duration::from_secs(10)).await {
        Ok(r) if r.ok => {
            tracing::info!(model = %record.name, job = %record.job_id, "model created; its job started");
            app.hub.watch(&record.job_id);
            let state = match &r.body {
                Some(Body::Job(j)) => Some(j.state()),
                _ => None,
            };
            (StatusCode::CREATED, axum::Json(model_json(&app, &record, state))).into_response()
        }
        other => {
            // Nothing is kept of a model whose job did not start.
            let why = match other {
                Ok(r) => r.text,
                Err(e) => e,
            };
            let _ = app.store.delete(&record.name);
            error(StatusCode::SERVICE_UNAVAILABLE, &format!("the coordinator did not start the model's job: {why}"))
        }
    }
}

enum Created {
    Store(StoreError),
    Invalid(Vec<FieldError>),
}

impl From<StoreError> for Created {
    fn from(e: StoreError) -> Created {
        Created::Store(e)
    }
}

/// The state of a model's job as the coordinator answers now (the hub's list may be a second
/// old); the list's when the coordinator does not answer.
pub async fn state_now(app: &App, rec: &ModelRecord) -> Option<JobState> {
    match app.hub.request(Kind::StatusJobId(rec.job_id.clone()), Duration::from_secs(3)).await {
        Ok(r) => coordinator::control::status_of(&r)
            .and_then(|s| s.record.as_ref())
            .filter(|j| j.job.is_some())
            .map(|j| j.state()),
        Err(_) => app.hub.job(&rec.job_id).map(|j| j.state()),
    }
}

/// A model's record and its job's status as the coordinator answers now.
async fn fresh(app: &App, name: &str) -> Result<(ModelRecord, Option<JobReply>), Response> {
    let rec = app.store.get(name).map_err(store_error)?;
    let r = app.hub.request(Kind::StatusJobId(rec.job_id.clone()), Duration::from_secs(3)).await.ok();
    Ok((rec, r))
}

/// `GET /api/v1/models/NAME`: the model, its status, and its job's figures.
pub async fn get_model(State(app): State<App>, Path(name): Path<String>) -> Response {
    let (rec, reply) = match fresh(&app, &name).await {
        Ok(x) => x,
        Err(r) => return r,
    };
    let job = reply.as_ref().and_then(coordinator::control::status_of).and_then(|s| s.record.clone());
    let mut v = model_json(&app, &rec, job.as_ref().filter(|j| j.job.is_some()).map(|j| j.state()));
    if let Some(j) = &job {
        let l = j.learner.clone().unwrap_or_default();
        v["training"] = json!({
            "iteration": l.iteration, "policy_version": l.policy_version, "episodes": l.episodes,
            "env_steps": l.env_steps, "progress": l.window_progress, "reward": l.window_reward,
            "eval_progress": l.eval_progress, "eval_laps": l.eval_laps, "stop_reason": l.stop_reason,
            "failure": l.failure, "steps_per_s": l.worlds.iter().map(|w| w.steps_per_s).sum::<f64>(),
            "worlds": l.worlds.iter().map(|w| json!({"world": w.world, "steps_per_s": w.steps_per_s, "progress": w.mean_progress})).collect::<Vec<_>>(),
        });
        v["events"] = json!(j.log);
    }
    if let Some(r) = &reply {
        v["status_text"] = json!(r.text);
    }
    axum::Json(v).into_response()
}

/// `POST /api/v1/models/NAME/stop`.
pub async fn stop_model(State(app): State<App>, Path(name): Path<String>) -> Response {
    let rec = match app.store.get(&name) {
        Ok(r) => r,
        Err(e) => return store_error(e),
    };
    match app.hub.request(Kind::StopJobId(rec.job_id.clone()), Duration::from_secs(10)).await {
        Ok(r) if r.ok => {
            let state = match &r.body {
                Some(Body::Job(j)) => Some(j.state()),
                _ => None,
            };
            axum::Json(model_json(&app, &rec, state)).into_response()
        }
        Ok(r) => error(StatusCode::CONFLICT, &r.text),
        Err(e) => error(StatusCode::SERVICE_UNAVAILABLE, &e),
    }
}

/// `DELETE /api/v1/models/NAME`: refused while it trains.
pub async fn delete_model(State(app): State<App>, Path(name): Path<String>) -> Response {
    let rec = match app.store.get(&name) {
        Ok(r) => r,
        Err(e) => return store_error(e),
    };
    let status = status_of(state_now(&app, &rec).await, &rec, &app.store);
    if matches!(status, "training" | "stopping") {
        crate::counters::refused("deleting a training model");
        return error(StatusCode::CONFLICT, &format!("model '{name}' is {status}: stop it first"));
    }
    match app.store.delete(&name) {
        Ok(()) => {
            tracing::info!(model = %name, "model deleted");
            StatusCode::NO_CONTENT.into_response()
        }
        Err(e) => store_error(e),
    }
}

/// A model's graph so far: `metrics.jsonl` and `evaluations.jsonl` from `skip` lines on.
pub fn metrics(store: &Store, name: &str, skip: (usize, usize)) -> (Vec<Value>, Vec<Value>) {
    let Ok(dir) = store.dir(name) else { return (Vec::new(), Vec::new()) };
    let read = |file: &str, skip: usize| -> Vec<Value> {
        std::fs::read_to_string(dir.join("run").join(file))
            .unwrap_or_default()
            .lines()
            .skip(skip)
            .filter_map(|l| serde_json::from_str::<Value>(l).ok())
            .collect()
    };
    let updates = read("metrics.jsonl", skip.0)
        .into_iter()
        .map(|m| {
            json!({"iteration": m["iteration"], "time_s": m["time_s"], "reward": m["mean_reward"],
                   "progress": m["mean_progress"], "entropy": m.get("entropy"), "samples_per_s": m["samples_per_s"],
                   "env_steps": m["env_steps"]})
        })
        .collect();
    let evals = read("evaluations.jsonl", skip.1)
        .into_iter()
        .map(|e| {
            json!({"iteration": e["iteration"], "progress": e["progress"], "reward": e.get("reward"), "lap_time": e["lap_time"],
                   "best": e["best"], "min_laps": e["min_laps"], "verification": e["verification"],
                   "worlds": e["worlds"]})
        })
        .collect();
    (updates, evals)
}

/// `GET /api/v1/models/NAME/metrics`: every update's and evaluation's figures.
pub async fn model_metrics(State(app): State<App>, Path(name): Path<String>) -> Response {
    if let Err(e) = app.store.get(&name) {
        return store_error(e);
    }
    let (updates, evaluations) = metrics(&app.store, &name, (0, 0));
    axum::Json(json!({"updates": updates, "evaluations": evaluations})).into_response()
}

/// `GET /api/v1/models/NAME/camera.png?agent=ID`: the latest frame of one of its agents (the
/// most recent of any agent without `agent`).
pub async fn camera(
    State(app): State<App>,
    Path(name): Path<String>,
    axum::extract::Query(q): axum::extract::Query<std::collections::HashMap<String, String>>,
) -> Response {
    let rec = match app.store.get(&name) {
        Ok(r) => r,
        Err(e) => return store_error(e),
    };
    app.hub.watch(&rec.job_id);
    let frames = app.hub.frames(&rec.job_id);
    let frame = match q.get("agent") {
        Some(a) => frames.get(a),
        None => frames.values().max_by_key(|f| f.count),
    };
    match frame {
        Some(f) => {
            ([(header::CONTENT_TYPE, "image/png"), (header::CACHE_CONTROL, "no-store")], f.png.to_vec()).into_response()
        }
        None => error(StatusCode::NOT_FOUND, "no camera frame yet (models with a camera, while they train)"),
    }
}

/// `GET /api/v1/models/NAME/events`: server-sent events, once a second when something is new:
/// `status` (the model's status and job figures), `metrics` (new updates and evaluations),
/// `camera` (new frames: each agent's latest, its world and how many it has sent).
pub async fn events(State(app): State<App>, Path(name): Path<String>) -> Response {
    let rec = match app.store.get(&name) {
        Ok(r) => r,
        Err(e) => return store_error(e),
    };
    app.hub.watch(&rec.job_id);
    struct Seen {
        lines: (usize, usize),
        status: Option<Value>,
        frames: u64,
        first: bool,
    }
    let start = Seen { lines: (0, 0), status: None, frames: 0, first: true };
    let stream = futures_util::stream::unfold((app, rec, start), |(app, rec, mut seen)| async move {
        if !seen.first {
            tokio::time::sleep(Duration::from_secs(1)).await;
        }
        seen.first = false;
        let mut out: Vec<Result<Event, std::convert::Infallible>> = Vec::new();
        let job = app.hub.job(&rec.job_id);
        let summary = job.as_ref().map(|j| {
            json!({"state": j.state().name(), "minutes": j.minutes, "episodes": j.episodes, "progress": j.progress,
                   "queued": j.queued})
        });
        let status = json!({"status": status_of(job.map(|j| j.state()), &rec, &app.store), "job": summary});
        if seen.status.as_ref() != Some(&status) {
            out.push(Ok(Event::default().event("status").data(status.to_string())));
            seen.status = Some(status);
        }
        let (updates, evaluations) = metrics(&app.store, &rec.name, seen.lines);
        if !updates.is_empty() || !evaluations.is_empty() {
            seen.lines.0 += updates.len();
            seen.lines.1 += evaluations.len();
            out.push(Ok(Event::default()
                .event("metrics")
                .data(json!({"updates": updates, "evaluations": evaluations}).to_string())));
        }
        let frames = app.hub.frames(&rec.job_id);
        let total: u64 = frames.values().map(|f| f.count).sum();
        if total != seen.frames {
            seen.frames = total;
            let agents: Vec<Value> = frames
                .values()
                .map(|f| json!({"agent": f.agent, "world": f.world, "policy_version": f.policy_version, "count": f.count}))
                .collect();
            out.push(Ok(Event::default().event("camera").data(json!({"agents": agents, "count": total}).to_string())));
        }
        Some((futures_util::stream::iter(out), (app, rec, seen)))
    });
    use futures_util::StreamExt;
    Sse::new(stream.flatten()).keep_alive(KeepAlive::default()).into_response()
}

/// `GET /api/v1/models/NAME/car.tar.gz`: DeepRacer's car archive of the best model
/// (`physicalmodel-NAME.tar.gz`). 409 before a model is written; 422 for a model no car can
/// drive (the state vector).
pub async fn car_archive(State(app): State<App>, Path(name): Path<String>) -> Response {
    let dir = match app.store.get(&name).and_then(|r| app.store.dir(&r.name)) {
        Ok(d) => d,
        Err(e) => return store_error(e),
    };
    let made = tokio::task::spawn_blocking(move || -> Result<Vec<u8>, (StatusCode, String)> {
        let f = policy::folder::load(&dir.join("run/model"))
            .map_err(|e| (StatusCode::CONFLICT, format!("it has no trained model yet ({e})")))?;
        policy::carpkg::pack(&f.model, &f.metadata)
            .map_err(|e| (StatusCode::UNPROCESSABLE_ENTITY, format!("it cannot go to a car: {e}")))
    })
    .await;
    match made {
        Ok(Ok(bytes)) => (
            [
                (header::CONTENT_TYPE, "application/gzip".to_string()),
                (header::CONTENT_DISPOSITION, format!("attachment; filename=\"physicalmodel-{name}.tar.gz\"")),
            ],
            bytes,
        )
            .into_response(),
        Ok(Err((code, e))) => error(code, &format!("model '{name}': {e}")),
        Err(e) => error(StatusCode::INTERNAL_SERVER_ERROR, &e.to_string()),
    }
}

/// `POST /api/v1/models/NAME/evaluations`: start an evaluation of the model's best model
/// (202 with its record; it runs in the background).
pub async fn start_evaluation(
    State(app): State<App>,
    axum::Extension(p): axum::Extension<crate::auth::Principal>,
    Path(name): Path<String>,
    body: Bytes,
) -> Response {
    let rec = match app.store.get(&name) {
        Ok(r) => r,
        Err(e) => return store_error(e),
    };
    let v = match json_body(&body) {
        Ok(v) => v,
        Err(f) => return invalid(&[f]),
    };
    // An evaluation spends minutes: some must be left, of the evaluator's and the instance's.
    if let Err(r) = crate::quota::check_off_thread(&app, &p, crate::quota::Ask::EVALUATION).await {
        return r.into_response();
    }
    let status = status_of(state_now(&app, &rec).await, &rec, &app.store);
    let model_dir = app.store.dir(&name).expect("a stored model's name is valid").join("run/model");
    if status == "training" || status == "stopping" || !model_dir.join("manifest.json").exists() {
        crate::counters::refused("evaluating a model that is not ready");
        return error(
            StatusCode::CONFLICT,
            &format!("model '{name}' is {status}: it can be evaluated once it is ready"),
        );
    }
    let now = protocol::job::now_unix();
    let id = format!("eval-{}", (now * 1000.0) as u64);
    let checked = match crate::evaluations::check(&v, &id, now) {
        Ok(c) => c,
        Err(e) => return invalid(&e),
    };
    let dir = match crate::evaluations::dir(&app.store, &name) {
        Ok(d) => d,
        Err(e) => return store_error(e),
    };
    if let Err(e) = crate::evaluations::save(&dir, &checked.record) {
        return error(StatusCode::INTERNAL_SERVER_ERROR, &format!("{}: {e}", dir.display()));
    }
    let record = checked.record.clone();
    app.running.lock().expect("running").insert(id.clone());
    let running = app.running.clone();
    tokio::task::spawn_blocking(move || {
        tracing::info!(model = %name, evaluation = %id, "evaluation started");
        crate::evaluations::run(&dir, &model_dir, checked);
        running.lock().expect("running").remove(&id);
        tracing::info!(model = %name, evaluation = %id, "evaluation done");
    });
    (StatusCode::ACCEPTED, axum::Json(record)).into_response()
}

/// `GET /api/v1/models/NAME/evaluations`: newest first.
pub async fn list_evaluations(State(app): State<App>, Path(name): Path<String>) -> Response {
    match app.store.get(&name).and_then(|r| crate::evaluations::dir(&app.store, &r.name)) {
        Ok(dir) => {
            let running = app.running.lock().expect("running").clone();
            axum::Json(crate::evaluations::list(&dir, &running)).into_response()
        }
        Err(e) => store_error(e),
    }
}

fn evaluation_of(app: &App, name: &str, id: &str) -> Result<(std::path::PathBuf, Value), Box<Response>> {
    let dir = app
        .store
        .get(name)
        .and_then(|r| crate::evaluations::dir(&app.store, &r.name))
        .map_err(|e| Box::new(store_error(e)))?;
    let v = crate::evaluations::get(&dir, id).ok_or_else(|| {
        crate::counters::refused("an unknown evaluation");
        Box::new(error(StatusCode::NOT_FOUND, &format!("model '{name}' has no evaluation '{id}'")))
    })?;
    Ok((dir, v))
}

/// `GET /api/v1/models/NAME/evaluations/ID`: its trials and its fastest lap's path.
pub async fn get_evaluation(State(app): State<App>, Path((name, id)): Path<(String, String)>) -> Response {
    match evaluation_of(&app, &name, &id) {
        Ok((_, v)) => axum::Json(v).into_response(),
        Err(r) => *r,
    }
}

/// `GET /api/v1/models/NAME/evaluations/ID/lap.svg`: the fastest lap, coloured by speed.
pub async fn evaluation_lap(State(app): State<App>, Path((name, id)): Path<(String, String)>) -> Response {
    let v = match evaluation_of(&app, &name, &id) {
        Ok((_, v)) => v,
        Err(r) => return *r,
    };
    let path: Vec<[f64; 3]> = serde_json::from_value(v["path"].clone()).unwrap_or_default();
    match tracks::world(v["track"].as_str().unwrap_or("")) {
        Ok(w) => ([(header::CONTENT_TYPE, "image/svg+xml")], crate::pictures::lap_svg(&w, &path, "speed (m/s)"))
            .into_response(),
        Err(e) => error(StatusCode::NOT_FOUND, &e.to_string()),
    }
}

/// `GET /api/v1/models/NAME/evaluations/ID/frames.png`: what the car saw in its first trial.
pub async fn evaluation_frames(State(app): State<App>, Path((name, id)): Path<(String, String)>) -> Response {
    let dir = match evaluation_of(&app, &name, &id) {
        Ok((d, _)) => d,
        Err(r) => return *r,
    };
    match std::fs::read(dir.join(format!("{id}-frames.png"))) {
        Ok(png) => ([(header::CONTENT_TYPE, "image/png")], png).into_response(),
        Err(_) => error(StatusCode::NOT_FOUND, "this evaluation kept no camera frames (camera models only)"),
    }
}

fn attachment(kind: &str, file: &str, bytes: Vec<u8>) -> Response {
    (
        [
            (header::CONTENT_TYPE, kind.to_string()),
            (header::CONTENT_DISPOSITION, format!("attachment; filename=\"{file}\"")),
        ],
        bytes,
    )
        .into_response()
}

/// `GET /api/v1/models/NAME/policy.onnx`: the best model's policy as ONNX.
pub async fn onnx(State(app): State<App>, Path(name): Path<String>) -> Response {
    let dir = match app.store.get(&name).and_then(|r| app.store.dir(&r.name)) {
        Ok(d) => d,
        Err(e) => return store_error(e),
    };
    let label = name.clone();
    let made = tokio::task::spawn_blocking(move || {
        policy::folder::load(&dir.join("run/model")).map(|f| coordinator::onnx::policy_to_onnx(&f.model, &label))
    })
    .await;
    match made {
        Ok(Ok(bytes)) => attachment("application/octet-stream", &format!("{name}.onnx"), bytes),
        Ok(Err(e)) => error(StatusCode::CONFLICT, &format!("model '{name}' has no trained model yet ({e})")),
        Err(e) => error(StatusCode::INTERNAL_SERVER_ERROR, &e.to_string()),
    }
}

/// `GET /api/v1/models/NAME/run.tar.gz`: the run folder (DeepRacer's metrics, sim-traces and
/// logs, the model), without its checkpoints, for the log-analysis notebooks.
pub async fn run_archive(State(app): State<App>, Path(name): Path<String>) -> Response {
    let dir = match app.store.get(&name).and_then(|r| app.store.dir(&r.name)) {
        Ok(d) => d.join("run"),
        Err(e) => return store_error(e),
    };
    if !dir.is_dir() {
        return error(StatusCode::CONFLICT, &format!("model '{name}' has no run folder yet"));
    }
    let label = name.clone();
    let made = tokio::task::spawn_blocking(move || -> std::io::Result<Vec<u8>> {
        let gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
        let mut tar = tar::Builder::new(gz);
        tar.follow_symlinks(false);
        let mut stack = vec![dir.clone()];
        while let Some(d) = stack.pop() {
            let mut entries: Vec<_> = std::fs::read_dir(&d)?.flatten().collect();
            entries.sort_by_key(|e| e.file_name());
            for e in entries {
                let p = e.path();
                let rel = p.strip_prefix(&dir).expect("under the run folder");
                let kind = e.file_type()?;
                if kind.is_dir() && rel.components().next().is_some_and(|c| c.as_os_str() != "checkpoints") {
                    stack.push(p);
                } else if kind.is_file() {
                    tar.append_path_with_name(&p, std::path::Path::new(&label).join(rel))?;
                }
            }
        }
        tar.into_inner()?.finish()
    })
    .await;
    match made {
        Ok(Ok(bytes)) => attachment("application/gzip", &format!("{name}-run.tar.gz"), bytes),
        Ok(Err(e)) => error(StatusCode::INTERNAL_SERVER_ERROR, &format!("packing the run folder: {e}")),
        Err(e) => error(StatusCode::INTERNAL_SERVER_ERROR, &e.to_string()),
    }
}

/// The largest car archive `POST /api/v1/models/import` takes.
pub const MAX_IMPORT: usize = 256 << 20;

/// `POST /api/v1/models/import?name=NAME[&description=TEXT]` with a car archive
/// (`physicalmodel-*.tar.gz`, DeepRacer's model.pb and model_metadata.json) as the body: a new
/// ready model, checked as `coordinator import` checks it.
pub async fn import(
    State(app): State<App>,
    axum::Extension(principal): axum::Extension<crate::auth::Principal>,
    axum::extract::Query(q): axum::extract::Query<std::collections::HashMap<String, String>>,
    body: Bytes,
) -> Response {
    let owner = principal.user.clone();
    let name = q.get("name").cloned().unwrap_or_default();
    let description = q.get("description").cloned().unwrap_or_default();
    let mut errors = Vec::new();
    if let Some(p) = crate::store::name_problem(&name) {
        errors.push(field("name", p));
    }
    if let Some(p) = crate::store::description_problem(&description) {
        errors.push(field("description", p));
    }
    if body.is_empty() {
        errors.push(field("body", "the car archive (a .tar.gz) is the request's body".into()));
    }
    if !errors.is_empty() {
        return invalid(&errors);
    }
    if app.store.get(&name).is_ok() {
        return store_error(StoreError::Taken(name));
    }
    if let Err(r) = crate::quota::check_off_thread(&app, &principal, crate::quota::Ask::IMPORT).await {
        return r.into_response();
    }
    let store = app.store.clone();
    let made = tokio::task::spawn_blocking(move || -> Result<ModelRecord, Created> {
        let origin = format!("the uploaded archive for '{name}'");
        let pkg =
            policy::carpkg::unpack(&body, &origin).map_err(|e| Created::Invalid(vec![field("body", e.to_string())]))?;
        let f = pkg.to_folder(&origin, 1).map_err(|e| Created::Invalid(vec![field("body", e.to_string())]))?;
        let record = ModelRecord {
            name: name.clone(),
            description,
            created: protocol::job::now_unix(),
            job_id: String::new(),
            tracks: Vec::new(),
            reversed: false,
            agents: None,
            owner: owner.clone(),
            algorithm: models::algorithm_name(f.metadata.training_algorithm).into(),
            sensors: f.metadata.sensor.iter().map(|s| s.name().to_string()).collect(),
            reward: String::new(),
            stop: toml::Table::new(),
            clone_of: None,
        };
        let files = crate::store::NewFiles {
            record: record.clone(),
            reward_source: None,
            model_metadata: pkg.metadata_text.clone(),
            hyperparameters: learner::Hyperparameters::default().to_json(),
        };
        store.create(&files, |tmp| -> Result<(), Created> {
            policy::folder::save(&tmp.join("run/model"), &f.metadata, &f.model, &f.manifest)
                .map(|_| ())
                .map_err(|e| Created::Store(StoreError::Io { path: "run/model".into(), msg: e.to_string() }))
        })?;
        Ok(record)
    })
    .await;
    match made {
        Ok(Ok(rec)) => {
            tracing::info!(model = %rec.name, "model imported from a car archive");
            (StatusCode::CREATED, axum::Json(model_json(&app, &rec, None))).into_response()
        }
        Ok(Err(Created::Store(e))) => store_error(e),
        Ok(Err(Created::Invalid(e))) => invalid(&e),
        Err(e) => error(StatusCode::INTERNAL_SERVER_ERROR, &e.to_string()),
    }
}

/// `GET /api/v1/openapi.json`.
pub async fn openapi() -> Response {
    ([(header::CONTENT_TYPE, "application/json")], crate::OPENAPI).into_response()
}
