//! The coarse-to-fine TGV solve (paper 4.5): one stage per level l, `solution-LL`, whose units
//! are the treetop units. The level cut is every cube at depth l plus every octree leaf above
//! it; it tiles the root because the octree is complete. Inside a unit all cut cubes (set A) are
//! free; their face neighbours in other units (set B) are frozen to the values of the cube that
//! covered them at level l - 1 (their parent, or themselves if they are coarser leaves). Each
//! cube starts from the same previous-level values.
//!
//! Every level is a version, so `solve --resume` continues at the level and unit where it
//! stopped, and each level's segments (key, u, v, p, q; the finest without p and q: `level_segment`) remain
//! readable.

use std::collections::BTreeMap;
use std::sync::Arc;

use redb::WriteTransaction;
use serde::{Deserialize, Serialize};

use super::HISTOGRAMS;
use super::observed::{measured_weight, sampled_of, seen_weight, surface_offset};
use super::treetop::{Treetop, TreetopUnit, UnitKeys, children_on_min_face};
use crate::format::Scene;
use crate::format::key::{find_sorted_from, last_at_or_below_from};
use crate::format::{CubeKey, MAX_DEPTH};
use crate::kernels::tgv::{Problem, State};
use crate::kernels::votes::BINS;
use crate::store::StageError;
use crate::store::catalog::{self, UnitRecord};
use crate::store::{Plan, Replace, Result, Snapshot, Stage, StoreError, UnitOutput, UnitSpec};

mod coarse;
mod cut;
mod level_segment;
mod params;
mod plus_faces;
mod ssd;

use plus_faces::PlusNeighbours;

pub use coarse::{COARSE_ROWS_LEVEL, CoarseRowsCache};

pub use ssd::{CoarseSamplesCache, METHOD_COLUMN, PendingCoarseSamples, method_of_segment};

use cut::WindowTest;
pub use cut::{CutValue, LeafValues, LevelCut, read_level_u};
pub use level_segment::{Kept, LevelSegments, LevelValues, read_level_values};
use level_segment::{ObservedColumns, columns_of, read_level_values_where};

pub use params::{DEFAULT_SSD_TOLERANCE, DEFAULT_TOLERANCE, Method, MethodChoice, SolveParams, SsdParams};

/// Stage names of the levels.
pub const LEVEL_STAGES: [&str; MAX_DEPTH as usize + 1] = [
    "solution-00",
    "solution-01",
    "solution-02",
    "solution-03",
    "solution-04",
    "solution-05",
    "solution-06",
    "solution-07",
    "solution-08",
    "solution-09",
    "solution-10",
    "solution-11",
    "solution-12",
    "solution-13",
    "solution-14",
    "solution-15",
    "solution-16",
    "solution-17",
    "solution-18",
    "solution-19",
    "solution-20",
    "solution-21",
    "solution-22",
    "solution-23",
    "solution-24",
    "solution-25",
    "solution-26",
    "solution-27",
    "solution-28",
    "solution-29",
    "solution-30",
    "solution-31",
    "solution-32",
];

/// A unit is small, and batched with its neighbours, when it has at most 1 / this of the cubes
/// a level group may hold.
pub const SMALL_UNIT_FRACTION: u64 = 8;

/// Previous-level (u, v, p, q) of one cube.
type Inherited = (f32, [f32; 3], [f32; 3], [f32; 6]);

/// Lazily loaded keys and previous-level values of the units a worker touches.
struct Neighbourhood<'a, 's> {
    base: &'a Snapshot<'s>,
    treetop: &'a Treetop,
    level: u8,
    previous_level: Option<LevelSegments>,
    /// At the coarse levels, where the units' nodes come from.
    coarse: Option<&'a CoarseRowsCache>,
    keys: BTreeMap<usize, Arc<LevelKeys>>,
    /// Per unit, where its last [`Neighbourhood::node`] lookup ended: the cut asks about cubes
    /// in ascending order, mostly a few keys past the last one.
    key_cursors: BTreeMap<usize, usize>,
    /// Previous-level values by group id, with where the last lookup in them ended (the cut's
    /// sources ascend likewise).
    values: BTreeMap<u64, (LevelValues, usize)>,
    /// The cubes whose previous-level values or octree nodes are asked for (the units' own
    /// and those across their faces, and their ancestors) all meet this box: the blocks of a
    /// neighbour's segment behind the shared face are not decoded.
    window: WindowTest,
    /// The units being solved, whose keys are read whole (their rows index the histograms).
    members: &'a [usize],
}

/// A unit's octree keys down to the level being solved, with their rows in the unit's segment.
/// Every question a level asks concerns cubes of depth at most the level, and the octree is
/// complete, so the leaf test still holds on the shortened list (an internal node's next key is
/// its first child); a group of many small leaves then holds only its cut, not its octree.
struct LevelKeys {
    keys: UnitKeys,
    rows: Vec<u32>,
    /// Rows of the unit's whole segment.
    total: usize,
}

impl Neighbourhood<'_, '_> {
    fn unit_keys(&mut self, unit: usize) -> Result<Arc<LevelKeys>> {
        if let Some(k) = self.keys.get(&unit) {
            return Ok(k.clone());
        }
        let info = self.treetop.units.get(unit).ok_or_else(|| StoreError::Stage {
            stage: "solution".into(),
            unit: format!("unit {unit}"),
            error: Box::new(StageError::internal("no such treetop unit")),
        })?;
        if let Some(cache) = self.coarse
            && let Some(coarse) = cache.unit(self.base, self.treetop, unit)?
        {
            let (keys, rows): (Vec<CubeKey>, Vec<u32>) = coarse
                .keys
                .iter()
                .zip(&coarse.rows)
                .filter(|(key, _)| key.depth() <= self.level)
                .map(|(key, row)| (*key, *row))
                .unzip();
            let loaded = Arc::new(LevelKeys {
                keys: UnitKeys { keys, top: info.top },
                rows,
                total: coarse.total,
            });
            self.keys.insert(unit, loaded.clone());
            return Ok(loaded);
        }
        let file = self.base.open_segment(&info.segment)?;
        let whole = file.reader()?;
        // A neighbour is asked only about cubes that touch the units (and their ancestors),
        // whose leaf test holds on the blocks that may hold such cubes: an internal node that
        // meets the window has a descendant that does, in a kept block, and every key between
        // them is its descendant. Its rows are then not the segment's, and never read.
        let reader = if self.members.contains(&unit) {
            whole
        } else {
            whole.with_blocks_where(|first, last| self.window.may_meet_keys_between(first, last))
        };
        let all = reader.read_keys().map_err(|e| file.corruption(e))?;
        let total = all.len();
        let (keys, rows): (Vec<CubeKey>, Vec<u32>) = all
            .into_iter()
            .zip(0u32..)
            .filter(|(key, _)| key.depth() <= self.level)
            .unzip();
        let loaded = Arc::new(LevelKeys {
            keys: UnitKeys { keys, top: info.top },
            rows,
            total,
        });
        self.keys.insert(unit, loaded.clone());
        Ok(loaded)
    }

    /// Whether `key` exists, and if so whether it is an octree leaf.
    fn node(&mut self, key: CubeKey) -> Result<Option<bool>> {
        let unit = self.treetop.unit_of(key);
        if !self.keys.contains_key(&unit) {
            self.unit_keys(unit)?;
        }
        // Borrowed, not cloned (an atomic count up and down per lookup), and searched from the
        // last lookup's end (a bisection of the whole unit missed the cache at every step).
        let Some(keys) = self.keys.get(&unit) else {
            return Ok(None);
        };
        let cursor = self.key_cursors.entry(unit).or_default();
        let found = last_at_or_below_from(&keys.keys.keys, *cursor, key);
        *cursor = found.unwrap_or(0);
        Ok(found
            .filter(|&i| keys.keys.keys.get(i) == Some(&key))
            .map(|i| keys.keys.is_leaf(i)))
    }

    fn previous(&mut self, key: CubeKey) -> Result<Option<Inherited>> {
        let Some(segments) = &self.previous_level else {
            return Ok(None);
        };
        let Some((group, name)) = segments.group_of(self.treetop.unit_of(key)) else {
            return Ok(None);
        };
        if !self.values.contains_key(&group) {
            let loaded = read_level_values_where(self.base, name, Some(&self.window))?;
            self.values.insert(group, (loaded, 0));
        }
        // Searched from where the last lookup in this group ended: the cut asks in ascending order.
        let Some((values, cursor)) = self.values.get_mut(&group) else {
            return Ok(None);
        };
        let found = last_at_or_below_from(&values.keys, *cursor, key);
        *cursor = found.unwrap_or(0);
        Ok(found
            .filter(|&i| values.keys.get(i) == Some(&key))
            .map(|i| (values.u[i], values.v[i], values.p[i], values.q[i])))
    }
}

pub struct LevelStage {
    pub level: u8,
    pub scene: Scene,
    pub params: SolveParams,
    treetop: std::sync::OnceLock<Treetop>,
    /// Treetop units solved together, by group id (the first member's index).
    groups: std::sync::OnceLock<BTreeMap<u64, Vec<usize>>>,
    /// What the level's segments keep: set by planning, from the octree's maximum depth (in
    /// the level's inputs, so a deeper octree solves this level again, with its duals).
    kept: std::sync::OnceLock<Kept>,
    /// Where the iterations run; `None` is the CPU kernel.
    gpu: Option<std::sync::Arc<crate::gpu::Gpu>>,
    method: Method,
    /// SSD: the units' samples summed for the coarse levels, shared by the levels of a solve.
    coarse_samples: ssd::CoarseSamplesCache,
    /// The units' nodes, histograms and `sampled` flags for the coarse levels, shared likewise;
    /// `None` reads them from the segments at every level.
    coarse_rows: Option<CoarseRowsCache>,
}

#[derive(Serialize, Deserialize, Default, Clone, Copy)]
struct LevelUnitExtra {
    cubes: u64,
    energy_before: f64,
    energy_after: f64,
    /// Iterations the unit ran (all its members together).
    iterations: u64,
}

impl LevelStage {
    pub fn new(level: u8, scene: Scene, params: SolveParams) -> LevelStage {
        LevelStage {
            level,
            scene,
            params,
            treetop: std::sync::OnceLock::new(),
            groups: std::sync::OnceLock::new(),
            kept: std::sync::OnceLock::new(),
            gpu: None,
            method: Method::Tgv,
            coarse_samples: ssd::CoarseSamplesCache::default(),
            coarse_rows: Some(CoarseRowsCache::default()),
        }
    }

    /// Shares the cache of the units' coarse nodes with the other levels of a solve (`None`:
    /// no cache, the same result).
    pub fn with_coarse_rows(mut self, cache: Option<CoarseRowsCache>) -> LevelStage {
        self.coarse_rows = cache;
        self
    }

    /// The cache the level reads its units through, at the coarse levels.
    fn coarse_rows(&self) -> Option<&CoarseRowsCache> {
        self.coarse_rows.as_ref().filter(|_| self.level <= COARSE_ROWS_LEVEL)
    }

    /// Whether samples reached each cut cube of `keys` (`stages::observed::sampled_of`).
    fn sampled(&self, base: &Snapshot<'_>, treetop: &Treetop, keys: &[CubeKey]) -> Result<Vec<bool>> {
        match self.coarse_rows() {
            Some(cache) => cache.sampled(base, treetop, keys),
            None => sampled_of(base, treetop, keys),
        }
    }

    /// Minimises `method`'s energy rather than TGV's.
    pub fn with_method(mut self, method: Method) -> LevelStage {
        self.method = method;
        self
    }

    /// Shares SSD's cache of the units' coarse sample sums with the other levels of a solve.
    pub fn with_coarse_samples(mut self, cache: ssd::CoarseSamplesCache) -> LevelStage {
        self.coarse_samples = cache;
        self
    }

    /// Runs the iterations on `gpu` (falling back to the CPU per unit on a GPU failure).
    pub fn with_gpu(mut self, gpu: Option<std::sync::Arc<crate::gpu::Gpu>>) -> LevelStage {
        self.gpu = gpu;
        self
    }

    /// Batches consecutive small treetop units into groups of at most `cap` cut cubes, counting each
    /// unit at its bound: no more cubes than it has, and no more than 8^(level - depth) for a
    /// leaf at `depth` (the cut tiles the leaf's cube with cubes of depth at most `level`). The
    /// grouping depends only on the octree, so every process (and a cluster's workers) derives
    /// the same one. Units whose leaf lies below the level have no cut cubes and are left out.
    pub fn groups(treetop: &Treetop, level: u8) -> Vec<Vec<usize>> {
        let cap = treetop.units.iter().map(|u| u.record.rows).max().unwrap_or(0).max(64);
        let mut groups: Vec<Vec<usize>> = Vec::new();
        let mut load = 0u64;
        // Whether the last group is one of small units that may take more.
        let mut open = false;
        for (index, unit) in treetop.units.iter().enumerate() {
            let Some(cubes) = cut_bound(unit, level) else {
                continue;
            };
            // Only small units are batched; a unit with more than an eighth of the cap solves
            // alone. A group also reads its neighbours' previous-level values, so fine levels
            // (where most units are large) keep the memory of one unit per worker.
            let small = cubes.saturating_mul(SMALL_UNIT_FRACTION) <= cap;
            match groups.last_mut() {
                Some(group) if small && open && load.saturating_add(cubes) <= cap => {
                    group.push(index);
                    load += cubes;
                }
                _ => {
                    groups.push(vec![index]);
                    load = cubes;
                    open = small;
                }
            }
        }
        groups
    }

    /// The cut cubes of a group of treetop units, each counted at its bound ([`cut_bound`]).
    fn group_cubes(treetop: &Treetop, members: &[usize], level: u8) -> u64 {
        members
            .iter()
            .filter_map(|&i| treetop.units.get(i))
            .filter_map(|unit| cut_bound(unit, level))
            .fold(0, u64::saturating_add)
    }

    /// What the level's segments keep ([`Kept`]), once planned.
    fn kept(&self, unit: &UnitSpec) -> Result<Kept> {
        self.kept
            .get()
            .copied()
            .ok_or_else(|| self.stage_error(unit, StageError::internal("units run before planning")))
    }

    fn previous_stage(&self) -> Option<&'static str> {
        (self.level > 0).then(|| LEVEL_STAGES[usize::from(self.level - 1)])
    }

    /// The key whose previous-level values a cut cube inherits.
    fn source_key(&self, key: CubeKey) -> CubeKey {
        if key.depth() == self.level {
            key.parent().unwrap_or(key)
        } else {
            key
        }
    }

    fn stage_error(&self, unit: &UnitSpec, error: StageError) -> StoreError {
        StoreError::Stage {
            stage: LEVEL_STAGES[usize::from(self.level)].into(),
            unit: unit.label.clone(),
            error: Box::new(error),
        }
    }

    /// Builds the unit's TGV problem and initial state; `None` when the unit has no cut cubes.
    pub fn build_problem(&self, base: &Snapshot<'_>, unit_index: usize) -> Result<Option<UnitProblem>> {
        let Some(cut) = self.build_cut(base, unit_index)? else {
            return Ok(None);
        };
        let side = |k: CubeKey| k.side() as f32;
        let n = cut.keys.len();
        let mut state = State::zeros(n);
        for (c, previous) in cut.previous.iter().enumerate() {
            if let Some((u, v, p, q)) = previous {
                state.u[c] = *u;
                state.v[c] = *v;
                state.p[c] = *p;
                state.q[c] = *q;
            }
        }
        let (frozen_u, frozen_v) = cut
            .frozen
            .iter()
            .map(|(_, previous)| previous.map_or((0.0, [0.0; 3]), |(u, v, _, _)| (u, v)))
            .unzip();
        let problem = Problem {
            n,
            start: cut.start,
            terms: cut.terms,
            frozen_u,
            frozen_v,
            hist: cut.hist,
            alpha1: cut.keys.iter().map(|k| self.params.alpha1 * side(*k)).collect(),
            alpha0: cut
                .keys
                .iter()
                .map(|k| self.params.alpha0 * side(*k) * side(*k))
                .collect(),
            lambda: self.params.lambda,
        };
        Ok(Some((cut.keys, problem, state, cut.offset)))
    }

    // long function build_cut: one pass that gathers a unit's cubes, their frozen neighbours and the difference terms, in the order the kernel's gather lists need.
    /// Gathers the unit's level cut; `None` when the unit has no cut cubes.
    fn build_cut(&self, base: &Snapshot<'_>, unit_index: usize) -> Result<Option<UnitCut>> {
        let treetop = self.treetop.get().ok_or_else(|| StoreError::Stage {
            stage: LEVEL_STAGES[usize::from(self.level)].into(),
            unit: format!("unit {unit_index}"),
            error: Box::new(StageError::internal("units run before planning")),
        })?;
        let level = self.level;
        let members = self
            .groups
            .get()
            .and_then(|groups| groups.get(&(unit_index as u64)))
            .cloned()
            .unwrap_or_else(|| vec![unit_index]);
        let mut hood = Neighbourhood {
            base,
            treetop,
            level,
            previous_level: self.previous_stage().map(|stage| LevelSegments::of(base, stage)),
            coarse: self.coarse_rows(),
            keys: BTreeMap::new(),
            key_cursors: BTreeMap::new(),
            values: BTreeMap::new(),
            window: WindowTest::around_units(treetop, &members),
            members: &members,
        };
        let histogram_segments: BTreeMap<u128, String> = base
            .segments(HISTOGRAMS)
            .iter()
            .map(|(name, record)| (record.first_key, name.clone()))
            .collect();
        // The cut cubes of every member with their histograms, then sorted by key (the internal
        // unit's cubes interleave with the leaves').
        let mut cut: Vec<(CubeKey, [f32; BINS], [f32; 2])> = Vec::new();
        for &member in &members {
            let own = hood.unit_keys(member)?;
            let rows: Vec<usize> = (0..own.keys.keys.len())
                .filter(|&i| {
                    let d = own.keys.keys[i].depth();
                    d == level || (d < level && own.keys.is_leaf(i))
                })
                .collect();
            if rows.is_empty() {
                continue;
            }
            let first_key = treetop.units.get(member).map(|u| u.record.first_key);
            let name = first_key
                .and_then(|k| histogram_segments.get(&k))
                .ok_or_else(|| StoreError::Stage {
                    stage: LEVEL_STAGES[usize::from(level)].into(),
                    unit: format!("unit {member}"),
                    error: Box::new(StageError::NoHistograms),
                })?;
            if let Some(cache) = self.coarse_rows()
                && let Some(coarse) = cache.unit(base, treetop, member)?
            {
                let histograms = cache.histograms(base, name, &coarse)?;
                cut.extend(rows.iter().map(|&i| {
                    let row = own.rows.get(i).copied().unwrap_or(u32::MAX);
                    let (hist, distance) = histograms.at(&coarse, row);
                    (own.keys.keys[i], hist, distance)
                }));
                continue;
            }
            let (h, distance) = read_histograms(base, name, own.total)?;
            cut.extend(rows.iter().map(|&i| {
                let row = own.rows.get(i).map_or(usize::MAX, |r| *r as usize);
                (
                    own.keys.keys[i],
                    std::array::from_fn(|b| h.get(row.saturating_mul(BINS) + b).copied().unwrap_or(0.0)),
                    std::array::from_fn(|k| distance.get(row.saturating_mul(2) + k).copied().unwrap_or(0.0)),
                )
            }));
        }
        if cut.is_empty() {
            return Ok(None);
        }
        cut.sort_by_key(|(key, _, _)| *key);
        let mut keys = Vec::with_capacity(cut.len());
        let mut hist = Vec::with_capacity(cut.len());
        let mut offset = Vec::with_capacity(cut.len());
        for (key, row, distance) in cut {
            keys.push(key);
            offset.push(surface_offset(distance));
            hist.push(row);
        }
        let n = keys.len();
        // Up to two lookups per cube and axis. A `+` neighbour (or the leaf holding it) sorts
        // after its cube, mostly a few keys on, so each search starts at the cube's own index:
        // a hash table of the keys missed the cache twice a lookup (half of this function in
        // `perf`), and a binary search over the whole cut was most of this loop before that.
        let index_of = |from: usize, k: CubeKey| find_sorted_from(&keys, from, k).map(|i| i as u32);

        // Lengths in units of the root side: the discrete problem, and so every iterate, is then
        // the same for a scaled or translated scene.
        let side = |k: CubeKey| k.side() as f32;
        let mut frozen: BTreeMap<CubeKey, u32> = BTreeMap::new();
        let mut frozen_cubes: Vec<(CubeKey, Option<Inherited>)> = Vec::new();
        let mut start = Vec::with_capacity(3 * n + 1);
        start.push(0u32);
        let mut terms: Vec<(u32, f32)> = Vec::with_capacity(3 * n);
        for (at, &key) in keys.iter().enumerate() {
            for axis in 0..3 {
                let neighbours = match key.plus_neighbour(axis) {
                    None => PlusNeighbours::default(),
                    // A neighbour in the unit's own cut is a cut cube: no need to ask the octree.
                    Some(n0) => match index_of(at, n0) {
                        Some(i) => PlusNeighbours::one(n0, Some(i)),
                        None => match hood.node(n0)? {
                            Some(leaf) if leaf || n0.depth() == level => PlusNeighbours::one(n0, None),
                            Some(_) => PlusNeighbours::four(children_on_min_face(n0, axis)),
                            None => {
                                let mut found = PlusNeighbours::default();
                                let mut up = n0.parent();
                                while let Some(a) = up {
                                    if hood.node(a)?.is_some() {
                                        found = PlusNeighbours::one(a, None);
                                        break;
                                    }
                                    up = a.parent();
                                }
                                found
                            }
                        },
                    },
                };
                let count = neighbours.len() as f32;
                for (neighbour, known) in neighbours.iter() {
                    let w = 1.0 / (count * 0.5 * (side(key) + side(neighbour)));
                    let target = match known.or_else(|| index_of(at, neighbour)) {
                        Some(i) => i,
                        None => {
                            let slot = match frozen.get(&neighbour) {
                                Some(s) => *s,
                                None => {
                                    let s = frozen_cubes.len() as u32;
                                    frozen_cubes.push((neighbour, hood.previous(self.source_key(neighbour))?));
                                    frozen.insert(neighbour, s);
                                    s
                                }
                            };
                            n as u32 + slot
                        }
                    };
                    terms.push((target, w));
                }
                start.push(terms.len() as u32);
            }
        }
        // Sibling cubes at the level share their source, and come one after another.
        let mut last: Option<(CubeKey, Option<Inherited>)> = None;
        let previous = keys
            .iter()
            .map(|key| {
                let source = self.source_key(*key);
                if let Some((known, values)) = last
                    && known == source
                {
                    return Ok(values);
                }
                let values = hood.previous(source)?;
                last = Some((source, values));
                Ok(values)
            })
            .collect::<Result<_>>()?;
        Ok(Some(UnitCut {
            keys,
            members,
            hist,
            offset,
            start,
            terms,
            frozen: frozen_cubes,
            previous,
        }))
    }
}

/// A histogram segment's `hist` and `distance` values, checked against its octree unit's
/// `rows`.
/// A treetop unit's cut cubes at `level`, at most: no more cubes than it has, and no more than
/// 8^(level - depth) for a leaf at `depth` (the cut tiles the leaf's cube with cubes of depth at
/// most `level`). None when the leaf lies below the level (the unit has no cut cubes).
fn cut_bound(unit: &TreetopUnit, level: u8) -> Option<u64> {
    let depth = CubeKey::from_raw(unit.record.first_key).depth();
    let below = u32::from(level.checked_sub(depth)?);
    let bound = if below >= 21 { u64::MAX } else { 8u64.pow(below) };
    Some(bound.min(unit.record.rows))
}

fn read_histograms(base: &Snapshot<'_>, segment: &str, rows: usize) -> Result<(Vec<f32>, Vec<f32>)> {
    let file = base.open_segment(segment)?;
    let reader = file.reader()?;
    let (_, h) = reader.read_f32("hist").map_err(|e| file.corruption(e))?;
    // Histograms written before the distance column existed measured no distances.
    let distance = if reader.column("distance").is_ok() {
        reader.read_f32("distance").map_err(|e| file.corruption(e))?.1
    } else {
        vec![0.0; 2 * rows]
    };
    if h.len() != rows * BINS || distance.len() != 2 * rows {
        return Err(file.corruption(crate::format::DecodeError::MissingColumn(
            "hist and distance rows matching the octree unit".into(),
        )));
    }
    Ok((h, distance))
}

impl Stage for LevelStage {
    fn name(&self) -> &'static str {
        LEVEL_STAGES[usize::from(self.level)]
    }

    fn params(&self) -> Vec<u8> {
        // TGV's bytes are those of the builds before SSD existed, so their levels stay current.
        match self.method {
            Method::Tgv => catalog::encode(&(self.params, self.scene)),
            Method::Ssd(ssd) => catalog::encode(&(self.params, self.scene, ssd)),
            Method::Hybrid(ssd) => catalog::encode(&(self.params, self.scene, ssd, "hybrid")),
        }
    }

    fn input_digest(&self, base: &Snapshot<'_>) -> Vec<u8> {
        let mut digest = base.digest(HISTOGRAMS).to_le_bytes().to_vec();
        digest.extend_from_slice(&base.digest(super::OCTREE).to_le_bytes());
        if self.method.ssd().is_some() {
            digest.extend_from_slice(&base.digest(super::samples::SAMPLES).to_le_bytes());
        }
        if let Some(previous) = self.previous_stage() {
            digest.extend_from_slice(&base.digest(previous).to_le_bytes());
        }
        digest
    }

    fn plan(&self, base: &Snapshot<'_>) -> Result<Plan> {
        let treetop = Treetop::of(base)?;
        let groups = Self::groups(&treetop, self.level);
        let units = groups
            .iter()
            .filter_map(|members| {
                let (first, last) = (*members.first()?, *members.last()?);
                let key = |i: usize| treetop.units.get(i).map(|u| u.key);
                Some(UnitSpec {
                    id: first as u64,
                    label: if members.len() == 1 {
                        format!("level {} leaf {:?}", self.level, key(first)?)
                    } else {
                        format!(
                            "level {} leaves {:?} to {:?} ({} units)",
                            self.level,
                            key(first)?,
                            key(last)?,
                            members.len()
                        )
                    },
                    cubes: Self::group_cubes(&treetop, members, self.level),
                })
            })
            .collect();
        let by_id = groups
            .into_iter()
            .filter_map(|members| Some((*members.first()? as u64, members)))
            .collect();
        let finest = crate::stages::octree_max_depth(base.store())?;
        let _ = self.treetop.set(treetop);
        let _ = self.groups.set(by_id);
        let _ = self.kept.set(if self.level >= finest {
            Kept::Solution
        } else {
            Kept::WithDuals
        });
        Ok(Plan {
            units,
            replace: Replace::All,
        })
    }

    fn run_unit(&self, base: &Snapshot<'_>, unit: &UnitSpec) -> Result<UnitOutput> {
        if let Some(params) = self.method.ssd() {
            return self.run_ssd_unit(base, unit, params);
        }
        let Some((keys, problem, mut state, offset)) = self.build_problem(base, unit.id as usize)? else {
            return Ok(UnitOutput {
                extra: catalog::encode(&LevelUnitExtra::default()),
                ..UnitOutput::default()
            });
        };
        if problem.start.len() != 3 * problem.n + 1 {
            return Err(self.stage_error(unit, StageError::internal("malformed neighbour lists")));
        }
        let solved = crate::gpu::solve_on(self.gpu.as_deref(), &problem, &mut state, self.params.stopping());
        let seen = problem.hist.iter().map(seen_weight).collect();
        let measured = problem.hist.iter().map(measured_weight).collect();
        let treetop = self
            .treetop
            .get()
            .ok_or_else(|| self.stage_error(unit, StageError::internal("units run before planning")))?;
        let sampled = self.sampled(base, treetop, &keys)?.into_iter().map(u32::from).collect();
        let values = LevelValues {
            keys,
            u: state.u,
            v: state.v,
            p: state.p,
            q: state.q,
        };
        Ok(UnitOutput {
            segments: vec![
                columns_of(
                    &values,
                    ObservedColumns {
                        seen,
                        sampled,
                        offset,
                        measured,
                    },
                    self.kept(unit)?,
                )
                .into(),
            ],
            extra: catalog::encode(&LevelUnitExtra {
                cubes: values.keys.len() as u64,
                energy_before: solved.energy_before,
                energy_after: solved.energy_after,
                iterations: solved.iterations as u64,
            }),
            block_rows: super::FACE_READ_BLOCK_ROWS,
        })
    }

    fn finish(&self, _txn: &WriteTransaction, _base: &Snapshot<'_>, units: &[(u64, UnitRecord)]) -> Result<String> {
        let mut total = LevelUnitExtra::default();
        let (mut fewest, mut most, mut cube_iterations) = (u64::MAX, 0u64, 0u128);
        for (_, record) in units {
            let e: LevelUnitExtra = catalog::decode("units_done", &record.extra)?;
            total.cubes += e.cubes;
            total.energy_before += e.energy_before;
            total.energy_after += e.energy_after;
            if e.cubes > 0 {
                fewest = fewest.min(e.iterations);
                most = most.max(e.iterations);
                cube_iterations += u128::from(e.cubes) * u128::from(e.iterations);
            }
        }
        let mean = cube_iterations as f64 / total.cubes.max(1) as f64;
        let iterations = if fewest >= most {
            format!("{mean:.0} iterations per cube")
        } else {
            format!("{mean:.0} iterations per cube, {fewest} to {most} per unit")
        };
        let settings = match self.method {
            Method::Tgv => format!(
                "at most {}, tolerance {}; alpha1 {}, alpha0 {}, lambda {}",
                self.params.iterations,
                self.params.tolerance,
                self.params.alpha1,
                self.params.alpha0,
                self.params.lambda
            ),
            Method::Ssd(ssd) | Method::Hybrid(ssd) => format!(
                "{}, at most {}, residual {}; lambda1 {} (up to {} in noisy units), lambda2 {} (up to {} in noisy units)",
                self.method.name(),
                ssd.iterations,
                ssd.tolerance,
                ssd.normal_weight,
                ssd::noise_normal_weight(ssd.normal_weight, f64::INFINITY),
                ssd.smoothness,
                ssd::noise_smoothness(ssd.smoothness, Some(f64::INFINITY))
            ),
        };
        let line = format!(
            "level {}: {} cubes, energy {:.6e} -> {:.6e} ({iterations}, {settings})",
            self.level, total.cubes, total.energy_before, total.energy_after,
        );
        tracing::info!("{line}");
        Ok(line)
    }
}

/// A unit's level cut, as both solvers start from it.
struct UnitCut {
    /// The cut cubes, sorted.
    keys: Vec<CubeKey>,
    /// The treetop units solved together.
    members: Vec<usize>,
    hist: Vec<[f32; BINS]>,
    /// Each cube's measured surface offset (`stages::observed::surface_offset`).
    offset: Vec<f32>,
    /// The difference rows, as [`Problem`]'s.
    start: Vec<u32>,
    terms: Vec<(u32, f32)>,
    /// The frozen neighbours by slot, with the previous-level values of the cube each
    /// inherits from ([`LevelStage::source_key`]).
    frozen: Vec<(CubeKey, Option<Inherited>)>,
    /// The previous-level values each cut cube starts from.
    previous: Vec<Option<Inherited>>,
}

/// A unit's problem at one level: its cut keys, the problem, the starting state, and each
/// cube's measured surface offset (`stages::observed::surface_offset`).
pub type UnitProblem = (Vec<CubeKey>, Problem, State, Vec<f32>);
