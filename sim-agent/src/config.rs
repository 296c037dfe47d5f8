//! The simulator's configuration: every knob in one struct, documented field by field.
//!
//! `config/default.toml` at the repository root is this struct's defaults written out (a
//! test parses it and compares). Commands take `--config FILE` and `--set key=value`
//! overrides on top; see [`load_config`].

use crate::car::CarParams;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Everything the simulator needs besides the world and the reward.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SimConfig {
    /// Control (agent step) rate in Hz: DeepRacer steps at the camera's 15 Hz.
    pub control_hz: f64,
    /// Physics steps per control step (4 ⇒ 60 Hz, DeepRacer's controller rate).
    pub physics_substeps: u32,
    /// The car's physical parameters.
    pub car: CarParams,
    /// Actuator noise added to the executed command (not to the commanded values that
    /// reward `params` report).
    pub noise: NoiseConfig,
    /// Episode and reset rules.
    pub episode: EpisodeConfig,
    /// What the policy observes.
    pub observation: ObservationConfig,
    /// Camera domain randomisation (used when the observation is the camera).
    pub camera: CameraConfig,
    /// Seconds one call of a Python `reward_function` may take: a call past it stops the job
    /// (and `reward validate`) with the file, the step and where the code was stuck.
    pub reward_time_limit: f64,
    /// Record every step's sim-trace fields and send them with the experience: the learner
    /// writes DeepRacer's sim-trace CSVs, metrics JSON and an MCAP log into the run folder.
    pub record_trace: bool,
    /// The race: time trial, object avoidance or head-to-bot, with DeepRacer's keys.
    pub race: crate::race::RaceConfig,
    /// Generated worlds (`generated:N`) in training.
    pub generated: GeneratedConfig,
}

impl Default for SimConfig {
    fn default() -> Self {
        SimConfig {
            control_hz: 15.0,
            physics_substeps: 4,
            car: CarParams::default(),
            noise: NoiseConfig::default(),
            episode: EpisodeConfig::default(),
            observation: ObservationConfig::default(),
            camera: CameraConfig::default(),
            reward_time_limit: 1.0,
            record_trace: true,
            race: crate::race::RaceConfig::default(),
            generated: GeneratedConfig::default(),
        }
    }
}

impl SimConfig {
    /// [`SimConfig::reward_time_limit`] as a duration (at least a millisecond).
    pub fn reward_time_limit(&self) -> std::time::Duration {
        std::time::Duration::from_secs_f64(
            if self.reward_time_limit.is_finite() { self.reward_time_limit } else { 1.0 }.clamp(1e-3, 86_400.0),
        )
    }
}

/// Camera domain randomisation, drawn afresh for every episode of every environment (and
/// image noise for every frame). Off by default, as in DeepRacer's simulator.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CameraConfig {
    /// Turn randomisation on.
    pub randomize: bool,
    /// Light intensity range (1 = nominal).
    pub light_intensity: [f64; 2],
    /// Light elevation range (degrees above the floor).
    pub light_elevation_deg: [f64; 2],
    /// Vary the surface texture (a new pattern seed each episode).
    pub texture_variation: bool,
    /// Camera height jitter, ± metres.
    pub height_jitter: f64,
    /// Camera pitch jitter, ± degrees.
    pub pitch_jitter_deg: f64,
    /// Gaussian image noise, standard deviation in grey levels (0–255).
    pub image_noise: f64,
}

impl Default for CameraConfig {
    fn default() -> Self {
        CameraConfig {
            randomize: false,
            light_intensity: [0.7, 1.3],
            light_elevation_deg: [30.0, 90.0],
            texture_variation: true,
            height_jitter: 0.01,
            pitch_jitter_deg: 2.0,
            image_noise: 3.0,
        }
    }
}

/// Gaussian actuator noise. DeepRacer's simapp sends the action unchanged; a real car's
/// servo and ESC do not, so Paddock perturbs what the simulated car executes (on by default,
/// set both to 0 for DeepRacer's exact behaviour).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct NoiseConfig {
    /// Standard deviation of steering noise (degrees).
    pub steering_deg: f64,
    /// Standard deviation of speed noise, as a fraction of the commanded speed.
    pub speed_fraction: f64,
}

impl Default for NoiseConfig {
    fn default() -> Self {
        NoiseConfig { steering_deg: 1.0, speed_fraction: 0.03 }
    }
}

/// Episode rules (simapp's step loop and `markov/reset/rules`); defaults are DeepRacer's
/// training values.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EpisodeConfig {
    /// Fraction of the track the start moves forward each episode (`ROUND_ROBIN_ADVANCE_DIST`).
    pub round_robin_advance: f64,
    /// Consecutive steps of falling progress that end an episode as `reversed`.
    pub reverse_steps: u32,
    /// Consecutive steps moving at most `immobilized_distance` that end it as `immobilized`.
    pub immobilized_steps: u32,
    /// Distance (m) per step under which the car counts as not moving.
    pub immobilized_distance: f64,
    /// Hard cap on steps per episode (`MAX_STEPS`).
    pub max_steps: u64,
}

impl Default for EpisodeConfig {
    fn default() -> Self {
        EpisodeConfig {
            round_robin_advance: 0.05,
            reverse_steps: 15,
            immobilized_steps: 15,
            immobilized_distance: 0.0003,
            max_steps: 100_000,
        }
    }
}

/// How training drives a generated world (`generated:N`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GeneratedConfig {
    /// Episodes an environment drives one generated track before it draws the next (0: it
    /// keeps to track N).
    pub episodes_per_track: u64,
}

impl Default for GeneratedConfig {
    fn default() -> Self {
        GeneratedConfig { episodes_per_track: 10 }
    }
}

/// The observation vector (see [`crate::obs`] for the exact layout).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ObservationConfig {
    /// Which sensors make up the observation.
    pub kind: ObservationKind,
    /// Number of centre-line points ahead included in the state vector.
    pub lookahead_points: usize,
    /// Spacing of those points along the centre line (m).
    pub lookahead_spacing: f64,
    /// Lidar rays.
    pub lidar_rays: usize,
    /// Lidar field of view, centred on the heading (degrees); DeepRacer's LiDAR covers 300°.
    pub lidar_fov_deg: f64,
    /// Lidar range (m); readings are clipped to it.
    pub lidar_range: f64,
    /// DeepRacer's LiDAR beside the camera, as the model's sensors ask for it (set from
    /// `model_metadata.json`; absent without one).
    pub camera_lidar: Option<CameraLidar>,
}

/// DeepRacer's simulated LiDAR ([`crate::lidar`]) fed beside the camera: its 64 clipped
/// ranges (`LIDAR`), or a one-hot distance bin per sector (`SECTOR_LIDAR`,
/// `DISCRETIZED_SECTOR_LIDAR`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraLidar {
    /// Which of DeepRacer's LiDAR inputs.
    pub sensor: LidarSensor,
    /// Sectors of consecutive rays (64 for `lidar`).
    pub sectors: usize,
    /// Distance bins per sector (1 for `lidar`).
    pub values: usize,
    /// Readings beyond this (m) count as nothing (`lidar`: clipped to [0.15, 1.0]).
    pub clip: f32,
    /// The LiDAR's values come before the camera's in the observation (DeepRacer's sorted
    /// input names: `DISCRETIZED_SECTOR_LIDAR` before `FRONT_FACING_CAMERA`, `LIDAR` before
    /// `STEREO_CAMERAS`).
    pub first: bool,
}

impl CameraLidar {
    /// Values per observation.
    pub fn size(&self) -> usize {
        self.sectors * self.values
    }
}

/// DeepRacer's LiDAR inputs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LidarSensor {
    /// `LIDAR`.
    Lidar,
    /// `SECTOR_LIDAR`.
    SectorLidar,
    /// `DISCRETIZED_SECTOR_LIDAR`.
    DiscretizedSectorLidar,
}

impl Default for ObservationConfig {
    fn default() -> Self {
        ObservationConfig {
            kind: ObservationKind::State,
            lookahead_points: 10,
            lookahead_spacing: 0.3,
            lidar_rays: 32,
            lidar_fov_deg: 300.0,
            lidar_range: 2.0,
            camera_lidar: None,
        }
    }
}

/// Observation sensors.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ObservationKind {
    /// The state vector: pose relative to the track, speed, centre-line points ahead.
    State,
    /// Lidar rays against the road borders.
    Lidar,
    /// Both, state first.
    StateLidar,
    /// The front camera: frames rendered with wgpu (on a GPU, or on lavapipe without one).
    Camera,
    /// DeepRacer's stereo pair (`STEREO_CAMERAS`): two front cameras 0.06 m apart, their
    /// grey frames as the two channels of one image (left first).
    Stereo,
}

impl ObservationKind {
    /// Rendered by the camera (one or two frames per step).
    pub fn is_camera(self) -> bool {
        matches!(self, ObservationKind::Camera | ObservationKind::Stereo)
    }
}

/// Why a configuration could not be loaded: a [`policy::FileError`] naming the file, the
/// `--set` override or the defaults, and the field.
pub type ConfigError = policy::FileError;

/// Parse TOML text into `T`, naming `origin` in errors.
pub fn parse_toml<T: serde::de::DeserializeOwned>(text: &str, origin: &str) -> Result<T, ConfigError> {
    toml::from_str(text).map_err(|e| ConfigError::invalid(origin, e.to_string()))
}

/// Load `T` from an optional TOML file, then apply `key=value` overrides (dotted keys,
/// values in TOML syntax; a bare word is taken as a string).
pub fn load_config<T>(file: Option<&Path>, sets: &[String]) -> Result<T, ConfigError>
where
    T: serde::de::DeserializeOwned + Serialize + Default,
{
    let table: toml::Table = match file {
        Some(path) => {
            let text = std::fs::read_to_string(path).map_err(ConfigError::io_at(path))?;
            parse_toml(&text, &path.display().to_string())?
        }
        None => toml::Table::try_from(T::default()).expect("defaults serialise"),
    };
    let origin = file.map(|p| p.display().to_string()).unwrap_or_else(|| "defaults".into());
    overridden(table, &origin, sets)
}

/// `value` with `key=value` overrides applied as [`load_config`] applies them (`origin`
/// names `value` in errors): typed settings first, `--set` on top.
pub fn apply_sets<T>(value: T, origin: &str, sets: &[String]) -> Result<T, ConfigError>
where
    T: serde::de::DeserializeOwned + Serialize,
{
    if sets.is_empty() {
        return Ok(value);
    }
    overridden(toml::Table::try_from(&value).expect("a configuration serialises"), origin, sets)
}

/// `table` with `sets` applied, as `T`.
fn overridden<T: serde::de::DeserializeOwned>(
    mut table: toml::Table,
    origin: &str,
    sets: &[String],
) -> Result<T, ConfigError> {
    for set in sets {
        let bad = |msg: String| ConfigError::invalid(format!("--set {set}"), msg);
        let (key, value) = set.split_once('=').ok_or_else(|| bad("expected key=value".into()))?;
        let value: toml::Value = match toml::from_str::<toml::Table>(&format!("v = {value}")) {
            Ok(mut t) => t.remove("v").expect("parsed key"),
            Err(_) => toml::Value::String(value.to_string()),
        };
        let mut node = &mut table;
        let parts: Vec<&str> = key.trim().split('.').collect();
        for part in &parts[..parts.len() - 1] {
            node = node
                .entry(part.to_string())
                .or_insert_with(|| toml::Value::Table(toml::Table::new()))
                .as_table_mut()
                .ok_or_else(|| bad(format!("'{part}' is not a section")))?;
        }
        node.insert(parts[parts.len() - 1].to_string(), value);
    }
    T::deserialize(toml::Value::Table(table)).map_err(|e| {
        let origin = if sets.is_empty() { origin.to_string() } else { format!("{origin} with --set overrides") };
        ConfigError::invalid(origin, e.to_string())
    })
}

/// A model's `sensor` list that the simulator cannot observe.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
#[error("sensor {sensors:?} is not supported: Paddock trains from a camera (with or without a LiDAR) or STATE_VECTOR")]
pub struct UnsupportedSensors {
    /// The model's sensors (DeepRacer's names).
    pub sensors: Vec<&'static str>,
}

impl ObservationConfig {
    /// The observation a model's `sensor` list calls for: the state vector (with or without
    /// Paddock's border lidar), or the front camera or the stereo pair, each with or without
    /// DeepRacer's LiDAR.
    pub fn set_sensors(&mut self, meta: &policy::ModelMetadata) -> Result<(), UnsupportedSensors> {
        use policy::Sensor;
        let camera = [Sensor::FrontFacingCamera, Sensor::LeftCamera, Sensor::Observation, Sensor::StereoCameras]
            .into_iter()
            .find(|s| meta.sensor.contains(s));
        self.camera_lidar = None;
        if meta.sensor.contains(&Sensor::StateVector) {
            self.kind =
                if meta.sensor.contains(&Sensor::Lidar) { ObservationKind::StateLidar } else { ObservationKind::State };
        } else if let Some(camera) = camera {
            self.kind = if camera == Sensor::StereoCameras { ObservationKind::Stereo } else { ObservationKind::Camera };
            if let Some(l) = meta.lidar {
                let inputs = policy::model::inputs(meta, 0);
                self.camera_lidar = Some(CameraLidar {
                    sensor: match l.sensor {
                        Sensor::Lidar => LidarSensor::Lidar,
                        Sensor::SectorLidar => LidarSensor::SectorLidar,
                        _ => LidarSensor::DiscretizedSectorLidar,
                    },
                    sectors: l.sectors,
                    values: l.values,
                    clip: l.clip,
                    first: inputs[0].0 == l.sensor,
                });
            }
        } else {
            return Err(UnsupportedSensors { sensors: meta.sensor.iter().map(|s| s.name()).collect() });
        }
        Ok(())
    }
}
