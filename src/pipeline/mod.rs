//! The pipeline as a library: what `octstore ingest`, `solve`, `extract` and `demo` do, for
//! code that drives a store itself. Each call runs its stages through the store's stage
//! runner, so it is resumable and a no-op when its inputs have not changed. Cluster runs
//! (Slurm, chunked extraction) are in [`cluster`].
//!
//! ```
//! use octstore::pipeline::{SolveOptions, ingest, solve};
//! use octstore::{BoundingBox, DiscoverOptions, IndicatorField, IngestOptions, SceneSpec, SolveParams, Store};
//!
//! let dir = tempfile::tempdir()?;
//! // The built-in demo scene: a sphere on a box, seen by 16 cameras of 160x120 pixels.
//! let scene = SceneSpec::demo();
//! let manifest = scene.write(&dir.path().join("input"))?;
//!
//! let store = Store::create(dir.path().join("store"))?;
//! let ingest_options = IngestOptions { max_depth: 8, root_margin: 0.05, ..IngestOptions::default() };
//! ingest(&store, &[manifest], &DiscoverOptions::default(), &ingest_options, &Default::default())?;
//! let params = SolveParams { iterations: 60, ..SolveParams::default() };
//! solve(&store, &SolveOptions { params, ..SolveOptions::default() }, |_report| {})?;
//! drop(store);
//!
//! // Read the indicator field from a read-only handle: negative inside, positive outside.
//! let store = Store::open_read_only(dir.path().join("store"))?;
//! let snapshot = store.latest()?;
//! let inside = snapshot.indicator_at(glam::DVec3::new(0.0, 0.0, 0.62))?.expect("inside the root");
//! let outside = snapshot.indicator_at(glam::DVec3::new(1.0, 0.0, 0.4))?.expect("inside the root");
//! assert!(inside < 0.0 && outside > 0.0, "u inside {inside}, outside {outside}");
//! // The cubes of the finest level around the sphere's top, with centre, size, u, histogram.
//! let level = snapshot.finest_level().expect("solved");
//! let top = BoundingBox { min: glam::DVec3::new(-0.1, -0.1, 0.6), max: glam::DVec3::new(0.1, 0.1, 0.8) };
//! let cubes = snapshot.cubes_in(&top, level)?;
//! assert!(cubes.iter().any(|c| c.u < 0.0) && cubes.iter().any(|c| c.u > 0.0));
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

pub mod cluster;
mod demo;
mod error;

use std::path::{Path, PathBuf};
use std::sync::Arc;

pub use self::demo::{DemoOptions, DemoOutput, demo};
pub use self::error::{PipelineError, Result};
pub(crate) use self::error::{io_error, save_png};
use crate::format::Scene;
use crate::gpu::{DeviceChoice, Gpu};
use crate::inputs::{DiscoverOptions, discover};
use crate::stages::extract::{ExtractOptions, MeshSummary, extract_to_file};
use crate::stages::histograms::HistogramsStage;
use crate::stages::ingest::{IngestOptions, IngestStage, read_scene, registered_depth_maps, scene_at};
use crate::stages::octree::{OctreeStage, effective_leaf_cubes, leaves_in_flight};
use crate::stages::samples::SamplesStage;
use crate::stages::solve::{CoarseSamplesCache, LevelStage, Method, MethodChoice, PendingCoarseSamples, SolveParams};
use crate::stages::{INGEST, OCTREE, octree_max_depth};
use crate::store::{RunOptions, RunReport, Store};

/// How far `solve` goes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, clap::ValueEnum)]
pub enum SolveUntil {
    /// The octree and its treetop.
    Octree,
    /// The octree, then the histograms.
    Histograms,
    /// Everything: the octree, the histograms, every level of the solution.
    Solution,
}

/// How `solve` runs.
#[derive(Clone, Debug)]
pub struct SolveOptions {
    /// The last stage to bring up to date.
    pub until: SolveUntil,
    /// Treetop leaves hold fewer cubes than this (capped by the memory budget).
    pub leaf_cubes: u64,
    /// Bytes the whole process may use; the octree build's sorter gets a quarter.
    pub memory_budget: u64,
    /// The TGV weights and iterations.
    pub params: SolveParams,
    /// The energy minimised on each level: by default SSD for an object against empty
    /// background and TGV for a scene ([`MethodChoice::resolve`]).
    pub method: MethodChoice,
    /// Threads, resumption, progress bars.
    pub run: RunOptions,
    /// Where the histogram votes and the solver's iterations run.
    pub device: DeviceChoice,
}

impl Default for SolveOptions {
    fn default() -> Self {
        SolveOptions {
            until: SolveUntil::Solution,
            leaf_cubes: 1 << 24,
            memory_budget: 1 << 30,
            params: SolveParams::default(),
            method: MethodChoice::default(),
            run: RunOptions::default(),
            device: DeviceChoice::Auto,
        }
    }
}

/// The store's scene, or an error for `step` that says to ingest first.
pub(crate) fn required_scene(store: &Store, step: &str) -> Result<Scene> {
    read_scene(store)?.ok_or_else(|| PipelineError::NotIngested { step: step.into() })
}

/// Registers the depth maps named by `inputs` and writes their cubes, as one new version.
pub fn ingest(
    store: &Store,
    inputs: &[PathBuf],
    discover_options: &DiscoverOptions,
    options: &IngestOptions,
    run: &RunOptions,
) -> Result<RunReport> {
    let started = std::time::Instant::now();
    let sources = discover(inputs, discover_options)?;
    let stage = IngestStage::prepare(store, sources, options)?;
    if stage.new_depth_maps() == 0 {
        // Not a stage run at all: the catalog stays byte for byte as it was (a run, even an
        // empty one, would record its inputs).
        return Ok(RunReport {
            stage: INGEST.to_string(),
            version: None,
            units: 0,
            resumed_units: 0,
            rows: 0,
            seconds: started.elapsed().as_secs_f64(),
            summary: "up to date: every depth map is already in the store".into(),
        });
    }
    let report = store.run_stage(&stage, run);
    // Spilled runs are unlinked files: the folder is empty once the run ends, either way.
    let scratch = store.scratch_path(INGEST);
    let _ = std::fs::remove_dir(&scratch);
    if let Some(parent) = scratch.parent() {
        let _ = std::fs::remove_dir(parent);
    }
    Ok(report?)
}

/// Runs the pending stages up to `options.until`: the octree, (for SSD) the samples, the
/// histograms, then every level of the solution coarse to fine. `on_report` sees each stage's report as it finishes.
pub fn solve(store: &Store, options: &SolveOptions, on_report: impl FnMut(&RunReport)) -> Result<()> {
    let gpu = if options.until >= SolveUntil::Histograms {
        open_gpu(options.device)?
    } else {
        None
    };
    solve_with_gpu(store, options, gpu, on_report)
}

/// [`solve`] with the votes and the solver's iterations on an already open `gpu`
/// (`options.device` unused).
pub(crate) fn solve_with_gpu(
    store: &Store,
    options: &SolveOptions,
    gpu: Option<Arc<Gpu>>,
    mut on_report: impl FnMut(&RunReport),
) -> Result<()> {
    let scene = required_scene(store, OCTREE)?;
    let leaf_cubes = effective_leaf_cubes(options.leaf_cubes, options.memory_budget);
    // Leaves in flight within the budget; the rayon pool keeps every thread for the work
    // inside them.
    let run = RunOptions {
        threads: leaves_in_flight(leaf_cubes, options.memory_budget, options.run.threads),
        ..options.run.clone()
    };
    // The method matters only to the samples and the levels; deciding it reads a few maps.
    let method = if options.until >= SolveUntil::Solution {
        options.method.resolve(&store.latest()?)?
    } else {
        Method::Tgv
    };
    if options.until >= SolveUntil::Solution
        && method.ssd().is_some()
        && !crate::stages::ingest::records_sample_sums(store)?
    {
        // SSD reads the samples' sums, which a plain ingest leaves out (they cost it about
        // five times the time): read the store's maps again and add them to its runs, once.
        tracing::info!(
            "the store's runs carry no sample sums (ingest --sample-sums gathers them up front): reading its depth maps again to add them"
        );
        let stage = IngestStage::adding_sample_sums(store, options.memory_budget)?;
        on_report(&store.run_stage(&stage, &run)?);
    }
    if options.until >= SolveUntil::Octree {
        let scratch = store.scratch_dir(OCTREE)?;
        let stage = OctreeStage::new(scene, leaf_cubes, options.memory_budget / 4, scratch.clone());
        let report = store.run_stage(&stage, &run);
        // Scratch files are rebuilt by any later run, so they go whether the run finished or
        // failed (a full disk most of all); a failure to remove them costs only disk.
        let _ = std::fs::remove_dir_all(&scratch);
        if let Some(parent) = scratch.parent() {
            // Only if empty: another stage's scratch may live there.
            let _ = std::fs::remove_dir(parent);
        }
        on_report(&report?);
    }
    let coarse_samples = CoarseSamplesCache::default();
    if options.until >= SolveUntil::Solution && method.ssd().is_some() {
        // Before the histograms: a store ingested without sample moments fails in seconds. An
        // eighth of the budget for run blocks that several units read, as the histograms give
        // their decoded depth maps, and another eighth for the blocks the units in flight hold
        // to add.
        //
        // The coarse levels take every unit's samples by their coarse sums: summed here from
        // the sums at hand, level 0 need not decode every unit's segment on one worker.
        let pending = Arc::new(PendingCoarseSamples::default());
        let shown = pending.clone();
        let stage = SamplesStage::new()
            .with_cache_bytes(options.memory_budget / 8)
            .with_group_bytes(options.memory_budget / 8 / run.threads.max(1) as u64)
            .with_unit_sums(move |unit, keys, sums| shown.add(unit, keys, sums));
        on_report(&store.run_stage(&stage, &run)?);
        drop(stage);
        if let Ok(pending) = Arc::try_unwrap(pending) {
            pending.file_into(&coarse_samples, &store.latest()?);
        }
    }
    if options.until >= SolveUntil::Histograms {
        // Stages run one at a time: an eighth of the budget for decoded depth maps, beside the
        // group of leaves being voted (sized for the leaves in flight), keeps the histogram
        // stage within the budget.
        let stage = HistogramsStage::new(scene, registered_depth_maps(store)?)
            .with_cache_bytes(options.memory_budget / 8)
            .with_gpu(gpu.clone());
        on_report(&store.run_stage(&stage, &run)?);
    }
    if options.until >= SolveUntil::Solution {
        let coarse_rows = crate::stages::solve::CoarseRowsCache::default();
        for level in 0..=octree_max_depth(store)? {
            let stage = LevelStage::new(level, scene, options.params)
                .with_gpu(gpu.clone())
                .with_method(method)
                .with_coarse_samples(coarse_samples.clone())
                .with_coarse_rows(Some(coarse_rows.clone()));
            on_report(&store.run_stage(&stage, &run)?);
        }
    }
    Ok(())
}

/// The device `choice` names: an error only when `gpu` was asked for and none opens; `auto`
/// falls back to the CPU with a warning.
pub(crate) fn open_gpu(choice: DeviceChoice) -> Result<Option<Arc<Gpu>>> {
    match Gpu::open(choice) {
        Ok(gpu) => Ok(gpu.map(std::sync::Arc::new)),
        Err(error) if choice == DeviceChoice::Auto => {
            tracing::warn!("{error}; solving on the CPU");
            Ok(None)
        }
        Err(error) => Err(PipelineError::NoGpu(error)),
    }
}

/// Extracts the surface of the latest solved version (or of `version`) into `output`: PLY, GLB
/// or OBJ by extension; streamed leaf by leaf, and cut at the region, if there is one, as it streams.
/// An eighth of `memory_budget` holds leaves' pieces computed ahead of the weld.
pub fn extract(
    store: &Store,
    output: &Path,
    options: &ExtractOptions,
    version: Option<u64>,
    memory_budget: u64,
) -> Result<MeshSummary> {
    let snapshot = match version {
        Some(v) => store.snapshot(v)?,
        None => store.latest()?,
    };
    crate::query::ensure_solution_is_current(&snapshot)?;
    if let Some((solved, deepest)) = crate::query::unfinished_solve(&snapshot)? {
        tracing::warn!("{}", crate::query::unfinished_solve_note(solved, deepest));
    }
    // The snapshot's own scene and finest level: a later ingest may have grown the root.
    let scene =
        scene_at(store, snapshot.version())?.ok_or_else(|| PipelineError::NotIngested { step: "extract".into() })?;
    let finest = crate::query::IndicatorField::finest_level(&snapshot).map_or_else(|| octree_max_depth(store), Ok)?;
    Ok(extract_to_file(
        &snapshot,
        &scene,
        finest,
        options,
        output,
        memory_budget,
    )?)
}
