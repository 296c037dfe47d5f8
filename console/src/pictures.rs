//! Pictures Paddock draws itself: a track as SVG from its own lines (the picker's tiles and
//! the model page), in the track's coordinates, so the browser scales it.

use std::fmt::Write as _;

/// The track's road (between its borders) and its centre line, as an SVG document.
pub fn track_svg(world: &tracks::World) -> String {
    let t = world.track(tracks::Direction::Forward);
    let all: Vec<_> = t.inner().points().iter().chain(t.outer().points()).copied().collect();
    let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
    for p in &all {
        x0 = x0.min(p.x);
        y0 = y0.min(p.y);
        x1 = x1.max(p.x);
        y1 = y1.max(p.y);
    }
    let pad = 0.3;
    // SVG's y grows downwards: flip it so the track reads as seen from above.
    let path = |pts: &[tracks::P2]| -> String {
        let mut d = String::new();
        for (i, p) in pts.iter().enumerate() {
            let _ = write!(d, "{}{:.3},{:.3}", if i == 0 { "M" } else { "L" }, p.x - x0 + pad, y1 - p.y + pad);
        }
        d
    };
    format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" viewBox=\"0 0 {w:.3} {h:.3}\" role=\"img\" aria-label=\"{name}\">\
         <path d=\"{outer}Z{inner}Z\" fill=\"#555\" fill-rule=\"evenodd\" stroke=\"#fff\" stroke-width=\"0.05\"/>\
         <path d=\"{centre}\" fill=\"none\" stroke=\"#f5c400\" stroke-width=\"0.03\" stroke-dasharray=\"0.15 0.1\"/></svg>",
        w = x1 - x0 + 2.0 * pad,
        h = y1 - y0 + 2.0 * pad,
        name = world.name,
        outer = path(t.outer().points()),
        inner = path(t.inner().points()),
        centre = path(t.center().points()),
    )
}
