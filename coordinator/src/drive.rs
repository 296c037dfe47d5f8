//! `coordinator drive` (the scripted driver), `coordinator reward validate` and
//! `coordinator reward export`.

use crate::cli::{DriveArgs, ValidateArgs};
use crate::tracks_cmd::{draw, resolve_world};
use anyhow::{Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use policy::{ActionSpace, ModelMetadata};
use sim_agent::driver::PurePursuit;
use sim_agent::reward_check::{self, RewardInput, Severity};
use sim_agent::simtrace::{ActionTaken, SimTraceWriter};
use sim_agent::validate::Sampling;
use sim_agent::{Env, EnvSpec, EvalRules, Mode, RewardFn, SimConfig};
use std::io::BufWriter;
use std::sync::Arc;
use tracks::{Direction, P2};

fn direction(reversed: bool) -> Direction {
    if reversed { Direction::Reversed } else { Direction::Forward }
}

pub fn drive(args: DriveArgs) -> Result<i32> {
    let cfg: SimConfig = args.race.sim_config(args.config.as_deref(), &args.sets)?;
    let world = resolve_world(&args.track)?;
    let mut reward = RewardFn::from_spec(&args.reward)?;
    let spec = EnvSpec::from_world(&world, direction(args.reversed));
    let rules = EvalRules {
        max_resets: args.resets,
        penalty_s: args.penalty,
        collision_penalty_s: args.collision_penalty,
        time_limit_s: args.time_limit,
    };
    // A timed race is one long trial.
    let trials = if args.time_limit.is_some() { 1 } else { args.laps };
    let mut env = Env::new(spec, Arc::new(cfg), Mode::Evaluation(rules), args.seed, 0.0)?;
    let driver = PurePursuit { max_speed: args.max_speed, ..PurePursuit::default() };
    tracing::info!(world = %world.name, surface = world.surface.name(), reward = %reward.describe(), laps = args.laps, "driving");
    println!(
        "driving {} ({}, {}, {:.3} m) with the pure-pursuit driver, reward {}",
        world.name,
        world.surface.name(),
        if args.reversed { "reversed" } else { "forward" },
        env.track().length(),
        reward.describe()
    );
    let mut trace = match &args.simtrace {
        Some(p) => Some(SimTraceWriter::new(BufWriter::new(
            std::fs::File::create(p).with_context(|| format!("creating {}", p.display()))?,
        ))?),
        None => None,
    };
    let bar = ProgressBar::new(trials as u64)
        .with_style(ProgressStyle::with_template("lap {pos}/{len} [{bar:30}] {msg}").expect("template"));
    let mut path: Vec<P2> = Vec::new();
    // The race's objects where the last lap left them, for the drawing.
    let mut shapes: Vec<([P2; 4], bool)> = Vec::new();
    let mut completed = 0;
    let mut race_laps = 0;
    for lap in 1..=trials {
        env.reset();
        loop {
            let action = driver.act(&env);
            env.advance(action);
            let r = env.reward_with(&mut reward)?;
            let o = env.finish(r);
            path.push(P2::new(o.trace.x, o.trace.y));
            if let Some(t) = trace.as_mut() {
                let wall = sim_agent::rollout::unix_now();
                t.row(lap as u64 - 1, env.track().length(), ActionTaken::Continuous(action), &o, wall)?;
            }
            bar.set_message(format!("progress {:.1} %", o.progress));
            if let (Some(_), Some(t)) = (args.time_limit, o.lap_time) {
                race_laps += 1;
                bar.suspend(|| {
                    println!(
                        "race lap {race_laps}: time {t:>8.2} s  race time {:>8.2} s  resets so far {}",
                        o.sim_time, o.resets
                    )
                });
            }
            if o.done {
                shapes = env
                    .objects()
                    .iter()
                    .map(|o| (tracks::objects::corners(o.pose.position, o.pose.heading, o.footprint), o.car))
                    .collect();
                let time = o.lap_time.map(|t| format!("{t:.2} s")).unwrap_or_else(|| "-".into());
                bar.suspend(|| {
                    println!(
                        "lap {lap}: {:<12} time {time:>8}  steps {:>5}  progress {:>6.1} %  off-track {:>2}  crashes {:>2}  reward {:>8.1}",
                        o.status.label(),
                        o.steps,
                        o.progress,
                        o.off_track(),
                        o.crashes,
                        o.episode_reward
                    )
                });
                if o.status == sim_agent::EpisodeStatus::LapComplete {
                    completed += 1;
                }
                break;
            }
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    if args.time_limit.is_some() {
        println!("{race_laps} laps in the timed race");
    } else {
        println!("{completed} of {} laps completed", args.laps);
    }
    if let Some(t) = trace {
        t.finish()?;
        println!("sim-trace    {}", args.simtrace.as_ref().expect("set").display());
    }
    if let Some(png) = &args.png {
        draw(&world, png, &path, &shapes)?;
    }
    Ok(0)
}

/// `reward validate`: every finding about the file on its line (the static checks, then the
/// calls on sampled states, which go on past a failed call), the rewards of the calls that
/// returned, and the first failed call in full (its traceback and params); or all of it as
/// one JSON object (`--json`).
pub fn validate(args: ValidateArgs) -> Result<i32> {
    let race: SimConfig = args.race.sim_config(None, &[])?;
    let world = resolve_world(&args.track)?;
    let track = world.track(direction(args.reversed));
    let space = match &args.model_metadata {
        Some(p) => ModelMetadata::load(p)?.action_space,
        None => ActionSpace::Continuous { steering_angle: (-30.0, 30.0), speed: (0.5, 4.0) },
    };
    let limit = sim_agent::config::SimConfig { reward_time_limit: args.time_limit, ..Default::default() };
    let file = args.file.as_str();
    if !args.json {
        println!("validating {file} on {} ({})", world.name, if args.reversed { "reversed" } else { "forward" });
    }
    let at =
        Sampling { track: &track, surface: world.surface, space: &space, positions: args.positions, race: &race.race };
    let v = reward_check::validate(RewardInput::of_spec(file), at, limit.reward_time_limit())
        .map_err(|e| anyhow::anyhow!("{file}: {e}"))?;
    let code = if v.ok() { 0 } else { 1 };
    if args.json {
        println!("{}", v.to_json());
        return Ok(code);
    }
    for f in &v.findings {
        match f.line {
            Some(line) => println!("{file}:{line}: {}: {}", f.severity.label(), f.message),
            None => println!("{file}: {}: {}", f.severity.label(), f.message),
        }
    }
    if let Some(report) = &v.report {
        for (kind, mean) in &report.mean_by_kind {
            println!("  {kind:<22} mean reward {mean:.4}");
        }
        println!("{} calls: min {:.4}, mean {:.4}, max {:.4}", report.calls, report.min, report.mean, report.max);
    }
    let (errors, warnings) = (v.count(Severity::Error), v.count(Severity::Warning));
    match (errors, warnings) {
        (0, 0) => println!("PASSED"),
        (0, n) => println!("PASSED, with {n} warning{} (DeepRacer's console would refuse the file)", plural(n)),
        (e, w) => {
            println!("FAILED: {e} error{}, {w} warning{}", plural(e), plural(w));
            if let Some(e) = &v.first_failure {
                println!("the first failed call:\n{e}");
            }
        }
    }
    Ok(code)
}

fn plural(n: usize) -> &'static str {
    if n == 1 { "" } else { "s" }
}

/// `reward export`: a built-in as a Python reward file giving the same rewards.
pub fn export(spec: &str, world: &str, out: &std::path::Path) -> Result<i32> {
    let name = spec.strip_prefix("builtin:").unwrap_or(spec);
    let Some(&(builtin, _)) = sim_agent::BuiltinReward::ALL.iter().find(|(_, n)| *n == name) else {
        let known: Vec<String> = sim_agent::BuiltinReward::ALL.iter().map(|(_, n)| format!("builtin:{n}")).collect();
        anyhow::bail!("{spec}: not a built-in reward; expected one of {}", known.join(", "));
    };
    let text = match builtin.python_source() {
        Some(text) => text.to_string(),
        None => {
            use sim_agent::race_line::{LinePlan, python_source};
            let world = resolve_world(world)?;
            let car = SimConfig::default().car;
            let plan = |d: Direction| {
                LinePlan::new(&world.track(d), &car, world.surface)
                    .with_context(|| format!("{}: the racing line", world.name))
            };
            let (forward, reversed) = (plan(Direction::Forward)?, plan(Direction::Reversed)?);
            println!(
                "{}: the racing line laps in {:.2} s forward, {:.2} s reversed ({})",
                world.name,
                forward.lap_time,
                reversed.lap_time,
                world.surface.name()
            );
            python_source(&world.name, world.surface, &forward, &reversed)
        }
    };
    std::fs::write(out, text).with_context(|| format!("writing {}", out.display()))?;
    println!("written {} (builtin:{name} as a DeepRacer reward function)", out.display());
    Ok(0)
}
