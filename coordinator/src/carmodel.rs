//! `export --car`, `export --virtual` and `import`: Paddock models as DeepRacer's model archive
//! or as DeepRacer's whole model (DRoA's `virtualmodel-NAME.tar.gz`, deepracer-for-cloud's
//! folder), and DeepRacer's models (an archive, a bare `model.pb` with its
//! `model_metadata.json`, or a whole model) as Paddock model folders. The formats are
//! `policy::carpkg`, `policy::tfgraph` and `coordinator::virtual_model`; here are the commands.

use crate::cli::{ImportArgs, VirtualArgs};
use anyhow::{Context, Result, bail};
use coordinator::virtual_model::{self, Choice, ExportOptions};
use policy::carpkg::{self, Package};
use policy::folder;
use policy::metadata::ModelMetadata;
use std::path::Path;
use std::time::Instant;

/// Write `model`'s archive at `out`; prints what a car will call it.
pub fn export_car(model: &Path, out: &Path) -> Result<()> {
    let t = Instant::now();
    let f = folder::load(model)?;
    let bytes = carpkg::write(out, &f.model, &f.metadata).with_context(|| format!("exporting {}", model.display()))?;
    let name = carpkg::car_model_name(out);
    println!(
        "{}: policy v{} as DeepRacer's model archive ({:.1} MB, {:.2} s): {} + {}; a car lists it as '{name}'",
        out.display(),
        f.manifest.policy_version,
        bytes as f64 / 1e6,
        t.elapsed().as_secs_f64(),
        carpkg::GRAPH_PATH,
        carpkg::METADATA_PATH,
    );
    let file = out.file_name().map(|f| f.to_string_lossy().into_owned()).unwrap_or_default();
    if !file.ends_with(".tar.gz") {
        eprintln!("note: a car's console takes only files named *.tar.gz");
    }
    Ok(())
}

/// What `import` read: the archive's contents, or a bare graph and the metadata beside it.
fn package_of(args: &ImportArgs) -> Result<Package> {
    let src = &args.source;
    if src.extension().is_some_and(|e| e == "pb") {
        let meta_path = match &args.model_metadata {
            Some(p) => p.clone(),
            None => src.with_file_name(carpkg::METADATA_PATH),
        };
        let metadata_text = std::fs::read_to_string(&meta_path).with_context(|| {
            format!("reading {} (a bare .pb needs its model_metadata.json: --model-metadata FILE)", meta_path.display())
        })?;
        let metadata = ModelMetadata::parse(&metadata_text, &meta_path.display().to_string())?;
        let graph = std::fs::read(src).with_context(|| format!("reading {}", src.display()))?;
        return Ok(Package { graph_path: src.display().to_string(), graph, metadata_text, metadata });
    }
    if args.model_metadata.is_some() {
        bail!("--model-metadata is for a bare .pb; an archive carries its own model_metadata.json");
    }
    Ok(carpkg::read(src)?)
}

/// `export --virtual FILE` and `--virtual-dir DIR`.
pub fn export_virtual(model: &Path, archive: Option<&Path>, dir: Option<&Path>, args: &VirtualArgs) -> Result<()> {
    let t = Instant::now();
    let opts = ExportOptions {
        reward_function: args.reward_function.clone(),
        track: args.track.clone(),
        clockwise: if args.clockwise {
            Some(true)
        } else if args.counter_clockwise {
            Some(false)
        } else {
            None
        },
        reversed: args.reversed,
        drfc: args.deepracer_for_cloud,
    };
    if let Some(out) = dir.filter(|d| d.exists() && !args.force) {
        bail!("{} exists (--force replaces it)", out.display());
    }
    let files = virtual_model::export_files(model, &opts).with_context(|| format!("exporting {}", model.display()))?;
    let checkpoint =
        files.keys().find_map(|k| k.strip_prefix("model/")?.strip_suffix(".index")).unwrap_or("").to_string();
    let total: usize = files.values().map(|b| b.len()).sum();
    if let Some(out) = archive {
        let bytes = virtual_model::write_archive(&files, out)?;
        println!(
            "{}: DeepRacer's whole model ({} files, {:.1} MB packed), checkpoint {checkpoint}; unpack it and pick the folder on DRoA's Import model page",
            out.display(),
            files.len(),
            bytes as f64 / 1e6
        );
    }
    if let Some(out) = dir {
        virtual_model::write_folder(&files, out, args.force)?;
        println!(
            "{}: DeepRacer's whole model ({} files, {:.1} MB), checkpoint {checkpoint}: DRoA's Import model page takes the folder; for deepracer-for-cloud copy it to s3://BUCKET/PREFIX/ and set DR_LOCAL_S3_PRETRAINED_PREFIX=PREFIX",
            out.display(),
            files.len(),
            total as f64 / 1e6
        );
    }
    println!("({:.2} s)", t.elapsed().as_secs_f64());
    Ok(())
}

/// `import` of DRoA's or deepracer-for-cloud's whole model.
fn import_virtual(args: &ImportArgs) -> Result<i32> {
    let t = Instant::now();
    let choice: Choice = args.checkpoint.parse().map_err(|e: String| anyhow::anyhow!("--checkpoint: {e}"))?;
    let imported = virtual_model::read(&args.source, &choice)?;
    if args.out.exists() {
        if !args.force {
            bail!("{} exists (--force replaces it)", args.out.display());
        }
        std::fs::remove_dir_all(&args.out).with_context(|| format!("removing {}", args.out.display()))?;
    }
    virtual_model::save(&imported, &args.out)?;
    let f = &imported.folder;
    let discrete = matches!(f.metadata.action_space, policy::metadata::ActionSpace::Discrete(_));
    let networks = match f.metadata.training_algorithm {
        policy::TrainingAlgorithm::ClippedPpo => "policy and value networks",
        policy::TrainingAlgorithm::Sac => "policy, twin Q and V networks",
    };
    println!(
        "{}: {} {} with {} {} from {}, checkpoint {}: {networks} read ({:.2} s); `clone` it to train on",
        args.out.display(),
        f.metadata.training_algorithm.name(),
        f.metadata.neural_network.name(),
        f.metadata.action_space.dim(),
        if discrete { "actions" } else { "continuous outputs" },
        args.source.display(),
        imported.checkpoint,
        t.elapsed().as_secs_f64()
    );
    if !imported.unused.is_empty() {
        println!(
            "{} variables of the checkpoint belong to no network of the model: {}",
            imported.unused.len(),
            imported.unused.join(", ")
        );
    }
    for n in &imported.notes {
        println!("note: {n}");
    }
    if !imported.missing.is_empty() {
        println!("not in the model folder: {}", imported.missing.join(", "));
    }
    Ok(0)
}

/// `coordinator import`.
pub fn import(args: ImportArgs) -> Result<i32> {
    if virtual_model::is_virtual_model(&args.source) {
        if args.model_metadata.is_some() {
            bail!("--model-metadata is for a bare .pb; a DeepRacer model folder carries its own model_metadata.json");
        }
        return import_virtual(&args);
    }
    let t = Instant::now();
    let pkg = package_of(&args)?;
    let origin = args.source.display().to_string();
    let f = pkg.to_folder(&origin, args.seed)?;
    if args.out.exists() {
        if !args.force {
            bail!("{} exists (--force replaces it)", args.out.display());
        }
        std::fs::remove_dir_all(&args.out).with_context(|| format!("removing {}", args.out.display()))?;
    }
    folder::save(&args.out, &f.metadata, &f.model, &f.manifest)?;
    let discrete = matches!(f.metadata.action_space, policy::metadata::ActionSpace::Discrete(_));
    println!(
        "{}: {} with {} {} from {} ({:.2} s); its value tower is new: `clone` it to train on",
        args.out.display(),
        f.metadata.neural_network.name(),
        f.metadata.action_space.dim(),
        if discrete { "actions" } else { "continuous outputs" },
        origin,
        t.elapsed().as_secs_f64()
    );
    Ok(0)
}
