//! `ingest`: registers depth maps and writes one sorted run of cubes per depth map (paper 4.1).
//!
//! One ingest is one version; it is committed unit by unit (a unit is one depth map), so a
//! killed ingest resumes. Depth maps are identified by a hash of their content (pixels, pose,
//! intrinsics, kind, weight), which makes the input order irrelevant and a repeated ingest of
//! the same files a no-op. Depth maps that see beyond the root grow it (`growth.rs`): the
//! ingest then also re-keys every earlier run, one unit per run, in the same version.

use std::collections::BTreeSet;

use glam::DVec3;
use rayon::prelude::*;
use redb::{ReadableTable, WriteTransaction};
use serde::{Deserialize, Serialize};
use xxhash_rust::xxh3::Xxh3;

mod growth;

pub use growth::{
    GROWTH_MARGIN, MAX_DOUBLINGS_PER_INGEST, META_ROOT_FIXED, META_SCENE_UNTIL_PREFIX, RADIUS_SUM, root_is_fixed,
    scene_at, scene_until_key,
};

use super::INGEST;
use super::samples::{Moments, moment_columns};
use crate::format::{Column, ColumnValues, CubeKey, META_SCENE, Scene};
use crate::inputs::{DepthImage, DepthMapSource, DepthNoise, InputError, Projection};
use crate::store::catalog::{self, META, UnitRecord};
use crate::store::{Plan, Replace, Result, Snapshot, Stage, Store, StoreError, UnitOutput, UnitSpec};

pub use crate::store::catalog::DEPTH_MAPS;

/// Block size of ingest runs: small, so that merging many runs at once stays within memory.
pub const RUN_BLOCK_ROWS: u32 = 1024;

/// The column of ingest runs and octree segments that counts, per cube, the spikes among the
/// samples that spawned it (format-spec.md, "Columns used by stages").
pub const SPIKE_COUNT: &str = "spike_count";

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
    /// Samples outside the root cube (stray outliers; more than 1% that are not spikes is an
    /// error).
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
/// robust at depth discontinuities), widened by the map's noise model (`DepthNoise::radius`).
pub struct Samples {
    pub points: Vec<DVec3>,
    pub radii: Vec<f64>,
    /// Whether each sample is a spike: fewer than two of its 4-neighbours lie within
    /// `SPIKE_SPACING` pixel footprints.
    pub spikes: Vec<bool>,
    /// World-frame unit normals from the local depth gradient, oriented towards the camera;
    /// zero where no neighbour on one of the axes is valid.
    pub normals: Vec<DVec3>,
    /// The surface area each sample stands for: the squared distance to its nearest valid
    /// 4-neighbour (world units).
    pub areas: Vec<f64>,
    pub stats: SampleStats,
}

pub fn back_project(source: &DepthMapSource, image: &DepthImage) -> Samples {
    let grid = CameraGrid::new(source, image);
    let mut stats = grid.stats;
    let pose = source.pose();
    let pixel_angle = source.pixel_angle();
    // Sized for every pixel up front: grown by doubling, the three columns were copied about
    // twice over and their fresh pages faulted in again (a sixth of ingest's time).
    let valid = grid.points.iter().filter(|p| p.is_some()).count();
    let mut points = Vec::with_capacity(valid);
    let mut radii = Vec::with_capacity(valid);
    let mut spikes = Vec::with_capacity(valid);
    let mut normals = Vec::with_capacity(valid);
    let mut areas = Vec::with_capacity(valid);
    let rotation = glam::DMat3::from_mat4(pose);
    for j in 0..grid.height {
        for i in 0..grid.width {
            let Some(p) = grid.at(i, j) else { continue };
            let reach = SPIKE_SPACING * pixel_angle * p.length();
            let (mut nearest, mut close) = (f64::INFINITY, 0);
            for q in grid.neighbours(i, j) {
                let distance = (q - p).length();
                nearest = nearest.min(distance);
                close += usize::from(distance <= reach);
            }
            if !nearest.is_finite() || nearest <= 0.0 {
                stats.isolated += 1;
                continue;
            }
            let depth = match source.projection {
                Projection::Pinhole { .. } => p.z,
                Projection::Spherical => p.length(),
            };
            points.push(pose.transform_point3(p));
            radii.push(source.noise.radius(nearest * 0.5, depth));
            spikes.push(close < 2);
            normals.push(
                grid.normal(i, j, p)
                    .map_or(DVec3::ZERO, |n| (rotation * n).normalize_or_zero()),
            );
            areas.push(nearest * nearest);
        }
    }
    stats.samples = points.len() as u64;
    Samples {
        points,
        radii,
        spikes,
        normals,
        areas,
        stats,
    }
}

/// A depth map's valid pixels as camera-frame points, with their 4-neighbourhoods (wrapping
/// around horizontally for spherical maps).
struct CameraGrid {
    width: usize,
    height: usize,
    wraps: bool,
    points: Vec<Option<DVec3>>,
    stats: SampleStats,
}

impl CameraGrid {
    fn new(source: &DepthMapSource, image: &DepthImage) -> CameraGrid {
        let (width, height) = (image.width as usize, image.height as usize);
        let mut stats = SampleStats {
            pixels: (width * height) as u64,
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
        let points = (0..width * height)
            .map(|index| {
                let d = image.depth.get(index).copied().unwrap_or(f32::NAN);
                if !(d.is_finite() && d > 0.0) || d > limit {
                    return None;
                }
                let (i, j) = ((index % width) as f64, (index / width) as f64);
                Some(source.ray(i, j) * f64::from(d))
            })
            .collect();
        stats.absurd = image
            .depth
            .iter()
            .filter(|d| d.is_finite() && **d > 0.0 && **d > limit)
            .count() as u64;
        CameraGrid {
            width,
            height,
            wraps: matches!(source.projection, crate::inputs::Projection::Spherical),
            points,
            stats,
        }
    }

    fn at(&self, i: usize, j: usize) -> Option<DVec3> {
        self.points.get(j * self.width + i).copied().flatten()
    }

    /// The valid ones among the left, right, upper and lower neighbours of pixel (i, j).
    fn neighbours(&self, i: usize, j: usize) -> impl Iterator<Item = DVec3> + '_ {
        self.neighbour_pixels(i, j)
            .into_iter()
            .filter_map(|(ni, nj)| self.at(ni?, nj?))
    }

    /// The camera-frame normal at pixel (i, j), whose point is `p`: the cross product of the
    /// depth gradient along the rows and along the columns, each taken towards the neighbour
    /// nearer to `p` (a difference across a depth edge would tilt it), oriented towards the
    /// camera. `None` when an axis has no valid neighbour.
    fn normal(&self, i: usize, j: usize, p: DVec3) -> Option<DVec3> {
        let [left, right, up, down] = self.neighbour_pixels(i, j).map(|(ni, nj)| self.at(ni?, nj?));
        let along = |before: Option<DVec3>, after: Option<DVec3>| match (before, after) {
            (Some(b), Some(a)) if (a - p).length() <= (p - b).length() => Some(a - p),
            (Some(b), _) => Some(p - b),
            (None, Some(a)) => Some(a - p),
            (None, None) => None,
        };
        let n = along(left, right)?.cross(along(up, down)?).normalize_or_zero();
        if n == DVec3::ZERO {
            return None;
        }
        Some(if n.dot(p) > 0.0 { -n } else { n })
    }

    /// Left, right, upper and lower neighbours of pixel (i, j), wrapping around horizontally
    /// for spherical maps; a `None` coordinate lies outside the image.
    fn neighbour_pixels(&self, i: usize, j: usize) -> [(Option<usize>, Option<usize>); 4] {
        let left = i
            .checked_sub(1)
            .or(if self.wraps { self.width.checked_sub(1) } else { None });
        let right = if i + 1 < self.width {
            Some(i + 1)
        } else if self.wraps {
            Some(0)
        } else {
            None
        };
        let up = j.checked_sub(1);
        let down = if j + 1 < self.height { Some(j + 1) } else { None };
        [(left, Some(j)), (right, Some(j)), (Some(i), up), (Some(i), down)]
    }
}

/// A sample with fewer than two 4-neighbours within this many pixel footprints is a spike (an
/// isolated wrong depth, or a pair of them). Surfaces seen at up to about 80 degrees from
/// head-on keep their neighbours within it; random outlier depths almost never have two.
/// Spikes do not size the root, and spikes outside the root are dropped without complaint.
const SPIKE_SPACING: f64 = 8.0;

/// Up to about `count` of a map's samples, evenly strided, for sizing the root cube. Spikes
/// are left out: a few percent of wild depths would otherwise stretch the root far beyond the
/// scene and cost every cube resolution (with `--max-depth` fixed, the finest cube grows with
/// the root). Spikes still spawn cubes and vote like any other sample inside the root.
pub fn bounds_sample(samples: &Samples, count: usize) -> Vec<DVec3> {
    let consistent: Vec<DVec3> = samples
        .points
        .iter()
        .zip(&samples.spikes)
        .filter(|(_, spike)| !**spike)
        .map(|(p, _)| *p)
        .collect();
    // A map of nothing but spikes (pure noise) still bounds the scene through all its samples.
    let chosen = if consistent.is_empty() {
        samples.points.clone()
    } else {
        consistent
    };
    let step = (chosen.len() / count.max(1)).max(1);
    chosen.into_iter().step_by(step).collect()
}

/// A box robust to stray points: per axis, the 0.1 % and 99.9 % quantiles. None without points.
pub fn robust_bounds(points: &[DVec3]) -> Option<(DVec3, DVec3)> {
    if points.is_empty() {
        return None;
    }
    let quantile = |axis: usize, q: f64| -> f64 {
        let mut v: Vec<f64> = points.iter().map(|p| p[axis]).collect();
        v.sort_by(f64::total_cmp);
        let index = ((v.len() - 1) as f64 * q).round() as usize;
        v.get(index).copied().unwrap_or(0.0)
    };
    let lo = DVec3::new(quantile(0, 0.001), quantile(1, 0.001), quantile(2, 0.001));
    let hi = DVec3::new(quantile(0, 0.999), quantile(1, 0.999), quantile(2, 0.999));
    Some((lo, hi))
}

/// Content id of a depth map: xxh3 of its file bytes and its registration (path excluded).
/// The file is streamed: a LIDAR file can be far larger than the memory budget.
/// What of a registration makes a depth map's identity: every field of its source but the path
/// and the noise model, in the order (and so the bytes) of the source's encoding before
/// catalog version 3, so ids stay what they were.
fn identity(
    source: &DepthMapSource,
) -> (
    &str,
    &crate::inputs::ImageFormat,
    u32,
    u32,
    &Projection,
    &[f64; 16],
    &crate::inputs::Kind,
    f32,
) {
    (
        "",
        &source.format,
        source.width,
        source.height,
        &source.projection,
        &source.camera_to_world,
        &source.kind,
        source.weight,
    )
}

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
    hasher.update(&catalog::encode(&identity(source)));
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
    /// The scene the new maps are keyed in (grown, if they needed it).
    scene: Scene,
    scene_is_new: bool,
    /// Given with `--root` at the first ingest: recorded so that the root never grows.
    root_is_fixed: bool,
    /// The store's scene before this ingest and the doublings (octants) that grew it into
    /// `scene`; `None` when the root did not grow.
    growth: Option<(Scene, Vec<[u32; 3]>)>,
    /// New depth maps, ordered by id.
    maps: Vec<(u64, DepthMapSource)>,
}

/// The error as the stage's, with the file as its unit (named once).
fn input_error(e: InputError) -> StoreError {
    let (unit, message) = match &e {
        InputError::Bad { file, problem } => (file.display().to_string(), problem.clone()),
        InputError::Io { file, source } => (file.display().to_string(), source.to_string()),
    };
    StoreError::Stage {
        stage: INGEST.into(),
        unit,
        message,
    }
}

pub fn read_scene(store: &Store) -> Result<Option<Scene>> {
    let txn = store.catalog().begin_read()?;
    let meta = txn.open_table(META)?;
    match meta.get(META_SCENE)? {
        Some(v) => Ok(Some(catalog::unseal_decode("meta", META_SCENE, v.value())?)),
        None => Ok(None),
    }
}

/// All registered depth maps, by id.
pub fn registered_depth_maps(store: &Store) -> Result<Vec<(u64, DepthMapRecord)>> {
    let version = store.catalog_format_version()?;
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
            let record = if version < 3 {
                catalog::decode("depth_maps", &catalog::depth_map_record_v2_to_v3(v.value())?)?
            } else {
                catalog::unseal_decode("depth_maps", &k.value(), v.value())?
            };
            Ok((k.value(), record))
        })
        .collect()
}

impl IngestStage {
    /// Identifies the new depth maps and fixes the scene (the root cube) if the store has none.
    pub fn prepare(store: &Store, sources: Vec<DepthMapSource>, options: &IngestOptions) -> Result<IngestStage> {
        let registered = registered_depth_maps(store)?;
        let known: BTreeSet<u64> = registered.iter().map(|(id, _)| *id).collect();
        let ids: Vec<u64> = sources
            .par_iter()
            .map(depth_map_id)
            .collect::<std::result::Result<_, _>>()
            .map_err(input_error)?;
        let recorded: std::collections::BTreeMap<u64, DepthNoise> = registered
            .iter()
            .map(|(id, record)| (*id, record.source.noise))
            .collect();
        let other_noise = ids
            .iter()
            .zip(&sources)
            .filter(|(id, source)| recorded.get(id).is_some_and(|noise| *noise != source.noise))
            .count();
        if other_noise > 0 {
            tracing::warn!(
                "{other_noise} depth map(s) are already in the store with another depth noise model; they keep theirs (a depth map is ingested once)"
            );
        }
        let mut maps: Vec<(u64, DepthMapSource)> = ids
            .into_iter()
            .zip(sources)
            .filter(|(id, _)| !known.contains(id))
            .collect();
        maps.sort_by_key(|(id, _)| *id);
        maps.dedup_by_key(|(id, _)| *id);

        if !(1..=crate::format::MAX_DEPTH).contains(&options.max_depth) {
            return Err(StoreError::Stage {
                stage: INGEST.into(),
                unit: "options".into(),
                message: format!(
                    "max depth {} is outside 1..={} (the cube keys' limit)",
                    options.max_depth,
                    crate::format::MAX_DEPTH
                ),
            });
        }
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
                        let per_map: Vec<Vec<DVec3>> = maps
                            .par_iter()
                            .map(|(_, source)| {
                                let image = source.load().map_err(input_error)?;
                                // At most ~200,000 points in total, whatever the number of maps.
                                let per_map = (200_000 / maps.len().max(1)).max(64);
                                Ok(bounds_sample(&back_project(source, &image), per_map))
                            })
                            .collect::<Result<_>>()?;
                        let points: Vec<DVec3> = per_map.into_iter().flatten().collect();
                        let Some((lo, hi)) = robust_bounds(&points) else {
                            return Err(StoreError::Stage {
                                stage: INGEST.into(),
                                unit: "all depth maps".into(),
                                message: "no valid depth samples: nothing to build a scene from".into(),
                            });
                        };
                        Scene::around(lo, hi, options.root_margin, options.max_depth)
                    }
                };
                (scene, true)
            }
        };
        let root_is_fixed = if scene_is_new {
            options.root.is_some()
        } else {
            root_is_fixed(store)?
        };
        let mut growth = None;
        let mut scene = scene;
        if !scene_is_new && !root_is_fixed && !maps.is_empty() {
            let octants = growth::growth_for(&scene, &maps)?;
            if !octants.is_empty() {
                let old = scene;
                for octant in &octants {
                    scene = scene.doubled(*octant).ok_or_else(|| StoreError::Stage {
                        stage: INGEST.into(),
                        unit: "new depth maps".into(),
                        message: "the root cannot grow past the keys' depth limit".into(),
                    })?;
                }
                growth = Some((old, octants));
            }
        }
        Ok(IngestStage {
            scene,
            scene_is_new,
            root_is_fixed,
            growth,
            maps,
        })
    }

    /// The scene before this ingest and the doublings that grew it, if the root grew.
    pub fn growth(&self) -> Option<&(Scene, Vec<[u32; 3]>)> {
        self.growth.as_ref()
    }

    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    pub fn new_depth_maps(&self) -> usize {
        self.maps.len()
    }

    /// Cubes of one depth map, merged by key: (keys, radius sums, counts, spike counts, and
    /// the SSD solver's sample moments, `stages::samples`).
    pub fn cubes(&self, source: &DepthMapSource) -> std::result::Result<(Vec<Column>, SampleStats), InputError> {
        let image = source.load()?;
        let samples = back_project(source, &image);
        let mut stats = samples.stats;
        let mut entries: Vec<(CubeKey, u64, bool, Moments)> = Vec::with_capacity(samples.points.len());
        // Consistent samples outside the root mean the map sees beyond the scene the store was
        // sized for; spikes outside it are noise.
        let mut consistent_outside = 0u64;
        let weight = f64::from(source.weight);
        for (((p, r), spike), (normal, area)) in samples
            .points
            .iter()
            .zip(&samples.radii)
            .zip(&samples.spikes)
            .zip(samples.normals.iter().zip(&samples.areas))
        {
            if !self.scene.contains(*p) {
                stats.outside += 1;
                consistent_outside += u64::from(!*spike);
                continue;
            }
            let depth = self.scene.depth_for_radius(*r);
            let key = self.scene.key_at(*p, depth);
            // Spikes and samples without a normal say nothing SSD can use.
            let moments = if *spike || *normal == DVec3::ZERO {
                Moments::default()
            } else {
                Moments::of_sample(&self.scene, key, *p, area * weight, *normal)
            };
            entries.push((key, self.scene.quantize_radius(*r), *spike, moments));
        }
        if consistent_outside * 100 > stats.samples.max(1) {
            return Err(crate::inputs::bad(
                &source.path,
                format!(
                    "{consistent_outside} of {} samples (not counting isolated spikes) lie outside the store's root cube (min {:?}, side {}){}",
                    stats.samples,
                    self.scene.root_min,
                    self.scene.root_side,
                    if self.root_is_fixed {
                        ", which was fixed by --root at the store's first ingest; create a new store with a root that holds this depth map"
                    } else {
                        "; check the map's pose and depth scale, or give a larger --root-margin to a new store"
                    }
                ),
            ));
        }
        // By key alone: entries of one key are summed, in any order.
        entries.sort_unstable_by_key(|(key, _, _, _)| *key);
        let mut keys: Vec<CubeKey> = Vec::new();
        let mut sums: Vec<u64> = Vec::new();
        let mut counts: Vec<u32> = Vec::new();
        let mut spike_counts: Vec<u32> = Vec::new();
        let mut moments: Vec<Moments> = Vec::new();
        for (key, r, spike, m) in entries {
            if keys.last() == Some(&key) {
                if let (Some(s), Some(c), Some(sc), Some(sm)) = (
                    sums.last_mut(),
                    counts.last_mut(),
                    spike_counts.last_mut(),
                    moments.last_mut(),
                ) {
                    *s += r;
                    *c += 1;
                    *sc += u32::from(spike);
                    sm.add(&m);
                }
            } else {
                keys.push(key);
                sums.push(r);
                counts.push(1);
                spike_counts.push(u32::from(spike));
                moments.push(m);
            }
        }
        stats.cubes = keys.len() as u64;
        let mut columns = vec![
            Column::keys(keys),
            Column::new(RADIUS_SUM, 1, ColumnValues::U64(sums)),
            Column::new("radius_count", 1, ColumnValues::U32(counts)),
            Column::new(SPIKE_COUNT, 1, ColumnValues::U32(spike_counts)),
        ];
        columns.extend(moment_columns(&moments));
        Ok((columns, stats))
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
        let maps: Vec<(u64, DepthNoise)> = self.maps.iter().map(|(id, source)| (*id, source.noise)).collect();
        catalog::encode(&(maps, self.scene))
    }

    fn plan(&self, base: &Snapshot<'_>) -> Result<Plan> {
        let mut units: Vec<UnitSpec> = self
            .maps
            .iter()
            .enumerate()
            .map(|(index, (_, source))| UnitSpec {
                id: index as u64,
                label: source.path.display().to_string(),
            })
            .collect();
        if self.growth.is_none() {
            return Ok(Plan {
                units,
                replace: Replace::Nothing,
            });
        }
        // Every earlier run is re-keyed into the grown root (units after the new maps').
        let runs = base.segments(INGEST);
        units.extend(runs.iter().enumerate().map(|(index, (name, _))| UnitSpec {
            id: (self.maps.len() + index) as u64,
            label: format!("re-key {name}"),
        }));
        Ok(Plan {
            units,
            replace: Replace::Names(runs.iter().map(|(name, _)| name.clone()).collect()),
        })
    }

    fn run_unit(&self, base: &Snapshot<'_>, unit: &UnitSpec) -> Result<UnitOutput> {
        if let Some(run) = (unit.id as usize).checked_sub(self.maps.len()) {
            return self.rekey_unit(base, run, unit);
        }
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
        let mut rekeyed = 0usize;
        for (id, record) in units {
            if *id >= self.maps.len() as u64 {
                rekeyed += 1;
                continue;
            }
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
            table.insert(
                extra.id,
                catalog::seal_encode("depth_maps", &extra.id, &record).as_slice(),
            )?;
        }
        let mut meta = txn.open_table(META)?;
        if self.scene_is_new {
            meta.insert(
                META_SCENE,
                catalog::seal_encode("meta", META_SCENE, &self.scene).as_slice(),
            )?;
            if self.root_is_fixed {
                meta.insert(
                    META_ROOT_FIXED,
                    catalog::seal("meta", META_ROOT_FIXED, &[1u8]).as_slice(),
                )?;
            }
        }
        let grown = match &self.growth {
            Some((old, octants)) => {
                meta.insert(
                    META_SCENE,
                    catalog::seal_encode("meta", META_SCENE, &self.scene).as_slice(),
                )?;
                let until = scene_until_key(base.version() + 1);
                meta.insert(
                    until.as_str(),
                    catalog::seal_encode("meta", until.as_str(), old).as_slice(),
                )?;
                format!(
                    "; root grown {} time(s) to min {:?}, side {} ({rekeyed} earlier run(s) re-keyed)",
                    octants.len(),
                    self.scene.root_min,
                    self.scene.root_side
                )
            }
            None => String::new(),
        };
        Ok(format!(
            "{} depth map(s): {} samples, {} cubes; skipped {} invalid, {} absurd, {} isolated of {} pixels, {} outside the root{grown}",
            units.len() - rekeyed,
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

impl IngestStage {
    /// Unit `run` of the re-keying that a grown root needs: the base version's ingest run of
    /// that index, keyed into the grown root.
    fn rekey_unit(&self, base: &Snapshot<'_>, run: usize, unit: &UnitSpec) -> Result<UnitOutput> {
        let (Some((_, octants)), Some((name, _))) = (&self.growth, base.segments(INGEST).get(run)) else {
            return Err(StoreError::Stage {
                stage: INGEST.into(),
                unit: unit.label.clone(),
                message: "unit out of range".into(),
            });
        };
        let file = base.open_segment(name)?;
        Ok(UnitOutput {
            segments: vec![growth::rekeyed_run(&file, octants)?],
            extra: Vec::new(),
            block_rows: RUN_BLOCK_ROWS,
        })
    }
}

#[cfg(test)]
mod tests;
