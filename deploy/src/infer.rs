//! The policy tower as the car runs it: the big dense layer's weights in half precision.
//!
//! At batch 1 a SHALLOW tower's time is its first dense layer (11264 × 512 weights: 23 MB of
//! f32 read per frame, 1.4 of its 1.8 ms here; the convolutions take 0.4). DeepRacer's car runs
//! its models in FP16 (the model optimizer's `--data_type FP16`); so does this: dense layers
//! with at least [`HALF_FROM`] weights keep them as f16 (half the memory to stream; subnormal
//! weights, below 6.1e-5, become zero), and each row's dot product converts and multiplies in
//! one pass, in f32: eight lanes at a time with AVX2, FMA and F16C where the CPU has them
//! (`pulp`'s safe runtime dispatch), one at a time otherwise. Every other layer is Paddock's own
//! f32 code. The logits differ from the f32 tower's by the weights' rounding (a relative 2⁻¹¹),
//! which a test bounds.

use half::f16;
use policy::model::{ActorCritic, Choice, Head};
use policy::nn::{Layer, Net, Tape};
use pulp::x86::V3;
use pulp::{f32x8, u16x8, u32x8};

/// Dense layers with at least this many weights run in half precision.
pub const HALF_FROM: usize = 1 << 20;

/// A dense layer with f16 weights (their bits, `out × inp`, row-major) and f32 biases.
#[derive(Debug)]
struct HalfDense {
    inp: usize,
    out: usize,
    w: Vec<u16>,
    b: Vec<f32>,
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

/// `Σ w[i]·x[i]` with `w` in f16 bits, one element at a time.
fn dot_half_scalar(w: &[u16], x: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    let (cw, cx) = (w.chunks_exact(8), x.chunks_exact(8));
    let (rw, rx) = (cw.remainder(), cx.remainder());
    for (a, b) in cw.zip(cx) {
        for k in 0..8 {
            acc[k] += from_half(a[k]) * b[k];
        }
    }
    let mut s: f32 = acc.iter().sum();
    for (a, b) in rw.iter().zip(rx) {
        s += from_half(*a) * b;
    }
    s
}

/// The same, eight lanes at a time (AVX2 + FMA + F16C-level CPUs).
fn dot_half_v3(simd: V3, w: &[u16], x: &[f32]) -> f32 {
    struct Op<'a> {
        s: V3,
        w: &'a [u16],
        x: &'a [f32],
    }
    impl pulp::NullaryFnOnce for Op<'_> {
        type Output = f32;
        #[inline(always)]
        fn call(self) -> f32 {
            let s = self.s;
            let (wc, wr) = pulp::as_arrays::<8, u16>(self.w);
            let (xc, xr) = pulp::as_arrays::<8, f32>(self.x);
            let (sign_m, abs_m, bias, zero) =
                (s.splat_u32x8(0x8000), s.splat_u32x8(0x7fff), s.splat_u32x8(0x1c000), s.splat_u32x8(0));
            // Two accumulators, so that consecutive FMAs do not wait on each other. (Written
            // out in this loop: a helper closure would not inherit the target features.)
            let (mut acc0, mut acc1) = (s.splat_f32x8(0.0), s.splat_f32x8(0.0));
            let mut odd = false;
            for (a, b) in wc.iter().zip(xc) {
                let h: u32x8 = s.convert_u16x8_to_u32x8(bytemuck::cast::<[u16; 8], u16x8>(*a));
                let e = s.and_u32x8(h, abs_m);
                let sign = s.shl_const_u32x8::<16>(s.and_u32x8(h, sign_m));
                let v = s.or_u32x8(sign, s.shl_const_u32x8::<13>(s.wrapping_add_u32x8(e, bias)));
                let wf: f32x8 = bytemuck::cast(s.select_u32x8(s.cmp_eq_u32x8(e, zero), sign, v));
                let xv: f32x8 = bytemuck::cast(*b);
                if odd {
                    acc1 = s.mul_add_f32x8(wf, xv, acc1);
                } else {
                    acc0 = s.mul_add_f32x8(wf, xv, acc0);
                }
                odd = !odd;
            }
            let lanes: [f32; 8] = bytemuck::cast(s.add_f32x8(acc0, acc1));
            let mut total: f32 = lanes.iter().sum();
            for (a, b) in wr.iter().zip(xr) {
                total += from_half(*a) * b;
            }
            total
        }
    }
    simd.vectorize(Op { s: simd, w, x })
}

/// One stage of the car's tower.
#[derive(Debug)]
enum Stage {
    /// Paddock's layers, in f32.
    Exact(Net),
    /// A big dense layer in half precision.
    Half(HalfDense),
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
    Net { layers: out, params }
}

impl CarPolicy {
    /// The car's tower for a model.
    pub fn new(model: &ActorCritic) -> CarPolicy {
        let net = &model.pi;
        let mut stages = Vec::new();
        let mut run: Vec<Layer> = Vec::new();
        for l in &net.layers {
            match *l {
                Layer::Dense { inp, out, offset } if inp * out >= HALF_FROM => {
                    if !run.is_empty() {
                        stages.push(Stage::Exact(subnet(net, &run)));
                        run.clear();
                    }
                    stages.push(Stage::Half(HalfDense {
                        inp,
                        out,
                        w: net.params[offset..offset + inp * out].iter().map(|v| to_half(*v)).collect(),
                        b: net.params[offset + inp * out..offset + inp * out + out].to_vec(),
                    }));
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
                    for (o, y) in s.b.iter_mut().enumerate() {
                        let row = &d.w[o * d.inp..(o + 1) * d.inp];
                        *y = d.b[o]
                            + match self.simd {
                                Some(v3) => dot_half_v3(v3, row, &s.a),
                                None => dot_half_scalar(row, &s.a),
                            };
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
        let car = CarPolicy::new(&m);
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
        // Both dot products agree, and the scalar one is the conversion's reference.
        let w: Vec<u16> = (0..1003).map(|i| to_half((i as f32 - 500.0) * 0.013)).collect();
        let x: Vec<f32> = (0..1003).map(|i| (i % 17) as f32 - 8.0).collect();
        let scalar = dot_half_scalar(&w, &x);
        let exact: f32 = w.iter().zip(&x).map(|(a, b)| f16::from_bits(*a).to_f32() * b).sum();
        assert!((scalar - exact).abs() < 1e-2, "{scalar} vs {exact}");
        if let Some(v3) = V3::try_new() {
            assert!((dot_half_v3(v3, &w, &x) - scalar).abs() < 1e-2);
        }
        assert_eq!((to_half(1e-6), to_half(-1e-6), from_half(to_half(0.5))), (0, 0x8000, 0.5));
        // A small network has no half-precision stage: exactly Paddock's own forward pass.
        let sv = ModelMetadata::default_state_vector();
        let m = ActorCritic::new(&sv, 20, &mut rand_chacha::ChaCha8Rng::seed_from_u64(1));
        let car = CarPolicy::new(&m);
        let obs = vec![0.3f32; 20];
        m.pi.forward(&obs, 1, &mut tape, faer::Par::Seq);
        assert_eq!(car.logits(&obs, &mut s), tape.output());
    }
}
