//! Host side of `shaders/tgv_dual.wgsl` and `shaders/tgv_primal.wgsl`: the compiled
//! [`Kernel`]'s columns and gather lists are uploaded as they are (the structs are `#[repr(C)]`
//! and bytemuck, checked against the shaders' layout by a test), the iterations run as pairs of
//! dispatches, and the packed state is read back.

use glam::Vec4;
use wgpu::util::DeviceExt;

use super::{Gpu, GpuError, grid};
use crate::stages::tgv::{Kernel, Packed};

/// The uniform both shaders read (`Params` in the WGSL).
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct Params {
    pub n: u32,
    pub lambda: f32,
    /// Invocations per row of the 2-D dispatch grid.
    pub row_stride: u32,
    pub padding: u32,
}

pub const DUAL_SHADER: &str = include_str!("../../shaders/tgv_dual.wgsl");
pub const PRIMAL_SHADER: &str = include_str!("../../shaders/tgv_primal.wgsl");

/// Iterations recorded per submission: few enough that one command buffer never runs long
/// enough to trip a driver watchdog on a large leaf, many enough that submission is noise.
const ITERATIONS_PER_SUBMIT: usize = 25;

pub struct Pipelines {
    dual: wgpu::ComputePipeline,
    primal: wgpu::ComputePipeline,
}

fn pipeline(device: &wgpu::Device, label: &str, source: &str) -> wgpu::ComputePipeline {
    let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
        label: Some(label),
        source: wgpu::ShaderSource::Wgsl(source.into()),
    });
    device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some(label),
        layout: None,
        module: &module,
        entry_point: Some("main"),
        compilation_options: wgpu::PipelineCompilationOptions::default(),
        cache: None,
    })
}

impl Pipelines {
    pub fn new(device: &wgpu::Device) -> Pipelines {
        Pipelines {
            dual: pipeline(device, "tgv_dual", DUAL_SHADER),
            primal: pipeline(device, "tgv_primal", PRIMAL_SHADER),
        }
    }
}

/// Bytes of a slice, padded to one element of 16 bytes when empty: a binding cannot be empty.
fn contents<T: bytemuck::Pod>(values: &[T]) -> &[u8] {
    const EMPTY: [u8; 16] = [0; 16];
    if values.is_empty() {
        &EMPTY
    } else {
        bytemuck::cast_slice(values)
    }
}

/// Runs `iterations` steps of `kernel` on `state` on the GPU. On error `state` is untouched, so
/// the caller can run the same iterations on the CPU.
pub fn iterate(gpu: &Gpu, kernel: &Kernel, state: &mut Packed, iterations: usize) -> Result<(), GpuError> {
    let n = kernel.n;
    if n == 0 || iterations == 0 {
        return Ok(());
    }
    let n32 = u32::try_from(n).map_err(|_| GpuError::TooLarge {
        what: "cube index",
        needed: n as u64,
        limit: u64::from(u32::MAX),
    })?;
    let vec4_bytes = std::mem::size_of::<Vec4>() as u64;
    for (what, bytes) in [
        ("bar", (n + kernel.frozen.len()) as u64 * vec4_bytes),
        ("dual rows", 3 * n as u64 * vec4_bytes),
        ("D terms", std::mem::size_of_val(kernel.row_terms.as_slice()) as u64),
        (
            "adjoint terms",
            std::mem::size_of_val(kernel.col_terms.as_slice()) as u64,
        ),
        (
            "dual constants",
            std::mem::size_of_val(kernel.dual_constants.as_slice()) as u64,
        ),
    ] {
        gpu.check_binding(what, bytes)?;
    }
    let (groups_x, groups_y, row_stride) = grid(n32, gpu.limits.max_compute_workgroups_per_dimension);
    let params = Params {
        n: n32,
        lambda: kernel.lambda,
        row_stride,
        padding: 0,
    };
    let device = &gpu.device;
    let result = gpu.scoped(|| {
        let storage = wgpu::BufferUsages::STORAGE;
        let buffer = |label: &str, bytes: &[u8], usage: wgpu::BufferUsages| {
            device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: bytes,
                usage,
            })
        };
        let bar_init: Vec<Vec4> = state.uv.iter().chain(&kernel.frozen).copied().collect();
        let params = buffer("params", bytemuck::bytes_of(&params), wgpu::BufferUsages::UNIFORM);
        let bar = buffer("bar", contents(&bar_init), storage);
        let row_start = buffer("row_start", contents(&kernel.row_start), storage);
        let row_terms = buffer("row_terms", contents(&kernel.row_terms), storage);
        let dual_constants = buffer("dual_constants", contents(&kernel.dual_constants), storage);
        let copy_out = storage | wgpu::BufferUsages::COPY_SRC;
        let p = buffer("p", contents(&state.p), copy_out);
        let q_diag = buffer("q_diag", contents(&state.q_diag), copy_out);
        let q_off = buffer("q_off", contents(&state.q_off), copy_out);
        let rows = device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("rows"),
            size: 3 * n as u64 * vec4_bytes,
            usage: storage,
            mapped_at_creation: false,
        });
        let col_start = buffer("col_start", contents(&kernel.col_start), storage);
        let col_terms = buffer("col_terms", contents(&kernel.col_terms), storage);
        let primal_constants = buffer("primal_constants", contents(&kernel.primal_constants), storage);
        let slopes = buffer("slopes", contents(&kernel.slopes), storage);
        let uv = buffer("uv", contents(&state.uv), copy_out);
        let bind = |pipeline, buffers: &[&wgpu::Buffer]| gpu.bind(pipeline, buffers);
        let dual_group = bind(
            &gpu.tgv.dual,
            &[
                &params,
                &bar,
                &row_start,
                &row_terms,
                &dual_constants,
                &p,
                &q_diag,
                &q_off,
                &rows,
            ],
        );
        let primal_group = bind(
            &gpu.tgv.primal,
            &[
                &params,
                &rows,
                &col_start,
                &col_terms,
                &primal_constants,
                &slopes,
                &uv,
                &bar,
            ],
        );
        let mut done = 0;
        while done < iterations {
            let batch = (iterations - done).min(ITERATIONS_PER_SUBMIT);
            let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("tgv") });
            {
                let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("tgv iterations"),
                    timestamp_writes: None,
                });
                for _ in 0..batch {
                    pass.set_pipeline(&gpu.tgv.dual);
                    pass.set_bind_group(0, &dual_group, &[]);
                    pass.dispatch_workgroups(groups_x, groups_y, 1);
                    pass.set_pipeline(&gpu.tgv.primal);
                    pass.set_bind_group(0, &primal_group, &[]);
                    pass.dispatch_workgroups(groups_x, groups_y, 1);
                }
            }
            gpu.queue.submit([encoder.finish()]);
            done += batch;
        }
        read_back(gpu, &[&uv, &p, &q_diag, &q_off], n as u64 * vec4_bytes)
    })?;
    let mut columns = result.into_iter();
    let mut next = || {
        columns
            .next()
            .ok_or_else(|| GpuError::Readback("missing column".into()))
    };
    let (uv, p, q_diag, q_off) = (next()?, next()?, next()?, next()?);
    state.uv = uv;
    state.p = p;
    state.q_diag = q_diag;
    state.q_off = q_off;
    Ok(())
}

/// Reads each of `buffers` (`bytes` long) back as packed vectors.
fn read_back(gpu: &Gpu, buffers: &[&wgpu::Buffer], bytes: u64) -> Result<Vec<Vec<Vec4>>, GpuError> {
    let parts: Vec<(&wgpu::Buffer, u64)> = buffers.iter().map(|buffer| (*buffer, bytes)).collect();
    Ok(super::read_back(gpu, &parts)?
        .iter()
        .map(|part| bytemuck::pod_collect_to_vec(part))
        .collect())
}
