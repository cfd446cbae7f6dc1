//! Reading the indicator field from code: an extension of [`Snapshot`] (the store layer knows
//! nothing of stages, so the field's queries live here).
//!
//! [`crate::pipeline`]'s documentation has a runnable example that builds a store and reads
//! its field.

use glam::DVec3;
use serde::Serialize;

use crate::format::{BoundingBox, CubeKey, MAX_DEPTH, Scene};
use crate::kernels::votes::BINS;

/// Bins of a cube's vote histogram ([`CubeInfo::histogram`]): the signed distance to the
/// surface, in units of the cube's noise band, is split into this many equal bins over [-1, 1].
pub const HISTOGRAM_BINS: usize = BINS;
use crate::stages::HISTOGRAMS;
use crate::stages::ingest::scene_at;
use crate::stages::solve::{CutValue, LEVEL_STAGES, LevelCut, method_of_segment};
use crate::stages::treetop::Treetop;
use crate::store::StageError;
use crate::store::{Result, Snapshot, StoreError};

/// One cube of a level cut, as `cubes_in` returns it.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct CubeInfo {
    /// The cube's key, in its display form.
    pub key: String,
    /// The cube's depth.
    pub depth: u8,
    /// Centre in world units.
    pub center: [f64; 3],
    /// Side in world units.
    pub size: f64,
    /// The indicator: negative inside, positive outside.
    pub u: f32,
    /// Whether a depth map saw the cube (votes near a surface or in free space; format-spec.md,
    /// "Columns used by stages"). Extraction meshes only between seen cubes unless `--closed`.
    pub seen: bool,
    /// Whether samples spawned the cube, an ancestor or a descendant (format-spec.md, "Columns
    /// used by stages"). Extraction meshes only dual cells with a sampled corner.
    pub sampled: bool,
    /// Where the votes that measured a distance put the surface from the centre, in units of
    /// the voting distance; absent when no vote measured one.
    pub offset: Option<f32>,
    /// The cube's vote histogram (8 bins over the signed distance [-1, 1]).
    pub histogram: [f32; HISTOGRAM_BINS],
}

/// One treetop leaf, as `leaves` lists it.
#[derive(Clone, Debug, Serialize, PartialEq)]
pub struct LeafInfo {
    /// The leaf's key, in its display form.
    pub key: String,
    /// The leaf's depth.
    pub depth: u8,
    /// Minimum corner and side of the leaf's cube, in world units.
    pub min: [f64; 3],
    /// Side of the leaf's cube.
    pub size: f64,
    /// Octree cubes in the leaf.
    pub cubes: u64,
}

/// Reading the solved indicator field u from a pinned [`Snapshot`].
pub trait IndicatorField {
    /// The deepest solved level visible in this snapshot.
    fn finest_level(&self) -> Option<u8>;

    /// Every solved level visible in this snapshot, coarse to fine.
    fn levels(&self) -> Vec<u8>;

    /// The treetop leaves of the snapshot's octree, in key order.
    fn leaves(&self) -> Result<Vec<LeafInfo>>;

    /// u at a point, interpolated by inverse distance over the leaves around the octree corner
    /// nearest to the point (exact at leaf centres); `None` outside the root or before a solve.
    fn indicator_at(&self, point: DVec3) -> Result<Option<f32>>;

    /// Whether a depth map saw the finest-cut leaf that contains the point; `None` outside the
    /// root or before a solve.
    fn seen_at(&self, point: DVec3) -> Result<Option<bool>>;

    /// Cubes of the level-`level` cut that meet `bbox`, with centre, size, u and histogram.
    fn cubes_in(&self, bbox: &BoundingBox, level: u8) -> Result<Vec<CubeInfo>>;

    /// The solver of the finest level: `tgv` (u an indicator in [-1, 1]), `ssd` or `hybrid`
    /// (u a signed distance in units of the root side); `None` before a solve.
    fn method(&self) -> Result<Option<&'static str>>;
}

/// The last version at which `stage`'s visible content changed (0 when it has none).
fn last_change(snapshot: &Snapshot<'_>, stage: &str) -> u64 {
    snapshot
        .segments(stage)
        .iter()
        .map(|(_, r)| r.created)
        .max()
        .unwrap_or(0)
}

/// Whether the snapshot's finest solution was computed from its own octree and histograms.
///
/// A solve runs the octree, the histograms and the levels in that order, and each rewrites the
/// units whose inputs changed, so a complete version has the octree's last change no later
/// than the histograms' and theirs no later than the finest level's. After `solve --until
/// octree`, or while a solve runs, a newer octree or histograms sit under an older solution:
/// its surface would combine the new cubes with values solved for the old ones.
pub fn solution_is_current(snapshot: &Snapshot<'_>) -> bool {
    let Some(finest) = snapshot.finest_level() else {
        return true;
    };
    let octree = last_change(snapshot, crate::stages::OCTREE);
    let histograms = last_change(snapshot, HISTOGRAMS);
    let solution = last_change(snapshot, LEVEL_STAGES[usize::from(finest)]);
    octree <= histograms && histograms <= solution
}

/// An error unless [`solution_is_current`]; it names the latest older version that is.
pub fn ensure_solution_is_current(snapshot: &Snapshot<'_>) -> Result<()> {
    if solution_is_current(snapshot) {
        return Ok(());
    }
    let store = snapshot.store();
    let complete = (1..snapshot.version()).rev().find(|&v| {
        store
            .snapshot(v)
            .is_ok_and(|s| s.finest_level().is_some() && solution_is_current(&s))
    });
    Err(StoreError::Stage {
        stage: "read".into(),
        unit: format!("version {}", snapshot.version()),
        error: Box::new(StageError::SolutionBehind {
            latest_complete: complete,
        }),
    })
}

/// `(finest solved level, the octree's deepest level)` when a solve stopped part way: the
/// first below the second. Reads then see the finest solved level, which is a complete,
/// coarser solution; the user must be told that it is not the finished one.
pub fn unfinished_solve(snapshot: &Snapshot<'_>) -> Result<Option<(u8, u8)>> {
    let Some(solved) = snapshot.finest_level() else {
        return Ok(None);
    };
    let deepest = crate::stages::octree_max_depth(snapshot.store())?;
    Ok((solved < deepest).then_some((solved, deepest)))
}

/// What `extract`, `query` and `info` say of an [`unfinished_solve`].
pub fn unfinished_solve_note(solved: u8, deepest: u8) -> String {
    format!(
        "the solution reaches level {solved} of the octree's {deepest}: a solve stopped part way, and reads see level {solved}; `octstore solve --resume` finishes it"
    )
}

fn scene_of(snapshot: &Snapshot<'_>) -> Result<Scene> {
    scene_at(snapshot.store(), snapshot.version())?.ok_or_else(|| StoreError::Stage {
        stage: "query".into(),
        unit: "-".into(),
        error: Box::new(StageError::NotIngested),
    })
}

fn full_resolution(scene: &Scene, p: DVec3) -> Option<[i64; 3]> {
    let q = (p - scene.min()) / scene.root_side * 4294967296.0;
    if q.cmplt(DVec3::ZERO).any() || q.cmpge(DVec3::splat(4294967296.0)).any() {
        return None;
    }
    Some([q.x as i64, q.y as i64, q.z as i64])
}

/// The scene, the finest solved level and the full-resolution cell of a point; `None` before a
/// solve or outside the root.
fn finest_cell_at(snapshot: &Snapshot<'_>, point: DVec3) -> Result<Option<(Scene, u8, [i64; 3])>> {
    let Some(level) = snapshot.finest_level() else {
        return Ok(None);
    };
    ensure_solution_is_current(snapshot)?;
    let scene = scene_of(snapshot)?;
    Ok(full_resolution(&scene, point).map(|cell| (scene, level, cell)))
}

/// The cut cubes found last, for a run of nearby lookups: points taken in Morton order probe
/// around each other, so most probes fall in a cube found for a point just before. The cut
/// tiles what it covers, so a remembered cube that contains a probe is the answer.
struct RecentCubes<'l, 'a, 's> {
    lookup: &'l mut LevelCut<'a, 's>,
    cubes: [Option<(CubeKey, CutValue)>; 16],
    next: usize,
}

impl<'l, 'a, 's> RecentCubes<'l, 'a, 's> {
    fn new(lookup: &'l mut LevelCut<'a, 's>) -> Self {
        RecentCubes {
            lookup,
            cubes: [None; 16],
            next: 0,
        }
    }

    fn cube_at(&mut self, cell: [u32; 3]) -> Result<Option<(CubeKey, CutValue)>> {
        let probe = CubeKey::new(MAX_DEPTH, cell[0], cell[1], cell[2]);
        if let Some(found) = self
            .cubes
            .iter()
            .flatten()
            .find(|(key, _)| key.is_ancestor_or_self_of(probe))
        {
            return Ok(Some(*found));
        }
        let found = self.lookup.cube_containing(probe)?;
        if let (Some(found), Some(slot)) = (found, self.cubes.get_mut(self.next)) {
            *slot = Some(found);
            self.next = (self.next + 1) % 16;
        }
        Ok(found)
    }
}

/// The cut cubes around one octree corner, as [`interpolated`] weighs them: each distinct
/// cube's centre and u, in octant order.
struct CornerCubes {
    /// The leaf that holds the point, and the corner of it nearest the point (finest cells).
    leaf: CubeKey,
    corner: [i64; 3],
    cubes: Vec<(DVec3, f32)>,
}

/// u at `point`, whose full-resolution cell is `cell`: interpolated by inverse distance over
/// the cut cubes around the octree corner nearest to the point (exact at cube centres).
/// `last` keeps the previous point's corner cubes: points taken in Morton order often share
/// a leaf and its nearest corner, and then only the distances are new.
fn interpolated(
    lookup: &mut RecentCubes<'_, '_, '_>,
    last: &mut Option<CornerCubes>,
    scene: &Scene,
    cell: [i64; 3],
    point: DVec3,
) -> Result<Option<f32>> {
    let Some((leaf, own)) = lookup.cube_at(cell.map(|c| c as u32))? else {
        return Ok(None);
    };
    // The nearest corner of the containing leaf, and the leaves in its 8 octants.
    let side = 1i64 << (u32::from(MAX_DEPTH) - u32::from(leaf.depth()));
    let corner = leaf.corner_full_resolution().map(i64::from);
    let v: [i64; 3] = std::array::from_fn(|a| {
        if cell[a] - corner[a] >= side / 2 {
            corner[a] + side
        } else {
            corner[a]
        }
    });
    if !last.as_ref().is_some_and(|c| c.leaf == leaf && c.corner == v) {
        let limit = 1i64 << 32;
        let mut keys: Vec<CubeKey> = Vec::with_capacity(8);
        let mut cubes = Vec::with_capacity(8);
        for octant in 0..8usize {
            let probe: [i64; 3] = std::array::from_fn(|a| v[a] - 1 + ((octant >> a) & 1) as i64);
            if probe.iter().any(|c| *c < 0 || *c >= limit) {
                continue;
            }
            let Some((key, value)) = lookup.cube_at(probe.map(|c| c as u32))? else {
                continue;
            };
            if keys.contains(&key) {
                continue;
            }
            keys.push(key);
            cubes.push((scene.cube_center(key), value.u));
        }
        *last = Some(CornerCubes { leaf, corner: v, cubes });
    }
    let mut weights = 0f64;
    let mut sum = 0f64;
    for (center, u) in last.iter().flat_map(|c| c.cubes.iter()) {
        let distance = (*center - point).length();
        if distance < 1e-12 * scene.root_side {
            return Ok(Some(*u));
        }
        let w = 1.0 / (distance * distance);
        weights += w;
        sum += w * f64::from(*u);
    }
    Ok(Some(if weights > 0.0 { (sum / weights) as f32 } else { own.u }))
}

/// Points per batch of [`indicator_at_points`], at least and at most: each batch decodes the
/// level's groups it touches once (decoding dominated with 16,384-point batches), and holds
/// them, so memory follows a batch's extent, not the scene's.
const POINTS_PER_BATCH: std::ops::RangeInclusive<usize> = (1 << 14)..=(1 << 20);

/// u at many points ([`IndicatorField::indicator_at`] for each, NaN where it gives `None`),
/// on every core: the version's checks run once, and the points are taken in Morton order of
/// their cells in batches that each decode the groups they touch once. The values do not
/// depend on the batching (each is its own point's).
pub fn indicator_at_points(snapshot: &Snapshot<'_>, points: &[DVec3]) -> Result<Vec<f32>> {
    use rayon::prelude::*;
    let mut values = vec![f32::NAN; points.len()];
    let Some(level) = snapshot.finest_level() else {
        return Ok(values);
    };
    ensure_solution_is_current(snapshot)?;
    let scene = scene_of(snapshot)?;
    let treetop = Treetop::of(snapshot)?;
    let mut order: Vec<(CubeKey, usize)> = points
        .par_iter()
        .enumerate()
        .filter_map(|(index, p)| {
            let cell = full_resolution(&scene, *p)?;
            Some((
                CubeKey::new(MAX_DEPTH, cell[0] as u32, cell[1] as u32, cell[2] as u32),
                index,
            ))
        })
        .collect();
    order.par_sort_unstable();
    // The points in that order, gathered in one pass of independent loads: read inside the
    // interpolation loop, each was a cache miss the loop waited for.
    let sorted: Vec<(usize, DVec3)> = order
        .par_iter()
        .map(|(_, index)| (*index, points.get(*index).copied().unwrap_or(DVec3::NAN)))
        .collect();
    // Two batches per worker when that keeps them within bounds.
    let batch = (sorted.len() / (2 * rayon::current_num_threads().max(1)))
        .clamp(*POINTS_PER_BATCH.start(), *POINTS_PER_BATCH.end());
    let found: Vec<Vec<(usize, f32)>> = sorted
        .par_chunks(batch)
        .map(|batch| {
            let mut lookup = LevelCut::new(snapshot, &treetop, level);
            let mut recent = RecentCubes::new(&mut lookup);
            let mut last = None;
            batch
                .iter()
                .map(|(index, point)| {
                    let point = *point;
                    let u = match full_resolution(&scene, point) {
                        Some(cell) => interpolated(&mut recent, &mut last, &scene, cell, point)?,
                        None => None,
                    };
                    Ok((*index, u.unwrap_or(f32::NAN)))
                })
                .collect::<Result<Vec<_>>>()
        })
        .collect::<Result<_>>()?;
    for (index, u) in found.into_iter().flatten() {
        if let Some(slot) = values.get_mut(index) {
            *slot = u;
        }
    }
    Ok(values)
}

impl IndicatorField for Snapshot<'_> {
    fn finest_level(&self) -> Option<u8> {
        (0..=MAX_DEPTH)
            .rev()
            .find(|&l| !self.segments(LEVEL_STAGES[usize::from(l)]).is_empty())
    }

    fn method(&self) -> Result<Option<&'static str>> {
        let Some(level) = self.finest_level() else {
            return Ok(None);
        };
        match self.segments(LEVEL_STAGES[usize::from(level)]).first() {
            Some((name, _)) => Ok(Some(method_of_segment(self, name)?)),
            None => Ok(None),
        }
    }

    fn levels(&self) -> Vec<u8> {
        (0..=MAX_DEPTH)
            .filter(|&l| !self.segments(LEVEL_STAGES[usize::from(l)]).is_empty())
            .collect()
    }

    fn leaves(&self) -> Result<Vec<LeafInfo>> {
        let scene = scene_of(self)?;
        let treetop = Treetop::of(self)?;
        Ok(treetop
            .units
            .iter()
            .filter(|unit| !unit.top)
            .map(|unit| {
                let size = scene.cube_side(unit.key.depth());
                LeafInfo {
                    key: format!("{:?}", unit.key),
                    depth: unit.key.depth(),
                    min: (scene.cube_center(unit.key) - DVec3::splat(size * 0.5)).to_array(),
                    size,
                    cubes: unit.record.rows,
                }
            })
            .collect())
    }

    fn indicator_at(&self, point: DVec3) -> Result<Option<f32>> {
        let Some((scene, level, cell)) = finest_cell_at(self, point)? else {
            return Ok(None);
        };
        let treetop = Treetop::of(self)?;
        let mut lookup = LevelCut::new(self, &treetop, level);
        interpolated(&mut RecentCubes::new(&mut lookup), &mut None, &scene, cell, point)
    }

    fn seen_at(&self, point: DVec3) -> Result<Option<bool>> {
        let Some((_, level, cell)) = finest_cell_at(self, point)? else {
            return Ok(None);
        };
        let treetop = Treetop::of(self)?;
        let mut lookup = LevelCut::new(self, &treetop, level);
        Ok(lookup.cube_at(cell.map(|c| c as u32))?.map(|(_, value)| value.seen()))
    }

    fn cubes_in(&self, bbox: &BoundingBox, level: u8) -> Result<Vec<CubeInfo>> {
        ensure_solution_is_current(self)?;
        let scene = scene_of(self)?;
        let treetop = Treetop::of(self)?;
        let mut level_cut = LevelCut::new(self, &treetop, level);
        let mut out = Vec::new();
        for (index, unit) in treetop.units.iter().enumerate() {
            if !unit.top {
                let side = scene.cube_side(unit.key.depth());
                let lo = scene.cube_center(unit.key) - DVec3::splat(side * 0.5);
                if lo.cmpgt(bbox.max).any() || (lo + DVec3::splat(side)).cmplt(bbox.min).any() {
                    continue;
                }
            }
            let Some(values) = level_cut.unit(index)? else {
                continue;
            };
            let hist_segment = self
                .segments(HISTOGRAMS)
                .iter()
                .find(|(_, r)| r.first_key == unit.record.first_key)
                .map(|(n, _)| n.clone());
            let (hist_keys, hist) = match hist_segment {
                Some(n) => {
                    let file = self.open_segment(&n)?;
                    let reader = file.reader()?;
                    let keys = reader.read_keys().map_err(|e| file.corruption(e))?;
                    let (_, h) = reader.read_f32("hist").map_err(|e| file.corruption(e))?;
                    (keys, h)
                }
                None => (Vec::new(), Vec::new()),
            };
            for (key, value) in values.0.iter().zip(&values.1) {
                let center = scene.cube_center(*key);
                let half = scene.cube_side(key.depth()) * 0.5;
                if (center + DVec3::splat(half)).cmplt(bbox.min).any()
                    || (center - DVec3::splat(half)).cmpgt(bbox.max).any()
                {
                    continue;
                }
                let histogram = hist_keys
                    .binary_search(key)
                    .ok()
                    .map(|i| std::array::from_fn(|b| hist.get(i * BINS + b).copied().unwrap_or(0.0)))
                    .unwrap_or([0.0; BINS]);
                out.push(CubeInfo {
                    key: format!("{key:?}"),
                    depth: key.depth(),
                    center: center.to_array(),
                    size: 2.0 * half,
                    u: value.u,
                    seen: value.seen(),
                    sampled: value.sampled,
                    offset: (!value.offset.is_nan()).then_some(value.offset),
                    histogram,
                });
            }
        }
        Ok(out)
    }
}
