//! `coordinator tracks …`: list, show, import and generate tracks.

use crate::cli::TracksCommand;
use anyhow::{Context, Result};
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
