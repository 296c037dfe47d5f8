//! Objects on the track, as DeepRacer's simapp places and tests them: where obstacles go
//! (`ObstaclesCtrl._compute_obstacle_poses`), their footprints and the car's
//! (`track_geom/constants.py ObstacleDimensions`), the crash rule
//! (`TrackData.get_collided_object_name`), the start lane beside an object
//! (`_get_car_start_model_state`) and `closest_objects` (`get_object_reward_params`).
//!
//! Lanes are the quarter-width lines between the centre line and each border, row by row.
//! DeepRacer's lane numbers: `-1` is the outer lane, anything else the inner one (the simapp's
//! code; deepracer-for-cloud's documentation reads the other way round, the code wins).
//!
//! One deliberate difference: the simapp converts the minimum gap between obstacles from
//! percent of the track's length to metres *in place*, so every episode shrinks it again
//! (2 % of a 17.7 m track is 0.354 m, then 0.063 m, then 0.011 m…). Here the gap is what
//! DeepRacer documents, `MIN_DISTANCE_BETWEEN_OBSTACLES` percent of the length, every episode.

use crate::geometry::{P2, Polyline, Track};
use rand::Rng;
use rand::seq::SliceRandom;

/// The logical footprint of a box obstacle, across × along its heading (m): DeepRacer's
/// `BOX_OBSTACLE_DIMENSION` (0.4 × 0.4 box plus a 0.1 m buffer along).
pub const BOX_FOOTPRINT: (f64, f64) = (0.4, 0.5);
/// A car's footprint, across × along (m): DeepRacer's `BOT_CAR_DIMENSION`, for bots and the
/// racing car alike.
pub const CAR_FOOTPRINT: (f64, f64) = (0.1961, 0.32352);
/// How near an object must be to the start for the car to start in the other lane (m,
/// DeepRacer's `CLOSEST_OBJ_GAP`).
pub const START_GAP: f64 = 1.0;
/// Obstacles end this far before the end of the centre line (m).
const END_MARGIN: f64 = 1.0;
/// The least centre-line distance between neighbouring obstacles in opposite lanes that a car
/// can weave through (m). A car clear of a box stands 0.11 m past the centre line on the other
/// side (the box covers the centre line by 0.01 m, half the car is 0.098 m): from one side to
/// the other is 0.22 m across, which at the tightest steering (0.28 m radius) takes 0.45 m
/// along, after the first box's 0.5 m footprint and the car's own 0.32 m: 1.27 m.
pub const PASSABLE_GAP: f64 = 1.3;

/// A lane.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Lane {
    /// Between the centre line and the inner border.
    Inner,
    /// Between the centre line and the outer border.
    Outer,
}

impl Lane {
    /// DeepRacer's lane number (`OBJECT_POSITIONS`' second field): `-1` outer, else inner.
    pub fn from_number(n: i64) -> Lane {
        if n == -1 { Lane::Outer } else { Lane::Inner }
    }

    /// The other lane.
    pub fn other(self) -> Lane {
        match self {
            Lane::Inner => Lane::Outer,
            Lane::Outer => Lane::Inner,
        }
    }
}

/// Where an object stands.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ObjectPose {
    /// Its centre.
    pub position: P2,
    /// Its heading (radians): its lane's direction.
    pub heading: f64,
    /// Its distance along the centre line (m) from waypoint 0 of the driving direction.
    pub along: f64,
    /// Its lane.
    pub lane: Lane,
}

/// How obstacles are placed.
#[derive(Clone, Debug, PartialEq)]
pub enum Placement {
    /// At fractions of the track's length, each in its lane (`OBJECT_POSITIONS`); the same
    /// every episode.
    Fixed(Vec<(f64, Lane)>),
    /// `count` obstacles from `min_gap_percent` of the length to 1 m before its end, at least
    /// that gap apart: evenly spaced in alternating lanes (inner first), or, `random`, each
    /// moved at random within its neighbours' gaps into a random lane, every episode.
    Spaced {
        /// How many.
        count: usize,
        /// The smallest gap between two obstacles, in percent of the track's length.
        min_gap_percent: f64,
        /// Random positions and lanes, drawn anew every episode.
        random: bool,
    },
}

/// Why obstacles cannot be placed; the message names DeepRacer's key.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("{0}")]
pub struct PlacementError(pub String);

impl Track {
    /// The lane's line.
    pub fn lane(&self, lane: Lane) -> &Polyline {
        match lane {
            Lane::Inner => &self.lanes[0],
            Lane::Outer => &self.lanes[1],
        }
    }

    /// The pose in `lane` beside the centre-line point at distance `along`: that point
    /// projected onto the lane, facing along it.
    pub fn lane_pose(&self, lane: Lane, along: f64) -> ObjectPose {
        let line = self.lane(lane);
        let p = line.project(self.center().interpolate(along));
        ObjectPose { position: p.point, heading: line.direction_at(p.along), along, lane }
    }
}

/// The obstacles' poses for one episode (`rng` draws the random ones).
pub fn place(track: &Track, placement: &Placement, rng: &mut impl Rng) -> Result<Vec<ObjectPose>, PlacementError> {
    let len = track.length();
    match placement {
        Placement::Fixed(at) => at
            .iter()
            .map(|&(f, lane)| {
                if !(0.0..1.0).contains(&f) {
                    return Err(PlacementError(format!(
                        "OBJECT_POSITIONS: {f} is not a fraction of the track's length (0 to 1, 1 excluded)"
                    )));
                }
                Ok(track.lane_pose(lane, f * len))
            })
            .collect(),
        &Placement::Spaced { count, min_gap_percent, random } => {
            if count == 0 {
                return Ok(vec![]);
            }
            if !(min_gap_percent.is_finite() && min_gap_percent >= 0.0) {
                return Err(PlacementError(format!(
                    "MIN_DISTANCE_BETWEEN_OBSTACLES is {min_gap_percent}; expected a percentage of the track's length"
                )));
            }
            let gap = min_gap_percent / 100.0 * len;
            let (start, end) = (gap, len - END_MARGIN);
            let fits = if count == 1 { start <= end } else { (end - start) / (count - 1) as f64 >= gap };
            if !fits {
                let most = if gap > 0.0 { ((end - start) / gap).floor() as i64 + 1 } else { 1 };
                return Err(PlacementError(format!(
                    "NUMBER_OF_OBSTACLES is {count}, but {} ({len:.1} m) holds at most {} obstacles {gap:.2} m apart \
                     (MIN_DISTANCE_BETWEEN_OBSTACLES {min_gap_percent} % of its length)",
                    track.name(),
                    most.max(0)
                )));
            }
            let mut d: Vec<f64> = if count == 1 {
                vec![start]
            } else {
                (0..count).map(|i| start + (end - start) * i as f64 / (count - 1) as f64).collect()
            };
            let lanes: Vec<Lane> = if random {
                let mut order: Vec<usize> = (0..count).collect();
                order.shuffle(rng);
                for i in order {
                    let lo = if i == 0 { start } else { d[i - 1] + gap };
                    let hi = if i == count - 1 { end } else { d[i + 1] - gap };
                    if lo < hi {
                        d[i] = rng.random_range(lo..hi);
                    }
                }
                (0..count).map(|_| if rng.random::<bool>() { Lane::Inner } else { Lane::Outer }).collect()
            } else {
                (0..count).map(|i| if i % 2 == 0 { Lane::Inner } else { Lane::Outer }).collect()
            };
            Ok(d.iter().zip(lanes).map(|(&along, lane)| track.lane_pose(lane, along)).collect())
        }
    }
}

/// Whether a car can get past every obstacle of `poses`: no two neighbours along the lap
/// (the last and the first included) stand in opposite lanes under [`PASSABLE_GAP`] apart.
pub fn passable(track: &Track, poses: &[ObjectPose]) -> bool {
    let len = track.length();
    let mut sorted: Vec<&ObjectPose> = poses.iter().collect();
    sorted.sort_by(|a, b| a.along.total_cmp(&b.along));
    let n = sorted.len();
    n < 2
        || (0..n).all(|i| {
            let (a, b) = (sorted[i], sorted[(i + 1) % n]);
            a.lane == b.lane || (b.along - a.along).rem_euclid(len) >= PASSABLE_GAP
        })
}

/// The four corners of a footprint (`across` × `along` metres) centred at `at`, facing
/// `heading`.
pub fn corners(at: P2, heading: f64, footprint: (f64, f64)) -> [P2; 4] {
    let (hw, hl) = (footprint.0 / 2.0, footprint.1 / 2.0);
    let (s, c) = heading.sin_cos();
    [(hl, hw), (hl, -hw), (-hl, -hw), (-hl, hw)].map(|(x, y)| P2::new(at.x + x * c - y * s, at.y + x * s + y * c))
}

/// Whether `p` lies strictly inside the footprint centred at `at` facing `heading` (shapely's
/// `contains`: the boundary is outside).
pub fn inside(p: P2, at: P2, heading: f64, footprint: (f64, f64)) -> bool {
    let (s, c) = heading.sin_cos();
    let d = p - at;
    let (x, y) = (d.x * c + d.y * s, -d.x * s + d.y * c);
    x.abs() < footprint.1 / 2.0 && y.abs() < footprint.0 / 2.0
}

/// The crash rule: the first object (index into `objects`: position, heading, footprint)
/// with any of the car's four corners inside it. The car's rectangle is [`CAR_FOOTPRINT`]
/// around its model pose. An object narrower than the car that sits between two of its
/// corners is not a crash, as in DeepRacer.
pub fn crashed(car: P2, car_heading: f64, objects: &[(P2, f64, (f64, f64))]) -> Option<usize> {
    let cs = corners(car, car_heading, CAR_FOOTPRINT);
    objects.iter().position(|&(at, h, fp)| cs.iter().any(|&p| inside(p, at, h, fp)))
}

/// The lane a car starts in when an object is within [`START_GAP`] of its start (`None`: the
/// centre line), as the simapp's training start: the lane other than that object's. The
/// simapp's test, `|object − start| % L < gap`, does not look across the start line; neither
/// does this.
pub fn start_lane(track: &Track, start_along: f64, objects: &[ObjectPose]) -> Option<Lane> {
    let len = track.length();
    objects.iter().find(|o| (o.along - start_along).abs() % len < START_GAP).map(|o| o.lane.other())
}

/// DeepRacer's `closest_objects`: `[previous, next]` object indices (into `distances`, the
/// objects' distances along the centre line) around the car's distance `car_along`. The next
/// object is the nearest one strictly ahead; the previous the one before it in track order;
/// both wrap around the lap. No or one object: `[0, 0]`.
pub fn closest_objects(distances: &[f64], car_along: f64) -> [usize; 2] {
    let n = distances.len();
    if n == 0 {
        return [0, 0];
    }
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&a, &b| distances[a].total_cmp(&distances[b]));
    let next = order.partition_point(|&i| distances[i] <= car_along);
    let next_i = order[next % n];
    let prev_i = order[(next + n - 1) % n];
    [prev_i, next_i]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Direction;
    use rand::SeedableRng;

    fn base() -> Track {
        crate::world("reinvent_base").unwrap().track(Direction::Forward)
    }

    /// Issue 55: a layout is passable unless neighbours in opposite lanes (across the start line
    /// too) stand under 1.3 m apart.
    #[test]
    fn a_layout_is_passable_unless_neighbours_in_opposite_lanes_stand_too_near() {
        let t = base();
        let len = t.length();
        let (i, o) = (Lane::Inner, Lane::Outer);
        for (at, want) in [
            (vec![(5.0, i), (6.0, o)], false),
            (vec![(5.0, i), (6.4, o)], true),
            (vec![(5.0, i), (5.5, i)], true),
            (vec![(9.0, o), (5.0, i), (6.2, o)], false),
            (vec![(0.5, i), (len - 0.4, o)], false),
            (vec![(2.0, i), (len - 0.4, o)], true),
            (vec![(5.0, i)], true),
        ] {
            let poses: Vec<ObjectPose> = at.iter().map(|&(a, l)| t.lane_pose(l, a)).collect();
            assert_eq!(passable(&t, &poses), want, "{at:?}");
        }
    }

    /// Issue 31: fixed positions are fractions of the length in DeepRacer's lanes.
    #[test]
    fn fixed_positions_are_fractions_of_the_length_in_deepracers_lanes() {
        let t = base();
        let len = t.length();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        let at = vec![(0.23, Lane::from_number(-1)), (0.46, Lane::from_number(1)), (0.7, Lane::from_number(0))];
        let p = place(&t, &Placement::Fixed(at), &mut rng).unwrap();
        assert_eq!(p.iter().map(|o| o.lane).collect::<Vec<_>>(), [Lane::Outer, Lane::Inner, Lane::Inner]);
        for (o, f) in p.iter().zip([0.23, 0.46, 0.7]) {
            assert!((o.along - f * len).abs() < 1e-9);
            // On its lane: a quarter of the width from the centre line, on its side (the
            // inner border is on the left of a counter-clockwise lap).
            let q = t.query(o.position);
            assert!(t.lane(o.lane).project(o.position).distance < 1e-6, "{o:?}");
            assert!((q.distance_from_center - q.track_width / 4.0).abs() < 0.05, "{q:?}");
            assert_eq!(q.is_left_of_center, (o.lane == Lane::Inner) == t.is_ccw(), "{o:?}");
        }
        for bad in [1.0, -0.1, f64::NAN] {
            let e = place(&t, &Placement::Fixed(vec![(bad, Lane::Inner)]), &mut rng).unwrap_err();
            assert!(e.0.contains("OBJECT_POSITIONS"), "{e}");
        }
    }

    /// Issue 31: spaced obstacles keep DeepRacer's documented gap every episode.
    #[test]
    fn spaced_obstacles_keep_deepracers_documented_gap_every_episode() {
        let t = base();
        let len = t.length();
        let gap = 0.02 * len;
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2);
        // Evenly: linspace(gap, L − 1, N), lanes inner, outer, inner…
        let even = place(&t, &Placement::Spaced { count: 3, min_gap_percent: 2.0, random: false }, &mut rng).unwrap();
        let want = [gap, (gap + len - 1.0) / 2.0, len - 1.0];
        for (o, w) in even.iter().zip(want) {
            assert!((o.along - w).abs() < 1e-9, "{o:?} {w}");
        }
        assert_eq!(even.iter().map(|o| o.lane).collect::<Vec<_>>(), [Lane::Inner, Lane::Outer, Lane::Inner]);
        // Randomly: 200 episodes, each within [gap, L − 1] and at least the gap apart (it does
        // not shrink), positions and lanes varying.
        let spec = Placement::Spaced { count: 6, min_gap_percent: 2.0, random: true };
        let mut lanes_seen = [false; 2];
        let mut firsts = vec![];
        for _ in 0..200 {
            let p = place(&t, &spec, &mut rng).unwrap();
            for w in p.windows(2) {
                assert!(w[1].along - w[0].along >= gap - 1e-9, "{p:?}");
            }
            assert!(p[0].along >= gap - 1e-9 && p[5].along <= len - 1.0 + 1e-9);
            for o in &p {
                lanes_seen[(o.lane == Lane::Outer) as usize] = true;
            }
            firsts.push(p[0].along);
        }
        assert!(lanes_seen == [true, true]);
        assert!(firsts.iter().any(|f| (f - firsts[0]).abs() > 0.1), "random positions move");
        // The same seed, the same episode.
        let a = place(&t, &spec, &mut rand_chacha::ChaCha8Rng::seed_from_u64(9)).unwrap();
        let b = place(&t, &spec, &mut rand_chacha::ChaCha8Rng::seed_from_u64(9)).unwrap();
        assert_eq!(a, b);
    }

    /// Issue 31: more obstacles than the track holds are refused naming the keys.
    #[test]
    fn more_obstacles_than_the_track_holds_are_refused_naming_the_keys() {
        let t = base();
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(3);
        // 10 % gaps on a lap: at most 9 or 10 fit between 10 % and L − 1 m.
        let e = place(&t, &Placement::Spaced { count: 12, min_gap_percent: 10.0, random: true }, &mut rng).unwrap_err();
        assert!(e.0.contains("NUMBER_OF_OBSTACLES is 12") && e.0.contains("MIN_DISTANCE_BETWEEN_OBSTACLES"), "{e}");
        assert!(
            place(&t, &Placement::Spaced { count: 0, min_gap_percent: 2.0, random: true }, &mut rng)
                .unwrap()
                .is_empty()
        );
    }

    /// Issue 31: the crash rule is a car corner inside an object.
    #[test]
    fn the_crash_rule_is_a_car_corner_inside_an_object() {
        let o = P2::new(0.0, 0.0);
        let boxed = |at: P2, h: f64| crashed(at, h, &[(o, 0.0, BOX_FOOTPRINT)]);
        // (car position, car heading, crashed?) against a box at the origin facing +x
        // (0.5 m along x, 0.4 m across y). The car is 0.3235 m long, 0.1961 m wide.
        let half_car = CAR_FOOTPRINT.1 / 2.0;
        for (x, y, h, want) in [
            (0.0, 0.0, 0.0, true),                           // on top of it
            (-0.25 - half_car + 0.01, 0.0, 0.0, true),       // its nose 1 cm into the back
            (-0.25 - half_car - 0.01, 0.0, 0.0, false),      // 1 cm short
            (0.0, 0.2 + 0.098 + 0.01, 0.0, false),           // beside it, 1 cm clear
            (0.0, 0.2 + 0.098 - 0.01, 0.0, true),            // beside it, 1 cm in
            (-0.4, 0.0, std::f64::consts::FRAC_PI_2, false), // across, clear behind
        ] {
            assert_eq!(boxed(P2::new(x, y), h).is_some(), want, "car at ({x}, {y}) heading {h}");
        }
        // A narrow object between two of the car's corners is not a crash (DeepRacer tests
        // the car's corners only).
        assert_eq!(crashed(o, 0.0, &[(o, 0.0, (0.05, 0.05))]), None);
        // The first object hit is named.
        let far = (P2::new(5.0, 0.0), 0.0, BOX_FOOTPRINT);
        assert_eq!(crashed(o, 0.0, &[far, (o, 0.0, BOX_FOOTPRINT)]), Some(1));
    }

    /// Issue 31: closest objects wrap around the lap.
    #[test]
    fn closest_objects_wrap_around_the_lap() {
        // Objects at 5, 12, 2 m (unsorted, as the simapp's list is).
        let d = [5.0, 12.0, 2.0];
        for (car, want) in [
            (0.0, [1, 2]), // before every object: previous is the farthest
            (2.0, [2, 0]), // exactly at one: it is behind (bisect_right)
            (3.0, [2, 0]),
            (6.0, [0, 1]),
            (13.0, [1, 2]), // past every object: next is the nearest
        ] {
            assert_eq!(closest_objects(&d, car), want, "car at {car}");
        }
        assert_eq!(closest_objects(&[4.0], 1.0), [0, 0]);
        assert_eq!(closest_objects(&[], 1.0), [0, 0]);
    }

    /// Issue 31: the car starts in the other lane beside an object.
    #[test]
    fn the_car_starts_in_the_other_lane_beside_an_object() {
        let t = base();
        let objs = [t.lane_pose(Lane::Inner, 0.5), t.lane_pose(Lane::Outer, 8.0)];
        assert_eq!(start_lane(&t, 0.0, &objs), Some(Lane::Outer));
        assert_eq!(start_lane(&t, 8.6, &objs), Some(Lane::Inner));
        assert_eq!(start_lane(&t, 4.0, &objs), None);
    }
}
