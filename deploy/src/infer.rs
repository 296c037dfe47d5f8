//! The policy tower as the car runs it: the big dense layer's weights in half precision.
//!
//! At batch 1 a SHALLOW tower's time is its first dense layer (11264 × 512 weights: 23 MB of
//! f32 read per frame, 1.4 of its 1.8 ms here; the convolutions take 0.4). DeepRacer's car runs
//! its models in FP16 (the model optimizer's `--data_type FP16`); so does this: dense layers
//! with at least [`HALF_FROM`] weights keep them as f16 (half the memory to stream; subnormal
//! weights, below 6.1e-5, become zero), or, with `car.toml`'s `precision = "int8"`, in 8 bits
//! with one scale per output (half the bytes again). At batch 1 the layer is bound by reading
//! its weights from memory: they are laid out by blocks of 64 outputs, input after input, so
//! that one sequential stream feeds 64 outputs held in registers (`y += x[i] · W[i, block]`),
//! converting and multiplying in one pass in f32: eight lanes at a time with AVX2 and FMA where
//! the CPU has them (`pulp`'s safe runtime dispatch), one at a time otherwise. (Skipping the
//! rows of zero inputs — a ReLU's output is half zeros — read fewer bytes but broke the
//! prefetcher's stream: slower with cold caches, measured.) Every other layer is Paddock's own f32 code. The
//! logits differ from the f32 tower's by the weights' rounding (a relative 2⁻¹¹) and the order
//! of the sums, which a test bounds.

use half::f16;
use policy::car::Precision;
use policy::model::{ActorCritic, Choice, Head};
use policy::nn::{Layer, Net, Tape};
use pulp::x86::V3;
use pulp::{f32x8, i8x16, i16x8, i32x8, u32x8};

/// Dense layers with at least this many weights run in half precision.
pub const HALF_FROM: usize = 1 << 20;

/// Outputs per block of the half-precision layer: eight accumulators of eight lanes.
const BLOCK: usize = 64;

/// `2¹¹²`: an f16's exponent bias (15) against an f32's (127).
const REBIAS: f32 = 5.192_297e33;

/// A dense layer with f16 weights and f32 biases, laid out for a batch of one.
///
/// The weights are stored by blocks of [`BLOCK`] outputs, and within a block by input:
/// weight (input `i`, output `b·BLOCK + k`) is at `(b·inp + i)·BLOCK + k`, the last block
/// padded with zeros. The layer runs as `y += x[i] · W[i, block]`, input after input, with a
/// block's outputs held in registers.
#[derive(Debug)]
struct HalfDense {
    inp: usize,
    out: usize,
    w: Vec<u16>,
    b: Vec<f32>,
}

impl HalfDense {
    /// From Paddock's dense layout (`out × inp` weights, a row per output, then `out` biases).
    fn new(inp: usize, out: usize, params: &[f32]) -> HalfDense {
        let blocks = out.div_ceil(BLOCK);
        let mut w = vec![0u16; blocks * inp * BLOCK];
        // Written in order; the 64 rows read stay in L1 across consecutive inputs.
        for (n, v) in w.iter_mut().enumerate() {
            let (blk, i, k) = (n / (inp * BLOCK), n / BLOCK % inp, n % BLOCK);
            let o = blk * BLOCK + k;
            if o < out {
                *v = to_half(params[o * inp + i]);
            }
        }
        HalfDense { inp, out, w, b: params[inp * out..inp * out + out].to_vec() }
    }
}

/// A dense layer with 8-bit weights, one scale per output, and f32 biases; the same blocked
/// layout as [`HalfDense`], one 64-byte line (aligned) per input and block.
#[derive(Debug)]
struct Int8Dense {
    inp: usize,
    out: usize,
    q: Vec<Line>,
    /// Per output (padded to whole blocks): the weight of one step.
    scale: Vec<f32>,
    b: Vec<f32>,
}

/// One input's weights for one block of outputs.
#[derive(Clone, Copy, Debug)]
#[repr(C, align(64))]
struct Line([i8; BLOCK]);

impl Int8Dense {
    /// From Paddock's dense layout: `q = round(w / scale)` with `scale = max |w| / 127` per output.
    fn new(inp: usize, out: usize, params: &[f32]) -> Int8Dense {
        let blocks = out.div_ceil(BLOCK);
        let mut scale = vec![0.0f32; blocks * BLOCK];
        for (o, s) in scale.iter_mut().enumerate().take(out) {
            let m = params[o * inp..(o + 1) * inp].iter().fold(0.0f32, |m, w| m.max(w.abs()));
            *s = m / 127.0;
        }
        let mut q = vec![Line([0; BLOCK]); blocks * inp];
        for (n, line) in q.iter_mut().enumerate() {
            let (blk, i) = (n / inp, n % inp);
            for (k, v) in line.0.iter_mut().enumerate() {
                let o = blk * BLOCK + k;
                if o < out && scale[o] > 0.0 {
                    *v = (params[o * inp + i] / scale[o]).round().clamp(-127.0, 127.0) as i8;
                }
            }
        }
        Int8Dense { inp, out, q, scale, b: params[inp * out..inp * out + out].to_vec() }
    }
}

/// The 8-bit layer for the input `x`, one weight at a time.
fn int8_dense_scalar(d: &Int8Dense, x: &[f32], y: &mut [f32]) {
    for (blk, (lines, yb)) in d.q.chunks_exact(d.inp).zip(y.chunks_mut(BLOCK)).enumerate() {
        let mut acc = [0.0f32; BLOCK];
        for (line, x) in lines.iter().zip(x) {
            for (a, w) in acc.iter_mut().zip(&line.0) {
                *a += *w as f32 * x;
            }
        }
        for (k, v) in yb.iter_mut().enumerate() {
            let o = blk * BLOCK + k;
            *v = d.b[o] + d.scale[o] * acc[k];
        }
    }
}

/// The same, eight lanes at a time: sign-extend eight bytes, convert, multiply-add.
fn int8_dense_v3(simd: V3, d: &Int8Dense, x: &[f32], y: &mut [f32]) {
    struct Op<'a> {
        s: V3,
        d: &'a Int8Dense,
        x: &'a [f32],
        y: &'a mut [f32],
    }
    impl pulp::NullaryFnOnce for Op<'_> {
        type Output = ();
        #[inline(always)]
        fn call(self) {
            let s = self.s;
            let d = self.d;
            for (blk, (lines, yb)) in d.q.chunks_exact(d.inp).zip(self.y.chunks_mut(BLOCK)).enumerate() {
                let mut acc = [s.splat_f32x8(0.0); BLOCK / 8];
                for (line, &x) in lines.iter().zip(self.x) {
                    let parts: &[[i8; 8]; BLOCK / 8] = bytemuck::cast_ref(&line.0);
                    let xv = s.splat_f32x8(x);
                    for (a, p) in acc.iter_mut().zip(parts) {
                        let mut b = [0i8; 16];
                        b[..8].copy_from_slice(p);
                        let w =
                            s.convert_i32x8_to_f32x8(s.convert_i8x16_to_i32x8(bytemuck::cast::<[i8; 16], i8x16>(b)));
                        *a = s.mul_add_f32x8(w, xv, *a);
                    }
                }
                let lanes: [f32; BLOCK] = bytemuck::cast(acc);
                for (k, v) in yb.iter_mut().enumerate() {
                    let o = blk * BLOCK + k;
                    *v = d.b[o] + d.scale[o] * lanes[k];
                }
            }
        }
    }
    simd.vectorize(Op { s: simd, d, x, y })
}

/// f32 to f16 bits, subnormals flushed to (signed) zero.
fn to_half(x: f32) -> u16 {
    let h = f16::from_f32(x).to_bits();
    if h & 0x7c00 == 0 { h & 0x8000 } else { h }
}

/// f16 bits (no subnormals, no infinities) to f32.
#[inline(always)]
fn from_half(h: u16) -> f32 {
    let h = h as u32;
    let e = h & 0x7fff;
    f32::from_bits(if e == 0 { (h & 0x8000) << 16 } else { ((h & 0x8000) << 16) | ((e + 0x1c000) << 13) })
}

/// The layer's outputs for the input `x`, one weight at a time.
fn half_dense_scalar(d: &HalfDense, x: &[f32], y: &mut [f32]) {
    for (blk, (wb, yb)) in d.w.chunks_exact(d.inp * BLOCK).zip(y.chunks_mut(BLOCK)).enumerate() {
        let mut acc = [0.0f32; BLOCK];
        for (row, x) in wb.chunks_exact(BLOCK).zip(x) {
            for (a, w) in acc.iter_mut().zip(row) {
                *a += from_half(*w) * x;
            }
        }
        for (k, v) in yb.iter_mut().enumerate() {
            *v = d.b[blk * BLOCK + k] + acc[k];
        }
    }
}

/// The same, eight lanes at a time (AVX2 + FMA-level CPUs, `pulp`'s safe dispatch).
///
/// An f16 becomes an f32 in three integer operations and a multiply, exactly: sign-extend
/// the 16 bits, shift them left by 13 (the exponent and mantissa land where an f32's do), keep
/// the sign and those 15 bits, and multiply by 2¹¹² to move the exponent from f16's bias to
/// f32's. (Zero stays zero; there are no subnormals, [`to_half`] flushes them.)
fn half_dense_v3(simd: V3, d: &HalfDense, x: &[f32], y: &mut [f32]) {
    struct Op<'a> {
        s: V3,
        d: &'a HalfDense,
        x: &'a [f32],
        y: &'a mut [f32],
    }
    impl pulp::NullaryFnOnce for Op<'_> {
        type Output = ();
        #[inline(always)]
        fn call(self) {
            let s = self.s;
            let (mask, rebias) = (s.splat_u32x8(0x8fff_e000), s.splat_f32x8(REBIAS));
            let d = self.d;
            for (blk, (wb, yb)) in d.w.chunks_exact(d.inp * BLOCK).zip(self.y.chunks_mut(BLOCK)).enumerate() {
                let (rows, _) = pulp::as_arrays::<BLOCK, u16>(wb);
                let mut acc = [s.splat_f32x8(0.0); BLOCK / 8];
                for (row, &x) in rows.iter().zip(self.x) {
                    let row: &[[u16; 8]; BLOCK / 8] = bytemuck::cast_ref(row);
                    let xv = s.splat_f32x8(x);
                    for (a, w8) in acc.iter_mut().zip(row) {
                        let h: i32x8 = s.convert_i16x8_to_i32x8(bytemuck::cast::<[u16; 8], i16x8>(*w8));
                        let bits = s.and_u32x8(s.shl_const_u32x8::<13>(bytemuck::cast(h)), mask);
                        let wf = s.mul_f32x8(bytemuck::cast::<u32x8, f32x8>(bits), rebias);
                        *a = s.mul_add_f32x8(wf, xv, *a);
                    }
                }
                let lanes: [f32; BLOCK] = bytemuck::cast(acc);
                for (k, v) in yb.iter_mut().enumerate() {
                    *v = d.b[blk * BLOCK + k] + lanes[k];
                }
            }
        }
    }
    simd.vectorize(Op { s: simd, d, x, y })
}

/// One stage of the car's tower.
#[derive(Debug)]
enum Stage {
    /// Paddock's layers, in f32.
    Exact(Net),
    /// A big dense layer in half precision.
    Half(HalfDense),
    /// A big dense layer in 8 bits.
    Int8(Int8Dense),
}

/// The policy tower for the car.
#[derive(Debug)]
pub struct CarPolicy {
    stages: Vec<Stage>,
    head: Head,
    simd: Option<V3>,
}

/// Buffers kept between frames (one per driving thread).
#[derive(Default)]
pub struct Scratch {
    /// One tape per f32 stage (a tape shared by two networks would resize its buffers twice
    /// a frame).
    tapes: Vec<Tape>,
    a: Vec<f32>,
    b: Vec<f32>,
}

/// The layers `range` of `net` as a network of their own (parameters copied, offsets re-based).
fn subnet(net: &Net, layers: &[Layer]) -> Net {
    let mut params = Vec::new();
    let out = layers
        .iter()
        .map(|l| match *l {
            Layer::Dense { inp, out, offset } => {
                let n = inp * out + out;
                let at = params.len();
                params.extend_from_slice(&net.params[offset..offset + n]);
                Layer::Dense { inp, out, offset: at }
            }
            Layer::Conv2d { input, filters, kernel, stride, offset } => {
                let n = filters * kernel * kernel * input[2] + filters;
                let at = params.len();
                params.extend_from_slice(&net.params[offset..offset + n]);
                Layer::Conv2d { input, filters, kernel, stride, offset: at }
            }
            ref other => other.clone(),
        })
        .collect();
    Net { layers: out, params, inputs: Vec::new() }
}

impl CarPolicy {
    /// The car's tower for a model, its big dense layers held in `precision`.
    pub fn new(model: &ActorCritic, precision: Precision) -> CarPolicy {
        let net = &model.pi;
        let mut stages = Vec::new();
        let mut run: Vec<Layer> = Vec::new();
        // A camera + LiDAR network: its embedders, in f32, as a first stage that hands over
        // their concatenated outputs; the middleware and head staged as a camera's are.
        let trunk = net.sections().last().expect("the rest").start;
        if !net.inputs.is_empty() {
            let mut embedders = subnet(net, &net.layers[..trunk]);
            embedders.inputs = net.inputs.clone();
            stages.push(Stage::Exact(embedders));
        }
        for l in &net.layers[trunk..] {
            match *l {
                Layer::Dense { inp, out, offset } if inp * out >= HALF_FROM => {
                    if !run.is_empty() {
                        stages.push(Stage::Exact(subnet(net, &run)));
                        run.clear();
                    }
                    let p = &net.params[offset..offset + inp * out + out];
                    stages.push(match precision {
                        Precision::F16 => Stage::Half(HalfDense::new(inp, out, p)),
                        Precision::Int8 => Stage::Int8(Int8Dense::new(inp, out, p)),
                    });
                }
                _ => run.push(l.clone()),
            }
        }
        if !run.is_empty() {
            stages.push(Stage::Exact(subnet(net, &run)));
        }
        CarPolicy { stages, head: model.head.clone(), simd: V3::try_new() }
    }

    /// The tower's outputs (logits, or the Gaussian's means) for one observation.
    pub fn logits<'s>(&self, obs: &[f32], s: &'s mut Scratch) -> &'s [f32] {
        s.a.clear();
        s.a.extend_from_slice(obs);
        s.tapes.resize_with(self.stages.len(), Tape::default);
        for (i, stage) in self.stages.iter().enumerate() {
            match stage {
                Stage::Exact(net) => {
                    net.forward(&s.a, 1, &mut s.tapes[i], faer::Par::Seq);
                    s.b.clear();
                    s.b.extend_from_slice(s.tapes[i].output());
                }
                Stage::Half(d) => {
                    s.b.clear();
                    s.b.resize(d.out, 0.0);
                    match self.simd {
                        Some(v3) => half_dense_v3(v3, d, &s.a, &mut s.b),
                        None => half_dense_scalar(d, &s.a, &mut s.b),
                    }
                }
                Stage::Int8(d) => {
                    s.b.clear();
                    s.b.resize(d.out, 0.0);
                    match self.simd {
                        Some(v3) => int8_dense_v3(v3, d, &s.a, &mut s.b),
                        None => int8_dense_scalar(d, &s.a, &mut s.b),
                    }
                }
            }
            std::mem::swap(&mut s.a, &mut s.b);
        }
        &s.a
    }

    /// The most likely choice: the argmax class, or the means.
    pub fn mode(&self, obs: &[f32], s: &mut Scratch) -> Choice {
        let z = self.logits(obs, s);
        match self.head {
            Head::Categorical(_) => Choice::Discrete(
                z.iter().enumerate().fold((0, f32::MIN), |b, (i, &x)| if x > b.1 { (i, x) } else { b }).0,
            ),
            Head::Gaussian { .. } => Choice::Continuous([z[0], z[1]]),
            // SAC: the simulator's deterministic action, tanh of the means. (DeepRacer's
            // navigation node clips the pre-tanh means instead.)
            Head::Squashed { .. } => Choice::Continuous([z[0].tanh(), z[1].tanh()]),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use policy::ModelMetadata;
    use rand::SeedableRng;

    #[test]
    fn the_half_precision_tower_stays_within_the_weights_rounding() {
        let meta = ModelMetadata::default_camera();
        let m = ActorCritic::new(&meta, 120 * 160, &mut rand_chacha::ChaCha8Rng::seed_from_u64(3));
        let car = CarPolicy::new(&m, Precision::F16);
        assert!(car.stages.iter().any(|s| matches!(s, Stage::Half(_))), "the big dense layer runs in f16");
        let mut s = Scratch::default();
        let mut tape = Tape::default();
        for seed in 0..4u32 {
            let obs: Vec<f32> = (0..120 * 160u32).map(|i| ((i * (seed + 3) + i / 160 * 7) % 256) as f32).collect();
            m.pi.forward(&obs, 1, &mut tape, faer::Par::Seq);
            let exact = tape.output().to_vec();
            let got = car.logits(&obs, &mut s).to_vec();
            let scale = exact.iter().fold(0.0f32, |a, v| a.max(v.abs()));
            for (a, b) in got.iter().zip(&exact) {
                assert!((a - b).abs() <= 2e-3 * scale, "{got:?} vs {exact:?}");
            }
        }
        // Both kernels agree with the f32 product of the rounded weights, with an output count
        // that leaves the last block part-filled.
        let (inp, out) = (1003, 150);
        let params: Vec<f32> = (0..inp * out + out).map(|i| ((i * 37 % 1001) as f32 - 500.0) * 0.0013).collect();
        let d = HalfDense::new(inp, out, &params);
        let x: Vec<f32> = (0..inp).map(|i| if i % 3 == 0 { 0.0 } else { (i % 17) as f32 - 8.0 }).collect();
        let mut y = vec![0.0; out];
        half_dense_scalar(&d, &x, &mut y);
        let mut y3 = vec![0.0; out];
        if let Some(v3) = V3::try_new() {
            half_dense_v3(v3, &d, &x, &mut y3);
        }
        for o in 0..out {
            let terms: Vec<f64> = (0..inp).map(|i| f16::from_f32(params[o * inp + i]).to_f64() * x[i] as f64).collect();
            let exact = (params[inp * out + o] as f64 + terms.iter().sum::<f64>()) as f32;
            let tol = 1e-6 * terms.iter().map(|t| t.abs()).sum::<f64>() as f32 + 1e-5;
            assert!((y[o] - exact).abs() <= tol, "output {o}: {} vs {exact}", y[o]);
            if V3::try_new().is_some() {
                assert!((y3[o] - exact).abs() <= tol, "output {o}: {} vs {exact}", y3[o]);
            }
        }
        assert_eq!((to_half(1e-6), to_half(-1e-6), from_half(to_half(0.5))), (0, 0x8000, 0.5));
        // A small network has no half-precision stage: exactly Paddock's own forward pass.
        let sv = ModelMetadata::default_state_vector();
        let m = ActorCritic::new(&sv, 20, &mut rand_chacha::ChaCha8Rng::seed_from_u64(1));
        let car = CarPolicy::new(&m, Precision::F16);
        let obs = vec![0.3f32; 20];
        m.pi.forward(&obs, 1, &mut tape, faer::Par::Seq);
        assert_eq!(car.logits(&obs, &mut s), tape.output());
    }

    /// Issue 32: a SAC model drives the simulator's action, tanh of the means.
    #[test]
    fn a_sac_model_drives_the_simulators_action_tanh_of_the_means() {
        let meta = ModelMetadata::parse(
            r#"{"action_space":{"steering_angle":{"low":-30,"high":30},"speed":{"low":1,"high":2}},
                "sensor":["FRONT_FACING_CAMERA"],"training_algorithm":"sac","action_space_type":"continuous"}"#,
            "m.json",
        )
        .unwrap();
        let m = ActorCritic::new(&meta, 120 * 160, &mut rand_chacha::ChaCha8Rng::seed_from_u64(5));
        let obs: Vec<f32> = (0..120 * 160u32).map(|i| ((i * 2654435761) >> 24) as f32).collect();
        let (mut s, mut tape) = (Scratch::default(), Tape::default());
        let sim = m.mode(&obs, &mut tape);
        let Choice::Continuous(want) = sim else { panic!("a continuous choice") };
        m.pi.forward(&obs, 1, &mut tape, faer::Par::Seq);
        assert_eq!(want, [tape.output()[0].tanh(), tape.output()[1].tanh()], "the simulator: tanh of the means");
        let car = CarPolicy::new(&m, Precision::F16);
        let Choice::Continuous(got) = car.mode(&obs, &mut s) else { panic!("a continuous choice") };
        for k in 0..2 {
            assert!((got[k] - want[k]).abs() < 2e-2, "action {k}: car {} simulator {}", got[k], want[k]);
        }
    }

    /// Issue 31: a camera and LiDAR tower runs its embedders then the half-precision middleware.
    #[test]
    fn a_camera_and_lidar_tower_runs_its_embedders_then_the_half_precision_middleware() {
        let meta = ModelMetadata::parse(
            r#"{"action_space":[{"steering_angle":-20,"speed":1},{"steering_angle":20,"speed":1}],
                "sensor":["STEREO_CAMERAS","LIDAR"],"version":"5"}"#,
            "m.json",
        )
        .unwrap();
        let size = 2 * 120 * 160 + 64;
        let m = ActorCritic::new(&meta, size, &mut rand_chacha::ChaCha8Rng::seed_from_u64(4));
        for precision in [Precision::F16, Precision::Int8] {
            let car = CarPolicy::new(&m, precision);
            assert!(matches!(&car.stages[0], Stage::Exact(n) if n.inputs.len() == 2), "the embedders first");
            assert!(matches!(car.stages[1], Stage::Half(_) | Stage::Int8(_)), "then the merged 11,520 → 512 layer");
            let (mut s, mut tape) = (Scratch::default(), Tape::default());
            // LiDAR first (LIDAR < STEREO_CAMERAS): ranges, then the two channels' pixels.
            let obs: Vec<f32> = (0..size as u32)
                .map(|i| if i < 64 { 0.15 + (i % 7) as f32 * 0.1 } else { ((i * 7 + i / 320 * 3) % 256) as f32 })
                .collect();
            m.pi.forward(&obs, 1, &mut tape, faer::Par::Seq);
            let exact = tape.output().to_vec();
            let got = car.logits(&obs, &mut s).to_vec();
            let scale = exact.iter().fold(0.0f32, |a, v| a.max(v.abs()));
            let tol = if precision == Precision::F16 { 2e-3 } else { 2e-2 };
            for (a, b) in got.iter().zip(&exact) {
                assert!((a - b).abs() <= tol * scale, "{precision:?}: {got:?} vs {exact:?}");
            }
        }
    }

    #[test]
    fn the_8_bit_tower_stays_within_its_quantisation_and_picks_the_same_actions() {
        // The kernels: exactly the quantised weights times their scales.
        let (inp, out) = (1003, 150);
        let params: Vec<f32> = (0..inp * out + out).map(|i| ((i * 37 % 1001) as f32 - 500.0) * 0.0013).collect();
        let d = Int8Dense::new(inp, out, &params);
        let x: Vec<f32> = (0..inp).map(|i| if i % 3 == 0 { 0.0 } else { (i % 17) as f32 - 8.0 }).collect();
        let mut y = vec![0.0; out];
        int8_dense_scalar(&d, &x, &mut y);
        let mut y3 = vec![0.0; out];
        if let Some(v3) = V3::try_new() {
            int8_dense_v3(v3, &d, &x, &mut y3);
        }
        for o in 0..out {
            let q = |i: usize| d.q[(o / BLOCK) * inp + i].0[o % BLOCK] as f64;
            let terms: Vec<f64> = (0..inp).map(|i| q(i) * x[i] as f64).collect();
            let exact = (params[inp * out + o] as f64 + d.scale[o] as f64 * terms.iter().sum::<f64>()) as f32;
            // Each weight within half a step of the original.
            let step = d.scale[o] as f64;
            assert!((0..inp).all(|i| (q(i) * step - params[o * inp + i] as f64).abs() <= step * 0.5001));
            assert!((y[o] - exact).abs() <= 1e-4 * exact.abs().max(1.0), "output {o}: {} vs {exact}", y[o]);
            if V3::try_new().is_some() {
                assert!((y3[o] - exact).abs() <= 1e-4 * exact.abs().max(1.0), "output {o}: {} vs {exact}", y3[o]);
            }
        }
        // The tower: logits within 2 % of their scale; the same action wherever the exact
        // tower's choice is clear by more than that.
        let meta = ModelMetadata::default_camera();
        let m = ActorCritic::new(&meta, 120 * 160, &mut rand_chacha::ChaCha8Rng::seed_from_u64(3));
        let car = CarPolicy::new(&m, Precision::Int8);
        assert!(car.stages.iter().any(|s| matches!(s, Stage::Int8(_))));
        let (mut s, mut tape) = (Scratch::default(), Tape::default());
        for seed in 0..8u32 {
            let obs: Vec<f32> = (0..120 * 160u32).map(|i| ((i * (seed + 3) + i / 160 * 7) % 256) as f32).collect();
            m.pi.forward(&obs, 1, &mut tape, faer::Par::Seq);
            let exact = tape.output().to_vec();
            let got = car.logits(&obs, &mut s).to_vec();
            let scale = exact.iter().fold(0.0f32, |a, v| a.max(v.abs()));
            for (a, b) in got.iter().zip(&exact) {
                assert!((a - b).abs() <= 2e-2 * scale, "{got:?} vs {exact:?}");
            }
            let mut sorted = exact.clone();
            sorted.sort_by(|a, b| b.total_cmp(a));
            if sorted[0] - sorted[1] > 4e-2 * scale {
                let argmax = |v: &[f32]| v.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)).unwrap().0;
                assert_eq!(argmax(&got), argmax(&exact));
            }
        }
    }
}
