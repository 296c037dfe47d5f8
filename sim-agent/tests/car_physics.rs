//! The car against a kinematic bicycle model, on every surface (issue 2).

use sim_agent::car::{Car, CarParams};
use tracks::Surface;

const DT: f64 = 1.0 / 60.0;

/// Drive with fixed steering and speed for 6 s, then average 2 s: (speed, turning radius at the chassis origin).
fn circle(surface: Surface, steer_deg: f64, speed: f64) -> (f64, f64) {
    let mut car = Car::new(&CarParams::default(), surface.friction(), DT);
    car.reset(1.0, 2.0, 0.3);
    let steer = steer_deg.to_radians();
    for _ in 0..(6.0 / DT) as usize {
        car.step(steer, speed);
    }
    let (mut v, mut w) = (0.0, 0.0);
    let n = (2.0 / DT) as usize;
    for _ in 0..n {
        car.step(steer, speed);
        let s = car.state();
        v += s.forward_speed.hypot(s.lateral_speed);
        w += s.yaw_rate;
    }
    let (v, w) = (v / n as f64, w / n as f64);
    (v, v / w)
}

/// Kinematic bicycle: the rear axle turns on L / tan(δ); the chassis origin sits `b` ahead of it.
/// Signed: + = left (counter-clockwise).
fn bicycle_radius(steer_deg: f64) -> f64 {
    let p = CarParams::default();
    let rear = p.wheelbase / steer_deg.to_radians().tan();
    let b = p.wheelbase - p.front_axle_x;
    rear.hypot(b).copysign(steer_deg)
}

#[test]
fn low_speed_turning_matches_the_bicycle_model_within_5_percent_on_every_surface() {
    for surface in Surface::ALL {
        for (steer, speed) in [(10.0, 0.5), (20.0, 0.5), (30.0, 0.5), (-30.0, 0.5), (15.0, 1.0)] {
            let (v, r) = circle(surface, steer, speed);
            let want = bicycle_radius(steer);
            let ratio = r / want;
            assert!(
                (ratio - 1.0).abs() < 0.05,
                "{surface:?} steer {steer} speed {speed}: radius {r:.3} vs bicycle {want:.3}"
            );
            assert!((v - speed).abs() < 0.05 * speed, "{surface:?}: speed {v} vs {speed}");
        }
    }
}

#[test]
fn top_speed_is_reached_on_every_surface() {
    for surface in Surface::ALL {
        let mut car = Car::new(&CarParams::default(), surface.friction(), DT);
        car.reset(0.0, 0.0, 0.0);
        for _ in 0..(3.0 / DT) as usize {
            car.step(0.0, 4.0);
        }
        let s = car.state();
        assert!((s.forward_speed - 4.0).abs() < 0.02 * 4.0, "{surface:?}: {}", s.forward_speed);
        assert!(s.yaw.abs() < 1e-3 && s.lateral_speed.abs() < 1e-3, "{surface:?} drives straight: {s:?}");
    }
}

#[test]
fn grip_differs_between_surfaces_when_cornering_hard() {
    // 20° at 2.5 m/s asks for ~14 m/s² of lateral acceleration: more than any surface gives.
    let mut by_grip: Vec<(f64, f64)> = Surface::ALL.iter().map(|&s| (s.friction(), circle(s, 20.0, 2.5).1)).collect();
    by_grip.sort_by(|a, b| a.0.total_cmp(&b.0));
    for w in by_grip.windows(2) {
        assert!(w[0].1 > w[1].1 * 1.03, "less grip, wider circle: {by_grip:?}");
    }
    // And every radius exceeds the kinematic one: the tyres slide.
    assert!(by_grip.iter().all(|&(_, r)| r > bicycle_radius(20.0) * 1.1), "{by_grip:?}");
}
