//! `--device auto|cpu|gpu`: where a learner's network maths run. The GPU path is PPO's
//! update for a learner alone on a network of one input (`ppo/on_gpu.rs`); what it does not
//! run is refused by name under `gpu`, and under `auto` runs on faer with a log line that
//! says so (never a silent substitute for what was asked).

use gpu::{DeviceChoice, Gpu};
use policy::{ModelMetadata, TrainingAlgorithm};
use std::sync::Arc;

/// Why `--device gpu` cannot be had.
#[derive(Debug, thiserror::Error)]
pub enum DeviceError {
    /// No adapter, or one that would not open.
    #[error(transparent)]
    Gpu(#[from] gpu::GpuError),
    /// A model the GPU path does not train.
    #[error("--device gpu: {0} train on the CPU only; use --device cpu or auto")]
    Unsupported(String),
}

/// What of `meta`'s model the GPU path does not train, if anything.
pub fn unsupported(meta: &ModelMetadata) -> Option<String> {
    if meta.training_algorithm == TrainingAlgorithm::Sac {
        return Some("SAC's networks".into());
    }
    let inputs = policy::model::inputs(meta, 0);
    (inputs.len() > 1).then(|| format!("networks of several inputs ({} sensors)", inputs.len()))
}

/// Open the device `choice` asks for the model `meta` describes: `None` is the CPU.
pub fn open(choice: DeviceChoice, meta: &ModelMetadata) -> Result<Option<Arc<Gpu>>, DeviceError> {
    if choice == DeviceChoice::Cpu {
        return Ok(None);
    }
    if let Some(what) = unsupported(meta) {
        if choice == DeviceChoice::Gpu {
            return Err(DeviceError::Unsupported(what));
        }
        tracing::info!("device auto: {what} train on the CPU");
        return Ok(None);
    }
    Ok(Gpu::open(choice)?.map(Arc::new))
}
