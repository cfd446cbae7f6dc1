//! The compiled kernel: the operator packed into gather lists and per-cube constants, and the
//! fused dual and primal passes that run the iterations (the GPU shaders' CPU reference).

use glam::{Mat4, Vec4};
use rayon::prelude::*;

use super::lanes::*;
use super::*;

/// Cubes per parallel task: large enough that scheduling is noise, small enough to balance.
pub(super) const CHUNK: usize = 2048;

/// One gather entry: an index into a packed array and its weight.
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct Gather {
    pub index: u32,
    pub weight: f32,
}

/// Per-cube constants of the dual step, packed for 4-wide arithmetic; the two passes read
/// disjoint columns, so neither streams the other's bytes.
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct DualConstants {
    /// sigma_p alpha1 per axis; w holds alpha1.
    pub sigma_p: Vec4,
    /// sigma_q alpha0 for the diagonal rows (xx, yy, zz) of E'; w holds alpha0.
    pub sigma_q_diag: Vec4,
    /// sigma_q alpha0 for the off-diagonal rows (xy, xz, yz); w unused.
    pub sigma_q_off: Vec4,
}

/// Per-cube constants of the primal step.
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct PrimalConstants {
    /// (tau_u, tau_v0, tau_v1, tau_v2).
    pub tau: Vec4,
    /// Minus the coefficient of the cube itself in its rows of D, per axis; w unused.
    pub own: Vec4,
}

/// A [`Problem`] compiled into the layout the iterations read: columns of per-cube constants,
/// and both D and its adjoint as gather lists. Every primal value a dual row reads is one packed
/// `(u, v0, v1, v2)`, and every dual row the adjoint reads is one packed
/// `(alpha1 p_axis, alpha0 Q[axis][0..3])` with Q the symmetric matrix of E'^T's weights, so a
/// term costs one 16-byte load and one 4-wide multiply-add.
pub struct Kernel {
    pub n: usize,
    /// Dual gather: terms of row 3c + axis are `row_terms[row_start[r] .. row_start[r + 1]]`;
    /// their indices point into the packed primal array (free cubes, then frozen ones).
    pub row_start: Vec<u32>,
    pub row_terms: Vec<Gather>,
    /// Primal gather: rows whose terms target cube j, as indices into the packed dual rows.
    pub col_start: Vec<u32>,
    pub col_terms: Vec<Gather>,
    pub dual_constants: Vec<DualConstants>,
    pub primal_constants: Vec<PrimalConstants>,
    /// Per cube: the number of terms of its 3 rows, and of its adjoint gather.
    pub lengths: Vec<[u16; 4]>,
    /// Packed (u, v) of the frozen neighbours, appended after the free cubes.
    pub frozen: Vec<Vec4>,
    pub slopes: Vec<Slopes>,
    pub lambda: f32,
}

/// The iterate in the kernel's layout: p with w = 0, q split into diagonal and off-diagonal.
#[derive(Clone, Debug, PartialEq)]
pub struct Packed {
    pub uv: Vec<Vec4>,
    pub p: Vec<Vec4>,
    pub q_diag: Vec<Vec4>,
    pub q_off: Vec<Vec4>,
}

impl Packed {
    pub fn of(state: &State) -> Packed {
        let three = |x: &[f32; 3]| Vec4::new(x[0], x[1], x[2], 0.0);
        Packed {
            uv: state
                .u
                .par_iter()
                .zip(&state.v)
                .map(|(u, v)| Vec4::new(*u, v[0], v[1], v[2]))
                .collect(),
            p: state.p.par_iter().map(three).collect(),
            q_diag: state.q.par_iter().map(|q| Vec4::new(q[0], q[1], q[2], 0.0)).collect(),
            q_off: state.q.par_iter().map(|q| Vec4::new(q[3], q[4], q[5], 0.0)).collect(),
        }
    }

    pub fn unpack_into(&self, state: &mut State) {
        state
            .u
            .par_iter_mut()
            .zip(state.v.par_iter_mut())
            .zip(state.p.par_iter_mut())
            .zip(state.q.par_iter_mut())
            .zip(self.uv.par_iter())
            .zip(self.p.par_iter())
            .zip(self.q_diag.par_iter().zip(self.q_off.par_iter()))
            .for_each(|((((((u, v), p), q), uv), packed_p), (qd, qo))| {
                *u = uv.x;
                *v = [uv.y, uv.z, uv.w];
                *p = [packed_p.x, packed_p.y, packed_p.z];
                *q = [qd.x, qd.y, qd.z, qo.x, qo.y, qo.z];
            });
    }
}

/// Scales `x` (and its partner, as one vector) into the unit ball; norms at most 1 are scaled
/// by exactly 1, without a branch.
#[inline(always)]
fn unit_ball_scale(squared_norm: f32) -> f32 {
    1.0 / squared_norm.sqrt().max(1.0)
}

#[inline(always)]
fn sum3(x: Vec4) -> f32 {
    x.x * x.x + x.y * x.y + x.z * x.z
}

impl Kernel {
    /// `None` when a gather list is longer than the packed lengths hold (2^16 terms; a 2:1
    /// balanced cut has at most 4 per row and 12 per column); the caller then runs the
    /// reference iteration.
    pub fn new(op: &Operator<'_>) -> Option<Kernel> {
        let problem = op.problem;
        let steps = op.step_sizes();
        let n = problem.n;
        let gather = |(index, weight): &(u32, f32)| Gather {
            index: *index,
            weight: *weight,
        };
        let (dual_constants, primal_constants): (Vec<DualConstants>, Vec<PrimalConstants>) = (0..n)
            .into_par_iter()
            .map(|c| {
                let (a1, a0) = (problem.alpha1[c], problem.alpha0[c]);
                let sp = steps.sigma_p[c].map(|s| s * a1);
                let sq = steps.sigma_q[c].map(|s| s * a0);
                let tv = steps.tau_v[c];
                let own = |axis: usize| op.reverse.row_sum.get(3 * c + axis).copied().unwrap_or(0.0);
                let dual = DualConstants {
                    sigma_p: Vec4::new(sp[0], sp[1], sp[2], a1),
                    sigma_q_diag: Vec4::new(sq[0], sq[1], sq[2], a0),
                    sigma_q_off: Vec4::new(sq[3], sq[4], sq[5], 0.0),
                };
                let primal = PrimalConstants {
                    tau: Vec4::new(steps.tau_u[c], tv[0], tv[1], tv[2]),
                    own: Vec4::new(own(0), own(1), own(2), 0.0),
                };
                (dual, primal)
            })
            .unzip();
        let len = |start: &[u32], i: usize| {
            let span = start
                .get(i + 1)
                .copied()
                .unwrap_or(0)
                .saturating_sub(start.get(i).copied().unwrap_or(0));
            u16::try_from(span).ok()
        };
        let lengths = (0..n)
            .into_par_iter()
            .map(|c| {
                Some([
                    len(&problem.start, 3 * c)?,
                    len(&problem.start, 3 * c + 1)?,
                    len(&problem.start, 3 * c + 2)?,
                    len(&op.reverse.start, c)?,
                ])
            })
            .collect::<Option<Vec<_>>>()?;
        Some(Kernel {
            n,
            lengths,
            row_start: problem.start.clone(),
            row_terms: problem.terms.par_iter().map(gather).collect(),
            col_start: op.reverse.start.clone(),
            col_terms: op.reverse.entries.par_iter().map(gather).collect(),
            dual_constants,
            primal_constants,
            frozen: problem
                .frozen_u
                .iter()
                .zip(&problem.frozen_v)
                .map(|(u, v)| Vec4::new(*u, v[0], v[1], v[2]))
                .collect(),
            slopes: problem.hist.par_iter().map(Slopes::of).collect(),
            lambda: problem.lambda,
        })
    }

    /// [`energy`] of the iterate in `state`, to the bit, read in the kernel's layout: each
    /// cube's differences gathered once as packed `(u, v0, v1, v2)` where the reference walks
    /// its rows four times through closures, and no copy back into a [`State`] per check (the
    /// stopping rule's checks took a tenth of RedKitchen's finest level). Every lane is the
    /// reference's sum in the reference's order; starting from +0 where the reference's sums
    /// start from -0 changes at most the sign of a zero, which the squares drop.
    ///
    /// Whole groups of [`LANES`] cubes of each chunk compute their terms with cubes as lanes
    /// ([`energy_lanes`]: the same operations per lane, so the same bits as [`cube_energy`]),
    /// the rest one cube at a time; the cubes' terms are then summed in cube order.
    pub fn energy(&self, problem: &Problem, state: &Packed) -> f64 {
        let n = self.n;
        let per_cube: Vec<f64> = (0..n.div_ceil(CHUNK))
            .into_par_iter()
            .flat_map_iter(|chunk| {
                let (first, end) = (chunk * CHUNK, ((chunk + 1) * CHUNK).min(n));
                let groups = (end - first) / LANES;
                let mut terms = Vec::with_capacity(end - first);
                for group in 0..groups {
                    let cube = first + group * LANES;
                    let centres: [Vec4; LANES] =
                        std::array::from_fn(|i| state.uv.get(cube + i).copied().unwrap_or(Vec4::ZERO));
                    let differences = std::array::from_fn(|i| self.differences(state, cube + i, centres[i]));
                    terms.extend(energy_lanes(problem, cube, &centres, &differences));
                }
                terms.extend((first + groups * LANES..end).map(|c| {
                    let centre = state.uv.get(c).copied().unwrap_or(Vec4::ZERO);
                    packed_cube_energy(problem, c, centre, self.differences(state, c, centre))
                }));
                terms
            })
            .collect();
        per_cube.iter().sum()
    }

    /// Cube `c`'s differences along each axis, `(D_axis u, D_axis v0, D_axis v1, D_axis v2)`,
    /// at the iterate `state` whose value at `c` is `centre`.
    #[inline(always)]
    pub(super) fn differences(&self, state: &Packed, c: usize, centre: Vec4) -> [Vec4; 3] {
        let n = self.n;
        let value = |index: u32| {
            let index = index as usize;
            if index < n {
                state.uv.get(index).copied()
            } else {
                self.frozen.get(index - n).copied()
            }
        };
        std::array::from_fn(|axis| {
            let row = 3 * c + axis;
            let from = self.row_start.get(row).copied().unwrap_or(0) as usize;
            let to = self.row_start.get(row + 1).copied().unwrap_or(0) as usize;
            self.row_terms
                .get(from..to)
                .unwrap_or(&[])
                .iter()
                .fold(Vec4::ZERO, |acc, term| {
                    acc + term.weight * (value(term.index).unwrap_or(centre) - centre)
                })
        })
    }

    /// The gather terms from row (or column) `first` on; a chunk walks them with a cursor.
    fn terms_from<'k>(&self, start: &[u32], terms: &'k [Gather], first: usize) -> &'k [Gather] {
        let from = start.get(first).copied().unwrap_or(0) as usize;
        terms.get(from..).unwrap_or(&[])
    }

    /// Runs `iterations` steps on the packed state. Each pass computes every output from a
    /// fixed gather list in a fixed order, so the result does not depend on the thread count.
    /// The per-cube columns are walked with zipped iterators, so only the gathers check bounds.
    /// Cubes go through the passes in groups of [`LANES`] with cubes as lanes (the pointwise
    /// steps then cost one 4-wide operation per value instead of a partly used one per cube),
    /// and a unit's last few cubes one at a time; both give the same bits. While it runs, the
    /// constants and `state` of the full groups are in lane layout ([`DualLanes`],
    /// [`PrimalLanes`]), rewritten in place; both are back in their per-cube layout when it
    /// returns, which is why it takes `&mut self`.
    pub fn iterate(&mut self, state: &mut Packed, iterations: usize) {
        let n = self.n;
        let mut bar: Vec<Vec4> = state.uv.iter().chain(&self.frozen).copied().collect();
        let mut rows = vec![Vec4::ZERO; 3 * n];
        relayout(self, state, true);
        // The passes fork from a worker of the pool: called from a unit's own thread, each
        // pass was injected into the pool and the thread slept until it ended, two futex
        // round trips an iteration (RedKitchen's solve: 66,092 voluntary context switches,
        // 39,462 with the passes forked here; system time 2.39 s, now 2.00 s).
        rayon::scope(|_| self.passes(state, &mut bar, &mut rows, iterations));
        relayout(self, state, false);
    }

    /// `iterations` dual and primal passes on the lane-layout state ([`Self::iterate`]).
    fn passes(&self, state: &mut Packed, bar: &mut [Vec4], rows: &mut [Vec4], iterations: usize) {
        let n = self.n;
        for _ in 0..iterations {
            {
                let bar: &[Vec4] = bar;
                state
                    .p
                    .par_chunks_mut(CHUNK)
                    .zip(state.q_diag.par_chunks_mut(CHUNK))
                    .zip(state.q_off.par_chunks_mut(CHUNK))
                    .zip(rows.par_chunks_mut(3 * CHUNK))
                    .zip(self.dual_constants.par_chunks(CHUNK))
                    .zip(self.lengths.par_chunks(CHUNK))
                    .zip(bar[..n].par_chunks(CHUNK))
                    .enumerate()
                    .for_each(
                        |(chunk, ((((((p, q_diag), q_off), rows), constants), lengths), centres))| {
                            let work = DualChunk {
                                terms: self.terms_from(&self.row_start, &self.row_terms, 3 * chunk * CHUNK),
                                bar,
                                p,
                                q_diag,
                                q_off,
                                rows,
                                constants,
                                lengths,
                                centres,
                            };
                            crate::sys::with_wide_vectors(work);
                        },
                    );
            }
            {
                let rows: &[Vec4] = rows;
                state
                    .uv
                    .par_chunks_mut(CHUNK)
                    .zip(bar[..n].par_chunks_mut(CHUNK))
                    .zip(rows.par_chunks(3 * CHUNK))
                    .zip(self.primal_constants.par_chunks(CHUNK))
                    .zip(self.lengths.par_chunks(CHUNK))
                    .zip(self.slopes.par_chunks(CHUNK))
                    .enumerate()
                    .for_each(|(chunk, (((((uv, bar), own_rows), constants), lengths), slopes))| {
                        let work = PrimalChunk {
                            terms: self.terms_from(&self.col_start, &self.col_terms, chunk * CHUNK),
                            rows,
                            uv,
                            bar,
                            own_rows,
                            constants,
                            lengths,
                            slopes,
                            lambda: self.lambda,
                        };
                        crate::sys::with_wide_vectors(work);
                    });
            }
        }
    }
}

/// One chunk's dual pass: its cubes' columns and the gather terms from its first row on. Run
/// through [`crate::sys::with_wide_vectors`], which compiles the steps it inlines (every
/// helper of the passes is `#[inline(always)]`) for AVX2 where the processor has it: the same
/// 4-wide float operations in three-operand encodings, so the same bits, without the register
/// copies of SSE's two-operand forms.
struct DualChunk<'a> {
    terms: &'a [Gather],
    bar: &'a [Vec4],
    p: &'a mut [Vec4],
    q_diag: &'a mut [Vec4],
    q_off: &'a mut [Vec4],
    rows: &'a mut [Vec4],
    constants: &'a [DualConstants],
    lengths: &'a [[u16; 4]],
    centres: &'a [Vec4],
}

impl crate::sys::WideWork for DualChunk<'_> {
    type Output = ();

    #[inline(always)]
    fn run(self) {
        let mut terms = self.terms.iter();
        let (p_lanes, p) = self.p.as_chunks_mut::<LANES>();
        let (qd_lanes, qd) = self.q_diag.as_chunks_mut::<LANES>();
        let (qo_lanes, qo) = self.q_off.as_chunks_mut::<LANES>();
        let (rows_lanes, rows) = self.rows.as_chunks_mut::<{ 3 * LANES }>();
        let (k_lanes, constants) = self.constants.as_chunks::<LANES>();
        let (lengths_lanes, lengths) = self.lengths.as_chunks::<LANES>();
        let (centres_lanes, centres) = self.centres.as_chunks::<LANES>();
        let groups = p_lanes
            .iter_mut()
            .zip(qd_lanes.iter_mut())
            .zip(qo_lanes.iter_mut())
            .zip(rows_lanes.iter_mut())
            .zip(k_lanes.iter().zip(lengths_lanes).zip(centres_lanes));
        for ((((p, qd), qo), rows), ((k, lengths), centres)) in groups {
            let k = bytemuck::cast_ref(k);
            dual_lanes(&mut terms, self.bar, centres, k, lengths, p, qd, qo, rows);
        }
        // The chunk's last cubes, fewer than LANES: the same steps one at a time.
        let cubes = p
            .iter_mut()
            .zip(qd.iter_mut())
            .zip(qo.iter_mut())
            .zip(rows.chunks_exact_mut(3))
            .zip(constants.iter().zip(lengths).zip(centres));
        for ((((p, qd), qo), rows), ((k, lengths), centre)) in cubes {
            dual(&mut terms, self.bar, *centre, k, lengths, p, qd, qo, rows);
        }
    }
}

/// One chunk's primal pass: its cubes' columns and the gather terms from its first cube on; run
/// as [`DualChunk`] is.
struct PrimalChunk<'a> {
    terms: &'a [Gather],
    rows: &'a [Vec4],
    uv: &'a mut [Vec4],
    bar: &'a mut [Vec4],
    own_rows: &'a [Vec4],
    constants: &'a [PrimalConstants],
    lengths: &'a [[u16; 4]],
    slopes: &'a [Slopes],
    lambda: f32,
}

impl crate::sys::WideWork for PrimalChunk<'_> {
    type Output = ();

    #[inline(always)]
    fn run(self) {
        let mut terms = self.terms.iter();
        let (uv_lanes, uv) = self.uv.as_chunks_mut::<LANES>();
        let (bar_lanes, bar) = self.bar.as_chunks_mut::<LANES>();
        let (own_lanes, own_rows) = self.own_rows.as_chunks::<{ 3 * LANES }>();
        let (k_lanes, constants) = self.constants.as_chunks::<LANES>();
        let (lengths_lanes, lengths) = self.lengths.as_chunks::<LANES>();
        let (slopes_lanes, slopes) = self.slopes.as_chunks::<LANES>();
        let groups = uv_lanes
            .iter_mut()
            .zip(bar_lanes.iter_mut())
            .zip(own_lanes)
            .zip(k_lanes.iter().zip(lengths_lanes).zip(slopes_lanes));
        for (((uv, bar), own_rows), ((k, lengths), slopes)) in groups {
            let (k, slopes) = (bytemuck::cast_ref(k), bytemuck::cast_ref(slopes));
            primal_lanes(
                &mut terms,
                self.rows,
                own_rows,
                k,
                lengths,
                slopes,
                self.lambda,
                uv,
                bar,
            );
        }
        let cubes = uv
            .iter_mut()
            .zip(bar.iter_mut())
            .zip(own_rows.chunks_exact(3))
            .zip(constants.iter().zip(lengths).zip(slopes));
        for (((uv, bar), own_rows), ((k, lengths), slopes)) in cubes {
            primal(
                &mut terms,
                self.rows,
                own_rows,
                k,
                lengths,
                slopes,
                self.lambda,
                uv,
                bar,
            );
        }
    }
}

/// [`cube_energy`] of cube `c` from its packed `(u, v0, v1, v2)` and its `differences` (per
/// axis, `(D_axis u, D_axis v0, D_axis v1, D_axis v2)`, as [`Kernel::differences`] gives them).
pub(super) fn packed_cube_energy(problem: &Problem, c: usize, centre: Vec4, differences: [Vec4; 3]) -> f64 {
    let du = differences.map(|d| d.x);
    // dv[i][j] = D_j v_i
    let dv: [[f32; 3]; 3] = std::array::from_fn(|i| std::array::from_fn(|j| differences[j][1 + i]));
    cube_energy(problem, c, centre.x, [centre.y, centre.z, centre.w], du, dv)
}

/// Dual step of one cube from the extrapolated primal `bar`: p and q move along K and are
/// projected onto their unit balls; then the cube's three packed dual rows are written.
/// Advances `terms` past this cube's.
#[inline(always)]
#[expect(clippy::too_many_arguments, reason = "one cube's columns, borrowed apart")]
pub(super) fn dual(
    terms: &mut std::slice::Iter<'_, Gather>,
    bar: &[Vec4],
    centre: Vec4,
    k: &DualConstants,
    lengths: &[u16; 4],
    p: &mut Vec4,
    q_diag: &mut Vec4,
    q_off: &mut Vec4,
    rows: &mut [Vec4],
) {
    // acc[axis] = (D_axis u, D_axis v0, D_axis v1, D_axis v2)
    let acc: [Vec4; 3] = std::array::from_fn(|axis| {
        let mut acc = Vec4::ZERO;
        for term in terms.by_ref().take(usize::from(lengths[axis])) {
            let t = bar.get(term.index as usize).copied().unwrap_or(centre);
            acc += term.weight * (t - centre);
        }
        acc
    });
    // Rows of the transpose: du = (D_x u, D_y u, D_z u, 0), dv_i = (D_x v_i, D_y v_i, D_z v_i, 0).
    let t = Mat4::from_cols(acc[0], acc[1], acc[2], Vec4::ZERO).transpose();
    let (du, dv0, dv1, dv2) = (t.x_axis, t.y_axis, t.z_axis, t.w_axis);
    let v = Vec4::new(centre.y, centre.z, centre.w, 0.0);
    let new_p = *p + k.sigma_p * (du - v);
    *p = new_p * unit_ball_scale(sum3(new_p));
    let diag = Vec4::new(dv0.x, dv1.y, dv2.z, 0.0);
    let off = SQRT_HALF * Vec4::new(dv0.y + dv1.x, dv0.z + dv2.x, dv1.z + dv2.y, 0.0);
    let (qd, qo) = (*q_diag + k.sigma_q_diag * diag, *q_off + k.sigma_q_off * off);
    let s = unit_ball_scale(sum3(qd) + sum3(qo));
    let (qd, qo) = (qd * s, qo * s);
    *q_diag = qd;
    *q_off = qo;
    // E'^T weights: Q = [[q0, s q3, s q4], [s q3, q1, s q5], [s q4, s q5, q2]], symmetric.
    let (a1, a0) = (k.sigma_p.w, k.sigma_q_diag.w);
    let (o3, o4, o5) = (SQRT_HALF * qo.x, SQRT_HALF * qo.y, SQRT_HALF * qo.z);
    let packed = [
        Vec4::new(a1 * p.x, a0 * qd.x, a0 * o3, a0 * o4),
        Vec4::new(a1 * p.y, a0 * o3, a0 * qd.y, a0 * o5),
        Vec4::new(a1 * p.z, a0 * o4, a0 * o5, a0 * qd.z),
    ];
    for (row, value) in rows.iter_mut().zip(packed) {
        *row = value;
    }
}

/// Primal step of one cube: the adjoint gathered from the packed dual rows, the prox of the
/// data term for u, a plain step for v; writes the extrapolation 2 x_new - x_old to `bar`.
/// Advances `terms` past this cube's.
#[inline(always)]
#[expect(clippy::too_many_arguments, reason = "one cube's columns, borrowed apart")]
pub(super) fn primal(
    terms: &mut std::slice::Iter<'_, Gather>,
    rows: &[Vec4],
    own_rows: &[Vec4],
    k: &PrimalConstants,
    lengths: &[u16; 4],
    slopes: &Slopes,
    lambda: f32,
    uv: &mut Vec4,
    bar: &mut Vec4,
) {
    let [r0, r1, r2] = [0, 1, 2].map(|axis| own_rows.get(axis).copied().unwrap_or(Vec4::ZERO));
    let mut adjoint = -(k.own.x * r0 + k.own.y * r1 + k.own.z * r2);
    for term in terms.by_ref().take(usize::from(lengths[3])) {
        adjoint += term.weight * rows.get(term.index as usize).copied().unwrap_or(Vec4::ZERO);
    }
    // v's adjoint also has -alpha1 p, the first entries of the cube's own rows.
    adjoint -= Vec4::new(0.0, r0.x, r1.x, r2.x);
    let old = *uv;
    let mut new = old - k.tau * adjoint;
    new.x = prox_slopes(new.x, k.tau.x * lambda, slopes);
    *uv = new;
    *bar = 2.0 * new - old;
}
