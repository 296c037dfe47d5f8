//! `coordinator bench cluster|pixels|wire|publish|record|long-job`: what distribution costs, and
//! the checks of quality that take minutes of training.
//!
//! - `cluster`: useful work end to end: samples trained on per second (the steps of the episodes
//!   the learner used, every update's optimiser step included), of the single-process trainer
//!   and of `up` with 1, 2 and 4 agent processes on loopback, in the same run with the same
//!   total envs; beside it the env steps simulated and the share of episodes dropped stale.
//! - `pixels`: wall-clock to 3/3 laps on every world from pixels (domain randomisation on),
//!   `train` in one process against `up` with 2 agents, in one run; then both final models
//!   evaluated on the training worlds and on tracks they never saw.
//! - `wire`: experience throughput agent -> learner, plain TCP against mutual TLS with the
//!   access rules (the cost of a secured cluster), interleaved rounds in one run.
//! - `long-job`: the quality of a long `up` job's last model (it must still lap every world),
//!   with a verdict; minutes of training, so it is a benchmark and not a test.
//! - `publish`: time from publishing a SHALLOW camera model until 4 agent sessions on loopback
//!   hold it, and the bytes per env step of experience on the wire.

use anyhow::{Context, Result, bail};
use protocol::net::{self, NetArgs, zenoh};
use protocol::{PROTOCOL_VERSION, PolicyUpdate, keys};
use rand::SeedableRng;
use std::collections::BTreeMap;
use std::process::Command;
use std::sync::Arc;
use std::time::{Duration, Instant};
use zenoh::Wait;

pub fn cluster(seconds: f64, envs: usize, world: &str) -> Result<()> {
    let me = std::env::current_exe()?;
    let tmp = std::env::temp_dir().join(format!("paddock-bench-cluster-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir_all(&tmp)?;
    let minutes = format!("{}", seconds / 60.0);
    println!("# coordinator bench cluster: {world}, {envs} environments in total, {seconds:.0} s per row, 2 cores");
    println!();
    println!(
        "| setup | samples trained on | updates | seconds | samples trained on/s | vs single process | env steps simulated | episodes dropped stale |"
    );
    println!("|---|---|---|---|---|---|---|---|");
    // The single-process trainer (same learner and sim code, no network).
    let out = tmp.join("single");
    let t0 = Instant::now();
    let o = Command::new(&me)
        .args([
            "train",
            "--world",
            world,
            "--minutes",
            &minutes,
            "--target-laps",
            "0",
            "--envs",
            &envs.to_string(),
            "--checkpoint-seconds",
            "2",
            "--out",
        ])
        .arg(&out)
        .output()?;
    if !o.status.success() {
        bail!("train failed: {}", String::from_utf8_lossy(&o.stderr));
    }
    let wall = t0.elapsed().as_secs_f64();
    let s: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("summary.json"))?)?;
    let (used, updates) = used_samples(&out)?;
    let secs = s["seconds"].as_f64().unwrap_or(wall);
    let base = used / secs;
    println!(
        "| single process (`coordinator train`) | {used:.0} | {updates} | {secs:.1} | {base:.0} | 1.00× | {:.0} | {} of {} |",
        s["env_steps"].as_f64().unwrap_or(0.0),
        s["dropped_stale"].as_u64().unwrap_or(0),
        s["episodes_received"].as_u64().unwrap_or(0)
    );
    for agents in [1usize, 2, 4] {
        let per = (envs / agents).max(1);
        let r = up_row(&tmp.join(format!("up{agents}")), world, agents, per, &minutes, None)?;
        println!(
            "| `up` with {agents} agent process(es) × {per} envs (+ coordinator + learner) | {:.0} | {} | {:.1} | {:.0} | {:.2}× | {:.0} | {} of {} |",
            r.used,
            r.updates,
            r.secs,
            r.used / r.secs,
            r.used / r.secs / base,
            r.steps,
            r.stale,
            r.received
        );
    }
    let _ = std::fs::remove_dir_all(&tmp);
    Ok(())
}

/// One `up` job's useful work.
struct UpRow {
    used: f64,
    updates: usize,
    secs: f64,
    steps: f64,
    stale: u64,
    received: u64,
}

/// Run `up` on one world with `agents` × `per` envs for `minutes` (with `certs`: mutual TLS and
/// the access rules on every link) and read what it did from its summary and metrics.
fn up_row(
    out: &std::path::Path,
    world: &str,
    agents: usize,
    per: usize,
    minutes: &str,
    certs: Option<&std::path::Path>,
) -> Result<UpRow> {
    let me = std::env::current_exe()?;
    let mut cmd = Command::new(&me);
    cmd.args([
        "up",
        "--world",
        world,
        "--agents",
        &agents.to_string(),
        "--envs",
        &per.to_string(),
        "--minutes",
        minutes,
        "--target-laps",
        "0",
        "--out",
    ])
    .arg(out);
    if let Some(c) = certs {
        cmd.arg("--certs").arg(c);
    }
    let o = cmd.output()?;
    if !o.status.success() {
        bail!("up failed: {}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
    }
    let s: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json"))?).context("up's summary")?;
    let (used, updates) = used_samples(&out.join("run"))?;
    Ok(UpRow {
        used,
        updates,
        secs: s["ended"].as_f64().unwrap_or(0.0) - s["started"].as_f64().unwrap_or(0.0),
        steps: s["learner"]["env_steps"].as_f64().unwrap_or(0.0),
        stale: s["learner"]["dropped_stale"].as_u64().unwrap_or(0),
        received: s["learner"]["episodes_received"].as_u64().unwrap_or(0),
    })
}

/// Samples trained on (the steps of every update's episodes) and updates, from a run folder.
fn used_samples(run: &std::path::Path) -> Result<(f64, usize)> {
    let text = std::fs::read_to_string(run.join("metrics.jsonl")).with_context(|| format!("{}", run.display()))?;
    let mut used = 0.0;
    let mut updates = 0;
    for line in text.lines() {
        let v: serde_json::Value = serde_json::from_str(line)?;
        used += v["steps"].as_f64().unwrap_or(0.0);
        updates += 1;
    }
    Ok((used, updates))
}

/// Where a run's verified model was made: its checkpoint's iteration, the environment steps
/// the learner had received and the seconds since the run's start then (the model's
/// manifest), and the updates and samples trained on up to it (`metrics.jsonl`).
#[derive(Clone, Copy, Debug, PartialEq)]
struct Verified {
    iteration: u64,
    env_steps: u64,
    made_s: f64,
    updates: usize,
    samples: u64,
}

/// The run's verified model (`model/manifest.json` with `verified_trials`); None when its
/// best model was not verified.
fn verified_point(run: &std::path::Path) -> Result<Option<Verified>> {
    let path = run.join("model/manifest.json");
    let Ok(text) = std::fs::read_to_string(&path) else { return Ok(None) };
    let m: serde_json::Value = serde_json::from_str(&text).with_context(|| format!("{}", path.display()))?;
    let t = &m["training"];
    if t["verified_trials"].is_null() {
        return Ok(None);
    }
    let field = |k: &str| t[k].as_f64().with_context(|| format!("{}: training.{k} missing", path.display()));
    let iteration = field("iteration")? as u64;
    let metrics = std::fs::read_to_string(run.join("metrics.jsonl")).with_context(|| format!("{}", run.display()))?;
    let (mut updates, mut samples) = (0, 0);
    for line in metrics.lines() {
        let v: serde_json::Value = serde_json::from_str(line)?;
        if v["iteration"].as_u64().is_some_and(|i| i <= iteration) {
            updates += 1;
            samples += v["steps"].as_u64().unwrap_or(0);
        }
    }
    Ok(Some(Verified { iteration, env_steps: field("env_steps")? as u64, made_s: field("seconds")?, updates, samples }))
}

/// A camera model of DeepRacer's `network` (5 discrete actions, seed 1, policy version 1),
/// as the benches publish and write it.
pub(crate) fn camera_model(network: &str) -> Result<policy::ModelFolder> {
    let text = format!(
        r#"{{"action_space":[{{"steering_angle":-30,"speed":1}},{{"steering_angle":-15,"speed":1}},{{"steering_angle":0,"speed":1}},{{"steering_angle":15,"speed":1}},{{"steering_angle":30,"speed":1}}],"sensor":["FRONT_FACING_CAMERA"],"neural_network":"{network}","version":"5"}}"#
    );
    let metadata = policy::ModelMetadata::parse(&text, "bench")?;
    let model = policy::ActorCritic::new(&metadata, 0, &mut rand_chacha::ChaCha8Rng::seed_from_u64(1));
    let manifest = policy::Manifest {
        format: "paddock-model-1".into(),
        policy_version: 1,
        parent: None,
        weights_sha256: String::new(),
        obs_size: model.obs_size(),
        observation: serde_json::json!({"kind": "camera"}),
        training: serde_json::Value::Null,
    };
    Ok(policy::ModelFolder { metadata, model, manifest })
}

/// `bench model-files`: for each DeepRacer network (one camera, 5 discrete actions), the
/// median time to export the policy as DeepRacer's archive and to import it back, beside the
/// time to save and load the same model as a Paddock folder (the reference, measured in the
/// same run); the archive's size.
pub fn model_files(repeats: usize) -> Result<()> {
    let repeats = repeats.max(1);
    let dir = std::env::temp_dir().join(format!("paddock-bench-model-files-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    println!(
        "network                               archive MB  export ms  import ms  folder save ms  folder load ms  export/save  import/load"
    );
    for network in
        ["DEEP_CONVOLUTIONAL_NETWORK_SHALLOW", "DEEP_CONVOLUTIONAL_NETWORK", "DEEP_CONVOLUTIONAL_NETWORK_DEEP"]
    {
        let policy::ModelFolder { metadata: meta, model, manifest } = camera_model(network)?;
        let archive = dir.join("m.tar.gz");
        let folder = dir.join("m");
        let median = |mut v: Vec<f64>| {
            v.sort_by(f64::total_cmp);
            v[v.len() / 2]
        };
        let time = |f: &mut dyn FnMut() -> Result<()>| -> Result<f64> {
            let mut v = vec![];
            for _ in 0..repeats {
                let t = Instant::now();
                f()?;
                v.push(t.elapsed().as_secs_f64() * 1e3);
            }
            Ok(median(v))
        };
        let mut size = 0;
        let export = time(&mut || {
            size = policy::carpkg::write(&archive, &model, &meta)?;
            Ok(())
        })?;
        let import = time(&mut || {
            let f = policy::carpkg::read(&archive)?.to_folder("bench", 1)?;
            anyhow::ensure!(f.model.pi == model.pi, "the imported policy differs");
            Ok(())
        })?;
        let save = time(&mut || {
            policy::folder::save(&folder, &meta, &model, &manifest)?;
            Ok(())
        })?;
        let load = time(&mut || {
            policy::folder::load(&folder)?;
            Ok(())
        })?;
        println!(
            "{network:<37} {:>10.1} {export:>10.0} {import:>10.0} {save:>15.0} {load:>15.0} {:>12.2} {:>12.2}",
            size as f64 / 1e6,
            export / save,
            import / load
        );
    }
    std::fs::remove_dir_all(&dir)?;
    Ok(())
}

pub fn publish(repeats: usize) -> Result<()> {
    let port = coordinator::supervise::free_port()?;
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let learner = net::open(&NetArgs { listen: vec![endpoint.clone()], ..Default::default() })?;
    let folder = camera_model("DEEP_CONVOLUTIONAL_NETWORK_SHALLOW")?;
    let (m, man, w) = policy::folder::to_parts(&folder);
    let job = "bench";
    let (tx, rx) = std::sync::mpsc::channel::<(usize, u64, Instant)>();
    let mut agents = Vec::new();
    for i in 0..4 {
        let s = net::open(&NetArgs { connect: vec![endpoint.clone()], ..Default::default() })?;
        let tx = tx.clone();
        let sub = s
            .declare_subscriber(keys::policy(job))
            .callback(move |sample| {
                let got = Instant::now();
                let bytes = sample.payload().to_bytes();
                if let Ok(u) = protocol::decode::<PolicyUpdate>(&bytes) {
                    let _ = tx.send((i, u.policy_version, got));
                }
            })
            .wait()
            .map_err(|e| anyhow::anyhow!("{e}"))?;
        agents.push((s, sub));
    }
    std::thread::sleep(Duration::from_secs(2));
    let publisher = learner
        .declare_publisher(keys::policy(job))
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let size = protocol::encode(&PolicyUpdate {
        protocol_version: PROTOCOL_VERSION,
        job_id: job.into(),
        policy_version: 0,
        weights: w.clone(),
        model_metadata_json: m.clone(),
        manifest_json: man.clone(),
        signature_json: String::new(),
    })
    .len();
    println!(
        "# coordinator bench publish: SHALLOW camera model (policy + value towers), {:.1} MB on the wire, 4 agent sessions on loopback",
        size as f64 / 1e6
    );
    println!();
    let mut lat = Vec::new();
    for v in 1..=repeats as u64 {
        let u = PolicyUpdate {
            protocol_version: PROTOCOL_VERSION,
            job_id: job.into(),
            policy_version: v,
            weights: w.clone(),
            model_metadata_json: m.clone(),
            manifest_json: man.clone(),
            signature_json: String::new(),
        };
        let t0 = Instant::now();
        publisher.put(protocol::encode(&u)).wait().map_err(|e| anyhow::anyhow!("{e}"))?;
        let mut seen = 0;
        let mut last = t0;
        while seen < 4 {
            let (_, ver, at) =
                rx.recv_timeout(Duration::from_secs(10)).context("an agent did not receive the model within 10 s")?;
            if ver == v {
                seen += 1;
                last = last.max(at);
            }
        }
        lat.push(last.duration_since(t0).as_secs_f64() * 1e3);
        std::thread::sleep(Duration::from_millis(200));
    }
    lat.sort_by(|a, b| a.total_cmp(b));
    println!("| measurement | value |");
    println!("|---|---|");
    println!(
        "| publish → all 4 agents hold it (encode + send + receive + decode), median of {repeats} | {:.1} ms |",
        lat[lat.len() / 2]
    );
    println!("| same, worst | {:.1} ms |", lat[lat.len() - 1]);
    // Experience on the wire: a real batch from the state-vector simulator.
    let cfg = Arc::new(sim_agent::SimConfig::default());
    let spec = sim_agent::EnvSpec::from_world(&tracks::world("reinvent_base")?, tracks::Direction::Forward);
    let vec = sim_agent::VecEnv::new(
        vec![spec; 8],
        cfg.clone(),
        1,
        sim_agent::RewardFn::Builtin(sim_agent::BuiltinReward::CenterLine),
        1,
    )?;
    let meta = policy::ModelMetadata::default_state_vector();
    let obs = sim_agent::obs::obs_dim(&cfg.observation);
    let mut collector = sim_agent::rollout::Collector::new(vec, meta.action_space.clone(), 1);
    let model = Arc::new(policy::ActorCritic::new(&meta, obs, &mut rand_chacha::ChaCha8Rng::seed_from_u64(1)));
    let trajs = collector.collect(&model, 0, 16)?;
    let steps: usize = trajs.iter().map(|t| t.len()).sum();
    let batch = protocol::ExperienceBatch {
        protocol_version: PROTOCOL_VERSION,
        job_id: "bench".into(),
        agent_id: "agent-1".into(),
        seq: 1,
        trajectories: trajs.iter().map(|t| protocol::trajectory_to_wire(t, obs)).collect(),
        env_steps: steps as u64,
        seconds: 0.0,
        credit_version: 0,
        credit_round: 1,
    };
    let bytes = protocol::encode(&batch).len();
    println!(
        "| experience on the wire, state vector ({obs} floats), {steps} steps in 16 episodes | {:.0} bytes per env step |",
        bytes as f64 / steps as f64
    );
    drop(agents);
    Ok(())
}

/// Prints a bench's last line, `verdict: pass: WHAT` or `verdict: FAIL: ` and the failures,
/// and returns its exit code (0 or 1).
pub(crate) fn verdict(failed: &[String], pass: &str) -> i32 {
    if failed.is_empty() {
        println!("verdict: pass: {pass}");
        0
    } else {
        println!("verdict: FAIL: {}", failed.join(", "));
        1
    }
}

/// Run `coordinator ARGS` in `dir`, showing its progress; return its stdout.
fn child(me: &std::path::Path, dir: &std::path::Path, args: &[String]) -> Result<String> {
    eprintln!("bench: coordinator {}", args.join(" "));
    let o = Command::new(me).args(args).current_dir(dir).stderr(std::process::Stdio::inherit()).output()?;
    let text = String::from_utf8_lossy(&o.stdout).to_string();
    if !o.status.success() {
        bail!("coordinator {} failed:\n{text}", args.join(" "));
    }
    Ok(text)
}

/// Wall-clock (s, from the run's start) of each iteration in a run's `metrics.jsonl`.
fn iteration_times(run: &std::path::Path) -> Result<Vec<f64>> {
    let text = std::fs::read_to_string(run.join("metrics.jsonl")).with_context(|| format!("{}", run.display()))?;
    text.lines()
        .map(|l| Ok(serde_json::from_str::<serde_json::Value>(l)?["time_s"].as_f64().unwrap_or(f64::NAN)))
        .collect()
}

/// How a run's evaluations went after its first that lapped every trial on every world:
/// (iteration of that one, evaluations after it, of those the ones that lapped everywhere).
/// Verifications are not counted: they are the same checkpoint again.
fn after_first_lap(run: &std::path::Path) -> Result<Option<(u64, usize, usize)>> {
    let path = run.join("evaluations.jsonl");
    let text = std::fs::read_to_string(&path).with_context(|| format!("{}", path.display()))?;
    let mut first = None;
    let (mut after, mut held) = (0, 0);
    for line in text.lines() {
        let e: serde_json::Value = serde_json::from_str(line).with_context(|| format!("{}", path.display()))?;
        if e["verification"].as_bool() == Some(true) {
            continue;
        }
        let everywhere = e["min_laps"].as_u64().unwrap_or(0) >= e["trials"].as_u64().unwrap_or(u64::MAX);
        if first.is_some() {
            after += 1;
            held += usize::from(everywhere);
        } else if everywhere {
            first = e["iteration"].as_u64();
        }
    }
    Ok(first.map(|f| (f, after, held)))
}

/// "v of n (p %)" for evaluations after the first that lapped everywhere.
fn held_share(a: Option<(u64, usize, usize)>) -> String {
    match a {
        None => "never lapped everywhere".into(),
        Some((it, 0, _)) => format!("first at iteration {it}; none after"),
        Some((it, n, h)) => format!("first at iteration {it}; then {h} of {n} ({:.0} %)", 100.0 * h as f64 / n as f64),
    }
}

/// One seed's two runs of one variant.
struct PixelsRun {
    /// The variant's name (`today` for the setup as it is).
    variant: String,
    /// Its folder.
    here: std::path::PathBuf,
    seed: u64,
    train_s: f64,
    up_s: f64,
    train_reason: String,
    up_reason: String,
    /// (updates, samples trained on) of each.
    train: (usize, f64),
    up: (usize, f64),
    /// Each iteration's wall-clock in each.
    train_times: Vec<f64>,
    up_times: Vec<f64>,
    /// [`after_first_lap`] of each.
    train_after: Option<(u64, usize, usize)>,
    up_after: Option<(u64, usize, usize)>,
    /// [`verified_point`] of each.
    train_verified: Option<Verified>,
    up_verified: Option<Verified>,
}

/// Laps out of trials.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
struct Laps {
    laps: u32,
    trials: u32,
}

impl Laps {
    fn describe(&self) -> String {
        format!("{} of {}", self.laps, self.trials)
    }
}

/// The laps of a setup's models at the end, on the worlds trained on and on the others.
#[derive(Default)]
struct LapTally {
    training: Laps,
    unseen: Laps,
    by_world: BTreeMap<String, Laps>,
}

impl LapTally {
    /// Count one model's table; worlds in `training` were trained on.
    fn add(&mut self, rows: &[(String, Laps)], training: &[String]) {
        for (world, l) in rows {
            let part = if training.contains(world) { &mut self.training } else { &mut self.unseen };
            for c in [part, self.by_world.entry(world.clone()).or_default()] {
                c.laps += l.laps;
                c.trials += l.trials;
            }
        }
    }
}

/// The rows of `coordinator evaluate`'s table (`WORLD  LAPS  PROGRESS  MEAN LAP`): each
/// world's laps out of its trials.
fn table_laps(text: &str) -> Vec<(String, Laps)> {
    text.lines()
        .skip_while(|l| !l.starts_with("WORLD"))
        .skip(1)
        .map_while(|l| {
            let mut cols = l.split_whitespace();
            let world = cols.next()?;
            let (laps, trials) = cols.next()?.split_once('/')?;
            Some((world.to_string(), Laps { laps: laps.parse().ok()?, trials: trials.parse().ok()? }))
        })
        .collect()
}

/// `bench pixels`: `train` and `up` from pixels on several worlds, per seed, to the verified
/// model (or, with `keep_training`, for the whole time, to see whether a policy that lapped
/// everywhere stays good), then both models on those worlds and on unseen ones.
/// A setup's command line `base` with a variant's arguments `more` added; a flag of `more` that
/// `base` gives too (`--checkpoint-seconds 2`, `--force`) replaces `base`'s, with its value.
fn with_variant(mut base: Vec<String>, more: &[String]) -> Vec<String> {
    let valued = |args: &[String], i: usize| args.get(i + 1).is_some_and(|v| !v.starts_with("--"));
    for (k, flag) in more.iter().enumerate().filter(|(_, a)| a.starts_with("--")) {
        if let Some(i) = base.iter().position(|a| a == flag) {
            let n = if valued(more, k) && valued(&base, i) { 2 } else { 1 };
            base.drain(i..i + n);
        }
    }
    base.extend(more.iter().cloned());
    base
}

pub fn pixels(args: &crate::cli::PixelsArgs) -> Result<()> {
    let crate::cli::PixelsArgs {
        worlds,
        unseen,
        trials,
        minutes,
        envs,
        evals,
        verify_trials,
        keep_training,
        checkpoint_seconds,
        seeds,
        variants,
        out,
    } = args;
    let (minutes, envs, evals, verify_trials, keep_training, checkpoint_seconds) =
        (*minutes, *envs, *evals, *verify_trials, *keep_training, *checkpoint_seconds);
    if seeds.is_empty() {
        bail!("--seeds: give at least one seed");
    }
    // Today's setup first, then each variant with its arguments.
    let mut setups: Vec<(String, Vec<String>)> = vec![("today".into(), vec![])];
    for v in variants {
        let (name, more) = v.split_once('=').unwrap_or((v.as_str(), ""));
        if name.is_empty()
            || !name.chars().all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
            || setups.iter().any(|(n, _)| n == name)
        {
            bail!(
                "--variant '{v}': expected NAME=ARGS, NAME of letters, digits, '-' and '_', each name once (not 'today')"
            );
        }
        // The runs start in their own folders: a file named here is passed as its full path.
        setups.push((name.to_string(), more.split_whitespace().map(full_path).collect()));
    }
    let me = std::env::current_exe()?;
    std::fs::create_dir_all(out)?;
    let dir = out.canonicalize()?;
    // One setup's command line: its own arguments, then what both setups share.
    let command = |head: &[&str], seed: u64| -> Vec<String> {
        let mut v: Vec<String> = head.iter().map(|s| s.to_string()).collect();
        for w in worlds {
            v.extend(["--world".into(), w.clone()]);
        }
        v.extend(["--sensor", "camera", "--set", "camera.randomize=true"].map(String::from));
        v.extend(["--checkpoint-seconds".into(), checkpoint_seconds.to_string()]);
        let laps = if keep_training { "0" } else { "3" };
        v.extend(["--target-laps".into(), laps.into(), "--target-evals".into(), evals.to_string()]);
        v.extend(["--verify-trials".into(), verify_trials.to_string(), "--minutes".into(), minutes.to_string()]);
        v.extend(["--seed".into(), seed.to_string()]);
        v
    };
    let timed = |here: &std::path::Path, args: &[String]| -> Result<(f64, String)> {
        let t0 = Instant::now();
        let text = child(&me, here, args)?;
        Ok((t0.elapsed().as_secs_f64(), text))
    };
    let (envs_s, agent_envs) = (envs.to_string(), (envs / 2).max(1).to_string());
    let mut all_runs = Vec::new();
    // Seed by seed, every variant in turn: whatever the machine does over the hours falls
    // on all of them alike.
    for (&seed, (variant, more)) in seeds.iter().flat_map(|s| setups.iter().map(move |v| (s, v))) {
        let here = match setups.len() {
            1 => dir.join(format!("seed-{seed}")),
            _ => dir.join(format!("seed-{seed}")).join(variant),
        };
        std::fs::create_dir_all(&here)?;
        let train = with_variant(command(&["train", "--envs", &envs_s, "--out", "train", "--force"], seed), more);
        let (train_s, text) = timed(&here, &train)?;
        let train_reason = text.lines().find(|l| l.starts_with("stopped after")).unwrap_or("").to_string();
        let up = with_variant(
            command(&["up", "--agents", "2", "--envs", &agent_envs, "--out", "up", "--force"], seed),
            more,
        );
        let (up_s, text) = timed(&here, &up)?;
        let up_reason =
            text.lines().find(|l| l.contains(": Finished") || l.contains(": Failed")).unwrap_or("").trim().to_string();
        let (ts, tu) = used_samples(&here.join("train"))?;
        let (us, uu) = used_samples(&here.join("up/run"))?;
        all_runs.push(PixelsRun {
            variant: variant.clone(),
            here: here.clone(),
            seed,
            train_s,
            up_s,
            train_reason,
            up_reason,
            train: (tu, ts),
            up: (uu, us),
            train_times: iteration_times(&here.join("train"))?,
            up_times: iteration_times(&here.join("up/run"))?,
            train_after: after_first_lap(&here.join("train"))?,
            up_after: after_first_lap(&here.join("up/run"))?,
            train_verified: verified_point(&here.join("train"))?,
            up_verified: verified_point(&here.join("up/run"))?,
        });
    }
    println!(
        "# coordinator bench pixels: {} from pixels, domain randomisation on, {envs} environments, seeds {seeds:?}",
        worlds.join(", ")
    );
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        let n = v.len();
        if n == 0 {
            return f64::NAN;
        }
        if n % 2 == 1 { v[n / 2] } else { (v[n / 2 - 1] + v[n / 2]) / 2.0 }
    };
    let mut lap_rows: Vec<(String, LapTally)> = Vec::new();
    for (variant, more) in &setups {
        let runs: Vec<&PixelsRun> = all_runs.iter().filter(|r| &r.variant == variant).collect();
        if setups.len() > 1 {
            println!();
            println!(
                "## {variant}{}",
                if more.is_empty() { " (the setup as it is)".to_string() } else { format!(": {}", more.join(" ")) }
            );
        }
        println!();
        println!(
            "| seed | setup | wall-clock s (process start to model) | updates | samples trained on | how it stopped | evaluations after the first that lapped everywhere, lapping everywhere |"
        );
        println!("|---|---|---|---|---|---|---|");
        for r in &runs {
            println!(
                "| {} | `train` in one process | {:.0} | {} | {:.0} | {} | {} |",
                r.seed,
                r.train_s,
                r.train.0,
                r.train.1,
                r.train_reason,
                held_share(r.train_after)
            );
            println!(
                "| {} | `up`, 2 agents × {agent_envs} envs (+ coordinator + learner) | {:.0} | {} | {:.0} | {} | {} |",
                r.seed,
                r.up_s,
                r.up.0,
                r.up.1,
                r.up_reason,
                held_share(r.up_after)
            );
        }
        let (n, h) = runs
            .iter()
            .flat_map(|r| [r.train_after, r.up_after])
            .flatten()
            .fold((0, 0), |(n, h), (_, a, b)| (n + a, h + b));
        if n > 0 {
            println!();
            println!(
                "After their first evaluation that lapped everywhere, {h} of the runs' {n} later evaluations lapped everywhere ({:.0} %).",
                100.0 * h as f64 / n as f64
            );
        }
        println!();
        // What the verified model took: a change that makes each step cheaper shows in the seconds
        // alone, one that makes fewer steps suffice in the steps and updates too.
        println!(
            "The verified model: when its checkpoint was made (s from the learner's start), the updates, environment steps and samples trained on up to it."
        );
        println!();
        println!(
            "| seed | setup | made at s | stopped at s (process) | iteration | updates | env steps | samples trained on |"
        );
        println!("|---|---|---|---|---|---|---|---|");
        let mut made: [Vec<f64>; 2] = [Vec::new(), Vec::new()];
        let mut steps: [Vec<f64>; 2] = [Vec::new(), Vec::new()];
        for r in &runs {
            for (k, (setup, v, stop)) in
                [("`train`", r.train_verified, r.train_s), ("`up`", r.up_verified, r.up_s)].into_iter().enumerate()
            {
                match v {
                    Some(v) => {
                        println!(
                            "| {} | {setup} | {:.0} | {stop:.0} | {} | {} | {} | {} |",
                            r.seed, v.made_s, v.iteration, v.updates, v.env_steps, v.samples
                        );
                        made[k].push(v.made_s);
                        steps[k].push(v.env_steps as f64);
                    }
                    None => println!("| {} | {setup} | no verified model | {stop:.0} | | | | |", r.seed),
                }
            }
        }
        for (k, setup) in ["`train`", "`up`"].iter().enumerate() {
            if !made[k].is_empty() {
                println!();
                println!(
                    "{setup}: median made at {:.0} s, after {:.0} environment steps ({} of {} seeds verified).",
                    median(made[k].clone()),
                    median(steps[k].clone()),
                    made[k].len(),
                    runs.len()
                );
            }
        }
        println!();
        let (mt, mu) =
            (median(runs.iter().map(|r| r.train_s).collect()), median(runs.iter().map(|r| r.up_s).collect()));
        let (st, su) = (runs.iter().map(|r| r.train_s).sum::<f64>(), runs.iter().map(|r| r.up_s).sum::<f64>());
        let mut ratios: Vec<f64> = runs.iter().map(|r| r.up_s / r.train_s).collect();
        ratios.sort_by(f64::total_cmp);
        let ratios: Vec<String> = ratios.iter().map(|r| format!("{r:.2}")).collect();
        println!(
            "Time to the stop over {} seed(s): summed, `train` {st:.0} s, `up` {su:.0} s ({:.2}×); medians {mt:.0} s and {mu:.0} s ({:.2}×); `up` was faster in {} of them; per seed `up` / `train` {}.",
            runs.len(),
            su / st,
            mu / mt,
            runs.iter().filter(|r| r.up_s < r.train_s).count(),
            ratios.join(", ")
        );
        println!();
        // The pace of learning, apart from when the stop rule fires: the wall-clock at which each
        // setup finished the same PPO iteration (the same number of episodes trained on).
        println!("Pace: wall-clock (s from the run's start) at the end of the same PPO iteration.");
        println!();
        println!("| seed | iteration | `train` s | `up` s | `up` / `train` |");
        println!("|---|---|---|---|---|");
        let mut paces = Vec::new();
        for r in &runs {
            let common = r.train_times.len().min(r.up_times.len());
            let mut marks = vec![common / 4, common / 2, common];
            marks.retain(|&k| k > 0);
            marks.dedup();
            for k in marks {
                let (t, u) = (r.train_times[k - 1], r.up_times[k - 1]);
                println!("| {} | {k} | {t:.0} | {u:.0} | {:.2} |", r.seed, u / t);
                if k == common {
                    paces.push(u / t);
                }
            }
        }
        if !paces.is_empty() {
            println!();
            println!(
                "Pace at the last iteration both reached, median over seeds: `up` / `train` = {:.2}.",
                median(paces)
            );
        }
        println!();
        // Both models on the training worlds and on tracks they never saw.
        let all: Vec<String> = worlds.iter().chain(unseen).cloned().collect();
        let mut laps = LapTally::default();
        for r in &runs {
            let here = &r.here;
            for (name, model) in [("train", "train/model"), ("up", "up/run/model")] {
                let mut args = vec!["evaluate".to_string(), model.into(), "--trials".into(), trials.to_string()];
                for w in &all {
                    args.extend(["--world".into(), w.clone()]);
                }
                let text = child(&me, here, &args)?;
                laps.add(&table_laps(&text), worlds);
                println!("seed {}, {name} model ({}):", r.seed, here.join(model).display());
                println!();
                println!("```");
                for l in text.lines().skip_while(|l| !l.starts_with("WORLD")) {
                    println!("{l}");
                }
                println!("```");
                println!();
            }
        }
        println!(
            "Laps of both models of every seed, {trials} trials a world: the training worlds {}; the unseen tracks {}.",
            laps.training.describe(),
            laps.unseen.describe()
        );
        let by_world: Vec<String> = laps.by_world.iter().map(|(w, c)| format!("{w} {}", c.describe())).collect();
        println!();
        println!("By world: {}.", by_world.join(", "));
        lap_rows.push((variant.clone(), laps));
    }
    if setups.len() > 1 {
        // Medians over the seeds, per variant: a variant that makes steps cheaper shows in
        // the seconds alone, one that makes fewer suffice in the steps and updates too.
        println!();
        println!("## The variants side by side (medians over seeds {seeds:?})");
        println!();
        println!(
            "| variant | `train` stop s | `up` stop s | `train` model made at s | `up` model made at s | env steps to it (`train`, `up`) | updates to it (`train`, `up`) | verified (`train`, `up`) | laps, {trials} trials a world (training worlds; unseen) |"
        );
        println!("|---|---|---|---|---|---|---|---|---|");
        for (variant, _) in &setups {
            let runs: Vec<&PixelsRun> = all_runs.iter().filter(|r| &r.variant == variant).collect();
            let of = |f: &dyn Fn(&PixelsRun) -> Option<f64>| median(runs.iter().filter_map(|r| f(r)).collect());
            let shown = |x: f64| if x.is_finite() { format!("{x:.0}") } else { "-".into() };
            println!(
                "| {variant} | {} | {} | {} | {} | {}, {} | {}, {} | {} of {}, {} of {} | {} |",
                shown(of(&|r| Some(r.train_s))),
                shown(of(&|r| Some(r.up_s))),
                shown(of(&|r| r.train_verified.map(|v| v.made_s))),
                shown(of(&|r| r.up_verified.map(|v| v.made_s))),
                shown(of(&|r| r.train_verified.map(|v| v.env_steps as f64))),
                shown(of(&|r| r.up_verified.map(|v| v.env_steps as f64))),
                shown(of(&|r| r.train_verified.map(|v| v.updates as f64))),
                shown(of(&|r| r.up_verified.map(|v| v.updates as f64))),
                runs.iter().filter(|r| r.train_verified.is_some()).count(),
                runs.len(),
                runs.iter().filter(|r| r.up_verified.is_some()).count(),
                runs.len(),
                lap_rows
                    .iter()
                    .find(|(v, _)| v == variant)
                    .map(|(_, l)| format!("{}; {}", l.training.describe(), l.unseen.describe()))
                    .unwrap_or_default()
            );
        }
    }
    Ok(())
}

/// One wire round: a learner session listening on loopback and an agent session connected to
/// it, both with `certs` (mutual TLS and the access rules) or plain TCP; the agent puts `batch`
/// as fast as the link takes it for `seconds`. Returns (messages/s, MB/s) received.
fn wire_round(certs: Option<&std::path::Path>, batch: &[u8], seconds: f64) -> Result<(f64, f64)> {
    use protocol::secure::Role;
    use std::sync::atomic::{AtomicU64, Ordering};
    let port = coordinator::supervise::free_port()?;
    let proto = if certs.is_some() { "tls" } else { "tcp" };
    let endpoint = format!("{proto}/127.0.0.1:{port}");
    let base = NetArgs { certs: certs.map(|p| p.to_path_buf()), ..Default::default() };
    let learner = net::open(&NetArgs { listen: vec![endpoint.clone()], ..base.clone() }.as_role(Role::Learner))?;
    let agent = net::open(&NetArgs { connect: vec![endpoint.clone()], ..base.clone() }.as_role(Role::Agent))?;
    let job = "wirebench";
    let (msgs, bytes) = (Arc::new(AtomicU64::new(0)), Arc::new(AtomicU64::new(0)));
    let (m2, b2) = (msgs.clone(), bytes.clone());
    let _sub = learner
        .declare_subscriber(keys::experience_all(job))
        .callback(move |s| {
            m2.fetch_add(1, Ordering::Relaxed);
            b2.fetch_add(s.payload().len() as u64, Ordering::Relaxed);
        })
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let publisher = agent
        .declare_publisher(keys::experience(job, "agent-1"))
        .congestion_control(zenoh::qos::CongestionControl::Block)
        .wait()
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let t0 = Instant::now();
    while !publisher.matching_status().wait().map_err(|e| anyhow::anyhow!("{e}"))?.matching() {
        if t0.elapsed() > Duration::from_secs(10) {
            bail!("{proto}: the learner's subscriber did not reach the agent within 10 s");
        }
        std::thread::sleep(Duration::from_millis(20));
    }
    // Warm up, then count what arrives while the agent sends for `seconds`.
    for _ in 0..20 {
        publisher.put(batch.to_vec()).wait().map_err(|e| anyhow::anyhow!("{e}"))?;
    }
    std::thread::sleep(Duration::from_millis(200));
    let (m0, b0) = (msgs.load(Ordering::Relaxed), bytes.load(Ordering::Relaxed));
    let t = Instant::now();
    while t.elapsed().as_secs_f64() < seconds {
        publisher.put(batch.to_vec()).wait().map_err(|e| anyhow::anyhow!("{e}"))?;
    }
    let dt = t.elapsed().as_secs_f64();
    let (m1, b1) = (msgs.load(Ordering::Relaxed), bytes.load(Ordering::Relaxed));
    if m1 == m0 {
        bail!("{proto}: nothing arrived at the learner");
    }
    drop(publisher);
    let _ = agent.close().wait();
    let _ = learner.close().wait();
    Ok(((m1 - m0) as f64 / dt, (b1 - b0) as f64 / dt / 1e6))
}

/// Run `measure(plain)` and `measure(secured)` `rounds` times each, alternating which goes
/// first (neither always gets the warmer machine); the medians of each pair's two figures,
/// plain first.
fn interleaved(rounds: usize, mut measure: impl FnMut(bool) -> Result<(f64, f64)>) -> Result<[(f64, f64); 2]> {
    let mut runs: [Vec<(f64, f64)>; 2] = [Vec::new(), Vec::new()];
    for r in 0..rounds {
        let order = if r % 2 == 0 { [false, true] } else { [true, false] };
        for secure in order {
            runs[secure as usize].push(measure(secure)?);
        }
    }
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    Ok(runs.map(|v| (median(v.iter().map(|x| x.0).collect()), median(v.iter().map(|x| x.1).collect()))))
}

/// `bench wire`: experience throughput agent → learner on loopback, plain TCP against mutual
/// TLS with the access rules, rounds interleaved in one run, medians compared.
pub fn wire(seconds: f64, rounds: usize, up_seconds: f64) -> Result<()> {
    let certs = std::env::temp_dir().join(format!("paddock-bench-wire-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&certs);
    crate::certs::write(&certs, false, &protocol::secure::DEFAULT_SLOTS)?;
    let batch = |trajectories: usize, steps: usize, obs: usize| {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        use rand::Rng;
        let t = (0..trajectories)
            .map(|i| protocol::Trajectory {
                env: i as u32,
                episode: i as u64,
                policy_version: 1,
                obs_size: obs as u32,
                obs: (0..steps * obs).map(|_| rng.random::<f32>()).collect(),
                discrete_actions: (0..steps).map(|_| rng.random_range(0..5)).collect(),
                logp: vec![-1.6; steps],
                values: vec![0.5; steps],
                rewards: vec![1.0; steps],
                done: true,
                progress: 50.0,
                world: "reinvent_base".into(),
                ..Default::default()
            })
            .collect();
        protocol::encode(&protocol::ExperienceBatch {
            protocol_version: PROTOCOL_VERSION,
            job_id: "wirebench".into(),
            agent_id: "agent-1".into(),
            seq: 1,
            trajectories: t,
            env_steps: (trajectories * steps) as u64,
            seconds: 1.0,
            ..Default::default()
        })
    };
    println!(
        "# coordinator bench wire: experience agent -> learner on loopback, {seconds} s x {rounds} rounds per link, interleaved; medians"
    );
    println!();
    println!("| batch | bytes | TCP msgs/s | TCP MB/s | TLS+ACL msgs/s | TLS+ACL MB/s | TLS+ACL / TCP |");
    println!("|---|---:|---:|---:|---:|---:|---:|");
    let workloads = [
        ("state: 16 episodes x 120 steps x 27 floats", batch(16, 120, 27)),
        ("camera: 4 episodes x 15 steps x 19200 floats", batch(4, 15, 19200)),
    ];
    for (name, b) in &workloads {
        let [(tm, tb), (sm, sb)] =
            interleaved(rounds, |secure| wire_round(secure.then_some(certs.as_path()), b, seconds))?;
        println!("| {name} | {} | {tm:.0} | {tb:.0} | {sm:.0} | {sb:.0} | {:.3} |", b.len(), sb / tb);
    }
    if up_seconds > 0.0 {
        // The whole loop: experience the learner trained on, with and without TLS + access
        // control, `up` with 2 agents on one world, alternating.
        println!();
        println!(
            "| `up`, 2 agents x 8 envs, reinvent_base, {up_seconds:.0} s | samples trained on/s (median of {rounds}) | env steps simulated/s | ratio |"
        );
        println!("|---|---:|---:|---:|");
        let minutes = format!("{}", up_seconds / 60.0);
        let tmp = std::env::temp_dir().join(format!("paddock-bench-wire-up-{}", std::process::id()));
        let mut n = 0;
        let [(pu, ps), (su, ss)] = interleaved(rounds, |secure| {
            n += 1;
            let row =
                up_row(&tmp.join(n.to_string()), "reinvent_base", 2, 8, &minutes, secure.then_some(certs.as_path()))?;
            Ok((row.used / row.secs, row.steps / row.secs))
        })?;
        let _ = std::fs::remove_dir_all(&tmp);
        println!("| plain TCP | {pu:.0} | {ps:.0} | 1.000 |");
        println!("| TLS + access control (`--certs`) | {su:.0} | {ss:.0} | {:.3} |", su / pu);
    }
    let _ = std::fs::remove_dir_all(&certs);
    Ok(())
}

/// `bench record`: what recording (sim-trace, metrics JSON, MCAP) costs. The same training
/// with `record_trace` on and off, rounds interleaved in one run: `train` in one process and
/// `up` with 2 agents, on reinvent_base, state vector; medians of env steps/s and samples
/// trained on/s.
pub fn record(seconds: f64, rounds: usize) -> Result<()> {
    let me = std::env::current_exe()?;
    let tmp = std::env::temp_dir().join(format!("paddock-bench-record-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir_all(&tmp)?;
    let minutes = format!("{}", seconds / 60.0);
    println!(
        "# coordinator bench record: recording on against off, {seconds} s x {rounds} rounds each, interleaved; medians"
    );
    println!();
    println!("| setup | recording | env steps/s | samples trained on/s | run folder MB | on / off (steps/s) |");
    println!("|---|---|---:|---:|---:|---:|");
    let mut n = 0;
    for setup in ["train", "up"] {
        let mut sizes = [0.0f64; 2];
        let [(off_steps, off_used), (on_steps, on_used)] = interleaved(rounds, |on| {
            n += 1;
            let out = tmp.join(n.to_string());
            let set = format!("record_trace={on}");
            let (steps, used, secs, run) = if setup == "train" {
                let args: Vec<String> = [
                    "train",
                    "--world",
                    "reinvent_base",
                    "--target-laps",
                    "0",
                    "--minutes",
                    &minutes,
                    "--set",
                    &set,
                    "--out",
                ]
                .iter()
                .map(|s| s.to_string())
                .chain([out.display().to_string()])
                .collect();
                child(&me, &tmp, &args)?;
                let s: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("summary.json"))?)?;
                let (used, _) = used_samples(&out)?;
                (s["env_steps"].as_f64().unwrap_or(0.0), used, s["seconds"].as_f64().unwrap_or(1.0), out.clone())
            } else {
                let mut cmd = Command::new(&me);
                cmd.args([
                    "up",
                    "--world",
                    "reinvent_base",
                    "--agents",
                    "2",
                    "--envs",
                    "8",
                    "--minutes",
                    &minutes,
                    "--set",
                    &set,
                    "--out",
                ])
                .arg(&out);
                eprintln!("bench: coordinator up ... --set {set}");
                let o = cmd.output()?;
                if !o.status.success() {
                    bail!("up failed: {}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
                }
                let s: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("summary.json"))?)?;
                let (used, _) = used_samples(&out.join("run"))?;
                let secs = s["ended"].as_f64().unwrap_or(0.0) - s["started"].as_f64().unwrap_or(0.0);
                (s["learner"]["env_steps"].as_f64().unwrap_or(0.0), used, secs, out.join("run"))
            };
            sizes[on as usize] = folder_bytes(&run) as f64 / 1e6;
            let _ = std::fs::remove_dir_all(&out);
            Ok((steps / secs.max(1e-9), used / secs.max(1e-9)))
        })?;
        println!("| `{setup}` | off | {off_steps:.0} | {off_used:.0} | {:.1} | 1.000 |", sizes[0]);
        println!("| `{setup}` | on | {on_steps:.0} | {on_used:.0} | {:.1} | {:.3} |", sizes[1], on_steps / off_steps);
    }
    let _ = std::fs::remove_dir_all(&tmp);
    Ok(())
}

/// Bytes under `dir`.
fn folder_bytes(dir: &std::path::Path) -> u64 {
    std::fs::read_dir(dir)
        .map(|rd| {
            rd.flatten()
                .map(|e| match e.file_type() {
                    Ok(t) if t.is_dir() => folder_bytes(&e.path()),
                    _ => e.metadata().map(|m| m.len()).unwrap_or(0),
                })
                .sum()
        })
        .unwrap_or(0)
}

/// `bench long-job`: an `up` job on two worlds with two agents for `minutes`, then the model of
/// its last update evaluated; the verdict's exit code is 0 (pass) or 1 (fail).
pub fn long_job(minutes: f64, trials: u32, out: &std::path::Path) -> Result<i32> {
    let me = std::env::current_exe()?;
    if out.exists() {
        bail!("{} exists: pass another --out, or delete it", out.display());
    }
    std::fs::create_dir_all(out).with_context(|| format!("{}", out.display()))?;
    let worlds = ["reinvent_carpet", "reinvent_concrete"];
    let mut args: Vec<String> = vec!["up".into()];
    for w in worlds {
        args.extend(["--world".into(), w.into()]);
    }
    // Stability is under test, not the logs: no gigabytes of sim-trace.
    args.extend(["--agents", "2", "--set", "record_trace=false", "--out", "up"].map(String::from));
    // The whole time: a soak, not a race to the first verified model.
    args.extend(["--minutes".into(), minutes.to_string(), "--target-laps".into(), "0".into()]);
    child(&me, out, &args)?;
    let run = out.join("up/run");
    let index: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("checkpoints/deepracer_checkpoints.json"))?)?;
    let last = &index["last_checkpoint"];
    let iterations = last["iteration"].as_u64().unwrap_or(0);
    let name = last["name"].as_str().context("deepracer_checkpoints.json names no last checkpoint")?;
    let mut eval: Vec<String> = vec!["evaluate".into(), format!("up/run/checkpoints/{name}")];
    for w in worlds {
        eval.extend(["--world".into(), w.into()]);
    }
    eval.extend(["--trials".into(), trials.to_string()]);
    let table = child(&me, out, &eval)?;
    let all = trials as usize * worlds.len();
    // `evaluate` ends with "N of M laps completed, …".
    let laps = table
        .lines()
        .filter(|l| l.contains("laps completed"))
        .find_map(|l| l.split(" of ").next()?.split_whitespace().last()?.parse::<usize>().ok())
        .unwrap_or(0);
    let summary: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("up/summary.json"))?)?;
    let l = &summary["learner"];
    let received = l["episodes_received"].as_f64().unwrap_or(0.0);
    let stale = l["dropped_stale"].as_f64().unwrap_or(0.0);
    let checks = [
        (format!("the last model ({name}) laps every trial"), format!("{laps} of {all}"), laps == all),
        ("updates went on past 120 iterations".to_string(), iterations.to_string(), iterations >= 120),
        (
            "episodes dropped as stale at most 5 %".to_string(),
            format!("{stale:.0} of {received:.0}"),
            received > 0.0 && stale <= 0.05 * received,
        ),
    ];
    println!("{table}");
    println!("| check | figure | verdict |\n|---|---|---|");
    for (what, figure, ok) in &checks {
        println!("| {what} | {figure} | {} |", if *ok { "pass" } else { "FAIL" });
    }
    let pass = checks.iter().all(|c| c.2);
    println!("verdict: {} ({} min job, run folder {})", if pass { "PASS" } else { "FAIL" }, minutes, run.display());
    Ok(if pass { 0 } else { 1 })
}

/// `arg` as given, or its full path when it names a file or folder here (a bench's runs start
/// in folders of their own).
fn full_path(arg: &str) -> String {
    match std::path::Path::new(arg).canonicalize() {
        Ok(p) if !arg.starts_with('-') => p.display().to_string(),
        _ => arg.to_string(),
    }
}

/// One race of `bench races`: its name, the flags that make it (sensor, race, reward). The
/// head-to-bot race is issue 55's: 3 bots at 0.3 m/s, which every lap from the start line meets.
const RACES: [(&str, &[&str]); 5] = [
    ("time_trial", &["--sensor", "camera"]),
    ("object_avoidance", &["--sensor", "camera", "--obstacles", "3", "--reward", "builtin:object_avoidance"]),
    (
        "head_to_bot",
        &["--sensor", "camera", "--bots", "3", "--bot-speed", "0.3", "--reward", "builtin:object_avoidance"],
    ),
    ("stereo", &["--sensor", "stereo"]),
    ("camera_sector_lidar", &["--sensor", "camera+lidar", "--obstacles", "3", "--reward", "builtin:object_avoidance"]),
];

/// Run the training `args` (`train` or `up`), then evaluate its `model` again on `world`
/// (3 trials, with the `race` flags): the wall-clock to the model, how the training stopped,
/// the evaluation's summary line and its laps.
fn train_then_evaluate(
    me: &std::path::Path,
    dir: &std::path::Path,
    args: &[String],
    model: String,
    world: &str,
    race: &[String],
) -> Result<(f64, String, String, u32)> {
    let (secs, stop) = train_to_stop(me, dir, args)?;
    let mut eval = vec!["evaluate".to_string(), model, "--world".into(), world.into(), "--trials".into(), "3".into()];
    eval.extend(race.iter().cloned());
    let verdict = child(me, dir, &eval)?;
    let line = verdict.lines().find(|l| l.contains("laps completed")).unwrap_or("").to_string();
    let laps = line.split_whitespace().next().and_then(|n| n.parse::<u32>().ok()).unwrap_or(0);
    Ok((secs, stop, line, laps))
}

/// Run the training `args` (`train` or `up`): its wall-clock and the line that says how it
/// stopped.
fn train_to_stop(me: &std::path::Path, dir: &std::path::Path, args: &[String]) -> Result<(f64, String)> {
    let t0 = Instant::now();
    let text = child(me, dir, args)?;
    let secs = t0.elapsed().as_secs_f64();
    let stop = text
        .lines()
        .find(|l| l.starts_with("stopped after") || l.contains(": Finished") || l.contains(": Failed"))
        .unwrap_or("")
        .trim()
        .to_string();
    Ok((secs, stop))
}

/// The `--set`s that make an evaluation place head-to-bot's bots as the run's checks do (at
/// random, changing lanes: `RaceConfig::for_checks`).
const CHECKED_BOTS: [&str; 4] = ["--set", "race.randomize_bot_car_locations=true", "--set", "race.is_lane_change=true"];

/// The verification that let a run stop at its verified model (`evaluations.jsonl`'s record of
/// that iteration): "laps/trials, crashes[, overtakes]".
fn verification_of(run: &std::path::Path, iteration: u64) -> Result<Option<String>> {
    let path = run.join("evaluations.jsonl");
    let text = std::fs::read_to_string(&path).with_context(|| format!("{}", path.display()))?;
    let mut found = None;
    for line in text.lines() {
        let e: serde_json::Value = serde_json::from_str(line).with_context(|| format!("{}", path.display()))?;
        if e["verification"].as_bool() == Some(true) && e["iteration"].as_u64() == Some(iteration) {
            found = Some(format!(
                "{}/{} laps, {} crashes{}",
                e["min_laps"].as_u64().unwrap_or(0),
                e["trials"].as_u64().unwrap_or(0),
                e["crashes"].as_u64().unwrap_or(0),
                e["overtakes"].as_u64().map(|o| format!(", {o} overtakes")).unwrap_or_default()
            ));
        }
    }
    Ok(found)
}

/// An evaluation's trials (`coordinator evaluate`'s output): (laps, crashes, the trials that
/// overtook no bot where it counts overtakes).
fn trial_counts(text: &str) -> (usize, u32, usize) {
    let (mut laps, mut crashes, mut none) = (0, 0, 0);
    for l in text.lines().filter(|l| l.starts_with("trial ")) {
        let after =
            |k: &str| l.split(k).nth(1).and_then(|r| r.split_whitespace().next()).and_then(|n| n.parse::<u32>().ok());
        laps += usize::from(l.contains("lap_complete"));
        crashes += after("crashes ").unwrap_or(0);
        none += usize::from(after("overtakes ") == Some(0));
    }
    (laps, crashes, none)
}

/// One training of `bench races` and what it gave.
struct RaceRow {
    race: String,
    seed: u64,
    setup: &'static str,
    secs: f64,
    stop: String,
    verified: Option<Verified>,
    verification: Option<String>,
    evaluation: String,
    ok: bool,
}

/// `bench races`: every race trained from pixels per seed, to a verified model; each model
/// then evaluated again with seeds the run never drew (head-to-bot's bots placed as the
/// run's checks place them).
pub fn races(a: &crate::cli::RacesArgs) -> Result<i32> {
    for w in &a.races {
        if !RACES.iter().any(|(n, _)| n == w) {
            bail!("--race {w}: expected one of {:?}", RACES.map(|r| r.0));
        }
    }
    if a.seeds.is_empty() {
        bail!("--seeds: give at least one seed");
    }
    let me = std::env::current_exe()?;
    std::fs::create_dir_all(&a.out)?;
    let dir = a.out.canonicalize()?;
    let world = a.world.as_str();
    let sets: Vec<String> = a.sets.iter().flat_map(|s| ["--set".to_string(), s.clone()]).collect();
    let mut rows = Vec::new();
    for (name, flags) in RACES.iter().filter(|(n, _)| a.races.is_empty() || a.races.iter().any(|w| w == n)) {
        let mut flags: Vec<String> = flags.iter().map(|s| s.to_string()).collect();
        // The reward given replaces the race's (a time trial's too, which has none here).
        if let Some(r) = &a.reward {
            let r = full_path(r);
            match flags.iter().position(|f| f == "--reward") {
                Some(i) => flags[i + 1] = r,
                None => flags.extend(["--reward".to_string(), r]),
            }
        }
        // The race alone, for `evaluate` (no sensor or reward there), and the settings given.
        let mut race: Vec<String> = flags
            .chunks(2)
            .filter(|kv| !matches!(kv[0].as_str(), "--sensor" | "--reward"))
            .flat_map(|kv| kv.to_vec())
            .collect();
        // `evaluate` takes the race's keys.
        race.extend(a.sets.iter().filter(|s| s.starts_with("race.")).flat_map(|s| ["--set".to_string(), s.clone()]));
        let bots = flags.iter().any(|f| f == "--bots");
        if bots {
            race.extend(CHECKED_BOTS.map(String::from));
        }
        for &seed in &a.seeds {
            let mut setups = vec![("train", "train", format!("{name}-{seed}-train"), String::new())];
            if !a.no_up {
                setups.push(("up, 2 agents", "up", format!("{name}-{seed}-up"), "/run".to_string()));
            }
            for (setup, cmd, folder, inner) in setups {
                let mut args = vec![
                    cmd.to_string(),
                    "--world".into(),
                    world.into(),
                    "--out".into(),
                    folder.clone(),
                    "--force".into(),
                ];
                args.extend(flags.iter().cloned());
                args.extend(sets.iter().cloned());
                args.extend(
                    ["--target-laps", "3", "--minutes", &a.minutes.to_string(), "--seed", &seed.to_string()]
                        .map(String::from),
                );
                if cmd == "up" {
                    args.extend(["--agents", "2", "--envs", "8"].map(String::from));
                }
                let (secs, stop) = train_to_stop(&me, &dir, &args)?;
                let run = dir.join(format!("{folder}{inner}"));
                let verified = verified_point(&run)?;
                let verification = match verified {
                    Some(v) => verification_of(&run, v.iteration)?,
                    None => None,
                };
                // Seeds the run never drew: 1000 + the run's.
                let mut eval = vec!["evaluate".to_string(), format!("{folder}{inner}/model"), "--world".into()];
                eval.extend([world.to_string(), "--trials".into(), a.eval_trials.to_string()]);
                eval.extend(["--seed".to_string(), (1000 + seed).to_string()]);
                eval.extend(race.iter().cloned());
                let out = child(&me, &dir, &eval)?;
                let (laps, crashes, no_overtake) = trial_counts(&out);
                let line = out.lines().find(|l| l.contains("laps completed")).unwrap_or("").to_string();
                let ok = verified.is_some() && laps == a.eval_trials && crashes == 0 && no_overtake == 0;
                rows.push(RaceRow {
                    race: name.to_string(),
                    seed,
                    setup,
                    secs,
                    stop,
                    verified,
                    verification,
                    evaluation: line,
                    ok,
                });
            }
        }
    }
    let seeds: Vec<String> = a.seeds.iter().map(u64::to_string).collect();
    println!(
        "# coordinator bench races: {world}, from pixels, seeds {}, {} min budget each{}{}",
        seeds.join(","),
        a.minutes,
        a.reward.as_ref().map(|r| format!(", reward {r}")).unwrap_or_default(),
        if a.sets.is_empty() { String::new() } else { format!(", --set {}", a.sets.join(" --set ")) }
    );
    println!();
    println!(
        "| race | seed | setup | wall-clock s | how it stopped | verified model made at s (updates, env steps) | \
         its verification | evaluation ({} trials, seed 1000 + the run's) | verdict |",
        a.eval_trials
    );
    println!("|---|---|---|---|---|---|---|---|---|");
    for r in &rows {
        let made = r
            .verified
            .map_or("none".to_string(), |v| format!("{:.0} ({} updates, {} steps)", v.made_s, v.updates, v.env_steps));
        println!(
            "| {} | {} | {} | {:.0} | {} | {made} | {} | {} | {} |",
            r.race,
            r.seed,
            r.setup,
            r.secs,
            r.stop,
            r.verification.as_deref().unwrap_or("-"),
            r.evaluation,
            if r.ok { "pass" } else { "FAIL" }
        );
    }
    println!();
    // Per race and setup over the seeds: the median time to the verified model.
    let mut groups: Vec<(&str, &str)> = rows.iter().map(|r| (r.race.as_str(), r.setup)).collect();
    groups.sort();
    groups.dedup();
    for (race, setup) in groups {
        let mut made: Vec<f64> = rows
            .iter()
            .filter(|r| r.race == race && r.setup == setup)
            .map(|r| r.verified.map_or(f64::INFINITY, |_| r.secs))
            .collect();
        made.sort_by(f64::total_cmp);
        let median = made[made.len() / 2];
        println!(
            "{race} ({setup}): median wall-clock to the stop at a verified model (a seed not verified counts as never) {}",
            if median.is_finite() { format!("{median:.0} s") } else { "none (most seeds not verified)".into() }
        );
    }
    let failed: Vec<String> =
        rows.iter().filter(|r| !r.ok).map(|r| format!("{} seed {} ({})", r.race, r.seed, r.setup)).collect();
    let pass = format!(
        "every run stopped at a verified model and lapped {0}/{0} again with no crash{1}",
        a.eval_trials,
        if rows.iter().any(|r| r.race == "head_to_bot") { ", overtaking in every head-to-bot trial" } else { "" }
    );
    Ok(verdict(&failed, &pass))
}

/// deepracer-for-cloud's `defaults/model_metadata_sac.json` (speed 1–2 m/s, steering ±30°),
/// for `sensor` and `network`, trained by `algorithm`.
fn drfc_continuous(sensor: &str, network: &str, algorithm: &str) -> String {
    format!(
        r#"{{"action_space": {{"speed": {{"high": 2, "low": 1}}, "steering_angle": {{"high": 30, "low": -30}}}},
  "sensor": ["{sensor}"], "neural_network": "{network}", "training_algorithm": "{algorithm}",
  "action_space_type": "continuous", "version": "4"}}"#
    )
}

/// One training of `bench sac`: wall-clock to its model, how it stopped, the model evaluated
/// again (laps of 3).
struct SacRow {
    label: String,
    secs: f64,
    stop: String,
    eval: String,
    laps: u32,
}

/// `bench sac`: SAC against PPO from the same files, then SAC with 1, 2 and 4 agents.
pub fn sac(
    world: &str,
    minutes: f64,
    sensors: &[String],
    agents: &[usize],
    seed: u64,
    out: &std::path::Path,
) -> Result<i32> {
    let sensors: Vec<&str> =
        if sensors.is_empty() { vec!["state", "camera"] } else { sensors.iter().map(|s| s.as_str()).collect() };
    let agents: Vec<usize> = if agents.is_empty() { vec![1, 2, 4] } else { agents.to_vec() };
    let me = std::env::current_exe()?;
    std::fs::create_dir_all(out)?;
    let dir = out.canonicalize()?;
    let mut rows: Vec<SacRow> = Vec::new();
    let mut run = |label: String, args: Vec<String>, model: String| -> Result<()> {
        let (secs, stop, eval, laps) = train_then_evaluate(&me, &dir, &args, model, world, &[])?;
        rows.push(SacRow { label, secs, stop, eval, laps });
        Ok(())
    };
    let common = |cmd: &str, folder: &str, meta: &str| -> Vec<String> {
        [cmd, "--world", world, "--out", folder, "--force", "--model-metadata", meta, "--target-laps", "3"]
            .iter()
            .map(|s| s.to_string())
            .chain(["--minutes".into(), minutes.to_string(), "--seed".into(), seed.to_string()])
            .collect()
    };
    for sensor in &sensors {
        let (name, network) = match *sensor {
            "state" => ("STATE_VECTOR", "PADDOCK_MLP"),
            "camera" => ("FRONT_FACING_CAMERA", "DEEP_CONVOLUTIONAL_NETWORK_SHALLOW"),
            other => bail!("--sensor {other}: expected state or camera"),
        };
        for algorithm in ["sac", "clipped_ppo"] {
            let meta = format!("{sensor}-{algorithm}.json");
            std::fs::write(dir.join(&meta), drfc_continuous(name, network, algorithm))?;
            let folder = format!("{sensor}-{algorithm}-train");
            run(format!("{sensor}, {algorithm}, train"), common("train", &folder, &meta), format!("{folder}/model"))?;
        }
    }
    // SAC under `up`: the learner's intake bound by one gradient step per transition.
    std::fs::write(dir.join("state-sac.json"), drfc_continuous("STATE_VECTOR", "PADDOCK_MLP", "sac"))?;
    for n in &agents {
        let folder = format!("state-sac-up{n}");
        let mut args = common("up", &folder, "state-sac.json");
        args.extend(["--agents".to_string(), n.to_string(), "--envs".into(), "8".into()]);
        run(format!("state, sac, up {n} agent(s) × 8 envs"), args, format!("{folder}/run/model"))?;
    }
    println!("# coordinator bench sac: {world}, seed {seed}, {minutes} min budget each");
    println!();
    println!("| training | wall-clock s (start to model) | how it stopped | evaluated again (3 trials) |");
    println!("|---|---|---|---|");
    for r in &rows {
        println!("| {} | {:.0} | {} | {} |", r.label, r.secs, r.stop, r.eval);
    }
    println!();
    let mut failed: Vec<String> =
        rows.iter().filter(|r| r.label.contains("sac") && r.laps < 3).map(|r| r.label.clone()).collect();
    let up_secs = |n: usize| rows.iter().find(|r| r.label.starts_with(&format!("state, sac, up {n} "))).map(|r| r.secs);
    if let (Some(one), Some(two)) = (up_secs(1), up_secs(2)) {
        let speedup = one / two.max(1e-9);
        println!("2 agents against 1: {speedup:.2}× (goal ≥ 1.6×)");
        if speedup < 1.6 {
            failed.push(format!("2 agents {speedup:.2}× faster than 1"));
        }
    }
    Ok(verdict(&failed, "every SAC model lapped 3/3 and 2 agents were 1.6× faster than 1"))
}

/// `bench race-line`: per sensor, the same training (the racing line's action space, the same
/// seed and minutes) with the racing line's reward and with the centre line's, then the two
/// models raced on the world (`coordinator race`, 3 trials, a lap ends at the first
/// off-track). Passes when the racing line's model laps 3/3 within 1.15× the line's
/// theoretical time and faster than the centre line's model.
pub fn race_line(world: &str, minutes: f64, sensors: &[String], seed: u64, out: &std::path::Path) -> Result<i32> {
    let sensors: Vec<&str> =
        if sensors.is_empty() { vec!["state", "camera"] } else { sensors.iter().map(|s| s.as_str()).collect() };
    let w = crate::tracks_cmd::resolve_world(world)?;
    let car = sim_agent::SimConfig::default().car;
    let plan = sim_agent::race_line::LinePlan::new(&w.track(tracks::Direction::Forward), &car, w.surface)
        .with_context(|| format!("{}: the racing line", w.name))?;
    let goal = 1.15 * plan.lap_time;
    let me = std::env::current_exe()?;
    std::fs::create_dir_all(out)?;
    let dir = out.canonicalize()?;
    let mut rows = Vec::new();
    let mut failed = Vec::new();
    for sensor in &sensors {
        let mut models = Vec::new();
        let mut secs = Vec::new();
        for reward in ["race_line", "center_line"] {
            let folder = format!("{sensor}-{reward}");
            let args: Vec<String> = [
                "train",
                "--world",
                world,
                "--sensor",
                sensor,
                "--reward",
                &format!("builtin:{reward}"),
                "--action-space-from-line",
                "--target-laps",
                "0",
                "--minutes",
                &minutes.to_string(),
                "--seed",
                &seed.to_string(),
                "--out",
                &folder,
                "--force",
            ]
            .map(String::from)
            .to_vec();
            let t0 = Instant::now();
            child(&me, &dir, &args)?;
            secs.push(t0.elapsed().as_secs_f64());
            models.push(dir.join(&folder).join("model"));
        }
        let standings = crate::race_cmd::run(&crate::cli::RaceCmdArgs {
            models,
            world: world.to_string(),
            reversed: false,
            trials: 3,
            resets: 0,
            penalty: 2.0,
            collision_penalty: 5.0,
            seed,
            out: dir.join(format!("race-{sensor}")),
            race: Default::default(),
        })?;
        let of = |reward: &str| standings.iter().find(|s| s.name == format!("{sensor}-{reward}")).cloned();
        let (Some(fast), Some(centre)) = (of("race_line"), of("center_line")) else {
            bail!("the race of {sensor} lost a model: {standings:?}");
        };
        let ok = fast.laps == fast.trials
            && fast.mean.is_some_and(|m| m <= goal)
            && match (fast.mean, centre.mean) {
                (Some(a), Some(b)) => a < b,
                (Some(_), None) => true,
                _ => false,
            };
        if !ok {
            failed.push(sensor.to_string());
        }
        for (s, t) in [(fast, secs[0]), (centre, secs[1])] {
            rows.push((sensor.to_string(), s, t));
        }
    }
    let lap = |t: Option<f64>| t.map(|l| format!("{l:.2}")).unwrap_or_else(|| "-".into());
    println!(
        "# coordinator bench race-line: {}, seed {seed}, {minutes} min a training; the line's theoretical lap {:.2} s, goal ≤ {goal:.2} s",
        w.name, plan.lap_time
    );
    println!();
    println!("| sensor | reward | training s | laps | best lap s | mean lap s | mean / line's |");
    println!("|---|---|---:|---:|---:|---:|---:|");
    for (sensor, s, t) in &rows {
        println!(
            "| {sensor} | {} | {t:.0} | {}/{} | {} | {} | {} |",
            s.name.trim_start_matches(&format!("{sensor}-")),
            s.laps,
            s.trials,
            lap(s.best),
            lap(s.mean),
            s.mean.map(|m| format!("{:.2}", m / plan.lap_time)).unwrap_or_else(|| "-".into())
        );
    }
    println!();
    println!("pictures: {}/race-SENSOR/race.html", dir.display());
    Ok(verdict(&failed, "the racing line's models lap 3/3 within 1.15× the line's time, faster than the centre line's"))
}

/// The worlds of `bench schedule` by default: four tracks of different difficulty, one of
/// them on a surface of less grip.
const SCHEDULE_WORLDS: [&str; 5] =
    ["reinvent_base", "reinvent_wood", "Oval_track", "Bowtie_track", "reInvent2019_track"];

/// `bench schedule`: the same `up` job (several worlds, 2 agents) with the adaptive schedule
/// and with an even one, for each seed, one after the other; the wall-clock until an
/// evaluation lapped 3/3 on every world. Passes when the adaptive schedule's median time is
/// shorter (a job that does not get there counts as its budget).
pub fn schedule(worlds: &[String], sensor: &str, minutes: f64, seeds: &[u64], out: &std::path::Path) -> Result<i32> {
    let worlds: Vec<String> =
        if worlds.is_empty() { SCHEDULE_WORLDS.map(String::from).to_vec() } else { worlds.to_vec() };
    let seeds: Vec<u64> = if seeds.is_empty() { vec![1, 2, 3] } else { seeds.to_vec() };
    let me = std::env::current_exe()?;
    std::fs::create_dir_all(out)?;
    let dir = out.canonicalize()?;
    // (schedule, seed, seconds to 3/3 everywhere or None, how it stopped)
    let mut rows: Vec<(&str, u64, Option<f64>, String)> = Vec::new();
    for &seed in &seeds {
        for how in ["adaptive", "even"] {
            let folder = format!("{how}-{seed}");
            let mut args: Vec<String> = ["up", "--schedule", how, "--sensor", sensor, "--agents", "2", "--envs", "8"]
                .map(String::from)
                .to_vec();
            for w in &worlds {
                args.extend(["--world".to_string(), w.clone()]);
            }
            args.extend(
                ["--target-laps", "3", "--minutes", &minutes.to_string(), "--seed", &seed.to_string()]
                    .map(String::from),
            );
            args.extend(["--out".to_string(), folder.clone(), "--force".into()]);
            let t0 = Instant::now();
            let text = child(&me, &dir, &args)?;
            let secs = t0.elapsed().as_secs_f64();
            let stop = text.lines().find(|l| l.contains(": Finished") || l.contains(": Failed")).unwrap_or("").trim();
            let lapped = text.contains("target laps reached");
            rows.push((how, seed, lapped.then_some(secs), stop.to_string()));
        }
    }
    let median = |how: &str| -> f64 {
        let mut v: Vec<f64> = rows.iter().filter(|r| r.0 == how).map(|r| r.2.unwrap_or(minutes * 60.0)).collect();
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    println!(
        "# coordinator bench schedule: {} worlds ({}), {sensor}, 2 agents × 8 envs, {minutes} min budget",
        worlds.len(),
        worlds.join(", ")
    );
    println!();
    println!("| schedule | seed | s to 3/3 on every world | how it stopped |");
    println!("|---|---:|---:|---|");
    for (how, seed, secs, stop) in &rows {
        let s = secs.map(|s| format!("{s:.0}")).unwrap_or_else(|| "did not".into());
        println!("| {how} | {seed} | {s} | {stop} |");
    }
    let (a, e) = (median("adaptive"), median("even"));
    println!();
    println!("median: adaptive {a:.0} s, even {e:.0} s ({:.2}× the even schedule's time)", a / e.max(1e-9));
    let failed = if a < e { vec![] } else { vec!["the adaptive schedule is not faster".to_string()] };
    Ok(verdict(&failed, "the adaptive schedule gets every world to 3/3 sooner"))
}

/// Catalog tracks `bench generated` evaluates on by default: none of them generated.
const UNSEEN_WORLDS: [&str; 3] = ["reinvent_base", "Oval_track", "Bowtie_track"];

/// `bench generated`: a model trained only on generated tracks (`generated:N`, a new track
/// every `generated.episodes_per_track` episodes), then evaluated (3 trials) on catalog
/// tracks it never saw. The model is the run's last checkpoint, the whole training's: the
/// run's best is chosen on track N alone, by its lap time, and is often an early model that
/// laps N fast and nothing else. Passes when it laps 3/3 on every catalog track.
pub fn generated(
    family: u64,
    unseen: &[String],
    sensor: &str,
    minutes: f64,
    seed: u64,
    out: &std::path::Path,
) -> Result<i32> {
    let unseen: Vec<String> =
        if unseen.is_empty() { UNSEEN_WORLDS.map(String::from).to_vec() } else { unseen.to_vec() };
    if let Some(w) = unseen.iter().find(|w| tracks::generated_seed(w).is_some()) {
        bail!("--unseen {w}: the tracks to evaluate on are catalog tracks the model never saw");
    }
    let me = std::env::current_exe()?;
    std::fs::create_dir_all(out)?;
    let dir = out.canonicalize()?;
    let world = format!("generated:{family}");
    let args: Vec<String> = [
        "train",
        "--world",
        &world,
        "--sensor",
        sensor,
        "--target-laps",
        "0",
        "--minutes",
        &minutes.to_string(),
        "--seed",
        &seed.to_string(),
        "--out",
        "generated",
        "--force",
    ]
    .map(String::from)
    .to_vec();
    let t0 = Instant::now();
    child(&me, &dir, &args)?;
    let secs = t0.elapsed().as_secs_f64();
    use learner::checkpoints::{OpenMode, RunDir};
    let run = RunDir::open(&dir.join("generated"), OpenMode::Resume)?;
    let last = run.index()?.last_checkpoint.with_context(|| format!("{}: no checkpoint", run.root().display()))?;
    let model = run.checkpoint_dir(&last.name).display().to_string();
    let mut eval = vec!["evaluate".to_string(), model, "--trials".into(), "3".into()];
    for w in std::iter::once(&world).chain(&unseen) {
        eval.extend(["--world".to_string(), w.clone()]);
    }
    let text = child(&me, &dir, &eval)?;
    // The evaluation's table: WORLD, LAPS (n/3), PROGRESS, MEAN LAP.
    let rows: Vec<(String, String, String, String)> = text
        .lines()
        .skip_while(|l| !l.starts_with("WORLD"))
        .skip(1)
        .take_while(|l| !l.trim().is_empty() && !l.contains("laps completed"))
        .filter_map(|l| {
            let f: Vec<&str> = l.split_whitespace().collect();
            (f.len() >= 4).then(|| (f[0].to_string(), f[1].to_string(), f[2].to_string(), f[3..].join(" ")))
        })
        .collect();
    println!(
        "# coordinator bench generated: {sensor}, trained {secs:.0} s on {world} only (a new track every few episodes), seed {seed}; the last checkpoint, {} (iteration {})",
        last.name, last.iteration
    );
    println!();
    println!("| world | seen in training | laps | progress | mean lap |");
    println!("|---|---|---:|---:|---:|");
    let mut failed = Vec::new();
    for (w, laps, progress, lap) in &rows {
        let seen = if *w == world { "its track N (evaluation's)" } else { "never" };
        println!("| {w} | {seen} | {laps} | {progress} | {lap} |");
        if *w != world && laps != "3/3" {
            failed.push(format!("not 3/3 on {w}"));
        }
    }
    println!();
    if rows.len() != unseen.len() + 1 {
        println!("verdict: FAIL: the evaluation's table was not read:\n{text}");
        return Ok(1);
    }
    Ok(verdict(&failed, "trained on generated tracks only, the model laps 3/3 on every catalog track it never saw"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_closing_tables_laps_are_counted_by_world_and_by_whether_it_was_trained_on() {
        // `coordinator evaluate`'s output, as the bench reads it.
        let text = "trial 10: Oval_track  off_track  progress  40.7 %  lap time  -  off-track  1\n\
                    WORLD                      LAPS   PROGRESS   MEAN LAP\n\
                    reinvent_wood              3/3      100.0%    14.10 s\n\
                    Oval_track                 0/3       39.6%          -\n\
                    generated:2               20/20     100.0%    19.19 s\n\
                    23 of 26 laps completed, mean progress 82.1 %, 0 crashes\n";
        let rows = table_laps(text);
        let names: Vec<&str> = rows.iter().map(|(w, _)| w.as_str()).collect();
        assert_eq!(names, ["reinvent_wood", "Oval_track", "generated:2"]);
        assert_eq!(rows[1].1, Laps { laps: 0, trials: 3 });
        let mut tally = LapTally::default();
        tally.add(&rows, &["reinvent_wood".to_string()]);
        tally.add(&rows, &["reinvent_wood".to_string()]);
        assert_eq!(tally.training, Laps { laps: 6, trials: 6 });
        assert_eq!(tally.unseen, Laps { laps: 40, trials: 46 });
        assert_eq!(tally.by_world["Oval_track"].describe(), "0 of 6");
        // No table (a failed evaluation's text): nothing counted.
        assert!(table_laps("error: no such model").is_empty());
    }

    /// Issue 55: the verified model's point is read from its manifest, and the updates and
    /// samples up to its iteration from `metrics.jsonl`; a best model never verified has none.
    #[test]
    fn the_verified_models_point_counts_what_came_before_it() {
        let run = tempfile::tempdir().unwrap();
        std::fs::create_dir_all(run.path().join("model")).unwrap();
        let lines: Vec<String> = (1..=5)
            .map(|i| serde_json::json!({"iteration": i, "steps": 100 * i, "time_s": 10.0 * i as f64}).to_string())
            .collect();
        std::fs::write(run.path().join("metrics.jsonl"), lines.join("\n")).unwrap();
        let manifest = |verified: bool| {
            let mut t = serde_json::json!({"iteration": 3, "env_steps": 777, "seconds": 31.5});
            if verified {
                t["verified_trials"] = 10.into();
            }
            serde_json::json!({"training": t}).to_string()
        };
        std::fs::write(run.path().join("model/manifest.json"), manifest(true)).unwrap();
        let v = verified_point(run.path()).unwrap();
        assert_eq!(v, Some(Verified { iteration: 3, env_steps: 777, made_s: 31.5, updates: 3, samples: 600 }));
        std::fs::write(run.path().join("model/manifest.json"), manifest(false)).unwrap();
        assert_eq!(verified_point(run.path()).unwrap(), None);
        std::fs::remove_dir_all(run.path().join("model")).unwrap();
        assert_eq!(verified_point(run.path()).unwrap(), None);
    }

    /// Issue 55: a variant's arguments follow the setup's, and a flag the setup already gives
    /// with a value takes the variant's value instead of appearing twice.
    #[test]
    fn a_variants_flag_replaces_the_benchs_own() {
        let v = |x: &str| x.split_whitespace().map(String::from).collect::<Vec<_>>();
        let cases = [
            (
                "train --checkpoint-seconds 20 --seed 1",
                "--checkpoint-seconds 2",
                "train --seed 1 --checkpoint-seconds 2",
            ),
            ("train --seed 1", "--hyperparameters h.json", "train --seed 1 --hyperparameters h.json"),
            ("up --force --seed 1", "--force", "up --seed 1 --force"),
        ];
        for (base, more, want) in cases {
            assert_eq!(with_variant(v(base), &v(more)), v(want), "{base} + {more}");
        }
    }

    /// Issue 55: `bench races` reads an evaluation's laps, crashes and the trials that overtook
    /// no bot from `evaluate`'s own lines, and the verification of the verified iteration from
    /// `evaluations.jsonl`.
    #[test]
    fn bench_races_reads_the_trials_and_the_verification_it_judges() {
        use policy::exchange::Trial;
        let trial = |status: &str, crashes: u32, overtakes: Option<u32>| Trial {
            status: status.into(),
            progress: 100.0,
            lap_time: (status == "lap_complete").then_some(12.5),
            crashes,
            overtakes,
            steps: 190,
            ..Trial::default()
        };
        let text = |trials: &[Trial]| -> String {
            let mut lines: Vec<String> =
                trials.iter().enumerate().map(|(i, t)| crate::train::trial_line(i, "reinvent_base", t)).collect();
            lines.push("2 of 3 laps completed, mean progress 90.0 %, 1 crashes".into());
            lines.join("\n")
        };
        let bots = [trial("lap_complete", 0, Some(2)), trial("crashed", 1, Some(0)), trial("lap_complete", 0, Some(1))];
        assert_eq!(trial_counts(&text(&bots)), (2, 1, 1));
        let boxes = [trial("lap_complete", 0, None), trial("lap_complete", 0, None)];
        assert_eq!(trial_counts(&text(&boxes)), (2, 0, 0), "no overtakes counted where there are no bots");
        let run = tempfile::tempdir().unwrap();
        let lines = [
            serde_json::json!({"iteration": 4, "verification": false, "min_laps": 3, "trials": 3, "crashes": 0}),
            serde_json::json!({"iteration": 4, "verification": true, "min_laps": 10, "trials": 10, "crashes": 0, "overtakes": 17}),
            serde_json::json!({"iteration": 6, "verification": true, "min_laps": 8, "trials": 10, "crashes": 2}),
        ];
        let body: Vec<String> = lines.iter().map(|l| l.to_string()).collect();
        std::fs::write(run.path().join("evaluations.jsonl"), body.join("\n")).unwrap();
        assert_eq!(verification_of(run.path(), 4).unwrap().as_deref(), Some("10/10 laps, 0 crashes, 17 overtakes"));
        assert_eq!(verification_of(run.path(), 6).unwrap().as_deref(), Some("8/10 laps, 2 crashes"));
        assert_eq!(verification_of(run.path(), 5).unwrap(), None);
    }
}
