//! `--device auto|cpu|gpu`: where a learner's network maths run. The GPU path is PPO's
//! update and SAC's gradient steps for a learner alone (`ppo/on_gpu.rs`, `sac/on_gpu.rs`), on
//! every network Paddock builds (one input or several); a learner team's members train on
//! faer. The Adam step both GPU paths record is here ([`adam`]).

use gpu::kernels::AdamStep;
use gpu::{DeviceChoice, Gpu, GpuNet};
use policy::nn::Adam;
use std::sync::{Arc, Mutex};

/// A process's `--device`: the GPU is opened once, the first time a run asks for it, and
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

    /// The GPU the maths run on: `None` is the CPU. `gpu` without an adapter is an error.
    pub fn gpu(&self) -> Result<Option<Arc<Gpu>>, gpu::GpuError> {
        if self.choice == DeviceChoice::Cpu {
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

/// Say once a process that a learner with a GPU, in a team, makes its updates on faer (the
/// team's exchange is the CPU path's): never a quiet substitute for `--device`.
pub(crate) fn note_team_on_cpu() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| {
        tracing::warn!("in a learner team the updates run on the CPU (faer); the GPU trains a learner alone")
    });
}

/// Record Adam's step `t` of `net` with `opt`'s settings.
pub(crate) fn adam(gpu: &Gpu, enc: &mut wgpu::CommandEncoder, net: &GpuNet, opt: &Adam, t: u32, flag: &wgpu::Buffer) {
    let step = opt.lr / (1.0 - opt.beta1.powi(t as i32));
    let inv_c2 = 1.0 / (1.0 - opt.beta2.powi(t as i32));
    let constants = AdamStep { b1: opt.beta1, b2: opt.beta2, eps: opt.eps, step, inv_c2 };
    gpu.adam(enc, net.len(), [&net.params, &net.m, &net.v], &net.grad, flag, constants);
}
