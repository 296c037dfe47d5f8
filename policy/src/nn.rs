//! A small neural-network core on faer: dense, conv2d (im2col + GEMM), ReLU and input
//! scaling, forward over a batch and backward, with all parameters in one flat vector.
//!
//! Activations are row-major `batch × features`; images are NHWC (as DeepRacer's
//! channels-last Keras layers), so a conv output is already "flattened" for the dense
//! layer that follows. Every GEMM goes through faer ([`gemm`]).

use faer::{Accum, MatMut, MatRef, Par};
use rand::Rng;
use rand_distr::{Distribution, Normal};

/// One matrix product's sizes and storage: `dst (m×n) = op(a) (m×k) · op(b) (k×n)`, all
/// row-major; `a_t`: `a` is stored as `k×m`; `b_t`: `b` is stored as `n×k`; `add`: the
/// product is added to `dst` rather than written over it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Product {
    /// Rows of the result.
    pub m: usize,
    /// Columns of the result.
    pub n: usize,
    /// The inner dimension.
    pub k: usize,
    /// `a` is stored transposed (`k×m`).
    pub a_t: bool,
    /// `b` is stored transposed (`n×k`).
    pub b_t: bool,
    /// Add into `dst` (else replace it).
    pub add: bool,
}

impl Product {
    /// `m×k · k×n`, both operands as they are, written over `dst`.
    pub fn new(m: usize, n: usize, k: usize) -> Product {
        Product { m, n, k, a_t: false, b_t: false, add: false }
    }

    /// `a` is stored transposed.
    pub fn a_t(self) -> Product {
        Product { a_t: true, ..self }
    }

    /// `b` is stored transposed.
    pub fn b_t(self) -> Product {
        Product { b_t: true, ..self }
    }

    /// Added into `dst`.
    pub fn add(self) -> Product {
        Product { add: true, ..self }
    }
}

/// `dst = op(a) · op(b)` (+ `dst`) as `p` describes.
pub fn gemm(dst: &mut [f32], a: &[f32], b: &[f32], p: Product, par: Par) {
    let Product { m, n, k, a_t, b_t, add } = p;
    debug_assert_eq!(dst.len(), m * n);
    let lhs =
        if a_t { MatRef::from_row_major_slice(a, k, m).transpose() } else { MatRef::from_row_major_slice(a, m, k) };
    let rhs =
        if b_t { MatRef::from_row_major_slice(b, n, k).transpose() } else { MatRef::from_row_major_slice(b, k, n) };
    let out = MatMut::from_row_major_slice_mut(dst, m, n);
    let beta = if add { Accum::Add } else { Accum::Replace };
    faer::linalg::matmul::matmul(out, beta, lhs, rhs, 1.0f32, par);
}

/// The precision of a network's matrix products in a pass.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Precision {
    /// f32 operands and sums (faer).
    #[default]
    F32,
    /// Operands rounded to bf16, f32 sums, on a CPU with AVX-512 BF16 (twice the multiply-adds
    /// a cycle); where the CPU lacks it, f32 (a caller that asks for it checks
    /// [`Precision::bf16_available`] first and says so).
    Bf16,
}

impl Precision {
    /// Whether this CPU makes bf16 products.
    pub fn bf16_available() -> bool {
        #[cfg(target_arch = "x86_64")]
        return crate::bf16::available();
        #[cfg(not(target_arch = "x86_64"))]
        return false;
    }
}

/// [`gemm`] in `precision`.
pub fn gemm_in(precision: Precision, dst: &mut [f32], a: &[f32], b: &[f32], p: Product, par: Par) {
    #[cfg(target_arch = "x86_64")]
    if precision == Precision::Bf16 && crate::bf16::available() {
        return crate::bf16::gemm(dst, a, b, p, par);
    }
    let _ = precision;
    gemm(dst, a, b, p, par)
}

/// Whether a dense layer's forward pass over `batch` samples is made as `outᵀ (out × batch)
/// = b + W · xᵀ` and then turned into `out`, rather than as `out = b + x · Wᵀ`: over more
/// than one sample. faer makes the product in that orientation faster for the camera
/// networks' big layer (11,264 → 512): 1.4-1.8× at a minibatch of 64, about 2× at the 2-16
/// samples of a sim agent's environments, the same at 1. The turn is over the small output
/// only.
pub fn turns_dense_forward(batch: usize) -> bool {
    batch > 1
}

/// One layer of a sequential network.
#[derive(Clone, Debug, PartialEq)]
pub enum Layer {
    /// Multiply every input by a constant (DeepRacer's in-graph `/255`).
    Scale {
        /// Features in (= out).
        size: usize,
        /// The factor.
        factor: f32,
    },
    /// `y = x Wᵀ + b`; `W` is `out × in`.
    Dense {
        /// Inputs.
        inp: usize,
        /// Outputs.
        out: usize,
        /// Offset of `W` in the parameter vector (then `b`, `out` values).
        offset: usize,
    },
    /// 2-D convolution, padding `valid`, NHWC; weights `filters × (k·k·c)` in (ky, kx, c) order.
    Conv2d {
        /// Input height, width, channels.
        input: [usize; 3],
        /// Filters (output channels).
        filters: usize,
        /// Kernel side.
        kernel: usize,
        /// Stride.
        stride: usize,
        /// Offset of the weights (then `filters` biases).
        offset: usize,
    },
    /// `max(0, x)`.
    Relu {
        /// Features.
        size: usize,
    },
}

impl Layer {
    /// Features per sample going in.
    pub fn in_size(&self) -> usize {
        match *self {
            Layer::Scale { size, .. } | Layer::Relu { size } => size,
            Layer::Dense { inp, .. } => inp,
            Layer::Conv2d { input: [h, w, c], .. } => h * w * c,
        }
    }

    /// Features per sample coming out.
    pub fn out_size(&self) -> usize {
        match *self {
            Layer::Scale { size, .. } | Layer::Relu { size } => size,
            Layer::Dense { out, .. } => out,
            Layer::Conv2d { .. } => {
                let [oh, ow] = self.conv_out();
                oh * ow * self.filters()
            }
        }
    }

    fn filters(&self) -> usize {
        match *self {
            Layer::Conv2d { filters, .. } => filters,
            _ => 0,
        }
    }

    /// Output height and width of a convolution.
    pub fn conv_out(&self) -> [usize; 2] {
        match *self {
            Layer::Conv2d { input: [h, w, _], kernel, stride, .. } => {
                [(h - kernel) / stride + 1, (w - kernel) / stride + 1]
            }
            _ => [0, 0],
        }
    }

    /// Samples a conv layer unfolds and multiplies at a time, in the forward and the
    /// backward pass: as many as fit 512 KiB of unfolded input, at least one, so the
    /// unfolded chunk stays in L2; 1 for other layers.
    pub fn conv_chunk(&self) -> usize {
        match *self {
            Layer::Conv2d { filters, .. } => {
                let [oh, ow] = self.conv_out();
                let kkc = self.param_count() / filters - 1;
                (CONV_CHUNK_BYTES / (oh * ow * kkc * std::mem::size_of::<f32>())).max(1)
            }
            _ => 1,
        }
    }

    /// Parameters this layer owns.
    pub fn param_count(&self) -> usize {
        match *self {
            Layer::Dense { inp, out, .. } => inp * out + out,
            Layer::Conv2d { input: [_, _, c], filters, kernel, .. } => filters * kernel * kernel * c + filters,
            _ => 0,
        }
    }
}

/// A network: layers and one flat parameter vector. Sequential from one input, or, for
/// several inputs (DeepRacer's camera and LiDAR), one embedder per input whose outputs are
/// concatenated, in input order, into the rest of the layers (COACH's `merger`).
#[derive(Clone, Debug, PartialEq)]
pub struct Net {
    /// The layers, in order: each input's embedder in turn (see `inputs`), then the layers
    /// that take their concatenated outputs.
    pub layers: Vec<Layer>,
    /// All parameters.
    pub params: Vec<f32>,
    /// The inputs of a multi-input network, in the order their values sit in a sample and
    /// their embedders' outputs are concatenated; empty for a sequential network.
    pub inputs: Vec<Embedder>,
}

/// One input of a multi-input network and its embedder.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Embedder {
    /// The input's name (DeepRacer's sensor name: the graph's placeholder).
    pub name: String,
    /// The input's shape.
    pub shape: InputShape,
    /// How many of the network's layers, from where the previous embedder's end, are this
    /// input's embedder (0: the input goes into the concatenation as it is).
    pub layers: usize,
}

impl InputShape {
    /// Values per sample.
    pub fn size(self) -> usize {
        match self {
            InputShape::Flat(n) => n,
            InputShape::Image(h, w, c) => h * w * c,
        }
    }
}

/// What a forward pass keeps for the backward pass, and the backward pass's scratch
/// buffers. Reuse one tape across calls: its buffers keep their memory, so a training step
/// allocates nothing.
#[derive(Default, Debug)]
pub struct Tape {
    /// Input of every layer, then the final output (a multi-input network: each embedder's
    /// input, layers' inputs and output in turn, then the concatenation and the rest).
    acts: Vec<Vec<f32>>,
    /// The conv layers' scratch, one per thread's share of the samples.
    conv: Vec<ConvScratch>,
    batch: usize,
    d: Vec<f32>,
    d_prev: Vec<f32>,
    /// Buffers handed back by [`Tape::take_back`], swapped in for the inputs a backward pass
    /// hands out as [`Factors`] (no copy, and no 3 MB allocation per minibatch).
    spare: Vec<Vec<f32>>,
    /// A dense layer's output as `out × batch`, before it is turned into `batch × out`.
    out_t: Vec<f32>,
    /// A multi-input network's gradient wrt its concatenated embeddings.
    merged: Vec<f32>,
    /// The precision of the passes' matrix products (f32 unless a learner asks otherwise).
    pub precision: Precision,
}

impl Tape {
    /// The network's output of the last forward pass (`batch × out`).
    pub fn output(&self) -> &[f32] {
        self.acts.last().map(|v| v.as_slice()).unwrap_or(&[])
    }

    /// Give back the buffers of factors this tape's backward pass handed out, for the next
    /// pass to reuse.
    pub fn take_back(&mut self, factors: Vec<Factors>) {
        self.spare.extend(factors.into_iter().map(|f| f.x));
    }
}

/// Building blocks for [`Net::new`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum LayerSpec {
    /// Scale inputs by a factor.
    Scale(f32),
    /// Dense layer with this many outputs.
    Dense(usize),
    /// Conv layer: (filters, kernel, stride).
    Conv(usize, usize, usize),
    /// ReLU.
    Relu,
}

/// Input shape: a flat vector, or an NHWC image.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum InputShape {
    /// `n` features.
    Flat(usize),
    /// Height, width, channels.
    Image(usize, usize, usize),
}

/// Append the layers of `specs` on an input of `input` to `layers`, their parameters from
/// `offset` on; returns the features per sample coming out.
fn push_layers(input: InputShape, specs: &[LayerSpec], layers: &mut Vec<Layer>, offset: &mut usize) -> usize {
    let (mut flat, mut image) = match input {
        InputShape::Flat(n) => (n, None),
        InputShape::Image(h, w, c) => (h * w * c, Some([h, w, c])),
    };
    for spec in specs {
        let layer = match *spec {
            LayerSpec::Scale(factor) => Layer::Scale { size: flat, factor },
            LayerSpec::Relu => Layer::Relu { size: flat },
            LayerSpec::Dense(out) => {
                image = None;
                Layer::Dense { inp: flat, out, offset: *offset }
            }
            LayerSpec::Conv(filters, kernel, stride) => {
                let input = image.expect("a conv layer needs an image input");
                Layer::Conv2d { input, filters, kernel, stride, offset: *offset }
            }
        };
        *offset += layer.param_count();
        flat = layer.out_size();
        if let Layer::Conv2d { filters, .. } = layer {
            let [oh, ow] = layer.conv_out();
            image = Some([oh, ow, filters]);
        }
        layers.push(layer);
    }
    flat
}

impl Net {
    /// Build a network; weights are drawn with He-normal scaling from `rng`, biases zero.
    /// `last_std`, when given, is the standard deviation of the final dense layer's weights
    /// (DeepRacer's heads use small initial weights).
    pub fn new(input: InputShape, specs: &[LayerSpec], last_std: Option<f32>, rng: &mut impl Rng) -> Net {
        let mut layers = Vec::new();
        let mut offset = 0;
        push_layers(input, specs, &mut layers, &mut offset);
        Net::init(layers, offset, Vec::new(), last_std, rng)
    }

    /// A network of several inputs: each `(name, shape, embedder)` in the order of a sample's
    /// values, their embedders' (flattened) outputs concatenated in that order into `trunk`.
    pub fn new_multi(
        inputs: &[(&str, InputShape, &[LayerSpec])],
        trunk: &[LayerSpec],
        last_std: Option<f32>,
        rng: &mut impl Rng,
    ) -> Net {
        let mut layers = Vec::new();
        let mut offset = 0;
        let mut merged = 0;
        let mut embedders = Vec::new();
        for (name, shape, specs) in inputs {
            let before = layers.len();
            merged += push_layers(*shape, specs, &mut layers, &mut offset);
            embedders.push(Embedder { name: name.to_string(), shape: *shape, layers: layers.len() - before });
        }
        push_layers(InputShape::Flat(merged), trunk, &mut layers, &mut offset);
        Net::init(layers, offset, embedders, last_std, rng)
    }

    fn init(layers: Vec<Layer>, n: usize, inputs: Vec<Embedder>, last_std: Option<f32>, rng: &mut impl Rng) -> Net {
        let mut params = vec![0.0f32; n];
        let last_dense = layers.iter().rposition(|l| matches!(l, Layer::Dense { .. }));
        for (i, layer) in layers.iter().enumerate() {
            let (fan_in, n_w, off) = match *layer {
                Layer::Dense { inp, out, offset } => (inp, inp * out, offset),
                Layer::Conv2d { input: [_, _, c], filters, kernel, offset, .. } => {
                    (kernel * kernel * c, filters * kernel * kernel * c, offset)
                }
                _ => continue,
            };
            let std = match last_std {
                Some(s) if Some(i) == last_dense => s,
                _ => (2.0 / fan_in as f32).sqrt(),
            };
            let normal = Normal::new(0.0f32, std).expect("finite std");
            for p in &mut params[off..off + n_w] {
                *p = normal.sample(rng);
            }
        }
        Net { layers, params, inputs }
    }

    /// The layers of each embedder (in input order) and then of the rest, as index ranges;
    /// one range, all layers, for a sequential network.
    pub fn sections(&self) -> Vec<std::ops::Range<usize>> {
        let mut out = Vec::new();
        let mut at = 0;
        for e in &self.inputs {
            out.push(at..at + e.layers);
            at += e.layers;
        }
        out.push(at..self.layers.len());
        out
    }

    /// Features per sample in.
    pub fn in_size(&self) -> usize {
        if self.inputs.is_empty() {
            self.layers.first().map(|l| l.in_size()).unwrap_or(0)
        } else {
            self.inputs.iter().map(|e| e.shape.size()).sum()
        }
    }

    /// Features per sample out (a multi-input network without layers after its embedders:
    /// their outputs side by side).
    pub fn out_size(&self) -> usize {
        let sections = self.sections();
        let trunk = sections.last().expect("the rest");
        if !trunk.is_empty() || self.inputs.is_empty() {
            return self.layers.last().map(|l| l.out_size()).unwrap_or(0);
        }
        (self.inputs.iter().zip(&sections))
            .map(|(e, r)| self.layers[r.clone()].last().map_or(e.shape.size(), |l| l.out_size()))
            .sum()
    }

    /// Forward a batch (`batch × in`), keeping what backward needs in `tape`.
    pub fn forward(&self, x: &[f32], batch: usize, tape: &mut Tape, par: Par) {
        assert_eq!(x.len(), batch * self.in_size(), "input size");
        let sections = self.sections();
        tape.acts.resize_with(self.layers.len() + sections.len(), Vec::new);
        tape.batch = batch;
        if self.inputs.is_empty() {
            tape.acts[0].clear();
            tape.acts[0].extend_from_slice(x);
            self.forward_layers(0..self.layers.len(), 0, batch, tape, par);
            return;
        }
        // Each input's values out of every sample, through its embedder.
        let per = self.in_size();
        let mut at = 0;
        for (j, (e, range)) in self.inputs.iter().zip(&sections).enumerate() {
            let n = e.shape.size();
            let slot = &mut tape.acts[range.start + j];
            slot.clear();
            for row in x.chunks_exact(per) {
                slot.extend_from_slice(&row[at..at + n]);
            }
            at += n;
            self.forward_layers(range.clone(), j, batch, tape, par);
        }
        // Their outputs, concatenated sample by sample, into the rest.
        let trunk = sections.last().expect("the rest").clone();
        let nb = self.inputs.len();
        let mut merged = std::mem::take(&mut tape.acts[trunk.start + nb]);
        merged.clear();
        for b in 0..batch {
            for (j, range) in sections[..nb].iter().enumerate() {
                let out = &tape.acts[range.end + j];
                let n = out.len() / batch;
                merged.extend_from_slice(&out[b * n..(b + 1) * n]);
            }
        }
        tape.acts[trunk.start + nb] = merged;
        self.forward_layers(trunk, nb, batch, tape, par);
    }

    /// Forward through the layers `range`, whose inputs are the tape's slots `range` shifted
    /// by `shift` (the slot of layer `i`'s input is `i + shift`, its output's `i + shift + 1`).
    fn forward_layers(&self, range: std::ops::Range<usize>, shift: usize, batch: usize, tape: &mut Tape, par: Par) {
        let mut done = false;
        for i in range.clone() {
            let layer = &self.layers[i];
            if std::mem::take(&mut done) {
                // A ReLU its conv layer applied.
                continue;
            }
            let (before, after) = tape.acts.split_at_mut(i + shift + 1);
            let inp = &before[i + shift];
            let (out, rest) = after.split_first_mut().expect("an output per layer");
            out.resize(batch * layer.out_size(), 0.0);
            match *layer {
                Layer::Scale { factor, .. } => {
                    for (o, v) in out.iter_mut().zip(inp) {
                        *o = v * factor;
                    }
                }
                Layer::Relu { .. } => {
                    for (o, v) in out.iter_mut().zip(inp) {
                        *o = v.max(0.0);
                    }
                }
                Layer::Dense { inp: n_in, out: n_out, offset } => {
                    let w = &self.params[offset..offset + n_in * n_out];
                    let b = &self.params[offset + n_in * n_out..offset + n_in * n_out + n_out];
                    if turns_dense_forward(batch) {
                        let out_t = &mut tape.out_t;
                        out_t.clear();
                        out_t.extend(b.iter().flat_map(|&v| std::iter::repeat_n(v, batch)));
                        gemm_in(tape.precision, out_t, w, inp, Product::new(n_out, batch, n_in).b_t().add(), par);
                        for (o, col) in out_t.chunks_exact(batch).enumerate() {
                            for (row, v) in out.chunks_exact_mut(n_out).zip(col) {
                                row[o] = *v;
                            }
                        }
                    } else {
                        for row in out.chunks_mut(n_out) {
                            row.copy_from_slice(b);
                        }
                        gemm_in(tape.precision, out, inp, w, Product::new(batch, n_out, n_in).b_t().add(), par);
                    }
                }
                Layer::Conv2d { filters, offset, .. } => {
                    let kkc = layer.param_count() / filters - 1;
                    let w = &self.params[offset..offset + filters * kkc];
                    let b = &self.params[offset + filters * kkc..offset + filters * kkc + filters];
                    // A ReLU after it is applied chunk by chunk, while the output is in cache.
                    let relu = match self.layers.get(i + 1) {
                        Some(Layer::Relu { .. }) if i + 1 < range.end => {
                            rest[0].resize(out.len(), 0.0);
                            done = true;
                            Some(&mut rest[0][..])
                        }
                        _ => None,
                    };
                    Conv { layer, w, b, par, precision: tape.precision }.forward(inp, out, relu, &mut tape.conv);
                }
            }
        }
    }

    /// Backward from `d_out` (`batch × out`, gradient of the loss wrt the output) through
    /// the last forward pass: adds parameter gradients into `grad` (same layout as `params`).
    /// The input gradient is not computed (nothing upstream needs it).
    pub fn backward(&self, tape: &mut Tape, d_out: &[f32], grad: &mut [f32], par: Par) {
        self.backward_factored(tape, d_out, grad, par, Deferral::none(&mut Vec::new()));
    }

    /// [`Net::backward`], and the gradient wrt the network's input into `d_in` (`batch ×
    /// in`, a sample's inputs in their order): what a loss that flows through this network
    /// into something upstream needs (SAC's policy loss through the Q network's action).
    pub fn backward_input(&self, tape: &mut Tape, d_out: &[f32], grad: &mut [f32], par: Par, d_in: &mut Vec<f32>) {
        self.backward_input_factored(tape, d_out, grad, par, Deferral::none(&mut Vec::new()), d_in);
    }

    /// [`Net::backward_input`], leaving the weight gradient of the dense layers `defer`
    /// names as their factors, as [`Net::backward_factored`] does.
    pub fn backward_input_factored(
        &self,
        tape: &mut Tape,
        d_out: &[f32],
        grad: &mut [f32],
        par: Par,
        defer: Deferral<'_>,
        d_in: &mut Vec<f32>,
    ) {
        let batch = tape.batch;
        d_in.clear();
        d_in.resize(batch * self.in_size(), 0.0);
        let Deferral { layers: defer, factors } = defer;
        let pass = Backward { tape, grad, par, defer, factors, want_input: true };
        self.backward_pass(pass, d_out, Some(d_in));
    }

    /// The dense layers whose weight gradient for `batch` samples is at least four times
    /// the size of its factors (the layer's inputs and output gradients): the camera
    /// networks' first dense layer (11.5 M weights; 64 samples' factors are 1.5 M numbers).
    pub fn factorable(&self, batch: usize) -> Vec<usize> {
        (self.layers.iter().enumerate())
            .filter_map(|(i, l)| match *l {
                Layer::Dense { inp, out, .. } if inp * out >= 4 * batch * (inp + out) => Some(i),
                _ => None,
            })
            .collect()
    }

    /// [`Net::backward`], leaving the weight gradient of the dense layers `defer` names as
    /// their factors (pushed to its `factors`, last layer first) instead of adding it to
    /// `grad`.
    pub fn backward_factored(&self, tape: &mut Tape, d_out: &[f32], grad: &mut [f32], par: Par, defer: Deferral<'_>) {
        let Deferral { layers: defer, factors } = defer;
        let pass = Backward { tape, grad, par, defer, factors, want_input: false };
        self.backward_pass(pass, d_out, None);
    }

    /// The backward pass `pass` describes, from `d_out`; the input gradient into `d_in` when
    /// one is given (`pass.want_input`).
    fn backward_pass(&self, mut pass: Backward<'_, '_>, d_out: &[f32], mut d_in: Option<&mut Vec<f32>>) {
        debug_assert_eq!(pass.want_input, d_in.is_some());
        let batch = pass.tape.batch;
        assert_eq!(d_out.len(), batch * self.out_size());
        assert_eq!(pass.grad.len(), self.params.len());
        let mut d = std::mem::take(&mut pass.tape.d);
        let mut d_prev = std::mem::take(&mut pass.tape.d_prev);
        d.clear();
        d.extend_from_slice(d_out);
        let sections = self.sections();
        let nb = self.inputs.len();
        let trunk = sections.last().expect("the rest").clone();
        let want_input = pass.want_input;
        self.backward_layers(trunk.clone(), nb, 0, &mut d, &mut d_prev, &mut pass);
        if let (0, Some(d_in)) = (nb, d_in.as_deref_mut()) {
            let n = d_in.len();
            d_in.copy_from_slice(&d[..n]);
        }
        if nb > 0 {
            // The gradient wrt the concatenation, split between the embedders.
            let mut merged = std::mem::take(&mut pass.tape.merged);
            merged.clear();
            let width = if trunk.is_empty() { self.out_size() } else { self.layers[trunk.start].in_size() };
            merged.extend_from_slice(&d[..batch * width]);
            let width = merged.len() / batch.max(1);
            let (per, mut at_in) = (self.in_size(), 0);
            let mut at = 0;
            for (j, range) in sections[..nb].iter().enumerate() {
                let n = pass.tape.acts[range.end + j].len() / batch.max(1);
                let n_in = self.inputs[j].shape.size();
                if !want_input && (range.is_empty() || !self.layers[range.clone()].iter().any(|l| l.param_count() > 0))
                {
                    at += n;
                    continue;
                }
                d.clear();
                for row in merged.chunks_exact(width) {
                    d.extend_from_slice(&row[at..at + n]);
                }
                at += n;
                if !range.is_empty() {
                    self.backward_layers(range.clone(), j, range.start, &mut d, &mut d_prev, &mut pass);
                }
                if let Some(d_in) = d_in.as_deref_mut() {
                    for (row, g) in d_in.chunks_exact_mut(per).zip(d.chunks_exact(n_in)) {
                        row[at_in..at_in + n_in].copy_from_slice(g);
                    }
                }
                at_in += n_in;
            }
            pass.tape.merged = merged;
        }
        pass.tape.d = d;
        pass.tape.d_prev = d_prev;
    }

    /// Backward through the layers `range` (tape slots shifted by `shift`, as in
    /// [`Net::forward_layers`]) from `d`, the gradient wrt their output; an input gradient
    /// is computed as long as a layer from `first` on before it has parameters.
    fn backward_layers(
        &self,
        range: std::ops::Range<usize>,
        shift: usize,
        first: usize,
        d: &mut Vec<f32>,
        d_prev: &mut Vec<f32>,
        pass: &mut Backward<'_, '_>,
    ) {
        let Backward { tape, grad, par, defer, factors, want_input } = pass;
        let (par, defer, want_input) = (*par, *defer, *want_input);
        let (batch, precision) = (tape.batch, tape.precision);
        for i in range.clone().rev() {
            let layer = &self.layers[i];
            let inp = &tape.acts[i + shift];
            let need_dx = want_input || self.layers[first..i].iter().any(|l| l.param_count() > 0);
            match *layer {
                Layer::Scale { factor, .. } => {
                    if !need_dx {
                        break;
                    }
                    d.iter_mut().for_each(|v| *v *= factor);
                    continue;
                }
                Layer::Relu { .. } => {
                    if i > range.start && matches!(self.layers[i - 1], Layer::Conv2d { .. }) {
                        // The conv layer before masks the gradient chunk by chunk.
                        continue;
                    }
                    // A select with an unconditional store, so the loop vectorises (a
                    // conditional store kept it scalar: 11 % of a SHALLOW training step).
                    for (g, x) in d.iter_mut().zip(inp) {
                        *g = if *x <= 0.0 { 0.0 } else { *g };
                    }
                    continue;
                }
                Layer::Dense { inp: n_in, out: n_out, offset } => {
                    let (gw, gb) = grad[offset..offset + n_in * n_out + n_out].split_at_mut(n_in * n_out);
                    if defer.contains(&i) {
                        // The layer's input is not read again by this pass: hand it out as it
                        // is, and leave a spare buffer for the next forward pass to fill.
                        let x = std::mem::replace(&mut tape.acts[i + shift], tape.spare.pop().unwrap_or_default());
                        factors.push(Factors { offset, n_in, n_out, batch, x, d: d.clone() });
                    } else {
                        // dW (out × in) += dᵀ (out × batch) · x (batch × in)
                        gemm_in(precision, gw, d, inp, Product::new(n_out, n_in, batch).a_t().add(), par);
                    }
                    for row in d.chunks(n_out) {
                        for (g, v) in gb.iter_mut().zip(row) {
                            *g += v;
                        }
                    }
                    if need_dx {
                        d_prev.resize(batch * n_in, 0.0);
                        let w = &self.params[offset..offset + n_in * n_out];
                        gemm_in(precision, d_prev, d, w, Product::new(batch, n_in, n_out), par);
                    }
                }
                Layer::Conv2d { filters, offset, .. } => {
                    let kkc = layer.param_count() / filters - 1;
                    let w = &self.params[offset..offset + filters * kkc];
                    let b = &self.params[offset + filters * kkc..offset + filters * kkc + filters];
                    let sums = grad[offset..offset + filters * kkc + filters].split_at_mut(filters * kkc);
                    let relu_in = match self.layers.get(i + 1) {
                        Some(Layer::Relu { .. }) if i + 1 < range.end => Some(&tape.acts[i + shift + 1][..]),
                        _ => None,
                    };
                    let dx = if need_dx {
                        d_prev.clear();
                        d_prev.resize(batch * layer.in_size(), 0.0);
                        Some(&mut d_prev[..])
                    } else {
                        None
                    };
                    Conv { layer, w, b, par, precision }.backward(inp, d, relu_in, dx, sums, &mut tape.conv);
                }
            }
            if !need_dx {
                break;
            }
            std::mem::swap(d, d_prev);
        }
    }
}

/// What one backward pass carries through every section of a network.
struct Backward<'t, 'f> {
    tape: &'t mut Tape,
    grad: &'t mut [f32],
    par: Par,
    defer: &'t [usize],
    factors: &'f mut Vec<Factors>,
    /// Carry the gradient down to the network's input.
    want_input: bool,
}

/// The dense layers (indices into a net's layers) whose weight gradient a backward pass
/// leaves as their factors, and where it pushes them.
#[derive(Debug)]
pub struct Deferral<'a> {
    /// The layers deferred.
    pub layers: &'a [usize],
    /// Where their factors go, last layer first.
    pub factors: &'a mut Vec<Factors>,
}

impl<'a> Deferral<'a> {
    /// No layer deferred (`factors` stays as it is).
    pub fn none(factors: &'a mut Vec<Factors>) -> Deferral<'a> {
        Deferral { layers: &[], factors }
    }
}

/// A dense layer's weight gradient as its factors, `dW = dᵀ · x`: what a learner team's
/// members exchange for the big layers instead of the product.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Factors {
    /// Where the layer's weights start in the net's parameters.
    pub offset: usize,
    /// Inputs.
    pub n_in: usize,
    /// Outputs.
    pub n_out: usize,
    /// Samples.
    pub batch: usize,
    /// The layer's inputs, `batch × n_in`.
    pub x: Vec<f32>,
    /// The loss's gradient wrt the layer's outputs, `batch × n_out`.
    pub d: Vec<f32>,
}

/// Bytes of a conv layer's unfolded input (im2col) worked on at a time. A conv layer
/// unfolds and multiplies its samples a few at a time, so that the unfolded matrix stays in
/// the core's L2 cache between the copy that makes it and the GEMM that reads it, rather
/// than going out to memory and back (SHALLOW's unfolded inputs are 75 MB a tower for 64
/// samples; one sample's are 0.3-0.5 MB).
const CONV_CHUNK_BYTES: usize = 512 * 1024;

/// One thread's scratch for the conv layers: an unfolded chunk, its gradient, and this
/// thread's share of the weight and bias gradients.
#[derive(Clone, Debug, Default)]
struct ConvScratch {
    cols: Vec<f32>,
    d_cols: Vec<f32>,
    gw: Vec<f32>,
    gb: Vec<f32>,
}

/// A conv layer's geometry for one pass over `x`, and how the pass splits its samples:
/// each thread takes a contiguous `share` and works through it `chunk` samples at a time on
/// its own (one share with one thread).
struct ConvPlan {
    filters: usize,
    kkc: usize,
    oh: usize,
    ow: usize,
    per_in: usize,
    per_out: usize,
    share: usize,
    chunk: usize,
    shares: usize,
}

impl ConvPlan {
    /// The plan for the samples of `x`, with a scratch buffer set for every share.
    fn new(layer: &Layer, x: &[f32], par: Par, scratch: &mut Vec<ConvScratch>) -> ConvPlan {
        let Layer::Conv2d { filters, .. } = *layer else { unreachable!() };
        let [oh, ow] = layer.conv_out();
        let (per_in, per_out) = (layer.in_size(), layer.out_size());
        let batch = x.len() / per_in;
        let threads = par.degree().clamp(1, batch.max(1));
        let share = batch.div_ceil(threads).max(1);
        let shares = batch.div_ceil(share);
        if scratch.len() < shares {
            scratch.resize_with(shares, Default::default);
        }
        let kkc = layer.param_count() / filters - 1;
        ConvPlan { filters, kkc, oh, ow, per_in, per_out, share, chunk: layer.conv_chunk(), shares }
    }
}

/// Split `v` into consecutive pieces of `len` (the last may be shorter), or none.
fn pieces<T>(v: Option<&mut [T]>, len: usize) -> impl Iterator<Item = Option<&mut [T]>> {
    let mut it = v.map(|v| v.chunks_mut(len));
    std::iter::from_fn(move || Some(it.as_mut().and_then(|it| it.next())))
}

/// A conv layer, its weights (`filters × k·k·c`) and biases, and the threads its passes may
/// use.
#[derive(Clone, Copy)]
struct Conv<'a> {
    layer: &'a Layer,
    w: &'a [f32],
    b: &'a [f32],
    par: Par,
    precision: Precision,
}

impl Conv<'_> {
    /// The forward pass, chunk by chunk (see [`CONV_CHUNK_BYTES`]), samples split between
    /// threads when `par` allows: `out (batch·oh·ow × filters) = b + im2col(x) · wᵀ`, and, when
    /// the next layer is a ReLU (`relu`, its output), `relu = max(0, out)` while the chunk is in
    /// cache.
    fn forward(&self, x: &[f32], out: &mut [f32], relu: Option<&mut [f32]>, scratch: &mut Vec<ConvScratch>) {
        let Conv { layer, w, b, par, precision } = *self;
        let ConvPlan { filters, kkc, oh, ow, per_in, per_out, share, chunk, shares } =
            ConvPlan::new(layer, x, par, scratch);
        let run = |x: &[f32], out: &mut [f32], mut relu: Option<&mut [f32]>, s: &mut ConvScratch| {
            for (c, (xc, oc)) in x.chunks(chunk * per_in).zip(out.chunks_mut(chunk * per_out)).enumerate() {
                let n = xc.len() / per_in;
                im2col(layer, xc, n, &mut s.cols);
                for row in oc.chunks_mut(filters) {
                    row.copy_from_slice(b);
                }
                gemm_in(precision, oc, &s.cols, w, Product::new(n * oh * ow, filters, kkc).b_t().add(), Par::Seq);
                if let Some(relu) = relu.as_deref_mut() {
                    for (r, v) in relu[c * chunk * per_out..][..oc.len()].iter_mut().zip(oc.iter()) {
                        *r = v.max(0.0);
                    }
                }
            }
        };
        if shares == 1 {
            return run(x, out, relu, &mut scratch[0]);
        }
        let parts: Vec<_> = (x.chunks(share * per_in).zip(out.chunks_mut(share * per_out)))
            .zip(pieces(relu, share * per_out))
            .zip(scratch.iter_mut())
            .collect();
        use rayon::prelude::*;
        parts.into_par_iter().for_each(|(((x, out), relu), s)| run(x, out, relu, s));
    }

    /// The backward pass, chunk by chunk as [`Conv::forward`] (the input unfolded again, from
    /// cache, rather than kept). `d` is the gradient wrt the layer's outputs; when the next layer
    /// is a ReLU, `relu_in` is that ReLU's input (this layer's output) and `d` the gradient wrt
    /// the ReLU's output, masked here chunk by chunk. Then `gb += Σ d`, `gw += dᵀ · im2col(x)`
    /// and, when `dx` is given, `dx += col2im(d · w)` (`dx` zeroed by the caller). With several
    /// threads each adds its samples' gradients into its own buffers, and those are summed in
    /// thread order, so the result depends on the thread count but not on scheduling.
    fn backward(
        &self,
        x: &[f32],
        d: &mut [f32],
        relu_in: Option<&[f32]>,
        dx: Option<&mut [f32]>,
        (gw, gb): (&mut [f32], &mut [f32]),
        scratch: &mut Vec<ConvScratch>,
    ) {
        let Conv { layer, w, par, precision, .. } = *self;
        let ConvPlan { filters, kkc, oh, ow, per_in, per_out, share, chunk, shares } =
            ConvPlan::new(layer, x, par, scratch);
        let run = |x: &[f32],
                   d: &mut [f32],
                   relu_in: Option<&[f32]>,
                   mut dx: Option<&mut [f32]>,
                   s: &mut ConvScratch,
                   sums: Option<(&mut [f32], &mut [f32])>| {
            let ConvScratch { cols, d_cols, gw: own_gw, gb: own_gb } = s;
            let (gw, gb) = match sums {
                Some(sums) => sums,
                None => {
                    own_gw.clear();
                    own_gw.resize(filters * kkc, 0.0);
                    own_gb.clear();
                    own_gb.resize(filters, 0.0);
                    (&mut own_gw[..], &mut own_gb[..])
                }
            };
            let n_all = x.len() / per_in;
            for first in (0..n_all).step_by(chunk) {
                let n = chunk.min(n_all - first);
                let rows = n * oh * ow;
                let dc = &mut d[first * per_out..(first + n) * per_out];
                if let Some(pre) = relu_in {
                    // A select with an unconditional store, so the loop vectorises.
                    for (g, v) in dc.iter_mut().zip(&pre[first * per_out..(first + n) * per_out]) {
                        *g = if *v <= 0.0 { 0.0 } else { *g };
                    }
                }
                for row in dc.chunks(filters) {
                    for (g, v) in gb.iter_mut().zip(row) {
                        *g += v;
                    }
                }
                im2col(layer, &x[first * per_in..(first + n) * per_in], n, cols);
                gemm_in(precision, gw, dc, cols, Product::new(filters, kkc, rows).a_t().add(), Par::Seq);
                if let Some(dx) = dx.as_deref_mut() {
                    d_cols.resize(rows * kkc, 0.0);
                    gemm_in(precision, &mut d_cols[..rows * kkc], dc, w, Product::new(rows, kkc, filters), Par::Seq);
                    col2im(layer, &d_cols[..rows * kkc], n, &mut dx[first * per_in..(first + n) * per_in]);
                }
            }
        };
        if shares == 1 {
            return run(x, d, relu_in, dx, &mut scratch[0], Some((gw, gb)));
        }
        let parts: Vec<_> = (x.chunks(share * per_in).zip(d.chunks_mut(share * per_out)))
            .zip(
                relu_in
                    .map(|r| r.chunks(share * per_out))
                    .into_iter()
                    .flatten()
                    .map(Some)
                    .chain(std::iter::repeat(None)),
            )
            .zip(pieces(dx, share * per_in))
            .zip(scratch.iter_mut())
            .collect();
        use rayon::prelude::*;
        parts.into_par_iter().for_each(|((((x, d), relu_in), dx), s)| run(x, d, relu_in, dx, s, None));
        for s in &scratch[..shares] {
            for (g, v) in gw.iter_mut().zip(&s.gw) {
                *g += v;
            }
            for (g, v) in gb.iter_mut().zip(&s.gb) {
                *g += v;
            }
        }
    }
}

/// Copy `src` to `dst` (the same length) in blocks of 8 when it divides: im2col's patch
/// rows are 8-192 floats, too short for a `memcpy` call to pay (a call per 32 bytes took
/// most of SHALLOW's first-layer unfolding).
#[inline(always)]
fn copy_patch_row(dst: &mut [f32], src: &[f32]) {
    if dst.len().is_multiple_of(8) {
        for (d, s) in dst.chunks_exact_mut(8).zip(src.chunks_exact(8)) {
            let s: &[f32; 8] = s.try_into().expect("8");
            let d: &mut [f32; 8] = d.try_into().expect("8");
            *d = *s;
        }
    } else {
        dst.copy_from_slice(src);
    }
}

/// Unfold NHWC input patches of `batch` samples into rows: `(batch·oh·ow) × (k·k·c)`.
/// Compiled for the CPU's widest vectors (`pulp`'s runtime dispatch), as the copies are
/// short and run from cache.
fn im2col(layer: &Layer, x: &[f32], batch: usize, cols: &mut Vec<f32>) {
    let Layer::Conv2d { input: [h, w, c], kernel: k, stride: s, .. } = *layer else { unreachable!() };
    let [oh, ow] = layer.conv_out();
    let kkc = k * k * c;
    cols.resize(batch * oh * ow * kkc, 0.0);
    struct Op<'a> {
        geometry: [usize; 7],
        x: &'a [f32],
        cols: &'a mut [f32],
    }
    impl pulp::WithSimd for Op<'_> {
        type Output = ();
        #[inline(always)]
        fn with_simd<S: pulp::Simd>(self, _simd: S) {
            let [h, w, c, k, s, oh, ow] = self.geometry;
            let (kc, kkc) = (k * c, k * k * c);
            if kc == 8 {
                // SHALLOW's first layer (8×8 kernel, 1 channel): a patch row is k pieces of
                // 8 floats, copied as fixed-size arrays and each row written whole (twice
                // as fast as the loop below, whose short copies have run-time lengths).
                return patch_rows::<8>([h, w, c, k, s, oh, ow], self.x, self.cols);
            }
            // Row by row of patches and of kernel, so the innermost loop walks one image row
            // with constant strides.
            for (img, out) in self.x.chunks(h * w * c).zip(self.cols.chunks_mut(oh * ow * kkc)) {
                for (oy, rows) in out.chunks_exact_mut(ow * kkc).enumerate() {
                    for ky in 0..k {
                        let line = &img[(oy * s + ky) * w * c..(oy * s + ky + 1) * w * c];
                        for (row, src) in rows.chunks_exact_mut(kkc).zip(line.windows(kc).step_by(s * c)) {
                            copy_patch_row(&mut row[ky * kc..(ky + 1) * kc], src);
                        }
                    }
                }
            }
        }
    }
    pulp::Arch::new().dispatch(Op { geometry: [h, w, c, k, s, oh, ow], x, cols })
}

/// [`im2col`] for layers whose kernel rows are `KC` floats (`k·c`): every patch row written
/// whole, a kernel row at a time, with copies of a length known when compiling.
#[inline(always)]
fn patch_rows<const KC: usize>([h, w, c, k, s, oh, ow]: [usize; 7], x: &[f32], cols: &mut [f32]) {
    let kkc = k * KC;
    for (img, out) in x.chunks_exact(h * w * c).zip(cols.chunks_exact_mut(oh * ow * kkc)) {
        for (oy, rows) in out.chunks_exact_mut(ow * kkc).enumerate() {
            let lines = &img[oy * s * w * c..(oy * s + k) * w * c];
            for (ox, row) in rows.chunks_exact_mut(kkc).enumerate() {
                for (ky, dst) in row.chunks_exact_mut(KC).enumerate() {
                    let at = ky * w * c + ox * s * c;
                    let src: &[f32; KC] = lines[at..at + KC].try_into().expect("a kernel row");
                    let dst: &mut [f32; KC] = dst.try_into().expect("a kernel row");
                    *dst = *src;
                }
            }
        }
    }
}

/// The adjoint of [`im2col`]: scatter-add patch gradients back into the input gradient.
fn col2im(layer: &Layer, d_cols: &[f32], batch: usize, dx: &mut [f32]) {
    let Layer::Conv2d { input: [h, w, c], kernel: k, stride: s, .. } = *layer else { unreachable!() };
    let [oh, ow] = layer.conv_out();
    debug_assert_eq!(dx.len(), batch * h * w * c);
    struct Op<'a> {
        geometry: [usize; 7],
        d_cols: &'a [f32],
        dx: &'a mut [f32],
    }
    impl pulp::WithSimd for Op<'_> {
        type Output = ();
        #[inline(always)]
        fn with_simd<S: pulp::Simd>(self, _simd: S) {
            let [h, w, c, k, s, oh, ow] = self.geometry;
            let (kc, kkc) = (k * c, k * k * c);
            for (img, rows) in self.dx.chunks_mut(h * w * c).zip(self.d_cols.chunks(oh * ow * kkc)) {
                for (oy, rows) in rows.chunks_exact(ow * kkc).enumerate() {
                    for ky in 0..k {
                        let line = &mut img[(oy * s + ky) * w * c..(oy * s + ky + 1) * w * c];
                        for (ox, row) in rows.chunks_exact(kkc).enumerate() {
                            let dst = &mut line[ox * s * c..ox * s * c + kc];
                            for (d, v) in dst.iter_mut().zip(&row[ky * kc..(ky + 1) * kc]) {
                                *d += v;
                            }
                        }
                    }
                }
            }
        }
    }
    pulp::Arch::new().dispatch(Op { geometry: [h, w, c, k, s, oh, ow], d_cols, dx })
}

/// Optimiser moments that do not fit the optimiser's parameters.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("optimiser state for {m} and {v} parameters where {expected} were expected")]
pub struct MomentsMismatch {
    /// First moments given.
    pub m: usize,
    /// Second moments given.
    pub v: usize,
    /// Parameters of the optimiser.
    pub expected: usize,
}

/// A dense layer's weight gradient left as its factors, `dW = Σ_r d_rᵀ · x_r`: one share per
/// learner of a team, in rank order, or one for a learner alone.
#[derive(Clone, Debug)]
pub struct FactoredGrad<'a> {
    /// Where the layer's weights start in the net's parameters.
    pub offset: usize,
    /// Inputs.
    pub n_in: usize,
    /// Outputs.
    pub n_out: usize,
    /// Each share's layer inputs (`b × n_in`) and output gradients (`b × n_out`).
    pub shares: Vec<(&'a [f32], &'a [f32])>,
}

/// One Adam step's constants.
#[derive(Clone, Copy)]
struct Step {
    b1: f32,
    b2: f32,
    eps: f32,
    step: f32,
    inv_c2: f32,
}

impl Step {
    /// Update a run of parameters; returns non-zero when a gradient value was not finite.
    /// The loop is compiled for the widest vectors the CPU has (`pulp`'s safe runtime
    /// dispatch: AVX2 where present, SSE2 otherwise); lane by lane it is the same IEEE
    /// arithmetic (no fused multiply-add), so every CPU gets the same bits.
    #[inline]
    fn apply(&self, p: &mut [f32], g: &[f32], m: &mut [f32], v: &mut [f32]) -> u32 {
        struct Op<'a> {
            k: Step,
            p: &'a mut [f32],
            g: &'a [f32],
            m: &'a mut [f32],
            v: &'a mut [f32],
        }
        impl pulp::WithSimd for Op<'_> {
            type Output = u32;
            #[inline(always)]
            fn with_simd<S: pulp::Simd>(self, _simd: S) -> u32 {
                let Step { b1, b2, eps, step, inv_c2 } = self.k;
                let mut bad = 0u32;
                for (((p, g), m), v) in self.p.iter_mut().zip(self.g).zip(self.m.iter_mut()).zip(self.v.iter_mut()) {
                    // Exponent all ones: infinite or NaN (an integer test, so the loop stays
                    // vectorised).
                    bad |= (g.to_bits() & 0x7f80_0000 == 0x7f80_0000) as u32;
                    *m = b1 * *m + (1.0 - b1) * g;
                    *v = b2 * *v + (1.0 - b2) * g * g;
                    *p -= step * *m / ((*v * inv_c2).sqrt() + eps);
                }
                bad
            }
        }
        pulp::Arch::new().dispatch(Op { k: *self, p, g, m, v })
    }

    /// [`Step::apply`] in chunks over the cores when `par` allows.
    fn apply_par(&self, p: &mut [f32], g: &[f32], m: &mut [f32], v: &mut [f32], par: Par) -> u32 {
        const CHUNK: usize = 1 << 15;
        if matches!(par, Par::Seq) || p.len() < 4 * CHUNK {
            return self.apply(p, g, m, v);
        }
        use rayon::prelude::*;
        (p.par_chunks_mut(CHUNK).zip(g.par_chunks(CHUNK)).zip(m.par_chunks_mut(CHUNK)).zip(v.par_chunks_mut(CHUNK)))
            .map(|(((p, g), m), v)| self.apply(p, g, m, v))
            .reduce(|| 0, |a, b| a | b)
    }

    /// A factored layer's update (`p`, `m`, `v`: its weights' slices): the layer's gradient
    /// multiplied out into `g` (bands of rows split between threads when `par` allows, each
    /// band's product on one thread), then Adam over it.
    fn apply_factored(
        &self,
        f: &FactoredGrad,
        p: &mut [f32],
        m: &mut [f32],
        v: &mut [f32],
        g: &mut Vec<f32>,
        par: Par,
    ) -> u32 {
        let (n_in, n_out) = (f.n_in, f.n_out);
        g.resize(n_in * n_out, 0.0);
        let g = &mut g[..n_in * n_out];
        let rows_per_band = n_out.div_ceil(par.degree().max(1));
        let band = |(i, g): (usize, &mut [f32])| {
            let rows = g.len() / n_in;
            let mut first = true;
            for (x, d) in &f.shares {
                let b = x.len() / n_in;
                if b == 0 {
                    continue;
                }
                // rows of dᵀ (n_out × b) times x (b × n_in)
                let lhs = MatRef::from_row_major_slice(d, b, n_out).transpose().subrows(i * rows_per_band, rows);
                let rhs = MatRef::from_row_major_slice(x, b, n_in);
                let out = MatMut::from_row_major_slice_mut(g, rows, n_in);
                let beta = if first { Accum::Replace } else { Accum::Add };
                faer::linalg::matmul::matmul(out, beta, lhs, rhs, 1.0f32, Par::Seq);
                first = false;
            }
            if first {
                g.fill(0.0);
            }
        };
        if matches!(par, Par::Seq) {
            band((0, &mut g[..]));
        } else {
            use rayon::prelude::*;
            g.par_chunks_mut(rows_per_band * n_in).enumerate().for_each(band);
        }
        self.apply_par(p, g, m, v, par)
    }
}

/// Adam (DeepRacer's settings: β1 0.9, β2 0.999, ε 1e-5).
#[derive(Clone, Debug, PartialEq)]
pub struct Adam {
    /// Learning rate.
    pub lr: f32,
    /// First-moment decay.
    pub beta1: f32,
    /// Second-moment decay.
    pub beta2: f32,
    /// Denominator epsilon.
    pub eps: f32,
    m: Vec<f32>,
    v: Vec<f32>,
    t: u32,
    /// The factored layers' multiplied-out gradient, kept for the next step.
    g: Scratch,
}

/// A buffer kept between calls so that a step allocates nothing; not part of its owner's
/// value (equal to any other, cloned empty).
#[derive(Default)]
struct Scratch(Vec<f32>);

impl Clone for Scratch {
    fn clone(&self) -> Scratch {
        Scratch::default()
    }
}

impl PartialEq for Scratch {
    fn eq(&self, _: &Scratch) -> bool {
        true
    }
}

impl std::fmt::Debug for Scratch {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Scratch({} floats)", self.0.len())
    }
}

impl Adam {
    /// An optimiser for `n` parameters.
    pub fn new(n: usize, lr: f32) -> Adam {
        Adam { lr, beta1: 0.9, beta2: 0.999, eps: 1e-5, m: vec![0.0; n], v: vec![0.0; n], t: 0, g: Scratch::default() }
    }

    /// One step: `params -= lr · m̂ / (√v̂ + ε)`.
    pub fn step(&mut self, params: &mut [f32], grad: &[f32]) {
        self.step_with(params, grad, Par::Seq);
    }

    /// One step, split over the cores when `par` says so (the same numbers either way: each
    /// parameter's update depends on that parameter alone).
    pub fn step_with(&mut self, params: &mut [f32], grad: &[f32], par: Par) {
        self.step_factored(params, grad, &[], par);
    }

    /// One step where the weight gradients of some dense layers are still their factors
    /// (`factored`; their part of `grad` is not read): the rest of `grad` as in
    /// [`Adam::step_with`]; each factored layer's gradient is multiplied out (into a buffer
    /// the optimiser keeps: 23 MB for a SHALLOW tower's first dense layer) and Adam applied
    /// over it. (Multiplying out a block of rows at a time and updating the block while it
    /// was in cache was slower: on this machine Adam's memory traffic does not overlap the
    /// product's arithmetic either way, and small blocks make slower products.) Each band
    /// of rows is multiplied on one thread, shares in rank order: the same numbers whatever
    /// `par` and on every learner of a team. Returns whether every gradient value was
    /// finite; when it was not, the caller restores the state it saved.
    pub fn step_factored(&mut self, params: &mut [f32], grad: &[f32], factored: &[FactoredGrad], par: Par) -> bool {
        assert_eq!((params.len(), grad.len()), (self.m.len(), self.m.len()));
        self.t += 1;
        let k = Step {
            b1: self.beta1,
            b2: self.beta2,
            eps: self.eps,
            step: self.lr / (1.0 - self.beta1.powi(self.t as i32)),
            inv_c2: 1.0 / (1.0 - self.beta2.powi(self.t as i32)),
        };
        let mut skip: Vec<(usize, usize)> = factored.iter().map(|f| (f.offset, f.offset + f.n_in * f.n_out)).collect();
        skip.sort_unstable();
        let mut bad = 0u32;
        let mut at = 0;
        for &(a, b) in skip.iter().chain(std::iter::once(&(params.len(), params.len()))) {
            bad |= k.apply_par(&mut params[at..a], &grad[at..a], &mut self.m[at..a], &mut self.v[at..a], par);
            at = b;
        }
        for f in factored {
            let w = f.offset..f.offset + f.n_in * f.n_out;
            bad |=
                k.apply_factored(f, &mut params[w.clone()], &mut self.m[w.clone()], &mut self.v[w], &mut self.g.0, par);
        }
        bad == 0
    }

    /// Steps taken.
    pub fn steps(&self) -> u32 {
        self.t
    }

    /// The moment estimates and the step count (what a learner joining a group receives).
    pub fn moments(&self) -> (&[f32], &[f32], u32) {
        (&self.m, &self.v, self.t)
    }

    /// Take over another optimiser's moments; refused unless they fit this one's parameters.
    pub fn set_moments(&mut self, m: Vec<f32>, v: Vec<f32>, t: u32) -> Result<(), MomentsMismatch> {
        if m.len() != self.m.len() || v.len() != self.v.len() {
            return Err(MomentsMismatch { m: m.len(), v: v.len(), expected: self.m.len() });
        }
        (self.m, self.v, self.t) = (m, v, t);
        Ok(())
    }
}
