//! Random closed tracks (`coordinator tracks generate`): a smooth loop of the asked length
//! and width that DeepRacer's `.npy` format holds and the car can drive. The centre line is a
//! star-shaped curve around the origin, `r(θ) = R·(1 + Σ aₖ·cos(kθ + φₖ))` for k = 2..5 with
//! random amplitudes and phases, so it never crosses itself; it is scaled to the length and
//! accepted only when every turn is wide enough (at the centre line, half the width and a
//! margin, so the inner border never folds into a point, and the car's tightest turn at full
//! lock and a margin, so the car can drive it: hairpins as tight as the catalog's) and no two
//! far parts of the loop come closer than the width and a gap (so the borders never touch). A draw that fails is
//! replaced by the next, with smaller amplitudes as the draws go on; a request no loop can
//! meet (too short to close with turns that wide) is refused before any draw.

use crate::P2;
use crate::npy::{TrackRows, validate_rows};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::f64::consts::PI;

/// The car's tightest turn: the centre's radius at full lock (wheelbase 0.164 m, 30°), m.
pub const CAR_MIN_RADIUS: f64 = 0.284;
/// Room kept beyond the car's tightest turn, and inside the inner border's turns, m.
const TURN_MARGIN: f64 = 0.15;
/// Room kept between the borders of two far parts of the loop, m.
const GAP: f64 = 0.3;
/// Waypoint spacing along the centre line, about (DeepRacer's tracks: 0.3–0.6 m), m.
const SPACING: f64 = 0.4;
/// Draws tried before a request is given up.
const DRAWS: u32 = 400;
/// The first draw's largest amplitude of the second harmonic (the k-th's is this / (k − 1)):
/// large enough that most tracks have turns both ways and turns near the tightest allowed.
const BOLDNESS: f64 = 0.7;

/// What to generate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GenSpec {
    /// Seed of the draws: the same seed gives the same track.
    pub seed: u64,
    /// Centre-line length, m.
    pub length: f64,
    /// Width between the borders, m.
    pub width: f64,
}

/// Why a request cannot be met.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum GenError {
    /// A length or width out of range.
    #[error("{what} must be {expected}, not {value}")]
    Range {
        /// Which setting.
        what: &'static str,
        /// What was asked.
        value: f64,
        /// What it must be.
        expected: &'static str,
    },
    /// No loop of that length has turns wide enough for that width.
    #[error(
        "a loop of {length} m cannot close with turns the car can take on a track {width} m wide: its tightest turn (radius {radius:.2} m at the centre line) needs at least {shortest:.1} m of length"
    )]
    TooShort {
        /// Asked length.
        length: f64,
        /// Asked width.
        width: f64,
        /// The tightest centre-line radius allowed.
        radius: f64,
        /// The shortest loop at that radius (a circle).
        shortest: f64,
    },
    /// Every draw failed the checks.
    #[error("no track of {length} m and {width} m width passed the checks in {draws} draws (seed {seed})")]
    NoDraw {
        /// Asked length.
        length: f64,
        /// Asked width.
        width: f64,
        /// Draws tried.
        draws: u32,
        /// The seed.
        seed: u64,
    },
}

impl GenSpec {
    /// The tightest centre-line radius a track of this width allows.
    pub fn min_radius(&self) -> f64 {
        CAR_MIN_RADIUS.max(self.width / 2.0) + TURN_MARGIN
    }
}

/// A random closed track for `spec`: rows of a DeepRacer `.npy` file (the first row repeated
/// last), counter-clockwise, the inner border on the left.
pub fn generate(spec: &GenSpec) -> Result<TrackRows, GenError> {
    let range = |what, value: f64, lo: f64, hi: f64, expected| {
        if value.is_finite() && value >= lo && value <= hi {
            Ok(())
        } else {
            Err(GenError::Range { what, value, expected })
        }
    };
    range("--width", spec.width, 0.3, 3.0, "between 0.3 and 3 m")?;
    range("--length", spec.length, 5.0, 500.0, "between 5 and 500 m")?;
    let radius = spec.min_radius();
    let shortest = 2.0 * PI * radius;
    if spec.length < shortest * 1.05 {
        return Err(GenError::TooShort { length: spec.length, width: spec.width, radius, shortest: shortest * 1.05 });
    }
    let mut rng = ChaCha8Rng::seed_from_u64(spec.seed);
    for draw in 0..DRAWS {
        // Bold shapes first (pinches that turn the other way, turns near the car's tightest),
        // rounder as the draws go on: the last ones are nearly circles.
        let scale = BOLDNESS * (1.0 - draw as f64 / DRAWS as f64);
        let terms: Vec<(f64, f64, f64)> = (2..=5)
            .map(|k| (k as f64, rng.random_range(0.0..scale / (k as f64 - 1.0)), rng.random_range(0.0..2.0 * PI)))
            .collect();
        if let Some(rows) = shape(spec, &terms) {
            return Ok(rows);
        }
    }
    Err(GenError::NoDraw { length: spec.length, width: spec.width, draws: DRAWS, seed: spec.seed })
}

/// The track of one draw's Fourier terms `(k, amplitude, phase)`, or `None` when it fails a
/// check.
fn shape(spec: &GenSpec, terms: &[(f64, f64, f64)]) -> Option<TrackRows> {
    // A fine polygon of the unit-radius curve, its length, then waypoints evenly spaced.
    let fine = 4096;
    let r = |t: f64| 1.0 + terms.iter().map(|&(k, a, p)| a * (k * t + p).cos()).sum::<f64>();
    let pts: Vec<P2> = (0..fine)
        .map(|i| {
            let t = 2.0 * PI * i as f64 / fine as f64;
            P2::new(r(t) * t.cos(), r(t) * t.sin())
        })
        .collect();
    if (0..fine).any(|i| r(2.0 * PI * i as f64 / fine as f64) <= 0.05) {
        return None;
    }
    let mut cum = vec![0.0];
    for i in 0..fine {
        let d = (pts[(i + 1) % fine] - pts[i]).norm();
        cum.push(cum[i] + d);
    }
    let unit_len = cum[fine];
    let k = spec.length / unit_len;
    let n = (spec.length / SPACING).round().max(12.0) as usize;
    let mut center = Vec::with_capacity(n + 1);
    let mut j = 0;
    for i in 0..n {
        let s = unit_len * i as f64 / n as f64;
        while cum[j + 1] < s {
            j += 1;
        }
        let f = (s - cum[j]) / (cum[j + 1] - cum[j]).max(1e-12);
        let (a, b) = (pts[j], pts[(j + 1) % fine]);
        center.push(P2::from((a.coords + (b.coords - a.coords) * f) * k));
    }
    // Turns: the circumscribed radius of every three neighbours.
    let min_radius = spec.min_radius();
    for i in 0..n {
        let (a, b, c) = (center[(i + n - 1) % n], center[i], center[(i + 1) % n]);
        let cross = (b - a).perp(&(c - b));
        let radius = (b - a).norm() * (c - b).norm() * (c - a).norm() / (2.0 * cross.abs()).max(1e-12);
        if radius < min_radius {
            return None;
        }
    }
    // Far parts of the loop: centre points more than a width and a gap apart.
    let far = spec.width + GAP;
    let arc = |i: usize, j: usize| {
        let d = i.abs_diff(j);
        d.min(n - d) as f64 * spec.length / n as f64
    };
    for i in 0..n {
        for j in i + 1..n {
            if arc(i, j) > PI * far && (center[i] - center[j]).norm() < far {
                return None;
            }
        }
    }
    // Borders: half the width either side along the normal (left, inner, for this CCW loop).
    let half = spec.width / 2.0;
    let normal = |i: usize| {
        let d = center[(i + 1) % n] - center[(i + n - 1) % n];
        let d = d / d.norm();
        nalgebra::Vector2::new(-d.y, d.x)
    };
    let mut rows = TrackRows {
        inner: (0..n).map(|i| center[i] + normal(i) * half).collect(),
        outer: (0..n).map(|i| center[i] - normal(i) * half).collect(),
        center,
    };
    for v in [&mut rows.center, &mut rows.inner, &mut rows.outer] {
        v.push(v[0]);
    }
    validate_rows(&rows).ok()?;
    Some(rows)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Direction, Track};

    /// Issue 34: a generated world is the same track everywhere by its name.
    #[test]
    fn a_generated_world_is_the_same_track_everywhere_by_its_name() {
        let w = crate::world("generated:7").unwrap();
        assert_eq!(w.name, "generated:7");
        let spec =
            GenSpec { seed: 7, length: crate::catalog::GENERATED_LENGTH, width: crate::catalog::GENERATED_WIDTH };
        assert_eq!(w.rows, generate(&spec).unwrap(), "what `tracks generate --seed 7` makes");
        assert_eq!(crate::world("generated:7").unwrap().rows, w.rows);
        assert_ne!(crate::world("generated:8").unwrap().rows, w.rows);
        let e = crate::world("generated:x").unwrap_err().to_string();
        assert!(e.contains("'generated:x'") && e.contains("expected generated:N"), "{e}");
        let e = crate::world("no_such_world").unwrap_err().to_string();
        assert!(e.contains("generated:N"), "{e}");
    }

    /// Issue 34: generated tracks have the asked size and hold together.
    #[test]
    fn generated_tracks_have_the_asked_size_and_hold_together() {
        for (seed, length, width) in [(1, 30.0, 1.07), (2, 60.0, 0.8), (3, 18.0, 1.2), (4, 100.0, 1.5), (5, 12.0, 0.6)]
        {
            let spec = GenSpec { seed, length, width };
            let rows = generate(&spec).unwrap_or_else(|e| panic!("{spec:?}: {e}"));
            assert!(rows.is_closed(), "{spec:?}");
            let track = Track::new("generated", &rows, Direction::Forward);
            assert!((track.length() - length).abs() < 0.02 * length, "{spec:?}: {} m", track.length());
            let (lo, _, hi) = rows.width_stats();
            assert!((lo - width).abs() < 1e-6 && (hi - width).abs() < 1e-6, "{spec:?}: {lo}..{hi}");
            assert!(track.is_ccw(), "{spec:?}");
            // The centre is on the road everywhere, the borders never reach another part.
            for p in track.waypoints() {
                assert!(track.on_road(*p), "{spec:?}");
            }
            // The same seed, the same track; another seed, another.
            assert_eq!(generate(&spec).unwrap(), rows);
            assert_ne!(generate(&GenSpec { seed: seed + 100, ..spec }).unwrap(), rows);
        }
    }

    /// Issue 34: a request no loop can meet is refused with the reason.
    #[test]
    fn a_request_no_loop_can_meet_is_refused_with_the_reason() {
        let e = generate(&GenSpec { seed: 1, length: 5.0, width: 1.5 }).unwrap_err();
        assert!(matches!(e, GenError::TooShort { .. }), "{e}");
        assert!(e.to_string().contains("needs at least"), "{e}");
        for (length, width, what) in [(30.0, 0.1, "--width"), (f64::NAN, 1.0, "--length"), (1e4, 1.0, "--length")] {
            let e = generate(&GenSpec { seed: 1, length, width }).unwrap_err();
            assert!(e.to_string().starts_with(what), "{e}");
        }
    }
}
