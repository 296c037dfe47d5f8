//! `coordinator report RUN_DIR` and `coordinator job report JOB`: a run folder's charts (SVG
//! and PNG, drawn with plotters) and one HTML page that puts them together with the job's
//! hyperparameters and figures. Everything comes from the run folder alone: DeepRacer's
//! metrics JSON and sim-trace (the learner's `record` module writes them), `metrics.jsonl`,
//! `evaluations.jsonl`, `summary.json`, `tracks.json` and `model_metadata.json`.
//!
//! Charts: reward and progress per training episode with their moving averages per world and
//! the best model marked (the console's training graph); evaluation progress and lap time per
//! checkpoint per world; the racing line of the best model's evaluation laps over the track,
//! coloured by speed; the mean reward along the track (a heat map on the centre line); and
//! how often each action was taken in the last iterations.

use anyhow::{Context, Result, bail};
use plotters::coord::Shift;
use plotters::prelude::*;
use policy::{ActionSpace, ModelMetadata, TrackLines};
use serde_json::Value;
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

/// Moving-average window of the training graph (episodes).
const WINDOW: usize = 50;
/// The last fraction of iterations the heat map and the action chart look at.
const RECENT: f64 = 0.25;

const PALETTE: [RGBColor; 6] = [
    RGBColor(31, 119, 180),
    RGBColor(255, 127, 14),
    RGBColor(44, 160, 44),
    RGBColor(214, 39, 40),
    RGBColor(148, 103, 189),
    RGBColor(140, 86, 75),
];

/// One training or evaluation episode from DeepRacer's metrics JSON.
#[derive(Clone, Debug)]
struct Episode {
    world: String,
    iteration: u64,
    reward: f64,
    progress: f64,
    /// It ended in a crash (obstacles, bots).
    crashed: bool,
}

/// One row of an evaluation's `evaluations.jsonl`.
#[derive(Clone, Debug)]
struct Evaluation {
    iteration: u64,
    /// world → (mean progress, mean lap time)
    worlds: BTreeMap<String, (f64, Option<f64>)>,
    best: bool,
    simtrace: BTreeMap<String, String>,
}

/// A sim-trace row, the columns the charts use.
#[derive(Clone, Debug)]
struct Row {
    episode: u64,
    x: f64,
    y: f64,
    throttle: f64,
    action: String,
    reward: f64,
    closest_waypoint: usize,
}

/// What the report reads from a run folder.
struct RunData {
    training: Vec<Episode>,
    evaluations: Vec<Evaluation>,
    tracks: Vec<TrackLines>,
    space: Option<ActionSpace>,
    summary: Value,
    hyper: Value,
}

fn read_json(path: &Path) -> Result<Value> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("{}: not JSON", path.display()))
}

fn read_lines(path: &Path) -> Result<Vec<Value>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    text.lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty())
        .map(|(i, l)| serde_json::from_str(l).with_context(|| format!("{}: line {}: not JSON", path.display(), i + 1)))
        .collect()
}

/// The sim-trace rows of one CSV file.
fn read_simtrace(path: &Path) -> Result<Vec<Row>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let mut lines = text.lines();
    let header = lines.next().unwrap_or_default();
    if header != policy::simtrace::HEADER {
        bail!("{}: line 1: not DeepRacer's 19-column sim-trace header", path.display());
    }
    let mut rows = Vec::new();
    for (i, l) in lines.enumerate() {
        let c: Vec<&str> = l.split(',').collect();
        let bad = || anyhow::anyhow!("{}: line {}: expected 19 sim-trace columns", path.display(), i + 2);
        if c.len() != 19 {
            return Err(bad());
        }
        let f = |k: usize| c[k].parse::<f64>().map_err(|_| bad());
        rows.push(Row {
            episode: c[0].parse().map_err(|_| bad())?,
            x: f(2)?,
            y: f(3)?,
            throttle: f(6)?,
            action: c[7].to_string(),
            reward: f(8)?,
            closest_waypoint: c[12].parse().map_err(|_| bad())?,
        });
    }
    Ok(rows)
}

impl RunData {
    fn load(run: &Path) -> Result<RunData> {
        if !run.join("metrics.jsonl").exists() {
            bail!("{}: not a run folder (no metrics.jsonl)", run.display());
        }
        let workers: Vec<String> = std::fs::read_to_string(run.join("metrics/workers.json"))
            .ok()
            .and_then(|t| serde_json::from_str(&t).ok())
            .unwrap_or_default();
        let mut training = Vec::new();
        for i in 0..workers.len().max(1) {
            let name = if i == 0 { "TrainingMetrics.json".into() } else { format!("TrainingMetrics_{i}.json") };
            let path = run.join("metrics").join(name);
            if !path.exists() {
                continue;
            }
            for m in read_json(&path)?["metrics"].as_array().cloned().unwrap_or_default() {
                if m["phase"] == "training" {
                    training.push(Episode {
                        world: m["world"].as_str().unwrap_or("?").to_string(),
                        iteration: m["paddock_iteration"].as_u64().unwrap_or(0),
                        reward: m["reward_score"].as_f64().unwrap_or(0.0),
                        progress: m["completion_percentage"].as_f64().unwrap_or(0.0),
                        crashed: m["episode_status"] == "Crashed",
                    });
                }
            }
        }
        training.sort_by_key(|e| e.iteration);
        let evaluations = if run.join("evaluations.jsonl").exists() {
            read_lines(&run.join("evaluations.jsonl"))?
                .into_iter()
                .map(|e| Evaluation {
                    iteration: e["iteration"].as_u64().unwrap_or(0),
                    worlds: e["worlds"]
                        .as_array()
                        .map(|ws| {
                            ws.iter()
                                .filter_map(|w| Some((w[0].as_str()?.to_string(), (w[1].as_f64()?, w[2].as_f64()))))
                                .collect()
                        })
                        .unwrap_or_default(),
                    best: e["best"].as_bool().unwrap_or(false),
                    simtrace: e["simtrace"]
                        .as_array()
                        .map(|ws| {
                            ws.iter()
                                .filter_map(|w| Some((w[0].as_str()?.to_string(), w[1].as_str()?.to_string())))
                                .collect()
                        })
                        .unwrap_or_default(),
                })
                .collect()
        } else {
            Vec::new()
        };
        let tracks: Vec<TrackLines> = match std::fs::read_to_string(run.join("tracks.json")) {
            Ok(t) => serde_json::from_str(&t)
                .with_context(|| format!("{}: not track lines", run.join("tracks.json").display()))?,
            Err(_) => Vec::new(),
        };
        let space = std::fs::read_to_string(run.join("model_metadata.json"))
            .ok()
            .and_then(|t| ModelMetadata::parse(&t, "model_metadata.json").ok())
            .map(|m| m.action_space);
        let summary = read_json(&run.join("summary.json")).unwrap_or(Value::Null);
        let hyper = read_json(&run.join("hyperparameters.json")).unwrap_or(Value::Null);
        Ok(RunData { training, evaluations, tracks, space, summary, hyper })
    }

    fn worlds(&self) -> Vec<String> {
        let mut w: Vec<String> = self.training.iter().map(|e| e.world.clone()).collect();
        w.extend(self.evaluations.iter().flat_map(|e| e.worlds.keys().cloned()));
        w.sort();
        w.dedup();
        w
    }

    /// The best model's evaluation (the last marked best).
    fn best(&self) -> Option<&Evaluation> {
        self.evaluations.iter().rev().find(|e| e.best)
    }

    /// The training sim-trace rows of the last iterations, per world (the metrics JSON says
    /// which world each worker's episode was on).
    fn recent_rows(&self, run: &Path) -> Result<BTreeMap<String, Vec<Row>>> {
        let last = self.training.last().map(|e| e.iteration).unwrap_or(0);
        let from = last.saturating_sub(((last as f64) * RECENT).ceil() as u64).max(1);
        let mut out: BTreeMap<String, Vec<Row>> = BTreeMap::new();
        for i in 0..16 {
            let dir = run.join(i.to_string()).join("training-simtrace");
            if !dir.is_dir() {
                continue;
            }
            let name = if i == 0 { "TrainingMetrics.json".into() } else { format!("TrainingMetrics_{i}.json") };
            let worlds: Vec<String> = read_json(&run.join("metrics").join(name))
                .ok()
                .and_then(|v| v["metrics"].as_array().cloned())
                .unwrap_or_default()
                .iter()
                .filter(|m| m["phase"] == "training")
                .map(|m| m["world"].as_str().unwrap_or("?").to_string())
                .collect();
            for it in from..=last {
                let file = dir.join(format!("{}-iteration.csv", it - 1));
                if !file.exists() {
                    continue;
                }
                for r in read_simtrace(&file)? {
                    let w = worlds.get(r.episode as usize).cloned().unwrap_or_else(|| "?".into());
                    out.entry(w).or_default().push(r);
                }
            }
        }
        Ok(out)
    }
}

/// Draw `chart` into `<dir>/<name>.svg` and `<dir>/<name>.png`.
macro_rules! both {
    ($dir:expr, $name:expr, $size:expr, $draw:expr) => {{
        let svg = $dir.join(format!("{}.svg", $name));
        let png = $dir.join(format!("{}.png", $name));
        {
            let root = SVGBackend::new(&svg, $size).into_drawing_area();
            $draw(&root).map_err(|e| anyhow::anyhow!("{}: {e}", svg.display()))?;
            root.present().map_err(|e| anyhow::anyhow!("{}: {e}", svg.display()))?;
        }
        {
            // Drawn into memory and encoded by `image` (plotters' own encoder would build a
            // second, older `image`).
            let (w, h): (u32, u32) = $size;
            let mut rgb = vec![0u8; (w * h * 3) as usize];
            {
                let root = BitMapBackend::with_buffer(&mut rgb, $size).into_drawing_area();
                $draw(&root).map_err(|e| anyhow::anyhow!("{}: {e}", png.display()))?;
                root.present().map_err(|e| anyhow::anyhow!("{}: {e}", png.display()))?;
            }
            image::save_buffer(&png, &rgb, w, h, image::ExtendedColorType::Rgb8)
                .map_err(|e| anyhow::anyhow!("{}: {e}", png.display()))?;
        }
        $name.to_string()
    }};
}

type Draw<DB> = std::result::Result<(), DrawingAreaErrorKind<<DB as DrawingBackend>::ErrorType>>;

fn moving_average(ys: &[f64], window: usize) -> Vec<f64> {
    let mut out = Vec::with_capacity(ys.len());
    let mut sum = 0.0;
    for i in 0..ys.len() {
        sum += ys[i];
        if i >= window {
            sum -= ys[i - window];
        }
        out.push(sum / (i + 1).min(window) as f64);
    }
    out
}

fn range(vals: impl Iterator<Item = f64>, pad: f64) -> (f64, f64) {
    let (lo, hi) = vals.fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), v| (a.min(v), b.max(v)));
    if !lo.is_finite() {
        return (0.0, 1.0);
    }
    let span = (hi - lo).max(1e-9);
    (lo - pad * span, hi + pad * span)
}

/// Per-episode values (`value` of each training episode) with their moving averages, per
/// world, on one axis of episodes trained on; the best model's iteration as a vertical line.
fn episodes_chart<DB: DrawingBackend>(
    root: &DrawingArea<DB, Shift>,
    data: &RunData,
    title: &str,
    y_desc: &str,
    value: fn(&Episode) -> f64,
    fixed: Option<(f64, f64)>,
) -> Draw<DB> {
    root.fill(&WHITE)?;
    let n = data.training.len().max(1);
    let (lo, hi) = fixed.unwrap_or_else(|| range(data.training.iter().map(value), 0.05));
    let mut chart = ChartBuilder::on(root)
        .caption(title, ("sans-serif", 22))
        .margin(14)
        .x_label_area_size(42)
        .y_label_area_size(64)
        .build_cartesian_2d(0f64..n as f64, lo..hi)?;
    chart
        .configure_mesh()
        .x_desc("episodes trained on")
        .x_label_formatter(&|v| format!("{v:.0}"))
        .y_desc(y_desc)
        .light_line_style(RGBColor(235, 235, 235))
        .draw()?;
    for (k, world) in data.worlds().iter().enumerate() {
        let color = PALETTE[k % PALETTE.len()];
        let pts: Vec<(f64, f64)> = data
            .training
            .iter()
            .enumerate()
            .filter(|(_, e)| &e.world == world)
            .map(|(i, e)| (i as f64, value(e)))
            .collect();
        if pts.is_empty() {
            continue;
        }
        chart.draw_series(pts.iter().map(|p| Circle::new(*p, 2, color.mix(0.25).filled())))?;
        let avg = moving_average(&pts.iter().map(|p| p.1).collect::<Vec<_>>(), WINDOW);
        chart
            .draw_series(LineSeries::new(pts.iter().zip(avg).map(|(p, a)| (p.0, a)), color.stroke_width(3)))?
            .label(format!("{world} ({WINDOW}-episode mean)"))
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(3)));
    }
    if let Some(best) = data.best() {
        let x = data.training.iter().filter(|e| e.iteration <= best.iteration).count() as f64;
        chart
            .draw_series(std::iter::once(PathElement::new(vec![(x, lo), (x, hi)], BLACK.stroke_width(2))))?
            .label(format!("best model (iteration {})", best.iteration))
            .legend(|(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], BLACK.stroke_width(2)));
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::LowerRight)
        .background_style(WHITE.mix(0.85))
        .border_style(RGBColor(200, 200, 200))
        .draw()?;
    Ok(())
}

/// Evaluation progress (top) and mean lap time (bottom) per checkpoint, per world.
fn evaluations_chart<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, data: &RunData) -> Draw<DB> {
    root.fill(&WHITE)?;
    let (top, bottom) = root.split_vertically(root.dim_in_pixel().1 / 2);
    let max_it = data.evaluations.iter().map(|e| e.iteration).max().unwrap_or(1).max(1) as f64;
    let mut chart = ChartBuilder::on(&top)
        .caption("Evaluation progress per checkpoint", ("sans-serif", 22))
        .margin(14)
        .x_label_area_size(36)
        .y_label_area_size(64)
        .build_cartesian_2d(0f64..max_it * 1.02, 0f64..105f64)?;
    chart
        .configure_mesh()
        .x_desc("iteration")
        .x_label_formatter(&|v| format!("{v:.0}"))
        .y_desc("mean progress %")
        .y_label_formatter(&|v| format!("{v:.0}"))
        .light_line_style(RGBColor(235, 235, 235))
        .draw()?;
    let laps: Vec<(f64, f64)> = data
        .evaluations
        .iter()
        .flat_map(|e| e.worlds.values().filter_map(move |(_, l)| l.map(|l| (e.iteration as f64, l))))
        .collect();
    let (llo, lhi) = range(laps.iter().map(|l| l.1), 0.1);
    let mut lap_chart = ChartBuilder::on(&bottom)
        .caption("Mean lap time per checkpoint (every trial completed)", ("sans-serif", 22))
        .margin(14)
        .x_label_area_size(42)
        .y_label_area_size(64)
        .build_cartesian_2d(0f64..max_it * 1.02, llo.max(0.0)..lhi)?;
    lap_chart
        .configure_mesh()
        .x_desc("iteration")
        .x_label_formatter(&|v| format!("{v:.0}"))
        .y_desc("lap time s")
        .light_line_style(RGBColor(235, 235, 235))
        .draw()?;
    for (k, world) in data.worlds().iter().enumerate() {
        let color = PALETTE[k % PALETTE.len()];
        let pts: Vec<(f64, f64)> =
            data.evaluations.iter().filter_map(|e| e.worlds.get(world).map(|w| (e.iteration as f64, w.0))).collect();
        chart
            .draw_series(LineSeries::new(pts.clone(), color.stroke_width(2)).point_size(3))?
            .label(world.clone())
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 18, y)], color.stroke_width(2)));
        let lp: Vec<(f64, f64)> = data
            .evaluations
            .iter()
            .filter_map(|e| e.worlds.get(world).and_then(|w| w.1).map(|l| (e.iteration as f64, l)))
            .collect();
        lap_chart.draw_series(lp.iter().map(|p| Circle::new(*p, 4, color.filled())))?;
    }
    if let Some(b) = data.best() {
        chart.draw_series(std::iter::once(PathElement::new(
            vec![(b.iteration as f64, 0.0), (b.iteration as f64, 105.0)],
            BLACK.stroke_width(1),
        )))?;
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::LowerRight)
        .background_style(WHITE.mix(0.85))
        .border_style(RGBColor(200, 200, 200))
        .draw()?;
    Ok(())
}

/// The square drawing box around a track (metres), with a margin.
fn track_box(t: &TrackLines) -> ((f64, f64), (f64, f64)) {
    let pts = t.outer.iter().chain(&t.inner).chain(&t.centre);
    let (x0, x1) = range(pts.clone().map(|p| p[0]), 0.04);
    let (y0, y1) = range(pts.map(|p| p[1]), 0.04);
    let side = (x1 - x0).max(y1 - y0);
    let (cx, cy) = ((x0 + x1) / 2.0, (y0 + y1) / 2.0);
    ((cx - side / 2.0, cx + side / 2.0), (cy - side / 2.0, cy + side / 2.0))
}

/// A chart in metres over a track's bounding box.
type TrackChart<'a, DB> =
    ChartContext<'a, DB, Cartesian2d<plotters::coord::types::RangedCoordf64, plotters::coord::types::RangedCoordf64>>;

fn track_chart<'a, DB: DrawingBackend>(
    root: &'a DrawingArea<DB, Shift>,
    t: &TrackLines,
    title: &str,
) -> std::result::Result<TrackChart<'a, DB>, DrawingAreaErrorKind<DB::ErrorType>> {
    root.fill(&WHITE)?;
    let ((x0, x1), (y0, y1)) = track_box(t);
    let mut chart = ChartBuilder::on(root)
        .caption(title, ("sans-serif", 20))
        .margin(14)
        .x_label_area_size(34)
        .y_label_area_size(48)
        .build_cartesian_2d(x0..x1, y0..y1)?;
    chart.configure_mesh().x_desc("x m").y_desc("y m").disable_mesh().draw()?;
    // The road, then its borders.
    let grey = RGBColor(90, 90, 90);
    for line in [&t.outer, &t.inner] {
        chart.draw_series(LineSeries::new(line.iter().map(|p| (p[0], p[1])), grey.stroke_width(2)))?;
    }
    chart
        .draw_series(LineSeries::new(t.centre.iter().map(|p| (p[0], p[1])), RGBColor(200, 200, 200).stroke_width(1)))?;
    Ok(chart)
}

/// A colour for `v` in [0, 1] (viridis).
fn heat(v: f64) -> RGBColor {
    ViridisRGB::get_color(v.clamp(0.0, 1.0))
}

/// The best model's evaluation laps over the track, coloured by commanded speed.
fn racing_line<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, t: &TrackLines, rows: &[Row], best: u64) -> Draw<DB> {
    let mut chart =
        track_chart(root, t, &format!("{}: best model (iteration {best}), evaluation laps, colour = speed", t.world))?;
    let (lo, hi) = range(rows.iter().map(|r| r.throttle), 0.0);
    let mut by_trial: BTreeMap<u64, Vec<&Row>> = BTreeMap::new();
    for r in rows {
        by_trial.entry(r.episode).or_default().push(r);
    }
    for trial in by_trial.values() {
        chart.draw_series(trial.windows(2).map(|w| {
            let c = heat((w[1].throttle - lo) / (hi - lo).max(1e-9));
            PathElement::new(vec![(w[0].x, w[0].y), (w[1].x, w[1].y)], c.stroke_width(3))
        }))?;
    }
    legend_bar(root, &format!("speed {lo:.2}"), &format!("{hi:.2} m/s"))
}

/// A colour bar with its two ends labelled, in the top-right corner.
fn legend_bar<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, lo: &str, hi: &str) -> Draw<DB> {
    let (w, _) = root.dim_in_pixel();
    let (x0, y0) = (w as i32 - 230, 44);
    for i in 0..100 {
        root.draw(&Rectangle::new([(x0 + i, y0), (x0 + i + 1, y0 + 12)], heat(i as f64 / 99.0).filled()))?;
    }
    let style = ("sans-serif", 14).into_font().color(&BLACK);
    root.draw(&Text::new(lo.to_string(), (x0 - 4 - 7 * lo.len() as i32, y0 - 1), style.clone()))?;
    root.draw(&Text::new(hi.to_string(), (x0 + 106, y0 - 1), style))?;
    Ok(())
}

/// Mean reward per waypoint of the last iterations, on the centre line.
fn reward_heatmap<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, t: &TrackLines, rows: &[Row]) -> Draw<DB> {
    let mut chart = track_chart(
        root,
        t,
        &format!("{}: mean reward per waypoint, last {:.0} % of iterations", t.world, RECENT * 100.0),
    )?;
    let n = t.centre.len();
    let mut sum = vec![0.0; n];
    let mut count = vec![0usize; n];
    for r in rows.iter().filter(|r| r.closest_waypoint < n) {
        sum[r.closest_waypoint] += r.reward;
        count[r.closest_waypoint] += 1;
    }
    let mean: Vec<Option<f64>> = sum.iter().zip(&count).map(|(s, &c)| (c > 0).then(|| s / c as f64)).collect();
    let (lo, hi) = range(mean.iter().flatten().copied(), 0.0);
    chart.draw_series((0..n.saturating_sub(1)).filter_map(|i| {
        let m = mean[i]?;
        let c = heat((m - lo) / (hi - lo).max(1e-9));
        Some(PathElement::new(
            vec![(t.centre[i][0], t.centre[i][1]), (t.centre[i + 1][0], t.centre[i + 1][1])],
            c.stroke_width(9),
        ))
    }))?;
    legend_bar(root, &format!("reward {lo:.2}"), &format!("{hi:.2}"))
}

/// How often each action was taken in the last iterations.
fn actions_chart<DB: DrawingBackend>(root: &DrawingArea<DB, Shift>, counts: &[(String, u64)]) -> Draw<DB> {
    root.fill(&WHITE)?;
    let total: u64 = counts.iter().map(|c| c.1).sum::<u64>().max(1);
    let max = counts.iter().map(|c| c.1 as f64 / total as f64 * 100.0).fold(1.0, f64::max);
    let labels: Vec<String> = counts.iter().map(|c| c.0.clone()).collect();
    let n = counts.len().max(1);
    let mut chart = ChartBuilder::on(root)
        .caption(format!("Actions taken, last {:.0} % of iterations", RECENT * 100.0), ("sans-serif", 22))
        .margin(14)
        .x_label_area_size(50)
        .y_label_area_size(64)
        .build_cartesian_2d(-0.5f64..n as f64 - 0.5, 0f64..max * 1.1)?;
    chart
        .configure_mesh()
        .disable_x_mesh()
        .x_labels(n + 1)
        .x_label_formatter(&|v| {
            let i = v.round();
            if (v - i).abs() < 1e-6 && i >= 0.0 {
                labels.get(i as usize).cloned().unwrap_or_default()
            } else {
                String::new()
            }
        })
        .x_label_style(("sans-serif", 12))
        .x_desc("action (steering °, speed m/s)")
        .y_desc("% of steps")
        .y_label_formatter(&|v| format!("{v:.0}"))
        .light_line_style(RGBColor(235, 235, 235))
        .draw()?;
    chart.draw_series(counts.iter().enumerate().map(|(i, c)| {
        let v = c.1 as f64 / total as f64 * 100.0;
        Rectangle::new([(i as f64 - 0.38, 0.0), (i as f64 + 0.38, v)], PALETTE[0].mix(0.85).filled())
    }))?;
    Ok(())
}

/// Write the report of run folder `run` into `out` (default `<run>/report`); returns the HTML page.
pub fn write(run: &Path, out: Option<&Path>, title: &str) -> Result<PathBuf> {
    let _ = plotters::style::register_font("sans-serif", FontStyle::Normal, dejavu::sans::regular());
    let data = RunData::load(run)?;
    let dir = out.map(Path::to_path_buf).unwrap_or_else(|| run.join("report"));
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    let mut charts: Vec<(String, String)> = Vec::new();
    if !data.training.is_empty() {
        let n = both!(dir, "reward", (1000, 520), |r| episodes_chart(
            r,
            &data,
            "Reward per training episode",
            "episode reward",
            |e| e.reward,
            None
        ));
        charts.push((n, "Reward per training episode (dots) and its moving average per world; the black line marks the iteration of the best model.".into()));
        let n = both!(dir, "progress", (1000, 520), |r| episodes_chart(
            r,
            &data,
            "Progress per training episode",
            "progress %",
            |e| e.progress,
            Some((0.0, 105.0))
        ));
        charts.push((n, "Track completion per training episode and its moving average per world.".into()));
    }
    if !data.evaluations.is_empty() {
        let n = both!(dir, "evaluations", (1000, 720), |r| evaluations_chart(r, &data));
        charts.push((n, "Every checkpoint's evaluation (trials from the start line, most likely action): mean progress and, where every trial finished, mean lap time.".into()));
    }
    let recent = data.recent_rows(run)?;
    for t in &data.tracks {
        let slug = t.world.replace(|c: char| !c.is_ascii_alphanumeric() && c != '_', "-");
        if let Some(best) = data.best()
            && let Some(folder) = best.simtrace.get(&t.world)
        {
            let rows = read_simtrace(&run.join(folder).join("evaluation-simtrace").join("0-iteration.csv"))?;
            if !rows.is_empty() {
                let n =
                    both!(dir, format!("racing-line-{slug}"), (820, 820), |r| racing_line(r, t, &rows, best.iteration));
                charts
                    .push((n, format!("{}: the best model's evaluation laps, coloured by commanded speed.", t.world)));
            }
        }
        if let Some(rows) = recent.get(&t.world).filter(|r| !r.is_empty()) {
            let n = both!(dir, format!("reward-map-{slug}"), (820, 820), |r| reward_heatmap(r, t, rows));
            charts.push((n, format!("{}: where the reward is earned (mean reward per waypoint).", t.world)));
        }
    }
    let mut counts: BTreeMap<String, u64> = BTreeMap::new();
    for r in recent.values().flatten() {
        *counts.entry(r.action.clone()).or_default() += 1;
    }
    if !counts.is_empty() {
        let mut list: Vec<(String, u64)> = counts.into_iter().collect();
        let label = |a: &str| match (&data.space, a.parse::<usize>()) {
            (Some(ActionSpace::Discrete(acts)), Ok(i)) if i < acts.len() => {
                format!("{i}: {:.0}°, {:.2}", acts[i].steering_angle, acts[i].speed)
            }
            _ => a.to_string(),
        };
        if matches!(data.space, Some(ActionSpace::Discrete(_))) {
            list.sort_by_key(|(a, _)| a.parse::<usize>().unwrap_or(usize::MAX));
            list = list.into_iter().map(|(a, c)| (label(&a), c)).collect();
            let n = both!(dir, "actions", (1000, 520), |r| actions_chart(r, &list));
            charts.push((n, "How often the policy chose each action (the model's action space).".into()));
        }
    }
    let page = dir.join("index.html");
    std::fs::write(&page, html(title, &data, &charts)).with_context(|| format!("writing {}", page.display()))?;
    Ok(page)
}

fn esc(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;")
}

fn html(title: &str, data: &RunData, charts: &[(String, String)]) -> String {
    let mut h = String::new();
    let _ = write!(
        h,
        "<!doctype html><html><head><meta charset=\"utf-8\"><title>{t}</title><style>\
         body{{font-family:sans-serif;max-width:1040px;margin:24px auto;color:#222}}\
         table{{border-collapse:collapse;margin:8px 0 24px}}td,th{{border:1px solid #ddd;padding:4px 10px;text-align:left}}\
         figure{{margin:0 0 28px}}img{{max-width:100%;border:1px solid #eee}}figcaption{{color:#555}}\
         </style></head><body><h1>{t}</h1>",
        t = esc(title)
    );
    let s = &data.summary;
    let fig = |k: &str| s.get(k).map(|v| v.to_string()).unwrap_or_else(|| "-".into());
    let _ = write!(h, "<h2>Figures</h2><table>");
    for (name, key) in [
        ("worlds", "worlds"),
        ("stopped because", "stop_reason"),
        ("iterations", "iterations"),
        ("episodes trained on", "episodes"),
        ("episodes received", "episodes_received"),
        ("dropped as stale", "dropped_stale"),
        ("environment steps", "env_steps"),
        ("seconds", "seconds"),
        ("final policy version", "policy_version"),
    ] {
        let _ = write!(h, "<tr><th>{name}</th><td>{}</td></tr>", esc(fig(key).trim_matches('"')));
    }
    if data.training.iter().any(|e| e.crashed) {
        let per_world: Vec<String> = data
            .worlds()
            .iter()
            .map(|w| {
                let eps: Vec<&Episode> = data.training.iter().filter(|e| &e.world == w).collect();
                format!("{w}: {} of {}", eps.iter().filter(|e| e.crashed).count(), eps.len())
            })
            .collect();
        let _ = write!(h, "<tr><th>training episodes crashed</th><td>{}</td></tr>", esc(&per_world.join("; ")));
    }
    if let Some(b) = data.best() {
        let worlds: Vec<String> = b
            .worlds
            .iter()
            .map(|(w, (p, l))| format!("{w}: {p:.1} %{}", l.map(|l| format!(", lap {l:.2} s")).unwrap_or_default()))
            .collect();
        let _ =
            write!(h, "<tr><th>best model</th><td>iteration {}: {}</td></tr>", b.iteration, esc(&worlds.join("; ")));
    }
    if let Some(t) = data.summary.get("trend").and_then(|t| t.as_str()).filter(|t| !t.is_empty()) {
        let _ = write!(h, "<tr><th>when to stop</th><td>{}</td></tr>", esc(t));
    }
    let _ = write!(h, "</table>");
    for (name, caption) in charts {
        let _ = write!(
            h,
            "<figure><img src=\"{name}.svg\" alt=\"{c}\"><figcaption>{c} (<a href=\"{name}.png\">PNG</a>)</figcaption></figure>",
            c = esc(caption)
        );
    }
    let _ = write!(h, "<h2>Hyperparameters</h2><table>");
    if let Some(o) = data.hyper.as_object() {
        for (k, v) in o {
            let _ = write!(h, "<tr><th>{}</th><td>{}</td></tr>", esc(k), esc(&v.to_string()));
        }
    }
    let _ = writeln!(h, "</table></body></html>");
    h
}
