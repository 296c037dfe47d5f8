//! `coordinator bench cluster|publish`: what distribution costs.
//!
//! - `cluster`: useful work end to end: samples trained on per second (the steps of the episodes
//!   the learner used, every update's optimiser step included), of the single-process trainer
//!   and of `up` with 1, 2 and 4 agent processes on loopback, in the same run with the same
//!   total envs; beside it the env steps simulated and the share of episodes dropped stale.
//! - `pixels`: wall-clock to 3/3 laps on every world from pixels (domain randomisation on),
//!   `train` in one process against `up` with 2 agents, in one run; then both final models
//!   evaluated on the training worlds and on tracks they never saw.
//! - `publish`: time from publishing a SHALLOW camera model until 4 agent sessions on loopback
//!   hold it, and the bytes per env step of experience on the wire.

use anyhow::{Context, Result, bail};
use protocol::net::{self, NetArgs, zenoh};
use protocol::{PROTOCOL_VERSION, PolicyUpdate, keys};
use rand::SeedableRng;
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
        let out = tmp.join(format!("up{agents}"));
        let per = (envs / agents).max(1);
        let o = Command::new(&me)
            .args([
                "up",
                "--world",
                world,
                "--agents",
                &agents.to_string(),
                "--envs",
                &per.to_string(),
                "--minutes",
                &minutes,
                "--out",
            ])
            .arg(&out)
            .output()?;
        if !o.status.success() {
            bail!("up failed: {}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr));
        }
        let s: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("summary.json"))?).context("up's summary")?;
        let steps = s["learner"]["env_steps"].as_f64().unwrap_or(0.0);
        let secs = s["ended"].as_f64().unwrap_or(0.0) - s["started"].as_f64().unwrap_or(0.0);
        let (used, updates) = used_samples(&out.join("run"))?;
        let rate = used / secs;
        let stale = s["learner"]["dropped_stale"].as_u64().unwrap_or(0);
        let received = s["learner"]["episodes_received"].as_u64().unwrap_or(0);
        println!(
            "| `up` with {agents} agent process(es) × {per} envs (+ coordinator + learner) | {used:.0} | {updates} | {secs:.1} | {rate:.0} | {:.2}× | {steps:.0} | {stale} of {received} |",
            rate / base
        );
    }
    let _ = std::fs::remove_dir_all(&tmp);
    Ok(())
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

pub fn publish(repeats: usize) -> Result<()> {
    let port = crate::up::free_port()?;
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let learner = net::open(&NetArgs { listen: vec![endpoint.clone()], ..Default::default() })?;
    let meta = policy::ModelMetadata::parse(
        r#"{"action_space":[{"steering_angle":-30,"speed":1},{"steering_angle":-15,"speed":1},{"steering_angle":0,"speed":1},{"steering_angle":15,"speed":1},{"steering_angle":30,"speed":1}],"sensor":["FRONT_FACING_CAMERA"],"neural_network":"DEEP_CONVOLUTIONAL_NETWORK_SHALLOW","version":"5"}"#,
        "bench",
    )?;
    let model = policy::ActorCritic::new(&meta, 0, &mut rand_chacha::ChaCha8Rng::seed_from_u64(1));
    let manifest = policy::Manifest {
        format: "paddock-model-1".into(),
        policy_version: 1,
        parent: None,
        weights_sha256: String::new(),
        obs_size: 19200,
        observation: serde_json::Value::Null,
        training: serde_json::Value::Null,
    };
    let folder = policy::ModelFolder { metadata: meta, model, manifest };
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

pub fn pixels(
    worlds: &[String],
    unseen: &[String],
    minutes: f64,
    envs: usize,
    evals: u32,
    out: &std::path::Path,
) -> Result<()> {
    let me = std::env::current_exe()?;
    std::fs::create_dir_all(out)?;
    let dir = out.canonicalize()?;
    let common = |v: &mut Vec<String>| {
        for w in worlds {
            v.extend(["--world".into(), w.clone()]);
        }
        v.extend(
            [
                "--sensor",
                "camera",
                "--set",
                "camera.randomize=true",
                "--target-laps",
                "3",
                "--checkpoint-seconds",
                "20",
            ]
            .map(String::from),
        );
        v.extend(["--minutes".into(), minutes.to_string(), "--target-evals".into(), evals.to_string()]);
    };
    let mut train =
        vec!["train".to_string(), "--envs".into(), envs.to_string(), "--out".into(), "train".into(), "--force".into()];
    common(&mut train);
    let t0 = Instant::now();
    let text = child(&me, &dir, &train)?;
    let train_s = t0.elapsed().as_secs_f64();
    let train_reason = text.lines().find(|l| l.starts_with("stopped after")).unwrap_or("").to_string();
    let mut up = vec![
        "up".to_string(),
        "--agents".into(),
        "2".into(),
        "--envs".into(),
        (envs / 2).max(1).to_string(),
        "--out".into(),
        "up".into(),
        "--force".into(),
    ];
    common(&mut up);
    let t0 = Instant::now();
    let text = child(&me, &dir, &up)?;
    let up_s = t0.elapsed().as_secs_f64();
    let up_reason =
        text.lines().find(|l| l.contains(": Finished") || l.contains(": Failed")).unwrap_or("").trim().to_string();
    let metrics = |run: &std::path::Path| -> Result<(usize, f64)> {
        let (used, updates) = used_samples(run)?;
        Ok((updates, used))
    };
    let (tu, ts) = metrics(&dir.join("train"))?;
    let (uu, us) = metrics(&dir.join("up/run"))?;
    println!(
        "# coordinator bench pixels: {} from pixels, domain randomisation on, {envs} environments",
        worlds.join(", ")
    );
    println!();
    println!("| setup | wall-clock s (process start to model) | updates | samples trained on | how it stopped |");
    println!("|---|---|---|---|---|");
    println!("| `train` in one process | {train_s:.0} | {tu} | {ts:.0} | {train_reason} |");
    println!(
        "| `up`, 2 agents × {} envs (+ coordinator + learner) | {up_s:.0} | {uu} | {us:.0} | {up_reason} |",
        (envs / 2).max(1)
    );
    println!();
    println!("Ratio: `up` took {:.2}× the wall-clock of one process.", up_s / train_s);
    println!();
    // Both models on the training worlds and on tracks they never saw.
    let all: Vec<String> = worlds.iter().chain(unseen).cloned().collect();
    for (name, model) in [("train", "train/model"), ("up", "up/run/model")] {
        let mut args = vec!["evaluate".to_string(), model.into(), "--trials".into(), "3".into()];
        for w in &all {
            args.extend(["--world".into(), w.clone()]);
        }
        let text = child(&me, &dir, &args)?;
        println!("{name} model ({}):", dir.join(model).display());
        println!();
        println!("```");
        for l in text.lines().skip_while(|l| !l.starts_with("WORLD")) {
            println!("{l}");
        }
        println!("```");
        println!();
    }
    Ok(())
}
