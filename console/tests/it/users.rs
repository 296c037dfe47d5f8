//! Issue 52: the console with users. The CLI (`coordinator users`, which runs `console users`)
//! makes them in the data folder; the console then asks for a login, keeps each racer to their
//! own models, each role to its rights, each quota on every path that spends it, and refuses
//! (and counts) a planted session, a cross-origin post, a login flood.

use crate::support::{Console, Reply, TOKEN, bin, http, state_metadata, wait_for};
use serde_json::json;
use std::path::Path;
use std::process::Command;

const ADA: &str = "Admin-pass-1";
const RITA: &str = "Racer-pass-1";

fn users(data: &Path, args: &[&str]) -> std::process::Output {
    Command::new(bin("coordinator")).arg("users").args(args).arg("--data").arg(data).output().unwrap()
}

fn add(data: &Path, dir: &Path, name: &str, role: &str, password: &str) {
    let f = dir.join(format!("{name}.pw"));
    std::fs::write(&f, format!("{password}\n")).unwrap();
    let o = users(data, &["add", name, "--role", role, "--password-file", f.to_str().unwrap()]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

/// A logged-in user's requests: the session cookie, and the console's own Origin on those that
/// change something (as the console's pages send them).
struct As<'a> {
    c: &'a Console,
    cookie: String,
}

impl As<'_> {
    fn call(&self, method: &str, path: &str, body: Option<serde_json::Value>) -> Reply {
        let origin = format!("http://{}", self.c.addr);
        let body = body.map(|b| b.to_string());
        http(
            &self.c.addr,
            method,
            path,
            &[("Cookie", &self.cookie), ("Origin", &origin), ("Content-Type", "application/json")],
            body.as_deref().map(str::as_bytes),
        )
    }
}

fn login<'a>(c: &'a Console, user: &str, password: &str, extra: &[(&str, &str)]) -> (Reply, Option<As<'a>>) {
    let body = json!({"user": user, "password": password}).to_string();
    let mut headers = vec![("Content-Type", "application/json")];
    headers.extend_from_slice(extra);
    let r = http(&c.addr, "POST", "/api/v1/session", &headers, Some(body.as_bytes()));
    let cookie = r.header("set-cookie").filter(|_| r.code == 200).map(|s| s.split(';').next().unwrap().to_string());
    let who = cookie.map(|cookie| As { c, cookie });
    (r, who)
}

fn new_model(name: &str, minutes: f64) -> serde_json::Value {
    json!({"name": name, "tracks": ["reinvent_base"], "reward_function": "builtin:center_line",
           "model_metadata": state_metadata(), "stop": {"minutes": minutes}})
}

/// Issue 52: users log in; a racer sees and changes only their own models, a facilitator sees
/// every model but changes none of others', an admin manages users and quotas; each quota is
/// refused on every path that spends it; a planted session, a cross-origin post and a login
/// flood are refused and counted.
#[test]
fn users_log_in_and_do_only_what_their_role_and_quota_allow() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    std::fs::create_dir_all(&data).unwrap();
    add(&data, dir.path(), "ada", "admin", ADA);
    add(&data, dir.path(), "rita", "racer", RITA);
    add(&data, dir.path(), "rex", "racer", RITA);
    add(&data, dir.path(), "fay", "facilitator", RITA);
    let c = Console::start(&data);

    // The token no longer opens the console; a page sends to the login.
    assert_eq!(c.api("GET", "/api/v1/models", None).code, 401);
    let r = http(&c.addr, "GET", &format!("/?token={TOKEN}"), &[], None);
    assert_eq!((r.code, r.header("location")), (303, Some("/login?next=/")));
    let r = http(&c.addr, "GET", "/models/new", &[], None);
    assert_eq!((r.code, r.header("location")), (303, Some("/login?next=/models/new")));
    assert_eq!(http(&c.addr, "GET", "/login", &[], None).code, 200);

    // A session id planted before the login is worth nothing after it: the login mints its own.
    let planted = format!("paddock_session={}", "a".repeat(64));
    let (r, rita) = login(&c, "rita", RITA, &[("Cookie", &planted)]);
    let rita = rita.unwrap_or_else(|| panic!("{}", String::from_utf8_lossy(&r.body)));
    assert_ne!(rita.cookie, planted);
    assert_eq!(As { c: &c, cookie: planted.clone() }.call("GET", "/api/v1/session", None).code, 401);
    assert_eq!(rita.call("GET", "/api/v1/session", None).json(), json!({"user": "rita", "role": "racer"}));
    // A page elsewhere cannot post with rita's cookie, nor log her in.
    let evil =
        [("Cookie", rita.cookie.as_str()), ("Origin", "http://evil.example"), ("Content-Type", "application/json")];
    let body = new_model("csrf", 1.0).to_string();
    assert_eq!(http(&c.addr, "POST", "/api/v1/models", &evil, Some(body.as_bytes())).code, 403);
    let (r, _) = login(&c, "rita", RITA, &[("Origin", "http://evil.example")]);
    assert_eq!(r.code, 403);
    let r = http(&c.addr, "POST", "/api/v1/session", &[("Content-Type", "application/json")], Some(b"{not json"));
    assert_eq!(r.code, 400);

    // Rita's model is hers: another racer neither sees nor touches it; a facilitator sees it
    // but does not stop it; the admin may.
    let r = rita.call("POST", "/api/v1/models", Some(new_model("rita-1", 0.2)));
    assert_eq!(r.code, 201, "{}", String::from_utf8_lossy(&r.body));
    assert_eq!(r.json()["owner"], "rita");
    let (_, rex) = login(&c, "rex", RITA, &[]);
    let rex = rex.unwrap();
    assert_eq!(rex.call("GET", "/api/v1/models", None).json(), json!([]));
    // While rita-1 has the cluster, the others wait their turn, round-robin by user: rex's job,
    // though newer, goes before rita's second.
    assert_eq!(rita.call("POST", "/api/v1/models", Some(new_model("rita-2", 0.2))).code, 201);
    assert_eq!(rex.call("POST", "/api/v1/models", Some(new_model("rex-1", 0.2))).code, 201);
    let places = wait_for(20, "the queue", || {
        let place =
            |who: &As<'_>, m: &str| who.call("GET", &format!("/api/v1/models/{m}"), None).json()["queued"].as_u64();
        let p = (place(&rita, "rita-1"), place(&rex, "rex-1"), place(&rita, "rita-2"));
        (p.1 > Some(0) && p.2 > Some(0)).then_some(p)
    });
    assert_eq!(places, (Some(0), Some(1), Some(2)), "rita-1 runs; rex-1 next; rita-2 after");
    let r = rex.call("GET", "/api/v1/models/rita-1", None);
    assert_eq!(r.code, 403);
    assert!(r.json()["error"].as_str().unwrap().contains("facilitator role"), "{}", r.json());
    assert_eq!(rex.call("DELETE", "/api/v1/models/rita-1", None).code, 403);
    assert_eq!(rex.call("GET", "/api/v1/models/rita%2D1", None).code, 403, "the name as the router decodes it");
    assert_eq!(rex.call("GET", "/api/v1/models/rita%2D1/metrics", None).code, 403);
    assert_eq!(rex.call("GET", "/models/rita-1", None).code, 403, "the page too");
    assert_eq!(rex.call("GET", "/api/v1/models/rita-1/car.tar.gz", None).code, 403);
    let (_, fay) = login(&c, "fay", RITA, &[]);
    let fay = fay.unwrap();
    let seen: Vec<String> = fay
        .call("GET", "/api/v1/models", None)
        .json()
        .as_array()
        .unwrap()
        .iter()
        .map(|m| m["name"].as_str().unwrap().to_string())
        .collect();
    assert!(seen.contains(&"rita-1".to_string()) && seen.contains(&"rex-1".to_string()), "{seen:?}");
    let r = fay.call("POST", "/api/v1/models/rita-1/stop", None);
    assert_eq!(r.code, 403);
    assert!(r.json()["error"].as_str().unwrap().contains("admin role"), "{}", r.json());
    // Users are the admin's: a racer is refused, naming the role.
    let r = rex.call("POST", "/api/v1/users", Some(json!({"name": "mallory", "role": "admin"})));
    assert_eq!(r.code, 403);
    assert!(r.json()["error"].as_str().unwrap().contains("needs the admin role"));
    assert_eq!(rex.call("GET", "/users", None).code, 403);
    let (_, ada) = login(&c, "ada", ADA, &[]);
    let ada = ada.unwrap();
    assert_eq!(ada.call("GET", "/users", None).code, 200);
    // An invitation: its link sets the password, then the user logs in.
    let r = ada.call("POST", "/api/v1/users", Some(json!({"name": "newbie", "role": "racer"})));
    assert_eq!(r.code, 201, "{}", r.json());
    let link = r.json()["invitation"].as_str().unwrap().to_string();
    let secret = link.strip_prefix("/invite/").unwrap();
    assert_eq!(http(&c.addr, "GET", &link, &[], None).code, 200);
    let take = json!({"invitation": secret, "password": "short"}).to_string();
    let r =
        http(&c.addr, "POST", "/api/v1/invitations", &[("Content-Type", "application/json")], Some(take.as_bytes()));
    assert_eq!(r.code, 400, "the password rule");
    let take = json!({"invitation": secret, "password": "Newbie-pass-1"}).to_string();
    let r =
        http(&c.addr, "POST", "/api/v1/invitations", &[("Content-Type", "application/json")], Some(take.as_bytes()));
    assert_eq!(r.code, 200, "{}", String::from_utf8_lossy(&r.body));
    assert!(login(&c, "newbie", "Newbie-pass-1", &[]).1.is_some());
    // A new role takes effect at the next request of the same session.
    assert_eq!(ada.call("PATCH", "/api/v1/users/rex", Some(json!({"role": "facilitator"}))).code, 200);
    assert_eq!(rex.call("GET", "/api/v1/models/rita-1", None).code, 200);

    // Quotas. Rita may keep two models: a third is refused, and so is an import.
    let r = ada.call("PATCH", "/api/v1/users/rita", Some(json!({"quota": {"models": 2, "minutes": null}})));
    assert_eq!(r.code, 200, "{}", r.json());
    let r = rita.call("POST", "/api/v1/models", Some(new_model("rita-3", 0.2)));
    assert_eq!(r.code, 403);
    assert!(r.json()["error"].as_str().unwrap().contains("your quota of models: 2 of 2 kept, 0 left"), "{}", r.json());
    let imported = http(
        &c.addr,
        "POST",
        "/api/v1/models/import?name=rita-3",
        &[("Cookie", &rita.cookie), ("Origin", &format!("http://{}", c.addr))],
        Some(b"a car archive"),
    );
    assert_eq!(imported.code, 403, "{}", String::from_utf8_lossy(&imported.body));
    // The instance's minutes: the three models hold their 0.2 each; a model asking for more
    // than is left is refused, whoever asks.
    assert_eq!(ada.call("PUT", "/api/v1/quota", Some(json!({"models": null, "minutes": 1.0}))).code, 200);
    let r = ada.call("POST", "/api/v1/models", Some(new_model("ada-1", 1.0)));
    assert_eq!(r.code, 403);
    assert!(r.json()["error"].as_str().unwrap().contains("the instance's quota of minutes"), "{}", r.json());
    let q = rita.call("GET", "/api/v1/quota", None).json();
    assert_eq!(q["user"]["quota"]["models"], 2, "{q}");
    assert!(q["instance"]["used"]["minutes"].as_f64().unwrap() >= 0.6, "{q}");
    // An evaluation needs minutes left: none are once the instance's are spent.
    wait_for(60, "rita-1 trained", || {
        (rita.call("GET", "/api/v1/models/rita-1", None).json()["status"] == "ready").then_some(())
    });
    let minutes_before = rita.call("GET", "/api/v1/quota", None).json()["user"]["used"]["minutes"].as_f64().unwrap();

    // Races: a facilitator makes them, a racer may not; a racer enters her own ready model
    // while the race is open, as many times as it allows; each entry is evaluated as it
    // arrives and ranked, one row per racer.
    let newbie = login(&c, "newbie", "Newbie-pass-1", &[]).1.unwrap();
    let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().as_secs_f64();
    let cup = json!({"name": "cup", "track": "reinvent_base", "ranking": "best_lap", "min_laps": 1, "max_laps": 2,
                     "max_submissions": 2, "closes": now + 3600.0});
    let r = rita.call("POST", "/api/v1/races", Some(cup.clone()));
    assert_eq!(r.code, 403);
    assert!(r.json()["error"].as_str().unwrap().contains("needs the facilitator role"), "{}", r.json());
    assert_eq!(fay.call("POST", "/api/v1/races", Some(cup.clone())).code, 201);
    let r = rita.call("POST", "/api/v1/races/cup/live", Some(json!({"action": "launch"})));
    assert_eq!(r.code, 403, "running a live race is a facilitator's");
    assert_eq!(fay.call("POST", "/api/v1/races", Some(cup)).code, 409, "the name is taken");
    let later = json!({"name": "later", "track": "reinvent_base", "opens": now + 3600.0, "closes": now + 7200.0});
    assert_eq!(fay.call("POST", "/api/v1/races", Some(later)).code, 201);
    assert_eq!(rita.call("PATCH", "/api/v1/races/later", Some(json!({"max_laps": 3}))).code, 403);
    let r = fay.call("PATCH", "/api/v1/races/later", Some(json!({"max_laps": 3})));
    assert_eq!((r.code, r.json()["min_laps"].as_u64()), (200, Some(3)), "{}", r.json());
    let r = rita.call("POST", "/api/v1/races/later/entries", Some(json!({"model": "rita-1"})));
    assert_eq!(r.code, 409, "not open yet: {}", r.json());
    let r = rita.call("POST", "/api/v1/races/cup/entries", Some(json!({"model": "rex-1"})));
    assert_eq!(r.code, 404, "rex's model is not rita's to see: {}", r.json());
    let r = rita.call("POST", "/api/v1/races/cup/entries", Some(json!({"model": "rita-1", "car": 1})));
    assert_eq!(r.code, 400);
    for _ in 0..2 {
        let r = rita.call("POST", "/api/v1/races/cup/entries", Some(json!({"model": "rita-1"})));
        assert_eq!(r.code, 202, "{}", String::from_utf8_lossy(&r.body));
        assert_eq!((r.json()["racer"].as_str(), r.json()["status"].as_str()), (Some("rita"), Some("queued")));
    }
    let r = rita.call("POST", "/api/v1/races/cup/entries", Some(json!({"model": "rita-1"})));
    assert_eq!(r.code, 403);
    assert!(r.json()["error"].as_str().unwrap().contains("at most 2 entries"), "{}", r.json());
    let entries = wait_for(60, "both entries evaluated", || {
        let list = rita.call("GET", "/api/v1/races/cup/entries", None).json();
        list.as_array().unwrap().iter().all(|e| e["status"] == "done").then_some(list)
    });
    let entries = entries.as_array().unwrap();
    assert_eq!(entries.len(), 2);
    for e in entries {
        assert_eq!(e["laps"].as_array().unwrap().len(), 2, "{e}");
        assert!(e["laps"][0]["progress"].as_f64().unwrap() > 0.0, "{e}");
    }
    // One row for rita however many of her entries are ranked: the better one.
    let board = newbie.call("GET", "/api/v1/races/cup/leaderboard", None).json();
    let ranked: Vec<u64> =
        entries.iter().filter(|e| e["ranked"] == true).map(|e| e["time_ms"].as_u64().unwrap()).collect();
    let rows = board["rows"].as_array().unwrap();
    assert_eq!(rows.len(), usize::from(!ranked.is_empty()), "{board}");
    if let Some(row) = rows.first() {
        assert_eq!((row["rank"].as_u64(), row["racer"].as_str()), (Some(1), Some("rita")), "{board}");
        assert_eq!(row["time_ms"].as_u64(), ranked.iter().min().copied(), "{board}");
        // Her fastest lap, drawn on the track, is everyone's to see.
        let lap =
            newbie.call("GET", &format!("/api/v1/races/cup/entries/{}/lap.svg", row["entry"].as_str().unwrap()), None);
        assert_eq!(lap.code, 200);
        assert!(String::from_utf8_lossy(&lap.body).contains("<line"), "the lap is drawn");
    }
    // Each racer sees their own entries; a facilitator sees all.
    assert_eq!(newbie.call("GET", "/api/v1/races/cup/entries", None).json(), json!([]));
    assert_eq!(fay.call("GET", "/api/v1/races/cup/entries", None).json().as_array().unwrap().len(), 2);
    assert_eq!(rita.call("GET", "/races/cup", None).code, 200);
    assert_eq!(newbie.call("GET", "/races", None).code, 200);
    // An open race stays; one not open goes, by a facilitator.
    assert_eq!(fay.call("DELETE", "/api/v1/races/cup", None).code, 409);
    assert_eq!(newbie.call("DELETE", "/api/v1/races/later", None).code, 403);
    assert_eq!(fay.call("DELETE", "/api/v1/races/later", None).code, 204);
    // The entries' time is counted against rita's minutes.
    let minutes_after = rita.call("GET", "/api/v1/quota", None).json()["user"]["used"]["minutes"].as_f64().unwrap();
    assert!(minutes_after > minutes_before, "{minutes_before} → {minutes_after}");

    // The queued jobs start as the cluster frees: rex-1 next.
    wait_for(60, "rex-1 started", || {
        (rex.call("GET", "/api/v1/models/rex-1", None).json()["queued"].as_u64().unwrap_or(0) == 0).then_some(())
    });
    // Rita's own minutes: none left refuses her evaluation, naming her quota.
    let r = ada.call("PATCH", "/api/v1/users/rita", Some(json!({"quota": {"models": 2, "minutes": 0.0}})));
    assert_eq!(r.code, 200, "{}", r.json());
    let r =
        rita.call("POST", "/api/v1/models/rita-1/evaluations", Some(json!({"track": "reinvent_base", "trials": 1})));
    assert_eq!(r.code, 403, "{}", String::from_utf8_lossy(&r.body));
    assert!(r.json()["error"].as_str().unwrap().contains("your quota of minutes"), "{}", r.json());
    let r = ada.call("PATCH", "/api/v1/users/rita", Some(json!({"quota": {"models": 2, "minutes": null}})));
    assert_eq!(r.code, 200, "{}", r.json());
    // The instance's models: as many as are kept (rita-1, rita-2, rex-1) refuses one more,
    // whoever asks.
    assert_eq!(ada.call("PUT", "/api/v1/quota", Some(json!({"models": 3, "minutes": null}))).code, 200);
    let r = ada.call("POST", "/api/v1/models", Some(new_model("ada-2", 0.1)));
    assert_eq!(r.code, 403);
    assert!(r.json()["error"].as_str().unwrap().contains("the instance's quota of models"), "{}", r.json());
    assert_eq!(ada.call("PUT", "/api/v1/quota", Some(json!({"models": null, "minutes": 0.0}))).code, 200);
    let r =
        rita.call("POST", "/api/v1/models/rita-1/evaluations", Some(json!({"track": "reinvent_base", "trials": 1})));
    assert_eq!(r.code, 403, "{}", String::from_utf8_lossy(&r.body));
    assert!(r.json()["error"].as_str().unwrap().contains("none left"), "{}", r.json());
    // A race entry spends minutes too.
    let r = rita.call("POST", "/api/v1/races/cup/entries", Some(json!({"model": "rita-1"})));
    assert_eq!(r.code, 403, "{}", String::from_utf8_lossy(&r.body));
    assert!(r.json()["error"].as_str().unwrap().contains("none left"), "{}", r.json());

    // A login flood: five failures for a name, then even the right password waits.
    for _ in 0..5 {
        assert_eq!(login(&c, "fay", "Wrong-pass-1", &[]).0.code, 401);
    }
    let (r, _) = login(&c, "fay", RITA, &[]);
    assert_eq!(r.code, 429);
    assert!(r.header("retry-after").unwrap().parse::<u64>().unwrap() > 0);
    // Logging out ends the session; removing a user ends theirs.
    assert_eq!(rita.call("DELETE", "/api/v1/session", None).code, 204);
    assert_eq!(rita.call("GET", "/api/v1/session", None).code, 401);
    assert_eq!(ada.call("DELETE", "/api/v1/users/rex", None).code, 204);
    assert_eq!(rex.call("GET", "/api/v1/session", None).code, 401);
    assert_eq!(ada.call("DELETE", "/api/v1/users/ada", None).code, 409, "the last admin stays");
    let health = ada.call("GET", "/api/v1/health", None).json();
    for reason in [
        "a failed login",
        "a login past the limit",
        "an unknown session",
        "a cross-origin request",
        "another user's model",
        "a role too low",
        "a quota",
        "a racer's submissions spent",
        "an entry outside the race's window",
        "removing an open race",
    ] {
        assert!(health["refused"][reason].as_u64().unwrap_or(0) >= 1, "{reason}: {health}");
    }
    c.stop();
}

/// Issue 52: `coordinator users` manages the data folder's users: each subcommand, and its
/// refusals naming what was wrong.
#[test]
fn coordinator_users_adds_invites_changes_and_removes_users() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let out = |o: std::process::Output| {
        (o.status.success(), format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr)))
    };
    let (ok, text) = out(users(&data, &["add", "ada", "--role", "admin"]));
    assert!(ok && text.contains("added ada (admin)") && text.contains("password "), "{text}");
    let (ok, text) = out(users(&data, &["invite", "rex", "--url", "http://127.0.0.1:8100/"]));
    assert!(ok && text.trim().starts_with("http://127.0.0.1:8100/invite/"), "{text}");
    let (ok, text) = out(users(&data, &["quota", "rex", "--models", "3", "--minutes", "unlimited"]));
    assert!(ok && text.contains("rex: models 3, minutes unlimited"), "{text}");
    let (ok, text) = out(users(&data, &["quota", "--instance", "--minutes", "600"]));
    assert!(ok && text.contains("the instance: models unlimited, minutes 600"), "{text}");
    let (ok, text) = out(users(&data, &["role", "rex", "facilitator"]));
    assert!(ok && text.contains("rex is now facilitator"), "{text}");
    let (ok, text) = out(users(&data, &["list"]));
    assert!(ok && text.contains("ada") && text.contains("rex") && text.contains("invited"), "{text}");
    for (args, want) in [
        (&["add", "x", "--role", "racer"][..], "name: 2 to 64"),
        (&["add", "ada"], "already exists"),
        (&["remove", "ada"], "last admin"),
        (&["role", "nobody", "racer"], "no user named 'nobody'"),
        (&["quota", "rex", "--models", "many"], "--models many"),
    ] {
        let (ok, text) = out(users(&data, args));
        assert!(!ok && text.contains(want), "{args:?}: {text}");
    }
    let (ok, _) = out(users(&data, &["remove", "rex"]));
    assert!(ok);
}

fn curl(args: &[&str]) -> (bool, String) {
    let o = Command::new("curl").args(["-sS", "--max-time", "10"]).args(args).output().unwrap();
    (o.status.success(), format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr)))
}

/// Issue 52: beyond loopback the console serves HTTPS with a certificate from the cluster's CA
/// and asks for a login; without either it does not start. OpenSSL's client verifies the
/// certificate; curl logs in (the cookie Secure); a plain-HTTP request is refused and counted.
#[test]
fn the_console_beyond_loopback_serves_https_and_asks_for_a_login() {
    let dir = tempfile::tempdir().unwrap();
    let (data, certs) = (dir.path().join("data"), dir.path().join("certs"));
    let coordinator = |args: &[&str]| {
        let o = Command::new(bin("coordinator")).args(args).output().unwrap();
        assert!(o.status.success(), "{args:?}: {}", String::from_utf8_lossy(&o.stderr));
    };
    let c = certs.to_str().unwrap();
    coordinator(&["certs", "new", c]);
    coordinator(&["certs", "issue", c, "console", "127.0.0.1"]);
    let (cert, key) = (certs.join("console-127.0.0.1.pem"), certs.join("console-127.0.0.1.key"));
    let tls = ["--tls-cert", cert.to_str().unwrap(), "--tls-key", key.to_str().unwrap()];
    // Beyond loopback: refused without HTTPS, then without a user.
    let start = |extra: &[&str]| {
        Command::new(bin("console")).args(["--listen", "0.0.0.0:0", "--data"]).arg(&data).args(extra).output().unwrap()
    };
    let o = start(&[]);
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("--tls-cert"), "{o:?}");
    let o = start(&tls);
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("no user yet"), "{o:?}");
    add(&data, dir.path(), "ada", "admin", ADA);
    let mut args = vec!["--listen", "0.0.0.0:0"];
    args.extend(tls);
    let console = Console::with_args(&data, 1, &args);
    let port = console.addr.rsplit(':').next().unwrap().to_string();
    let base = format!("https://127.0.0.1:{port}");
    let ca = certs.join("ca.pem");
    let ca = ca.to_str().unwrap();
    // OpenSSL's own client checks the chain against the CA and the name.
    let o = Command::new("openssl")
        .args(["s_client", "-connect", &format!("127.0.0.1:{port}"), "-CAfile", ca, "-verify_ip", "127.0.0.1"])
        .args(["-verify_return_error", "-brief"])
        .stdin(std::process::Stdio::null())
        .output()
        .unwrap();
    let text = format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    assert!(text.contains("Verification: OK"), "{text}");
    // Not trusted without the CA; the login page with it.
    let (ok, text) = curl(&[&format!("{base}/login")]);
    assert!(!ok && text.contains("certificate"), "{text}");
    let (ok, text) = curl(&["--cacert", ca, &format!("{base}/login")]);
    assert!(ok && text.contains("login-password"), "{text}");
    let (ok, text) = curl(&["--cacert", ca, &format!("{base}/api/v1/models")]);
    assert!(ok && text.contains("a login is needed"), "the API asks for a login: {text}");
    // Logged in over HTTPS, the session cookie is Secure and HttpOnly.
    let body = json!({"user": "ada", "password": ADA}).to_string();
    let (ok, text) = curl(&[
        "--cacert",
        ca,
        "-D",
        "-",
        "-H",
        "Content-Type: application/json",
        "-H",
        &format!("Origin: {base}"),
        "--data",
        &body,
        &format!("{base}/api/v1/session"),
    ]);
    let cookie = text.lines().find(|l| l.to_lowercase().starts_with("set-cookie:")).unwrap_or("").to_string();
    assert!(ok && cookie.contains("Secure") && cookie.contains("HttpOnly"), "{text}");
    let session = cookie.split_once(':').unwrap().1.trim().split(';').next().unwrap().to_string();
    // A plain-HTTP request to the HTTPS port gets no page: refused and counted.
    let plain = std::panic::catch_unwind(|| http(&format!("127.0.0.1:{port}"), "GET", "/login", &[], None));
    assert!(plain.is_err() || plain.as_ref().is_ok_and(|r| r.code != 200), "plain HTTP was served");
    let (ok, text) = curl(&["--cacert", ca, "-H", &format!("Cookie: {session}"), &format!("{base}/api/v1/health")]);
    let health: serde_json::Value = serde_json::from_str(&text).unwrap_or_else(|_| panic!("{ok} {text}"));
    assert!(health["refused"]["a failed TLS handshake"].as_u64().unwrap_or(0) >= 1, "{health}");
    console.stop();
}
