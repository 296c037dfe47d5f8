//! A uniform grid over a track that makes the per-step queries exact and cheap.
//!
//! For nearest-segment queries each cell keeps the segments that can be nearest to some
//! point of the cell: a segment whose smallest distance to the cell box exceeds the
//! smallest *largest* distance of any segment to the box can never win. For polygon
//! containment each cell keeps whether its centre lies inside the road and the border
//! edges that cross the cell, so a query counts crossings along a short path only.
//! Points outside the grid fall back to a full scan, so answers never depend on the grid.

use crate::geometry::{P2, point_segment_distance, segments_intersect};

/// Grid geometry shared by both indexes.
#[derive(Clone, Debug)]
pub(crate) struct GridFrame {
    origin: P2,
    cell: f64,
    nx: usize,
    ny: usize,
}

impl GridFrame {
    /// A frame covering `points` plus `margin` on every side, with cells of side `cell`.
    pub(crate) fn covering(points: impl Iterator<Item = P2>, margin: f64, cell: f64) -> GridFrame {
        let (mut lo, mut hi) = (P2::new(f64::MAX, f64::MAX), P2::new(f64::MIN, f64::MIN));
        for p in points {
            lo = lo.inf(&p);
            hi = hi.sup(&p);
        }
        let origin = lo - nalgebra::Vector2::new(margin, margin);
        let nx = (((hi.x - lo.x) + 2.0 * margin) / cell).ceil().max(1.0) as usize;
        let ny = (((hi.y - lo.y) + 2.0 * margin) / cell).ceil().max(1.0) as usize;
        GridFrame { origin, cell, nx, ny }
    }

    #[inline]
    pub(crate) fn cell_of(&self, p: P2) -> Option<usize> {
        let fx = (p.x - self.origin.x) / self.cell;
        let fy = (p.y - self.origin.y) / self.cell;
        if fx < 0.0 || fy < 0.0 {
            return None;
        }
        let (ix, iy) = (fx as usize, fy as usize);
        (ix < self.nx && iy < self.ny).then_some(iy * self.nx + ix)
    }

    fn cells(&self) -> usize {
        self.nx * self.ny
    }

    fn bounds(&self, idx: usize) -> (P2, P2) {
        let (ix, iy) = (idx % self.nx, idx / self.nx);
        let lo = P2::new(self.origin.x + ix as f64 * self.cell, self.origin.y + iy as f64 * self.cell);
        (lo, P2::new(lo.x + self.cell, lo.y + self.cell))
    }

    pub(crate) fn centre(&self, idx: usize) -> P2 {
        let (lo, hi) = self.bounds(idx);
        nalgebra::center(&lo, &hi)
    }
}

/// Candidate segments per cell for exact nearest-segment queries on one polyline.
#[derive(Clone, Debug)]
pub(crate) struct SegmentGrid {
    pub(crate) frame: GridFrame,
    starts: Vec<u32>,
    segs: Vec<u32>,
}

impl SegmentGrid {
    pub(crate) fn build(pts: &[P2], margin: f64, cell: f64) -> SegmentGrid {
        let frame = GridFrame::covering(pts.iter().copied(), margin, cell);
        let nseg = pts.len() - 1;
        let mut starts = Vec::with_capacity(frame.cells() + 1);
        let mut segs = Vec::new();
        let mut dmin = vec![0.0; nseg];
        for c in 0..frame.cells() {
            starts.push(segs.len() as u32);
            let (lo, hi) = frame.bounds(c);
            let corners = [lo, P2::new(hi.x, lo.y), hi, P2::new(lo.x, hi.y)];
            let mut best_max = f64::MAX;
            for s in 0..nseg {
                let (a, b) = (pts[s], pts[s + 1]);
                let dmax = corners.iter().map(|&q| point_segment_distance(q, a, b)).fold(0.0, f64::max);
                best_max = best_max.min(dmax);
                dmin[s] = segment_box_distance(a, b, lo, hi, &corners);
            }
            for (s, &d) in dmin.iter().enumerate() {
                if d <= best_max + 1e-12 {
                    segs.push(s as u32);
                }
            }
        }
        starts.push(segs.len() as u32);
        SegmentGrid { frame, starts, segs }
    }

    /// Candidate segment indices (ascending) for the cell holding `p`, if it is in the grid.
    #[inline]
    pub(crate) fn candidates(&self, p: P2) -> Option<&[u32]> {
        let c = self.frame.cell_of(p)?;
        Some(&self.segs[self.starts[c] as usize..self.starts[c + 1] as usize])
    }
}

/// Per-cell inside/outside state and crossing edges for a polygon with holes.
#[derive(Clone, Debug)]
pub(crate) struct PolygonGrid {
    frame: GridFrame,
    refs: Vec<P2>,
    inside: Vec<bool>,
    starts: Vec<u32>,
    edges: Vec<(P2, P2)>,
}

impl PolygonGrid {
    /// The polygon is the even-odd union of `edges` (closed rings, holes included).
    pub(crate) fn build_from_edges(edges: &[(P2, P2)], margin: f64, cell: f64) -> PolygonGrid {
        let frame = GridFrame::covering(edges.iter().flat_map(|&(a, b)| [a, b]), margin, cell);
        let mut per_cell: Vec<Vec<(P2, P2)>> = vec![Vec::new(); frame.cells()];
        for &(a, b) in edges {
            // Only the cells under the edge's bounding box can meet it.
            let (lo, hi) = (a.inf(&b), a.sup(&b));
            let ix0 = ((lo.x - frame.origin.x) / frame.cell).floor().max(0.0) as usize;
            let iy0 = ((lo.y - frame.origin.y) / frame.cell).floor().max(0.0) as usize;
            let ix1 = (((hi.x - frame.origin.x) / frame.cell).floor() as usize).min(frame.nx - 1);
            let iy1 = (((hi.y - frame.origin.y) / frame.cell).floor() as usize).min(frame.ny - 1);
            for iy in iy0..=iy1 {
                for ix in ix0..=ix1 {
                    let c = iy * frame.nx + ix;
                    let (clo, chi) = frame.bounds(c);
                    let corners = [clo, P2::new(chi.x, clo.y), chi, P2::new(clo.x, chi.y)];
                    if segment_box_distance(a, b, clo, chi, &corners) <= 1e-12 {
                        per_cell[c].push((a, b));
                    }
                }
            }
        }
        // Each cell's reference point keeps clear of its edges: track files are full of
        // axis-aligned borders on round coordinates, which the plain cell centre can sit on.
        let mut refs = Vec::with_capacity(frame.cells());
        for (c, list) in per_cell.iter().enumerate() {
            let (lo, _) = frame.bounds(c);
            let clear = |p: P2| list.iter().all(|&(a, b)| point_segment_distance(p, a, b) > 1e-6 * frame.cell);
            let reference = REFERENCE_OFFSETS
                .iter()
                .map(|&(fx, fy)| P2::new(lo.x + fx * frame.cell, lo.y + fy * frame.cell))
                .find(|&p| clear(p))
                .unwrap_or_else(|| frame.centre(c));
            refs.push(reference);
        }
        let inside = refs.iter().map(|&r| even_odd_contains(edges, r)).collect();
        let mut starts = Vec::with_capacity(frame.cells() + 1);
        let mut flat = Vec::new();
        for list in per_cell {
            starts.push(flat.len() as u32);
            flat.extend(list);
        }
        starts.push(flat.len() as u32);
        PolygonGrid { frame, refs, inside, starts, edges: flat }
    }

    /// Whether `p` is inside; `None` when `p` is outside the grid (the caller scans).
    #[inline]
    pub(crate) fn contains(&self, p: P2) -> Option<bool> {
        let c = self.frame.cell_of(p)?;
        let reference = self.refs[c];
        let mut inside = self.inside[c];
        for &(a, b) in &self.edges[self.starts[c] as usize..self.starts[c + 1] as usize] {
            // The straight path from the cell's reference point to `p` stays in the cell,
            // so only the edges that meet the cell can flip inside/outside along it.
            if segments_intersect(reference, p, a, b) {
                inside = !inside;
            }
        }
        Some(inside)
    }
}

/// Candidate reference points inside a cell, as fractions of its side.
const REFERENCE_OFFSETS: [(f64, f64); 4] = [(0.5173, 0.4709), (0.3137, 0.6551), (0.7219, 0.2843), (0.1931, 0.8377)];

/// Even-odd ray casting over a set of edges (the straightforward O(n) test).
pub(crate) fn even_odd_contains(edges: &[(P2, P2)], p: P2) -> bool {
    let mut inside = false;
    for &(a, b) in edges {
        if (a.y > p.y) != (b.y > p.y) {
            let x = a.x + (p.y - a.y) * (b.x - a.x) / (b.y - a.y);
            if p.x < x {
                inside = !inside;
            }
        }
    }
    inside
}

/// Smallest distance between segment `a..b` and the axis-aligned box `lo..hi`.
fn segment_box_distance(a: P2, b: P2, lo: P2, hi: P2, corners: &[P2; 4]) -> f64 {
    let inside = |p: P2| p.x >= lo.x && p.x <= hi.x && p.y >= lo.y && p.y <= hi.y;
    if inside(a) || inside(b) {
        return 0.0;
    }
    for i in 0..4 {
        if segments_intersect(a, b, corners[i], corners[(i + 1) % 4]) {
            return 0.0;
        }
    }
    let box_dist = |p: P2| {
        let dx = (lo.x - p.x).max(0.0).max(p.x - hi.x);
        let dy = (lo.y - p.y).max(0.0).max(p.y - hi.y);
        (dx * dx + dy * dy).sqrt()
    };
    let mut d = box_dist(a).min(box_dist(b));
    for &q in corners {
        d = d.min(point_segment_distance(q, a, b));
    }
    d
}
