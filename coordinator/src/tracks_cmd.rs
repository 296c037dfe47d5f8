//! `coordinator tracks …`: list, show, import and generate tracks, and racing lines.

use crate::cli::TracksCommand;
use anyhow::{Context, Result, bail};
use std::path::Path;
use tracks::{Direction, TrackSummary, World};

/// A built-in world by name, or a world made from a user's .npy file (default surface).
pub fn resolve_world(name: &str) -> Result<World> {
    let path = Path::new(name);
    if name.ends_with(".npy") || path.is_file() {
        let rows = tracks::load_npy(path)?;
        let stem = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_else(|| name.to_string());
        return Ok(World { name: stem, rows, surface: tracks::Surface::Asphalt, lighting: Default::default() });
    }
    Ok(tracks::world(name)?)
}

pub fn run(command: TracksCommand) -> Result<i32> {
    match command {
        TracksCommand::List { json } => {
            let worlds = tracks::worlds();
            if json {
                let rows: Vec<serde_json::Value> = worlds
                    .iter()
                    .map(|w| {
                        let s = TrackSummary::of(&w.name, &w.rows);
                        serde_json::json!({
                            "name": w.name, "length_m": s.length, "width_m": s.mean_width,
                            "min_width_m": s.min_width, "max_width_m": s.max_width,
                            "direction": s.direction, "surface": w.surface.name(), "friction": w.surface.friction(),
                        })
                    })
                    .collect();
                println!("{}", serde_json::to_string_pretty(&rows)?);
            } else {
                println!("{:<26} {:>10} {:>9} {:>9}  SURFACE", "NAME", "LENGTH m", "WIDTH m", "DIRECTION");
                for w in &worlds {
                    let s = TrackSummary::of(&w.name, &w.rows);
                    println!(
                        "{:<26} {:>10.3} {:>9.3} {:>9}  {}",
                        w.name,
                        s.length,
                        s.mean_width,
                        s.direction,
                        w.surface.name()
                    );
                }
            }
            Ok(0)
        }
        TracksCommand::Show { name, png } => {
            let world = resolve_world(&name)?;
            print_summary(&TrackSummary::of(&world.name, &world.rows));
            println!("surface      {} (friction {})", world.surface.name(), world.surface.friction());
            if let Some(png) = png {
                draw(&world, &png, &[], &[])?;
            }
            Ok(0)
        }
        TracksCommand::Import { file, name, png } => {
            let rows = tracks::load_npy(&file)?;
            let name =
                name.unwrap_or_else(|| file.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default());
            print_summary(&TrackSummary::of(&name, &rows));
            println!("valid: use it with --track {}", file.display());
            if let Some(png) = png {
                let world = World { name, rows, surface: tracks::Surface::Asphalt, lighting: Default::default() };
                draw(&world, &png, &[], &[])?;
            }
            Ok(0)
        }
        TracksCommand::Raceline { track, reversed, margin, surface, out, actions } => {
            raceline(&track, reversed, margin, surface.as_deref(), out, actions)
        }
        TracksCommand::Generate { seed, length, width, out, png } => {
            let rows = tracks::generate::generate(&tracks::generate::GenSpec { seed, length, width })?;
            let out = out.unwrap_or_else(|| format!("generated-{seed}.npy").into());
            std::fs::write(&out, rows.to_npy()).with_context(|| format!("writing {}", out.display()))?;
            let name = out.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
            print_summary(&TrackSummary::of(&name, &rows));
            println!(
                "written      {} (use it with --world {} or --track {})",
                out.display(),
                out.display(),
                out.display()
            );
            if let Some(png) = png {
                let world = World { name, rows, surface: tracks::Surface::Asphalt, lighting: Default::default() };
                draw(&world, &png, &[], &[])?;
            }
            Ok(0)
        }
    }
}

/// `tracks raceline`: the line, its speeds and lap time against the centre line's, the
/// action space it proposes, and its files.
fn raceline(
    name: &str,
    reversed: bool,
    margin: f64,
    surface: Option<&str>,
    out: Option<String>,
    actions: usize,
) -> Result<i32> {
    use tracks::raceline::{centre_line, race_line, speed_profile};
    if actions == 0 {
        bail!("--actions 0: the action space needs at least one action");
    }
    let world = resolve_world(name)?;
    let surface = match surface {
        None => world.surface,
        Some(s) => *tracks::Surface::ALL
            .iter()
            .find(|x| x.name() == s)
            .with_context(|| format!("--surface {s}: expected one of asphalt, carpet, concrete, wood"))?,
    };
    let direction = if reversed { Direction::Reversed } else { Direction::Forward };
    let track = world.track(direction);
    let limits = measured_limits(surface);
    let line = race_line(&world.rows, margin).with_context(|| format!("{}: the racing line", world.name))?;
    let centre = centre_line(&world.rows);
    // The line is the same either way round; the speeds are not (braking before a turn).
    let ordered = |pts: &[tracks::P2]| -> Vec<tracks::P2> {
        let mut v = pts.to_vec();
        if reversed {
            v.reverse();
        }
        v
    };
    let (points, centre_points) = (ordered(&line.points), ordered(&centre.points));
    let fast = speed_profile(&points, line.closed, &limits);
    let slow = speed_profile(&centre_points, centre.closed, &limits);
    println!(
        "track        {} ({}, {:.3} m), {} (friction {})",
        world.name,
        if track.is_ccw() { "ccw" } else { "cw" },
        track.length(),
        surface.name(),
        surface.friction()
    );
    println!(
        "the car      top speed {:.2} m/s, accelerating {:.1} m/s², braking {:.1} m/s², turning {:.1} m/s² (measured in the simulator on {})",
        limits.top_speed,
        limits.accel,
        limits.brake,
        limits.lateral,
        surface.name()
    );
    let (lo, hi) = fast.speed.iter().fold((f64::MAX, 0.0f64), |(a, b), v| (a.min(*v), b.max(*v)));
    println!("racing line  {:.3} m, {:.2} s a lap, {lo:.2}–{hi:.2} m/s", fast.length, fast.lap_time);
    println!("centre line  {:.3} m, {:.2} s a lap", slow.length, slow.lap_time);
    println!("line/centre  {:.3} of the centre line's time", fast.lap_time / slow.lap_time);
    let prefix = out.unwrap_or_else(|| format!("{}-raceline", world.name));
    let npy = format!("{prefix}.npy");
    std::fs::write(&npy, tracks::npy::points_to_npy(&points)).with_context(|| format!("writing {npy}"))?;
    let py = format!("{prefix}.py");
    let mut text = format!(
        "# The racing line of {} ({}), from `coordinator tracks raceline`: x, y (m), the fastest\n\
         # speed there on {} (m/s), and the seconds to the next point. Laps in {:.2} s, the\n\
         # centre line in {:.2} s.\nracing_track = [\n",
        world.name,
        if reversed { "reversed" } else { "forward" },
        surface.name(),
        fast.lap_time,
        slow.lap_time
    );
    for ((p, v), dt) in points.iter().zip(&fast.speed).zip(&fast.dt) {
        text.push_str(&format!("    [{:.5}, {:.5}, {:.4}, {:.5}],\n", p.x, p.y, v, dt));
    }
    text.push_str("]\n");
    std::fs::write(&py, text).with_context(|| format!("writing {py}"))?;
    let png = format!("{prefix}.png");
    let bytes = tracks::render::render_png_speed(&track, &points, &fast.speed).map_err(anyhow::Error::msg)?;
    std::fs::write(&png, bytes).with_context(|| format!("writing {png}"))?;
    let meta_path = format!("{prefix}.model_metadata.json");
    let meta = line_metadata(&sim_agent::race_line::LinePlan::from_profile(&points, line.closed, &fast), actions);
    std::fs::write(&meta_path, meta.to_json()).with_context(|| format!("writing {meta_path}"))?;
    if let policy::ActionSpace::Discrete(list) = &meta.action_space {
        let shown: Vec<String> = list.iter().map(|a| format!("{:+.1}° {:.2} m/s", a.steering_angle, a.speed)).collect();
        println!("actions      {}", shown.join(", "));
    }
    println!("written      {npy} (x, y), {py} (racing_track), {png} (coloured by speed: blue slow, red fast)");
    println!("             {meta_path} (the camera's model_metadata.json with the line's action space)");
    Ok(0)
}

/// DeepRacer's camera model_metadata.json with `actions` actions proposed by `plan`: its
/// steering and speeds, weighted by the time spent on them, within the console's ±30° and
/// 4 m/s.
fn line_metadata(plan: &sim_agent::race_line::LinePlan, actions: usize) -> policy::ModelMetadata {
    let mut meta = policy::ModelMetadata::default_camera();
    meta.action_space =
        policy::ActionSpace::Discrete(plan.action_space(&sim_agent::SimConfig::default().car, actions, 30.0, 4.0));
    meta
}

/// The car's limits on `surface`, as the simulator's own manoeuvres measure them.
fn measured_limits(surface: tracks::Surface) -> tracks::raceline::Limits {
    sim_agent::handling::limits(&sim_agent::SimConfig::default().car, surface)
}

fn print_summary(s: &TrackSummary) {
    println!("track        {}", s.name);
    println!("rows         {}", s.rows);
    println!("waypoints    {}", s.waypoints);
    println!("length       {:.3} m", s.length);
    println!("width        min {:.3} m, mean {:.3} m, max {:.3} m", s.min_width, s.mean_width, s.max_width);
    println!("closed       {}", if s.closed { "yes (loop)" } else { "no (open)" });
    println!("direction    {}", s.direction);
    if !s.repeated_rows.is_empty() {
        println!(
            "repeated     rows {:?} repeat the row before (dropped on load, as DeepRacer's simapp drops them)",
            s.repeated_rows
        );
    }
}

/// Draw a world top-down with an optional driven path.
pub fn draw(world: &World, png: &Path, path: &[tracks::P2], objects: &[([tracks::P2; 4], bool)]) -> Result<()> {
    let bytes =
        tracks::render::render_png(&world.track(Direction::Forward), path, objects).map_err(anyhow::Error::msg)?;
    std::fs::write(png, bytes).with_context(|| format!("writing {}", png.display()))?;
    println!("drawing      {}", png.display());
    Ok(())
}
