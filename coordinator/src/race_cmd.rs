//! `coordinator race`: models raced against each other on one world under DeepRacer's race
//! rules (a car that leaves the track is put back with a time penalty, a crash costs more),
//! ranked by best lap, with a page that draws each model's fastest lap on the track,
//! coloured by speed, and the camera frames of that lap as a strip.
//!
//! A model is a Paddock model folder or DeepRacer's model archive (`.tar.gz`, `.tar`), read as
//! `import` reads it. Each trial is one evaluation from the start line (the most likely action
//! at every step), seeded apart, so that every trial keeps its own camera frames.

use crate::cli::RaceCmdArgs;
use crate::tracks_cmd::resolve_world;
use anyhow::{Context, Result, bail};
use policy::folder::{self, ModelFolder};
use sim_agent::rollout::{EvalPlan, TrialResult, evaluate};
use sim_agent::{EnvSpec, EvalRules, SimConfig};
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use tracks::{Direction, P2};

/// Frames in a lap's camera strip at most.
const STRIP: usize = 10;

/// One model's race.
struct Entry {
    name: String,
    source: PathBuf,
    network: String,
    trials: Vec<TrialResult>,
}

impl Entry {
    fn laps(&self) -> Vec<f64> {
        self.trials.iter().filter_map(|t| t.lap_time).collect()
    }

    fn best(&self) -> Option<f64> {
        self.laps().into_iter().reduce(f64::min)
    }

    fn mean(&self) -> Option<f64> {
        let l = self.laps();
        (!l.is_empty()).then(|| l.iter().sum::<f64>() / l.len() as f64)
    }

    fn progress(&self) -> f64 {
        self.trials.iter().map(|t| t.progress).sum::<f64>() / self.trials.len().max(1) as f64
    }

    fn off_track(&self) -> u32 {
        self.trials.iter().map(|t| t.off_track).sum()
    }

    fn crashes(&self) -> u32 {
        self.trials.iter().map(|t| t.crashes).sum()
    }

    /// The trial of the fastest lap, or the one that got farthest.
    fn showcase(&self) -> Option<&TrialResult> {
        let key = |t: &TrialResult| (t.lap_time.is_none(), t.lap_time.unwrap_or(0.0), -t.progress);
        self.trials.iter().min_by(|a, b| key(a).partial_cmp(&key(b)).unwrap_or(std::cmp::Ordering::Equal))
    }
}

/// A model folder, or DeepRacer's archive read as `import` reads it; and the name it races
/// under (the run folder's name for RUN/model, the archive's up to its first dot).
fn load_model(path: &Path, seed: u64) -> Result<(String, ModelFolder)> {
    let file = path.file_name().map(|f| f.to_string_lossy().into_owned()).unwrap_or_default();
    if path.is_file() {
        if !(file.ends_with(".tar.gz") || file.ends_with(".tar") || file.ends_with(".tgz")) {
            bail!("{}: expected a model folder or DeepRacer's model archive (.tar.gz, .tar)", path.display());
        }
        let pkg = policy::carpkg::read(path)?;
        let f = pkg.to_folder(&path.display().to_string(), seed)?;
        return Ok((file.split('.').next().unwrap_or(&file).to_string(), f));
    }
    let f = folder::load(path).with_context(|| format!("{}: not a model folder", path.display()))?;
    let name = if file == "model" {
        path.parent().and_then(|p| p.file_name()).map(|f| f.to_string_lossy().into_owned()).unwrap_or(file)
    } else {
        file
    };
    Ok((name, f))
}

/// One model's line of the leaderboard.
#[derive(Clone, Debug)]
pub struct Standing {
    /// The name it raced under.
    pub name: String,
    /// Its best lap (s).
    pub best: Option<f64>,
    /// Its mean lap (s).
    pub mean: Option<f64>,
    /// Laps completed.
    pub laps: usize,
    /// Trials run.
    pub trials: usize,
}

/// `coordinator race`.
pub fn race(args: RaceCmdArgs) -> Result<i32> {
    run(&args).map(|_| 0)
}

/// Race `args.models`; the leaderboard, best first (and race.html written).
pub fn run(args: &RaceCmdArgs) -> Result<Vec<Standing>> {
    if args.trials == 0 {
        bail!("--trials 0: a race needs at least one trial");
    }
    let race: SimConfig = args.race.sim_config(None, &[])?;
    let world = resolve_world(&args.world)?;
    let direction = if args.reversed { Direction::Reversed } else { Direction::Forward };
    let spec = EnvSpec::from_world(&world, direction);
    let rules = EvalRules {
        max_resets: args.resets,
        penalty_s: args.penalty,
        collision_penalty_s: args.collision_penalty,
        time_limit_s: None,
    };
    let threads = std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1);
    // Read every model before racing any: a bad one stops the race at once.
    let mut models = Vec::new();
    let mut names = std::collections::BTreeMap::<String, usize>::new();
    for path in &args.models {
        let (mut name, f) = load_model(path, args.seed)?;
        let seen = names.entry(name.clone()).or_insert(0);
        *seen += 1;
        if *seen > 1 {
            name = format!("{name}-{seen}");
        }
        let cfg = SimConfig {
            race: race.race.clone(),
            observation: serde_json::from_value(f.manifest.observation.clone())
                .with_context(|| format!("{}: manifest.json's observation settings", path.display()))?,
            record_trace: true,
            ..SimConfig::default()
        };
        let inputs = sim_agent::obs::obs_dim(&cfg.observation);
        if inputs != f.manifest.obs_size {
            bail!(
                "{}: the observation settings give {inputs} inputs, the model takes {}",
                path.display(),
                f.manifest.obs_size
            );
        }
        models.push((name, path.clone(), f, Arc::new(cfg)));
    }
    println!(
        "racing {} model(s) on {} ({}), {} trial(s) each: off-track +{} s, crash +{} s, {} resets a trial",
        models.len(),
        world.name,
        if args.reversed { "reversed" } else { "forward" },
        args.trials,
        args.penalty,
        args.collision_penalty,
        args.resets
    );
    let mut entries = Vec::new();
    for (name, source, f, cfg) in models {
        let model = Arc::new(f.model.clone());
        let mut trials = Vec::new();
        for t in 0..args.trials {
            let seed = args.seed.wrapping_add(t as u64);
            let plan = EvalPlan {
                rules: rules.clone(),
                count: 1,
                seed,
                threads,
                all_frames: false,
                spread: true,
                give_up_after_misses: None,
            };
            let mut one = evaluate(&model, &f.metadata.action_space, &spec, &cfg, &plan, None)?;
            let r = one.remove(0);
            println!(
                "  {name:<24} trial {}: {:<10} progress {:>5.1} %  lap {:>8}  off-track {}  crashes {}",
                t + 1,
                r.status.label(),
                r.progress,
                r.lap_time.map(|l| format!("{l:.2} s")).unwrap_or_else(|| "-".into()),
                r.off_track,
                r.crashes
            );
            trials.push(r);
        }
        entries.push(Entry { name, source, network: f.metadata.neural_network.name().to_string(), trials });
    }
    // DeepRacer's leaderboard: the best lap first; models without a lap after, by progress.
    entries.sort_by(|a, b| match (a.best(), b.best()) {
        (Some(x), Some(y)) => x.total_cmp(&y),
        (Some(_), None) => std::cmp::Ordering::Less,
        (None, Some(_)) => std::cmp::Ordering::Greater,
        (None, None) => b.progress().total_cmp(&a.progress()),
    });
    let lap = |t: Option<f64>| t.map(|l| format!("{l:.2} s")).unwrap_or_else(|| "-".into());
    println!();
    println!(
        "{:<4} {:<24} {:>9} {:>9} {:>6} {:>9} {:>9} {:>7}",
        "RANK", "MODEL", "BEST LAP", "MEAN LAP", "LAPS", "PROGRESS", "OFF-TRACK", "CRASHES"
    );
    for (i, e) in entries.iter().enumerate() {
        println!(
            "{:<4} {:<24} {:>9} {:>9} {:>6} {:>8.1}% {:>9} {:>7}",
            i + 1,
            e.name,
            lap(e.best()),
            lap(e.mean()),
            format!("{}/{}", e.laps().len(), e.trials.len()),
            e.progress(),
            e.off_track(),
            e.crashes()
        );
    }
    std::fs::create_dir_all(&args.out).with_context(|| format!("creating {}", args.out.display()))?;
    let track = world.track(direction);
    let hz = SimConfig::default().control_hz;
    let mut sections = String::new();
    for (i, e) in entries.iter().enumerate() {
        let stem = format!("{}-{}", i + 1, file_safe(&e.name));
        let Some(t) = e.showcase() else { continue };
        let (points, speeds) = lap_path(t, hz);
        let lap_png = format!("{stem}-lap.png");
        if points.len() >= 2 {
            let bytes = tracks::render::render_png_speed(&track, &points, &speeds).map_err(anyhow::Error::msg)?;
            std::fs::write(args.out.join(&lap_png), bytes).with_context(|| format!("writing {lap_png}"))?;
        }
        let strip_png = format!("{stem}-camera.png");
        let has_strip = write_strip(&t.log.frames, &args.out.join(&strip_png))?;
        let what = match t.lap_time {
            Some(l) => format!("fastest lap {l:.2} s"),
            None => format!("no lap: {:.1} % before it ended ({})", t.progress, t.status.label()),
        };
        let (lo, hi) = speeds.iter().fold((f64::MAX, 0.0f64), |(a, b), v| (a.min(*v), b.max(*v)));
        let _ = write!(
            sections,
            "<section><h2>{}. {}</h2><p>{} &middot; {what} &middot; {:.2}–{:.2} m/s (blue slow, red fast) &middot; <code>{}</code></p>\n<img src=\"{lap_png}\" alt=\"{} on {}\">\n{}</section>\n",
            i + 1,
            html(&e.name),
            html(&e.network),
            if lo == f64::MAX { 0.0 } else { lo },
            hi,
            html(&e.source.display().to_string()),
            html(&e.name),
            html(&world.name),
            if has_strip {
                format!(
                    "<p>What its camera saw on that lap:</p>\n<img class=\"strip\" src=\"{strip_png}\" alt=\"camera frames\">\n"
                )
            } else {
                "<p>No camera frames: the model drives on the state vector.</p>\n".to_string()
            }
        );
    }
    let mut rows = String::new();
    for (i, e) in entries.iter().enumerate() {
        let _ = writeln!(
            rows,
            "<tr><td>{}</td><td>{}</td><td>{}</td><td>{}</td><td>{}/{}</td><td>{:.1} %</td><td>{}</td><td>{}</td></tr>",
            i + 1,
            html(&e.name),
            lap(e.best()),
            lap(e.mean()),
            e.laps().len(),
            e.trials.len(),
            e.progress(),
            e.off_track(),
            e.crashes()
        );
    }
    let page = format!(
        "<!doctype html>\n<html><head><meta charset=\"utf-8\"><title>Race on {w}</title>\n<style>body{{font-family:sans-serif;max-width:1000px;margin:2em auto}}table{{border-collapse:collapse}}td,th{{border:1px solid #ccc;padding:4px 10px;text-align:right}}td:nth-child(2){{text-align:left}}img{{max-width:100%}}img.strip{{image-rendering:pixelated}}</style></head><body>\n<h1>Race on {w} ({dir})</h1>\n<p>{n} trial(s) a model from the start line, the most likely action at every step; a car off the track is put back with {p} s added, a crash with {c} s, up to {r} times a trial.</p>\n<table><tr><th>rank</th><th>model</th><th>best lap</th><th>mean lap</th><th>laps</th><th>progress</th><th>off-track</th><th>crashes</th></tr>\n{rows}</table>\n{sections}</body></html>\n",
        w = html(&world.name),
        dir = if args.reversed { "reversed" } else { "forward" },
        n = args.trials,
        p = args.penalty,
        c = args.collision_penalty,
        r = args.resets,
    );
    let page_path = args.out.join("race.html");
    std::fs::write(&page_path, page).with_context(|| format!("writing {}", page_path.display()))?;
    println!(
        "\nwritten {} (leaderboard, each model's fastest lap on the track, its camera strip)",
        page_path.display()
    );
    Ok(entries
        .iter()
        .map(|e| Standing {
            name: e.name.clone(),
            best: e.best(),
            mean: e.mean(),
            laps: e.laps().len(),
            trials: e.trials.len(),
        })
        .collect())
}

/// The car's path over a trial and its speed at each point (m/s, from one step to the next;
/// the steps of a reset's pause and its jump back onto the track dropped).
fn lap_path(t: &TrialResult, hz: f64) -> (Vec<P2>, Vec<f64>) {
    let steps: Vec<&policy::StepTrace> =
        t.log.trace.iter().filter(|s| s.status != sim_agent::EpisodeStatus::Pause).collect();
    let points: Vec<P2> = steps.iter().map(|s| P2::new(s.x, s.y)).collect();
    let mut speeds: Vec<f64> = points.windows(2).map(|w| ((w[1] - w[0]).norm() * hz).min(5.0)).collect();
    if let Some(&last) = speeds.last() {
        speeds.push(last);
    }
    (points, speeds)
}

/// Up to [`STRIP`] frames spread over the lap, side by side, as a grey PNG; false when the
/// trial has none (a state-vector model).
fn write_strip(frames: &[policy::exchange::Frame], path: &Path) -> Result<bool> {
    let Some(first) = frames.first() else { return Ok(false) };
    let n = frames.len().min(STRIP);
    let (w, h) = (first.width as usize, first.height as usize);
    let mut img = image::GrayImage::new((w * n) as u32, h as u32);
    for k in 0..n {
        let f = &frames[k * frames.len() / n];
        if f.gray.len() != w * h {
            continue;
        }
        for y in 0..h {
            for x in 0..w {
                img.put_pixel((k * w + x) as u32, y as u32, image::Luma([f.gray[y * w + x]]));
            }
        }
    }
    img.save(path).with_context(|| format!("writing {}", path.display()))?;
    Ok(true)
}

fn file_safe(name: &str) -> String {
    name.chars().map(|c| if c.is_ascii_alphanumeric() || c == '-' || c == '_' { c } else { '_' }).collect()
}

fn html(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}
