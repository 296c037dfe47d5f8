//! The physical car: what it can run, and how a model's action becomes servo ratios.
//!
//! `car.toml` (the default, documented file is `deploy/car.toml`) is shared by the on-car
//! agent (`deploy`), which maps actions to commands, and the simulated car (`sim-agent car`),
//! which maps commands back to actions.
//!
//! The mapping is DeepRacer's navigation node's (`deepracer_navigation_node.py`):
//! `angle = steering / max_steering`; `throttle = throttle_scale × clamp(a·s² + b·s, -1, 1)`
//! with the parabola through (0, 0), (max_speed/2, 0.8) and (max_speed, 1.0). The node takes
//! `max_steering` (the largest |steering| of a discrete space, `high` of a continuous one) and
//! `max_speed` from the loaded model; `car.toml` may pin them instead, so that one speed means
//! one throttle whatever the model. `max_throttle` caps |throttle| after scaling.

use crate::metadata::{Action, ActionSpace, ModelMetadata, Sensor};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// The car's configuration (`car.toml`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CarConfig {
    /// The car's name: its status key and liveliness token (`paddock/v1/car/{id}/…`).
    pub id: String,
    /// The bridge namespace in front of the car's ROS topics (`car7` gives
    /// `car7/sensor_fusion_pkg/sensor_msg`); empty for none.
    pub namespace: String,
    /// The interfaces package's layout: `community` (JPEG `CompressedImage[]` + IMU, headed
    /// `ServoCtrlMsg`) or `aws` (raw `Image[]` in bgr8/rgb8/mono8, bare `ServoCtrlMsg`).
    pub layout: crate::car::Layout,
    /// The car's sensors: a model needing another one is refused.
    pub sensors: Vec<String>,
    /// Milliseconds without a frame after which the car gets throttle 0 (until frames return).
    pub watchdog_ms: u64,
    /// The action → servo mapping.
    pub mapping: Mapping,
    /// The largest steering angle (degrees, either way) a model's action space may ask for.
    pub max_model_steering_deg: f64,
    /// The largest speed (m/s) a model's action space may ask for.
    pub max_model_speed: f64,
    /// How the big dense layer's weights are held: `f16` (as DeepRacer's car runs its models)
    /// or `int8` (a scale per output: half the memory again, logits within 2 %).
    pub precision: Precision,
    /// DeepRacer archives (unsigned: DeepRacer signs nothing) the car drives all the same, by
    /// the name a car gives them (the file name up to its first dot). Empty: none.
    pub trust_unsigned: Vec<String>,
}

/// The precision of the car's big dense layer.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Precision {
    /// Half precision (DeepRacer's FP16 model).
    #[default]
    F16,
    /// 8-bit integers with one scale per output.
    Int8,
}

/// The message layout (the same names as `protocol::ros::Layout`, kept here so that this
/// crate knows no wire format).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Layout {
    /// The community car stack.
    Community,
    /// The original AWS release.
    Aws,
}

/// How actions become servo ratios.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Mapping {
    /// The console's speed slider (the navigation node's `navigation_throttle`), in [0, 1].
    pub throttle_scale: f64,
    /// Cap on |throttle| after scaling, in [0, 1].
    pub max_throttle: f64,
    /// Steering (degrees) that maps to angle ±1; absent: the model's largest.
    pub max_steering_deg: Option<f64>,
    /// Speed (m/s) that maps to throttle 1 before scaling; absent: the model's largest.
    pub max_speed: Option<f64>,
}

impl Default for CarConfig {
    fn default() -> CarConfig {
        CarConfig {
            id: "car".into(),
            namespace: String::new(),
            layout: Layout::Community,
            sensors: vec!["FRONT_FACING_CAMERA".into()],
            watchdog_ms: 250,
            mapping: Mapping::default(),
            max_model_steering_deg: crate::MAX_STEERING_DEG,
            max_model_speed: crate::MAX_SPEED,
            precision: Precision::F16,
            trust_unsigned: vec![],
        }
    }
}

impl Default for Mapping {
    fn default() -> Mapping {
        Mapping { throttle_scale: 1.0, max_throttle: 1.0, max_steering_deg: None, max_speed: None }
    }
}

/// Why `car.toml` could not be used.
#[derive(Debug, thiserror::Error)]
#[error("{path}: {msg}")]
pub struct CarConfigError {
    /// The file.
    pub path: String,
    /// What is wrong (the field and what was expected).
    pub msg: String,
}

impl CarConfig {
    /// Read and check `car.toml`.
    pub fn load(path: &Path) -> Result<CarConfig, CarConfigError> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| CarConfigError { path: path.display().to_string(), msg: e.to_string() })?;
        CarConfig::parse(&text, &path.display().to_string())
    }

    /// Parse and check `car.toml`'s text (`origin` names it in errors).
    pub fn parse(text: &str, origin: &str) -> Result<CarConfig, CarConfigError> {
        let err = |msg: String| CarConfigError { path: origin.into(), msg };
        let c: CarConfig = toml::from_str(text).map_err(|e| err(e.to_string()))?;
        let m = &c.mapping;
        let unit = |v: f64| (0.0..=1.0).contains(&v);
        if !unit(m.throttle_scale) {
            return Err(err(format!("mapping.throttle_scale is {}; expected a number in [0, 1]", m.throttle_scale)));
        }
        if !unit(m.max_throttle) {
            return Err(err(format!("mapping.max_throttle is {}; expected a number in [0, 1]", m.max_throttle)));
        }
        for (k, v) in [("mapping.max_steering_deg", m.max_steering_deg), ("mapping.max_speed", m.max_speed)] {
            if let Some(v) = v.filter(|v| !(v.is_finite() && *v > 0.0)) {
                return Err(err(format!("{k} is {v}; expected a positive number (or leave it out: the model's)")));
            }
        }
        if !(1..=60_000).contains(&c.watchdog_ms) {
            return Err(err(format!("watchdog_ms is {}; expected 1 to 60000", c.watchdog_ms)));
        }
        if !c.id.chars().all(|ch| ch.is_ascii_alphanumeric() || "-_.".contains(ch)) || c.id.is_empty() {
            return Err(err(format!("id '{}': expected letters, digits, '-', '_' or '.'", c.id)));
        }
        for s in &c.sensors {
            if Sensor::parse_name(s).is_none() {
                return Err(err(format!(
                    "sensors: unknown sensor '{s}' (DeepRacer's names, e.g. FRONT_FACING_CAMERA)"
                )));
            }
        }
        Ok(c)
    }

    /// Whether a model can run on this car: its sensors are the car's (never the simulator's
    /// state vector) and its actions within the car's limits. The reason when not.
    pub fn fits(&self, meta: &ModelMetadata) -> Result<(), DoesNotFit> {
        for s in &meta.sensor {
            if *s == Sensor::StateVector {
                return Err(DoesNotFit::StateVector);
            }
            if !self.sensors.iter().any(|c| c == s.name()) {
                return Err(DoesNotFit::Sensor { sensor: s.name(), car: self.sensors.clone() });
            }
        }
        let (steer, speed) = extremes(&meta.action_space);
        if steer > self.max_model_steering_deg + 1e-9 {
            return Err(DoesNotFit::Steering { model: steer, car: self.max_model_steering_deg });
        }
        if speed > self.max_model_speed + 1e-9 {
            return Err(DoesNotFit::Speed { model: speed, car: self.max_model_speed });
        }
        Ok(())
    }
}

/// Why a model cannot run on a car ([`CarConfig::fits`]): the sensor or the `car.toml` limit,
/// and what the model asks for.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum DoesNotFit {
    /// The model drives from the simulator's state vector.
    #[error(
        "the model drives from STATE_VECTOR, the simulator's state: a real car has no state vector; \
         train it with --sensor camera"
    )]
    StateVector,
    /// The model needs a sensor `car.toml`'s `sensors` does not list.
    #[error("the model needs sensor {sensor}, the car has {car:?}")]
    Sensor {
        /// The sensor (DeepRacer's name).
        sensor: &'static str,
        /// The car's sensors.
        car: Vec<String>,
    },
    /// The action space steers further than `max_model_steering_deg`.
    #[error("the action space steers up to {model}°; the car allows {car}° (max_model_steering_deg)")]
    Steering {
        /// The model's largest steering angle (degrees).
        model: f64,
        /// `car.toml`'s limit.
        car: f64,
    },
    /// The action space goes faster than `max_model_speed`.
    #[error("the action space goes up to {model} m/s; the car allows {car} m/s (max_model_speed)")]
    Speed {
        /// The model's largest speed (m/s).
        model: f64,
        /// `car.toml`'s limit.
        car: f64,
    },
}

/// The largest |steering| and |speed| an action space can ask for, as the navigation node
/// takes them (a continuous space: its `high` values).
pub fn extremes(space: &ActionSpace) -> (f64, f64) {
    match space {
        ActionSpace::Discrete(a) => (
            a.iter().map(|x| x.steering_angle.abs()).fold(0.0, f64::max),
            a.iter().map(|x| x.speed.abs()).fold(0.0, f64::max),
        ),
        ActionSpace::Continuous { steering_angle, speed } => (steering_angle.1.abs(), speed.1.abs()),
    }
}

/// A mapping made concrete for one model.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ServoMap {
    max_steering: f64,
    max_speed: f64,
    a: f64,
    b: f64,
    scale: f64,
    cap: f64,
}

impl ServoMap {
    /// The mapping for a model's action space (`car.toml`'s values where pinned).
    pub fn new(mapping: &Mapping, space: &ActionSpace) -> ServoMap {
        let (steer, speed) = extremes(space);
        ServoMap::with(mapping, mapping.max_steering_deg.unwrap_or(steer), mapping.max_speed.unwrap_or(speed))
    }

    /// The mapping with both full-scale values given.
    pub fn with(mapping: &Mapping, max_steering: f64, max_speed: f64) -> ServoMap {
        // The navigation node's parabola through (0, 0), (max/2, 0.8), (max, 1.0).
        let (y_max, y_half) = (1.0, 0.8);
        let a = (2.0 * y_max - 4.0 * y_half) / (max_speed * max_speed);
        let b = (4.0 * y_half - y_max) / max_speed;
        ServoMap { max_steering, max_speed, a, b, scale: mapping.throttle_scale, cap: mapping.max_throttle }
    }

    /// An action to (angle, throttle) ratios.
    pub fn to_servo(&self, action: Action) -> (f32, f32) {
        let angle =
            if self.max_steering > 0.0 { (action.steering_angle / self.max_steering).clamp(-1.0, 1.0) } else { 0.0 };
        let s = action.speed;
        let throttle = (self.scale * (self.a * s * s + self.b * s).clamp(-1.0, 1.0)).clamp(-self.cap, self.cap);
        (angle as f32, throttle as f32)
    }

    /// (angle, throttle) ratios back to an action (the simulated car): the rising half of
    /// the parabola. The parabola peaks at 1.008 (at 11/12 of `max_speed`) and the node clamps
    /// it to 1, so every speed from 5/6 of `max_speed` up gives throttle 1, which comes back
    /// as `max_speed`: on a real car, too, those speeds are one throttle.
    pub fn to_action(&self, angle: f32, throttle: f32) -> Action {
        let steering_angle = angle.clamp(-1.0, 1.0) as f64 * self.max_steering;
        let y = if self.scale > 0.0 { (throttle as f64 / self.scale).clamp(-1.0, 1.0) } else { 0.0 };
        if y.abs() >= 1.0 - 1e-6 {
            return Action { steering_angle, speed: y.signum() * self.max_speed };
        }
        // a·s² + b·s − y = 0, the root with s between 0 and max_speed for y in [0, 1].
        let speed = if self.a.abs() < 1e-12 {
            y / self.b
        } else {
            let disc = (self.b * self.b + 4.0 * self.a * y.abs()).max(0.0);
            y.signum() * (-self.b + disc.sqrt()) / (2.0 * self.a)
        };
        Action { steering_angle, speed }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn space() -> ActionSpace {
        ActionSpace::Discrete(vec![
            Action { steering_angle: -30.0, speed: 1.0 },
            Action { steering_angle: 15.0, speed: 4.0 },
            Action { steering_angle: 0.0, speed: 2.0 },
        ])
    }

    #[test]
    fn the_navigation_nodes_parabola() {
        let m = ServoMap::new(&Mapping::default(), &space());
        // Through (max/2, 0.8) and (max, 1.0); angle = steering / max |steering|.
        assert_eq!(m.to_servo(Action { steering_angle: 15.0, speed: 4.0 }), (0.5, 1.0));
        let (a, t) = m.to_servo(Action { steering_angle: -30.0, speed: 2.0 });
        assert_eq!(a, -1.0);
        assert!((t - 0.8).abs() < 1e-6, "{t}");
        assert_eq!(m.to_servo(Action { steering_angle: 0.0, speed: 0.0 }).1, 0.0);
        // The slider and the cap.
        let slow = Mapping { throttle_scale: 0.5, max_throttle: 0.3, ..Mapping::default() };
        assert_eq!(ServoMap::new(&slow, &space()).to_servo(Action { steering_angle: 0.0, speed: 4.0 }).1, 0.3);
    }

    #[test]
    fn the_simulated_car_inverts_the_mapping() {
        let pinned = Mapping { max_steering_deg: Some(30.0), max_speed: Some(4.0), ..Mapping::default() };
        let m = ServoMap::new(&pinned, &space());
        for (steer, speed) in [(0.0, 0.5), (12.5, 1.3), (-30.0, 4.0), (7.0, 2.0), (1.0, 3.3)] {
            let (a, t) = m.to_servo(Action { steering_angle: steer, speed });
            let back = m.to_action(a, t);
            assert!((back.steering_angle - steer).abs() < 1e-4 && (back.speed - speed).abs() < 1e-4, "{back:?}");
        }
    }

    #[test]
    fn the_default_car_toml_parses_and_bad_fields_are_named() {
        let c = CarConfig::parse(include_str!("../../deploy/car.toml"), "deploy/car.toml").unwrap();
        assert_eq!(c.watchdog_ms, 250);
        assert_eq!(c.layout, Layout::Community);
        for (text, field) in [
            ("[mapping]\nthrottle_scale = 2.0", "mapping.throttle_scale"),
            ("watchdog_ms = 0", "watchdog_ms"),
            ("layout = \"ros1\"", "layout"),
            ("sensors = [\"SONAR\"]", "SONAR"),
            ("[mapping]\nmax_speed = -1.0", "mapping.max_speed"),
            ("speed = 1", "speed"),
        ] {
            let e = CarConfig::parse(text, "car.toml").unwrap_err().to_string();
            assert!(e.starts_with("car.toml") && e.contains(field), "{text}: {e}");
        }
    }

    #[test]
    fn a_state_vector_model_or_one_beyond_the_car_does_not_fit() {
        let car = CarConfig::default();
        assert!(car.fits(&ModelMetadata::default_camera()).is_ok());
        let narrow = CarConfig { max_model_steering_deg: 10.0, ..CarConfig::default() };
        let slow = CarConfig { max_model_speed: 1.5, ..CarConfig::default() };
        let blind = CarConfig { sensors: vec![], ..CarConfig::default() };
        // Issue 50: each reason names the sensor or the car.toml field.
        for (car, meta, field) in [
            (&car, ModelMetadata::default_state_vector(), "STATE_VECTOR"),
            (&narrow, ModelMetadata::default_camera(), "max_model_steering_deg"),
            (&slow, ModelMetadata::default_camera(), "max_model_speed"),
            (&blind, ModelMetadata::default_camera(), "needs sensor FRONT_FACING_CAMERA"),
        ] {
            let e = car.fits(&meta).unwrap_err().to_string();
            assert!(e.contains(field), "{e}");
        }
    }
}
