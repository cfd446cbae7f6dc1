//! Cluster runs: the stages a cluster works on, the Slurm job chain that runs them, and the
//! chunked extraction (plan, work, commit) that ends it. Workers never write the catalog; the
//! commit step is the only writer (format-spec.md, "Cluster chunk files").

use std::path::{Path, PathBuf};
use std::sync::Arc;

use super::{PipelineError, Result, io_error, required_scene};
use crate::gpu::{DeviceChoice, Gpu};
use crate::mesh::UnitMesh;
use crate::stages::extract::{ExtractOptions, MeshSummary, extract_units, unit_mesh, write_pieces};
use crate::stages::histograms::HistogramsStage;
use crate::stages::ingest::registered_depth_maps;
use crate::stages::samples::{SAMPLES, SamplesStage};
use crate::stages::solve::{LEVEL_STAGES, LevelStage, Method, SolveParams};
use crate::stages::treetop::Treetop;
use crate::stages::{HISTOGRAMS, OCTREE, octree_max_depth};
use crate::store::StageError;
use crate::store::cluster::{ClusterPlan, WorkReport, decode_chunk_file, encode_chunk_file};
use crate::store::{Stage, Store};

/// The stage a cluster run works on, by its catalog name: `samples`, `histograms` or
/// `solution-LL`. The
/// octree is one global merge and is built by a single process (`solve --until octree`).
/// `gpu`, when given, runs the votes or the iterations (with the CPU fallback per unit).
pub(crate) fn cluster_stage(
    store: &Store,
    name: &str,
    params: SolveParams,
    method: Method,
    gpu: Option<Arc<Gpu>>,
) -> Result<Box<dyn Stage>> {
    let scene = required_scene(store, name)?;
    if name == SAMPLES {
        return Ok(Box::new(SamplesStage::new()));
    }
    if name == HISTOGRAMS {
        return Ok(Box::new(
            HistogramsStage::new(scene, registered_depth_maps(store)?).with_gpu(gpu),
        ));
    }
    if let Some(level) = LEVEL_STAGES.iter().position(|s| *s == name) {
        return Ok(Box::new(
            LevelStage::new(level as u8, scene, params)
                .with_gpu(gpu)
                .with_method(method),
        ));
    }
    let hint = if name == OCTREE {
        "the octree is one global merge: build it with `octstore solve STORE --until octree`"
    } else {
        "cluster stages are `samples` (ssd and hybrid only), `histograms` and `solution-00` to `solution-32`"
    };
    Err(PipelineError::NotAClusterStage {
        stage: name.into(),
        hint,
    })
}

/// The stage of a recorded cluster plan, rebuilt with the plan's solver parameters.
pub(crate) fn stage_of_plan(store: &Store, stage: &str, gpu: Option<Arc<Gpu>>) -> Result<Box<dyn Stage>> {
    let plan = store
        .cluster_plan(stage)?
        .ok_or_else(|| PipelineError::NoPlan { stage: stage.into() })?;
    // Plans recorded before the method existed hold the parameters alone: TGV.
    let (params, method): (SolveParams, Method) = match crate::store::catalog::decode("cluster plan args", &plan.args) {
        Ok(both) => both,
        Err(_) => (
            crate::store::catalog::decode("cluster plan args", &plan.args)?,
            Method::Tgv,
        ),
    };
    cluster_stage(store, stage, params, method, gpu)
}

/// Options of the generated Slurm job chain.
#[derive(Clone, Debug)]
pub struct SlurmOptions {
    /// Tasks of each job array.
    pub chunks: u32,
    /// The Slurm partition, if not the default.
    pub partition: Option<String>,
    /// Extra `#SBATCH` options, verbatim (for example `--time=01:00:00`).
    pub sbatch_args: Vec<String>,
    /// The `octstore` binary the jobs run (the same on every node).
    pub binary: PathBuf,
    /// The solver's parameters.
    pub params: SolveParams,
    /// The energy the levels minimise; ssd and hybrid add the samples stage after the octree.
    pub method: Method,
    /// Bytes each job may use.
    pub memory_budget: u64,
    /// Treetop leaf size of the octree job.
    pub leaf_cubes: u64,
    /// `--device` of the work jobs of the histograms and the levels.
    pub device: DeviceChoice,
    /// Extract the mesh into this file at the end of the chain.
    pub output: Option<PathBuf>,
}

/// One job of the chain: its name, whether it is an array of `chunks` tasks, and its script.
#[derive(Clone, Debug, PartialEq)]
pub struct SlurmJob {
    /// The job's name (`octree`, `histograms-plan`, `solution-05-work`, ...).
    pub name: String,
    /// Tasks of a job array; `None` for a single task.
    pub array: Option<u32>,
    /// The batch script.
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
pub fn slurm_jobs(store: &Path, levels: u8, options: &SlurmOptions) -> Vec<SlurmJob> {
    let store = shell_quote(&store.display().to_string());
    let bin = shell_quote(&options.binary.display().to_string());
    let p = options.params;
    // The method by name, always: `plan`'s default would decide it again from the capture.
    let mut solver = format!(
        "--alpha1 {} --alpha0 {} --lambda {} --iterations {} --method {}",
        p.alpha1,
        p.alpha0,
        p.lambda,
        p.iterations,
        options.method.name()
    );
    if let Some(ssd) = options.method.ssd() {
        solver.push_str(&format!(
            " --ssd-normal-weight {} --ssd-smoothness {} --ssd-tolerance {}",
            ssd.normal_weight, ssd.smoothness, ssd.tolerance
        ));
    }
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
    let stages = options
        .method
        .ssd()
        .map(|_| SAMPLES.to_string())
        .into_iter()
        .chain(std::iter::once(HISTOGRAMS.to_string()))
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
const UNIT_MESH_MAGIC: &[u8; 8] = b"OCTMESH2";

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
/// Also gives each unit's cubes in plan order (the treetop unit's rows), which the catalog does
/// not record.
pub fn plan_extract(
    store: &Store,
    chunks: u32,
    mut options: ExtractOptions,
    output: PathBuf,
) -> Result<(ClusterPlan, Vec<u64>)> {
    let scene = required_scene(store, EXTRACT)?;
    let snapshot = store.latest()?;
    // As `octstore extract`: a solution older than the latest ingest is refused, not meshed.
    crate::query::ensure_solution_is_current(&snapshot)?;
    let finest = octree_max_depth(store)?;
    let treetop = Treetop::of(&snapshot)?;
    let units = extract_units(&snapshot, &treetop, &scene, finest, options.region)?;
    // Decided once, here: every worker meshes what the plan records.
    options.surface = options.surface.resolve(&snapshot)?.into();
    let cubes = units
        .iter()
        .map(|&u| treetop.units.get(u).map_or(0, |unit| unit.record.rows))
        .collect();
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
    Ok((plan, cubes))
}

/// The extraction plan, checked against the store it was made for.
fn checked_extract_plan(store: &Store) -> Result<(ClusterPlan, ExtractPlanArgs, u8)> {
    let plan = store.recorded_plan(EXTRACT)?;
    let args: ExtractPlanArgs = crate::store::catalog::decode("cluster plan args", &plan.args)?;
    let snapshot = store.latest()?;
    crate::query::ensure_solution_is_current(&snapshot)?;
    let finest = octree_max_depth(store)?;
    if snapshot.version() != plan.base_version || extract_fingerprint(&snapshot, finest, &args) != plan.fingerprint {
        return Err(PipelineError::StalePlan);
    }
    Ok((plan, args, finest))
}

/// The error naming the chunks of `units`, whose mesh pieces in `dir` do not decode, and the
/// pieces' files.
fn damaged_units_error(plan: &ClusterPlan, dir: &Path, units: &[u64]) -> crate::store::StoreError {
    let chunks = units.iter().map(|&unit| plan.chunk_of(unit)).collect();
    let files: Vec<PathBuf> = units.iter().map(|&unit| dir.join(unit_mesh_name(unit))).collect();
    plan.missing_chunks_error(&chunks, &files)
}

fn unit_mesh_name(unit: u64) -> String {
    format!("u{unit:010}.mesh")
}

/// Extracts chunk `chunk`'s units into the chunk folder (read-only on the catalog; safe to
/// repeat and to run twice).
pub fn work_extract(store: &Store, chunk: u32) -> Result<WorkReport> {
    let (plan, args, finest) = checked_extract_plan(store)?;
    plan.check_chunk(chunk)?;
    let scene = required_scene(store, EXTRACT)?;
    let snapshot = store.latest()?;
    let treetop = Treetop::of(&snapshot)?;
    let dir = store.chunk_dir(&plan);
    std::fs::create_dir_all(&dir).map_err(io_error("create directory", &dir))?;
    let units = plan.chunk_units(chunk);
    // The plan holds the decided surface, so this reads no depth map.
    let surface = args.options.surface.resolve(&snapshot)?;
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
        let mesh = unit_mesh(&snapshot, &treetop, &scene, finest, unit as usize, surface)?;
        store.write_chunk_file(&dir, &name, &encode_chunk_file(UNIT_MESH_MAGIC, &mesh))?;
    }
    Ok(WorkReport {
        units: units.len(),
        skipped,
    })
}

/// Welds every unit's piece into the planned mesh file, exactly as `octstore extract` would
/// (simplified, and cut to the region, as planned; within `memory_budget`); names the missing
/// or damaged chunks instead when there are any.
pub fn commit_extract(store: &Store, memory_budget: u64) -> Result<(MeshSummary, PathBuf)> {
    let (plan, args, finest) = checked_extract_plan(store)?;
    let scene = required_scene(store, EXTRACT)?;
    let dir = store.chunk_dir(&plan);
    let read = |unit: u64| -> Option<UnitMesh> {
        std::fs::read(dir.join(unit_mesh_name(unit)))
            .ok()
            .and_then(|b| decode_chunk_file::<UnitMesh>(UNIT_MESH_MAGIC, &b))
    };
    let absent: Vec<u64> = plan
        .units
        .iter()
        .copied()
        .filter(|&unit| !dir.join(unit_mesh_name(unit)).is_file())
        .collect();
    if !absent.is_empty() {
        let chunks = absent.iter().map(|&unit| plan.chunk_of(unit)).collect();
        let files: Vec<PathBuf> = absent.iter().map(|&unit| dir.join(unit_mesh_name(unit))).collect();
        return Err(plan.missing_chunks_error(&chunks, &files).into());
    }
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
                damaged.borrow_mut().insert(unit);
                None
            }
        }
    });
    // A damaged piece ends the stream with an error after the last piece, so the mesh file
    // is abandoned before its rename: whatever the output path held stays as it was.
    let refuse_if_damaged = std::iter::once(()).filter(|()| !damaged.borrow().is_empty()).map(|()| {
        Err(crate::store::StoreError::Stage {
            stage: "extract".into(),
            unit: "-".into(),
            error: Box::new(StageError::internal("damaged chunks")),
        })
    });
    let written = write_pieces(
        pieces.chain(refuse_if_damaged),
        &treetop,
        &scene,
        finest,
        &args.options,
        &args.output,
        memory_budget,
        // The pieces come from files, read as the weld takes them: nothing waits to give way.
        &|_| {},
    );
    let damaged: Vec<u64> = damaged.into_inner().into_iter().collect();
    if !damaged.is_empty() {
        return Err(damaged_units_error(&plan, &dir, &damaged).into());
    }
    let summary = written?;
    store.remove_cluster_plan(&plan)?;
    Ok((summary, args.output))
}

/// Submits the chain with `sbatch --parsable`, each job after the previous one succeeded, and
/// hands `on_submitted` each job's name and id as soon as it is submitted (so the ids of the jobs
/// already queued are known even when a later submission fails). The scripts are kept in
/// `STORE/slurm/`.
pub fn submit_slurm_jobs(store: &Path, jobs: &[SlurmJob], mut on_submitted: impl FnMut(&str, &str)) -> Result<()> {
    let scripts = store.join("slurm");
    std::fs::create_dir_all(&scripts).map_err(io_error("create directory", &scripts))?;
    let mut previous: Option<String> = None;
    for job in jobs {
        let path = scripts.join(format!("{}.sh", job.name));
        std::fs::write(&path, &job.script).map_err(io_error("write job script", &path))?;
        let mut command = std::process::Command::new("sbatch");
        command
            .arg("--parsable")
            .arg(format!("--output={}/%x-%A_%a.out", scripts.display()));
        if let Some(id) = &previous {
            command.arg(format!("--dependency=afterok:{id}"));
        }
        let output = command.arg(&path).output().map_err(io_error("run sbatch", &path))?;
        if !output.status.success() {
            return Err(PipelineError::Sbatch {
                job: job.name.clone(),
                message: String::from_utf8_lossy(&output.stderr).trim().to_string(),
            });
        }
        let id = String::from_utf8_lossy(&output.stdout)
            .trim()
            .split(';')
            .next()
            .unwrap_or_default()
            .to_string();
        on_submitted(&job.name, &id);
        previous = Some(id);
    }
    Ok(())
}
