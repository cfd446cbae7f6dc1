//! TGV minimisation on one unit of an adaptive level cut (paper 3.2; ARCHITECTURE.md,
//! "Method notes").
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

use glam::Vec4;
use rayon::prelude::*;

use crate::kernels::votes::{BINS, bin_center};

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
#[inline(always)]
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
            let du = p.diff(c, &state.u, |k| p.frozen_u[k]);
            let dv: [[f32; 3]; 3] = std::array::from_fn(|i| p.diff_by(c, |t| state.v[t][i], |k| p.frozen_v[k][i]));
            cube_energy(p, c, state.u[c], state.v[c], du, dv)
        })
        .collect();
    per_cube.iter().sum()
}

/// Cube `c`'s share of the energy from its u, v and their differences `du` (D u) and `dv`
/// (`dv[i][j]` = D_j v_i): alpha1 |D u - v| + alpha0 |E'(v)| + lambda times the histogram's
/// data term. [`energy`] and the kernel's `Kernel::energy` both end here, so they agree to
/// the bit wherever their differences do.
pub(super) fn cube_energy(p: &Problem, c: usize, u: f32, v: [f32; 3], du: [f32; 3], dv: [[f32; 3]; 3]) -> f64 {
    let (w1, w0) = (
        p.alpha1.get(c).copied().unwrap_or(0.0),
        p.alpha0.get(c).copied().unwrap_or(0.0),
    );
    let g = [w1 * (du[0] - v[0]), w1 * (du[1] - v[1]), w1 * (du[2] - v[2])];
    let e = Operator::sym(dv).map(|e| w0 * e);
    let tv = g.iter().map(|x| x * x).sum::<f32>().sqrt();
    let tgv = e.iter().map(|x| x * x).sum::<f32>().sqrt();
    let hist = p.hist.get(c).copied().unwrap_or_default();
    let data: f32 = hist
        .iter()
        .enumerate()
        .map(|(b, h)| h * (u - bin_center(b)).abs())
        .sum();
    f64::from(tv) + f64::from(tgv) + f64::from(p.lambda * data)
}

/// Puts the duals inside their (unit) balls.
fn project_duals(state: &mut State) {
    state.p.par_iter_mut().zip(state.q.par_iter_mut()).for_each(|(p, q)| {
        project(p);
        project(q);
    });
}

/// Puts the duals inside their (unit) balls; returns the starting energy.
fn start(op: &Operator<'_>, state: &mut State) -> f64 {
    project_duals(state);
    energy(op, state)
}

/// The reference iteration, written with the operator and its adjoint; [`solve`] is its fused
/// twin and is tested against it.
pub fn solve_reference(problem: &Problem, state: &mut State, iterations: usize) -> (f64, f64) {
    let op = Operator::new(problem);
    let before = start(&op, state);
    reference_steps(&op, state, iterations);
    let after = energy(&op, state);
    (before, after)
}

/// `iterations` reference steps from `state`, the extrapolation starting afresh (u_bar = u).
fn reference_steps(op: &Operator<'_>, state: &mut State, iterations: usize) {
    let problem = op.problem;
    let StepSizes {
        sigma_p,
        sigma_q,
        tau_u,
        tau_v,
    } = op.step_sizes();
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
}

mod fused;
mod lanes;
#[cfg(test)]
mod tests;

pub use fused::{DualConstants, Gather, Kernel, Packed, PrimalConstants};
pub use lanes::{DualLanes, PrimalLanes};

/// Runs `iterations` preconditioned primal-dual steps from `state`; returns the energy before
/// and after. The fused twin of [`solve_reference`], on the compiled [`Kernel`].
pub fn solve(problem: &Problem, state: &mut State, iterations: usize) -> (f64, f64) {
    let solved = solve_accelerated(problem, state, Stopping::after(iterations), |_, _, _| false);
    (solved.energy_before, solved.energy_after)
}

/// Iterations between two checks of the stopping rule. A check costs about one iteration (the
/// energy, and unpacking the state), so checks add about 4 % to a unit's time.
pub const CHECK_INTERVAL: usize = 25;

/// When a unit's iterations stop: after `max_iterations`, or at the first check (every
/// [`CHECK_INTERVAL`] iterations) where the energy changed by at most `tolerance` times its
/// magnitude since the previous check. A tolerance of 0 runs every iteration, unchecked.
///
/// The rule reads only the unit's own energy, which is summed in cube order, so where a unit
/// stops depends on its data alone: never on the thread count or on other units. Each batch
/// between checks starts its extrapolation afresh (u_bar = u), on the CPU and the GPU alike;
/// with a tolerance of 0 there is one batch and the iteration is the unchecked one.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Stopping {
    pub max_iterations: usize,
    pub tolerance: f64,
}

impl Stopping {
    /// Exactly `iterations` iterations, unchecked.
    pub fn after(iterations: usize) -> Stopping {
        Stopping {
            max_iterations: iterations,
            tolerance: 0.0,
        }
    }

    /// The size of the next batch after `done` iterations.
    fn batch(&self, done: usize) -> usize {
        let left = self.max_iterations.saturating_sub(done);
        if self.tolerance > 0.0 {
            left.min(CHECK_INTERVAL)
        } else {
            left
        }
    }

    /// Whether a check that found `energy`, after `previous` at the check before, stops.
    fn converged(&self, previous: f64, energy: f64) -> bool {
        self.tolerance > 0.0 && (previous - energy).abs() <= self.tolerance * energy.abs().max(f64::MIN_POSITIVE)
    }
}

/// What a unit's solve did: its energy before and after, and the iterations it ran.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Solved {
    pub energy_before: f64,
    pub energy_after: f64,
    pub iterations: usize,
}

/// Solves as [`Stopping`] says, offering the compiled kernel, the packed state and each
/// batch's iteration count to `accelerate` first (a GPU, say): when it returns true it has
/// run the batch on the packed state; when it returns false (it failed, or declined) that
/// batch and every later one run on the CPU from the same state. A problem the kernel cannot
/// compile runs [`solve_reference`]'s steps instead, under the same rule.
pub fn solve_accelerated(
    problem: &Problem,
    state: &mut State,
    stopping: Stopping,
    mut accelerate: impl FnMut(&Kernel, &mut Packed, usize) -> bool,
) -> Solved {
    let op = Operator::new(problem);
    project_duals(state);
    let mut done = 0;
    let Some(mut kernel) = Kernel::new(&op) else {
        let energy_before = energy(&op, state);
        let mut previous = energy_before;
        let mut checked = None;
        loop {
            let batch = stopping.batch(done);
            if batch == 0 {
                break;
            }
            reference_steps(&op, state, batch);
            done += batch;
            checked = None;
            if stopping.tolerance > 0.0 {
                let energy = energy(&op, state);
                checked = Some(energy);
                if stopping.converged(previous, energy) {
                    break;
                }
                previous = energy;
            }
        }
        return Solved {
            energy_before,
            energy_after: checked.unwrap_or_else(|| energy(&op, state)),
            iterations: done,
        };
    };
    let mut packed = Packed::of(state);
    // The kernel's energy is the reference's to the bit, at a fraction of its cost (it was
    // about 2 % of RedKitchen's finest level).
    let energy_before = kernel.energy(problem, &packed);
    let mut previous = energy_before;
    let mut accelerated = true;
    let mut checked = None;
    loop {
        let batch = stopping.batch(done);
        if batch == 0 {
            break;
        }
        accelerated = accelerated && accelerate(&kernel, &mut packed, batch);
        if !accelerated {
            kernel.iterate(&mut packed, batch);
        }
        done += batch;
        checked = None;
        if stopping.tolerance > 0.0 {
            let energy = kernel.energy(problem, &packed);
            checked = Some(energy);
            if stopping.converged(previous, energy) {
                break;
            }
            previous = energy;
        }
    }
    packed.unpack_into(state);
    Solved {
        energy_before,
        energy_after: checked.unwrap_or_else(|| energy(&op, state)),
        iterations: done,
    }
}
