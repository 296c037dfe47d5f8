//! SAC's gradient steps with the network maths on the GPU (`--device gpu`), for a learner alone: the same batches, noise, losses, Adam steps and
//! target update as [`Sac::step`] on faer. An iteration puts the six networks (policy, the
//! critics' embedder and two heads, V and its target) and their optimisers' moments on the
//! GPU once ([`SacGpu::begin`]); each gradient step then sends its batch and noise in and
//! gets five figures a transition back (the losses' terms, which the finite check and the
//! temperature's step need before the next step); [`Session::finish`] reads the weights and
//! moments back once, for publication. The temperature's one parameter is stepped on the
//! CPU. A refused iteration reads nothing back: the learner's state is as it was.

use super::{Batch, Losses, Sac};
use gpu::kernels::{Op, SacArgs, sac as col};
use gpu::{Gpu, GpuError, GpuNet, Wants};
use policy::nn::Adam;
use std::sync::Arc;

/// A SAC learner's GPU.
#[derive(Clone)]
pub struct SacGpu {
    gpu: Arc<Gpu>,
}

impl std::fmt::Debug for SacGpu {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SacGpu").field("gpu", &self.gpu).finish()
    }
}

/// One iteration's state on the GPU.
pub struct Session {
    gpu: Arc<Gpu>,
    policy: GpuNet,
    embed: Option<GpuNet>,
    q1: GpuNet,
    q2: GpuNet,
    v: GpuNet,
    v_target: GpuNet,
    /// Adam's step counts: policy, embedder, q1, q2, v.
    t: [u32; 5],
    cap: usize,
    /// The embedding's width (the observation's, without an embedder).
    w: usize,
    obs: wgpu::Buffer,
    next_obs: wgpu::Buffer,
    x: wgpu::Buffer,
    dx1: wgpu::Buffer,
    dx2: wgpu::Buffer,
    d_emb: wgpu::Buffer,
    d_pol: wgpu::Buffer,
    cols: wgpu::Buffer,
    flag: wgpu::Buffer,
    staging: wgpu::Buffer,
}

/// The columns read back after a step, in this order, then the non-finite flag.
const READ: [usize; 5] = [col::E1, col::E2, col::LOGP, col::MINQ, col::EV];

impl SacGpu {
    /// SAC on `gpu`.
    pub fn new(gpu: Arc<Gpu>) -> SacGpu {
        SacGpu { gpu }
    }

    /// The adapter, as `render` prints it.
    pub fn adapter(&self) -> &str {
        &self.gpu.adapter
    }

    /// Put `sac`'s networks and moments on the GPU for steps of up to `cap` transitions.
    pub fn begin(&self, sac: &Sac, cap: usize) -> Result<Session, GpuError> {
        let gpu = &self.gpu;
        let cap = cap.max(1);
        let n = &sac.nets;
        let net = |net: &policy::nn::Net, opt: &Adam| -> Result<GpuNet, GpuError> {
            let g = GpuNet::new(gpu, net, cap)?;
            let (m, v, _) = opt.moments();
            g.set_moments(gpu, m, v);
            Ok(g)
        };
        let embed = match &n.q.embed {
            Some(e) => Some(net(e, &sac.adam_embed)?),
            None => None,
        };
        let os = n.policy.in_size();
        let w = n.q.embed.as_ref().map_or(os, |e| e.out_size());
        let staging = gpu.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("SAC's figures"),
            size: ((READ.len() * cap + 1) * 4) as u64,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let steps = |o: &Adam| o.moments().2;
        Ok(Session {
            policy: net(&n.policy, &sac.adam_policy)?,
            embed,
            q1: net(&n.q.q1, &sac.adam_q1)?,
            q2: net(&n.q.q2, &sac.adam_q2)?,
            v: net(&n.v, &sac.adam_v)?,
            v_target: GpuNet::new(gpu, &n.v_target, cap)?,
            t: [&sac.adam_policy, &sac.adam_embed, &sac.adam_q1, &sac.adam_q2, &sac.adam_v].map(steps),
            cap,
            w,
            obs: gpu.buffer("the batch's observations", cap * os)?,
            next_obs: gpu.buffer("the batch's next observations", cap * os)?,
            x: gpu.buffer("the critics' heads' input", cap * (w + 2))?,
            dx1: gpu.buffer("q1's input gradient", cap * (w + 2))?,
            dx2: gpu.buffer("q2's input gradient", cap * (w + 2))?,
            d_emb: gpu.buffer("the embedding's gradient", cap * w)?,
            d_pol: gpu.buffer("the policy's output gradient", cap * 4)?,
            cols: gpu.buffer("SAC's per-transition columns", cap * col::COLS)?,
            flag: gpu.buffer("the non-finite flag", 1)?,
            staging,
            gpu: gpu.clone(),
        })
    }
}

impl Session {
    /// [`Sac::step`] on `batch` (its noise drawn from `sac`'s generator as there): the
    /// losses, and whether every gradient value was finite. `sac`'s temperature and step
    /// count move on; its networks stay as they were until [`Session::finish`].
    pub fn step(&mut self, sac: &mut Sac, batch: &Batch) -> Result<(Losses, bool), GpuError> {
        let b = batch.len();
        assert!(b <= self.cap, "{b} transitions, room for {}", self.cap);
        let gpu = self.gpu.clone();
        let gpu = &*gpu;
        let eps = sac.noise(b);
        let alpha = sac.alpha();
        let s = &sac.settings;
        let inv = 1.0 / b.max(1) as f32;
        let cap = self.cap;
        let w = self.w;
        gpu.upload(&self.obs, 0, &batch.obs);
        gpu.upload(&self.next_obs, 0, &batch.next_obs);
        gpu.upload(&self.cols, col::REWARD * cap, &batch.reward);
        gpu.upload(&self.cols, col::DONE * cap, &batch.done);
        for k in 0..2 {
            let pick = |v: &[f32]| v.iter().skip(k).step_by(2).copied().collect::<Vec<f32>>();
            gpu.upload(&self.cols, (col::EPS + k) * cap, &pick(&eps));
            gpu.upload(&self.cols, (col::ACTION + k) * cap, &pick(&batch.action));
        }
        let args = SacArgs {
            n: b as u32,
            cap: cap as u32,
            w: w as u32,
            huber: s.huber,
            gamma: s.gamma,
            inv,
            alpha,
            scale: s.scale,
        };
        let column = |c: usize| (c * cap * 4) as u64;
        let mut enc = gpu.device.create_command_encoder(&Default::default());
        enc.clear_buffer(&self.flag, 0, None);
        // The policy's draws.
        self.policy.forward(gpu, &mut enc, &self.obs, b);
        gpu.sac(&mut enc, "draws", args, &[self.policy.output()], None, &self.cols);
        // The critics' embedding of s.
        if let Some(e) = self.embed.as_mut() {
            e.forward(gpu, &mut enc, &self.obs, b);
        }
        // Q at the batch's actions against r + (1 − done)·γ·V_target(s').
        self.v_target.forward(gpu, &mut enc, &self.next_obs, b);
        enc.copy_buffer_to_buffer(self.v_target.output(), 0, &self.cols, column(col::VNEXT), (b * 4) as u64);
        self.heads_at(gpu, &mut enc, b, col::ACTION, [col::Q1, col::Q2]);
        gpu.sac(&mut enc, "q_errors", args, &[], None, &self.cols);
        for net in [&self.policy, &self.q1, &self.q2, &self.v].into_iter().chain(self.embed.as_ref()) {
            net.zero_grad(&mut enc);
        }
        self.q1.backward_with(
            gpu,
            &mut enc,
            &self.x,
            (&self.cols, col::D1 * cap),
            b,
            Wants { params: true, d_in: Some(&self.dx1) },
        );
        self.q2.backward_with(
            gpu,
            &mut enc,
            &self.x,
            (&self.cols, col::D2 * cap),
            b,
            Wants { params: true, d_in: Some(&self.dx2) },
        );
        if let Some(e) = self.embed.as_mut() {
            let u = [w as u32, (w + 2) as u32, 0, 0, 0, 0, 0];
            gpu.op(&mut enc, Op::new("add_cols", b * w).u(u), &self.dx1, Some(&self.dx2), &self.d_emb);
            e.backward(gpu, &mut enc, &self.obs, &self.d_emb, b);
        }
        // The policy's draws through the heads: min(q1, q2) and its gradient wrt the action.
        self.heads_at(gpu, &mut enc, b, col::A, [col::Q1P, col::Q2P]);
        gpu.sac(&mut enc, "min_q", args, &[], None, &self.cols);
        self.q1.backward_with(
            gpu,
            &mut enc,
            &self.x,
            (&self.cols, col::DM1 * cap),
            b,
            Wants { params: false, d_in: Some(&self.dx1) },
        );
        self.q2.backward_with(
            gpu,
            &mut enc,
            &self.x,
            (&self.cols, col::DM2 * cap),
            b,
            Wants { params: false, d_in: Some(&self.dx2) },
        );
        let reads = [self.policy.output(), &self.dx1, &self.dx2];
        gpu.sac(&mut enc, "policy_grad", args, &reads, Some(&self.d_pol), &self.cols);
        self.policy.backward(gpu, &mut enc, &self.obs, &self.d_pol, b);
        // V against min q − α·log π of the same draws.
        self.v.forward(gpu, &mut enc, &self.obs, b);
        enc.copy_buffer_to_buffer(self.v.output(), 0, &self.cols, column(col::V), (b * 4) as u64);
        gpu.sac(&mut enc, "v_errors", args, &[], None, &self.cols);
        self.v.backward_with(
            gpu,
            &mut enc,
            &self.obs,
            (&self.cols, col::DV * cap),
            b,
            Wants { params: true, d_in: None },
        );
        // Each network's Adam step, from the gradients of the weights as they were.
        let opts = [&sac.adam_policy, &sac.adam_embed, &sac.adam_q1, &sac.adam_q2, &sac.adam_v];
        let nets = [Some(&self.policy), self.embed.as_ref(), Some(&self.q1), Some(&self.q2), Some(&self.v)];
        for (k, (net, opt)) in nets.into_iter().zip(opts).enumerate() {
            if let Some(net) = net {
                self.t[k] += 1;
                crate::device::adam(gpu, &mut enc, net, opt, self.t[k], &self.flag);
            }
        }
        for (k, &c) in READ.iter().enumerate() {
            enc.copy_buffer_to_buffer(&self.cols, column(c), &self.staging, (k * b * 4) as u64, (b * 4) as u64);
        }
        enc.copy_buffer_to_buffer(&self.flag, 0, &self.staging, (READ.len() * b * 4) as u64, 4);
        gpu.queue.submit([enc.finish()]);
        let out = gpu.read_staging(&self.staging, READ.len() * b + 1)?;
        let part = |k: usize| &out[k * b..(k + 1) * b];
        let (e1, e2, logp, min_q, ev) = (part(0), part(1), part(2), part(3), part(4));
        let finite_grads = out[READ.len() * b].to_bits() == 0;
        // The losses as faer sums them.
        let q = e1.iter().zip(e2).map(|(&a, &c)| 0.5 * (a as f64).powi(2) + 0.5 * (c as f64).powi(2)).sum::<f64>();
        let policy = logp.iter().zip(min_q).map(|(&l, &m)| (alpha * l - m) as f64).sum::<f64>();
        let entropy = -logp.iter().map(|&l| l as f64).sum::<f64>();
        let q_mean = min_q.iter().map(|&m| m as f64).sum::<f64>();
        let v = ev
            .iter()
            .map(|&e| {
                if s.huber {
                    if e.abs() <= 1.0 { 0.5 * (e as f64).powi(2) } else { e.abs() as f64 - 0.5 }
                } else {
                    (e as f64).powi(2)
                }
            })
            .sum::<f64>();
        if let Some(h) = s.target_entropy {
            let g = -logp.iter().map(|l| l + h).sum::<f32>() * inv;
            sac.step_alpha(g);
        }
        sac.steps += 1;
        let wt = inv as f64;
        Ok((
            Losses {
                policy: policy * wt,
                q: q * wt,
                v: v * wt,
                entropy: entropy * wt,
                q_mean: q_mean * wt,
                alpha: alpha as f64,
            },
            finite_grads,
        ))
    }

    /// Record both critics' heads on the embedding beside the actions of column `action`
    /// (two columns), their outputs copied into the columns `into`.
    fn heads_at(&mut self, gpu: &Gpu, enc: &mut wgpu::CommandEncoder, b: usize, action: usize, into: [usize; 2]) {
        let (w, cap) = (self.w, self.cap);
        let emb = self.embed.as_ref().map_or(&self.obs, |e| e.output());
        let u = [w as u32, 2, cap as u32, (action * cap) as u32, 0, 0, 0];
        gpu.op(enc, Op::new("concat_rows", b * (w + 2)).u(u), emb, Some(&self.cols), &self.x);
        for (head, c) in [&mut self.q1, &mut self.q2].into_iter().zip(into) {
            head.forward(gpu, enc, &self.x, b);
            enc.copy_buffer_to_buffer(head.output(), 0, &self.cols, (c * cap * 4) as u64, (b * 4) as u64);
        }
    }

    /// Move V's target copy towards V by `tau` (1: copy it), as [`Sac::update_target`].
    pub fn update_target(&self, tau: f32) {
        let gpu = &self.gpu;
        let mut enc = gpu.device.create_command_encoder(&Default::default());
        let n = self.v.len();
        if tau >= 1.0 {
            enc.copy_buffer_to_buffer(&self.v.params, 0, &self.v_target.params, 0, (n * 4) as u64);
        } else {
            gpu.op(&mut enc, Op::new("lerp", n).x(tau), &self.v.params, None, &self.v_target.params);
        }
        gpu.queue.submit([enc.finish()]);
    }

    /// Read the networks and their optimisers' moments back into `sac`.
    pub fn finish(self, sac: &mut Sac) -> Result<(), GpuError> {
        let gpu = &*self.gpu;
        let n = &mut sac.nets;
        n.policy.params = self.policy.read_params(gpu)?;
        if let (Some(e), Some(g)) = (n.q.embed.as_mut(), &self.embed) {
            e.params = g.read_params(gpu)?;
        }
        n.q.q1.params = self.q1.read_params(gpu)?;
        n.q.q2.params = self.q2.read_params(gpu)?;
        n.v.params = self.v.read_params(gpu)?;
        n.v_target.params = self.v_target.read_params(gpu)?;
        let opts = [&mut sac.adam_policy, &mut sac.adam_embed, &mut sac.adam_q1, &mut sac.adam_q2, &mut sac.adam_v];
        let nets = [Some(&self.policy), self.embed.as_ref(), Some(&self.q1), Some(&self.q2), Some(&self.v)];
        for ((net, opt), t) in nets.into_iter().zip(opts).zip(self.t) {
            if let Some(net) = net {
                let (m, v) = net.read_moments(gpu)?;
                opt.set_moments(m, v, t).map_err(|e| GpuError::Readback(e.to_string()))?;
            }
        }
        Ok(())
    }
}
