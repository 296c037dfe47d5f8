//! A policy acting on the GPU: both towers of an `ActorCritic` resident, their forward
//! passes over a sim agent's environments in one submission, the outputs read back in one
//! copy; the choice (sampling, log-probability) stays `ActorCritic::choose`'s on the CPU.
//! A few models are kept (the versions an agent's open episodes act with, usually one,
//! briefly two), each uploaded once.

use crate::{Gpu, GpuError, GpuNet};
use policy::ActorCritic;
use std::sync::Arc;

/// Models kept on the GPU at once.
const KEPT: usize = 3;

/// The models an agent acts with, on the GPU.
pub struct Acting {
    gpu: Arc<Gpu>,
    /// (the model, its towers on the GPU, the observations' buffer), most recent last.
    kept: Vec<(Arc<ActorCritic>, GpuNet, GpuNet, wgpu::Buffer)>,
    staging: Option<wgpu::Buffer>,
}

impl Acting {
    /// Acting on `gpu`.
    pub fn new(gpu: Arc<Gpu>) -> Acting {
        Acting { gpu, kept: Vec::new(), staging: None }
    }

    /// The adapter.
    pub fn adapter(&self) -> &str {
        &self.gpu.adapter
    }

    /// The towers' outputs over `batch` observations `obs` of `model`: the policy's
    /// (`batch × pi.out_size()`) and the values, or why the GPU could not give them.
    pub fn outputs(
        &mut self,
        model: &Arc<ActorCritic>,
        obs: &[f32],
        batch: usize,
    ) -> Result<(Vec<f32>, Vec<f32>), GpuError> {
        let gpu = self.gpu.clone();
        let at = match self.kept.iter().position(|(m, pi, ..)| Arc::ptr_eq(m, model) && pi.capacity() >= batch) {
            Some(i) => i,
            None => {
                let pi = GpuNet::new(&gpu, &model.pi, batch)?;
                let v = GpuNet::new(&gpu, &model.v, batch)?;
                let x = gpu.buffer("the environments' observations", batch * model.pi.in_size())?;
                if self.kept.len() == KEPT {
                    self.kept.remove(0);
                }
                self.kept.push((model.clone(), pi, v, x));
                self.kept.len() - 1
            }
        };
        let (_, pi, v, x) = &mut self.kept[at];
        gpu.upload(x, 0, obs);
        let (n_pi, n_v) = (batch * model.pi.out_size(), batch * model.v.out_size());
        let need = ((n_pi + n_v) * 4) as u64;
        if self.staging.as_ref().is_none_or(|s| s.size() < need) {
            self.staging = Some(gpu.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("the towers' outputs"),
                size: need,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }));
        }
        let staging = self.staging.as_ref().expect("made above");
        let mut enc = gpu.device.create_command_encoder(&Default::default());
        pi.forward(&gpu, &mut enc, x, batch);
        v.forward(&gpu, &mut enc, x, batch);
        enc.copy_buffer_to_buffer(pi.output(), 0, staging, 0, (n_pi * 4) as u64);
        enc.copy_buffer_to_buffer(v.output(), 0, staging, (n_pi * 4) as u64, (n_v * 4) as u64);
        gpu.queue.submit([enc.finish()]);
        let mut out = gpu.read_staging(staging, n_pi + n_v)?;
        let values = out.split_off(n_pi);
        Ok((out, values))
    }
}
