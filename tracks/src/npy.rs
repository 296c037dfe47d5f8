//! Reading and validating DeepRacer track files (`.npy`, `(N, 6)` float64).
//!
//! The columns are `[center_x, center_y, inner_x, inner_y, outer_x, outer_y]` in metres.
//! Parsing of the numpy container is `npyz`'s job; this module checks what DeepRacer's
//! simulator assumes of the numbers and says exactly which row or column is wrong.

use crate::TrackError;
use crate::geometry::P2;
use npyz::{DType, Order, TypeChar};

/// The raw rows of a track file, validated: at least 3 finite rows, no zero-length
/// centre-line segment (other than a whole row repeated, which DeepRacer's own files do),
/// no border crossing the centre line. [`TrackRows::sanitized`] drops the repeats, as
/// DeepRacer's simapp does when it loads a track; [`crate::Track`] is built from that.
#[derive(Clone, Debug, PartialEq)]
pub struct TrackRows {
    /// Centre line, one point per row.
    pub center: Vec<P2>,
    /// Inner border (the driver's left when driving a CCW file forwards).
    pub inner: Vec<P2>,
    /// Outer border.
    pub outer: Vec<P2>,
}

impl TrackRows {
    /// Number of rows (points) in the file.
    pub fn len(&self) -> usize {
        self.center.len()
    }

    /// True when there are no rows (never true for validated rows).
    pub fn is_empty(&self) -> bool {
        self.center.is_empty()
    }

    /// Whether row `i` repeats row `i - 1` in all six values (within 1e-9 m). DeepRacer's own
    /// files do this (e.g. `AWS_track` row 187, `reInvent2019_track` row 39).
    pub fn repeats_previous(&self, i: usize) -> bool {
        i > 0
            && (self.center[i] - self.center[i - 1]).norm() <= CLOSE_EPS
            && (self.inner[i] - self.inner[i - 1]).norm() <= CLOSE_EPS
            && (self.outer[i] - self.outer[i - 1]).norm() <= CLOSE_EPS
    }

    /// Rows that repeat the previous row (dropped by [`TrackRows::sanitized`]).
    pub fn repeated_rows(&self) -> Vec<usize> {
        (1..self.len()).filter(|&i| self.repeats_previous(i)).collect()
    }

    /// The rows without those that repeat the previous one: DeepRacer's simapp removes
    /// consecutive duplicate waypoints when it loads a track (its waypoint sanitising, eps
    /// 1e-9), so `reInvent2019_track`'s 155 rows give reward functions 154 `waypoints` and
    /// `closest_waypoints` count from that list. Validation allows a repeated centre point
    /// only as a whole repeated row, so dropping the row changes no line's shape.
    pub fn sanitized(&self) -> TrackRows {
        let keep: Vec<usize> = (0..self.len()).filter(|&i| !self.repeats_previous(i)).collect();
        TrackRows {
            center: keep.iter().map(|&i| self.center[i]).collect(),
            inner: keep.iter().map(|&i| self.inner[i]).collect(),
            outer: keep.iter().map(|&i| self.outer[i]).collect(),
        }
    }

    /// Width between border rows: (min, mean, max) over every row of the file, as STATS.md
    /// counts them (m).
    pub fn width_stats(&self) -> (f64, f64, f64) {
        let n = self.len();
        let (mut lo, mut hi, mut sum) = (f64::MAX, 0.0f64, 0.0);
        for w in self.inner.iter().zip(&self.outer).map(|(i, o)| (i - o).norm()) {
            lo = lo.min(w);
            hi = hi.max(w);
            sum += w;
        }
        (lo, sum / n as f64, hi)
    }

    /// The rows as a DeepRacer `.npy` file: float64, shape (N, 6), centre x, y, inner x, y,
    /// outer x, y per row.
    pub fn to_npy(&self) -> Vec<u8> {
        let rows = self.center.iter().zip(&self.inner).zip(&self.outer);
        float_rows_npy(self.len(), rows.map(|((c, i), o)| [c.x, c.y, i.x, i.y, o.x, o.y]))
    }

    /// A closed loop repeats its first row as its last, as every DeepRacer loop file does.
    pub fn is_closed(&self) -> bool {
        let n = self.len();
        n > 1
            && (self.center[0] - self.center[n - 1]).norm() < CLOSE_EPS
            && (self.inner[0] - self.inner[n - 1]).norm() < CLOSE_EPS
            && (self.outer[0] - self.outer[n - 1]).norm() < CLOSE_EPS
    }
}

/// Points as a `.npy` file: float64, shape (N, 2), x and y per row (a racing line, as the
/// community's notebooks keep them).
pub fn points_to_npy(points: &[P2]) -> Vec<u8> {
    float_rows_npy(points.len(), points.iter().map(|p| [p.x, p.y]))
}

/// `n` rows of `N` float64 values as a `.npy` file of shape (n, N).
fn float_rows_npy<const N: usize>(n: usize, rows: impl Iterator<Item = [f64; N]>) -> Vec<u8> {
    use npyz::WriterBuilder;
    let mut out = Vec::new();
    let mut w = npyz::WriteOptions::<f64>::new()
        .default_dtype()
        .shape(&[n as u64, N as u64])
        .writer(&mut out)
        .begin_nd()
        .expect("writing into memory");
    for row in rows {
        w.extend(row).expect("writing into memory");
    }
    w.finish().expect("writing into memory");
    out
}

/// Two rows closer than this are the same point (DeepRacer's sanitising epsilon).
const CLOSE_EPS: f64 = 1e-9;

/// The deepest bracket nesting a `.npy` header may have: a dict holding a tuple (a
/// structured dtype's list of tuples is one more). The header parser underneath takes time
/// exponential in the depth (a fuzzer's 40-deep header took more than 10 s), so deeper ones
/// are refused before it runs.
const MAX_HEADER_DEPTH: usize = 4;

/// How deep the brackets (`{`, `[`, `(`) of a `.npy` file's header nest (0 when the bytes
/// are not a `.npy` file: its parser says so).
fn header_depth(bytes: &[u8]) -> usize {
    if !bytes.starts_with(b"\x93NUMPY") || bytes.len() < 10 {
        return 0;
    }
    let (len, start) = if bytes[6] == 1 {
        (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10)
    } else if bytes.len() >= 12 {
        (u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize, 12)
    } else {
        return 0;
    };
    let header = &bytes[start.min(bytes.len())..start.saturating_add(len).min(bytes.len())];
    let (mut depth, mut deepest) = (0usize, 0usize);
    for b in header {
        match b {
            b'{' | b'[' | b'(' => {
                depth += 1;
                deepest = deepest.max(depth);
            }
            b'}' | b']' | b')' => depth = depth.saturating_sub(1),
            _ => {}
        }
    }
    deepest
}

/// Parse and validate the bytes of a `.npy` track file. `origin` names the file in errors.
pub fn parse_track_npy(bytes: &[u8], origin: &str) -> Result<TrackRows, TrackError> {
    let bad = |msg: String| TrackError::Invalid { origin: origin.to_string(), msg };
    let depth = header_depth(bytes);
    if depth > MAX_HEADER_DEPTH {
        return Err(bad(format!(
            "the header nests brackets {depth} deep; a track's is a flat dict \
             ({{'descr': '<f8', 'fortran_order': False, 'shape': (N, 6), }})"
        )));
    }
    let npy = npyz::NpyFile::new(bytes).map_err(|e| bad(format!("not a numpy .npy file: {e}")))?;
    match npy.dtype() {
        DType::Plain(ts) if ts.type_char() == TypeChar::Float && ts.size_field() == 8 => {}
        other => {
            return Err(bad(format!("dtype is {}, expected float64 ('<f8')", describe_dtype(&other))));
        }
    }
    let shape = npy.shape().to_vec();
    if shape.len() != 2 || shape[1] != 6 {
        return Err(bad(format!("shape is {shape:?}, expected (N, 6): centre x,y, inner x,y, outer x,y per row")));
    }
    let n = shape[0] as usize;
    let order = npy.order();
    let flat: Vec<f64> = npy.into_vec().map_err(|e| bad(format!("truncated or unreadable data: {e}")))?;
    if flat.len() != n * 6 {
        return Err(bad(format!("holds {} values, the header promises {}", flat.len(), n * 6)));
    }
    let at = |row: usize, col: usize| match order {
        Order::C => flat[row * 6 + col],
        Order::Fortran => flat[col * n + row],
    };
    const COLS: [&str; 6] = ["center_x", "center_y", "inner_x", "inner_y", "outer_x", "outer_y"];
    for row in 0..n {
        for (col, name) in COLS.iter().enumerate() {
            let v = at(row, col);
            if !v.is_finite() {
                return Err(bad(format!("row {row} column {col} ({name}) is {v}, expected a finite number")));
            }
        }
    }
    let rows = TrackRows {
        center: (0..n).map(|r| P2::new(at(r, 0), at(r, 1))).collect(),
        inner: (0..n).map(|r| P2::new(at(r, 2), at(r, 3))).collect(),
        outer: (0..n).map(|r| P2::new(at(r, 4), at(r, 5))).collect(),
    };
    validate_rows(&rows).map_err(|e| bad(e.to_string()))?;
    Ok(rows)
}

fn describe_dtype(dtype: &DType) -> String {
    match dtype {
        DType::Plain(ts) => format!("'{ts}'"),
        DType::Array(..) => "a nested array type".to_string(),
        DType::Record(..) => "a structured (record) type".to_string(),
    }
}

/// Why rows are not a usable track, naming the offending row.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum BadRows {
    /// The three columns' lengths differ.
    #[error("centre, inner and outer columns differ in length")]
    Lengths,
    /// Fewer than three distinct centre points.
    #[error("has {rows} rows ({distinct} distinct points), expected at least 3")]
    TooFew {
        /// Rows.
        rows: usize,
        /// Rows but a closing repeat of the first.
        distinct: usize,
    },
    /// A row repeats the previous centre point but not its borders.
    #[error(
        "row {row} repeats row {}'s centre point with different borders: a zero-length centre-line segment",
        .row - 1
    )]
    ZeroSegment {
        /// The row.
        row: usize,
    },
    /// A border crosses the centre line.
    #[error(
        "the {border} border segment starting at row {border_row} crosses the centre line segment starting at row {centre_row}"
    )]
    Crossing {
        /// `inner` or `outer`.
        border: &'static str,
        /// The border segment's first row.
        border_row: usize,
        /// The centre line segment's first row.
        centre_row: usize,
    },
}

/// The checks that make rows usable as a track, with the offending row named.
pub fn validate_rows(rows: &TrackRows) -> Result<(), BadRows> {
    let n = rows.len();
    if rows.inner.len() != n || rows.outer.len() != n {
        return Err(BadRows::Lengths);
    }
    let distinct = if rows.is_closed() { n - 1 } else { n };
    if distinct < 3 {
        return Err(BadRows::TooFew { rows: n, distinct });
    }
    for i in 1..n {
        if (rows.center[i] - rows.center[i - 1]).norm() <= CLOSE_EPS && !rows.repeats_previous(i) {
            return Err(BadRows::ZeroSegment { row: i });
        }
    }
    for (border, name) in [(&rows.inner, "inner"), (&rows.outer, "outer")] {
        if let Some((b, c)) = first_crossing(border, &rows.center) {
            return Err(BadRows::Crossing { border: name, border_row: b, centre_row: c });
        }
    }
    Ok(())
}

/// The first pair (border segment, centre segment) that properly intersect.
fn first_crossing(border: &[P2], center: &[P2]) -> Option<(usize, usize)> {
    for b in 0..border.len().saturating_sub(1) {
        let (b0, b1) = (border[b], border[b + 1]);
        if (b1 - b0).norm() <= CLOSE_EPS {
            continue; // a repeated border point draws nothing
        }
        let (bmin, bmax) = (b0.inf(&b1), b0.sup(&b1));
        for c in 0..center.len() - 1 {
            let (c0, c1) = (center[c], center[c + 1]);
            if c0.x.max(c1.x) < bmin.x || c0.x.min(c1.x) > bmax.x || c0.y.max(c1.y) < bmin.y || c0.y.min(c1.y) > bmax.y
            {
                continue;
            }
            if crate::geometry::segments_intersect(b0, b1, c0, c1) {
                return Some((b, c));
            }
        }
    }
    None
}
