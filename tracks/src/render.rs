//! Top-down drawings of a track (PNG): road, borders, centre line, start line and the
//! direction of travel, optionally with a driven path and a race's objects on top, or a
//! racing line coloured by speed.

use crate::geometry::{P2, Track};
use tiny_skia::{Color, FillRule, Paint, PathBuilder, Pixmap, Stroke, StrokeDash, Transform};

/// Pixels per metre of the drawing.
const SCALE: f32 = 80.0;
/// Border around the track (m).
const PAD: f64 = 0.5;

/// Draw `track` top-down; `path` (if not empty) is drawn over it in light blue, and each of
/// `objects` (footprint corners, and whether it is a car) filled: boxes brown, cars black.
/// Returns PNG bytes.
pub fn render_png(track: &Track, path: &[P2], objects: &[([P2; 4], bool)]) -> Result<Vec<u8>, String> {
    render(track, path, None, objects)
}

/// Draw `track` top-down with `line` over it, each stretch coloured by its `speed` (one a
/// point): blue the slowest, through green and yellow, to red the fastest. Returns PNG bytes.
pub fn render_png_speed(track: &Track, line: &[P2], speed: &[f64]) -> Result<Vec<u8>, String> {
    if speed.len() != line.len() {
        return Err(format!("{} speeds for {} points", speed.len(), line.len()));
    }
    render(track, line, Some(speed), &[])
}

/// The colour of `x` in 0..1: blue, cyan, green, yellow, red.
fn heat(x: f64) -> (u8, u8, u8) {
    let x = x.clamp(0.0, 1.0) * 4.0;
    let (r, g, b) = match x as u32 {
        0 => (0.0, x, 1.0),
        1 => (0.0, 1.0, 2.0 - x),
        2 => (x - 2.0, 1.0, 0.0),
        _ => (1.0, (4.0 - x).max(0.0), 0.0),
    };
    ((r * 255.0) as u8, (g * 255.0) as u8, (b * 255.0) as u8)
}

fn render(track: &Track, path: &[P2], speed: Option<&[f64]>, objects: &[([P2; 4], bool)]) -> Result<Vec<u8>, String> {
    let pts = track.inner().points().iter().chain(track.outer().points());
    let (mut lo, mut hi) = (P2::new(f64::MAX, f64::MAX), P2::new(f64::MIN, f64::MIN));
    for p in pts {
        lo = lo.inf(p);
        hi = hi.sup(p);
    }
    let w = ((hi.x - lo.x + 2.0 * PAD) as f32 * SCALE).ceil() as u32;
    let h = ((hi.y - lo.y + 2.0 * PAD) as f32 * SCALE).ceil() as u32;
    let mut pix = Pixmap::new(w.max(1), h.max(1)).ok_or("drawing too large")?;
    pix.fill(Color::from_rgba8(46, 125, 50, 255));
    // World (x right, y up) to image (x right, y down).
    let to_px = |p: &P2| ((p.x - lo.x + PAD) as f32 * SCALE, (hi.y - p.y + PAD) as f32 * SCALE);
    let line = |points: &[P2], close: bool| {
        let mut pb = PathBuilder::new();
        for (i, p) in points.iter().enumerate() {
            let (x, y) = to_px(p);
            if i == 0 { pb.move_to(x, y) } else { pb.line_to(x, y) }
        }
        if close {
            pb.close();
        }
        pb.finish()
    };
    let paint = |r, g, b| {
        let mut p = Paint::default();
        p.set_color_rgba8(r, g, b, 255);
        p.anti_alias = true;
        p
    };
    let id = Transform::identity();

    // Road: the polygon between the borders (even-odd: the inner ring is a hole).
    let mut pb = PathBuilder::new();
    if track.is_closed() {
        for ring in [track.outer().points(), track.inner().points()] {
            for (i, p) in ring.iter().enumerate() {
                let (x, y) = to_px(p);
                if i == 0 { pb.move_to(x, y) } else { pb.line_to(x, y) }
            }
            pb.close();
        }
    } else {
        let ring: Vec<&P2> = track.outer().points().iter().chain(track.inner().points().iter().rev()).collect();
        for (i, p) in ring.into_iter().enumerate() {
            let (x, y) = to_px(p);
            if i == 0 { pb.move_to(x, y) } else { pb.line_to(x, y) }
        }
        pb.close();
    }
    if let Some(road) = pb.finish() {
        pix.fill_path(&road, &paint(60, 60, 64), FillRule::EvenOdd, id, None);
    }
    let border = Stroke { width: 0.05 * SCALE, ..Stroke::default() };
    for b in [track.inner().points(), track.outer().points()] {
        if let Some(p) = line(b, false) {
            pix.stroke_path(&p, &paint(255, 255, 255), &border, id, None);
        }
    }
    let dashed = Stroke {
        width: 0.025 * SCALE,
        dash: StrokeDash::new(vec![0.15 * SCALE, 0.15 * SCALE], 0.0),
        ..Stroke::default()
    };
    if let Some(p) = line(track.waypoints(), false) {
        pix.stroke_path(&p, &paint(255, 214, 0), &dashed, id, None);
    }
    // Start line across the road at waypoint 0, and an arrow along the direction of travel.
    let start = [track.inner().points()[0], track.outer().points()[0]];
    if let Some(p) = line(&start, false) {
        pix.stroke_path(&p, &paint(230, 30, 30), &Stroke { width: 0.06 * SCALE, ..Stroke::default() }, id, None);
    }
    let (origin, heading) = track.pose_at(0.0);
    let ahead = |d: f64, side: f64| {
        P2::new(
            origin.x + d * heading.cos() - side * heading.sin(),
            origin.y + d * heading.sin() + side * heading.cos(),
        )
    };
    let arrow = [ahead(0.1, 0.0), ahead(0.6, 0.0), ahead(0.45, 0.12), ahead(0.6, 0.0), ahead(0.45, -0.12)];
    if let Some(p) = line(&arrow, false) {
        pix.stroke_path(&p, &paint(30, 30, 230), &Stroke { width: 0.05 * SCALE, ..Stroke::default() }, id, None);
    }
    for (corners, car) in objects {
        if let Some(p) = line(corners, true) {
            let fill = if *car { paint(15, 15, 18) } else { paint(123, 97, 79) };
            pix.fill_path(&p, &fill, FillRule::Winding, id, None);
        }
    }
    match speed {
        Some(speed) if path.len() > 1 => {
            let (lo, hi) = speed.iter().fold((f64::MAX, f64::MIN), |(a, b), v| (a.min(*v), b.max(*v)));
            let stroke = Stroke { width: 0.06 * SCALE, line_cap: tiny_skia::LineCap::Round, ..Stroke::default() };
            for (w, v) in path.windows(2).zip(speed) {
                let (r, g, b) = heat(if hi > lo { (v - lo) / (hi - lo) } else { 1.0 });
                if let Some(p) = line(w, false) {
                    pix.stroke_path(&p, &paint(r, g, b), &stroke, id, None);
                }
            }
        }
        _ => {
            if path.len() > 1
                && let Some(p) = line(path, false)
            {
                pix.stroke_path(
                    &p,
                    &paint(0, 200, 255),
                    &Stroke { width: 0.02 * SCALE, ..Stroke::default() },
                    id,
                    None,
                );
            }
        }
    }
    pix.encode_png().map_err(|e| format!("PNG encoding failed: {e}"))
}
