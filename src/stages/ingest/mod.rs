//! `ingest`: registers depth maps and writes their cubes as sorted runs, one per group of up
//! to [`MAPS_PER_RUN`] depth maps that look at one region (paper 4.1).
//!
//! One ingest is one version; it is committed unit by unit (a unit is one group of depth
//! maps, the maps of one run), so a
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

mod back_projection;
mod cube_runs;
mod growth;
pub mod noise;

pub use back_projection::{
    DepthMedian, DepthRowSource, ImageRows, Sample, SampleStream, Samples, back_project, bounds_sample, open_rows,
    robust_bounds, survey,
};

pub use growth::{
    GROWTH_MARGIN, MAX_DOUBLINGS_PER_INGEST, META_ROOT_FIXED, META_SCENE_UNTIL_PREFIX, RADIUS_SUM, root_is_fixed,
    scene_at, scene_until_key,
};

use super::INGEST;
use super::samples::Moments;
use crate::format::{META_SCENE, RadiusDepths, Scene};
use crate::inputs::{DepthMapSource, DepthNoise, InputError, Projection};
use crate::store::StageError;
use crate::store::catalog::{self, META, UnitRecord};
use crate::store::{Plan, Replace, Result, SegmentContent, Snapshot, Stage, Store, StoreError, UnitOutput, UnitSpec};
use cube_runs::CubeRuns;

pub use crate::store::catalog::DEPTH_MAPS;

/// Block size of ingest runs: small, so that merging many runs at once stays within memory.
pub const RUN_BLOCK_ROWS: u32 = 1024;

/// The column of ingest runs and octree segments that counts, per cube, the spikes among the
/// samples that spawned it (format-spec.md, "Columns used by stages").
pub const SPIKE_COUNT: &str = "spike_count";

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
    // Before opening: a FIFO would block the open until something wrote to it.
    crate::inputs::check_regular_file(&source.path)?;
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

/// How `ingest` reads depth maps and builds the store's root cube and sample runs.
#[derive(Clone, Debug)]
pub struct IngestOptions {
    /// The root cube as (min corner, side); computed from the first ingest's samples if absent.
    pub root: Option<([f64; 3], f64)>,
    /// Margin around the first ingest's bounding box, as a fraction of its largest extent.
    pub root_margin: f64,
    /// The deepest octree level a sample may reach (the cap on cube sizes the noise asks for).
    pub max_depth: u8,
    /// The memory the ingest may use, shared by the depth maps read at once.
    pub memory_budget: u64,
    /// Gather the samples' SSD sums (weights, centroids, normals per cube) that `solve
    /// --method ssd|hybrid` needs: set at a store's first ingest and kept by later ones
    /// (`META_SAMPLE_SUMS`). They make ingest about 1.6 times slower and its runs about 6
    /// times larger (RedKitchen), for data the default TGV solver does not use.
    pub sample_sums: bool,
    /// Depth maps a unit reads into one run (`MAPS_PER_RUN` by default; at least 1). The
    /// octree and every later stage are the same for any value; fewer maps a run mean more
    /// run rows for the octree merge and the samples stage to read, more mean a larger table.
    pub maps_per_run: usize,
}

impl Default for IngestOptions {
    fn default() -> Self {
        IngestOptions {
            root: None,
            root_margin: 0.1,
            max_depth: 24,
            memory_budget: 1 << 30,
            sample_sums: false,
            maps_per_run: MAPS_PER_RUN,
        }
    }
}

/// Memory for one depth map in flight: a worker reads one while up to one more finished map
/// per worker waits for its commit (`store::runner`), so each gets a share of half the
/// budget per worker.
fn memory_per_map(budget: u64) -> u64 {
    budget / (2 * rayon::current_num_threads().max(1) as u64)
}

/// Meta key: `[1]` when the store's ingest runs carry the SSD sample moments, `[0]` when they
/// do not; written by the first ingest. Stores from before the key existed lack it: their runs
/// carry the moments if a build since `--method ssd` wrote them, so absent reads as `[1]` (a
/// run without the columns is still named by the samples stage).
pub const META_SAMPLE_SUMS: &str = "sample_sums";

/// Whether the store's ingests gather sample sums ([`META_SAMPLE_SUMS`]).
pub fn records_sample_sums(store: &Store) -> Result<bool> {
    let txn = store.catalog().begin_read()?;
    let meta = txn.open_table(META)?;
    match meta.get(META_SAMPLE_SUMS.as_bytes())? {
        Some(v) => match catalog::unseal("meta", META_SAMPLE_SUMS, v.value())? {
            [0] => Ok(false),
            [1] => Ok(true),
            other => Err(StoreError::CatalogCorruption {
                table: "meta",
                reason: format!("{META_SAMPLE_SUMS} is {other:?}, not [0] or [1]"),
            }),
        },
        None => Ok(true),
    }
}

pub struct IngestStage {
    /// The scene the new maps are keyed in (grown, if they needed it).
    scene: Scene,
    /// The scene's depth of a sample's radius, by comparisons.
    radius_depths: RadiusDepths,
    scene_is_new: bool,
    /// The runs carry the SSD sample moments ([`META_SAMPLE_SUMS`]).
    sample_sums: bool,
    /// Given with `--root` at the first ingest: recorded so that the root never grows.
    root_is_fixed: bool,
    /// The store's scene before this ingest and the doublings (octants) that grew it into
    /// `scene`; `None` when the root did not grow.
    growth: Option<(Scene, Vec<[u32; 3]>)>,
    /// New depth maps, ordered by id.
    maps: Vec<(u64, DepthMapSource)>,
    /// Beside `maps` (or empty): each map's median depth, where a pass before ingest measured it.
    medians: Vec<DepthMedian>,
    /// The units: indices into `maps`, [`IngestOptions::maps_per_run`] maps a unit that look
    /// at one region ([`group_maps`]), each group written as one run.
    groups: Vec<Vec<usize>>,
    /// Memory for one depth map in flight ([`memory_per_map`]).
    map_memory: u64,
    /// Where maps too large for `map_memory` spill their runs (scratch files are unlinked at
    /// creation, so nothing outlives the process).
    scratch: std::path::PathBuf,
    /// The store's own maps read again to add the SSD sample sums to its runs
    /// ([`IngestStage::adding_sample_sums`]): every run is replaced, and the maps' records
    /// stay as they are.
    adding_sums: bool,
}

/// The error as the stage's (the input error names the file).
fn input_error(e: InputError) -> StoreError {
    StoreError::Stage {
        stage: INGEST.into(),
        unit: "input".into(),
        error: Box::new(StageError::Input(Box::new(e))),
    }
}

pub fn read_scene(store: &Store) -> Result<Option<Scene>> {
    let txn = store.catalog().begin_read()?;
    let meta = txn.open_table(META)?;
    match meta.get(META_SCENE.as_bytes())? {
        Some(v) => Ok(Some(catalog::unseal_decode("meta", META_SCENE, v.value())?)),
        None => Ok(None),
    }
}

/// The depth maps of `snapshot`: those registered in its store by its version or an earlier
/// one, in id order.
pub fn depth_maps_at(snapshot: &crate::store::Snapshot<'_>) -> Result<Vec<(u64, DepthMapRecord)>> {
    let mut maps = registered_depth_maps(snapshot.store())?;
    maps.retain(|(_, record)| record.added_in <= snapshot.version());
    Ok(maps)
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
            .filter(|(id, source)| {
                // A measured model is the map's own: the same pixels measure the same.
                !matches!(source.noise, DepthNoise::Auto { .. })
                    && recorded.get(id).is_some_and(|noise| *noise != source.noise)
            })
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
                error: Box::new(StageError::MaxDepthOutOfRange {
                    max_depth: options.max_depth,
                    limit: crate::format::MAX_DEPTH,
                }),
            });
        }
        // One survey of each new map before anything reads its samples: its median depth
        // (root sizing, growth and the units need it) and, where its noise is to be measured
        // (`--depth-noise auto`), its noise model, which then sizes its cubes and is recorded
        // with it.
        let map_memory = memory_per_map(options.memory_budget);
        let medians: Vec<DepthMedian> = maps
            .par_iter_mut()
            .map(|(_, source)| {
                let (median, noise) = {
                    let mut rows = open_rows(source, map_memory).map_err(input_error)?;
                    survey(source, rows.as_mut()).map_err(input_error)?
                };
                if let DepthNoise::Auto { sigmas } = source.noise {
                    source.noise = noise.model(sigmas);
                }
                Ok(median)
            })
            .collect::<Result<_>>()?;
        let (scene, scene_is_new) = match read_scene(store)? {
            Some(scene) => (scene, false),
            None => {
                let scene = match options.root {
                    Some((min, side)) => Scene {
                        root_min: min,
                        root_side: side,
                        max_depth: options.max_depth,
                    },
                    None => root_around_samples(&maps, &medians, map_memory, options)?,
                };
                (scene, true)
            }
        };
        let root_is_fixed = if scene_is_new {
            options.root.is_some()
        } else {
            root_is_fixed(store)?
        };
        let sample_sums = if scene_is_new {
            options.sample_sums
        } else {
            let recorded = records_sample_sums(store)?;
            if options.sample_sums && !recorded {
                return Err(StoreError::Stage {
                    stage: INGEST.into(),
                    unit: "options".into(),
                    error: Box::new(StageError::SampleSumsNotRecorded),
                });
            }
            recorded
        };
        let mut growth = None;
        let mut scene = scene;
        if !scene_is_new && !root_is_fixed && !maps.is_empty() {
            let octants = growth::growth_for(&scene, &maps, &medians, map_memory)?;
            if !octants.is_empty() {
                let old = scene;
                for octant in &octants {
                    scene = scene.doubled(*octant).ok_or_else(|| StoreError::Stage {
                        stage: INGEST.into(),
                        unit: "new depth maps".into(),
                        error: Box::new(StageError::RootAtDepthLimit),
                    })?;
                }
                growth = Some((old, octants));
            }
        }
        let groups = group_maps(&scene, &maps, &medians, options.maps_per_run);
        Ok(IngestStage {
            groups,
            radius_depths: RadiusDepths::new(&scene),
            scene,
            scene_is_new,
            sample_sums,
            root_is_fixed,
            growth,
            maps,
            medians,
            map_memory,
            scratch: store.scratch_path(INGEST),
            adding_sums: false,
        })
    }

    /// The SSD solver's sample sums for a store ingested without them (`solve --method ssd`
    /// or `hybrid` on a plain store): every registered depth map read again, with the noise
    /// model recorded for it, in the current scene, and its cubes written as new runs that
    /// carry the sums and replace all of the store's runs in one version. The cubes are the
    /// ones the maps spawned before (a run re-keyed by the root's growth holds the cubes a map
    /// spawns in the grown root), so the octree and everything after it come out the same; the
    /// store records sample sums from then on, and later ingests gather them too.
    pub fn adding_sample_sums(store: &Store, memory_budget: u64) -> Result<IngestStage> {
        let scene = read_scene(store)?.ok_or_else(|| StoreError::Stage {
            stage: INGEST.into(),
            unit: "sample sums".into(),
            error: Box::new(StageError::NotIngested),
        })?;
        // Registered maps come in id order, as a new ingest's do.
        let maps: Vec<(u64, DepthMapSource)> = registered_depth_maps(store)?
            .into_iter()
            .map(|(id, record)| (id, record.source))
            .collect();
        let groups = group_maps(&scene, &maps, &[], MAPS_PER_RUN);
        Ok(IngestStage {
            groups,
            radius_depths: RadiusDepths::new(&scene),
            scene,
            scene_is_new: false,
            sample_sums: true,
            root_is_fixed: root_is_fixed(store)?,
            growth: None,
            maps,
            medians: Vec::new(),
            map_memory: memory_per_map(memory_budget),
            scratch: store.scratch_path(INGEST),
            adding_sums: true,
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

    /// The cubes of a group of depth maps (`group`, indices into the new maps), merged by key,
    /// as one segment (keys, radius sums, counts, spike counts, and the SSD solver's sample
    /// moments, `stages::samples`); `None` without cubes; and each map's statistics. Memory
    /// stays within one map's share of the budget whatever the maps' size: rows are read a few
    /// at a time and cube entries spill to sorted runs (`cube_runs.rs`).
    fn group_cubes(&self, group: &[usize]) -> Result<(Option<SegmentContent>, Vec<MapStats>)> {
        let capacity = (self.map_memory * 3 / 4 / cube_runs::BYTES_PER_CUBE).max(1 << 12) as usize;
        let mut runs: Option<CubeRuns<'_>> = None;
        let mut all_stats = Vec::with_capacity(group.len());
        for &index in group {
            let (id, source) = self.maps.get(index).ok_or_else(|| StoreError::Stage {
                stage: INGEST.into(),
                unit: format!("depth map {index}"),
                error: Box::new(StageError::internal("depth map out of range")),
            })?;
            let median = self.medians.get(index).copied();
            let stream = map_samples(source, self.map_memory / 4, median)?;
            // Sized for the first map's cubes and a half more: the maps of a group overlap.
            let runs = runs.get_or_insert_with(|| {
                CubeRuns::new(
                    &self.scratch,
                    capacity,
                    stream.valid_pixels() as usize * 3 / 2,
                    self.sample_sums,
                )
            });
            let stats = self.map_cubes(source, stream, runs)?;
            all_stats.push((*id, stats));
        }
        let Some(runs) = runs else {
            return Ok((None, all_stats));
        };
        let (content, cubes) = runs.finish()?;
        // The run's cubes count once, on the group's first map (format-spec.md, "Ingest runs").
        if let Some((_, first)) = all_stats.first_mut() {
            first.cubes = cubes;
        }
        Ok((content, all_stats))
    }

    /// Adds one depth map's samples (`stream`, of `source`) to `runs`.
    fn map_cubes(
        &self,
        source: &DepthMapSource,
        stream: SampleStream<'_>,
        runs: &mut CubeRuns<'_>,
    ) -> Result<SampleStats> {
        // Consistent samples outside the root mean the map sees beyond the scene the store was
        // sized for; spikes outside it are noise.
        let (mut outside, mut consistent_outside) = (0u64, 0u64);
        let weight = f64::from(source.weight);
        let mut failure = None;
        let each = |sample: &Sample| {
            if failure.is_some() {
                return;
            }
            let fraction = self.scene.root_fraction(sample.point);
            if !Scene::fraction_inside(fraction) {
                outside += 1;
                consistent_outside += u64::from(!sample.spike);
                return;
            }
            let depth = self.radius_depths.depth(sample.radius);
            let key = Scene::key_at_fraction(fraction, depth);
            // Spikes and samples without a normal say nothing SSD can use.
            let moments = if !self.sample_sums || sample.spike || sample.normal == DVec3::ZERO {
                Moments::default()
            } else {
                Moments::of_sample(&self.scene, key, sample.point, sample.area * weight, sample.normal)
            };
            if let Err(e) = runs.push(key, self.scene.quantize_radius(sample.radius), sample.spike, &moments) {
                failure = Some(e);
            }
        };
        // Only the moments use the normals.
        let mut stats = if self.sample_sums {
            stream.for_each(each)
        } else {
            stream.for_each_without_normals(each)
        }
        .map_err(input_error)?;
        if let Some(e) = failure {
            return Err(e);
        }
        stats.outside = outside;
        if consistent_outside * 100 > stats.samples.max(1) {
            return Err(input_error(crate::inputs::bad(
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
            )));
        }
        Ok(stats)
    }
}

/// Depth maps a unit of ingest reads into one run. The maps of a capture that look at one
/// region share most of their cubes (RedKitchen's frames: each cube lies in about 28 of the
/// 1000 maps), so a run of several maps holds far fewer rows than their runs one by one, and
/// the octree merge and the samples stage, which read every run row, read fewer.
pub const MAPS_PER_RUN: usize = 16;

/// The new maps (`maps`, by id, with their `medians` where measured) in groups of `per_run`
/// (at least 1) that look at one region: ordered by the Morton code, in `scene`'s root, of
/// the point each camera looks at (its centre moved along its view axis by its median depth,
/// or by an eighth of the root's side where none was measured; ties by id), and cut into
/// consecutive groups. The grouping only decides which maps share a run; the octree and every
/// later stage are the same for any grouping, and it depends on nothing but the maps and the
/// scene, so not on the order they were named in.
fn group_maps(
    scene: &Scene,
    maps: &[(u64, DepthMapSource)],
    medians: &[DepthMedian],
    per_run: usize,
) -> Vec<Vec<usize>> {
    let mut order: Vec<(LookAtOrder, usize)> = maps
        .iter()
        .enumerate()
        .map(|(index, (id, source))| {
            let pose = source.pose();
            let distance = medians
                .get(index)
                .map(|(median, _)| f64::from(*median))
                .filter(|d| d.is_finite() && *d > 0.0)
                .unwrap_or(scene.root_side / 8.0);
            let centre = pose.transform_point3(DVec3::ZERO);
            let axis = pose.transform_vector3(DVec3::Z).normalize_or_zero();
            let fraction = scene
                .root_fraction(centre + axis * distance)
                .clamp(DVec3::ZERO, DVec3::splat(0.999_999));
            let fraction = if fraction.is_finite() { fraction } else { DVec3::ZERO };
            ((Scene::key_at_fraction(fraction, LOOK_AT_DEPTH), *id), index)
        })
        .collect();
    order.sort_unstable();
    order
        .chunks(per_run.max(1))
        .map(|chunk| chunk.iter().map(|(_, index)| *index).collect())
        .collect()
}

/// A map's place in [`group_maps`]' order: the cell of the point it looks at, then its id.
type LookAtOrder = (crate::format::CubeKey, u64);

/// The depth of the cells that order the maps' look-at points (2^10 cells a side).
const LOOK_AT_DEPTH: u8 = 10;

impl IngestStage {
    /// A unit's label: its first map's file, and how many more it reads.
    fn group_label(&self, group: &[usize]) -> String {
        let first = group
            .first()
            .and_then(|index| self.maps.get(*index))
            .map_or_else(String::new, |(_, source)| source.path.display().to_string());
        match group.len() {
            0 | 1 => first,
            n => format!("{first} and {} more", n - 1),
        }
    }
}

/// The first ingest's root, around a sample of every map's points: robust quantiles of their
/// union, without maps far off the others (named in a warning: [`back_projection::far_off_maps`]).
fn root_around_samples(
    maps: &[(u64, DepthMapSource)],
    medians: &[DepthMedian],
    map_memory: u64,
    options: &IngestOptions,
) -> Result<Scene> {
    let per_map: Vec<Vec<DVec3>> = maps
        .par_iter()
        .zip(medians)
        .map(|((_, source), median)| {
            // At most ~200,000 points in total, whatever the number of maps.
            let per_map = (200_000 / maps.len().max(1)).max(64);
            bounds_of(source, map_memory, per_map, *median)
        })
        .collect::<Result<_>>()?;
    let far_off = back_projection::far_off_maps(&per_map);
    for &i in &far_off {
        if let Some((_, source)) = maps.get(i) {
            tracing::warn!(
                "{}: its samples lie far from every other depth map's (a pose in other units, or a wrong translation?); the root is sized without them, and those outside it are left out",
                source.path.display()
            );
        }
    }
    let points: Vec<DVec3> = per_map
        .into_iter()
        .enumerate()
        .filter(|(i, _)| !far_off.contains(i))
        .flat_map(|(_, points)| points)
        .collect();
    let Some((lo, hi)) = robust_bounds(&points) else {
        return Err(StoreError::Stage {
            stage: INGEST.into(),
            unit: "all depth maps".into(),
            error: Box::new(StageError::NoValidSamples),
        });
    };
    Ok(Scene::around(lo, hi, options.root_margin, options.max_depth))
}

/// The root-sizing sample of `count` points of `source` ([`bounds_sample`]), whose median
/// depth its survey measured.
fn bounds_of(source: &DepthMapSource, memory: u64, count: usize, median: DepthMedian) -> Result<Vec<DVec3>> {
    let stream = map_samples(source, memory, Some(median))?;
    bounds_sample(stream, count).map_err(input_error)
}

/// `source`'s samples, its rows in memory when they take at most `memory` bytes.
fn map_samples(source: &DepthMapSource, memory: u64, median: Option<DepthMedian>) -> Result<SampleStream<'_>> {
    let rows = open_rows(source, memory).map_err(input_error)?;
    match median {
        Some(median) => Ok(SampleStream::with_median(source, rows, median)),
        None => SampleStream::new(source, rows).map_err(input_error),
    }
}

/// A depth map's id and statistics.
type MapStats = (u64, SampleStats);

/// What a unit records of each of its depth maps, by id.
#[derive(Serialize, Deserialize)]
struct IngestUnitExtra {
    maps: Vec<MapStats>,
}

impl Stage for IngestStage {
    fn name(&self) -> &'static str {
        INGEST
    }

    fn params(&self) -> Vec<u8> {
        let maps: Vec<(u64, DepthNoise)> = self.maps.iter().map(|(id, source)| (*id, source.noise)).collect();
        // A resumed ingest with the other sample-sums setting starts over, so a store's runs
        // all carry the moments or none does; so does one whose units group the maps otherwise
        // (an ingest begun by a build that wrote a run per map).
        if self.adding_sums {
            return catalog::encode(&(maps, self.scene, self.sample_sums, &self.groups, "adding sample sums"));
        }
        catalog::encode(&(maps, self.scene, self.sample_sums, &self.groups))
    }

    fn plan(&self, base: &Snapshot<'_>) -> Result<Plan> {
        let mut units: Vec<UnitSpec> = self
            .groups
            .iter()
            .enumerate()
            .map(|(index, group)| UnitSpec {
                id: index as u64,
                label: self.group_label(group),
                cubes: 0,
            })
            .collect();
        if self.adding_sums {
            // The maps' new runs replace every run the store has.
            let runs = base.segments(INGEST);
            return Ok(Plan {
                units,
                replace: Replace::Names(runs.iter().map(|(name, _)| name.clone()).collect()),
            });
        }
        if self.growth.is_none() {
            return Ok(Plan {
                units,
                replace: Replace::Nothing,
            });
        }
        // Every earlier run is re-keyed into the grown root (units after the new maps').
        let runs = base.segments(INGEST);
        units.extend(runs.iter().enumerate().map(|(index, (name, _))| UnitSpec {
            id: (self.groups.len() + index) as u64,
            label: format!("re-key {name}"),
            cubes: 0,
        }));
        Ok(Plan {
            units,
            replace: Replace::Names(runs.iter().map(|(name, _)| name.clone()).collect()),
        })
    }

    fn run_unit(&self, base: &Snapshot<'_>, unit: &UnitSpec) -> Result<UnitOutput> {
        if let Some(run) = (unit.id as usize).checked_sub(self.groups.len()) {
            return self.rekey_unit(base, run, unit);
        }
        let group = self.groups.get(unit.id as usize).ok_or_else(|| StoreError::Stage {
            stage: INGEST.into(),
            unit: unit.label.clone(),
            error: Box::new(StageError::internal("unit out of range")),
        })?;
        let (content, maps) = self.group_cubes(group)?;
        Ok(UnitOutput {
            segments: content.into_iter().collect(),
            extra: catalog::encode(&IngestUnitExtra { maps }),
            block_rows: RUN_BLOCK_ROWS,
        })
    }

    fn finish(&self, txn: &WriteTransaction, base: &Snapshot<'_>, units: &[(u64, UnitRecord)]) -> Result<String> {
        if self.adding_sums {
            let mut meta = txn.open_table(META)?;
            meta.insert(
                META_SAMPLE_SUMS.as_bytes(),
                catalog::seal("meta", META_SAMPLE_SUMS, &[1u8]).as_slice(),
            )?;
            return Ok(format!(
                "sample sums added: {} depth map(s) read again into {} run(s) that carry them",
                self.maps.len(),
                units.len()
            ));
        }
        let mut table = txn.open_table(DEPTH_MAPS)?;
        let mut total = SampleStats::default();
        let (mut rekeyed, mut maps, mut runs) = (0usize, 0usize, 0usize);
        for (id, record) in units {
            if *id >= self.groups.len() as u64 {
                rekeyed += 1;
                continue;
            }
            let extra: IngestUnitExtra = catalog::decode("units_done", &record.extra)?;
            runs += usize::from(extra.maps.iter().any(|(_, stats)| stats.cubes > 0));
            for (map_id, stats) in extra.maps {
                let source = self
                    .maps
                    .binary_search_by_key(&map_id, |(id, _)| *id)
                    .ok()
                    .and_then(|at| self.maps.get(at))
                    .map(|(_, s)| s.clone())
                    .ok_or_else(|| StoreError::CatalogCorruption {
                        table: "units_done",
                        reason: format!("depth map {map_id:016x} is not part of this ingest"),
                    })?;
                total.add(&stats);
                maps += 1;
                let record = DepthMapRecord {
                    source,
                    stats,
                    added_in: base.version() + 1,
                };
                table.insert(map_id, catalog::seal_encode("depth_maps", &map_id, &record).as_slice())?;
            }
        }
        let mut meta = txn.open_table(META)?;
        if self.scene_is_new {
            meta.insert(
                META_SCENE.as_bytes(),
                catalog::seal_encode("meta", META_SCENE, &self.scene).as_slice(),
            )?;
            if self.root_is_fixed {
                meta.insert(
                    META_ROOT_FIXED.as_bytes(),
                    catalog::seal("meta", META_ROOT_FIXED, &[1u8]).as_slice(),
                )?;
            }
            meta.insert(
                META_SAMPLE_SUMS.as_bytes(),
                catalog::seal("meta", META_SAMPLE_SUMS, &[u8::from(self.sample_sums)]).as_slice(),
            )?;
        }
        let grown = match &self.growth {
            Some((old, octants)) => {
                meta.insert(
                    META_SCENE.as_bytes(),
                    catalog::seal_encode("meta", META_SCENE, &self.scene).as_slice(),
                )?;
                let until = scene_until_key(base.version() + 1);
                meta.insert(
                    until.as_bytes(),
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
            "{maps} depth map(s): {} samples, {} cubes in {runs} run(s); skipped {} invalid, {} absurd, {} isolated of {} pixels, {} outside the root{grown}",
            total.samples, total.cubes, total.invalid, total.absurd, total.isolated, total.pixels, total.outside
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
                error: Box::new(StageError::internal("unit out of range")),
            });
        };
        let file = base.open_segment(name)?;
        Ok(UnitOutput {
            segments: vec![growth::rekeyed_run(&file, octants)?.into()],
            extra: Vec::new(),
            block_rows: RUN_BLOCK_ROWS,
        })
    }
}

#[cfg(test)]
mod tests;
