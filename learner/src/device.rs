//! `--device auto|cpu|gpu`: where a learner's network maths run. The GPU path is PPO's
//! update and SAC's gradient steps for a learner alone on networks of one input
//! (`ppo/on_gpu.rs`, `sac/on_gpu.rs`); what it does not
//! run is refused by name under `gpu`, and under `auto` runs on faer with a log line that
//! says so (never a silent substitute for what was asked).

use gpu::{DeviceChoice, Gpu};
use policy::ModelMetadata;
use std::sync::{Arc, Mutex};

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
    let inputs = policy::model::inputs(meta, 0);
    (inputs.len() > 1).then(|| format!("networks of several inputs ({} sensors)", inputs.len()))
}

/// A process's `--device`: the GPU is opened once, the first time a model can use it, and
/// shared by every run the process makes after (a learner serves one job after another).
#[derive(Debug)]
pub struct Device {
    choice: DeviceChoice,
    opened: Mutex<Option<Option<Arc<Gpu>>>>,
}

impl Device {
    /// Nothing opened yet.
    pub fn new(choice: DeviceChoice) -> Device {
        Device { choice, opened: Mutex::new(None) }
    }

    /// The GPU for the model `meta` describes: `None` is the CPU.
    pub fn for_model(&self, meta: &ModelMetadata) -> Result<Option<Arc<Gpu>>, DeviceError> {
        if self.choice == DeviceChoice::Cpu {
            return Ok(None);
        }
        if let Some(what) = unsupported(meta) {
            if self.choice == DeviceChoice::Gpu {
                return Err(DeviceError::Unsupported(what));
            }
            tracing::info!("device auto: {what} train on the CPU");
            return Ok(None);
        }
        let mut opened = self.opened.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(gpu) = &*opened {
            return Ok(gpu.clone());
        }
        let gpu = Gpu::open(self.choice)?.map(Arc::new);
        *opened = Some(gpu.clone());
        Ok(gpu)
    }
}
