//! The pipeline as a library: what `octstore ingest` and `octstore solve` do, for code that
//! drives a store itself. Each call runs its stages through the store's stage runner, so it is
//! resumable and a no-op when its inputs have not changed.
//!
//! ```
//! use octstore::pipeline::{SolveOptions, ingest, solve};
//! use octstore::scenes::SceneSpec;
//! use octstore::stages::extract::Region;
//! use octstore::stages::ingest::IngestOptions;
//! use octstore::stages::inputs::DiscoverOptions;
//! use octstore::stages::solve::SolveParams;
//! use octstore::{IndicatorField, Store};
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
//! let top = Region { min: glam::DVec3::new(-0.1, -0.1, 0.6), max: glam::DVec3::new(0.1, 0.1, 0.8) };
//! let cubes = snapshot.cubes_in(&top, level)?;
//! assert!(cubes.iter().any(|c| c.u < 0.0) && cubes.iter().any(|c| c.u > 0.0));
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use std::path::PathBuf;

use crate::stages::histograms::HistogramsStage;
use crate::stages::ingest::{IngestOptions, IngestStage, read_scene, registered_depth_maps};
use crate::stages::inputs::{DiscoverOptions, discover};
use crate::stages::octree::{OctreeStage, effective_leaf_cubes};
use crate::stages::solve::{LevelStage, SolveParams};
use crate::stages::{INGEST, OCTREE, octree_max_depth};
use crate::store::{Result, RunOptions, RunReport, Store, StoreError};

/// How far `solve` goes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, clap::ValueEnum)]
pub enum SolveUntil {
    Octree,
    Histograms,
    Solution,
}

#[derive(Clone, Debug)]
pub struct SolveOptions {
    pub until: SolveUntil,
    /// Treetop leaves hold fewer cubes than this (capped by the memory budget).
    pub leaf_cubes: u64,
    /// Bytes the whole process may use; the octree build's sorter gets a quarter.
    pub memory_budget: u64,
    pub params: SolveParams,
    pub run: RunOptions,
}

impl Default for SolveOptions {
    fn default() -> Self {
        SolveOptions {
            until: SolveUntil::Solution,
            leaf_cubes: 1 << 24,
            memory_budget: 1 << 30,
            params: SolveParams::default(),
            run: RunOptions::default(),
        }
    }
}

/// Registers the depth maps named by `inputs` and writes their cubes, as one new version.
pub fn ingest(
    store: &Store,
    inputs: &[PathBuf],
    discover_options: &DiscoverOptions,
    options: &IngestOptions,
    run: &RunOptions,
) -> Result<RunReport> {
    let sources = discover(inputs, discover_options).map_err(|e| StoreError::Stage {
        stage: INGEST.into(),
        unit: "inputs".into(),
        message: e.to_string(),
    })?;
    let stage = IngestStage::prepare(store, sources, options)?;
    store.run_stage(&stage, run)
}

/// Runs the pending stages up to `options.until`: the octree, the histograms, then every level
/// of the solution coarse to fine. `on_report` sees each stage's report as it finishes.
pub fn solve(store: &Store, options: &SolveOptions, mut on_report: impl FnMut(&RunReport)) -> Result<()> {
    let scene = read_scene(store)?.ok_or_else(|| StoreError::Stage {
        stage: OCTREE.into(),
        unit: "-".into(),
        message: "the store has no depth maps yet: run `octstore ingest` first".into(),
    })?;
    if options.until >= SolveUntil::Octree {
        let scratch = store.scratch_dir(OCTREE)?;
        let leaf_cubes = effective_leaf_cubes(options.leaf_cubes, options.memory_budget, options.run.threads);
        let stage = OctreeStage::new(scene, leaf_cubes, options.memory_budget / 4, scratch.clone());
        on_report(&store.run_stage(&stage, &options.run)?);
        // Scratch files are rebuilt by any later run; a failure to remove them costs only disk.
        let _ = std::fs::remove_dir_all(scratch);
    }
    if options.until >= SolveUntil::Histograms {
        let stage = HistogramsStage::new(scene, registered_depth_maps(store)?);
        on_report(&store.run_stage(&stage, &options.run)?);
    }
    if options.until >= SolveUntil::Solution {
        for level in 0..=octree_max_depth(store)? {
            let stage = LevelStage::new(level, scene, options.params);
            on_report(&store.run_stage(&stage, &options.run)?);
        }
    }
    Ok(())
}
