//! `coordinator train`, `evaluate` and `clone`: PPO in one process.
//!
//! The loop wires the same pieces the cluster will run apart: a `sim_agent::rollout::Collector`
//! produces trajectories tagged with the policy version, `learner::Ppo` trains on them, and
//! evaluation trials pick the best checkpoint.

use crate::cli::{CloneArgs, EvaluateArgs, TrainArgs};
use crate::tracks_cmd::resolve_world;
use anyhow::{Context, Result, bail};
use faer::Par;
use indicatif::{ProgressBar, ProgressStyle};
use learner::checkpoints::{CheckpointRecord, OpenMode, RunDir};
use learner::{Hyperparameters, Ppo};
use policy::folder::{self, Manifest, Parent};
use policy::{ActorCritic, ModelMetadata};
use rand::SeedableRng;
use sim_agent::config::{ObservationKind, load_config};
use sim_agent::obs::obs_dim;
use sim_agent::rollout::{Collector, TrialResult, evaluate};
use sim_agent::{EnvSpec, EvalRules, RewardFn, SimConfig, VecEnv};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;
use tracks::Direction;

/// The simulator configuration a model's sensors call for.
fn check_sensors(meta: &ModelMetadata, cfg: &mut SimConfig) -> Result<()> {
    cfg.observation.kind =
        sim_agent::config::observation_kind_for(meta).map_err(|e| anyhow::anyhow!("model_metadata.json: {e}"))?;
    Ok(())
}

fn hyperparameters(path: &Path) -> Result<Hyperparameters> {
    let parsed = Hyperparameters::load(path)?;
    for k in &parsed.unknown {
        tracing::warn!(file = %path.display(), key = %k, "unknown key in hyperparameters.json, not used");
        eprintln!("warning: {}: unknown key '{k}' is not used", path.display());
    }
    for k in &parsed.ignored {
        tracing::info!(file = %path.display(), "{k}");
    }
    Ok(parsed.hyperparameters)
}

fn default_run_dir(world: &str) -> PathBuf {
    let stamp = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or(0);
    PathBuf::from("runs").join(format!("{world}-{stamp}"))
}

/// Evaluation summary: mean progress, mean lap time when every trial completed.
fn summarise(trials: &[TrialResult]) -> (f64, Option<f64>, usize) {
    let n = trials.len().max(1) as f64;
    let progress = trials.iter().map(|t| t.progress).sum::<f64>() / n;
    let laps = trials.iter().filter(|t| t.lap_time.is_some()).count();
    let lap = (laps == trials.len()).then(|| trials.iter().filter_map(|t| t.lap_time).sum::<f64>() / n);
    (progress, lap, laps)
}

pub fn train(args: TrainArgs) -> Result<i32> {
    let start = Instant::now();
    let out = args.out.clone().unwrap_or_else(|| default_run_dir(&args.world));
    let mode = match (args.resume, args.force) {
        (true, true) => bail!("--resume and --force contradict each other"),
        (true, false) => OpenMode::Resume,
        (false, true) => OpenMode::Force,
        (false, false) => OpenMode::New,
    };
    // Inputs: flags first, then what the run folder holds (resume, clone), then defaults.
    let from_run = |name: &str| Some(out.join(name)).filter(|p| mode == OpenMode::Resume && p.exists());
    let meta_path = args.model_metadata.clone().or_else(|| from_run("model_metadata.json"));
    let hyper_path = args.hyperparameters.clone().or_else(|| from_run("hyperparameters.json"));
    let sim_path = args.config.clone().or_else(|| from_run("sim.toml"));
    let meta = match (&meta_path, args.sensor.as_str()) {
        (Some(p), _) => ModelMetadata::load(p)?,
        (None, "state") => ModelMetadata::default_state_vector(),
        (None, "camera") => ModelMetadata::default_camera(),
        (None, other) => bail!("--sensor is {other:?}, expected \"state\" or \"camera\""),
    };
    let mut hyper = match &hyper_path {
        Some(p) => hyperparameters(p)?,
        None => Hyperparameters::default(),
    };
    if let Some(lr) = args.lr {
        hyper.lr = lr;
    }
    let mut cfg: SimConfig = load_config(sim_path.as_deref(), &args.sets)?;
    check_sensors(&meta, &mut cfg)?;
    let world = resolve_world(&args.world)?;
    let mut reward = RewardFn::from_spec(&args.reward)?;
    // Validate the reward before any training: a broken file stops here with its traceback.
    let track = world.track(Direction::Forward);
    sim_agent::validate::validate_reward(&mut reward, &track, &meta.action_space, 20)
        .with_context(|| format!("the reward function {} failed validation", args.reward))?;
    let run = RunDir::open(&out, mode)?;
    let obs_size = obs_dim(&cfg.observation);
    let cfg = Arc::new(cfg);

    // The model: resumed from the last checkpoint, or fresh.
    let (model, version, parent) = if mode == OpenMode::Resume {
        let index = run.index()?;
        let dir = index
            .last_checkpoint
            .as_ref()
            .map(|l| run.checkpoint_dir(&l.name))
            .filter(|d| d.exists())
            .unwrap_or_else(|| run.model_dir());
        let f = folder::load(&dir)?;
        if let Err(why) = f.metadata.compatible_with(&meta) {
            bail!(
                "{}: cannot continue this run with {}: {why}",
                dir.display(),
                meta_path.as_ref().map(|p| p.display().to_string()).unwrap_or_default()
            );
        }
        if f.manifest.obs_size != obs_size {
            bail!(
                "{}: the model takes {} inputs, this configuration's observation has {obs_size}",
                dir.display(),
                f.manifest.obs_size
            );
        }
        tracing::info!(from = %dir.display(), version = f.manifest.policy_version, "resuming");
        (f.model, f.manifest.policy_version, f.manifest.parent)
    } else {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(args.seed);
        (ActorCritic::new(&meta, obs_size, &mut rng), 0, None)
    };
    run.write_file("model_metadata.json", meta.to_json().as_bytes())?;
    run.write_file("hyperparameters.json", hyper.to_json().as_bytes())?;
    run.write_file("sim.toml", toml::to_string_pretty(&*cfg)?.as_bytes())?;

    let spec = EnvSpec::from_world(&world, Direction::Forward);
    let threads = args.threads.unwrap_or_else(|| std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1));
    let vec = VecEnv::new(vec![spec.clone(); args.envs], cfg.clone(), args.seed, reward, threads)?;
    let mut collector = Collector::new(vec, meta.action_space.clone(), args.seed);
    // The camera networks are big enough to split over the cores; the MLP is not.
    let par = if cfg.observation.kind == ObservationKind::Camera { Par::rayon(threads) } else { Par::Seq };
    let mut ppo = Ppo::new(model, hyper.clone(), version, args.seed, par);
    let budget = args.minutes * 60.0;
    println!(
        "training on {} ({}) for up to {:.1} min, {} envs, reward {}, run folder {}",
        world.name,
        world.surface.name(),
        args.minutes,
        args.envs,
        args.reward,
        out.display()
    );
    let bar = ProgressBar::new(budget.ceil() as u64)
        .with_style(ProgressStyle::with_template("{elapsed_precise} [{bar:25}] {msg}").expect("template"));
    let eval_rules = EvalRules::default();
    let mut iteration = 0u64;
    let mut last_eval = f64::MIN;
    let mut best: Option<CheckpointRecord> = run.index()?.best_checkpoint;
    let mut total_episodes = 0u64;
    let mut reached = false;
    let mut streak = 0usize;
    let mut stop_reason = "time limit";
    loop {
        let t0 = Instant::now();
        let current = Arc::new(ppo.model.clone());
        let trajs = collector.collect(&current, ppo.version, hyper.num_episodes_between_training)?;
        let collect_s = t0.elapsed().as_secs_f64();
        let lag = trajs.iter().map(|t| ppo.version - t.policy_version).max().unwrap_or(0);
        let t1 = Instant::now();
        let stats = ppo.update(&trajs);
        let update_s = t1.elapsed().as_secs_f64();
        iteration += 1;
        total_episodes += trajs.len() as u64;
        let mean_reward =
            trajs.iter().map(|t| t.rewards.iter().map(|r| *r as f64).sum::<f64>()).sum::<f64>() / trajs.len() as f64;
        let mean_progress = trajs.iter().map(|t| t.progress).sum::<f64>() / trajs.len() as f64;
        let steps: usize = trajs.iter().map(|t| t.len()).sum();
        if let Some(why) = &stats.refused {
            tracing::warn!(iteration, "{why}");
            eprintln!("warning: iteration {iteration}: {why}");
        }
        let elapsed = start.elapsed().as_secs_f64();
        let mut eval = None;
        if elapsed - last_eval >= args.checkpoint_seconds || elapsed >= budget {
            last_eval = elapsed;
            let trials = evaluate(
                &ppo.model,
                &meta.action_space,
                &spec,
                &cfg,
                eval_rules.clone(),
                args.trials,
                args.seed ^ iteration,
                threads,
            )?;
            let (progress, lap, laps) = summarise(&trials);
            let name = RunDir::checkpoint_name(iteration);
            let manifest = Manifest {
                format: "paddock-model-1".into(),
                policy_version: ppo.version,
                parent: parent.clone(),
                weights_sha256: String::new(),
                obs_size,
                observation: serde_json::to_value(&cfg.observation)?,
                training: serde_json::json!({
                    "world": world.name, "iteration": iteration, "episodes": total_episodes,
                    "env_steps": collector.env_steps, "seconds": elapsed,
                    "eval_progress": progress, "eval_lap_time": lap, "eval_laps": laps, "eval_trials": args.trials,
                    "hyperparameters": hyper,
                }),
            };
            folder::save(&run.checkpoint_dir(&name), &meta, &ppo.model, &manifest)?;
            let rec = CheckpointRecord {
                name: name.clone(),
                iteration,
                policy_version: ppo.version,
                avg_eval_metric: progress,
                avg_lap_time: lap,
                time_stamp: elapsed,
            };
            if run.record(rec.clone())? {
                folder::save(&run.model_dir(), &meta, &ppo.model, &manifest)?;
                best = Some(rec);
            }
            // Stop only after the target is met in consecutive evaluations (each with fresh
            // actuator noise): one lucky evaluation is not a model that laps.
            streak = if args.target_laps > 0 && laps >= args.target_laps.min(args.trials) { streak + 1 } else { 0 };
            reached = streak >= args.target_evals.max(1);
            eval = Some((progress, lap, laps));
        }
        let sps = steps as f64 / (collect_s + update_s);
        run.append_metrics(&serde_json::json!({
            "iteration": iteration, "policy_version": stats.policy_version, "time_s": elapsed,
            "episodes": trajs.len(), "total_episodes": total_episodes, "steps": steps, "env_steps": collector.env_steps,
            "mean_reward": mean_reward, "mean_progress": mean_progress,
            "policy_loss": stats.policy_loss, "value_loss": stats.value_loss, "entropy": stats.entropy,
            "approx_kl": stats.approx_kl, "clip_fraction": stats.clip_fraction, "explained_variance": stats.explained_variance,
            "samples_per_s": sps, "collect_s": collect_s, "update_s": update_s, "policy_lag": lag,
            "refused": stats.refused,
            "eval_progress": eval.map(|e| e.0), "eval_lap_time": eval.and_then(|e| e.1), "eval_laps": eval.map(|e| e.2),
        }))?;
        bar.suspend(|| {
            println!(
                "it {iteration:>4} v{:<4} episodes {:>3} steps {:>6} reward {:>8.2} progress {:>5.1}% | pi {:>7.4} v {:>7.4} H {:.3} kl {:.4} clip {:.3} ev {:>5.2} | {:>6.0} samples/s lag {lag}{}",
                stats.policy_version,
                trajs.len(),
                steps,
                mean_reward,
                mean_progress,
                stats.policy_loss,
                stats.value_loss,
                stats.entropy,
                stats.approx_kl,
                stats.clip_fraction,
                stats.explained_variance,
                sps,
                eval.map(|(p, l, n)| format!(" | eval {p:.1}% {n}/{}{}", args.trials, l.map(|t| format!(" lap {t:.2}s")).unwrap_or_default()))
                    .unwrap_or_default()
            )
        });
        bar.set_position(elapsed.min(budget) as u64);
        bar.set_message(format!(
            "it {iteration} v{} reward {mean_reward:.1} progress {mean_progress:.1}% {sps:.0} samples/s{} {:.0}s left",
            stats.policy_version,
            eval.map(|(p, _, l)| format!(" eval {p:.0}% {l}/{}", args.trials)).unwrap_or_default(),
            (budget - elapsed).max(0.0)
        ));
        tracing::debug!(iteration, mean_reward, mean_progress, "iteration");
        if reached {
            stop_reason = "target laps reached";
            break;
        }
        if elapsed >= budget {
            break;
        }
        if total_episodes >= hyper.term_cond_max_episodes {
            stop_reason = "term_cond_max_episodes reached";
            break;
        }
        if mean_reward >= hyper.term_cond_avg_score {
            stop_reason = "term_cond_avg_score reached";
            break;
        }
    }
    bar.finish_and_clear();
    let secs = start.elapsed().as_secs_f64();
    println!(
        "stopped after {iteration} iterations, {total_episodes} episodes, {} env steps, {secs:.1} s: {stop_reason}",
        collector.env_steps
    );
    match &best {
        Some(b) => println!(
            "best model: {} (iteration {}, policy v{}): evaluation progress {:.1} %{}",
            run.model_dir().display(),
            b.iteration,
            b.policy_version,
            b.avg_eval_metric,
            b.avg_lap_time.map(|t| format!(", mean lap {t:.2} s")).unwrap_or_default()
        ),
        None => println!("no evaluation ran"),
    }
    run.write_file(
        "summary.json",
        serde_json::to_string_pretty(&serde_json::json!({
            "world": world.name, "iterations": iteration, "episodes": total_episodes, "env_steps": collector.env_steps,
            "seconds": secs, "stop_reason": stop_reason, "best": best,
        }))?
        .as_bytes(),
    )?;
    Ok(0)
}

pub fn evaluate_cmd(args: EvaluateArgs) -> Result<i32> {
    let f = folder::load(&args.model_dir)?;
    let mut cfg = SimConfig::default();
    cfg.observation = serde_json::from_value(f.manifest.observation.clone())
        .with_context(|| format!("{}: manifest.json's observation settings", args.model_dir.display()))?;
    if obs_dim(&cfg.observation) != f.manifest.obs_size {
        bail!(
            "{}: the observation settings give {} inputs, the model takes {}",
            args.model_dir.display(),
            obs_dim(&cfg.observation),
            f.manifest.obs_size
        );
    }
    let world = resolve_world(&args.world)?;
    let spec = EnvSpec::from_world(&world, if args.reversed { Direction::Reversed } else { Direction::Forward });
    let rules = if args.reset_rules {
        EvalRules { max_resets: 100, penalty_s: 2.0, time_limit_s: None }
    } else {
        EvalRules::default()
    };
    let cfg = Arc::new(cfg);
    println!(
        "evaluating {} (policy v{}) on {}: {} trials, argmax actions",
        args.model_dir.display(),
        f.manifest.policy_version,
        world.name,
        args.trials
    );
    let trials = evaluate(&f.model, &f.metadata.action_space, &spec, &cfg, rules, args.trials, args.seed, 1)?;
    for (i, t) in trials.iter().enumerate() {
        println!(
            "trial {}: {:<12} progress {:>6.1} %  lap time {:>8}  off-track {:>2}  steps {:>5}",
            i + 1,
            t.status.label(),
            t.progress,
            t.lap_time.map(|l| format!("{l:.2} s")).unwrap_or_else(|| "-".into()),
            t.off_track,
            t.steps
        );
    }
    let (progress, lap, laps) = summarise(&trials);
    println!(
        "{laps} of {} laps completed, mean progress {progress:.1} %{}",
        trials.len(),
        lap.map(|l| format!(", mean lap time {l:.2} s")).unwrap_or_default()
    );
    Ok(0)
}

pub fn clone_cmd(args: CloneArgs) -> Result<i32> {
    let f = folder::load(&args.model_dir)?;
    let meta = match &args.model_metadata {
        Some(p) => {
            let m = ModelMetadata::load(p)?;
            if let Err(why) = f.metadata.compatible_with(&m) {
                bail!("{} cannot be used with {}: {why}", p.display(), args.model_dir.display());
            }
            m
        }
        None => f.metadata.clone(),
    };
    let mut hyper = match &args.hyperparameters {
        Some(p) => hyperparameters(p)?,
        None => f
            .manifest
            .training
            .get("hyperparameters")
            .map(|h| Hyperparameters::parse(&h.to_string(), "parent manifest").map(|p| p.hyperparameters))
            .transpose()?
            .unwrap_or_default(),
    };
    if let Some(lr) = args.lr {
        hyper.lr = lr;
    }
    let run = RunDir::open(&args.out, OpenMode::New)?;
    let parent = Parent {
        path: args.model_dir.display().to_string(),
        policy_version: f.manifest.policy_version,
        weights_sha256: f.manifest.weights_sha256.clone(),
    };
    let manifest = Manifest {
        parent: Some(parent),
        training: serde_json::json!({"cloned": true, "hyperparameters": hyper}),
        ..f.manifest.clone()
    };
    folder::save(&run.model_dir(), &meta, &f.model, &manifest)?;
    run.write_file("model_metadata.json", meta.to_json().as_bytes())?;
    run.write_file("hyperparameters.json", hyper.to_json().as_bytes())?;
    let mut cfg = SimConfig::default();
    cfg.observation = serde_json::from_value(f.manifest.observation.clone())?;
    run.write_file("sim.toml", toml::to_string_pretty(&cfg)?.as_bytes())?;
    println!(
        "cloned {} (policy v{}) into {}: lr {}; continue with: coordinator train --world WORLD --out {} --resume",
        args.model_dir.display(),
        f.manifest.policy_version,
        args.out.display(),
        hyper.lr,
        args.out.display()
    );
    Ok(0)
}
