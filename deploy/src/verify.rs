//! Every check a model passes before a car drives it, in order: signed by a trusted key (or,
//! for a DeepRacer archive, which no one signs, named in `car.toml`'s `trust_unsigned`); the
//! weights' sha256 equals the manifest's (and every tensor fits `model_metadata.json`); the
//! model's sensors and action space fit the car (`car.toml`); its input is the camera frame
//! (and the LiDAR's values) the car produces.

use crate::infer::CarPolicy;
use policy::car::{CarConfig, ServoMap};
use policy::model::{CAMERA_SHAPE, input_shape};
use policy::nn::InputShape;
use policy::signature::TrustedKeys;
use policy::{ActorCritic, Manifest, ModelMetadata, ModelParts};
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

/// Check a model's files for this car (see the module documentation); the reason when not.
pub fn verify(parts: ModelParts, trust: &TrustedKeys, car: &CarConfig, source: &str) -> Result<VerifiedModel, String> {
    let key = parts.verify(trust).map_err(|e| format!("signature: {e}"))?.to_string();
    checked(parts, key, car, source)
}

/// [`verify`] for a model imported from DeepRacer's archive named `name` (see
/// `policy::carpkg::car_model_name`): unsigned, so driven only when `car.toml` trusts that name.
pub fn verify_import(parts: ModelParts, name: &str, car: &CarConfig, source: &str) -> Result<VerifiedModel, String> {
    if !car.trust_unsigned.iter().any(|n| n == name) {
        return Err(format!(
            "'{name}' is an unsigned DeepRacer model: the car drives it only if car.toml's trust_unsigned lists \"{name}\""
        ));
    }
    checked(parts, format!("unsigned, trusted by name ('{name}' in car.toml)"), car, source)
}

/// Every check after the signature's.
fn checked(parts: ModelParts, key: String, car: &CarConfig, source: &str) -> Result<VerifiedModel, String> {
    let folder = parts.decode(Path::new(source)).map_err(|e| e.to_string())?;
    car.fits(&folder.metadata)?;
    let input = match input_shape(&folder.metadata, folder.manifest.obs_size) {
        InputShape::Image(h, w, c) => (h, w, c),
        InputShape::Flat(n) => return Err(format!("the model takes a vector of {n}, not a camera frame")),
    };
    let (h, w, _) = CAMERA_SHAPE;
    let size = policy::model::input_size(&folder.metadata, folder.manifest.obs_size);
    if folder.manifest.obs_size != size || (input.0, input.1) != (h, w) {
        return Err(format!(
            "the manifest says {} inputs; the car gives {}×{}×{} frames{}",
            folder.manifest.obs_size,
            input.0,
            input.1,
            input.2,
            folder.metadata.lidar.map_or(String::new(), |l| format!(" and {} LiDAR values", l.size()))
        ));
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
