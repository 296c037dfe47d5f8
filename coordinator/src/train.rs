//! `coordinator train`, `evaluate` and `clone`: PPO in one process.
//!
//! `train` runs the one training loop ([`learner::run::run`]) with a sim worker
//! ([`sim_agent::worker::Worker`]) on another thread, joined by in-process channels
//! ([`crate::local`]): the same loop and the same worker that `learner serve` and
//! `sim-agent serve` run apart over Zenoh.

use crate::cli::{CloneArgs, EvaluateArgs, TrainArgs};
use crate::local::LocalLink;
use crate::tracks_cmd::resolve_world;
use anyhow::{Context, Result, bail};
use faer::Par;
use indicatif::{ProgressBar, ProgressStyle};
use learner::Hyperparameters;
use learner::checkpoints::{OpenMode, RunDir};
use learner::record::{EvalRecord, IterationRecord};
use learner::run::{Observer, RunSpec, Start, StopRules, TargetLaps, run};
use policy::ModelMetadata;
use policy::exchange::{Trial, summarise};
use policy::folder::{self, Manifest, Parent};
use sim_agent::obs::obs_dim;
use sim_agent::worker::{Worker, WorkerSetup};
use sim_agent::{EnvSpec, EvalRules, RewardFn, SimConfig};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use tracks::Direction;

/// The simulator configuration a model's sensors call for.
fn check_sensors(meta: &ModelMetadata, cfg: &mut SimConfig) -> Result<()> {
    cfg.observation.set_sensors(meta).map_err(|e| anyhow::anyhow!("model_metadata.json: {e}"))?;
    let (sim, model) = (obs_dim(&cfg.observation), policy::model::input_size(meta, obs_dim(&cfg.observation)));
    if sim != model {
        anyhow::bail!("model_metadata.json: the network takes {model} values a step, the simulator gives {sim}");
    }
    Ok(())
}

fn hyperparameters(path: &Path, algorithm: policy::TrainingAlgorithm) -> Result<Hyperparameters> {
    let parsed = Hyperparameters::load(path)?;
    for k in &parsed.unknown {
        tracing::warn!(file = %path.display(), key = %k, "unknown key in hyperparameters.json, not used");
        eprintln!("warning: {}: unknown key '{k}' is not used", path.display());
    }
    for k in parsed.ignored_for(algorithm) {
        if algorithm == policy::TrainingAlgorithm::Sac && !k.starts_with("stack_size") {
            tracing::warn!(file = %path.display(), "{k}");
            eprintln!("warning: {}: {k}", path.display());
        } else {
            tracing::info!(file = %path.display(), "{k}");
        }
    }
    Ok(parsed.hyperparameters)
}

fn default_run_dir(world: &str) -> PathBuf {
    let stamp = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_secs()).unwrap_or(0);
    PathBuf::from("runs").join(format!("{world}-{stamp}"))
}

/// Prints every iteration and evaluation above a progress bar.
struct Terminal {
    bar: ProgressBar,
    budget: f64,
}

impl Observer for Terminal {
    fn iteration(&mut self, r: &IterationRecord) {
        let head = format!(
            "it {:>4} v{:<4} episodes {:>3} steps {:>6} reward {:>8.2} progress {:>5.1}%",
            r.iteration, r.policy_version, r.episodes, r.steps, r.mean_reward, r.mean_progress
        );
        let maths = match &r.sac {
            Some(s) => format!(
                "pi {:>8.3} q {:>8.4} v {:>7.4} H {:>6.3} α {:.3} | {:>5} gradient steps, replay {}",
                r.policy_loss, s.q_loss, r.value_loss, r.entropy, s.alpha, r.gradient_steps, s.replay
            ),
            None => format!(
                "pi {:>7.4} v {:>7.4} H {:.3} kl {:.4} clip {:.3} ev {:>5.2} | {:>6.0} samples/s",
                r.policy_loss,
                r.value_loss,
                r.entropy,
                r.approx_kl,
                r.clip_fraction,
                r.explained_variance,
                r.samples_per_s
            ),
        };
        self.bar.suspend(|| println!("{head} | {maths} lag {}", r.policy_lag));
        if let Some(why) = &r.refused {
            self.bar.suspend(|| eprintln!("warning: iteration {}: {why}", r.iteration));
        }
        self.bar.set_position(r.time_s.min(self.budget) as u64);
        self.bar.set_message(format!(
            "it {} v{} reward {:.1} progress {:.1}% {:.0}s left",
            r.iteration,
            r.policy_version,
            r.mean_reward,
            r.mean_progress,
            (self.budget - r.time_s).max(0.0)
        ));
    }

    fn evaluation(&mut self, e: &EvalRecord) {
        let worlds: Vec<String> = e
            .worlds
            .iter()
            .map(|(w, p, lap, laps, n)| match n {
                // A verification the worker dropped once another world's could no longer hold.
                0 => format!("{w} not run"),
                _ => format!("{w} {p:.1}% {laps}/{n}{}", lap.map(|t| format!(" lap {t:.2}s")).unwrap_or_default()),
            })
            .collect();
        self.bar.suspend(|| {
            println!(
                "     {} v{}: {}{}{} {}",
                if e.verification { "verify" } else { "eval" },
                e.policy_version,
                worlds.join(" | "),
                if e.crashes > 0 { format!(" | {} crashes", e.crashes) } else { String::new() },
                e.overtakes.map(|o| format!(" | {o} overtakes")).unwrap_or_default(),
                if e.best { "(best so far)" } else { "" }
            );
            if !e.trend.is_empty() {
                println!("     {}", e.trend);
            }
        });
    }
}

/// The stop rules `train`'s flags ask for.
fn stop_rules(args: &TrainArgs) -> StopRules {
    StopRules {
        minutes: args.minutes,
        max_episodes: args.max_episodes,
        target_progress: args.target_progress,
        target_reward: args.target_reward,
        window: args.window.max(1),
        env_steps_budget: args.env_steps,
        target_laps: (args.target_laps > 0).then(|| TargetLaps {
            laps: args.target_laps,
            evaluations: args.target_evals.max(1),
            verify_trials: args.verify_trials,
        }),
        plateau_evals: args.stop_on_plateau,
        stop_on_collapse: args.stop_on_collapse,
    }
}

pub fn train(mut args: TrainArgs) -> Result<i32> {
    if let Some(f) = args.race.run_env_files()? {
        let meta = f.fill(&mut args.world, &mut args.reward, &mut args.hyperparameters, &mut args.sets);
        args.model_metadata = args.model_metadata.or(meta);
    }
    let reward_spec = args.reward.clone().unwrap_or_else(|| "builtin:center_line".into());
    let worlds_arg = if args.world.is_empty() { vec!["reinvent_base".to_string()] } else { args.world.clone() };
    let out = args.out.clone().unwrap_or_else(|| default_run_dir(&worlds_arg.join("+")));
    let start = match (args.resume, args.force) {
        (true, true) => bail!("--resume and --force contradict each other"),
        (true, false) => Start::Resume,
        (false, true) => Start::Force,
        (false, false) => Start::New { clone_from: None },
    };
    if start == (Start::New { clone_from: None }) && out.join("model").exists() {
        bail!("{} already holds a run: pass --resume to continue it or --force to start again", out.display());
    }
    // Inputs: flags first, then what the run folder holds (resume, clone), then defaults.
    let from_run = |name: &str| Some(out.join(name)).filter(|p| start == Start::Resume && p.exists());
    let meta_path = args.model_metadata.clone().or_else(|| from_run("model_metadata.json"));
    let hyper_path = args.hyperparameters.clone().or_else(|| from_run("hyperparameters.json"));
    let sim_path = args.config.clone().or_else(|| from_run("sim.toml"));
    let mut meta = match (&meta_path, args.sensor.as_str()) {
        (Some(p), _) => ModelMetadata::load(p)?,
        (None, name) => ModelMetadata::for_sensor(name).ok_or_else(|| {
            anyhow::anyhow!("--sensor is {name:?}, expected one of {:?}", ModelMetadata::SENSOR_NAMES)
        })?,
    };
    let mut hyper = match &hyper_path {
        Some(p) => hyperparameters(p, meta.training_algorithm)?,
        None => Hyperparameters::default(),
    };
    if let Some(lr) = args.lr {
        hyper.lr = lr;
    }
    let mut cfg: SimConfig = args.race.sim_config(sim_path.as_deref(), &args.sets)?;
    check_sensors(&meta, &mut cfg)?;
    let worlds = worlds_arg.iter().map(|w| resolve_world(w)).collect::<Result<Vec<_>>>()?;
    let direction = if args.reversed { Direction::Reversed } else { Direction::Forward };
    if let Some(n) = args.action_space_from_line {
        if let Some(p) = &meta_path {
            bail!(
                "--action-space-from-line proposes the action space, and {} names one: pass one or the other",
                p.display()
            );
        }
        if n == 0 {
            bail!("--action-space-from-line 0: the action space needs at least one action");
        }
        let w = &worlds[0];
        let plan = sim_agent::race_line::LinePlan::new(&w.track(direction), &cfg.car, w.surface)
            .with_context(|| format!("--action-space-from-line: {}'s racing line", w.name))?;
        let actions = plan.action_space(&cfg.car, n, 30.0, 4.0);
        let shown: Vec<String> =
            actions.iter().map(|a| format!("{:+.1}° {:.2} m/s", a.steering_angle, a.speed)).collect();
        println!("action space from {}'s racing line: {}", w.name, shown.join(", "));
        meta.action_space = policy::ActionSpace::Discrete(actions);
    }
    // Validate the reward before any training: a broken file stops here with its traceback.
    let mut reward = RewardFn::from_spec(&reward_spec)?.with_time_limit(cfg.reward_time_limit());
    for w in &worlds {
        sim_agent::validate::validate_reward(
            &mut reward,
            &w.track(direction),
            w.surface,
            &meta.action_space,
            20,
            &cfg.race,
        )
        .with_context(|| format!("the reward function {reward_spec} failed validation on {}", w.name))?;
    }
    let obs_size = obs_dim(&cfg.observation);
    let threads = learner::use_threads(args.threads);
    let camera = cfg.observation.kind.is_camera();
    // One GPU for the learner's update and the worker's acting.
    let gpu = learner::device::Device::new(args.device).gpu().context("--device")?;
    let spec = RunSpec {
        name: worlds.iter().map(|w| w.name.clone()).collect::<Vec<_>>().join("+"),
        metadata: meta.clone(),
        hyper: hyper.clone(),
        obs_size,
        observation: serde_json::to_value(&cfg.observation)?,
        sim_toml: toml::to_string_pretty(&cfg)?,
        worlds: worlds.iter().map(|w| w.name.clone()).collect(),
        out: out.clone(),
        start,
        seed: args.seed,
        max_policy_lag: 4,
        eval_trials: args.trials.max(1) as u32,
        eval_seconds: args.checkpoint_seconds,
        stop: stop_rules(&args),
        // The worker runs in this process, on the same cores.
        checks_first: true,
        // The camera networks are big enough to split over the cores; the MLP is not.
        par: if camera { Par::rayon(threads) } else { Par::Seq },
        gpu: gpu.clone(),
        adopt: None,
        signing_key: args.signing_key.clone(),
        tracks: worlds.iter().map(|w| sim_agent::track_lines(w, direction)).collect(),
    };
    let worker = Worker::new(WorkerSetup {
        id: "local".into(),
        worlds: worlds.iter().map(|w| EnvSpec::from_world(w, direction)).collect(),
        offset: 0,
        weights: Vec::new(),
        envs: args.envs.max(1),
        threads,
        cfg: Arc::new(cfg),
        reward,
        space: meta.action_space.clone(),
        seed: args.seed,
        first_seq: 0,
        gpu,
    })?;
    println!(
        "training on {} for up to {:.1} min, {} envs, reward {}, run folder {}",
        worlds
            .iter()
            .map(|w| format!("{} ({}{})", w.name, w.surface.name(), if args.reversed { ", reversed" } else { "" }))
            .collect::<Vec<_>>()
            .join(", "),
        args.minutes,
        args.envs,
        reward_spec,
        out.display()
    );
    let budget = args.minutes * 60.0;
    let bar = ProgressBar::new(budget.ceil() as u64)
        .with_style(ProgressStyle::with_template("{elapsed_precise} [{bar:25}] {msg}").expect("template"));
    let mut terminal = Terminal { bar, budget };
    let mut link = LocalLink::start(worker, "local");
    let summary = run(&spec, &mut link, &mut terminal);
    terminal.bar.finish_and_clear();
    drop(link);
    let summary = summary?;
    println!(
        "stopped after {} iterations, {} episodes, {} env steps, {:.1} s: {}",
        summary.iterations, summary.episodes, summary.env_steps, summary.seconds, summary.stop_reason
    );
    match &summary.best {
        Some(b) => println!(
            "best model: {} (iteration {}, policy v{}): evaluation progress {:.1} %{}",
            out.join("model").display(),
            b.iteration,
            b.policy_version,
            b.avg_eval_metric,
            b.avg_lap_time.map(|t| format!(", mean lap {t:.2} s")).unwrap_or_default()
        ),
        None => println!("no evaluation ran"),
    }
    if summary.write_failures.0 > 0 {
        eprintln!(
            "warning: {} write(s) to the run folder failed; the last: {}",
            summary.write_failures.0, summary.write_failures.1
        );
        return Ok(protocol::exit::WRITES_FAILED);
    }
    Ok(0)
}

/// `evaluate`'s line for trial `i` (from 0) on `world` (`bench races` reads it back).
pub(crate) fn trial_line(i: usize, world: &str, t: &Trial) -> String {
    format!(
        "trial {}: {:<20} {:<12} progress {:>6.1} %  lap time {:>8}  off-track {:>2}  crashes {:>2}  steps {:>5}{}",
        i + 1,
        world,
        t.status,
        t.progress,
        t.lap_time.map(|l| format!("{l:.2} s")).unwrap_or_else(|| "-".into()),
        t.off_track,
        t.crashes,
        t.steps,
        t.overtakes.map(|o| format!("  overtakes {o}")).unwrap_or_default()
    )
}

pub fn evaluate_cmd(args: EvaluateArgs) -> Result<i32> {
    // The evaluation drives its own car, camera and noise (the model's): only the race is
    // taken from a configuration.
    if let Some(s) = args.sets.iter().find(|s| !s.starts_with("race.")) {
        anyhow::bail!("--set {s}: evaluate takes the race's keys only (race.KEY=VALUE)");
    }
    let race: SimConfig = args.race.sim_config(args.config.as_deref(), &args.sets)?;
    let rules =
        if args.reset_rules { EvalRules { max_resets: 100, ..EvalRules::default() } } else { EvalRules::default() };
    let names = if args.world.is_empty() { vec!["reinvent_base".to_string()] } else { args.world.clone() };
    let worlds = names.iter().map(|n| resolve_world(n)).collect::<Result<Vec<_>>>()?;
    let req = coordinator::evaluation::Request {
        worlds,
        reversed: args.reversed,
        trials: args.trials,
        seed: args.seed,
        race: race.race,
        rules,
        record: false,
        all_frames: false,
    };
    let version = folder::load(&args.model_dir).map(|f| f.manifest.policy_version).unwrap_or(0);
    println!(
        "evaluating {} (policy v{version}) on {}: {} trials each, argmax actions",
        args.model_dir.display(),
        names.join(", "),
        args.trials
    );
    let done = coordinator::evaluation::run(&args.model_dir, &req)?;
    let mut table = Vec::new();
    let mut crashes = 0;
    let mut overtakes: Option<u32> = None;
    for w in done.worlds {
        let trials: Vec<Trial> = w.trials.into_iter().map(Trial::from).collect();
        for (i, t) in trials.iter().enumerate() {
            println!("{}", trial_line(i, &w.world, t));
        }
        let (progress, lap, laps) = summarise(&trials);
        crashes += trials.iter().map(|t| t.crashes).sum::<u32>();
        if let Some(o) = trials.iter().filter_map(|t| t.overtakes).reduce(|a, b| a + b) {
            *overtakes.get_or_insert(0) += o;
        }
        table.push((w.world.clone(), laps, trials.len(), progress, lap));
    }
    println!();
    println!("{:<24} {:>6} {:>10} {:>10}", "WORLD", "LAPS", "PROGRESS", "MEAN LAP");
    for (w, laps, n, p, lap) in &table {
        println!(
            "{w:<24} {:>6} {:>9.1}% {:>10}",
            format!("{laps}/{n}"),
            p,
            lap.map(|l| format!("{l:.2} s")).unwrap_or_else(|| "-".into())
        );
    }
    let laps: usize = table.iter().map(|t| t.1).sum();
    let n: usize = table.iter().map(|t| t.2).sum();
    let progress = table.iter().map(|t| t.3).sum::<f64>() / table.len().max(1) as f64;
    println!(
        "{laps} of {n} laps completed, mean progress {progress:.1} %, {crashes} crashes{}",
        overtakes.map(|o| format!(", {o} overtakes")).unwrap_or_default()
    );
    Ok(0)
}

/// Updates an imported model's new value tower trains alone after `clone` (one per
/// `num_episodes_between_training` episodes: 100 episodes with DeepRacer's defaults).
const IMPORT_VALUE_WARMUP: u64 = 5;

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
        Some(p) => hyperparameters(p, meta.training_algorithm)?,
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
    // A model imported from DeepRacer's graph has a new value tower: it learns alone first,
    // unless the user's hyperparameters.json says how long. One imported whole (a DRoA or
    // deepracer-for-cloud checkpoint) brought its own.
    let imported = f.manifest.training["imported"]["value_tower"].as_str().is_some_and(|v| v.starts_with("new"));
    let said = args
        .hyperparameters
        .as_ref()
        .and_then(|p| std::fs::read_to_string(p).ok())
        .is_some_and(|t| t.contains("\"value_warmup_updates\""));
    if imported && !said {
        hyper.value_warmup_updates = f.manifest.policy_version + IMPORT_VALUE_WARMUP;
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
    // SAC's critics go along; so do an imported model's DeepRacer files, into the run folder
    // (its model/ is rewritten as it trains), for `export --virtual` of what it trains.
    let critics = args.model_dir.join(learner::sac::trainer::CRITICS_FILE);
    if critics.is_file() {
        std::fs::copy(&critics, run.model_dir().join(learner::sac::trainer::CRITICS_FILE))
            .with_context(|| format!("copying {}", critics.display()))?;
    }
    let kept = args.model_dir.join(coordinator::virtual_model::KEPT);
    if kept.is_dir() {
        let to = args.out.join(coordinator::virtual_model::KEPT);
        std::fs::create_dir_all(&to).with_context(|| format!("writing {}", to.display()))?;
        for e in std::fs::read_dir(&kept).with_context(|| format!("reading {}", kept.display()))? {
            let p = e?.path();
            if p.is_file() {
                std::fs::copy(&p, to.join(p.file_name().expect("a file")))
                    .with_context(|| format!("copying {}", p.display()))?;
            }
        }
    }
    run.write_file("model_metadata.json", meta.to_json().as_bytes())?;
    run.write_file("hyperparameters.json", hyper.to_json().as_bytes())?;
    let cfg =
        SimConfig { observation: serde_json::from_value(f.manifest.observation.clone())?, ..SimConfig::default() };
    run.write_file("sim.toml", toml::to_string_pretty(&cfg)?.as_bytes())?;
    println!(
        "cloned {} (policy v{}) into {}: lr {}; continue with: coordinator train --world WORLD --out {} --resume",
        args.model_dir.display(),
        f.manifest.policy_version,
        args.out.display(),
        hyper.lr,
        args.out.display()
    );
    if hyper.value_warmup_updates > f.manifest.policy_version {
        println!(
            "the value tower is new: it learns alone until policy v{} (value_warmup_updates in {}), then the policy trains too",
            hyper.value_warmup_updates,
            args.out.join("hyperparameters.json").display()
        );
    }
    Ok(0)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cli::{Cli, Command};
    use clap::Parser;

    fn rules(flags: &[&str]) -> StopRules {
        let cli = Cli::try_parse_from(["coordinator", "train"].iter().chain(flags)).unwrap();
        let Command::Train(args) = cli.command else { panic!("not train") };
        stop_rules(&args)
    }

    /// Issue 29: each stop flag sets its rule and only that.
    #[test]
    fn each_stop_flag_sets_its_rule_and_only_that() {
        // The run's stop rules are tested through a whole run in learner/tests/it/run_scripted.rs;
        // here, that each flag of `train` reaches its rule.
        let base = rules(&[]);
        assert_eq!(base.target_laps, Some(TargetLaps { laps: 3, evaluations: 2, verify_trials: 10 }), "{base:?}");
        let table: Vec<(&[&str], StopRules)> = vec![
            (&["--max-episodes", "60"], StopRules { max_episodes: Some(60), ..base.clone() }),
            (&["--env-steps", "15000"], StopRules { env_steps_budget: Some(15000), ..base.clone() }),
            (&["--target-progress", "25"], StopRules { target_progress: Some(25.0), ..base.clone() }),
            (&["--target-reward", "15"], StopRules { target_reward: Some(15.0), ..base.clone() }),
            (&["--minutes", "0.1"], StopRules { minutes: 0.1, ..base.clone() }),
            (&["--window", "7"], StopRules { window: 7, ..base.clone() }),
            (&["--target-laps", "0"], StopRules { target_laps: None, ..base.clone() }),
            (
                &["--target-laps", "2", "--target-evals", "4"],
                StopRules {
                    target_laps: Some(TargetLaps { laps: 2, evaluations: 4, verify_trials: 10 }),
                    ..base.clone()
                },
            ),
            (
                &["--verify-trials", "0", "--target-evals", "1"],
                StopRules {
                    target_laps: Some(TargetLaps { laps: 3, evaluations: 1, verify_trials: 0 }),
                    ..base.clone()
                },
            ),
            (&["--stop-on-plateau", "2"], StopRules { plateau_evals: Some(2), ..base.clone() }),
            (&["--stop-on-collapse"], StopRules { stop_on_collapse: true, ..base.clone() }),
        ];
        for (flags, want) in table {
            assert_eq!(rules(flags), want, "{flags:?}");
        }
        // More verification trials than an agent takes: refused by name.
        let e = Cli::try_parse_from(["coordinator", "train", "--verify-trials", "1000000"]).err().unwrap().to_string();
        assert!(e.contains("--verify-trials"), "{e}");
    }
}
