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
        let xc = x[c];
        std::array::from_fn(|axis| {
            self.row(3 * c + axis)
                .iter()
                .map(|(t, w)| {
                    let t = *t as usize;
                    let xt = if t < self.n { x[t] } else { frozen(t - self.n) };
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
            .map(|c| std::array::from_fn(|a| inv(p.alpha1[c] * (row_abs[3 * c + a] + 1.0))))
            .collect();
        let sigma_q = (0..n)
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
        let tau_u = col1.iter().map(|c| inv(c[0] + c[1] + c[2])).collect();
        let tau_v = (0..n)
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

/// prox of tau lambda sum_b h_b |u - f_b| at u_tilde (Li and Osher; Zach 2008): the median of
/// the 8 bin centres and the 9 values w_i = u_tilde + tau lambda (sum_{b >= i} h_b - sum_{b < i} h_b),
/// then clamped to [-1, 1]. Without votes it is the identity (then the clamp).
pub fn prox_histogram(u_tilde: f32, tau_lambda: f32, hist: &[f32; BINS]) -> f32 {
    let total: f32 = hist.iter().sum();
    if total <= 0.0 {
        return u_tilde.clamp(-1.0, 1.0);
    }
    // The bin centres ascend and the w_i descend in i, so the 9th smallest of the 17 values is
    // found by merging the two sorted lists for 9 steps.
    let mut w = [0f32; BINS + 1];
    let mut below = 0f32;
    for (i, slot) in w.iter_mut().enumerate() {
        *slot = u_tilde + tau_lambda * ((total - below) - below);
        if let Some(h) = hist.get(i) {
            below += h;
        }
    }
    let (mut b, mut i) = (0usize, BINS); // next centre (ascending), next w (w[BINS] is smallest)
    let mut median = 0f32;
    for _ in 0..=BINS {
        let centre = if b < BINS { bin_center(b) } else { f32::INFINITY };
        let candidate = w[i];
        if centre <= candidate {
            median = centre;
            b += 1;
        } else {
            median = candidate;
            i = i.wrapping_sub(1);
            if i > BINS {
                // All w taken: the rest are centres.
                i = 0;
                w[0] = f32::INFINITY;
            }
        }
    }
    median.clamp(-1.0, 1.0)
}

fn project<const N: usize>(x: &mut [f32; N], radius: f32) {
    let norm = x.iter().map(|v| v * v).sum::<f32>().sqrt();
    if norm > radius {
        let s = if norm > 0.0 { radius / norm } else { 0.0 };
        x.iter_mut().for_each(|v| *v *= s);
    }
}

/// Energy of a state (free cubes only).
pub fn energy(op: &Operator<'_>, state: &State) -> f64 {
    let p = op.problem;
    let (g, e) = op.apply(&state.u, &state.v, true);
    (0..p.n)
        .map(|c| {
            let tv = g[c].iter().map(|x| x * x).sum::<f32>().sqrt();
            let tgv = e[c].iter().map(|x| x * x).sum::<f32>().sqrt();
            let data: f32 = (0..BINS)
                .map(|b| p.hist[c][b] * (state.u[c] - bin_center(b)).abs())
                .sum();
            f64::from(tv) + f64::from(tgv) + f64::from(p.lambda * data)
        })
        .sum()
}

/// Puts the duals inside their (unit) balls; returns the starting energy.
fn start(op: &Operator<'_>, state: &mut State) -> f64 {
    for (p, q) in state.p.iter_mut().zip(state.q.iter_mut()) {
        project(p, 1.0);
        project(q, 1.0);
    }
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
                project(p, 1.0);
                for k in 0..6 {
                    q[k] += sigma_q[c][k] * e[c][k];
                }
                project(q, 1.0);
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

/// Picks, for the adjoint of E' restricted to v component `i`, which q entry (and factor)
/// feeds the difference along each axis: `[axis] -> (q index, factor)`.
const SYM_PICK: [[(usize, f32); 3]; 3] = [
    [(0, 1.0), (3, SQRT_HALF), (4, SQRT_HALF)],
    [(3, SQRT_HALF), (1, 1.0), (5, SQRT_HALF)],
    [(4, SQRT_HALF), (5, SQRT_HALF), (2, 1.0)],
];

/// Runs `iterations` preconditioned primal-dual steps from `state`; returns the energy before
/// and after. Both steps are gathers over precomputed lists, in place and without allocation,
/// so every value is computed in a fixed order whatever the thread count.
pub fn solve(problem: &Problem, state: &mut State, iterations: usize) -> (f64, f64) {
    let op = Operator::new(problem);
    let steps = op.step_sizes();
    let n = problem.n;
    let before = start(&op, state);
    let mut u_bar = state.u.clone();
    let mut v_bar = state.v.clone();
    let reverse = &op.reverse;
    let (a1, a0) = (&problem.alpha1, &problem.alpha0);
    for _ in 0..iterations {
        // Dual step: p, q from the differences of u_bar, v_bar at each cube.
        {
            let (u_bar, v_bar) = (&u_bar, &v_bar);
            state
                .p
                .par_iter_mut()
                .zip(state.q.par_iter_mut())
                .enumerate()
                .for_each(|(c, (p, q))| {
                    let (uc, vc) = (u_bar[c], v_bar[c]);
                    let mut du = [0f32; 3];
                    let mut dv = [[0f32; 3]; 3]; // dv[i][axis] = D_axis v_i
                    for axis in 0..3 {
                        for &(t, w) in problem.row(3 * c + axis) {
                            let t = t as usize;
                            let (ut, vt) = if t < n {
                                (u_bar[t], v_bar[t])
                            } else {
                                (problem.frozen_u[t - n], problem.frozen_v[t - n])
                            };
                            du[axis] += w * (ut - uc);
                            for i in 0..3 {
                                dv[i][axis] += w * (vt[i] - vc[i]);
                            }
                        }
                    }
                    let sp = &steps.sigma_p[c];
                    for axis in 0..3 {
                        p[axis] += sp[axis] * a1[c] * (du[axis] - vc[axis]);
                    }
                    project(p, 1.0);
                    let e = Operator::sym(dv);
                    let sq = &steps.sigma_q[c];
                    for k in 0..6 {
                        q[k] += sq[k] * a0[c] * e[k];
                    }
                    project(q, 1.0);
                });
        }
        // Primal step: the adjoint gathered per cube, then the prox.
        {
            let (p, q) = (&state.p, &state.q);
            let lambda = problem.lambda;
            state
                .u
                .par_iter_mut()
                .zip(state.v.par_iter_mut())
                .zip(u_bar.par_iter_mut().zip(v_bar.par_iter_mut()))
                .enumerate()
                .for_each(|(j, ((u, v), (ub, vb)))| {
                    let mut ku = 0f32;
                    let mut kv = [0f32; 3];
                    for axis in 0..3 {
                        let own = reverse.row_sum[3 * j + axis];
                        ku -= own * a1[j] * p[j][axis];
                        for (i, pick) in SYM_PICK.iter().enumerate() {
                            let (k, f) = pick[axis];
                            kv[i] -= own * f * a0[j] * q[j][k];
                        }
                    }
                    let (from, to) = (reverse.start[j] as usize, reverse.start[j + 1] as usize);
                    for &(row, w) in &reverse.entries[from..to] {
                        let (c, axis) = (row as usize / 3, row as usize % 3);
                        ku += w * a1[c] * p[c][axis];
                        for (i, pick) in SYM_PICK.iter().enumerate() {
                            let (k, f) = pick[axis];
                            kv[i] += w * f * a0[c] * q[c][k];
                        }
                    }
                    for i in 0..3 {
                        kv[i] -= a1[j] * p[j][i];
                    }
                    let old_u = *u;
                    let new_u = prox_histogram(old_u - steps.tau_u[j] * ku, steps.tau_u[j] * lambda, &problem.hist[j]);
                    *u = new_u;
                    *ub = 2.0 * new_u - old_u;
                    for i in 0..3 {
                        let old = v[i];
                        let new = old - steps.tau_v[j][i] * kv[i];
                        v[i] = new;
                        vb[i] = 2.0 * new - old;
                    }
                });
        }
    }
    let after = energy(&op, state);
    (before, after)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fused_iteration_matches_the_reference() {
        // A small irregular problem: a chain with finer and frozen neighbours.
        let n = 40;
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
        let problem = Problem {
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
        };
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
