//! The network maths on a GPU, through wgpu compute: what `policy::nn` does with faer on the
//! CPU (dense and conv2d layers forward and backward, ReLU, input scaling), Adam, PPO's two
//! losses with their gradients and SAC's per-transition arithmetic, in hand-written WGSL
//! (docs/benchmarks.md says why no kernel library). faer stays the reference: every kernel
//! is checked against it.
//!
//! - `device`: which adapter (`--device auto|cpu|gpu`), opened once per process.
//! - `icd`: a headless NVIDIA server's Vulkan driver (its EGL library), found before any
//!   role opens an adapter, for the camera and the maths alike.
//! - `kernels`: the compiled pipelines and one function per dispatch (GEMM, split over K when
//!   the output is small; the element-wise kernels; unfold and fold; Adam; PPO's losses;
//!   SAC's draws, errors and policy gradient).
//! - `net`: a `policy::nn::Net` resident on the GPU (parameters, gradient, Adam's moments,
//!   activations), its forward and backward passes recorded into one command encoder.
//! - `acting`: a sim agent's policy over its environments, both towers in one submission.
//!
//! Tensors are `f32` storage buffers; integers ride in them as their bits.

pub mod acting;
pub mod device;
pub mod icd;
pub mod kernels;
pub mod net;

pub use acting::Acting;
pub use device::{DeviceChoice, Gpu};
pub use net::{GpuNet, Wants};

/// What can go wrong on the GPU path.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    /// `--device gpu` and no adapter with compute.
    #[error("no GPU adapter with compute shaders was found ({0}); `--device cpu` trains on the CPU")]
    NoAdapter(String),
    /// The adapter would not give a device.
    #[error("the GPU adapter {adapter} refused a device: {error}")]
    Device {
        /// The adapter.
        adapter: String,
        /// wgpu's error.
        error: String,
    },
    /// A buffer larger than the device allows in one binding.
    #[error("{what} needs {bytes} bytes in one buffer; this GPU binds at most {limit}")]
    TooLarge {
        /// Which buffer.
        what: String,
        /// Its size.
        bytes: u64,
        /// The device's limit.
        limit: u64,
    },
    /// Reading a result back failed (the device was lost).
    #[error("reading back from the GPU failed: {0}")]
    Readback(String),
}
