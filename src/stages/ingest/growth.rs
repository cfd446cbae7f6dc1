//! A root that grows: when new depth maps see beyond the store's root cube, the ingest doubles
//! the root (format-spec.md, "Growing the root") and re-keys every earlier ingest run in the
//! same version, one run per unit, so a killed ingest resumes like any other.
//!
//! Invariants: cube sides never change (each doubling adds one level: `Scene::doubled`,
//! `CubeKey::in_doubled_root`); re-keying preserves key order, so a run stays sorted; a root
//! given with `--root` at the first ingest is fixed and never grows; the scene an older version
//! was keyed in stays readable (`scene_until/` entries), so pinned readers of it see their own
//! geometry.

use glam::DVec3;
use rayon::prelude::*;
use redb::ReadableTable;

use super::{DepthMedian, bounds_of, robust_bounds};
use crate::format::{Column, ColumnValues, META_SCENE, Scene};
use crate::inputs::DepthMapSource;
use crate::store::StageError;
use crate::store::catalog::{self, META};
use crate::store::{Result, SegmentFile, Store, StoreError};

/// Meta key present (value `[1]`) when the first ingest was given its root (`--root`): such
/// a root never grows.
pub const META_ROOT_FIXED: &str = "root_fixed";

/// Meta key prefix: `scene_until/{v:020}` -> bincode [`Scene`] that versions before `v` were
/// keyed in (written by an ingest that grew the root into version `v`).
pub const META_SCENE_UNTIL_PREFIX: &str = "scene_until/";

/// The most doublings one ingest may apply (a root 65,536 times wider). Depth maps that would
/// need more see something absurdly far away, and are refused.
pub const MAX_DOUBLINGS_PER_INGEST: usize = 16;

/// Margin of the grown root around the new maps' samples, as a fraction of their largest
/// extent (what the first ingest leaves by default).
pub const GROWTH_MARGIN: f64 = 0.1;

pub fn scene_until_key(version: u64) -> String {
    format!("{META_SCENE_UNTIL_PREFIX}{version:020}")
}

/// The scene version `version` was keyed in: the oldest `scene_until/` entry after it, else the
/// store's current scene. `None` before the first ingest.
pub fn scene_at(store: &Store, version: u64) -> Result<Option<Scene>> {
    let txn = store.catalog().begin_read()?;
    let meta = txn.open_table(META)?;
    let from = scene_until_key(version.saturating_add(1));
    if let Some(entry) = meta.range(from.as_bytes()..)?.next() {
        let (key, value) = entry?;
        if key.value().starts_with(META_SCENE_UNTIL_PREFIX.as_bytes()) {
            return Ok(Some(catalog::unseal_decode("meta", key.value(), value.value())?));
        }
    }
    match meta.get(META_SCENE.as_bytes())? {
        Some(v) => Ok(Some(catalog::unseal_decode("meta", META_SCENE, v.value())?)),
        None => Ok(None),
    }
}

/// Whether the store's root was given at its first ingest, and so never grows.
pub fn root_is_fixed(store: &Store) -> Result<bool> {
    let txn = store.catalog().begin_read()?;
    let meta = txn.open_table(META)?;
    Ok(meta.get(META_ROOT_FIXED.as_bytes())?.is_some())
}

/// The doublings that let `scene` hold every new map's samples: the union of each map's robust
/// box (0.1 % to 99.9 % per axis, spikes left out, as the first ingest sizes its root), so a
/// map that sees a far corner is not trimmed away by the others. `medians` are the maps'
/// median depths, which their surveys measured.
pub fn growth_for(
    scene: &Scene,
    maps: &[(u64, DepthMapSource)],
    medians: &[DepthMedian],
    map_memory: u64,
) -> Result<Vec<[u32; 3]>> {
    let boxes: Vec<Option<(DVec3, DVec3)>> = maps
        .par_iter()
        .zip(medians)
        .map(|((_, source), median)| {
            let sample = bounds_of(source, map_memory, 20_000, *median)?;
            Ok(robust_bounds(&sample))
        })
        .collect::<Result<_>>()?;
    let Some((lo, hi)) = boxes
        .iter()
        .flatten()
        .copied()
        .reduce(|(lo, hi), (l, h)| (lo.min(l), hi.max(h)))
    else {
        return Ok(Vec::new());
    };
    if let Some(octants) = scene.growth_to_hold(lo, hi, GROWTH_MARGIN, MAX_DOUBLINGS_PER_INGEST) {
        return Ok(octants);
    }
    // Name the map that reaches farthest beyond the root.
    let beyond = |(l, h): (DVec3, DVec3)| {
        let max = scene.min() + DVec3::splat(scene.root_side);
        (scene.min() - l).max(h - max).max_element()
    };
    let farthest = maps
        .iter()
        .zip(&boxes)
        .filter_map(|((_, source), b)| b.map(|b| (source, b)))
        .max_by(|a, b| beyond(a.1).total_cmp(&beyond(b.1)));
    let (unit, (l, h)) = match farthest {
        Some((source, b)) => (source.path.display().to_string(), b),
        None => ("new depth maps".to_string(), (lo, hi)),
    };
    Err(StoreError::Stage {
        stage: super::INGEST.into(),
        unit,
        error: Box::new(StageError::BeyondRoot {
            low: l.to_array(),
            high: h.to_array(),
            root_min: scene.root_min,
            root_side: scene.root_side,
            doublings: MAX_DOUBLINGS_PER_INGEST,
        }),
    })
}

/// An ingest run's columns re-keyed into a root grown by `octants` (in order): keys move one
/// level deeper per doubling, radius sums (fixed point relative to the root's radius,
/// `Scene::quantize_radius`) halve with rounding, every other column is copied as it is (the
/// sample moments are relative to their own cube, whose side does not change).
pub fn rekeyed_run(run: &SegmentFile, octants: &[[u32; 3]]) -> Result<Vec<Column>> {
    let reader = run.reader()?;
    let mut columns = Vec::with_capacity(reader.columns().len());
    for info in reader.columns() {
        let mut column = reader.read_column(&info.name).map_err(|e| run.corruption(e))?;
        match &mut column.values {
            ColumnValues::Key(keys) => {
                for key in keys.iter_mut() {
                    for octant in octants {
                        *key = key.in_doubled_root(*octant).ok_or_else(|| StoreError::Stage {
                            stage: super::INGEST.into(),
                            unit: run.path().display().to_string(),
                            error: Box::new(StageError::RootAtDepthLimit),
                        })?;
                    }
                }
            }
            ColumnValues::U64(sums) if info.name == RADIUS_SUM => {
                for sum in sums.iter_mut() {
                    for _ in octants {
                        *sum = sum.div_ceil(2);
                    }
                }
            }
            _ => {}
        }
        columns.push(column);
    }
    Ok(columns)
}

/// The column of ingest runs and octree segments holding per-cube fixed-point radius sums.
pub const RADIUS_SUM: &str = "radius_sum";
