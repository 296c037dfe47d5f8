//! How a run opens: the run folder (new, forced, resumed or cloned, as [`Start`] says), the
//! model it goes on from, checked against the run, the run's inputs written into the folder,
//! its signing key, and its algorithm (PPO or SAC, taking over a learner team's newer state
//! when the spec carries one).

use super::spec::{RunFailure, RunSpec, Start};
use crate::algorithm::{Algorithm, Shared};
use crate::checkpoints::{OpenMode, RunDir};
use crate::ppo::Ppo;
use crate::sac::SacTrainer;
use policy::ActorCritic;
use policy::folder::{self, Parent};
use policy::signature::Signer;
use rand::SeedableRng;
use std::path::{Path, PathBuf};

/// The run folder and the model opened: the folder, the model, its version, the folder it was
/// cloned from, and the iteration it goes on from.
pub(super) type Opened = (RunDir, ActorCritic, u64, Option<Parent>, u64);

/// How the run folder is opened for `start`, and the model folder a new run clones. `model`:
/// the folder holds a model (`model/`), `manifest`: a written one (`model/manifest.json`),
/// `exists`: the folder exists. A run resumed or new resumes a folder whose model is written;
/// a new run in a folder without a model (a leftover of an earlier attempt, empty or logs
/// only) replaces it.
fn open_mode(start: &Start, exists: bool, model: bool, manifest: bool) -> (OpenMode, Option<PathBuf>) {
    let (mode, clone_from) = match start {
        Start::New { clone_from } => (OpenMode::New, clone_from.clone()),
        Start::Force => (OpenMode::Force, None),
        Start::Resume => (OpenMode::Resume, None),
        Start::ResumeOrNew { clone_from } => {
            if manifest {
                (OpenMode::Resume, None)
            } else {
                (OpenMode::New, clone_from.clone())
            }
        }
    };
    // A leftover empty (or log-only) folder from an earlier attempt is not a run.
    let mode = if mode == OpenMode::New && exists && !model { OpenMode::Force } else { mode };
    (mode, clone_from)
}

/// Open the run folder and the model.
pub(super) fn open(spec: &RunSpec) -> Result<Opened, RunFailure> {
    if spec.hyper.precision == policy::nn::Precision::Bf16 && !policy::nn::Precision::bf16_available() {
        return Err(RunFailure::Inputs(
            "hyperparameters: precision \"bf16\" needs a CPU with AVX-512 BF16 (AMD Zen 4 or later, Intel Sapphire \
             Rapids or later), and this learner's has none; set \"f32\""
                .into(),
        ));
    }
    if spec.hyper.precision == policy::nn::Precision::Bf16 && spec.gpu.is_some() {
        return Err(RunFailure::Inputs(
            "hyperparameters: precision \"bf16\" is the CPU's (faer's products in bf16); the GPU's update \
             is f32: train with --device cpu, or set \"f32\""
                .into(),
        ));
    }
    let model = spec.out.join("model");
    let (mode, clone_from) =
        open_mode(&spec.start, spec.out.exists(), model.exists(), model.join("manifest.json").exists());
    let run = RunDir::open(&spec.out, mode)?;
    if mode == OpenMode::Resume {
        return resume(spec, run);
    }
    if let Some(from) = clone_from {
        return clone_model(spec, run, &from);
    }
    let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(spec.seed);
    Ok((run, ActorCritic::new(&spec.metadata, spec.obs_size, &mut rng), 0, None, 0))
}

/// Refused unless a model of `inputs` inputs (in the folder `at`) takes the run's observation.
fn takes_the_observation(at: &Path, inputs: usize, spec: &RunSpec) -> Result<(), RunFailure> {
    if inputs == spec.obs_size {
        return Ok(());
    }
    Err(RunFailure::Inputs(format!(
        "{}: the model takes {} inputs, this configuration's observation has {}",
        at.display(),
        inputs,
        spec.obs_size
    )))
}

/// Go on from the run folder's last checkpoint (its model when the checkpoint is gone); the
/// records after it are dropped, as those updates are made again.
fn resume(spec: &RunSpec, run: RunDir) -> Result<Opened, RunFailure> {
    let index = run.index()?;
    let dir = index
        .last_checkpoint
        .as_ref()
        .map(|l| run.checkpoint_dir(&l.name))
        .filter(|d| d.exists())
        .unwrap_or_else(|| run.model_dir());
    let f = folder::load(&dir)?;
    if let Err(why) = f.metadata.compatible_with(&spec.metadata) {
        return Err(RunFailure::Inputs(format!("{}: cannot continue this run: {why}", dir.display())));
    }
    takes_the_observation(&dir, f.manifest.obs_size, spec)?;
    let iteration = index.last_checkpoint.map(|l| l.iteration).unwrap_or(0);
    let dropped = run.rewind_records(iteration)?;
    if dropped > 0 {
        tracing::warn!(run = %spec.name, iteration, dropped, "records after the last checkpoint dropped: those updates are made again");
    }
    tracing::info!(run = %spec.name, from = %dir.display(), version = f.manifest.policy_version, "resuming");
    Ok((run, f.model, f.manifest.policy_version, f.manifest.parent, iteration))
}

/// Start a new run from the weights of the model folder `from` (transfer learning).
fn clone_model(spec: &RunSpec, run: RunDir, from: &Path) -> Result<Opened, RunFailure> {
    let f = folder::load(from)?;
    f.metadata
        .compatible_with(&spec.metadata)
        .map_err(|why| RunFailure::Inputs(format!("{}: {why}", from.display())))?;
    takes_the_observation(from, f.manifest.obs_size, spec)?;
    if f.manifest.training.get("imported").is_some() && spec.hyper.value_warmup_updates <= f.manifest.policy_version {
        tracing::warn!(
            run = %spec.name,
            from = %from.display(),
            "the model was imported from DeepRacer's graph with a new value tower, and value_warmup_updates \
             does not hold the policy for it: the policy trains from the first update (`coordinator clone` sets a warm-up)"
        );
    }
    let parent = Parent {
        path: from.display().to_string(),
        policy_version: f.manifest.policy_version,
        weights_sha256: f.manifest.weights_sha256.clone(),
    };
    Ok((run, f.model, f.manifest.policy_version, Some(parent), 0))
}

/// Write the run's inputs into its folder: the model's metadata, the hyperparameters (also
/// where deepracer-for-cloud keeps them) and the simulator's configuration.
pub(super) fn write_inputs(spec: &RunSpec, dir: &RunDir) -> Result<(), RunFailure> {
    dir.write_file("model_metadata.json", spec.metadata.to_json().as_bytes())?;
    dir.write_file("hyperparameters.json", spec.hyper.to_json().as_bytes())?;
    // deepracer-for-cloud's place for it (`ip/`), where deepracer-utils looks.
    dir.write_file("ip/hyperparameters.json", spec.hyper.to_json().as_bytes())?;
    dir.write_file("sim.toml", spec.sim_toml.as_bytes())?;
    Ok(())
}

/// The run's signing key: the one the spec names, or the run folder's `signing.key` (made on
/// first use, with `signing.pub` beside it).
pub(super) fn signer_for(spec: &RunSpec, run: &RunDir) -> Result<Signer, RunFailure> {
    let r = match &spec.signing_key {
        Some(path) => Signer::load(path),
        None => Signer::load_or_create(&run.root().join("signing.key")),
    };
    r.map_err(|e| RunFailure::Inputs(format!("signing key: {e}")))
}

/// The run's algorithm for its metadata, from the opened model: PPO (taking over a team's
/// newer state when the spec carries one) or SAC (with the critics of the checkpoint it
/// resumes from and the replay memory the run folder kept, when there are).
pub(super) fn algorithm(
    spec: &RunSpec,
    dir: &RunDir,
    model: ActorCritic,
    version: u64,
    first_iteration: u64,
) -> Result<Box<dyn Algorithm>, RunFailure> {
    if spec.metadata.training_algorithm == policy::TrainingAlgorithm::Sac {
        let mut sac = SacTrainer::new(model, &spec.metadata, spec.obs_size, &spec.hyper, version, spec.seed, spec.par)
            .map_err(RunFailure::Inputs)?;
        if first_iteration > 0 {
            resume_sac(spec, dir, &mut sac)?;
        } else {
            critics_beside(spec, dir, &mut sac)?;
        }
        if let Some(g) = &spec.gpu {
            sac = sac.with_gpu(g.clone());
        }
        adopt(spec, &mut sac);
        return Ok(Box::new(sac));
    }
    let mut ppo = Ppo::new(model, spec.hyper.clone(), version, spec.seed, spec.par);
    if let Some(g) = &spec.gpu {
        ppo = ppo.with_gpu(g.clone());
    }
    adopt(spec, &mut ppo);
    Ok(Box::new(ppo))
}

/// A resumed SAC run's critics (from the last checkpoint) and replay memory (from the run
/// folder), or a warning that it starts without them.
fn resume_sac(spec: &RunSpec, dir: &RunDir, sac: &mut SacTrainer) -> Result<(), RunFailure> {
    let last = dir.index()?.last_checkpoint.map(|l| dir.checkpoint_dir(&l.name));
    match last.map(|d| sac.load_state(&d)).transpose() {
        Ok(Some(true)) => tracing::info!(run = %spec.name, "SAC: the critics go on from the checkpoint"),
        Ok(_) => tracing::warn!(run = %spec.name, "SAC: the checkpoint holds no critics: they start afresh"),
        Err(e) => tracing::warn!(run = %spec.name, "SAC: the critics start afresh: {e}"),
    }
    match sac.load_memory(dir.root()) {
        Ok(true) => {
            tracing::info!(run = %spec.name, transitions = sac.replay().len(), "SAC: the replay memory goes on")
        }
        Ok(false) => tracing::warn!(run = %spec.name, "SAC: the run folder holds no replay memory: it starts empty"),
        Err(e) => tracing::warn!(run = %spec.name, "SAC: the replay memory starts empty: {e}"),
    }
    Ok(())
}

/// A new SAC run's critics from the model it starts from, when that folder keeps them beside
/// its weights (a DeepRacer model imported whole, or one `clone` copied): the folder it clones,
/// else the run's own `model/`.
fn critics_beside(spec: &RunSpec, dir: &RunDir, sac: &mut SacTrainer) -> Result<(), RunFailure> {
    let from = match &spec.start {
        Start::New { clone_from } | Start::ResumeOrNew { clone_from } => clone_from.clone(),
        _ => None,
    };
    let candidates = from.into_iter().chain([dir.model_dir()]);
    if let Some(d) = candidates.into_iter().find(|d| d.join(crate::sac::trainer::CRITICS_FILE).is_file()) {
        // Critics that do not fit are refused: training on with fresh ones would silently
        // drop what the model brought.
        sac.load_state(&d).map_err(|e| RunFailure::Inputs(format!("SAC's critics beside the model: {e}")))?;
        tracing::info!(run = %spec.name, from = %d.display(), "SAC: the critics go on from the model's");
    }
    Ok(())
}

/// Take over the team's state the spec carries, when it is newer than the run folder's.
fn adopt(spec: &RunSpec, algo: &mut dyn Shared) {
    let Some((state, memory)) = spec.adopt.as_ref().filter(|(s, _)| s.version > algo.version()) else { return };
    let v = state.version;
    match algo.restore(state.clone(), memory.as_deref()) {
        Ok(()) => {
            tracing::info!(run = %spec.name, version = v, "taking over from the team's state (newer than the run folder's)")
        }
        Err(e) => tracing::warn!(run = %spec.name, "the team's state does not fit this run: {e}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue 50: each way of starting opens the run folder as it says; a run resumed or new
    /// resumes only a folder whose model is written, and a new run replaces a leftover
    /// folder without a model.
    #[test]
    fn each_start_opens_the_folder_as_it_says() {
        let from = Some(PathBuf::from("/models/a"));
        let new = Start::New { clone_from: from.clone() };
        let either = Start::ResumeOrNew { clone_from: from.clone() };
        // (start, folder exists, holds a model, holds a written model, mode, clone from)
        for (start, exists, model, manifest, mode, cloned) in [
            (&new, false, false, false, OpenMode::New, &from),
            (&new, true, false, false, OpenMode::Force, &from),
            (&new, true, true, true, OpenMode::New, &from),
            (&Start::Force, true, true, true, OpenMode::Force, &None),
            (&Start::Resume, true, true, true, OpenMode::Resume, &None),
            (&Start::Resume, true, false, false, OpenMode::Resume, &None),
            (&either, true, true, true, OpenMode::Resume, &None),
            (&either, true, true, false, OpenMode::New, &from),
            (&either, true, false, false, OpenMode::Force, &from),
            (&either, false, false, false, OpenMode::New, &from),
        ] {
            let got = open_mode(start, exists, model, manifest);
            assert_eq!(got, (mode, cloned.clone()), "{start:?} exists {exists} model {model} manifest {manifest}");
        }
    }
}
