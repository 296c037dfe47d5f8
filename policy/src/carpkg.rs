//! DeepRacer's model archive, the file a car's console, its USB loader and DeepRacer on AWS
//! ("physical car model") all move a model in: a gzip-compressed tar with `agent/model.pb`
//! (the frozen graph, [`crate::tfgraph`]) and `model_metadata.json` at its root, no top
//! folder. deepracer-for-cloud's `create-car-zip.sh` writes the same.
//!
//! Reading follows the car's loader (`model_loader_node.py`): the one `.pb` may be anywhere
//! in the archive (more than one is refused, as the car refuses it), the metadata must be at
//! the root. Beyond the car: entries that are not plain files or folders, paths that leave the
//! archive, and archives over [`MAX_ARCHIVE_BYTES`] unpacked are refused, naming the entry.

use crate::error::FileError;
use crate::folder::{Manifest, ModelFolder, sha256_hex};
use crate::metadata::ModelMetadata;
use crate::model::ActorCritic;
use crate::tfgraph::{self, GraphError};
use std::io::Read;
use std::path::{Component, Path};

/// The largest archive read, unpacked.
pub const MAX_ARCHIVE_BYTES: u64 = 1 << 30;
/// Where the graph goes in the archives Paddock writes.
pub const GRAPH_PATH: &str = "agent/model.pb";
/// The metadata's name, at the archive's root.
pub const METADATA_PATH: &str = "model_metadata.json";

/// Why an archive could not be written or read.
#[derive(Debug, thiserror::Error)]
pub enum PackageError {
    /// The archive could not be read or written, or is not what a car takes (the message
    /// names the entry).
    #[error(transparent)]
    File(#[from] FileError),
    /// Its metadata is not a `model_metadata.json` Paddock reads.
    #[error(transparent)]
    Metadata(#[from] crate::metadata::MetadataError),
    /// Its graph is not the network the metadata names.
    #[error("{path}: {error}")]
    Graph {
        /// The graph's file.
        path: String,
        /// What is wrong.
        error: GraphError,
    },
}

/// An archive's contents.
#[derive(Clone, Debug)]
pub struct Package {
    /// The graph's path inside the archive.
    pub graph_path: String,
    /// `model.pb`'s bytes.
    pub graph: Vec<u8>,
    /// `model_metadata.json` as written.
    pub metadata_text: String,
    /// It, parsed.
    pub metadata: ModelMetadata,
}

/// The name a car gives a model from its archive's file name: up to the first dot, spaces
/// as `_` (the loader's rule).
pub fn car_model_name(path: &Path) -> String {
    let file = path.file_name().map(|f| f.to_string_lossy().into_owned()).unwrap_or_default();
    file.split('.').next().unwrap_or("").replace(' ', "_")
}

/// The archive's bytes for `model`'s policy tower and its metadata.
pub fn pack(model: &ActorCritic, meta: &ModelMetadata) -> Result<Vec<u8>, GraphError> {
    let graph = tfgraph::write(model, meta)?;
    let metadata = meta.to_json();
    let gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    let mut tar = tar::Builder::new(gz);
    for (name, bytes) in [(GRAPH_PATH, graph.as_slice()), (METADATA_PATH, metadata.as_bytes())] {
        let mut h = tar::Header::new_gnu();
        h.set_size(bytes.len() as u64);
        h.set_mode(0o644);
        h.set_mtime(0);
        h.set_entry_type(tar::EntryType::Regular);
        h.set_cksum();
        tar.append_data(&mut h, name, bytes).expect("writing to memory");
    }
    Ok(tar.into_inner().and_then(|gz| gz.finish()).expect("writing to memory"))
}

/// Write the archive at `path` (whole or not at all: a temporary file renamed); its size.
pub fn write(path: &Path, model: &ActorCritic, meta: &ModelMetadata) -> Result<usize, PackageError> {
    let bytes =
        pack(model, meta).map_err(|source| PackageError::Graph { path: path.display().to_string(), error: source })?;
    let tmp = path.with_file_name(format!(
        ".{}.tmp",
        path.file_name().map(|f| f.to_string_lossy().into_owned()).unwrap_or_default()
    ));
    std::fs::write(&tmp, &bytes).map_err(FileError::io_at(path))?;
    std::fs::rename(&tmp, path).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        FileError::io(path, e)
    })?;
    Ok(bytes.len())
}

/// Read an archive (`.tar.gz`, or a plain `.tar`), as a car's loader does.
pub fn read(path: &Path) -> Result<Package, PackageError> {
    let bytes = std::fs::read(path).map_err(FileError::io_at(path))?;
    unpack(&bytes, &path.display().to_string())
}

/// [`read`] of an archive's bytes; `origin` names it in errors.
pub fn unpack(bytes: &[u8], origin: &str) -> Result<Package, PackageError> {
    let bad = |msg: String| PackageError::from(FileError::invalid(origin, msg));
    let gz = bytes.starts_with(&[0x1f, 0x8b]);
    let reader: Box<dyn Read + '_> =
        if gz { Box::new(flate2::read::GzDecoder::new(bytes).take(MAX_ARCHIVE_BYTES + 1)) } else { Box::new(bytes) };
    let mut archive = tar::Archive::new(reader);
    let mut graphs: Vec<(String, Vec<u8>)> = vec![];
    let mut metadata: Option<String> = None;
    let mut total = 0u64;
    let entries = archive.entries().map_err(|e| bad(format!("not a tar archive: {e}")))?;
    for entry in entries {
        let mut entry = entry.map_err(|e| bad(format!("not a tar archive (or a damaged one): {e}")))?;
        let name = entry.path().map_err(|e| bad(format!("an entry's name: {e}")))?.into_owned();
        let shown = name.display().to_string();
        let kind = entry.header().entry_type();
        if kind.is_dir() {
            continue;
        }
        if !(kind.is_file() || kind == tar::EntryType::Continuous) {
            return Err(bad(format!("entry {shown} is a {kind:?}, not a file (links are refused)")));
        }
        if name.components().any(|c| !matches!(c, Component::Normal(_) | Component::CurDir)) {
            return Err(bad(format!("entry {shown} leaves the archive")));
        }
        total += entry.size();
        if total > MAX_ARCHIVE_BYTES {
            return Err(bad(format!("over {MAX_ARCHIVE_BYTES} bytes unpacked")));
        }
        let is_graph = name.extension().is_some_and(|e| e == "pb");
        let at_root = name.components().filter(|c| matches!(c, Component::Normal(_))).count() == 1;
        let is_metadata = at_root && name.file_name().is_some_and(|f| f == METADATA_PATH);
        if !(is_graph || is_metadata) {
            continue;
        }
        let mut data = Vec::with_capacity(entry.size() as usize);
        entry.read_to_end(&mut data).map_err(|e| bad(format!("entry {shown}: {e}")))?;
        if is_graph {
            graphs.push((shown, data));
        } else {
            metadata = Some(String::from_utf8(data).map_err(|_| bad(format!("{METADATA_PATH} is not UTF-8 text")))?);
        }
    }
    let (graph_path, graph) = match graphs.len() {
        0 => return Err(bad("no model: the archive holds no .pb file (a car needs agent/model.pb)".into())),
        1 => graphs.pop().expect("one"),
        _ => {
            let names: Vec<&str> = graphs.iter().map(|(n, _)| n.as_str()).collect();
            return Err(bad(format!(
                "{} graphs ({}): a car refuses an archive with more than one .pb",
                names.len(),
                names.join(", ")
            )));
        }
    };
    let metadata_text =
        metadata.ok_or_else(|| bad(format!("no {METADATA_PATH} at the archive's root (a car needs it there)")))?;
    let metadata = ModelMetadata::parse(&metadata_text, &format!("{origin}: {METADATA_PATH}"))?;
    Ok(Package { graph_path, graph, metadata_text, metadata })
}

impl Package {
    /// The policy tower of the archive's graph, checked against its metadata, with a fresh
    /// value tower from `seed`.
    pub fn model(&self, origin: &str, seed: u64) -> Result<ActorCritic, PackageError> {
        tfgraph::read(&self.graph, &self.metadata, seed)
            .map_err(|source| PackageError::Graph { path: format!("{origin}: {}", self.graph_path), error: source })
    }

    /// The model as a Paddock model folder (policy version 0; the manifest says where it came
    /// from, and that its value tower is new).
    pub fn to_folder(&self, origin: &str, seed: u64) -> Result<ModelFolder, PackageError> {
        let model = self.model(origin, seed)?;
        let manifest = Manifest {
            format: "paddock-model-1".into(),
            policy_version: 0,
            parent: None,
            weights_sha256: String::new(),
            obs_size: model.obs_size(),
            observation: serde_json::json!({"kind": "camera"}),
            training: serde_json::json!({
                "imported": {
                    "from": origin,
                    "graph": self.graph_path,
                    "graph_sha256": sha256_hex(&self.graph),
                    "format": "DeepRacer frozen TensorFlow graph",
                    "value_tower": format!("new (seed {seed}): the graph holds the policy tower only"),
                }
            }),
        };
        Ok(ModelFolder { metadata: self.metadata.clone(), model, manifest })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn entry(tar: &mut tar::Builder<Vec<u8>>, name: &str, data: &[u8], kind: tar::EntryType) {
        let mut h = tar::Header::new_gnu();
        h.set_size(data.len() as u64);
        h.set_mode(0o644);
        h.set_entry_type(kind);
        // Names the builder would refuse (`..`) go into the header by hand, as a hostile
        // archive's would.
        let bytes = name.as_bytes();
        h.as_old_mut().name[..bytes.len()].copy_from_slice(bytes);
        h.set_cksum();
        tar.append(&h, data).unwrap();
    }

    fn archive(entries: &[(&str, &[u8], tar::EntryType)]) -> Vec<u8> {
        let mut tar = tar::Builder::new(Vec::new());
        for (n, d, k) in entries {
            entry(&mut tar, n, d, *k);
        }
        tar.into_inner().unwrap()
    }

    /// Issue 30: an archive is what a car loads and comes back whole.
    #[test]
    fn an_archive_is_what_a_car_loads_and_comes_back_whole() {
        let meta = ModelMetadata::default_camera();
        let mut rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(1);
        let model = ActorCritic::new(&meta, 0, &mut rng);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("my model.v2.tar.gz");
        write(&path, &model, &meta).unwrap();
        assert_eq!(car_model_name(&path), "my_model");
        // Exactly the two files, at the car's paths.
        let bytes = std::fs::read(&path).unwrap();
        let mut a = tar::Archive::new(flate2::read::GzDecoder::new(bytes.as_slice()));
        let names: Vec<String> =
            a.entries().unwrap().map(|e| e.unwrap().path().unwrap().display().to_string()).collect();
        assert_eq!(names, [GRAPH_PATH, METADATA_PATH]);
        let p = read(&path).unwrap();
        assert_eq!(p.metadata, meta);
        assert_eq!(p.model("a", 2).unwrap().pi, model.pi);
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1, "no temporary file left");
    }

    /// Issue 30: archives a car would refuse are refused naming the entry.
    #[test]
    fn archives_a_car_would_refuse_are_refused_naming_the_entry() {
        use tar::EntryType::{Regular, Symlink};
        let meta = ModelMetadata::default_camera().to_json();
        let m = meta.as_bytes();
        for (entries, want) in [
            (vec![("model_metadata.json", m, Regular)], "no .pb file"),
            (vec![("agent/model.pb", &b"x"[..], Regular)], "no model_metadata.json at the archive's root"),
            (
                vec![("agent/model.pb", &b"x"[..], Regular), ("agent/model_metadata.json", m, Regular)],
                "no model_metadata.json at the archive's root",
            ),
            (
                vec![
                    ("a.pb", &b"x"[..], Regular),
                    ("agent/model.pb", &b"x"[..], Regular),
                    ("model_metadata.json", m, Regular),
                ],
                "2 graphs (a.pb, agent/model.pb)",
            ),
            (vec![("../model.pb", &b"x"[..], Regular), ("model_metadata.json", m, Regular)], "leaves the archive"),
            (vec![("agent/model.pb", &b""[..], Symlink), ("model_metadata.json", m, Regular)], "not a file"),
        ] {
            let e = unpack(&archive(&entries), "car.tar").unwrap_err().to_string();
            assert!(e.starts_with("car.tar: ") && e.contains(want), "{want}: {e}");
        }
        assert!(unpack(b"\x1f\x8b\x08garbage", "x.tar.gz").unwrap_err().to_string().contains("x.tar.gz"));
        // The metadata is checked; the graph against it.
        let bad_meta = archive(&[("agent/model.pb", b"x", Regular), ("model_metadata.json", b"{}", Regular)]);
        assert!(unpack(&bad_meta, "c.tar").unwrap_err().to_string().contains("model_metadata.json"));
        let not_graph =
            unpack(&archive(&[("agent/model.pb", b"\xff\xff", Regular), ("model_metadata.json", m, Regular)]), "c.tar")
                .unwrap()
                .model("c.tar", 1)
                .unwrap_err()
                .to_string();
        assert!(not_graph.contains("c.tar: agent/model.pb: not a TensorFlow GraphDef"), "{not_graph}");
    }
}
