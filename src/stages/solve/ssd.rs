//! The SSD level units (`--method ssd`): the same level cut, frozen borders and segments as
//! TGV's, with `kernels::ssd` minimised on it. Each level's f (a signed distance in root units)
//! and its gradient g are the segment's `u` and `v`; `p` and `q` are zero. A cube inherits
//! the coarser cube's f carried along its gradient to the cube's centre, f_P + g_P . (c - c_P),
//! for its start, its anchor and, outside the unit, its frozen value: the cascadic multigrid
//! of Calakli et al., without which the seams would sit on values half a coarse cube off.

use std::collections::{BTreeMap, BTreeSet};

use rayon::prelude::*;

use super::{Inherited, LevelStage, LevelUnitExtra, LevelValues, ObservedColumns, UnitCut, columns_of};
use crate::format::key::last_at_or_below_from;
use crate::format::{Column, ColumnValues, CubeKey, MAX_DEPTH};
use crate::kernels::ssd::{CubeSamples, Solved, SsdProblem, UNSAMPLED_ANCHOR, solve};
use crate::stages::observed::{measured_weight, seen_weight};
use crate::stages::samples::{
    Moments, SAMPLES, SampleRows, cube_centre, normal_disagreement, read_sample_rows, read_samples,
};
use crate::stages::treetop::Treetop;
use crate::store::StageError;
use crate::store::catalog;
use crate::store::{Result, Snapshot, StoreError};
use crate::store::{UnitOutput, UnitSpec};

use super::{Method, SsdParams};
use crate::kernels::votes::BINS;

mod weights;
use weights::centroid_scatter;
pub use weights::{noise_normal_weight, noise_smoothness};

/// The column that marks an SSD level segment: 1 for `ssd`, 2 for `hybrid` in every row (a
/// TGV segment has none), so a reader knows u is a signed distance.
pub const METHOD_COLUMN: &str = "method";

/// The method that wrote a level segment, from its columns.
pub fn method_of_segment(snapshot: &Snapshot<'_>, segment: &str) -> Result<&'static str> {
    let file = snapshot.open_segment(segment)?;
    let reader = file.reader()?;
    if reader.column(METHOD_COLUMN).is_err() {
        return Ok("tgv");
    }
    let (_, codes) = reader.read_u32(METHOD_COLUMN).map_err(|e| file.corruption(e))?;
    Ok(match codes.first() {
        Some(2) => "hybrid",
        _ => "ssd",
    })
}

/// Below this share of a cube's votes measuring a distance to a surface, `hybrid` gives its
/// samples no weight; from [`FULL_EVIDENCE`] on, their whole weight. A floating outlier seen
/// through by the other maps (free space, bin 7) or lying behind a surface they saw (bin 0)
/// measures only in its own map's vote, a share of 1 / (maps that see the cube); around a
/// surface a third to a half of the votes measure (`stages::extract::dual_cells`).
pub const NO_EVIDENCE: f32 = 0.1;
/// See [`NO_EVIDENCE`].
pub const FULL_EVIDENCE: f32 = 0.25;

/// The factor `hybrid` puts on a cube's samples, from its histogram.
pub fn evidence(hist: &[f32; BINS]) -> f64 {
    let seen = seen_weight(hist);
    if seen <= 0.0 {
        return 0.0;
    }
    let share = measured_weight(hist) / seen;
    f64::from(((share - NO_EVIDENCE) / (FULL_EVIDENCE - NO_EVIDENCE)).clamp(0.0, 1.0))
}

/// f at `key`'s centre from the values of the cube it inherits from, `source`.
fn carried(key: CubeKey, source: CubeKey, values: Option<&Inherited>) -> (f64, [f64; 3]) {
    let Some((u, v, _, _)) = values else {
        return (0.0, [0.0; 3]);
    };
    let (to, from) = (cube_centre(key), cube_centre(source));
    let g = v.map(f64::from);
    let f = f64::from(*u) + (0..3).map(|k| g[k] * (to[k] - from[k])).sum::<f64>();
    (f, g)
}

/// The finest key holding a point in root units.
fn probe(point: [f64; 3]) -> CubeKey {
    // floor, then clamped to [0, 2^32 - 1]: the cast truncates (the floor of what is not
    // negative) and saturates (negatives and NaN to 0), where `floor` is a library call on
    // the baseline x86-64 this is built for.
    let full = |c: f64| ((c * 4294967296.0) as u64).min(u64::from(u32::MAX)) as u32;
    CubeKey::from_full_resolution(MAX_DEPTH, full(point[0]), full(point[1]), full(point[2]))
}

/// Finds the cube of a sorted, distinct list of keys that is a key or holds it.
struct HoldingCube<'k> {
    keys: &'k [CubeKey],
    /// The index the last search found.
    last: std::cell::Cell<usize>,
}

impl<'k> HoldingCube<'k> {
    fn new(keys: &'k [CubeKey]) -> HoldingCube<'k> {
        HoldingCube {
            keys,
            last: std::cell::Cell::new(0),
        }
    }

    /// The index of the last key at or below `key` if that key is `key` or holds it. Keys
    /// asked in order (a unit's nodes) nearly always find the last search's or the next, so
    /// the search starts there ([`last_at_or_below_from`]): a binary search over the whole
    /// list was half of `cut_samples`' sums.
    fn find(&self, key: CubeKey) -> Option<usize> {
        let found = last_at_or_below_from(self.keys, self.last.get(), key);
        if let Some(i) = found {
            self.last.set(i);
        }
        found.filter(|&i| self.keys.get(i).is_some_and(|k| k.is_ancestor_or_self_of(key)))
    }
}

/// Samples added up (root units).
#[derive(Clone, Copy, Debug, Default)]
struct SampleTotals {
    weight: f64,
    /// Sum of weight times centroid.
    position: [f64; 3],
    normal: [f64; 3],
}

/// Levels whose cuts take a unit's samples from its [`CoarseSamples`].
const COARSE_LEVELS: u8 = 8;

/// One unit's samples as the cuts of the coarse levels take them: at level L, a node deeper
/// than L gives its samples to the cut cube holding its ancestor at L (its centroid lies in
/// its cube, so in that ancestor), so its samples can be summed by that ancestor beforehand.
pub struct CoarseSamples {
    /// Per level L below [`COARSE_LEVELS`]: the nodes deeper than L summed by their ancestor
    /// at L, in key order.
    by_level: Vec<Vec<(CubeKey, SampleTotals)>>,
    /// The nodes of depth below [`COARSE_LEVELS`], taken one by one.
    shallow: Vec<(CubeKey, Moments)>,
    /// The segment's [`normal_disagreement`].
    disagreement: Option<(f64, f64)>,
}

impl CoarseSamples {
    fn of(keys: &[CubeKey], moments: &[Moments]) -> CoarseSamples {
        let mut by_level: Vec<Vec<(CubeKey, SampleTotals)>> = vec![Vec::new(); usize::from(COARSE_LEVELS)];
        let mut shallow = Vec::new();
        for (key, m) in keys.iter().zip(moments) {
            if key.depth() < COARSE_LEVELS {
                shallow.push((*key, *m));
            }
            let Some((w, centroid, normal)) = m.in_root_units(*key) else {
                continue;
            };
            // The ancestors from the deepest up, each its child's parent on the Morton code:
            // decoding the key's coordinates and encoding one ancestor per level took about
            // half of this.
            let mut ancestor = *key;
            while let Some(parent) = ancestor.parent() {
                ancestor = parent;
                let Some(sums) = by_level.get_mut(usize::from(ancestor.depth())) else {
                    continue;
                };
                // Keys come in depth-first order: a cube's descendants are consecutive.
                if sums.last().is_none_or(|(last, _)| *last != ancestor) {
                    sums.push((ancestor, SampleTotals::default()));
                }
                if let Some((_, totals)) = sums.last_mut() {
                    totals.weight += w;
                    for k in 0..3 {
                        totals.position[k] += w * centroid[k];
                        totals.normal[k] += normal[k];
                    }
                }
            }
        }
        CoarseSamples {
            by_level,
            shallow,
            disagreement: normal_disagreement(moments),
        }
    }
}

/// [`CoarseSamples`] by samples segment (segments are immutable, so a name is its content),
/// shared by the level stages of one solve: the coarse levels' cuts take every unit's samples,
/// and decoding all of them at every level cost SSD about half a second a level.
pub type CoarseSamplesCache = std::sync::Arc<std::sync::Mutex<BTreeMap<String, std::sync::Arc<CoarseSamples>>>>;

/// The coarse sums of units whose keys and moments are at hand, by unit id, filed into a
/// [`CoarseSamplesCache`] under their segments' names once those exist.
#[derive(Default)]
pub struct PendingCoarseSamples(std::sync::Mutex<BTreeMap<u64, std::sync::Arc<CoarseSamples>>>);

impl PendingCoarseSamples {
    /// Sums unit `unit`'s `keys` and `moments` (as its samples segment will hold them).
    pub fn add(&self, unit: u64, keys: &[CubeKey], moments: &[Moments]) {
        let coarse = std::sync::Arc::new(CoarseSamples::of(keys, moments));
        self.0
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .insert(unit, coarse);
    }

    /// Files the pending sums under the names of `snapshot`'s samples segments, unit for unit.
    pub fn file_into(self, cache: &CoarseSamplesCache, snapshot: &Snapshot<'_>) {
        let mut pending = self.0.into_inner().unwrap_or_else(std::sync::PoisonError::into_inner);
        let mut cache = cache.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        for (name, record) in snapshot.segments(SAMPLES) {
            if let Some(coarse) = pending.remove(&record.unit) {
                cache.insert(name.clone(), coarse);
            }
        }
    }
}

fn coarse_samples_of(
    base: &Snapshot<'_>,
    segment: &str,
    cache: &CoarseSamplesCache,
) -> Result<std::sync::Arc<CoarseSamples>> {
    let cached = cache
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
        .get(segment)
        .cloned();
    if let Some(coarse) = cached {
        return Ok(coarse);
    }
    let (keys, moments) = read_samples(base, segment)?;
    let coarse = std::sync::Arc::new(CoarseSamples::of(&keys, &moments));
    cache
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
        .insert(segment.to_string(), coarse.clone());
    Ok(coarse)
}

/// The units whose every node a cut of the units `members` at `level` takes, in the order
/// their samples are summed: the members, and with the treetop's unit every leaf unit below
/// the level.
fn units_taken_whole(treetop: &Treetop, members: &BTreeSet<usize>, level: u8) -> Vec<usize> {
    let mut taken: Vec<usize> = members.iter().copied().collect();
    if let Some(top) = treetop.units.iter().position(|u| u.top)
        && members.contains(&top)
    {
        taken.extend(
            treetop
                .units
                .iter()
                .enumerate()
                .filter(|(index, unit)| !unit.top && !members.contains(index) && unit.key.depth() > level)
                .map(|(index, _)| index),
        );
    }
    taken
}

/// Each cut cube's samples. Every octree node's own samples go to the cut cube holding their
/// centroid: their node's ancestor at the level, the node itself, or, for a node above the
/// level, the finer cube its samples gather in. Each node lands in exactly one unit's cut: a
/// leaf unit takes its own nodes and the treetop's nodes above it whose centroid lies in it;
/// the treetop's unit takes its own and every leaf unit's that lies below the level. At the
/// coarse levels a unit's nodes deeper than the level come summed by their ancestor at the
/// level ([`CoarseSamples`]; a centroid on the ancestor's upper face then counts in the
/// ancestor's cut cube, where the node-by-node rule would put it in the neighbour's).
///
/// Also the [`normal_disagreement`] of the units whose nodes the cut takes whole, averaged by
/// their sample weight (0 without samples): the noise the unit's normal weight follows.
fn cut_samples(
    base: &Snapshot<'_>,
    treetop: &Treetop,
    level: u8,
    cut: &UnitCut,
    cache: &CoarseSamplesCache,
) -> Result<(Vec<CubeSamples>, f64)> {
    let segments: BTreeMap<u64, &str> = base
        .segments(SAMPLES)
        .iter()
        .map(|(name, record)| (record.unit, name.as_str()))
        .collect();
    let missing = |unit: usize| StoreError::Stage {
        stage: SAMPLES.into(),
        unit: format!("unit {unit}"),
        error: Box::new(StageError::NoSamples),
    };
    let read = |unit: usize| -> Result<SampleRows> {
        match segments.get(&(unit as u64)) {
            Some(name) => read_sample_rows(base, name),
            None => Err(missing(unit)),
        }
    };
    let keys = &cut.keys;
    let holding = HoldingCube::new(keys);
    let holding = |key: CubeKey| holding.find(key);
    let sums = std::cell::RefCell::new((
        vec![0.0f64; keys.len()],
        vec![[0.0f64; 3]; keys.len()],
        vec![[0.0f64; 3]; keys.len()],
    ));
    // Adds to cut cube i a weight, its weighted offset from the cube's centre and a normal sum.
    let gather = |i: usize, w: f64, offset: [f64; 3], n: [f64; 3]| {
        let (weight, moment, normal) = &mut *sums.borrow_mut();
        if let (Some(weight), Some(moment), Some(normal)) = (weight.get_mut(i), moment.get_mut(i), normal.get_mut(i)) {
            *weight += w;
            for k in 0..3 {
                moment[k] += offset[k];
                normal[k] += n[k];
            }
        }
    };
    // The centre of the cut cube that took the last node's samples: consecutive nodes
    // mostly go to the same one, whose key's coordinates were decoded again for each.
    let last_centre = std::cell::Cell::new(None::<(usize, [f64; 3])>);
    let centre_of = |i: usize| match last_centre.get() {
        Some((last, centre)) if last == i => centre,
        _ => {
            let centre = keys.get(i).map_or([0.0; 3], |key| cube_centre(*key));
            last_centre.set(Some((i, centre)));
            centre
        }
    };
    let add = |node: CubeKey, m: &Moments| {
        let Some((w, centroid, n)) = m.in_root_units(node) else {
            return;
        };
        let Some(i) = holding(probe(centroid)) else {
            return;
        };
        let centre = centre_of(i);
        gather(i, w, std::array::from_fn(|k| w * (centroid[k] - centre[k])), n);
    };
    let top = treetop.units.iter().position(|u| u.top);
    let members: BTreeSet<usize> = cut.members.iter().copied().collect();
    // Every node of unit `index`, through its coarse sums at the coarse levels.
    let add_unit = |index: usize| -> Result<()> {
        if level >= COARSE_LEVELS {
            read(index)?.iter().for_each(|(k, m)| add(k, &m));
            return Ok(());
        }
        let segment = segments.get(&(index as u64)).ok_or_else(|| missing(index))?;
        let coarse = coarse_samples_of(base, segment, cache)?;
        for (ancestor, totals) in coarse
            .by_level
            .get(usize::from(level))
            .map(Vec::as_slice)
            .unwrap_or_default()
        {
            if let Some(i) = holding(*ancestor) {
                let centre = centre_of(i);
                let offset = std::array::from_fn(|k| totals.position[k] - totals.weight * centre[k]);
                gather(i, totals.weight, offset, totals.normal);
            }
        }
        coarse
            .shallow
            .iter()
            .filter(|(k, _)| k.depth() <= level)
            .for_each(|(k, m)| add(*k, m));
        Ok(())
    };
    let taken = units_taken_whole(treetop, &members, level);
    if level < COARSE_LEVELS {
        // Their coarse sums, decoded side by side into the cache before the sums below take
        // them in order: level 0's one unit reads every unit's samples while the other
        // workers would idle (0.64 s of RedKitchen's 1000 frames, one core).
        taken
            .par_iter()
            .filter_map(|unit| segments.get(&(*unit as u64)))
            .try_for_each(|segment| coarse_samples_of(base, segment, cache).map(|_| ()))?;
    }
    for &unit in &taken {
        add_unit(unit)?;
    }
    let whole: BTreeSet<usize> = taken.into_iter().collect();
    match top {
        Some(top) if members.contains(&top) => {}
        Some(top) => {
            for (k, m) in read(top)?.iter() {
                if members
                    .iter()
                    .filter_map(|&member| treetop.units.get(member))
                    .any(|unit| k.is_ancestor_or_self_of(unit.key) && k != unit.key)
                {
                    add(k, &m);
                }
            }
        }
        None => {}
    }
    // The normal disagreement of the units taken whole, averaged by their sample weight.
    let (mut sum, mut total) = (0.0, 0.0);
    for unit in whole {
        let segment = segments.get(&(unit as u64)).ok_or_else(|| missing(unit))?;
        if let Some((quartile, weight)) = coarse_samples_of(base, segment, cache)?.disagreement {
            sum += quartile * weight;
            total += weight;
        }
    }
    let disagreement = if total > 0.0 { sum / total } else { 0.0 };
    let (weight, moment, normal) = sums.into_inner();
    let samples = weight
        .into_iter()
        .zip(moment)
        .zip(normal)
        .map(|((weight, moment), normal)| CubeSamples {
            weight,
            centroid: if weight > 0.0 {
                moment.map(|x| x / weight)
            } else {
                [0.0; 3]
            },
            normal,
        })
        .collect();
    Ok((samples, disagreement))
}

impl LevelStage {
    /// The unit's SSD problem and start values.
    pub(super) fn ssd_problem(
        &self,
        base: &Snapshot<'_>,
        treetop: &Treetop,
        cut: &UnitCut,
        params: &SsdParams,
    ) -> Result<(SsdProblem, Vec<f64>)> {
        let (mut samples, disagreement) = cut_samples(base, treetop, self.level, cut, &self.coarse_samples)?;
        // Measured on the samples as they are: hybrid's evidence factors below scale a cube's
        // weight, not where its centroid lies.
        let scatter = centroid_scatter(&cut.keys, &samples, &cut.start, &cut.terms);
        let normal_weight = noise_normal_weight(params.normal_weight, disagreement);
        let smoothness = noise_smoothness(params.smoothness, scatter);
        tracing::debug!(
            level = self.level,
            cubes = cut.keys.len(),
            disagreement,
            scatter,
            normal_weight,
            smoothness,
            "ssd unit"
        );
        if let Method::Hybrid(_) = self.method {
            for (s, hist) in samples.iter_mut().zip(&cut.hist) {
                let factor = evidence(hist);
                s.weight *= factor;
                s.normal = s.normal.map(|n| n * factor);
            }
        }
        let start: Vec<f64> = cut
            .keys
            .iter()
            .zip(&cut.previous)
            .map(|(key, previous)| carried(*key, self.source_key(*key), previous.as_ref()).0)
            .collect();
        let (frozen_f, frozen_gradient) = cut
            .frozen
            .iter()
            .map(|(key, previous)| carried(*key, self.source_key(*key), previous.as_ref()))
            .unzip();
        let problem = SsdProblem {
            n: cut.keys.len(),
            start: cut.start.clone(),
            terms: cut.terms.clone(),
            side: cut.keys.iter().map(|k| k.side()).collect(),
            samples,
            anchor: start.clone(),
            frozen_f,
            frozen_gradient,
            normal_weight,
            smoothness,
            unsampled_anchor: UNSAMPLED_ANCHOR,
            ..SsdProblem::default()
        };
        Ok((problem, start))
    }

    /// Solves the unit's SSD problem: f and its gradient per cut cube, and how it ended.
    pub(super) fn solve_ssd(
        &self,
        base: &Snapshot<'_>,
        treetop: &Treetop,
        cut: &UnitCut,
        params: &SsdParams,
    ) -> Result<(Vec<f32>, Vec<[f32; 3]>, Solved)> {
        let (problem, mut f) = self.ssd_problem(base, treetop, cut, params)?;
        let solved = solve(&problem, &mut f, params.tolerance, params.iterations as usize);
        let gradient = problem.gradients(&f).into_iter().map(|g| g.map(|x| x as f32)).collect();
        Ok((f.into_iter().map(|x| x as f32).collect(), gradient, solved))
    }
}

impl LevelStage {
    /// A level unit under `--method ssd`: the level segment of TGV's layout with f as u, its
    /// gradient as v, zero p and q, and no measured offsets (extraction then places vertices where f's interpolation crosses zero,
    /// which is what SSD's accuracy is for).
    pub(super) fn run_ssd_unit(&self, base: &Snapshot<'_>, unit: &UnitSpec, params: &SsdParams) -> Result<UnitOutput> {
        let Some(cut) = self.build_cut(base, unit.id as usize)? else {
            return Ok(UnitOutput {
                extra: catalog::encode(&LevelUnitExtra::default()),
                ..UnitOutput::default()
            });
        };
        let treetop = self
            .treetop
            .get()
            .ok_or_else(|| self.stage_error(unit, StageError::internal("units run before planning")))?;
        let (f, gradient, solved) = self.solve_ssd(base, treetop, &cut, params)?;
        let n = cut.keys.len();
        let observed = ObservedColumns {
            seen: cut.hist.iter().map(seen_weight).collect(),
            sampled: self
                .sampled(base, treetop, &cut.keys)?
                .into_iter()
                .map(u32::from)
                .collect(),
            offset: vec![f32::NAN; n],
            measured: cut.hist.iter().map(measured_weight).collect(),
        };
        let values = LevelValues {
            keys: cut.keys,
            u: f,
            v: gradient,
            p: vec![[0.0; 3]; n],
            q: vec![[0.0; 6]; n],
        };
        let mut columns = columns_of(&values, observed, self.kept(unit)?);
        let code = if let Method::Hybrid(_) = self.method { 2 } else { 1 };
        columns.push(Column::new(METHOD_COLUMN, 1, ColumnValues::U32(vec![code; n])));
        Ok(UnitOutput {
            segments: vec![columns.into()],
            extra: catalog::encode(&LevelUnitExtra {
                cubes: n as u64,
                energy_before: solved.energy_before,
                energy_after: solved.energy_after,
                iterations: solved.iterations as u64,
            }),
            block_rows: crate::stages::FACE_READ_BLOCK_ROWS,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_probe_floors_and_clamps_as_floor_and_clamp_do() {
        let reference = |point: [f64; 3]| {
            let full = |c: f64| (c * 4294967296.0).floor().clamp(0.0, 4294967295.0) as u32;
            CubeKey::from_full_resolution(MAX_DEPTH, full(point[0]), full(point[1]), full(point[2]))
        };
        let tiny = f64::from_bits(1);
        let edges = [
            0.0,
            -0.0,
            tiny,
            -tiny,
            0.25,
            0.5 - f64::EPSILON,
            0.5,
            1.0 - f64::EPSILON,
            1.0,
            1.5,
            -0.3,
            -1e300,
            1e300,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
            2.3283064365386963e-10,
        ];
        for x in edges {
            for y in edges {
                for z in [0.75, x, -y] {
                    assert_eq!(probe([x, y, z]), reference([x, y, z]), "{x} {y} {z}");
                }
            }
        }
    }

    #[test]
    fn the_holding_cube_is_found_in_any_order_of_asking() {
        // A cut of depth-2 cubes with one octant refined to depth 3, and keys below it.
        let mut keys: Vec<CubeKey> = (0..64u32)
            .filter(|i| i % 8 != 3)
            .map(|i| CubeKey::new(2, i & 3, (i >> 2) & 3, i >> 4))
            .chain((0..8u32).map(|i| CubeKey::new(3, 2 + (i & 1), (i >> 1) & 1, (i >> 2) & 1)))
            .collect();
        keys.sort();
        let asked: Vec<CubeKey> = (0..512u32)
            .map(|i| CubeKey::new(4, (i * 7) & 15, ((i * 5) >> 3) & 15, ((i * 3) >> 5) & 15))
            .chain(keys.iter().copied())
            .collect();
        let by_search = |key: CubeKey| {
            keys.partition_point(|k| *k <= key)
                .checked_sub(1)
                .filter(|&i| keys[i].is_ancestor_or_self_of(key))
        };
        let mut in_order = asked.clone();
        in_order.sort();
        for order in [asked, in_order] {
            let holding = HoldingCube::new(&keys);
            for key in order {
                assert_eq!(holding.find(key), by_search(key), "{key:?}");
            }
        }
    }

    /// A node whose samples weigh `weight` (fixed point) in two halves with unit normals
    /// `angle` radians apart.
    fn node(weight: i64, angle: f64) -> Moments {
        let half = weight as f64 / 2.0;
        let (x, y) = (half * (1.0 + angle.cos()), half * angle.sin());
        Moments {
            weight,
            offset: [0; 3],
            normal: [x.round() as i64, y.round() as i64, 0],
        }
    }

    #[test]
    fn normal_disagreement_is_the_lower_quartile_by_weight_of_one_minus_the_mean_normals_length() {
        let w = 1 << 24;
        // Nodes of one normal say nothing: no measure, and they do not dilute one.
        assert_eq!(normal_disagreement(&[node(w, 0.0), node(3 * w, 0.0)]), None);
        assert_eq!(normal_disagreement(&[Moments::default()]), None);
        // Two halves t apart: 1 - cos(t / 2).
        let (value, total) = normal_disagreement(&[node(w, 0.4), node(5 * w, 0.0)]).unwrap();
        assert!(
            (value - (1.0 - 0.2f64.cos())).abs() < 1e-6 && total == w as f64,
            "{value} {total}"
        );
        // The lower quartile by weight: a quarter of the weight at 0.1, the rest far more.
        let mut nodes = vec![node(w, 0.1)];
        nodes.extend((0..3).map(|k| node(w, 1.0 + f64::from(k))));
        let (quartile, total) = normal_disagreement(&nodes).unwrap();
        assert!((quartile - (1.0 - 0.05f64.cos())).abs() < 1e-6, "{quartile}");
        assert_eq!(total, (4 * w) as f64);
        // Just under a quarter there: the next node's value.
        nodes.push(node(w / 10, 3.0));
        let (next, _) = normal_disagreement(&nodes).unwrap();
        assert!((next - (1.0 - 0.5f64.cos())).abs() < 1e-6, "{next}");
    }

    #[test]
    fn hybrid_evidence_ramps_with_the_share_of_measuring_votes() {
        let hist = |measuring: f32, free: f32, behind: f32| {
            let mut h = [0.0f32; BINS];
            h[0] = behind;
            h[3] = measuring;
            h[BINS - 1] = free;
            h
        };
        assert_eq!(evidence(&hist(0.0, 0.0, 0.0)), 0.0, "unseen");
        // One map's vote among 16 that saw through the cube, or behind a surface.
        assert_eq!(evidence(&hist(1.0, 15.0, 0.0)), 0.0);
        assert_eq!(evidence(&hist(1.0, 0.0, 15.0)), 0.0);
        // A surface: a third of the votes measure.
        assert_eq!(evidence(&hist(5.0, 10.0, 0.0)), 1.0);
        // 7 of 40 measure: halfway up the ramp from 0.1 to 0.25.
        let between = evidence(&hist(7.0, 33.0, 0.0));
        assert!((between - 0.5).abs() < 1e-6, "{between}");
    }

    #[test]
    fn coarse_sums_add_each_node_into_its_ancestor_at_every_coarse_level() {
        // Nodes of one subtree at depths 1 to 10, in key order, some without samples.
        let mut state = 3u64;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 33) as u32
        };
        let mut keys: Vec<CubeKey> = (0..3000)
            .map(|_| {
                let depth = 1 + (next() % 10) as u8;
                let mask = (1u32 << depth) - 1;
                CubeKey::new(depth, next() & mask, next() & mask, next() & mask)
            })
            .collect();
        keys.sort();
        keys.dedup();
        let moments: Vec<Moments> = keys
            .iter()
            .map(|_| Moments {
                weight: i64::from(next() % 3),
                offset: [0; 3].map(|_| i64::from(next() % 7) - 3),
                normal: [0; 3].map(|_| i64::from(next() % 9) - 4),
            })
            .collect();
        let coarse = CoarseSamples::of(&keys, &moments);
        assert_eq!(
            coarse.shallow.len(),
            keys.iter().filter(|k| k.depth() < COARSE_LEVELS).count()
        );
        for level in 0..COARSE_LEVELS {
            let mut expected: BTreeMap<CubeKey, SampleTotals> = BTreeMap::new();
            for (key, m) in keys.iter().zip(&moments) {
                let Some((w, centroid, normal)) = m.in_root_units(*key).filter(|_| key.depth() > level) else {
                    continue;
                };
                let mut ancestor = *key;
                while ancestor.depth() > level {
                    ancestor = ancestor.parent().expect("deeper than the level");
                }
                let entry = expected.entry(ancestor).or_default();
                entry.weight += w;
                for k in 0..3 {
                    entry.position[k] += w * centroid[k];
                    entry.normal[k] += normal[k];
                }
            }
            let got = &coarse.by_level[usize::from(level)];
            assert_eq!(got.len(), expected.len(), "level {level}: one entry per ancestor");
            let close = |a: f64, b: f64| (a - b).abs() <= 1e-9 * a.abs().max(b.abs()).max(1e-30);
            for ((ancestor, totals), (key, want)) in got.iter().zip(&expected) {
                assert_eq!(ancestor, key);
                assert!(close(totals.weight, want.weight), "level {level}");
                for k in 0..3 {
                    assert!(close(totals.position[k], want.position[k]), "level {level}");
                    assert!(close(totals.normal[k], want.normal[k]), "level {level}");
                }
            }
        }
    }

    #[test]
    fn values_carry_along_the_gradient_to_the_cube_centre() {
        let parent = CubeKey::new(2, 1, 2, 3);
        let child = CubeKey::new(3, 3, 4, 7);
        assert_eq!(child.parent(), Some(parent));
        let (f, g) = carried(child, parent, Some(&(0.5, [1.0, -2.0, 0.25], [0.0; 3], [0.0; 6])));
        // The child's centre is a quarter of the parent's side (1/16) off on each axis.
        // g . (c - c_P) = (1, -2, 0.25) . (1, -1, 1) / 16.
        let expected = 0.5 + (1.0 + 2.0 + 0.25) / 16.0;
        assert!((f - expected).abs() < 1e-12, "{f} vs {expected}");
        assert_eq!(g, [1.0, -2.0, 0.25]);
        assert_eq!(carried(child, parent, None), (0.0, [0.0; 3]));
    }
}
