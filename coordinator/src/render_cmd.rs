//! `coordinator render`: one camera frame as the car would see it, or a contact sheet of
//! several worlds side by side, so a person can look.

use crate::cli::RenderArgs;
use anyhow::{Context, Result, bail};
use sim_agent::camera::{HEIGHT, Renderer, View, WIDTH};
use tracks::Direction;

/// Write RGB frames side by side (`columns` per row) as a PNG.
fn write_png(frames: &[Vec<u8>], columns: usize, path: &std::path::Path) -> Result<()> {
    let rows = frames.len().div_ceil(columns);
    let (w, h) = (WIDTH as usize * columns.min(frames.len()), HEIGHT as usize * rows);
    let mut pix = tiny_skia::Pixmap::new(w as u32, h as u32).context("image size")?;
    let data = pix.data_mut();
    for (i, f) in frames.iter().enumerate() {
        let (cx, cy) = ((i % columns) * WIDTH as usize, (i / columns) * HEIGHT as usize);
        for y in 0..HEIGHT as usize {
            for x in 0..WIDTH as usize {
                let s = (y * WIDTH as usize + x) * 3;
                let d = ((cy + y) * w + cx + x) * 4;
                data[d..d + 3].copy_from_slice(&f[s..s + 3]);
                data[d + 3] = 255;
            }
        }
    }
    pix.save_png(path).with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}

pub fn render(args: RenderArgs) -> Result<i32> {
    let mut renderer = Renderer::new()?;
    let names: Vec<String> = if args.grid {
        if args.world.is_empty() {
            ["reinvent_base", "reinvent_carpet", "reinvent_concrete", "reinvent_wood"]
                .iter()
                .map(|s| s.to_string())
                .collect()
        } else {
            args.world.clone()
        }
    } else {
        vec![args.world.first().cloned().unwrap_or_else(|| "reinvent_base".into())]
    };
    let worlds = names.iter().map(|n| crate::tracks_cmd::resolve_world(n)).collect::<Result<Vec<_>>>()?;
    let tracks: Vec<tracks::Track> = worlds.iter().map(|w| w.track(Direction::Forward)).collect();
    let poses: Vec<[f64; 3]> = tracks
        .iter()
        .map(|t| match &args.pose {
            Some(p) => {
                let v: Vec<f64> = p
                    .split(',')
                    .map(|x| x.trim().parse::<f64>())
                    .collect::<Result<_, _>>()
                    .context("--pose x,y,heading (heading in degrees)")?;
                if v.len() != 3 {
                    bail!("--pose takes x,y,heading (heading in degrees), got {p}");
                }
                Ok([v[0], v[1], v[2].to_radians()])
            }
            None => {
                let (p, h) = t.pose_at(0.0);
                Ok([p.x, p.y, h])
            }
        })
        .collect::<Result<_>>()?;
    let views: Vec<View<'_>> = worlds
        .iter()
        .zip(&tracks)
        .zip(&poses)
        .map(|((w, t), p)| View {
            track: t,
            surface: w.surface,
            lighting: w.lighting,
            pose: *p,
            jitter: [0.0, 0.0],
            texture_seed: 0,
            objects: &[],
        })
        .collect();
    let rgb = renderer.render(&views, true);
    let frame = (WIDTH * HEIGHT * 3) as usize;
    let frames: Vec<Vec<u8>> = if args.rgb {
        rgb.chunks(frame).map(|c| c.to_vec()).collect()
    } else {
        // Grayscale as the policy sees it (DeepRacer's luma), drawn as grey RGB.
        rgb.chunks(frame)
            .map(|c| {
                c.chunks(3)
                    .flat_map(|p| {
                        let y = (0.2989 * p[0] as f32 + 0.5870 * p[1] as f32 + 0.1140 * p[2] as f32).round() as u8;
                        [y, y, y]
                    })
                    .collect()
            })
            .collect()
    };
    write_png(&frames, 4, &args.png)?;
    println!(
        "{} frame(s) of {WIDTH}x{HEIGHT} from {} on {}: {}",
        frames.len(),
        names.join(", "),
        renderer.adapter(),
        args.png.display()
    );
    Ok(0)
}
