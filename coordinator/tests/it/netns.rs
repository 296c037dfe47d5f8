//! Issues 4 and 10, several hosts: coordinator and learner in one network namespace, a sim
//! agent in each of two others, joined by veth links and explicit endpoints (as root; these
//! machines allow it), every link mutual TLS with the cluster's credentials (`certs new`) as
//! the README's several-machines recipe has it. Addresses are private to the namespaces this
//! test makes and removes.

use std::path::PathBuf;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::support::{bin, need_root};

fn ip(args: &[&str]) {
    let o = Command::new("ip").args(args).output().expect("the ip command (iproute2)");
    assert!(o.status.success(), "ip {}: {}", args.join(" "), String::from_utf8_lossy(&o.stderr));
}

/// Namespaces and processes, removed when dropped.
struct Hosts {
    names: Vec<String>,
    procs: Vec<Child>,
}

impl Drop for Hosts {
    fn drop(&mut self) {
        for p in &mut self.procs {
            let _ = p.kill();
            let _ = p.wait();
        }
        for n in &self.names {
            let _ = Command::new("ip").args(["netns", "del", n]).output();
        }
    }
}

impl Hosts {
    fn run(&mut self, ns: &str, cmd: &[String], log: PathBuf) {
        let f = std::fs::File::create(log).unwrap();
        let child = Command::new("ip")
            .args(["netns", "exec", ns])
            .args(cmd)
            .stdin(Stdio::null())
            .stdout(f.try_clone().unwrap())
            .stderr(f)
            .spawn()
            .unwrap();
        self.procs.push(child);
    }

    fn exec(&self, ns: &str, cmd: &[String]) -> std::process::Output {
        Command::new("ip").args(["netns", "exec", ns]).args(cmd).output().unwrap()
    }
}

/// Issue 4: a job runs across three network namespaces as root.
#[test]
fn a_job_runs_across_three_network_namespaces_as_root() {
    need_root("network namespaces");
    let dir = tempfile::tempdir().unwrap();
    let tag = std::process::id() % 10000;
    let (a, b, c) = (format!("pdk{tag}a"), format!("pdk{tag}b"), format!("pdk{tag}c"));
    let mut hosts = Hosts { names: vec![], procs: vec![] };
    for n in [&a, &b, &c] {
        ip(&["netns", "add", n]);
        hosts.names.push(n.clone());
        ip(&["-n", n, "link", "set", "lo", "up"]);
    }
    // a <-> b on 10.213.1.0/24, a <-> c on 10.213.2.0/24 (inside these namespaces only).
    for (peer, net, i) in [(&b, 1, 'b'), (&c, 2, 'c')] {
        let (va, vp) = (format!("v{tag}a{i}"), format!("v{tag}{i}a"));
        ip(&["link", "add", &va, "netns", &a, "type", "veth", "peer", "name", &vp, "netns", peer]);
        ip(&["-n", &a, "addr", "add", &format!("10.213.{net}.1/24"), "dev", &va]);
        ip(&["-n", peer, "addr", "add", &format!("10.213.{net}.2/24"), "dev", &vp]);
        ip(&["-n", &a, "link", "set", &va, "up"]);
        ip(&["-n", peer, "link", "set", &vp, "up"]);
    }
    let s = |x: &str| x.to_string();
    let coord = bin("coordinator").display().to_string();
    let db = dir.path().join("c.redb").display().to_string();
    // The README's several-machines recipe: the cluster's credentials, every link mutual TLS.
    let certs = dir.path().join("certs").display().to_string();
    let o = Command::new(&coord).args(["certs", "new", &certs]).output().unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    // Without credentials a coordinator will not listen beyond loopback.
    let o = hosts.exec(&a, &[coord.clone(), s("serve"), s("--listen"), s("tcp/0.0.0.0:7447"), s("--db"), db.clone()]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("refusing to listen on tcp/0.0.0.0:7447"), "{err}");
    hosts.run(
        &a,
        &[coord.clone(), s("serve"), s("--listen"), s("tls/0.0.0.0:7447"), s("--certs"), certs.clone(), s("--db"), db],
        dir.path().join("coordinator.log"),
    );
    let run = dir.path().join("run").display().to_string();
    hosts.run(
        &a,
        &[
            bin("learner").display().to_string(),
            s("serve"),
            s("--connect"),
            s("tls/127.0.0.1:7447"),
            s("--certs"),
            certs.clone(),
            s("--checkpoint-seconds"),
            s("1"),
        ],
        dir.path().join("learner.log"),
    );
    for (ns, net, id) in [(&b, 1, "agent-b"), (&c, 2, "agent-c")] {
        hosts.run(
            ns,
            &[
                bin("sim-agent").display().to_string(),
                s("serve"),
                s("--connect"),
                format!("tls/10.213.{net}.1:7447"),
                s("--certs"),
                certs.clone(),
                s("--id"),
                s(id),
                s("--envs"),
                s("8"),
                s("--threads"),
                s("1"),
            ],
            dir.path().join(format!("{id}.log")),
        );
    }
    let spec = dir.path().join("job.toml");
    std::fs::write(&spec, format!("worlds = [\"reinvent_carpet\", \"reinvent_concrete\"]\nout = {run:?}\nenvs_per_agent = 8\n[stop]\nminutes = 3\ntarget_progress = 70\n")).unwrap();
    let cli = |args: &[&str]| {
        let mut v: Vec<String> = vec![coord.clone()];
        v.extend(args.iter().map(|x| x.to_string()));
        v.extend([s("--connect"), s("tls/127.0.0.1:7447"), s("--certs"), certs.clone()]);
        hosts.exec(&a, &v)
    };
    let deadline = Instant::now() + Duration::from_secs(30);
    let mut tries = Vec::new();
    loop {
        let o = cli(&["job", "start", &spec.display().to_string(), "--id", "netjob"]);
        if o.status.success() {
            break;
        }
        // A first try can start the job and still report "no coordinator answered" (its reply
        // lost while the TLS session is new; seen in about one run in six): the retry sends
        // the same document and gets that very job back.
        tries.push(format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr)));
        assert!(
            Instant::now() < deadline,
            "job start failed {} times: {tries:?}\ncoordinator: {}",
            tries.len(),
            std::fs::read_to_string(dir.path().join("coordinator.log")).unwrap_or_default()
        );
        std::thread::sleep(Duration::from_millis(500));
    }
    let deadline = Instant::now() + Duration::from_secs(150);
    let status = loop {
        let o = cli(&["job", "status", "netjob", "--json"]);
        let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap_or_default();
        if v["state"] == "finished" {
            break v;
        }
        let logs: String = ["coordinator", "learner", "agent-b", "agent-c"]
            .iter()
            .map(|n| {
                format!(
                    "\n== {n} ==\n{}",
                    std::fs::read_to_string(dir.path().join(format!("{n}.log")))
                        .unwrap_or_default()
                        .lines()
                        .rev()
                        .take(10)
                        .collect::<Vec<_>>()
                        .join("\n")
                )
            })
            .collect();
        assert!(Instant::now() < deadline, "the job did not finish; status {v}{logs}");
        std::thread::sleep(Duration::from_secs(1));
    };
    // Both agents, each on its own host, worked on the job.
    let log = String::from_utf8_lossy(&cli(&["job", "logs", "netjob"]).stdout).to_string();
    assert!(log.contains("agent agent-b assigned") && log.contains("agent agent-c assigned"), "{log}");
    for w in status["learner"]["worlds"].as_array().unwrap() {
        assert!(w["episodes"].as_u64().unwrap() > 0, "{status}");
    }
    assert!(PathBuf::from(&run).join("model/model.safetensors").exists());
}
