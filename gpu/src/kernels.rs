//! The compiled kernels and one function per dispatch. Each records a compute pass into the
//! caller's encoder (wgpu orders the passes' reads after earlier writes), with its
//! arguments in a small uniform buffer of its own.

use crate::Gpu;
use wgpu::util::DeviceExt;

const GEMM: &str = include_str!("gemm.wgsl");
const OPS: &str = include_str!("ops.wgsl");
const ADAM: &str = include_str!("adam.wgsl");
const LOSS: &str = include_str!("loss.wgsl");
const SAC: &str = include_str!("sac.wgsl");

/// A sample's record in the loss kernels' `samples` buffer (loss.wgsl's `SAMPLE`).
pub const SAMPLE: usize = 6;
/// A sample's figures in the loss kernels' `stats` buffer (loss.wgsl's `STATS`).
pub const STATS: usize = 6;

/// The columns of SAC's per-transition buffer (sac.wgsl's `COL_` constants): a block of the
/// buffer's capacity each, the transition's row within it.
pub mod sac {
    /// The reward (uploaded).
    pub const REWARD: usize = 0;
    /// 1 where the episode ended (uploaded).
    pub const DONE: usize = 1;
    /// The policy's noise, two columns (uploaded).
    pub const EPS: usize = 2;
    /// The batch's actions, two columns (uploaded).
    pub const ACTION: usize = 4;
    /// V_target(s').
    pub const VNEXT: usize = 6;
    /// The heads at the batch's actions.
    pub const Q1: usize = 7;
    /// The second head.
    pub const Q2: usize = 8;
    /// The heads' errors.
    pub const E1: usize = 9;
    /// The second head's.
    pub const E2: usize = 10;
    /// Their gradients.
    pub const D1: usize = 11;
    /// The second head's.
    pub const D2: usize = 12;
    /// The policy's draws, two columns.
    pub const A: usize = 13;
    /// log π of the draws.
    pub const LOGP: usize = 15;
    /// The heads at the draws.
    pub const Q1P: usize = 16;
    /// The second head.
    pub const Q2P: usize = 17;
    /// Their minimum.
    pub const MINQ: usize = 18;
    /// The gradient of −min wrt the first head's output.
    pub const DM1: usize = 19;
    /// The second head's.
    pub const DM2: usize = 20;
    /// V(s).
    pub const V: usize = 21;
    /// V's error.
    pub const EV: usize = 22;
    /// Its gradient.
    pub const DV: usize = 23;
    /// Columns in all.
    pub const COLS: usize = 24;
}

/// What SAC's kernels are told (sac.wgsl's `Sac`).
#[derive(Clone, Copy, Debug, Default)]
pub struct SacArgs {
    /// Transitions in the batch.
    pub n: u32,
    /// A column block's length.
    pub cap: u32,
    /// The embedding's width (the heads' input less the action).
    pub w: u32,
    /// V's loss is Huber's.
    pub huber: bool,
    /// The discount.
    pub gamma: f32,
    /// A transition's weight (1 / batch).
    pub inv: f32,
    /// The temperature.
    pub alpha: f32,
    /// Half of each action's range.
    pub scale: [f32; 2],
}

/// A product's operand: its buffer, the float its matrix starts at, and whether it is
/// stored transposed.
#[derive(Clone, Copy)]
pub struct Operand<'a> {
    /// The buffer.
    pub buf: &'a wgpu::Buffer,
    /// Where the matrix starts (floats).
    pub at: usize,
    /// Stored transposed.
    pub t: bool,
}

/// One product for [`Gpu::gemm`]: `c (m×n) = op(a) (m×k) · op(b) (k×n)`, added to what `c`
/// holds when `add`.
#[derive(Clone, Copy)]
pub struct Gemm<'a> {
    /// m, n and k.
    pub mnk: [usize; 3],
    /// The left operand.
    pub a: Operand<'a>,
    /// The right operand.
    pub b: Operand<'a>,
    /// The output's buffer and where it starts (floats).
    pub c: (&'a wgpu::Buffer, usize),
    /// Add to the output rather than replace it.
    pub add: bool,
}

/// Every compiled pipeline.
pub struct Kernels {
    four: wgpu::BindGroupLayout,
    six_opt: wgpu::BindGroupLayout,
    six_loss: wgpu::BindGroupLayout,
    gemm: wgpu::ComputePipeline,
    reduce: wgpu::ComputePipeline,
    ops: std::collections::HashMap<&'static str, wgpu::ComputePipeline>,
    adam: wgpu::ComputePipeline,
    policy_loss: wgpu::ComputePipeline,
    value_loss: wgpu::ComputePipeline,
    sac: std::collections::HashMap<&'static str, wgpu::ComputePipeline>,
    /// Bound where a kernel reads nothing.
    dummy: wgpu::Buffer,
    /// Bound where a kernel writes nothing.
    dummy2: wgpu::Buffer,
}

#[derive(Clone, Copy)]
enum Slot {
    Read,
    Write,
    Uniform,
}

fn layout(device: &wgpu::Device, slots: &[Slot]) -> wgpu::BindGroupLayout {
    let entries: Vec<_> = (slots.iter().enumerate())
        .map(|(i, s)| wgpu::BindGroupLayoutEntry {
            binding: i as u32,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: match s {
                Slot::Read => wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Storage { read_only: true },
                    has_dynamic_offset: false,
                    min_binding_size: None,
                },
                Slot::Write => wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Storage { read_only: false },
                    has_dynamic_offset: false,
                    min_binding_size: None,
                },
                Slot::Uniform => wgpu::BindingType::Buffer {
                    ty: wgpu::BufferBindingType::Uniform,
                    has_dynamic_offset: false,
                    min_binding_size: None,
                },
            },
            count: None,
        })
        .collect();
    device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor { label: None, entries: &entries })
}

fn pipeline(
    device: &wgpu::Device,
    module: &wgpu::ShaderModule,
    layout: &wgpu::BindGroupLayout,
    entry: &str,
) -> wgpu::ComputePipeline {
    let pl = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
        label: None,
        bind_group_layouts: &[Some(layout)],
        immediate_size: 0,
    });
    device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some(entry),
        layout: Some(&pl),
        module,
        entry_point: Some(entry),
        compilation_options: Default::default(),
        cache: None,
    })
}

/// The element-wise kernels of ops.wgsl.
const OPS_ENTRIES: [&str; 12] = [
    "fill_rows",
    "relu",
    "relu_back",
    "scale",
    "ones",
    "gather_rows",
    "im2col",
    "col2im",
    "concat_rows",
    "add_cols",
    "lerp",
    "copy_cols",
];

/// SAC's kernels.
const SAC_ENTRIES: [&str; 5] = ["draws", "q_errors", "min_q", "policy_grad", "v_errors"];

impl Kernels {
    /// Compile every kernel on `device`.
    pub fn new(device: &wgpu::Device) -> Kernels {
        let module = |name: &str, src: &str| {
            device.create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(name),
                source: wgpu::ShaderSource::Wgsl(src.into()),
            })
        };
        use Slot::*;
        let four = layout(device, &[Read, Read, Write, Uniform]);
        let six_opt = layout(device, &[Write, Write, Write, Read, Write, Uniform]);
        let six_loss = layout(device, &[Read, Read, Read, Write, Write, Uniform]);
        let gemm_m = module("gemm", GEMM);
        let ops_m = module("ops", OPS);
        let adam_m = module("adam", ADAM);
        let loss_m = module("loss", LOSS);
        let sac_m = module("sac", SAC);
        let ops = OPS_ENTRIES.iter().map(|&e| (e, pipeline(device, &ops_m, &four, e))).collect();
        Kernels {
            gemm: pipeline(device, &gemm_m, &four, "gemm"),
            reduce: pipeline(device, &gemm_m, &four, "reduce"),
            ops,
            adam: pipeline(device, &adam_m, &six_opt, "adam"),
            policy_loss: pipeline(device, &loss_m, &six_loss, "policy_loss"),
            value_loss: pipeline(device, &loss_m, &six_loss, "value_loss"),
            sac: SAC_ENTRIES.iter().map(|&e| (e, pipeline(device, &sac_m, &six_loss, e))).collect(),
            dummy: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("dummy"),
                size: 16,
                usage: wgpu::BufferUsages::STORAGE,
                mapped_at_creation: false,
            }),
            dummy2: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("dummy to write"),
                size: 16,
                usage: wgpu::BufferUsages::STORAGE,
                mapped_at_creation: false,
            }),
            four,
            six_opt,
            six_loss,
        }
    }
}

/// Workgroups for `n` threads of 256, laid out over x and y (at most 65,535 a side).
fn groups(n: usize) -> (u32, u32) {
    let g = n.div_ceil(256).max(1) as u32;
    if g <= 65_535 { (g, 1) } else { (65_535, g.div_ceil(65_535)) }
}

/// One element-wise kernel of ops.wgsl: its entry point, the outputs it makes, and its
/// integer arguments `u` and float `x` (zero unless set).
#[derive(Clone, Copy, Debug)]
pub struct Op<'a> {
    /// The kernel's entry point in ops.wgsl.
    pub entry: &'a str,
    /// Outputs made.
    pub n: usize,
    /// The integer arguments.
    pub u: [u32; 7],
    /// The float argument.
    pub x: f32,
}

impl<'a> Op<'a> {
    /// `entry` over `n` outputs, its arguments zero.
    pub fn new(entry: &'a str, n: usize) -> Op<'a> {
        Op { entry, n, u: [0; 7], x: 0.0 }
    }

    /// With the integer arguments `u`.
    pub fn u(self, u: [u32; 7]) -> Op<'a> {
        Op { u, ..self }
    }

    /// With the float argument `x`.
    pub fn x(self, x: f32) -> Op<'a> {
        Op { x, ..self }
    }
}

/// One Adam step's constants (loss.wgsl's): `step` is lr / (1 − β1ᵗ), `inv_c2` 1 / (1 − β2ᵗ).
#[derive(Clone, Copy, Debug)]
pub struct AdamStep {
    /// β1.
    pub b1: f32,
    /// β2.
    pub b2: f32,
    /// ε.
    pub eps: f32,
    /// lr / (1 − β1ᵗ).
    pub step: f32,
    /// 1 / (1 − β2ᵗ).
    pub inv_c2: f32,
}

/// The buffers a PPO loss kernel reads and writes.
#[derive(Clone, Copy, Debug)]
pub struct LossBuffers<'a> {
    /// The tower's outputs.
    pub out: &'a wgpu::Buffer,
    /// The batch's samples.
    pub samples: &'a wgpu::Buffer,
    /// The minibatch's indices.
    pub idx: &'a wgpu::Buffer,
    /// The gradient wrt the outputs (written).
    pub d: &'a wgpu::Buffer,
    /// Each sample's figures (written).
    pub stats: &'a wgpu::Buffer,
}

/// What `policy_loss` and `value_loss` are told (loss.wgsl's `Loss`).
#[derive(Clone, Copy, Debug, Default)]
pub struct LossArgs {
    /// Samples in the minibatch.
    pub n: u32,
    /// Outputs per sample.
    pub dim: u32,
    /// Policy: 0 categorical, 1 Gaussian. Value: 0 Huber, 1 squared error.
    pub kind: u32,
    /// Where the minibatch's indices start in the index buffer.
    pub idx_off: u32,
    /// The entropy bonus's β.
    pub beta: f32,
    /// 1 / n.
    pub inv_n: f32,
    /// PPO's clip range.
    pub clip: f32,
    /// Dual-clip PPO's bound on a negative advantage's surrogate, in advantages (0: none; a
    /// shader may not meet infinities).
    pub dual_clip: f32,
    /// The Gaussian head's log-stds.
    pub log_std: [f32; 2],
}

impl Gpu {
    fn uniform(&self, words: &[u32]) -> wgpu::Buffer {
        self.device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: None,
            contents: bytemuck::cast_slice(words),
            usage: wgpu::BufferUsages::UNIFORM,
        })
    }

    fn run(
        &self,
        enc: &mut wgpu::CommandEncoder,
        pipeline: &wgpu::ComputePipeline,
        layout: &wgpu::BindGroupLayout,
        buffers: &[&wgpu::Buffer],
        grid: (u32, u32, u32),
    ) {
        let entries: Vec<_> = (buffers.iter().enumerate())
            .map(|(i, b)| wgpu::BindGroupEntry { binding: i as u32, resource: b.as_entire_binding() })
            .collect();
        let group =
            self.device.create_bind_group(&wgpu::BindGroupDescriptor { label: None, layout, entries: &entries });
        let mut pass = enc.begin_compute_pass(&Default::default());
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, &group, &[]);
        pass.dispatch_workgroups(grid.0, grid.1, grid.2);
    }

    /// Record `g`: `c (m×n) = op(a) · op(b)`, added to `c` when `add`. A small output over a
    /// long K is split over K into `scratch` (grown as needed) and the parts added in order.
    pub fn gemm(&self, enc: &mut wgpu::CommandEncoder, g: &Gemm<'_>, scratch: &mut Option<wgpu::Buffer>) {
        let Gemm { mnk: [m, n, k], a, b, c, add } = *g;
        let tiles = m.div_ceil(64) * n.div_ceil(64);
        // Enough workgroups to fill a big GPU, each with at least 512 of K.
        let splits = if tiles >= 64 { 1 } else { (k / 512).min(128 / tiles).max(1) };
        let kern = &self.kernels;
        let flags = |add: bool| a.t as u32 | (b.t as u32) << 1 | (add as u32) << 2;
        let grid = (n.div_ceil(64) as u32, m.div_ceil(64) as u32);
        if splits == 1 {
            let u = self.uniform(&[
                m as u32,
                n as u32,
                k as u32,
                flags(add),
                a.at as u32,
                b.at as u32,
                c.1 as u32,
                k as u32,
                0,
                0,
                0,
                0,
            ]);
            self.run(enc, &kern.gemm, &kern.four, &[a.buf, b.buf, c.0, &u], (grid.0, grid.1, 1));
            return;
        }
        let chunk = k.div_ceil(splits).next_multiple_of(16);
        let splits = k.div_ceil(chunk);
        let need = (splits * m * n * 4) as u64;
        if scratch.as_ref().is_none_or(|s| s.size() < need) {
            *scratch = Some(self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("split-K parts"),
                size: need,
                usage: wgpu::BufferUsages::STORAGE,
                mapped_at_creation: false,
            }));
        }
        let parts = scratch.as_ref().expect("made above");
        let u = self.uniform(&[
            m as u32,
            n as u32,
            k as u32,
            flags(false),
            a.at as u32,
            b.at as u32,
            0,
            chunk as u32,
            (m * n) as u32,
            0,
            0,
            0,
        ]);
        self.run(enc, &kern.gemm, &kern.four, &[a.buf, b.buf, parts, &u], (grid.0, grid.1, splits as u32));
        let u = self.uniform(&[m as u32, n as u32, splits as u32, (add as u32) << 2, 0, 0, c.1 as u32, 0, 0, 0, 0, 0]);
        let (gx, gy) = groups(m * n);
        self.run(enc, &kern.reduce, &kern.four, &[parts, &kern.dummy, c.0, &u], (gx, gy, 1));
    }

    /// One element-wise kernel of ops.wgsl, `op`: `dst` from `src` (and `src2`).
    pub fn op(
        &self,
        enc: &mut wgpu::CommandEncoder,
        op: Op<'_>,
        src: &wgpu::Buffer,
        src2: Option<&wgpu::Buffer>,
        dst: &wgpu::Buffer,
    ) {
        let Op { entry, n, u, x } = op;
        if n == 0 {
            return;
        }
        let kern = &self.kernels;
        let pipeline = kern.ops.get(entry).unwrap_or_else(|| panic!("no kernel `{entry}`"));
        let [u0, u1, u2, u3, u4, u5, u6] = u;
        let args = self.uniform(&[n as u32, u0, u1, u2, u3, u4, u5, u6, x.to_bits(), 0, 0, 0]);
        let (gx, gy) = groups(n);
        self.run(enc, pipeline, &kern.four, &[src, src2.unwrap_or(&kern.dummy), dst, &args], (gx, gy, 1));
    }

    /// Fill the first `n` floats of `buf` with 1.
    pub fn fill_ones(&self, enc: &mut wgpu::CommandEncoder, buf: &wgpu::Buffer, n: usize) {
        let kern = &self.kernels;
        let args = self.uniform(&[n as u32, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0]);
        let (gx, gy) = groups(n);
        let pipeline = &kern.ops["ones"];
        self.run(enc, pipeline, &kern.four, &[&kern.dummy, &kern.dummy, buf, &args], (gx, gy, 1));
    }

    /// Adam over `n` parameters (loss.wgsl's arithmetic is policy::nn::Adam's), with the
    /// constants `step` gives. A non-finite gradient value sets `flag`.
    pub fn adam(
        &self,
        enc: &mut wgpu::CommandEncoder,
        n: usize,
        [params, m, v]: [&wgpu::Buffer; 3],
        grad: &wgpu::Buffer,
        flag: &wgpu::Buffer,
        step: AdamStep,
    ) {
        let AdamStep { b1, b2, eps, step, inv_c2 } = step;
        let kern = &self.kernels;
        let u = self.uniform(&[
            n as u32,
            0,
            0,
            0,
            b1.to_bits(),
            b2.to_bits(),
            eps.to_bits(),
            step.to_bits(),
            inv_c2.to_bits(),
            0,
            0,
            0,
        ]);
        let (gx, gy) = groups(n);
        self.run(enc, &kern.adam, &kern.six_opt, &[params, m, v, grad, flag, &u], (gx, gy, 1));
    }

    /// PPO's policy loss (`value` false) or value loss over a minibatch: the tower's outputs,
    /// the batch's samples and the minibatch's indices in `bufs`; the gradient wrt the outputs
    /// into its `d`, each sample's figures into its `stats`.
    pub fn loss(&self, enc: &mut wgpu::CommandEncoder, value: bool, args: LossArgs, bufs: LossBuffers<'_>) {
        let LossBuffers { out, samples, idx, d, stats } = bufs;
        let kern = &self.kernels;
        let u = self.uniform(&[
            args.n,
            args.dim,
            args.kind,
            args.idx_off,
            args.beta.to_bits(),
            args.inv_n.to_bits(),
            args.clip.to_bits(),
            args.log_std[0].to_bits(),
            args.log_std[1].to_bits(),
            args.dual_clip.to_bits(),
            0,
            0,
        ]);
        let pipeline = if value { &kern.value_loss } else { &kern.policy_loss };
        self.run(enc, pipeline, &kern.six_loss, &[out, samples, idx, d, stats, &u], (args.n.div_ceil(64), 1, 1));
    }

    /// One of SAC's kernels (sac.wgsl) over a batch: the per-transition columns `cols`, and
    /// what the kernel reads (`reads`: up to three buffers) and writes besides (`out`).
    pub fn sac(
        &self,
        enc: &mut wgpu::CommandEncoder,
        entry: &str,
        args: SacArgs,
        reads: &[&wgpu::Buffer],
        out: Option<&wgpu::Buffer>,
        cols: &wgpu::Buffer,
    ) {
        let kern = &self.kernels;
        let pipeline = kern.sac.get(entry).unwrap_or_else(|| panic!("no kernel `{entry}`"));
        let u = self.uniform(&[
            args.n,
            args.cap,
            args.w,
            args.huber as u32,
            args.gamma.to_bits(),
            args.inv.to_bits(),
            args.alpha.to_bits(),
            args.scale[0].to_bits(),
            args.scale[1].to_bits(),
            0,
            0,
            0,
        ]);
        let read = |k: usize| reads.get(k).copied().unwrap_or(&kern.dummy);
        let buffers = [read(0), read(1), read(2), out.unwrap_or(&kern.dummy2), cols, &u];
        self.run(enc, pipeline, &kern.six_loss, &buffers, (args.n.div_ceil(64), 1, 1));
    }
}
