//! DeepRacer's whole models, both ways: DeepRacer on AWS's `virtualmodel-NAME.tar.gz` (or its
//! folder) and deepracer-for-cloud's model prefix, read into a Paddock model folder with both
//! networks, and a Paddock model written as the folder DRoA's import page takes and
//! deepracer-for-cloud clones from.
//!
//! ```text
//! model_metadata.json  reward_function.py  training_params.yaml   (root)
//! ip/hyperparameters.json
//! model/model_metadata.json  model/.coach_checkpoint  model/deepracer_checkpoints.json
//! model/N_Step-M.ckpt.index  model/N_Step-M.ckpt.data-00000-of-00001  model/model_N.pb
//! metrics/training/training-N_Step-M.json   (DeepRacer's training metrics)
//! ```
//!
//! The checkpoint is `policy::tfckpt` with `policy::coach`'s variables. An imported model
//! keeps DeepRacer's files in its folder (`deepracer/`), so that it goes back out as it came
//! in; a model trained here takes them from its run folder and the options. What DRoA cannot
//! take (a track it lacks, head-to-bot, a network or sensor it has not got, SAC with more than
//! one episode between trainings) is refused, naming what and why.

use anyhow::{Context, Result, anyhow, bail, ensure};
use learner::hyperparams::{Hyperparameters, LossType};
use policy::coach::{self, SacCritics};
use policy::folder::{self, Manifest};
use policy::metadata::{ActionSpace, ModelMetadata, TrainingAlgorithm};
use policy::tfckpt;
use std::collections::BTreeMap;
use std::io::Read;
use std::path::{Component, Path, PathBuf};

/// The folder inside a Paddock model folder that keeps an imported model's DeepRacer files.
pub const KEPT: &str = "deepracer";
/// SAC's critics beside a model (the learner's file: `learner::sac::trainer::CRITICS_FILE`).
pub const CRITICS_FILE: &str = learner::sac::trainer::CRITICS_FILE;
/// The kept file naming the checkpoint a model was imported from (`N_Step-M.ckpt`).
pub const CHECKPOINT_KEPT: &str = "checkpoint";
/// The most a model folder may hold, unpacked (DRoA's import page's `MAX_FOLDER_SIZE`).
pub const MAX_FOLDER_BYTES: u64 = 1 << 30;

/// DRoA's tracks (`@deepracer-indy/config`'s `tracks.json`): id and the directions it
/// enables (`ccw`, `cw`, or both).
pub const DROA_TRACKS: &[(&str, &str)] = &[
    ("2022_reinvent_champ", "both"),
    ("reInvent2019_wide", "both"),
    ("2022_april_open", "both"),
    ("2022_april_pro", "both"),
    ("Austin", "ccw"),
    ("Singapore", "ccw"),
    ("Singapore_building", "ccw"),
    ("Vegas_track", "ccw"),
    ("AmericasGeneratedInclStart", "ccw"),
    ("dubai_pro", "ccw"),
    ("dubai_open", "both"),
    ("Bowtie_track", "ccw"),
    ("2022_june_open", "both"),
    ("2022_june_pro", "both"),
    ("Spain_track", "cw"),
    ("jyllandsringen_pro", "both"),
    ("jyllandsringen_open", "both"),
    ("Mexico_track", "ccw"),
    ("Belille", "cw"),
    ("2022_july_open", "ccw"),
    ("2022_july_pro", "both"),
    ("New_York_Track", "ccw"),
    ("Monaco", "cw"),
    ("Monaco_building", "cw"),
    ("red_star_open", "ccw"),
    ("red_star_pro", "both"),
    ("2024_reinvent_champ", "both"),
    ("FS_June2020", "cw"),
    ("arctic_open", "both"),
    ("arctic_pro", "both"),
    ("2022_october_open", "both"),
    ("2022_october_pro", "both"),
    ("2022_august_pro", "both"),
    ("2022_august_open", "both"),
    ("hamption_open", "ccw"),
    ("hamption_pro", "ccw"),
    ("Tokyo_Training_track", "ccw"),
    ("thunder_hill_pro", "both"),
    ("thunder_hill_open", "ccw"),
    ("Virtual_May19_Train_track", "ccw"),
    ("Oval_track", "ccw"),
    ("morgan_open", "ccw"),
    ("morgan_pro", "ccw"),
    ("penbay_open", "both"),
    ("penbay_pro", "both"),
    ("reinvent_base", "ccw"),
    ("2022_summit_speedway", "both"),
    ("July_2020", "cw"),
    ("2022_september_open", "both"),
    ("2022_september_pro", "both"),
    ("2022_march_open", "both"),
    ("2022_march_pro", "both"),
    ("2022_may_open", "both"),
    ("2022_may_pro", "both"),
    ("China_track", "ccw"),
    ("reInvent2019_track", "both"),
    ("LGSWide", "ccw"),
    ("Aragon", "cw"),
    ("Canada_Training", "ccw"),
    ("caecer_loop", "ccw"),
    ("caecer_gp", "ccw"),
    ("Albert", "cw"),
];

/// Whether DRoA has `track` and lets it be driven clockwise or counter-clockwise.
pub fn droa_direction_ok(track: &str, clockwise: bool) -> Result<(), String> {
    let Some((_, dirs)) = DROA_TRACKS.iter().find(|(id, _)| *id == track) else {
        return Err(format!("DRoA has no track {track} (docs/models.md lists DRoA's tracks)"));
    };
    let ok = match *dirs {
        "both" => true,
        "cw" => clockwise,
        _ => !clockwise,
    };
    if ok {
        Ok(())
    } else {
        Err(format!(
            "DRoA's {track} is not available {}: it runs {} only",
            if clockwise { "clockwise" } else { "counter-clockwise" },
            if clockwise { "counter-clockwise" } else { "clockwise" }
        ))
    }
}

// ---------------------------------------------------------------------------------------
// Reading

/// Which checkpoint of a model folder to take.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Choice {
    /// `deepracer_checkpoints.json`'s best.
    Best,
    /// Its last.
    Last,
    /// A checkpoint by name (`12_Step-3456.ckpt`) or number (`12`).
    Named(String),
}

impl std::str::FromStr for Choice {
    type Err = String;
    fn from_str(s: &str) -> Result<Choice, String> {
        match s {
            "best" => Ok(Choice::Best),
            "last" => Ok(Choice::Last),
            "" => Err("expected best, last or a checkpoint's name (12_Step-3456.ckpt) or number".into()),
            s => Ok(Choice::Named(s.to_string())),
        }
    }
}

/// Whether `path` is a DeepRacer model folder or DRoA's archive of one (rather than a car's
/// archive or a bare graph).
pub fn is_virtual_model(path: &Path) -> bool {
    if path.is_dir() {
        return find_root(path).is_some();
    }
    let Ok(f) = std::fs::File::open(path) else { return false };
    let mut gz = flate2::read::GzDecoder::new(f);
    let mut a = tar::Archive::new(&mut gz);
    let Ok(entries) = a.entries() else { return false };
    for e in entries.take(10_000) {
        let Ok(e) = e else { return false };
        let Ok(p) = e.path() else { return false };
        let name = p.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        if name == ".coach_checkpoint" || name == "deepracer_checkpoints.json" || name.ends_with(".ckpt.index") {
            return true;
        }
    }
    false
}

/// The model folder's root: `dir` itself, or its one sub-folder, holding `model/` with rl_coach's
/// `.coach_checkpoint`, `deepracer_checkpoints.json` or TensorFlow's `checkpoint`.
fn find_root(dir: &Path) -> Option<PathBuf> {
    let holds = |d: &Path| {
        [".coach_checkpoint", "deepracer_checkpoints.json", "checkpoint"]
            .iter()
            .any(|f| d.join("model").join(f).is_file())
    };
    if holds(dir) {
        return Some(dir.to_path_buf());
    }
    let subs: Vec<PathBuf> = std::fs::read_dir(dir)
        .ok()?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_dir() && holds(p))
        .collect();
    (subs.len() == 1).then(|| subs[0].clone())
}

/// Unpack DRoA's archive into `into`, refusing links, paths that leave it, and more than
/// [`MAX_FOLDER_BYTES`].
fn unpack(archive: &Path, into: &Path) -> Result<()> {
    let f = std::fs::File::open(archive).with_context(|| format!("reading {}", archive.display()))?;
    let gz = flate2::read::GzDecoder::new(f).take(MAX_FOLDER_BYTES + 1);
    let mut a = tar::Archive::new(gz);
    let bad = |m: String| anyhow!("{}: {m}", archive.display());
    let mut total = 0u64;
    for e in a.entries().map_err(|e| bad(format!("not a tar.gz archive: {e}")))? {
        let mut e = e.map_err(|e| bad(format!("not a tar.gz archive (or a damaged one): {e}")))?;
        let name = e.path().map_err(|e| bad(format!("an entry's name: {e}")))?.into_owned();
        let kind = e.header().entry_type();
        if kind.is_dir() {
            continue;
        }
        if !(kind.is_file() || kind == tar::EntryType::Continuous) {
            bail!(bad(format!("entry {} is a {kind:?}, not a file (links are refused)", name.display())));
        }
        if name.components().any(|c| !matches!(c, Component::Normal(_) | Component::CurDir)) {
            bail!(bad(format!("entry {} leaves the archive", name.display())));
        }
        total += e.size();
        if total > MAX_FOLDER_BYTES {
            bail!(bad(format!("over {MAX_FOLDER_BYTES} bytes unpacked (DRoA's import takes up to 1 GiB)")));
        }
        let to = into.join(&name);
        let entry = |err: std::io::Error| bad(format!("entry {}: {err}", name.display()));
        if let Some(p) = to.parent() {
            std::fs::create_dir_all(p).map_err(entry)?;
        }
        let mut out = std::fs::File::create(&to).map_err(entry)?;
        std::io::copy(&mut e, &mut out).map_err(|err| bad(format!("entry {}: {err}", name.display())))?;
    }
    Ok(())
}

/// One of DeepRacer's model folders, read.
#[derive(Debug)]
pub struct Imported {
    /// The model folder to write.
    pub folder: folder::ModelFolder,
    /// SAC's critics and its temperature.
    pub critics: Option<(SacCritics, f32)>,
    /// The DeepRacer files kept in the model folder (`deepracer/NAME`).
    pub kept: BTreeMap<String, Vec<u8>>,
    /// The checkpoint read.
    pub checkpoint: String,
    /// The checkpoint's variables that no network of the model has.
    pub unused: Vec<String>,
    /// What was not found beside the model (files DRoA or deepracer-for-cloud write that this
    /// one lacks).
    pub missing: Vec<String>,
    /// What the reading had to decide (a checkpoint taken from `.coach_checkpoint`).
    pub notes: Vec<String>,
}

fn read_small(path: &Path) -> Result<Option<Vec<u8>>> {
    match std::fs::metadata(path) {
        Ok(m) if m.len() > 64 << 20 => {
            bail!("{}: {} bytes, over the 64 MiB read for such a file", path.display(), m.len())
        }
        Ok(_) => Ok(Some(std::fs::read(path).with_context(|| format!("reading {}", path.display()))?)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(e).with_context(|| format!("reading {}", path.display())),
    }
}

fn text(path: &Path, bytes: Vec<u8>) -> Result<String> {
    String::from_utf8(bytes).map_err(|_| anyhow!("{}: not UTF-8 text", path.display()))
}

/// The checkpoint named by `choice` in `model/`: its name (`N_Step-M.ckpt`), and a note when
/// `best` or `last` had to be taken from `.coach_checkpoint` (no `deepracer_checkpoints.json`
/// naming it).
fn choose_checkpoint(model: &Path, choice: &Choice) -> Result<(String, Option<String>)> {
    let json_path = model.join("deepracer_checkpoints.json");
    let from_json = |key: &str| -> Result<Option<String>> {
        let Some(bytes) = read_small(&json_path)? else { return Ok(None) };
        let v: serde_json::Value =
            serde_json::from_slice(&bytes).with_context(|| format!("{}: not valid JSON", json_path.display()))?;
        Ok(v.get(key).and_then(|c| c.get("name")).and_then(|n| n.as_str()).map(str::to_string))
    };
    let coach = || -> Result<Option<String>> {
        let p = model.join(".coach_checkpoint");
        if let Some(b) = read_small(&p)? {
            return Ok(Some(text(&p, b)?.trim().to_string()));
        }
        // TensorFlow's own state file, as models before metadata version 2 have.
        let p = model.join("checkpoint");
        let Some(b) = read_small(&p)? else { return Ok(None) };
        let t = text(&p, b)?;
        let line = t.lines().find(|l| l.starts_with("model_checkpoint_path:"));
        Ok(line.and_then(|l| l.split('"').nth(1)).map(|s| s.rsplit('/').next().unwrap_or(s).to_string()))
    };
    let present = || -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(model)
            .map(|d| {
                d.filter_map(|e| e.ok())
                    .filter_map(|e| e.file_name().to_str().and_then(|n| n.strip_suffix(".index")).map(str::to_string))
                    .collect()
            })
            .unwrap_or_default();
        v.sort_by_key(|n| (n.split('_').next().and_then(|x| x.parse::<u64>().ok()), n.clone()));
        v
    };
    let mut note = None;
    let name = match choice {
        Choice::Best | Choice::Last => {
            let key = if *choice == Choice::Best { "best_checkpoint" } else { "last_checkpoint" };
            match from_json(key)? {
                Some(n) => n,
                None => {
                    note = Some(format!(
                        "no deepracer_checkpoints.json naming its {key}: the checkpoint .coach_checkpoint names was taken"
                    ));
                    coach()?.ok_or_else(|| {
                    anyhow!(
                        "{}: no deepracer_checkpoints.json naming its {key}, nor a .coach_checkpoint (checkpoints there: {})",
                        model.display(),
                        present().join(", ")
                    )
                    })?
                }
            }
        }
        Choice::Named(n) if n.chars().all(|c| c.is_ascii_digit()) => {
            present().into_iter().find(|p| p.split('_').next() == Some(n.as_str())).ok_or_else(|| {
                anyhow!("{}: no checkpoint number {n} (there: {})", model.display(), present().join(", "))
            })?
        }
        Choice::Named(n) => {
            if n.ends_with(".ckpt") {
                n.clone()
            } else {
                format!("{n}.ckpt")
            }
        }
    };
    if name.contains('/') || name.contains('\\') || name.starts_with('.') {
        bail!("{}: checkpoint name {name:?} is not a file name", model.display());
    }
    if !tfckpt::index_path(&model.join(&name)).is_file() {
        bail!(
            "{}: checkpoint {name} is named but its files are not there ({name}.index, {name}.data-00000-of-00001); checkpoints there: {}",
            model.display(),
            if present().is_empty() { "none".to_string() } else { present().join(", ") }
        );
    }
    Ok((name, note))
}

/// A Paddock `Hyperparameters` from DeepRacer's file (unknown keys ignored, as DeepRacer
/// ignores them).
fn hyperparameters(text: &str, origin: &str) -> Result<Hyperparameters> {
    Ok(Hyperparameters::parse(text, origin)?.hyperparameters)
}

/// Read DeepRacer's model folder (or DRoA's archive of one) at `source`, choosing its
/// checkpoint by `choice`.
pub fn read(source: &Path, choice: &Choice) -> Result<Imported> {
    if source.is_dir() {
        let root = find_root(source).ok_or_else(|| {
            anyhow!(
                "{}: not a DeepRacer model folder: no model/.coach_checkpoint, model/deepracer_checkpoints.json or model/checkpoint in it or in its one sub-folder",
                source.display()
            )
        })?;
        return read_root(&root, source, choice);
    }
    let scratch = tempfile::tempdir().context("a scratch folder")?;
    unpack(source, scratch.path())?;
    let root = find_root(scratch.path()).ok_or_else(|| {
        anyhow!(
            "{}: not a DeepRacer model archive: no model/.coach_checkpoint or model/deepracer_checkpoints.json in it",
            source.display()
        )
    })?;
    // Errors name the archive and the entry, not the scratch folder it was unpacked into.
    let unpacked = format!("{}/", scratch.path().display());
    read_root(&root, source, choice)
        .map_err(|e| anyhow!("{}", format!("{e:#}").replace(&unpacked, &format!("{}: ", source.display()))))
}

/// [`read`] of the model folder at `root` (`source` as the user named it).
fn read_root(root: &Path, source: &Path, choice: &Choice) -> Result<Imported> {
    let shown = |rel: &str| format!("{}: {rel}", source.display());
    let model = root.join("model");
    let mut missing = Vec::new();
    // The metadata: DRoA's at the root, deepracer-for-cloud's in model/.
    let (meta_rel, meta_bytes) = match read_small(&root.join("model_metadata.json"))? {
        Some(b) => ("model_metadata.json", b),
        None => (
            "model/model_metadata.json",
            read_small(&model.join("model_metadata.json"))?
                .ok_or_else(|| anyhow!("{}: no model_metadata.json at its root or in model/", source.display()))?,
        ),
    };
    let meta_text = text(&root.join(meta_rel), meta_bytes)?;
    let metadata = ModelMetadata::parse(&meta_text, &shown(meta_rel))?;
    let (name, note) = choose_checkpoint(&model, choice)?;
    if let ActionSpace::Continuous { steering_angle: s, speed: v } = &metadata.action_space {
        ensure!(
            s.0 < s.1 && v.0 < v.1,
            "{}: the action space needs low < high for the steering angle and the speed",
            shown(meta_rel)
        );
    }
    let ckpt = tfckpt::read(&model.join(&name))?;
    let restored =
        coach::from_checkpoint(&ckpt, &metadata).map_err(|e| anyhow!("{}: {e}", shown(&format!("model/{name}"))))?;
    let mut kept = BTreeMap::new();
    kept.insert(CHECKPOINT_KEPT.to_string(), name.clone().into_bytes());
    for (rel, keep) in [
        ("reward_function.py", "reward_function.py"),
        ("training_params.yaml", "training_params.yaml"),
        ("ip/hyperparameters.json", "hyperparameters.json"),
        ("model/deepracer_checkpoints.json", "deepracer_checkpoints.json"),
    ] {
        let alt = match rel {
            "ip/hyperparameters.json" => Some("hyperparameters.json"),
            "training_params.yaml" => Some("training_params_0.yaml"),
            _ => None,
        };
        let found = match read_small(&root.join(rel))? {
            Some(b) => Some(b),
            None => match alt {
                Some(a) => read_small(&root.join(a))?,
                None => None,
            },
        };
        match found {
            Some(b) => {
                kept.insert(keep.to_string(), b);
            }
            None => missing.push(rel.to_string()),
        }
    }
    // The training metrics: DRoA's `metrics/training/*training-*.json`, or
    // deepracer-for-cloud's `metrics/TrainingMetrics.json`.
    let training_dir = std::fs::read_dir(root.join("metrics"))
        .ok()
        .and_then(|d| d.filter_map(|e| e.ok()).find(|e| e.file_name().eq_ignore_ascii_case("training")))
        .map(|e| e.path());
    let droa_metrics = training_dir.and_then(|t| std::fs::read_dir(t).ok()).and_then(|d| {
        let mut v: Vec<PathBuf> = d
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| {
                p.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.contains("training-") && n.ends_with(".json"))
            })
            .collect();
        v.sort();
        v.into_iter().next()
    });
    match droa_metrics
        .or_else(|| Some(root.join("metrics/TrainingMetrics.json")))
        .map(|p| read_small(&p))
        .transpose()?
    {
        Some(Some(b)) => {
            kept.insert("training_metrics.json".into(), b);
        }
        _ => missing.push("metrics/training/*-training-*.json or metrics/TrainingMetrics.json".into()),
    }
    // What the training parameters say of the track, direction and race.
    let params: BTreeMap<String, serde_yaml::Value> = match kept.get("training_params.yaml") {
        Some(b) => serde_yaml::from_slice(b)
            .map_err(|e| anyhow!("{}: not a YAML mapping: {e}", shown("training_params.yaml")))?,
        None => BTreeMap::new(),
    };
    let yaml_str = |k: &str| {
        params.get(k).and_then(|v| v.as_str().map(str::to_string).or_else(|| v.as_bool().map(|b| b.to_string())))
    };
    let hyper = match kept.get("hyperparameters.json") {
        Some(b) => Some(hyperparameters(
            &text(Path::new("ip/hyperparameters.json"), b.clone())?,
            &shown("ip/hyperparameters.json"),
        )?),
        None => None,
    };
    let number = name.split('_').next().and_then(|n| n.parse::<u64>().ok());
    let steps = name.split("_Step-").nth(1).and_then(|s| s.trim_end_matches(".ckpt").parse::<u64>().ok());
    let value = match metadata.training_algorithm {
        TrainingAlgorithm::ClippedPpo => "from the checkpoint (rl_coach's network_0)",
        TrainingAlgorithm::Sac => "from the checkpoint (rl_coach's v network; Q networks in sac.safetensors)",
    };
    let mut training = serde_json::json!({
        "imported": {
            "from": source.display().to_string(),
            "format": "DeepRacer model folder (rl_coach's TensorFlow checkpoint)",
            "checkpoint": name,
            "checkpoint_number": number,
            "env_steps": steps,
            "value_tower": value,
            "track": yaml_str("WORLD_NAME"),
            "clockwise": yaml_str("TRACK_DIRECTION_CLOCKWISE"),
            "race_type": yaml_str("RACE_TYPE"),
        }
    });
    if let Some(h) = &hyper {
        training["hyperparameters"] = serde_json::to_value(h)?;
    }
    let manifest = Manifest {
        format: "paddock-model-1".into(),
        policy_version: 0,
        parent: None,
        weights_sha256: String::new(),
        obs_size: restored.model.obs_size(),
        observation: serde_json::json!({"kind": "camera"}),
        training,
    };
    let critics = restored.critics.map(|c| {
        let alpha = hyper.as_ref().map_or(0.2, |h| h.sac_alpha) as f32;
        (c, alpha.max(1e-8).ln())
    });
    Ok(Imported {
        folder: folder::ModelFolder { metadata, model: restored.model, manifest },
        critics,
        kept,
        checkpoint: name,
        unused: restored.unused,
        missing,
        notes: note.into_iter().collect(),
    })
}

/// SAC's critics file as the learner reads it (`learner::sac::SacTrainer::load_state`): the
/// heads, their embedder, V's target (V itself: rl_coach saves no target), the temperature.
pub fn critics_bytes(c: &SacCritics, v: &policy::nn::Net, log_alpha: f32) -> Vec<u8> {
    use safetensors::{Dtype, tensor::TensorView};
    let bytes = |p: &[f32]| -> Vec<u8> { p.iter().flat_map(|x| x.to_le_bytes()).collect() };
    let mut named = vec![
        ("q1", bytes(&c.q1.params)),
        ("q2", bytes(&c.q2.params)),
        ("v_target", bytes(&v.params)),
        ("log_alpha", bytes(&[log_alpha])),
    ];
    if let Some(e) = &c.embed {
        named.push(("q_embed", bytes(&e.params)));
    }
    let views: Vec<(String, TensorView<'_>)> = named
        .iter()
        .map(|(n, b)| (n.to_string(), TensorView::new(Dtype::F32, vec![b.len() / 4], b).expect("sizes agree")))
        .collect();
    let info = std::collections::HashMap::from([
        ("format".to_string(), "paddock-sac-critics-1".to_string()),
        ("policy_version".to_string(), "0".to_string()),
    ]);
    safetensors::serialize(views, Some(info)).expect("serialisable")
}

/// SAC's critics and temperature from a model folder's `sac.safetensors`, for `meta`'s
/// networks; `None` when there is no such file.
pub fn read_critics(dir: &Path, meta: &ModelMetadata, obs_size: usize) -> Result<Option<(SacCritics, f32)>> {
    use rand::SeedableRng;
    let path = dir.join(CRITICS_FILE);
    let Some(bytes) = read_small_any(&path)? else { return Ok(None) };
    let st = safetensors::SafeTensors::deserialize(&bytes)
        .map_err(|e| anyhow!("{}: not a safetensors file: {e}", path.display()))?;
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0);
    let embed = policy::model::sac_q_embedder(meta, obs_size, &mut rng);
    let width = embed.as_ref().map_or(obs_size, |e| e.out_size());
    let mut c = SacCritics {
        embed,
        q1: policy::model::sac_q_head(width, &mut rng),
        q2: policy::model::sac_q_head(width, &mut rng),
    };
    let mut la = [0.0f32];
    let mut targets: Vec<(&str, &mut [f32])> =
        vec![("q1", &mut c.q1.params), ("q2", &mut c.q2.params), ("log_alpha", &mut la)];
    if let Some(e) = c.embed.as_mut() {
        targets.push(("q_embed", &mut e.params));
    }
    for (name, dst) in targets {
        let t = st.tensor(name).map_err(|_| anyhow!("{}: has no tensor '{name}'", path.display()))?;
        ensure!(
            t.dtype() == safetensors::Dtype::F32 && t.data().len() == dst.len() * 4,
            "{}: tensor '{name}' holds {} bytes, the model's network takes {} f32",
            path.display(),
            t.data().len(),
            dst.len()
        );
        for (d, b) in dst.iter_mut().zip(t.data().chunks_exact(4)) {
            *d = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
        }
    }
    Ok(Some((c, la[0])))
}

fn read_small_any(path: &Path) -> Result<Option<Vec<u8>>> {
    match std::fs::read(path) {
        Ok(b) => Ok(Some(b)),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        Err(e) => Err(e).with_context(|| format!("reading {}", path.display())),
    }
}

/// Write what [`read`] read as a Paddock model folder at `out` (whole or not at all).
pub fn save(imported: &Imported, out: &Path) -> Result<()> {
    let parent = out.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let name = out.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "model".into());
    let staging = parent.join(format!(".{name}.importing-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&staging);
    let written = (|| -> Result<()> {
        let f = &imported.folder;
        folder::save(&staging, &f.metadata, &f.model, &f.manifest)?;
        let kept = staging.join(KEPT);
        std::fs::create_dir_all(&kept)?;
        for (n, b) in &imported.kept {
            std::fs::write(kept.join(n), b).with_context(|| format!("writing {}", kept.join(n).display()))?;
        }
        if let Some((c, la)) = &imported.critics {
            std::fs::write(staging.join(CRITICS_FILE), critics_bytes(c, &f.model.v, *la))?;
        }
        Ok(())
    })();
    if let Err(e) = written {
        let _ = std::fs::remove_dir_all(&staging);
        return Err(e);
    }
    std::fs::rename(&staging, out).with_context(|| format!("writing {}", out.display()))?;
    Ok(())
}

// ---------------------------------------------------------------------------------------
// Writing

/// What `export --virtual` needs besides the model folder.
#[derive(Clone, Debug, Default)]
pub struct ExportOptions {
    /// The reward function (when the model folder and its run keep none).
    pub reward_function: Option<PathBuf>,
    /// DRoA's track id (default: the one it was imported with or trained on).
    pub track: Option<String>,
    /// Driven clockwise (default: as imported; else the direction of DeepRacer's waypoints,
    /// reversed when `reversed`).
    pub clockwise: Option<bool>,
    /// Trained on the reversed track.
    pub reversed: bool,
    /// For deepracer-for-cloud only: DRoA's own rules (its tracks, their directions, its
    /// races and sensors) are not applied.
    pub drfc: bool,
}

/// DeepRacer's hyperparameters file (its keys only) for `h`.
fn deepracer_hyperparameters(h: &Hyperparameters) -> String {
    let v = serde_json::json!({
        "batch_size": h.batch_size,
        "beta_entropy": h.beta_entropy,
        "discount_factor": h.discount_factor,
        "e_greedy_value": 0.05,
        "epsilon_steps": 10000,
        "exploration_type": "categorical",
        "loss_type": match h.loss_type { LossType::Huber => "huber", LossType::MeanSquaredError => "mean squared error" },
        "lr": h.lr,
        "num_episodes_between_training": h.num_episodes_between_training,
        "num_epochs": h.num_epochs,
        "stack_size": 1,
        "term_cond_avg_score": h.term_cond_avg_score,
        "term_cond_max_episodes": h.term_cond_max_episodes,
        "sac_alpha": h.sac_alpha,
    });
    serde_json::to_string_pretty(&v).expect("JSON") + "\n"
}

/// The run folder a model folder sits in (`RUN/model`, `RUN/checkpoints/ckpt_N`), if any.
fn run_of(model_dir: &Path) -> Option<PathBuf> {
    let abs = std::fs::canonicalize(model_dir).ok()?;
    let up = abs.parent()?;
    let run = if up.file_name().is_some_and(|n| n == "checkpoints") { up.parent()? } else { up };
    run.join("model_metadata.json").is_file().then(|| run.to_path_buf())
}

/// SAC's critics for the model at `model_dir`: its own `sac.safetensors`, or that of its run's
/// checkpoint of the same weights.
fn critics_for(model_dir: &Path, f: &folder::ModelFolder) -> Result<Option<(SacCritics, f32)>> {
    if let Some(c) = read_critics(model_dir, &f.metadata, f.model.obs_size())? {
        return Ok(Some(c));
    }
    let Some(run) = run_of(model_dir) else { return Ok(None) };
    let Ok(dir) = std::fs::read_dir(run.join("checkpoints")) else { return Ok(None) };
    for e in dir.filter_map(|e| e.ok()) {
        let p = e.path();
        let same = folder::load(&p).is_ok_and(|c| c.manifest.weights_sha256 == f.manifest.weights_sha256);
        if same && let Some(c) = read_critics(&p, &f.metadata, f.model.obs_size())? {
            return Ok(Some(c));
        }
    }
    Ok(None)
}

/// The checkpoint `N_Step-M.ckpt`'s number and steps.
fn checkpoint_numbers(name: &str) -> Option<(u64, u64)> {
    let (n, rest) = name.split_once("_Step-")?;
    Some((n.parse().ok()?, rest.trim_end_matches(".ckpt").parse().ok()?))
}

/// A YAML value as a boolean: `true`/`false`, or the strings Python's writers leave.
fn yaml_bool(v: &serde_yaml::Value) -> Option<bool> {
    v.as_bool().or_else(|| match v.as_str()?.to_ascii_lowercase().as_str() {
        "true" => Some(true),
        "false" => Some(false),
        _ => None,
    })
}

/// The files of the folder DRoA's import page takes for the model at `model_dir`: relative
/// path → bytes.
pub fn export_files(model_dir: &Path, opts: &ExportOptions) -> Result<BTreeMap<String, Vec<u8>>> {
    let f = folder::load(model_dir)?;
    let meta = &f.metadata;
    let shown = model_dir.display();
    let target = if opts.drfc { "deepracer-for-cloud" } else { "DRoA" };
    // What DeepRacer has no form for.
    policy::tfgraph::Names::of(meta).map_err(|e| anyhow!("{shown}: {target} cannot take this model: {e}"))?;
    if !opts.drfc && meta.sensor.contains(&policy::Sensor::LeftCamera) {
        bail!(
            "{shown}: DRoA's model validator takes FRONT_FACING_CAMERA, observation or STEREO_CAMERAS (with or without a LiDAR), not LEFT_CAMERA; --deepracer-for-cloud writes it for deepracer-for-cloud"
        );
    }
    if let (TrainingAlgorithm::Sac, ActionSpace::Discrete(_)) = (meta.training_algorithm, &meta.action_space) {
        bail!("{shown}: DeepRacer's SAC takes a continuous action space only");
    }
    if let ActionSpace::Continuous { steering_angle: s, speed: v } = &meta.action_space {
        ensure!(s.0 < s.1 && v.0 < v.1, "{shown}: DeepRacer needs low < high for the steering angle and the speed");
    }
    // DeepRacer's files: the model folder's own (imported whole), else its run's (a clone of
    // an imported model keeps them in RUN/deepracer/ as it trains on).
    let run = run_of(model_dir);
    let here = |n: &str| read_small(&model_dir.join(KEPT).join(n));
    let kept = |n: &str| -> Result<Option<Vec<u8>>> {
        match here(n)? {
            Some(b) => Ok(Some(b)),
            None => run.as_ref().map(|r| read_small(&r.join(KEPT).join(n))).transpose().map(Option::flatten),
        }
    };
    // The checkpoint's name: as imported; or, trained here, the run's iteration and steps,
    // counted on from the checkpoint the run's model was imported from.
    let name = match here(CHECKPOINT_KEPT)? {
        Some(b) => String::from_utf8_lossy(&b).trim().to_string(),
        None => {
            let t = &f.manifest.training;
            let it = t
                .get("iteration")
                .or_else(|| t.get("iterations"))
                .and_then(|v| v.as_u64())
                .unwrap_or(f.manifest.policy_version);
            let steps = t.get("env_steps").and_then(|v| v.as_u64()).unwrap_or(0);
            let (n0, m0) = kept(CHECKPOINT_KEPT)?
                .and_then(|b| checkpoint_numbers(String::from_utf8_lossy(&b).trim()))
                .unwrap_or((0, 0));
            format!("{}_Step-{}.ckpt", n0 + it, m0 + steps)
        }
    };
    let number = name.split('_').next().unwrap_or("0").to_string();
    // The reward function.
    let reward = match &opts.reward_function {
        Some(p) => std::fs::read(p).with_context(|| format!("reading {}", p.display()))?,
        None => match kept("reward_function.py")? {
            Some(b) => b,
            None => match run.as_ref().map(|r| read_small(&r.join("reward_function.py"))).transpose()?.flatten() {
                Some(b) => b,
                None => bail!(
                    "{shown}: {target}'s import needs reward_function.py and neither the model folder nor its run keeps one: pass --reward-function FILE"
                ),
            },
        },
    };
    // Hyperparameters: as imported, else those it was trained with.
    let hyper_json = match here("hyperparameters.json")? {
        Some(b) => b,
        None => {
            let h = match f.manifest.training.get("hyperparameters") {
                Some(v) => {
                    hyperparameters(&v.to_string(), &format!("{shown}/manifest.json: training.hyperparameters"))?
                }
                None => match run
                    .as_ref()
                    .map(|r| (r.join("hyperparameters.json"), read_small(&r.join("hyperparameters.json"))))
                {
                    Some((p, b)) => match b? {
                        Some(b) => hyperparameters(&String::from_utf8_lossy(&b), &p.display().to_string())?,
                        None => Hyperparameters::default(),
                    },
                    None => Hyperparameters::default(),
                },
            };
            deepracer_hyperparameters(&h).into_bytes()
        }
    };
    let h = hyperparameters(&String::from_utf8_lossy(&hyper_json), "ip/hyperparameters.json")?;
    if !opts.drfc && meta.training_algorithm == TrainingAlgorithm::Sac && h.num_episodes_between_training != 1 {
        bail!(
            "{shown}: DRoA takes SAC models with num_episodes_between_training 1; this one's is {}",
            h.num_episodes_between_training
        );
    }
    // The track, its direction and the race.
    let from_yaml: BTreeMap<String, serde_yaml::Value> = match kept("training_params.yaml")? {
        Some(b) => serde_yaml::from_slice(&b)
            .map_err(|e| anyhow!("{shown}: training_params.yaml kept from its import: {e}"))?,
        None => BTreeMap::new(),
    };
    let track = match (&opts.track, from_yaml.get("WORLD_NAME").and_then(|v| v.as_str())) {
        (Some(t), _) => t.clone(),
        (None, Some(t)) => t.to_string(),
        (None, None) => f
            .manifest
            .training
            .get("worlds")
            .and_then(|w| w.get(0))
            .and_then(|w| w.as_str())
            .map(str::to_string)
            .ok_or_else(|| anyhow!("{shown}: the model does not say which track it was trained on: pass --track ID"))?,
    };
    let (bare, suffix_cw) = match track.strip_suffix("_cw") {
        Some(t) => (t.to_string(), Some(true)),
        None => match track.strip_suffix("_ccw") {
            Some(t) => (t.to_string(), Some(false)),
            None => (track.clone(), None),
        },
    };
    let default_cw = DROA_TRACKS.iter().find(|(id, _)| *id == bare).is_some_and(|(_, d)| *d == "cw");
    let clockwise = opts
        .clockwise
        .or(suffix_cw)
        .or_else(|| from_yaml.get("TRACK_DIRECTION_CLOCKWISE").and_then(yaml_bool))
        .unwrap_or(default_cw != opts.reversed);
    let race = from_yaml.get("RACE_TYPE").and_then(|v| v.as_str()).unwrap_or("TIME_TRIAL").to_string();
    if !opts.drfc {
        droa_direction_ok(&bare, clockwise).map_err(|e| {
            anyhow!("{shown}: {e}; pass --track ID (and --clockwise or --counter-clockwise) for one DRoA has, or --deepracer-for-cloud")
        })?;
        if race == "HEAD_TO_BOT" || race == "HEAD_TO_MODEL" {
            bail!(
                "{shown}: DRoA trains time trials and object avoidance; it has no {race} race to import this model into (--deepracer-for-cloud writes it for deepracer-for-cloud)"
            );
        }
    }
    // DRoA's track id without a direction and the direction as a boolean; for
    // deepracer-for-cloud the world as it names it.
    let mut y = from_yaml.clone();
    y.insert("WORLD_NAME".into(), serde_yaml::Value::String(if opts.drfc { track.clone() } else { bare.clone() }));
    y.insert("TRACK_DIRECTION_CLOCKWISE".into(), serde_yaml::Value::Bool(clockwise));
    y.insert("RACE_TYPE".into(), serde_yaml::Value::String(race.clone()));
    y.entry("JOB_TYPE".into()).or_insert(serde_yaml::Value::String("TRAINING".into()));
    y.entry("BODY_SHELL_TYPE".into()).or_insert(serde_yaml::Value::String("deepracer".into()));
    y.entry("CAR_COLOR".into()).or_insert(serde_yaml::Value::String("Black".into()));
    let training_params = serde_yaml::to_string(&y)?.into_bytes();
    // The checkpoint and the frozen policy.
    let critics = match meta.training_algorithm {
        TrainingAlgorithm::Sac => Some(critics_for(model_dir, &f)?.ok_or_else(|| {
            anyhow!(
                "{shown}: DeepRacer's checkpoint of a SAC model holds its Q networks, and no sac.safetensors is beside this model or in its run's checkpoint of the same weights: export one of RUN/checkpoints/"
            )
        })?),
        TrainingAlgorithm::ClippedPpo => None,
    };
    let ckpt =
        coach::to_checkpoint(meta, &f.model, critics.as_ref().map(|c| &c.0)).map_err(|e| anyhow!("{shown}: {e}"))?;
    let (index, data) = tfckpt::encode(&ckpt);
    let graph = policy::tfgraph::write(&f.model, meta).map_err(|e| anyhow!("{shown}: {e}"))?;
    // deepracer_checkpoints.json names the one checkpoint written as best and last (as
    // deepracer-for-cloud's upload does), with its figures when the kept file has them.
    let kept_record = here("deepracer_checkpoints.json")?
        .and_then(|b| serde_json::from_slice::<serde_json::Value>(&b).ok())
        .and_then(|v| {
            ["last_checkpoint", "best_checkpoint"]
                .iter()
                .find_map(|k| v.get(*k).filter(|r| r["name"] == name.as_str()).cloned())
        });
    let record = kept_record.unwrap_or_else(|| {
        let t = &f.manifest.training;
        serde_json::json!({
            "name": name,
            "avg_eval_metric": t.get("best_progress").or_else(|| t.get("avg_eval_metric")).cloned().unwrap_or(serde_json::json!(0.0)),
            "time_stamp": t.get("seconds").cloned().unwrap_or(serde_json::json!(0.0)),
        })
    });
    let checkpoints =
        serde_json::to_vec_pretty(&serde_json::json!({"best_checkpoint": record, "last_checkpoint": record}))?;
    // The training metrics: the run's own when it trained here, else as imported.
    let metrics = match here("training_metrics.json")? {
        Some(b) => Some(b),
        None => {
            match run.as_ref().map(|r| read_small(&r.join("metrics/TrainingMetrics.json"))).transpose()?.flatten() {
                Some(b) => Some(b),
                None => kept("training_metrics.json")?,
            }
        }
    };
    let meta_json = meta.to_json().into_bytes();
    let mut files = BTreeMap::new();
    files.insert("model_metadata.json".to_string(), meta_json.clone());
    files.insert("reward_function.py".to_string(), reward);
    files.insert("training_params.yaml".to_string(), training_params);
    files.insert("ip/hyperparameters.json".to_string(), hyper_json);
    files.insert("model/model_metadata.json".to_string(), meta_json);
    files.insert("model/.coach_checkpoint".to_string(), name.clone().into_bytes());
    files.insert("model/deepracer_checkpoints.json".to_string(), checkpoints);
    files.insert(format!("model/{name}.index"), index);
    files.insert(format!("model/{name}.data-00000-of-00001"), data);
    files.insert(format!("model/model_{number}.pb"), graph);
    if let Some(m) = metrics {
        files.insert(format!("metrics/training/training-{}.json", name.trim_end_matches(".ckpt")), m);
    }
    Ok(files)
}

/// Write `files` as DRoA's `virtualmodel-NAME.tar.gz` (entries relative to the model, no top
/// folder, the same bytes for the same files).
pub fn write_archive(files: &BTreeMap<String, Vec<u8>>, out: &Path) -> Result<u64> {
    let gz = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    let mut tar = tar::Builder::new(gz);
    for (name, bytes) in files {
        let mut h = tar::Header::new_gnu();
        h.set_size(bytes.len() as u64);
        h.set_mode(0o644);
        h.set_mtime(0);
        h.set_entry_type(tar::EntryType::Regular);
        tar.append_data(&mut h, name, bytes.as_slice())?;
    }
    let bytes = tar.into_inner()?.finish()?;
    let tmp = out.with_file_name(format!(".{}.tmp", out.file_name().map(|f| f.to_string_lossy()).unwrap_or_default()));
    std::fs::write(&tmp, &bytes).with_context(|| format!("writing {}", out.display()))?;
    std::fs::rename(&tmp, out).with_context(|| format!("writing {}", out.display()))?;
    Ok(bytes.len() as u64)
}

/// Write `files` as a folder at `out` (whole or not at all); an existing `out` is replaced
/// once the new one is written, when `replace`.
pub fn write_folder(files: &BTreeMap<String, Vec<u8>>, out: &Path, replace: bool) -> Result<()> {
    if out.exists() && !replace {
        bail!("{} exists (--force replaces it)", out.display());
    }
    let parent = out.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let name = out.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| "model".into());
    let staging = parent.join(format!(".{name}.exporting-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&staging);
    let written = (|| -> Result<()> {
        for (rel, bytes) in files {
            let p = staging.join(rel);
            std::fs::create_dir_all(p.parent().expect("a file in a folder"))?;
            std::fs::write(&p, bytes).with_context(|| format!("writing {}", p.display()))?;
        }
        Ok(())
    })();
    if let Err(e) = written {
        let _ = std::fs::remove_dir_all(&staging);
        return Err(e);
    }
    if out.exists() {
        std::fs::remove_dir_all(out).with_context(|| format!("replacing {}", out.display()))?;
    }
    std::fs::rename(&staging, out).with_context(|| format!("writing {}", out.display()))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue 53: DRoA's track and direction rules.
    #[test]
    fn droa_track_and_direction_rules() {
        for (track, cw, ok) in [
            ("reInvent2019_track", true, true),
            ("reInvent2019_track", false, true),
            ("reinvent_base", true, false),
            ("reinvent_base", false, true),
            ("Spain_track", false, false),
            ("Spain_track", true, true),
            ("reinvent_wood", false, false),
        ] {
            assert_eq!(droa_direction_ok(track, cw).is_ok(), ok, "{track} cw {cw}");
        }
        assert_eq!(DROA_TRACKS.len(), 62);
    }

    /// Issue 53: a checkpoint is chosen by best, last, name or number.
    #[test]
    fn a_checkpoint_is_chosen_by_best_last_name_or_number() {
        let d = tempfile::tempdir().unwrap();
        let m = d.path();
        for n in ["3_Step-300.ckpt", "7_Step-700.ckpt", "12_Step-1200.ckpt"] {
            std::fs::write(m.join(format!("{n}.index")), b"x").unwrap();
        }
        std::fs::write(m.join(".coach_checkpoint"), "12_Step-1200.ckpt").unwrap();
        // Without deepracer_checkpoints.json, .coach_checkpoint's, and a note saying so.
        let (name, note) = choose_checkpoint(m, &Choice::Last).unwrap();
        assert_eq!(name, "12_Step-1200.ckpt");
        assert!(note.is_some_and(|n| n.contains(".coach_checkpoint")));
        std::fs::write(
            m.join("deepracer_checkpoints.json"),
            r#"{"best_checkpoint": {"name": "7_Step-700.ckpt"}, "last_checkpoint": {"name": "12_Step-1200.ckpt"}}"#,
        )
        .unwrap();
        assert_eq!(choose_checkpoint(m, &Choice::Best).unwrap(), ("7_Step-700.ckpt".to_string(), None));
        assert_eq!(choose_checkpoint(m, &Choice::Named("3".into())).unwrap().0, "3_Step-300.ckpt");
        assert_eq!(choose_checkpoint(m, &Choice::Named("3_Step-300".into())).unwrap().0, "3_Step-300.ckpt");
        let e = choose_checkpoint(m, &Choice::Named("9".into())).unwrap_err().to_string();
        assert!(
            e.contains("no checkpoint number 9") && e.contains("3_Step-300.ckpt, 7_Step-700.ckpt, 12_Step-1200.ckpt"),
            "{e}"
        );
        let e = choose_checkpoint(m, &Choice::Named("../x".into())).unwrap_err().to_string();
        assert!(e.contains("not a file name"), "{e}");
    }
}
