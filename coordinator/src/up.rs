//! `coordinator up`: one machine, one command. Starts `coordinator serve`, a learner and N
//! sim agents as child processes talking through real Zenoh sessions on loopback, runs one
//! job to its stop condition, and leaves the model folder and a summary.

use crate::cli::UpArgs;
use crate::client::request;
use anyhow::{Context, Result, bail};
use indicatif::{ProgressBar, ProgressStyle};
use protocol::job_request::Kind;
use protocol::net::{self, NetArgs};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

/// Children that are killed when this value is dropped.
struct Children(Vec<(String, Child)>);

impl Drop for Children {
    fn drop(&mut self) {
        for (_, c) in &mut self.0 {
            let _ = c.kill();
        }
        for (_, c) in &mut self.0 {
            let _ = c.wait();
        }
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

/// A free TCP port on loopback.
pub fn free_port() -> Result<u16> {
    Ok(std::net::TcpListener::bind("127.0.0.1:0")?.local_addr()?.port())
}

fn spawn(
    children: &mut Children,
    name: &str,
    bin: &Path,
    args: &[String],
    common: &[String],
    log: &Path,
) -> Result<()> {
    let out = std::fs::File::create(log)?;
    let child = Command::new(bin)
        .args(args)
        .args(common)
        .stdin(Stdio::null())
        .stdout(out.try_clone()?)
        .stderr(out)
        .spawn()
        .with_context(|| format!("starting {}", bin.display()))?;
    children.0.push((name.to_string(), child));
    Ok(())
}

pub fn up(args: UpArgs) -> Result<i32> {
    let out = args.out.clone().unwrap_or_else(|| {
        let t = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or(0);
        PathBuf::from("runs").join(format!("up-{t}"))
    });
    if out.exists() && std::fs::read_dir(&out)?.next().is_some() {
        if !args.force {
            bail!("{} already exists: pass --force to start again there, or choose another --out", out.display());
        }
        std::fs::remove_dir_all(&out)?;
    }
    let logs = out.join("logs");
    std::fs::create_dir_all(&logs)?;
    let out = out.canonicalize()?;
    let port = free_port()?;
    // With credentials every link is mutual TLS under the cluster's access rules, as across
    // machines; on loopback without them, plain TCP.
    let certs = match &args.certs {
        Some(d) => Some(d.canonicalize().with_context(|| format!("--certs {}", d.display()))?),
        None => None,
    };
    let endpoint = format!("{}/127.0.0.1:{port}", if certs.is_some() { "tls" } else { "tcp" });
    let common: Vec<String> = certs.iter().flat_map(|d| ["--certs".to_string(), d.display().to_string()]).collect();
    let me = std::env::current_exe()?;
    let (learner, agent) = (sibling("learner")?, sibling("sim-agent")?);
    let mut children = Children(Vec::new());
    spawn(
        &mut children,
        "coordinator",
        &me,
        &[
            "serve".into(),
            "--listen".into(),
            endpoint.clone(),
            "--db".into(),
            out.join("coordinator.redb").display().to_string(),
        ],
        &common,
        &logs.join("coordinator.log"),
    )?;
    spawn(
        &mut children,
        "learner",
        &learner,
        &[
            "serve".into(),
            "--connect".into(),
            endpoint.clone(),
            "--id".into(),
            "learner-1".into(),
            "--checkpoint-seconds".into(),
            args.checkpoint_seconds.to_string(),
        ]
        .into_iter()
        .chain(args.signing_key.iter().flat_map(|k| ["--signing-key".into(), k.display().to_string()]))
        .collect::<Vec<String>>(),
        &common,
        &logs.join("learner.log"),
    )?;
    let threads = (std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1) / args.agents.max(1)).max(1);
    for i in 1..=args.agents {
        spawn(
            &mut children,
            &format!("agent-{i}"),
            &agent,
            &[
                "serve".into(),
                "--connect".into(),
                endpoint.clone(),
                "--id".into(),
                format!("agent-{i}"),
                "--envs".into(),
                args.envs.to_string(),
                "--threads".into(),
                threads.to_string(),
            ],
            &common,
            &logs.join(format!("agent-{i}.log")),
        )?;
    }
    // The job spec, written where the user can read and re-use it.
    let worlds = if args.world.is_empty() {
        vec!["reinvent_carpet".to_string(), "reinvent_concrete".to_string()]
    } else {
        args.world.clone()
    };
    let reward_line = match &args.reward {
        Some(r) if !r.starts_with("builtin:") => format!(
            "reward = {:?}\n",
            Path::new(r).canonicalize().with_context(|| format!("reward file {r}"))?.display().to_string()
        ),
        Some(r) => format!("reward = {r:?}\n"),
        None => String::new(),
    };
    let mut target = args.target_progress.map(|t| format!("target_progress = {t}\n")).unwrap_or_default();
    if let Some(l) = args.target_laps {
        target += &format!("target_laps = {l}\ntarget_evals = {}\n", args.target_evals.max(1));
    }
    // `--set` overrides, checked against the simulator configuration now, kept in the spec.
    let sim: sim_agent::SimConfig = sim_agent::config::load_config(None, &args.sets)?;
    let sim_table = if args.sets.is_empty() {
        String::new()
    } else {
        let mut t = toml::Table::new();
        t.insert("sim".into(), toml::Value::try_from(&sim)?);
        toml::to_string(&t)?
    };
    let meta_line = match args.sensor.as_str() {
        "state" => String::new(),
        "camera" => {
            std::fs::write(out.join("model_metadata.json"), policy::ModelMetadata::default_camera().to_json())?;
            "model_metadata = \"model_metadata.json\"\n".to_string()
        }
        other => bail!("--sensor is {other:?}, expected \"state\" or \"camera\""),
    };
    let spec = format!(
        "# Written by `coordinator up`; `coordinator job start` takes this file as it is.\nworlds = {worlds:?}\n{reward_line}{meta_line}out = {:?}\nenvs_per_agent = {}\n[stop]\nminutes = {}\n{target}{sim_table}",
        out.join("run").display().to_string(),
        args.envs,
        args.minutes
    );
    let spec_path = out.join("job.toml");
    std::fs::write(&spec_path, &spec)?;
    let id = crate::client::new_job_id(&spec_path, Some("up"));
    let doc = coordinator::jobspec::load(&spec_path, &id)?;
    let session = net::open(&NetArgs { connect: vec![endpoint.clone()], certs: certs.clone(), ..Default::default() })?;
    let t0 = Instant::now();
    let started = loop {
        match request(&session, Kind::StartJobJson(serde_json::to_string(&doc)?), Duration::from_secs(2)) {
            Ok(r) => break r,
            Err(_) if t0.elapsed() < Duration::from_secs(30) => std::thread::sleep(Duration::from_millis(300)),
            Err(e) => {
                return Err(e.context(format!(
                    "the coordinator did not start (see {})",
                    logs.join("coordinator.log").display()
                )));
            }
        }
    };
    if !started.ok {
        println!("{}", started.text);
        return Ok(1);
    }
    println!(
        "job {id}: {} agent(s) x {} envs on {} for up to {} min; coordinator on {endpoint}; logs in {}",
        args.agents,
        args.envs,
        worlds.join(", "),
        args.minutes,
        logs.display()
    );
    let bar = ProgressBar::new((args.minutes * 60.0) as u64)
        .with_style(ProgressStyle::with_template("{elapsed_precise} [{bar:25}] {msg}").expect("template"));
    let final_json = loop {
        std::thread::sleep(Duration::from_secs(1));
        for (name, c) in &mut children.0 {
            if let Ok(Some(status)) = c.try_wait() {
                bail!("{name} exited ({status}); see {}", logs.join(format!("{name}.log")).display());
            }
        }
        let Ok(r) = request(&session, Kind::StatusJobId(id.clone()), Duration::from_secs(3)) else { continue };
        let v: serde_json::Value = serde_json::from_str(&r.json).unwrap_or_default();
        let l = v.get("learner").cloned().unwrap_or_default();
        let f = |k: &str| l.get(k).and_then(|x| x.as_f64()).unwrap_or(0.0);
        bar.set_position(t0.elapsed().as_secs().min(bar.length().unwrap_or(0)));
        bar.set_message(format!(
            "v{} it {} episodes {} progress {:.1}% eval {:.1}% {}",
            f("policy_version"),
            f("iteration"),
            f("episodes"),
            f("window_progress"),
            f("eval_progress"),
            v.get("state").and_then(|s| s.as_str()).unwrap_or("")
        ));
        match v.get("state").and_then(|s| s.as_str()) {
            Some("finished") | Some("failed") => break (r.text, v),
            _ => {}
        }
        if t0.elapsed().as_secs_f64() > args.minutes * 60.0 + 120.0 {
            bail!("the job did not finish within its time limit plus 2 minutes; see {}", logs.display());
        }
    };
    bar.finish_and_clear();
    println!("{}", final_json.0.trim_end());
    let state = final_json.1.get("state").and_then(|s| s.as_str()).unwrap_or("").to_string();
    std::fs::write(out.join("summary.json"), serde_json::to_string_pretty(&final_json.1)?)?;
    println!(
        "model folder: {}; summary: {}",
        out.join("run").join("model").display(),
        out.join("summary.json").display()
    );
    drop(children);
    Ok(if state == "finished" { 0 } else { 1 })
}
