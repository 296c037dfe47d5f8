//! Track geometry and DeepRacer's geometric queries, with the simulator's exact definitions.
//!
//! DeepRacer (SIMAPP `track_geom/track_data.py`, `agent_ctrl/utils.py`) builds shapely lines
//! from the three column pairs, reverses all three (without swapping inner and outer) for
//! the reversed direction, and answers every reward key from a handful of projections.
//! This module does the same with a precomputed grid so that a step's queries cost well
//! under a microsecond. `tests/` checks every query against a plain full scan.

use crate::grid::{PolygonGrid, SegmentGrid, even_odd_contains};
use crate::npy::TrackRows;
use std::sync::OnceLock;

/// A point in the track plane (metres, Gazebo world frame).
pub type P2 = nalgebra::Point2<f64>;

/// Distance from `p` to segment `a..b`.
pub fn point_segment_distance(p: P2, a: P2, b: P2) -> f64 {
    let ab = b - a;
    let len2 = ab.norm_squared();
    let t = if len2 > 0.0 { ((p - a).dot(&ab) / len2).clamp(0.0, 1.0) } else { 0.0 };
    (p - (a + ab * t)).norm()
}

/// Whether closed segments `p1..p2` and `q1..q2` share a point.
pub fn segments_intersect(p1: P2, p2: P2, q1: P2, q2: P2) -> bool {
    fn orient(a: P2, b: P2, c: P2) -> f64 {
        (b.x - a.x) * (c.y - a.y) - (b.y - a.y) * (c.x - a.x)
    }
    fn on_seg(a: P2, b: P2, p: P2) -> bool {
        p.x >= a.x.min(b.x) && p.x <= a.x.max(b.x) && p.y >= a.y.min(b.y) && p.y <= a.y.max(b.y)
    }
    let d1 = orient(q1, q2, p1);
    let d2 = orient(q1, q2, p2);
    let d3 = orient(p1, p2, q1);
    let d4 = orient(p1, p2, q2);
    if ((d1 > 0.0 && d2 < 0.0) || (d1 < 0.0 && d2 > 0.0)) && ((d3 > 0.0 && d4 < 0.0) || (d3 < 0.0 && d4 > 0.0)) {
        return true;
    }
    (d1 == 0.0 && on_seg(q1, q2, p1))
        || (d2 == 0.0 && on_seg(q1, q2, p2))
        || (d3 == 0.0 && on_seg(p1, p2, q1))
        || (d4 == 0.0 && on_seg(p1, p2, q2))
}

/// Wrap an angle in degrees into DeepRacer's heading range (-180, 180].
pub fn wrap_degrees(deg: f64) -> f64 {
    let mut d = deg % 360.0;
    if d <= -180.0 {
        d += 360.0;
    } else if d > 180.0 {
        d -= 360.0;
    }
    d
}

/// DeepRacer's `compute_current_prog`: progress (%) from the normalised distance travelled
/// since the episode's start (`ndist - start_ndist`) and the previous step's progress.
pub fn compute_progress(ndist_delta: f64, prev_progress: f64) -> f64 {
    let mut p = 100.0 * ndist_delta;
    if p <= 0.0 {
        p += 100.0;
    }
    if prev_progress > p + 50.0 {
        p += 100.0;
    }
    if p > prev_progress + 50.0 {
        p -= 100.0;
    }
    p.min(100.0)
}

/// Where a point projects onto a polyline (shapely's `project` + `interpolate`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Projection {
    /// Index of the segment holding the nearest point.
    pub segment: usize,
    /// Distance along the line to the nearest point (m).
    pub along: f64,
    /// The nearest point on the line.
    pub point: P2,
    /// Distance from the query point to `point` (m).
    pub distance: f64,
}

/// A polyline with cumulative lengths and (built on first use) a grid index.
#[derive(Debug)]
pub struct Polyline {
    pts: Vec<P2>,
    cum: Vec<f64>,
    grid: OnceLock<SegmentGrid>,
    margin: f64,
}

impl Clone for Polyline {
    fn clone(&self) -> Self {
        Polyline { pts: self.pts.clone(), cum: self.cum.clone(), grid: OnceLock::new(), margin: self.margin }
    }
}

/// Grid cell side for segment indexes (m).
const SEGMENT_CELL: f64 = 0.25;

impl Polyline {
    /// A polyline through `pts` whose grid covers `margin` metres around it.
    pub fn new(pts: Vec<P2>, margin: f64) -> Polyline {
        let mut cum = Vec::with_capacity(pts.len());
        let mut total = 0.0;
        cum.push(0.0);
        for w in pts.windows(2) {
            total += (w[1] - w[0]).norm();
            cum.push(total);
        }
        Polyline { pts, cum, grid: OnceLock::new(), margin }
    }

    /// The vertices.
    pub fn points(&self) -> &[P2] {
        &self.pts
    }

    /// Total length (m), closing segment included for rings (their last point repeats the first).
    pub fn length(&self) -> f64 {
        *self.cum.last().unwrap_or(&0.0)
    }

    /// Cumulative length at each vertex.
    pub fn cumulative(&self) -> &[f64] {
        &self.cum
    }

    fn grid(&self) -> &SegmentGrid {
        self.grid.get_or_init(|| SegmentGrid::build(&self.pts, self.margin, SEGMENT_CELL))
    }

    #[inline]
    fn project_segments(&self, p: P2, segs: impl Iterator<Item = usize>) -> Projection {
        let mut best = Projection { segment: 0, along: 0.0, point: self.pts[0], distance: f64::MAX };
        let mut best_d2 = f64::MAX;
        for s in segs {
            let (a, b) = (self.pts[s], self.pts[s + 1]);
            let ab = b - a;
            let len2 = ab.norm_squared();
            let t = if len2 > 0.0 { ((p - a).dot(&ab) / len2).clamp(0.0, 1.0) } else { 0.0 };
            let q = a + ab * t;
            let d2 = (p - q).norm_squared();
            if d2 < best_d2 {
                best_d2 = d2;
                best = Projection { segment: s, along: self.cum[s] + t * len2.sqrt(), point: q, distance: 0.0 };
            }
        }
        best.distance = best_d2.sqrt();
        best
    }

    /// The nearest point of the line to `p` (first segment wins a tie, as in GEOS).
    #[inline]
    pub fn project(&self, p: P2) -> Projection {
        match self.grid().candidates(p) {
            Some(c) => self.project_segments(p, c.iter().map(|&s| s as usize)),
            None => self.project_scan(p),
        }
    }

    /// [`Polyline::project`] by scanning every segment (reference implementation).
    pub fn project_scan(&self, p: P2) -> Projection {
        self.project_segments(p, 0..self.pts.len() - 1)
    }

    /// The point at distance `along` from the start (clamped to the line).
    pub fn interpolate(&self, along: f64) -> P2 {
        let (s, t) = self.locate(along);
        let (a, b) = (self.pts[s], self.pts[s + 1]);
        a + (b - a) * t
    }

    /// Segment index and fraction within it for a distance along the line.
    fn locate(&self, along: f64) -> (usize, f64) {
        let along = along.clamp(0.0, self.length());
        let s = match self.cum.partition_point(|&c| c <= along) {
            0 => 0,
            i => (i - 1).min(self.pts.len() - 2),
        };
        let len = self.cum[s + 1] - self.cum[s];
        (s, if len > 0.0 { (along - self.cum[s]) / len } else { 0.0 })
    }

    /// Direction (radians) of the segment holding distance `along`.
    pub fn direction_at(&self, along: f64) -> f64 {
        let (s, _) = self.locate(along);
        let d = self.pts[s + 1] - self.pts[s];
        d.y.atan2(d.x)
    }
}

/// Everything DeepRacer derives from the reference point's position on the track.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrackQuery {
    /// `center_line.project(point, normalized=True)`, in [0, 1].
    pub ndist: f64,
    /// Distance to the centre line (m).
    pub distance_from_center: f64,
    /// The nearest centre-line point.
    pub center_point: P2,
    /// `[prev, next]` waypoint indices around `ndist`.
    pub closest_waypoints: [usize; 2],
    /// Left of the centre line relative to the driving direction.
    pub is_left_of_center: bool,
    /// Local width: between the border points nearest to `center_point` (m).
    pub track_width: f64,
}

/// Which way round the track is driven.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Direction {
    /// The file's own order.
    #[default]
    Forward,
    /// Every column reversed (DeepRacer's `REVERSE_DIR`).
    Reversed,
}

/// A track's geometry for one driving direction, with the queries the simulator needs.
#[derive(Clone, Debug)]
pub struct Track {
    name: String,
    closed: bool,
    direction: Direction,
    ccw: bool,
    center: Polyline,
    inner: Polyline,
    outer: Polyline,
    /// The lanes: midlines between the centre line and each border, row by row (DeepRacer's
    /// `inner_lane` / `outer_lane`), where a reset puts the car.
    pub(crate) lanes: [Polyline; 2],
    /// Normalised distance of each centre vertex, last = 1.0 (`TrackLine.ndists`).
    ndists: Vec<f64>,
    road_edges: Vec<(P2, P2)>,
    road_grid: OnceLock<PolygonGrid>,
}

/// How far beyond the borders the grids reach; farther points take the full scan.
const GRID_MARGIN: f64 = 1.5;
/// Cell side of the road containment grid (m).
const ROAD_CELL: f64 = 0.2;

impl Track {
    /// Build the geometry from validated rows for one direction. Repeated rows are dropped
    /// first ([`TrackRows::sanitized`]), as DeepRacer's simapp drops them.
    pub fn new(name: &str, rows: &TrackRows, direction: Direction) -> Track {
        let rows = &rows.sanitized();
        let closed = rows.is_closed();
        let rev = |v: &Vec<P2>| -> Vec<P2> {
            let mut v = v.clone();
            if direction == Direction::Reversed {
                v.reverse();
            }
            v
        };
        let center = Polyline::new(rev(&rows.center), GRID_MARGIN);
        let inner = Polyline::new(rev(&rows.inner), GRID_MARGIN);
        let outer = Polyline::new(rev(&rows.outer), GRID_MARGIN);
        let lane = |border: &Vec<P2>| -> Vec<P2> {
            rev(&border.iter().zip(&rows.center).map(|(b, c)| P2::from((b.coords + c.coords) / 2.0)).collect())
        };
        let lanes = [Polyline::new(lane(&rows.inner), GRID_MARGIN), Polyline::new(lane(&rows.outer), GRID_MARGIN)];
        let forward_ccw = if closed { signed_area(&rows.center) > 0.0 } else { true };
        let ccw = forward_ccw ^ (direction == Direction::Reversed);
        let len = center.length();
        let mut ndists: Vec<f64> = center.cumulative()[..center.points().len() - 1].iter().map(|c| c / len).collect();
        ndists.push(1.0);
        // Polygon(outer, [inner]) for loops; outer + flipped inner for open tracks.
        let road_edges: Vec<(P2, P2)> = if closed {
            [&rows.outer, &rows.inner].into_iter().flat_map(|r| r.windows(2).map(|w| (w[0], w[1]))).collect()
        } else {
            let mut ring: Vec<P2> = rows.outer.clone();
            ring.extend(rows.inner.iter().rev());
            ring.push(rows.outer[0]);
            ring.windows(2).map(|w| (w[0], w[1])).collect()
        };
        Track {
            name: name.to_string(),
            closed,
            direction,
            ccw,
            center,
            inner,
            outer,
            lanes,
            ndists,
            road_edges,
            road_grid: OnceLock::new(),
        }
    }

    /// The track's name (file stem or catalog name).
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Loop (first row == last row) or open.
    pub fn is_closed(&self) -> bool {
        self.closed
    }

    /// The driving direction this geometry is built for.
    pub fn direction(&self) -> Direction {
        self.direction
    }

    /// DeepRacer's `is_ccw`: the forward centre line's orientation XOR reversed (open tracks count as CCW).
    pub fn is_ccw(&self) -> bool {
        self.ccw
    }

    /// `track_length`: the centre line's length, closing segment included (m).
    pub fn length(&self) -> f64 {
        self.center.length()
    }

    /// `waypoints`: the centre-line points in driving order (loops repeat the first at the end).
    pub fn waypoints(&self) -> &[P2] {
        self.center.points()
    }

    /// The rows in driving order (a reversed track's rows run backwards; inner stays inner).
    pub fn rows(&self) -> crate::TrackRows {
        crate::TrackRows {
            center: self.center.points().to_vec(),
            inner: self.inner.points().to_vec(),
            outer: self.outer.points().to_vec(),
        }
    }

    /// The centre line.
    pub fn center(&self) -> &Polyline {
        &self.center
    }

    /// The inner border (the driver's left on a CCW file driven forwards).
    pub fn inner(&self) -> &Polyline {
        &self.inner
    }

    /// The outer border.
    pub fn outer(&self) -> &Polyline {
        &self.outer
    }

    /// `closest_waypoints` for a normalised distance (`find_prev_next` with `bisect_right`).
    pub fn closest_waypoints(&self, ndist: f64) -> [usize; 2] {
        let n = self.ndists.len();
        let next = self.ndists.partition_point(|&d| d <= ndist);
        let prev = if next == 0 { n - 1 } else { next - 1 };
        [prev, if next == n { 0 } else { next }]
    }

    /// All the position-derived reward values for the reference point `p`.
    #[inline]
    pub fn query(&self, p: P2) -> TrackQuery {
        self.query_with(p, |line, q| line.project(q))
    }

    /// [`Track::query`] by full scans (reference implementation for tests and benchmarks).
    pub fn query_scan(&self, p: P2) -> TrackQuery {
        self.query_with(p, |line, q| line.project_scan(q))
    }

    #[inline]
    fn query_with(&self, p: P2, project: impl Fn(&Polyline, P2) -> Projection) -> TrackQuery {
        let c = project(&self.center, p);
        let len = self.center.length();
        let ndist = if len > 0.0 { c.along / len } else { 0.0 };
        let near_in = project(&self.inner, c.point).point;
        let near_out = project(&self.outer, c.point).point;
        let d_in = (p - near_in).norm();
        let d_out = (p - near_out).norm();
        TrackQuery {
            ndist,
            distance_from_center: c.distance,
            center_point: c.point,
            closest_waypoints: self.closest_waypoints(ndist),
            is_left_of_center: (d_in < d_out) ^ !self.ccw,
            track_width: (near_in - near_out).norm(),
        }
    }

    /// Whether `p` is strictly inside the road polygon.
    #[inline]
    pub fn on_road(&self, p: P2) -> bool {
        let grid =
            self.road_grid.get_or_init(|| PolygonGrid::build_from_edges(&self.road_edges, GRID_MARGIN, ROAD_CELL));
        grid.contains(p).unwrap_or_else(|| even_odd_contains(&self.road_edges, p))
    }

    /// [`Track::on_road`] by a full scan (reference implementation).
    pub fn on_road_scan(&self, p: P2) -> bool {
        even_odd_contains(&self.road_edges, p)
    }

    /// Lidar: for each ray angle (radians, world frame) from `origin`, the distance to the
    /// nearest border (inner or outer), or `range` when none is that close. Writes `out`.
    pub fn border_distances(&self, origin: P2, angles: &[f64], range: f64, out: &mut [f64]) {
        let near = |a: &P2, b: &P2| {
            let lo = a.inf(b);
            let hi = a.sup(b);
            lo.x <= origin.x + range && hi.x >= origin.x - range && lo.y <= origin.y + range && hi.y >= origin.y - range
        };
        let mut segs: Vec<(P2, P2)> = Vec::with_capacity(64);
        for line in [&self.inner, &self.outer] {
            for w in line.points().windows(2) {
                if near(&w[0], &w[1]) {
                    segs.push((w[0], w[1]));
                }
            }
        }
        for (angle, out) in angles.iter().zip(out.iter_mut()) {
            let d = nalgebra::Vector2::new(angle.cos(), angle.sin());
            let mut best = range;
            for &(a, b) in &segs {
                // origin + t d = a + u (b - a), t in [0, best], u in [0, 1].
                let e = b - a;
                let denom = d.x * e.y - d.y * e.x;
                if denom.abs() < 1e-12 {
                    continue;
                }
                let w = a - origin;
                let t = (w.x * e.y - w.y * e.x) / denom;
                let u = (w.x * d.y - w.y * d.x) / denom;
                if t >= 0.0 && t < best && (0.0..=1.0).contains(&u) {
                    best = t;
                }
            }
            *out = best;
        }
    }

    /// Pose on the centre line at distance `along`: the point and the direction of travel
    /// (forward difference, as DeepRacer's `interpolate_pose`).
    pub fn pose_at(&self, along: f64) -> (P2, f64) {
        let len = self.length();
        let along = if self.closed { along.rem_euclid(len) } else { along.clamp(0.0, len) };
        (self.center.interpolate(along), self.center.direction_at(along))
    }

    /// Where DeepRacer puts a car back after it left the track (`_get_car_reset_model_state`):
    /// the centre-line point at distance `along`, projected onto the inner and the outer lane;
    /// of the two, the one nearer to `near` (the car's position before it left), facing along
    /// its lane (forward difference).
    pub fn reset_pose(&self, along: f64, near: P2) -> (P2, f64) {
        let len = self.length();
        let along = if self.closed { along.rem_euclid(len) } else { along.clamp(0.0, len) };
        let c = self.center.interpolate(along);
        let [a, b] = [&self.lanes[0], &self.lanes[1]].map(|lane| {
            let p = lane.project(c);
            (p.point, lane.direction_at(p.along))
        });
        if (a.0 - near).norm() < (b.0 - near).norm() { a } else { b }
    }
}

/// Shoelace signed area (positive = counter-clockwise).
fn signed_area(pts: &[P2]) -> f64 {
    pts.windows(2).map(|w| w[0].x * w[1].y - w[1].x * w[0].y).sum::<f64>() / 2.0
}
