//! What the console's tests share: a console started in a data folder and stopped as a user
//! stops it (SIGTERM, which stops its roles too), and a small HTTP/1.1 client.

use std::io::{BufRead, BufReader, Read, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// The token the tests give the console.
pub const TOKEN: &str = "0123456789abcdef0123456789abcdef";

/// A role binary built beside this test's `console`.
pub fn bin(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_BIN_EXE_console")).with_file_name(name)
}

/// A running console: its address (host:port) and its coordinator's endpoint.
pub struct Console {
    child: Child,
    /// host:port
    pub addr: String,
    /// The coordinator's Zenoh endpoint (the console started it).
    pub endpoint: String,
}

impl Console {
    /// Start `console` on one machine (one agent) with its data in `data`.
    pub fn start(data: &Path) -> Console {
        Console::with_agents(data, 1)
    }

    /// Start `console` on one machine with `agents` sim agents.
    pub fn with_agents(data: &Path, agents: usize) -> Console {
        Console::with_args(data, agents, &[])
    }

    /// Start `console` on one machine with `agents` sim agents and more flags.
    pub fn with_args(data: &Path, agents: usize, extra: &[&str]) -> Console {
        // Loopback unless the test names where.
        let listen: &[&str] = if extra.contains(&"--listen") { &[] } else { &["--listen", "127.0.0.1:0"] };
        let mut child = Command::new(env!("CARGO_BIN_EXE_console"))
            .args(listen)
            .args(["--agents", &agents.to_string(), "--envs", "8", "--token", TOKEN])
            .args(extra)
            .arg("--data")
            .arg(data)
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .unwrap();
        let mut lines = BufReader::new(child.stdout.take().unwrap()).lines();
        let (mut addr, mut endpoint) = (None, None);
        while addr.is_none() {
            let l = lines.next().expect("the console ended before printing its address").unwrap();
            if let Some(rest) = l.strip_prefix("roles        coordinator on ") {
                endpoint = Some(rest.split(',').next().unwrap().to_string());
            }
            if let Some(rest) =
                l.strip_prefix("console      http://").or_else(|| l.strip_prefix("console      https://"))
            {
                // With users the console asks for a login; without, the address carries the token.
                match rest.split_once("/?token=") {
                    Some((a, t)) => {
                        assert_eq!(t, TOKEN);
                        addr = Some(a.to_string());
                    }
                    None => addr = Some(rest.strip_suffix("/login").expect("the login page's address").to_string()),
                }
            }
        }
        std::thread::spawn(move || for _ in lines {});
        Console { child, addr: addr.unwrap(), endpoint: endpoint.expect("the roles' line") }
    }

    /// Stop it as Ctrl-C or a service manager does, and wait for it (and its roles) to end.
    pub fn stop(mut self) {
        self.terminate();
    }

    fn terminate(&mut self) {
        let _ = Command::new("kill").arg(self.child.id().to_string()).status();
        let deadline = Instant::now() + Duration::from_secs(20);
        while self.child.try_wait().unwrap().is_none() {
            if Instant::now() > deadline {
                let _ = self.child.kill();
                panic!("the console did not stop within 20 s of SIGTERM");
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    /// A request with the token as a Bearer header.
    pub fn api(&self, method: &str, path: &str, body: Option<&serde_json::Value>) -> Reply {
        let auth = format!("Bearer {TOKEN}");
        let body = body.map(|b| b.to_string());
        http(
            &self.addr,
            method,
            path,
            &[("Authorization", &auth), ("Content-Type", "application/json")],
            body.as_deref().map(str::as_bytes),
        )
    }
}

impl Drop for Console {
    fn drop(&mut self) {
        if self.child.try_wait().ok().flatten().is_none() {
            self.terminate();
        }
    }
}

/// An HTTP answer.
pub struct Reply {
    /// Status code.
    pub code: u16,
    /// Headers, names in lower case.
    pub headers: Vec<(String, String)>,
    /// The body.
    pub body: Vec<u8>,
}

impl Reply {
    /// The body as JSON.
    pub fn json(&self) -> serde_json::Value {
        serde_json::from_slice(&self.body)
            .unwrap_or_else(|e| panic!("not JSON ({e}): {}", String::from_utf8_lossy(&self.body)))
    }
    /// A header's value.
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers.iter().find(|(k, _)| k == name).map(|(_, v)| v.as_str())
    }
}

/// One HTTP/1.1 request (`Connection: close`).
pub fn http(addr: &str, method: &str, path: &str, headers: &[(&str, &str)], body: Option<&[u8]>) -> Reply {
    let mut s = std::net::TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(60))).unwrap();
    let mut req = format!("{method} {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n");
    for (k, v) in headers {
        req.push_str(&format!("{k}: {v}\r\n"));
    }
    req.push_str(&format!("Content-Length: {}\r\n\r\n", body.map_or(0, <[u8]>::len)));
    s.write_all(req.as_bytes()).unwrap();
    if let Some(b) = body {
        s.write_all(b).unwrap();
    }
    let mut raw = Vec::new();
    s.read_to_end(&mut raw).unwrap();
    let split = raw.windows(4).position(|w| w == b"\r\n\r\n").expect("an HTTP response");
    let head = String::from_utf8_lossy(&raw[..split]).to_string();
    let mut lines = head.lines();
    let code = lines.next().and_then(|l| l.split_whitespace().nth(1)).and_then(|c| c.parse().ok()).unwrap_or(0);
    let headers: Vec<(String, String)> = lines
        .filter_map(|l| l.split_once(':'))
        .map(|(k, v)| (k.trim().to_ascii_lowercase(), v.trim().to_string()))
        .collect();
    let mut body = raw[split + 4..].to_vec();
    if headers.iter().any(|(k, v)| k == "transfer-encoding" && v.contains("chunked")) {
        let mut out = Vec::new();
        let mut rest = &body[..];
        while let Some(eol) = rest.windows(2).position(|w| w == b"\r\n") {
            let n = usize::from_str_radix(String::from_utf8_lossy(&rest[..eol]).trim(), 16).unwrap_or(0);
            if n == 0 {
                break;
            }
            out.extend_from_slice(&rest[eol + 2..eol + 2 + n]);
            rest = &rest[eol + 2 + n + 2..];
        }
        body = out;
    }
    Reply { code, headers, body }
}

/// Poll `f` every 500 ms until it gives `Some`, at most `secs`.
pub fn wait_for<T>(secs: u64, what: &str, mut f: impl FnMut() -> Option<T>) -> T {
    let deadline = Instant::now() + Duration::from_secs(secs);
    loop {
        if let Some(v) = f() {
            return v;
        }
        assert!(Instant::now() < deadline, "{what}: not within {secs} s");
        std::thread::sleep(Duration::from_millis(500));
    }
}

/// A state-vector model's metadata (it trains to a verified model in seconds).
pub fn state_metadata() -> serde_json::Value {
    let actions: Vec<serde_json::Value> = [1.0, 2.0]
        .iter()
        .flat_map(|s| [-30.0, -15.0, 0.0, 15.0, 30.0].map(|a| serde_json::json!({"steering_angle": a, "speed": s})))
        .collect();
    serde_json::json!({
        "action_space": actions, "sensor": ["STATE_VECTOR"], "neural_network": "PADDOCK_MLP",
        "training_algorithm": "clipped_ppo", "version": "5",
    })
}
