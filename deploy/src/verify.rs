//! Every check a model passes before a car drives it, in order: signed by a trusted key (or,
//! for a DeepRacer archive, which no one signs, named in `car.toml`'s `trust_unsigned`); the
//! weights' sha256 equals the manifest's (and every tensor fits `model_metadata.json`); the
//! model's sensors and action space fit the car (`car.toml`); its input is the camera frame
//! (and the LiDAR's values) the car produces.

use crate::infer::CarPolicy;
use policy::car::{CarConfig, DoesNotFit, ServoMap};
use policy::model::{CAMERA_SHAPE, input_shape};
use policy::nn::InputShape;
use policy::signature::{SignatureError, TrustedKeys};
use policy::{ActorCritic, Manifest, ModelError, ModelMetadata, ModelParts};
use std::path::Path;

/// A model that passed every check, ready to drive.
#[derive(Debug)]
pub struct VerifiedModel {
    /// Its policy version.
    pub version: u64,
    /// Where it came from ("latest", "best", "folder DIR", …).
    pub source: String,
    /// The trusted key (its file) that signed it.
    pub key: String,
    /// `model_metadata.json`.
    pub metadata: ModelMetadata,
    /// `manifest.json`.
    pub manifest: Manifest,
    /// The networks as trained (f32).
    pub model: ActorCritic,
    /// The policy tower as the car runs it.
    pub policy: CarPolicy,
    /// Actions to servo ratios for this model.
    pub servo: ServoMap,
    /// The camera's input: rows, columns, channels.
    pub input: (usize, usize, usize),
    /// The LiDAR's input, when the model has one, and whether its values come before the
    /// camera's (DeepRacer's sorted input names).
    pub lidar: Option<(policy::metadata::LidarInput, bool)>,
    /// The files as verified (what `--model-dir` keeps).
    pub parts: ModelParts,
}

/// Why a car refuses a model: the check it failed, naming the file, key or limit.
#[derive(Debug, thiserror::Error)]
pub enum Refusal {
    /// Not signed by a trusted key.
    #[error("signature: {0}")]
    Signature(SignatureError),
    /// A DeepRacer archive's model whose name `car.toml` does not trust.
    #[error(
        "'{name}' is an unsigned DeepRacer model: the car drives it only if car.toml's trust_unsigned lists \"{name}\""
    )]
    Untrusted {
        /// The model's name (from the archive's file name).
        name: String,
    },
    /// A file of the model is damaged or does not match its metadata.
    #[error(transparent)]
    Model(#[from] ModelError),
    /// Its sensors or action space do not fit the car.
    #[error(transparent)]
    DoesNotFit(#[from] DoesNotFit),
    /// It takes a vector, not a camera frame.
    #[error("the model takes a vector of {0}, not a camera frame")]
    NotCamera(usize),
    /// Its input is not the frames (and LiDAR values) the car gives.
    #[error(
        "the manifest says {obs_size} inputs; the car gives {}×{}×{} frames{}",
        .frame.0, .frame.1, .frame.2,
        .lidar.map_or(String::new(), |n| format!(" and {n} LiDAR values"))
    )]
    Inputs {
        /// `manifest.json`'s `obs_size`.
        obs_size: usize,
        /// The frame the model takes: rows, columns, channels.
        frame: (usize, usize, usize),
        /// The LiDAR values it takes, if any.
        lidar: Option<usize>,
    },
}

/// Check a model's files for this car (see the module documentation); the reason when not.
pub fn verify(parts: ModelParts, trust: &TrustedKeys, car: &CarConfig, source: &str) -> Result<VerifiedModel, Refusal> {
    let key = parts.verify(trust).map_err(Refusal::Signature)?.to_string();
    checked(parts, key, car, source)
}

/// [`verify`] for a model imported from DeepRacer's archive named `name` (see
/// `policy::carpkg::car_model_name`): unsigned, so driven only when `car.toml` trusts that name.
pub fn verify_import(parts: ModelParts, name: &str, car: &CarConfig, source: &str) -> Result<VerifiedModel, Refusal> {
    if !car.trust_unsigned.iter().any(|n| n == name) {
        return Err(Refusal::Untrusted { name: name.to_string() });
    }
    checked(parts, format!("unsigned, trusted by name ('{name}' in car.toml)"), car, source)
}

/// Every check after the signature's.
fn checked(parts: ModelParts, key: String, car: &CarConfig, source: &str) -> Result<VerifiedModel, Refusal> {
    let folder = parts.decode(Path::new(source))?;
    car.fits(&folder.metadata)?;
    let input = match input_shape(&folder.metadata, folder.manifest.obs_size) {
        InputShape::Image(h, w, c) => (h, w, c),
        InputShape::Flat(n) => return Err(Refusal::NotCamera(n)),
    };
    let (h, w, _) = CAMERA_SHAPE;
    let size = policy::model::input_size(&folder.metadata, folder.manifest.obs_size);
    if folder.manifest.obs_size != size || (input.0, input.1) != (h, w) {
        return Err(Refusal::Inputs {
            obs_size: folder.manifest.obs_size,
            frame: input,
            lidar: folder.metadata.lidar.map(|l| l.size()),
        });
    }
    let lidar = folder.metadata.lidar.map(|l| {
        let first = policy::model::inputs(&folder.metadata, 0)[0].0 == l.sensor;
        (l, first)
    });
    let servo = ServoMap::new(&car.mapping, &folder.metadata.action_space);
    Ok(VerifiedModel {
        version: folder.manifest.policy_version,
        source: source.into(),
        key,
        servo,
        input,
        lidar,
        metadata: folder.metadata,
        manifest: folder.manifest,
        policy: CarPolicy::new(&folder.model, car.precision),
        model: folder.model,
        parts,
    })
}
