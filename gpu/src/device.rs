//! Which adapter the maths run on. `auto`: the CPU (faer), because on the one GPU measured
//! (an H200 beside 16 cores, docs/benchmarks.md) the kernels here made PPO's update 0.37–0.59×
//! as fast as faer and a training from pixels slower, and a software adapter is slower still;
//! `gpu`: the best adapter there is, a software one (lavapipe) included, or an error; `cpu`:
//! faer. The tests use `gpu` on lavapipe, so no test needs a GPU.

use crate::GpuError;
use crate::kernels::Kernels;

/// `--device`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum DeviceChoice {
    /// Where the maths were measured fastest: today the CPU.
    #[default]
    Auto,
    /// faer on the CPU.
    Cpu,
    /// The GPU, or an error when there is none (a software adapter counts).
    Gpu,
}

impl std::str::FromStr for DeviceChoice {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "auto" => Ok(DeviceChoice::Auto),
            "cpu" => Ok(DeviceChoice::Cpu),
            "gpu" => Ok(DeviceChoice::Gpu),
            _ => Err(format!("`{s}` is not a device: expected auto, cpu or gpu")),
        }
    }
}

impl std::fmt::Display for DeviceChoice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            DeviceChoice::Auto => "auto",
            DeviceChoice::Cpu => "cpu",
            DeviceChoice::Gpu => "gpu",
        })
    }
}

/// Whether an adapter of this type is a hardware GPU (lavapipe's type is `Cpu`).
pub fn is_hardware(kind: wgpu::DeviceType) -> bool {
    matches!(kind, wgpu::DeviceType::DiscreteGpu | wgpu::DeviceType::IntegratedGpu | wgpu::DeviceType::VirtualGpu)
}

/// An open GPU: the device, its queue and the compiled kernels.
pub struct Gpu {
    /// The device.
    pub device: wgpu::Device,
    /// Its queue.
    pub queue: wgpu::Queue,
    /// The kernels.
    pub kernels: Kernels,
    /// "name (type, backend)", as `render` prints it.
    pub adapter: String,
    /// Hardware or software (lavapipe's is `Cpu`).
    pub device_type: wgpu::DeviceType,
    /// The largest storage buffer one binding takes.
    pub max_binding: u64,
}

impl std::fmt::Debug for Gpu {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Gpu").field("adapter", &self.adapter).finish()
    }
}

impl Gpu {
    /// Open what `choice` asks for: `Ok(None)` means the CPU (`cpu` or `auto`).
    pub fn open(choice: DeviceChoice) -> Result<Option<Gpu>, GpuError> {
        match choice {
            DeviceChoice::Cpu => return Ok(None),
            DeviceChoice::Auto => {
                tracing::info!(
                    "device auto: the network maths run on the CPU (faer), faster than this build's GPU kernels on the GPU measured; --device gpu puts them on the GPU"
                );
                return Ok(None);
            }
            DeviceChoice::Gpu => {}
        }
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let adapter = pollster::block_on(instance.request_adapter(&wgpu::RequestAdapterOptions {
            power_preference: wgpu::PowerPreference::HighPerformance,
            force_fallback_adapter: false,
            compatible_surface: None,
            apply_limit_buckets: false,
        }));
        let adapter = adapter.map_err(|e| GpuError::NoAdapter(e.to_string()))?;
        let info = adapter.get_info();
        let name = format!("{} ({:?}, {:?})", info.name, info.device_type, info.backend);
        let limits = adapter.limits();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("paddock maths"),
            required_features: wgpu::Features::empty(),
            required_limits: limits.clone(),
            experimental_features: wgpu::ExperimentalFeatures::disabled(),
            memory_hints: wgpu::MemoryHints::Performance,
            trace: wgpu::Trace::Off,
        }))
        .map_err(|e| GpuError::Device { adapter: name.clone(), error: e.to_string() })?;
        let kernels = Kernels::new(&device);
        if !is_hardware(info.device_type) {
            tracing::warn!("the maths run on {name}, a software adapter: slower than the CPU path (faer)");
        }
        tracing::info!("the network maths run on {name}");
        Ok(Some(Gpu {
            device,
            queue,
            kernels,
            adapter: name,
            device_type: info.device_type,
            max_binding: limits.max_storage_buffer_binding_size.min(limits.max_buffer_size),
        }))
    }

    /// A zeroed storage buffer of `len` floats (one at least), or why it cannot be made.
    pub fn buffer(&self, what: &str, len: usize) -> Result<wgpu::Buffer, GpuError> {
        let bytes = (len.max(1) * 4) as u64;
        if bytes > self.max_binding {
            return Err(GpuError::TooLarge { what: what.to_string(), bytes, limit: self.max_binding });
        }
        Ok(self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(what),
            size: bytes,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        }))
    }

    /// Write `data` into `buf` from float `at` on.
    pub fn upload(&self, buf: &wgpu::Buffer, at: usize, data: &[f32]) {
        if !data.is_empty() {
            self.queue.write_buffer(buf, (at * 4) as u64, bytemuck::cast_slice(data));
        }
    }

    /// Read `len` floats of `buf` from float `at` on, after everything submitted so far.
    pub fn download(&self, buf: &wgpu::Buffer, at: usize, len: usize) -> Result<Vec<f32>, GpuError> {
        let mut enc = self.device.create_command_encoder(&Default::default());
        let staging = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("readback"),
            size: (len.max(1) * 4) as u64,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        if len > 0 {
            enc.copy_buffer_to_buffer(buf, (at * 4) as u64, &staging, 0, (len * 4) as u64);
        }
        self.queue.submit([enc.finish()]);
        self.read_staging(&staging, len)
    }

    /// Map a MAP_READ buffer (once the queue's work is done) and copy out its first `len`
    /// floats.
    pub fn read_staging(&self, staging: &wgpu::Buffer, len: usize) -> Result<Vec<f32>, GpuError> {
        if len == 0 {
            return Ok(Vec::new());
        }
        let slice = staging.slice(..(len * 4) as u64);
        let (tx, rx) = std::sync::mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        self.device.poll(wgpu::PollType::wait_indefinitely()).map_err(|e| GpuError::Readback(e.to_string()))?;
        rx.recv().map_err(|e| GpuError::Readback(e.to_string()))?.map_err(|e| GpuError::Readback(e.to_string()))?;
        let out = {
            let mapped = slice.get_mapped_range().map_err(|e| GpuError::Readback(e.to_string()))?;
            bytemuck::cast_slice::<u8, f32>(&mapped).to_vec()
        };
        staging.unmap();
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn choices_parse_and_hardware_is_told_from_software() {
        for (s, c) in [("auto", DeviceChoice::Auto), ("cpu", DeviceChoice::Cpu), ("gpu", DeviceChoice::Gpu)] {
            assert_eq!(s.parse::<DeviceChoice>(), Ok(c));
            assert_eq!(c.to_string(), s);
        }
        assert!("cuda".parse::<DeviceChoice>().unwrap_err().contains("auto, cpu or gpu"));
        use wgpu::DeviceType::*;
        for (kind, takes) in
            [(DiscreteGpu, true), (IntegratedGpu, true), (VirtualGpu, true), (Cpu, false), (Other, false)]
        {
            assert_eq!(is_hardware(kind), takes, "{kind:?}");
        }
    }

    /// `auto` keeps the maths on faer, whatever adapters the machine has (lavapipe here, a
    /// GPU elsewhere); `gpu` takes the adapter there is.
    #[test]
    fn auto_keeps_the_maths_on_the_cpu_and_gpu_takes_the_adapter() {
        assert!(Gpu::open(DeviceChoice::Auto).unwrap().is_none());
        assert!(Gpu::open(DeviceChoice::Cpu).unwrap().is_none());
        let gpu = Gpu::open(DeviceChoice::Gpu).unwrap().expect("`gpu` opens lavapipe where there is no GPU");
        assert!(!gpu.adapter.is_empty());
    }
}
