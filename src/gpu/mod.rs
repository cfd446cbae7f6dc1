//! The heavy stages on a GPU, through wgpu (WGSL compute shaders in `shaders/`).
//!
//! The CPU code is the reference and the fallback: every shader has a CPU twin of the same name
//! in [`twins`], tests compare the two within a stated tolerance, and a unit whose GPU run fails
//! (out of memory, device lost, a limit exceeded) runs on the CPU instead, with a warning.
//!
//! Device choice (`--device`): `auto` takes a hardware adapter when there is one and never a
//! software rasteriser (llvmpipe would be slower than the CPU kernel); `gpu` takes the best
//! adapter there is, software included, which is how the tests reach the shaders on machines
//! without a GPU; `cpu` opens nothing. `WGPU_BACKEND` (and the other `wgpu` environment
//! variables) choose the backends.

// A private layer: its `pub` items are the crate's own API and, with the `testing` feature, its
// integration tests' and benches' (`octstore::testing`). Some exist only for those (reference
// kernels, the GPU tests' reading helpers), so a build without the feature sees them unused.
#![cfg_attr(not(feature = "testing"), allow(dead_code, unused_imports))]
// `octstore::testing` is not the documented public surface: its items need no docs there.
#![cfg_attr(feature = "testing", allow(missing_docs))]

pub mod tgv_dispatch;
#[cfg(any(test, feature = "testing"))]
pub mod twins;
pub mod votes_dispatch;

pub use tgv_dispatch::solve_on;

use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};

/// Where the solver runs.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum DeviceChoice {
    /// A hardware GPU if there is one, else the CPU.
    #[default]
    Auto,
    /// The CPU kernel.
    Cpu,
    /// The best GPU adapter there is, a software one included; an error when there is none.
    Gpu,
}

impl DeviceChoice {
    /// The name `--device` takes, from clap's own value names.
    pub fn name(self) -> String {
        clap::ValueEnum::to_possible_value(&self).map_or_else(String::new, |v| v.get_name().to_string())
    }
}

/// Why the GPU could not be opened or could not run a unit. wgpu reports these as text, which
/// the variants carry; a unit that fails on the GPU runs on the CPU instead, with a warning.
#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    /// `--device gpu` found no adapter (wgpu's reason follows).
    #[error("no GPU adapter found (backends from WGPU_BACKEND, default all); {0}")]
    NoAdapter(String),
    /// The adapter was found but its device would not open.
    #[error("opening the device of adapter {adapter} failed: {message}")]
    RequestDevice {
        /// The adapter's name.
        adapter: String,
        /// wgpu's reason.
        message: String,
    },
    /// A unit needs a buffer larger than the adapter allows.
    #[error("the unit needs a {what} buffer of {needed} bytes; the adapter allows {limit}")]
    TooLarge {
        /// Which buffer.
        what: &'static str,
        /// Its size in bytes.
        needed: u64,
        /// The adapter's largest buffer, in bytes.
        limit: u64,
    },
    /// An allocation on the device failed.
    #[error("out of GPU memory: {0}")]
    OutOfMemory(String),
    /// The device was lost (driver reset, removal); it is not used again by this process.
    #[error("GPU device lost: {0}")]
    DeviceLost(String),
    /// wgpu rejected a call (a bug in octstore or the driver).
    #[error("GPU validation error: {0}")]
    Validation(String),
    /// Mapping a result buffer for reading failed.
    #[error("reading results back from the GPU failed: {0}")]
    Readback(String),
}

/// One adapter as `octstore info --devices` lists it.
#[derive(Clone, Debug, serde::Serialize)]
pub struct AdapterSummary {
    /// The adapter's name, as the driver reports it.
    pub name: String,
    /// The wgpu backend (Vulkan, Metal, ...).
    pub backend: String,
    /// Discrete, integrated, virtual or CPU.
    pub device_type: String,
    /// The driver's name and version.
    pub driver: String,
    /// A software rasteriser (llvmpipe, SwiftShader): never chosen by `auto`.
    pub software: bool,
    /// Largest storage buffer binding, in bytes.
    pub max_storage_binding: u64,
}

fn instance() -> wgpu::Instance {
    wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env())
}

fn summary(adapter: &wgpu::Adapter) -> AdapterSummary {
    let info = adapter.get_info();
    AdapterSummary {
        name: info.name.clone(),
        backend: format!("{:?}", info.backend),
        device_type: format!("{:?}", info.device_type),
        driver: format!("{} {}", info.driver, info.driver_info).trim().to_string(),
        software: info.device_type == wgpu::DeviceType::Cpu,
        max_storage_binding: adapter.limits().max_storage_buffer_binding_size,
    }
}

/// Every adapter wgpu finds, in its order.
pub fn adapters() -> Vec<AdapterSummary> {
    let instance = instance();
    pollster::block_on(instance.enumerate_adapters(wgpu::Backends::all()))
        .iter()
        .map(summary)
        .collect()
}

fn no_adapter() -> GpuError {
    GpuError::NoAdapter("on Debian, the package mesa-vulkan-drivers provides a software one (llvmpipe)".into())
}

/// Whether `dev` (Linux's `/dev`) holds a node through which a hardware GPU reaches Vulkan: a
/// DRM render node (AMD, Intel, virtio), NVIDIA's nodes, or WSL's `dxg`. Without one, `auto`
/// can only find a software rasteriser, which it never takes, and probing for it loads the
/// Vulkan drivers for nothing: on a machine without a GPU they stayed resident through the
/// run, 55 MB of RedKitchen's histogram step at 256 MiB (226 MB with `--device cpu`, 281 MB
/// with `auto`), past the budget.
fn may_have_hardware_gpu(dev: &Path) -> bool {
    let any_named = |dir: &Path, prefix: &str| {
        std::fs::read_dir(dir).is_ok_and(|entries| {
            entries
                .flatten()
                .any(|entry| entry.file_name().to_string_lossy().starts_with(prefix))
        })
    };
    any_named(&dev.join("dri"), "renderD") || any_named(dev, "nvidia") || dev.join("dxg").exists()
}

/// Preference among adapters: discrete, integrated, virtual, other, then software.
fn rank(device_type: wgpu::DeviceType) -> u8 {
    match device_type {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Other => 3,
        wgpu::DeviceType::Cpu => 4,
    }
}

/// An open device with the solver's pipelines.
pub struct Gpu {
    pub adapter: AdapterSummary,
    device: wgpu::Device,
    queue: wgpu::Queue,
    limits: wgpu::Limits,
    tgv: tgv_dispatch::Pipelines,
    votes: votes_dispatch::Pipeline,
    /// Set by the device-lost callback; later units go straight to the CPU.
    lost: Arc<AtomicBool>,
    /// Units whose iterations ran here, and units that fell back to the CPU.
    units: AtomicU64,
    fallbacks: AtomicU64,
}

impl Gpu {
    /// The device `choice` asks for: `None` for `cpu`, and for `auto` without a hardware GPU.
    pub fn open(choice: DeviceChoice) -> Result<Option<Gpu>, GpuError> {
        if choice == DeviceChoice::Cpu {
            return Ok(None);
        }
        if choice == DeviceChoice::Auto && cfg!(target_os = "linux") && !may_have_hardware_gpu(Path::new("/dev")) {
            return Ok(None);
        }
        let instance = instance();
        let mut found = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::all()));
        found.sort_by_key(|a| rank(a.get_info().device_type));
        let usable =
            |a: &wgpu::Adapter| choice == DeviceChoice::Gpu || a.get_info().device_type != wgpu::DeviceType::Cpu;
        let Some(adapter) = found.into_iter().find(usable) else {
            return match choice {
                DeviceChoice::Gpu => Err(no_adapter()),
                _ => Ok(None),
            };
        };
        Gpu::on(adapter).map(Some)
    }

    /// The adapter at `index` of [`adapters`]' list, whatever its kind (for benchmarks).
    pub fn open_adapter(index: usize) -> Result<Gpu, GpuError> {
        let instance = instance();
        let found = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::all()));
        let adapter = found.into_iter().nth(index).ok_or_else(no_adapter)?;
        Gpu::on(adapter)
    }

    fn on(adapter: wgpu::Adapter) -> Result<Gpu, GpuError> {
        let summary = summary(&adapter);
        // Everything the adapter allows: large leaves need large storage bindings.
        let limits = adapter.limits();
        let descriptor = wgpu::DeviceDescriptor {
            label: Some("octstore"),
            required_limits: limits.clone(),
            ..Default::default()
        };
        let (device, queue) =
            pollster::block_on(adapter.request_device(&descriptor)).map_err(|e| GpuError::RequestDevice {
                adapter: summary.name.clone(),
                message: e.to_string(),
            })?;
        let lost = Arc::new(AtomicBool::new(false));
        let flag = lost.clone();
        device.set_device_lost_callback(move |reason, message| {
            tracing::warn!("GPU device lost ({reason:?}): {message}");
            flag.store(true, Ordering::SeqCst);
        });
        // Errors outside an error scope would otherwise panic; every unit's work runs inside
        // scopes, so anything reaching this handler is logged, not fatal.
        device.on_uncaptured_error(Arc::new(|error| tracing::error!("uncaptured GPU error: {error}")));
        let tgv = tgv_dispatch::Pipelines::new(&device);
        let votes = votes_dispatch::Pipeline::new(&device);
        tracing::info!(
            "GPU: {} ({}, {}, {})",
            summary.name,
            summary.backend,
            summary.device_type,
            summary.driver
        );
        Ok(Gpu {
            adapter: summary,
            device,
            queue,
            limits,
            tgv,
            votes,
            lost,
            units: AtomicU64::new(0),
            fallbacks: AtomicU64::new(0),
        })
    }

    /// Caps the storage bindings this process will use below the adapter's limit, so that
    /// larger units take the CPU fallback (for tests of that path, and to leave room for other
    /// work on a shared GPU).
    pub fn with_binding_limit(mut self, bytes: u64) -> Gpu {
        self.limits.max_storage_buffer_binding_size = self.limits.max_storage_buffer_binding_size.min(bytes);
        self
    }

    /// (units run on this device, units that fell back to the CPU) so far.
    pub fn counts(&self) -> (u64, u64) {
        (self.units.load(Ordering::SeqCst), self.fallbacks.load(Ordering::SeqCst))
    }

    pub(crate) fn count(&self, on_gpu: bool) {
        let counter = if on_gpu { &self.units } else { &self.fallbacks };
        counter.fetch_add(1, Ordering::SeqCst);
    }

    /// Destroys the device, as a driver reset or a removed card would: the device-lost
    /// callback fires and every later unit runs on the CPU (for tests of that path).
    pub fn destroy(&self) {
        self.device.destroy();
        // wgpu reports the loss from its next poll; a failed poll means the same.
        if self.device.poll(wgpu::PollType::Poll).is_err() {
            self.lost.store(true, Ordering::SeqCst);
        }
    }

    pub fn is_lost(&self) -> bool {
        self.lost.load(Ordering::SeqCst)
    }

    /// A bind group of `pipeline`'s group 0 holding `buffers` whole, at bindings 0, 1, ...
    fn bind(&self, pipeline: &wgpu::ComputePipeline, buffers: &[&wgpu::Buffer]) -> wgpu::BindGroup {
        let entries: Vec<wgpu::BindGroupEntry<'_>> = buffers
            .iter()
            .enumerate()
            .map(|(binding, buffer)| wgpu::BindGroupEntry {
                binding: binding as u32,
                resource: buffer.as_entire_binding(),
            })
            .collect();
        self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: None,
            layout: &pipeline.get_bind_group_layout(0),
            entries: &entries,
        })
    }

    /// The largest storage binding this device takes, in bytes.
    fn binding_limit(&self) -> u64 {
        self.limits
            .max_storage_buffer_binding_size
            .min(self.limits.max_buffer_size)
    }

    /// Checks that one storage binding of `bytes` fits the device.
    fn check_binding(&self, what: &'static str, bytes: u64) -> Result<(), GpuError> {
        let limit = self.binding_limit();
        if bytes > limit {
            return Err(GpuError::TooLarge {
                what,
                needed: bytes,
                limit,
            });
        }
        Ok(())
    }

    /// Runs `work` inside out-of-memory and validation error scopes, and turns what they catch
    /// (or a lost device) into an error.
    pub(crate) fn scoped<T>(&self, work: impl FnOnce() -> Result<T, GpuError>) -> Result<T, GpuError> {
        if self.is_lost() {
            return Err(GpuError::DeviceLost("lost during an earlier unit".into()));
        }
        let out_of_memory = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let validation = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let result = work();
        let invalid = pollster::block_on(validation.pop());
        let exhausted = pollster::block_on(out_of_memory.pop());
        if let Some(error) = exhausted {
            return Err(GpuError::OutOfMemory(error.to_string()));
        }
        if let Some(error) = invalid {
            return Err(GpuError::Validation(error.to_string()));
        }
        if self.is_lost() {
            return Err(GpuError::DeviceLost("during this unit".into()));
        }
        result
    }
}

/// Workgroups for `n` invocations of a 256-wide shader, as a 2-D grid within the per-dimension
/// limit; returns (x, y, invocations per grid row).
pub fn grid(n: u32, max_per_dimension: u32) -> (u32, u32, u32) {
    let groups = n.div_ceil(WORKGROUP_SIZE).max(1);
    let x = groups.min(max_per_dimension.max(1));
    let y = groups.div_ceil(x);
    (x, y, x * WORKGROUP_SIZE)
}

/// `@workgroup_size` of every compute shader.
pub const WORKGROUP_SIZE: u32 = 256;

/// Copies `(buffer, bytes)` pairs into one mappable buffer and returns each one's bytes.
pub(crate) fn read_back(gpu: &Gpu, parts: &[(&wgpu::Buffer, u64)]) -> Result<Vec<Vec<u8>>, GpuError> {
    // Copies must be multiples of 4 bytes at offsets that are too; every part here is.
    let total: u64 = parts.iter().map(|(_, bytes)| *bytes).sum();
    if total == 0 {
        return Ok(parts.iter().map(|_| Vec::new()).collect());
    }
    let staging = gpu.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some("read back"),
        size: total,
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    });
    let mut encoder = gpu.device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
        label: Some("read back"),
    });
    let mut offset = 0;
    for (buffer, bytes) in parts {
        if *bytes > 0 {
            encoder.copy_buffer_to_buffer(buffer, 0, &staging, offset, *bytes);
        }
        offset += bytes;
    }
    gpu.queue.submit([encoder.finish()]);
    let (sender, receiver) = std::sync::mpsc::channel();
    staging.map_async(wgpu::MapMode::Read, .., move |result| {
        let _ = sender.send(result);
    });
    gpu.device
        .poll(wgpu::PollType::wait_indefinitely())
        .map_err(|e| GpuError::Readback(e.to_string()))?;
    receiver
        .recv()
        .map_err(|e| GpuError::Readback(e.to_string()))?
        .map_err(|e| GpuError::Readback(e.to_string()))?;
    let out = {
        let view = staging
            .slice(..)
            .get_mapped_range()
            .map_err(|e| GpuError::Readback(e.to_string()))?;
        let mut out = Vec::with_capacity(parts.len());
        let mut offset = 0usize;
        for (_, bytes) in parts {
            let end = offset + *bytes as usize;
            out.push(view.get(offset..end).unwrap_or(&[]).to_vec());
            offset = end;
        }
        out
    };
    staging.unmap();
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::may_have_hardware_gpu;

    #[test]
    fn hardware_gpu_nodes_are_recognised_and_their_absence_too() {
        let dev = tempfile::tempdir().unwrap();
        let path = dev.path();
        // A VM without a GPU: no dri folder, or one with only a display card node.
        assert!(!may_have_hardware_gpu(path));
        std::fs::create_dir(path.join("dri")).unwrap();
        std::fs::write(path.join("dri").join("card0"), b"").unwrap();
        assert!(!may_have_hardware_gpu(path));
        std::fs::write(path.join("dri").join("renderD128"), b"").unwrap();
        assert!(may_have_hardware_gpu(path));
        let nvidia = tempfile::tempdir().unwrap();
        std::fs::write(nvidia.path().join("nvidia0"), b"").unwrap();
        assert!(may_have_hardware_gpu(nvidia.path()));
        let wsl = tempfile::tempdir().unwrap();
        std::fs::write(wsl.path().join("dxg"), b"").unwrap();
        assert!(may_have_hardware_gpu(wsl.path()));
    }
}
