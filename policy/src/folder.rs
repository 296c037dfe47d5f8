//! The model folder: what a trained model is on disk, and what a car will receive.
//!
//! ```text
//! model/
//!   model.safetensors     weights: pi.<layer>.weight/bias, v.<layer>.weight/bias, pi.log_std
//!   model_metadata.json   DeepRacer's file, as DeepRacer writes it
//!   manifest.json         policy version, parent model, sha256 of the weights, figures
//!   signature.json        the learner's ed25519 signature over the three (see `signature`)
//! ```
//!
//! Saving writes a sibling temporary folder and renames it into place, so a reader sees the
//! old folder or the new one, never half of one. Loading checks every tensor's presence and
//! shape against what `model_metadata.json` implies, and the weights' checksum.

use crate::error::FileError;
use crate::metadata::ModelMetadata;
use crate::model::{ActorCritic, Head};
use crate::nn::{Layer, Net};
use crate::signature::{ModelSignature, SignatureError, Signer, TrustedKeys};
use safetensors::{Dtype, SafeTensors, tensor::TensorView};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// The folder's manifest.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Manifest {
    /// Format tag: `paddock-model-1`.
    pub format: String,
    /// The policy version these weights are (0 = freshly initialised; +1 per update).
    pub policy_version: u64,
    /// The model this one was cloned or trained from.
    pub parent: Option<Parent>,
    /// sha256 of `model.safetensors`, hex.
    pub weights_sha256: String,
    /// Inputs per observation (the state vector's length; the camera's pixel count).
    pub obs_size: usize,
    /// The simulator's observation settings the model was trained with (opaque here).
    pub observation: serde_json::Value,
    /// Training figures (iteration, steps, best evaluation, hyperparameters…).
    pub training: serde_json::Value,
}

/// Where a model came from.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Parent {
    /// The parent folder as given.
    pub path: String,
    /// Its policy version.
    pub policy_version: u64,
    /// Its weights' checksum.
    pub weights_sha256: String,
}

/// A loaded model folder.
#[derive(Clone, Debug, PartialEq)]
pub struct ModelFolder {
    /// `model_metadata.json`.
    pub metadata: ModelMetadata,
    /// The networks.
    pub model: ActorCritic,
    /// `manifest.json`.
    pub manifest: Manifest,
}

/// Why a model folder could not be read or written: a [`FileError`] naming the folder's file
/// (the weights, the metadata, the manifest or the signature).
pub type ModelError = FileError;

/// Named tensors of a model: (name, shape, values).
fn tensors(model: &ActorCritic) -> Vec<(String, Vec<usize>, &[f32])> {
    let mut out = Vec::new();
    for (tower, net) in [("pi", &model.pi), ("v", &model.v)] {
        for (i, layer) in net.layers.iter().enumerate() {
            let (wshape, offset, nw, nb) = match *layer {
                Layer::Dense { inp, out, offset } => (vec![out, inp], offset, inp * out, out),
                Layer::Conv2d { input: [_, _, c], filters, kernel, offset, .. } => {
                    (vec![filters, kernel, kernel, c], offset, filters * kernel * kernel * c, filters)
                }
                _ => continue,
            };
            out.push((format!("{tower}.{i}.weight"), wshape, &net.params[offset..offset + nw]));
            out.push((format!("{tower}.{i}.bias"), vec![nb], &net.params[offset + nw..offset + nw + nb]));
        }
    }
    if let Head::Gaussian { log_std } = &model.head {
        out.push(("pi.log_std".into(), vec![2], log_std.as_slice()));
    }
    out
}

/// The safetensors bytes of a model's weights.
pub fn weights_bytes(model: &ActorCritic, policy_version: u64) -> Vec<u8> {
    let named = tensors(model);
    let bytes: Vec<(String, Vec<usize>, Vec<u8>)> =
        named.into_iter().map(|(n, s, v)| (n, s, v.iter().flat_map(|x| x.to_le_bytes()).collect())).collect();
    let views: Vec<(String, TensorView<'_>)> = bytes
        .iter()
        .map(|(n, s, b)| (n.clone(), TensorView::new(Dtype::F32, s.clone(), b).expect("sizes agree")))
        .collect();
    let info = HashMap::from([
        ("format".to_string(), "paddock-policy-1".to_string()),
        ("policy_version".to_string(), policy_version.to_string()),
    ]);
    safetensors::serialize(views, Some(info)).expect("serialisable")
}

/// sha256 of bytes, hex.
pub fn sha256_hex(bytes: &[u8]) -> String {
    format!("{:x}", Sha256::digest(bytes))
}

/// A model's files as bytes: what a folder holds and what travels on the network.
#[derive(Clone, Debug, PartialEq)]
pub struct ModelParts {
    /// `model_metadata.json`.
    pub metadata_json: String,
    /// `manifest.json`.
    pub manifest_json: String,
    /// `model.safetensors`.
    pub weights: Vec<u8>,
    /// `signature.json`, when the model is signed.
    pub signature: Option<ModelSignature>,
}

impl ModelParts {
    /// The parts of a model; `manifest.weights_sha256` is filled in, and the parts are signed
    /// when a signer is given.
    pub fn new(
        metadata: &ModelMetadata,
        model: &ActorCritic,
        manifest: &Manifest,
        signer: Option<&Signer>,
    ) -> ModelParts {
        let weights = weights_bytes(model, manifest.policy_version);
        let mut manifest = manifest.clone();
        manifest.weights_sha256 = sha256_hex(&weights);
        let metadata_json = metadata.to_json();
        let manifest_json = serde_json::to_string_pretty(&manifest).expect("JSON");
        let signature = signer.map(|s| s.sign(&weights, &metadata_json, &manifest_json));
        ModelParts { metadata_json, manifest_json, weights, signature }
    }

    /// Read a folder's files as they are (nothing checked but that they are there).
    pub fn read(dir: &Path) -> Result<ModelParts, ModelError> {
        let read_text = |file: &str| -> Result<String, ModelError> {
            let p = dir.join(file);
            std::fs::read_to_string(&p).map_err(FileError::io_at(&p))
        };
        let metadata_json = read_text("model_metadata.json")?;
        let manifest_json = read_text("manifest.json")?;
        let w_path = dir.join("model.safetensors");
        let weights = std::fs::read(&w_path).map_err(FileError::io_at(&w_path))?;
        let s_path = dir.join("signature.json");
        let signature =
            match std::fs::read_to_string(&s_path) {
                Ok(text) => Some(serde_json::from_str(&text).map_err(|e| {
                    FileError::invalid(s_path.display().to_string(), format!("not a signature file: {e}"))
                })?),
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
                Err(e) => return Err(FileError::io(&s_path, e)),
            };
        Ok(ModelParts { metadata_json, manifest_json, weights, signature })
    }

    /// Write them as the folder `dir` (replacing one that is there): a sibling temporary
    /// folder renamed into place, so that a reader sees the old folder or the new one.
    pub fn write(&self, dir: &Path) -> Result<(), ModelError> {
        let parent = dir.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
        std::fs::create_dir_all(parent).map_err(FileError::io_at(parent))?;
        let name = dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "model".into());
        let tmp = parent.join(format!(".{name}.tmp-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&tmp);
        std::fs::create_dir_all(&tmp).map_err(FileError::io_at(&tmp))?;
        let write = |file: &str, bytes: &[u8]| -> Result<(), ModelError> {
            use std::io::Write;
            let p = tmp.join(file);
            let mut f = std::fs::File::create(&p).map_err(FileError::io_at(&p))?;
            f.write_all(bytes).and_then(|()| f.sync_all()).map_err(FileError::io_at(&p))
        };
        let written = (|| {
            write("model.safetensors", &self.weights)?;
            write("model_metadata.json", self.metadata_json.as_bytes())?;
            write("manifest.json", self.manifest_json.as_bytes())?;
            if let Some(sig) = &self.signature {
                write("signature.json", serde_json::to_string_pretty(sig).expect("JSON").as_bytes())?;
            }
            Ok(())
        })();
        if let Err(e) = written {
            // Nothing half-written is left behind; the folder at `dir`, if any, is untouched.
            let _ = std::fs::remove_dir_all(&tmp);
            return Err(e);
        }
        let old: PathBuf = parent.join(format!(".{name}.old-{}", std::process::id()));
        if dir.exists() {
            std::fs::rename(dir, &old).map_err(FileError::io_at(dir))?;
        }
        std::fs::rename(&tmp, dir).map_err(FileError::io_at(dir))?;
        let _ = std::fs::remove_dir_all(&old);
        Ok(())
    }

    /// The model, with every check of [`load`] (`origin` names the files in errors).
    pub fn decode(&self, origin: &Path) -> Result<ModelFolder, ModelError> {
        from_parts(&self.metadata_json, &self.manifest_json, &self.weights, origin)
    }

    /// Check the signature against `trust` (the key's name on success).
    pub fn verify<'t>(&self, trust: &'t TrustedKeys) -> Result<&'t str, SignatureError> {
        match &self.signature {
            Some(sig) => trust.verify(sig, &self.weights, &self.metadata_json, &self.manifest_json),
            None => Err(SignatureError::Refused("the model is not signed".into())),
        }
    }
}

/// Write a model folder at `dir` (replacing one that is there), unsigned. `manifest.weights_sha256`
/// is filled in here.
pub fn save(
    dir: &Path,
    metadata: &ModelMetadata,
    model: &ActorCritic,
    manifest: &Manifest,
) -> Result<Manifest, ModelError> {
    save_signed(dir, metadata, model, manifest, None)
}

/// Write a model folder at `dir`, with `signature.json` when a signer is given.
pub fn save_signed(
    dir: &Path,
    metadata: &ModelMetadata,
    model: &ActorCritic,
    manifest: &Manifest,
    signer: Option<&Signer>,
) -> Result<Manifest, ModelError> {
    let parts = ModelParts::new(metadata, model, manifest, signer);
    parts.write(dir)?;
    let mut manifest = manifest.clone();
    manifest.weights_sha256 = sha256_hex(&parts.weights);
    Ok(manifest)
}

/// Read a model folder, checking the weights against the metadata and the checksum.
pub fn load(dir: &Path) -> Result<ModelFolder, ModelError> {
    ModelParts::read(dir)?.decode(dir)
}

/// The three files of a model folder, as bytes (what travels on the network).
pub fn to_parts(folder: &ModelFolder) -> (String, String, Vec<u8>) {
    let p = ModelParts::new(&folder.metadata, &folder.model, &folder.manifest, None);
    (p.metadata_json, p.manifest_json, p.weights)
}

/// A model from its three files' contents (`dir` names them in errors), with every check of
/// [`load`].
pub fn from_parts(meta_text: &str, manifest_text: &str, bytes: &[u8], dir: &Path) -> Result<ModelFolder, ModelError> {
    let meta_path = dir.join("model_metadata.json");
    let metadata = ModelMetadata::parse(meta_text, &meta_path.display().to_string())
        .map_err(|e| FileError::invalid(meta_path.display().to_string(), e.msg))?;
    let man_path = dir.join("manifest.json");
    let manifest: Manifest = serde_json::from_str(manifest_text)
        .map_err(|e| FileError::invalid(man_path.display().to_string(), e.to_string()))?;
    let w_path = dir.join("model.safetensors");
    let bad = |msg: String| FileError::invalid(w_path.display().to_string(), msg);
    let sum = sha256_hex(bytes);
    if sum != manifest.weights_sha256 {
        return Err(bad(format!(
            "sha256 is {sum}, manifest.json says {}: the weights were changed or damaged",
            manifest.weights_sha256
        )));
    }
    let st = SafeTensors::deserialize(bytes).map_err(|e| bad(format!("not a safetensors file: {e}")))?;
    // The architecture the metadata implies; its weights are replaced below.
    let mut model = ActorCritic::new(
        &metadata,
        manifest.obs_size,
        &mut <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(0),
    );
    let expected: Vec<(String, Vec<usize>)> = tensors(&model).into_iter().map(|(n, s, _)| (n, s)).collect();
    let mut names: Vec<String> = st.names().into_iter().map(str::to_string).collect();
    names.sort();
    for (name, shape) in &expected {
        let t = st.tensor(name).map_err(|_| {
            bad(format!(
                "has no tensor '{name}' (shape {shape:?}) that model_metadata.json ({}, {} outputs) needs; it holds {names:?}",
                metadata.neural_network.name(),
                metadata.action_space.dim()
            ))
        })?;
        if t.dtype() != Dtype::F32 || t.shape() != shape.as_slice() {
            return Err(bad(format!(
                "tensor '{name}' is {:?} {:?}; model_metadata.json ({}, {} outputs, {} inputs) needs F32 {shape:?}",
                t.dtype(),
                t.shape(),
                metadata.neural_network.name(),
                metadata.action_space.dim(),
                manifest.obs_size
            )));
        }
    }
    if names.len() != expected.len() {
        let extra: Vec<&String> = names.iter().filter(|n| !expected.iter().any(|(e, _)| e == *n)).collect();
        return Err(bad(format!("holds tensors the metadata does not explain: {extra:?}")));
    }
    let read = |name: &str, dst: &mut [f32]| {
        let t = st.tensor(name).expect("checked above");
        for (d, c) in dst.iter_mut().zip(t.data().chunks_exact(4)) {
            *d = f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
        }
    };
    for (tower, net) in [("pi", &mut model.pi), ("v", &mut model.v)] {
        fill_net(tower, net, &read);
    }
    if let Head::Gaussian { log_std } = &mut model.head {
        read("pi.log_std", log_std);
    }
    Ok(ModelFolder { metadata, model, manifest })
}

fn fill_net(tower: &str, net: &mut Net, read: &impl Fn(&str, &mut [f32])) {
    let layers = net.layers.clone();
    for (i, layer) in layers.iter().enumerate() {
        let (offset, nw, nb) = match *layer {
            Layer::Dense { inp, out, offset } => (offset, inp * out, out),
            Layer::Conv2d { input: [_, _, c], filters, kernel, offset, .. } => {
                (offset, filters * kernel * kernel * c, filters)
            }
            _ => continue,
        };
        read(&format!("{tower}.{i}.weight"), &mut net.params[offset..offset + nw]);
        read(&format!("{tower}.{i}.bias"), &mut net.params[offset + nw..offset + nw + nb]);
    }
}
