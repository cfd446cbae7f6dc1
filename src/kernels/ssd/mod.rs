//! Smooth signed distance (Calakli and Taubin 2011; Calakli et al. 2012, eq. 11) on one unit
//! of an adaptive level cut: the second solver on the store (ARCHITECTURE.md, "Method notes").
//!
//! The unknown is f at the cut's cube centres, where the store keeps every per-cube value (the
//! paper puts f on the primal vertices; the centres let SSD share the level cut, its frozen
//! borders, the segments and the dual extractor with TGV). f > 0 is outside, like TGV's u.
//! The gradient g_c = (D f)_c is TGV's forward difference to the `+` face neighbour(s), which
//! has no checkerboard null space. Per free cube c, with side h_c and the samples that fell in
//! it summarised by their weight W_c, weighted centroid offset d_c and weighted normal sum N_c:
//!
//!   E(f) = sum_c W_c (f_c + g_c . d_c)^2                               (f = 0 at the samples)
//!        + lambda1 sum_c h_c^2 (W_c |g_c|^2 - 2 g_c . N_c + W_c)        (grad f = n there)
//!        + lambda2 sum_(c,t) sigma_ct h^3 |g_c - g_t|^2                  (smooth gradient)
//!        + sum_c a_c h_c^2 (f_c - f0_c)^2                                 (a_c: ANCHOR, more
//!                                                                          where W_c = 0)
//!
//! over the pairs (c, t) of each difference row, sigma_ct the shared face area over the centre
//! distance (the paper's sigma), h the row's cube side. The factors of h make every term scale
//! as h^4 (W is an area, f a length): each level solves the same problem in its own units,
//! which is what lets a coarse level's solution start the next (cascadic multigrid). The
//! anchor ties f to the start f0 (the coarser level's f carried to the cube centre): very
//! weakly where samples lie, so that they place the surface, and firmly enough where none lies
//! that the level follows the coarse solution there ([`UNSAMPLED_ANCHOR`]). A target t
//! outside the unit is frozen: its f and g are constants.
//!
//! E(f) = f^T A f - 2 b^T f + const with A symmetric positive definite; [`solve`] runs
//! conjugate gradients preconditioned by A's diagonal, in f64, with every sum in a fixed order
//! so the result does not depend on the thread count.

use rayon::prelude::*;

#[cfg(test)]
mod tests;

/// Weight of the anchor to the start values, relative to one sample's data term at full
/// weight: small enough not to move a surface that data constrains, large enough to make A
/// positive definite in a cube no sample and no neighbour reaches.
pub const ANCHOR: f64 = 1.0e-10;

/// The anchor's weight, on top of [`ANCHOR`] and in the same units, in cubes without sample
/// weight (under `hybrid`, without samples that have evidence). There f is only the smoothest
/// extension of the surface's distance, which the coarser level has already found, so a level
/// refines f where its data are and elsewhere follows the coarse solution carried to its
/// cubes (the cascadic start). With [`ANCHOR`] alone that extension, held only by the frozen
/// borders, was what the conjugate gradients spent most of their iterations on.
///
/// Measured (docs/parameters.md, "Solvers"): RedKitchen's finest level 204 iterations per cube before, 33
/// after. The groundtruth bunny's clean Chamfer went from 0.00111 to 0.00089. Sparing the
/// cubes within 2, 4 or 6 face steps of samples gave 0.00107, 0.00135 and 0.00117 there, at 36
/// to 71 iterations. The anchor does cost an isolated clean sphere solved as one unit: its
/// surface lies 0.085 finest cubes off against 0.044 (as 653 units, 0.051 against 0.100;
/// `tests/ssd.rs`).
pub const UNSAMPLED_ANCHOR: f64 = 0.1;

/// lambda1 and lambda2 by default, in the cube-relative units above: on a sphere 4.8 cubes in
/// radius (the kernel's test), 1 and 1 put the zero set 0.07 cubes off on average, 0.1 and
/// 0.1 0.02 cubes; 10 times more normal weight or smoothness doubles to sextuples the error.
/// The level stages raise both where the depth maps are noisy
/// (`stages::solve::ssd::noise_normal_weight` and `noise_smoothness`).
pub const DEFAULT_NORMAL_WEIGHT: f64 = 0.1;
/// See [`DEFAULT_NORMAL_WEIGHT`]. More smoothness smooths noisy surfaces but pulls them inwards
/// where they curve (docs/parameters.md, "Solvers").
pub const DEFAULT_SMOOTHNESS: f64 = 0.1;

/// Index of a difference-term target: a free cube (< n) or a frozen one (n + index).
pub type Target = u32;

/// What the samples in one cube say: the data of its energy terms.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct CubeSamples {
    /// Sum of the samples' weights: footprint areas (root units squared) times their maps'
    /// weights, the paper's surface density mu integrated over the cube.
    pub weight: f64,
    /// Weighted mean offset of the samples from the cube centre (root units).
    pub centroid: [f64; 3],
    /// Weighted sum of the samples' unit normals, oriented towards their cameras.
    pub normal: [f64; 3],
}

/// For each free cube, the rows (3 c + axis) with a term that targets it, in row order; and
/// each row's weight sum (the coefficient of the row's own cube is minus it).
#[derive(Clone, Debug, Default)]
pub struct Reverse {
    start: Vec<u32>,
    entries: Vec<(u32, f32)>,
    row_sum: Vec<f64>,
}

impl Reverse {
    fn of(&self, c: usize) -> &[(u32, f32)] {
        let (a, b) = (
            self.start.get(c).copied().unwrap_or(0) as usize,
            self.start.get(c + 1).copied().unwrap_or(0) as usize,
        );
        self.entries.get(a..b).unwrap_or(&[])
    }
}

/// One unit's SSD problem. Lengths are in root units, like TGV's.
#[derive(Clone, Debug, Default)]
pub struct SsdProblem {
    pub n: usize,
    /// Difference rows exactly as [`crate::kernels::tgv::Problem`]'s: the terms of row
    /// (c, axis) are `terms[start[3c + axis] .. start[3c + axis + 1]]`.
    pub start: Vec<u32>,
    pub terms: Vec<(Target, f32)>,
    /// Cube sides (root units).
    pub side: Vec<f64>,
    pub samples: Vec<CubeSamples>,
    /// The start values the anchor ties f to.
    pub anchor: Vec<f64>,
    pub frozen_f: Vec<f64>,
    pub frozen_gradient: Vec<[f64; 3]>,
    /// lambda1: the normal term's weight.
    pub normal_weight: f64,
    /// lambda2: the smoothness term's weight.
    pub smoothness: f64,
    /// The anchor's weight on top of [`ANCHOR`] in cubes without sample weight:
    /// [`UNSAMPLED_ANCHOR`] in the level stages; zero holds f there only by the smoothness.
    pub unsampled_anchor: f64,
    /// Built from `start` and `terms` on first use: set those first (construct with
    /// `..SsdProblem::default()`).
    pub reverse: std::sync::OnceLock<Reverse>,
}

/// How a solve ended.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Solved {
    pub iterations: usize,
    /// |A f - b| / |b| at the end (0 when b = 0).
    pub relative_residual: f64,
    pub energy_before: f64,
    pub energy_after: f64,
}

impl SsdProblem {
    fn row(&self, row: usize) -> &[(Target, f32)] {
        let (a, b) = (
            self.start.get(row).copied().unwrap_or(0) as usize,
            self.start.get(row + 1).copied().unwrap_or(0) as usize,
        );
        self.terms.get(a..b).unwrap_or(&[])
    }

    /// The face-pair weight of a term of row (c, axis): sigma (shared area over distance)
    /// times h^3, so that it scales as h^4 like the data terms (|g_c - g_t| is O(h) where
    /// the surface curves, O(1) where f kinks).
    fn pair_weight(&self, c: usize, w: f32) -> f64 {
        let h = self.side.get(c).copied().unwrap_or(0.0);
        // w = 1 / (count * distance), and the shared area is h^2 / count for `count` finer
        // neighbours or h^2 for one coarser one: sigma = w h^2 either way.
        // h^5 as `powi(5)` computes it, without the call: (h^2)^2 h.
        let h2 = h * h;
        self.smoothness * f64::from(w) * (h2 * h2 * h)
    }

    /// The anchor's coefficient of (f_c - f0_c)^2: [`ANCHOR`] h^2, plus
    /// [`unsampled_anchor`](Self::unsampled_anchor) h^2 where the cube holds no sample weight.
    fn anchor_weight(&self, c: usize) -> f64 {
        let h = self.side.get(c).copied().unwrap_or(0.0);
        let sampled = self.samples.get(c).is_some_and(|s| s.weight > 0.0);
        let weight = if sampled {
            ANCHOR
        } else {
            ANCHOR + self.unsampled_anchor
        };
        weight * h * h
    }

    /// g_c for free values `f`, frozen values included when `with_frozen`.
    fn gradient(&self, c: usize, f: &[f64], with_frozen: bool) -> [f64; 3] {
        let fc = f.get(c).copied().unwrap_or(0.0);
        std::array::from_fn(|axis| {
            self.row(3 * c + axis)
                .iter()
                .map(|(t, w)| {
                    let t = *t as usize;
                    let ft = if t < self.n {
                        f.get(t).copied().unwrap_or(0.0)
                    } else if with_frozen {
                        self.frozen_f.get(t - self.n).copied().unwrap_or(0.0)
                    } else {
                        0.0
                    };
                    f64::from(*w) * (ft - fc)
                })
                .sum()
        })
    }

    /// The gradient of target `t` of a row: a free cube's, or a frozen one's constant.
    fn target_gradient(&self, t: usize, g: &[[f64; 3]], with_frozen: bool) -> [f64; 3] {
        if t < self.n {
            g.get(t).copied().unwrap_or([0.0; 3])
        } else if with_frozen {
            self.frozen_gradient.get(t - self.n).copied().unwrap_or([0.0; 3])
        } else {
            [0.0; 3]
        }
    }

    /// The energy's gradient dE/df for free values `f`; without `with_constants` the frozen
    /// values, normals and anchor values count as zero (then it is 2 A f). Every output is
    /// gathered in a fixed order (own rows, then the reverse lists), so the result does not
    /// depend on the thread count. The right-hand side takes it with the constants; without
    /// them it is the straightforward reference that tests hold [`Operator`]'s product to.
    fn energy_gradient(&self, f: &[f64], with_constants: bool) -> Vec<f64> {
        let n = self.n;
        let reverse = self.reverse();
        let g: Vec<[f64; 3]> = (0..n)
            .into_par_iter()
            .map(|c| self.gradient(c, f, with_constants))
            .collect();
        // r_c = dE/dg_c: the cube's own data terms, its rows' pairs, and the pairs of the rows
        // that target it.
        let r: Vec<[f64; 3]> = (0..n)
            .into_par_iter()
            .map(|c| {
                let (s, gc, h) = (self.samples[c], g[c], self.side[c]);
                let h2 = h * h;
                let e = f[c] + dot(gc, s.centroid);
                let normal = if with_constants { s.normal } else { [0.0; 3] };
                let mut rc: [f64; 3] = std::array::from_fn(|axis| {
                    2.0 * s.weight * e * s.centroid[axis]
                        + 2.0 * self.normal_weight * h2 * (s.weight * gc[axis] - normal[axis])
                });
                for axis in 0..3 {
                    for (t, w) in self.row(3 * c + axis) {
                        let sigma = self.pair_weight(c, *w);
                        let gt = self.target_gradient(*t as usize, &g, with_constants);
                        (0..3).for_each(|k| rc[k] += 2.0 * sigma * (gc[k] - gt[k]));
                    }
                }
                for (row, w) in reverse.of(c) {
                    let source = *row as usize / 3;
                    let sigma = self.pair_weight(source, *w);
                    (0..3).for_each(|k| rc[k] -= 2.0 * sigma * (g[source][k] - gc[k]));
                }
                rc
            })
            .collect();
        (0..n)
            .into_par_iter()
            .map(|c| {
                let (s, gc) = (self.samples[c], g[c]);
                let anchor = if with_constants { self.anchor[c] } else { 0.0 };
                let mut total =
                    2.0 * s.weight * (f[c] + dot(gc, s.centroid)) + 2.0 * self.anchor_weight(c) * (f[c] - anchor);
                for (axis, rc) in r[c].iter().enumerate() {
                    total -= reverse.row_sum[3 * c + axis] * rc;
                }
                for (row, w) in reverse.of(c) {
                    let row = *row as usize;
                    total += f64::from(*w) * r[row / 3][row % 3];
                }
                total
            })
            .collect()
    }

    /// The reverse lists of the difference rows, built once.
    fn reverse(&self) -> &Reverse {
        self.reverse.get_or_init(|| {
            let n = self.n;
            let mut start = vec![0u32; n + 1];
            for (t, _) in &self.terms {
                if (*t as usize) < n
                    && let Some(count) = start.get_mut(*t as usize + 1)
                {
                    *count += 1;
                }
            }
            for i in 0..n {
                start[i + 1] += start[i];
            }
            let mut fill = start.clone();
            let mut entries = vec![(0u32, 0f32); start[n] as usize];
            let mut row_sum = vec![0f64; 3 * n];
            for (row, sum) in row_sum.iter_mut().enumerate() {
                for (t, w) in self.row(row) {
                    *sum += f64::from(*w);
                    if (*t as usize) < n
                        && let Some(slot) = fill.get_mut(*t as usize)
                    {
                        entries[*slot as usize] = (row as u32, *w);
                        *slot += 1;
                    }
                }
            }
            Reverse {
                start,
                entries,
                row_sum,
            }
        })
    }

    /// g = D f at every free cube, frozen values included: what a level stores beside f.
    pub fn gradients(&self, f: &[f64]) -> Vec<[f64; 3]> {
        (0..self.n).into_par_iter().map(|c| self.gradient(c, f, true)).collect()
    }

    /// A f.
    pub fn apply(&self, f: &[f64]) -> Vec<f64> {
        let mut product = Product::of(self);
        let mut af = vec![0.0; self.n];
        product.apply(f, &mut af);
        af
    }

    /// b: minus half the energy's gradient at f = 0.
    pub fn rhs(&self) -> Vec<f64> {
        self.energy_gradient(&vec![0.0; self.n], true)
            .into_iter()
            .map(|x| -0.5 * x)
            .collect()
    }

    /// E(f), constants included: what a solve reports and decreases. Summed piece by piece
    /// ([`PIECE`]), then the pieces in order: the same for any thread count.
    pub fn energy(&self, f: &[f64]) -> f64 {
        let n = self.n;
        let g: Vec<[f64; 3]> = (0..n).into_par_iter().map(|c| self.gradient(c, f, true)).collect();
        let cube = |c: usize| {
            let (s, gc, h) = (self.samples[c], g[c], self.side[c]);
            let h2 = h * h;
            let e = f[c] + dot(gc, s.centroid);
            let mut total = s.weight * e * e;
            total += self.normal_weight * h2 * (s.weight * dot(gc, gc) - 2.0 * dot(gc, s.normal) + s.weight);
            total += self.anchor_weight(c) * (f[c] - self.anchor[c]).powi(2);
            for (t, w) in (0..3).flat_map(|axis| self.row(3 * c + axis)) {
                let gt = self.target_gradient(*t as usize, &g, true);
                let d = [gc[0] - gt[0], gc[1] - gt[1], gc[2] - gt[2]];
                total += self.pair_weight(c, *w) * dot(d, d);
            }
            total
        };
        let pieces: Vec<f64> = (0..n.div_ceil(PIECE))
            .into_par_iter()
            .map(|piece| (piece * PIECE..n.min((piece + 1) * PIECE)).map(cube).sum::<f64>())
            .collect();
        pieces.into_iter().sum()
    }

    /// Writes g_c's coefficients on the free values to the front of `out` (at least one
    /// entry per term of c's rows, plus one): its own cube first, then its rows' other free
    /// targets in the order they first appear. Returns how many it wrote.
    fn support_into(&self, c: usize, out: &mut [(u32, [f64; 3])]) -> usize {
        let mut length = 1;
        if let Some(own) = out.first_mut() {
            *own = (c as u32, [0.0; 3]);
        }
        for axis in 0..3 {
            let mut own = 0.0;
            for (t, w) in self.row(3 * c + axis) {
                let w = f64::from(*w);
                own -= w;
                let t = *t as usize;
                if t == c {
                    own += w;
                } else if t < self.n {
                    let others = out.get_mut(1..length).unwrap_or_default();
                    match others.iter_mut().find(|(j, _)| *j as usize == t) {
                        Some((_, coefficient)) => coefficient[axis] += w,
                        None => {
                            if let Some(slot) = out.get_mut(length) {
                                let mut coefficient = [0.0; 3];
                                coefficient[axis] = w;
                                *slot = (t as u32, coefficient);
                                length += 1;
                            }
                        }
                    }
                }
            }
            if let Some((_, coefficient)) = out.first_mut() {
                coefficient[axis] = own;
            }
        }
        length
    }

    /// Where cube c's slots start in [`supports`](Self::supports)' entries: one per term of
    /// the rows before it, and one more per cube before it.
    fn support_slot(&self, c: usize) -> usize {
        c + self.start.get(3 * c).copied().unwrap_or(0) as usize
    }

    /// Every free cube's [`support_into`](Self::support_into), packed: cube c's take the
    /// slots from c plus the index of its first term (one per term and one more), of which the
    /// first `lengths[c]` are written. One allocation for all, and the supports of
    /// neighbouring cubes lie side by side.
    fn supports(&self) -> (Vec<u32>, Vec<(u32, [f64; 3])>) {
        let n = self.n;
        let mut entries = vec![(0u32, [0.0; 3]); self.support_slot(n)];
        let mut lengths = vec![0u32; n];
        // Each piece of cubes writes its own run of slots.
        let mut runs = Vec::with_capacity(n.div_ceil(PIECE));
        let mut rest = entries.as_mut_slice();
        for piece_start in (0..n).step_by(PIECE) {
            let end = (piece_start + PIECE).min(n);
            let (run, tail) =
                rest.split_at_mut((self.support_slot(end) - self.support_slot(piece_start)).min(rest.len()));
            runs.push((piece_start, run));
            rest = tail;
        }
        runs.into_par_iter()
            .zip(lengths.par_chunks_mut(PIECE))
            .for_each(|((piece_start, run), lengths)| {
                for (i, length) in lengths.iter_mut().enumerate() {
                    let c = piece_start + i;
                    let from = self.support_slot(c) - self.support_slot(piece_start);
                    let written = self.support_into(c, run.get_mut(from..).unwrap_or_default());
                    *length = written as u32;
                }
            });
        (lengths, entries)
    }

    /// A's diagonal, for the Jacobi preconditioner: A_jj = E_h(e_j), the homogeneous energy of
    /// the unit vector, summed term by term.
    pub fn diagonal(&self) -> Vec<f64> {
        let n = self.n;
        let (lengths, entries) = self.supports();
        let support = |c: usize| {
            let from = self.support_slot(c);
            let length = lengths.get(c).copied().unwrap_or(0) as usize;
            entries.get(from..from + length).unwrap_or_default()
        };
        let mut diagonal = vec![0.0; n];
        // Where each free cube sits in the support of the cube at hand (u32::MAX: not in it),
        // so that a term's two supports are matched in one pass (a search per entry was a
        // fifth of this loop's time).
        let mut position = vec![u32::MAX; n];
        let mut difference: Vec<[f64; 3]> = Vec::new();
        for c in 0..n {
            let (s, h) = (self.samples[c], self.side[c]);
            let h2 = h * h;
            diagonal[c] += self.anchor_weight(c);
            let own = support(c);
            for (index, (j, coefficient)) in own.iter().enumerate() {
                let de = if index == 0 { 1.0 } else { 0.0 } + dot(*coefficient, s.centroid);
                if let Some(d) = diagonal.get_mut(*j as usize) {
                    *d += s.weight * de * de + self.normal_weight * h2 * s.weight * dot(*coefficient, *coefficient);
                }
                if let Some(p) = position.get_mut(*j as usize) {
                    *p = index as u32;
                }
            }
            // Each term adds sigma |d_j|^2 once to every j of the two supports, with d_j g_c's
            // coefficient less g_t's: the order of the adds to each diagonal entry, and so
            // every bit, is that of a pass over the merged supports.
            for (t, w) in (0..3).flat_map(|axis| self.row(3 * c + axis)) {
                let sigma = self.pair_weight(c, *w);
                difference.clear();
                difference.extend(own.iter().map(|(_, coefficient)| *coefficient));
                if (*t as usize) < n {
                    for (j, coefficient) in support(*t as usize) {
                        let at = position.get(*j as usize).copied().unwrap_or(u32::MAX);
                        match difference.get_mut(at as usize) {
                            Some(d) => (0..3).for_each(|k| d[k] -= coefficient[k]),
                            None => {
                                if let Some(value) = diagonal.get_mut(*j as usize) {
                                    *value += sigma * dot(*coefficient, *coefficient);
                                }
                            }
                        }
                    }
                }
                for ((j, _), d) in own.iter().zip(&difference) {
                    if let Some(value) = diagonal.get_mut(*j as usize) {
                        *value += sigma * dot(*d, *d);
                    }
                }
            }
            for (j, _) in own {
                if let Some(p) = position.get_mut(*j as usize) {
                    *p = u32::MAX;
                }
            }
        }
        diagonal
    }
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

/// Elements per piece of the parallel loops: every piece's result depends on its elements
/// only, and reductions add the pieces' sums in piece order, so the results are the same for
/// any thread count.
const PIECE: usize = 1 << 13;

/// sum a_i b_i, deterministic for any thread count ([`PIECE`]).
fn inner(a: &[f64], b: &[f64]) -> f64 {
    let partial: Vec<f64> = a
        .par_chunks(PIECE)
        .zip(b.par_chunks(PIECE))
        .map(|(a, b)| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>())
        .collect();
    partial.into_iter().sum()
}

/// The homogeneous product A f of an [`SsdProblem`] (frozen values, normals and anchors read
/// as zero), with what every product would recompute computed once: the halved energy
/// gradient of [`SsdProblem::energy_gradient`] in three gathers (g = D f; r_c = dE/dg_c / 2
/// with the scalar part of the cube's own row; then D^T r), each output written by one piece
/// of work and summed in a fixed order.
///
/// A piece walks its cubes' rows and reverse lists with cursors over the packed lists, and
/// reads each cube's constants as one record: with bounds-checked lookups per row and per
/// constant, the product spent about 50 ns a cube even where every byte was in the L1 cache.
struct Operator<'a> {
    problem: &'a SsdProblem,
    /// Per cube, what the response pass reads of it.
    constants: Vec<CubeConstants>,
    /// Per cube, the number of terms of its three rows and of its reverse list.
    lengths: Vec<[u8; 4]>,
}

/// The constants of one cube's response, read together.
#[derive(Clone, Copy, Debug, Default)]
struct CubeConstants {
    /// The cube's sample weight W and centroid.
    weight: f64,
    centroid: [f64; 3],
    /// The coefficient of g_c in r_c: lambda1 h^2 W plus the pair weights of the cube's terms
    /// and of the terms that target it.
    coupling: f64,
    /// The anchor's coefficient of f_c ([`SsdProblem::anchor_weight`]).
    anchor_weight: f64,
    /// The sums of the weights of the cube's three rows (minus their own coefficients).
    row_sum: [f64; 3],
}

/// The buffers of [`Operator::apply`], kept between products.
struct Workspace {
    /// g_c, and beside it the cube's pair scale, smoothness h^5 (a term's pair weight is this
    /// times the term's w), read together by the cubes its rows target; written once.
    gradient: Vec<[f64; 4]>,
    /// r_c.
    response: Vec<[f64; 3]>,
    /// The part of (A f)_c from the cube's own terms.
    own: Vec<f64>,
}

/// The entries from `first` on of a list whose entries of item i start at `start[i]`.
fn entries_from<'e, T>(start: &[u32], entries: &'e [T], first: usize) -> &'e [T] {
    let from = start.get(first).copied().unwrap_or(0) as usize;
    entries.get(from..).unwrap_or(&[])
}

/// Splits the next `count` entries off `cursor`.
#[inline]
fn take<'e, T>(cursor: &mut &'e [T], count: u8) -> &'e [T] {
    let (head, tail) = cursor.split_at(usize::from(count).min(cursor.len()));
    *cursor = tail;
    head
}

impl<'a> Operator<'a> {
    /// `None` when a row or reverse list has more than 255 terms (a 2:1 balanced cut has at
    /// most 4 a row and 12 a list); the caller then takes [`SsdProblem::energy_gradient`].
    fn new(problem: &'a SsdProblem) -> Option<Operator<'a>> {
        let n = problem.n;
        let reverse = problem.reverse();
        let pair_scale: Vec<f64> = (0..n).map(|c| problem.pair_weight(c, 1.0)).collect();
        let constants = (0..n)
            .into_par_iter()
            .map(|c| {
                let h = problem.side.get(c).copied().unwrap_or(0.0);
                let samples = problem.samples.get(c).copied().unwrap_or_default();
                let scale = pair_scale.get(c).copied().unwrap_or(0.0);
                let own: f64 = (0..3)
                    .flat_map(|axis| problem.row(3 * c + axis))
                    .map(|(_, w)| scale * f64::from(*w))
                    .sum();
                let targeting: f64 = reverse
                    .of(c)
                    .iter()
                    .map(|(row, w)| pair_scale.get(*row as usize / 3).copied().unwrap_or(0.0) * f64::from(*w))
                    .sum();
                let row_sum = |axis: usize| reverse.row_sum.get(3 * c + axis).copied().unwrap_or(0.0);
                CubeConstants {
                    weight: samples.weight,
                    centroid: samples.centroid,
                    coupling: problem.normal_weight * h * h * samples.weight + own + targeting,
                    anchor_weight: problem.anchor_weight(c),
                    row_sum: [row_sum(0), row_sum(1), row_sum(2)],
                }
            })
            .collect();
        let lengths = (0..n)
            .into_par_iter()
            .map(|c| {
                let length = |list: &[(u32, f32)]| u8::try_from(list.len()).ok();
                Some([
                    length(problem.row(3 * c))?,
                    length(problem.row(3 * c + 1))?,
                    length(problem.row(3 * c + 2))?,
                    length(reverse.of(c))?,
                ])
            })
            .collect::<Option<Vec<_>>>()?;
        Some(Operator {
            problem,
            constants,
            lengths,
        })
    }

    /// The buffers of [`apply`](Self::apply), the pair scales in place.
    fn workspace(&self) -> Workspace {
        let n = self.problem.n;
        Workspace {
            gradient: (0..n)
                .map(|c| [0.0, 0.0, 0.0, self.problem.pair_weight(c, 1.0)])
                .collect(),
            response: vec![[0.0; 3]; n],
            own: vec![0.0; n],
        }
    }

    /// `af` = A `f`.
    fn apply(&self, f: &[f64], work: &mut Workspace, af: &mut [f64]) {
        let problem = self.problem;
        let reverse = problem.reverse();
        let lengths = &self.lengths;
        work.gradient
            .par_chunks_mut(PIECE)
            .zip(lengths.par_chunks(PIECE))
            .zip(f.par_chunks(PIECE))
            .enumerate()
            .for_each(|(piece, ((out, lengths), own_f))| {
                let mut terms = entries_from(&problem.start, &problem.terms, 3 * piece * PIECE);
                for ((g, length), fc) in out.iter_mut().zip(lengths).zip(own_f) {
                    for (value, count) in g.iter_mut().zip(length.iter().take(3)) {
                        *value = take(&mut terms, *count)
                            .iter()
                            .map(|(t, w)| f64::from(*w) * (f.get(*t as usize).copied().unwrap_or(0.0) - fc))
                            .sum();
                    }
                }
            });
        let gradient = &work.gradient;
        work.response
            .par_chunks_mut(PIECE)
            .zip(work.own.par_chunks_mut(PIECE))
            .zip(self.constants.par_chunks(PIECE))
            .zip(lengths.par_chunks(PIECE))
            .zip(f.par_chunks(PIECE))
            .zip(gradient.par_chunks(PIECE))
            .enumerate()
            .for_each(|(piece, (((((responses, owns), constants), lengths), own_f), own_g))| {
                let mut terms = entries_from(&problem.start, &problem.terms, 3 * piece * PIECE);
                let mut targeting = entries_from(&reverse.start, &reverse.entries, piece * PIECE);
                let cubes = responses
                    .iter_mut()
                    .zip(owns)
                    .zip(constants)
                    .zip(lengths)
                    .zip(own_f)
                    .zip(own_g);
                for (((((rc, own), k), length), fc), g) in cubes {
                    let gc = [g[0], g[1], g[2]];
                    let we = k.weight * (fc + dot(gc, k.centroid));
                    let mut r: [f64; 3] = std::array::from_fn(|a| we * k.centroid[a] + k.coupling * gc[a]);
                    let scale = g[3];
                    // The three rows' terms are one run of `terms`, taken in row order.
                    let rows = length[0].saturating_add(length[1]).saturating_add(length[2]);
                    for (t, w) in take(&mut terms, rows) {
                        // Frozen targets (t >= n) lie past the buffer and read as absent.
                        if let Some(gt) = gradient.get(*t as usize) {
                            let sigma = scale * f64::from(*w);
                            (0..3).for_each(|a| r[a] -= sigma * gt[a]);
                        }
                    }
                    for (row, w) in take(&mut targeting, length[3]) {
                        if let Some(gs) = gradient.get(*row as usize / 3) {
                            let sigma = gs[3] * f64::from(*w);
                            (0..3).for_each(|a| r[a] -= sigma * gs[a]);
                        }
                    }
                    *own =
                        we + k.anchor_weight * fc - (k.row_sum[0] * r[0] + k.row_sum[1] * r[1] + k.row_sum[2] * r[2]);
                    *rc = r;
                }
            });
        // r_c's components are rows 3 c .. 3 c + 3 of the flat buffer, so a row indexes it
        // (a division and a remainder per entry were a third of the product's time).
        let (response, own) = (work.response.as_flattened(), &work.own);
        af.par_chunks_mut(PIECE)
            .zip(own.par_chunks(PIECE))
            .zip(lengths.par_chunks(PIECE))
            .enumerate()
            .for_each(|(piece, ((out, own), lengths))| {
                let mut targeting = entries_from(&reverse.start, &reverse.entries, piece * PIECE);
                for ((value, own), length) in out.iter_mut().zip(own).zip(lengths) {
                    let mut total = *own;
                    for (row, w) in take(&mut targeting, length[3]) {
                        total += f64::from(*w) * response.get(*row as usize).copied().unwrap_or(0.0);
                    }
                    *value = total;
                }
            });
    }
}

/// A f by the packed [`Operator`], or by the energy's gradient where a list is too long to pack.
enum Product<'a> {
    Packed(Operator<'a>, Workspace),
    Reference(&'a SsdProblem),
}

impl<'a> Product<'a> {
    fn of(problem: &'a SsdProblem) -> Product<'a> {
        match Operator::new(problem) {
            Some(operator) => {
                let workspace = operator.workspace();
                Product::Packed(operator, workspace)
            }
            None => Product::Reference(problem),
        }
    }

    /// `af` = A `f`.
    fn apply(&mut self, f: &[f64], af: &mut [f64]) {
        match self {
            Product::Packed(operator, workspace) => operator.apply(f, workspace, af),
            Product::Reference(problem) => {
                for (out, gradient) in af.iter_mut().zip(problem.energy_gradient(f, false)) {
                    *out = 0.5 * gradient;
                }
            }
        }
    }
}

/// Minimises the unit's energy from `f` (the start values) by conjugate gradients with A's
/// diagonal as preconditioner, until |A f - b| <= tolerance |b| or `max_iterations`.
pub fn solve(problem: &SsdProblem, f: &mut [f64], tolerance: f64, max_iterations: usize) -> Solved {
    let n = problem.n;
    let start: &[f64] = f;
    // The diagonal is one sequential pass (its adds keep one order for every bit); the energy,
    // the right-hand side and the packed operator are built beside it, on a core the unit's
    // neighbours leave idle (at the end of a level, one unit on two cores). Each is a pure
    // function of the problem, so the results are the same as one after the other.
    let (inverse_diagonal, (energy_before, b, mut product)) = rayon::join(
        || {
            problem
                .diagonal()
                .into_iter()
                .map(|d| if d > 0.0 { 1.0 / d } else { 0.0 })
                .collect::<Vec<f64>>()
        },
        || (problem.energy(start), problem.rhs(), Product::of(problem)),
    );
    let b_norm = inner(&b, &b).sqrt();
    let mut ap = vec![0.0; n];
    product.apply(f, &mut ap);
    let mut r: Vec<f64> = b.iter().zip(&ap).map(|(b, a)| b - a).collect();
    let mut z: Vec<f64> = r.iter().zip(&inverse_diagonal).map(|(r, m)| r * m).collect();
    let mut p = z.clone();
    let mut rz = inner(&r, &z);
    let mut rr = inner(&r, &r);
    let mut iterations = 0;
    let target = tolerance * b_norm;
    while iterations < max_iterations && rr.sqrt() > target && rz > 0.0 {
        product.apply(&p, &mut ap);
        let pap = inner(&p, &ap);
        if pap <= 0.0 {
            break;
        }
        let alpha = rz / pap;
        // f += alpha p, r -= alpha A p, z = M^-1 r, with r.z and r.r of the pieces.
        let sums: Vec<(f64, f64)> = f
            .par_chunks_mut(PIECE)
            .zip(r.par_chunks_mut(PIECE))
            .zip(z.par_chunks_mut(PIECE))
            .zip(p.par_chunks(PIECE))
            .zip(ap.par_chunks(PIECE))
            .zip(inverse_diagonal.par_chunks(PIECE))
            .map(|(((((f, r), z), p), ap), m)| {
                let (mut rz, mut rr) = (0.0, 0.0);
                for (((((f, r), z), p), ap), m) in f.iter_mut().zip(r).zip(z).zip(p).zip(ap).zip(m) {
                    *f += alpha * p;
                    *r -= alpha * ap;
                    *z = *r * m;
                    rz += *r * *z;
                    rr += *r * *r;
                }
                (rz, rr)
            })
            .collect();
        let rz_next: f64 = sums.iter().map(|s| s.0).sum();
        rr = sums.iter().map(|s| s.1).sum();
        let beta = rz_next / rz;
        rz = rz_next;
        p.par_chunks_mut(PIECE)
            .zip(z.par_chunks(PIECE))
            .for_each(|(p, z)| p.iter_mut().zip(z).for_each(|(p, z)| *p = z + beta * *p));
        iterations += 1;
    }
    Solved {
        iterations,
        relative_residual: if b_norm > 0.0 { rr.sqrt() / b_norm } else { 0.0 },
        energy_before,
        energy_after: problem.energy(f),
    }
}
