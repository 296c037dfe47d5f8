//! DeepRacer's geometric queries: a hand-derived table on a rectangle, and agreement with
//! the plain full-scan implementation on every built-in track in both directions.

use crate::common::{f8_rows, rectangle_rows};
use rand::{Rng, SeedableRng};
use tracks::{Direction, P2, Track, compute_progress, parse_track_npy, world_names};

fn rectangle(direction: Direction) -> Track {
    let rows = parse_track_npy(&f8_rows(&rectangle_rows()), "rect.npy").unwrap();
    Track::new("rect", &rows, direction)
}

/// (direction, x, y) -> (ndist, distance_from_center, closest_waypoints, left, width, on road)
#[test]
#[allow(clippy::type_complexity)] // one row per case, as a table
fn rectangle_table_derived_by_hand() {
    use Direction::*;
    let table: &[(Direction, f64, f64, f64, f64, [usize; 2], bool, f64, bool)] = &[
        // On the bottom edge, inside of the loop (left when driving CCW).
        (Forward, 1.0, 0.2, 1.0 / 12.0, 0.2, [0, 1], true, 1.0, true),
        // Outside the bottom edge: right of centre, still on the road.
        (Forward, 1.0, -0.3, 1.0 / 12.0, 0.3, [0, 1], false, 1.0, true),
        // Right edge, outside the loop: along = 4 + 1.
        (Forward, 4.2, 1.0, 5.0 / 12.0, 0.2, [1, 2], false, 1.0, true),
        // Top edge, inside: along = 4 + 2 + 2.5.
        (Forward, 1.5, 1.7, 8.5 / 12.0, 0.3, [2, 3], true, 1.0, true),
        // Off the road: beyond the outer border, and inside the infield.
        (Forward, 2.0, -0.7, 2.0 / 12.0, 0.7, [0, 1], false, 1.0, false),
        (Forward, 2.0, 1.0, 2.0 / 12.0, 1.0, [0, 1], true, 1.0, false),
        // Reversed: the order is (0,0) (0,2) (4,2) (4,0) (0,0); the same point is near the end.
        (Reversed, 1.0, 0.2, 11.0 / 12.0, 0.2, [3, 4], false, 1.0, true),
        (Reversed, 1.0, -0.3, 11.0 / 12.0, 0.3, [3, 4], true, 1.0, true),
        (Reversed, -0.2, 1.0, 1.0 / 12.0, 0.2, [0, 1], true, 1.0, true),
    ];
    for &(dir, x, y, ndist, dist, wps, left, width, on_road) in table {
        let t = rectangle(dir);
        let q = t.query(P2::new(x, y));
        let ctx = format!("{dir:?} ({x}, {y}): {q:?}");
        assert!((q.ndist - ndist).abs() < 1e-12, "{ctx}");
        assert!((q.distance_from_center - dist).abs() < 1e-12, "{ctx}");
        assert_eq!(q.closest_waypoints, wps, "{ctx}");
        assert_eq!(q.is_left_of_center, left, "{ctx}");
        assert!((q.track_width - width).abs() < 1e-12, "{ctx}");
        assert_eq!(t.on_road(P2::new(x, y)), on_road, "{ctx}");
    }
}

#[test]
fn progress_follows_deepracer_compute_current_prog() {
    // (ndist - start_ndist, previous progress, expected)
    let table = [
        (0.0, 0.0, 0.0),
        (0.25, 20.0, 25.0),
        (-0.75, 20.0, 25.0),  // past the file's end: wrapped
        (-0.01, 0.0, -1.0),   // just behind the start line
        (0.99, 0.0, -1.0),    // the same place seen without wrap
        (-0.005, 99.0, 99.5), // about to finish
        (0.0, 99.8, 100.0),   // crossed the line: lap complete
        (0.02, 99.8, 100.0),  // clamped
    ];
    for (delta, prev, want) in table {
        let got = compute_progress(delta, prev);
        assert!((got - want).abs() < 1e-9, "({delta}, {prev}): {got} != {want}");
    }
}

#[test]
fn grid_queries_agree_with_full_scans_on_every_track() {
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(2);
    for name in world_names() {
        let world = tracks::world(name).unwrap();
        for dir in [Direction::Forward, Direction::Reversed] {
            let t = world.track(dir);
            for i in 0..3000 {
                // Points near the road (most), and some far away (outside every grid).
                let along = rng.random_range(0.0..t.length());
                let (c, h) = t.pose_at(along);
                let reach = if i % 10 == 0 { 4.0 } else { 1.0 };
                let p = P2::new(c.x + rng.random_range(-reach..reach) - 0.0 * h, c.y + rng.random_range(-reach..reach));
                let (fast, slow) = (t.query(p), t.query_scan(p));
                assert_eq!(fast, slow, "{name} {dir:?} at {p:?}");
                assert_eq!(t.on_road(p), t.on_road_scan(p), "{name} {dir:?} on_road at {p:?}");
            }
        }
    }
}

#[test]
fn centre_line_points_are_on_the_road_and_heading_follows_it() {
    for name in world_names() {
        let t = tracks::world(name).unwrap().track(Direction::Forward);
        for k in 0..50 {
            let along = t.length() * (k as f64 + 0.5) / 50.0;
            let (p, _) = t.pose_at(along);
            assert!(t.on_road(p), "{name}: centre point at {along} is off the road");
            let q = t.query(p);
            assert!(q.distance_from_center < 1e-9, "{name}");
            assert!((q.ndist * t.length() - along).abs() < 1e-6, "{name}: {} vs {along}", q.ndist * t.length());
        }
    }
}
