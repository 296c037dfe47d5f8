//! The pages: server-rendered templates (minijinja, every value HTML-escaped), the embedded
//! assets with their licences, and the reward editor's samples. What a page shows comes from
//! the same functions the API answers with.

use crate::api::{App, best_lap, status_of};
use crate::auth::Principal;
use crate::users::Role;
use axum::Extension;
use axum::extract::{Path, Query, State};
use axum::http::{StatusCode, header};
use axum::response::{Html, IntoResponse, Response};
use minijinja::Environment;
use serde_json::{Value, json};
use std::collections::HashMap;
use std::sync::LazyLock;

static TEMPLATES: LazyLock<Environment<'static>> = LazyLock::new(|| {
    let mut env = Environment::new();
    for (name, text) in [
        ("base.html", include_str!("../templates/base.html")),
        ("models.html", include_str!("../templates/models.html")),
        ("rows.html", include_str!("../templates/rows.html")),
        ("new.html", include_str!("../templates/new.html")),
        ("model.html", include_str!("../templates/model.html")),
        ("licences.html", include_str!("../templates/licences.html")),
        ("import.html", include_str!("../templates/import.html")),
        ("login.html", include_str!("../templates/login.html")),
        ("invite.html", include_str!("../templates/invite.html")),
        ("users.html", include_str!("../templates/users.html")),
        ("races.html", include_str!("../templates/races.html")),
        ("race.html", include_str!("../templates/race.html")),
        ("broadcast.html", include_str!("../templates/broadcast.html")),
        ("cars.html", include_str!("../templates/cars.html")),
    ] {
        env.add_template(name, text).expect("the console's templates parse");
    }
    env
});

/// An embedded asset: its path under `/assets/`, type, bytes, and where it comes from.
pub struct Asset {
    /// The file name.
    pub name: &'static str,
    /// Its Content-Type.
    pub kind: &'static str,
    /// The bytes.
    pub bytes: &'static [u8],
}

/// Every asset the pages load: nothing comes from elsewhere (the console works offline).
pub const ASSETS: &[Asset] = &[
    Asset { name: "console.css", kind: "text/css", bytes: include_bytes!("../assets/console.css") },
    Asset { name: "console.js", kind: "text/javascript", bytes: include_bytes!("../assets/console.js") },
    Asset { name: "htmx.min.js", kind: "text/javascript", bytes: include_bytes!("../assets/htmx.min.js") },
    Asset { name: "uPlot.iife.min.js", kind: "text/javascript", bytes: include_bytes!("../assets/uPlot.iife.min.js") },
    Asset { name: "uPlot.min.css", kind: "text/css", bytes: include_bytes!("../assets/uPlot.min.css") },
    Asset { name: "codemirror.min.js", kind: "text/javascript", bytes: include_bytes!("../assets/codemirror.min.js") },
    Asset { name: "codemirror.css", kind: "text/css", bytes: include_bytes!("../assets/codemirror.css") },
];

/// The libraries inside the console, with their licences (shown at `/licences`).
pub const LICENCES: &[(&str, &str, &str)] = &[
    ("htmx 2.0.11", "https://htmx.org", include_str!("../assets/licences/htmx.txt")),
    ("uPlot 1.6.32", "https://github.com/leeoniya/uPlot", include_str!("../assets/licences/uplot.txt")),
    (
        "CodeMirror 5.65.21 (with its Python mode)",
        "https://codemirror.net/5/",
        include_str!("../assets/licences/codemirror.txt"),
    ),
];

/// The reward editor's samples: DeepRacer's four, then Paddock's.
pub const SAMPLES: &[(&str, &str)] = &[
    (
        "Time trial: follow the center line (DeepRacer's default)",
        include_str!("../../examples/rewards/follow_center_line.py"),
    ),
    ("Time trial: stay inside the two borders", include_str!("../../examples/rewards/stay_inside_two_borders.py")),
    ("Time trial: prevent zig-zag", include_str!("../../examples/rewards/prevent_zig_zag.py")),
    ("Object avoidance: stay in one lane, do not crash", include_str!("../../examples/rewards/object_avoidance.py")),
    ("Point in the right direction", include_str!("../../examples/rewards/point_in_the_right_direction.py")),
    ("Paddock: the racing line (built in)", "builtin:race_line"),
    ("Paddock: the center line (built in)", "builtin:center_line"),
    ("Paddock: object avoidance and head-to-bot, clear of the next object (built in)", "builtin:clearance"),
];

fn render(name: &str, ctx: Value) -> Response {
    match TEMPLATES.get_template(name).and_then(|t| t.render(ctx)) {
        Ok(html) => Html(html).into_response(),
        Err(e) => {
            tracing::error!("the page {name} did not render: {e:#}");
            (StatusCode::INTERNAL_SERVER_ERROR, format!("the page {name} did not render: {e}")).into_response()
        }
    }
}

/// `/assets/NAME`.
pub async fn asset(Path(name): Path<String>) -> Response {
    match ASSETS.iter().find(|a| a.name == name) {
        Some(a) => ([(header::CONTENT_TYPE, a.kind), (header::CACHE_CONTROL, "max-age=3600")], a.bytes).into_response(),
        None => {
            crate::counters::refused("an unknown asset");
            (StatusCode::NOT_FOUND, "no such asset").into_response()
        }
    }
}

/// `/licences`.
pub async fn licences() -> Response {
    let list: Vec<Value> = LICENCES.iter().map(|(n, u, t)| json!({"name": n, "url": u, "text": t})).collect();
    render("licences.html", json!({"licences": list}))
}

fn when(unix: f64) -> String {
    let secs = unix as i64;
    let (days, rest) = (secs.div_euclid(86_400), secs.rem_euclid(86_400));
    // Civil date from days since 1970-01-01 (Howard Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!("{y:04}-{m:02}-{d:02} {:02}:{:02} UTC", rest / 3600, rest % 3600 / 60)
}

/// The principal as the pages show it (the header's name, role and links).
fn me(p: &Principal) -> Value {
    json!({"user": p.user, "role": p.role.name()})
}

fn rows(app: &App, p: &Principal, q: &str, sort: &str) -> Vec<Value> {
    let q = q.to_lowercase();
    let mut list: Vec<Value> = crate::api::visible_models(app, p)
        .into_iter()
        .filter(|r| q.is_empty() || r.name.to_lowercase().contains(&q) || r.description.to_lowercase().contains(&q))
        .map(|r| {
            let status = status_of(app.hub.job(&r.job_id).map(|j| j.state()), &r, &app.store);
            json!({"name": r.name, "description": r.description, "status": status, "algorithm": r.algorithm,
                   "sensors": r.sensors, "tracks": r.tracks, "reversed": r.reversed, "best_lap_s": best_lap(&app.store, &r.name),
                   "created": r.created, "created_text": when(r.created)})
        })
        .collect();
    let key = |v: &Value| -> String {
        match sort {
            "name" | "status" | "algorithm" => v[sort].as_str().unwrap_or("").to_lowercase(),
            "sensors" | "track" => v[if sort == "track" { "tracks" } else { "sensors" }].to_string(),
            _ => String::new(),
        }
    };
    match sort {
        "created" | "" => {}
        "best_lap" => list.sort_by(|a, b| {
            let f = |v: &Value| v["best_lap_s"].as_f64().unwrap_or(f64::INFINITY);
            f(a).total_cmp(&f(b))
        }),
        _ => list.sort_by_key(|v| key(v)),
    }
    list
}

/// `/`: the models.
pub async fn models(State(app): State<App>, Extension(p): Extension<Principal>) -> Response {
    let list = rows(&app, &p, "", "created");
    let owned: std::collections::BTreeSet<String> = app.store.list().into_iter().map(|r| r.job_id).collect();
    // Jobs started elsewhere (the CLI) are nobody's: facilitators and admins see them.
    let others_shown = p.role >= Role::Facilitator;
    let (other, error) = {
        let s = app.hub.seen.lock().expect("hub state");
        let other: Vec<Value> = s
            .jobs
            .values()
            .filter(|j| others_shown && !owned.contains(&j.id))
            .map(|j| {
                json!({"id": j.id, "state": j.state().name(), "worlds": j.worlds, "minutes": j.minutes,
                            "episodes": j.episodes, "progress": j.progress})
            })
            .collect();
        (other, s.error.clone())
    };
    render("models.html", json!({"models": list, "other_jobs": other, "coordinator_error": error, "me": me(&p)}))
}

/// `/models/rows?q=&sort=`: the table's rows (htmx swaps them in).
pub async fn model_rows(
    State(app): State<App>,
    Extension(p): Extension<Principal>,
    Query(q): Query<HashMap<String, String>>,
) -> Response {
    let text = q.get("q").map(String::as_str).unwrap_or("");
    let sort = q.get("sort").map(String::as_str).unwrap_or("created");
    render("rows.html", json!({"models": rows(&app, &p, text, sort), "q": text}))
}

/// `/models/new` (`?clone=NAME`: the wizard filled in from that model).
pub async fn new_model(
    State(app): State<App>,
    Extension(p): Extension<Principal>,
    Query(q): Query<HashMap<String, String>>,
) -> Response {
    let tracks: Vec<Value> = tracks::worlds()
        .iter()
        .map(|w| {
            let t = w.track(tracks::Direction::Forward);
            let forward = if t.is_ccw() { "counterclockwise" } else { "clockwise" };
            json!({"name": w.name, "surface": w.surface.name(), "length": t.length(), "forward": forward})
        })
        .collect();
    let samples: Vec<Value> = SAMPLES.iter().map(|(t, c)| json!({"title": t, "code": c})).collect();
    let mut prefill = Value::Null;
    let mut clone_of = Value::Null;
    if let Some(from) = q.get("clone") {
        let rec = match app.store.get(from) {
            Ok(r) if p.may_see(r.owner.as_deref()) => r,
            Ok(r) => return not_found(&format!("model '{}' is another user's", r.name)),
            Err(e) => return not_found(&e.to_string()),
        };
        let dir = app.store.dir(&rec.name).expect("a stored model's name is valid");
        let read = |f: &str| std::fs::read_to_string(dir.join(f)).ok();
        let json_file = |f: &str| read(f).and_then(|t| serde_json::from_str::<Value>(&t).ok()).unwrap_or(Value::Null);
        prefill = json!({
            "name": format!("{}-clone", rec.name).chars().take(64).collect::<String>(),
            "description": format!("Clone of {}", rec.name).chars().take(255).collect::<String>(),
            "tracks": rec.tracks, "reversed": rec.reversed, "agents": rec.agents, "stop": rec.stop, "clone_from": rec.name,
            "reward_source": read("reward_function.py").unwrap_or_else(|| rec.reward.clone()),
            "model_metadata": json_file("model_metadata.json"),
            "hyperparameters": json_file("hyperparameters.json"),
        });
        clone_of = json!(rec.name);
    }
    render(
        "new.html",
        json!({"tracks": tracks, "samples": samples, "default_track": "reinvent_base", "prefill": prefill,
               "clone_of": clone_of, "me": me(&p)}),
    )
}

fn not_found(message: &str) -> Response {
    crate::counters::refused("an unknown model");
    let mut r = render("licences.html", json!({"error": message}));
    *r.status_mut() = StatusCode::NOT_FOUND;
    r
}

/// `/login?next=PATH`.
pub async fn login(Query(q): Query<HashMap<String, String>>) -> Response {
    // Only a path of this console: never an address elsewhere.
    let next = q.get("next").filter(|n| n.starts_with('/') && !n.starts_with("//")).cloned().unwrap_or("/".into());
    render("login.html", json!({"next": next}))
}

/// `/invite/SECRET`: set the password of an invitation.
pub async fn invite(Path(secret): Path<String>) -> Response {
    render("invite.html", json!({"invitation": secret}))
}

/// `/users` (admin): the users, their roles and quotas; invite one.
pub async fn users(State(app): State<App>, Extension(p): Extension<Principal>) -> Response {
    if let Err(r) = p.require(Role::Admin, "managing users") {
        return r.into_response();
    }
    let models = app.store.list();
    let list: Vec<Value> = app
        .gate
        .users
        .list()
        .iter()
        .map(|u| {
            let mut v = u.to_json();
            v["models"] = json!(models.iter().filter(|m| m.owner.as_deref() == Some(u.name.as_str())).count());
            v["created_text"] = json!(when(u.created));
            v
        })
        .collect();
    render("users.html", json!({"users": list, "me": me(&p)}))
}

/// `/models/import`.
pub async fn import() -> Response {
    render("import.html", json!({}))
}

/// `/models/NAME`.
pub async fn model(State(app): State<App>, Extension(p): Extension<Principal>, Path(name): Path<String>) -> Response {
    let rec = match app.store.get(&name) {
        Ok(r) => r,
        Err(e) => return not_found(&e.to_string()),
    };
    app.hub.watch(&rec.job_id);
    let status = status_of(app.hub.job(&rec.job_id).map(|j| j.state()), &rec, &app.store);
    let m = json!({"name": rec.name, "description": rec.description, "status": status, "tracks": rec.tracks,
                   "reversed": rec.reversed, "agents": rec.agents, "sensors": rec.sensors, "algorithm": rec.algorithm, "reward": rec.reward, "stop": rec.stop,
                   "job_id": rec.job_id});
    let tracks: Vec<String> = tracks::world_names().map(String::from).collect();
    render(
        "model.html",
        json!({"m": m, "created_text": when(rec.created), "status_text": "", "tracks": tracks, "me": me(&p)}),
    )
}

/// A race as the pages show it.
fn race_view(app: &App, r: &crate::races::Race, now: f64) -> Value {
    let mut v = crate::race_api::summary(app, r, now);
    v["opens_text"] = json!(when(r.opens));
    v["closes_text"] = json!(when(r.closes));
    v["ranking_title"] = json!(r.ranking.title());
    v["type_title"] = json!(match r.race.race_type {
        sim_agent::race::RaceType::TimeTrial => "Time trial".to_string(),
        sim_agent::race::RaceType::ObjectAvoidance =>
            format!("Object avoidance ({} objects)", r.race.number_of_obstacles),
        sim_agent::race::RaceType::HeadToBot => format!("Head-to-bot ({} bots)", r.race.number_of_bot_cars),
    });
    v
}

/// `/races`: open and closed races; a facilitator's form to make one.
pub async fn races(State(app): State<App>, Extension(p): Extension<Principal>) -> Response {
    let now = protocol::job::now_unix();
    let list: Vec<Value> = app.races.list().iter().map(|r| race_view(&app, r, now)).collect();
    let tracks: Vec<String> = tracks::world_names().map(String::from).collect();
    render(
        "races.html",
        json!({"races": list, "tracks": tracks, "may_make": p.role >= Role::Facilitator, "me": me(&p)}),
    )
}

/// `/races/NAME`: the race's details, rules and live leaderboard; the requester's entries and
/// their ready models to enter.
pub async fn race(State(app): State<App>, Extension(p): Extension<Principal>, Path(name): Path<String>) -> Response {
    let r = match app.races.get(&name) {
        Ok(r) => r,
        Err(e) => {
            crate::counters::refused("an unknown race");
            let mut page = render("licences.html", json!({"error": e.to_string()}));
            *page.status_mut() = StatusCode::NOT_FOUND;
            return page;
        }
    };
    let models: Vec<String> = crate::api::visible_models(&app, &p)
        .into_iter()
        .filter(|m| p.may_change(m.owner.as_deref()))
        .filter(|m| status_of(app.hub.job(&m.job_id).map(|j| j.state()), m, &app.store) == "ready")
        .map(|m| m.name)
        .collect();
    render(
        "race.html",
        json!({"r": race_view(&app, &r, protocol::job::now_unix()), "models": models,
               "may_manage": p.role >= Role::Facilitator, "me": me(&p)}),
    )
}

/// `/cars`: the cars on the network, live; an organiser assigns each a model or a live race's
/// entry, and holds or releases its e-stop.
pub async fn cars(State(app): State<App>, Extension(p): Extension<Principal>) -> Response {
    let models: Vec<String> = crate::api::visible_models(&app, &p)
        .into_iter()
        .filter(|m| status_of(app.hub.job(&m.job_id).map(|j| j.state()), m, &app.store) != "unknown")
        .map(|m| m.name)
        .collect();
    let races: Vec<String> = app.races.list().into_iter().filter(|r| r.live()).map(|r| r.name).collect();
    render(
        "cars.html",
        json!({"models": models, "races": races, "may_drive": p.role >= Role::Facilitator, "me": me(&p)}),
    )
}

/// `/races/NAME/broadcast`: a live race full screen, for the big screen and the stream.
pub async fn broadcast(State(app): State<App>, Path(name): Path<String>) -> Response {
    match app.races.get(&name) {
        Ok(r) if r.live() => render("broadcast.html", json!({"r": race_view(&app, &r, protocol::job::now_unix())})),
        Ok(_) => {
            let mut page = render("licences.html", json!({"error": format!("race '{name}' is a community race")}));
            *page.status_mut() = StatusCode::NOT_FOUND;
            page
        }
        Err(e) => {
            crate::counters::refused("an unknown race");
            let mut page = render("licences.html", json!({"error": e.to_string()}));
            *page.status_mut() = StatusCode::NOT_FOUND;
            page
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dates_are_civil_utc() {
        assert_eq!(when(0.0), "1970-01-01 00:00 UTC");
        assert_eq!(when(1_796_000_000.0), "2026-11-30 00:53 UTC");
        assert_eq!(when(951_782_400.0), "2000-02-29 00:00 UTC");
    }

    #[test]
    fn every_template_renders_and_escapes_what_it_shows() {
        let evil = "<img src=x onerror=alert(1)>";
        let html = TEMPLATES
            .get_template("rows.html")
            .unwrap()
            .render(json!({"models": [{"name": evil, "description": evil, "status": "ready", "algorithm": "sac",
                                       "sensors": [evil], "tracks": [evil], "created_text": "now"}]}))
            .unwrap();
        assert!(!html.contains("<img"), "{html}");
        assert!(html.contains("&lt;img src=x onerror=alert(1)&gt;"), "{html}");
    }

    /// Each page renders with what its handler gives it; JSON inside a script cannot close it.
    #[test]
    fn every_page_renders_with_its_handlers_context() {
        let evil = "</script><img src=x onerror=alert(1)>";
        let m = json!({"name": "m1", "description": evil, "status": "training", "tracks": ["reinvent_base"],
                       "sensors": ["FRONT_FACING_CAMERA"], "algorithm": "clipped_ppo", "reward": evil,
                       "stop": {"minutes": 10}, "job_id": "m1-1"});
        for (page, ctx) in [
            ("model.html", json!({"m": m, "created_text": "now", "status_text": evil, "tracks": ["reinvent_base"]})),
            (
                "new.html",
                json!({"tracks": [{"name": "reinvent_base", "surface": "asphalt", "length": 17.7}],
                       "samples": [{"title": "t", "code": evil}], "default_track": "reinvent_base",
                       "prefill": {"name": evil}, "clone_of": evil}),
            ),
            (
                "models.html",
                json!({"models": [], "other_jobs": [{"id": evil, "state": "running", "worlds": [evil],
                                   "minutes": 1.0, "episodes": 3, "progress": 4.0}], "coordinator_error": evil}),
            ),
            ("licences.html", json!({"licences": [{"name": "x", "url": "https://x", "text": evil}]})),
            ("licences.html", json!({"error": evil})),
            (
                "races.html",
                json!({"races": [{"name": evil, "status": "open", "type_title": evil, "track": evil, "opens_text": evil,
                                  "closes_text": evil, "ranking_title": evil, "entries": 1,
                                  "leader": {"racer": evil, "time": "00:09.000"}}],
                       "tracks": [evil], "may_make": true}),
            ),
            (
                "race.html",
                json!({"r": {"name": evil, "description": evil, "status": "open", "type_title": evil, "track": evil,
                             "race_type": "object_avoidance", "opens_text": evil, "closes_text": evil},
                       "models": [evil], "may_manage": true}),
            ),
            (
                "race.html",
                json!({"r": {"name": evil, "mode": "live", "status": "open", "type_title": evil, "track": evil,
                             "race_type": "time_trial", "closes_text": evil, "max_resets": 3},
                       "models": [evil], "may_manage": true}),
            ),
            ("broadcast.html", json!({"r": {"name": evil, "track": evil}})),
            ("cars.html", json!({"models": [evil], "races": [evil], "may_drive": true})),
        ] {
            let html = TEMPLATES.get_template(page).unwrap().render(ctx).unwrap_or_else(|e| panic!("{page}: {e:#}"));
            assert!(!html.contains(evil) && !html.contains("<img src=x"), "{page} shows the text as HTML:\n{html}");
        }
    }
}
