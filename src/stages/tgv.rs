//! TGV minimisation on one unit of an adaptive level cut (paper 3.2, DESIGN.md section 4).
//!
//! Energy over the unit's free cubes c:
//!   sum_c alpha1_c |D u_c - v_c| + alpha0_c |E'(v)_c| + lambda sum_b h_b(c) |u_c - f_b|,  u in [-1, 1]
//! with alpha1_c = alpha1 h_c and alpha0_c = alpha0 h_c^2 (h_c the cube side) so that the energy
//! is invariant to scaling the scene. D is the forward difference to the `+` face neighbour(s)
//! (the mean over up to 4 finer ones), divided by the centre distance along the axis; none at
//! the root boundary. E'(v) is the symmetric gradient of v built from D, with off-diagonal rows
//! scaled by sqrt(2) so that the Euclidean norm of the 6 rows is the Frobenius norm.
//! Neighbours outside the unit are frozen (their u and v are constants).
//!
//! D and its adjoint are generated from one list of difference terms; the adjoint is in gather
//! form (precomputed reverse lists), so every output is computed independently, in a fixed
//! order: results do not depend on the thread count. Step sizes are the diagonal
//! preconditioning of Pock and Chambolle (2011), alpha = 1.

use glam::{Mat4, Vec4};
use rayon::prelude::*;

use super::histograms::{BINS, bin_center};

const SQRT_HALF: f32 = std::f32::consts::FRAC_1_SQRT_2;

/// Index of a difference-term target: a free cube (< n) or a frozen one (n + index).
pub type Target = u32;

#[derive(Clone, Debug, Default)]
pub struct Problem {
    pub n: usize,
    /// Terms of row (c, axis) are `terms[start[3c + axis] .. start[3c + axis + 1]]`.
    pub start: Vec<u32>,
    pub terms: Vec<(Target, f32)>,
    pub frozen_u: Vec<f32>,
    pub frozen_v: Vec<[f32; 3]>,
    pub hist: Vec<[f32; BINS]>,
    /// Row weights of K: alpha1 h_c and alpha0 h_c^2 (the duals live in unit balls, so the
    /// preconditioner sees O(alpha) entries rather than O(1/h) ones).
    pub alpha1: Vec<f32>,
    pub alpha0: Vec<f32>,
    pub lambda: f32,
}

#[derive(Clone, Debug, Default, PartialEq)]
pub struct State {
    pub u: Vec<f32>,
    pub v: Vec<[f32; 3]>,
    pub p: Vec<[f32; 3]>,
    pub q: Vec<[f32; 6]>,
}

impl State {
    pub fn zeros(n: usize) -> State {
        State {
            u: vec![0.0; n],
            v: vec![[0.0; 3]; n],
            p: vec![[0.0; 3]; n],
            q: vec![[0.0; 6]; n],
        }
    }
}

/// Reverse lists of D in gather form: for free cube j, the rows (3c + axis) whose terms target j.
struct Reverse {
    start: Vec<u32>,
    entries: Vec<(u32, f32)>,
    /// Sum of the weights of each row: the coefficient of the row's own cube is minus this.
    row_sum: Vec<f32>,
}

impl Problem {
    fn row(&self, row: usize) -> &[(Target, f32)] {
        let (a, b) = (
            self.start.get(row).copied().unwrap_or(0) as usize,
            self.start.get(row + 1).copied().unwrap_or(0) as usize,
        );
        self.terms.get(a..b).unwrap_or(&[])
    }

    fn reverse(&self) -> Reverse {
        let n = self.n;
        let mut counts = vec![0u32; n + 1];
        for (t, _) in &self.terms {
            if (*t as usize) < n {
                counts[*t as usize + 1] += 1;
            }
        }
        for i in 0..n {
            counts[i + 1] += counts[i];
        }
        let mut fill = counts.clone();
        let mut entries = vec![(0u32, 0f32); counts[n] as usize];
        let mut row_sum = vec![0f32; 3 * n];
        for (row, sum) in row_sum.iter_mut().enumerate() {
            for (t, w) in self.row(row) {
                *sum += w;
                if (*t as usize) < n {
                    let slot = &mut fill[*t as usize];
                    entries[*slot as usize] = (row as u32, *w);
                    *slot += 1;
                }
            }
        }
        Reverse {
            start: counts,
            entries,
            row_sum,
        }
    }

    /// D applied to a scalar field with frozen values: (D x)_c for the 3 axes.
    pub fn diff(&self, c: usize, x: &[f32], frozen: impl Fn(usize) -> f32) -> [f32; 3] {
        self.diff_by(c, |t| x[t], frozen)
    }

    /// [`Problem::diff`] with the free values read through `free` (one component of v, say).
    fn diff_by(&self, c: usize, free: impl Fn(usize) -> f32, frozen: impl Fn(usize) -> f32) -> [f32; 3] {
        let xc = free(c);
        std::array::from_fn(|axis| {
            self.row(3 * c + axis)
                .iter()
                .map(|(t, w)| {
                    let t = *t as usize;
                    let xt = if t < self.n { free(t) } else { frozen(t - self.n) };
                    w * (xt - xc)
                })
                .sum()
        })
    }
}

/// Diagonal preconditioners of the dual rows (sigma) and primal columns (tau).
pub struct StepSizes {
    pub sigma_p: Vec<[f32; 3]>,
    pub sigma_q: Vec<[f32; 6]>,
    pub tau_u: Vec<f32>,
    pub tau_v: Vec<[f32; 3]>,
}

/// The linear operator K(u, v) = (alpha1 (D u - v), alpha0 E'(v)) and its adjoint.
pub struct Operator<'a> {
    pub problem: &'a Problem,
    reverse: Reverse,
}

impl<'a> Operator<'a> {
    pub fn new(problem: &'a Problem) -> Operator<'a> {
        Operator {
            problem,
            reverse: problem.reverse(),
        }
    }

    /// D^T y for y with 3 components per cube (frozen cubes carry no rows and no columns).
    fn diff_t(&self, j: usize, y: &[[f32; 3]]) -> f32 {
        let mut acc = 0f32;
        for (axis, yj) in y[j].iter().enumerate() {
            acc -= self.reverse.row_sum[3 * j + axis] * yj;
        }
        let (a, b) = (self.reverse.start[j] as usize, self.reverse.start[j + 1] as usize);
        for (row, w) in &self.reverse.entries[a..b] {
            let row = *row as usize;
            acc += w * y[row / 3][row % 3];
        }
        acc
    }

    /// E'(v)_c from the differences of each component.
    fn sym(dv: [[f32; 3]; 3]) -> [f32; 6] {
        // dv[i][j] = D_j v_i
        [
            dv[0][0],
            dv[1][1],
            dv[2][2],
            SQRT_HALF * (dv[0][1] + dv[1][0]),
            SQRT_HALF * (dv[0][2] + dv[2][0]),
            SQRT_HALF * (dv[1][2] + dv[2][1]),
        ]
    }

    fn components(v: &[[f32; 3]]) -> [Vec<f32>; 3] {
        std::array::from_fn(|i| v.iter().map(|x| x[i]).collect())
    }

    /// K(u, v) with frozen values set to `frozen` (zero for the linear part).
    pub fn apply(&self, u: &[f32], v: &[[f32; 3]], with_frozen: bool) -> (Vec<[f32; 3]>, Vec<[f32; 6]>) {
        let p = self.problem;
        let vc = Self::components(v);
        let fu = |k: usize| if with_frozen { p.frozen_u[k] } else { 0.0 };
        let out: Vec<([f32; 3], [f32; 6])> = (0..p.n)
            .into_par_iter()
            .map(|c| {
                let g = p.diff(c, u, fu);
                let dv: [[f32; 3]; 3] =
                    std::array::from_fn(|i| p.diff(c, &vc[i], |k| if with_frozen { p.frozen_v[k][i] } else { 0.0 }));
                let (w1, w0) = (p.alpha1[c], p.alpha0[c]);
                (
                    [w1 * (g[0] - v[c][0]), w1 * (g[1] - v[c][1]), w1 * (g[2] - v[c][2])],
                    Self::sym(dv).map(|e| w0 * e),
                )
            })
            .collect();
        out.into_iter().unzip()
    }

    /// K^T(y, z): (D^T (alpha1 y), -alpha1 y + E'^T (alpha0 z)).
    pub fn apply_t(&self, y: &[[f32; 3]], z: &[[f32; 6]]) -> (Vec<f32>, Vec<[f32; 3]>) {
        let p = self.problem;
        let y: Vec<[f32; 3]> = y.iter().zip(&p.alpha1).map(|(r, w)| r.map(|x| w * x)).collect();
        let z: Vec<[f32; 6]> = z.iter().zip(&p.alpha0).map(|(r, w)| r.map(|x| w * x)).collect();
        let (y, z) = (&y[..], &z[..]);
        // E'^T z: v_x gets D_x^T z_xx + s (D_y^T z_xy + D_z^T z_xz), etc.
        let pick = |rows: [(usize, f32); 3]| -> Vec<[f32; 3]> {
            z.iter()
                .map(|q| std::array::from_fn(|axis| rows[axis].1 * q[rows[axis].0]))
                .collect()
        };
        let for_x = pick([(0, 1.0), (3, SQRT_HALF), (4, SQRT_HALF)]);
        let for_y = pick([(3, SQRT_HALF), (1, 1.0), (5, SQRT_HALF)]);
        let for_z = pick([(4, SQRT_HALF), (5, SQRT_HALF), (2, 1.0)]);
        let n = self.problem.n;
        let u: Vec<f32> = (0..n).into_par_iter().map(|j| self.diff_t(j, y)).collect();
        let v: Vec<[f32; 3]> = (0..n)
            .into_par_iter()
            .map(|j| {
                [
                    -y[j][0] + self.diff_t(j, &for_x),
                    -y[j][1] + self.diff_t(j, &for_y),
                    -y[j][2] + self.diff_t(j, &for_z),
                ]
            })
            .collect();
        (u, v)
    }

    /// Diagonal preconditioners: sigma per dual row = 1 / sum_j |K_ij|, tau per primal column =
    /// 1 / sum_i |K_ij| (all weights are positive, so these are sums of coefficients).
    pub fn step_sizes(&self) -> StepSizes {
        let p = self.problem;
        let n = p.n;
        // |D| row sums: own coefficient plus free targets.
        let row_abs: Vec<f32> = (0..3 * n)
            .into_par_iter()
            .map(|row| {
                p.row(row)
                    .iter()
                    .map(|(t, w)| if (*t as usize) < n { 2.0 * w } else { *w })
                    .sum()
            })
            .collect();
        // Column sums of |K| per (cube, axis), with the rows' weights: own rows (coefficient
        // row_sum) plus the rows of the cubes whose terms target this one.
        let col_abs = |weights: &[f32]| -> Vec<[f32; 3]> {
            (0..n)
                .into_par_iter()
                .map(|j| {
                    let mut c = [0f32; 3];
                    for (axis, slot) in c.iter_mut().enumerate() {
                        *slot = weights[j] * self.reverse.row_sum[3 * j + axis];
                    }
                    let (a, b) = (self.reverse.start[j] as usize, self.reverse.start[j + 1] as usize);
                    for (row, w) in &self.reverse.entries[a..b] {
                        let row = *row as usize;
                        c[row % 3] += weights[row / 3] * w;
                    }
                    c
                })
                .collect()
        };
        let col1 = col_abs(&p.alpha1);
        let col0 = col_abs(&p.alpha0);
        let inv = |s: f32| if s > 0.0 { 1.0 / s } else { 1.0 };
        let sigma_p = (0..n)
            .into_par_iter()
            .map(|c| std::array::from_fn(|a| inv(p.alpha1[c] * (row_abs[3 * c + a] + 1.0))))
            .collect();
        let sigma_q = (0..n)
            .into_par_iter()
            .map(|c| {
                let r = |a: usize| row_abs[3 * c + a];
                [
                    r(0),
                    r(1),
                    r(2),
                    SQRT_HALF * (r(1) + r(0)),
                    SQRT_HALF * (r(2) + r(0)),
                    SQRT_HALF * (r(2) + r(1)),
                ]
                .map(|x| inv(p.alpha0[c] * x))
            })
            .collect();
        let tau_u = col1.par_iter().map(|c| inv(c[0] + c[1] + c[2])).collect();
        let tau_v = (0..n)
            .into_par_iter()
            .map(|j| {
                let (c, w) = (col0[j], p.alpha1[j]);
                [
                    inv(w + c[0] + SQRT_HALF * (c[1] + c[2])),
                    inv(w + c[1] + SQRT_HALF * (c[0] + c[2])),
                    inv(w + c[2] + SQRT_HALF * (c[0] + c[1])),
                ]
            })
            .collect();
        StepSizes {
            sigma_p,
            sigma_q,
            tau_u,
            tau_v,
        }
    }
}

/// prox of tau lambda sum_b h_b |u - f_b| at u_tilde (Li and Osher; Zach 2008), clamped to
/// [-1, 1]. On the open interval between centres f_{i-1} and f_i the optimality condition gives
/// w_i = u_tilde + tau lambda (sum_{b >= i} h_b - sum_{b < i} h_b). The w_i do not increase in i
/// while the intervals ascend, so clamp(w_i, f_{i-1}, f_i) equals f_i before the minimiser's
/// interval, the minimiser inside it, and f_{i-1} after it: the minimiser is the sum of the 9
/// clamps minus the sum of the centres, which is 0. Branch-free; without votes it is the
/// identity (then the clamp).
pub fn prox_histogram(u_tilde: f32, tau_lambda: f32, hist: &[f32; BINS]) -> f32 {
    prox_slopes(u_tilde, tau_lambda, &Slopes::of(hist))
}

/// The data term's slopes on the 9 intervals between bin centres: (votes at or above) minus
/// (votes below), i.e. total - 2 below_i. They depend on the histogram only, so the kernel
/// computes them once per solve.
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(transparent)]
pub struct Slopes(pub [f32; BINS + 1]);

impl Slopes {
    pub fn of(hist: &[f32; BINS]) -> Slopes {
        let mut below = [0f32; BINS + 1];
        for i in 0..BINS {
            below[i + 1] = below[i] + hist[i];
        }
        let total = below[BINS];
        let slope = |i: usize| total - 2.0 * below[i];
        Slopes(std::array::from_fn(slope))
    }
}

/// [`prox_histogram`] on precomputed slopes: nine independent clamps, four at a time.
#[inline]
pub fn prox_slopes(u_tilde: f32, tau_lambda: f32, slopes: &Slopes) -> f32 {
    let [s0, s1, s2, s3, s4, s5, s6, s7, s8] = slopes.0;
    let u = Vec4::splat(u_tilde);
    let c_first = (u + tau_lambda * Vec4::new(s0, s1, s2, s3))
        .max(INTERVAL_LOW_V[0])
        .min(INTERVAL_HIGH_V[0]);
    let c_second = (u + tau_lambda * Vec4::new(s4, s5, s6, s7))
        .max(INTERVAL_LOW_V[1])
        .min(INTERVAL_HIGH_V[1]);
    let last = (u_tilde + tau_lambda * s8).max(INTERVAL_LOW[BINS]);
    let pair = c_first + c_second;
    let sum = (pair.x + pair.y) + (pair.z + pair.w) + last;
    sum.clamp(-1.0, 1.0)
}

const INTERVAL_LOW_V: [Vec4; 2] = [
    Vec4::from_array([INTERVAL_LOW[0], INTERVAL_LOW[1], INTERVAL_LOW[2], INTERVAL_LOW[3]]),
    Vec4::from_array([INTERVAL_LOW[4], INTERVAL_LOW[5], INTERVAL_LOW[6], INTERVAL_LOW[7]]),
];
const INTERVAL_HIGH_V: [Vec4; 2] = [
    Vec4::from_array([INTERVAL_HIGH[0], INTERVAL_HIGH[1], INTERVAL_HIGH[2], INTERVAL_HIGH[3]]),
    Vec4::from_array([INTERVAL_HIGH[4], INTERVAL_HIGH[5], INTERVAL_HIGH[6], INTERVAL_HIGH[7]]),
];

/// The intervals between consecutive bin centres, open at both ends.
const INTERVAL_LOW: [f32; BINS + 1] = {
    let mut low = [f32::NEG_INFINITY; BINS + 1];
    let mut i = 1;
    while i <= BINS {
        low[i] = -1.0 + (2.0 * (i - 1) as f32 + 1.0) / 8.0;
        i += 1;
    }
    low
};
const INTERVAL_HIGH: [f32; BINS + 1] = {
    let mut high = [f32::INFINITY; BINS + 1];
    let mut i = 0;
    while i < BINS {
        high[i] = -1.0 + (2.0 * i as f32 + 1.0) / 8.0;
        i += 1;
    }
    high
};

/// Projection onto the unit ball, without a branch: norms at most 1 are scaled by exactly 1.
#[inline]
fn project<const N: usize>(x: &mut [f32; N]) {
    let norm = x.iter().map(|v| v * v).sum::<f32>().sqrt();
    let s = 1.0 / norm.max(1.0);
    x.iter_mut().for_each(|v| *v *= s);
}

/// Energy of a state (free cubes only). Each cube's term is computed on its own, as
/// [`Operator::apply`] would give it, and the terms are summed in cube order, so the value does
/// not depend on the thread count.
pub fn energy(op: &Operator<'_>, state: &State) -> f64 {
    let p = op.problem;
    let per_cube: Vec<f64> = (0..p.n)
        .into_par_iter()
        .map(|c| {
            let g = p.diff(c, &state.u, |k| p.frozen_u[k]);
            let dv: [[f32; 3]; 3] = std::array::from_fn(|i| p.diff_by(c, |t| state.v[t][i], |k| p.frozen_v[k][i]));
            let (w1, w0) = (p.alpha1[c], p.alpha0[c]);
            let v = state.v[c];
            let g = [w1 * (g[0] - v[0]), w1 * (g[1] - v[1]), w1 * (g[2] - v[2])];
            let e = Operator::sym(dv).map(|e| w0 * e);
            let tv = g.iter().map(|x| x * x).sum::<f32>().sqrt();
            let tgv = e.iter().map(|x| x * x).sum::<f32>().sqrt();
            let data: f32 = (0..BINS)
                .map(|b| p.hist[c][b] * (state.u[c] - bin_center(b)).abs())
                .sum();
            f64::from(tv) + f64::from(tgv) + f64::from(p.lambda * data)
        })
        .collect();
    per_cube.iter().sum()
}

/// Puts the duals inside their (unit) balls; returns the starting energy.
fn start(op: &Operator<'_>, state: &mut State) -> f64 {
    state.p.par_iter_mut().zip(state.q.par_iter_mut()).for_each(|(p, q)| {
        project(p);
        project(q);
    });
    energy(op, state)
}

/// The reference iteration, written with the operator and its adjoint; [`solve`] is its fused
/// twin and is tested against it.
pub fn solve_reference(problem: &Problem, state: &mut State, iterations: usize) -> (f64, f64) {
    let op = Operator::new(problem);
    let StepSizes {
        sigma_p,
        sigma_q,
        tau_u,
        tau_v,
    } = op.step_sizes();
    let before = start(&op, state);
    let mut u_bar = state.u.clone();
    let mut v_bar = state.v.clone();
    for _ in 0..iterations {
        // Dual step.
        let (g, e) = op.apply(&u_bar, &v_bar, true);
        state
            .p
            .par_iter_mut()
            .zip(state.q.par_iter_mut())
            .enumerate()
            .for_each(|(c, (p, q))| {
                for a in 0..3 {
                    p[a] += sigma_p[c][a] * g[c][a];
                }
                project(p);
                for k in 0..6 {
                    q[k] += sigma_q[c][k] * e[c][k];
                }
                project(q);
            });
        // Primal step.
        let (ku, kv) = op.apply_t(&state.p, &state.q);
        let lambda = problem.lambda;
        state
            .u
            .par_iter_mut()
            .zip(state.v.par_iter_mut())
            .zip(u_bar.par_iter_mut().zip(v_bar.par_iter_mut()))
            .enumerate()
            .for_each(|(c, ((u, v), (ub, vb)))| {
                let old_u = *u;
                let new_u = prox_histogram(old_u - tau_u[c] * ku[c], tau_u[c] * lambda, &problem.hist[c]);
                *u = new_u;
                *ub = 2.0 * new_u - old_u;
                for a in 0..3 {
                    let old = v[a];
                    let new = old - tau_v[c][a] * kv[c][a];
                    v[a] = new;
                    vb[a] = 2.0 * new - old;
                }
            });
    }
    let after = energy(&op, state);
    (before, after)
}

/// Cubes per parallel task: large enough that scheduling is noise, small enough to balance.
const CHUNK: usize = 2048;

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
#[inline]
fn unit_ball_scale(squared_norm: f32) -> f32 {
    1.0 / squared_norm.sqrt().max(1.0)
}

#[inline]
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
        for _ in 0..iterations {
            {
                let bar = &bar;
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
                    .for_each(|(chunk, ((((((p, qd), qo), rows), constants), lengths), centres))| {
                        let mut terms = self
                            .terms_from(&self.row_start, &self.row_terms, 3 * chunk * CHUNK)
                            .iter();
                        let (p_lanes, p) = p.as_chunks_mut::<LANES>();
                        let (qd_lanes, qd) = qd.as_chunks_mut::<LANES>();
                        let (qo_lanes, qo) = qo.as_chunks_mut::<LANES>();
                        let (rows_lanes, rows) = rows.as_chunks_mut::<{ 3 * LANES }>();
                        let (k_lanes, constants) = constants.as_chunks::<LANES>();
                        let (lengths_lanes, lengths) = lengths.as_chunks::<LANES>();
                        let (centres_lanes, centres) = centres.as_chunks::<LANES>();
                        let groups = p_lanes
                            .iter_mut()
                            .zip(qd_lanes.iter_mut())
                            .zip(qo_lanes.iter_mut())
                            .zip(rows_lanes.iter_mut())
                            .zip(k_lanes.iter().zip(lengths_lanes).zip(centres_lanes));
                        for ((((p, qd), qo), rows), ((k, lengths), centres)) in groups {
                            let k = bytemuck::cast_ref(k);
                            dual_lanes(&mut terms, bar, centres, k, lengths, p, qd, qo, rows);
                        }
                        // The chunk's last cubes, fewer than LANES: the same steps one at a time.
                        let cubes = p
                            .iter_mut()
                            .zip(qd.iter_mut())
                            .zip(qo.iter_mut())
                            .zip(rows.chunks_exact_mut(3))
                            .zip(constants.iter().zip(lengths).zip(centres));
                        for ((((p, qd), qo), rows), ((k, lengths), centre)) in cubes {
                            dual(&mut terms, bar, *centre, k, lengths, p, qd, qo, rows);
                        }
                    });
            }
            {
                let rows = &rows;
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
                        let mut terms = self.terms_from(&self.col_start, &self.col_terms, chunk * CHUNK).iter();
                        let (uv_lanes, uv) = uv.as_chunks_mut::<LANES>();
                        let (bar_lanes, bar) = bar.as_chunks_mut::<LANES>();
                        let (own_lanes, own_rows) = own_rows.as_chunks::<{ 3 * LANES }>();
                        let (k_lanes, constants) = constants.as_chunks::<LANES>();
                        let (lengths_lanes, lengths) = lengths.as_chunks::<LANES>();
                        let (slopes_lanes, slopes) = slopes.as_chunks::<LANES>();
                        let groups = uv_lanes
                            .iter_mut()
                            .zip(bar_lanes.iter_mut())
                            .zip(own_lanes)
                            .zip(k_lanes.iter().zip(lengths_lanes).zip(slopes_lanes));
                        for (((uv, bar), own_rows), ((k, lengths), slopes)) in groups {
                            let (k, slopes) = (bytemuck::cast_ref(k), bytemuck::cast_ref(slopes));
                            primal_lanes(&mut terms, rows, own_rows, k, lengths, slopes, self.lambda, uv, bar);
                        }
                        let cubes = uv
                            .iter_mut()
                            .zip(bar.iter_mut())
                            .zip(own_rows.chunks_exact(3))
                            .zip(constants.iter().zip(lengths).zip(slopes));
                        for (((uv, bar), own_rows), ((k, lengths), slopes)) in cubes {
                            primal(&mut terms, rows, own_rows, k, lengths, slopes, self.lambda, uv, bar);
                        }
                    });
            }
        }
        relayout(self, state, false);
    }
}

/// Dual step of one cube from the extrapolated primal `bar`: p and q move along K and are
/// projected onto their unit balls; then the cube's three packed dual rows are written.
/// Advances `terms` past this cube's.
#[inline]
#[expect(clippy::too_many_arguments, reason = "one cube's columns, borrowed apart")]
fn dual(
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
#[inline]
#[expect(clippy::too_many_arguments, reason = "one cube's columns, borrowed apart")]
fn primal(
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

/// Cubes per lane group of [`dual_lanes`] and [`primal_lanes`]: one `Vec4` holds one value of
/// each of 4 cubes.
const LANES: usize = 4;

// `relayout` groups a unit's cubes from cube 0 and `iterate` groups each chunk's cubes from the
// chunk's first cube: the two agree only while chunks hold whole groups.
const _: () = assert!(CHUNK.is_multiple_of(LANES), "a chunk must hold whole lane groups");

/// The transpose of 4 vectors: lane i of the result's column j is lane j of `x[i]`.
#[inline]
fn transpose(x: [Vec4; LANES]) -> [Vec4; 4] {
    let t = Mat4::from_cols(x[0], x[1], x[2], x[3]).transpose();
    [t.x_axis, t.y_axis, t.z_axis, t.w_axis]
}

/// `1 / max(sqrt(s), 1)` per lane: [`unit_ball_scale`] of 4 cubes. `max` returns its second
/// operand when the first is NaN, as `f32::max` does here.
#[inline]
fn unit_ball_scale_lanes(squared_norm: Vec4) -> Vec4 {
    // f32::sqrt is correctly rounded, so each lane is the one-cube value; LLVM emits sqrtps.
    Vec4::ONE / squared_norm.map(f32::sqrt).max(Vec4::ONE)
}

/// `x.x^2 + x.y^2 + x.z^2` of 4 cubes, summed in [`sum3`]'s order.
#[inline]
fn sum3_lanes(x: [Vec4; 3]) -> Vec4 {
    x[0] * x[0] + x[1] * x[1] + x[2] * x[2]
}

/// [`dual`] of 4 consecutive cubes with cubes as lanes: the gathers run per cube as in
/// [`dual`], the rest on lane-layout values (`p`, `q_diag`, `q_off` hold one vector per
/// component, their w lanes stay 0). Every cube sees the same float operations in the same
/// order as in [`dual`], so both give the same bits (the GPU twins check this).
#[inline]
#[expect(clippy::too_many_arguments, reason = "4 cubes' columns, borrowed apart")]
fn dual_lanes(
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
#[inline]
#[expect(clippy::too_many_arguments, reason = "4 cubes' columns, borrowed apart")]
fn primal_lanes(
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
#[inline]
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
type SlopeLanes = [f32; (BINS + 1) * LANES];

/// A group of [`LANES`] cubes' values in lane layout, stored in the memory of the per-cube
/// values (`Self` and `[Self::Cube; LANES]` have the same size and alignment).
trait LaneLayout: bytemuck::Pod + Send {
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
fn relayout(kernel: &mut Kernel, state: &mut Packed, to_lanes: bool) {
    relayout_column::<DualLanes>(&mut kernel.dual_constants, to_lanes);
    relayout_column::<PrimalLanes>(&mut kernel.primal_constants, to_lanes);
    relayout_column::<SlopeLanes>(&mut kernel.slopes, to_lanes);
    // The transpose of a 4x4 block is its own inverse.
    for column in [&mut state.uv, &mut state.p, &mut state.q_diag, &mut state.q_off] {
        let (groups, _) = column.as_chunks_mut::<LANES>();
        groups.par_iter_mut().for_each(|group| *group = transpose(*group));
    }
}

/// Runs `iterations` preconditioned primal-dual steps from `state`; returns the energy before
/// and after. The fused twin of [`solve_reference`], on the compiled [`Kernel`].
pub fn solve(problem: &Problem, state: &mut State, iterations: usize) -> (f64, f64) {
    solve_on(None, problem, state, iterations)
}

/// [`solve`] with the iterations on `gpu` when given. A GPU failure (out of memory, device
/// lost, a buffer over the adapter's limits) is logged and the same iterations run on the CPU,
/// from the same starting state.
pub fn solve_on(gpu: Option<&crate::gpu::Gpu>, problem: &Problem, state: &mut State, iterations: usize) -> (f64, f64) {
    let op = Operator::new(problem);
    let Some(mut kernel) = Kernel::new(&op) else {
        return solve_reference(problem, state, iterations);
    };
    let before = start(&op, state);
    let mut packed = Packed::of(state);
    let on_gpu = match gpu {
        Some(gpu) => {
            let result = crate::gpu::tgv::iterate(gpu, &kernel, &mut packed, iterations);
            gpu.count(result.is_ok());
            match result {
                Ok(()) => true,
                Err(error) => {
                    tracing::warn!("{error}; this unit's {} cubes run on the CPU", kernel.n);
                    false
                }
            }
        }
        None => false,
    };
    if !on_gpu {
        kernel.iterate(&mut packed, iterations);
    }
    packed.unpack_into(state);
    let after = energy(&op, state);
    (before, after)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An irregular problem: rows with one, four or no terms, and frozen neighbours.
    fn irregular_problem(n: usize) -> Problem {
        let mut start = vec![0u32];
        let mut terms = Vec::new();
        for c in 0..n {
            for axis in 0..3 {
                match (c + axis) % 4 {
                    0 => terms.push((((c + 1) % n) as u32, 2.0)),
                    1 => {
                        for k in 0..4 {
                            terms.push((((c + 3 + k) % n) as u32, 0.75));
                        }
                    }
                    2 => terms.push(((n + c % 5) as u32, 1.5)),
                    _ => {}
                }
                start.push(terms.len() as u32);
            }
        }
        Problem {
            n,
            start,
            terms,
            frozen_u: (0..5).map(|i| i as f32 * 0.3 - 0.6).collect(),
            frozen_v: (0..5).map(|i| [i as f32 * 0.1, -0.2, 0.05]).collect(),
            hist: (0..n)
                .map(|c| std::array::from_fn(|b| ((c * 7 + b * 3) % 5) as f32))
                .collect(),
            alpha1: (0..n).map(|c| 0.5 + (c % 3) as f32 * 0.25).collect(),
            alpha0: (0..n).map(|c| 0.3 + (c % 2) as f32 * 0.2).collect(),
            lambda: 0.2,
        }
    }

    #[test]
    fn kernel_results_do_not_depend_on_the_thread_count() {
        // More cubes than one parallel chunk, so the chunks' term cursors are exercised.
        let n = 2 * CHUNK + 123;
        let problem = irregular_problem(n);
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("thread pool");
            let mut state = State::zeros(n);
            state
                .u
                .iter_mut()
                .enumerate()
                .for_each(|(i, u)| *u = (i as f32 * 0.11).cos());
            pool.install(|| solve(&problem, &mut state, 15));
            state
        };
        let (one, three) = (run(1), run(3));
        assert!(one == three, "1 and 3 threads gave different iterates");
        // And the chunked kernel still follows the reference on a multi-chunk problem.
        let mut reference = State::zeros(n);
        reference
            .u
            .iter_mut()
            .enumerate()
            .for_each(|(i, u)| *u = (i as f32 * 0.11).cos());
        solve_reference(&problem, &mut reference, 15);
        let worst = one
            .u
            .iter()
            .zip(&reference.u)
            .map(|(a, b)| (a - b).abs())
            .fold(0f32, f32::max);
        assert!(worst < 1e-4, "kernel and reference differ by {worst}");
    }

    #[test]
    fn fused_iteration_matches_the_reference() {
        let n = 40;
        let problem = irregular_problem(n);
        let mut a = State::zeros(n);
        a.u.iter_mut()
            .enumerate()
            .for_each(|(i, u)| *u = (i as f32 * 0.37).sin());
        let mut b = a.clone();
        solve(&problem, &mut a, 25);
        solve_reference(&problem, &mut b, 25);
        for c in 0..n {
            assert!((a.u[c] - b.u[c]).abs() < 1e-4, "u[{c}]: {} vs {}", a.u[c], b.u[c]);
            for i in 0..3 {
                assert!((a.v[c][i] - b.v[c][i]).abs() < 1e-4);
                assert!((a.p[c][i] - b.p[c][i]).abs() < 1e-4);
            }
            for k in 0..6 {
                assert!((a.q[c][k] - b.q[c][k]).abs() < 1e-4);
            }
        }
    }

    /// The lane groups must give exactly the bits of the one-cube steps, projections active or
    /// not, with signed zeros among the inputs, so that where a chunk's cubes fall into groups
    /// (and so the thread count) changes nothing.
    #[test]
    fn lane_groups_are_the_one_cube_steps_bit_for_bit() {
        struct Draw(u64);
        impl Draw {
            fn unit(&mut self) -> f32 {
                self.0 = self
                    .0
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                (self.0 >> 40) as f32 / (1u64 << 24) as f32
            }
            fn value(&mut self, scale: f32) -> f32 {
                match (self.unit() * 10.0) as u32 {
                    0 => 0.0,
                    1 => -0.0,
                    _ => (self.unit() * 2.0 - 1.0) * scale,
                }
            }
            fn v4(&mut self, scale: f32) -> Vec4 {
                Vec4::new(
                    self.value(scale),
                    self.value(scale),
                    self.value(scale),
                    self.value(scale),
                )
            }
            fn v3(&mut self, scale: f32) -> Vec4 {
                Vec4::new(self.value(scale), self.value(scale), self.value(scale), 0.0)
            }
        }
        let mut draw = Draw(99);
        for _ in 0..300 {
            let scale = if draw.unit() < 0.5 { 3.0 } else { 0.2 };
            let bar: Vec<Vec4> = (0..8).map(|_| draw.v4(scale)).collect();
            let rows: Vec<Vec4> = (0..12).map(|_| draw.v4(scale)).collect();
            let lengths: [[u16; 4]; LANES] =
                std::array::from_fn(|_| std::array::from_fn(|_| (draw.unit() * 4.0) as u16));
            let gathers: Vec<Gather> = (0..64)
                .map(|_| Gather {
                    // Some indices past the end: the gathers' fallbacks are part of the twin.
                    index: (draw.unit() * 14.0) as u32,
                    weight: draw.value(4.0),
                })
                .collect();
            let dual_k: [DualConstants; LANES] = std::array::from_fn(|_| DualConstants {
                sigma_p: draw.v4(2.0).abs(),
                sigma_q_diag: draw.v4(2.0).abs(),
                sigma_q_off: draw.v3(2.0).abs(),
            });
            let primal_k: [PrimalConstants; LANES] = std::array::from_fn(|_| PrimalConstants {
                tau: draw.v4(1.0).abs(),
                own: draw.v3(2.0),
            });
            let slopes: [Slopes; LANES] = std::array::from_fn(|_| Slopes(std::array::from_fn(|_| draw.value(6.0))));
            let centres: [Vec4; LANES] = std::array::from_fn(|_| draw.v4(scale));
            let (p, qd, qo): ([Vec4; LANES], [Vec4; LANES], [Vec4; LANES]) = (
                std::array::from_fn(|_| draw.v3(scale)),
                std::array::from_fn(|_| draw.v3(scale)),
                std::array::from_fn(|_| draw.v3(scale)),
            );
            let bits = |x: &[Vec4]| {
                x.iter()
                    .flat_map(|v| v.to_array().map(f32::to_bits))
                    .collect::<Vec<_>>()
            };

            // The lane path reads and writes the lane layout that `relayout` makes.
            let (mut lp, mut lqd, mut lqo) = (transpose(p), transpose(qd), transpose(qo));
            let mut lrows = [Vec4::ZERO; 3 * LANES];
            let mut terms = gathers.iter();
            let lane_k = DualLanes::of(&dual_k);
            assert_eq!(
                lane_k
                    .cubes()
                    .map(|k| bits(&[k.sigma_p, k.sigma_q_diag, k.sigma_q_off])),
                dual_k.map(|k| bits(&[k.sigma_p, k.sigma_q_diag, k.sigma_q_off]))
            );
            dual_lanes(
                &mut terms, &bar, &centres, &lane_k, &lengths, &mut lp, &mut lqd, &mut lqo, &mut lrows,
            );
            let (lp, lqd, lqo) = (transpose(lp), transpose(lqd), transpose(lqo));
            let lanes_left = terms.len();
            let (mut op, mut oqd, mut oqo, mut orows) = (p, qd, qo, [Vec4::ZERO; 3 * LANES]);
            let mut terms = gathers.iter();
            for c in 0..LANES {
                let rows = &mut orows[3 * c..3 * c + 3];
                dual(
                    &mut terms,
                    &bar,
                    centres[c],
                    &dual_k[c],
                    &lengths[c],
                    &mut op[c],
                    &mut oqd[c],
                    &mut oqo[c],
                    rows,
                );
            }
            assert_eq!(lanes_left, terms.len(), "both walk the same terms");
            assert_eq!(bits(&lrows), bits(&orows));
            assert_eq!((bits(&lp), bits(&lqd), bits(&lqo)), (bits(&op), bits(&oqd), bits(&oqo)));

            let uv: [Vec4; LANES] = std::array::from_fn(|_| draw.v4(1.5));
            let (mut luv, mut lbar) = (transpose(uv), [Vec4::ZERO; LANES]);
            let mut terms = gathers.iter();
            let (lane_k, lane_slopes) = (PrimalLanes::of(&primal_k), SlopeLanes::of(&slopes));
            assert_eq!(
                lane_slopes.cubes().map(|s| s.0.map(f32::to_bits)),
                slopes.map(|s| s.0.map(f32::to_bits))
            );
            assert_eq!(
                lane_k.cubes().map(|k| bits(&[k.tau, k.own])),
                primal_k.map(|k| bits(&[k.tau, k.own]))
            );
            primal_lanes(
                &mut terms,
                &rows,
                &lrows,
                &lane_k,
                &lengths,
                &lane_slopes,
                0.3,
                &mut luv,
                &mut lbar,
            );
            let luv = transpose(luv);
            let (mut ouv, mut obar) = (uv, [Vec4::ZERO; LANES]);
            let mut terms = gathers.iter();
            for c in 0..LANES {
                let own = &lrows[3 * c..3 * c + 3];
                primal(
                    &mut terms,
                    &rows,
                    own,
                    &primal_k[c],
                    &lengths[c],
                    &slopes[c],
                    0.3,
                    &mut ouv[c],
                    &mut obar[c],
                );
            }
            assert_eq!((bits(&luv), bits(&lbar)), (bits(&ouv), bits(&obar)));
        }
    }

    #[test]
    fn prox_matches_brute_force() {
        let mut seed = 12345u64;
        let mut rand = || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (seed >> 33) as f32 / (1u64 << 31) as f32
        };
        for _ in 0..500 {
            let hist: [f32; BINS] = std::array::from_fn(|_| if rand() < 0.4 { 0.0 } else { (rand() * 6.0).round() });
            let u_tilde = rand() * 3.0 - 1.5;
            let tau_lambda = rand() * 0.3;
            let got = prox_histogram(u_tilde, tau_lambda, &hist);
            let objective = |u: f32| {
                (u - u_tilde).powi(2) / 2.0
                    + tau_lambda * (0..BINS).map(|b| hist[b] * (u - bin_center(b)).abs()).sum::<f32>()
            };
            let mut best = (f32::INFINITY, 0f32);
            for i in 0..=20000 {
                let u = -1.0 + 2.0 * i as f32 / 20000.0;
                let o = objective(u);
                if o < best.0 {
                    best = (o, u);
                }
            }
            assert!(
                objective(got) <= best.0 + 1e-4,
                "prox {got} (objective {}) vs brute force {} ({}) for {hist:?}, u~ {u_tilde}, tl {tau_lambda}",
                objective(got),
                best.1,
                best.0
            );
        }
    }
}
