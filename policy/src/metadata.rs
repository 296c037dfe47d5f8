//! `model_metadata.json`, parsed as DeepRacer's simapp parses it
//! (`markov/boto/s3/files/model_metadata.py::parse_model_metadata`).

use serde_json::{Map, Value};
use std::path::Path;

/// DeepRacer's steering limit (degrees either way); the simulator clamps commands to it.
pub const MAX_STEERING_DEG: f64 = 30.0;
/// DeepRacer's lowest commanded speed (m/s).
pub const MIN_SPEED: f64 = 0.1;
/// DeepRacer's highest commanded speed (m/s).
pub const MAX_SPEED: f64 = 4.0;

/// A concrete command: what the car is asked to do for one step.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Action {
    /// Steering angle in degrees, + = left.
    pub steering_angle: f64,
    /// Speed in m/s.
    pub speed: f64,
}

/// The actions a model chooses from.
#[derive(Clone, Debug, PartialEq)]
pub enum ActionSpace {
    /// A list of actions; the network's output index picks one.
    Discrete(Vec<Action>),
    /// Ranges; the network acts in [-1, 1]² and is rescaled linearly to [low, high].
    Continuous {
        /// Steering range (degrees): (low, high).
        steering_angle: (f64, f64),
        /// Speed range (m/s): (low, high).
        speed: (f64, f64),
    },
}

impl ActionSpace {
    /// Number of network outputs: discrete actions, or 2 means for a continuous space.
    pub fn dim(&self) -> usize {
        match self {
            ActionSpace::Discrete(a) => a.len(),
            ActionSpace::Continuous { .. } => 2,
        }
    }

    /// The discrete action at `index`.
    pub fn discrete(&self, index: usize) -> Option<Action> {
        match self {
            ActionSpace::Discrete(a) => a.get(index).copied(),
            ActionSpace::Continuous { .. } => None,
        }
    }

    /// Map a network output in [-1, 1]² (clipped) to a continuous action
    /// (`ScalableBoxActionSpace`: linear rescale).
    pub fn scale(&self, unit: [f64; 2]) -> Option<Action> {
        match *self {
            ActionSpace::Continuous { steering_angle: (sl, sh), speed: (vl, vh) } => {
                let lerp = |u: f64, lo: f64, hi: f64| lo + (u.clamp(-1.0, 1.0) + 1.0) * 0.5 * (hi - lo);
                Some(Action { steering_angle: lerp(unit[0], sl, sh), speed: lerp(unit[1], vl, vh) })
            }
            ActionSpace::Discrete(_) => None,
        }
    }
}

/// Sensors DeepRacer knows (`sensor` list).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Sensor {
    /// The front camera (grayscale 160×120).
    FrontFacingCamera,
    /// The left camera of the stereo pair, alone.
    LeftCamera,
    /// Both cameras as two channels.
    StereoCameras,
    /// Version-1 legacy camera name.
    Observation,
    /// 64-ray LiDAR.
    Lidar,
    /// 8 binary sectors.
    SectorLidar,
    /// Sectors × values per sector.
    DiscretizedSectorLidar,
    /// Paddock's extension: the simulator's state vector (pose relative to the track, speed,
    /// centre-line points ahead). It takes the camera's place; simulation only.
    StateVector,
}

impl Sensor {
    /// The sensor a `model_metadata.json` name stands for.
    pub fn parse_name(s: &str) -> Option<Sensor> {
        Sensor::parse(s)
    }

    fn parse(s: &str) -> Option<Sensor> {
        Some(match s {
            "FRONT_FACING_CAMERA" => Sensor::FrontFacingCamera,
            "LEFT_CAMERA" => Sensor::LeftCamera,
            "STEREO_CAMERAS" => Sensor::StereoCameras,
            "observation" => Sensor::Observation,
            "LIDAR" => Sensor::Lidar,
            "SECTOR_LIDAR" => Sensor::SectorLidar,
            "DISCRETIZED_SECTOR_LIDAR" => Sensor::DiscretizedSectorLidar,
            "STATE_VECTOR" => Sensor::StateVector,
            _ => return None,
        })
    }

    /// The name written in `model_metadata.json`.
    pub fn name(self) -> &'static str {
        match self {
            Sensor::FrontFacingCamera => "FRONT_FACING_CAMERA",
            Sensor::LeftCamera => "LEFT_CAMERA",
            Sensor::StereoCameras => "STEREO_CAMERAS",
            Sensor::Observation => "observation",
            Sensor::Lidar => "LIDAR",
            Sensor::SectorLidar => "SECTOR_LIDAR",
            Sensor::DiscretizedSectorLidar => "DISCRETIZED_SECTOR_LIDAR",
            Sensor::StateVector => "STATE_VECTOR",
        }
    }

    /// A camera (or the state vector, which takes its place).
    pub fn is_primary(self) -> bool {
        matches!(
            self,
            Sensor::FrontFacingCamera
                | Sensor::LeftCamera
                | Sensor::StereoCameras
                | Sensor::Observation
                | Sensor::StateVector
        )
    }
}

/// DeepRacer's network names.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NeuralNetwork {
    /// 3-layer CNN (the default).
    DeepConvolutionalNetworkShallow,
    /// 5-layer CNN.
    DeepConvolutionalNetwork,
    /// The deeper CNN.
    DeepConvolutionalNetworkDeep,
    /// Paddock's extension for the state vector and lidar: two dense layers of 128 (ReLU).
    PaddockMlp,
}

impl NeuralNetwork {
    /// The name written in `model_metadata.json`.
    pub fn name(self) -> &'static str {
        match self {
            NeuralNetwork::DeepConvolutionalNetworkShallow => "DEEP_CONVOLUTIONAL_NETWORK_SHALLOW",
            NeuralNetwork::DeepConvolutionalNetwork => "DEEP_CONVOLUTIONAL_NETWORK",
            NeuralNetwork::DeepConvolutionalNetworkDeep => "DEEP_CONVOLUTIONAL_NETWORK_DEEP",
            NeuralNetwork::PaddockMlp => "PADDOCK_MLP",
        }
    }
}

/// `training_algorithm`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TrainingAlgorithm {
    /// Clipped PPO (the default).
    ClippedPpo,
    /// Soft actor-critic (continuous action spaces only).
    Sac,
}

impl TrainingAlgorithm {
    /// Its name in `model_metadata.json`.
    pub fn name(self) -> &'static str {
        match self {
            TrainingAlgorithm::ClippedPpo => "clipped_ppo",
            TrainingAlgorithm::Sac => "sac",
        }
    }
}

/// A parsed `model_metadata.json`. Unknown keys are kept so that writing it back loses nothing.
#[derive(Clone, Debug, PartialEq)]
pub struct ModelMetadata {
    /// The actions.
    pub action_space: ActionSpace,
    /// Sensors (defaults to `["observation"]` for version-1 files without the key).
    pub sensor: Vec<Sensor>,
    /// Network topology.
    pub neural_network: NeuralNetwork,
    /// Algorithm.
    pub training_algorithm: TrainingAlgorithm,
    /// Simapp version (parsed as a number by DeepRacer).
    pub version: f64,
    /// How the LiDAR sensor in `sensor`, if any, is fed to the network.
    pub lidar: Option<LidarInput>,
    /// The file as read, for round-tripping.
    pub raw: Map<String, Value>,
}

/// A LiDAR sensor's input to the network: the 64 clipped ranges (`LIDAR`), or per sector of
/// consecutive rays a one-hot distance bin (`SECTOR_LIDAR`: 8 sectors, 1 value, 0.5 m;
/// `DISCRETIZED_SECTOR_LIDAR`: its `lidar_config`, by default 8 × 8 within 2 m).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LidarInput {
    /// Which LiDAR sensor.
    pub sensor: Sensor,
    /// Sectors (64 for `LIDAR`: a value per ray).
    pub sectors: usize,
    /// Values per sector (distance bins).
    pub values: usize,
    /// Readings beyond this distance (m) count as nothing (`LIDAR`: clipped to [0.15, 1.0]).
    pub clip: f32,
}

impl LidarInput {
    /// The rays of DeepRacer's simulated LiDAR.
    pub const RAYS: usize = 64;

    /// Values per sample.
    pub fn size(&self) -> usize {
        self.sectors * self.values
    }

    /// DeepRacer's input filter on a scan of [`LidarInput::RAYS`] ranges (m; infinity where
    /// nothing is in range): the network's input.
    pub fn filter(&self, scan: &[f32]) -> Vec<f32> {
        match self.sensor {
            Sensor::Lidar => clipped(scan),
            _ => sectors(scan, self.sectors, self.values, self.clip),
        }
    }
}

/// `LIDAR`'s input: every reading clipped to [0.15, 1.0] m (infinity reads 1.0).
pub fn clipped(scan: &[f32]) -> Vec<f32> {
    scan.iter().map(|&d| if d.is_nan() { 1.0 } else { d.clamp(0.15, 1.0) }).collect()
}

/// `SECTOR_LIDAR` (8 sectors, 1 value, 0.5 m) and `DISCRETIZED_SECTOR_LIDAR` (its
/// `lidar_config`): per sector of consecutive rays its nearest reading `v` (infinity reads
/// `clip`), `min(v, clip)`, bin `k = floor(v / (clip / values))` up to `values`, one-hot over
/// `values + 1` bins with the last (nothing within `clip`) dropped.
pub fn sectors(scan: &[f32], sectors: usize, values: usize, clip: f32) -> Vec<f32> {
    let per = scan.len() / sectors.max(1);
    let mut out = vec![0.0; sectors * values];
    for s in 0..sectors {
        let v = scan[s * per..(s + 1) * per].iter().map(|&d| if d.is_finite() { d } else { clip }).fold(clip, f32::min);
        let k = ((v / (clip / values as f32)).floor().max(0.0) as usize).min(values);
        if k < values {
            out[s * values + k] = 1.0;
        }
    }
    out
}

/// Why a `model_metadata.json` was refused.
#[derive(Debug, thiserror::Error)]
#[error("{origin}: {msg}")]
pub struct MetadataError {
    /// The file.
    pub origin: String,
    /// What is wrong, naming the field.
    pub msg: String,
}

impl ModelMetadata {
    /// Read and parse a file.
    pub fn load(path: &Path) -> Result<ModelMetadata, MetadataError> {
        let origin = path.display().to_string();
        let text =
            std::fs::read_to_string(path).map_err(|e| MetadataError { origin: origin.clone(), msg: e.to_string() })?;
        ModelMetadata::parse(&text, &origin)
    }

    /// Parse JSON text; `origin` names it in errors.
    pub fn parse(text: &str, origin: &str) -> Result<ModelMetadata, MetadataError> {
        let err = |msg: String| MetadataError { origin: origin.to_string(), msg };
        let value: Value = serde_json::from_str(text).map_err(|e| err(format!("not valid JSON: {e}")))?;
        let Value::Object(raw) = value else {
            return Err(err("expected a JSON object at the top level".into()));
        };
        let kind = match raw.get("action_space_type") {
            None => "discrete".to_string(),
            Some(Value::String(s)) => s.trim().to_lowercase(),
            Some(other) => {
                return Err(err(format!(
                    "field 'action_space_type' is {other}, expected \"discrete\" or \"continuous\""
                )));
            }
        };
        let space = raw
            .get("action_space")
            .ok_or_else(|| err("no action space defined (field 'action_space' is missing)".into()))?;
        let action_space = match kind.as_str() {
            "discrete" => parse_discrete(space).map_err(err)?,
            "continuous" => parse_continuous(space).map_err(err)?,
            other => {
                return Err(err(format!(
                    "field 'action_space_type' is \"{other}\", expected \"discrete\" or \"continuous\""
                )));
            }
        };
        let training_algorithm = match raw.get("training_algorithm").map(|v| v.as_str()) {
            None => TrainingAlgorithm::ClippedPpo,
            Some(Some(s)) if s.trim().eq_ignore_ascii_case("clipped_ppo") => TrainingAlgorithm::ClippedPpo,
            Some(Some(s)) if s.trim().eq_ignore_ascii_case("sac") => TrainingAlgorithm::Sac,
            Some(_) => return Err(err("field 'training_algorithm' must be \"clipped_ppo\" or \"sac\"".into())),
        };
        if training_algorithm == TrainingAlgorithm::Sac && matches!(action_space, ActionSpace::Discrete(_)) {
            return Err(err("training_algorithm \"sac\" needs a continuous action space (DeepRacer: \"Unsupported \
                 action space type passed while defining SACActionSpaceConfig\"); field 'action_space_type' is \
                 \"discrete\""
                .into()));
        }
        let neural_network = match raw.get("neural_network").map(|v| v.as_str()) {
            None | Some(Some("DEEP_CONVOLUTIONAL_NETWORK_SHALLOW")) => NeuralNetwork::DeepConvolutionalNetworkShallow,
            Some(Some("DEEP_CONVOLUTIONAL_NETWORK")) => NeuralNetwork::DeepConvolutionalNetwork,
            Some(Some("DEEP_CONVOLUTIONAL_NETWORK_DEEP")) => NeuralNetwork::DeepConvolutionalNetworkDeep,
            Some(Some("PADDOCK_MLP")) => NeuralNetwork::PaddockMlp,
            Some(_) => {
                return Err(err("field 'neural_network' must be one of DEEP_CONVOLUTIONAL_NETWORK_SHALLOW, DEEP_CONVOLUTIONAL_NETWORK, DEEP_CONVOLUTIONAL_NETWORK_DEEP, PADDOCK_MLP".into()));
            }
        };
        let version = match raw.get("version") {
            None => 1.0,
            Some(Value::Number(n)) => n.as_f64().unwrap_or(1.0),
            Some(Value::String(s)) => {
                s.trim().parse().map_err(|_| err(format!("field 'version' is \"{s}\", expected a number")))?
            }
            Some(other) => return Err(err(format!("field 'version' is {other}, expected a number"))),
        };
        let sensor = match raw.get("sensor") {
            None if version < 2.0 => vec![Sensor::Observation],
            None => return Err(err(format!("field 'sensor' is required for version {version}"))),
            Some(Value::Array(items)) => items
                .iter()
                .map(|v| {
                    v.as_str()
                        .and_then(Sensor::parse)
                        .ok_or_else(|| err(format!("field 'sensor' has unknown sensor {v}")))
                })
                .collect::<Result<Vec<_>, _>>()?,
            Some(other) => return Err(err(format!("field 'sensor' is {other}, expected a list of sensor names"))),
        };
        // DeepRacer's own errors (`parse_model_metadata`), with the field named.
        let cameras = sensor.iter().filter(|s| s.is_primary()).count();
        let lidars = sensor.len() - cameras;
        let names = sensor.iter().map(|s| s.name()).collect::<Vec<_>>();
        if cameras != 1 {
            return Err(err(format!(
                "field 'sensor': model_metadata MUST contain only 1 camera sensor: {names:?} (exactly one camera, or STATE_VECTOR)"
            )));
        }
        if lidars > 1 {
            return Err(err(format!("field 'sensor': model_metadata contains more than 1 lidar sensor: {names:?}")));
        }
        let lidar = match sensor.iter().find(|s| !s.is_primary()) {
            Some(&Sensor::DiscretizedSectorLidar) => Some(parse_lidar_config(raw.get("lidar_config")).map_err(err)?),
            Some(&Sensor::SectorLidar) => {
                Some(LidarInput { sensor: Sensor::SectorLidar, sectors: 8, values: 1, clip: 0.5 })
            }
            Some(&Sensor::Lidar) => {
                Some(LidarInput { sensor: Sensor::Lidar, sectors: LidarInput::RAYS, values: 1, clip: 1.0 })
            }
            _ => None,
        };
        let state = sensor.contains(&Sensor::StateVector);
        if state != (neural_network == NeuralNetwork::PaddockMlp) {
            return Err(err(format!(
                "sensor STATE_VECTOR goes with neural_network PADDOCK_MLP (and cameras with the convolutional networks); got {} with {}",
                sensor.iter().map(|s| s.name()).collect::<Vec<_>>().join(", "),
                neural_network.name()
            )));
        }
        Ok(ModelMetadata { action_space, sensor, neural_network, training_algorithm, version, lidar, raw })
    }

    /// Paddock's default for state-vector training: 5 steering angles × 2 speeds, discrete.
    pub fn default_state_vector() -> ModelMetadata {
        let mut actions = Vec::new();
        for speed in [1.0, 2.0] {
            for steering_angle in [-30.0, -15.0, 0.0, 15.0, 30.0] {
                actions.push(Action { steering_angle, speed });
            }
        }
        let meta = ModelMetadata {
            action_space: ActionSpace::Discrete(actions),
            sensor: vec![Sensor::StateVector],
            neural_network: NeuralNetwork::PaddockMlp,
            training_algorithm: TrainingAlgorithm::ClippedPpo,
            version: 5.0,
            lidar: None,
            raw: Map::new(),
        };
        let text = meta.to_json();
        ModelMetadata::parse(&text, "default").expect("the default metadata parses")
    }

    /// DeepRacer's camera model: FRONT_FACING_CAMERA, the SHALLOW network, 5 steering × 2 speeds.
    pub fn default_camera() -> ModelMetadata {
        let mut m = ModelMetadata::default_state_vector();
        m.sensor = vec![Sensor::FrontFacingCamera];
        m.neural_network = NeuralNetwork::DeepConvolutionalNetworkShallow;
        let text = m.to_json();
        ModelMetadata::parse(&text, "default").expect("the default camera metadata parses")
    }

    /// DeepRacer's stereo model: STEREO_CAMERAS, the SHALLOW network, 5 steering × 2 speeds.
    pub fn default_stereo() -> ModelMetadata {
        let mut m = ModelMetadata::default_camera();
        m.sensor = vec![Sensor::StereoCameras];
        let text = m.to_json();
        ModelMetadata::parse(&text, "default").expect("the default stereo metadata parses")
    }

    /// The default metadata for a `--sensor` name: `state`, `camera`, `stereo`, and either
    /// camera with the LiDAR as the DeepRacer console's checkbox adds it (`SECTOR_LIDAR`):
    /// `camera+lidar`, `stereo+lidar`.
    pub fn for_sensor(name: &str) -> Option<ModelMetadata> {
        let (camera, lidar) = match name.split_once('+') {
            Some((c, "lidar")) => (c, true),
            Some(_) => return None,
            None => (name, false),
        };
        let mut m = match camera {
            "state" if !lidar => return Some(ModelMetadata::default_state_vector()),
            "camera" => ModelMetadata::default_camera(),
            "stereo" => ModelMetadata::default_stereo(),
            _ => return None,
        };
        if lidar {
            m.sensor.push(Sensor::SectorLidar);
            m = ModelMetadata::parse(&m.to_json(), "default").expect("the default LiDAR metadata parses");
        }
        Some(m)
    }

    /// The `--sensor` names [`ModelMetadata::for_sensor`] knows.
    pub const SENSOR_NAMES: [&'static str; 5] = ["state", "camera", "stereo", "camera+lidar", "stereo+lidar"];

    /// The file as DeepRacer writes it (its keys, in its order; unknown keys kept).
    pub fn to_json(&self) -> String {
        let mut out = Map::new();
        let action_space = match &self.action_space {
            ActionSpace::Discrete(a) => Value::Array(
                a.iter()
                    .enumerate()
                    .map(|(i, a)| serde_json::json!({"steering_angle": a.steering_angle, "speed": a.speed, "index": i}))
                    .collect(),
            ),
            ActionSpace::Continuous { steering_angle: (sl, sh), speed: (vl, vh) } => {
                serde_json::json!({"steering_angle": {"low": sl, "high": sh}, "speed": {"low": vl, "high": vh}})
            }
        };
        out.insert("action_space".into(), action_space);
        out.insert("sensor".into(), Value::Array(self.sensor.iter().map(|s| Value::String(s.name().into())).collect()));
        out.insert("neural_network".into(), Value::String(self.neural_network.name().into()));
        out.insert(
            "training_algorithm".into(),
            Value::String(match self.training_algorithm {
                TrainingAlgorithm::ClippedPpo => "clipped_ppo".into(),
                TrainingAlgorithm::Sac => "sac".into(),
            }),
        );
        out.insert(
            "action_space_type".into(),
            Value::String(
                if matches!(self.action_space, ActionSpace::Discrete(_)) { "discrete" } else { "continuous" }.into(),
            ),
        );
        out.insert("version".into(), Value::String(format!("{}", self.version)));
        for (k, v) in &self.raw {
            out.entry(k.clone()).or_insert_with(|| v.clone());
        }
        serde_json::to_string_pretty(&Value::Object(out)).expect("JSON")
    }

    /// Whether another metadata's network inputs and outputs match this one's
    /// (same sensors, same network, same action count and kind); the reason if not.
    pub fn compatible_with(&self, other: &ModelMetadata) -> Result<(), Incompatible> {
        if self.sensor != other.sensor {
            return Err(Incompatible::Sensors { ours: self.sensor.clone(), theirs: other.sensor.clone() });
        }
        if self.neural_network != other.neural_network {
            return Err(Incompatible::Network { ours: self.neural_network, theirs: other.neural_network });
        }
        let kind = |m: &ModelMetadata| {
            if matches!(m.action_space, ActionSpace::Discrete(_)) { "discrete" } else { "continuous" }
        };
        if kind(self) != kind(other) || self.action_space.dim() != other.action_space.dim() {
            return Err(Incompatible::Outputs {
                ours: (kind(self), self.action_space.dim()),
                theirs: (kind(other), other.action_space.dim()),
            });
        }
        if self.action_space != other.action_space {
            return Err(Incompatible::ActionValues);
        }
        Ok(())
    }
}

/// Why a model's network does not fit another `model_metadata.json` (resuming or cloning a
/// run with other metadata): what differs, both values, and why it matters.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum Incompatible {
    /// `sensor` differs: the network's inputs would not match.
    #[error("sensors differ ({ours:?} vs {theirs:?}): the network's inputs would no longer match")]
    Sensors {
        /// This model's sensors.
        ours: Vec<Sensor>,
        /// The other metadata's.
        theirs: Vec<Sensor>,
    },
    /// `neural_network` differs.
    #[error("neural_network differs ({} vs {})", .ours.name(), .theirs.name())]
    Network {
        /// This model's network.
        ours: NeuralNetwork,
        /// The other metadata's.
        theirs: NeuralNetwork,
    },
    /// The action space's kind or size differs: the output layer would not match.
    #[error(
        "the action space differs ({} {} outputs vs {} {}): the output layer would no longer match",
        .ours.0, .ours.1, .theirs.0, .theirs.1
    )]
    Outputs {
        /// This model's action space: `discrete` or `continuous`, and its outputs.
        ours: (&'static str, usize),
        /// The other metadata's.
        theirs: (&'static str, usize),
    },
    /// Same shape, other values: each output would mean another action.
    #[error("the action space's values differ: each output of the trained network would change meaning")]
    ActionValues,
}

/// `lidar_config` for `DISCRETIZED_SECTOR_LIDAR`, with DeepRacer's defaults and checks
/// (`DiscretizedSectorLidarDefaults`, `parse_model_metadata`).
fn parse_lidar_config(config: Option<&Value>) -> Result<LidarInput, String> {
    let mut out = LidarInput { sensor: Sensor::DiscretizedSectorLidar, sectors: 8, values: 8, clip: 2.0 };
    let Some(config) = config else { return Ok(out) };
    let Value::Object(config) = config else {
        return Err(format!("field 'lidar_config' is {config}, expected an object"));
    };
    let count = |key: &str, default: usize| match config.get(key) {
        None => Ok(default),
        Some(v) => v
            .as_u64()
            .or_else(|| v.as_f64().filter(|f| f.fract() == 0.0 && *f >= 0.0).map(|f| f as u64))
            .map(|n| n as usize)
            .ok_or_else(|| format!("field 'lidar_config.{key}' is {v}, expected a whole number")),
    };
    out.sectors = count("num_sectors", 8)?;
    if out.sectors == 0 || !LidarInput::RAYS.is_multiple_of(out.sectors) {
        return Err(format!(
            "field 'lidar_config.num_sectors' is {}: 64 % Number of sector (n) must be 0! (1, 2, 4, 8, 16, 32 or 64)",
            out.sectors
        ));
    }
    out.values = count("num_values_per_sector", 8)?;
    if out.values == 0 {
        return Err("field 'lidar_config.num_values_per_sector' is 0, expected at least 1".into());
    }
    if let Some(v) = config.get("clipping_dist") {
        let clip = number(v, "lidar_config.clipping_dist")?;
        if clip <= 0.0 {
            return Err(format!("field 'lidar_config.clipping_dist' is {clip}, expected a distance over 0 m"));
        }
        // DeepRacer's filter clamps it to the sensor's range.
        out.clip = clip.clamp(0.15, 12.0) as f32;
    }
    Ok(out)
}

fn number(v: &Value, field: &str) -> Result<f64, String> {
    v.as_f64().filter(|x| x.is_finite()).ok_or_else(|| format!("field '{field}' is {v}, expected a number"))
}

fn parse_discrete(space: &Value) -> Result<ActionSpace, String> {
    let Value::Array(items) = space else {
        return Err("field 'action_space' must be a list of {steering_angle, speed} for a discrete action space".into());
    };
    if items.is_empty() {
        return Err("field 'action_space' is an empty list".into());
    }
    let mut actions = Vec::with_capacity(items.len());
    for (i, item) in items.iter().enumerate() {
        let get = |k: &str| {
            item.get(k)
                .ok_or_else(|| format!("action_space[{i}] has no '{k}'"))
                .and_then(|v| number(v, &format!("action_space[{i}].{k}")))
        };
        actions.push(Action { steering_angle: get("steering_angle")?, speed: get("speed")? });
    }
    Ok(ActionSpace::Discrete(actions))
}

fn parse_continuous(space: &Value) -> Result<ActionSpace, String> {
    let range = |k: &str| -> Result<(f64, f64), String> {
        let r = space.get(k).ok_or_else(|| format!("continuous 'action_space' has no '{k}'"))?;
        let get = |b: &str| {
            r.get(b)
                .ok_or_else(|| format!("action_space.{k} has no '{b}'"))
                .and_then(|v| number(v, &format!("action_space.{k}.{b}")))
        };
        let (lo, hi) = (get("low")?, get("high")?);
        if lo >= hi {
            return Err(format!("action_space.{k}: low ({lo}) must be less than high ({hi})"));
        }
        Ok((lo, hi))
    };
    if !space.is_object() {
        return Err("field 'action_space' must be an object {steering_angle:{low,high}, speed:{low,high}} for a continuous action space".into());
    }
    Ok(ActionSpace::Continuous { steering_angle: range("steering_angle")?, speed: range("speed")? })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn drfc_defaults_parse() {
        let d = ModelMetadata::parse(
            r#"{"action_space":[{"steering_angle":-30,"speed":0.6},{"steering_angle":0,"speed":0.6,"index":1}],
                "sensor":["FRONT_FACING_CAMERA"],"neural_network":"DEEP_CONVOLUTIONAL_NETWORK_SHALLOW",
                "training_algorithm":"clipped_ppo","action_space_type":"discrete","version":"5"}"#,
            "m.json",
        )
        .unwrap();
        assert_eq!(d.action_space.dim(), 2);
        assert_eq!(d.action_space.discrete(1), Some(Action { steering_angle: 0.0, speed: 0.6 }));
        assert_eq!(d.version, 5.0);
        let c = ModelMetadata::parse(
            r#"{"action_space":{"speed":{"high":2,"low":1},"steering_angle":{"high":30,"low":-30}},
                "sensor":["FRONT_FACING_CAMERA"],"action_space_type":"continuous","version":"5"}"#,
            "c.json",
        )
        .unwrap();
        assert_eq!(c.action_space.scale([-1.0, 1.0]), Some(Action { steering_angle: -30.0, speed: 2.0 }));
        assert_eq!(c.action_space.scale([0.0, 0.0]), Some(Action { steering_angle: 0.0, speed: 1.5 }));
        let v1 = ModelMetadata::parse(r#"{"action_space":[{"steering_angle":0,"speed":1}]}"#, "v1.json").unwrap();
        assert_eq!(v1.sensor, vec![Sensor::Observation]);
    }

    #[test]
    fn bad_files_name_the_field() {
        let cases = [
            ("[]", "expected a JSON object"),
            ("{}", "field 'action_space' is missing"),
            (r#"{"action_space":[{"speed":1}]}"#, "action_space[0] has no 'steering_angle'"),
            (r#"{"action_space":[{"steering_angle":"x","speed":1}]}"#, "action_space[0].steering_angle"),
            (
                r#"{"action_space":{"speed":{"low":2,"high":1},"steering_angle":{"low":-1,"high":1}},"action_space_type":"continuous"}"#,
                "low (2) must be less than high (1)",
            ),
            (r#"{"action_space":[{"steering_angle":0,"speed":1}],"action_space_type":"weird"}"#, "action_space_type"),
            (r#"{"action_space":[{"steering_angle":0,"speed":1}],"version":"4"}"#, "'sensor' is required"),
            (
                r#"{"action_space":[{"steering_angle":0,"speed":1}],"version":"4","sensor":["LIDAR"]}"#,
                "model_metadata MUST contain only 1 camera sensor: [\"LIDAR\"]",
            ),
            (
                r#"{"action_space":[{"steering_angle":0,"speed":1}],"version":"4","sensor":["FRONT_FACING_CAMERA","STEREO_CAMERAS"]}"#,
                "model_metadata MUST contain only 1 camera sensor",
            ),
            (
                r#"{"action_space":[{"steering_angle":0,"speed":1}],"version":"4","sensor":["FRONT_FACING_CAMERA","LIDAR","SECTOR_LIDAR"]}"#,
                "model_metadata contains more than 1 lidar sensor",
            ),
            (r#"{"action_space":[{"steering_angle":0,"speed":1}],"training_algorithm":"sac"}"#, "needs a continuous"),
            (
                r#"{"action_space":[{"steering_angle":0,"speed":1}],"version":"4","sensor":["FRONT_FACING_CAMERA","DISCRETIZED_SECTOR_LIDAR"],"lidar_config":{"num_sectors":3}}"#,
                "field 'lidar_config.num_sectors' is 3: 64 % Number of sector (n) must be 0!",
            ),
            (
                r#"{"action_space":[{"steering_angle":0,"speed":1}],"version":"4","sensor":["FRONT_FACING_CAMERA","DISCRETIZED_SECTOR_LIDAR"],"lidar_config":{"num_values_per_sector":0}}"#,
                "field 'lidar_config.num_values_per_sector' is 0",
            ),
            (
                r#"{"action_space":[{"steering_angle":0,"speed":1}],"version":"4","sensor":["FRONT_FACING_CAMERA","DISCRETIZED_SECTOR_LIDAR"],"lidar_config":{"clipping_dist":"far"}}"#,
                "field 'lidar_config.clipping_dist' is \"far\", expected a number",
            ),
        ];
        for (text, want) in cases {
            let e = ModelMetadata::parse(text, "bad.json").expect_err(want).to_string();
            assert!(e.starts_with("bad.json: ") && e.contains(want), "{want}: {e}");
        }
    }

    /// Issue 31: LiDAR inputs are read as DeepRacer reads them.
    #[test]
    fn lidar_inputs_are_read_as_deepracer_reads_them() {
        let parse = |sensors: &str, extra: &str| {
            ModelMetadata::parse(
                &format!(
                    r#"{{"action_space":[{{"steering_angle":0,"speed":1}}],"version":"5","sensor":[{sensors}]{extra}}}"#
                ),
                "m.json",
            )
            .unwrap()
            .lidar
        };
        let l = |sensor, sectors, values, clip| Some(LidarInput { sensor, sectors, values, clip });
        // (sensors, lidar_config, what the network gets)
        let table = [
            (r#""FRONT_FACING_CAMERA""#, "", None),
            (r#""FRONT_FACING_CAMERA","LIDAR""#, "", l(Sensor::Lidar, 64, 1, 1.0)),
            (r#""STEREO_CAMERAS","SECTOR_LIDAR""#, "", l(Sensor::SectorLidar, 8, 1, 0.5)),
            // SECTOR_LIDAR ignores lidar_config, as DeepRacer does.
            (
                r#""FRONT_FACING_CAMERA","SECTOR_LIDAR""#,
                r#","lidar_config":{"num_sectors":4}"#,
                l(Sensor::SectorLidar, 8, 1, 0.5),
            ),
            (r#""FRONT_FACING_CAMERA","DISCRETIZED_SECTOR_LIDAR""#, "", l(Sensor::DiscretizedSectorLidar, 8, 8, 2.0)),
            (
                r#""FRONT_FACING_CAMERA","DISCRETIZED_SECTOR_LIDAR""#,
                r#","lidar_config":{"num_sectors":16,"num_values_per_sector":4,"clipping_dist":20}"#,
                l(Sensor::DiscretizedSectorLidar, 16, 4, 12.0),
            ),
        ];
        for (sensors, extra, want) in table {
            assert_eq!(parse(sensors, extra), want, "{sensors} {extra}");
        }
    }
}
