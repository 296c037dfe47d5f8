//! The console in a real browser: Debian's Chromium, headless, driven through WebDriver
//! (chromedriver) by Selenium's Python client. A racer's path: a reward whose error the editor
//! shows on its line, fixed; a state-vector model driven the other way round, trained from the
//! wizard to a verified model; a camera model trained from the wizard, its page's graph drawing
//! points and its camera updating; the car's archive downloaded, and `coordinator import`
//! taking it; an evaluation from the page with its trials, lap and frames; the run's MCAP holding the camera frames of its evaluation laps (Foxglove's
//! `mcap` reader).

use crate::support::{Console, TOKEN, bin};
use std::path::PathBuf;
use std::process::Command;

pub(crate) fn python() -> PathBuf {
    std::env::var_os("PADDOCK_PYTHON").map(PathBuf::from).unwrap_or_else(|| {
        panic!("PADDOCK_PYTHON is not set: run `./paddock test`, which makes target/pyenv with Selenium")
    })
}

/// Issue 51: models made in the browser: a reward's error on its line, fixed; a state-vector
/// model driven the other way round to a verified model; a camera model to the car's archive.
#[test]
fn a_racer_makes_models_in_chromium_from_a_reward_error_to_a_verified_model_and_the_cars_archive() {
    assert!(
        std::path::Path::new("/usr/bin/chromedriver").exists(),
        "no chromedriver: run `./paddock test`, which installs Debian's chromium-driver"
    );
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let c = Console::with_args(&data, 1, &["--live-speed", "3"]);
    let o = Command::new(python())
        .arg("-c")
        .arg(format!("{CHROMIUM}{RACER}"))
        .args([&c.addr, TOKEN])
        .arg(dir.path())
        .output()
        .unwrap();
    let out = String::from_utf8_lossy(&o.stdout).to_string();
    assert!(o.status.success(), "the browser's run failed:\n{out}\n{}", String::from_utf8_lossy(&o.stderr));
    let v: serde_json::Value = serde_json::from_str(out.lines().last().unwrap_or("")).unwrap();
    // The error was marked on its line, then the fixed file passed.
    assert_eq!(v["marked_lines"], serde_json::json!([6]), "{v}");
    assert!(v["validation_error"].as_str().unwrap().contains("line 6"), "{v}");
    assert!(v["validation_fixed"].as_str().unwrap().contains("passed"), "{v}");
    assert!(v["submit_error"].as_str().unwrap().contains("reward_function: line 6"), "{v}");
    // The fixed reward's dry run, and the picked track's racing line, drawn.
    assert!(v["dry_run"].as_u64().unwrap() > 100, "{v}");
    assert!(v["race_line"].as_u64().unwrap() > 50, "{v}");
    // The state-vector model went the other way round on one agent to a verified model, its
    // graph with the evaluations' rewards.
    assert_eq!(v["state_status"], "ready", "{v}");
    assert!(v["state_events"].as_str().unwrap().contains("verified"), "{v}");
    assert!(v["state_graph_points"].as_u64().unwrap() >= 2, "{v}");
    assert!(v["eval_reward_points"].as_u64().unwrap() >= 1, "{v}");
    assert_eq!(v["reversed_label"], "Clockwise", "reinvent_base runs counterclockwise: {v}");
    let state = c.api("GET", "/api/v1/models/state-1", None).json();
    assert_eq!((&state["reversed"], &state["agents"]), (&serde_json::json!(true), &serde_json::json!(1)), "{state}");
    // The camera model's graph drew points as updates came, and its camera's picture changed.
    assert!(v["graph_points"].as_u64().unwrap() >= 2, "{v}");
    assert!(v["camera_frames"].as_array().unwrap().len() >= 2, "{v}");
    assert_eq!(v["status"], "ready", "{v}");
    // An evaluation from the page: DeepRacer's columns a trial, the lap drawn, the frames.
    assert_eq!(v["trial_rows"], 3, "{v}");
    assert!(v["trial_text"].as_str().unwrap().contains("Off-track penalty"), "{v}");
    assert_eq!((&v["lap_drawn"], &v["frames_shown"]), (&serde_json::json!(true), &serde_json::json!(true)), "{v}");

    assert_eq!(v["imported_status"], "ready", "{v}");
    // The live race: reordered, refused a launch with submissions open, then each entry shown
    // in turn on both pages (the car moving; camera-1's camera), the winner on both.
    assert_eq!(v["queue"], serde_json::json!(["state-1", "camera-1"]), "{v}");
    assert!(v["launch_early"].as_str().unwrap().contains("close submissions"), "{v}");
    assert!(v["broadcast_waiting"].as_str().unwrap().contains("Waiting for the facilitator"), "{v}");
    assert_eq!(v["camera_on_broadcast"], true, "{v}");
    assert!(v["live_board"].as_str().unwrap().contains("state-1"), "{v}");
    for page in ["winner_organiser", "winner_broadcast"] {
        assert!(v[page].as_str().unwrap().starts_with("Winner!"), "{page}: {v}");
    }
    let winner = c.api("GET", "/api/v1/races/final/live", None).json();
    assert_eq!(winner["phase"], "completed", "{winner}");
    assert!(v["winner_broadcast"].as_str().unwrap().contains(winner["winner"]["racer"].as_str().unwrap()), "{v}");
    let shot = std::fs::metadata(dir.path().join("broadcast.png")).map(|m| m.len()).unwrap_or(0);
    assert!(shot > 10_000, "the broadcast page's screenshot: {shot} bytes");
    if let Ok(keep) = std::env::var("PADDOCK_KEEP_SCREENSHOTS") {
        for shot in ["broadcast.png", "racing.png"] {
            std::fs::copy(dir.path().join(shot), std::path::Path::new(&keep).join(shot)).unwrap();
        }
    }
    let r = c.api("POST", "/api/v1/models/import?name=junk", None);
    assert_eq!(r.code, 400, "an empty upload");
    let auth = format!("Bearer {TOKEN}");
    let r = crate::support::http(
        &c.addr,
        "POST",
        "/api/v1/models/import?name=junk",
        &[("Authorization", &auth)],
        Some(b"not a tar.gz"),
    );
    assert_eq!(r.code, 400);
    assert_eq!(r.json()["errors"][0]["field"], "body", "{}", r.json());
    assert_eq!(c.api("GET", "/api/v1/models/junk", None).code, 404, "nothing half-made");
    // ONNX, checked by onnx's own checker; the run folder for the notebooks.
    let r = c.api("GET", "/api/v1/models/camera-1/policy.onnx", None);
    assert_eq!(r.code, 200);
    let onnx = dir.path().join("camera-1.onnx");
    std::fs::write(&onnx, &r.body).unwrap();
    let o = Command::new(python())
        .args([
            "-c",
            "import onnx, sys; m = onnx.load(sys.argv[1]); onnx.checker.check_model(m); print(len(m.graph.node))",
        ])
        .arg(&onnx)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let r = c.api("GET", "/api/v1/models/camera-1/run.tar.gz", None);
    assert_eq!(r.code, 200);
    let names: Vec<String> = tar::Archive::new(flate2::read::GzDecoder::new(&r.body[..]))
        .entries()
        .unwrap()
        .map(|e| e.unwrap().path().unwrap().display().to_string())
        .collect();
    assert!(names.iter().any(|n| n.starts_with("camera-1/metrics/TrainingMetrics")), "{names:?}");
    assert!(names.iter().any(|n| n.starts_with("camera-1/model/")), "{names:?}");
    assert!(!names.iter().any(|n| n.contains("checkpoints/")), "{names:?}");
    // The car's archive, as the page's link downloads it, is one `coordinator import` takes.
    let r = c.api("GET", "/api/v1/models/camera-1/car.tar.gz", None);
    assert_eq!(r.code, 200);
    assert!(r.header("content-disposition").unwrap().contains("physicalmodel-camera-1.tar.gz"));
    let archive = dir.path().join("physicalmodel-camera-1.tar.gz");
    std::fs::write(&archive, &r.body).unwrap();
    let o = Command::new(bin("coordinator"))
        .arg("import")
        .arg(&archive)
        .arg("--out")
        .arg(dir.path().join("imported"))
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(String::from_utf8_lossy(&o.stdout).contains("DEEP_CONVOLUTIONAL_NETWORK_SHALLOW"));
    c.stop();

    // The run's MCAP holds what the car saw in its evaluation laps, read by Foxglove's reader.
    let mcap = data.join("models/camera-1/run/trace.mcap");
    let o = Command::new(python()).arg("-c").arg(FRAMES).arg(&mcap).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert!(v["frames"].as_u64().unwrap() > 10, "{v}");
    assert_eq!(v["schema"], "foxglove.RawImage");
    assert_eq!(v["pixels"], 160 * 120);
    assert!(v["levels"].as_u64().unwrap() > 20, "a picture, not a flat frame: {v}");
}

/// Counts the MCAP's evaluation camera frames with Foxglove's `mcap` package.
const FRAMES: &str = r#"
import base64, json, sys
from mcap.reader import make_reader
n, schema, pixels, levels = 0, None, 0, 0
with open(sys.argv[1], "rb") as f:
    for s, c, m in make_reader(f).iter_messages(topics=["/evaluation/camera"]):
        d = json.loads(m.data)
        data = base64.b64decode(d["data"])
        n, schema, pixels = n + 1, s.name, len(data)
        assert d["width"] * d["height"] == len(data) and d["encoding"] == "mono8"
        levels = max(levels, len(set(data)))
print(json.dumps({"frames": n, "schema": schema, "pixels": pixels, "levels": levels}))
"#;

/// What each browser script starts with: Debian's Chromium, headless, through chromedriver;
/// `addr` (the first argument), `tmp` (the last), `out` (printed at the end) and `wait`.
pub(crate) const CHROMIUM: &str = r###"
import json, sys, time
from selenium import webdriver
from selenium.webdriver.chrome.service import Service
from selenium.webdriver.common.by import By
from selenium.common.exceptions import StaleElementReferenceException

addr, tmp = sys.argv[1], sys.argv[-1]
opts = webdriver.ChromeOptions()
for a in ["--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--no-first-run",
          "--disable-background-networking", "--disable-component-update", "--disable-sync",
          "--window-size=1300,1000", "--user-data-dir=" + tmp + "/chromium"]:
    opts.add_argument(a)
opts.binary_location = "/usr/bin/chromium"
d = webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=opts)
out = {}

def wait(what, f, secs=60):
    end = time.time() + secs
    while time.time() < end:
        try:
            v = f()
        except StaleElementReferenceException:
            # A live update replaced the element between finding it and reading it: look again.
            v = None
        if v:
            return v
        time.sleep(0.3)
    d.save_screenshot(tmp + "/timeout.png")
    raise SystemExit("not within %ds: %s (page: %s)" % (secs, what, d.current_url))

"###;

/// The racer, in Chromium (after [`CHROMIUM`]): prints one JSON line of what the pages showed.
const RACER: &str = r###"
token = sys.argv[2]

def click(css):
    # Once it shows and takes clicks: a page still settling (a busy machine) is waited for,
    # and a control that never shows fails with a screenshot and its name.
    def ready():
        e = d.find_element(By.CSS_SELECTOR, css)
        return e.is_displayed() and e.is_enabled() and e
    wait("%s to take a click" % css, ready, 30).click()

BAD = '''def reward_function(params):
    track_width = params["track_width"]
    distance = params["distance_from_center"]
    if distance <= 0.25 * track_width:
        return 1.0
    return float(1e-3 * speeed)
'''
GOOD = BAD.replace("speeed", "params['speed']")
def new_model(name):
    d.get("http://%s/models/new" % addr)
    d.find_element(By.ID, "name").send_keys(name)

def graph_points():
    return d.execute_script("return window.paddockGraphs[0].data[0].length")

try:
    d.get("http://%s/?token=%s" % (addr, token))
    assert "Your models" in d.title, d.title
    assert "token=" not in d.current_url, d.current_url
    # A state-vector model, the other way round on one agent, to the verified model (the
    # wizard's default stop).
    new_model("state-1")
    click('[name="direction"][value="reversed"]')
    out["reversed_label"] = d.find_element(By.ID, "dir-reversed").text
    click("#next")
    click('[name="camera"][value="STATE_VECTOR"]')
    d.find_element(By.CSS_SELECTOR, '[name="agents"]').send_keys("1")
    click("#next")
    click("#next")
    click("#next")
    d.execute_script("document.querySelector('.CodeMirror').CodeMirror.setValue(arguments[0])", BAD)
    click("#validate")
    out["validation_error"] = wait("the validation's errors", lambda: "error" in d.find_element(By.ID, "validation").text and d.find_element(By.ID, "validation").text)
    out["marked_lines"] = d.execute_script(
        "var cm = document.querySelector('.CodeMirror').CodeMirror, out = [];"
        "for (var i = 0; i < cm.lineCount(); i++) { var b = cm.lineInfo(i).bgClass || ''; if (b.indexOf('error-line') >= 0) out.push(i + 1); }"
        "return out;")
    click("#submit")
    out["submit_error"] = wait("the refusal", lambda: d.find_element(By.ID, "errors").text)
    d.execute_script("document.querySelector('.CodeMirror').CodeMirror.setValue(arguments[0])", GOOD)
    click("#validate")
    out["validation_fixed"] = wait("a passed validation", lambda: "passed" in d.find_element(By.ID, "validation").text and d.find_element(By.ID, "validation").text)
    click("#dry-run")
    out["dry_run"] = wait("the dry run's lap", lambda: len(d.find_elements(By.CSS_SELECTOR, "#dry-run-lap svg line")))
    out["race_line"] = len(d.find_elements(By.CSS_SELECTOR, "#race-line svg line"))
    click("#submit")
    wait("the model's page", lambda: d.current_url.endswith("/models/state-1"))
    out["state_status"] = wait("a ready model", lambda: d.find_element(By.ID, "status").text == "ready" and "ready", 90)
    out["state_events"] = wait("its events", lambda: "verified" in d.find_element(By.ID, "events").text and d.find_element(By.ID, "events").text)
    out["state_graph_points"] = wait("points on the graph", lambda: graph_points() >= 2 and graph_points())
    # DeepRacer's evaluation reward, drawn beside the completion.
    out["eval_reward_points"] = d.execute_script("return window.paddockGraphs[0].data[4].filter(function (v) { return v !== null; }).length")

    # A camera model, trained for half a minute: its camera, its evaluation, the car's archive.
    new_model("camera-1")
    click("#next")
    click("#next")
    click("#next")
    click('[name="stop_kind"][value="time"]')
    d.execute_script("document.querySelector('[name=minutes]').value = '0.5'")
    click("#next")
    d.execute_script("document.querySelector('.CodeMirror').CodeMirror.setValue(arguments[0])", GOOD)
    click("#submit")
    wait("the model's page", lambda: d.current_url.endswith("/models/camera-1"))
    frames = []
    def camera_changed():
        imgs = d.find_elements(By.CSS_SELECTOR, "#cameras img")
        if not imgs:
            return False
        img = imgs[0]
        src = img.get_attribute("src") or ""
        if img.is_displayed() and src and (not frames or frames[-1] != src):
            ok = d.execute_script("return arguments[0].complete && arguments[0].naturalWidth", img)
            if ok:
                frames.append(src)
        return len(frames) >= 2
    wait("two camera frames", camera_changed, 90)
    out["camera_frames"] = frames
    out["graph_points"] = wait("points on the graph", lambda: graph_points() >= 2 and graph_points(), 90)
    out["status"] = wait("a ready model", lambda: d.find_element(By.ID, "status").text == "ready" and "ready", 120)
    click("#start-evaluation")
    out["trial_rows"] = wait("the evaluation's trials", lambda: len(d.find_elements(By.CSS_SELECTOR, "#trials tbody tr")), 120)
    out["lap_drawn"] = wait("the lap's picture", lambda: d.execute_script("var i = document.getElementById('lap'); return i.complete && i.naturalWidth > 0"))
    out["frames_shown"] = wait("the evaluation's frames", lambda: d.execute_script("var i = document.getElementById('frames'); return !i.hidden && i.complete && i.naturalWidth > 0"))
    out["trial_text"] = d.find_element(By.ID, "trials").text
    d.save_screenshot(tmp + "/model.png")
    # The car's archive, downloaded as a program would, then uploaded on the import page.
    import urllib.request
    req = urllib.request.Request("http://%s/api/v1/models/camera-1/car.tar.gz" % addr, headers={"Authorization": "Bearer " + token})
    archive = tmp + "/physicalmodel-camera-1.tar.gz"
    with urllib.request.urlopen(req) as r, open(archive, "wb") as f:
        f.write(r.read())
    d.get("http://%s/models/import" % addr)
    d.find_element(By.ID, "archive").send_keys(archive)
    assert d.find_element(By.ID, "import-name").get_attribute("value") == "camera-1"
    d.find_element(By.ID, "import-name").clear()
    d.find_element(By.ID, "import-name").send_keys("camera-1-imported")
    click("#import-submit")
    wait("the imported model's page", lambda: d.current_url.endswith("/models/camera-1-imported"))
    out["imported_status"] = wait("its status", lambda: d.find_element(By.ID, "status").text)

    # A live race: made on the races page, entered from its page, run from the organiser's
    # controls while a second viewer watches the broadcast page.
    d.get("http://%s/races" % addr)
    click('[name="race-mode"][value="live"]')
    d.find_element(By.ID, "race-name").send_keys("final")
    click('[name="race-direction"][value="reversed"]')
    event = time.time() + 3
    d.execute_script("var t = new Date(arguments[0] * 1000 - new Date().getTimezoneOffset() * 60000);"
                     "document.getElementById('race-closes').value = t.toISOString().slice(0, 19);", event)
    d.find_element(By.CSS_SELECTOR, '#race-ranking option[value="best_lap"]').click()
    for f, v in [("race-min-laps", "1"), ("race-max-laps", "1")]:
        d.find_element(By.ID, f).clear()
        d.find_element(By.ID, f).send_keys(v)
    click("#race-submit")
    wait("the race's page", lambda: d.current_url.endswith("/races/final"))
    for m in ["camera-1", "state-1"]:
        d.find_element(By.CSS_SELECTOR, '#enter-model option[value="%s"]' % m).click()
        click("#enter-submit")
        wait(m + " in the queue", lambda: m in d.find_element(By.ID, "queue").text)
    def queue():
        return [r.text for r in d.find_elements(By.CSS_SELECTOR, "#queue tbody tr td:nth-child(3)")]
    wait("both in the queue", lambda: len(queue()) == 2)
    d.find_element(By.CSS_SELECTOR, '#queue tr[data-entry]:nth-child(2) .queue-move-up').click()
    out["queue"] = wait("state-1 moved up", lambda: queue()[0] == "state-1" and queue())
    time.sleep(max(0, event + 1 - time.time()))
    click("#live-launch")
    out["launch_early"] = wait("the refusal", lambda: d.find_element(By.ID, "live-errors").text)
    click("#live-submissions")
    wait("submissions closed", lambda: "closed" in d.find_element(By.ID, "live-banner").text)
    organiser = d.current_window_handle
    d.switch_to.new_window("window")
    d.get("http://%s/races/final/broadcast" % addr)
    broadcaster = d.current_window_handle
    out["broadcast_waiting"] = wait("the broadcast's banner", lambda: d.find_element(By.ID, "live-banner").text)
    d.switch_to.window(organiser)
    click("#live-launch")
    wait("state-1 launched", lambda: d.find_element(By.ID, "now-racing").text == "state-1", 20)
    click("#live-autolaunch")
    def car(handle):
        d.switch_to.window(handle)
        return d.execute_script("var c = document.getElementById('live-car'); return c && c.style.display !== 'none' ? c.getAttribute('cx') + ',' + c.getAttribute('cy') : null")
    seen = {}
    def both_see_the_car_move():
        for h in [organiser, broadcaster]:
            at = car(h)
            if at:
                seen.setdefault(h, set()).add(at)
        return all(len(seen.get(h, ())) >= 2 for h in [organiser, broadcaster])
    wait("the car moving on both pages", both_see_the_car_move, 60)
    out["car_positions"] = {("organiser" if h == organiser else "broadcast"): len(v) for h, v in seen.items()}
    d.switch_to.window(broadcaster)
    out["broadcast_racing"] = d.find_element(By.ID, "now-racing").text
    out["camera_on_broadcast"] = wait("camera-1's camera", lambda: d.find_element(By.ID, "now-racing").text == "camera-1" and d.execute_script("var i = document.getElementById('live-camera'); return !i.hidden && i.complete && i.naturalWidth > 0"), 90)
    d.save_screenshot(tmp + "/racing.png")
    d.switch_to.window(organiser)
    wait("both shown", lambda: d.find_element(By.ID, "race-progress-text").text.startswith("2 of 2"), 120)
    out["live_board"] = wait("the leaderboard", lambda: d.find_element(By.CSS_SELECTOR, "#leaderboard tbody").text)
    click("#live-winner")
    out["winner_organiser"] = wait("the winner", lambda: d.find_element(By.ID, "winner").is_displayed() and d.find_element(By.ID, "winner").text)
    d.switch_to.window(broadcaster)
    out["winner_broadcast"] = wait("the winner on the broadcast", lambda: d.find_element(By.ID, "winner").is_displayed() and d.find_element(By.ID, "winner").text)
    out["broadcast_board"] = d.find_element(By.ID, "live-board").text
    d.save_screenshot(tmp + "/broadcast.png")
finally:
    d.quit()
print(json.dumps(out))
"###;

/// Issue 52: in Chromium, an admin logs in, invites a racer from the Users page and logs out;
/// the racer sets her password at the invitation's link and logs in, and sees no Users page.
#[test]
fn an_admin_invites_a_racer_in_chromium_who_sets_her_password_and_logs_in() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    std::fs::create_dir_all(&data).unwrap();
    let pw = dir.path().join("ada.pw");
    std::fs::write(&pw, "Admin-pass-1\n").unwrap();
    let o = Command::new(bin("coordinator"))
        .args(["users", "add", "ada", "--role", "admin", "--password-file"])
        .arg(&pw)
        .arg("--data")
        .arg(&data)
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let c = Console::start(&data);
    let o = Command::new(python())
        .arg("-c")
        .arg(format!("{CHROMIUM}{INVITE}"))
        .arg(&c.addr)
        .arg(dir.path())
        .output()
        .unwrap();
    let out = String::from_utf8_lossy(&o.stdout).to_string();
    assert!(o.status.success(), "the browser's run failed:\n{out}\n{}", String::from_utf8_lossy(&o.stderr));
    let v: serde_json::Value = serde_json::from_str(out.lines().last().unwrap_or("")).unwrap();
    assert!(v["first_page"].as_str().unwrap().contains("/login?next=/"), "{v}");
    assert_eq!(v["wrong_password"], "wrong user name or password", "{v}");
    assert!(v["admin_header"].as_str().unwrap().contains("ada (admin)"), "{v}");
    assert!(v["link"].as_str().unwrap().contains("/invite/"), "{v}");
    assert!(v["after_logout"].as_str().unwrap().ends_with("/login"), "{v}");
    assert!(v["weak_password"].as_str().unwrap().contains("upper-case"), "{v}");
    assert!(v["racer_header"].as_str().unwrap().contains("rita (racer)"), "{v}");
    assert_eq!(v["racer_sees_users_link"], false, "{v}");
    let users = std::fs::read_to_string(data.join("users.json")).unwrap();
    assert!(users.contains("\"rita\"") && users.contains("$argon2id$"), "{users}");
}

/// The admin and the racer, in Chromium (after [`CHROMIUM`]): prints one JSON line of what the
/// pages showed.
const INVITE: &str = r###"
def log_in(user, password):
    d.find_element(By.ID, "login-user").clear()
    d.find_element(By.ID, "login-user").send_keys(user)
    d.find_element(By.ID, "login-password").clear()
    d.find_element(By.ID, "login-password").send_keys(password)
    d.find_element(By.ID, "login-submit").click()

try:
    d.get("http://%s/" % addr)
    out["first_page"] = d.current_url
    log_in("ada", "Not-her-pass-1")
    out["wrong_password"] = wait("the refusal", lambda: d.find_element(By.ID, "login-errors").text)
    log_in("ada", "Admin-pass-1")
    wait("the models page", lambda: "Your models" in d.title)
    out["admin_header"] = d.find_element(By.CSS_SELECTOR, "header .who").text
    d.find_element(By.LINK_TEXT, "Users").click()
    wait("the users page", lambda: d.current_url.endswith("/users"))
    d.find_element(By.ID, "new-user").send_keys("rita")
    d.find_element(By.ID, "add-user-submit").click()
    out["link"] = wait("the invitation's link", lambda: d.find_element(By.ID, "invitation-link").text)
    d.find_element(By.ID, "logout").click()
    out["after_logout"] = wait("the login page", lambda: d.current_url.split("?")[0].endswith("/login") and d.current_url)
    d.get(out["link"])
    d.find_element(By.ID, "invite-password").send_keys("weakpass")
    d.find_element(By.ID, "invite-again").send_keys("weakpass")
    d.find_element(By.ID, "invite-submit").click()
    out["weak_password"] = wait("the password rule", lambda: d.find_element(By.ID, "invite-errors").text)
    for f in ["invite-password", "invite-again"]:
        d.find_element(By.ID, f).clear()
        d.find_element(By.ID, f).send_keys("Racer-pass-1")
    d.find_element(By.ID, "invite-submit").click()
    wait("the login page", lambda: d.current_url.endswith("/login"))
    log_in("rita", "Racer-pass-1")
    wait("the models page", lambda: "Your models" in d.title)
    out["racer_header"] = d.find_element(By.CSS_SELECTOR, "header .who").text
    out["racer_sees_users_link"] = len(d.find_elements(By.LINK_TEXT, "Users")) > 0
    d.save_screenshot(tmp + "/racer.png")
finally:
    d.quit()
print(json.dumps(out))
"###;
