//! `coordinator up`: one machine, one command. Starts `coordinator serve`, a learner and N
//! sim agents as child processes talking through real Zenoh sessions on loopback, runs one
//! job to its stop condition, and leaves the model folder and a summary. It supervises them: a
//! role that dies is started again (the learner from its last checkpoint, the coordinator from
//! its database), and the event goes to the job's log; `logs/pids.json` names the processes.

use crate::cli::UpArgs;
use crate::client::request;
use anyhow::{Context, Result, bail};
use coordinator::supervise::{Children, free_port, sibling, spawn, write_pids};
use indicatif::{ProgressBar, ProgressStyle};
use protocol::JobState;
use protocol::job_request::Kind;
use protocol::net::{self, NetArgs};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

pub fn up(mut args: UpArgs) -> Result<i32> {
    // The race flags, checked before anything starts (the job's spec applies them).
    args.race.apply(&mut sim_agent::race::RaceConfig::default())?;
    if let Some(f) = args.race.run_env_files()? {
        let meta = f.fill(&mut args.world, &mut args.reward, &mut args.hyperparameters, &mut args.sets);
        // An explicit --sensor is the user's choice of model; the file's metadata does not
        // override it.
        if args.sensor == "state" {
            args.model_metadata = args.model_metadata.or(meta);
        }
    }
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
    let certs = args
        .certs
        .as_deref()
        .map(|d| d.canonicalize().with_context(|| format!("--certs {}", d.display())))
        .transpose()?;
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
            "--device".into(),
            args.device.to_string(),
            // The agents run on this machine, and no other learner reaches its coordinator.
            "--checks-first".into(),
            "--alone".into(),
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
                "--device".into(),
                args.device.to_string(),
            ],
            &common,
            &logs.join(format!("agent-{i}.log")),
        )?;
    }
    // The job: the user's spec as it is, or one made from the flags and written where the
    // user can read and re-use it.
    let spec_path = match &args.job {
        Some(p) => p.clone(),
        None => {
            let spec_path = out.join("job.toml");
            std::fs::write(&spec_path, job_spec(&args, &out)?)?;
            spec_path
        }
    };
    let id = crate::client::new_job_id(&spec_path, Some("up"));
    let doc = coordinator::jobspec::load(&spec_path, &id)?;
    // The learner runs here: a spec's relative run folder is relative to here.
    let run_dir = PathBuf::from(&doc.out);
    let minutes = doc.stop().minutes;
    let session = net::open(&NetArgs { connect: vec![endpoint.clone()], certs: certs.clone(), ..Default::default() })?;
    let t0 = Instant::now();
    let started = loop {
        match request(&session, Kind::StartJob(doc.clone()), Duration::from_secs(2)) {
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
        doc.envs_per_agent,
        doc.worlds.join(", "),
        minutes,
        logs.display()
    );
    let bar = ProgressBar::new((minutes * 60.0) as u64)
        .with_style(ProgressStyle::with_template("{elapsed_precise} [{bar:25}] {msg}").expect("template"));
    write_pids(&logs, &children)?;
    let mut pending: Vec<String> = Vec::new();
    let final_json = loop {
        std::thread::sleep(Duration::from_secs(1));
        // A role that dies is started again; the event goes to the job's log (once the
        // coordinator answers: it may be the one restarting).
        for e in children.supervise()? {
            bar.println(&e);
            tracing::warn!("{e}");
            pending.push(e);
            write_pids(&logs, &children)?;
        }
        pending.retain(|e| {
            let ev = protocol::JobEvent { job_id: id.clone(), text: e.clone() };
            !request(&session, Kind::Event(ev), Duration::from_secs(2)).is_ok_and(|r| r.ok)
        });
        let Ok(r) = request(&session, Kind::StatusJobId(id.clone()), Duration::from_secs(3)) else { continue };
        let Some(status) = crate::client::status_of(&r).cloned() else { continue };
        let Some(rec) = status.record.as_ref() else { continue };
        let l = rec.learner.clone().unwrap_or_default();
        bar.set_position(t0.elapsed().as_secs().min(bar.length().unwrap_or(0)));
        bar.set_message(format!(
            "v{} it {} episodes {} progress {:.1}% eval {:.1}% {}",
            l.policy_version,
            l.iteration,
            l.episodes,
            l.window_progress,
            l.eval_progress,
            rec.state().name()
        ));
        if matches!(rec.state(), JobState::Finished | JobState::Failed) {
            break (r.text, status);
        }
        if t0.elapsed().as_secs_f64() > minutes * 60.0 + 120.0 {
            bail!("the job did not finish within its time limit plus 2 minutes; see {}", logs.display());
        }
    };
    bar.finish_and_clear();
    println!("{}", final_json.0.trim_end());
    let finished = final_json.1.record.as_ref().is_some_and(|j| j.state() == JobState::Finished);
    std::fs::write(out.join("summary.json"), serde_json::to_string_pretty(&final_json.1)?)?;
    println!("model folder: {}; summary: {}", run_dir.join("model").display(), out.join("summary.json").display());
    drop(children);
    Ok(if finished { 0 } else { 1 })
}

/// A path in the job spec: absolute, so that the spec reads the same from anywhere.
fn absolute(flag: &str, p: &Path) -> Result<String> {
    Ok(p.canonicalize().with_context(|| format!("{flag} {}", p.display()))?.display().to_string())
}

/// The job spec `up`'s flags describe (TOML, as `job start` takes it), with its run folder in
/// `out/run`. Files (reward, metadata, hyperparameters, a model to clone) are named by absolute
/// paths; `--sensor camera` writes DeepRacer's default camera metadata into `out`.
pub(crate) fn job_spec(args: &UpArgs, out: &Path) -> Result<String> {
    use toml::Value;
    let mut t = toml::Table::new();
    let worlds = if args.world.is_empty() {
        vec!["reinvent_carpet".to_string(), "reinvent_concrete".to_string()]
    } else {
        args.world.clone()
    };
    t.insert("worlds".into(), Value::Array(worlds.into_iter().map(Value::String).collect()));
    if args.reversed {
        t.insert("reversed".into(), Value::Boolean(true));
    }
    match &args.reward {
        Some(r) if r.starts_with("builtin:") => {
            t.insert("reward".into(), Value::String(r.clone()));
        }
        Some(r) => {
            t.insert("reward".into(), Value::String(absolute("reward file", Path::new(r))?));
        }
        None => {}
    }
    let meta = match (&args.model_metadata, args.sensor.as_str()) {
        (Some(p), _) => Some(absolute("--model-metadata", p)?),
        (None, "state") => None,
        (None, name) => {
            let meta = policy::ModelMetadata::for_sensor(name).ok_or_else(|| {
                anyhow::anyhow!("--sensor is {name:?}, expected one of {:?}", policy::ModelMetadata::SENSOR_NAMES)
            })?;
            let p = out.join("model_metadata.json");
            std::fs::write(&p, meta.to_json())?;
            Some(p.display().to_string())
        }
    };
    if let Some(m) = meta {
        t.insert("model_metadata".into(), Value::String(m));
    }
    if let Some(h) = &args.hyperparameters {
        t.insert("hyperparameters".into(), Value::String(absolute("--hyperparameters", h)?));
    }
    if let Some(c) = &args.clone_from {
        t.insert("clone_from".into(), Value::String(absolute("--clone-from", c)?));
    }
    t.insert("out".into(), Value::String(out.join("run").display().to_string()));
    t.insert("envs_per_agent".into(), Value::Integer(args.envs as i64));
    t.insert("seed".into(), Value::Integer(args.seed as i64));
    let mut stop = toml::Table::new();
    stop.insert("minutes".into(), Value::Float(args.minutes));
    let int = |v: u64| Value::Integer(v as i64);
    // The verified model is the default stop, as `train`'s; `--target-laps 0` trains on.
    let laps = (args.target_laps > 0).then_some(args.target_laps);
    for (key, v) in [
        ("max_episodes", args.max_episodes.map(int)),
        ("env_steps_budget", args.env_steps.map(int)),
        ("target_progress", args.target_progress.map(Value::Float)),
        ("target_reward", args.target_reward.map(Value::Float)),
        ("window", Some(int(args.window))),
        ("target_laps", laps.map(|l| int(l.into()))),
        ("target_evals", laps.map(|_| int(args.target_evals.max(1).into()))),
        ("verify_trials", laps.map(|_| int(args.verify_trials.into()))),
        ("plateau_evals", args.stop_on_plateau.map(|p| int(p.into()))),
        ("stop_on_collapse", args.stop_on_collapse.then_some(Value::Boolean(true))),
    ] {
        if let Some(v) = v {
            stop.insert(key.into(), v);
        }
    }
    t.insert("stop".into(), Value::Table(stop));
    if let Some(how) = &args.schedule {
        let mut schedule = toml::Table::new();
        schedule.insert("adaptive".into(), Value::Boolean(how == "adaptive"));
        t.insert("schedule".into(), Value::Table(schedule));
    }
    // The race flags and `--set` overrides, checked against the simulator configuration now,
    // kept in the spec.
    if !args.sets.is_empty() || args.race.given() {
        let sim = args.race.sim_config(None, &args.sets)?;
        t.insert("sim".into(), Value::try_from(&sim)?);
    }
    Ok(format!(
        "# Written by `coordinator up`; `coordinator job start` takes this file as it is.\n{}",
        toml::to_string(&t)?
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cli::{Cli, Command};
    use clap::Parser;

    fn spec(flags: &[&str], out: &Path) -> protocol::Job {
        let cli = Cli::try_parse_from(["coordinator", "up"].iter().chain(flags)).unwrap();
        let Command::Up(args) = cli.command else { panic!("not up") };
        let text = job_spec(&args, out).unwrap();
        coordinator::jobspec::parse(&text, out, "job.toml", "up").unwrap_or_else(|e| panic!("{e:#}\n{text}"))
    }

    /// Issue 29: `up` takes into its job every input `train` takes.
    #[test]
    fn up_takes_every_input_train_takes_into_its_job() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        std::fs::write(d.join("h.json"), r#"{"batch_size": 32, "term_cond_max_episodes": 40}"#).unwrap();
        std::fs::write(d.join("m.json"), policy::ModelMetadata::default_state_vector().to_json()).unwrap();
        let h = d.join("h.json").display().to_string();
        let m = d.join("m.json").display().to_string();
        let job = spec(
            &[
                "--world",
                "reinvent_wood",
                "--hyperparameters",
                &h,
                "--model-metadata",
                &m,
                "--max-episodes",
                "60",
                "--env-steps",
                "15000",
                "--target-progress",
                "25",
                "--target-reward",
                "15",
                "--window",
                "7",
                "--target-laps",
                "3",
                "--target-evals",
                "2",
                "--stop-on-plateau",
                "4",
                "--stop-on-collapse",
                "--minutes",
                "0.5",
                "--seed",
                "9",
                "--envs",
                "3",
                "--set",
                "record_trace=false",
            ],
            d,
        );
        assert_eq!(job.worlds, ["reinvent_wood"]);
        assert!(job.hyperparameters_json.contains("term_cond_max_episodes"), "{}", job.hyperparameters_json);
        assert!(job.model_metadata_json.contains("STATE_VECTOR"), "{}", job.model_metadata_json);
        let want = protocol::job::JobStop {
            minutes: 0.5,
            max_episodes: 60,
            target_progress: Some(25.0),
            target_reward: Some(15.0),
            window: 7,
            env_steps_budget: Some(15000),
            target_laps: Some(3),
            target_evals: 2,
            plateau_evals: 4,
            stop_on_collapse: true,
            verify_trials: 10,
        };
        assert_eq!(job.stop, Some(want));
        assert_eq!((job.seed, job.envs_per_agent), (9, 3));
        assert!(job.sim_config_toml.contains("record_trace = false"), "{}", job.sim_config_toml);
        assert_eq!(job.out, d.join("run").display().to_string());
        // The defaults: two worlds, the state vector, DeepRacer's hyperparameters, and the stop
        // at the verified model (3/3 in two evaluations in a row, then 10 trials a world), 5 minutes at most.
        let plain = spec(&[], d);
        assert_eq!(plain.worlds, ["reinvent_carpet", "reinvent_concrete"]);
        let stop = plain.stop();
        assert_eq!((stop.minutes, stop.target_laps, stop.target_evals, stop.verify_trials), (5.0, Some(3), 2, 10));
        // `--target-laps 0`: no lap target, the job trains to its time limit.
        assert_eq!(spec(&["--target-laps", "0"], d).stop().target_laps, None);
        // A spec file instead: the flags that describe a job are refused beside it.
        let both = Cli::try_parse_from(["coordinator", "up", "--job", "job.toml", "--minutes", "3"]);
        assert!(both.is_err_and(|e| e.to_string().contains("cannot be used with")));
    }
}
