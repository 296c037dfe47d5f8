//! The races' API (`/api/v1/races…`): facilitators make, change and remove races; racers
//! enter their ready models while a race is open; everyone reads the races and their
//! leaderboards. Entries are evaluated in the background, at most `App::race_slots` at once,
//! and those a stop interrupted are run again at the next start ([`resume`]).

use crate::api::{App, error, invalid, status_of};
use crate::auth::Principal;
use crate::quota::Ask;
use crate::races::{Entry, EntryStatus, Race, RaceError, clock, leaderboard};
use crate::users::Role;
use axum::Extension;
use axum::body::Bytes;
use axum::extract::{Path, State};
use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};
use protocol::job::now_unix;
use serde_json::{Value, json};

fn race_error(e: RaceError) -> Response {
    match e {
        RaceError::NotFound(_) => {
            crate::counters::refused("an unknown race");
            error(StatusCode::NOT_FOUND, &e.to_string())
        }
        RaceError::Taken(_) => {
            crate::counters::refused("a race name taken");
            error(StatusCode::CONFLICT, &e.to_string())
        }
        RaceError::Io { .. } => {
            tracing::error!("{e}");
            error(StatusCode::INTERNAL_SERVER_ERROR, &e.to_string())
        }
    }
}

fn body_json(body: &Bytes) -> Result<Value, Box<Response>> {
    serde_json::from_slice(body).map_err(|e| {
        Box::new(invalid(&[crate::models::FieldError {
            field: String::new(),
            message: format!("the body is not JSON: {e}"),
            line: None,
        }]))
    })
}

/// The leaderboard as the API and the pages show it.
pub fn board_json(race: &Race, entries: &[Entry]) -> Vec<Value> {
    leaderboard(race, entries)
        .into_iter()
        .map(|r| {
            let mut v = serde_json::to_value(&r).expect("a row is JSON");
            v["time"] = json!(clock(r.time_ms));
            v["gap"] = json!(if r.rank == 1 { "-".to_string() } else { format!("+{}", clock(r.gap_ms)) });
            v
        })
        .collect()
}

/// The entries a race ranks at `now`: every one of a community race; a live race's shown to
/// their end since its leaderboard was cleared.
pub fn ranked(app: &App, race: &Race, entries: &[Entry], now: f64) -> Vec<Entry> {
    if race.live() {
        crate::live::ranked_entries(&app.races.live(&race.name), entries, now, app.live_speed)
    } else {
        entries.to_vec()
    }
}

/// A race with its count of entries and its leader.
pub fn summary(app: &App, race: &Race, now: f64) -> Value {
    let entries = app.races.entries(&race.name);
    let mut v = race.to_json(now);
    v["entries"] = json!(entries.len());
    v["leader"] = board_json(race, &ranked(app, race, &entries, now)).into_iter().next().unwrap_or(Value::Null);
    if race.live() {
        let s = app.races.live(&race.name);
        v["phase"] = json!(s.phase);
        v["submissions_open"] = json!(s.submissions_open);
    }
    v
}

/// `GET /api/v1/races`: every race, the latest to close first.
pub async fn list(State(app): State<App>) -> Response {
    off_thread(move || {
        let now = now_unix();
        let out: Vec<Value> = app.races.list().iter().map(|r| summary(&app, r, now)).collect();
        axum::Json(out).into_response()
    })
    .await
}

/// A handler's file work on a blocking thread (the pages poll these).
async fn off_thread(f: impl FnOnce() -> Response + Send + 'static) -> Response {
    tokio::task::spawn_blocking(f).await.unwrap_or_else(|e| error(StatusCode::INTERNAL_SERVER_ERROR, &e.to_string()))
}

/// `POST /api/v1/races` (facilitator): make a race (201).
pub async fn create(State(app): State<App>, Extension(p): Extension<Principal>, body: Bytes) -> Response {
    if let Err(r) = p.require(Role::Facilitator, "making a race") {
        return r.into_response();
    }
    let v = match body_json(&body) {
        Ok(v) => v,
        Err(r) => return *r,
    };
    let race = match crate::races::check(&v, None, now_unix(), p.user.as_deref()) {
        Ok(r) => r,
        Err(e) => return invalid(&e),
    };
    if let Err(e) = app.races.create(&race) {
        return race_error(e);
    }
    tracing::info!(race = %race.name, by = ?p.user, "race made");
    (StatusCode::CREATED, axum::Json(summary(&app, &race, now_unix()))).into_response()
}

/// `GET /api/v1/races/RACE`.
pub async fn get(State(app): State<App>, Path(name): Path<String>) -> Response {
    match app.races.get(&name) {
        Ok(r) => axum::Json(summary(&app, &r, now_unix())).into_response(),
        Err(e) => race_error(e),
    }
}

/// `PATCH /api/v1/races/RACE` (facilitator): change a race before it opens.
pub async fn change(
    State(app): State<App>,
    Extension(p): Extension<Principal>,
    Path(name): Path<String>,
    body: Bytes,
) -> Response {
    if let Err(r) = p.require(Role::Facilitator, "changing a race") {
        return r.into_response();
    }
    let base = match app.races.get(&name) {
        Ok(r) => r,
        Err(e) => return race_error(e),
    };
    let now = now_unix();
    if base.status(now) != "upcoming" {
        crate::counters::refused("changing a race that has opened");
        return error(
            StatusCode::CONFLICT,
            &format!("race '{name}' is {}: a race can be changed until it opens", base.status(now)),
        );
    }
    let v = match body_json(&body) {
        Ok(v) => v,
        Err(r) => return *r,
    };
    let race = match crate::races::check(&v, Some(&base), now, None) {
        Ok(r) => r,
        Err(e) => return invalid(&e),
    };
    if let Err(e) = app.races.save(&race) {
        return race_error(e);
    }
    axum::Json(summary(&app, &race, now)).into_response()
}

/// `DELETE /api/v1/races/RACE` (facilitator): remove a race that is not open, with its entries.
pub async fn remove(State(app): State<App>, Extension(p): Extension<Principal>, Path(name): Path<String>) -> Response {
    if let Err(r) = p.require(Role::Facilitator, "removing a race") {
        return r.into_response();
    }
    let race = match app.races.get(&name) {
        Ok(r) => r,
        Err(e) => return race_error(e),
    };
    if race.status(now_unix()) == "open" {
        crate::counters::refused("removing an open race");
        return error(StatusCode::CONFLICT, &format!("race '{name}' is open: it can be removed once it has closed"));
    }
    if app.races.entries(&name).iter().any(|e| matches!(e.status, EntryStatus::Queued | EntryStatus::Running)) {
        crate::counters::refused("removing a race being evaluated");
        return error(StatusCode::CONFLICT, &format!("race '{name}' has entries being evaluated: wait for them"));
    }
    match app.races.delete(&name) {
        Ok(()) => StatusCode::NO_CONTENT.into_response(),
        Err(e) => race_error(e),
    }
}

/// `GET /api/v1/races/RACE/leaderboard`: one row per racer, fastest first.
pub async fn board(State(app): State<App>, Path(name): Path<String>) -> Response {
    off_thread(move || board_now(&app, &name)).await
}

fn board_now(app: &App, name: &str) -> Response {
    match app.races.get(name) {
        Ok(r) => {
            let entries = app.races.entries(name);
            let running =
                entries.iter().filter(|e| matches!(e.status, EntryStatus::Queued | EntryStatus::Running)).count();
            let rows = board_json(&r, &ranked(app, &r, &entries, now_unix()));
            axum::Json(json!({"race": name, "ranking": r.ranking.name(), "evaluating": running, "rows": rows}))
                .into_response()
        }
        Err(e) => race_error(e),
    }
}

/// Whether `p` may see `e`'s details: their own (their model's), or any as a facilitator.
fn may_see_entry(p: &Principal, e: &Entry) -> bool {
    p.role >= Role::Facilitator || p.user.as_deref() == Some(e.racer.as_str())
}

/// `GET /api/v1/races/RACE/entries`: the requester's entries (a facilitator's: every one),
/// oldest first.
pub async fn entries(State(app): State<App>, Extension(p): Extension<Principal>, Path(name): Path<String>) -> Response {
    off_thread(move || {
        let race = match app.races.get(&name) {
            Ok(r) => r,
            Err(e) => return race_error(e),
        };
        let out: Vec<Value> =
            app.races.entries(&name).iter().filter(|e| may_see_entry(&p, e)).map(|e| e.to_json(&race)).collect();
        axum::Json(out).into_response()
    })
    .await
}

fn entry_of(app: &App, p: &Principal, race: &str, id: &str) -> Result<(Race, Entry), Box<Response>> {
    let r = app.races.get(race).map_err(|e| Box::new(race_error(e)))?;
    let e = app.races.entry(race, id).ok_or_else(|| {
        crate::counters::refused("an unknown entry");
        Box::new(error(StatusCode::NOT_FOUND, &format!("race '{race}' has no entry '{id}'")))
    })?;
    // An entry on the leaderboard is everyone's to see; others are their racer's.
    let entries = app.races.entries(race);
    let shown = leaderboard(&r, &ranked(app, &r, &entries, now_unix())).iter().any(|row| row.entry == e.id);
    if !shown && !may_see_entry(p, &e) {
        crate::counters::refused("another racer's entry");
        return Err(Box::new(error(
            StatusCode::FORBIDDEN,
            "another racer's entry: seeing it needs the facilitator role",
        )));
    }
    Ok((r, e))
}

/// `GET /api/v1/races/RACE/entries/ID`: an entry with its laps.
pub async fn entry(
    State(app): State<App>,
    Extension(p): Extension<Principal>,
    Path((race, id)): Path<(String, String)>,
) -> Response {
    match entry_of(&app, &p, &race, &id) {
        Ok((r, e)) => axum::Json(e.to_json(&r)).into_response(),
        Err(r) => *r,
    }
}

/// `GET /api/v1/races/RACE/entries/ID/lap.svg`: the entry's fastest lap on the track,
/// coloured by speed.
pub async fn lap(
    State(app): State<App>,
    Extension(p): Extension<Principal>,
    Path((race, id)): Path<(String, String)>,
) -> Response {
    let (r, e) = match entry_of(&app, &p, &race, &id) {
        Ok(x) => x,
        Err(r) => return *r,
    };
    match tracks::world(&r.track) {
        Ok(w) => ([(header::CONTENT_TYPE, "image/svg+xml")], crate::pictures::lap_svg(&w, &e.path, "speed (m/s)"))
            .into_response(),
        Err(e) => error(StatusCode::NOT_FOUND, &e.to_string()),
    }
}

static NEXT: std::sync::atomic::AtomicU64 = std::sync::atomic::AtomicU64::new(0);

/// `POST /api/v1/races/RACE/entries` with `{"model"}`: enter a ready model of one's own while
/// the race is open (202; it is evaluated in the background). Counted against the racer's
/// submissions to the race and the minutes of their quota and the instance's.
pub async fn enter(
    State(app): State<App>,
    Extension(p): Extension<Principal>,
    Path(name): Path<String>,
    body: Bytes,
) -> Response {
    let race = match app.races.get(&name) {
        Ok(r) => r,
        Err(e) => return race_error(e),
    };
    let now = now_unix();
    if race.live() {
        let s = app.races.live(&name);
        if s.phase == crate::live::Phase::Completed || !s.submissions_open {
            crate::counters::refused("an entry outside the race's window");
            return error(StatusCode::CONFLICT, &format!("race '{name}': submissions are closed"));
        }
    } else if race.status(now) != "open" {
        crate::counters::refused("an entry outside the race's window");
        return error(
            StatusCode::CONFLICT,
            &format!("race '{name}' is {}: it takes entries while it is open", race.status(now)),
        );
    }
    let v = match body_json(&body) {
        Ok(v) => v,
        Err(r) => return *r,
    };
    let Some(model) = v.get("model").and_then(Value::as_str) else {
        return invalid(&[crate::models::FieldError {
            field: "model".into(),
            message: "required: the name of one of your ready models".into(),
            line: None,
        }]);
    };
    if let Some(k) = v.as_object().and_then(|o| o.keys().find(|k| *k != "model")) {
        return invalid(&[crate::models::FieldError {
            field: k.clone(),
            message: "unknown field; expected model".into(),
            line: None,
        }]);
    }
    let rec = match app.store.get(model) {
        Ok(r) if p.may_see(r.owner.as_deref()) => r,
        _ => {
            crate::counters::refused("an unknown model");
            return error(StatusCode::NOT_FOUND, &format!("no model named '{model}'"));
        }
    };
    if !p.may_change(rec.owner.as_deref()) {
        crate::counters::refused("another user's model");
        return error(
            StatusCode::FORBIDDEN,
            &format!("model '{model}' is another user's: entering it needs the admin role"),
        );
    }
    let state = crate::api::state_now(&app, &rec).await;
    let status = status_of(state, &rec, &app.store);
    let model_dir = app.store.dir(&rec.name).expect("a stored model's name is valid").join("run/model");
    if status == "training" || status == "stopping" || !model_dir.join("manifest.json").exists() {
        crate::counters::refused("entering a model that is not ready");
        return error(StatusCode::CONFLICT, &format!("model '{model}' is {status}: it can race once it is ready"));
    }
    if let Err(r) = crate::quota::check_off_thread(&app, &p, Ask::EVALUATION).await {
        return r.into_response();
    }
    let racer = rec.owner.clone().or_else(|| p.user.clone()).unwrap_or_else(|| rec.name.clone());
    let n = NEXT.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
    let entry = Entry {
        id: format!("entry-{}-{n}", (now * 1000.0) as u64),
        racer,
        model: rec.name.clone(),
        policy_version: None,
        created: now,
        finished: None,
        status: EntryStatus::Queued,
        error: None,
        laps: vec![],
        path: vec![],
        launched: None,
        resets: 0,
        replay_s: None,
        started: None,
        spent_s: 0.0,
    };
    let races = app.races.clone();
    let (r2, e2) = (race.clone(), entry.clone());
    let entered = tokio::task::spawn_blocking(move || races.enter(&r2, &e2, &model_dir)).await;
    match entered {
        Ok(Ok(())) => {}
        Ok(Err(Ok(why))) => {
            crate::counters::refused("a racer's submissions spent");
            return error(StatusCode::FORBIDDEN, &why);
        }
        Ok(Err(Err(e))) => return race_error(e),
        Err(e) => return error(StatusCode::INTERNAL_SERVER_ERROR, &e.to_string()),
    }
    tracing::info!(race = %name, entry = %entry.id, model = %entry.model, racer = %entry.racer, "entry made");
    start(&app, race.clone(), entry.clone());
    (StatusCode::ACCEPTED, axum::Json(entry.to_json(&race))).into_response()
}

/// Evaluate `entry` once one of the console's race slots is free.
fn start(app: &App, race: Race, entry: Entry) {
    let (races, slots) = (app.races.clone(), app.race_slots.clone());
    tokio::spawn(async move {
        let Ok(_permit) = slots.acquire_owned().await else { return };
        let id = entry.id.clone();
        let done = tokio::task::spawn_blocking(move || crate::races::evaluate(&races, &race, entry)).await;
        if let Err(e) = done {
            tracing::error!(entry = %id, "the entry's evaluation panicked: {e}");
        }
    });
}

/// Run again the entries a stop left queued or running (in the order they were made).
pub fn resume(app: &App) {
    for (race, entry) in app.races.unfinished() {
        match app.races.get(&race) {
            Ok(r) => {
                tracing::info!(race = %race, entry = %entry.id, "an interrupted entry is evaluated again");
                start(app, r, entry);
            }
            Err(e) => tracing::warn!("{e}"),
        }
    }
}

/// `GET /api/v1/races/RACE/live`: a live race as every viewer sees it now.
pub async fn live(State(app): State<App>, Path(name): Path<String>) -> Response {
    match app.races.get(&name) {
        Ok(r) if r.live() => {
            let (races, speed) = (app.races.clone(), app.live_speed);
            let snap = tokio::task::spawn_blocking(move || crate::live::snapshot(&races, &r, now_unix(), speed)).await;
            match snap {
                Ok(v) => axum::Json(v).into_response(),
                Err(e) => error(StatusCode::INTERNAL_SERVER_ERROR, &e.to_string()),
            }
        }
        Ok(_) => not_live(&name),
        Err(e) => race_error(e),
    }
}

fn not_live(name: &str) -> Response {
    crate::counters::refused("a live race's route on a community race");
    error(StatusCode::NOT_FOUND, &format!("race '{name}' is a community race, not a live one"))
}

/// `POST /api/v1/races/RACE/live` (facilitator) with `{"action", …}`: launch, autolaunch,
/// submissions, move, remove, reset, clear, winner. Answers the race as viewers see it.
pub async fn live_action(
    State(app): State<App>,
    Extension(p): Extension<Principal>,
    Path(name): Path<String>,
    body: Bytes,
) -> Response {
    if let Err(r) = p.require(Role::Facilitator, "running a live race") {
        return r.into_response();
    }
    let race = match app.races.get(&name) {
        Ok(r) if r.live() => r,
        Ok(_) => return not_live(&name),
        Err(e) => return race_error(e),
    };
    let v = match body_json(&body) {
        Ok(v) => v,
        Err(r) => return *r,
    };
    let action = match crate::live::Action::parse(&v) {
        Ok(a) => a,
        Err(why) => {
            return invalid(&[crate::models::FieldError { field: "action".into(), message: why, line: None }]);
        }
    };
    let (races, speed, r2) = (app.races.clone(), app.live_speed, race.clone());
    let done = tokio::task::spawn_blocking(move || races.act(&r2, &action, now_unix(), speed)).await;
    match done {
        Ok(Ok(Ok(after))) => {
            for e in after.evaluate {
                start(&app, race.clone(), e);
            }
            tracing::info!(race = %name, by = ?p.user, action = %v["action"], "live race action");
            let (races, speed) = (app.races.clone(), app.live_speed);
            let snap =
                tokio::task::spawn_blocking(move || crate::live::snapshot(&races, &race, now_unix(), speed)).await;
            axum::Json(snap.unwrap_or(Value::Null)).into_response()
        }
        Ok(Ok(Err(crate::live::Refused(why)))) => {
            crate::counters::refused("a live race action out of turn");
            error(StatusCode::CONFLICT, &why)
        }
        Ok(Err(e)) => race_error(e),
        Err(e) => error(StatusCode::INTERNAL_SERVER_ERROR, &e.to_string()),
    }
}

/// `GET /api/v1/races/RACE/live/camera.png`: what the racing car sees now (camera models).
pub async fn live_camera(State(app): State<App>, Path(name): Path<String>) -> Response {
    let race = match app.races.get(&name) {
        Ok(r) if r.live() => r,
        Ok(_) => return not_live(&name),
        Err(e) => return race_error(e),
    };
    let (races, speed) = (app.races.clone(), app.live_speed);
    let png = tokio::task::spawn_blocking(move || {
        let now = now_unix();
        let entries = races.entries(&race.name);
        let (e, start) = entries.iter().find_map(|e| match crate::live::shown(e, now, speed) {
            crate::live::Shown::Racing { start } => Some((e, start)),
            _ => None,
        })?;
        let replay = races.replay(&race.name, &e.id)?;
        let frame = replay.at((now - start) * speed)?.frame?;
        replay.frame_png(&races.frames_file(&race.name, &e.id).ok()?, frame)
    })
    .await
    .ok()
    .flatten();
    match png {
        Some(png) => ([(header::CONTENT_TYPE, "image/png"), (header::CACHE_CONTROL, "no-store")], png).into_response(),
        None => error(StatusCode::NOT_FOUND, "no camera now: no car is racing, or it has no camera"),
    }
}

/// Launch live races' next entries (autolaunch) every half second while the console serves.
pub fn tick(app: &App) {
    let (races, speed) = (app.races.clone(), app.live_speed);
    tokio::spawn(async move {
        loop {
            tokio::time::sleep(std::time::Duration::from_millis(500)).await;
            let r = races.clone();
            let _ = tokio::task::spawn_blocking(move || r.autolaunch(now_unix(), speed)).await;
        }
    });
}
