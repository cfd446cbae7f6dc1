//! The geometry of a division: the root cube, octree nodes, their core and grown cubes, the
//! per-node point counts of the counting pass, and the lookup from a point to the cubes that
//! take it.
//!
//! Exactness: the root's side is a power of two, at least a millionth of the coordinates'
//! magnitude, and its corner a multiple of the side / 2^[`GRID_BITS`], so every node's corner,
//! `min + index * side`, is exact in f64, and so is `min + side`: the core cubes
//! that `subspaces.json` lists tile the root exactly, and a point's node, found through its
//! integer grid coordinates, agrees with the comparisons `min <= p < min + size` a user makes.

use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};

use serde::{Deserialize, Serialize};

/// Levels of the integer grid under the root: no node is deeper.
pub const GRID_BITS: u32 = 32;

/// 2^-GRID_BITS: the grid's unit over the root's side.
const UNIT_PER_SIDE: f64 = 1.0 / 4_294_967_296.0;

/// The root cube of a division.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Root {
    /// Lowest corner.
    pub min: [f64; 3],
    /// Side, a power of two.
    pub size: f64,
}

/// An octree node: its level (0 is the root) and its integer position among the 2^level
/// nodes along each axis.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct Node {
    /// Depth below the root.
    pub level: u32,
    /// Position along x, y, z (each below 2^level).
    pub index: [u32; 3],
}

/// An axis-aligned box, half-open: `min <= p < max`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Bounds {
    /// Lowest corner.
    pub min: [f64; 3],
    /// Highest corner (excluded).
    pub max: [f64; 3],
}

impl Bounds {
    /// Whether `p` lies inside (half-open). All six comparisons are made: in the write pass
    /// most candidates fail one of them at random, and a mispredicted branch costs more than
    /// the rest.
    #[inline]
    pub fn contains(&self, p: [f64; 3]) -> bool {
        let [x, y, z] = p;
        let [x0, y0, z0] = self.min;
        let [x1, y1, z1] = self.max;
        (x0 <= x) & (x < x1) & (y0 <= y) & (y < y1) & (z0 <= z) & (z < z1)
    }

    /// Whether the two boxes share a point.
    pub fn meets(&self, other: &Bounds) -> bool {
        (0..3).all(|a| self.min[a] < other.max[a] && other.min[a] < self.max[a])
    }

    /// The common part (possibly empty).
    pub fn intersection(&self, other: &Bounds) -> Bounds {
        Bounds {
            min: [0, 1, 2].map(|a| self.min[a].max(other.min[a])),
            max: [0, 1, 2].map(|a| self.max[a].min(other.max[a])),
        }
    }
}

/// One coordinate of [`Root::grid`].
#[inline]
fn grid_axis(p: f64, min: f64, unit: f64, per_unit: f64) -> u32 {
    const LAST: i64 = (1i64 << GRID_BITS) - 1;
    // Truncation is floor for the positive values it is used on; the unit is a power of two,
    // so multiplying by its inverse is the exact division.
    let t = (p - min) * per_unit;
    let mut g = if t > 0.0 { (t as i64).min(LAST) } else { 0 };
    // The subtraction rounds: settle the cell with the exact boundaries.
    // The root's side is at least a millionth of the coordinates' magnitude (`Root::around`),
    // so the subtraction errs by at most half a unit and the quotient is at most one cell off:
    // one comparison with the exact boundaries settles it.
    if g > 0 && p < min + g as f64 * unit {
        g -= 1;
    } else if g < LAST && p >= min + (g + 1) as f64 * unit {
        g += 1;
    }
    g as u32
}

impl Root {
    /// The smallest power-of-two cube, on the grid, that holds every point of the box
    /// `[low, high]` (closed), `None` for an empty box.
    pub fn around(low: [f64; 3], high: [f64; 3]) -> Option<Root> {
        if (0..3).any(|a| !low[a].is_finite() || !high[a].is_finite() || low[a] > high[a]) {
            return None;
        }
        let extent = (0..3).map(|a| high[a] - low[a]).fold(0.0f64, f64::max);
        let magnitude = (0..3).map(|a| low[a].abs().max(high[a].abs())).fold(0.0f64, f64::max);
        // A side of at least a millionth of the coordinates' magnitude (a single point, or
        // points on a plane, still get a cube) and some slack, so the highest point is inside.
        let wanted = (extent * (1.0 + 1e-6))
            .max(magnitude * 1e-6)
            .max(f64::MIN_POSITIVE * 1e10);
        let mut size = 2f64.powi(wanted.log2().ceil() as i32);
        loop {
            let unit = size * UNIT_PER_SIDE;
            let min = low.map(|l| (l / unit).floor() * unit);
            if (0..3).all(|a| high[a] < min[a] + size) {
                return Some(Root { min, size });
            }
            size *= 2.0;
        }
    }

    fn unit(&self) -> f64 {
        // Exact: the side is a power of two.
        self.size * UNIT_PER_SIDE
    }

    /// Side of the nodes of `level`.
    pub fn side(&self, level: u32) -> f64 {
        // Exact: a power of two over a power of two (levels stop at GRID_BITS).
        self.size / (1u64 << level.min(63)) as f64
    }

    /// The integer grid coordinates of `p` (clamped to the root): the unique `g` with
    /// `min + g * unit <= p < min + (g + 1) * unit` for a point inside.
    #[inline]
    pub fn grid(&self, p: [f64; 3]) -> [u32; 3] {
        let unit = self.unit();
        let per_unit = 1.0 / unit;
        [
            grid_axis(p[0], self.min[0], unit, per_unit),
            grid_axis(p[1], self.min[1], unit, per_unit),
            grid_axis(p[2], self.min[2], unit, per_unit),
        ]
    }

    /// Finds the nodes of `level` that hold points, quickly (`NodeLocator`).
    pub(crate) fn locator(&self, level: u32) -> NodeLocator {
        let level = level.min(GRID_BITS);
        let nodes = (1u64 << level) as f64;
        NodeLocator {
            root: *self,
            level,
            nodes,
            nodes_whole: 1u64 << level,
            // Exact: powers of two.
            per_node: nodes / self.size,
            // The subtraction errs by at most half a grid unit, 2^(level - GRID_BITS - 1) of a
            // node (see `grid_axis`): a fraction farther than four times that from both faces
            // names the node exactly.
            clear_half: 0.5 - nodes * (4.0 * 0.5 * UNIT_PER_SIDE),
        }
    }

    /// Whether `p` lies in the root cube.
    pub fn contains(&self, p: [f64; 3]) -> bool {
        self.bounds().contains(p)
    }

    /// The root cube as a box.
    pub fn bounds(&self) -> Bounds {
        self.core(Node::ROOT)
    }

    /// A node's own cube.
    pub fn core(&self, node: Node) -> Bounds {
        let side = self.side(node.level);
        let min = [0, 1, 2].map(|a| self.min[a] + f64::from(node.index[a]) * side);
        Bounds {
            min,
            max: [0, 1, 2].map(|a| min[a] + side),
        }
    }

    /// A node's cube grown by `overlap` times its side on every face.
    pub fn grown(&self, node: Node, overlap: f64) -> Bounds {
        let side = self.side(node.level);
        let core = self.core(node);
        let min = core.min.map(|m| m - overlap * side);
        let grown_side = side * (1.0 + 2.0 * overlap);
        Bounds {
            min,
            max: min.map(|m| m + grown_side),
        }
    }
}

/// The index of the node of one level that holds a point (clamped to the root), as
/// `Node::holding(root.grid(p), level).index` gives it, without the grid's exact correction for
/// the points (nearly all) that lie clearly inside a node: the hot loop of every pass.
#[derive(Clone, Copy, Debug)]
pub struct NodeLocator {
    root: Root,
    level: u32,
    nodes: f64,
    /// `nodes` as an integer.
    nodes_whole: u64,
    per_node: f64,
    /// Half a node less the margin: a fraction `f` of a node with `|f - 0.5|` below it lies
    /// farther than the margin from both faces.
    clear_half: f64,
}

impl NodeLocator {
    /// The index of the node that holds `p`.
    #[inline(always)]
    pub fn index(&self, p: [f64; 3]) -> [u32; 3] {
        match self.clear_index(p) {
            Some(index) => index,
            None => self.exact(p),
        }
    }

    /// [`NodeLocator::index`] of a point that lies farther than the margin from its node's
    /// faces, inside the root; `None` for the others. A point it gives the index of lies
    /// strictly inside that node's cube.
    #[inline(always)]
    pub fn clear_index(&self, p: [f64; 3]) -> Option<[u32; 3]> {
        // Adding 1.5 * 2^52 rounds a float below 2^51 in magnitude to a whole number, which
        // then sits in the low bits of the sum: a conversion with no saturation or NaN checks
        // (those took a quarter of the counting pass), and one that runs in SIMD lanes.
        const ROUNDER: f64 = 6_755_399_441_055_744.0;
        let mut index = [0u32; 3];
        let mut clear = true;
        for ((i, &pa), &min) in index.iter_mut().zip(&p).zip(&self.root.min) {
            // Clamped with comparisons that send NaN to -1, which is not clear.
            let t = (pa - min) * self.per_node;
            let t = if t > -1.0 { t } else { -1.0 };
            let t = if t < self.nodes { t } else { self.nodes };
            // The nearest whole number to t - 1/2 (exact: t < 2^33), which is t's floor
            // wherever t is clear of whole numbers.
            let rounded = (t - 0.5) + ROUNDER;
            let whole = rounded.to_bits().wrapping_sub(ROUNDER.to_bits());
            // Exact: `t` and the whole number are within one of each other. A fraction of 0
            // or 1 (t clamped, or a tie rounded to even) is not clear, nor is a whole number
            // below 0, which wraps to a huge value.
            let fraction = t - (rounded - ROUNDER);
            // `fraction - 0.5` errs by at most 2^-54, far inside the margin's slack of four.
            clear &= (whole < self.nodes_whole) & ((fraction - 0.5).abs() < self.clear_half);
            *i = whole as u32;
        }
        clear.then_some(index)
    }

    /// The index of the node that holds `p`, through the grid's exact correction.
    #[cold]
    #[inline(never)]
    pub fn exact(&self, p: [f64; 3]) -> [u32; 3] {
        Node::holding(self.root.grid(p), self.level).index
    }
}

impl Node {
    /// The root.
    pub const ROOT: Node = Node {
        level: 0,
        index: [0; 3],
    };

    /// The node of `level` that holds grid coordinates `g`.
    #[inline]
    pub fn holding(g: [u32; 3], level: u32) -> Node {
        let shift = GRID_BITS - level;
        Node {
            level,
            index: g.map(|c| c.checked_shr(shift).unwrap_or(0)),
        }
    }

    /// Its eight children, in Morton order (x fastest).
    pub fn children(self) -> [Node; 8] {
        std::array::from_fn(|i| Node {
            level: self.level + 1,
            index: [0, 1, 2].map(|a| self.index[a] * 2 + ((i as u32 >> a) & 1)),
        })
    }

    /// Whether `other` is this node or lies inside it.
    pub fn holds(self, other: Node) -> bool {
        other.level >= self.level
            && (0..3).all(|a| other.index[a].checked_shr(other.level - self.level).unwrap_or(0) == self.index[a])
    }

    /// Its ancestor at `level` (itself at its own level).
    pub fn ancestor(self, level: u32) -> Node {
        let up = self.level.saturating_sub(level);
        Node {
            level: self.level.min(level),
            index: self.index.map(|c| c.checked_shr(up).unwrap_or(0)),
        }
    }

    /// A name for files: `L{level}_{x}_{y}_{z}`.
    pub fn name(self) -> String {
        let [x, y, z] = self.index;
        format!("L{}_{x}_{y}_{z}", self.level)
    }
}

/// Point counts of the nodes below `top`, down to `depth` levels below it, counted in one pass
/// over the points (concurrently: relaxed atomic adds commute, so the counts do not depend on
/// the order or the threads).
pub struct Counts {
    top: Node,
    depth: u32,
    finest: Vec<AtomicU64>,
    /// One private copy of the finest counts per worker thread when they fit the budget:
    /// atomic adds of two cores to the same cache lines cost more than the rest of the pass.
    per_thread: Vec<Mutex<Vec<u64>>>,
    /// Per level, relative 0..=depth, once [`Counts::finish`] has summed them.
    levels: Vec<Vec<u64>>,
}

/// The finest counted cells of a [`Counts`], apart from the counts: a copy in the hot loop
/// stays in registers, where the fields of [`Counts`] (behind atomics and locks, which any
/// write may change) are loaded again for every point.
#[derive(Clone, Copy, Debug)]
pub struct CountCells {
    /// The index of the first finest cell along each axis.
    base: [u32; 3],
    /// Finest cells along each axis.
    n: u32,
}

impl CountCells {
    /// The finest counted cell of the node of index `index` at [`Counts::level`], `None`
    /// outside the counted node.
    #[inline]
    pub fn of_index(&self, index: [u32; 3]) -> Option<usize> {
        let relative = [0, 1, 2].map(|a| index[a].wrapping_sub(self.base[a]));
        relative
            .iter()
            .all(|r| *r < self.n)
            .then(|| linear_cell(relative, self.n as usize))
    }
}

/// The place of the cell at `relative` in a grid of `n` cells along each axis, x fastest.
#[inline]
fn linear_cell(relative: [u32; 3], n: usize) -> usize {
    relative[0] as usize + n * (relative[1] as usize + n * relative[2] as usize)
}

/// Adds points to the cells of [`Counts`] ([`Counts::add_with`]).
pub struct CellAdder<'a> {
    copy: Option<std::sync::MutexGuard<'a, Vec<u64>>>,
    shared: &'a [AtomicU64],
    /// Points of one cell not yet added to `shared`.
    run: Option<(usize, u64)>,
}

impl CellAdder<'_> {
    /// Adds one point to `cell`.
    #[inline]
    pub fn add(&mut self, cell: usize) {
        match &mut self.copy {
            Some(copy) => {
                if let Some(c) = copy.get_mut(cell) {
                    *c += 1;
                }
            }
            None => match &mut self.run {
                Some((c, n)) if *c == cell => *n += 1,
                _ => {
                    self.flush();
                    self.run = Some((cell, 1));
                }
            },
        }
    }

    fn flush(&mut self) {
        if let Some((c, n)) = self.run.take()
            && let Some(shared) = self.shared.get(c)
        {
            shared.fetch_add(n, Ordering::Relaxed);
        }
    }
}

/// Bytes a count grid of `depth` levels takes (finest counts and the sums above them).
pub fn counts_bytes(depth: u32) -> u64 {
    (8u64.pow(depth) * 8) * 8 / 7 * 2
}

impl Counts {
    /// Empty counts under `top`, `depth` levels deep; per-thread copies when they take at
    /// most `spare_bytes`.
    pub fn new(top: Node, depth: u32, spare_bytes: u64) -> Counts {
        let cells = 1usize << (3 * depth);
        let threads = rayon::current_num_threads();
        let copies = if (threads * cells * 8) as u64 <= spare_bytes {
            threads
        } else {
            0
        };
        Counts {
            top,
            depth,
            finest: (0..cells).map(|_| AtomicU64::new(0)).collect(),
            per_thread: (0..copies).map(|_| Mutex::new(vec![0; cells])).collect(),
            levels: Vec::new(),
        }
    }

    /// Lets `fill` add points to cells (cells of [`Counts::cells`]) through a
    /// [`CellAdder`]: to this thread's private copy when there is one (locked once for all of
    /// `fill`), else atomically, one add per run of equal cells.
    pub fn add_with<R>(&self, fill: impl FnOnce(&mut CellAdder<'_>) -> R) -> R {
        let copy = rayon::current_thread_index()
            .and_then(|t| self.per_thread.get(t))
            .and_then(|m| m.lock().ok());
        let mut adder = CellAdder {
            copy,
            shared: &self.finest,
            run: None,
        };
        let result = fill(&mut adder);
        adder.flush();
        result
    }

    /// The level of the finest counted cells.
    pub fn level(&self) -> u32 {
        self.top.level + self.depth
    }

    /// Finds the finest counted cells ([`CountCells`]).
    pub fn cells(&self) -> CountCells {
        CountCells {
            base: self.top.index.map(|c| c << self.depth),
            n: 1u32 << self.depth,
        }
    }

    /// Sums the finest counts into every coarser level.
    pub fn finish(&mut self) {
        let mut finest: Vec<u64> = self.finest.iter().map(|c| c.load(Ordering::Relaxed)).collect();
        for copy in self.per_thread.drain(..) {
            let copy = copy.into_inner().unwrap_or_else(std::sync::PoisonError::into_inner);
            for (sum, c) in finest.iter_mut().zip(copy) {
                *sum += c;
            }
        }
        let mut levels = vec![finest];
        for depth in (0..self.depth).rev() {
            let n = 1usize << depth;
            let finer = levels.last().map(Vec::as_slice).unwrap_or_default();
            let mut coarse = vec![0u64; n * n * n];
            for z in 0..n {
                for y in 0..n {
                    for x in 0..n {
                        let mut sum = 0;
                        for child in 0..8 {
                            let (cx, cy, cz) = (2 * x + (child & 1), 2 * y + ((child >> 1) & 1), 2 * z + (child >> 2));
                            sum += finer.get(cx + 2 * n * (cy + 2 * n * cz)).copied().unwrap_or(0);
                        }
                        if let Some(c) = coarse.get_mut(x + n * (y + n * z)) {
                            *c = sum;
                        }
                    }
                }
            }
            levels.push(coarse);
        }
        levels.reverse();
        self.levels = levels;
    }

    /// The count of `node`, which lies under `top` within the counted depth (after
    /// [`Counts::finish`]).
    pub fn of(&self, node: Node) -> u64 {
        let depth = node.level - self.top.level;
        let relative = [0, 1, 2].map(|a| node.index[a] - (self.top.index[a] << depth));
        self.levels
            .get(depth as usize)
            .and_then(|level| level.get(linear_cell(relative, 1 << depth)))
            .copied()
            .unwrap_or(0)
    }
}

/// A node and the points in its core.
pub type NodeCount = (Node, u64);

/// Which nodes under `top` become subspaces (at most `max_points` points each, or at the
/// grid's last level) and which, at the counted depth, still hold too many and are divided
/// again from their own points. Both in depth-first Morton order.
pub fn choose_leaves(counts: &Counts, max_points: u64) -> (Vec<NodeCount>, Vec<NodeCount>) {
    let mut leaves = Vec::new();
    let mut again = Vec::new();
    let mut stack = vec![counts.top];
    while let Some(node) = stack.pop() {
        let count = counts.of(node);
        if count == 0 {
            continue;
        }
        if count <= max_points || node.level == GRID_BITS {
            leaves.push((node, count));
        } else if node.level == counts.top.level + counts.depth {
            again.push((node, count));
        } else {
            stack.extend(node.children().iter().rev());
        }
    }
    (leaves, again)
}

/// For each cell of a uniform grid over a node, the targets (by number) whose grown cube
/// meets the cell: a point's candidates are its cell's. A target whose grown cube holds the
/// whole cell holds every point inside the cell, with no test; the others get an exact test.
/// Points outside the node are looked up in the nearest cell, which lists every target whose
/// grown cube reaches them (a target lies inside the node and its grown cube is a box, so it
/// also holds the point's projection onto the node), and are tested against all of them.
pub struct Lookup {
    locator: NodeLocator,
    top: Node,
    depth: u32,
    /// The node's cube: a point outside it is outside its cell too.
    node: Bounds,
    /// Per cell: [`Lookup::SOLE`] and the target when one target's grown cube holds the whole
    /// cell and no other meets it (most cells: their points need no second load), else where
    /// the cell's list starts in `lists`.
    cells: Vec<u32>,
    /// Each listed cell's number of targets, then its targets, those that hold the whole cell
    /// first, marked with [`Lookup::HOLDS_CELL`].
    lists: Vec<u32>,
}

impl Lookup {
    /// The bit of a target in [`Lookup::lists`] whose grown cube holds the whole cell.
    const HOLDS_CELL: u32 = 1 << 31;

    /// The bit of an entry of [`Lookup::cells`] that is the cell's sole target.
    const SOLE: u32 = 1 << 31;

    /// The lookup of `grown` boxes over `top`, `depth` levels fine.
    pub fn new(root: &Root, top: Node, depth: u32, grown: &[Bounds]) -> Lookup {
        let n = 1usize << depth;
        let cell_side = root.side(top.level + depth);
        let origin = root.core(top).min;
        let range = |b: &Bounds, a: usize| {
            let lo = ((b.min[a] - origin[a]) / cell_side).floor().max(0.0) as usize;
            let hi = (((b.max[a] - origin[a]) / cell_side).ceil().max(0.0) as usize).min(n);
            (lo.min(n), hi)
        };
        let mut offsets = vec![0u32; n * n * n + 1];
        let each_cell = |b: &Bounds, f: &mut dyn FnMut(usize, [usize; 3])| {
            let (x0, x1) = range(b, 0);
            let (y0, y1) = range(b, 1);
            let (z0, z1) = range(b, 2);
            for z in z0..z1 {
                for y in y0..y1 {
                    for x in x0..x1 {
                        f(x + n * (y + n * z), [x, y, z]);
                    }
                }
            }
        };
        for b in grown {
            each_cell(b, &mut |cell, _| {
                if let Some(o) = offsets.get_mut(cell + 1) {
                    *o += 1;
                }
            });
        }
        for i in 1..offsets.len() {
            let before = offsets.get(i - 1).copied().unwrap_or(0);
            if let Some(o) = offsets.get_mut(i) {
                *o += before;
            }
        }
        let mut targets = vec![0u32; offsets.last().copied().unwrap_or(0) as usize];
        let mut fill = offsets.clone();
        // The cells' corners are exact: the origin and the side are multiples of the root's
        // grid unit (a power of two), and so are their sums.
        let cell = |xyz: [usize; 3]| {
            let min = [0, 1, 2].map(|a| origin[a] + xyz[a] as f64 * cell_side);
            Bounds {
                min,
                max: min.map(|m| m + cell_side),
            }
        };
        for (t, b) in grown.iter().enumerate() {
            each_cell(b, &mut |index, xyz| {
                let c = cell(xyz);
                let holds = (0..3).all(|a| b.min[a] <= c.min[a] && c.max[a] <= b.max[a]);
                if let Some(at) = fill.get_mut(index) {
                    if let Some(slot) = targets.get_mut(*at as usize) {
                        *slot = if holds { t as u32 | Self::HOLDS_CELL } else { t as u32 };
                    }
                    *at += 1;
                }
            });
        }
        // Those that hold the cell first, each part in target order.
        for w in offsets.windows(2) {
            if let [from, to] = *w
                && let Some(cell_targets) = targets.get_mut(from as usize..to as usize)
            {
                cell_targets.sort_unstable_by_key(|&t| (t & Self::HOLDS_CELL == 0, t));
            }
        }
        let mut cells = Vec::with_capacity(n * n * n);
        let mut lists = Vec::new();
        for w in offsets.windows(2) {
            let cell_targets = match *w {
                [from, to] => targets.get(from as usize..to as usize).unwrap_or_default(),
                _ => &[],
            };
            match *cell_targets {
                [sole] if sole & Self::HOLDS_CELL != 0 => cells.push(Self::SOLE | (sole & !Self::HOLDS_CELL)),
                _ => {
                    cells.push(lists.len() as u32);
                    lists.push(cell_targets.len() as u32);
                    lists.extend_from_slice(cell_targets);
                }
            }
        }
        Lookup {
            locator: root.locator(top.level + depth),
            top,
            depth,
            node: root.core(top),
            cells,
            lists,
        }
    }

    /// Bytes it takes.
    pub fn bytes(&self) -> u64 {
        ((self.cells.len() + self.lists.len()) * std::mem::size_of::<u32>()) as u64
    }

    /// Calls `hit` with every target, in increasing order of the cell's list (those that hold
    /// the cell, then the others), whose grown cube (`grown`, as given to [`Lookup::new`])
    /// holds the point `p` of grid coordinates `g`.
    #[inline]
    pub fn place_grid(&self, g: [u32; 3], p: [f64; 3], grown: &[Bounds], hit: impl FnMut(u32)) {
        let index = Node::holding(g, self.top.level + self.depth).index;
        // The grid coordinates' node and the float point's can differ on a face: the node's
        // cube decides.
        self.place_entry(self.cell_entry(index).0, p, self.node.contains(p), grown, hit);
    }

    /// [`Lookup::place_grid`] for a point whose grid coordinates are not known.
    #[inline]
    pub fn place(&self, p: [f64; 3], grown: &[Bounds], hit: impl FnMut(u32)) {
        let (entry, in_node) = self.locate(p);
        self.place_entry(entry, p, in_node, grown, hit);
    }

    /// [`Lookup::place`] for a run of points: `hit` gets each point's index in `positions`
    /// and a target. The same targets in the same order as [`Lookup::place`] gives.
    #[inline]
    pub fn place_run(&self, positions: &[[f64; 3]], grown: &[Bounds], mut hit: impl FnMut(usize, u32)) {
        // Points in random order miss the cache on every cell: the entries of a whole chunk's
        // cells are loaded first, with no load waiting on another, so the misses overlap.
        const CHUNK: usize = 64;
        let mut entries = [0u32; CHUNK];
        let mut inside = [false; CHUNK];
        for (chunk_index, chunk) in positions.chunks(CHUNK).enumerate() {
            for ((entry, in_node), &p) in entries.iter_mut().zip(&mut inside).zip(chunk) {
                (*entry, *in_node) = self.locate(p);
            }
            for (i, ((&p, &entry), &in_node)) in chunk.iter().zip(&entries).zip(&inside).enumerate() {
                let at = chunk_index * CHUNK + i;
                self.place_entry(entry, p, in_node, grown, |target| hit(at, target));
            }
        }
    }

    /// The [`Lookup::cells`] entry of the cell that holds the node `index` at the lookup's
    /// level (or is nearest to it), and whether the index lies inside the lookup's node.
    #[inline]
    fn cell_entry(&self, index: [u32; 3]) -> (u32, bool) {
        let n = 1u32 << self.depth;
        let base = self.top.index.map(|c| c << self.depth);
        // Clamped to the node: below it wraps to a huge value, so compare signed.
        let offset = [0, 1, 2].map(|a| i64::from(index[a]) - i64::from(base[a]));
        let inside = offset.iter().all(|&o| (0..i64::from(n)).contains(&o));
        let relative = offset.map(|o| o.clamp(0, i64::from(n) - 1) as usize);
        let n = n as usize;
        let cell = relative[0] + n * (relative[1] + n * relative[2]);
        // An empty list for a cell that is not there (never, for a clamped index).
        (self.cells.get(cell).copied().unwrap_or(!Self::SOLE), inside)
    }

    /// The [`Lookup::cells`] entry for `p`, and whether `p` lies inside the lookup's node.
    #[inline(always)]
    fn locate(&self, p: [f64; 3]) -> (u32, bool) {
        // A point clear of its node's faces lies inside the lookup's node when its index
        // does: no test of the node's cube for nearly every point (a tenth of the write
        // pass). The others get the test.
        match self.locator.clear_index(p) {
            Some(index) => self.cell_entry(index),
            None => (self.cell_entry(self.locator.exact(p)).0, self.node.contains(p)),
        }
    }

    /// Calls `hit` with the targets of the cell of `entry` that hold `p`; `in_cell`: whether
    /// `p` lies inside the lookup's node, and so inside the cell of `entry`. (Points outside
    /// the node were looked up in the nearest cell, which does not hold them.)
    #[inline]
    fn place_entry(&self, entry: u32, p: [f64; 3], in_cell: bool, grown: &[Bounds], mut hit: impl FnMut(u32)) {
        if entry & Self::SOLE != 0 {
            let target = entry & !Self::SOLE;
            if in_cell || grown.get(target as usize).is_some_and(|b| b.contains(p)) {
                hit(target);
            }
            return;
        }
        let start = entry as usize;
        let count = self.lists.get(start).copied().unwrap_or(0) as usize;
        let candidates = self.lists.get(start + 1..start + 1 + count).unwrap_or_default();
        for &candidate in candidates {
            let target = candidate & !Self::HOLDS_CELL;
            if (in_cell && candidate & Self::HOLDS_CELL != 0)
                || grown.get(target as usize).is_some_and(|b| b.contains(p))
            {
                hit(target);
            }
        }
    }
}

#[cfg(test)]
mod tests;
