//! DeepRacer's simulated LiDAR and its observation filters (simapp's `sensors/constants.py`,
//! `racecar.gazebo`, and the input filters of `sagemaker_graph_manager.py`).
//!
//! The sensor: 64 rays from −150° to +150° in the laser's frame, which is mounted 0.02913 m
//! ahead of the car's origin and turned 180°, so ray 0 points 30° left of straight ahead, the
//! scan runs round the back, and the blind 60° faces forward (the camera's side). Ranges
//! 0.15–12 m, Gaussian noise σ 0.01 m; a ray that hits nothing in range reads infinity. The
//! rays hit the race's objects (boxes and bot cars): DeepRacer's tracks have no walls at the
//! LiDAR's height.
//!
//! The filters turn a scan into the network's input: `LIDAR` clips to [0.15, 1.0] m;
//! `SECTOR_LIDAR` and `DISCRETIZED_SECTOR_LIDAR` take the nearest reading of each sector of
//! consecutive rays and one-hot encode its distance bin ([`sectors`]).
//!
//! The environment scans once a step when the observation has the LiDAR
//! (`observation.camera_lidar`, set from `model_metadata.json`); [`crate::obs`] filters it.

use crate::objects::Object;
use rand::Rng;
use rand_distr::{Distribution, Normal};
use tracks::P2;

/// Rays per scan.
pub const RAYS: usize = 64;
/// The first and last rays' angles in the laser frame (rad, ±150°).
pub const HALF_FOV: f64 = 2.61799;
/// Shortest and longest readings (m).
pub const RANGE: (f64, f64) = (0.15, 12.0);
/// Reading noise, standard deviation (m).
pub const NOISE: f64 = 0.01;
/// The laser's mount ahead of the car's origin (m).
pub const MOUNT_AHEAD: f64 = 0.02913;
/// The box obstacle's size as the LiDAR sees it, along × across (m): the model's collision box.
pub const BOX_BODY: (f64, f64) = (0.40, 0.30);

/// Ray `k`'s direction in the car's frame (rad, 0 = ahead, counter-clockwise positive).
pub fn ray_angle(k: usize) -> f64 {
    let laser = -HALF_FOV + 2.0 * HALF_FOV * k as f64 / (RAYS - 1) as f64;
    laser + std::f64::consts::PI
}

/// Distance along a ray from `o` in direction `(dx, dy)` (unit) to a rectangle of
/// `(along, across)` centred at `at` facing `heading`; `None` if it misses (0 from inside).
pub fn ray_rectangle(o: P2, dx: f64, dy: f64, at: P2, heading: f64, size: (f64, f64)) -> Option<f64> {
    let (s, c) = heading.sin_cos();
    let (rx, ry) = (o.x - at.x, o.y - at.y);
    // Into the rectangle's frame.
    let (ox, oy) = (rx * c + ry * s, -rx * s + ry * c);
    let (ux, uy) = (dx * c + dy * s, -dx * s + dy * c);
    let (hl, hw) = (size.0 / 2.0, size.1 / 2.0);
    let (mut t0, mut t1) = (0.0f64, f64::INFINITY);
    for (p, u, h) in [(ox, ux, hl), (oy, uy, hw)] {
        if u.abs() < 1e-12 {
            if p.abs() > h {
                return None;
            }
        } else {
            let (a, b) = ((-h - p) / u, (h - p) / u);
            t0 = t0.max(a.min(b));
            t1 = t1.min(a.max(b));
        }
    }
    (t0 <= t1).then_some(t0)
}

/// One scan from a car at `car` (origin) facing `yaw` among `objects`, with DeepRacer's noise
/// drawn from `rng`: metres, or infinity where nothing is in range.
pub fn scan(car: P2, yaw: f64, objects: &[Object], rng: &mut impl Rng) -> [f32; RAYS] {
    let noise = Normal::new(0.0, NOISE).expect("a positive deviation");
    let o = P2::new(car.x + MOUNT_AHEAD * yaw.cos(), car.y + MOUNT_AHEAD * yaw.sin());
    let mut out = [f32::INFINITY; RAYS];
    for (k, r) in out.iter_mut().enumerate() {
        let a = yaw + ray_angle(k);
        let (dx, dy) = (a.cos(), a.sin());
        let hit = objects
            .iter()
            .filter_map(|b| {
                let size = if b.car { (b.footprint.1, b.footprint.0) } else { BOX_BODY };
                ray_rectangle(o, dx, dy, b.pose.position, b.pose.heading, size)
            })
            .fold(f64::INFINITY, f64::min);
        let d = hit + noise.sample(rng);
        if (RANGE.0..=RANGE.1).contains(&d) {
            *r = d as f32;
        }
    }
    out
}

pub use policy::metadata::{clipped, sectors};

#[cfg(test)]
mod tests {
    use super::*;
    use crate::objects::Kind;
    use rand::SeedableRng;
    use tracks::objects::{BOX_FOOTPRINT, CAR_FOOTPRINT, Lane, ObjectPose};

    fn object(x: f64, y: f64, heading: f64, car: bool) -> Object {
        Object {
            kind: if car { Kind::Bot } else { Kind::Obstacle },
            pose: ObjectPose { position: P2::new(x, y), heading, along: 0.0, lane: Lane::Inner },
            footprint: if car { CAR_FOOTPRINT } else { BOX_FOOTPRINT },
            car,
        }
    }

    /// Issue 31: the rays run round the back from 30 degrees left.
    #[test]
    fn the_rays_run_round_the_back_from_30_degrees_left() {
        assert!((ray_angle(0).to_degrees() - 30.0).abs() < 1e-3);
        assert!((ray_angle(63).to_degrees() - 330.0).abs() < 1e-3);
        // Rays 31 and 32 straddle straight behind.
        assert!(ray_angle(31).to_degrees() < 180.0 && ray_angle(32).to_degrees() > 180.0);
    }

    /// Issue 31: rays hit rectangles where the geometry says.
    #[test]
    fn rays_hit_rectangles_where_the_geometry_says() {
        let o = P2::new(0.0, 0.0);
        // A 0.4 × 0.3 box 2 m ahead along x: its near face at 1.8 m.
        assert_eq!(ray_rectangle(o, 1.0, 0.0, P2::new(2.0, 0.0), 0.0, (0.4, 0.3)), Some(1.8));
        // Turned 90°, the 0.3 m side faces the ray: 1.85 m.
        let d = ray_rectangle(o, 1.0, 0.0, P2::new(2.0, 0.0), std::f64::consts::FRAC_PI_2, (0.4, 0.3)).unwrap();
        assert!((d - 1.85).abs() < 1e-12);
        // Beside the ray, or behind its origin: missed.
        assert_eq!(ray_rectangle(o, 1.0, 0.0, P2::new(2.0, 0.2), 0.0, (0.4, 0.3)), None);
        assert_eq!(ray_rectangle(o, 1.0, 0.0, P2::new(-2.0, 0.0), 0.0, (0.4, 0.3)), None);
        // From inside: 0.
        assert_eq!(ray_rectangle(o, 1.0, 0.0, o, 0.3, (0.4, 0.3)), Some(0.0));
    }

    /// Issue 31: a scan sees a box behind and a car beside but not ahead.
    #[test]
    fn a_scan_sees_a_box_behind_and_a_car_beside_but_not_ahead() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(1);
        // The car at the origin facing +x. A box 1 m behind the laser: its face 0.8 m away.
        let behind = [object(-1.0 + MOUNT_AHEAD, 0.0, 0.0, false)];
        let s = scan(P2::new(0.0, 0.0), 0.0, &behind, &mut rng);
        for k in [31, 32] {
            assert!((s[k] - 0.8).abs() < 0.05, "ray {k}: {}", s[k]);
        }
        assert!(s[0].is_infinite() && s[63].is_infinite());
        // A box straight ahead sits in the blind cone: nothing.
        let ahead = [object(1.0, 0.0, 0.0, false)];
        assert!(scan(P2::new(0.0, 0.0), 0.0, &ahead, &mut rng).iter().all(|d| d.is_infinite()));
        // A bot car 0.5 m to the left, along the car: its side (the footprint's width) at
        // 0.5 − 0.098 m from the laser on the ray pointing left (90°: between rays 12 and 13).
        let beside = [object(MOUNT_AHEAD, 0.5, 0.0, true)];
        let s = scan(P2::new(0.0, 0.0), 0.0, &beside, &mut rng);
        let k = (0..RAYS).min_by(|&a, &b| s[a].total_cmp(&s[b])).unwrap();
        assert!((11..=13).contains(&k), "nearest on ray {k}");
        assert!((s[k] as f64 - (0.5 - CAR_FOOTPRINT.0 / 2.0)).abs() < 0.05, "{}", s[k]);
        // Too near reads infinity (under 0.15 m), as Gazebo's ray sensor does.
        let touching = [object(-0.2, 0.0, 0.0, false)];
        let s = scan(P2::new(0.0, 0.0), 0.0, &touching, &mut rng);
        assert!(s[31].is_infinite() && s[32].is_infinite());
    }

    /// Issue 31: the LiDAR filters match DeepRacer's on hand-computed scans.
    #[test]
    fn the_lidar_filters_match_deepracers_on_hand_computed_scans() {
        let mut scan = [f32::INFINITY; RAYS];
        scan[3] = 0.3; // sector 0
        scan[20] = 0.6; // sector 2
        scan[40] = 0.05; // sector 5 (below range: as given)
        scan[63] = 1.7; // sector 7
        // LIDAR: clipped to [0.15, 1.0], infinity reads 1.0.
        let c = clipped(&scan);
        assert_eq!((c[3], c[20], c[40], c[63], c[0]), (0.3, 0.6, 0.15, 1.0, 1.0));
        // SECTOR_LIDAR: 8 sectors, 1 value, 0.5 m: 1 where something is nearer than 0.5 m.
        assert_eq!(sectors(&scan, 8, 1, 0.5), [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0]);
        // DISCRETIZED_SECTOR_LIDAR's default: 8 sectors × 8 values, 2.0 m (bins of 0.25 m).
        let d = sectors(&scan, 8, 8, 2.0);
        assert_eq!(d.len(), 64);
        let hot: Vec<(usize, usize)> =
            d.iter().enumerate().filter(|(_, v)| **v == 1.0).map(|(i, _)| (i / 8, i % 8)).collect();
        assert_eq!(hot, [(0, 1), (2, 2), (5, 0), (7, 6)]);
        // Nothing within the clip: all zeros.
        assert!(sectors(&[f32::INFINITY; RAYS], 8, 8, 2.0).iter().all(|v| *v == 0.0));
    }
}
