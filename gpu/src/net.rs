//! A `policy::nn::Net` resident on the GPU: its parameters, their gradient and Adam's
//! moments, and every layer's output for up to `capacity` samples, so a training update
//! moves nothing between host and device but the minibatch's indices and its figures.
//! Forward and backward are `policy::nn::Net`'s, layer for layer: a dense layer is a bias
//! fill and one product; a conv layer unfolds its input (im2col), multiplies, and its
//! backward pass folds the input gradient back (col2im); bias gradients are products with
//! a row of ones. A network of several inputs (camera and LiDAR) takes each input's values
//! out of the samples into its embedder and the embeddings side by side into the rest.

use crate::kernels::{Gemm, Op, Operand};
use crate::{Gpu, GpuError};
use policy::nn::{Layer, Net};

/// What a backward pass makes besides the gradients inside the network.
#[derive(Clone, Copy, Debug)]
pub struct Wants<'a> {
    /// The parameters' gradient, added into the network's `grad`.
    pub params: bool,
    /// The gradient wrt the network's input, into this buffer.
    pub d_in: Option<&'a wgpu::Buffer>,
}

/// A network on the GPU.
pub struct GpuNet {
    /// The layers (the CPU network's).
    pub layers: Vec<Layer>,
    /// Parameters, in `Net::params`' layout.
    pub params: wgpu::Buffer,
    /// The gradient the last backward passes added up.
    pub grad: wgpu::Buffer,
    /// Adam's first moments.
    pub m: wgpu::Buffer,
    /// Adam's second moments.
    pub v: wgpu::Buffer,
    n_params: usize,
    capacity: usize,
    acts: Vec<wgpu::Buffer>,
    cols: Vec<Option<wgpu::Buffer>>,
    d: [wgpu::Buffer; 2],
    d_cols: wgpu::Buffer,
    ones: wgpu::Buffer,
    scratch: Option<wgpu::Buffer>,
    in_size: usize,
    /// The layers after the embedders (all of them for a network of one input).
    trunk: std::ops::Range<usize>,
    /// A network of several inputs: each input's embedder.
    inputs: Vec<Input>,
    /// A network of several inputs: the embedders' outputs side by side.
    merged: Option<Merged>,
}

/// The embeddings of a network of several inputs, side by side.
struct Merged {
    /// Their values (the rest's input, or the output when there is no rest).
    values: wgpu::Buffer,
    /// The gradient wrt them.
    grad: wgpu::Buffer,
    /// Values a sample.
    width: usize,
}

/// One input of a network of several inputs.
struct Input {
    /// Where its values start in a sample, and how many there are.
    at: usize,
    size: usize,
    /// Its embedder's output width.
    out: usize,
    /// Its embedder's layers.
    layers: std::ops::Range<usize>,
    /// Its values out of every sample.
    values: wgpu::Buffer,
}

/// A dense or conv layer as the one product it is: `rows` (samples, or samples × output
/// positions) by `n_in` (inputs, or the unfolded patch) times its weights to `n_out`.
struct Product {
    rows: usize,
    n_in: usize,
    n_out: usize,
    offset: usize,
    /// A conv layer's unfold geometry (h, w, c, kernel, stride, oh, ow).
    geometry: Option<[u32; 7]>,
}

impl Product {
    fn of(layer: &Layer, batch: usize) -> Product {
        match *layer {
            Layer::Dense { inp, out, offset } => Product { rows: batch, n_in: inp, n_out: out, offset, geometry: None },
            Layer::Conv2d { input: [h, w, c], filters, kernel, stride, offset } => {
                let [oh, ow] = layer.conv_out();
                Product {
                    rows: batch * oh * ow,
                    n_in: kernel * kernel * c,
                    n_out: filters,
                    offset,
                    geometry: Some([h, w, c, kernel, stride, oh, ow].map(|v| v as u32)),
                }
            }
            _ => unreachable!("only dense and conv layers are products"),
        }
    }
}

/// Record copying `n` values a row, `batch` rows, from `src` (row width, column offset) to
/// `dst` (the same).
fn copy_cols(
    gpu: &Gpu,
    enc: &mut wgpu::CommandEncoder,
    batch: usize,
    src: (&wgpu::Buffer, usize, usize),
    dst: (&wgpu::Buffer, usize, usize),
    n: usize,
) {
    let u = [n, dst.1, dst.2, src.1, src.2, 0, 0].map(|v| v as u32);
    gpu.op(enc, Op::new("copy_cols", batch * n).u(u), src.0, None, dst.0);
}

impl GpuNet {
    /// Upload `net` (Adam's moments zero) with room for `capacity` samples a pass.
    pub fn new(gpu: &Gpu, net: &Net, capacity: usize) -> Result<GpuNet, GpuError> {
        let sections = net.sections();
        let capacity = capacity.max(1);
        let n = net.params.len();
        let params = gpu.buffer("parameters", n)?;
        gpu.upload(&params, 0, &net.params);
        let mut acts = Vec::new();
        let mut cols = Vec::new();
        let (mut widest, mut widest_cols, mut most_rows) = (net.in_size(), 0, capacity);
        for (i, l) in net.layers.iter().enumerate() {
            acts.push(gpu.buffer(&format!("layer {i}'s output"), capacity * l.out_size())?);
            widest = widest.max(l.out_size()).max(l.in_size());
            cols.push(match *l {
                Layer::Conv2d { filters, .. } => {
                    let [oh, ow] = l.conv_out();
                    let rows = capacity * oh * ow;
                    let kkc = l.param_count() / filters - 1;
                    most_rows = most_rows.max(rows);
                    widest_cols = widest_cols.max(rows * kkc);
                    Some(gpu.buffer(&format!("layer {i}'s unfolded input"), rows * kkc)?)
                }
                _ => None,
            });
        }
        // Several inputs: each input's values, and the embedders' outputs side by side.
        let mut inputs = Vec::new();
        let mut at = 0;
        for (e, range) in net.inputs.iter().zip(&sections) {
            let n_in = e.shape.size();
            let out = net.layers[range.clone()].last().map_or(n_in, |l| l.out_size());
            inputs.push(Input {
                at,
                size: n_in,
                out,
                layers: range.clone(),
                values: gpu.buffer(&format!("input {}", e.name), capacity * n_in)?,
            });
            at += n_in;
        }
        let merged = match sections.last() {
            Some(trunk) if !net.inputs.is_empty() => {
                let width = inputs.iter().map(|e| e.out).sum::<usize>();
                debug_assert!(trunk.is_empty() || net.layers[trunk.start].in_size() == width);
                Some(Merged {
                    values: gpu.buffer("the embeddings side by side", capacity * width)?,
                    grad: gpu.buffer("the gradient wrt the embeddings", capacity * width)?,
                    width,
                })
            }
            _ => None,
        };
        let ones = gpu.buffer("ones", most_rows)?;
        let mut enc = gpu.device.create_command_encoder(&Default::default());
        gpu.fill_ones(&mut enc, &ones, most_rows);
        gpu.queue.submit([enc.finish()]);
        Ok(GpuNet {
            layers: net.layers.clone(),
            grad: gpu.buffer("gradient", n)?,
            m: gpu.buffer("Adam's first moments", n)?,
            v: gpu.buffer("Adam's second moments", n)?,
            params,
            n_params: n,
            capacity,
            acts,
            cols,
            d: [gpu.buffer("gradient a", capacity * widest)?, gpu.buffer("gradient b", capacity * widest)?],
            d_cols: gpu.buffer("unfolded gradient", widest_cols)?,
            ones,
            scratch: None,
            in_size: net.in_size(),
            trunk: sections.last().cloned().unwrap_or(0..net.layers.len()),
            inputs,
            merged,
        })
    }

    /// Parameters.
    pub fn len(&self) -> usize {
        self.n_params
    }

    /// Whether the network has no parameters.
    pub fn is_empty(&self) -> bool {
        self.n_params == 0
    }

    /// Samples a pass takes at most.
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Values a sample puts in.
    pub fn in_size(&self) -> usize {
        self.in_size
    }

    /// The last forward pass's output (`batch × out`).
    pub fn output(&self) -> &wgpu::Buffer {
        match &self.merged {
            // Several inputs and nothing after their embedders: the embeddings side by side.
            Some(m) if self.trunk.is_empty() => &m.values,
            _ => self.acts.last().expect("a network has layers"),
        }
    }

    /// Values a sample's output has.
    fn out_size(&self) -> usize {
        match &self.merged {
            Some(m) if self.trunk.is_empty() => m.width,
            _ => self.layers.last().expect("a network has layers").out_size(),
        }
    }

    /// Record a forward pass over `batch` samples of `x` (`batch × in`, from float 0). A
    /// network of several inputs takes each input's values out of every sample into its
    /// embedder, and their outputs side by side into the rest, as `policy::nn::Net` does.
    pub fn forward(&mut self, gpu: &Gpu, enc: &mut wgpu::CommandEncoder, x: &wgpu::Buffer, batch: usize) {
        assert!(batch <= self.capacity, "{batch} samples, room for {}", self.capacity);
        let Some((merged, width)) = self.merged.as_ref().map(|m| (m.values.clone(), m.width)) else {
            self.forward_layers(gpu, enc, 0..self.layers.len(), x, batch);
            return;
        };
        let mut o = 0;
        for k in 0..self.inputs.len() {
            let e = &self.inputs[k];
            let (values, layers, (at, size, out)) = (e.values.clone(), e.layers.clone(), (e.at, e.size, e.out));
            copy_cols(gpu, enc, batch, (x, self.in_size, at), (&values, size, 0), size);
            self.forward_layers(gpu, enc, layers.clone(), &values, batch);
            let embedded = if layers.is_empty() { values } else { self.acts[layers.end - 1].clone() };
            copy_cols(gpu, enc, batch, (&embedded, out, 0), (&merged, width, o), out);
            o += out;
        }
        self.forward_layers(gpu, enc, self.trunk.clone(), &merged, batch);
    }

    /// Forward through the layers `range`, the first of which reads `x`.
    fn forward_layers(
        &mut self,
        gpu: &Gpu,
        enc: &mut wgpu::CommandEncoder,
        range: std::ops::Range<usize>,
        x: &wgpu::Buffer,
        batch: usize,
    ) {
        for i in range.clone() {
            let (before, after) = self.acts.split_at(i);
            let input = if i == range.start { x } else { &before[i - 1] };
            let out = &after[0];
            match self.layers[i] {
                Layer::Scale { size, factor } => {
                    gpu.op(enc, Op::new("scale", batch * size).x(factor), input, None, out)
                }
                Layer::Relu { size } => gpu.op(enc, Op::new("relu", batch * size), input, None, out),
                Layer::Dense { .. } | Layer::Conv2d { .. } => {
                    // A dense layer is a conv over one position a sample: the product's rows.
                    let p = Product::of(&self.layers[i], batch);
                    let unfolded = match (&self.cols[i], p.geometry) {
                        (Some(cols), Some(geometry)) => {
                            gpu.op(enc, Op::new("im2col", p.rows * p.n_in).u(geometry), input, None, cols);
                            cols
                        }
                        _ => input,
                    };
                    let bias = [(p.offset + p.n_in * p.n_out) as u32, p.n_out as u32, 0, 0, 0, 0, 0];
                    gpu.op(enc, Op::new("fill_rows", p.rows * p.n_out).u(bias), &self.params, None, out);
                    gpu.gemm(
                        enc,
                        &Gemm {
                            mnk: [p.rows, p.n_out, p.n_in],
                            a: Operand { buf: unfolded, at: 0, t: false },
                            b: Operand { buf: &self.params, at: p.offset, t: true },
                            c: (out, 0),
                            add: true,
                        },
                        &mut self.scratch,
                    );
                }
            }
        }
    }

    /// Record zeroing the gradient.
    pub fn zero_grad(&self, enc: &mut wgpu::CommandEncoder) {
        enc.clear_buffer(&self.grad, 0, None);
    }

    /// Record the backward pass of the last forward pass over `batch` samples of `x`, from
    /// `d_out` (`batch × out`, the loss's gradient wrt the output): adds the parameters'
    /// gradient into `grad`. No input gradient (nothing upstream needs one).
    pub fn backward(
        &mut self,
        gpu: &Gpu,
        enc: &mut wgpu::CommandEncoder,
        x: &wgpu::Buffer,
        d_out: &wgpu::Buffer,
        batch: usize,
    ) {
        self.backward_with(gpu, enc, x, (d_out, 0), batch, Wants { params: true, d_in: None });
    }

    /// [`GpuNet::backward`] with `d_out` from float `d_out.1` of its buffer, making what
    /// `wants` says: the parameters' gradient (added into `grad`), the gradient wrt the input
    /// (`batch × in`, into the buffer given: a network upstream needs it), or both.
    pub fn backward_with(
        &mut self,
        gpu: &Gpu,
        enc: &mut wgpu::CommandEncoder,
        x: &wgpu::Buffer,
        d_out: (&wgpu::Buffer, usize),
        batch: usize,
        wants: Wants<'_>,
    ) {
        let Wants { params, d_in } = wants;
        let last = self.out_size();
        let Some((merged, d_merged, width)) = self.merged.as_ref().map(|m| (m.values.clone(), m.grad.clone(), m.width))
        else {
            enc.copy_buffer_to_buffer(d_out.0, (d_out.1 * 4) as u64, &self.d[0], 0, (batch * last * 4) as u64);
            let cur = self.backward_layers(
                gpu,
                enc,
                0..self.layers.len(),
                x,
                Pass { batch, params, want_in: d_in.is_some() },
            );
            if let Some(d_in) = d_in {
                enc.copy_buffer_to_buffer(&self.d[cur], 0, d_in, 0, (batch * self.in_size * 4) as u64);
            }
            return;
        };
        // The trunk, down to the gradient wrt the embeddings side by side.
        let bytes = (batch * width * 4) as u64;
        if self.trunk.is_empty() {
            enc.copy_buffer_to_buffer(d_out.0, (d_out.1 * 4) as u64, &d_merged, 0, bytes);
        } else {
            enc.copy_buffer_to_buffer(d_out.0, (d_out.1 * 4) as u64, &self.d[0], 0, (batch * last * 4) as u64);
            let cur =
                self.backward_layers(gpu, enc, self.trunk.clone(), &merged, Pass { batch, params, want_in: true });
            enc.copy_buffer_to_buffer(&self.d[cur], 0, &d_merged, 0, bytes);
        }
        let mut o = 0;
        for k in 0..self.inputs.len() {
            let e = &self.inputs[k];
            let (values, layers, (at, size, out)) = (e.values.clone(), e.layers.clone(), (e.at, e.size, e.out));
            let trains = params && self.layers[layers.clone()].iter().any(|l| l.param_count() > 0);
            if trains || d_in.is_some() {
                let d0 = self.d[0].clone();
                copy_cols(gpu, enc, batch, (&d_merged, width, o), (&d0, out, 0), out);
                let cur =
                    self.backward_layers(gpu, enc, layers, &values, Pass { batch, params, want_in: d_in.is_some() });
                if let Some(d_in) = d_in {
                    copy_cols(gpu, enc, batch, (&self.d[cur].clone(), size, 0), (d_in, self.in_size, at), size);
                }
            }
            o += out;
        }
    }

    /// Backward through the layers `range` (the first of which read `x`) from the gradient
    /// wrt their output in `d[0]`: the parameters' gradient when `params`, and the gradient
    /// wrt `x` when `want_in` (else down to the range's first layer with parameters).
    /// Returns which of the two gradient buffers holds the last gradient computed.
    fn backward_layers(
        &mut self,
        gpu: &Gpu,
        enc: &mut wgpu::CommandEncoder,
        range: std::ops::Range<usize>,
        x: &wgpu::Buffer,
        pass: Pass,
    ) -> usize {
        let Pass { batch, params, want_in } = pass;
        let first_param = range.clone().find(|&i| self.layers[i].param_count() > 0).unwrap_or(range.end);
        let lowest = if want_in { range.start } else { first_param };
        let mut cur = 0;
        for i in (lowest..range.end).rev() {
            let need_in = i > lowest || want_in;
            let input = if i == range.start { x } else { &self.acts[i - 1] };
            let (d, d_prev) = if cur == 0 { (&self.d[0], &self.d[1]) } else { (&self.d[1], &self.d[0]) };
            match self.layers[i] {
                Layer::Scale { size, factor } => gpu.op(enc, Op::new("scale", batch * size).x(factor), d, None, d_prev),
                Layer::Relu { size } => gpu.op(enc, Op::new("relu_back", batch * size), d, Some(&self.acts[i]), d_prev),
                Layer::Dense { .. } | Layer::Conv2d { .. } => {
                    let p = Product::of(&self.layers[i], batch);
                    let unfolded = self.cols[i].as_ref().unwrap_or(input);
                    if params {
                        gpu.gemm(
                            enc,
                            &Gemm {
                                mnk: [p.n_out, p.n_in, p.rows],
                                a: Operand { buf: d, at: 0, t: true },
                                b: Operand { buf: unfolded, at: 0, t: false },
                                c: (&self.grad, p.offset),
                                add: true,
                            },
                            &mut self.scratch,
                        );
                        gpu.gemm(
                            enc,
                            &Gemm {
                                mnk: [1, p.n_out, p.rows],
                                a: Operand { buf: &self.ones, at: 0, t: false },
                                b: Operand { buf: d, at: 0, t: false },
                                c: (&self.grad, p.offset + p.n_in * p.n_out),
                                add: true,
                            },
                            &mut self.scratch,
                        );
                    }
                    if need_in {
                        // A conv layer's input gradient is unfolded first, then folded back.
                        let target = if p.geometry.is_some() { &self.d_cols } else { d_prev };
                        gpu.gemm(
                            enc,
                            &Gemm {
                                mnk: [p.rows, p.n_in, p.n_out],
                                a: Operand { buf: d, at: 0, t: false },
                                b: Operand { buf: &self.params, at: p.offset, t: false },
                                c: (target, 0),
                                add: false,
                            },
                            &mut self.scratch,
                        );
                        if let Some(geometry) = p.geometry {
                            let size = batch * self.layers[i].in_size();
                            gpu.op(enc, Op::new("col2im", size).u(geometry), &self.d_cols, None, d_prev);
                        }
                    }
                }
            }
            if !need_in {
                break;
            }
            cur ^= 1;
        }
        cur
    }

    /// Replace the parameters.
    pub fn set_params(&self, gpu: &Gpu, params: &[f32]) {
        assert_eq!(params.len(), self.n_params);
        gpu.upload(&self.params, 0, params);
    }

    /// Replace Adam's moments.
    pub fn set_moments(&self, gpu: &Gpu, m: &[f32], v: &[f32]) {
        assert_eq!((m.len(), v.len()), (self.n_params, self.n_params));
        gpu.upload(&self.m, 0, m);
        gpu.upload(&self.v, 0, v);
    }

    /// The parameters, read back.
    pub fn read_params(&self, gpu: &Gpu) -> Result<Vec<f32>, GpuError> {
        gpu.download(&self.params, 0, self.n_params)
    }

    /// The gradient, read back.
    pub fn read_grad(&self, gpu: &Gpu) -> Result<Vec<f32>, GpuError> {
        gpu.download(&self.grad, 0, self.n_params)
    }

    /// Adam's moments, read back.
    pub fn read_moments(&self, gpu: &Gpu) -> Result<(Vec<f32>, Vec<f32>), GpuError> {
        Ok((gpu.download(&self.m, 0, self.n_params)?, gpu.download(&self.v, 0, self.n_params)?))
    }
}

/// What one backward pass through a range of layers computes: over `batch` samples, the
/// parameters' gradient when `params`, and the gradient wrt the range's input when `want_in`.
#[derive(Clone, Copy)]
struct Pass {
    batch: usize,
    params: bool,
    want_in: bool,
}
