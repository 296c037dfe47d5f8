#!/usr/bin/env python3
"""Recompute DeepRacer's reward `params` with shapely, as DeepRacer's simapp does, and compare.

An independent implementation: nothing here comes from Paddock's Rust code. It reads a
DeepRacer track file (.npy) and the `params` a reward function received while a car drove on
it (one JSON object per line, written by the reward function in
coordinator/tests/it/fidelity.rs), rebuilds the track the way the simapp's `TrackData` does
(shapely LinearRing/LineString, road polygon, consecutive duplicate rows dropped), and
recomputes from each step's `x`, `y` and `heading`:

  waypoints, track_length, closest_waypoints, distance_from_center, is_left_of_center,
  track_width, progress, projection_distance, is_reversed, all_wheels_on_track, is_offtrack

(the last two from the four wheel centres of DeepRacer's URDF: front hinges at x 0.082311,
y ±0.079601; rear axle at x -0.081663, y ±0.08105; the params' x, y being 0.14 m ahead of the
car's origin). Prints one line per key with the rows checked and the largest difference;
exits 1 naming the first disagreeing row and key.

Usage: fidelity_check.py TRACK.npy PARAMS.jsonl [--reversed]
"""

import argparse
import bisect
import json
import math
import sys

import numpy as np
from shapely.geometry import LinearRing, LineString, Point, Polygon

FRONT_OF_CAR = 0.14  # RELATIVE_POSITION_OF_FRONT_OF_CAR
WHEELS = [  # LINK_NAMES order: left_rear, left_front, right_rear, right_front (URDF)
    (-0.081663, 0.08105),
    (0.082311, 0.079601),
    (-0.081663, -0.08105),
    (0.082311, -0.079601),
]
TOL = 1e-9


class Track:
    def __init__(self, path, reversed_dir):
        w = np.load(path)
        # The simapp's waypoint sanitising: a row that repeats the one before is dropped.
        keep = [0] + [i for i in range(1, len(w)) if np.linalg.norm(w[i, 0:2] - w[i - 1, 0:2]) > 1e-9]
        w = w[keep]
        self.is_loop = bool(np.all(w[0, :] == w[-1, :]))
        line = LinearRing if self.is_loop else LineString
        c, i, o = w[:, 0:2], w[:, 2:4], w[:, 4:6]
        if reversed_dir:
            c, i, o = c[::-1], i[::-1], o[::-1]
        self.center, self.inner, self.outer = line(c), line(i), line(o)
        if self.is_loop:
            self.road = Polygon(self.outer, [self.inner])
            self.is_ccw = LinearRing(w[:, 0:2]).is_ccw ^ reversed_dir
        else:
            self.road = Polygon(np.vstack((np.asarray(self.outer.coords), np.flipud(np.asarray(self.inner.coords)))))
            self.is_ccw = True ^ reversed_dir  # open tracks count as CCW, XOR the direction
        self.reversed = reversed_dir
        self.ndists = [self.center.project(Point(p), normalized=True) for p in self.center.coords[:-1]] + [1.0]

    def prev_next(self, ndist):
        nxt = bisect.bisect_right(self.ndists, ndist)
        prev = nxt - 1
        if prev == -1:
            prev = len(self.ndists) - 1
        if nxt == len(self.ndists):
            nxt = 0
        return [prev, nxt]


def compute_current_prog(current, prev):
    p = 100.0 * current
    if p <= 0:
        p += 100.0
    if prev > p + 50.0:
        p += 100.0
    if p > prev + 50.0:
        p -= 100.0
    return min(p, 100.0)


def expected(track, row, prev_progress):
    x, y = row["x"], row["y"]
    pt = Point(x, y)
    ndist = track.center.project(pt, normalized=True)
    near_c = track.center.interpolate(ndist, normalized=True)
    near_in = track.inner.interpolate(track.inner.project(near_c))
    near_out = track.outer.interpolate(track.outer.project(near_c))
    h = math.radians(row["heading"])
    ox, oy = x - FRONT_OF_CAR * math.cos(h), y - FRONT_OF_CAR * math.sin(h)
    wheels = [Point(ox + wx * math.cos(h) - wy * math.sin(h), oy + wx * math.sin(h) + wy * math.cos(h)) for wx, wy in WHEELS]
    on = [track.road.contains(p) for p in wheels]
    out = {
        "waypoints": [list(p) for p in track.center.coords],
        "track_length": track.center.length,
        "closest_waypoints": track.prev_next(ndist),
        "distance_from_center": near_c.distance(pt),
        "is_left_of_center": (near_in.distance(pt) < near_out.distance(pt)) ^ (not track.is_ccw),
        "track_width": near_in.distance(near_out),
        "projection_distance": ndist * track.center.length,
        "is_reversed": track.reversed,
        "all_wheels_on_track": all(on),
        "is_offtrack": not any(on),
    }
    if prev_progress is not None:
        out["progress"] = compute_current_prog(ndist, prev_progress)  # evaluation: start_ndist 0
    return out


def differs(got, want):
    if isinstance(want, bool) or isinstance(want, int):
        return 0.0 if got == want else math.inf
    if isinstance(want, float):
        return abs(got - want)
    if isinstance(want, list):
        if len(got) != len(want):
            return math.inf
        return max((differs(g, w) for g, w in zip(got, want)), default=0.0)
    raise TypeError(want)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("track")
    ap.add_argument("params")
    ap.add_argument("--reversed", action="store_true")
    a = ap.parse_args()
    track = Track(a.track, a.reversed)
    worst, counts, prev = {}, {}, None
    rows = [json.loads(line) for line in open(a.params)]
    if not rows:
        sys.exit(f"{a.params}: no params recorded")
    for n, row in enumerate(rows):
        # progress chains on the previous step's; a gap in `steps` (the prepare or pause
        # steps, where the reward function is not called) breaks the chain.
        chained = prev is not None and row["steps"] == prev["steps"] + 1
        prev_progress = (0.0 if prev["progress"] >= 100.0 else prev["progress"]) if chained else None
        for key, want in expected(track, row, prev_progress).items():
            d = differs(row[key], want)
            if d > TOL:
                sys.exit(f"{a.params} row {n} (steps {row['steps']}): {key} = {row[key]!r}, shapely gives {want!r}")
            worst[key] = max(worst.get(key, 0.0), d)
            counts[key] = counts.get(key, 0) + 1
        prev = row
    for key in sorted(worst):
        print(f"{key:22} {counts[key]:6} rows  max difference {worst[key]:.3g}")
    print(f"OK: {len(rows)} steps agree with shapely ({a.track}{' reversed' if a.reversed else ''})")


if __name__ == "__main__":
    main()
