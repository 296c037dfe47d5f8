//! The API of logins and users: `POST`/`GET`/`DELETE /api/v1/session`, `POST
//! /api/v1/invitations` (taking an invitation), and the admin's `/api/v1/users`. The same
//! [`crate::users::Users`] as `coordinator users …` (one code path for the CLI and the browser).

use crate::api::{App, error};
use crate::auth::{FAILURES_PER_ADDRESS, FAILURES_PER_USER, Principal, SESSION_COOKIE};
use crate::models::FieldError;
use crate::users::{Quota, Role, UsersError};
use axum::Extension;
use axum::body::Bytes;
use axum::extract::{ConnectInfo, Path, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde_json::{Value, json};
use std::net::SocketAddr;

/// How long an invitation made in the console lasts.
pub const INVITATION_TTL_S: f64 = 7.0 * 24.0 * 3600.0;

fn field(name: &str, message: impl Into<String>) -> FieldError {
    FieldError { field: name.into(), message: message.into(), line: None }
}

fn body_json(body: &Bytes) -> Option<serde_json::Map<String, Value>> {
    match serde_json::from_slice::<Value>(body) {
        Ok(Value::Object(m)) => Some(m),
        _ => None,
    }
}

fn not_an_object() -> Response {
    crate::api::invalid(&[field("", "expected a JSON object")])
}

fn text<'a>(m: &'a serde_json::Map<String, Value>, key: &str, errors: &mut Vec<FieldError>) -> &'a str {
    match m.get(key) {
        Some(Value::String(s)) => s,
        _ => {
            errors.push(field(key, "required: a string"));
            ""
        }
    }
}

/// A users error as an answer.
pub fn users_error(e: UsersError) -> Response {
    match e {
        UsersError::Invalid { field: f, message } => crate::api::invalid(&[field(&f, message)]),
        UsersError::NotFound(_) => {
            crate::counters::refused("an unknown user");
            error(StatusCode::NOT_FOUND, &e.to_string())
        }
        UsersError::Taken(_) | UsersError::LastAdmin(_) => error(StatusCode::CONFLICT, &e.to_string()),
        UsersError::File { .. } => error(StatusCode::INTERNAL_SERVER_ERROR, &e.to_string()),
    }
}

/// `POST /api/v1/session` `{"user", "password"}`: a new session (its cookie set; the id in the
/// body for programs), any session the request carried closed. Failed logins are limited per
/// name and per client address: past the limit, 429 with `Retry-After`.
pub async fn login(
    State(app): State<App>,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    headers: HeaderMap,
    body: Bytes,
) -> Response {
    if !app.gate.logins() {
        return crate::api::invalid(&[field(
            "user",
            "this console has no users: it opens with its token (coordinator users add NAME --role admin --data DIR makes the first)",
        )]);
    }
    let Some(m) = body_json(&body) else { return not_an_object() };
    let mut errors = Vec::new();
    let (user, password) = (text(&m, "user", &mut errors).to_string(), text(&m, "password", &mut errors).to_string());
    if !errors.is_empty() {
        return crate::api::invalid(&errors);
    }
    let keys = [(format!("user:{user}"), FAILURES_PER_USER), (format!("address:{}", peer.ip()), FAILURES_PER_ADDRESS)];
    if let Some(wait) = app.gate.limiter.wait(&keys) {
        crate::counters::refused("a login past the limit");
        let mut r = error(
            StatusCode::TOO_MANY_REQUESTS,
            &format!("too many failed logins: try again in {} s", wait.as_secs().max(1)),
        );
        r.headers_mut().insert(header::RETRY_AFTER, wait.as_secs().max(1).into());
        return r;
    }
    let gate = app.gate.clone();
    let checked = tokio::task::spawn_blocking(move || gate.users.verify(&user, &password)).await.ok().flatten();
    let Some(u) = checked else {
        app.gate.limiter.fail(&keys);
        crate::counters::refused("a failed login");
        tracing::warn!(%peer, "a failed login");
        return error(StatusCode::UNAUTHORIZED, "wrong user name or password");
    };
    app.gate.limiter.clear(&keys[0].0);
    // A session id the request already carried (planted or old) is closed: the new one is
    // minted here and nowhere else.
    if let Some(old) = crate::auth::cookie(&headers, SESSION_COOKIE) {
        app.gate.close_session(&old);
    }
    let id = app.gate.open_session(&u.name);
    tracing::info!(user = %u.name, %peer, "logged in");
    let secure = if app.https { "; Secure" } else { "" };
    let cookie = format!("{SESSION_COOKIE}={id}; Path=/; HttpOnly; SameSite=Strict{secure}");
    ([(header::SET_COOKIE, cookie)], axum::Json(json!({"user": u.name, "role": u.role.name(), "session": id})))
        .into_response()
}

/// `GET /api/v1/session`: who this is.
pub async fn whoami(Extension(p): Extension<Principal>) -> Response {
    axum::Json(json!({"user": p.user, "role": p.role.name()})).into_response()
}

/// `DELETE /api/v1/session`: log out (the session ends; the cookie is cleared).
pub async fn logout(State(app): State<App>, headers: HeaderMap) -> Response {
    if let Some(id) = crate::auth::cookie(&headers, SESSION_COOKIE) {
        app.gate.close_session(&id);
    }
    if let Some(id) = crate::auth::bearer(&headers) {
        app.gate.close_session(id);
    }
    let cookie = format!("{SESSION_COOKIE}=; Path=/; HttpOnly; SameSite=Strict; Max-Age=0");
    // htmx (the header's Log out) follows HX-Redirect.
    (
        [(header::SET_COOKIE, cookie), (header::HeaderName::from_static("hx-redirect"), "/login".into())],
        StatusCode::NO_CONTENT,
    )
        .into_response()
}

/// `POST /api/v1/invitations` `{"invitation", "password"}`: take an invitation.
pub async fn accept_invitation(State(app): State<App>, body: Bytes) -> Response {
    let Some(m) = body_json(&body) else { return not_an_object() };
    let mut errors = Vec::new();
    let (secret, password) =
        (text(&m, "invitation", &mut errors).to_string(), text(&m, "password", &mut errors).to_string());
    if !errors.is_empty() {
        return crate::api::invalid(&errors);
    }
    let gate = app.gate.clone();
    match tokio::task::spawn_blocking(move || gate.users.accept(&secret, &password)).await {
        Ok(Ok(name)) => {
            tracing::info!(user = %name, "invitation taken");
            axum::Json(json!({"user": name})).into_response()
        }
        Ok(Err(e)) => users_error(e),
        Err(e) => error(StatusCode::INTERNAL_SERVER_ERROR, &e.to_string()),
    }
}

/// `GET /api/v1/users` (admin).
pub async fn list_users(State(app): State<App>, Extension(p): Extension<Principal>) -> Response {
    if let Err(r) = p.require(Role::Admin, "managing users") {
        return r.into_response();
    }
    axum::Json(app.gate.users.list().iter().map(|u| u.to_json()).collect::<Vec<_>>()).into_response()
}

/// `POST /api/v1/users` `{"name", "role", "password"?}` (admin): a user with that password, or
/// without one an invitation, whose link the answer carries (`invitation`: `/invite/SECRET`).
pub async fn add_user(State(app): State<App>, Extension(p): Extension<Principal>, body: Bytes) -> Response {
    if let Err(r) = p.require(Role::Admin, "managing users") {
        return r.into_response();
    }
    let Some(m) = body_json(&body) else { return not_an_object() };
    let mut errors = Vec::new();
    for k in m.keys().filter(|k| !["name", "role", "password"].contains(&k.as_str())) {
        errors.push(field(k, "unknown field; expected name, role, password"));
    }
    let name = text(&m, "name", &mut errors).to_string();
    if let Some(e) = crate::users::name_problem(&name).filter(|_| !name.is_empty()) {
        errors.push(field("name", e));
    }
    let role = match Role::parse(m.get("role").and_then(Value::as_str).unwrap_or("racer")) {
        Ok(r) => r,
        Err(e) => {
            errors.push(field("role", e.to_string().trim_start_matches("role: ")));
            Role::Racer
        }
    };
    let password = match m.get("password") {
        None | Some(Value::Null) => None,
        Some(Value::String(s)) => {
            if let Some(e) = crate::users::password_problem(s) {
                errors.push(field("password", e));
            }
            Some(s.clone())
        }
        Some(_) => {
            errors.push(field("password", "a string"));
            None
        }
    };
    if !errors.is_empty() {
        return crate::api::invalid(&errors);
    }
    let gate = app.gate.clone();
    let made = tokio::task::spawn_blocking(move || match password {
        Some(pw) => gate.users.add(&name, role, &pw).map(|u| (u, None)),
        None => {
            let secret = gate.users.invite(&name, role, INVITATION_TTL_S)?;
            Ok((gate.users.get(&name).expect("just invited"), Some(format!("/invite/{secret}"))))
        }
    })
    .await;
    match made {
        Ok(Ok((u, invitation))) => {
            tracing::info!(user = %u.name, role = u.role.name(), by = ?p.user, "user added");
            let mut v = u.to_json();
            v["invitation"] = json!(invitation);
            (StatusCode::CREATED, axum::Json(v)).into_response()
        }
        Ok(Err(e)) => users_error(e),
        Err(e) => error(StatusCode::INTERNAL_SERVER_ERROR, &e.to_string()),
    }
}

/// `PATCH /api/v1/users/NAME` `{"role"?, "quota"?: {"models"?, "minutes"?}}` (admin).
pub async fn change_user(
    State(app): State<App>,
    Extension(p): Extension<Principal>,
    Path(name): Path<String>,
    body: Bytes,
) -> Response {
    if let Err(r) = p.require(Role::Admin, "managing users") {
        return r.into_response();
    }
    let Some(m) = body_json(&body) else { return not_an_object() };
    let mut errors = Vec::new();
    for k in m.keys().filter(|k| !["role", "quota"].contains(&k.as_str())) {
        errors.push(field(k, "unknown field; expected role, quota"));
    }
    let role = match m.get("role").map(|r| r.as_str().map(Role::parse)) {
        None => None,
        Some(Some(Ok(r))) => Some(r),
        _ => {
            errors.push(field("role", "admin, facilitator or racer"));
            None
        }
    };
    let quota = match m.get("quota") {
        None => None,
        Some(q) => match serde_json::from_value::<Quota>(q.clone()) {
            Ok(q) => Some(q),
            Err(e) => {
                errors.push(field("quota", format!("{{\"models\": N or null, \"minutes\": M or null}}: {e}")));
                None
            }
        },
    };
    if !errors.is_empty() {
        return crate::api::invalid(&errors);
    }
    let gate = app.gate.clone();
    let done = tokio::task::spawn_blocking(move || -> Result<Value, UsersError> {
        let mut u = gate.users.get(&name).ok_or_else(|| UsersError::NotFound(name.clone()))?;
        if let Some(r) = role {
            u = gate.users.set_role(&name, r)?;
        }
        if let Some(q) = quota {
            u = gate.users.set_quota(&name, q)?;
        }
        Ok(u.to_json())
    })
    .await;
    match done {
        Ok(Ok(v)) => axum::Json(v).into_response(),
        Ok(Err(e)) => users_error(e),
        Err(e) => error(StatusCode::INTERNAL_SERVER_ERROR, &e.to_string()),
    }
}

/// `DELETE /api/v1/users/NAME` (admin; not the last admin). Their models stay, shown to
/// facilitators and admins.
pub async fn remove_user(
    State(app): State<App>,
    Extension(p): Extension<Principal>,
    Path(name): Path<String>,
) -> Response {
    if let Err(r) = p.require(Role::Admin, "managing users") {
        return r.into_response();
    }
    match app.gate.users.remove(&name) {
        Ok(()) => {
            tracing::info!(user = %name, by = ?p.user, "user removed");
            StatusCode::NO_CONTENT.into_response()
        }
        Err(e) => users_error(e),
    }
}

fn usage_json(u: crate::quota::Usage) -> Value {
    json!({"models": u.models, "minutes": u.minutes})
}

/// `GET /api/v1/quota`: the requester's quota and what they use, and the instance's.
pub async fn quota(State(app): State<App>, Extension(p): Extension<Principal>) -> Response {
    let gate = app.gate.clone();
    let v = tokio::task::spawn_blocking(move || {
        let mine = p.user.as_deref().map(|u| {
            let quota = gate.users.get(u).map(|x| x.quota).unwrap_or_default();
            json!({"user": u, "quota": quota, "used": usage_json(crate::quota::usage(&app, Some(u)))})
        });
        json!({"user": mine, "instance": {"quota": gate.users.instance_quota(),
               "used": usage_json(crate::quota::usage(&app, None))}})
    })
    .await;
    match v {
        Ok(v) => axum::Json(v).into_response(),
        Err(e) => error(StatusCode::INTERNAL_SERVER_ERROR, &e.to_string()),
    }
}

/// `PUT /api/v1/quota` `{"models": N | null, "minutes": M | null}` (admin): the instance's
/// quota (null: no limit).
pub async fn set_instance_quota(State(app): State<App>, Extension(p): Extension<Principal>, body: Bytes) -> Response {
    if let Err(r) = p.require(Role::Admin, "setting the instance's quota") {
        return r.into_response();
    }
    let q: Quota = match serde_json::from_slice(&body) {
        Ok(q) => q,
        Err(e) => {
            return crate::api::invalid(&[field(
                "",
                format!("{{\"models\": N or null, \"minutes\": M or null}}: {e}"),
            )]);
        }
    };
    match app.gate.users.set_instance_quota(q) {
        Ok(q) => axum::Json(json!(q)).into_response(),
        Err(e) => users_error(e),
    }
}
