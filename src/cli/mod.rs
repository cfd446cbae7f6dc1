//! The `octstore` command line.

use crate::pipeline;
use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Args, Parser, Subcommand};
use serde::Serialize;

use crate::stages::extract::Region;
use crate::stages::histograms::HistogramsStage;
use crate::stages::ingest::{IngestOptions, IngestStage};
use crate::stages::inputs::{DiscoverOptions, InputFormat};
use crate::stages::octree::{self, OctreeStage};
use crate::stages::solve::{LevelStage, SolveParams};
use crate::stages::{self, synthetic::SyntheticStage};
use crate::store::{RunOptions, Store, StoreError};

#[derive(Parser, Debug)]
#[command(
    name = "octstore",
    version,
    about = "Out-of-core surface reconstruction on a versioned octree store"
)]
pub struct Cli {
    #[command(flatten)]
    pub global: GlobalOptions,
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Args, Debug, Clone)]
pub struct GlobalOptions {
    /// Memory the whole process may use, e.g. 512MiB, 1GiB.
    #[arg(long, global = true, default_value = "1GiB", value_parser = parse_size)]
    pub memory_budget: u64,
    /// Worker threads (default: all cores).
    #[arg(long, global = true)]
    pub threads: Option<usize>,
    /// No progress bars.
    #[arg(long, global = true)]
    pub quiet: bool,
}

pub use crate::pipeline::SolveUntil as SolveStage;

/// Solver parameters of a cluster plan (the same as `solve`'s).
#[derive(clap::Args, Debug, Clone, Copy)]
pub struct SolverArgs {
    /// TGV weight of |grad u - v| (times the cube side).
    #[arg(long, default_value_t = SolveParams::default().alpha1)]
    alpha1: f32,
    /// TGV weight of |E(v)| (times the cube side squared).
    #[arg(long, default_value_t = SolveParams::default().alpha0)]
    alpha0: f32,
    /// Weight of the histogram data term.
    #[arg(long, default_value_t = SolveParams::default().lambda)]
    lambda: f32,
    /// Primal-dual iterations per level.
    #[arg(long, default_value_t = SolveParams::default().iterations)]
    iterations: u32,
}

impl SolverArgs {
    fn params(self) -> SolveParams {
        SolveParams {
            alpha1: self.alpha1,
            alpha0: self.alpha0,
            lambda: self.lambda,
            iterations: self.iterations,
        }
    }
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Register depth maps and write their cubes (one sorted run per depth map). Run it again
    /// with more depth maps later: the store grows incrementally.
    Ingest {
        store: PathBuf,
        #[arg(required = true)]
        inputs: Vec<PathBuf>,
        #[arg(long, value_enum, default_value = "auto")]
        format: InputFormat,
        /// Take every n-th frame of a folder.
        #[arg(long, default_value_t = 1)]
        stride: usize,
        /// Take at most this many frames of a folder.
        #[arg(long)]
        limit: Option<usize>,
        /// Root cube as minx,miny,minz,side (first ingest only; default: the samples' bounding
        /// box grown by --root-margin).
        #[arg(long, value_parser = parse_root)]
        root: Option<([f64; 3], f64)>,
        #[arg(long, default_value_t = 0.1)]
        root_margin: f64,
        /// Deepest octree level a sample may create (first ingest only).
        #[arg(long, default_value_t = 24)]
        max_depth: u8,
        #[arg(long)]
        resume: bool,
    },
    /// Bring everything derived up to date: the octree and its treetop, the histograms, then
    /// the TGV solution level by level.
    Solve {
        store: PathBuf,
        /// Continue an interrupted run from its last committed unit.
        #[arg(long)]
        resume: bool,
        /// Run the pending stages up to and including this one.
        #[arg(long, value_enum, default_value = "solution")]
        until: SolveStage,
        #[command(flatten)]
        solver: SolverArgs,
        /// Treetop leaves hold fewer cubes than this.
        #[arg(long, default_value_t = octree::DEFAULT_LEAF_CUBES)]
        leaf_cubes: u64,
        /// Where the histogram votes and the TGV iterations run: auto takes a hardware GPU
        /// when there is one (never a software rasteriser), gpu any adapter (llvmpipe
        /// included), cpu the CPU code.
        #[arg(long, value_enum, default_value = "auto")]
        device: crate::gpu::DeviceChoice,
    },
    /// Cluster run, step 1: split a stage's pending units into chunks and record the plan.
    Plan {
        store: PathBuf,
        /// `histograms`, `solution-LL` or `extract`.
        #[arg(long)]
        stage: String,
        #[arg(long, default_value_t = 16)]
        chunks: u32,
        #[command(flatten)]
        solver: SolverArgs,
        /// extract: the mesh file the commit writes.
        #[arg(short, long, required_if_eq("stage", "extract"))]
        output: Option<PathBuf>,
        /// extract: only what lies in this box.
        #[arg(long, value_parser = parse_region)]
        region: Option<Region>,
        /// extract: keep about this fraction of each leaf's triangles.
        #[arg(long, value_parser = parse_ratio)]
        decimate: Option<f32>,
    },
    /// Cluster run, step 2: compute one chunk of the recorded plan (read-only on the catalog;
    /// writes only segment files; safe to retry or to run twice).
    Work {
        store: PathBuf,
        #[arg(long)]
        stage: String,
        #[arg(long)]
        chunk: u32,
        /// Where this chunk's votes and iterations run, as for `solve`. Every chunk of a stage
        /// should use the same kind of device: GPU votes may differ from the CPU's in rare
        /// boundary cubes.
        #[arg(long, value_enum, default_value = "auto")]
        device: crate::gpu::DeviceChoice,
    },
    /// Cluster run, step 3: verify every chunk's output and commit the stage as one version.
    Commit {
        store: PathBuf,
        #[arg(long)]
        stage: String,
    },
    /// Submit the pipeline after ingest to Slurm as job arrays chained with afterok.
    Slurm {
        store: PathBuf,
        #[arg(long, default_value_t = 16)]
        chunks: u32,
        #[arg(long)]
        partition: Option<String>,
        /// Extra sbatch option for every job, e.g. --sbatch-arg=--time=02:00:00 (repeatable).
        #[arg(long = "sbatch-arg", allow_hyphen_values = true)]
        sbatch_args: Vec<String>,
        /// Print the job scripts instead of submitting them.
        #[arg(long)]
        dry_run: bool,
        /// Treetop leaves of the octree job hold fewer cubes than this.
        #[arg(long, default_value_t = octree::DEFAULT_LEAF_CUBES)]
        leaf_cubes: u64,
        /// Also extract the mesh into this file, chunked like the other stages.
        #[arg(short, long)]
        output: Option<PathBuf>,
        #[command(flatten)]
        solver: SolverArgs,
        /// `--device` of the work jobs (ask Slurm for GPUs with --sbatch-arg=--gres=gpu:1).
        #[arg(long, value_enum, default_value = "auto")]
        device: crate::gpu::DeviceChoice,
    },
    /// Render the built-in synthetic scene, then ingest, solve and extract it (no files needed).
    Demo {
        /// Output folder: depth maps, the store, demo.ply.
        #[arg(long, default_value = "octstore-demo")]
        out: PathBuf,
        /// Primal-dual iterations per level.
        #[arg(long, default_value_t = 100)]
        iterations: u32,
    },
    /// Write the surface u = 0 as a mesh (binary PLY, or OBJ by extension).
    Extract {
        store: PathBuf,
        #[arg(short, long)]
        output: PathBuf,
        /// Only what lies in this box: minx,miny,minz,maxx,maxy,maxz.
        #[arg(long, value_parser = parse_region)]
        region: Option<Region>,
        /// Extract from this version instead of the latest.
        #[arg(long)]
        version: Option<u64>,
        /// Keep about this fraction (0..1] of the triangles: quadric-error simplification per
        /// treetop leaf that never moves a vertex shared with another leaf.
        #[arg(long, value_parser = parse_ratio)]
        decimate: Option<f32>,
    },
    /// The indicator u at a point (interpolated), from the latest or a given version.
    Query {
        store: PathBuf,
        /// x,y,z in world coordinates.
        #[arg(long, value_parser = parse_point, required_unless_present_any = ["levels", "leaves"])]
        point: Option<[f64; 3]>,
        #[arg(long)]
        version: Option<u64>,
        #[arg(long)]
        json: bool,
        /// List the solved levels (JSON).
        #[arg(long)]
        levels: bool,
        /// List the treetop leaves: key, depth, min corner, size, cubes (JSON).
        #[arg(long)]
        leaves: bool,
    },
    /// Render a mesh (PLY, OFF or OBJ, optionally .gz) as a shaded PNG.
    Render {
        mesh: PathBuf,
        #[arg(short, long)]
        output: PathBuf,
        #[arg(long, default_value_t = 800)]
        width: u32,
        #[arg(long, default_value_t = 600)]
        height: u32,
        /// Take the picture from this camera instead of the fitted 3/4 view: a text file of 16
        /// numbers, the camera-to-world 4x4 matrix row by row, OpenCV axes (a 7-Scenes
        /// `frame-*.pose.txt` as is).
        #[arg(long)]
        pose: Option<PathBuf>,
        /// Focal length in pixels for `--pose` (principal point at the image centre).
        #[arg(long, default_value_t = 525.0, requires = "pose")]
        focal: f64,
    },
    /// Summary of a store: version, inputs, cubes, leaves, segments, bytes, content digests.
    Info {
        /// The store; not needed with --devices.
        #[arg(required_unless_present = "devices")]
        store: Option<PathBuf>,
        /// List the GPU adapters wgpu finds (and which one `--device auto` would take).
        #[arg(long)]
        devices: bool,
        #[arg(long)]
        json: bool,
        /// Show this version instead of the latest.
        #[arg(long)]
        version: Option<u64>,
    },
    /// Check every segment byte and every catalog invariant; exits non-zero on any problem.
    Verify { store: PathBuf },
    /// The store's versions, oldest first.
    Log {
        store: PathBuf,
        #[arg(long)]
        json: bool,
    },
    /// Remove segments that no kept version can see.
    Gc {
        store: PathBuf,
        /// Versions to keep readable, counting the latest.
        #[arg(long, default_value_t = 1)]
        keep: u64,
    },
    /// Run the synthetic test stage (exercises the stage runner without input files).
    #[command(hide = true)]
    DebugSynthetic {
        store: PathBuf,
        #[arg(long, default_value_t = 8)]
        units: u32,
        #[arg(long, default_value_t = 2000)]
        rows: u32,
        #[arg(long, default_value_t = 1)]
        seed: u64,
        #[arg(long, default_value_t = 0)]
        delay_ms: u64,
        #[arg(long)]
        resume: bool,
    },
}

fn parse_point(text: &str) -> Result<[f64; 3], String> {
    let v: Vec<f64> = text
        .split(',')
        .map(|t| t.trim().parse::<f64>().map_err(|_| format!("'{t}' is not a number")))
        .collect::<Result<_, _>>()?;
    match v[..] {
        [x, y, z] => Ok([x, y, z]),
        _ => Err("expected x,y,z".into()),
    }
}

fn save_png(image: &image::RgbImage, path: &std::path::Path) -> Result<(), StoreError> {
    image.save(path).map_err(|e| StoreError::Io {
        action: "write image",
        path: path.to_path_buf(),
        source: std::io::Error::other(e.to_string()),
    })
}

fn parse_region(text: &str) -> Result<Region, String> {
    let v: Vec<f64> = text
        .split(',')
        .map(|t| t.trim().parse::<f64>().map_err(|_| format!("'{t}' is not a number")))
        .collect::<Result<_, _>>()?;
    match v[..] {
        [a, b, c, d, e, f] if a < d && b < e && c < f => Ok(Region {
            min: glam::DVec3::new(a, b, c),
            max: glam::DVec3::new(d, e, f),
        }),
        _ => Err("expected minx,miny,minz,maxx,maxy,maxz with min < max".into()),
    }
}

/// Extracts the latest (or a given) version's surface into `output`; prints a summary.
pub fn extract_to(
    store: &Store,
    output: &std::path::Path,
    options: &stages::extract::ExtractOptions,
    version: Option<u64>,
) -> Result<stages::extract::MeshSummary, StoreError> {
    let started = std::time::Instant::now();
    let scene = stages::ingest::read_scene(store)?.ok_or_else(|| StoreError::Stage {
        stage: "extract".into(),
        unit: "-".into(),
        message: "the store has no depth maps yet".into(),
    })?;
    let snapshot = match version {
        Some(v) => store.snapshot(v)?,
        None => store.latest()?,
    };
    let finest = stages::octree_max_depth(store)?;
    let summary = stages::extract::extract_to_file(&snapshot, &scene, finest, options, output)?;
    print_extract_summary(&summary, output, started);
    Ok(summary)
}

fn print_extract_summary(
    summary: &stages::extract::MeshSummary,
    output: &std::path::Path,
    started: std::time::Instant,
) {
    println!(
        "extract    {} vertices, {} triangles, {} boundary edges, {} non-manifold edges -> {} | {:.2}s | peak memory {:.0} MB",
        summary.vertices,
        summary.triangles,
        summary.boundary_edges,
        summary.non_manifold_edges,
        output.display(),
        started.elapsed().as_secs_f64(),
        peak_rss_bytes() as f64 / 1e6
    );
}

/// The stage of a recorded cluster plan, rebuilt with the plan's solver parameters.
fn cluster_stage_of_plan(
    store: &Store,
    stage: &str,
    gpu: Option<std::sync::Arc<crate::gpu::Gpu>>,
) -> Result<Box<dyn crate::store::Stage>, StoreError> {
    let plan = store.cluster_plan(stage)?.ok_or_else(|| StoreError::Stage {
        stage: stage.into(),
        unit: "plan".into(),
        message: "no cluster plan: run `octstore plan` first".into(),
    })?;
    let params: SolveParams = crate::store::catalog::decode("cluster plan args", &plan.args)?;
    pipeline::cluster_stage(store, stage, params, gpu)
}

/// Submits the chain with `sbatch --parsable`, each job after the previous one succeeded, and
/// prints the job ids.
fn submit_slurm_jobs(store: &std::path::Path, jobs: &[pipeline::SlurmJob]) -> Result<(), StoreError> {
    let scripts = store.join("slurm");
    std::fs::create_dir_all(&scripts).map_err(crate::store::io_error("create directory", &scripts))?;
    let mut previous: Option<String> = None;
    for job in jobs {
        let path = scripts.join(format!("{}.sh", job.name));
        std::fs::write(&path, &job.script).map_err(crate::store::io_error("write job script", &path))?;
        let mut command = std::process::Command::new("sbatch");
        command
            .arg("--parsable")
            .arg(format!("--output={}/%x-%A_%a.out", scripts.display()));
        if let Some(id) = &previous {
            command.arg(format!("--dependency=afterok:{id}"));
        }
        let output = command
            .arg(&path)
            .output()
            .map_err(crate::store::io_error("run sbatch", &path))?;
        if !output.status.success() {
            return Err(StoreError::Stage {
                stage: "slurm".into(),
                unit: job.name.clone(),
                message: format!("sbatch failed: {}", String::from_utf8_lossy(&output.stderr).trim()),
            });
        }
        let id = String::from_utf8_lossy(&output.stdout)
            .trim()
            .split(';')
            .next()
            .unwrap_or_default()
            .to_string();
        println!("{} {id}", job.name);
        previous = Some(id);
    }
    Ok(())
}

fn parse_ratio(text: &str) -> Result<f32, String> {
    match text.trim().parse::<f32>() {
        Ok(r) if r > 0.0 && r <= 1.0 => Ok(r),
        _ => Err(format!("'{text}' is not a ratio in (0, 1]")),
    }
}

fn parse_root(text: &str) -> Result<([f64; 3], f64), String> {
    let v: Vec<f64> = text
        .split(',')
        .map(|t| t.trim().parse::<f64>().map_err(|_| format!("'{t}' is not a number")))
        .collect::<Result<_, _>>()?;
    match v[..] {
        [x, y, z, side] if side > 0.0 && side.is_finite() => Ok(([x, y, z], side)),
        _ => Err("expected minx,miny,minz,side with side > 0".into()),
    }
}

/// Peak resident memory of this process so far, in bytes (Linux; 0 elsewhere).
pub fn peak_rss_bytes() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1).and_then(|v| v.parse::<u64>().ok()))
        })
        .map_or(0, |kb| kb * 1024)
}

fn summary(report: &crate::store::RunReport) {
    println!(
        "{:<10} {} | units {} ({} resumed) | rows {} | {:.2}s | peak memory {:.0} MB",
        report.stage,
        match report.version {
            Some(v) => format!("version {v}: {}", report.summary),
            None => report.summary.clone(),
        },
        report.units,
        report.resumed_units,
        report.rows,
        report.seconds,
        peak_rss_bytes() as f64 / 1e6
    );
}

/// Parses sizes like `512MiB`, `1GiB`, `1.5G`, `4096`.
pub fn parse_size(text: &str) -> Result<u64, String> {
    let text = text.trim();
    let split = text
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .unwrap_or(text.len());
    let (number, unit) = text.split_at(split);
    let value: f64 = number
        .parse()
        .map_err(|_| format!("'{text}' is not a size (examples: 512MiB, 1GiB, 1000000)"))?;
    let scale: f64 = match unit.trim().to_ascii_lowercase().as_str() {
        "" | "b" => 1.0,
        "k" | "kb" => 1e3,
        "kib" => 1024.0,
        "m" | "mb" => 1e6,
        "mib" => 1024.0 * 1024.0,
        "g" | "gb" => 1e9,
        "gib" => 1024.0 * 1024.0 * 1024.0,
        other => {
            return Err(format!(
                "unknown size unit '{other}' (use B, KiB, MiB, GiB, KB, MB, GB)"
            ));
        }
    };
    Ok((value * scale) as u64)
}

#[derive(Serialize, Debug)]
pub struct InfoJson {
    pub store: String,
    pub version: u64,
    pub depth_maps: u64,
    pub cubes: u64,
    pub treetop_leaves: u64,
    pub segments: u64,
    pub bytes: u64,
    /// Content digest per stage (hex), equal for equal content however it was produced.
    pub digest: std::collections::BTreeMap<String, String>,
    /// Side of the root cube in world units (absent before the first ingest).
    pub root_side: Option<f64>,
    /// The deepest solved level and the side of its cubes in world units (absent before a solve).
    pub finest_level: Option<u8>,
    pub finest_cube_side: Option<f64>,
}

pub fn info(store: &Store, version: Option<u64>) -> Result<InfoJson, StoreError> {
    use crate::IndicatorField;
    let snapshot = match version {
        Some(v) => store.snapshot(v)?,
        None => store.latest()?,
    };
    let digest = snapshot
        .stages()
        .map(|stage| (stage.to_string(), format!("{:016x}", snapshot.digest(stage))))
        .collect();
    let scene = stages::ingest::read_scene(store)?;
    let finest_level = snapshot.finest_level();
    Ok(InfoJson {
        root_side: scene.map(|s| s.root_side),
        finest_level,
        finest_cube_side: scene.zip(finest_level).map(|(s, level)| s.cube_side(level)),
        store: store.root().display().to_string(),
        version: snapshot.version(),
        depth_maps: stages::ingest::registered_depth_maps(store)?
            .iter()
            .filter(|(_, r)| r.added_in <= snapshot.version())
            .count() as u64,
        cubes: snapshot.rows(stages::OCTREE),
        treetop_leaves: {
            // One segment per treetop leaf, plus one for the treetop's internal nodes when the
            // root is not itself the only leaf.
            let n = snapshot.segments(stages::OCTREE).len() as u64;
            if n > 1 { n - 1 } else { n }
        },
        segments: snapshot.all_segments().count() as u64,
        bytes: snapshot.all_segments().map(|(_, r)| r.bytes).sum(),
        digest,
    })
}

fn run_options(global: &GlobalOptions, resume: bool) -> RunOptions {
    RunOptions {
        resume,
        threads: global.threads.unwrap_or_else(rayon::current_num_threads),
        progress: !global.quiet,
    }
}

fn open_or_create(path: &std::path::Path) -> Result<Store, StoreError> {
    if path.join(crate::store::CATALOG_FILE).exists() {
        Store::open(path)
    } else {
        Store::create(path)
    }
}

pub fn run(cli: Cli) -> Result<ExitCode, StoreError> {
    let global = cli.global;
    if let Some(threads) = global.threads {
        // Only the first call configures the global pool; later calls are harmless.
        let _ = rayon::ThreadPoolBuilder::new().num_threads(threads).build_global();
    }
    match cli.command {
        Command::Ingest {
            store,
            inputs,
            format,
            stride,
            limit,
            root,
            root_margin,
            max_depth,
            resume,
        } => {
            let discover = DiscoverOptions { format, stride, limit };
            let store = open_or_create(&store)?;
            let options = IngestOptions {
                root,
                root_margin,
                max_depth,
            };
            let report = pipeline::ingest(&store, &inputs, &discover, &options, &run_options(&global, resume))?;
            summary(&report);
        }
        Command::Solve {
            store,
            resume,
            until,
            leaf_cubes,
            solver,
            device,
        } => {
            let store = Store::open(&store)?;
            let options = pipeline::SolveOptions {
                until,
                leaf_cubes,
                memory_budget: global.memory_budget,
                params: solver.params(),
                run: run_options(&global, resume),
                device,
            };
            pipeline::solve(&store, &options, summary)?;
        }
        Command::Plan {
            store,
            stage,
            chunks,
            solver,
            output,
            region,
            decimate,
        } => {
            let store = Store::open(&store)?;
            if stage == pipeline::EXTRACT {
                let output = output.unwrap_or_else(|| PathBuf::from("mesh.ply"));
                let output = std::path::absolute(&output).map_err(crate::store::io_error("resolve", &output))?;
                let options = stages::extract::ExtractOptions { region, decimate };
                let plan = pipeline::plan_extract(&store, chunks, options, output.clone())?;
                println!(
                    "plan extract: {} unit(s) in {} chunk(s) at version {} -> {}",
                    plan.units.len(),
                    plan.chunks,
                    plan.base_version,
                    output.display()
                );
                return Ok(ExitCode::SUCCESS);
            }
            let params = solver.params();
            let runnable = pipeline::cluster_stage(&store, &stage, params, None)?;
            let plan = store.plan_cluster_run(runnable.as_ref(), chunks, crate::store::catalog::encode(&params))?;
            println!(
                "plan {stage}: {} pending unit(s) in {} chunk(s), base version {}, target {}",
                plan.units.len(),
                plan.chunks,
                plan.base_version,
                plan.target()
            );
            for chunk in 0..plan.chunks {
                println!("  chunk {chunk}: {} unit(s)", plan.chunk_units(chunk).len());
            }
        }
        Command::Work {
            store,
            stage,
            chunk,
            device,
        } => {
            let store = Store::open_read_only(&store)?;
            let started = std::time::Instant::now();
            let mut on_device = String::new();
            let report = if stage == pipeline::EXTRACT {
                pipeline::work_extract(&store, chunk)?
            } else {
                let gpu = pipeline::open_gpu(device)?;
                let runnable = cluster_stage_of_plan(&store, &stage, gpu.clone())?;
                let report = store.work_cluster_chunk(runnable.as_ref(), chunk)?;
                if let Some(gpu) = gpu {
                    let (units, fallbacks) = gpu.counts();
                    on_device = format!(" ({units} on {}, {fallbacks} fell back to the CPU)", gpu.adapter.name);
                }
                report
            };
            println!(
                "work {stage} chunk {chunk}: {} unit(s){on_device}, {} already done | {:.2}s | peak memory {:.0} MB",
                report.units,
                report.skipped,
                started.elapsed().as_secs_f64(),
                peak_rss_bytes() as f64 / 1e6
            );
        }
        Command::Commit { store, stage } => {
            let store = Store::open(&store)?;
            if stage == pipeline::EXTRACT {
                let started = std::time::Instant::now();
                let (summary, output) = pipeline::commit_extract(&store)?;
                print_extract_summary(&summary, &output, started);
                return Ok(ExitCode::SUCCESS);
            }
            let runnable = cluster_stage_of_plan(&store, &stage, None)?;
            let report = store.commit_cluster_run(runnable.as_ref(), &run_options(&global, false))?;
            summary(&report);
        }
        Command::Slurm {
            store,
            chunks,
            partition,
            sbatch_args,
            dry_run,
            leaf_cubes,
            output,
            solver,
            device,
        } => {
            let opened = Store::open_read_only(&store)?;
            let scene = stages::ingest::read_scene(&opened)?.ok_or_else(|| StoreError::Stage {
                stage: "slurm".into(),
                unit: "-".into(),
                message: "the store has no depth maps yet: run `octstore ingest` first".into(),
            })?;
            drop(opened);
            let options = pipeline::SlurmOptions {
                chunks,
                partition,
                sbatch_args,
                binary: std::env::current_exe().map_err(crate::store::io_error("locate octstore", &store))?,
                params: solver.params(),
                memory_budget: global.memory_budget,
                leaf_cubes,
                device,
                output: output
                    .map(|o| std::path::absolute(&o).map_err(crate::store::io_error("resolve", &o)))
                    .transpose()?,
            };
            let store_path = std::path::absolute(&store).map_err(crate::store::io_error("resolve", &store))?;
            let jobs = pipeline::slurm_jobs(&store_path, scene.max_depth, &options);
            if dry_run {
                for job in &jobs {
                    println!(
                        "# ---- {}{}",
                        job.name,
                        if job.array.is_some() { " (array)" } else { "" }
                    );
                    println!("{}", job.script);
                }
            } else {
                submit_slurm_jobs(&store_path, &jobs)?;
            }
        }
        Command::Demo { out, iterations } => {
            let started = std::time::Instant::now();
            let spec = crate::scenes::SceneSpec::demo();
            let manifest = spec
                .write(&out.join("input"))
                .map_err(crate::store::io_error("write demo input", &out))?;
            println!(
                "demo: rendered {} depth maps of {}x{} into {}",
                spec.cameras,
                spec.width,
                spec.height,
                out.join("input").display()
            );
            let store_path = out.join("store");
            if store_path.exists() {
                std::fs::remove_dir_all(&store_path).map_err(crate::store::io_error("remove", &store_path))?;
            }
            let store = Store::create(&store_path)?;
            let sources =
                stages::inputs::discover(&[manifest], &DiscoverOptions::default()).map_err(|e| StoreError::Stage {
                    stage: stages::INGEST.into(),
                    unit: "demo inputs".into(),
                    message: e.to_string(),
                })?;
            let options = IngestOptions {
                root: None,
                root_margin: 0.05,
                max_depth: 9,
            };
            let ingest = IngestStage::prepare(&store, sources, &options)?;
            let run = run_options(&global, false);
            summary(&store.run_stage(&ingest, &run)?);
            let scene = *ingest.scene();
            let scratch = store.scratch_dir(stages::OCTREE)?;
            let leaf_cubes = octree::effective_leaf_cubes(20_000, global.memory_budget, run.threads);
            let octree_stage = OctreeStage::new(scene, leaf_cubes, global.memory_budget / 4, scratch.clone());
            summary(&store.run_stage(&octree_stage, &run)?);
            let _ = std::fs::remove_dir_all(scratch);
            let histograms = HistogramsStage::new(scene, stages::ingest::registered_depth_maps(&store)?);
            summary(&store.run_stage(&histograms, &run)?);
            let params = SolveParams {
                iterations,
                ..SolveParams::default()
            };
            for level in 0..=stages::octree_max_depth(&store)? {
                summary(&store.run_stage(&LevelStage::new(level, scene, params), &run)?);
            }
            extract_to(&store, &out.join("demo.ply"), &Default::default(), None)?;
            let mesh = stages::extract::read_ply(&out.join("demo.ply")).map_err(|message| StoreError::Stage {
                stage: "demo".into(),
                unit: "demo.ply".into(),
                message,
            })?;
            // The preview shows the objects, not the room around them.
            let objects = Region {
                min: glam::DVec3::new(-0.7, -0.6, -0.45),
                max: glam::DVec3::new(0.7, 0.6, 0.85),
            };
            let preview = stages::extract::clip(&mesh, objects);
            save_png(&crate::render::render(&preview, 800, 600), &out.join("demo.png"))?;
            println!(
                "demo: wrote {} and {}",
                out.join("demo.ply").display(),
                out.join("demo.png").display()
            );
            println!(
                "demo: done in {:.1}s; store at {}",
                started.elapsed().as_secs_f64(),
                store_path.display()
            );
        }
        Command::Extract {
            store,
            output,
            region,
            version,
            decimate,
        } => {
            let store = Store::open_for_reading(&store)?;
            let options = stages::extract::ExtractOptions { region, decimate };
            extract_to(&store, &output, &options, version)?;
        }
        Command::Query {
            store,
            point,
            version,
            json,
            levels,
            leaves,
        } => {
            use crate::IndicatorField;
            let store = Store::open_for_reading(&store)?;
            let snapshot = match version {
                Some(v) => store.snapshot(v)?,
                None => store.latest()?,
            };
            if leaves || levels {
                let value = serde_json::json!({
                    "version": snapshot.version(),
                    "levels": snapshot.levels(),
                    "leaves": if leaves { Some(snapshot.leaves()?) } else { None },
                });
                println!("{}", serde_json::to_string_pretty(&value).unwrap_or_default());
                return Ok(ExitCode::SUCCESS);
            }
            let Some(point) = point else {
                return Err(StoreError::Stage {
                    stage: "query".into(),
                    unit: "-".into(),
                    message: "give --point x,y,z (or --levels / --leaves)".into(),
                });
            };
            let u = snapshot.indicator_at(glam::DVec3::from_array(point))?;
            if json {
                let value = serde_json::json!({"version": snapshot.version(), "point": point, "u": u, "level": snapshot.finest_level()});
                println!("{value}");
            } else {
                match u {
                    Some(u) => println!(
                        "u = {u:.6} ({}) at version {}",
                        if u < 0.0 { "inside" } else { "outside" },
                        snapshot.version()
                    ),
                    None => println!("no value: the point is outside the root cube, or nothing is solved yet"),
                }
            }
        }
        Command::Render {
            mesh,
            output,
            width,
            height,
            pose,
            focal,
        } => {
            let render_error = |unit: &std::path::Path, message: String| StoreError::Stage {
                stage: "render".into(),
                unit: unit.display().to_string(),
                message,
            };
            let view = match pose {
                None => crate::render::View::Fitted,
                Some(path) => {
                    let text = std::fs::read_to_string(&path).map_err(|e| render_error(&path, e.to_string()))?;
                    let numbers = text
                        .split_whitespace()
                        .map(str::parse::<f64>)
                        .collect::<std::result::Result<Vec<f64>, _>>()
                        .map_err(|e| render_error(&path, format!("not a 4x4 matrix of numbers: {e}")))?;
                    let rows: [f64; 16] = numbers.try_into().map_err(|n: Vec<f64>| {
                        render_error(&path, format!("expected 16 numbers (a 4x4 matrix), found {}", n.len()))
                    })?;
                    let camera_to_world = glam::DMat4::from_cols_array(&rows).transpose();
                    if camera_to_world.determinant().abs().is_nan() || camera_to_world.determinant().abs() <= 1e-9 {
                        return Err(render_error(&path, "the pose is not invertible".into()));
                    }
                    crate::render::View::Pinhole { camera_to_world, focal }
                }
            };
            let mesh = crate::quality::meshio::read_mesh(&mesh).map_err(|message| render_error(&mesh, message))?;
            save_png(&crate::render::render_view(&mesh, width, height, view), &output)?;
        }
        Command::Info {
            devices: true, json, ..
        } => {
            let adapters = crate::gpu::adapters();
            if json {
                println!("{}", serde_json::to_string_pretty(&adapters).unwrap_or_default());
            } else if adapters.is_empty() {
                println!("no GPU adapters (solve runs on the CPU; WGPU_BACKEND chooses backends)");
            } else {
                let auto = adapters.iter().position(|a| !a.software);
                for (index, a) in adapters.iter().enumerate() {
                    let mark = if Some(index) == auto { "  <- --device auto" } else { "" };
                    println!(
                        "{index}: {} ({}, {}{}, {}; storage bindings up to {} MiB){mark}",
                        a.name,
                        a.backend,
                        a.device_type,
                        if a.software { ", software" } else { "" },
                        a.driver,
                        a.max_storage_binding >> 20
                    );
                }
            }
        }
        Command::Info {
            store, json, version, ..
        } => {
            let store = store.ok_or_else(|| StoreError::Stage {
                stage: "info".into(),
                unit: "arguments".into(),
                message: "give a store, or --devices".into(),
            })?;
            let store = Store::open_for_reading(&store)?;
            let info = info(&store, version)?;
            if json {
                println!("{}", serde_json::to_string_pretty(&info).unwrap_or_default());
            } else {
                println!("store          {}", info.store);
                println!("version        {}", info.version);
                println!("depth maps     {}", info.depth_maps);
                println!("cubes          {}", info.cubes);
                println!("treetop leaves {}", info.treetop_leaves);
                println!("segments       {} ({} bytes)", info.segments, info.bytes);
                if let Some(side) = info.root_side {
                    println!("root side      {side}");
                }
                if let (Some(level), Some(side)) = (info.finest_level, info.finest_cube_side) {
                    println!("finest level   {level} (cubes of side {side})");
                }
                for (stage, digest) in &info.digest {
                    println!("digest         {stage:<12} {digest}");
                }
            }
        }
        Command::Verify { store } => {
            // Writable: recovers the catalog after a crash and removes crash debris first.
            let store = Store::open(&store)?;
            let report = store.verify(&[stages::octree::verify_octree])?;
            for problem in &report.problems {
                eprintln!("error: {problem}");
            }
            if !report.is_ok() {
                eprintln!(
                    "verify: {} problem(s) in {} segment(s) of {}",
                    report.problems.len(),
                    report.segments,
                    store.root().display()
                );
                return Ok(ExitCode::FAILURE);
            }
            println!(
                "verify: ok: {} segment(s), {} rows, {} bytes",
                report.segments, report.rows, report.bytes
            );
        }
        Command::Log { store, json } => {
            let store = Store::open_for_reading(&store)?;
            let log = store.log()?;
            if json {
                let rows: Vec<serde_json::Value> = log
                    .iter()
                    .map(|(v, r, t)| {
                        serde_json::json!({"version": v, "parent": r.parent, "kind": r.kind, "summary": r.summary, "unix_ms": t})
                    })
                    .collect();
                println!("{}", serde_json::to_string_pretty(&rows).unwrap_or_default());
            } else {
                for (version, record, time) in log {
                    let when = time.map(|t| format!("{:.3}s", t as f64 / 1000.0)).unwrap_or_default();
                    println!("{version:>6}  {:<12} {}  (unix {when})", record.kind, record.summary);
                }
            }
        }
        Command::Gc { store, keep } => {
            let store = Store::open(&store)?;
            let (files, bytes) = store.gc(keep)?;
            println!("gc: removed {files} segment file(s), {bytes} bytes");
        }
        Command::DebugSynthetic {
            store,
            units,
            rows,
            seed,
            delay_ms,
            resume,
        } => {
            let store = open_or_create(&store)?;
            let stage = SyntheticStage {
                units,
                rows_per_unit: rows,
                seed,
                delay_ms,
            };
            let report = store.run_stage(&stage, &run_options(&global, resume))?;
            println!(
                "{}: version {:?}, {} unit(s) ({} resumed), {} rows, {:.2}s",
                report.stage, report.version, report.units, report.resumed_units, report.rows, report.seconds
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}
