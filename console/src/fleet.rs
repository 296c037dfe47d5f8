//! The fleet: every `deploy` car on the network (`GET /api/v1/cars`, the cars page) and an
//! organiser's orders to one (`POST /api/v1/cars/CAR`): drive a model (the car follows that
//! model's job from then on, and checks the model's signature as it checks every model), drive
//! a live race's current entry, hold or release the e-stop.

use crate::api::{App, error, invalid};
use crate::auth::Principal;
use crate::hub::CarOrder;
use crate::models::FieldError;
use crate::users::Role;
use axum::Extension;
use axum::body::Bytes;
use axum::extract::{Path, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use protocol::CarStatus;
use serde_json::{Value, json};

/// A car as the API shows it to `p`, with the console's model whose job it follows (a model
/// `p` may not see is not named).
pub fn car_json(app: &App, p: &Principal, c: &CarStatus) -> Value {
    let model = app
        .store
        .list()
        .into_iter()
        .find(|m| !c.job_id.is_empty() && m.job_id == c.job_id)
        .filter(|m| p.may_see(m.owner.as_deref()))
        .map(|m| m.name)
        // A live race's entry, driven on its own channel: the model entered.
        .or_else(|| app.races.find_entry(&c.job_id).map(|e| e.model));
    json!({
        "car": c.car_id, "job": c.job_id, "model": model, "follow": c.follow, "has_model": c.has_model,
        "policy_version": c.has_model.then_some(c.policy_version), "source": c.model_source, "key": c.model_key,
        "frames_per_s": c.frames_per_s, "inference_ms_p50": c.inference_ms_p50, "inference_ms_p99": c.inference_ms_p99,
        "latency_ms_p50": c.frame_to_command_ms_p50, "latency_ms_p99": c.frame_to_command_ms_p99,
        "refused": c.refused, "last_refusal": c.last_refusal, "state": c.watchdog, "frames": c.frames,
        "commands": c.commands, "swaps": c.swaps,
    })
}

/// `GET /api/v1/cars`: the cars heard from in the last seconds.
pub async fn list(State(app): State<App>, Extension(p): Extension<Principal>) -> Response {
    let cars = tokio::task::spawn_blocking(move || {
        app.hub.cars().iter().map(|c| car_json(&app, &p, c)).collect::<Vec<Value>>()
    })
    .await
    .unwrap_or_default();
    axum::Json(cars).into_response()
}

fn field(name: &str, message: impl Into<String>) -> Response {
    invalid(&[FieldError { field: name.into(), message: message.into(), line: None }])
}

/// A model folder as the car receives it: its job's PolicyUpdate (signed models only).
fn update(job: &str, dir: &std::path::Path, what: &str) -> Result<Vec<u8>, Box<Response>> {
    let parts = policy::ModelParts::read(dir).map_err(|e| {
        Box::new(error(StatusCode::CONFLICT, &format!("{what} has no model to drive ({}): {e}", dir.display())))
    })?;
    if parts.signature.is_none() {
        crate::counters::refused("assigning an unsigned model");
        return Err(Box::new(error(
            StatusCode::CONFLICT,
            &format!(
                "{what} is not signed, and cars drive only signed models: start the console with --signing-key \
                 (or --certs holding the cluster's models key) and train it again"
            ),
        )));
    }
    let version = serde_json::from_str::<policy::Manifest>(&parts.manifest_json).map(|m| m.policy_version).unwrap_or(0);
    Ok(protocol::encode(&protocol::exchange::parts_to_wire(job, version, &parts)))
}

/// `POST /api/v1/cars/CAR` (facilitator) with one of `{"model": NAME}`, `{"race": NAME}` (the
/// live race's entry racing now, or else the next), `{"estop": true|false}`.
pub async fn order(
    State(app): State<App>,
    Extension(p): Extension<Principal>,
    Path(car): Path<String>,
    body: Bytes,
) -> Response {
    if let Err(r) = p.require(Role::Facilitator, "driving the cars") {
        return r.into_response();
    }
    if !app.hub.cars().iter().any(|c| c.car_id == car) {
        crate::counters::refused("an unknown car");
        return error(StatusCode::NOT_FOUND, &format!("no car '{car}' on the network"));
    }
    let v: Value = match serde_json::from_slice(&body) {
        Ok(v) => v,
        Err(e) => return field("", format!("the body is not JSON: {e}")),
    };
    let keys: Vec<&String> = v.as_object().map(|o| o.keys().collect()).unwrap_or_default();
    if keys.len() != 1 || !["model", "race", "estop"].contains(&keys[0].as_str()) {
        return field("", "expected one of: {\"model\": NAME}, {\"race\": NAME}, {\"estop\": true|false}");
    }
    // Reading a model (and a live race's state) is file work: off the web server's threads.
    let (app2, p2) = (app.clone(), p.clone());
    let order = match tokio::task::spawn_blocking(move || build(&app2, &p2, &v)).await {
        Ok(Ok(o)) => o,
        Ok(Err(r)) => return *r,
        Err(e) => return error(StatusCode::INTERNAL_SERVER_ERROR, &e.to_string()),
    };
    let what = format!("{order:?}").split('(').next().unwrap_or("").to_string();
    match app.hub.order(&car, order).await {
        Ok(()) => {
            tracing::info!(car = %car, by = ?p.user, order = %what, "car ordered");
            (StatusCode::ACCEPTED, axum::Json(json!({"car": car, "sent": what.to_lowercase()}))).into_response()
        }
        Err(e) => error(StatusCode::BAD_GATEWAY, &format!("car '{car}': {e}")),
    }
}

/// What `v` (checked to have one of `model`, `race`, `estop`) tells the car.
fn build(app: &App, p: &Principal, v: &Value) -> Result<CarOrder, Box<Response>> {
    let bad = |name: &str, message: &str| Box::new(field(name, message));
    if let Some(hold) = v.get("estop") {
        return hold.as_bool().map(CarOrder::Estop).ok_or_else(|| bad("estop", "expected true or false"));
    }
    if let Some(name) = v.get("model") {
        let name = name.as_str().ok_or_else(|| bad("model", "expected a model's name"))?;
        let rec = match app.store.get(name) {
            Ok(r) if p.may_see(r.owner.as_deref()) => r,
            _ => {
                crate::counters::refused("an unknown model");
                return Err(Box::new(error(StatusCode::NOT_FOUND, &format!("no model named '{name}'"))));
            }
        };
        let dir = app.store.dir(&rec.name).expect("a stored model's name is valid").join("run/model");
        let bytes = update(&rec.job_id, &dir, &format!("model '{name}'"))?;
        return Ok(CarOrder::Assign(rec.job_id.clone(), bytes));
    }
    let name = v["race"].as_str().ok_or_else(|| bad("race", "expected a live race's name"))?;
    let race = match app.races.get(name) {
        Ok(r) if r.live() => r,
        _ => {
            crate::counters::refused("an unknown race");
            return Err(Box::new(error(StatusCode::NOT_FOUND, &format!("no live race named '{name}'"))));
        }
    };
    let snap = crate::live::snapshot(&app.races, &race, protocol::job::now_unix(), app.live_speed);
    let conflict = |m: String| Box::new(error(StatusCode::CONFLICT, &m));
    let entry = snap["current"]["entry"]
        .as_str()
        .or(snap["up_next"]["entry"].as_str())
        .ok_or_else(|| conflict(format!("race '{name}' has no entry racing or waiting")))?;
    let e = app.races.entry(name, entry).ok_or_else(|| conflict(format!("race '{name}' has no entry '{entry}'")))?;
    // The entry is driven as it was entered: on its own channel, which nothing else publishes
    // on (the model's job, if it still trains, would move the car on to newer versions).
    let dir =
        app.races.entry_model(name, entry).map_err(|err| Box::new(error(StatusCode::NOT_FOUND, &err.to_string())))?;
    let bytes = update(&e.id, &dir, &format!("{}'s entry '{}'", e.racer, e.model))?;
    Ok(CarOrder::Assign(e.id.clone(), bytes))
}
