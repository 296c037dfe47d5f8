//! Roles as child processes of one command (`up`, the console on one machine): started
//! with their output in a log file, started again when they exit (the learner from its last
//! checkpoint, the coordinator from its database), and killed with the value that holds them.

use anyhow::{Context, Result, bail};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};

/// One supervised role: how to start it again.
pub struct Role {
    name: String,
    child: Child,
    bin: PathBuf,
    args: Vec<String>,
    log: PathBuf,
    restarts: u32,
}

/// Children that are killed when this value is dropped.
pub struct Children(pub Vec<Role>);

impl Drop for Children {
    fn drop(&mut self) {
        for r in &mut self.0 {
            let _ = r.child.kill();
        }
        for r in &mut self.0 {
            let _ = r.child.wait();
        }
    }
}

/// Restarts of one role before `up` gives up on the job.
const MAX_RESTARTS: u32 = 10;

/// `logs/pids.json`, replaced whole (a reader never sees half of it).
pub fn write_pids(logs: &Path, children: &Children) -> Result<()> {
    let tmp = logs.join(".pids.json.tmp");
    std::fs::write(&tmp, children.pids().to_string())?;
    std::fs::rename(&tmp, logs.join("pids.json"))?;
    Ok(())
}

/// Start `bin` with `args`, its output appended to `log`.
pub fn start(bin: &Path, args: &[String], log: &Path) -> Result<Child> {
    let out = std::fs::OpenOptions::new().create(true).append(true).open(log)?;
    Command::new(bin)
        .args(args)
        .stdin(Stdio::null())
        .stdout(out.try_clone()?)
        .stderr(out)
        .spawn()
        .with_context(|| format!("starting {}", bin.display()))
}

impl Children {
    /// Start again every role that exited (the learner resumes from its last checkpoint, the
    /// coordinator from its database); what happened, one line each.
    pub fn supervise(&mut self) -> Result<Vec<String>> {
        let mut events = Vec::new();
        for r in &mut self.0 {
            let Ok(Some(status)) = r.child.try_wait() else { continue };
            if r.restarts >= MAX_RESTARTS {
                bail!("{} exited {} times (last: {status}); see {}", r.name, r.restarts + 1, r.log.display());
            }
            r.restarts += 1;
            r.child = start(&r.bin, &r.args, &r.log)?;
            events
                .push(format!("up: {} exited ({status}) and was restarted ({} of {MAX_RESTARTS})", r.name, r.restarts));
        }
        Ok(events)
    }

    /// Kill the role `name` and start it again at once (a deliberate restart: not counted
    /// against its restarts).
    pub fn restart(&mut self, name: &str) -> Result<()> {
        let r = self.0.iter_mut().find(|r| r.name == name).with_context(|| format!("no role named {name}"))?;
        let _ = r.child.kill();
        let _ = r.child.wait();
        r.child = start(&r.bin, &r.args, &r.log)?;
        Ok(())
    }

    /// The process id of each role, by name (for `logs/pids.json`).
    pub fn pids(&self) -> serde_json::Value {
        self.0
            .iter()
            .map(|r| (r.name.clone(), serde_json::json!(r.child.id())))
            .collect::<serde_json::Map<_, _>>()
            .into()
    }
}

/// A sibling binary of this one (`target/release/learner` next to `coordinator`).
pub fn sibling(name: &str) -> Result<PathBuf> {
    let me = std::env::current_exe()?;
    let p = me.with_file_name(name);
    if !p.exists() {
        bail!(
            "{} not found next to {}: build every role with `cargo build --release --workspace` (./paddock does)",
            p.display(),
            me.display()
        );
    }
    Ok(p)
}

/// A free TCP port on loopback, below the kernel's ephemeral range where it can: a port the
/// kernel hands out for a bind to port 0 (every Zenoh session listens on one) can be taken
/// by another process between this pick and the role's own bind, and whoever connects to it
/// then meets that process (seen: a console connecting to itself).
pub fn free_port() -> Result<u16> {
    let ephemeral = std::fs::read_to_string("/proc/sys/net/ipv4/ip_local_port_range")
        .ok()
        .and_then(|s| s.split_whitespace().next()?.parse::<u16>().ok())
        .unwrap_or(32768);
    let floor = 10_000.min(ephemeral / 2);
    if ephemeral > floor + 1000 {
        for _ in 0..100 {
            let port = rand::random_range(floor..ephemeral);
            if std::net::TcpListener::bind(("127.0.0.1", port)).is_ok() {
                return Ok(port);
            }
        }
    }
    Ok(std::net::TcpListener::bind("127.0.0.1:0")?.local_addr()?.port())
}

/// Start a role (`args` then `common`, output to `log`, started afresh) and hold it in
/// `children`.
pub fn spawn(
    children: &mut Children,
    name: &str,
    bin: &Path,
    args: &[String],
    common: &[String],
    log: &Path,
) -> Result<()> {
    let args: Vec<String> = args.iter().chain(common).cloned().collect();
    let _ = std::fs::remove_file(log);
    let child = start(bin, &args, log)?;
    children.0.push(Role {
        name: name.to_string(),
        child,
        bin: bin.to_path_buf(),
        args,
        log: log.to_path_buf(),
        restarts: 0,
    });
    Ok(())
}
