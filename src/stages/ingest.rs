//! `ingest`: registers depth maps and writes one sorted run of cubes per depth map (paper 4.1).
//!
//! One ingest is one version; it is committed unit by unit (a unit is one depth map), so a
//! killed ingest resumes. Depth maps are identified by a hash of their content (pixels, pose,
//! intrinsics, kind, weight), which makes the input order irrelevant and a repeated ingest of
//! the same files a no-op.

use std::collections::BTreeSet;

use glam::DVec3;
use rayon::prelude::*;
use redb::{ReadableTable, WriteTransaction};
use serde::{Deserialize, Serialize};
use xxhash_rust::xxh3::Xxh3;

use super::INGEST;
use super::depthmap::{DepthImage, DepthMapSource, InputError};
use super::scene::{META_SCENE, Scene};
use crate::format::{Column, ColumnValues, CubeKey};
use crate::store::catalog::{self, META, UnitRecord};
use crate::store::{Plan, Replace, Result, Snapshot, Stage, Store, StoreError, UnitOutput, UnitSpec};

pub use crate::store::catalog::DEPTH_MAPS;

/// Block size of ingest runs: small, so that merging many runs at once stays within memory.
pub const RUN_BLOCK_ROWS: u32 = 1024;

/// A depth is absurd when it exceeds this multiple of the map's median depth.
const ABSURD_DEPTH_FACTOR: f32 = 1.0e4;

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct DepthMapRecord {
    pub source: DepthMapSource,
    pub stats: SampleStats,
    /// The version whose ingest added it.
    pub added_in: u64,
}

#[derive(Serialize, Deserialize, Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct SampleStats {
    pub pixels: u64,
    pub samples: u64,
    pub cubes: u64,
    /// Zero, NaN, infinite or negative depths.
    pub invalid: u64,
    /// Depths beyond ABSURD_DEPTH_FACTOR times the median.
    pub absurd: u64,
    /// Valid pixels without a valid 4-neighbour: no radius can be estimated.
    pub isolated: u64,
    /// Samples outside the root cube (stray outliers; more than 1% is an error).
    pub outside: u64,
}

impl SampleStats {
    fn add(&mut self, o: &SampleStats) {
        self.pixels += o.pixels;
        self.samples += o.samples;
        self.cubes += o.cubes;
        self.invalid += o.invalid;
        self.absurd += o.absurd;
        self.isolated += o.isolated;
        self.outside += o.outside;
    }
}

/// Back-projected samples of one depth map: world positions and radii r_x (paper 4.1: half
/// the 3D distance to the neighbouring samples; the nearest valid 4-neighbour here, which is
/// robust at depth discontinuities).
pub struct Samples {
    pub points: Vec<DVec3>,
    pub radii: Vec<f64>,
    pub stats: SampleStats,
}

pub fn back_project(source: &DepthMapSource, image: &DepthImage) -> Samples {
    let (w, h) = (image.width as usize, image.height as usize);
    let mut stats = SampleStats {
        pixels: (w * h) as u64,
        ..SampleStats::default()
    };
    let mut valid: Vec<f32> = image
        .depth
        .iter()
        .copied()
        .filter(|d| d.is_finite() && *d > 0.0)
        .collect();
    stats.invalid = stats.pixels - valid.len() as u64;
    let median = if valid.is_empty() {
        0.0
    } else {
        let mid = valid.len() / 2;
        *valid.select_nth_unstable_by(mid, f32::total_cmp).1
    };
    let limit = median * ABSURD_DEPTH_FACTOR;
    let pose = source.pose();
    let camera: Vec<Option<DVec3>> = (0..w * h)
        .map(|index| {
            let d = image.depth.get(index).copied().unwrap_or(f32::NAN);
            if !(d.is_finite() && d > 0.0) || d > limit {
                return None;
            }
            let (i, j) = ((index % w) as f64, (index / w) as f64);
            Some(source.ray(i, j) * f64::from(d))
        })
        .collect();
    stats.absurd = image
        .depth
        .iter()
        .filter(|d| d.is_finite() && **d > 0.0 && **d > limit)
        .count() as u64;
    let wraps = matches!(source.projection, super::depthmap::Projection::Spherical);
    let mut points = Vec::with_capacity(valid.len());
    let mut radii = Vec::with_capacity(valid.len());
    for j in 0..h {
        for i in 0..w {
            let Some(p) = camera[j * w + i] else { continue };
            let mut nearest = f64::INFINITY;
            let neighbours = [
                (i.checked_sub(1).or(if wraps { Some(w - 1) } else { None }), Some(j)),
                (
                    if i + 1 < w {
                        Some(i + 1)
                    } else if wraps {
                        Some(0)
                    } else {
                        None
                    },
                    Some(j),
                ),
                (Some(i), j.checked_sub(1)),
                (Some(i), if j + 1 < h { Some(j + 1) } else { None }),
            ];
            for (ni, nj) in neighbours {
                if let (Some(ni), Some(nj)) = (ni, nj)
                    && let Some(q) = camera[nj * w + ni]
                {
                    nearest = nearest.min((q - p).length());
                }
            }
            if !nearest.is_finite() || nearest <= 0.0 {
                stats.isolated += 1;
                continue;
            }
            points.push(pose.transform_point3(p));
            radii.push(nearest * 0.5);
        }
    }
    stats.samples = points.len() as u64;
    Samples { points, radii, stats }
}

/// Content id of a depth map: xxh3 of its file bytes and its registration (path excluded).
/// The file is streamed: a LIDAR file can be far larger than the memory budget.
pub fn depth_map_id(source: &DepthMapSource) -> std::result::Result<u64, InputError> {
    use std::io::Read;
    let io = |e| InputError::Io {
        file: source.path.clone(),
        source: e,
    };
    let mut file = std::fs::File::open(&source.path).map_err(io)?;
    let mut hasher = Xxh3::new();
    let mut buffer = vec![0u8; 1 << 20];
    loop {
        let n = file.read(&mut buffer).map_err(io)?;
        if n == 0 {
            break;
        }
        hasher.update(buffer.get(..n).unwrap_or_default());
    }
    let mut without_path = source.clone();
    without_path.path = Default::default();
    hasher.update(&catalog::encode(&without_path));
    Ok(hasher.digest())
}

#[derive(Clone, Debug)]
pub struct IngestOptions {
    /// The root cube as (min corner, side); computed from the first ingest's samples if absent.
    pub root: Option<([f64; 3], f64)>,
    /// Margin around the first ingest's bounding box, as a fraction of its largest extent.
    pub root_margin: f64,
    pub max_depth: u8,
}

impl Default for IngestOptions {
    fn default() -> Self {
        IngestOptions {
            root: None,
            root_margin: 0.1,
            max_depth: 24,
        }
    }
}

pub struct IngestStage {
    scene: Scene,
    scene_is_new: bool,
    /// New depth maps, ordered by id.
    maps: Vec<(u64, DepthMapSource)>,
}

fn input_error(e: InputError) -> StoreError {
    let unit = match &e {
        InputError::Bad { file, .. } | InputError::Io { file, .. } => file.display().to_string(),
    };
    StoreError::Stage {
        stage: INGEST.into(),
        unit,
        message: e.to_string(),
    }
}

pub fn read_scene(store: &Store) -> Result<Option<Scene>> {
    let txn = store.catalog().begin_read()?;
    let meta = txn.open_table(META)?;
    match meta.get(META_SCENE)? {
        Some(v) => Ok(Some(catalog::decode("meta", v.value())?)),
        None => Ok(None),
    }
}

/// All registered depth maps, by id.
pub fn registered_depth_maps(store: &Store) -> Result<Vec<(u64, DepthMapRecord)>> {
    let txn = store.catalog().begin_read()?;
    let table = match txn.open_table(DEPTH_MAPS) {
        Ok(t) => t,
        Err(redb::TableError::TableDoesNotExist(_)) => return Ok(Vec::new()),
        Err(e) => return Err(e.into()),
    };
    table
        .iter()?
        .map(|e| {
            let (k, v) = e?;
            Ok((k.value(), catalog::decode("depth_maps", v.value())?))
        })
        .collect()
}

impl IngestStage {
    /// Identifies the new depth maps and fixes the scene (the root cube) if the store has none.
    pub fn prepare(store: &Store, sources: Vec<DepthMapSource>, options: &IngestOptions) -> Result<IngestStage> {
        let known: BTreeSet<u64> = registered_depth_maps(store)?.into_iter().map(|(id, _)| id).collect();
        let ids: Vec<u64> = sources
            .par_iter()
            .map(depth_map_id)
            .collect::<std::result::Result<_, _>>()
            .map_err(input_error)?;
        let mut maps: Vec<(u64, DepthMapSource)> = ids
            .into_iter()
            .zip(sources)
            .filter(|(id, _)| !known.contains(id))
            .collect();
        maps.sort_by_key(|(id, _)| *id);
        maps.dedup_by_key(|(id, _)| *id);

        let (scene, scene_is_new) = match read_scene(store)? {
            Some(scene) => (scene, false),
            None => {
                let scene = match options.root {
                    Some((min, side)) => Scene {
                        root_min: min,
                        root_side: side,
                        max_depth: options.max_depth,
                    },
                    None => {
                        // A robust box: per axis, the 0.1% and 99.9% quantiles of a sample of
                        // every map's points, so that stray outliers do not inflate the root.
                        let per_map: Vec<Vec<DVec3>> = maps
                            .par_iter()
                            .map(|(_, source)| {
                                let image = source.load().map_err(input_error)?;
                                let samples = back_project(source, &image);
                                // At most ~200,000 points in total, whatever the number of maps.
                                let per_map = (200_000 / maps.len().max(1)).max(64);
                                let step = (samples.points.len() / per_map).max(1);
                                Ok(samples.points.iter().step_by(step).copied().collect())
                            })
                            .collect::<Result<_>>()?;
                        let points: Vec<DVec3> = per_map.into_iter().flatten().collect();
                        if points.is_empty() {
                            return Err(StoreError::Stage {
                                stage: INGEST.into(),
                                unit: "all depth maps".into(),
                                message: "no valid depth samples: nothing to build a scene from".into(),
                            });
                        }
                        let quantile = |axis: usize, q: f64| -> f64 {
                            let mut v: Vec<f64> = points.iter().map(|p| p[axis]).collect();
                            v.sort_by(f64::total_cmp);
                            v[((v.len() - 1) as f64 * q).round() as usize]
                        };
                        let lo = DVec3::new(quantile(0, 0.001), quantile(1, 0.001), quantile(2, 0.001));
                        let hi = DVec3::new(quantile(0, 0.999), quantile(1, 0.999), quantile(2, 0.999));
                        Scene::around(lo, hi, options.root_margin, options.max_depth)
                    }
                };
                (scene, true)
            }
        };
        Ok(IngestStage {
            scene,
            scene_is_new,
            maps,
        })
    }

    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    pub fn new_depth_maps(&self) -> usize {
        self.maps.len()
    }

    /// Cubes of one depth map, merged by key: (keys, radius sums, counts).
    pub fn cubes(&self, source: &DepthMapSource) -> std::result::Result<(Vec<Column>, SampleStats), InputError> {
        let image = source.load()?;
        let samples = back_project(source, &image);
        let mut stats = samples.stats;
        let mut entries: Vec<(CubeKey, u64)> = Vec::with_capacity(samples.points.len());
        for (p, r) in samples.points.iter().zip(&samples.radii) {
            if !self.scene.contains(*p) {
                stats.outside += 1;
                continue;
            }
            let depth = self.scene.depth_for_radius(*r);
            entries.push((self.scene.key_at(*p, depth), self.scene.quantize_radius(*r)));
        }
        if stats.outside * 100 > stats.samples.max(1) {
            return Err(super::depthmap::bad(
                &source.path,
                format!(
                    "{} of {} samples lie outside the store's root cube (min {:?}, side {}); create a new store whose first ingest includes this depth map, or give --root / a larger --root-margin",
                    stats.outside, stats.samples, self.scene.root_min, self.scene.root_side
                ),
            ));
        }
        entries.sort_unstable();
        let mut keys: Vec<CubeKey> = Vec::new();
        let mut sums: Vec<u64> = Vec::new();
        let mut counts: Vec<u32> = Vec::new();
        for (key, r) in entries {
            if keys.last() == Some(&key) {
                if let (Some(s), Some(c)) = (sums.last_mut(), counts.last_mut()) {
                    *s += r;
                    *c += 1;
                }
            } else {
                keys.push(key);
                sums.push(r);
                counts.push(1);
            }
        }
        stats.cubes = keys.len() as u64;
        Ok((
            vec![
                Column::keys(keys),
                Column::new("radius_sum", 1, ColumnValues::U64(sums)),
                Column::new("radius_count", 1, ColumnValues::U32(counts)),
            ],
            stats,
        ))
    }
}

#[derive(Serialize, Deserialize)]
struct IngestUnitExtra {
    id: u64,
    stats: SampleStats,
}

impl Stage for IngestStage {
    fn name(&self) -> &'static str {
        INGEST
    }

    fn params(&self) -> Vec<u8> {
        let ids: Vec<u64> = self.maps.iter().map(|(id, _)| *id).collect();
        catalog::encode(&(ids, self.scene))
    }

    fn plan(&self, _base: &Snapshot<'_>) -> Result<Plan> {
        Ok(Plan {
            units: self
                .maps
                .iter()
                .enumerate()
                .map(|(index, (_, source))| UnitSpec {
                    id: index as u64,
                    label: source.path.display().to_string(),
                })
                .collect(),
            replace: Replace::Nothing,
        })
    }

    fn run_unit(&self, _base: &Snapshot<'_>, unit: &UnitSpec) -> Result<UnitOutput> {
        let (id, source) = self.maps.get(unit.id as usize).ok_or_else(|| StoreError::Stage {
            stage: INGEST.into(),
            unit: unit.label.clone(),
            message: "unit out of range".into(),
        })?;
        let (columns, stats) = self.cubes(source).map_err(input_error)?;
        let extra = catalog::encode(&IngestUnitExtra { id: *id, stats });
        if stats.cubes == 0 {
            return Ok(UnitOutput {
                segments: Vec::new(),
                extra,
                block_rows: RUN_BLOCK_ROWS,
            });
        }
        Ok(UnitOutput {
            segments: vec![columns],
            extra,
            block_rows: RUN_BLOCK_ROWS,
        })
    }

    fn finish(&self, txn: &WriteTransaction, base: &Snapshot<'_>, units: &[(u64, UnitRecord)]) -> Result<String> {
        let mut table = txn.open_table(DEPTH_MAPS)?;
        let mut total = SampleStats::default();
        for (_, record) in units {
            let extra: IngestUnitExtra = catalog::decode("units_done", &record.extra)?;
            let source = self
                .maps
                .iter()
                .find(|(id, _)| *id == extra.id)
                .map(|(_, s)| s.clone())
                .ok_or_else(|| StoreError::CatalogCorruption {
                    table: "units_done",
                    reason: format!("depth map {:016x} is not part of this ingest", extra.id),
                })?;
            total.add(&extra.stats);
            let record = DepthMapRecord {
                source,
                stats: extra.stats,
                added_in: base.version() + 1,
            };
            table.insert(extra.id, catalog::encode(&record).as_slice())?;
        }
        if self.scene_is_new {
            txn.open_table(META)?
                .insert(META_SCENE, catalog::encode(&self.scene).as_slice())?;
        }
        Ok(format!(
            "{} depth map(s): {} samples, {} cubes; skipped {} invalid, {} absurd, {} isolated of {} pixels, {} outside the root",
            units.len(),
            total.samples,
            total.cubes,
            total.invalid,
            total.absurd,
            total.isolated,
            total.pixels,
            total.outside
        ))
    }
}
