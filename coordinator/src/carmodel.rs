//! `export --car` and `import`: Paddock models as DeepRacer's model archive, and DeepRacer's
//! models (an archive, or a bare `model.pb` with its `model_metadata.json`) as Paddock model
//! folders. The formats are `policy::carpkg` and `policy::tfgraph`; here are the commands.

use crate::cli::ImportArgs;
use anyhow::{Context, Result, bail};
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

/// `coordinator import`.
pub fn import(args: ImportArgs) -> Result<i32> {
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
