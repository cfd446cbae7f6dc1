//! Cubes as lanes: the dual and primal steps on groups of 4 cubes, one `Vec4` per value, with
//! the same float operations in the same order as the one-cube steps (same bits).

use glam::{Mat4, Vec4};
use rayon::prelude::*;

use super::fused::*;
use super::*;

/// Cubes per lane group of [`dual_lanes`] and [`primal_lanes`]: one `Vec4` holds one value of
/// each of 4 cubes.
pub(super) const LANES: usize = 4;

// `relayout` groups a unit's cubes from cube 0 and `iterate` groups each chunk's cubes from the
// chunk's first cube: the two agree only while chunks hold whole groups.
const _: () = assert!(CHUNK.is_multiple_of(LANES), "a chunk must hold whole lane groups");

/// The transpose of 4 vectors: lane i of the result's column j is lane j of `x[i]`.
#[inline(always)]
pub(super) fn transpose(x: [Vec4; LANES]) -> [Vec4; 4] {
    let t = Mat4::from_cols(x[0], x[1], x[2], x[3]).transpose();
    [t.x_axis, t.y_axis, t.z_axis, t.w_axis]
}

/// `1 / max(sqrt(s), 1)` per lane: [`unit_ball_scale`] of 4 cubes. `max` returns its second
/// operand when the first is NaN, as `f32::max` does here.
#[inline(always)]
fn unit_ball_scale_lanes(squared_norm: Vec4) -> Vec4 {
    // f32::sqrt is correctly rounded, so each lane is the one-cube value; LLVM emits sqrtps.
    Vec4::ONE / squared_norm.map(f32::sqrt).max(Vec4::ONE)
}

/// `x.x^2 + x.y^2 + x.z^2` of 4 cubes, summed in [`sum3`]'s order.
#[inline(always)]
fn sum3_lanes(x: [Vec4; 3]) -> Vec4 {
    x[0] * x[0] + x[1] * x[1] + x[2] * x[2]
}

/// [`dual`] of 4 consecutive cubes with cubes as lanes: the gathers run per cube as in
/// [`dual`], the rest on lane-layout values (`p`, `q_diag`, `q_off` hold one vector per
/// component, their w lanes stay 0). Every cube sees the same float operations in the same
/// order as in [`dual`], so both give the same bits (the GPU twins check this).
#[inline(always)]
#[expect(clippy::too_many_arguments, reason = "4 cubes' columns, borrowed apart")]
pub(super) fn dual_lanes(
    terms: &mut std::slice::Iter<'_, Gather>,
    bar: &[Vec4],
    centres: &[Vec4; LANES],
    k: &DualLanes,
    lengths: &[[u16; 4]; LANES],
    p: &mut [Vec4; 4],
    q_diag: &mut [Vec4; 4],
    q_off: &mut [Vec4; 4],
    rows: &mut [Vec4; 3 * LANES],
) {
    // acc[cube][axis] = (D_axis u, D_axis v0, D_axis v1, D_axis v2) of that cube.
    let acc: [[Vec4; 3]; LANES] = std::array::from_fn(|cube| {
        let centre = centres[cube];
        std::array::from_fn(|axis| {
            let mut acc = Vec4::ZERO;
            for term in terms.by_ref().take(usize::from(lengths[cube][axis])) {
                let t = bar.get(term.index as usize).copied().unwrap_or(centre);
                acc += term.weight * (t - centre);
            }
            acc
        })
    });
    // d[axis] = [D_axis u, D_axis v0, D_axis v1, D_axis v2], each over the 4 cubes.
    let d: [[Vec4; 4]; 3] = std::array::from_fn(|axis| transpose(acc.map(|a| a[axis])));
    let [_, v0, v1, v2] = transpose(*centres);
    let v = [v0, v1, v2];
    let [sp0, sp1, sp2, a1] = k.sigma_p;
    let [sqd0, sqd1, sqd2, a0] = k.sigma_q_diag;
    let [sqo0, sqo1, sqo2, _] = k.sigma_q_off;
    let sp = [sp0, sp1, sp2];
    let new_p: [Vec4; 3] = std::array::from_fn(|axis| p[axis] + sp[axis] * (d[axis][0] - v[axis]));
    let scale = unit_ball_scale_lanes(sum3_lanes(new_p));
    let new_p = new_p.map(|x| x * scale);
    // dv(i, axis) = D_axis v_i.
    let dv = |i: usize, axis: usize| d[axis][i + 1];
    let diag = [dv(0, 0), dv(1, 1), dv(2, 2)];
    let off = [
        SQRT_HALF * (dv(0, 1) + dv(1, 0)),
        SQRT_HALF * (dv(0, 2) + dv(2, 0)),
        SQRT_HALF * (dv(1, 2) + dv(2, 1)),
    ];
    let qd = [
        q_diag[0] + sqd0 * diag[0],
        q_diag[1] + sqd1 * diag[1],
        q_diag[2] + sqd2 * diag[2],
    ];
    let qo = [
        q_off[0] + sqo0 * off[0],
        q_off[1] + sqo1 * off[1],
        q_off[2] + sqo2 * off[2],
    ];
    let s = unit_ball_scale_lanes(sum3_lanes(qd) + sum3_lanes(qo));
    let (qd, qo) = (qd.map(|x| x * s), qo.map(|x| x * s));
    // The w lanes (index 3) stay 0, as [`dual`]'s w components do.
    [p[0], p[1], p[2]] = new_p;
    [q_diag[0], q_diag[1], q_diag[2]] = qd;
    [q_off[0], q_off[1], q_off[2]] = qo;
    // The packed rows of [`dual`], built over the lanes and transposed back to one per cube.
    let a1p = new_p.map(|x| a1 * x);
    let a0qd = qd.map(|x| a0 * x);
    let a0o = qo.map(|x| a0 * (SQRT_HALF * x));
    let packed = [
        transpose([a1p[0], a0qd[0], a0o[0], a0o[1]]),
        transpose([a1p[1], a0o[0], a0qd[1], a0o[2]]),
        transpose([a1p[2], a0o[1], a0o[2], a0qd[2]]),
    ];
    for (cube, rows) in rows.chunks_exact_mut(3).enumerate() {
        for (axis, row) in rows.iter_mut().enumerate() {
            *row = packed[axis][cube];
        }
    }
}

/// [`primal`] of 4 consecutive cubes with cubes as lanes: the adjoint is gathered per cube as
/// in [`primal`], the steps and the prox run on lane-layout values (`uv` holds u, v0, v1, v2 of
/// the 4 cubes), with the same float operations in the same order, so both give the same bits.
#[inline(always)]
#[expect(clippy::too_many_arguments, reason = "4 cubes' columns, borrowed apart")]
pub(super) fn primal_lanes(
    terms: &mut std::slice::Iter<'_, Gather>,
    rows: &[Vec4],
    own_rows: &[Vec4; 3 * LANES],
    k: &PrimalLanes,
    lengths: &[[u16; 4]; LANES],
    slopes: &SlopeLanes,
    lambda: f32,
    uv: &mut [Vec4; 4],
    bar: &mut [Vec4; LANES],
) {
    let adjoint: [Vec4; LANES] = std::array::from_fn(|cube| {
        let [r0, r1, r2] = [0, 1, 2].map(|axis| own_rows[3 * cube + axis]);
        let own = k.own[cube];
        let mut adjoint = -(own.x * r0 + own.y * r1 + own.z * r2);
        for term in terms.by_ref().take(usize::from(lengths[cube][3])) {
            adjoint += term.weight * rows.get(term.index as usize).copied().unwrap_or(Vec4::ZERO);
        }
        adjoint - Vec4::new(0.0, r0.x, r1.x, r2.x)
    });
    let old = *uv;
    let adjoint = transpose(adjoint);
    let mut new: [Vec4; 4] = std::array::from_fn(|i| old[i] - k.tau[i] * adjoint[i]);
    new[0] = prox_slopes_lanes(new[0], k.tau[0] * lambda, slopes);
    *uv = new;
    *bar = transpose(std::array::from_fn(|i| 2.0 * new[i] - old[i]));
}

/// [`prox_slopes`] of 4 cubes, with the same operations in the same order per cube.
#[inline(always)]
fn prox_slopes_lanes(u_tilde: Vec4, tau_lambda: Vec4, slopes: &SlopeLanes) -> Vec4 {
    let slope = |i: usize| {
        let at = LANES * i;
        match slopes.get(at..at + LANES) {
            Some(&[a, b, c, d]) => Vec4::new(a, b, c, d),
            _ => Vec4::ZERO,
        }
    };
    let clamp = |i: usize| {
        (u_tilde + tau_lambda * slope(i))
            .max(Vec4::splat(INTERVAL_LOW[i]))
            .min(Vec4::splat(INTERVAL_HIGH[i]))
    };
    // prox_slopes pairs interval i with i + 4, then sums the pairs as (0 + 1) + (2 + 3).
    let pair = [
        clamp(0) + clamp(4),
        clamp(1) + clamp(5),
        clamp(2) + clamp(6),
        clamp(3) + clamp(7),
    ];
    let last = (u_tilde + tau_lambda * slope(BINS)).max(Vec4::splat(INTERVAL_LOW[BINS]));
    let sum = (pair[0] + pair[1]) + (pair[2] + pair[3]) + last;
    // f32::clamp's semantics, NaN included: below -> -1, above -> 1, otherwise unchanged.
    let (low, high) = (Vec4::NEG_ONE, Vec4::ONE);
    let sum = Vec4::select(sum.cmplt(low), low, sum);
    Vec4::select(sum.cmpgt(high), high, sum)
}

/// [`cube_energy`] of the [`LANES`] cubes from `first` on, with cubes as lanes: `centres` are
/// their packed `(u, v0, v1, v2)` and `differences[cube][axis]` their `(D_axis u, D_axis v0,
/// D_axis v1, D_axis v2)`. Each lane sees [`cube_energy`]'s float operations in its order (its
/// sums start from -0, as `f32`'s `Sum` does), so each term has the same bits.
#[inline(always)]
pub(super) fn energy_lanes(
    problem: &Problem,
    first: usize,
    centres: &[Vec4; LANES],
    differences: &[[Vec4; 3]; LANES],
) -> [f64; LANES] {
    let column =
        |values: &[f32]| Vec4::from_array(std::array::from_fn(|i| values.get(first + i).copied().unwrap_or(0.0)));
    let (w1, w0) = (column(&problem.alpha1), column(&problem.alpha0));
    // d[axis] = [D_axis u, D_axis v0, D_axis v1, D_axis v2], each over the 4 cubes.
    let d: [[Vec4; 4]; 3] = std::array::from_fn(|axis| transpose(differences.map(|a| a[axis])));
    let [u, v0, v1, v2] = transpose(*centres);
    let v = [v0, v1, v2];
    let g: [Vec4; 3] = std::array::from_fn(|axis| w1 * (d[axis][0] - v[axis]));
    // dv(i, j) = D_j v_i
    let dv = |i: usize, j: usize| d[j][i + 1];
    let e = [
        dv(0, 0),
        dv(1, 1),
        dv(2, 2),
        SQRT_HALF * (dv(0, 1) + dv(1, 0)),
        SQRT_HALF * (dv(0, 2) + dv(2, 0)),
        SQRT_HALF * (dv(1, 2) + dv(2, 1)),
    ]
    .map(|x| w0 * x);
    let squares = |x: &[Vec4]| x.iter().fold(Vec4::splat(-0.0), |sum, x| sum + *x * *x);
    let tv = squares(&g).map(f32::sqrt);
    let tgv = squares(&e).map(f32::sqrt);
    let hist: [[f32; BINS]; LANES] = std::array::from_fn(|i| problem.hist.get(first + i).copied().unwrap_or_default());
    let data = (0..BINS).fold(Vec4::splat(-0.0), |sum, b| {
        let h = Vec4::from_array(hist.map(|h| h.get(b).copied().unwrap_or(0.0)));
        sum + h * (u - Vec4::splat(bin_center(b))).abs()
    });
    let data = problem.lambda * data;
    std::array::from_fn(|i| f64::from(tv[i]) + f64::from(tgv[i]) + f64::from(data[i]))
}

/// [`DualConstants`] of a group of [`LANES`] cubes in lane layout: each field's 4 vectors are
/// the transpose of the 4 cubes' values, so `sigma_p[axis]` holds that axis's sigma_p of all 4
/// cubes and `sigma_p[3]` their alpha1. Same size and alignment as `[DualConstants; LANES]`,
/// whose memory it reuses.
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct DualLanes {
    pub sigma_p: [Vec4; 4],
    pub sigma_q_diag: [Vec4; 4],
    pub sigma_q_off: [Vec4; 4],
}

/// [`PrimalConstants`] of a group in lane layout: `tau` transposed, `own` kept per cube (the
/// adjoint is gathered per cube). Reuses the memory of `[PrimalConstants; LANES]`.
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct PrimalLanes {
    pub tau: [Vec4; 4],
    pub own: [Vec4; LANES],
}

/// [`Slopes`] of a group in lane layout: entry `4 i + cube` is slope i of that cube. Reuses the
/// memory of `[Slopes; LANES]`.
pub(super) type SlopeLanes = [f32; (BINS + 1) * LANES];

/// A group of [`LANES`] cubes' values in lane layout, stored in the memory of the per-cube
/// values (`Self` and `[Self::Cube; LANES]` have the same size and alignment).
pub(super) trait LaneLayout: bytemuck::Pod + Send {
    type Cube: bytemuck::Pod + Send;
    fn of(cubes: &[Self::Cube; LANES]) -> Self;
    fn cubes(&self) -> [Self::Cube; LANES];
}

impl LaneLayout for DualLanes {
    type Cube = DualConstants;

    fn of(cubes: &[DualConstants; LANES]) -> DualLanes {
        DualLanes {
            sigma_p: transpose(cubes.map(|k| k.sigma_p)),
            sigma_q_diag: transpose(cubes.map(|k| k.sigma_q_diag)),
            sigma_q_off: transpose(cubes.map(|k| k.sigma_q_off)),
        }
    }

    fn cubes(&self) -> [DualConstants; LANES] {
        let (p, d, o) = (
            transpose(self.sigma_p),
            transpose(self.sigma_q_diag),
            transpose(self.sigma_q_off),
        );
        std::array::from_fn(|cube| DualConstants {
            sigma_p: p[cube],
            sigma_q_diag: d[cube],
            sigma_q_off: o[cube],
        })
    }
}

impl LaneLayout for PrimalLanes {
    type Cube = PrimalConstants;

    fn of(cubes: &[PrimalConstants; LANES]) -> PrimalLanes {
        PrimalLanes {
            tau: transpose(cubes.map(|k| k.tau)),
            own: cubes.map(|k| k.own),
        }
    }

    fn cubes(&self) -> [PrimalConstants; LANES] {
        let tau = transpose(self.tau);
        std::array::from_fn(|cube| PrimalConstants {
            tau: tau[cube],
            own: self.own[cube],
        })
    }
}

impl LaneLayout for SlopeLanes {
    type Cube = Slopes;

    fn of(cubes: &[Slopes; LANES]) -> SlopeLanes {
        std::array::from_fn(|at| cubes[at % LANES].0[at / LANES])
    }

    fn cubes(&self) -> [Slopes; LANES] {
        std::array::from_fn(|cube| Slopes(std::array::from_fn(|i| self[LANES * i + cube])))
    }
}

/// Rewrites the full groups of `column` between the per-cube and the lane layout, in place.
fn relayout_column<L: LaneLayout>(column: &mut [L::Cube], to_lanes: bool) {
    let (groups, _) = column.as_chunks_mut::<LANES>();
    groups.par_iter_mut().for_each(|group| {
        let lanes: &mut L = bytemuck::cast_mut(group);
        *lanes = if to_lanes {
            L::of(bytemuck::cast_ref(lanes))
        } else {
            bytemuck::cast(lanes.cubes())
        };
    });
}

/// Rewrites every full group of [`LANES`] cubes of the kernel's constants and of `state` between
/// the per-cube layout and the lane layout, in place (a chunk's cubes form whole groups except
/// the last few cubes of the unit, which stay per cube). Pure data movement, so a round trip
/// returns the same bits.
pub(super) fn relayout(kernel: &mut Kernel, state: &mut Packed, to_lanes: bool) {
    relayout_column::<DualLanes>(&mut kernel.dual_constants, to_lanes);
    relayout_column::<PrimalLanes>(&mut kernel.primal_constants, to_lanes);
    relayout_column::<SlopeLanes>(&mut kernel.slopes, to_lanes);
    // The transpose of a 4x4 block is its own inverse.
    for column in [&mut state.uv, &mut state.p, &mut state.q_diag, &mut state.q_off] {
        let (groups, _) = column.as_chunks_mut::<LANES>();
        groups.par_iter_mut().for_each(|group| *group = transpose(*group));
    }
}
