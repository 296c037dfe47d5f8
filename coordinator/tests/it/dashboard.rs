//! `coordinator dashboard JOB` shows a job live: a camera job runs under `up`, the
//! dashboard serves its page, and headless Chromium (Debian's package, which `./paddock test`
//! installs) renders it; the screenshot must show the training graph's line and the camera
//! frame of an agent, and `/status.json` what the coordinator says. Once the job is stopped,
//! the run's MCAP holds the camera frames of its evaluation laps (Foxglove's `mcap` reader).

use std::io::{BufRead, BufReader, Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::support;

fn chromium() -> PathBuf {
    ["/usr/bin/chromium-headless-shell", "/usr/bin/chromium"]
        .iter()
        .map(PathBuf::from)
        .find(|p| p.exists())
        .unwrap_or_else(|| panic!("no Chromium: run `./paddock test`, which installs Debian's chromium-headless-shell"))
}

/// GET `path` from `addr` (host:port): the status code and the body.
fn get(addr: &str, path: &str) -> (u16, Vec<u8>) {
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    write!(s, "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n").unwrap();
    let mut raw = Vec::new();
    s.read_to_end(&mut raw).unwrap();
    let split = raw.windows(4).position(|w| w == b"\r\n\r\n").expect("an HTTP response");
    let head = String::from_utf8_lossy(&raw[..split]).to_string();
    let code = head.split_whitespace().nth(1).and_then(|c| c.parse().ok()).unwrap_or(0);
    let mut body = raw[split + 4..].to_vec();
    if head.to_ascii_lowercase().contains("transfer-encoding: chunked") {
        // tiny_http chunks large bodies: undo it.
        let mut out = Vec::new();
        let mut rest = &body[..];
        loop {
            let eol = rest.windows(2).position(|w| w == b"\r\n").unwrap();
            let n = usize::from_str_radix(String::from_utf8_lossy(&rest[..eol]).trim(), 16).unwrap();
            if n == 0 {
                break;
            }
            out.extend_from_slice(&rest[eol + 2..eol + 2 + n]);
            rest = &rest[eol + 2 + n + 2..];
        }
        body = out;
    }
    (code, body)
}

struct Killed(Child);
impl Drop for Killed {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn first_line_with(child: &mut Child, needle: &str) -> String {
    let out = child.stdout.take().unwrap();
    let mut lines = BufReader::new(out).lines();
    loop {
        let l = lines.next().expect("the process ended before printing its address").unwrap();
        if l.contains(needle) {
            // Keep draining stdout so the child never blocks on a full pipe.
            std::thread::spawn(move || for _ in lines {});
            return l;
        }
    }
}

/// Issue 11: the dashboard shows the graph and the camera live in Chromium.
#[test]
fn the_dashboard_shows_the_graph_and_the_camera_live_in_chromium() {
    let dir = tempfile::tempdir().unwrap();
    let coordinator = env!("CARGO_BIN_EXE_coordinator");
    let mut up = Command::new(coordinator)
        .args([
            "up",
            "--sensor",
            "camera",
            "--world",
            "reinvent_wood",
            "--agents",
            "1",
            "--envs",
            "2",
            "--minutes",
            "3",
            "--target-laps",
            "0",
        ])
        .args(["--out", "up"])
        .current_dir(dir.path())
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let line = first_line_with(&mut up, "coordinator on ");
    let up = Killed(up);
    // "job ID: ... coordinator on ENDPOINT; logs in ..."
    let job = line.split(':').next().unwrap().trim_start_matches("job ").to_string();
    let endpoint = line.split("coordinator on ").nth(1).unwrap().split(';').next().unwrap().to_string();
    let mut dash = Command::new(coordinator)
        .args(["dashboard", &job, "--connect", &endpoint, "--bind", "127.0.0.1:0"])
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let line = first_line_with(&mut dash, "http://");
    let _dash = Killed(dash);
    let addr = line.split("http://").nth(1).unwrap().split('/').next().unwrap().to_string();

    // Wait for an update and a camera frame.
    let deadline = Instant::now() + Duration::from_secs(150);
    let status = loop {
        let (code, body) = get(&addr, "/status.json");
        assert_eq!(code, 200);
        let v: serde_json::Value = serde_json::from_slice(&body).unwrap();
        if !v["history"].as_array().unwrap().is_empty() && v["frame"]["agent"].is_string() {
            break v;
        }
        assert!(Instant::now() < deadline, "no update and camera frame in 150 s: {v}");
        std::thread::sleep(Duration::from_secs(1));
    };
    assert_eq!(status["job"], job.as_str());
    assert!(status["text"].as_str().unwrap().contains(&format!("job {job}")), "{status}");
    assert_eq!(status["frame"]["world"], "reinvent_wood");
    let (code, png) = get(&addr, "/camera.png");
    assert_eq!(code, 200);
    let frame = image::load_from_memory(&png).unwrap().to_luma8();
    assert_eq!((frame.width(), frame.height()), (160, 120), "the agent's camera frame");
    let (code, page) = get(&addr, "/");
    assert_eq!(code, 200);
    assert!(String::from_utf8_lossy(&page).contains("/status.json"));

    // Headless Chromium renders the page; the screenshot shows the graph and the camera.
    let shot = dir.path().join("shot.png");
    let o = Command::new(chromium())
        .args(["--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", "--window-size=1400,1000"])
        .arg("--virtual-time-budget=4000")
        .arg(format!("--screenshot={}", shot.display()))
        .arg(format!("http://{addr}/"))
        .output()
        .unwrap();
    assert!(shot.exists(), "no screenshot: {}", String::from_utf8_lossy(&o.stderr));
    check_screenshot(&shot);

    // Stop the job; `up` ends by itself.
    let o = Command::new(coordinator).args(["job", "stop", &job, "--connect", &endpoint]).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let mut up = up;
    let deadline = Instant::now() + Duration::from_secs(90);
    while up.0.try_wait().unwrap().is_none() && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(500));
    }
    assert!(up.0.try_wait().unwrap().is_some(), "up ended after the job was stopped");

    // The run's MCAP holds what the car saw in its evaluation laps, read by Foxglove's reader.
    let py = support::python("mcap");
    let o = Command::new(py).arg("-c").arg(FRAMES).arg(dir.path().join("up/run/trace.mcap")).output().unwrap();
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

/// The graph's progress line (#1f77b4) is drawn, and a camera frame (grey levels, many of
/// them) fills its box.
fn check_screenshot(shot: &Path) {
    let img = image::open(shot).unwrap().to_rgb8();
    let near = |p: &image::Rgb<u8>, c: [u8; 3]| p.0.iter().zip(c).all(|(a, b)| (*a as i32 - b as i32).abs() <= 12);
    let blue = img.pixels().filter(|p| near(p, [31, 119, 180])).count();
    assert!(blue > 100, "the progress line is drawn ({blue} pixels)");
    let mut greys = std::collections::BTreeSet::new();
    let mut grey_pixels = 0;
    for p in img.pixels() {
        let [r, g, b] = p.0;
        if r == g && g == b && r < 240 && r > 5 {
            greys.insert(r);
            grey_pixels += 1;
        }
    }
    assert!(
        grey_pixels > 50_000 && greys.len() > 20,
        "the camera frame is shown ({grey_pixels} grey pixels, {} levels)",
        greys.len()
    );
}
