//! `coordinator bench scale`: N machines, each in a network namespace of its own with its
//! own address (a veth link to a bridge in the hub's namespace), join one coordinator with
//! one token; then a signed model is broadcast to all of them, round after round, over
//! Zenoh's peer mesh and through a router. Measured: the time until all have joined, and
//! the time from publication until every machine holds the model (its signature and hash
//! checked by each), against N; every copy counted, and no transport closed.
//!
//! The machines are `bench scale-receive` processes with the credentials their join wrote
//! (agent slots, as sim agents would hold); the publisher is `bench scale-send` with the
//! learner's certificate and the cluster's model-signing key. Needs root (network
//! namespaces, as the suite's several-hosts test).

use anyhow::{Context, Result, bail};
use protocol::net::{self, NetArgs, zenoh};
use protocol::secure::Role;
use protocol::{PROTOCOL_VERSION, PolicyUpdate, keys};
use sha2::Digest;
use std::io::Write;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};
use zenoh::Wait;

/// The hub's address on the bridge; machine `i` (from 1) is `10.54.X.(i+1)`.
const NET: &str = "10.54.0";

fn ip(args: &[&str]) -> Result<()> {
    let o = Command::new("ip").args(args).output().context("the ip command (iproute2)")?;
    anyhow::ensure!(o.status.success(), "ip {}: {}", args.join(" "), String::from_utf8_lossy(&o.stderr).trim());
    Ok(())
}

/// The namespaces of one run and the processes in them, removed when dropped.
struct Lab {
    hub: String,
    machines: Vec<String>,
    procs: Vec<Child>,
}

impl Drop for Lab {
    fn drop(&mut self) {
        for p in &mut self.procs {
            let _ = p.kill();
            let _ = p.wait();
        }
        for n in self.machines.iter().chain([&self.hub]) {
            let _ = Command::new("ip").args(["netns", "del", n]).output();
        }
    }
}

impl Lab {
    /// A hub namespace with a bridge, and `n` machine namespaces linked to it.
    fn new(n: usize) -> Result<Lab> {
        let tag = std::process::id() % 10000;
        let hub = format!("pdks{tag}h");
        let mut lab = Lab { hub: hub.clone(), machines: Vec::new(), procs: Vec::new() };
        ip(&["netns", "add", &hub])?;
        ip(&["-n", &hub, "link", "set", "lo", "up"])?;
        ip(&["-n", &hub, "link", "add", "br0", "type", "bridge"])?;
        ip(&["-n", &hub, "addr", "add", &format!("{NET}.1/24"), "dev", "br0"])?;
        ip(&["-n", &hub, "link", "set", "br0", "up"])?;
        for i in 1..=n {
            let ns = format!("pdks{tag}m{i}");
            ip(&["netns", "add", &ns])?;
            lab.machines.push(ns.clone());
            ip(&["-n", &ns, "link", "set", "lo", "up"])?;
            let (h, m) = (format!("vh{i}"), format!("vm{i}"));
            ip(&["link", "add", &h, "netns", &hub, "type", "veth", "peer", "name", &m, "netns", &ns])?;
            ip(&["-n", &hub, "link", "set", &h, "master", "br0"])?;
            ip(&["-n", &hub, "link", "set", &h, "up"])?;
            ip(&["-n", &ns, "addr", "add", &format!("{NET}.{}/24", i + 1), "dev", &m])?;
            ip(&["-n", &ns, "link", "set", &m, "up"])?;
        }
        Ok(lab)
    }

    fn command(&self, ns: &str, bin: &Path, args: &[String]) -> Command {
        let mut c = Command::new("ip");
        c.args(["netns", "exec", ns]).arg(bin).args(args);
        c
    }

    fn spawn(&mut self, ns: &str, bin: &Path, args: &[String], log: &Path) -> Result<()> {
        let f = std::fs::File::create(log)?;
        let child = self.command(ns, bin, args).stdin(Stdio::null()).stdout(f.try_clone()?).stderr(f).spawn()?;
        self.procs.push(child);
        Ok(())
    }
}

/// What one run measured.
struct Row {
    topology: &'static str,
    n: usize,
    join_s: f64,
    p50_ms: f64,
    worst_ms: f64,
    copies: usize,
    expected: usize,
    bad: usize,
    closed: usize,
}

fn s(v: &[&str]) -> Vec<String> {
    v.iter().map(|x| x.to_string()).collect()
}

/// `bench scale --machines 1,2,4,8,16 --rounds R`.
pub fn scale(machines: &[usize], rounds: usize, out: &Path) -> Result<i32> {
    anyhow::ensure!(
        !machines.is_empty() && machines.iter().all(|n| (1..=200).contains(n)),
        "--machines: 1 to 200 each"
    );
    anyhow::ensure!(rounds >= 1, "--rounds: at least 1");
    if out.exists() {
        bail!("{} exists: pass another --out, or delete it", out.display());
    }
    std::fs::create_dir_all(out)?;
    let out = out.canonicalize()?;
    let me = std::env::current_exe()?;
    let sim_agent = coordinator::supervise::sibling("sim-agent")?;
    std::fs::write(out.join("router.json5"), "{ mode: \"router\", scouting: { multicast: { enabled: false } } }\n")?;
    std::fs::write(out.join("client.json5"), "{ mode: \"client\", scouting: { multicast: { enabled: false } } }\n")?;
    println!(
        "# coordinator bench scale: machines in network namespaces of their own, joined with one token each run; a signed SHALLOW camera model broadcast {rounds} times"
    );
    let mut rows = Vec::new();
    for topology in ["peer mesh", "router"] {
        for &n in machines {
            let dir = out.join(format!("{}-{n}", topology.replace(' ', "-")));
            std::fs::create_dir_all(&dir)?;
            let row = run(topology, n, rounds, &dir, &out, &me, &sim_agent)
                .with_context(|| format!("{topology}, {n} machine(s): logs in {}", dir.display()))?;
            println!(
                "{topology:>9} N={n:>3}: all joined in {:.2} s; model to all p50 {:.0} ms, worst {:.0} ms; {} of {} copies, {} bad, {} transports closed",
                row.join_s, row.p50_ms, row.worst_ms, row.copies, row.expected, row.bad, row.closed
            );
            rows.push(row);
        }
    }
    println!();
    println!(
        "| topology | machines | all joined (s) | model to all, p50 (ms) | worst (ms) | copies held | bad | transports closed |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    for r in &rows {
        println!(
            "| {} | {} | {:.2} | {:.0} | {:.0} | {}/{} | {} | {} |",
            r.topology, r.n, r.join_s, r.p50_ms, r.worst_ms, r.copies, r.expected, r.bad, r.closed
        );
    }
    let ok = rows.iter().all(|r| r.copies == r.expected && r.bad == 0 && r.closed == 0);
    println!("verdict: {} (every copy held and checked, no transport closed)", if ok { "PASS" } else { "FAIL" });
    Ok(if ok { 0 } else { 1 })
}

fn run(topology: &str, n: usize, rounds: usize, dir: &Path, out: &Path, me: &Path, sim_agent: &Path) -> Result<Row> {
    let mut lab = Lab::new(n)?;
    // A cluster of its own for each run: its slots are this run's machines.
    let ca_dir = dir.join("ca");
    coordinator::certs::write(&ca_dir, false, &[(Role::Agent, n as u32), (Role::Learner, 1), (Role::Car, 0)])?;
    let ca = ca_dir.display().to_string();
    let ep = format!("tls/{NET}.1:7447");
    let router = topology == "router";
    let hub = lab.hub.clone();
    let mut serve = s(&["serve", "--certs", &ca, "--listen", &ep, "--join-listen", &format!("{NET}.1:7449")]);
    serve.extend(s(&["--db", &dir.join("c.redb").display().to_string()]));
    if router {
        serve.extend(s(&["-c", &out.join("router.json5").display().to_string()]));
    }
    lab.spawn(&hub, me, &serve, &dir.join("coordinator.log"))?;
    // The token, as an operator on the hub.
    let t0 = Instant::now();
    let token = loop {
        let mut args = s(&["token", "create", "--role", "agent", "--uses", &n.to_string(), "--connect", &ep]);
        args.extend(s(&["--certs", &ca]));
        let o = lab.command(&hub, me, &args).output()?;
        if o.status.success() {
            break String::from_utf8_lossy(&o.stdout).trim().to_string();
        }
        anyhow::ensure!(t0.elapsed() < Duration::from_secs(60), "token create: {}", String::from_utf8_lossy(&o.stderr));
        std::thread::sleep(Duration::from_millis(300));
    };
    // Every machine joins at once.
    let t0 = Instant::now();
    let joins: Vec<Child> = lab
        .machines
        .iter()
        .enumerate()
        .map(|(i, ns)| {
            let certs = dir.join(format!("m{}", i + 1)).display().to_string();
            lab.command(ns, sim_agent, &s(&["join", &token, "--certs", &certs]))
                .stdout(Stdio::piped())
                .stderr(Stdio::piped())
                .spawn()
                .map_err(anyhow::Error::from)
        })
        .collect::<Result<_>>()?;
    for (i, j) in joins.into_iter().enumerate() {
        let o = j.wait_with_output()?;
        anyhow::ensure!(o.status.success(), "machine {} join: {}", i + 1, String::from_utf8_lossy(&o.stderr));
    }
    let join_s = t0.elapsed().as_secs_f64();
    // The machines: each holds its joined credentials and checks every model it receives.
    let machines = lab.machines.clone();
    for (i, ns) in machines.iter().enumerate() {
        let mut args = s(&["bench", "scale-receive", "--connect", &ep, "--certs"]);
        args.push(dir.join(format!("m{}", i + 1)).display().to_string());
        args.extend(s(&["--record", &dir.join(format!("m{}.txt", i + 1)).display().to_string()]));
        if router {
            args.extend(s(&["-c", &out.join("client.json5").display().to_string()]));
        }
        lab.spawn(ns, me, &args, &dir.join(format!("m{}.log", i + 1)))?;
    }
    let t0 = Instant::now();
    while (1..=n).any(|i| !std::fs::read_to_string(dir.join(format!("m{i}.txt"))).is_ok_and(|t| t.starts_with("ready")))
    {
        anyhow::ensure!(t0.elapsed() < Duration::from_secs(60), "the machines were not all subscribed within 60 s");
        std::thread::sleep(Duration::from_millis(200));
    }
    // Let the links settle (the mesh's peers find each other by gossip).
    std::thread::sleep(Duration::from_secs(3));
    let mut args = s(&["bench", "scale-send", "--connect", &ep, "--certs", &ca, "--rounds", &rounds.to_string()]);
    args.extend(s(&["--record", &dir.join("sent.txt").display().to_string()]));
    if router {
        args.extend(s(&["-c", &out.join("client.json5").display().to_string()]));
    }
    let o = lab.command(&hub, me, &args).output()?;
    anyhow::ensure!(o.status.success(), "scale-send: {}", String::from_utf8_lossy(&o.stderr));
    std::thread::sleep(Duration::from_secs(3));
    // Publication times and hashes, then each machine's receipts.
    let sent: Vec<(u64, u128, String)> = std::fs::read_to_string(dir.join("sent.txt"))?
        .lines()
        .filter_map(|l| {
            let mut w = l.split_whitespace();
            Some((w.next()?.parse().ok()?, w.next()?.parse().ok()?, w.next()?.to_string()))
        })
        .collect();
    let mut last_ms = vec![0.0f64; sent.len()];
    let (mut copies, mut bad) = (0, 0);
    for i in 1..=n {
        let text = std::fs::read_to_string(dir.join(format!("m{i}.txt")))?;
        for l in text.lines().skip(1) {
            let w: Vec<&str> = l.split_whitespace().collect();
            let [v, at, hash, verdict] = w.as_slice() else { continue };
            let (Ok(v), Ok(at)) = (v.parse::<u64>(), at.parse::<u128>()) else { continue };
            let Some(k) = sent.iter().position(|x| x.0 == v) else { continue };
            if *verdict != "ok" || *hash != sent[k].2 {
                bad += 1;
                continue;
            }
            copies += 1;
            last_ms[k] = last_ms[k].max(at.saturating_sub(sent[k].1) as f64 / 1e6);
        }
    }
    let mut lat = last_ms.clone();
    lat.sort_by(f64::total_cmp);
    // Transports closed: Zenoh logs each close it did not ask for.
    let closed = (1..=n)
        .map(|i| std::fs::read_to_string(dir.join(format!("m{i}.log"))).unwrap_or_default())
        .map(|log| log.lines().filter(|l| l.contains("Closing") || l.contains("closed transport")).count())
        .sum();
    Ok(Row {
        topology: if router { "router" } else { "peer mesh" },
        n,
        join_s,
        p50_ms: lat.get(lat.len() / 2).copied().unwrap_or(f64::NAN),
        worst_ms: lat.last().copied().unwrap_or(f64::NAN),
        copies,
        expected: n * sent.len(),
        bad,
        closed,
    })
}

fn unix_ns() -> u128 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_nanos()).unwrap_or(0)
}

/// The job the broadcasts are for.
const JOB: &str = "scale";

/// `bench scale-receive`: a joined machine holding every model broadcast, each checked
/// (signed by the cluster's key, its weights' hash); `record` gets "ready", then one line per
/// model: version, arrival (unix ns), the weights' sha256, ok or why not.
pub fn receive(net: NetArgs, record: &Path) -> Result<i32> {
    let dir = net.certs.clone().context("--certs: the folder `join` wrote")?;
    let id = protocol::secure::only_id(&dir, Role::Agent).context("no agent certificate of a machine's own there")?;
    let session = net::open(&net.as_machine(Role::Agent, &id))?;
    let trust = policy::signature::TrustedKeys::load(&[dir.join(protocol::secure::MODEL_PUB_FILE)])?;
    let (tx, rx) = std::sync::mpsc::channel::<(u128, Vec<u8>)>();
    let _sub = session
        .declare_subscriber(keys::policy(JOB))
        .callback(move |sample| {
            let _ = tx.send((unix_ns(), sample.payload().to_bytes().to_vec()));
        })
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let mut f = std::fs::File::create(record)?;
    writeln!(f, "ready {id}")?;
    while let Ok((at, bytes)) = rx.recv() {
        let line = match protocol::decode::<PolicyUpdate>(&bytes) {
            Ok(u) => {
                let hash = hex::encode(sha2::Sha256::digest(&u.weights));
                let verdict = protocol::exchange::policy_signature(&u).map_err(|e| e.to_string()).and_then(|sig| {
                    let sig = sig.context("unsigned").map_err(|e| e.to_string())?;
                    trust
                        .verify(&sig, &u.weights, &u.model_metadata_json, &u.manifest_json)
                        .map(|_| ())
                        .map_err(|e| e.to_string())
                });
                match verdict {
                    Ok(()) => format!("{} {at} {hash} ok", u.policy_version),
                    Err(e) => format!("{} {at} {hash} refused:{}", u.policy_version, e.replace(' ', "_")),
                }
            }
            Err(e) => format!("0 {at} - malformed:{}", e.to_string().replace(' ', "_")),
        };
        writeln!(f, "{line}")?;
        f.flush()?;
    }
    Ok(0)
}

/// `bench scale-send`: `rounds` signed models published as the learner, 1.5 s apart;
/// `record` gets one line per model: version, publication (unix ns), the weights' sha256.
pub fn send(net: NetArgs, rounds: usize, record: &Path) -> Result<i32> {
    let dir = net.certs.clone().context("--certs: the cluster's folder")?;
    let signer = policy::signature::Signer::load(&dir.join(protocol::secure::MODEL_KEY_FILE))?;
    let session = net::open(&net.as_role(Role::Learner))?;
    let publisher = session
        .declare_publisher(keys::policy(JOB))
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    std::thread::sleep(Duration::from_secs(2));
    let folder = crate::bench::camera_model("DEEP_CONVOLUTIONAL_NETWORK_SHALLOW")?;
    let (m, man, mut w) = policy::folder::to_parts(&folder);
    let mut f = std::fs::File::create(record)?;
    for v in 1..=rounds as u64 {
        // A different model each round (its weights' last byte), so each hash is its own.
        if let Some(b) = w.last_mut() {
            *b = b.wrapping_add(1);
        }
        let sig = signer.sign(&w, &m, &man);
        let u = PolicyUpdate {
            protocol_version: PROTOCOL_VERSION,
            job_id: JOB.into(),
            policy_version: v,
            weights: w.clone(),
            model_metadata_json: m.clone(),
            manifest_json: man.clone(),
            signature_json: serde_json::to_string(&sig)?,
        };
        let bytes = protocol::encode(&u);
        let at = unix_ns();
        publisher.put(bytes).wait().map_err(|e| anyhow::anyhow!("{e}"))?;
        writeln!(f, "{v} {at} {}", hex::encode(sha2::Sha256::digest(&w)))?;
        std::thread::sleep(Duration::from_millis(1500));
    }
    Ok(0)
}
