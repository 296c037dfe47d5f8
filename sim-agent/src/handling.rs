//! The car's handling, measured on each surface: top speed, time from rest to 4 m/s,
//! stopping distance from 4 m/s, and the turning radius at full lock by speed, each beside
//! the simple model it should follow (the kinematic bicycle model for the radius, a
//! friction-limited point mass for the grip limits, under the same speed controller). `sim-agent handling` prints the table
//! that docs/simulator.md records; the tests hold the car to it and to staying upright.

use crate::car::{Car, CarParams};
use tracks::Surface;

/// Physics step of the measurements (s): DeepRacer's 60 Hz controller rate, Paddock's
/// default 15 Hz control × 4 substeps.
pub const DT: f64 = 1.0 / 60.0;
const G: f64 = 9.81;

/// What the chassis did over one manoeuvre, physics step by physics step.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Manoeuvre {
    /// Largest |roll| (degrees).
    pub max_roll_deg: f64,
    /// Largest |pitch| (degrees).
    pub max_pitch_deg: f64,
    /// Largest heading change within one physics step (degrees): a flip shows as a jump.
    pub max_heading_step_deg: f64,
    /// Lowest and highest chassis height (m).
    pub height: (f64, f64),
}

impl Manoeuvre {
    fn new(car: &Car) -> Manoeuvre {
        let h = car.height();
        Manoeuvre { height: (h, h), ..Default::default() }
    }

    fn record(&mut self, car: &Car, yaw_before: f64) {
        let (roll, pitch) = car.tilt();
        self.max_roll_deg = self.max_roll_deg.max(roll.abs().to_degrees());
        self.max_pitch_deg = self.max_pitch_deg.max(pitch.abs().to_degrees());
        let turn = tracks::wrap_degrees((car.state().yaw - yaw_before).to_degrees()).abs();
        self.max_heading_step_deg = self.max_heading_step_deg.max(turn);
        let h = car.height();
        self.height = (self.height.0.min(h), self.height.1.max(h));
    }

    fn merge(&mut self, o: &Manoeuvre) {
        self.max_roll_deg = self.max_roll_deg.max(o.max_roll_deg);
        self.max_pitch_deg = self.max_pitch_deg.max(o.max_pitch_deg);
        self.max_heading_step_deg = self.max_heading_step_deg.max(o.max_heading_step_deg);
        self.height = (self.height.0.min(o.height.0), self.height.1.max(o.height.1));
    }
}

/// Drive `seconds` holding `steer_deg` and `speed`, recording the chassis.
pub fn hold(car: &mut Car, steer_deg: f64, speed: f64, seconds: f64, m: &mut Manoeuvre) {
    for _ in 0..(seconds / DT).round() as usize {
        let yaw = car.state().yaw;
        car.step(steer_deg.to_radians(), speed);
        m.record(car, yaw);
    }
}

/// One surface's figures.
#[derive(Clone, Debug, PartialEq)]
pub struct Handling {
    /// The surface.
    pub surface: Surface,
    /// Its tyre friction coefficient.
    pub friction: f64,
    /// Speed after 4 s of a 4 m/s command from rest, straight (m/s).
    pub top_speed: f64,
    /// Time from rest to 3.9 m/s at full throttle (s).
    pub time_to_top: f64,
    /// The same for a point mass under the same speed controller, limited by friction (s).
    pub time_to_top_model: f64,
    /// Distance from a 4 m/s cruise until the speed is down to 0.15 m/s after the command
    /// drops to DeepRacer's lowest, 0.1 m/s (m).
    pub stopping_distance: f64,
    /// The same for a point mass under the same speed controller, limited by friction (m).
    pub stopping_distance_model: f64,
    /// (speed m/s, measured radius m, kinematic bicycle radius m, grip-limited radius
    /// max(bicycle, v² / μg) m) at 30° of steering, radius at the chassis origin.
    pub radius_full_lock: Vec<(f64, f64, f64, f64)>,
    /// The chassis over all the manoeuvres above.
    pub chassis: Manoeuvre,
}

/// The kinematic bicycle model's turning radius at the chassis origin for `steer_deg`.
pub fn bicycle_radius(params: &CarParams, steer_deg: f64) -> f64 {
    let rear = params.wheelbase / steer_deg.to_radians().tan().abs();
    rear.hypot(params.wheelbase - params.front_axle_x)
}

/// A point mass whose speed controller asks `m (target − v) / τ` and whose tyres give at
/// most `μ m g`: the time from rest to 3.9 m/s (target 4), and the distance from 4 m/s to
/// 0.15 m/s (target 0.1). Each is a constant-acceleration phase while the ask exceeds the
/// grip, then the controller's exponential approach.
pub fn point_mass(mu: f64, tau: f64) -> (f64, f64) {
    let a = mu * G;
    let gap = a * tau; // the speed error below which the controller asks for less than the grip
    let t_top = if gap > 0.1 { (4.0 - gap) / a + tau * (gap / 0.1).ln() } else { 3.9 / a };
    let v1 = 0.1 + gap;
    let stop = if v1 > 0.15 {
        let t2 = tau * ((v1 - 0.1) / 0.05).ln();
        (16.0 - v1 * v1) / (2.0 * a) + 0.1 * t2 + tau * (v1 - 0.15)
    } else {
        (16.0 - 0.15f64.powi(2)) / (2.0 * a)
    };
    (t_top, stop)
}

/// Measure one surface.
pub fn measure(params: &CarParams, surface: Surface) -> Handling {
    let mu = surface.friction();
    let mut chassis = Manoeuvre { height: (f64::INFINITY, f64::NEG_INFINITY), ..Default::default() };

    // Full throttle from rest, then the brake.
    let mut car = Car::new(params, mu, DT);
    car.reset(0.0, 0.0, 0.0);
    let mut m = Manoeuvre::new(&car);
    let mut time_to_top = f64::NAN;
    for i in 0..(4.0 / DT) as usize {
        let yaw = car.state().yaw;
        car.step(0.0, 4.0);
        m.record(&car, yaw);
        if time_to_top.is_nan() && car.state().forward_speed >= 3.9 {
            time_to_top = (i + 1) as f64 * DT;
        }
    }
    let top_speed = car.state().forward_speed;
    let s0 = car.state();
    let mut stopping_distance = f64::NAN;
    for _ in 0..(4.0 / DT) as usize {
        let yaw = car.state().yaw;
        car.step(0.0, 0.1);
        m.record(&car, yaw);
        let s = car.state();
        if stopping_distance.is_nan() && s.forward_speed <= 0.15 {
            stopping_distance = (s.x - s0.x).hypot(s.y - s0.y);
        }
    }
    chassis.merge(&m);

    let mut radius_full_lock = Vec::new();
    for speed in [0.5, 1.0, 2.0, 3.0, 4.0] {
        let mut car = Car::new(params, mu, DT);
        car.reset(0.0, 0.0, 0.0);
        let mut m = Manoeuvre::new(&car);
        hold(&mut car, 30.0, speed, 6.0, &mut m);
        let (mut v, mut w) = (0.0, 0.0);
        let n = (2.0 / DT) as usize;
        for _ in 0..n {
            let yaw = car.state().yaw;
            car.step(30f64.to_radians(), speed);
            m.record(&car, yaw);
            let s = car.state();
            v += s.forward_speed.hypot(s.lateral_speed);
            w += s.yaw_rate;
        }
        chassis.merge(&m);
        let bicycle = bicycle_radius(params, 30.0);
        radius_full_lock.push((speed, (v / w).abs(), bicycle, bicycle.max(speed * speed / (mu * G))));
    }
    let (time_to_top_model, stopping_distance_model) = point_mass(mu, params.speed_time_constant);
    Handling {
        surface,
        friction: mu,
        top_speed,
        time_to_top,
        time_to_top_model,
        stopping_distance,
        stopping_distance_model,
        radius_full_lock,
        chassis,
    }
}

/// The car's limits on `surface` for a speed profile, as its own manoeuvres measure them:
/// its top speed, the mean acceleration from rest to 3.9 m/s, the mean deceleration from
/// 4 m/s to rest, and the largest sideways acceleration it held at full lock.
pub fn limits(params: &CarParams, surface: Surface) -> tracks::raceline::Limits {
    let h = measure(params, surface);
    let lateral = h.radius_full_lock.iter().map(|&(v, r, ..)| v * v / r).fold(0.0, f64::max);
    tracks::raceline::Limits {
        top_speed: h.top_speed,
        accel: 3.9 / h.time_to_top,
        brake: (4.0f64.powi(2) - 0.15f64.powi(2)) / (2.0 * h.stopping_distance),
        lateral,
    }
}

/// The figures of every surface as Markdown tables.
pub fn markdown(params: &CarParams) -> String {
    let all: Vec<Handling> = Surface::ALL.iter().map(|&s| measure(params, s)).collect();
    let mut out = String::new();
    out.push_str("| surface | μ | top speed m/s (command 4) | 0 → 3.9 m/s s (point mass) | stopping from 4 m/s m (point mass) | max roll ° | max pitch ° | max heading change per 1/60 s ° |\n");
    out.push_str("|---|---:|---:|---:|---:|---:|---:|---:|\n");
    for h in &all {
        out.push_str(&format!(
            "| {} | {:.2} | {:.3} | {:.2} ({:.2}) | {:.2} ({:.2}) | {:.2} | {:.2} | {:.2} |\n",
            h.surface.name(),
            h.friction,
            h.top_speed,
            h.time_to_top,
            h.time_to_top_model,
            h.stopping_distance,
            h.stopping_distance_model,
            h.chassis.max_roll_deg,
            h.chassis.max_pitch_deg,
            h.chassis.max_heading_step_deg,
        ));
    }
    out.push_str("\nTurning radius at full lock (30°), at the chassis origin, m: measured / kinematic bicycle / grip limit max(bicycle, v²/μg)\n\n");
    out.push_str("| surface |");
    for (v, ..) in &all[0].radius_full_lock {
        out.push_str(&format!(" {v} m/s |"));
    }
    out.push_str("\n|---|");
    out.push_str(&"---:|".repeat(all[0].radius_full_lock.len()));
    out.push('\n');
    for h in &all {
        out.push_str(&format!("| {} |", h.surface.name()));
        for (_, r, b, g) in &h.radius_full_lock {
            out.push_str(&format!(" {r:.3} / {b:.3} / {g:.3} |"));
        }
        out.push('\n');
    }
    out
}
