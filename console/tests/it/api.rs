//! The API from a program's side: what it refuses (401, 403, 400 with every field, 404, 409)
//! and a model from creation to a verified model, seen by the CLI, kept across a restart.

use crate::support::{Console, TOKEN, bin, http, state_metadata, wait_for};
use serde_json::json;
use std::process::Command;

/// Issue 51: the API refuses what it should, with every invalid field named.
#[test]
fn the_api_refuses_requests_without_the_token_from_elsewhere_or_with_invalid_fields() {
    let dir = tempfile::tempdir().unwrap();
    let c = Console::start(&dir.path().join("data"));
    // No token, a wrong one: 401, and the API says how to authenticate.
    let r = http(&c.addr, "GET", "/api/v1/models", &[], None);
    assert_eq!(r.code, 401);
    assert_eq!(r.header("www-authenticate"), Some("Bearer"));
    assert_eq!(http(&c.addr, "GET", "/api/v1/models", &[("Authorization", "Bearer nope")], None).code, 401);
    assert_eq!(http(&c.addr, "GET", "/?token=nope", &[], None).code, 401);
    assert_eq!(http(&c.addr, "GET", "/models/new", &[], None).code, 401, "pages too");
    // The token in the address: a cookie, and the address cleaned of it.
    let r = http(&c.addr, "GET", &format!("/models/new?token={TOKEN}"), &[], None);
    assert_eq!(r.code, 303);
    assert_eq!(r.header("location"), Some("/models/new"));
    let cookie = r.header("set-cookie").unwrap().split(';').next().unwrap().to_string();
    assert!(r.header("set-cookie").unwrap().contains("HttpOnly"));
    let page = http(&c.addr, "GET", "/models/new", &[("Cookie", &cookie)], None);
    assert_eq!(page.code, 200);
    assert!(String::from_utf8_lossy(&page.body).contains("Reward function"));
    // The cookie does not let another site's page change anything.
    let body = br#"{"name": "x"}"#;
    let evil = [("Cookie", cookie.as_str()), ("Origin", "http://evil.example"), ("Content-Type", "application/json")];
    assert_eq!(http(&c.addr, "POST", "/api/v1/models", &evil, Some(body)).code, 403);
    let host = format!("http://{}", c.addr);
    let own = [("Cookie", cookie.as_str()), ("Origin", host.as_str()), ("Content-Type", "application/json")];
    assert_eq!(http(&c.addr, "POST", "/api/v1/models", &own, Some(body)).code, 400, "its own pages may");

    // Every invalid field, not the first.
    let bad = json!({
        "name": "<img src=x onerror=alert(1)>",
        "description": "commas, are not allowed",
        "tracks": ["reinvent_base", "no_such_track", 3],
        "reward_function": "import os\n\ndef reward_function(params):\n    return float(speed)\n",
        "model_metadata": {"action_space": [], "sensor": ["EYES"]},
        "hyperparameters": {"batch_size": "many"},
        "stop": {"minutes": -1},
        "race": {"race_type": "drag_race"},
        "reversed": "yes",
        "agents": 0,
        "colour": "red",
    });
    let r = c.api("POST", "/api/v1/models", Some(&bad));
    assert_eq!(r.code, 400);
    let v = r.json();
    let fields: Vec<&str> = v["errors"].as_array().unwrap().iter().map(|e| e["field"].as_str().unwrap()).collect();
    for want in [
        "colour",
        "name",
        "description",
        "tracks[1]",
        "tracks[2]",
        "reversed",
        "agents",
        "model_metadata",
        "hyperparameters",
        "stop",
        "race",
    ] {
        assert!(fields.contains(&want), "{want} is named: {v:#}");
    }
    assert!(!r.body.windows(4).any(|w| w == b"<img"), "the name is not echoed");
    // The reward's error is on its line (the metadata was bad, so it ran on DeepRacer's widest
    // actions); the import of os is only DeepRacer's warning, not an error.
    let reward: Vec<&serde_json::Value> =
        v["errors"].as_array().unwrap().iter().filter(|e| e["field"] == "reward_function").collect();
    assert_eq!(reward.len(), 1, "{v:#}");
    assert_eq!(reward[0]["line"], 4, "{v:#}");
    assert!(reward[0]["message"].as_str().unwrap().contains("speed"));
    assert_eq!(c.api("POST", "/api/v1/models", None).code, 400, "no body");
    let r =
        http(&c.addr, "POST", "/api/v1/models", &[("Authorization", &format!("Bearer {TOKEN}"))], Some(b"{not json"));
    assert_eq!(r.code, 400);
    assert!(r.json()["error"].as_str().unwrap().contains("not JSON"));
    let big = "#".repeat(2 << 20);
    let r = c.api("POST", "/api/v1/rewards/validate", Some(&json!({"reward_function": big})));
    assert_eq!(r.code, 413, "a body over the limit is refused");
    let health = c.api("GET", "/api/v1/health", None).json();
    assert!(health["refused"]["an oversized request"].as_u64() >= Some(1), "counted: {health}");

    // Validate: every finding on its line.
    let r = c.api(
        "POST",
        "/api/v1/rewards/validate",
        Some(&json!({"reward_function": "import os\n\ndef reward_function(params):\n    return float(speeed)\n", "track": "reinvent_wood"})),
    );
    assert_eq!(r.code, 200);
    let v = r.json();
    assert_eq!(v["ok"], false);
    assert_eq!(v["errors"][0]["line"], 4, "{v}");
    assert_eq!(v["warnings"][0]["line"], 1, "{v}");
    let ok = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../examples/rewards/follow_center_line.py"))
        .unwrap();
    let v = c.api("POST", "/api/v1/rewards/validate", Some(&json!({"reward_function": ok}))).json();
    assert_eq!(v["ok"], true, "{v}");
    assert!(v["rewards"]["calls"].as_u64().unwrap() > 0, "{v}");
    let r = c.api("POST", "/api/v1/rewards/validate", Some(&json!({"reward_function": ok, "track": "mars"})));
    assert_eq!((r.code, r.json()["errors"][0]["field"].as_str()), (400, Some("track")));

    // The dry run: the reward along a lap of the scripted driver, drawn; a broken file's errors.
    let v = c
        .api("POST", "/api/v1/rewards/dry_run", Some(&json!({"reward_function": ok, "track": "reinvent_base"})))
        .json();
    assert_eq!(v["status"], "lap_complete", "{v}");
    assert!(v["points"].as_array().unwrap().len() > 100, "{v}");
    assert!(v["svg"].as_str().unwrap().matches("<line").count() > 100);
    let r = c.api(
        "POST",
        "/api/v1/rewards/dry_run",
        Some(&json!({"reward_function": "def reward_function(params):\n    return float(nope)\n"})),
    );
    assert_eq!((r.code, r.json()["errors"][0]["line"].as_u64()), (400, Some(2)), "{}", r.json());
    // The racing line and an action space that drives it.
    let v = c.api("GET", "/api/v1/tracks/reinvent_base/race_line?actions=7", None).json();
    assert_eq!(v["actions"].as_array().unwrap().len(), 7, "{v}");
    assert!(v["lap_time_s"].as_f64().unwrap() > 3.0, "{v}");
    assert_eq!(c.api("GET", "/api/v1/tracks/reinvent_base/race_line?actions=1", None).code, 400);
    assert_eq!(c.api("GET", "/api/v1/tracks/mars/race_line", None).code, 404);

    // Unknown models and routes; names that would leave the data folder.
    assert_eq!(c.api("GET", "/api/v1/models/nobody", None).code, 404);
    assert_eq!(c.api("GET", "/api/v1/models/..%2F..%2Fetc/metrics", None).code, 404);
    assert_eq!(c.api("POST", "/api/v1/models/nobody/stop", None).code, 404);
    assert_eq!(c.api("DELETE", "/api/v1/models/nobody", None).code, 404);
    assert_eq!(c.api("GET", "/api/v1/nothing", None).code, 404);
    assert_eq!(c.api("GET", "/assets/../Cargo.toml", None).code, 404);
    assert_eq!(c.api("GET", "/assets/..%2FCargo.toml", None).code, 404);
    // A model stopped before its job's learner took it stops at once (no checkpoint to wait
    // for), not "stopping" for ever.
    let quick = json!({"name": "quick-stop", "tracks": ["reinvent_base"], "reward_function": "builtin:center_line",
                       "model_metadata": crate::support::state_metadata()});
    assert_eq!(c.api("POST", "/api/v1/models", Some(&quick)).code, 201);
    assert_eq!(c.api("POST", "/api/v1/models/quick-stop/stop", None).code, 200);
    let v = crate::support::wait_for(60, "the stopped model", || {
        let v = c.api("GET", "/api/v1/models/quick-stop", None).json();
        (v["status"] != "training" && v["status"] != "stopping").then_some(v)
    });
    assert!(v["status"] == "failed" || v["status"] == "ready", "{v:#}");
    // Each refusal is counted.
    let health = c.api("GET", "/api/v1/health", None).json();
    assert!(health["refused"]["no token"].as_u64().unwrap() >= 2, "{health}");
    assert!(health["refused"]["invalid fields"].as_u64().unwrap() >= 3, "{health}");
    assert!(health["refused"]["a cross-origin request"].as_u64().unwrap() >= 1, "{health}");
    c.stop();
}

/// Issue 51: a model made through the API, driven the other way round on one of the two
/// agents, trains to a verified model; `coordinator job status` sees its job; the graph's
/// figures (evaluation rewards among them), the events and the status come back; a console
/// restarted on the same data folder finds it all; then it is deleted.
#[test]
fn a_model_created_through_the_api_trains_to_a_verified_model_and_survives_a_restart() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let c = Console::with_agents(&data, 2);
    // The OpenAPI document is JSON and names every route the console answers.
    let doc = c.api("GET", "/api/v1/openapi.json", None).json();
    assert_eq!(doc["openapi"], "3.1.0");
    let tracks = c.api("GET", "/api/v1/tracks", None).json();
    assert!(tracks.as_array().unwrap().iter().any(|t| t["name"] == "reinvent_wood" && t["surface"] == "wood"));
    let svg = c.api("GET", "/api/v1/tracks/reinvent_base/picture.svg", None);
    assert!(svg.code == 200 && svg.body.starts_with(b"<svg"));

    let model = json!({
        "name": "state-1",
        "description": "A quick model",
        "tracks": ["reinvent_base"],
        "reward_function": "builtin:center_line",
        "model_metadata": state_metadata(),
        "stop": {"minutes": 3, "target_laps": 3, "target_evals": 1, "verify_trials": 10},
        "reversed": true,
        "agents": 1,
    });
    let r = c.api("POST", "/api/v1/models", Some(&model));
    assert_eq!(r.code, 201, "{}", String::from_utf8_lossy(&r.body));
    let made = r.json();
    assert_eq!(made["status"], "training");
    assert_eq!((&made["reversed"], &made["agents"]), (&json!(true), &json!(1)), "{made}");
    let job = made["job_id"].as_str().unwrap().to_string();
    assert_eq!(c.api("POST", "/api/v1/models", Some(&model)).code, 409, "the name is taken");
    // The CLI sees the job the console started (one job-control protocol).
    let o = Command::new(bin("coordinator")).args(["job", "status", &job, "--connect", &c.endpoint]).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stdout).contains(&format!("job {job}")));
    let status = wait_for(120, "a verified model", || {
        let v = c.api("GET", "/api/v1/models/state-1", None).json();
        (v["status"] != "training" && v["status"] != "stopping").then_some(v)
    });
    assert_eq!(status["status"], "ready", "{status:#}");
    assert!(status["training"]["stop_reason"].as_str().unwrap().contains("verified"), "{status:#}");
    assert!(status["best_lap_s"].as_f64().unwrap() > 5.0, "{status:#}");
    let metrics = c.api("GET", "/api/v1/models/state-1/metrics", None).json();
    assert!(!metrics["updates"].as_array().unwrap().is_empty());
    assert!(
        metrics["evaluations"].as_array().unwrap().iter().any(|e| e["best"] == true && e["min_laps"] == 3),
        "{metrics}"
    );
    // DeepRacer's evaluation reward: the centre-line reward summed along each trial.
    assert!(
        metrics["evaluations"].as_array().unwrap().iter().all(|e| e["reward"].as_f64().unwrap() > 1.0),
        "{metrics}"
    );
    // One agent of the two drove it, the other way round along the track.
    let assigned: std::collections::BTreeSet<&str> = status["events"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|e| e.as_str()?.split_once("agent ")?.1.split_once(" assigned to ").map(|(a, _)| a))
        .collect();
    assert_eq!(assigned.len(), 1, "{status:#}");
    let (along, against) = motion_along_the_track(&data.join("models/state-1/run"), "reinvent_base");
    assert!(against > 10 * along.max(1), "{along} steps along the track's own direction, {against} against it");
    // Every path of the OpenAPI document is a route (none answers "no such route"); its stop
    // comes after training, when there is nothing left to stop.
    for path in doc["paths"].as_object().unwrap().keys() {
        let p = path.replace("{name}", if path.contains("tracks") { "reinvent_base" } else { "state-1" });
        let r = if p.ends_with("/validate") || p.ends_with("/stop") {
            c.api("POST", &p, Some(&json!({})))
        } else if p.ends_with("/events") {
            continue;
        } else {
            c.api("GET", &p, None)
        };
        assert!(!String::from_utf8_lossy(&r.body).contains("no such page or API route"), "{path} is served");
    }
    // An evaluation: 3 trials on another world, DeepRacer's columns, the lap drawn.
    let bad =
        c.api("POST", "/api/v1/models/state-1/evaluations", Some(&json!({"track": "mars", "trials": 50, "colour": 1})));
    assert_eq!(bad.code, 400);
    let fields: Vec<String> =
        bad.json()["errors"].as_array().unwrap().iter().map(|e| e["field"].as_str().unwrap().to_string()).collect();
    assert_eq!(fields, ["colour", "track", "trials"], "{}", bad.json());
    let r = c.api("POST", "/api/v1/models/state-1/evaluations", Some(&json!({"track": "reinvent_wood", "trials": 3})));
    assert_eq!(r.code, 202, "{}", String::from_utf8_lossy(&r.body));
    let id = r.json()["id"].as_str().unwrap().to_string();
    let done = wait_for(60, "the evaluation", || {
        let v = c.api("GET", &format!("/api/v1/models/state-1/evaluations/{id}"), None).json();
        (v["status"] != "running").then_some(v)
    });
    assert_eq!(done["status"], "done", "{done:#}");
    let rows = done["results"].as_array().unwrap();
    assert_eq!(rows.len(), 3);
    for key in
        ["time_s", "progress", "status", "resets", "off_tracks", "off_track_penalty_s", "crashes", "crash_penalty_s"]
    {
        assert!(rows.iter().all(|t| !t[key].is_null()), "{key} in every trial: {done:#}");
    }
    assert!(done["path"].as_array().unwrap().len() > 50, "the fastest lap's path");
    let lap = c.api("GET", &format!("/api/v1/models/state-1/evaluations/{id}/lap.svg"), None);
    assert!(String::from_utf8_lossy(&lap.body).matches("<line").count() > 50);
    let listed = c.api("GET", "/api/v1/models/state-1/evaluations", None).json();
    assert_eq!(listed[0]["id"], id.as_str());
    assert_eq!(c.api("GET", "/api/v1/models/state-1/evaluations/nope", None).code, 404);
    // A state-vector model cannot go to a car, and says why.
    let r = c.api("GET", "/api/v1/models/state-1/car.tar.gz", None);
    assert_eq!(r.code, 422);
    assert!(r.json()["error"].as_str().unwrap().contains("STATE_VECTOR"));
    // The events stream opens with the status.
    let list = c.api("GET", "/api/v1/models", None).json();
    assert_eq!(list[0]["name"], "state-1");
    c.stop();

    // A new console on the same data folder: the model, its status and its figures are there.
    let c = Console::start(&data);
    let v = wait_for(30, "the restarted coordinator's job list", || {
        let v = c.api("GET", "/api/v1/models/state-1", None).json();
        (v["status"] == "ready").then_some(v)
    });
    assert_eq!(v["description"], "A quick model");
    assert_eq!(c.api("GET", "/api/v1/models/state-1/metrics", None).json(), metrics);
    let page = http(&c.addr, "GET", "/", &[("Authorization", &format!("Bearer {TOKEN}"))], None);
    assert!(String::from_utf8_lossy(&page.body).contains("/models/state-1"));
    assert_eq!(c.api("DELETE", "/api/v1/models/state-1", None).code, 204);
    assert_eq!(c.api("GET", "/api/v1/models/state-1", None).code, 404);
    assert!(!data.join("models/state-1").exists());
    c.stop();
}

/// Issue 51: a console stopped while a model trains (its roles with it) and started again on
/// the same data folder shows the model training; it goes on from its last checkpoint to a
/// verified model, and its graph runs on without a gap or a repeat.
#[test]
fn a_console_restarted_while_a_model_trains_shows_it_training_and_nothing_is_lost() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let c = Console::start(&data);
    let model = json!({
        "name": "two-worlds",
        "tracks": ["reinvent_base", "reinvent_wood"],
        "reward_function": "builtin:center_line",
        "model_metadata": state_metadata(),
        "stop": {"minutes": 4, "target_laps": 3, "target_evals": 1, "verify_trials": 10},
    });
    assert_eq!(c.api("POST", "/api/v1/models", Some(&model)).code, 201);
    let before = wait_for(60, "two updates", || {
        let m = c.api("GET", "/api/v1/models/two-worlds/metrics", None).json();
        (m["updates"].as_array().unwrap().len() >= 2).then_some(m)
    });
    c.stop();
    let c = Console::start(&data);
    let v = c.api("GET", "/api/v1/models/two-worlds", None).json();
    assert_eq!(v["status"], "training", "{v:#}");
    let v = wait_for(150, "a verified model after the restart", || {
        let v = c.api("GET", "/api/v1/models/two-worlds", None).json();
        (v["status"] != "training" && v["status"] != "stopping").then_some(v)
    });
    assert_eq!(v["status"], "ready", "{v:#}");
    let after = c.api("GET", "/api/v1/models/two-worlds/metrics", None).json();
    let (b, a) = (before["updates"].as_array().unwrap(), after["updates"].as_array().unwrap());
    assert!(a.len() > b.len(), "training went on: {} updates before, {} after", b.len(), a.len());
    // The learner resumed from its last checkpoint: the points up to it are kept, those after
    // it were trained again, and the graph runs 1, 2, 3, … without a gap or a repeat.
    assert_eq!(a[0], b[0], "the first point is kept");
    let its: Vec<u64> = a.iter().map(|u| u["iteration"].as_u64().unwrap()).collect();
    assert_eq!(its, (1..=its.len() as u64).collect::<Vec<_>>(), "one point an iteration");
    // Each world's evaluation is there for the graph's per-world series.
    let last = after["evaluations"].as_array().unwrap().last().unwrap().clone();
    assert_eq!(last["worlds"].as_array().unwrap().len(), 2, "{last}");
    c.stop();
}

/// Issue 51: beyond loopback the console has no TLS or login yet, so it refuses to listen
/// there unless told `--insecure`.
#[test]
fn the_console_refuses_to_listen_beyond_loopback_without_insecure() {
    let dir = tempfile::tempdir().unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_console"))
        .args(["--listen", "0.0.0.0:0", "--data"])
        .arg(dir.path().join("data"))
        .output()
        .unwrap();
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("beyond loopback") && err.contains("--insecure"), "{err}");
    assert!(!dir.path().join("data/logs").exists(), "no role was started");
}

/// Steps of the training sim-traces under `run` that moved along `world`'s own direction and
/// against it (from each step's motion and the centre line's direction where it is).
fn motion_along_the_track(run: &std::path::Path, world: &str) -> (usize, usize) {
    let track = tracks::world(world).unwrap().track(tracks::Direction::Forward);
    let (mut along, mut against) = (0, 0);
    for worker in std::fs::read_dir(run).unwrap().flatten() {
        let Ok(files) = std::fs::read_dir(worker.path().join("training-simtrace")) else { continue };
        for csv in files.flatten() {
            let text = std::fs::read_to_string(csv.path()).unwrap();
            let rows: Vec<Vec<&str>> = text.lines().skip(1).map(|l| l.split(',').collect()).collect();
            for w in rows.windows(2) {
                let p = |r: &[&str]| tracks::P2::new(r[2].parse().unwrap(), r[3].parse().unwrap());
                let (a, b) = (p(&w[0]), p(&w[1]));
                if w[0][0] != w[1][0] || (b - a).norm() < 0.01 {
                    continue;
                }
                let dir = track.center().direction_at(track.center().project(a).along);
                if (b - a).dot(&tracks::P2::new(dir.cos(), dir.sin()).coords) > 0.0 {
                    along += 1;
                } else {
                    against += 1;
                }
            }
        }
    }
    (along, against)
}
