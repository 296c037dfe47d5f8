//! Pictures Paddock draws itself, as SVG in the track's own coordinates (the browser scales
//! them): a track from its lines (the picker's tiles), and an evaluation's lap over it,
//! coloured by speed.

use std::fmt::Write as _;

const PAD: f64 = 0.3;

/// The track's bounds: `(x0, y0, x1, y1)` (m).
fn bounds(world: &tracks::World) -> (f64, f64, f64, f64) {
    let t = world.track(tracks::Direction::Forward);
    let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
    for p in t.inner().points().iter().chain(t.outer().points()) {
        x0 = x0.min(p.x);
        y0 = y0.min(p.y);
        x1 = x1.max(p.x);
        y1 = y1.max(p.y);
    }
    (x0, y0, x1, y1)
}

/// The function from track coordinates (m) to the pictures' (a live race's car is drawn over
/// the track's picture with it).
pub fn to_picture(world: &tracks::World) -> impl Fn(f64, f64) -> (f64, f64) + use<> {
    let (x0, _, _, y1) = bounds(world);
    // SVG's y grows downwards: flip it so the track reads as seen from above.
    move |x: f64, y: f64| (x - x0 + PAD, y1 - y + PAD)
}

/// The track's road (between its borders) and its centre line, with `over` drawn on top; `over`
/// gets the function from track coordinates (m) to the picture's.
fn drawing(world: &tracks::World, over: impl Fn(&dyn Fn(f64, f64) -> (f64, f64)) -> String) -> String {
    let t = world.track(tracks::Direction::Forward);
    let (x0, y0, x1, y1) = bounds(world);
    let pad = PAD;
    let at = to_picture(world);
    let path = |pts: &[tracks::P2]| -> String {
        let mut d = String::new();
        for (i, p) in pts.iter().enumerate() {
            let (x, y) = at(p.x, p.y);
            let _ = write!(d, "{}{x:.3},{y:.3}", if i == 0 { "M" } else { "L" });
        }
        d
    };
    format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" viewBox=\"0 0 {w:.3} {h:.3}\" role=\"img\" aria-label=\"{name}\">\
         <path d=\"{outer}Z{inner}Z\" fill=\"#555\" fill-rule=\"evenodd\" stroke=\"#fff\" stroke-width=\"0.05\"/>\
         <path d=\"{centre}\" fill=\"none\" stroke=\"#f5c400\" stroke-width=\"0.03\" stroke-dasharray=\"0.15 0.1\"/>{over}</svg>",
        w = x1 - x0 + 2.0 * pad,
        h = y1 - y0 + 2.0 * pad,
        name = world.name,
        outer = path(t.outer().points()),
        inner = path(t.inner().points()),
        centre = path(t.center().points()),
        over = over(&at),
    )
}

/// The track alone.
pub fn track_svg(world: &tracks::World) -> String {
    drawing(world, |_| String::new())
}

/// A lap over the track: each step's segment coloured by its value, from blue (the lap's
/// lowest) to red (its highest); `path` is `[x, y, value]` a step, `what` names the value.
pub fn lap_svg(world: &tracks::World, path: &[[f64; 3]], what: &str) -> String {
    drawing(world, |at| {
        let (lo, hi) = path.iter().fold((f64::MAX, f64::MIN), |(lo, hi), p| (lo.min(p[2]), hi.max(p[2])));
        let span = (hi - lo).max(1e-9);
        let mut out = String::new();
        for w in path.windows(2) {
            let f = ((w[1][2] - lo) / span).clamp(0.0, 1.0);
            let (r, b) = ((255.0 * f) as u8, (255.0 * (1.0 - f)) as u8);
            let (a, c) = (at(w[0][0], w[0][1]), at(w[1][0], w[1][1]));
            let _ = write!(
                out,
                "<line x1=\"{:.3}\" y1=\"{:.3}\" x2=\"{:.3}\" y2=\"{:.3}\" stroke=\"rgb({r},40,{b})\" stroke-width=\"0.06\" stroke-linecap=\"round\"/>",
                a.0, a.1, c.0, c.1
            );
        }
        if !path.is_empty() {
            let _ = write!(out, "<desc>{what} from {lo:.2} (blue) to {hi:.2} (red)</desc>");
        }
        out
    })
}
