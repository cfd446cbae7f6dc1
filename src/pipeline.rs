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

use crate::stages::extract::{
    ExtractOptions, MeshSummary, UnitMesh, assemble, extract_units, stream_to_file, unit_mesh, write_assembled,
};
use crate::stages::histograms::HistogramsStage;
use crate::stages::ingest::{IngestOptions, IngestStage, read_scene, registered_depth_maps};
use crate::stages::inputs::{DiscoverOptions, discover};
use crate::stages::octree::{OctreeStage, effective_leaf_cubes};
use crate::stages::solve::{LEVEL_STAGES, LevelStage, SolveParams};
use crate::stages::treetop::Treetop;
use crate::stages::{HISTOGRAMS, INGEST, OCTREE, octree_max_depth};
use crate::store::cluster::{ClusterPlan, WorkReport, decode_chunk_file, encode_chunk_file};
use crate::store::{Result, RunOptions, RunReport, Stage, Store, StoreError};

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
    /// Where the histogram votes and the solver's iterations run.
    pub device: crate::gpu::DeviceChoice,
}

impl Default for SolveOptions {
    fn default() -> Self {
        SolveOptions {
            until: SolveUntil::Solution,
            leaf_cubes: 1 << 24,
            memory_budget: 1 << 30,
            params: SolveParams::default(),
            run: RunOptions::default(),
            device: crate::gpu::DeviceChoice::Auto,
        }
    }
}

/// The store's scene, or an error for `stage` that says to ingest first.
fn required_scene(store: &Store, stage: &str) -> Result<crate::stages::scene::Scene> {
    read_scene(store)?.ok_or_else(|| StoreError::Stage {
        stage: stage.into(),
        unit: "-".into(),
        message: "the store has no depth maps yet: run `octstore ingest` first".into(),
    })
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
pub fn solve_with_gpu(
    store: &Store,
    options: &SolveOptions,
    gpu: Option<std::sync::Arc<crate::gpu::Gpu>>,
    mut on_report: impl FnMut(&RunReport),
) -> Result<()> {
    let scene = required_scene(store, OCTREE)?;
    if options.until >= SolveUntil::Octree {
        let scratch = store.scratch_dir(OCTREE)?;
        let leaf_cubes = effective_leaf_cubes(options.leaf_cubes, options.memory_budget, options.run.threads);
        let stage = OctreeStage::new(scene, leaf_cubes, options.memory_budget / 4, scratch.clone());
        on_report(&store.run_stage(&stage, &options.run)?);
        // Scratch files are rebuilt by any later run; a failure to remove them costs only disk.
        let _ = std::fs::remove_dir_all(scratch);
    }
    if options.until >= SolveUntil::Histograms {
        // Stages run one at a time: an eighth of the budget for decoded depth maps, beside the
        // workers' groups of leaves, keeps the histogram stage within the budget.
        let stage = HistogramsStage::new(scene, registered_depth_maps(store)?)
            .with_cache_bytes(options.memory_budget / 8)
            .with_gpu(gpu.clone());
        on_report(&store.run_stage(&stage, &options.run)?);
    }
    if options.until >= SolveUntil::Solution {
        for level in 0..=octree_max_depth(store)? {
            let stage = LevelStage::new(level, scene, options.params).with_gpu(gpu.clone());
            on_report(&store.run_stage(&stage, &options.run)?);
        }
    }
    Ok(())
}

/// The device `choice` names: an error only when `gpu` was asked for and none opens; `auto`
/// falls back to the CPU with a warning.
pub fn open_gpu(choice: crate::gpu::DeviceChoice) -> Result<Option<std::sync::Arc<crate::gpu::Gpu>>> {
    match crate::gpu::Gpu::open(choice) {
        Ok(gpu) => Ok(gpu.map(std::sync::Arc::new)),
        Err(error) if choice == crate::gpu::DeviceChoice::Auto => {
            tracing::warn!("{error}; solving on the CPU");
            Ok(None)
        }
        Err(error) => Err(StoreError::Stage {
            stage: "solve".into(),
            unit: "--device gpu".into(),
            message: error.to_string(),
        }),
    }
}

/// The stage a cluster run works on, by its catalog name: `histograms` or `solution-LL`. The
/// octree is one global merge and is built by a single process (`solve --until octree`).
/// `gpu`, when given, runs the votes or the iterations (with the CPU fallback per unit).
pub fn cluster_stage(
    store: &Store,
    name: &str,
    params: SolveParams,
    gpu: Option<std::sync::Arc<crate::gpu::Gpu>>,
) -> Result<Box<dyn Stage>> {
    let scene = required_scene(store, name)?;
    if name == HISTOGRAMS {
        return Ok(Box::new(
            HistogramsStage::new(scene, registered_depth_maps(store)?).with_gpu(gpu),
        ));
    }
    if let Some(level) = LEVEL_STAGES.iter().position(|s| *s == name) {
        return Ok(Box::new(LevelStage::new(level as u8, scene, params).with_gpu(gpu)));
    }
    let hint = if name == OCTREE {
        "the octree is one global merge: build it with `octstore solve STORE --until octree`"
    } else {
        "cluster stages are `histograms` and `solution-00` to `solution-32`"
    };
    Err(StoreError::Stage {
        stage: name.into(),
        unit: "-".into(),
        message: hint.into(),
    })
}

/// Options of the generated Slurm job chain.
#[derive(Clone, Debug)]
pub struct SlurmOptions {
    pub chunks: u32,
    pub partition: Option<String>,
    /// Extra `#SBATCH` options, verbatim (for example `--time=01:00:00`).
    pub sbatch_args: Vec<String>,
    /// The `octstore` binary the jobs run (the same on every node).
    pub binary: PathBuf,
    pub params: SolveParams,
    pub memory_budget: u64,
    /// Treetop leaf size of the octree job.
    pub leaf_cubes: u64,
    /// `--device` of the work jobs of the histograms and the levels.
    pub device: crate::gpu::DeviceChoice,
    /// Extract the mesh into this file at the end of the chain.
    pub output: Option<PathBuf>,
}

/// One job of the chain: its name, whether it is an array of `chunks` tasks, and its script.
#[derive(Clone, Debug, PartialEq)]
pub struct SlurmJob {
    pub name: String,
    pub array: Option<u32>,
    pub script: String,
}

fn shell_quote(text: &str) -> String {
    if !text.is_empty()
        && text
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "/._-=:,+@".contains(c))
    {
        text.to_string()
    } else {
        format!("'{}'", text.replace('\'', r"'\''"))
    }
}

/// The whole pipeline after ingest as a chain of Slurm jobs, each to run after the previous one
/// succeeds: the octree (one task), then per stage (histograms, each solution level) a plan
/// job, an array of `chunks` work tasks and a commit job. `levels` is the deepest level the
/// chain solves (the scene's maximum depth: levels past the octree's finest have no units).
pub fn slurm_jobs(store: &std::path::Path, levels: u8, options: &SlurmOptions) -> Vec<SlurmJob> {
    let store = shell_quote(&store.display().to_string());
    let bin = shell_quote(&options.binary.display().to_string());
    let p = options.params;
    let solver = format!(
        "--alpha1 {} --alpha0 {} --lambda {} --iterations {}",
        p.alpha1, p.alpha0, p.lambda, p.iterations
    );
    let budget = format!("--memory-budget {} --quiet", options.memory_budget);
    let header = |name: &str, array: Option<u32>| {
        let mut lines = vec!["#!/bin/bash".to_string(), format!("#SBATCH --job-name=octstore-{name}")];
        if let Some(tasks) = array {
            lines.push(format!("#SBATCH --array=0-{}", tasks.saturating_sub(1)));
        }
        if let Some(partition) = &options.partition {
            lines.push(format!("#SBATCH --partition={partition}"));
        }
        lines.extend(options.sbatch_args.iter().map(|a| format!("#SBATCH {a}")));
        lines.push("set -euo pipefail".into());
        lines.join("\n")
    };
    let mut jobs = vec![SlurmJob {
        name: "octree".into(),
        array: None,
        script: format!(
            "{}\n{bin} {budget} solve {store} --until octree --leaf-cubes {}\n",
            header("octree", None),
            options.leaf_cubes
        ),
    }];
    let stages = std::iter::once(HISTOGRAMS.to_string())
        .chain((0..=levels.min(crate::format::MAX_DEPTH)).map(|l| LEVEL_STAGES[usize::from(l)].to_string()))
        .chain(options.output.as_ref().map(|_| EXTRACT.to_string()));
    for stage in stages {
        let name = format!("{stage}-plan");
        let plan_args = match (&options.output, stage == EXTRACT) {
            (Some(output), true) => format!("--output {}", shell_quote(&output.display().to_string())),
            _ => solver.clone(),
        };
        jobs.push(SlurmJob {
            script: format!(
                "{}\n{bin} {budget} plan {store} --stage {stage} --chunks {} {plan_args}\n",
                header(&name, None),
                options.chunks
            ),
            name,
            array: None,
        });
        let name = format!("{stage}-work");
        jobs.push(SlurmJob {
            script: format!(
                "{}\n{bin} {budget} work {store} --stage {stage} --chunk \"$SLURM_ARRAY_TASK_ID\"{}\n",
                header(&name, Some(options.chunks)),
                if stage == EXTRACT {
                    String::new()
                } else {
                    format!(" --device {}", options.device.name())
                }
            ),
            name,
            array: Some(options.chunks),
        });
        let name = format!("{stage}-commit");
        jobs.push(SlurmJob {
            script: format!(
                "{}\n{bin} {budget} commit {store} --stage {stage}\n",
                header(&name, None)
            ),
            name,
            array: None,
        });
    }
    jobs
}

/// Cluster name of the extraction: its units are treetop leaves, its result a mesh file.
pub const EXTRACT: &str = "extract";
const UNIT_MESH_MAGIC: &[u8; 8] = b"OCTMESH1";

/// What an extraction plan records: how to extract, and where the mesh goes.
#[derive(serde::Serialize, serde::Deserialize, Clone, Debug, PartialEq)]
struct ExtractPlanArgs {
    options: ExtractOptions,
    output: PathBuf,
}

fn extract_fingerprint(snapshot: &crate::Snapshot<'_>, finest: u8, args: &ExtractPlanArgs) -> Vec<u8> {
    let mut fingerprint = crate::store::catalog::encode(args);
    fingerprint.extend(snapshot.digest(LEVEL_STAGES[usize::from(finest)]).to_le_bytes());
    fingerprint.extend(snapshot.digest(OCTREE).to_le_bytes());
    fingerprint
}

/// Plans a chunked extraction of the latest solution into `output`.
pub fn plan_extract(store: &Store, chunks: u32, options: ExtractOptions, output: PathBuf) -> Result<ClusterPlan> {
    let scene = required_scene(store, EXTRACT)?;
    let snapshot = store.latest()?;
    let finest = octree_max_depth(store)?;
    let units = extract_units(&snapshot, &scene, finest, options.region)?;
    let args = ExtractPlanArgs { options, output };
    let plan = ClusterPlan {
        stage: EXTRACT.into(),
        base_version: snapshot.version(),
        fingerprint: extract_fingerprint(&snapshot, finest, &args),
        units: units.into_iter().map(|u| u as u64).collect(),
        chunks: chunks.max(1),
        args: crate::store::catalog::encode(&args),
    };
    drop(snapshot);
    store.record_cluster_plan(&plan)?;
    Ok(plan)
}

/// The extraction plan, checked against the store it was made for.
fn checked_extract_plan(store: &Store) -> Result<(ClusterPlan, ExtractPlanArgs, u8)> {
    let plan = store.recorded_plan(EXTRACT)?;
    let args: ExtractPlanArgs = crate::store::catalog::decode("cluster plan args", &plan.args)?;
    let snapshot = store.latest()?;
    let finest = octree_max_depth(store)?;
    if snapshot.version() != plan.base_version || extract_fingerprint(&snapshot, finest, &args) != plan.fingerprint {
        return Err(StoreError::Stage {
            stage: EXTRACT.into(),
            unit: "plan".into(),
            message: "the store changed since the plan was made: run `octstore plan` again".into(),
        });
    }
    Ok((plan, args, finest))
}

fn unit_mesh_name(unit: u64) -> String {
    format!("u{unit:010}.mesh")
}

/// Extracts chunk `chunk`'s units into the chunk folder (read-only on the catalog; safe to
/// repeat and to run twice).
pub fn work_extract(store: &Store, chunk: u32) -> Result<WorkReport> {
    let (plan, _, finest) = checked_extract_plan(store)?;
    plan.check_chunk(chunk)?;
    let scene = required_scene(store, EXTRACT)?;
    let snapshot = store.latest()?;
    let treetop = Treetop::of(&snapshot)?;
    let dir = store.chunk_dir(&plan);
    std::fs::create_dir_all(&dir).map_err(crate::store::io_error("create directory", &dir))?;
    let units = plan.chunk_units(chunk);
    let mut skipped = 0;
    for &unit in units {
        let name = unit_mesh_name(unit);
        let done = std::fs::read(dir.join(&name))
            .ok()
            .and_then(|b| decode_chunk_file::<UnitMesh>(UNIT_MESH_MAGIC, &b))
            .is_some();
        if done {
            skipped += 1;
            continue;
        }
        let mesh = unit_mesh(&snapshot, &treetop, &scene, finest, unit as usize)?;
        store.write_chunk_file(&dir, &name, &encode_chunk_file(UNIT_MESH_MAGIC, &mesh))?;
    }
    Ok(WorkReport {
        units: units.len(),
        skipped,
    })
}

/// Welds every unit's piece into the planned mesh file, exactly as `octstore extract` would;
/// names the missing or damaged chunks instead when there are any.
pub fn commit_extract(store: &Store) -> Result<(MeshSummary, PathBuf)> {
    let (plan, args, _) = checked_extract_plan(store)?;
    let dir = store.chunk_dir(&plan);
    let read = |unit: u64| -> Option<UnitMesh> {
        std::fs::read(dir.join(unit_mesh_name(unit)))
            .ok()
            .and_then(|b| decode_chunk_file::<UnitMesh>(UNIT_MESH_MAGIC, &b))
    };
    let missing: std::collections::BTreeSet<_> = plan
        .units
        .iter()
        .filter(|&&unit| !dir.join(unit_mesh_name(unit)).is_file())
        .map(|&unit| plan.chunk_of(unit))
        .collect();
    if !missing.is_empty() {
        return Err(plan.missing_chunks_error(&missing));
    }
    let summary = if args.options.region.is_none() && args.options.decimate.is_none() {
        // Streamed one piece at a time, like `octstore extract`.
        let treetop = Treetop::of(&store.latest()?)?;
        let damaged = std::cell::RefCell::new(std::collections::BTreeSet::new());
        let pieces = plan.units.iter().filter_map(|&unit| {
            let key = usize::try_from(unit)
                .ok()
                .and_then(|i| treetop.units.get(i))
                .map(|u| u.key);
            match (key, usize::try_from(unit), read(unit)) {
                (Some(key), Ok(index), Some(mesh)) => Some(Ok((index, key, mesh))),
                _ => {
                    damaged.borrow_mut().insert(plan.chunk_of(unit));
                    None
                }
            }
        });
        let streamed = stream_to_file(pieces, &treetop, &args.output);
        let damaged = damaged.into_inner();
        if !damaged.is_empty() {
            let _ = std::fs::remove_file(&args.output);
            return Err(plan.missing_chunks_error(&damaged));
        }
        streamed?
    } else {
        let mut meshes = Vec::with_capacity(plan.units.len());
        let mut damaged = std::collections::BTreeSet::new();
        for &unit in &plan.units {
            match read(unit) {
                Some(mesh) => meshes.push(mesh),
                None => {
                    damaged.insert(plan.chunk_of(unit));
                }
            }
        }
        if !damaged.is_empty() {
            return Err(plan.missing_chunks_error(&damaged));
        }
        write_assembled(&args.output, &assemble(meshes, &args.options))?
    };
    store.remove_cluster_plan(&plan)?;
    Ok((summary, args.output))
}
