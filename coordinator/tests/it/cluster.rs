//! Real processes, real Zenoh on loopback (and across network namespaces).

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

use crate::support::{bin, free_port};

/// One cluster at a time: each test starts several processes that want both cores, and
/// timings (flow control, updates to the end of a job) mean something only on a quiet machine.
/// `./paddock test` runs every test in its own process and these alone (.config/nextest.toml);
/// this lock keeps them apart under plain `cargo test` too, where they share a process.
static ONE_AT_A_TIME: std::sync::Mutex<()> = std::sync::Mutex::new(());

fn exclusive() -> std::sync::MutexGuard<'static, ()> {
    ONE_AT_A_TIME.lock().unwrap_or_else(|e| e.into_inner())
}

/// Processes killed when dropped.
struct Procs(Vec<(String, Child)>);

impl Drop for Procs {
    fn drop(&mut self) {
        for (_, c) in &mut self.0 {
            let _ = c.kill();
            let _ = c.wait();
        }
    }
}

impl Procs {
    fn spawn(&mut self, name: &str, cmd: &mut Command, log: &Path) {
        let f = std::fs::File::create(log).unwrap();
        // The roles' own allocator settings, whatever the test's environment says.
        cmd.env_remove(protocol::secure::PURGE_DELAY_VAR).env_remove("MIMALLOC_RESET_DELAY");
        let child = cmd.stdin(Stdio::null()).stdout(f.try_clone().unwrap()).stderr(f).spawn().unwrap();
        self.0.push((name.into(), child));
    }

    fn pid(&self, name: &str) -> u32 {
        self.0.iter().find(|(n, _)| n == name).unwrap().1.id()
    }

    fn kill(&mut self, name: &str) {
        let i = self.0.iter().position(|(n, _)| n == name).unwrap();
        let (_, mut c) = self.0.remove(i);
        c.kill().unwrap(); // SIGKILL
        c.wait().unwrap();
    }
}

struct Cluster {
    dir: tempfile::TempDir,
    endpoint: String,
    /// `--certs DIR` for every role and CLI call once [`Cluster::secure`] made credentials.
    certs: Vec<String>,
    /// Arguments every learner gets (a team's shared signing key).
    learner_args: Vec<String>,
    procs: Procs,
    // Last: released after the processes are gone.
    _turn: std::sync::MutexGuard<'static, ()>,
}

impl Cluster {
    fn new() -> Cluster {
        let dir = tempfile::tempdir().unwrap();
        let turn = exclusive();
        Cluster {
            _turn: turn,
            endpoint: format!("tcp/127.0.0.1:{}", free_port()),
            certs: vec![],
            learner_args: vec![],
            dir,
            procs: Procs(vec![]),
        }
    }

    /// One signing key for every learner from now on, as a team spread over machines needs
    /// (agents take one key's policies per job).
    fn shared_signing_key(&mut self) {
        let (secret, _) = policy::signature::Signer::generate().write_pair(&self.path("team")).unwrap();
        self.learner_args = vec!["--signing-key".into(), secret.display().to_string()];
    }

    /// The cluster's credentials (`certs new certs`) for every role from now on, on `tls/`.
    fn secure(&mut self) {
        let o = Command::new(bin("coordinator"))
            .args(["certs", "new", "certs"])
            .current_dir(self.dir.path())
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        self.endpoint = self.endpoint.replace("tcp/", "tls/");
        self.certs = vec!["--certs".into(), self.path("certs").display().to_string()];
    }

    fn path(&self, p: &str) -> PathBuf {
        self.dir.path().join(p)
    }

    fn coordinator(&mut self) {
        let (ep, db, log) = (self.endpoint.clone(), self.path("c.redb"), self.path("coordinator.log"));
        self.procs.spawn(
            "coordinator",
            Command::new(bin("coordinator"))
                .args(["serve", "--listen", &ep, "--db"])
                .arg(db)
                .args(&self.certs)
                .current_dir(self.dir.path()),
            &log,
        );
    }

    fn learner(&mut self) {
        self.learner_as("learner", "learner-1");
    }

    fn learner_as(&mut self, name: &str, id: &str) {
        self.learner_in(name, id, ".");
    }

    /// A learner working in its own folder (as on another machine: its own run folder).
    fn learner_in(&mut self, name: &str, id: &str, folder: &str) {
        let (ep, log, dir) = (self.endpoint.clone(), self.path(&format!("{name}.log")), self.path(folder));
        std::fs::create_dir_all(&dir).unwrap();
        self.procs.spawn(
            name,
            Command::new(bin("learner"))
                .args(["serve", "--connect", &ep, "--id", id, "--checkpoint-seconds", "0"])
                .args(&self.certs)
                .args(&self.learner_args)
                .current_dir(dir),
            &log,
        );
    }

    fn agent(&mut self, id: &str) {
        self.agent_as(id, id);
    }

    /// An agent process called `name` that serves as `id`.
    fn agent_as(&mut self, name: &str, id: &str) {
        let (ep, log) = (self.endpoint.clone(), self.path(&format!("{name}.log")));
        self.procs.spawn(
            name,
            Command::new(bin("sim-agent"))
                .args(["serve", "--connect", &ep, "--id", id, "--envs", "8", "--threads", "1"])
                .args(&self.certs)
                .current_dir(self.dir.path()),
            &log,
        );
    }

    fn cli(&self, args: &[&str]) -> Output {
        let mut a: Vec<&str> = args.to_vec();
        a.extend(["--connect", &self.endpoint]);
        a.extend(self.certs.iter().map(String::as_str));
        Command::new(bin("coordinator")).args(&a).current_dir(self.dir.path()).output().unwrap()
    }

    fn start(&self, spec: &str) -> String {
        self.start_as(spec, "job1")
    }

    /// Start a job (waiting for the coordinator to answer). A query sent while the roles are
    /// still starting may reach no queryable and wait out the CLI's 10 s; a fresh-clone CI run
    /// on two busy cores once used up 20 s that way under TLS, so a minute.
    fn start_as(&self, spec: &str, id: &str) -> String {
        std::fs::write(self.path("job.toml"), spec).unwrap();
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            let o = self.cli(&["job", "start", "job.toml", "--id", id]);
            if o.status.success() {
                return id.into();
            }
            let text = String::from_utf8_lossy(&o.stderr).to_string() + &String::from_utf8_lossy(&o.stdout);
            assert!(Instant::now() < deadline && text.contains("no coordinator answered"), "{text}");
            std::thread::sleep(Duration::from_millis(300));
        }
    }

    fn status(&self, id: &str) -> serde_json::Value {
        let o = self.cli(&["job", "status", id, "--json"]);
        serde_json::from_slice(&o.stdout).unwrap_or(serde_json::Value::Null)
    }

    /// Wait until `f(status)` holds.
    fn wait(&self, id: &str, secs: u64, what: &str, f: impl Fn(&serde_json::Value) -> bool) -> serde_json::Value {
        let deadline = Instant::now() + Duration::from_secs(secs);
        loop {
            let s = self.status(id);
            if f(&s) {
                return s;
            }
            assert!(Instant::now() < deadline, "timed out waiting for {what}; last status: {s}\nlogs: {}", self.logs());
            std::thread::sleep(Duration::from_millis(300));
        }
    }

    fn logs(&self) -> String {
        let mut out = String::new();
        for e in std::fs::read_dir(self.dir.path()).unwrap().flatten() {
            if e.path().extension().is_some_and(|x| x == "log") {
                let t = std::fs::read_to_string(e.path()).unwrap_or_default();
                // The roles' own lines (zenoh's connection chatter left out), the last 40.
                let tail: Vec<&str> = t.lines().rev().filter(|l| !l.contains(" zenoh")).take(40).collect();
                out += &format!(
                    "\n== {} ==\n{}",
                    e.path().display(),
                    tail.into_iter().rev().collect::<Vec<_>>().join("\n")
                );
            }
        }
        out
    }
}

/// One of `agent`'s real experience batches (with trajectories) on `job`, as `session` sees it.
fn a_real_batch(session: &protocol::net::zenoh::Session, job: &str, agent: &str) -> protocol::ExperienceBatch {
    use protocol::net;
    let real = net::subscribe(session, &protocol::keys::experience(job, agent)).unwrap();
    let drops = net::DropCounters::default();
    let until = Instant::now() + Duration::from_secs(30);
    loop {
        if let Some((_, b)) = net::try_next::<protocol::ExperienceBatch>(&real, &drops)
            && !b.trajectories.is_empty()
        {
            return b;
        }
        assert!(Instant::now() < until, "no experience from {agent} seen");
        std::thread::sleep(Duration::from_millis(20));
    }
}

fn version(s: &serde_json::Value) -> u64 {
    s["learner"]["policy_version"].as_u64().unwrap_or(0)
}

fn world_of(s: &serde_json::Value, agent: &str) -> Option<String> {
    s["assignments"][agent]["worlds"][0].as_str().map(str::to_string)
}

fn worlds_of(s: &serde_json::Value, agent: &str) -> Vec<String> {
    s["assignments"][agent]["worlds"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(|w| w.as_str())
        .map(str::to_string)
        .collect()
}

/// Issue 8: a retried job start or stop is the same job and another spec cannot take its id.
#[test]
fn a_retried_job_start_or_stop_is_the_same_job_and_another_spec_cannot_take_its_id() {
    // A `job start` whose reply is lost has started the job; the CLI's retry sends the very
    // same document and must get the job back, not "taken". Another spec under that id is
    // refused.
    let mut c = Cluster::new();
    c.coordinator();
    let id = c.start(SPEC);
    let again = c.cli(&["job", "start", "job.toml", "--id", &id]);
    let text = String::from_utf8_lossy(&again.stdout).to_string() + &String::from_utf8_lossy(&again.stderr);
    assert!(again.status.success() && text.contains("already started with this very spec"), "{text}");
    std::fs::write(c.path("job.toml"), SPEC.replace("minutes = 5", "minutes = 6")).unwrap();
    let other = c.cli(&["job", "start", "job.toml", "--id", &id]);
    let text = String::from_utf8_lossy(&other.stdout).to_string() + &String::from_utf8_lossy(&other.stderr);
    assert!(!other.status.success() && text.contains("is taken"), "{text}");
    let stop = c.status(&id)["job"]["stop"].clone();
    assert_eq!(stop["minutes"], 5.0, "the first spec's job is untouched: {stop}");
    // Likewise a retried `job stop`: the job is stopped, which is what was asked. No learner
    // has taken it, so it stops at once (no checkpoint will come) rather than wait forever.
    for attempt in ["stopped before a learner took it", "already stopped: stopped by the user"] {
        let o = c.cli(&["job", "stop", &id]);
        let text = String::from_utf8_lossy(&o.stdout).to_string() + &String::from_utf8_lossy(&o.stderr);
        assert!(o.status.success() && text.contains(attempt), "{attempt}: {text}");
    }
    assert_eq!(c.status(&id)["state"], "failed");
}

const SPEC: &str =
    "worlds = [\"reinvent_carpet\", \"reinvent_concrete\"]\nout = \"run\"\nenvs_per_agent = 8\n[stop]\nminutes = 5\n";

/// Issue 4: `up` runs a job to its stop and the model improves.
#[test]
fn up_runs_a_job_to_its_stop_and_the_model_improves() {
    let _turn = exclusive();
    let dir = tempfile::tempdir().unwrap();
    let o = Command::new(bin("coordinator"))
        .args(["up", "--agents", "2", "--envs", "8", "--minutes", "2", "--target-progress", "80", "--target-laps", "0"])
        .args(["--seed", "7"])
        .args(["--out", "up"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&o.stdout).to_string() + &String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{text}");
    assert!(text.contains("Finished") && text.contains("reached the target 80"), "{text}");
    let model = dir.path().join("up/run/model");
    assert!(model.join("model.safetensors").exists() && dir.path().join("up/summary.json").exists());
    // `--seed` reaches the job the learner and the agents run.
    let job = std::fs::read_to_string(dir.path().join("up/job.toml")).unwrap();
    let spec = coordinator::jobspec::parse(&job, &dir.path().join("up"), "job.toml", "up").unwrap();
    assert_eq!(spec.seed, 7, "{job}");
    let metrics = std::fs::read_to_string(dir.path().join("up/run/metrics.jsonl")).unwrap();
    // The learner binary records its memory after each update: resident, and what its
    // allocations hold (a leak's measure).
    for l in metrics.lines() {
        let m: serde_json::Value = serde_json::from_str(l).unwrap();
        for k in ["resident_mb", "live_mb"] {
            assert!(m[k].as_f64().is_some_and(|mb| mb > 1.0), "{k} missing or empty: {m}");
        }
        let (waiting, live) = (m["waiting_mb"].as_f64(), m["live_mb"].as_f64().unwrap_or(0.0));
        assert!(waiting.is_some_and(|w| (0.0..live).contains(&w)), "waiting_mb missing or past live_mb: {m}");
    }
    let progress: Vec<f64> = metrics
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap()["mean_progress"].as_f64().unwrap())
        .collect();
    let n = progress.len();
    assert!(n >= 3, "{metrics}");
    let head = progress[..2].iter().sum::<f64>() / 2.0;
    let tail = progress[n - 2..].iter().sum::<f64>() / 2.0;
    assert!(tail > head + 20.0, "mean progress improves over the job: {progress:?}");
    // Both worlds got experience.
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("up/summary.json")).unwrap()).unwrap();
    for w in summary["learner"]["worlds"].as_array().unwrap() {
        assert!(w["episodes"].as_u64().unwrap() > 0, "{summary}");
    }
}

/// Issue 32: SAC trains to laps under `up` with every step the agents simulate.
#[test]
fn sac_trains_to_laps_under_up_with_every_step_the_agents_simulate() {
    let _turn = exclusive();
    let dir = tempfile::tempdir().unwrap();
    // deepracer-for-cloud's SAC model_metadata.json, on the state vector.
    std::fs::write(
        dir.path().join("sac.json"),
        r#"{"action_space":{"speed":{"high":2,"low":1},"steering_angle":{"high":30,"low":-30}},
            "sensor":["STATE_VECTOR"],"neural_network":"PADDOCK_MLP","training_algorithm":"sac",
            "action_space_type":"continuous","version":"4"}"#,
    )
    .unwrap();
    let o = Command::new(bin("coordinator"))
        .args(["up", "--model-metadata", "sac.json", "--world", "reinvent_base", "--agents", "2", "--envs", "8"])
        .args(["--minutes", "2", "--target-laps", "3", "--out", "up"])
        .current_dir(dir.path())
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&o.stdout).to_string() + &String::from_utf8_lossy(&o.stderr);
    // The stop needs evaluations, which arrive while the next round's experience streams in.
    assert!(o.status.success() && text.contains("target laps reached"), "{text}");
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("up/summary.json")).unwrap()).unwrap();
    let learner = &summary["learner"];
    assert_eq!(learner["dropped_stale"], 0, "off-policy experience is never stale: {summary}");
    let metrics = std::fs::read_to_string(dir.path().join("up/run/metrics.jsonl")).unwrap();
    let last: serde_json::Value = serde_json::from_str(metrics.lines().last().unwrap()).unwrap();
    assert!(last["sac"]["replay"].as_u64().unwrap() > 0, "{last}");
}

/// Issue 4: a killed agent's world is reassigned, and a restarted learner and coordinator carry on.
#[test]
fn a_killed_agents_world_is_reassigned_and_a_restarted_learner_and_coordinator_carry_on() {
    let mut c = Cluster::new();
    c.coordinator();
    c.learner();
    c.agent("agent-1");
    c.agent("agent-2");
    let id = c.start(SPEC);
    let s = c.wait(&id, 60, "training under way, one world per agent", |s| {
        version(s) >= 3 && worlds_of(s, "agent-1").len() == 1 && worlds_of(s, "agent-2").len() == 1
    });
    let lost_world = world_of(&s, "agent-2").expect("agent-2 has a world");
    // Each role runs for days, so it hands freed memory back to the system soon: the process
    // the test started (the same id: run again in place) carries mimalloc's purge delay.
    for (name, ms) in [("coordinator", "0"), ("learner", "0"), ("agent-1", "100")] {
        let env = std::fs::read(format!("/proc/{}/environ", c.procs.pid(name))).unwrap();
        let want = format!("MIMALLOC_PURGE_DELAY={ms}");
        assert!(env.split(|b| *b == 0).any(|v| v == want.as_bytes()), "{name} runs without {want}");
    }
    // `coordinator agents`: both agents, their worlds and throughput.
    let deadline = Instant::now() + Duration::from_secs(20);
    loop {
        let o = c.cli(&["agents"]);
        let text = String::from_utf8_lossy(&o.stdout).to_string();
        let rows: Vec<&str> = text.lines().filter(|l| l.starts_with("agent-")).collect();
        let busy = rows
            .iter()
            .filter(|l| l.split_whitespace().nth(4).and_then(|x| x.parse::<f64>().ok()).unwrap_or(0.0) > 0.0)
            .count();
        if rows.len() == 2 && busy == 2 && text.contains("reinvent_") {
            break;
        }
        assert!(Instant::now() < deadline, "{text}");
        std::thread::sleep(Duration::from_millis(500));
    }

    // SIGKILL an agent: its world goes to the other within 5 s (which now drives both).
    c.procs.kill("agent-2");
    let t = Instant::now();
    c.wait(&id, 20, "the lost agent's world reassigned", |s| worlds_of(s, "agent-1").contains(&lost_world));
    assert!(t.elapsed() < Duration::from_secs(5) + Duration::from_millis(2500), "reassigned after {:?}", t.elapsed());
    let logs = c.cli(&["job", "logs", &id]);
    let log = String::from_utf8_lossy(&logs.stdout);
    assert!(log.contains("agent agent-2 lost"), "{log}");

    // SIGKILL the learner, start another: it resumes from the last checkpoint.
    let before = version(&c.status(&id));
    c.procs.kill("learner");
    let index = c.path("run/checkpoints/deepracer_checkpoints.json");
    let last: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&index).unwrap()).unwrap();
    let ckpt = last["last_checkpoint"]["policy_version"].as_u64().unwrap();
    assert!(ckpt + 1 >= before, "at most one iteration lost: checkpoint v{ckpt}, learner was at v{before}");
    c.learner();
    c.wait(&id, 60, "the restarted learner trains on", |s| version(s) > ckpt + 1);

    // Kill and restart the coordinator: the job is still there and goes on.
    c.procs.kill("coordinator");
    std::thread::sleep(Duration::from_millis(500));
    c.coordinator();
    let s = c.wait(&id, 30, "the job back after a coordinator restart", |s| s["state"] == "running");
    let v = version(&s);
    c.wait(&id, 60, "training continuing after the restart", |s| version(s) > v + 1);

    // Graceful stop: final checkpoint and best model.
    let o = c.cli(&["job", "stop", &id]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stdout));
    let s = c.wait(&id, 60, "the job finished", |s| s["state"] == "finished");
    assert_eq!(s["learner"]["dropped_duplicate"].as_u64(), Some(0), "no experience counted twice: {s}");
    assert!(c.path("run/model/model.safetensors").exists());
    let list = String::from_utf8_lossy(&c.cli(&["job", "list"]).stdout).to_string();
    assert!(list.contains("job1") && list.contains("finished"), "{list}");
}

/// `coordinator agents`: each agent's row (its seconds up), by id.
fn agents_up(c: &Cluster) -> Vec<(String, f64)> {
    let o = c.cli(&["agents"]);
    String::from_utf8_lossy(&o.stdout)
        .lines()
        .filter_map(|l| {
            let up = l.rsplit_once("(up ")?.1.strip_suffix(" s)")?.parse().ok()?;
            Some((l.split_whitespace().next()?.to_string(), up))
        })
        .collect()
}

/// A machine that loses power or its network leaves its connection open until Zenoh's lease
/// runs out, and its liveliness token with it: started again under its id meanwhile, the
/// agent's new token is the same key, and no leave or join is seen. Its new life is.
#[test]
fn an_agent_started_again_while_its_old_connection_lingers_is_seen_as_started_again() {
    let mut c = Cluster::new();
    c.coordinator();
    c.agent("agent-1");
    let deadline = Instant::now() + Duration::from_secs(60);
    while !agents_up(&c).iter().any(|(id, up)| id == "agent-1" && *up >= 8.0) {
        assert!(Instant::now() < deadline, "agent-1 not up 8 s: {:?}\n{}", agents_up(&c), c.logs());
        std::thread::sleep(Duration::from_millis(500));
    }
    // Frozen, as a machine without power: its connection stays open, it answers nothing.
    let frozen = c.procs.pid("agent-1").to_string();
    assert!(Command::new("kill").args(["-STOP", &frozen]).status().unwrap().success());
    c.agent_as("agent-1-again", "agent-1");
    let again = Instant::now();
    let deadline = again + Duration::from_secs(30);
    loop {
        let rows = agents_up(&c);
        if rows.iter().any(|(id, up)| id == "agent-1" && *up <= again.elapsed().as_secs_f64() + 1.0) {
            break;
        }
        assert!(Instant::now() < deadline, "the new life not seen: {rows:?}\n{}", c.logs());
        std::thread::sleep(Duration::from_millis(500));
    }
    // The old connection's lease runs out (10 s): the id stays, up since its new life.
    std::thread::sleep(Duration::from_secs(15).saturating_sub(again.elapsed()));
    c.procs.kill("agent-1");
    let rows = agents_up(&c);
    assert!(
        rows.iter().any(|(id, up)| id == "agent-1" && *up <= again.elapsed().as_secs_f64() + 1.0),
        "agent-1 gone or not up since its new life after the old lease ran out: {rows:?}\n{}",
        c.logs()
    );
}

/// Issue 4: bad input is counted and dropped and bad jobs are refused.
#[test]
fn bad_input_is_counted_and_dropped_and_bad_jobs_are_refused() {
    use protocol::net::{self, NetArgs, zenoh};
    use zenoh::Wait;
    let mut c = Cluster::new();
    c.coordinator();
    c.learner();
    c.agent("agent-1");
    // A job spec with errors names the field.
    std::fs::write(c.path("bad.toml"), "worlds = [\"reinvent_wood\"]\n[stop]\nminuts = 3\n").unwrap();
    let o = c.cli(&["job", "start", "bad.toml"]);
    assert!(
        !o.status.success() && String::from_utf8_lossy(&o.stderr).contains("minuts"),
        "{}",
        String::from_utf8_lossy(&o.stderr)
    );
    // A reward that raises: the job fails with the traceback, nothing trains on it.
    let raising = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/data/rewards/raises_key_error.py");
    std::fs::write(
        c.path("raise.toml"),
        format!("worlds = [\"reinvent_wood\"]\nreward = {:?}\n", raising.canonicalize().unwrap().display().to_string()),
    )
    .unwrap();
    let deadline = Instant::now() + Duration::from_secs(20);
    let o = loop {
        let o = c.cli(&["job", "start", "raise.toml", "--id", "raiser"]);
        if o.status.success()
            || !String::from_utf8_lossy(&o.stderr).contains("no coordinator answered")
            || Instant::now() > deadline
        {
            break o;
        }
        std::thread::sleep(Duration::from_millis(300));
    };
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(
        !o.status.success() && out.contains("KeyError: 'distance_from_centre'") && out.contains("Traceback"),
        "{out}"
    );
    assert_eq!(c.status("raiser")["state"], "failed");
    assert!(!c.path("runs/raiser").exists(), "nothing trained");
    // A reward that never returns is stopped at the job's time limit (here 0.5 s),
    // and the job is refused with the file and the step; the coordinator goes on.
    let endless = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../tests/data/rewards/never_returns.py");
    std::fs::write(
        c.path("endless.toml"),
        format!(
            "worlds = [\"reinvent_wood\"]\nreward = {:?}\n[sim]\nreward_time_limit = 0.5\n",
            endless.canonicalize().unwrap().display().to_string()
        ),
    )
    .unwrap();
    let o = c.cli(&["job", "start", "endless.toml", "--id", "endless"]);
    let out = String::from_utf8_lossy(&o.stdout).to_string() + &String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success()
            && out.contains("never_returns.py")
            && out.contains("did not return within the time limit of 500ms at step"),
        "{out}"
    );

    // Garbage on every key the roles subscribe to, while a good job runs.
    let id = c.start("worlds = [\"reinvent_wood\"]\nout = \"run\"\n[stop]\nminutes = 5\n");
    c.wait(&id, 60, "training", |s| version(s) >= 2);
    let session = net::open(&NetArgs { connect: vec![c.endpoint.clone()], ..Default::default() }).unwrap();
    let garbage: Vec<Vec<u8>> =
        vec![vec![0xff; 7], b"not protobuf at all".to_vec(), vec![0x08, 0x63], vec![0x12; 3 << 20]];
    let keys = [
        protocol::keys::assignment("agent-1"),
        protocol::keys::JOBS.to_string(),
        protocol::keys::policy(&id),
        protocol::keys::experience(&id, "intruder"),
        protocol::keys::credit(&id),
        protocol::keys::eval_request(&id, "agent-1"),
        protocol::keys::eval_report(&id, "intruder"),
        protocol::keys::learner_status(&id),
        protocol::keys::agent_report(&id, "intruder"),
    ];
    for k in &keys {
        for g in &garbage {
            session.put(k.as_str(), g.clone()).wait().unwrap();
        }
    }
    for g in &garbage {
        let _ = session.get(protocol::keys::CONTROL).payload(g.clone()).timeout(Duration::from_secs(2)).wait();
    }
    // Batches that decode but do not fit the job, sent as agent-1 (a copy of one of
    // its real batches with one number changed): an action index of 99 killed the learner.
    let batch = a_real_batch(&session, &id, "agent-1");
    type Lie = (&'static str, fn(&mut protocol::Trajectory));
    let hostile: [Lie; 4] = [
        ("action", |t| t.discrete_actions[0] = 99),
        ("reward", |t| t.rewards[0] = 1e9),
        ("progress", |t| t.progress = 500.0),
        ("observation", |t| t.obs[0] = f32::INFINITY),
    ];
    // Sent with blocking congestion control (a dropped put is Zenoh's right under load), and
    // a batch whose reason has not shown up after 15 s is sent again with a new number.
    let send = |i: usize, round: u64| {
        let mut b = batch.clone();
        b.seq += 1_000_000 * (round + 1) + i as u64;
        (hostile[i].1)(&mut b.trajectories[0]);
        b.trajectories.truncate(1);
        session
            .put(protocol::keys::experience(&id, "agent-1"), protocol::encode(&b))
            .congestion_control(zenoh::qos::CongestionControl::Block)
            .wait()
            .unwrap();
    };
    for i in 0..hostile.len() {
        send(i, 0);
    }
    // Everyone is still alive and the job goes on, counting what it dropped.
    let v = version(&c.status(&id));
    let s = c.wait(&id, 60, "training after the garbage", |s| {
        version(s) > v + 1 && s["learner"]["dropped_bad"].as_u64().unwrap_or(0) >= 4
    });
    assert_eq!(s["state"], "running");
    for (name, p) in &mut c.procs.0 {
        assert!(p.try_wait().unwrap().is_none(), "{name} died");
    }
    // Each is counted under its reason, which `job status` shows (the four batches arrive
    // and are counted in their own time: wait for all of them, not for the first).
    let wants = ["outside the action space", "reward", "progress", "non-finite"];
    let start = Instant::now();
    let mut round = 0;
    let reasons = loop {
        let reasons = c.status(&id)["learner"]["drops"].to_string();
        let missing: Vec<usize> = (0..wants.len()).filter(|&i| !reasons.contains(wants[i])).collect();
        if missing.is_empty() || start.elapsed() > Duration::from_secs(90) {
            break reasons;
        }
        if start.elapsed() > Duration::from_secs(15 * (round + 1)) {
            round += 1;
            for &i in &missing {
                send(i, round);
            }
        }
        std::thread::sleep(Duration::from_millis(500));
    };
    for want in wants {
        assert!(reasons.contains(want), "{want}: {reasons}");
    }
    let text = String::from_utf8_lossy(&c.cli(&["job", "status", &id]).stdout).to_string();
    assert!(text.contains("outside the action space of # actions"), "{text}");
}

/// Issue 4: a job runs to its stop with every message through a router.
#[test]
fn a_job_runs_to_its_stop_with_every_message_through_a_router() {
    // The coordinator's session runs as a Zenoh router; the learner and the agent are clients
    // of it (zenoh configuration files, `-c`), so every message goes through the router.
    let mut c = Cluster::new();
    let port = free_port();
    std::fs::write(c.path("router.json5"), format!("{{ mode: \"router\", listen: {{ endpoints: [\"tcp/127.0.0.1:{port}\"] }}, scouting: {{ multicast: {{ enabled: false }} }} }}")).unwrap();
    std::fs::write(c.path("client.json5"), format!("{{ mode: \"client\", connect: {{ endpoints: [\"tcp/127.0.0.1:{port}\"] }}, scouting: {{ multicast: {{ enabled: false }} }} }}")).unwrap();
    c.endpoint = format!("tcp/127.0.0.1:{port}");
    let (db, dir) = (c.path("c.redb"), c.dir.path().to_path_buf());
    c.procs.spawn(
        "coordinator",
        Command::new(bin("coordinator")).args(["serve", "-c", "router.json5", "--db"]).arg(db).current_dir(&dir),
        &dir.join("coordinator.log"),
    );
    c.procs.spawn(
        "learner",
        Command::new(bin("learner"))
            .args(["serve", "-c", "client.json5", "--checkpoint-seconds", "0"])
            .current_dir(&dir),
        &dir.join("learner.log"),
    );
    c.procs.spawn(
        "agent-1",
        Command::new(bin("sim-agent"))
            .args(["serve", "-c", "client.json5", "--id", "agent-1", "--envs", "8", "--threads", "1"])
            .current_dir(&dir),
        &dir.join("agent-1.log"),
    );
    let id = c.start("worlds = [\"reinvent_wood\"]\nout = \"run\"\n[stop]\nminutes = 3\ntarget_progress = 60\n");
    let s = c.wait(&id, 90, "the job finished through the router", |s| s["state"] == "finished");
    assert!(version(&s) >= 2, "{s}");
    assert!(c.path("run/model/model.safetensors").exists());
}

/// Issue 8: a stop condition from DeepRacer's hyperparameters.json finishes the job, and a job the
/// learner cannot start fails.
#[test]
fn a_hyperparameters_stop_condition_finishes_the_job_and_a_job_the_learner_cannot_start_fails() {
    // Each rule is tested through a whole run in learner/tests/it/run_scripted.rs and each
    // `[stop]` key across the wire in the learner's unit tests; here one of them end to end,
    // from DeepRacer's hyperparameters.json: the job finishes with the reason in its status
    // and its final model saved.
    let mut c = Cluster::new();
    c.coordinator();
    c.learner();
    c.agent("agent-1");
    std::fs::write(c.path("h.json"), r#"{"term_cond_max_episodes": 40}"#).unwrap();
    let spec = "worlds = [\"reinvent_base\"]\nout = \"run\"\nenvs_per_agent = 8\nhyperparameters = \"h.json\"\n[stop]\nminutes = 2\n";
    let id = c.start(spec);
    let s = c.wait(&id, 150, "the job finished", |s| s["state"] == "finished" || s["state"] == "failed");
    assert_eq!(s["state"], "finished", "{spec}: {s}");
    let reason = s["stop_reason"].as_str().unwrap_or("");
    let want = "term_cond_max_episodes (40)";
    assert!(reason.contains(want), "{spec}: stopped because {reason:?}, want {want:?}");
    assert!(c.path("run/model/model.safetensors").exists(), "{spec}");
    // A run the learner cannot start (a model to clone that is not on its machine) fails,
    // with the learner's reason in the status and the job's log, not as a finished job.
    let spec = "worlds = [\"reinvent_base\"]\nout = \"run2\"\nclone_from = \"no/such/model\"\n[stop]\nminutes = 2\n";
    let id = c.start_as(spec, "cannot");
    let s = c.wait(&id, 60, "the job failed", |s| s["state"] == "failed" || s["state"] == "finished");
    assert_eq!(s["state"], "failed", "{s}");
    let failure = s["learner"]["failure"].as_str().unwrap_or("");
    assert!(failure.contains("no/such/model") && s["stop_reason"] == failure, "{s}");
    let log = String::from_utf8_lossy(&c.cli(&["job", "logs", &id]).stdout).to_string();
    assert!(log.contains("learner failed: ") && log.contains("no/such/model"), "{log}");
}

/// Run `up` on three worlds with two agents; return (summary, metrics lines, job seconds).
fn up_three_worlds(dir: &Path, extra: &[&str]) -> (serde_json::Value, Vec<serde_json::Value>, f64) {
    let _turn = exclusive();
    let mut args = vec![
        "up",
        "--world",
        "reinvent_carpet",
        "--world",
        "reinvent_concrete",
        "--world",
        "reinvent_wood",
        "--agents",
        "2",
        "--out",
        "up",
    ];
    args.extend(extra);
    let o = Command::new(bin("coordinator")).args(&args).current_dir(dir).output().unwrap();
    let text = String::from_utf8_lossy(&o.stdout).to_string() + &String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{text}");
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("up/summary.json")).unwrap()).unwrap();
    let metrics: Vec<serde_json::Value> = std::fs::read_to_string(dir.join("up/run/metrics.jsonl"))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let seconds = summary["ended"].as_f64().unwrap() - summary["started"].as_f64().unwrap();
    (summary, metrics, seconds)
}

/// Every world's episodes reached the learner, updates kept coming to the end, and (nearly)
/// nothing simulated was thrown away as stale.
fn assert_no_waste(summary: &serde_json::Value, metrics: &[serde_json::Value], seconds: f64, min_iterations: usize) {
    let l = &summary["learner"];
    let worlds = l["worlds"].as_array().unwrap();
    for w in ["reinvent_carpet", "reinvent_concrete", "reinvent_wood"] {
        let e = worlds.iter().find(|x| x["world"] == w).map(|x| x["episodes"].as_u64().unwrap()).unwrap_or(0);
        assert!(e > 0, "no episode of {w} reached the learner: {summary}");
    }
    assert!(metrics.len() >= min_iterations, "{} iterations: {metrics:?}", metrics.len());
    let last = metrics.last().unwrap()["time_s"].as_f64().unwrap();
    let gaps: Vec<f64> =
        metrics.windows(2).map(|w| w[1]["time_s"].as_f64().unwrap() - w[0]["time_s"].as_f64().unwrap()).collect();
    let longest = gaps.iter().copied().fold(0.0, f64::max);
    assert!(
        seconds - last <= (2.0 * longest).max(0.25 * seconds),
        "updates stopped {:.0} s before the end of a {seconds:.0} s job (longest gap {longest:.0} s)",
        seconds - last
    );
    let received = l["episodes_received"].as_f64().unwrap();
    let stale = l["dropped_stale"].as_f64().unwrap();
    assert!(received > 0.0 && stale <= 0.05 * received, "{stale} of {received} episodes dropped stale");
}

/// The learner wrote the cluster's logs from what the agents sent: one sim-trace
/// folder per agent (deepracer-for-cloud's multi-worker layout), every step trained on once,
/// each agent's metrics JSON naming every world it drove, and the MCAP file.
fn assert_cluster_logs(run: &Path, metrics: &[serde_json::Value]) {
    let steps: u64 = metrics.iter().map(|m| m["steps"].as_u64().unwrap()).sum();
    let mut rows = 0u64;
    let mut worlds = std::collections::BTreeSet::new();
    for worker in ["0", "1"] {
        let dir = run.join(worker).join("training-simtrace");
        let files: Vec<_> = std::fs::read_dir(&dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display())).collect();
        assert!(!files.is_empty(), "{}: no sim-trace", dir.display());
        for f in files {
            let text = std::fs::read_to_string(f.unwrap().path()).unwrap();
            assert!(text.starts_with("episode,steps,X,Y,yaw,"), "DeepRacer's header");
            rows += text.lines().count() as u64 - 1;
        }
        let name =
            if worker == "0" { "TrainingMetrics.json".to_string() } else { format!("TrainingMetrics_{worker}.json") };
        let m: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(run.join("metrics").join(name)).unwrap()).unwrap();
        for e in m["metrics"].as_array().unwrap().iter().filter(|e| e["phase"] == "training") {
            worlds.insert(e["world"].as_str().unwrap().to_string());
        }
    }
    assert_eq!(rows, steps, "one sim-trace row per step trained on");
    assert_eq!(worlds.len(), 3, "{worlds:?}");
    assert!(std::fs::metadata(run.join("trace.mcap")).unwrap().len() > 10_000, "the MCAP log");
}

/// Issue 8: three state worlds on two agents are all trained and nothing is wasted.
#[test]
fn three_state_worlds_on_two_agents_are_all_trained_and_nothing_is_wasted() {
    let dir = tempfile::tempdir().unwrap();
    let (summary, metrics, seconds) =
        up_three_worlds(dir.path(), &["--envs", "6", "--env-steps", "300000", "--minutes", "10", "--target-laps", "0"]);
    assert_no_waste(&summary, &metrics, seconds, 10);
    assert_cluster_logs(&dir.path().join("up/run"), &metrics);
    // Each agent drove all three worlds at once: no hopping between worlds.
    let log = summary["log"].as_array().unwrap().iter().filter_map(|l| l.as_str()).collect::<Vec<_>>().join("\n");
    assert!(log.contains("reinvent_carpet+reinvent_concrete+reinvent_wood"), "{log}");
    assert!(!log.contains(" -> "), "no agent was moved: {log}");
    // Three worlds: the adaptive schedule (issue 34) weighed them from every world's last
    // evaluation, which the learner reports per world.
    assert!(log.contains("schedule: reinvent_carpet "), "{log}");
    let weights: Vec<f64> = summary["weights"].as_array().unwrap().iter().map(|w| w.as_f64().unwrap()).collect();
    assert!(weights.len() == 3 && (weights.iter().sum::<f64>() - 1.0).abs() < 1e-9, "{weights:?}");
    assert!(weights.iter().all(|&w| w >= 0.5 / 3.0 - 1e-9), "every world keeps its floor: {weights:?}");
    for w in summary["learner"]["worlds"].as_array().unwrap() {
        assert!(w["evaluated"] == true && w["eval_progress"].as_f64().unwrap() > 0.0, "{w}");
    }
}

/// Issue 8: three camera worlds on two agents are all trained and nothing is wasted.
#[test]
fn three_camera_worlds_on_two_agents_are_all_trained_and_nothing_is_wasted() {
    let dir = tempfile::tempdir().unwrap();
    let (summary, metrics, seconds) = up_three_worlds(
        dir.path(),
        &["--sensor", "camera", "--envs", "3", "--max-episodes", "80", "--minutes", "10", "--target-laps", "0"],
    );
    assert_no_waste(&summary, &metrics, seconds, 3);
}

fn learners(s: &serde_json::Value) -> Vec<String> {
    s["learner"]["learners"]
        .as_array()
        .map(|a| a.iter().filter_map(|x| x.as_str().map(str::to_string)).collect())
        .unwrap_or_default()
}

fn team_updates(s: &serde_json::Value) -> u64 {
    s["learner"]["team_updates"].as_u64().unwrap_or(0)
}

/// Issue 8: learners share updates, drop the dead, take joiners and take over.
#[test]
fn learners_share_updates_drop_the_dead_take_joiners_and_take_over() {
    let mut c = Cluster::new();
    c.shared_signing_key();
    c.coordinator();
    c.learner_as("learner-a", "learner-a");
    // learner-b works in a folder of its own, as on another machine.
    c.learner_in("learner-b", "learner-b", "machine-b");
    c.agent("agent-1");
    let id = c.start(SPEC);
    // The lowest id leads; the other joins its team and shares every update.
    let s = c.wait(&id, 90, "a team of two training", |s| learners(s).len() == 2 && team_updates(s) >= 3);
    assert_eq!(s["learner"]["learner_id"], "learner-a", "the lowest id leads: {s}");
    assert_eq!(learners(&s), ["learner-a", "learner-b"]);
    let text = String::from_utf8_lossy(&c.cli(&["job", "status", &id]).stdout).to_string();
    assert!(text.contains("learner team: learner-a, learner-b"), "{text}");
    let log = std::fs::read_to_string(c.path("learner-b.log")).unwrap();
    assert!(log.contains("took over the leader's weights and optimiser state") && log.contains("team update"), "{log}");
    // A member that dies is dropped within seconds; the leader goes on from the current version.
    c.procs.kill("learner-b");
    let gone = Instant::now();
    let s = c.wait(&id, 30, "learner-b dropped from the team", |s| learners(s) == ["learner-a"]);
    assert!(gone.elapsed() < Duration::from_secs(10), "dropped after {:?}", gone.elapsed());
    let v = version(&s);
    let s = c.wait(&id, 60, "training goes on without learner-b", |s| version(s) >= v + 2);
    // One that joins receives the weights and optimiser state first, then takes part.
    let before = team_updates(&s);
    c.learner_in("learner-b2", "learner-b", "machine-b");
    c.wait(&id, 90, "learner-b back in the team", |s| learners(s).len() == 2 && team_updates(s) >= before + 2);
    let log = std::fs::read_to_string(c.path("learner-b2.log")).unwrap();
    assert!(log.contains("took over the leader's weights and optimiser state"), "{log}");
    // The leader dies: the member takes the job over from the team's state (its own run
    // folder has no checkpoint: it goes on from the version the team had reached).
    let s = c.wait(&id, 60, "a few more team updates", |s| team_updates(s) >= before + 4);
    let before_kill = version(&s);
    c.procs.kill("learner-a");
    let s = c.wait(&id, 60, "learner-b took over", |s| s["learner"]["learner_id"] == "learner-b");
    assert!(version(&s) + 1 >= before_kill, "learner-b went on from v{} (the team was at v{before_kill})", version(&s));
    let log = std::fs::read_to_string(c.path("learner-b2.log")).unwrap();
    assert!(log.contains("taking over from the team's state"), "{log}");
    let v = version(&s);
    c.wait(&id, 60, "training goes on under learner-b", |s| version(s) > v + 1);
}

/// Issue 32: a learner team shares SAC updates and a joiner takes the replay memory.
#[test]
fn a_learner_team_shares_sac_updates_and_a_joiner_takes_the_replay_memory() {
    let mut c = Cluster::new();
    c.shared_signing_key();
    c.coordinator();
    c.learner_as("learner-a", "learner-a");
    c.agent("agent-1");
    std::fs::write(
        c.path("sac.json"),
        r#"{"action_space":{"speed":{"high":2,"low":1},"steering_angle":{"high":30,"low":-30}},
            "sensor":["STATE_VECTOR"],"neural_network":"PADDOCK_MLP","training_algorithm":"sac",
            "action_space_type":"continuous","version":"4"}"#,
    )
    .unwrap();
    // A gradient step per 20 new transitions: the state vector's small networks make each
    // shared step a round trip more than arithmetic.
    std::fs::write(c.path("h.json"), r#"{"sac_gradient_steps_per_transition": 0.05}"#).unwrap();
    let id = c.start(concat!(
        "worlds = [\"reinvent_base\"]\nout = \"run\"\nenvs_per_agent = 8\nmodel_metadata = \"sac.json\"\n",
        "hyperparameters = \"h.json\"\n[stop]\nminutes = 5\n"
    ));
    // Updates alone first: the replay memory holds experience when learner-b joins.
    c.wait(&id, 60, "SAC training alone", |s| version(s) >= 3);
    c.learner_in("learner-b", "learner-b", "machine-b");
    let s = c.wait(&id, 90, "a team of two making SAC's updates", |s| learners(s).len() == 2 && team_updates(s) >= 3);
    assert_eq!(learners(&s), ["learner-a", "learner-b"]);
    let log = std::fs::read_to_string(c.path("learner-b.log")).unwrap();
    assert!(log.contains("took over the leader's weights and optimiser state and its replay memory"), "{log}");
    assert!(log.contains("team update") && !log.contains("does not fit"), "{log}");
    let lead = std::fs::read_to_string(c.path("learner-a.log")).unwrap();
    assert!(lead.contains("sent the replay memory to the team's joiners"), "{lead}");
    assert!(!lead.contains("making the update again"), "{lead}");
    // The leader dies: learner-b takes the job over from the team's state, its replay memory
    // included (its own folder holds no run).
    c.procs.kill("learner-a");
    let s = c.wait(&id, 60, "learner-b took over", |s| s["learner"]["learner_id"] == "learner-b");
    let v = version(&s);
    c.wait(&id, 60, "training goes on under learner-b", |s| version(s) > v + 1);
    let log = std::fs::read_to_string(c.path("learner-b.log")).unwrap();
    assert!(log.contains("taking over from the team's state"), "{log}");
    assert!(!log.contains("replay memory starts empty") && !log.contains("does not fit"), "{log}");
}

/// Issue 9: the learner signs what it publishes, and a person promotes the version cars drive.
#[test]
fn the_learner_signs_what_it_publishes_and_a_person_promotes_the_version_cars_drive() {
    use policy::signature::TrustedKeys;
    use protocol::net::{self, DropCounters, NetArgs};
    use protocol::{PolicyUpdate, keys};
    let mut c = Cluster::new();
    c.coordinator();
    c.learner();
    c.agent("agent-1");
    let id = c.start(SPEC);
    let session = net::open(&NetArgs { connect: vec![c.endpoint.clone()], ..NetArgs::default() }).unwrap();
    let drops = DropCounters::default();
    let ask = |key: &str| -> Option<PolicyUpdate> {
        net::query::<PolicyUpdate>(&session, key, None, Duration::from_secs(3), &drops).unwrap().into_iter().next()
    };
    // The best model (after the first evaluation) and the latest, both signed by the run's key.
    let deadline = Instant::now() + Duration::from_secs(90);
    let best = loop {
        if let Some(b) = ask(&keys::best(&id)) {
            break b;
        }
        assert!(Instant::now() < deadline, "no best model published:\n{}", c.logs());
        std::thread::sleep(Duration::from_millis(500));
    };
    let trust = TrustedKeys::load(&[c.path("run/signing.pub")]).unwrap();
    let latest = ask(&keys::policy(&id)).expect("the latest model");
    for u in [&best, &latest] {
        let parts = protocol::exchange::policy_parts(u).unwrap();
        parts.verify(&trust).unwrap_or_else(|e| panic!("v{}: {e}", u.policy_version));
    }
    // A person promotes an older checkpoint: the best key now carries it, signed.
    c.wait(&id, 60, "several checkpoints", |s| version(s) >= 6);
    let versions: Vec<u64> = std::fs::read_dir(c.path("run/checkpoints"))
        .unwrap()
        .filter_map(|e| policy::ModelParts::read(&e.unwrap().path()).ok())
        .map(|p| {
            serde_json::from_str::<serde_json::Value>(&p.manifest_json).unwrap()["policy_version"].as_u64().unwrap()
        })
        .collect();
    // The newest other than the best (older checkpoints are rotated out as training goes on).
    let old = *versions.iter().filter(|v| **v != best.policy_version).max().expect("another checkpoint");
    let o = c.cli(&["job", "promote", &id, &old.to_string()]);
    let text = String::from_utf8_lossy(&o.stdout).to_string() + &String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success() && text.contains("promoted"), "{text}");
    let promoted = ask(&keys::best(&id)).unwrap();
    assert_eq!(promoted.policy_version, old);
    protocol::exchange::policy_parts(&promoted).unwrap().verify(&trust).unwrap();
    // It stays while training goes on (new evaluations do not displace a person's choice).
    std::thread::sleep(Duration::from_secs(4));
    assert_eq!(ask(&keys::best(&id)).unwrap().policy_version, old);
    // A version the run never saved is refused, naming what there is.
    let o = c.cli(&["job", "promote", &id, "99999"]);
    let text = String::from_utf8_lossy(&o.stdout).to_string() + &String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && text.contains("no checkpoint of v99999"), "{text}\n{}", c.logs());
    c.cli(&["job", "stop", &id]);
}

/// The CLI with another credentials folder (or none) against the cluster's endpoint.
fn cli_with(c: &Cluster, args: &[&str], extra: &[&str]) -> String {
    let o = Command::new(bin("coordinator"))
        .args(args)
        .args(["--connect", &c.endpoint])
        .args(extra)
        .current_dir(c.dir.path())
        .output()
        .unwrap();
    assert!(!o.status.success(), "{args:?} {extra:?} was answered: {}", String::from_utf8_lossy(&o.stdout));
    String::from_utf8_lossy(&o.stdout).to_string() + &String::from_utf8_lossy(&o.stderr)
}

/// A folder holding `role`'s certificate and key under the operator's file names: what a
/// thief who copied one machine's credentials would try.
fn stolen(c: &Cluster, role: &str) -> String {
    let d = c.path(&format!("stolen-{role}"));
    std::fs::create_dir_all(&d).unwrap();
    std::fs::copy(c.path("certs/ca.pem"), d.join("ca.pem")).unwrap();
    std::fs::copy(c.path(&format!("certs/{role}.pem")), d.join("operator.pem")).unwrap();
    std::fs::copy(c.path(&format!("certs/{role}.key")), d.join("operator.key")).unwrap();
    d.display().to_string()
}

/// Issue 10: only the cluster's roles connect and each does only its part.
#[test]
fn only_the_clusters_roles_connect_and_each_does_only_its_part() {
    use protocol::net::{self, NetArgs, zenoh};
    use protocol::secure::Role;
    use zenoh::Wait;
    let mut c = Cluster::new();
    c.secure();
    // The credentials: a CA and one certificate per role; keys readable by their owner only.
    for f in ["ca.pem", "coordinator.pem", "learner.pem", "agent.pem", "car.pem", "operator.pem"] {
        assert!(std::fs::read_to_string(c.path("certs").join(f)).unwrap().contains("BEGIN CERTIFICATE"), "{f}");
    }
    // The learners' model-signing key, whose public half agents and cars trust.
    policy::signature::TrustedKeys::load(&[c.path("certs/models.pub")]).unwrap();
    policy::signature::Signer::load(&c.path("certs/models.key")).unwrap();
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        for key in ["agent.key", "models.key"] {
            let mode = std::fs::metadata(c.path("certs").join(key)).unwrap().permissions().mode();
            assert_eq!(mode & 0o077, 0, "{key} is private: {mode:o}");
        }
    }
    let o =
        Command::new(bin("coordinator")).args(["certs", "new", "certs"]).current_dir(c.dir.path()).output().unwrap();
    assert!(!o.status.success() && String::from_utf8_lossy(&o.stderr).contains("--force"), "credentials kept");
    // Secure by default: no listening beyond loopback without credentials or --insecure.
    let port = free_port();
    let wide = format!("tcp/0.0.0.0:{port}");
    let o = Command::new(bin("coordinator"))
        .args(["serve", "--listen", &wide, "--db", "open.redb"])
        .current_dir(c.dir.path())
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("refusing to listen on") && err.contains("--insecure"), "{err}");
    let mut open = Command::new(bin("coordinator"))
        .args(["serve", "--listen", &wide, "--db", "open.redb", "--insecure"])
        .current_dir(c.dir.path())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_secs(2));
    assert!(open.try_wait().unwrap().is_none(), "--insecure starts");
    open.kill().unwrap();
    open.wait().unwrap();

    // A cluster on mutual TLS under the access rules trains as any other.
    c.coordinator();
    c.learner();
    c.agent("agent-1");
    let id = c.start("worlds = [\"reinvent_wood\"]\nout = \"run\"\n[stop]\nminutes = 5\n");
    let s = c.wait(&id, 90, "training over TLS", |s| version(s) >= 2);
    let world = world_of(&s, "agent-1").unwrap();

    // No credentials: plain TCP, TLS without a certificate of its own (trusting the CA, as a
    // curious peer could), a job with Python in it: nobody answers.
    let tcp = c.endpoint.replace("tls/", "tcp/");
    let o = Command::new(bin("coordinator"))
        .args(["job", "list", "--connect", &tcp])
        .current_dir(c.dir.path())
        .output()
        .unwrap();
    assert!(!o.status.success(), "plain TCP is not answered");
    std::fs::write(
        c.path("anon.json5"),
        format!(
            "{{ mode: \"peer\", listen: {{ endpoints: [] }}, connect: {{ endpoints: [{:?}] }}, transport: {{ link: {{ tls: {{ root_ca_certificate: {:?} }} }} }} }}",
            c.endpoint,
            c.path("certs/ca.pem").display().to_string()
        ),
    )
    .unwrap();
    std::fs::write(
        c.path("evil.py"),
        "import os\ndef reward_function(params):\n    os.system('touch pwned')\n    return 1.0\n",
    )
    .unwrap();
    std::fs::write(c.path("evil.toml"), "worlds = [\"reinvent_wood\"]\nreward = \"evil.py\"\n").unwrap();
    for args in [&["job", "list"][..], &["job", "start", "evil.toml"], &["job", "stop", &id], &["job", "status", &id]] {
        let mut a = args.to_vec();
        a.extend(["-c", "anon.json5"]);
        let o = Command::new(bin("coordinator")).args(&a).current_dir(c.dir.path()).output().unwrap();
        let text = String::from_utf8_lossy(&o.stdout).to_string() + &String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && text.contains("no coordinator answered"), "{args:?}: {text}");
    }
    // Another role's credentials: a stolen agent, learner or car certificate cannot run jobs.
    for role in ["agent", "learner", "car"] {
        let d = stolen(&c, role);
        for args in
            [&["job", "list"][..], &["job", "start", "evil.toml"], &["job", "stop", &id], &["job", "status", &id]]
        {
            let text = cli_with(&c, args, &["--certs", &d]);
            assert!(text.contains("no coordinator answered"), "{role} {args:?}: {text}");
        }
    }
    assert!(!c.path("pwned").exists() && !c.dir.path().join("run/../pwned").exists());

    // Roles publishing what is not theirs: an agent re-publishing a model (v1000000) and
    // re-assigning agent-1, a car sending experience with an action index of 99.
    let certs = c.path("certs");
    let as_role = |r: Role| {
        net::open(
            &NetArgs { connect: vec![c.endpoint.clone()], certs: Some(certs.clone()), ..Default::default() }.as_role(r),
        )
        .unwrap()
    };
    let watcher = as_role(Role::Operator);
    let seen = net::subscribe(&watcher, &protocol::keys::policy(&id)).unwrap();
    let agent = as_role(Role::Agent);
    let car = as_role(Role::Car);
    std::thread::sleep(Duration::from_secs(2));
    let batch = a_real_batch(&watcher, &id, "agent-1");
    let update = protocol::PolicyUpdate {
        protocol_version: protocol::PROTOCOL_VERSION,
        job_id: id.clone(),
        policy_version: 1_000_000,
        ..Default::default()
    };
    let hijack = protocol::Assignment {
        protocol_version: protocol::PROTOCOL_VERSION,
        agent_id: "agent-1".into(),
        job_id: "elsewhere".into(),
        generation: 1_000_000,
        worlds: vec![protocol::WorldSpec { name: "reinvent_carpet".into(), ..Default::default() }],
        ..Default::default()
    };
    let mut bad = batch.clone();
    bad.seq += 1_000_000;
    bad.trajectories.truncate(1);
    bad.trajectories[0].discrete_actions[0] = 99;
    let before = c.status(&id)["learner"]["dropped_bad"].as_u64().unwrap_or(0);
    for _ in 0..5 {
        net::put(&agent, &protocol::keys::policy(&id), &update).unwrap();
        net::put(&agent, &protocol::keys::assignment("agent-1"), &hijack).unwrap();
        let table = protocol::AssignmentTable {
            protocol_version: protocol::PROTOCOL_VERSION,
            job_id: id.clone(),
            running: false,
            ..Default::default()
        };
        net::put(&agent, protocol::keys::JOBS, &table).unwrap();
        net::put(&car, &protocol::keys::experience(&id, "agent-1"), &bad).unwrap();
        let _ = agent
            .get(protocol::keys::CONTROL)
            .timeout(Duration::from_secs(1))
            .wait()
            .map(|r| while r.recv().is_ok() {});
        std::thread::sleep(Duration::from_millis(200));
    }
    // The job goes on, untouched: same world, no model from elsewhere, the learner never saw
    // the hostile batch (refused before decoding), and everyone is alive.
    let v = version(&c.status(&id));
    let s = c.wait(&id, 60, "training after the attacks", |s| version(s) > v + 1);
    assert_eq!(world_of(&s, "agent-1").as_deref(), Some(world.as_str()));
    assert_eq!(
        s["learner"]["dropped_bad"].as_u64().unwrap_or(0),
        before,
        "the car's batch never reached the learner: {s}"
    );
    while let Ok(Some(sample)) = seen.try_recv() {
        let u = protocol::decode::<protocol::PolicyUpdate>(&sample.payload().to_bytes()).unwrap();
        assert!(u.policy_version < 1_000_000, "the operator received the agent's model");
    }
    // Issue 35: a stolen learner certificate may publish policies, but without the learners'
    // signing key: a copy of the latest model as v777777 signed by the thief's own key, and
    // as v777778 unsigned. The agent checks the signature and drives neither; both are
    // counted at the agent and shown by `job status`.
    let learner = as_role(Role::Learner);
    std::thread::sleep(Duration::from_secs(1));
    let latest = net::query::<protocol::PolicyUpdate>(
        &agent,
        &protocol::keys::policy(&id),
        None,
        Duration::from_secs(3),
        &protocol::net::DropCounters::default(),
    )
    .unwrap()
    .into_iter()
    .next()
    .expect("the latest policy");
    let thief = policy::signature::Signer::generate();
    let as_version = |v: u64, signer: Option<&policy::signature::Signer>| {
        let mut manifest: serde_json::Value = serde_json::from_str(&latest.manifest_json).unwrap();
        manifest["policy_version"] = v.into();
        let manifest_json = manifest.to_string();
        let signature_json = signer
            .map(|s| {
                serde_json::to_string(&s.sign(&latest.weights, &latest.model_metadata_json, &manifest_json)).unwrap()
            })
            .unwrap_or_default();
        protocol::PolicyUpdate { policy_version: v, manifest_json, signature_json, ..latest.clone() }
    };
    for _ in 0..3 {
        net::put(&learner, &protocol::keys::policy(&id), &as_version(777_777, Some(&thief))).unwrap();
        net::put(&learner, &protocol::keys::policy(&id), &as_version(777_778, None)).unwrap();
        std::thread::sleep(Duration::from_millis(300));
    }
    let s = c.wait(&id, 30, "the agent's signature refusals reported", |s| {
        let a = s["agent_refused"]["agent-1"].to_string();
        a.contains("signature: signed by key") && a.contains("signature: the model is not signed")
    });
    let text = String::from_utf8_lossy(&c.cli(&["job", "status", &id]).stdout).to_string();
    assert!(text.contains("refused at agent-1") && text.contains("which is not trusted"), "{text}\n{s}");
    let log = std::fs::read_to_string(c.path("agent-1.log")).unwrap();
    assert!(log.contains("new policy") && !log.contains("version=77777"), "agent-1 drove a forged policy: {log}");
    // A peer refused again and again is logged once by its certificate's name and named by
    // `job status`: the stolen agent certificate, announcing job tables to the learner.
    let table = protocol::AssignmentTable {
        protocol_version: protocol::PROTOCOL_VERSION,
        job_id: id.clone(),
        running: false,
        ..Default::default()
    };
    for _ in 0..30 {
        net::put(&agent, protocol::keys::JOBS, &table).unwrap();
    }
    let s = c.wait(&id, 30, "the hostile peer named", |s| {
        s["learner"]["hostile_peers"].to_string().contains("certificate 'paddock-agent'")
    });
    let text = String::from_utf8_lossy(&c.cli(&["job", "status", &id]).stdout).to_string();
    assert!(text.contains("HOSTILE PEER certificate 'paddock-agent' (zenoh id "), "{text}\n{s}");
    let log = std::fs::read_to_string(c.path("learner.log")).unwrap();
    let named = log
        .lines()
        .filter(|l| l.contains("certificate 'paddock-agent'") && l.contains("messages refused within"))
        .count();
    assert_eq!(named, 1, "logged once: {log}");
    for (name, p) in &mut c.procs.0 {
        assert!(p.try_wait().unwrap().is_none(), "{name} died");
    }
    // Counted per reason where it was refused (each node judges what it receives), shown by
    // `job status` for the coordinator and the learner, logged by every role.
    let s = c.wait(&id, 30, "the refusals counted", |s| {
        s["coordinator_refused"].to_string().contains("car may not query on paddock/v1/control")
            && s["learner"]["refused"].to_string().contains("car may not put on paddock/v1/job/*/experience/agent-1")
            && s["learner"]["refused"].to_string().contains("agent may not put on paddock/v1/jobs")
    });
    let coordinator = s["coordinator_refused"].to_string();
    // Beside them, what the coordinator's allocations hold (counted by its binary).
    assert!(s["coordinator_live_mb"].as_f64().is_some_and(|mb| mb > 1.0 && mb < 1024.0), "coordinator_live_mb: {s}");
    for want in [
        "TLS: a connection refused",
        "access control: agent may not query on paddock/v1/control",
        "access control: learner may not query on paddock/v1/control",
        "access control: car may not query on paddock/v1/control",
    ] {
        assert!(coordinator.contains(want), "{want}: {coordinator}");
    }
    let text = String::from_utf8_lossy(&c.cli(&["job", "status", &id]).stdout).to_string();
    assert!(text.contains("refused at the coordinator") && text.contains("refused at the learner"), "{text}");
    let deadline = Instant::now() + Duration::from_secs(25);
    loop {
        let log = std::fs::read_to_string(c.path("agent-1.log")).unwrap();
        if log.contains("agent may not put on paddock/v1/assign/agent-1")
            && log.contains("agent may not put on paddock/v1/job/*/policy")
        {
            break;
        }
        assert!(Instant::now() < deadline, "agent-1 logs what it refused: {log}");
        std::thread::sleep(Duration::from_secs(1));
    }
    // Issue 35: the whole cluster under a hostile peer (the stolen agent certificate) for a
    // bounded time while the job trains: garbage and an oversized message on the keys an
    // agent may send on, replays of a real batch, out-of-role puts and a flood of queries.
    // The job goes on and finishes, its model laps, nothing is lost, every refusal is counted.
    let before = c.status(&id);
    let real = a_real_batch(&watcher, &id, "agent-1");
    let dups_before = before["learner"]["dropped_duplicate"].as_u64().unwrap_or(0);
    let (mut rounds, mut queries) = (0u64, 0u64);
    let block = |key: &str, bytes: Vec<u8>| {
        agent.put(key, bytes).congestion_control(zenoh::qos::CongestionControl::Block).wait().unwrap();
    };
    let attack = Instant::now();
    while attack.elapsed() < Duration::from_secs(10) {
        block(&protocol::keys::experience(&id, "agent-1"), vec![0xff; 64]);
        block(&protocol::keys::eval_report(&id, "agent-1"), b"not protobuf".to_vec());
        block(&protocol::keys::experience(&id, "agent-1"), protocol::encode(&real));
        block(&protocol::keys::policy(&id), protocol::encode(&update));
        for _ in 0..10 {
            let _ = agent.get(protocol::keys::policy(&id)).timeout(Duration::from_millis(300)).callback(|_| {}).wait();
            let _ =
                agent.get(protocol::keys::job_spec(&id)).timeout(Duration::from_millis(300)).callback(|_| {}).wait();
            queries += 2;
        }
        rounds += 1;
        std::thread::sleep(Duration::from_millis(100));
    }
    block(&protocol::keys::experience(&id, "agent-1"), vec![0x0a; protocol::MAX_MESSAGE_BYTES + 1]);
    eprintln!("hostile peer: {rounds} rounds, {queries} queries");
    let count = |s: &serde_json::Value, list: &str, want: &str| -> u64 {
        let counted = |v: &serde_json::Value| {
            v.as_array()
                .map(|a| {
                    a.iter()
                        .filter(|d| d["reason"].as_str().is_some_and(|r| r.contains(want)))
                        .map(|d| d["count"].as_u64().unwrap_or(0))
                        .sum::<u64>()
                })
                .unwrap_or(0)
        };
        match list {
            "everywhere" => {
                counted(&s["coordinator_refused"])
                    + counted(&s["learner"]["refused"])
                    + s["agent_refused"].as_object().map_or(0, |m| m.values().map(|a| counted(&a["counts"])).sum())
            }
            _ => counted(&s["learner"][list]),
        }
    };
    let s = c.wait(&id, 60, "every hostile message counted", |s| {
        count(s, "drops", "malformed") >= count(&before, "drops", "malformed") + 2 * rounds
            && count(s, "drops", "over the size limit") >= 1
            && s["learner"]["dropped_duplicate"].as_u64().unwrap_or(0) >= dups_before + rounds
            && count(s, "everywhere", "agent may not put on paddock/v1/job/*/policy")
                >= count(&before, "everywhere", "agent may not put on paddock/v1/job/*/policy") + rounds
    });
    let v = version(&s);
    c.wait(&id, 60, "training after the hostile peer", |s| version(s) > v + 1);
    for (name, p) in &mut c.procs.0 {
        assert!(p.try_wait().unwrap().is_none(), "{name} died under the hostile peer");
    }
    // The operator's credentials still stop the job, which ends as any other; a watcher sees
    // it live and leaves when it has finished.
    let watch = Command::new(bin("coordinator"))
        .args(["job", "status", &id, "--watch", "--connect", &c.endpoint])
        .args(&c.certs)
        .current_dir(c.dir.path())
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    std::thread::sleep(Duration::from_secs(5));
    let o = c.cli(&["job", "stop", &id]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stdout));
    let s = c.wait(&id, 60, "the job finished", |s| s["state"] == "finished");
    assert!(c.path("run/model/model.safetensors").exists());
    // Its model laps; nothing was lost or trained on twice: updates 1, 2, … each recorded
    // once, no more episodes trained on than were delivered, none counted twice as new.
    assert!(s["learner"]["eval_laps"].as_u64().unwrap_or(0) >= 1, "the model laps: {s}");
    let l = &s["learner"];
    assert!(l["episodes"].as_u64().unwrap() <= l["episodes_received"].as_u64().unwrap(), "{l}");
    let metrics = std::fs::read_to_string(c.path("run/metrics.jsonl")).unwrap();
    let its: Vec<u64> = metrics
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap()["iteration"].as_u64().unwrap())
        .collect();
    assert_eq!(its, (1..=its.len() as u64).collect::<Vec<_>>(), "{metrics}");
    let o = watch.wait_with_output().unwrap();
    let frames = String::from_utf8_lossy(&o.stdout).to_string();
    assert!(o.status.success(), "{frames}");
    let n = frames.matches(&format!("job {id}: ")).count();
    assert!(n >= 2 && frames.contains("Finished"), "{n} frames: {frames}");
}

/// Issue 10: `chaos up` restarts whatever is killed and the job completes with whole records.
#[test]
fn chaos_up_restarts_whatever_is_killed_and_the_job_completes_with_whole_records() {
    let _turn = exclusive();
    let dir = tempfile::tempdir().unwrap();
    let log = std::fs::File::create(dir.path().join("up.out")).unwrap();
    let mut up = Command::new(bin("coordinator"))
        .args([
            "up",
            "--agents",
            "2",
            "--envs",
            "8",
            "--minutes",
            "1.25",
            "--target-laps",
            "0",
            "--checkpoint-seconds",
            "1",
        ])
        .args(["--out", "up"])
        .current_dir(dir.path())
        .stdout(log.try_clone().unwrap())
        .stderr(log)
        .spawn()
        .unwrap();
    // A bounded number of SIGKILLs at random moments, of random roles: each of the learner and
    // the coordinator at least once, an agent at least once (the seed is printed to replay it).
    let seed = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap().subsec_nanos() as u64 | 1;
    eprintln!("chaos seed {seed}");
    let mut x = seed;
    let mut next = move |n: u64| {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        x % n
    };
    let mut victims = vec!["learner", "coordinator", if next(2) == 0 { "agent-1" } else { "agent-2" }];
    victims.push(["agent-1", "agent-2", "learner", "coordinator"][next(4) as usize]);
    for i in (1..victims.len()).rev() {
        victims.swap(i, next(i as u64 + 1) as usize);
    }
    let pids = dir.path().join("up/logs/pids.json");
    let mut killed = Vec::new();
    // The kills end by 50 s into the 75 s job, leaving the restarted roles time to finish it.
    std::thread::sleep(Duration::from_secs(10));
    for v in &victims {
        std::thread::sleep(Duration::from_secs(5 + next(6)));
        let p: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&pids).unwrap()).unwrap();
        let pid = p[v].as_u64().unwrap_or_else(|| panic!("{v} in {p}"));
        let o = Command::new("kill").args(["-9", &pid.to_string()]).output().unwrap();
        assert!(o.status.success(), "kill {v} ({pid})");
        killed.push(*v);
        // The next victim's pid must be the restarted one.
        let deadline = Instant::now() + Duration::from_secs(10);
        let now = || -> u64 {
            serde_json::from_str::<serde_json::Value>(&std::fs::read_to_string(&pids).unwrap()).unwrap()[v]
                .as_u64()
                .unwrap_or(0)
        };
        while now() == pid {
            assert!(Instant::now() < deadline, "{v} was not restarted");
            std::thread::sleep(Duration::from_millis(200));
        }
    }
    let deadline = Instant::now() + Duration::from_secs(300);
    let status = loop {
        if let Some(s) = up.try_wait().unwrap() {
            break s;
        }
        assert!(Instant::now() < deadline, "up did not end");
        std::thread::sleep(Duration::from_secs(1));
    };
    let out = std::fs::read_to_string(dir.path().join("up.out")).unwrap();
    assert!(status.success(), "killed {killed:?}: {out}");
    // The job finished and its log tells what happened.
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("up/summary.json")).unwrap()).unwrap();
    assert_eq!(summary["state"], "finished", "{summary}");
    let events = summary["log"].to_string();
    for v in &killed {
        assert!(events.contains(&format!("up: {v} exited")), "{v}: {events}");
    }
    // No update recorded twice, none missing: iterations 1, 2, … in order, each line whole.
    let run = dir.path().join("up/run");
    let metrics = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
    let its: Vec<u64> = metrics
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap()["iteration"].as_u64().unwrap())
        .collect();
    assert!(its.len() >= 3, "{metrics}");
    assert_eq!(its, (1..=its.len() as u64).collect::<Vec<_>>(), "{metrics}");
    // The totals carry on across restarts (a restarted learner does not start counting over).
    let totals: Vec<u64> = metrics
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap()["total_episodes"].as_u64().unwrap())
        .collect();
    assert!(totals.windows(2).all(|w| w[0] < w[1]), "{totals:?}");
    // No episode trained on twice: the learner never counted a duplicate as new, and trained on
    // no more than was delivered.
    let l = &summary["learner"];
    assert!(l["episodes"].as_u64().unwrap() <= l["episodes_received"].as_u64().unwrap(), "{l}");
    // Every checkpoint and the model folder load.
    let mut folders = vec![run.join("model")];
    for e in std::fs::read_dir(run.join("checkpoints")).unwrap().flatten() {
        if e.path().is_dir() {
            folders.push(e.path());
        }
    }
    assert!(folders.len() >= 2);
    for f in folders {
        policy::folder::load(&f).unwrap_or_else(|e| panic!("{}: {e}", f.display()));
    }
}

/// Issue 8: a reply that cannot be read is not reported as silence.
#[test]
fn a_reply_that_cannot_be_read_is_not_reported_as_silence() {
    // Something answers the job-control query with bytes that are not a reply: the CLI says
    // so (and why), instead of "no coordinator answered".
    use protocol::net::{self, NetArgs, zenoh::Wait};
    // In turn with the clusters: a port one of them has picked but not bound yet is "free"
    // here too (CI once failed here with "Address already in use").
    let _turn = exclusive();
    let endpoint = format!("tcp/127.0.0.1:{}", free_port());
    let session = net::open(&NetArgs { listen: vec![endpoint.clone()], ..NetArgs::default() }).unwrap();
    let _q = session
        .declare_queryable(protocol::keys::CONTROL)
        .callback(|q| {
            let _ = q.reply(q.key_expr().clone(), vec![0xffu8; 12]).wait();
        })
        .wait()
        .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let o = Command::new(bin("coordinator"))
            .args(["job", "status", "job1", "--connect", &endpoint])
            .current_dir(dir.path())
            .output()
            .unwrap();
        let text = String::from_utf8_lossy(&o.stdout).to_string() + &String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "{text}");
        // The first query may go out before the session's routes are up: that one is silence.
        if text.contains("no coordinator answered") && Instant::now() < deadline {
            continue;
        }
        assert!(text.contains("a reply came but could not be read") && text.contains("1 ×"), "{text}");
        break;
    }
}
