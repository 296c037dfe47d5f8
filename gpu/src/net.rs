//! A `policy::nn::Net` resident on the GPU: its parameters, their gradient and Adam's
//! moments, and every layer's output for up to `capacity` samples, so a training update
//! moves nothing between host and device but the minibatch's indices and its figures.
//! Forward and backward are `policy::nn::Net`'s, layer for layer: a dense layer is a bias
//! fill and one product; a conv layer unfolds its input (im2col), multiplies, and its
//! backward pass folds the input gradient back (col2im); bias gradients are products with
//! a row of ones. Sequential networks only: several inputs (camera and LiDAR) are refused.

use crate::kernels::Operand;
use crate::{Gpu, GpuError};
use policy::nn::{Layer, Net};

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
    first_param: usize,
}

impl GpuNet {
    /// Upload `net` (Adam's moments zero) with room for `capacity` samples a pass.
    pub fn new(gpu: &Gpu, net: &Net, capacity: usize) -> Result<GpuNet, GpuError> {
        if !net.inputs.is_empty() {
            return Err(GpuError::Unsupported(format!(
                "networks of several inputs ({})",
                net.inputs.iter().map(|e| e.name.as_str()).collect::<Vec<_>>().join(" and ")
            )));
        }
        let capacity = capacity.max(1);
        let n = net.params.len();
        let params = gpu.buffer("parameters", n)?;
        gpu.upload(&params, 0, &net.params);
        let mut acts = Vec::new();
        let mut cols = Vec::new();
        let (mut widest, mut widest_cols, mut most_rows) = (net.in_size(), 0, capacity);
        for (i, l) in net.layers.iter().enumerate() {
            acts.push(gpu.buffer(&format!("layer {i}'s output"), capacity * l.out_size())?);
            widest = widest.max(l.out_size());
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
            first_param: net.layers.iter().position(|l| l.param_count() > 0).unwrap_or(net.layers.len()),
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

    /// The last forward pass's output (`batch × out`).
    pub fn output(&self) -> &wgpu::Buffer {
        self.acts.last().expect("a network has layers")
    }

    /// Record a forward pass over `batch` samples of `x` (`batch × in`, from float 0).
    pub fn forward(&mut self, gpu: &Gpu, enc: &mut wgpu::CommandEncoder, x: &wgpu::Buffer, batch: usize) {
        assert!(batch <= self.capacity, "{batch} samples, room for {}", self.capacity);
        for i in 0..self.layers.len() {
            let (before, after) = self.acts.split_at(i);
            let input = if i == 0 { x } else { &before[i - 1] };
            let out = &after[0];
            match self.layers[i] {
                Layer::Scale { size, factor } => gpu.op(enc, "scale", batch * size, input, None, out, [0; 7], factor),
                Layer::Relu { size } => gpu.op(enc, "relu", batch * size, input, None, out, [0; 7], 0.0),
                Layer::Dense { inp, out: n_out, offset } => {
                    let bias = (offset + inp * n_out) as u32;
                    gpu.op(
                        enc,
                        "fill_rows",
                        batch * n_out,
                        &self.params,
                        None,
                        out,
                        [bias, n_out as u32, 0, 0, 0, 0, 0],
                        0.0,
                    );
                    gpu.gemm(
                        enc,
                        [batch, n_out, inp],
                        Operand { buf: input, at: 0, t: false },
                        Operand { buf: &self.params, at: offset, t: true },
                        (out, 0),
                        true,
                        &mut self.scratch,
                    );
                }
                Layer::Conv2d { input: [h, w, c], filters, kernel, stride, offset } => {
                    let layer = &self.layers[i];
                    let [oh, ow] = layer.conv_out();
                    let kkc = kernel * kernel * c;
                    let rows = batch * oh * ow;
                    let cols = self.cols[i].as_ref().expect("a conv layer's columns");
                    let geometry = [h, w, c, kernel, stride, oh, ow].map(|v| v as u32);
                    gpu.op(enc, "im2col", rows * kkc, input, None, cols, geometry, 0.0);
                    let bias = (offset + filters * kkc) as u32;
                    gpu.op(
                        enc,
                        "fill_rows",
                        rows * filters,
                        &self.params,
                        None,
                        out,
                        [bias, filters as u32, 0, 0, 0, 0, 0],
                        0.0,
                    );
                    gpu.gemm(
                        enc,
                        [rows, filters, kkc],
                        Operand { buf: cols, at: 0, t: false },
                        Operand { buf: &self.params, at: offset, t: true },
                        (out, 0),
                        true,
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
        self.backward_with(gpu, enc, x, (d_out, 0), batch, true, None);
    }

    /// [`GpuNet::backward`] with `d_out` from float `d_out.1` of its buffer; the parameters'
    /// gradient added into `grad` only when `params`; and the gradient wrt the input written
    /// into `d_in` (`batch × in`) when one is given (a network upstream needs it).
    #[allow(clippy::too_many_arguments)]
    pub fn backward_with(
        &mut self,
        gpu: &Gpu,
        enc: &mut wgpu::CommandEncoder,
        x: &wgpu::Buffer,
        d_out: (&wgpu::Buffer, usize),
        batch: usize,
        params: bool,
        d_in: Option<&wgpu::Buffer>,
    ) {
        let last = self.layers.last().expect("a network has layers").out_size();
        enc.copy_buffer_to_buffer(d_out.0, (d_out.1 * 4) as u64, &self.d[0], 0, (batch * last * 4) as u64);
        let lowest = if d_in.is_some() { 0 } else { self.first_param };
        let mut cur = 0;
        for i in (lowest..self.layers.len()).rev() {
            let need_in = i > lowest || d_in.is_some();
            let input = if i == 0 { x } else { &self.acts[i - 1] };
            let (d, d_prev) = if cur == 0 { (&self.d[0], &self.d[1]) } else { (&self.d[1], &self.d[0]) };
            match self.layers[i] {
                Layer::Scale { size, factor } => gpu.op(enc, "scale", batch * size, d, None, d_prev, [0; 7], factor),
                Layer::Relu { size } => {
                    gpu.op(enc, "relu_back", batch * size, d, Some(&self.acts[i]), d_prev, [0; 7], 0.0)
                }
                Layer::Dense { inp, out, offset } => {
                    if params {
                        gpu.gemm(
                            enc,
                            [out, inp, batch],
                            Operand { buf: d, at: 0, t: true },
                            Operand { buf: input, at: 0, t: false },
                            (&self.grad, offset),
                            true,
                            &mut self.scratch,
                        );
                        gpu.gemm(
                            enc,
                            [1, out, batch],
                            Operand { buf: &self.ones, at: 0, t: false },
                            Operand { buf: d, at: 0, t: false },
                            (&self.grad, offset + inp * out),
                            true,
                            &mut self.scratch,
                        );
                    }
                    if need_in {
                        gpu.gemm(
                            enc,
                            [batch, inp, out],
                            Operand { buf: d, at: 0, t: false },
                            Operand { buf: &self.params, at: offset, t: false },
                            (d_prev, 0),
                            false,
                            &mut self.scratch,
                        );
                    }
                }
                Layer::Conv2d { input: [h, w, c], filters, kernel, stride, offset } => {
                    let [oh, ow] = self.layers[i].conv_out();
                    let kkc = kernel * kernel * c;
                    let rows = batch * oh * ow;
                    let cols = self.cols[i].as_ref().expect("a conv layer's columns");
                    if params {
                        gpu.gemm(
                            enc,
                            [filters, kkc, rows],
                            Operand { buf: d, at: 0, t: true },
                            Operand { buf: cols, at: 0, t: false },
                            (&self.grad, offset),
                            true,
                            &mut self.scratch,
                        );
                        gpu.gemm(
                            enc,
                            [1, filters, rows],
                            Operand { buf: &self.ones, at: 0, t: false },
                            Operand { buf: d, at: 0, t: false },
                            (&self.grad, offset + filters * kkc),
                            true,
                            &mut self.scratch,
                        );
                    }
                    if need_in {
                        gpu.gemm(
                            enc,
                            [rows, kkc, filters],
                            Operand { buf: d, at: 0, t: false },
                            Operand { buf: &self.params, at: offset, t: false },
                            (&self.d_cols, 0),
                            false,
                            &mut self.scratch,
                        );
                        let geometry = [h, w, c, kernel, stride, oh, ow].map(|v| v as u32);
                        gpu.op(enc, "col2im", batch * h * w * c, &self.d_cols, None, d_prev, geometry, 0.0);
                    }
                }
            }
            if !need_in {
                break;
            }
            cur ^= 1;
        }
        if let Some(d_in) = d_in {
            let size = batch * self.layers[0].in_size();
            enc.copy_buffer_to_buffer(&self.d[cur], 0, d_in, 0, (size * 4) as u64);
        }
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
