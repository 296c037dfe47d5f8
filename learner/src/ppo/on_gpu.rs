//! PPO's update with the network maths on the GPU (`--device gpu`): the same epochs, shuffles, minibatches, losses, Adam steps and KL stop as
//! [`Ppo::train`](super::Ppo) on faer, for a learner alone. Both towers' weights, Adam's
//! moments, the iteration's batch and each minibatch stay on the GPU for the whole update;
//! what crosses over per minibatch is its indices going in and its loss figures (a few
//! hundred floats) coming out, which the KL stop and the finite check need before the next.
//! The log-std's two parameters (Gaussian head) are stepped on the CPU from the kernel's
//! per-sample terms. The weights are read back once an update, for publication. The batch's
//! old log-probabilities and GAE's values are the resident towers' forward passes too.

use super::{Batch, CLIP_EPSILON, PpoStats, batch_with, logp_of};
use crate::device::adam;
use crate::hyperparams::{Hyperparameters, LossType};
use crate::update::Refused;
use gpu::kernels::{LossArgs, LossBuffers, Op, SAMPLE, STATS};
use gpu::{Gpu, GpuError, GpuNet};
use policy::model::LOG_STD_RANGE;
use policy::nn::Adam;
use policy::{ActorCritic, Choice, Head, Trajectory};
use std::sync::Arc;

/// One update's epochs on the GPU: the batch, its minibatch size, whether the policy is
/// held (the value warm-up), and the epochs in which the value tower trains; `version` names
/// the update in a refusal.
pub(super) struct Epochs<'a> {
    pub batch: &'a Batch,
    pub bs: usize,
    pub hold_policy: bool,
    pub value_epochs: usize,
    pub version: u64,
}

/// One gradient step: `len` samples from `at` in the epoch's order, the Gaussian head's
/// log-stds, whether the policy is held, and whether the value tower trains.
struct Step {
    at: usize,
    len: usize,
    log_std: [f32; 2],
    hold_policy: bool,
    value: bool,
}

/// A learner's GPU: the device, and the model's state on it once the first update put it
/// there. A clone (a saved copy of the learner) shares the device and holds nothing on it.
pub struct GpuTrainer {
    gpu: Arc<Gpu>,
    resident: Option<Resident>,
}

impl Clone for GpuTrainer {
    fn clone(&self) -> Self {
        GpuTrainer { gpu: self.gpu.clone(), resident: None }
    }
}

impl std::fmt::Debug for GpuTrainer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuTrainer").field("gpu", &self.gpu).field("resident", &self.resident.is_some()).finish()
    }
}

/// The model's state on the GPU, and the update's buffers.
struct Resident {
    pi: GpuNet,
    v: GpuNet,
    /// Adam's step counts (the CPU optimisers' are behind while the model is here).
    t: [u32; 2],
    /// Capacity in samples of `obs` and `samples`.
    batch_cap: usize,
    obs: wgpu::Buffer,
    samples: wgpu::Buffer,
    idx: wgpu::Buffer,
    mb_obs: wgpu::Buffer,
    d_pi: wgpu::Buffer,
    d_v: wgpu::Buffer,
    stats_pi: wgpu::Buffer,
    stats_v: wgpu::Buffer,
    flag: wgpu::Buffer,
    staging: wgpu::Buffer,
    /// Parameters and moments at the start of the update (pi: 3, v: 3), put back when it is
    /// refused.
    backup: Vec<wgpu::Buffer>,
}

/// An optimiser's moments and step count: first, second, steps.
pub type Moments = (Vec<f32>, Vec<f32>, u32);

/// The minibatch's figures, read back.
struct Figures {
    policy_loss: f64,
    value_loss: f64,
    entropy: f64,
    approx_kl: f64,
    clip_fraction: f64,
    grad_log_std: [f32; 2],
    finite_grads: bool,
}

impl GpuTrainer {
    /// A trainer on `gpu`.
    pub fn new(gpu: Arc<Gpu>) -> GpuTrainer {
        GpuTrainer { gpu, resident: None }
    }

    /// The adapter, as `render` prints it.
    pub fn adapter(&self) -> &str {
        &self.gpu.adapter
    }

    /// Whether the model's state is on the GPU (then the CPU optimisers' moments are stale).
    pub fn is_resident(&self) -> bool {
        self.resident.is_some()
    }

    /// Forget the state on the GPU (the CPU's changed: a restore).
    pub fn evict(&mut self) {
        self.resident = None;
    }

    /// The optimisers' moments and step counts as they are on the GPU (pi, v).
    pub fn moments(&self) -> Result<Option<[Moments; 2]>, GpuError> {
        let Some(r) = &self.resident else { return Ok(None) };
        let (pm, pv) = r.pi.read_moments(&self.gpu)?;
        let (vm, vv) = r.v.read_moments(&self.gpu)?;
        Ok(Some([(pm, pv, r.t[0]), (vm, vv, r.t[1])]))
    }

    fn ensure(&mut self, model: &ActorCritic, opts: [&Adam; 2], bs: usize, n: usize) -> Result<(), GpuError> {
        let gpu = &self.gpu;
        if self.resident.as_ref().is_some_and(|r| r.pi.capacity() < bs) {
            // A bigger minibatch than the buffers were made for: move the state over.
            let r = self.resident.take().expect("checked");
            let (pm, pv) = r.pi.read_moments(gpu)?;
            let (vm, vv) = r.v.read_moments(gpu)?;
            let mut fresh = Resident::new(gpu, model, bs, n)?;
            fresh.pi.set_moments(gpu, &pm, &pv);
            fresh.v.set_moments(gpu, &vm, &vv);
            fresh.t = r.t;
            self.resident = Some(fresh);
        }
        if self.resident.is_none() {
            let r = Resident::new(gpu, model, bs, n)?;
            let (m, v, t_pi) = opts[0].moments();
            r.pi.set_moments(gpu, m, v);
            let (m, v, t_v) = opts[1].moments();
            r.v.set_moments(gpu, m, v);
            self.resident = Some(Resident { t: [t_pi, t_v], ..r });
        }
        let r = self.resident.as_mut().expect("made above");
        if r.batch_cap < n {
            r.batch_cap = n.next_power_of_two();
            r.obs = gpu.buffer("the batch's observations", r.batch_cap * model.pi.in_size())?;
            r.samples = gpu.buffer("the batch's samples", r.batch_cap * SAMPLE)?;
            r.idx = gpu.buffer("the minibatch order", r.batch_cap)?;
        }
        Ok(())
    }

    /// The update's batch, as `make_batch_for` makes it on faer: the old log-probabilities and
    /// the values behind GAE from the towers as the update begins, their forward passes here.
    pub(super) fn make_batch(
        &mut self,
        trajs: &[Trajectory],
        model: &ActorCritic,
        opts: [&Adam; 2],
        hyper: &Hyperparameters,
    ) -> Result<Batch, GpuError> {
        let n: usize = trajs.iter().map(|t| t.len()).sum();
        self.ensure(model, opts, hyper.batch_size.min(n.max(1)), n)?;
        let r = self.resident.as_mut().expect("ensured");
        let gpu = &self.gpu;
        batch_with(trajs, model.obs_size(), hyper.discount_factor, |obs, choices| r.relabel(gpu, model, obs, choices))
    }

    /// PPO's update of `model` on `epochs.batch` (made on the CPU, as for faer), in the
    /// order `order` gives each epoch. `opts`: the CPU optimisers of pi, v and the log-std
    /// (the last is stepped here; the first two's moments are taken over the first time). A
    /// refused update leaves the state on the GPU as it was.
    pub(super) fn train(
        &mut self,
        model: &mut ActorCritic,
        opts: [&mut Adam; 3],
        hyper: &Hyperparameters,
        epochs: Epochs<'_>,
        mut order: impl FnMut(&mut Vec<usize>),
        stats: &mut PpoStats,
    ) -> Result<(), Refused> {
        let Epochs { batch, bs, hold_policy, value_epochs, version } = epochs;
        let n = batch.len();
        let [opt_pi, opt_v, opt_log_std] = opts;
        let lost = |e: GpuError| Refused::Device { error: e.to_string(), version };
        self.ensure(model, [opt_pi, opt_v], bs, n).map_err(lost)?;
        let gpu = self.gpu.clone();
        let r = self.resident.as_mut().expect("ensured");
        // The update's starting point, and its batch.
        let mut enc = gpu.device.create_command_encoder(&Default::default());
        for (i, b) in [&r.pi.params, &r.pi.m, &r.pi.v, &r.v.params, &r.v.m, &r.v.v].into_iter().enumerate() {
            enc.copy_buffer_to_buffer(b, 0, &r.backup[i], 0, b.size());
        }
        gpu.queue.submit([enc.finish()]);
        gpu.upload(&r.obs, 0, &batch.obs);
        gpu.upload(&r.samples, 0, &samples(batch));
        let log_std_before = match model.head {
            Head::Gaussian { log_std } => Some(log_std),
            _ => None,
        };
        let t_before = r.t;
        let (lo, hi) = LOG_STD_RANGE;
        let mut idx: Vec<usize> = (0..n).collect();
        let steps_per_epoch = n / bs;
        let result = (|| {
            for epoch in 0..hyper.num_epochs {
                let value = epoch < value_epochs;
                order(&mut idx);
                let bits: Vec<f32> = idx.iter().map(|&i| f32::from_bits(i as u32)).collect();
                gpu.upload(&r.idx, 0, &bits);
                for mb in 0..steps_per_epoch {
                    let log_std = match model.head {
                        Head::Gaussian { log_std } => log_std,
                        _ => [0.0; 2],
                    };
                    let step = Step { at: mb * bs, len: bs, log_std, hold_policy, value };
                    let f = r.minibatch(&gpu, model, hyper, step, [opt_pi, opt_v]).map_err(lost)?;
                    let mut g_log_std = f.grad_log_std;
                    if let Head::Gaussian { log_std } = &mut model.head {
                        for j in 0..2 {
                            if log_std[j] > lo && log_std[j] < hi {
                                g_log_std[j] -= hyper.beta_entropy as f32;
                            }
                        }
                        if !hold_policy {
                            opt_log_std.step(log_std, &g_log_std);
                        }
                    }
                    let total = f.policy_loss - hyper.beta_entropy * f.entropy + f.value_loss;
                    let step = stats.gradient_steps;
                    if !(f.finite_grads && total.is_finite() && g_log_std.iter().all(|g| g.is_finite())) {
                        return Err(Refused::NonFinite { step, loss: total, version });
                    }
                    stats.policy_loss += f.policy_loss;
                    stats.value_loss += f.value_loss;
                    stats.value_steps += usize::from(value);
                    stats.entropy += f.entropy;
                    stats.approx_kl += f.approx_kl;
                    stats.clip_fraction += f.clip_fraction;
                    stats.gradient_steps += 1;
                    if hyper.target_kl.is_some_and(|t| f.approx_kl > 1.5 * t) {
                        stats.kl_stop = Some(stats.gradient_steps);
                        return Ok(());
                    }
                }
            }
            Ok(())
        })();
        if let Err(e) = result {
            // Back to where the update started, on both sides.
            let mut enc = gpu.device.create_command_encoder(&Default::default());
            for (i, b) in [&r.pi.params, &r.pi.m, &r.pi.v, &r.v.params, &r.v.m, &r.v.v].into_iter().enumerate() {
                enc.copy_buffer_to_buffer(&r.backup[i], 0, b, 0, b.size());
            }
            gpu.queue.submit([enc.finish()]);
            r.t = t_before;
            if let (Some(before), Head::Gaussian { log_std }) = (log_std_before, &mut model.head) {
                *log_std = before;
            }
            return Err(e);
        }
        model.pi.params = r.pi.read_params(&gpu).map_err(lost)?;
        model.v.params = r.v.read_params(&gpu).map_err(lost)?;
        Ok(())
    }
}

/// Each sample's record for the loss kernels: advantage, behaviour log-probability,
/// return, the action (a choice's index as bits, or two values), 0.
fn samples(b: &Batch) -> Vec<f32> {
    let mut out = Vec::with_capacity(b.len() * SAMPLE);
    for i in 0..b.len() {
        let (a0, a1) = match b.choices[i] {
            Choice::Discrete(c) => (f32::from_bits(c as u32), 0.0),
            Choice::Continuous([x, y]) => (x, y),
        };
        out.extend_from_slice(&[b.adv[i], b.logp_old[i], b.returns[i], a0, a1, 0.0]);
    }
    out
}

impl Resident {
    fn new(gpu: &Gpu, model: &ActorCritic, bs: usize, n: usize) -> Result<Resident, GpuError> {
        let pi = GpuNet::new(gpu, &model.pi, bs)?;
        let v = GpuNet::new(gpu, &model.v, bs)?;
        let cap = n.next_power_of_two();
        let backup = [pi.len(), pi.len(), pi.len(), v.len(), v.len(), v.len()]
            .iter()
            .map(|&len| gpu.buffer("the update's starting point", len))
            .collect::<Result<_, _>>()?;
        // The minibatch's figures, or a minibatch's outputs of both towers.
        let figures = (2 * bs * STATS + 1).max(bs * (model.pi.out_size() + 1));
        Ok(Resident {
            t: [0, 0],
            batch_cap: cap,
            obs: gpu.buffer("the batch's observations", cap * model.pi.in_size())?,
            samples: gpu.buffer("the batch's samples", cap * SAMPLE)?,
            idx: gpu.buffer("the minibatch order", cap)?,
            mb_obs: gpu.buffer("the minibatch's observations", bs * model.pi.in_size())?,
            d_pi: gpu.buffer("the policy's output gradient", bs * model.pi.out_size())?,
            d_v: gpu.buffer("the value's output gradient", bs)?,
            stats_pi: gpu.buffer("the policy loss's figures", bs * STATS)?,
            stats_v: gpu.buffer("the value loss's figures", bs * STATS)?,
            flag: gpu.buffer("the non-finite flag", 1)?,
            staging: gpu.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("the minibatch's figures"),
                size: (figures * 4) as u64,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }),
            backup,
            pi,
            v,
        })
    }

    /// log π(choice) and V for every row of `obs`, a minibatch's worth at a time.
    fn relabel(
        &mut self,
        gpu: &Gpu,
        model: &ActorCritic,
        obs: &[f32],
        choices: &[Choice],
    ) -> Result<(Vec<f32>, Vec<f32>), GpuError> {
        let (os, dim, cap) = (model.obs_size(), model.pi.out_size(), self.pi.capacity());
        let (mut logp, mut values) = (Vec::with_capacity(choices.len()), Vec::with_capacity(choices.len()));
        for (rows, picked) in obs.chunks(cap * os).zip(choices.chunks(cap)) {
            let k = picked.len();
            gpu.upload(&self.mb_obs, 0, rows);
            let mut enc = gpu.device.create_command_encoder(&Default::default());
            self.pi.forward(gpu, &mut enc, &self.mb_obs, k);
            self.v.forward(gpu, &mut enc, &self.mb_obs, k);
            enc.copy_buffer_to_buffer(self.pi.output(), 0, &self.staging, 0, (k * dim * 4) as u64);
            enc.copy_buffer_to_buffer(self.v.output(), 0, &self.staging, (k * dim * 4) as u64, (k * 4) as u64);
            gpu.queue.submit([enc.finish()]);
            let out = gpu.read_staging(&self.staging, k * (dim + 1))?;
            let (pi, v) = out.split_at(k * dim);
            logp.extend(pi.chunks_exact(dim).zip(picked).map(|(row, c)| logp_of(model, row, *c)));
            values.extend_from_slice(v);
        }
        Ok((logp, values))
    }

    /// One gradient step on the minibatch `step` says.
    fn minibatch(
        &mut self,
        gpu: &Gpu,
        model: &ActorCritic,
        hyper: &Hyperparameters,
        step: Step,
        opts: [&mut Adam; 2],
    ) -> Result<Figures, GpuError> {
        let Step { at, len, log_std, hold_policy, value } = step;
        let os = model.pi.in_size() as u32;
        let inv_n = 1.0 / len as f32;
        let mut enc = gpu.device.create_command_encoder(&Default::default());
        gpu.op(
            &mut enc,
            Op::new("gather_rows", len * os as usize).u([os, at as u32, 0, 0, 0, 0, 0]),
            &self.obs,
            Some(&self.idx),
            &self.mb_obs,
        );
        enc.clear_buffer(&self.flag, 0, None);
        // The policy tower: forward, the clipped surrogate and entropy, backward.
        self.pi.forward(gpu, &mut enc, &self.mb_obs, len);
        let (dim, kind) = match model.head {
            Head::Gaussian { .. } => (2, 1),
            _ => (model.pi.out_size() as u32, 0),
        };
        let args = LossArgs {
            n: len as u32,
            dim,
            kind,
            idx_off: at as u32,
            beta: hyper.beta_entropy as f32,
            inv_n,
            clip: CLIP_EPSILON,
            dual_clip: hyper.dual_clip.map_or(0.0, |c| c as f32),
            log_std,
        };
        let bufs = LossBuffers {
            out: self.pi.output(),
            samples: &self.samples,
            idx: &self.idx,
            d: &self.d_pi,
            stats: &self.stats_pi,
        };
        gpu.loss(&mut enc, false, args, bufs);
        self.pi.zero_grad(&mut enc);
        self.pi.backward(gpu, &mut enc, &self.mb_obs, &self.d_pi, len);
        // The value tower, in the update's value epochs.
        if value {
            self.v.forward(gpu, &mut enc, &self.mb_obs, len);
            let kind = match hyper.loss_type {
                LossType::Huber => 0,
                LossType::MeanSquaredError => 1,
            };
            let args = LossArgs { dim: 1, kind, ..args };
            let bufs = LossBuffers {
                out: self.v.output(),
                samples: &self.samples,
                idx: &self.idx,
                d: &self.d_v,
                stats: &self.stats_v,
            };
            gpu.loss(&mut enc, true, args, bufs);
            self.v.zero_grad(&mut enc);
            self.v.backward(gpu, &mut enc, &self.mb_obs, &self.d_v, len);
        }
        // Adam on the towers that trained (the policy's held while the value tower warms up).
        let [opt_pi, opt_v] = opts;
        if !hold_policy {
            self.t[0] += 1;
            adam(gpu, &mut enc, &self.pi, opt_pi, self.t[0], &self.flag);
        }
        if value {
            self.t[1] += 1;
            adam(gpu, &mut enc, &self.v, opt_v, self.t[1], &self.flag);
        }
        let n = len * STATS;
        enc.copy_buffer_to_buffer(&self.stats_pi, 0, &self.staging, 0, (n * 4) as u64);
        enc.copy_buffer_to_buffer(&self.stats_v, 0, &self.staging, (n * 4) as u64, (n * 4) as u64);
        enc.copy_buffer_to_buffer(&self.flag, 0, &self.staging, (2 * n * 4) as u64, 4);
        gpu.queue.submit([enc.finish()]);
        let out = gpu.read_staging(&self.staging, 2 * n + 1)?;
        let nf = len as f64;
        let col = |part: &[f32], c: usize| part.chunks_exact(STATS).map(|s| s[c] as f64).sum::<f64>();
        let (p, v) = out[..2 * n].split_at(n);
        let sum32 = |c: usize| p.chunks_exact(STATS).map(|s| s[c]).sum::<f32>();
        Ok(Figures {
            policy_loss: col(p, 0) / nf,
            entropy: col(p, 1) / nf,
            approx_kl: col(p, 2) / nf,
            clip_fraction: col(p, 3) / nf,
            value_loss: if value { col(v, 0) / nf } else { 0.0 },
            grad_log_std: [sum32(4), sum32(5)],
            finite_grads: out[2 * n].to_bits() == 0,
        })
    }
}
