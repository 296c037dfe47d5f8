//! Who may use the console. While the data folder has no users: whoever holds its secret
//! token, as Jupyter does. The token comes once in the address (`?token=…`, any page), is kept
//! in a cookie (HttpOnly, SameSite=Strict) and the address is cleaned of it; API clients send
//! `Authorization: Bearer TOKEN`. Once it has users ([`crate::users`]): a session, opened by a
//! login (`POST /api/v1/session`) that mints a new id every time (a session id planted before
//! the login is worth nothing), kept in memory by its hash, carried by a cookie or `Bearer`;
//! failed logins are limited per name and per address ([`Limiter`]). Without either: 401.
//! A request that changes something and rides on a cookie must also come from the console's
//! own pages (its `Origin` is the console's): a page elsewhere cannot make the browser act for
//! the user. Each request carries its [`Principal`], whose role the handlers check.

use crate::users::{Role, Users};
use axum::extract::{Request, State};
use axum::http::{HeaderMap, Method, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Redirect, Response};
use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// `s` with everything but letters, digits and `/-_.` percent-encoded (a path in a query).
fn url_encode(s: &str) -> String {
    s.bytes()
        .map(|b| {
            if b.is_ascii_alphanumeric() || b"/-_.".contains(&b) {
                (b as char).to_string()
            } else {
                format!("%{b:02X}")
            }
        })
        .collect()
}

/// The cookie's name.
pub const COOKIE: &str = "paddock_console";

/// A new secret: 32 random bytes as hex.
pub fn new_token() -> String {
    let bytes: [u8; 32] = rand::random();
    hex::encode(bytes)
}

/// Equal, in a time that does not depend on where they differ.
pub fn same(a: &str, b: &str) -> bool {
    a.len() == b.len() && a.bytes().zip(b.bytes()).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

/// How a request proved itself.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Proof {
    /// `Authorization: Bearer` (a program: no ambient credential to forge).
    Bearer,
    /// The cookie (a browser).
    Cookie,
}

/// The request's proof of the token, if it has one.
pub fn proof(headers: &HeaderMap, token: &str) -> Option<Proof> {
    if bearer(headers).is_some_and(|t| same(t, token)) {
        return Some(Proof::Bearer);
    }
    cookies(headers, COOKIE).any(|v| same(&v, token)).then_some(Proof::Cookie)
}

/// The credential of `Authorization: Bearer …`, if the request has one.
pub fn bearer(headers: &HeaderMap) -> Option<&str> {
    headers.get(header::AUTHORIZATION)?.to_str().ok()?.strip_prefix("Bearer ").map(str::trim)
}

/// The values of every cookie named `name` in the request.
fn cookies<'a>(headers: &'a HeaderMap, name: &'a str) -> impl Iterator<Item = String> + 'a {
    headers.get_all(header::COOKIE).iter().filter_map(|v| v.to_str().ok()).flat_map(move |c| {
        c.split(';')
            .filter_map(move |part| part.trim().split_once('=').filter(|(k, _)| *k == name).map(|(_, v)| v.to_string()))
    })
}

/// Whether a browser's request comes from the console's own pages: its `Origin` (or, without
/// one, `Sec-Fetch-Site`) says so.
pub fn same_origin(headers: &HeaderMap) -> bool {
    let host = headers.get(header::HOST).and_then(|v| v.to_str().ok()).unwrap_or("");
    match headers.get(header::ORIGIN).and_then(|v| v.to_str().ok()) {
        Some(origin) => {
            origin.strip_prefix("http://").or_else(|| origin.strip_prefix("https://")).is_some_and(|o| o == host)
        }
        None => headers
            .get("sec-fetch-site")
            .and_then(|v| v.to_str().ok())
            .is_some_and(|s| s == "same-origin" || s == "none"),
    }
}

/// The `?token=` of a query string, if any, and the query without it.
fn token_in_query(query: &str) -> Option<(String, String)> {
    let mut token = None;
    let mut rest = Vec::new();
    for pair in query.split('&').filter(|p| !p.is_empty()) {
        match pair.strip_prefix("token=") {
            Some(t) => token = Some(t.to_string()),
            None => rest.push(pair),
        }
    }
    token.map(|t| (t, rest.join("&")))
}

/// Sessions last this long without a request.
pub const SESSION_IDLE: Duration = Duration::from_secs(12 * 3600);

/// The session cookie's name (user mode).
pub const SESSION_COOKIE: &str = "paddock_session";

/// Who a request comes from, and what they may do.
#[derive(Clone, Debug, PartialEq)]
pub struct Principal {
    /// The user; none for the holder of the console's token (the console has no users).
    pub user: Option<String>,
    /// Their role (the token's holder is the admin).
    pub role: Role,
}

impl Principal {
    /// The holder of the console's token.
    pub fn owner() -> Principal {
        Principal { user: None, role: Role::Admin }
    }

    /// A refusal naming the role unless they have it (or a higher one).
    pub fn require(&self, role: Role, what: &str) -> Result<(), Forbidden> {
        if self.role >= role {
            return Ok(());
        }
        crate::counters::refused("a role too low");
        Err(Forbidden(format!("{what} needs the {} role", role.name())))
    }

    /// Whether they may see a model of `owner`: their own, or any as a facilitator or admin.
    pub fn may_see(&self, owner: Option<&str>) -> bool {
        self.role >= Role::Facilitator || (owner.is_some() && owner == self.user.as_deref())
    }

    /// Whether they may change a model of `owner`: their own, or any as an admin.
    pub fn may_change(&self, owner: Option<&str>) -> bool {
        self.role == Role::Admin || (owner.is_some() && owner == self.user.as_deref())
    }
}

/// A refusal: 403 with its reason.
#[derive(Debug)]
pub struct Forbidden(pub String);

impl IntoResponse for Forbidden {
    fn into_response(self) -> Response {
        crate::api::error(StatusCode::FORBIDDEN, &self.0)
    }
}

/// A session: its user and when it was last used.
struct Session {
    user: String,
    last: Instant,
}

/// Failed logins per user name and per client address, over a sliding window: past the limit a
/// login is refused (429) until the oldest failure leaves the window.
#[derive(Default)]
pub struct Limiter {
    failures: Mutex<HashMap<String, VecDeque<Instant>>>,
}

/// The window of [`Limiter`].
pub const LOGIN_WINDOW: Duration = Duration::from_secs(15 * 60);
/// Failed logins a user name may have in the window.
pub const FAILURES_PER_USER: usize = 5;
/// Failed logins a client address may have in the window.
pub const FAILURES_PER_ADDRESS: usize = 20;
/// The most names and addresses kept (a flood of new ones pushes out the oldest).
const LIMITER_KEYS: usize = 10_000;

impl Limiter {
    /// How long until a login under these (key, limit) pairs may be tried; none: now.
    pub fn wait(&self, keys: &[(String, usize)]) -> Option<Duration> {
        let now = Instant::now();
        let mut f = self.failures.lock().expect("limiter");
        keys.iter()
            .filter_map(|(k, limit)| {
                let q = f.get_mut(k)?;
                while q.front().is_some_and(|t| now.duration_since(*t) > LOGIN_WINDOW) {
                    q.pop_front();
                }
                (q.len() >= *limit).then(|| LOGIN_WINDOW.saturating_sub(now.duration_since(q[0])))
            })
            .max()
    }

    /// Count a failed login under each key.
    pub fn fail(&self, keys: &[(String, usize)]) {
        let now = Instant::now();
        let mut f = self.failures.lock().expect("limiter");
        if f.len() >= LIMITER_KEYS {
            f.retain(|_, q| q.back().is_some_and(|t| now.duration_since(*t) <= LOGIN_WINDOW));
            if f.len() >= LIMITER_KEYS {
                let oldest = f.iter().min_by_key(|(_, q)| q.back().copied()).map(|(k, _)| k.clone());
                if let Some(k) = oldest {
                    f.remove(&k);
                }
            }
        }
        for (k, _) in keys {
            f.entry(k.clone()).or_default().push_back(now);
        }
    }

    /// Forget a key's failures (a user who logged in).
    pub fn clear(&self, key: &str) {
        self.failures.lock().expect("limiter").remove(key);
    }
}

/// What the console checks requests against: its token, its users and their sessions, and
/// the login limiter.
pub struct Gate {
    /// The console's token (no users: it opens everything).
    pub token: String,
    /// The data folder's users.
    pub users: Users,
    sessions: Mutex<HashMap<String, Session>>,
    /// Failed logins.
    pub limiter: Limiter,
}

impl Gate {
    /// A gate with `token` and the users of `data`.
    pub fn new(token: String, users: Users) -> Gate {
        Gate { token, users, sessions: Mutex::new(HashMap::new()), limiter: Limiter::default() }
    }

    /// Whether the console asks for a login (it has users).
    pub fn logins(&self) -> bool {
        self.users.any()
    }

    /// A new session for `user`: its id (the cookie's value). Only its hash is kept.
    pub fn open_session(&self, user: &str) -> String {
        let id = new_token();
        let now = Instant::now();
        let mut s = self.sessions.lock().expect("sessions");
        s.retain(|_, v| now.duration_since(v.last) < SESSION_IDLE);
        s.insert(digest(&id), Session { user: user.into(), last: now });
        id
    }

    /// End the session `id`, if it is one.
    pub fn close_session(&self, id: &str) {
        self.sessions.lock().expect("sessions").remove(&digest(id));
    }

    /// The user of a live session `id` (its idle time starts again), while they exist.
    pub fn session_user(&self, id: &str) -> Option<crate::users::User> {
        let name = {
            let mut s = self.sessions.lock().expect("sessions");
            let key = digest(id);
            match s.get_mut(&key) {
                Some(v) if v.last.elapsed() < SESSION_IDLE => {
                    v.last = Instant::now();
                    v.user.clone()
                }
                Some(_) => {
                    s.remove(&key);
                    return None;
                }
                None => return None,
            }
        };
        self.users.get(&name).filter(|u| u.password.is_some())
    }
}

fn digest(id: &str) -> String {
    use sha2::Digest;
    hex::encode(sha2::Sha256::digest(id.as_bytes()))
}

/// A cookie's value in the request.
pub fn cookie(headers: &HeaderMap, name: &str) -> Option<String> {
    cookies(headers, name).next()
}

/// The session id a request carries: `Authorization: Bearer ID` (a program) or the cookie.
fn session_id(headers: &HeaderMap) -> Option<(String, Proof)> {
    if let Some(t) = bearer(headers) {
        return Some((t.to_string(), Proof::Bearer));
    }
    cookie(headers, SESSION_COOKIE).map(|c| (c, Proof::Cookie))
}

/// Routes open without a session: the login and invitation pages and their API.
fn open_route(method: &Method, path: &str) -> bool {
    path == "/login"
        || path.starts_with("/invite/")
        || (path == "/api/v1/session" && method == Method::POST)
        || (path == "/api/v1/invitations" && method == Method::POST)
}

/// The middleware: every route but the embedded assets goes through it. Without users, the
/// token opens the console (its holder is the admin); with users, a session does, and the
/// request carries its [`Principal`].
pub async fn guard(State(gate): State<Arc<Gate>>, mut req: Request, next: Next) -> Response {
    let uri = req.uri().clone();
    let unsafe_method = !matches!(*req.method(), Method::GET | Method::HEAD);
    if gate.logins() {
        if open_route(req.method(), uri.path()) {
            if unsafe_method && req.headers().contains_key(header::ORIGIN) && !same_origin(req.headers()) {
                return cross_origin();
            }
            return next.run(req).await;
        }
        if uri.query().and_then(token_in_query).is_some() {
            crate::counters::refused("a token where a login is needed");
            return unauthorized(uri.path(), true);
        }
        let Some((id, proof)) = session_id(req.headers()) else {
            crate::counters::refused("no session");
            return unauthorized(uri.path(), true);
        };
        let Some(user) = gate.session_user(&id) else {
            crate::counters::refused("an unknown session");
            return unauthorized(uri.path(), true);
        };
        if proof == Proof::Cookie && unsafe_method && !same_origin(req.headers()) {
            return cross_origin();
        }
        req.extensions_mut().insert(Principal { user: Some(user.name), role: user.role });
        return next.run(req).await;
    }
    let token = gate.token.as_str();
    if let Some((given, rest)) = uri.query().and_then(token_in_query) {
        if !same(&given, token) {
            crate::counters::refused("a wrong token");
            return unauthorized(uri.path(), false);
        }
        // Into the cookie, and out of the address bar and the history.
        let to = if rest.is_empty() { uri.path().to_string() } else { format!("{}?{rest}", uri.path()) };
        let cookie = format!("{COOKIE}={token}; Path=/; HttpOnly; SameSite=Strict");
        return ([(header::SET_COOKIE, cookie)], Redirect::to(&to)).into_response();
    }
    match proof(req.headers(), token) {
        None => {
            crate::counters::refused("no token");
            unauthorized(uri.path(), false)
        }
        Some(Proof::Cookie) if unsafe_method && !same_origin(req.headers()) => cross_origin(),
        Some(_) => {
            req.extensions_mut().insert(Principal::owner());
            next.run(req).await
        }
    }
}

fn cross_origin() -> Response {
    crate::counters::refused("a cross-origin request");
    crate::api::error(StatusCode::FORBIDDEN, "a request that changes something must come from the console's own pages")
}

fn unauthorized(path: &str, logins: bool) -> Response {
    if path.starts_with("/api/") {
        let mut r = crate::api::error(
            StatusCode::UNAUTHORIZED,
            if logins {
                "a login is needed: POST /api/v1/session with {\"user\", \"password\"}, then the session cookie (or Authorization: Bearer SESSION)"
            } else {
                "the console's token is needed: Authorization: Bearer TOKEN (the console printed it when it started)"
            },
        );
        r.headers_mut().insert(header::WWW_AUTHENTICATE, "Bearer".parse().expect("a header"));
        return r;
    }
    if logins {
        let next: String = url_encode(path);
        return Redirect::to(&format!("/login?next={next}")).into_response();
    }
    (
        StatusCode::UNAUTHORIZED,
        [(header::CONTENT_TYPE, "text/html; charset=utf-8")],
        "<!doctype html><title>Paddock console</title><p>Open the address the console printed when it started \
         (it ends in <code>?token=…</code>).</p>",
    )
        .into_response()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_token_is_found_in_the_query_and_the_rest_kept() {
        assert_eq!(token_in_query("token=abc"), Some(("abc".into(), String::new())));
        assert_eq!(token_in_query("a=1&token=abc&b=2"), Some(("abc".into(), "a=1&b=2".into())));
        assert_eq!(token_in_query("a=1"), None);
    }

    #[test]
    fn only_the_console_itself_is_the_same_origin() {
        let h = |pairs: &[(&'static str, &'static str)]| {
            let mut m = HeaderMap::new();
            for (k, v) in pairs {
                m.insert(*k, v.parse().unwrap());
            }
            m
        };
        assert!(same_origin(&h(&[("host", "127.0.0.1:8100"), ("origin", "http://127.0.0.1:8100")])));
        assert!(!same_origin(&h(&[("host", "127.0.0.1:8100"), ("origin", "http://evil.example")])));
        assert!(!same_origin(&h(&[("host", "127.0.0.1:8100"), ("origin", "null")])));
        assert!(same_origin(&h(&[("host", "127.0.0.1:8100"), ("sec-fetch-site", "same-origin")])));
        assert!(!same_origin(&h(&[("host", "127.0.0.1:8100"), ("sec-fetch-site", "cross-site")])));
        assert!(!same_origin(&h(&[("host", "127.0.0.1:8100")])), "no sign of where it came from");
        let t = "f".repeat(64);
        assert_eq!(proof(&h(&[("authorization", "Bearer ffff")]), &t), None);
        let mut ok = HeaderMap::new();
        ok.insert("cookie", format!("x=1; {COOKIE}={t}").parse().unwrap());
        assert_eq!(proof(&ok, &t), Some(Proof::Cookie));
    }
}
