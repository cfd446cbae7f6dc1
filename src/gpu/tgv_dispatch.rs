//! Host side of `shaders/tgv_dual.wgsl` and `shaders/tgv_primal.wgsl`: the compiled
//! [`Kernel`]'s columns and gather lists are uploaded as they are (the structs are `#[repr(C)]`
//! and bytemuck, checked against the shaders' layout by a test), the iterations run as pairs of
//! dispatches, and the packed state is read back.
//!
//! A unit whose buffers exceed a storage binding is split into chunks of consecutive cubes
//! ([`split`]), each a kernel of its own with local indices: its `bar` holds its own cubes,
//! then copies of the other chunks' cubes its gathers read (the halo), then the frozen
//! neighbours it reads; its dual rows likewise hold its own rows, then halo copies.
//! `shaders/halo.wgsl` refreshes the halos after every dual and every primal pass, so each
//! chunk computes from exactly the values the whole unit would, and the result is the same bit
//! for bit. All chunks stay resident: GPU memory is bounded by the unit, which the memory
//! budget bounds; only the bindings are split.

use glam::Vec4;
use wgpu::util::DeviceExt;

use super::{Gpu, GpuError, grid};
use crate::kernels::tgv::{Gather, Kernel, Packed, Problem, Solved, State, Stopping};

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
pub const HALO_SHADER: &str = include_str!("../../shaders/halo.wgsl");

/// The uniform of `shaders/halo.wgsl` (`HaloParams` in the WGSL): copies `count` entries into
/// `destination[offset ..]`.
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct HaloParams {
    pub count: u32,
    pub offset: u32,
    pub row_stride: u32,
    pub padding: u32,
}

/// Iterations recorded per submission: few enough that one command buffer never runs long
/// enough to trip a driver watchdog on a large leaf, many enough that submission is noise.
const ITERATIONS_PER_SUBMIT: usize = 25;

pub struct Pipelines {
    dual: wgpu::ComputePipeline,
    primal: wgpu::ComputePipeline,
    halo: wgpu::ComputePipeline,
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
            halo: pipeline(device, "halo", HALO_SHADER),
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

/// Copies into a chunk's halo: entry `offset + j` of the destination array (the chunk's `bar`
/// or its dual rows) is entry `indices[j]` of chunk `source`'s array of the same kind.
#[derive(Clone, Debug, PartialEq)]
pub struct HaloRun {
    pub source: usize,
    pub offset: u32,
    pub indices: Vec<u32>,
}

/// Free cubes `start .. start + kernel.n` of a split kernel. The kernel's indices are local:
/// its `frozen` holds the halo's places (filled by the first exchange) and then the frozen
/// neighbours this chunk reads; its adjoint gathers read dual rows `3 n ..` from the row halo.
pub struct Chunk {
    pub start: usize,
    pub kernel: Kernel,
    pub bar_halo: Vec<HaloRun>,
    pub row_halo: Vec<HaloRun>,
}

impl Chunk {
    /// Entries of the chunk's dual-row array: its own rows, then the halo's.
    pub fn rows_len(&self) -> usize {
        3 * self.kernel.n + self.row_halo.iter().map(|run| run.indices.len()).sum::<usize>()
    }
}

/// Groups sorted global indices into runs by the chunk that owns them; `owner` maps an index
/// to (chunk, index local to that chunk), and the runs fill the destination from `first` on.
fn runs(sorted: &[u32], first: usize, owner: impl Fn(u32) -> (usize, u32)) -> Vec<HaloRun> {
    let mut runs: Vec<HaloRun> = Vec::new();
    for (position, &global) in sorted.iter().enumerate() {
        let (source, local) = owner(global);
        match runs.last_mut() {
            Some(run) if run.source == source => run.indices.push(local),
            _ => runs.push(HaloRun {
                source,
                offset: (first + position) as u32,
                indices: vec![local],
            }),
        }
    }
    runs
}

/// Splits `kernel` into chunks of `cubes` consecutive free cubes (the last may be shorter).
/// Iterating the chunks with halo exchanges between the passes computes exactly what
/// iterating `kernel` does (`twins::iterate_chunks` shows it bit for bit).
pub fn split(kernel: &Kernel, cubes: usize) -> Vec<Chunk> {
    let n = kernel.n;
    let cubes = cubes.max(1);
    let span = |starts: &[u32], first: usize, last: usize| -> std::ops::Range<usize> {
        let at = |i: usize| starts.get(i).copied().unwrap_or(0) as usize;
        at(first)..at(last).max(at(first))
    };
    (0..n)
        .step_by(cubes)
        .map(|start| {
            let end = (start + cubes).min(n);
            let len = end - start;
            let own = start..end;
            let dual_terms = kernel
                .row_terms
                .get(span(&kernel.row_start, 3 * start, 3 * end))
                .unwrap_or(&[]);
            let adjoint_terms = kernel.col_terms.get(span(&kernel.col_start, start, end)).unwrap_or(&[]);
            // Distinct outside targets, sorted, so each source chunk's copies form one run.
            let outside = |terms: &[Gather], inside: &dyn Fn(usize) -> bool, keep: &dyn Fn(usize) -> bool| {
                let set: std::collections::BTreeSet<u32> = terms
                    .iter()
                    .map(|t| t.index)
                    .filter(|&i| !inside(i as usize) && keep(i as usize))
                    .collect();
                set.into_iter().collect::<Vec<u32>>()
            };
            let in_own = |i: usize| own.contains(&i);
            let halo = outside(dual_terms, &in_own, &|i| i < n);
            let frozen = outside(dual_terms, &in_own, &|i| i >= n);
            let in_own_rows = |r: usize| (3 * start..3 * end).contains(&r);
            let halo_rows = outside(adjoint_terms, &in_own_rows, &|_| true);
            let position = |sorted: &[u32], i: u32| sorted.binary_search(&i).unwrap_or(0);
            let local_bar = |i: u32| -> u32 {
                let g = i as usize;
                (if own.contains(&g) {
                    g - start
                } else if g < n {
                    len + position(&halo, i)
                } else {
                    len + halo.len() + position(&frozen, i)
                }) as u32
            };
            let local_row = |r: u32| -> u32 {
                let g = r as usize;
                (if in_own_rows(g) {
                    g - 3 * start
                } else {
                    3 * len + position(&halo_rows, r)
                }) as u32
            };
            let rebase = |starts: &[u32], first: usize, last: usize| -> Vec<u32> {
                let base = starts.get(first).copied().unwrap_or(0);
                (first..=last)
                    .map(|i| starts.get(i).copied().unwrap_or(base).saturating_sub(base))
                    .collect()
            };
            let gathers = |terms: &[Gather], local: &dyn Fn(u32) -> u32| -> Vec<Gather> {
                terms
                    .iter()
                    .map(|t| Gather {
                        index: local(t.index),
                        weight: t.weight,
                    })
                    .collect()
            };
            let chunk_kernel = Kernel {
                n: len,
                row_start: rebase(&kernel.row_start, 3 * start, 3 * end),
                row_terms: gathers(dual_terms, &local_bar),
                col_start: rebase(&kernel.col_start, start, end),
                col_terms: gathers(adjoint_terms, &local_row),
                dual_constants: column(&kernel.dual_constants, &own),
                primal_constants: column(&kernel.primal_constants, &own),
                lengths: column(&kernel.lengths, &own),
                frozen: std::iter::repeat_n(Vec4::ZERO, halo.len())
                    .chain(
                        frozen
                            .iter()
                            .map(|&i| kernel.frozen.get(i as usize - n).copied().unwrap_or(Vec4::ZERO)),
                    )
                    .collect(),
                slopes: column(&kernel.slopes, &own),
                lambda: kernel.lambda,
            };
            let cube_owner = |i: u32| {
                let g = i as usize;
                (g / cubes, (g % cubes) as u32)
            };
            let row_owner = |r: u32| {
                let g = r as usize;
                let source = g / 3 / cubes;
                (source, (g - 3 * source * cubes) as u32)
            };
            Chunk {
                start,
                bar_halo: runs(&halo, len, cube_owner),
                row_halo: runs(&halo_rows, 3 * len, row_owner),
                kernel: chunk_kernel,
            }
        })
        .collect()
}

fn column<T: Clone>(values: &[T], own: &std::ops::Range<usize>) -> Vec<T> {
    values.get(own.clone()).unwrap_or(&[]).to_vec()
}

/// The storage bindings one chunk needs, in bytes.
fn bindings(kernel: &Kernel, rows_len: usize, runs: &[&HaloRun]) -> Vec<(&'static str, u64)> {
    let vec4_bytes = std::mem::size_of::<Vec4>() as u64;
    let bytes_of = |values: usize, size: usize| (values * size) as u64;
    let longest_run = runs.iter().map(|run| run.indices.len()).max().unwrap_or(0);
    vec![
        ("bar", (kernel.n + kernel.frozen.len()) as u64 * vec4_bytes),
        ("dual rows", rows_len as u64 * vec4_bytes),
        ("D terms", std::mem::size_of_val(kernel.row_terms.as_slice()) as u64),
        (
            "adjoint terms",
            std::mem::size_of_val(kernel.col_terms.as_slice()) as u64,
        ),
        (
            "D row starts",
            std::mem::size_of_val(kernel.row_start.as_slice()) as u64,
        ),
        (
            "dual constants",
            std::mem::size_of_val(kernel.dual_constants.as_slice()) as u64,
        ),
        (
            "primal constants",
            std::mem::size_of_val(kernel.primal_constants.as_slice()) as u64,
        ),
        ("slopes", std::mem::size_of_val(kernel.slopes.as_slice()) as u64),
        ("halo indices", bytes_of(longest_run, std::mem::size_of::<u32>())),
    ]
}

/// One piece of the unit as the GPU runs it: the whole kernel, or a chunk of it.
struct Part<'k> {
    start: usize,
    kernel: &'k Kernel,
    rows_len: usize,
    bar_halo: &'k [HaloRun],
    row_halo: &'k [HaloRun],
}

/// The chunks of `kernel` that fit `gpu`'s bindings: none when the whole kernel fits (it runs
/// as it is, with no copy), else halving chunk sizes until every chunk fits. Fails only when
/// chunks of one cube still do not.
fn chunks_for(gpu: &Gpu, kernel: &Kernel) -> Result<Option<Vec<Chunk>>, GpuError> {
    let fits = |kernel: &Kernel, rows_len: usize, runs: &[&HaloRun]| -> Result<(), GpuError> {
        bindings(kernel, rows_len, runs)
            .into_iter()
            .try_for_each(|(what, bytes)| gpu.check_binding(what, bytes))
    };
    let Err(mut error) = fits(kernel, 3 * kernel.n, &[]) else {
        return Ok(None);
    };
    let mut cubes = kernel.n / 2;
    while cubes > 0 {
        let chunks = split(kernel, cubes);
        let checked = chunks.iter().try_for_each(|chunk| {
            let runs: Vec<&HaloRun> = chunk.bar_halo.iter().chain(&chunk.row_halo).collect();
            fits(&chunk.kernel, chunk.rows_len(), &runs)
        });
        match checked {
            Ok(()) => return Ok(Some(chunks)),
            Err(e) => error = e,
        }
        cubes /= 2;
    }
    Err(error)
}

// long function iterate: buffer creation, bind groups and the dispatch loop share every buffer handle; split, each part would take a dozen of them as arguments.
/// Runs `iterations` steps of `kernel` on `state` on the GPU, in chunks when the unit's buffers
/// exceed a binding. On error `state` is untouched, so the caller can run the same iterations
/// on the CPU.
pub fn iterate(gpu: &Gpu, kernel: &Kernel, state: &mut Packed, iterations: usize) -> Result<(), GpuError> {
    let n = kernel.n;
    if n == 0 || iterations == 0 {
        return Ok(());
    }
    u32::try_from(n + kernel.frozen.len()).map_err(|_| GpuError::TooLarge {
        what: "cube index",
        needed: (n + kernel.frozen.len()) as u64,
        limit: u64::from(u32::MAX),
    })?;
    let chunks = chunks_for(gpu, kernel)?;
    let parts: Vec<Part<'_>> = match &chunks {
        None => vec![Part {
            start: 0,
            kernel,
            rows_len: 3 * n,
            bar_halo: &[],
            row_halo: &[],
        }],
        Some(chunks) => chunks
            .iter()
            .map(|chunk| Part {
                start: chunk.start,
                kernel: &chunk.kernel,
                rows_len: chunk.rows_len(),
                bar_halo: &chunk.bar_halo,
                row_halo: &chunk.row_halo,
            })
            .collect(),
    };
    if parts.len() > 1 {
        tracing::debug!("GPU: a unit of {n} cubes runs in {} chunks", parts.len());
    }
    let vec4_bytes = std::mem::size_of::<Vec4>() as u64;
    let device = &gpu.device;
    let max_groups = gpu.limits.max_compute_workgroups_per_dimension;
    let columns = gpu.scoped(|| {
        let storage = wgpu::BufferUsages::STORAGE;
        let buffer = |label: &str, bytes: &[u8], usage: wgpu::BufferUsages| {
            device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(label),
                contents: bytes,
                usage,
            })
        };
        let copy_out = storage | wgpu::BufferUsages::COPY_SRC;
        struct OnGpu {
            bar: wgpu::Buffer,
            rows: wgpu::Buffer,
            uv: wgpu::Buffer,
            p: wgpu::Buffer,
            q_diag: wgpu::Buffer,
            q_off: wgpu::Buffer,
            dual: wgpu::BindGroup,
            primal: wgpu::BindGroup,
            grid: (u32, u32),
        }
        let mut on_gpu = Vec::with_capacity(parts.len());
        for part in &parts {
            let k = part.kernel;
            let own = part.start..part.start + k.n;
            let slice = |values: &[Vec4]| values.get(own.clone()).unwrap_or(&[]).to_vec();
            let (groups_x, groups_y, row_stride) = grid(k.n as u32, max_groups);
            let params = Params {
                n: k.n as u32,
                lambda: k.lambda,
                row_stride,
                padding: 0,
            };
            let bar_init: Vec<Vec4> = slice(&state.uv).into_iter().chain(k.frozen.iter().copied()).collect();
            let params = buffer("params", bytemuck::bytes_of(&params), wgpu::BufferUsages::UNIFORM);
            let bar = buffer("bar", contents(&bar_init), storage);
            let row_start = buffer("row_start", contents(&k.row_start), storage);
            let row_terms = buffer("row_terms", contents(&k.row_terms), storage);
            let dual_constants = buffer("dual_constants", contents(&k.dual_constants), storage);
            let p = buffer("p", contents(&slice(&state.p)), copy_out);
            let q_diag = buffer("q_diag", contents(&slice(&state.q_diag)), copy_out);
            let q_off = buffer("q_off", contents(&slice(&state.q_off)), copy_out);
            let rows = device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("rows"),
                size: part.rows_len as u64 * vec4_bytes,
                usage: storage,
                mapped_at_creation: false,
            });
            let col_start = buffer("col_start", contents(&k.col_start), storage);
            let col_terms = buffer("col_terms", contents(&k.col_terms), storage);
            let primal_constants = buffer("primal_constants", contents(&k.primal_constants), storage);
            let slopes = buffer("slopes", contents(&k.slopes), storage);
            let uv = buffer("uv", contents(&slice(&state.uv)), copy_out);
            let dual = gpu.bind(
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
            let primal = gpu.bind(
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
            on_gpu.push(OnGpu {
                bar,
                rows,
                uv,
                p,
                q_diag,
                q_off,
                dual,
                primal,
                grid: (groups_x, groups_y),
            });
        }
        // Halo copies, as (bind group, grid) per run: rows after the dual pass, bar after the
        // primal pass (and once before the first iteration, to fill the halo).
        let halo_copies = |of_rows: bool| {
            let array_of = |on: &OnGpu| if of_rows { on.rows.clone() } else { on.bar.clone() };
            let mut copies = Vec::new();
            for (part, destination) in parts.iter().zip(&on_gpu) {
                let runs = if of_rows { part.row_halo } else { part.bar_halo };
                for run in runs {
                    let Some(source) = on_gpu.get(run.source) else { continue };
                    let count = run.indices.len() as u32;
                    let (groups_x, groups_y, row_stride) = grid(count, max_groups);
                    let params = HaloParams {
                        count,
                        offset: run.offset,
                        row_stride,
                        padding: 0,
                    };
                    let params = buffer("halo params", bytemuck::bytes_of(&params), wgpu::BufferUsages::UNIFORM);
                    let indices = buffer("halo indices", contents(&run.indices), storage);
                    let group = gpu.bind(
                        &gpu.tgv.halo,
                        &[&params, &array_of(source), &indices, &array_of(destination)],
                    );
                    copies.push((group, (groups_x, groups_y)));
                }
            }
            copies
        };
        let row_copies = halo_copies(true);
        let bar_copies = halo_copies(false);
        let run_copies = |pass: &mut wgpu::ComputePass<'_>, copies: &[(wgpu::BindGroup, (u32, u32))]| {
            if copies.is_empty() {
                return;
            }
            pass.set_pipeline(&gpu.tgv.halo);
            for (group, (x, y)) in copies {
                pass.set_bind_group(0, group, &[]);
                pass.dispatch_workgroups(*x, *y, 1);
            }
        };
        let mut done = 0;
        let mut first = true;
        while done < iterations {
            let batch = (iterations - done).min(ITERATIONS_PER_SUBMIT);
            let mut encoder = device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("tgv") });
            {
                let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("tgv iterations"),
                    timestamp_writes: None,
                });
                if first {
                    run_copies(&mut pass, &bar_copies);
                    first = false;
                }
                for _ in 0..batch {
                    pass.set_pipeline(&gpu.tgv.dual);
                    for chunk in &on_gpu {
                        pass.set_bind_group(0, &chunk.dual, &[]);
                        pass.dispatch_workgroups(chunk.grid.0, chunk.grid.1, 1);
                    }
                    run_copies(&mut pass, &row_copies);
                    pass.set_pipeline(&gpu.tgv.primal);
                    for chunk in &on_gpu {
                        pass.set_bind_group(0, &chunk.primal, &[]);
                        pass.dispatch_workgroups(chunk.grid.0, chunk.grid.1, 1);
                    }
                    run_copies(&mut pass, &bar_copies);
                }
            }
            gpu.queue.submit([encoder.finish()]);
            done += batch;
        }
        let mut columns = Vec::with_capacity(parts.len());
        for (part, chunk) in parts.iter().zip(&on_gpu) {
            let bytes = part.kernel.n as u64 * vec4_bytes;
            columns.push(read_back(
                gpu,
                &[&chunk.uv, &chunk.p, &chunk.q_diag, &chunk.q_off],
                bytes,
            )?);
        }
        Ok(columns)
    })?;
    let mut out = Packed {
        uv: Vec::with_capacity(n),
        p: Vec::with_capacity(n),
        q_diag: Vec::with_capacity(n),
        q_off: Vec::with_capacity(n),
    };
    for part in columns {
        let [uv, p, q_diag, q_off]: [Vec<Vec4>; 4] = part
            .try_into()
            .map_err(|_| GpuError::Readback("missing column".into()))?;
        out.uv.extend(uv);
        out.p.extend(p);
        out.q_diag.extend(q_diag);
        out.q_off.extend(q_off);
    }
    if out.uv.len() != n {
        return Err(GpuError::Readback(format!("{} of {n} cubes came back", out.uv.len())));
    }
    *state = out;
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

/// [`crate::kernels::tgv::solve_accelerated`] with the iterations on `gpu` when given. A GPU
/// failure (out of memory, device lost, a buffer over the adapter's limits) is logged and the
/// failed batch and the rest run on the CPU, from the state the last good batch left.
pub fn solve_on(gpu: Option<&Gpu>, problem: &Problem, state: &mut State, stopping: Stopping) -> Solved {
    let mut failed = false;
    let mut used = false;
    let solved = crate::kernels::tgv::solve_accelerated(problem, state, stopping, |kernel, packed, iterations| {
        let Some(gpu) = gpu else { return false };
        used = true;
        match iterate(gpu, kernel, packed, iterations) {
            Ok(()) => true,
            Err(error) => {
                tracing::warn!("{error}; this unit's {} cubes run on the CPU", kernel.n);
                failed = true;
                false
            }
        }
    });
    if let (Some(gpu), true) = (gpu, used) {
        gpu.count(!failed);
    }
    solved
}
