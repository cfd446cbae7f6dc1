//! CPU twins of the WGSL shaders, one function per shader with the shader's name, written
//! invocation by invocation in the shader's arithmetic order on the same buffers. They pin
//! down what a shader computes: tests check each twin against the CPU solver (bit for bit) and
//! the GPU against the twin (within a tolerance, since a GPU may fuse multiply-adds).

use glam::Vec4;

use super::tgv_dispatch::{Chunk, HaloRun};
use crate::kernels::tgv::{DualConstants, Gather, Kernel, Packed, PrimalConstants, Slopes};

const SQRT_HALF: f32 = std::f32::consts::FRAC_1_SQRT_2;

fn unit_ball_scale(squared_norm: f32) -> f32 {
    1.0 / squared_norm.sqrt().max(1.0)
}

fn sum3(x: Vec4) -> f32 {
    x.x * x.x + x.y * x.y + x.z * x.z
}

fn at<T: Copy + Default>(values: &[T], index: usize) -> T {
    values.get(index).copied().unwrap_or_default()
}

/// The buffers `tgv_dual.wgsl` binds.
pub struct DualBuffers<'a> {
    pub bar: &'a [Vec4],
    pub row_start: &'a [u32],
    pub row_terms: &'a [Gather],
    pub constants: &'a [DualConstants],
    pub p: &'a mut [Vec4],
    pub q_diag: &'a mut [Vec4],
    pub q_off: &'a mut [Vec4],
    pub rows: &'a mut [Vec4],
}

/// Twin of `shaders/tgv_dual.wgsl`, invocation `c`.
pub fn tgv_dual(c: usize, b: &mut DualBuffers<'_>) {
    let centre = at(b.bar, c);
    let difference = |row: usize| {
        let mut acc = Vec4::ZERO;
        for t in at(b.row_start, row)..at(b.row_start, row + 1) {
            let term = at(b.row_terms, t as usize);
            acc += term.weight * (at(b.bar, term.index as usize) - centre);
        }
        acc
    };
    let (ax, ay, az) = (difference(3 * c), difference(3 * c + 1), difference(3 * c + 2));
    let du = Vec4::new(ax.x, ay.x, az.x, 0.0);
    let dv0 = Vec4::new(ax.y, ay.y, az.y, 0.0);
    let dv1 = Vec4::new(ax.z, ay.z, az.z, 0.0);
    let dv2 = Vec4::new(ax.w, ay.w, az.w, 0.0);
    let Some(k) = b.constants.get(c) else { return };
    let v = Vec4::new(centre.y, centre.z, centre.w, 0.0);
    let moved_p = at(b.p, c) + k.sigma_p * (du - v);
    let new_p = moved_p * unit_ball_scale(sum3(moved_p));
    let diag = Vec4::new(dv0.x, dv1.y, dv2.z, 0.0);
    let off = SQRT_HALF * Vec4::new(dv0.y + dv1.x, dv0.z + dv2.x, dv1.z + dv2.y, 0.0);
    let moved_qd = at(b.q_diag, c) + k.sigma_q_diag * diag;
    let moved_qo = at(b.q_off, c) + k.sigma_q_off * off;
    let s = unit_ball_scale(sum3(moved_qd) + sum3(moved_qo));
    let (qd, qo) = (moved_qd * s, moved_qo * s);
    let (a1, a0) = (k.sigma_p.w, k.sigma_q_diag.w);
    let (o3, o4, o5) = (SQRT_HALF * qo.x, SQRT_HALF * qo.y, SQRT_HALF * qo.z);
    let packed = [
        Vec4::new(a1 * new_p.x, a0 * qd.x, a0 * o3, a0 * o4),
        Vec4::new(a1 * new_p.y, a0 * o3, a0 * qd.y, a0 * o5),
        Vec4::new(a1 * new_p.z, a0 * o4, a0 * o5, a0 * qd.z),
    ];
    if let Some(slot) = b.p.get_mut(c) {
        *slot = new_p;
    }
    if let Some(slot) = b.q_diag.get_mut(c) {
        *slot = qd;
    }
    if let Some(slot) = b.q_off.get_mut(c) {
        *slot = qo;
    }
    for (axis, value) in packed.into_iter().enumerate() {
        if let Some(slot) = b.rows.get_mut(3 * c + axis) {
            *slot = value;
        }
    }
}

/// The buffers `tgv_primal.wgsl` binds.
pub struct PrimalBuffers<'a> {
    pub lambda: f32,
    pub rows: &'a [Vec4],
    pub col_start: &'a [u32],
    pub col_terms: &'a [Gather],
    pub constants: &'a [PrimalConstants],
    pub slopes: &'a [Slopes],
    pub uv: &'a mut [Vec4],
    pub bar: &'a mut [Vec4],
}

/// `prox_slopes` of `tgv_primal.wgsl`: the clamps written out with the interval bounds.
#[expect(
    clippy::manual_clamp,
    reason = "the shader's min(max(x, lo), hi), which f32::clamp does not match on NaN"
)]
fn prox_slopes(u: f32, tau_lambda: f32, slopes: &Slopes) -> f32 {
    let s = slopes.0;
    let first = u + tau_lambda * Vec4::new(s[0], s[1], s[2], s[3]);
    let second = u + tau_lambda * Vec4::new(s[4], s[5], s[6], s[7]);
    let c_first = Vec4::new(
        first.x.min(-0.875),
        first.y.max(-0.875).min(-0.625),
        first.z.max(-0.625).min(-0.375),
        first.w.max(-0.375).min(-0.125),
    );
    let c_second = second
        .max(Vec4::new(-0.125, 0.125, 0.375, 0.625))
        .min(Vec4::new(0.125, 0.375, 0.625, 0.875));
    let last = (u + tau_lambda * s[8]).max(0.875);
    let pair = c_first + c_second;
    let sum = (pair.x + pair.y) + (pair.z + pair.w) + last;
    sum.max(-1.0).min(1.0)
}

/// Twin of `shaders/tgv_primal.wgsl`, invocation `j`.
pub fn tgv_primal(j: usize, b: &mut PrimalBuffers<'_>) {
    let (r0, r1, r2) = (at(b.rows, 3 * j), at(b.rows, 3 * j + 1), at(b.rows, 3 * j + 2));
    let (Some(k), Some(slopes)) = (b.constants.get(j), b.slopes.get(j)) else {
        return;
    };
    let mut adjoint = -(k.own.x * r0 + k.own.y * r1 + k.own.z * r2);
    for t in at(b.col_start, j)..at(b.col_start, j + 1) {
        let term = at(b.col_terms, t as usize);
        adjoint += term.weight * at(b.rows, term.index as usize);
    }
    adjoint -= Vec4::new(0.0, r0.x, r1.x, r2.x);
    let old = at(b.uv, j);
    let mut new = old - k.tau * adjoint;
    new.x = prox_slopes(new.x, k.tau.x * b.lambda, slopes);
    if let Some(slot) = b.uv.get_mut(j) {
        *slot = new;
    }
    if let Some(slot) = b.bar.get_mut(j) {
        *slot = 2.0 * new - old;
    }
}

/// The GPU's iteration run on the twins: every dual invocation, then every primal one.
pub fn iterate(kernel: &Kernel, state: &mut Packed, iterations: usize) {
    let n = kernel.n;
    let mut bar: Vec<Vec4> = state.uv.iter().chain(&kernel.frozen).copied().collect();
    let mut rows = vec![Vec4::ZERO; 3 * n];
    for _ in 0..iterations {
        let mut dual = DualBuffers {
            bar: &bar,
            row_start: &kernel.row_start,
            row_terms: &kernel.row_terms,
            constants: &kernel.dual_constants,
            p: &mut state.p,
            q_diag: &mut state.q_diag,
            q_off: &mut state.q_off,
            rows: &mut rows,
        };
        for c in 0..n {
            tgv_dual(c, &mut dual);
        }
        let mut primal = PrimalBuffers {
            lambda: kernel.lambda,
            rows: &rows,
            col_start: &kernel.col_start,
            col_terms: &kernel.col_terms,
            constants: &kernel.primal_constants,
            slopes: &kernel.slopes,
            uv: &mut state.uv,
            bar: &mut bar,
        };
        for j in 0..n {
            tgv_primal(j, &mut primal);
        }
    }
}

/// Twin of `shaders/halo.wgsl`, invocation `j`: one entry of a chunk's halo from the chunk that
/// owns it.
pub fn halo(j: usize, source: &[Vec4], indices: &[u32], destination: &mut [Vec4], offset: u32) {
    let Some(&index) = indices.get(j) else { return };
    if let Some(slot) = destination.get_mut(offset as usize + j) {
        *slot = at(source, index as usize);
    }
}

/// Runs the halo copies of `runs` into chunk `into`'s array, reading the arrays of `all`.
fn exchange(all: &mut [Vec<Vec4>], into: usize, runs: &[HaloRun]) {
    for run in runs {
        let source = all.get(run.source).cloned().unwrap_or_default();
        if let Some(destination) = all.get_mut(into) {
            for j in 0..run.indices.len() {
                halo(j, &source, &run.indices, destination, run.offset);
            }
        }
    }
}

/// The GPU's iteration of a split unit, on the twins: every chunk's dual pass, the row halos,
/// every chunk's primal pass, the bar halos (and the bar halos once before the first).
pub fn iterate_chunks(chunks: &[Chunk], state: &mut Packed, iterations: usize) {
    let own = |chunk: &Chunk, values: &[Vec4]| -> Vec<Vec4> {
        values
            .get(chunk.start..chunk.start + chunk.kernel.n)
            .unwrap_or(&[])
            .to_vec()
    };
    let mut bars: Vec<Vec<Vec4>> = chunks
        .iter()
        .map(|c| {
            own(c, &state.uv)
                .into_iter()
                .chain(c.kernel.frozen.iter().copied())
                .collect()
        })
        .collect();
    let mut rows: Vec<Vec<Vec4>> = chunks.iter().map(|c| vec![Vec4::ZERO; c.rows_len()]).collect();
    let mut parts: Vec<Packed> = chunks
        .iter()
        .map(|c| Packed {
            uv: own(c, &state.uv),
            p: own(c, &state.p),
            q_diag: own(c, &state.q_diag),
            q_off: own(c, &state.q_off),
        })
        .collect();
    for (index, chunk) in chunks.iter().enumerate() {
        exchange(&mut bars, index, &chunk.bar_halo);
    }
    for _ in 0..iterations {
        for ((chunk, part), (bar, rows)) in chunks.iter().zip(&mut parts).zip(bars.iter().zip(&mut rows)) {
            let k = &chunk.kernel;
            let mut dual = DualBuffers {
                bar,
                row_start: &k.row_start,
                row_terms: &k.row_terms,
                constants: &k.dual_constants,
                p: &mut part.p,
                q_diag: &mut part.q_diag,
                q_off: &mut part.q_off,
                rows,
            };
            for c in 0..k.n {
                tgv_dual(c, &mut dual);
            }
        }
        for (index, chunk) in chunks.iter().enumerate() {
            exchange(&mut rows, index, &chunk.row_halo);
        }
        for ((chunk, part), (bar, rows)) in chunks.iter().zip(&mut parts).zip(bars.iter_mut().zip(&rows)) {
            let k = &chunk.kernel;
            let mut primal = PrimalBuffers {
                lambda: k.lambda,
                rows,
                col_start: &k.col_start,
                col_terms: &k.col_terms,
                constants: &k.primal_constants,
                slopes: &k.slopes,
                uv: &mut part.uv,
                bar,
            };
            for j in 0..k.n {
                tgv_primal(j, &mut primal);
            }
        }
        for (index, chunk) in chunks.iter().enumerate() {
            exchange(&mut bars, index, &chunk.bar_halo);
        }
    }
    let mut joined = Packed {
        uv: Vec::new(),
        p: Vec::new(),
        q_diag: Vec::new(),
        q_off: Vec::new(),
    };
    for part in parts {
        joined.uv.extend(part.uv);
        joined.p.extend(part.p);
        joined.q_diag.extend(part.q_diag);
        joined.q_off.extend(part.q_off);
    }
    *state = joined;
}

/// Twin of `shaders/votes.wgsl`, invocation `c`: the bin cube `c` votes into for the map
/// `map`, added to its row (and its truncated distance to its distance sums), in f32 like the
/// shader. The arithmetic is the CPU voting loop's own
/// ([`crate::kernels::votes::vote_relative`]); this adds the shader's bindings.
#[expect(clippy::too_many_arguments, reason = "the shader's bindings, one by one")]
pub fn votes(
    c: usize,
    map: &crate::gpu::votes_dispatch::VoteMap,
    cubes: &[Vec4],
    levels: &[[u32; 4]],
    depths: &[f32],
    hist: &mut [f32],
    votes: &mut [u32],
    measured_distance: &mut [f32],
) {
    use crate::kernels::votes::{BINS, FlatPyramid, UnitView, vote_relative};
    if c >= map.n as usize {
        return;
    }
    let view = UnitView {
        unit_to_camera: map.unit_to_camera,
        intrinsics: map.intrinsics,
        spherical: map.spherical == 1,
        width: map.width,
        height: map.height,
        band_per_delta: map.band_per_delta,
        band_floor: map.band_floor,
    };
    let pyramid = FlatPyramid {
        levels: levels.get(..map.levels as usize).unwrap_or(levels),
        depths,
    };
    let Some((bin, distance)) = vote_relative(&view, at(cubes, c), &pyramid) else {
        return;
    };
    if let Some(h) = hist.get_mut(c * BINS + bin) {
        *h += map.weight;
    }
    if let Some(d) = distance
        && let Some([sum, total]) = measured_distance.get_mut(2 * c..2 * c + 2)
    {
        *sum += map.weight * d;
        *total += map.weight;
    }
    if let Some(count) = votes.get_mut(c) {
        *count += 1;
    }
}
