//! Who may use the console: whoever holds its secret token, as Jupyter does. The token comes
//! once in the address (`?token=…`, any page), is kept in a cookie (HttpOnly, SameSite=Strict)
//! and the address is cleaned of it; API clients send `Authorization: Bearer TOKEN`.
//! Without it: 401. A request that changes something and rides on the cookie must also come
//! from the console's own pages (its `Origin` is the console's): a page elsewhere cannot make
//! the browser act for the user.

use axum::extract::{Request, State};
use axum::http::{HeaderMap, Method, StatusCode, header};
use axum::middleware::Next;
use axum::response::{IntoResponse, Redirect, Response};

/// The cookie's name.
pub const COOKIE: &str = "paddock_console";

/// A new secret: 32 random bytes as hex.
pub fn new_token() -> String {
    let bytes: [u8; 32] = rand::random();
    hex::encode(bytes)
}

/// Equal, in a time that does not depend on where they differ.
fn same(a: &str, b: &str) -> bool {
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
    if let Some(v) = headers.get(header::AUTHORIZATION).and_then(|v| v.to_str().ok())
        && let Some(t) = v.strip_prefix("Bearer ")
        && same(t.trim(), token)
    {
        return Some(Proof::Bearer);
    }
    let cookies = headers.get_all(header::COOKIE);
    for c in cookies.iter().filter_map(|v| v.to_str().ok()) {
        for part in c.split(';') {
            if let Some((k, v)) = part.trim().split_once('=')
                && k == COOKIE
                && same(v, token)
            {
                return Some(Proof::Cookie);
            }
        }
    }
    None
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

/// The middleware: every route but the embedded assets goes through it.
pub async fn guard(State(token): State<std::sync::Arc<String>>, req: Request, next: Next) -> Response {
    let uri = req.uri().clone();
    if let Some((given, rest)) = uri.query().and_then(token_in_query) {
        if !same(&given, &token) {
            crate::counters::refused("a wrong token");
            return unauthorized(uri.path());
        }
        // Into the cookie, and out of the address bar and the history.
        let to = if rest.is_empty() { uri.path().to_string() } else { format!("{}?{rest}", uri.path()) };
        let cookie = format!("{COOKIE}={token}; Path=/; HttpOnly; SameSite=Strict");
        return ([(header::SET_COOKIE, cookie)], Redirect::to(&to)).into_response();
    }
    match proof(req.headers(), &token) {
        None => {
            crate::counters::refused("no token");
            unauthorized(uri.path())
        }
        Some(Proof::Cookie) if !matches!(*req.method(), Method::GET | Method::HEAD) && !same_origin(req.headers()) => {
            crate::counters::refused("a cross-origin request");
            crate::api::error(
                StatusCode::FORBIDDEN,
                "a request that changes something must come from the console's own pages",
            )
        }
        Some(_) => next.run(req).await,
    }
}

fn unauthorized(path: &str) -> Response {
    if path.starts_with("/api/") {
        let mut r = crate::api::error(
            StatusCode::UNAUTHORIZED,
            "the console's token is needed: Authorization: Bearer TOKEN (the console printed it when it started)",
        );
        r.headers_mut().insert(header::WWW_AUTHENTICATE, "Bearer".parse().expect("a header"));
        return r;
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
