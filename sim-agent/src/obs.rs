//! Observations: the state vector and the lidar, written into a caller's buffer.
//!
//! State vector (`kind = state`), all values roughly in [-1, 1]:
//!
//! | index | value |
//! |---|---|
//! | 0 | signed distance from the centre line / half the local width (+ = left) |
//! | 1, 2 | sin, cos of the heading error (car yaw − centre-line direction) |
//! | 3 | forward speed / 4 m/s |
//! | 4 | yaw rate / 2π rad/s |
//! | 5 | executed steering / 30° |
//! | 6 | progress / 100 |
//! | 7.. | the next K centre-line points, `lookahead_spacing` apart along the line from the car's projection, in the car frame (x forward, y left), divided by K × spacing: x₁, y₁, x₂, y₂, … |
//!
//! Lidar (`kind = lidar`): `lidar_rays` distances from the car origin to the nearest road
//! border, rays spread evenly over `lidar_fov_deg` centred on the heading (first ray on the
//! right), divided by `lidar_range` (1 = nothing within range).
//!
//! `state_lidar` concatenates both. The camera (`kind = camera`): 160×120 grayscale pixels,
//! 0–255 as floats (the model divides by 255), top row first, rendered by
//! [`crate::camera`] for a whole `VecEnv` in one batch. The stereo pair (`kind = stereo`):
//! the left and right cameras' pixels interleaved (120 × 160 × 2, channel 0 left), as
//! DeepRacer stacks them.
//!
//! DeepRacer's LiDAR beside a camera (`camera_lidar`): its filtered scan ([`crate::lidar`]),
//! before or after the pixels as DeepRacer orders the inputs (sorted by name).

use crate::config::{CameraLidar, LidarSensor, ObservationConfig, ObservationKind};
use crate::env::Env;
use tracks::P2;

/// Length of the observation vector for a configuration.
pub fn obs_dim(cfg: &ObservationConfig) -> usize {
    let state = 7 + 2 * cfg.lookahead_points;
    match cfg.kind {
        ObservationKind::State => state,
        ObservationKind::Lidar => cfg.lidar_rays,
        ObservationKind::StateLidar => state + cfg.lidar_rays,
        ObservationKind::Camera | ObservationKind::Stereo => camera_dim(cfg) + cfg.camera_lidar.map_or(0, |l| l.size()),
    }
}

/// Pixels per observation (0 without a camera).
pub fn camera_dim(cfg: &ObservationConfig) -> usize {
    let frame = (crate::camera::WIDTH * crate::camera::HEIGHT) as usize;
    match cfg.kind {
        ObservationKind::Camera => frame,
        ObservationKind::Stereo => 2 * frame,
        _ => 0,
    }
}

/// Where the camera's pixels start in an observation.
pub fn camera_offset(cfg: &ObservationConfig) -> usize {
    cfg.camera_lidar.filter(|l| l.first).map_or(0, |l| l.size())
}

/// Write `env`'s current observation into `out` (length [`obs_dim`]).
pub fn observe(env: &Env, out: &mut [f32]) {
    let cfg = &env.config().observation;
    debug_assert_eq!(out.len(), obs_dim(cfg));
    match cfg.kind {
        ObservationKind::State => state(env, cfg, out),
        ObservationKind::Lidar => lidar(env, cfg, out),
        ObservationKind::StateLidar => {
            let (s, l) = out.split_at_mut(7 + 2 * cfg.lookahead_points);
            state(env, cfg, s);
            lidar(env, cfg, l);
        }
        // Camera frames are rendered for a whole vector of environments at once
        // (`VecEnv`); a lone `Env` has no renderer.
        ObservationKind::Camera | ObservationKind::Stereo => {
            if let (Some(l), Some(scan)) = (cfg.camera_lidar, env.lidar_scan()) {
                let at = if l.first { 0 } else { camera_dim(cfg) };
                lidar_input(&l, scan, &mut out[at..at + l.size()]);
            }
        }
    }
}

/// DeepRacer's input filter for a LiDAR scan into `out` ([`CameraLidar::size`] values).
pub fn lidar_input(l: &CameraLidar, scan: &[f32], out: &mut [f32]) {
    match l.sensor {
        LidarSensor::Lidar => out.copy_from_slice(&crate::lidar::clipped(scan)),
        LidarSensor::SectorLidar | LidarSensor::DiscretizedSectorLidar => {
            out.copy_from_slice(&crate::lidar::sectors(scan, l.sectors, l.values, l.clip))
        }
    }
}

fn state(env: &Env, cfg: &ObservationConfig, out: &mut [f32]) {
    let track = env.track();
    let car = env.car_state();
    let pose = env.pose();
    let q = track.query(pose.front());
    let along = q.ndist * track.length();
    let direction = track.center().direction_at(along);
    let half = (q.track_width / 2.0).max(1e-6);
    let signed = if q.is_left_of_center { q.distance_from_center } else { -q.distance_from_center };
    let err = pose.yaw - direction;
    out[0] = (signed / half) as f32;
    out[1] = err.sin() as f32;
    out[2] = err.cos() as f32;
    out[3] = (car.forward_speed / policy::MAX_SPEED) as f32;
    out[4] = (car.yaw_rate / std::f64::consts::TAU) as f32;
    out[5] = (env.executed_steering_deg() / policy::MAX_STEERING_DEG) as f32;
    out[6] = (env.progress() / 100.0) as f32;
    let (c, s) = (pose.yaw.cos(), pose.yaw.sin());
    let scale = 1.0 / (cfg.lookahead_points as f64 * cfg.lookahead_spacing).max(1e-6);
    for k in 0..cfg.lookahead_points {
        let (p, _) = track.pose_at(along + (k + 1) as f64 * cfg.lookahead_spacing);
        let (dx, dy) = (p.x - pose.x, p.y - pose.y);
        out[7 + 2 * k] = ((c * dx + s * dy) * scale) as f32;
        out[8 + 2 * k] = ((-s * dx + c * dy) * scale) as f32;
    }
}

fn lidar(env: &Env, cfg: &ObservationConfig, out: &mut [f32]) {
    let pose = env.pose();
    let n = cfg.lidar_rays;
    let fov = cfg.lidar_fov_deg.to_radians();
    let angles: Vec<f64> = (0..n)
        .map(|i| pose.yaw - fov / 2.0 + if n > 1 { fov * i as f64 / (n - 1) as f64 } else { fov / 2.0 })
        .collect();
    let mut dist = vec![0.0; n];
    env.track().border_distances(P2::new(pose.x, pose.y), &angles, cfg.lidar_range, &mut dist);
    for (o, d) in out.iter_mut().zip(dist) {
        *o = (d / cfg.lidar_range) as f32;
    }
}
