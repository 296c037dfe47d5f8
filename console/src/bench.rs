//! `console bench`: the console's figures, measured on a console this command starts (its
//! own roles on loopback, a fresh data folder): from Submit to the first point on the graph
//! and the first camera frame; the model page's weight; its first paint in Chromium (when
//! the tests' Python with Selenium is there); and what viewers on the live graph and camera
//! cost the training, as simulation steps a second with none and with `--viewers` watching,
//! in alternating windows of one run. It ends with a verdict.

use anyhow::{Context, Result, bail};
use serde_json::{Value, json};
use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};

/// What to measure.
#[derive(Clone, Debug, clap::Args)]
pub struct BenchArgs {
    /// Viewers on the model's live page (its event stream and each new camera frame).
    #[arg(long, default_value_t = 50)]
    pub viewers: usize,
    /// Seconds a measuring window lasts (seven, after one of warm-up: none, viewers, none, …).
    #[arg(long, default_value_t = 30)]
    pub window: u64,
    /// Sim agent processes of the console's own.
    #[arg(long, default_value_t = 2)]
    pub agents: usize,
    /// Environments per agent.
    #[arg(long, default_value_t = 8)]
    pub envs: usize,
    /// The most the viewers may cost, in % of steps a second.
    #[arg(long, default_value_t = 2.0)]
    pub budget: f64,
}

const TOKEN: &str = "bench0123456789abcdef0123456789ab";

struct Console {
    child: Child,
    addr: String,
}

impl Drop for Console {
    fn drop(&mut self) {
        let _ = Command::new("kill").arg(self.child.id().to_string()).status();
        let deadline = Instant::now() + Duration::from_secs(20);
        while self.child.try_wait().ok().flatten().is_none() && Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(100));
        }
        let _ = self.child.kill();
    }
}

fn request(addr: &str, method: &str, path: &str, body: Option<&Value>) -> Result<(u16, Vec<u8>)> {
    let mut s = TcpStream::connect(addr)?;
    s.set_read_timeout(Some(Duration::from_secs(30)))?;
    let body = body.map(Value::to_string).unwrap_or_default();
    write!(
        s,
        "{method} {path} HTTP/1.1\r\nHost: {addr}\r\nAuthorization: Bearer {TOKEN}\r\nContent-Type: application/json\r\n\
         Content-Length: {}\r\nConnection: close\r\n\r\n{body}",
        body.len()
    )?;
    let mut raw = Vec::new();
    s.read_to_end(&mut raw)?;
    let split = raw.windows(4).position(|w| w == b"\r\n\r\n").context("not an HTTP answer")?;
    let code =
        String::from_utf8_lossy(&raw[..split]).split_whitespace().nth(1).and_then(|c| c.parse().ok()).unwrap_or(0);
    Ok((code, raw[split + 4..].to_vec()))
}

fn json_of(addr: &str, path: &str) -> Result<Value> {
    let (code, body) = request(addr, "GET", path, None)?;
    if code != 200 {
        bail!("GET {path}: {code} {}", String::from_utf8_lossy(&body));
    }
    Ok(serde_json::from_slice(&body)?)
}

/// One viewer: the model's event stream, and the camera's picture at each new frame, as the
/// page does, until `stop`.
fn viewer(addr: String, model: String, stop: Arc<AtomicBool>, fetched: Arc<AtomicU64>) {
    let Ok(mut s) = TcpStream::connect(&addr) else { return };
    let _ = s.set_read_timeout(Some(Duration::from_millis(500)));
    let _ = write!(
        s,
        "GET /api/v1/models/{model}/events HTTP/1.1\r\nHost: {addr}\r\nAuthorization: Bearer {TOKEN}\r\nAccept: text/event-stream\r\n\r\n"
    );
    let mut lines = BufReader::new(s);
    let mut line = String::new();
    while !stop.load(Ordering::Relaxed) {
        line.clear();
        match lines.read_line(&mut line) {
            Ok(0) => return,
            Ok(_)
                if line.starts_with("event: camera")
                    && request(&addr, "GET", &format!("/api/v1/models/{model}/camera.png"), None).is_ok() =>
            {
                fetched.fetch_add(1, Ordering::Relaxed);
            }
            _ => {}
        }
    }
}

/// Run the benchmark; prints its figures and a verdict (0: within the budget).
pub fn run(args: &BenchArgs) -> Result<i32> {
    let data = std::env::temp_dir().join(format!("paddock-console-bench-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&data);
    let mut child = Command::new(std::env::current_exe()?)
        .args(["--listen", "127.0.0.1:0", "--token", TOKEN, "--agents", &args.agents.to_string()])
        .args(["--envs", &args.envs.to_string(), "--data"])
        .arg(&data)
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()?;
    let mut lines = BufReader::new(child.stdout.take().context("the console's output")?).lines();
    let addr = loop {
        let l = lines.next().context("the console ended before printing its address")??;
        if let Some(rest) = l.strip_prefix("console      http://") {
            break rest.split('/').next().unwrap_or("").to_string();
        }
    };
    std::thread::spawn(move || for _ in lines {});
    let console = Console { child, addr };
    let addr = console.addr.clone();
    println!(
        "console bench: {} agent(s) x {} envs on this machine, data in {}",
        args.agents,
        args.envs,
        data.display()
    );

    // The model page's weight: its HTML and every asset it loads.
    let minutes = (args.window * 9 + 60) as f64 / 60.0 + 1.0;
    let model = json!({
        "name": "bench", "tracks": ["reinvent_base"], "reward_function": "builtin:center_line",
        "model_metadata": policy::ModelMetadata::for_sensor("camera").map(|m| serde_json::from_str::<Value>(&m.to_json()).unwrap_or(Value::Null)),
        "stop": {"minutes": minutes},
    });
    // Submit, then the first point on the graph and the first camera frame, as a page sees them.
    let t0 = Instant::now();
    let (code, body) = request(&addr, "POST", "/api/v1/models", Some(&model))?;
    if code != 201 {
        bail!("creating the model: {code} {}", String::from_utf8_lossy(&body));
    }
    let created = t0.elapsed().as_secs_f64();
    let mut s = TcpStream::connect(&addr)?;
    s.set_read_timeout(Some(Duration::from_secs(120)))?;
    write!(s, "GET /api/v1/models/bench/events HTTP/1.1\r\nHost: {addr}\r\nAuthorization: Bearer {TOKEN}\r\n\r\n")?;
    let (mut first_point, mut first_frame) = (None, None);
    let mut events = BufReader::new(s);
    let mut line = String::new();
    while first_point.is_none() || first_frame.is_none() {
        line.clear();
        if events.read_line(&mut line)? == 0 || t0.elapsed() > Duration::from_secs(180) {
            bail!("no point on the graph or no camera frame within 3 minutes of Submit");
        }
        if line.starts_with("event: metrics") && first_point.is_none() {
            first_point = Some(t0.elapsed().as_secs_f64());
        }
        if line.starts_with("event: camera") && first_frame.is_none() {
            first_frame = Some(t0.elapsed().as_secs_f64());
        }
    }
    drop(events);
    let (first_point, first_frame) = (first_point.unwrap_or(0.0), first_frame.unwrap_or(0.0));
    println!(
        "submit       201 after {created:.3} s; first point on the graph after {first_point:.1} s; first camera frame after {first_frame:.1} s"
    );

    let (code, html) = request(&addr, "GET", "/models/bench", None)?;
    if code != 200 {
        bail!("the model page: {code}");
    }
    let page = String::from_utf8_lossy(&html).to_string();
    let mut weight = html.len();
    let mut assets = Vec::new();
    for part in page.split("/assets/").skip(1) {
        let name: String = part.chars().take_while(|c| *c != '"').collect();
        let (code, bytes) = request(&addr, "GET", &format!("/assets/{name}"), None)?;
        if code == 200 {
            weight += bytes.len();
            assets.push(format!("{name} {:.1} kB", bytes.len() as f64 / 1e3));
        }
    }
    println!(
        "page weight  the model page {:.1} kB: HTML {:.1} kB + {}",
        weight as f64 / 1e3,
        html.len() as f64 / 1e3,
        assets.join(", ")
    );
    let paint = first_paint(&addr);
    match &paint {
        Ok(ms) => println!("first paint  {ms:.0} ms (Chromium, the model page, median of 5 loads)"),
        Err(e) => println!("first paint  not measured: {e:#}"),
    }

    // Steps a second with no viewer and with the viewers, in alternating windows after one of
    // warm-up; and the CPU time the console itself takes against all of its roles' (on a busy
    // machine a CPU second the console takes is one the training does not get).
    let steps = |addr: &str| -> Result<f64> {
        let v = json_of(addr, "/api/v1/models/bench")?;
        Ok(v["training"]["env_steps"].as_f64().unwrap_or(0.0))
    };
    let pids = |data: &std::path::Path| -> Vec<u32> {
        std::fs::read_to_string(data.join("logs/pids.json"))
            .ok()
            .and_then(|t| serde_json::from_str::<serde_json::Map<String, Value>>(&t).ok())
            .map(|m| m.values().filter_map(|v| v.as_u64()).map(|p| p as u32).collect())
            .unwrap_or_default()
    };
    let console_pid = console.child.id();
    std::thread::sleep(Duration::from_secs(args.window));
    let mut rates = [Vec::new(), Vec::new()];
    let mut shares = [Vec::new(), Vec::new()];
    let fetched = Arc::new(AtomicU64::new(0));
    for w in 0..7 {
        let watched = w % 2 == 1;
        let stop = Arc::new(AtomicBool::new(false));
        let viewers: Vec<_> = (0..if watched { args.viewers } else { 0 })
            .map(|_| {
                let (a, s, f) = (addr.clone(), stop.clone(), fetched.clone());
                std::thread::spawn(move || viewer(a, "bench".into(), s, f))
            })
            .collect();
        std::thread::sleep(Duration::from_secs(2));
        let roles = pids(&data);
        let (s0, t0, c0, r0) =
            (steps(&addr)?, Instant::now(), cpu(console_pid), roles.iter().map(|p| cpu(*p)).sum::<f64>());
        std::thread::sleep(Duration::from_secs(args.window));
        let (s1, t1, c1, r1) =
            (steps(&addr)?, Instant::now(), cpu(console_pid), roles.iter().map(|p| cpu(*p)).sum::<f64>());
        stop.store(true, Ordering::Relaxed);
        for v in viewers {
            let _ = v.join();
        }
        let rate = (s1 - s0) / (t1 - t0).as_secs_f64();
        let share = 100.0 * (c1 - c0) / ((c1 - c0) + (r1 - r0)).max(1e-9);
        println!(
            "window {}     {:>2} viewers: {rate:>5.0} steps/s; the console used {:.2} CPU s, {share:.2} % of the CPU of the console and its roles",
            w + 1,
            if watched { args.viewers } else { 0 },
            c1 - c0
        );
        rates[usize::from(watched)].push(rate);
        shares[usize::from(watched)].push(share);
    }
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len().max(1) as f64;
    let (none, watched) = (mean(&rates[0]), mean(&rates[1]));
    // Training speeds up as episodes lengthen: each watched window against the mean of the
    // unwatched windows on either side of it.
    let by_steps = 100.0
        * mean(
            &rates[1]
                .iter()
                .enumerate()
                .map(|(i, w)| 1.0 - w / ((rates[0][i] + rates[0][i + 1]) / 2.0).max(1e-9))
                .collect::<Vec<_>>(),
        );
    let cost = mean(&shares[1]) - mean(&shares[0]);
    println!(
        "viewers      {} viewers fetched {} camera frames; {watched:.0} steps/s watched against {none:.0} unwatched; each watched \
         window against its neighbours: {by_steps:+.1} % (the windows' spread shows how far steps/s alone can be trusted)",
        args.viewers,
        fetched.load(Ordering::Relaxed)
    );
    println!(
        "cpu          the console took {:.2} % of the CPU watched and {:.2} % unwatched: the viewers cost {cost:.2} % of the training's CPU",
        mean(&shares[1]),
        mean(&shares[0])
    );
    if let Ok(v) = json_of(&addr, "/api/v1/models/bench") {
        println!(
            "the model  {} after {} updates, {} env steps{}",
            v["status"].as_str().unwrap_or("?"),
            v["training"]["iteration"],
            v["training"]["env_steps"],
            v["training"]["stop_reason"]
                .as_str()
                .filter(|r| !r.is_empty())
                .map(|r| format!("; stop: {r}"))
                .unwrap_or_default()
        );
    }
    drop(console);
    let _ = std::fs::remove_dir_all(&data);
    let ok = cost < args.budget;
    println!(
        "verdict      {}: {} viewers cost the training {cost:.2} % of its CPU, the steps a second it could make (budget {} %)",
        if ok { "PASS" } else { "FAIL" },
        args.viewers,
        args.budget
    );
    Ok(if ok { 0 } else { 1 })
}

/// CPU seconds (user and system) process `pid` has used (0 when it is gone).
fn cpu(pid: u32) -> f64 {
    let Ok(stat) = std::fs::read_to_string(format!("/proc/{pid}/stat")) else { return 0.0 };
    // The fields after the command's closing parenthesis: utime and stime are the 12th and 13th.
    let rest = stat.rsplit_once(')').map(|(_, r)| r).unwrap_or("");
    let f: Vec<&str> = rest.split_whitespace().collect();
    let tick = |i: usize| f.get(i).and_then(|x| x.parse::<f64>().ok()).unwrap_or(0.0);
    // Clock ticks: 100 a second on Linux's every common configuration (USER_HZ).
    (tick(11) + tick(12)) / 100.0
}

/// The model page's first contentful paint in Debian's Chromium (ms, median of 5 loads), by
/// Selenium in the tests' Python (`PADDOCK_PYTHON`, made by `./paddock test`).
fn first_paint(addr: &str) -> Result<f64> {
    let python = std::env::var_os("PADDOCK_PYTHON")
        .map(PathBuf::from)
        .context("PADDOCK_PYTHON is not set (./paddock test makes target/pyenv with Selenium)")?;
    let o = Command::new(python).arg("-c").arg(PAINT).args([addr, TOKEN]).output()?;
    if !o.status.success() {
        bail!("{}", String::from_utf8_lossy(&o.stderr).lines().last().unwrap_or("Selenium failed"));
    }
    String::from_utf8_lossy(&o.stdout).trim().parse::<f64>().context("the paint's time")
}

const PAINT: &str = r#"
import statistics, sys, tempfile
from selenium import webdriver
from selenium.webdriver.chrome.service import Service
addr, token = sys.argv[1], sys.argv[2]
opts = webdriver.ChromeOptions()
for a in ["--headless=new", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-background-networking",
          "--disable-component-update", "--disable-sync", "--user-data-dir=" + tempfile.mkdtemp()]:
    opts.add_argument(a)
opts.binary_location = "/usr/bin/chromium"
d = webdriver.Chrome(service=Service("/usr/bin/chromedriver"), options=opts)
try:
    d.get("http://%s/?token=%s" % (addr, token))
    times = []
    for _ in range(5):
        d.get("http://%s/models/bench" % addr)
        t = d.execute_script("var p = performance.getEntriesByName('first-contentful-paint'); return p.length ? p[0].startTime : null")
        if t is not None:
            times.append(t)
    print(statistics.median(times))
finally:
    d.quit()
"#;
