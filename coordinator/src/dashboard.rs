//! `coordinator dashboard JOB`: a local web page that shows a job as it trains: the
//! console's live training graph (mean progress and reward of the recent episodes, and the
//! evaluations' progress, per iteration), the camera of one sim agent (camera jobs), the
//! job's status text (per world, per agent, when to stop), refreshed every second.
//!
//! A thin shell: a Zenoh session that asks the coordinator for the job's status every second
//! and listens to the agents' camera frames (`protocol::keys::cameras`), and a small HTTP
//! server (`tiny_http`) on loopback with three routes: `/` (the page, which draws with its
//! own script), `/status.json` and `/camera.png`.

use crate::cli::NetCli;
use crate::client::{net_args, request};
use anyhow::{Context, Result};
use protocol::job_request::Kind;
use protocol::net::zenoh;
use protocol::net::{self, DropCounters, try_next};
use protocol::{CameraFrame, keys};
use std::io::Write as _;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// One point of the live graph (one learner status with a new iteration).
#[derive(Clone, Debug, serde::Serialize)]
struct Point {
    iteration: u64,
    seconds: f64,
    progress: f64,
    reward: f64,
    eval_progress: f64,
    steps_per_s: f64,
}

#[derive(Default)]
struct Shared {
    text: String,
    state: String,
    history: Vec<Point>,
    frame_png: Option<Vec<u8>>,
    frame: serde_json::Value,
    trend: String,
}

const PAGE: &str = include_str!("dashboard.html");

/// Serve the dashboard of `job` on `bind` until killed. Prints the page's address first.
pub fn dashboard(job: String, bind: String, net_cli: NetCli) -> Result<i32> {
    let session = net::open(&net_args(&net_cli, true))?;
    let server = tiny_http::Server::http(&bind).map_err(|e| anyhow::anyhow!("listening on {bind}: {e}"))?;
    let addr = server.server_addr().to_ip().context("the server's address")?;
    println!("dashboard    http://{addr}/   (job {job}; Ctrl-C stops it)");
    std::io::stdout().flush()?;
    tracing::info!(%job, %addr, "dashboard serving");
    let shared = Arc::new(Mutex::new(Shared::default()));
    {
        let shared = shared.clone();
        let job = job.clone();
        std::thread::spawn(move || watch(&session, &job, &shared));
    }
    for req in server.incoming_requests() {
        let path = req.url().split('?').next().unwrap_or("/").to_string();
        let resp = {
            let s = shared.lock().expect("dashboard state");
            match path.as_str() {
                "/" | "/index.html" => respond(PAGE.as_bytes().to_vec(), "text/html; charset=utf-8", 200),
                "/status.json" => {
                    let v = serde_json::json!({
                        "job": job, "state": s.state, "text": s.text, "history": s.history,
                        "frame": s.frame, "trend": s.trend,
                    });
                    respond(serde_json::to_vec(&v)?, "application/json", 200)
                }
                "/camera.png" => match &s.frame_png {
                    Some(png) => respond(png.clone(), "image/png", 200),
                    None => respond(b"no camera frame yet (camera jobs only)".to_vec(), "text/plain", 404),
                },
                _ => respond(b"not found".to_vec(), "text/plain", 404),
            }
        };
        if let Err(e) = req.respond(resp) {
            tracing::debug!("dashboard: a response was not delivered: {e}");
        }
    }
    Ok(0)
}

fn respond(body: Vec<u8>, kind: &str, code: u16) -> tiny_http::Response<std::io::Cursor<Vec<u8>>> {
    let header = tiny_http::Header::from_bytes(&b"Content-Type"[..], kind.as_bytes()).expect("a valid header");
    let nocache = tiny_http::Header::from_bytes(&b"Cache-Control"[..], &b"no-store"[..]).expect("a valid header");
    tiny_http::Response::from_data(body).with_status_code(code).with_header(header).with_header(nocache)
}

/// Every second: the job's status from the coordinator; the camera frames as they come.
fn watch(session: &zenoh::Session, job: &str, shared: &Mutex<Shared>) {
    let drops = DropCounters::default();
    let frames = net::subscribe(session, &keys::cameras(job)).ok();
    let start = Instant::now();
    let mut last_status = Instant::now() - Duration::from_secs(10);
    loop {
        if let Some(sub) = &frames {
            while let Some((key, f)) = try_next::<CameraFrame>(sub, &drops) {
                let agent = keys::last(&key).to_string();
                match protocol::exchange::frame_from_wire(f, job, &agent) {
                    Ok(f) => {
                        let Some(img) = image::GrayImage::from_raw(f.width, f.height, f.gray) else { continue };
                        let mut png = std::io::Cursor::new(Vec::new());
                        if img.write_to(&mut png, image::ImageFormat::Png).is_ok() {
                            let mut s = shared.lock().expect("dashboard state");
                            s.frame_png = Some(png.into_inner());
                            s.frame = serde_json::json!({"agent": agent, "world": f.world, "policy_version": f.policy_version});
                        }
                    }
                    Err(e) => drops.refuse("a camera frame", &e),
                }
            }
        }
        if last_status.elapsed() >= Duration::from_secs(1) {
            last_status = Instant::now();
            match request(session, Kind::StatusJobId(job.to_string()), Duration::from_secs(2)) {
                Ok(r) => {
                    let rec = crate::client::status_of(&r).and_then(|st| st.record.clone()).unwrap_or_default();
                    let l = rec.learner.clone().unwrap_or_default();
                    let mut s = shared.lock().expect("dashboard state");
                    s.text = r.text;
                    s.state = if rec.job.is_some() { rec.state().name().to_string() } else { String::new() };
                    s.trend = l.trend.clone();
                    let it = l.iteration;
                    if it > 0 && s.history.last().is_none_or(|p| p.iteration != it) {
                        s.history.push(Point {
                            iteration: it,
                            seconds: start.elapsed().as_secs_f64(),
                            progress: l.window_progress,
                            reward: l.window_reward,
                            eval_progress: l.eval_progress,
                            steps_per_s: l.worlds.iter().map(|w| w.steps_per_s).sum(),
                        });
                    }
                }
                Err(e) => {
                    shared.lock().expect("dashboard state").text = format!("no answer from the coordinator: {e:#}")
                }
            }
        }
        std::thread::sleep(Duration::from_millis(100));
    }
}
