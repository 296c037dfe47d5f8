//! A racing line (`coordinator tracks raceline`): the line of least curvature inside a
//! track's borders less a margin, found as the DeepRacer community's race-line notebooks find
//! it (Rémi Coulom's K1999 relaxation): sweep after sweep, each point moves along its
//! cross-section (the segment from its inner to its outer border point) to where its
//! curvature is the mean of its neighbours', kept within the margin, until the line stops
//! moving. Then the fastest speed along it for a car of given limits (a friction-limited
//! point mass: the grip caps the speed in turns, and the speed can only rise and fall as
//! fast as acceleration and braking allow), and its lap time.

use crate::P2;
use crate::npy::TrackRows;

/// Sweeps at most, and the largest move (m) of the last sweep that counts as settled.
const SWEEPS: usize = 4000;
const SETTLED: f64 = 1e-6;
/// Bisection steps for one point's place on its cross-section.
const BISECT: usize = 30;

/// Why no line fits.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum LineError {
    /// The road is narrower than the car and its margin somewhere.
    #[error(
        "at row {row} the track is {width:.3} m wide: no line keeps {margin:.3} m from both borders (it needs {needs:.3} m)"
    )]
    TooNarrow {
        /// The row.
        row: usize,
        /// Its width.
        width: f64,
        /// The margin asked.
        margin: f64,
        /// Twice the margin.
        needs: f64,
    },
    /// A margin that is not a distance.
    #[error("the margin must be a distance of 0 m or more, not {0}")]
    Margin(f64),
}

/// A line through a track: a point per row (the closing row's point repeated last on a loop).
#[derive(Clone, Debug, PartialEq)]
pub struct Line {
    /// The points.
    pub points: Vec<P2>,
    /// Where each point sits on its cross-section: 0 at the inner border, 1 at the outer.
    pub offsets: Vec<f64>,
    /// Whether the line is a loop.
    pub closed: bool,
}

/// The car's limits for the speed profile.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Limits {
    /// Top speed (m/s).
    pub top_speed: f64,
    /// Largest acceleration (m/s²).
    pub accel: f64,
    /// Largest deceleration (m/s²).
    pub brake: f64,
    /// Largest sideways acceleration in a turn (m/s²): the grip.
    pub lateral: f64,
}

impl Limits {
    /// A car of `top_speed` on a surface of friction `mu` (a friction-limited point mass).
    pub fn friction_limited(top_speed: f64, mu: f64) -> Limits {
        let g = 9.81 * mu;
        Limits { top_speed, accel: g, brake: g, lateral: g }
    }
}

/// The fastest speeds along a line, and its lap time.
#[derive(Clone, Debug, PartialEq)]
pub struct Profile {
    /// Speed at each point (m/s).
    pub speed: Vec<f64>,
    /// Seconds from each point to the next.
    pub dt: Vec<f64>,
    /// The line's length (m).
    pub length: f64,
    /// Seconds along the whole line.
    pub lap_time: f64,
}

/// The points of `rows` (repeated rows dropped) as cross-sections: inner and outer.
fn sections(rows: &TrackRows) -> (Vec<P2>, Vec<P2>, bool) {
    let rows = rows.sanitized();
    let closed = rows.is_closed();
    let n = if closed { rows.len() - 1 } else { rows.len() };
    (rows.inner[..n].to_vec(), rows.outer[..n].to_vec(), closed)
}

/// The centre line as a [`Line`] (each point halfway across).
pub fn centre_line(rows: &TrackRows) -> Line {
    let (inner, outer, closed) = sections(rows);
    let mut line = Line { points: Vec::new(), offsets: vec![0.5; inner.len()], closed };
    line.points = inner.iter().zip(&outer).map(|(a, b)| P2::from((a.coords + b.coords) / 2.0)).collect();
    close(&mut line);
    line
}

/// The line of least curvature through `rows`, every point at least `margin` m from both
/// borders (the car's half-width and room to spare).
pub fn race_line(rows: &TrackRows, margin: f64) -> Result<Line, LineError> {
    if !(margin.is_finite() && margin >= 0.0) {
        return Err(LineError::Margin(margin));
    }
    let (inner, outer, closed) = sections(rows);
    let n = inner.len();
    let mut bounds = Vec::with_capacity(n);
    for (row, (a, b)) in inner.iter().zip(&outer).enumerate() {
        let width = (b - a).norm();
        if width < 2.0 * margin + 1e-9 {
            return Err(LineError::TooNarrow { row, width, margin, needs: 2.0 * margin });
        }
        bounds.push((margin / width, 1.0 - margin / width));
    }
    let at = |i: usize, t: f64| P2::from(inner[i].coords + (outer[i].coords - inner[i].coords) * t);
    let mut t = vec![0.5; n];
    let mut p: Vec<P2> = (0..n).map(|i| at(i, 0.5)).collect();
    // A point's neighbours (an open line's ends stay where they are).
    let neighbours = |i: usize| -> Option<(usize, usize)> {
        if closed {
            Some(((i + n - 1) % n, (i + 1) % n))
        } else if i == 0 || i + 1 == n {
            None
        } else {
            Some((i - 1, i + 1))
        }
    };
    for _ in 0..SWEEPS {
        let mut moved = 0.0f64;
        for i in 0..n {
            let Some((a, b)) = neighbours(i) else { continue };
            let kappa_at = |j: usize, p: &[P2]| neighbours(j).map_or(0.0, |(x, y)| curvature(p[x], p[j], p[y]));
            let target = (kappa_at(a, &p) + kappa_at(b, &p)) / 2.0;
            // Curvature through the neighbours as the point crosses the road: bisect for the
            // target between the bounds, or stop at the bound nearer it.
            let f = |s: f64| curvature(p[a], at(i, s), p[b]) - target;
            let (lo, hi) = bounds[i];
            let (flo, fhi) = (f(lo), f(hi));
            let s = if flo.signum() == fhi.signum() {
                if flo.abs() < fhi.abs() { lo } else { hi }
            } else {
                let (mut x0, mut x1, mut f0) = (lo, hi, flo);
                for _ in 0..BISECT {
                    let mid = 0.5 * (x0 + x1);
                    let fm = f(mid);
                    if fm.signum() == f0.signum() {
                        x0 = mid;
                        f0 = fm;
                    } else {
                        x1 = mid;
                    }
                }
                0.5 * (x0 + x1)
            };
            let q = at(i, s);
            moved = moved.max((q - p[i]).norm());
            p[i] = q;
            t[i] = s;
        }
        if moved < SETTLED {
            break;
        }
    }
    let mut line = Line { points: p, offsets: t, closed };
    close(&mut line);
    Ok(line)
}

/// A loop's first point repeated last.
fn close(line: &mut Line) {
    if line.closed && !line.points.is_empty() {
        line.points.push(line.points[0]);
        line.offsets.push(line.offsets[0]);
    }
}

/// Signed curvature (1/m) of the circle through three points: positive turning left.
pub fn curvature(a: P2, b: P2, c: P2) -> f64 {
    let (ab, bc, ca) = (b - a, c - b, a - c);
    let cross = ab.perp(&bc);
    let d = ab.norm() * bc.norm() * ca.norm();
    if d <= 1e-15 { 0.0 } else { 2.0 * cross / d }
}

/// The fastest speeds along `points` (a loop when `closed`: the first point repeated last)
/// for a car of `limits`, and the time it takes. An open line starts from rest.
pub fn speed_profile(points: &[P2], closed: bool, limits: &Limits) -> Profile {
    let pts: &[P2] = if closed && points.len() > 1 { &points[..points.len() - 1] } else { points };
    let n = pts.len();
    if n < 2 {
        return Profile { speed: vec![0.0; points.len()], dt: vec![0.0; points.len()], length: 0.0, lap_time: 0.0 };
    }
    let next = |i: usize| if closed { (i + 1) % n } else { (i + 1).min(n - 1) };
    let ds: Vec<f64> = (0..n).map(|i| (pts[next(i)] - pts[i]).norm()).collect();
    // The grip's cap in the turns.
    let mut v: Vec<f64> = (0..n)
        .map(|i| {
            let k = if closed || (i > 0 && i + 1 < n) {
                curvature(pts[(i + n - 1) % n], pts[i], pts[(i + 1) % n]).abs()
            } else {
                0.0
            };
            if k > 1e-9 { (limits.lateral / k).sqrt().min(limits.top_speed) } else { limits.top_speed }
        })
        .collect();
    if !closed {
        v[0] = 0.0;
    }
    // Speed can rise only as fast as the car accelerates, and fall as fast as it brakes:
    // twice round a loop so the passes meet where it closes.
    let rounds = if closed { 2 } else { 1 };
    for _ in 0..rounds {
        for i in 0..n {
            let j = next(i);
            if j != i {
                v[j] = v[j].min((v[i] * v[i] + 2.0 * limits.accel * ds[i]).sqrt());
            }
        }
    }
    for _ in 0..rounds {
        for i in (0..n).rev() {
            let j = next(i);
            if j != i {
                v[i] = v[i].min((v[j] * v[j] + 2.0 * limits.brake * ds[i]).sqrt());
            }
        }
    }
    let steps = if closed { n } else { n - 1 };
    let mut dt = vec![0.0; points.len()];
    for i in 0..steps {
        let mean = 0.5 * (v[i] + v[next(i)]);
        dt[i] = if mean > 1e-9 { ds[i] / mean } else { f64::INFINITY };
    }
    let mut speed = v;
    if closed {
        speed.push(speed[0]);
    }
    Profile { length: ds[..steps].iter().sum(), lap_time: dt.iter().sum(), speed, dt }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::generate::{GenSpec, generate};

    /// A circle of radius `r`, width `w`, `n` rows, counter-clockwise.
    fn circle(r: f64, w: f64, n: usize) -> TrackRows {
        let at = |rad: f64, i: usize| {
            let a = std::f64::consts::TAU * (i % n) as f64 / n as f64;
            P2::new(rad * a.cos(), rad * a.sin())
        };
        TrackRows {
            center: (0..=n).map(|i| at(r, i)).collect(),
            inner: (0..=n).map(|i| at(r - w / 2.0, i)).collect(),
            outer: (0..=n).map(|i| at(r + w / 2.0, i)).collect(),
        }
    }

    /// Issue 34: on a circle the line is a circle and its time is the grip's.
    #[test]
    fn on_a_circle_the_line_is_a_circle_and_its_time_is_the_grips() {
        // Every point's curvature is its neighbours' mean already: the line stays a circle
        // (K1999 evens curvature out; it has nothing to even out here).
        let rows = circle(3.0, 1.0, 120);
        let line = race_line(&rows, 0.2).unwrap();
        let radii: Vec<f64> = line.points.iter().map(|p| p.coords.norm()).collect();
        let (lo, hi) = radii.iter().fold((f64::MAX, 0.0f64), |(a, b), r| (a.min(*r), b.max(*r)));
        assert!(hi - lo < 1e-6, "{lo}..{hi}");
        let limits = Limits::friction_limited(10.0, 0.5);
        let p = speed_profile(&line.points, true, &limits);
        let v = (limits.lateral * lo).sqrt();
        for s in &p.speed {
            assert!((s - v).abs() < 0.02 * v, "{s} against √(a·r) = {v}");
        }
        assert!((p.lap_time - p.length / v).abs() < 0.02 * p.lap_time);
    }

    /// Issue 34: the line cuts the corners and laps faster than the centre.
    #[test]
    fn the_line_cuts_the_corners_and_laps_faster_than_the_centre() {
        for seed in [1, 2, 3] {
            let rows = generate(&GenSpec { seed, length: 30.0, width: 1.07 }).unwrap();
            let margin = 0.15;
            let line = race_line(&rows, margin).unwrap();
            let centre = centre_line(&rows);
            let limits = Limits::friction_limited(4.0, 0.9);
            let (fast, slow) =
                (speed_profile(&line.points, true, &limits), speed_profile(&centre.points, true, &limits));
            assert!(
                fast.lap_time < slow.lap_time * 0.97,
                "seed {seed}: {} s against {} s",
                fast.lap_time,
                slow.lap_time
            );
            // Never outside the margin, and its largest curvature below the centre's.
            for (i, t) in line.offsets.iter().enumerate() {
                let w = (rows.outer[i] - rows.inner[i]).norm();
                assert!(*t >= margin / w - 1e-9 && *t <= 1.0 - margin / w + 1e-9, "seed {seed} row {i}: {t}");
            }
            let most = |l: &Line| {
                let n = l.points.len() - 1;
                (0..n)
                    .map(|i| curvature(l.points[(i + n - 1) % n], l.points[i], l.points[(i + 1) % n]).abs())
                    .fold(0.0, f64::max)
            };
            assert!(most(&line) < most(&centre), "seed {seed}");
        }
    }

    /// Issue 34: no line fits a road narrower than the margins.
    #[test]
    fn no_line_fits_a_road_narrower_than_the_margins() {
        let rows = circle(3.0, 0.25, 60);
        let e = race_line(&rows, 0.15).unwrap_err();
        assert!(matches!(e, LineError::TooNarrow { row: 0, .. }), "{e}");
        assert!(e.to_string().contains("no line keeps 0.150 m from both borders"), "{e}");
        assert_eq!(race_line(&rows, -1.0).unwrap_err(), LineError::Margin(-1.0));
    }
}
