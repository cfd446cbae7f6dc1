//! The command line's arguments: global options, one struct per verb.

use std::path::PathBuf;

use clap::{Args, Parser, Subcommand};

use super::parse::{
    parse_depth_noise, parse_iterations, parse_margin, parse_max_error, parse_memory_budget, parse_mesh_path,
    parse_noise_sigmas, parse_overlap, parse_point, parse_positive, parse_ratio, parse_region, parse_root,
    parse_ssd_tolerance, parse_ssd_weight, parse_threads, parse_tolerance, parse_weight,
};
use crate::format::BoundingBox;
use crate::inputs::InputFormat;
use crate::stages::extract::{Simplify, SurfaceChoice};
use crate::stages::octree;
use crate::stages::solve::{Method, MethodChoice, SolveParams, SsdParams};

#[derive(Parser, Debug)]
#[command(
    name = "octstore",
    version,
    about = "Out-of-core surface reconstruction on a versioned octree store"
)]
/// The whole command line: global options and one verb.
pub struct Cli {
    /// Options that apply to every verb.
    #[command(flatten)]
    pub global: GlobalOptions,
    /// The verb and its arguments.
    #[command(subcommand)]
    pub command: Command,
}

/// Options that apply to every verb (before or after it).
#[derive(Args, Debug, Clone)]
pub struct GlobalOptions {
    /// Memory the whole process may use, e.g. 512MiB, 1GiB.
    #[arg(long, global = true, default_value = "1GiB", value_parser = parse_memory_budget)]
    pub memory_budget: u64,
    /// Worker threads (default: all cores; at most 4 times the cores).
    #[arg(long, global = true, value_parser = parse_threads)]
    pub threads: Option<usize>,
    /// No progress bars and no informational log lines on stderr (warnings and errors still
    /// print; the OCTSTORE_LOG variable, when set, decides instead).
    #[arg(long, global = true)]
    pub quiet: bool,
}

use crate::pipeline::SolveUntil;

/// Solver parameters and method of `solve`, a cluster plan and a Slurm chain.
#[derive(clap::Args, Debug, Clone, Copy)]
pub struct SolverArgs {
    /// TGV weight of |grad u - v| (times the cube side).
    #[arg(long, default_value_t = SolveParams::default().alpha1, value_parser = parse_weight)]
    alpha1: f32,
    /// TGV weight of |E(v)| (times the cube side squared).
    #[arg(long, default_value_t = SolveParams::default().alpha0, value_parser = parse_weight)]
    alpha0: f32,
    /// Weight of the histogram data term.
    #[arg(long, default_value_t = SolveParams::default().lambda, value_parser = parse_weight)]
    lambda: f32,
    /// The most primal-dual iterations a unit runs at each level (at least 1).
    #[arg(long, default_value_t = SolveParams::default().iterations, value_parser = parse_iterations)]
    iterations: u32,
    /// A unit stops iterating at the first check (every 25 iterations) where its energy moved
    /// by at most this fraction; 0 runs all --iterations.
    #[arg(long, default_value_t = SolveParams::default().tolerance, value_parser = parse_tolerance)]
    tolerance: f32,
    /// The energy minimised on each level: auto (ssd for an object seen against empty
    /// background, tgv for a scene), tgv (robust to outliers: the paper's method), ssd (smooth
    /// signed distance from the samples' positions and normals: sub-cube accuracy on clean
    /// data) or hybrid (ssd from the samples the histograms confirm). docs/parameters.md, "Solvers".
    #[arg(long, value_enum, default_value = "auto")]
    method: MethodName,
    /// ssd and hybrid: weight of the normal term, relative to the position term (> 0), where
    /// the samples' normals agree; units whose normals disagree (noisy depth maps) take up to
    /// 10 times it (docs/parameters.md, "Solvers").
    #[arg(long, default_value_t = SsdParams::default().normal_weight, value_parser = parse_ssd_weight)]
    ssd_normal_weight: f64,
    /// ssd and hybrid: weight of the smoothness term, relative to the position term (> 0), where
    /// the samples lie on a smooth surface; units whose sample centroids scatter (noisy depth
    /// maps) take up to 10 times it (docs/parameters.md, "Solvers").
    #[arg(long, default_value_t = SsdParams::default().smoothness, value_parser = parse_ssd_weight)]
    ssd_smoothness: f64,
    /// ssd and hybrid: a unit's conjugate gradients stop when the residual is at most this
    /// fraction of the right side's norm.
    #[arg(long, default_value_t = SsdParams::default().tolerance, value_parser = parse_ssd_tolerance)]
    ssd_tolerance: f64,
}

impl SolverArgs {
    pub(super) fn params(self) -> SolveParams {
        SolveParams {
            alpha1: self.alpha1,
            alpha0: self.alpha0,
            lambda: self.lambda,
            iterations: self.iterations,
            tolerance: self.tolerance,
        }
    }

    pub(super) fn method(self) -> MethodChoice {
        let ssd = SsdParams {
            normal_weight: self.ssd_normal_weight,
            smoothness: self.ssd_smoothness,
            tolerance: self.ssd_tolerance,
            ..SsdParams::default()
        };
        match self.method {
            MethodName::Auto => MethodChoice::Auto(ssd),
            MethodName::Tgv => Method::Tgv.into(),
            MethodName::Ssd => Method::Ssd(ssd).into(),
            MethodName::Hybrid => Method::Hybrid(ssd).into(),
        }
    }
}

/// `solve --method`.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum MethodName {
    /// ssd for an object seen against empty background, tgv for a scene.
    Auto,
    /// Total generalized variation with the histogram data term.
    Tgv,
    /// Smooth signed distance.
    Ssd,
    /// Smooth signed distance from the samples the histograms confirm.
    Hybrid,
}

/// The verbs.
#[derive(Subcommand, Debug)]
pub enum Command {
    /// Register depth maps and write their cubes (one sorted run per group of 16 maps that look
    /// at one region). Run it again with more depth maps later: the store grows incrementally.
    Ingest(IngestArgs),
    /// Bring everything derived up to date: the octree and its treetop, the histograms, then
    /// the TGV solution level by level.
    Solve(SolveArgs),
    /// Cluster run, step 1: split a stage's pending units into chunks and record the plan.
    Plan(PlanArgs),
    /// Cluster run, step 2: compute one chunk of the recorded plan (read-only on the catalog;
    /// writes only segment files; safe to retry or to run twice).
    Work(WorkArgs),
    /// Cluster run, step 3: verify every chunk's output and commit the stage as one version.
    Commit(CommitArgs),
    /// Submit the pipeline after ingest to Slurm as job arrays chained with afterok.
    Slurm(SlurmArgs),
    /// Render the built-in synthetic scene, then ingest, solve and extract it (no files needed).
    Demo(DemoArgs),
    /// Write the surface u = 0 as a mesh: by default the observed part, simplified (binary PLY, or
    /// GLB or OBJ by extension).
    Extract(ExtractArgs),
    /// The indicator u at a point (interpolated), from the latest or a given version.
    Query(QueryArgs),
    /// Render a mesh (PLY, OFF or OBJ, optionally .gz) as a shaded PNG.
    Render(RenderArgs),
    /// Summary of a store: version, inputs, the capture the defaults see (object or scene), cubes,
    /// leaves, segments, bytes, content digests.
    Info(InfoArgs),
    /// Check every segment byte and every catalog invariant; exits non-zero on any problem.
    Verify(VerifyArgs),
    /// The store's versions, oldest first.
    Log(LogArgs),
    /// Remove segments that no kept version can see.
    Gc(GcArgs),
    /// Divide huge point clouds (PLY, XYZ, TXT) into overlapping subspaces of at most
    /// --max-points points each, for reconstruction part by part (Kuhn and Mayer 2015); a
    /// later divide into the same folder adds points and rewrites only what they touch.
    Divide(DivideArgs),
    /// Fuse meshes reconstructed per subspace of a division: each keeps the triangles whose
    /// centroid lies in its core cube.
    Merge(MergeArgs),
    /// Run the synthetic test stage (exercises the stage runner without input files). Only in
    /// builds with the `testing` feature, which the crate's own tests turn on.
    #[cfg(feature = "testing")]
    #[command(hide = true)]
    DebugSynthetic(DebugSyntheticArgs),
}

impl Command {
    /// Whether the verb extracts a mesh (or a cluster's share of one): extraction is the stage
    /// that runs nearest the memory budget at scale, since its open seams grow with the scene's
    /// cross-section, so its process hands freed pages back at once
    /// ([`crate::purge_freed_pages_at_once`]); the other verbs keep the allocator's delay, which
    /// spares them the kernel time of faulting buffers back in.
    pub fn extracts(&self) -> bool {
        matches!(
            self,
            Command::Extract(_) | Command::Work(_) | Command::Commit(_) | Command::Demo(_)
        )
    }
}

/// Arguments of `octstore ingest`.
#[derive(Args, Debug)]
pub struct IngestArgs {
    /// The store's folder (created by the first ingest).
    pub store: PathBuf,
    /// Depth maps: RGB-D or TUM folders, frame files, JSON manifests, COLMAP workspaces,
    /// PTX / E57 scans (docs/inputs.md).
    #[arg(required = true)]
    pub inputs: Vec<PathBuf>,
    /// The inputs' layout.
    #[arg(long, value_enum, default_value = "auto")]
    pub format: InputFormat,
    /// Take every n-th frame of a folder (at least 1).
    #[arg(long, default_value_t = 1, value_parser = parse_positive::<usize>)]
    pub stride: usize,
    /// Take at most this many frames of a folder.
    #[arg(long)]
    pub limit: Option<usize>,
    /// Intrinsics of RGB-D frames (a 3x3 matrix, or fx fy cx cy) for folders and frames
    /// without a camera-intrinsics.txt beside them; it replaces theirs where they have one.
    #[arg(long, value_name = "FILE")]
    pub intrinsics: Option<PathBuf>,
    /// Depth noise of every map given (docs/parameters.md, "Cube sizes and depth noise"):
    /// `auto` (the default: measured from each map's own pixels, in its own units), `none` (cubes follow the pixel footprint
    /// alone), `kinect` (0.0012,0.0019,0.4, metres), `lidar` (0.002, metres), a sigma, or
    /// `constant,quadratic,offset` for sigma(d) = constant + quadratic (d - offset)^2, in scene
    /// units.
    #[arg(long, value_name = "MODEL", value_parser = parse_depth_noise)]
    pub depth_noise: Option<crate::inputs::DepthNoise>,
    /// A sample's radius spans at least this many standard deviations of its depth noise
    /// [default: auto's own choice (0.5 for independent noise, 2 for a quantized sensor), 1
    /// for the tables and numbers, or a manifest entry's noise_sigmas].
    #[arg(long, value_name = "K", value_parser = parse_noise_sigmas)]
    pub noise_sigmas: Option<f64>,
    /// Root cube as minx,miny,minz,side (first ingest only; default: the samples' bounding
    /// box grown by --root-margin).
    #[arg(long, value_parser = parse_root)]
    pub root: Option<([f64; 3], f64)>,
    /// How far the root cube reaches past the samples' box, in parts of its size (first
    /// ingest only; 0 to 10).
    #[arg(long, default_value_t = 0.1, value_parser = parse_margin)]
    pub root_margin: f64,
    /// Deepest octree level a sample may create (first ingest only; at most 32, the keys'
    /// limit).
    #[arg(long, default_value_t = 24, value_parser = clap::value_parser!(u8).range(1..=i64::from(crate::format::MAX_DEPTH)))]
    pub max_depth: u8,
    /// Also gather the samples' sums (weights, centroids, normals per cube) that `solve
    /// --method ssd|hybrid` needs (first ingest only: later ingests into the store keep its
    /// setting). About 1.6 times the ingest time and 6 times the runs' bytes; the default TGV solver does
    /// not use them.
    #[arg(long)]
    pub sample_sums: bool,
    /// Continue an interrupted ingest from its last committed unit.
    #[arg(long)]
    pub resume: bool,
}

/// Arguments of `octstore solve`.
#[derive(Args, Debug)]
pub struct SolveArgs {
    /// The store's folder.
    pub store: PathBuf,
    /// Continue an interrupted run from its last committed unit.
    #[arg(long)]
    pub resume: bool,
    /// Run the pending stages up to and including this one.
    #[arg(long, value_enum, default_value = "solution")]
    pub until: SolveUntil,
    /// The solver and its weights.
    #[command(flatten)]
    pub solver: SolverArgs,
    /// Treetop leaves hold fewer cubes than this.
    #[arg(long, default_value_t = octree::DEFAULT_LEAF_CUBES, value_parser = clap::value_parser!(u64).range(64..))]
    pub leaf_cubes: u64,
    /// Where the histogram votes and the TGV iterations run: auto takes a hardware GPU
    /// when there is one (never a software rasteriser), gpu any adapter (llvmpipe
    /// included), cpu the CPU code.
    #[arg(long, value_enum, default_value = "auto")]
    pub device: crate::gpu::DeviceChoice,
}

/// Arguments of `octstore plan`.
#[derive(Args, Debug)]
pub struct PlanArgs {
    /// The store's folder.
    pub store: PathBuf,
    /// `histograms`, `solution-LL` or `extract`.
    #[arg(long)]
    pub stage: String,
    /// Chunks to split the stage's units into: one worker task each.
    #[arg(long, default_value_t = 16)]
    pub chunks: u32,
    /// The solver and its weights (recorded in the plan, so every worker uses the same).
    #[command(flatten)]
    pub solver: SolverArgs,
    /// extract: the mesh file the commit writes (.ply, .glb or .obj).
    #[arg(short, long, required_if_eq("stage", "extract"), value_parser = parse_mesh_path)]
    pub output: Option<PathBuf>,
    /// extract: only what lies in this box.
    #[arg(long, value_parser = parse_region)]
    pub region: Option<BoundingBox>,
    /// extract: keep about this fraction of the triangles (see `octstore extract --help`).
    #[arg(long, value_parser = parse_ratio, conflicts_with = "max_error")]
    pub decimate: Option<f32>,
    /// extract: simplify within this error, in finest cube sides (see `octstore extract --help`).
    #[arg(long, value_parser = parse_max_error)]
    pub max_error: Option<f32>,
    /// extract: the whole zero set, closed at the root cube (see `octstore extract --help`).
    #[arg(long, conflicts_with = "open")]
    pub closed: bool,
    /// extract: only the observed surface (see `octstore extract --help`).
    #[arg(long)]
    pub open: bool,
}

/// Arguments of `octstore work`.
#[derive(Args, Debug)]
pub struct WorkArgs {
    /// The store's folder (shared by every worker).
    pub store: PathBuf,
    /// The planned stage this worker runs a chunk of.
    #[arg(long)]
    pub stage: String,
    /// The chunk to run, from 0 to the plan's chunks - 1.
    #[arg(long)]
    pub chunk: u32,
    /// Where this chunk's votes and iterations run, as for `solve`. Every chunk of a stage
    /// should use the same kind of device: GPU votes may differ from the CPU's in rare
    /// boundary cubes.
    #[arg(long, value_enum, default_value = "auto")]
    pub device: crate::gpu::DeviceChoice,
}

/// Arguments of `octstore commit`.
#[derive(Args, Debug)]
pub struct CommitArgs {
    /// The store's folder.
    pub store: PathBuf,
    /// The planned stage whose workers' output to adopt as one new version.
    #[arg(long)]
    pub stage: String,
}

/// Arguments of `octstore slurm`.
#[derive(Args, Debug)]
pub struct SlurmArgs {
    /// The store's folder, on a file system every node mounts.
    pub store: PathBuf,
    /// Chunks (array tasks) per stage.
    #[arg(long, default_value_t = 16)]
    pub chunks: u32,
    /// The Slurm partition to submit to (sbatch's default when absent).
    #[arg(long)]
    pub partition: Option<String>,
    /// Extra sbatch option for every job, e.g. --sbatch-arg=--time=02:00:00 (repeatable).
    #[arg(long = "sbatch-arg", allow_hyphen_values = true)]
    pub sbatch_args: Vec<String>,
    /// Print the job scripts instead of submitting them.
    #[arg(long)]
    pub dry_run: bool,
    /// Treetop leaves of the octree job hold fewer cubes than this.
    #[arg(long, default_value_t = octree::DEFAULT_LEAF_CUBES, value_parser = clap::value_parser!(u64).range(64..))]
    pub leaf_cubes: u64,
    /// Also extract the mesh into this file (.ply or .obj), chunked like the other stages.
    #[arg(short, long, value_parser = parse_mesh_path)]
    pub output: Option<PathBuf>,
    /// The solver and its weights.
    #[command(flatten)]
    pub solver: SolverArgs,
    /// `--device` of the work jobs (ask Slurm for GPUs with --sbatch-arg=--gres=gpu:1).
    #[arg(long, value_enum, default_value = "auto")]
    pub device: crate::gpu::DeviceChoice,
}

/// Arguments of `octstore demo`.
#[derive(Args, Debug)]
pub struct DemoArgs {
    /// Output folder: depth maps, the store, demo.ply.
    #[arg(long, default_value = "octstore-demo")]
    pub out: PathBuf,
    /// Primal-dual iterations per level (at least 1).
    #[arg(long, default_value_t = 100, value_parser = parse_iterations)]
    pub iterations: u32,
    /// Where the histogram votes and the TGV iterations run (as for `solve`).
    #[arg(long, value_enum, default_value = "auto")]
    pub device: crate::gpu::DeviceChoice,
}

/// Arguments of `octstore extract`.
#[derive(Args, Debug)]
pub struct ExtractArgs {
    /// The store's folder.
    pub store: PathBuf,
    /// The mesh file: binary PLY, or GLB (glTF binary) or OBJ by the extension `.glb` or `.obj`.
    #[arg(short, long, value_parser = parse_mesh_path)]
    pub output: PathBuf,
    /// Only what lies in this box: minx,miny,minz,maxx,maxy,maxz.
    #[arg(long, value_parser = parse_region)]
    pub region: Option<BoundingBox>,
    /// Extract from this version instead of the latest.
    #[arg(long)]
    pub version: Option<u64>,
    /// Simplify the mesh wherever that moves the surface by at most this many finest cube
    /// sides (quadric edge collapses, streamed across treetop leaf borders within the memory
    /// budget): flat walls become few large triangles, detailed parts keep theirs. 0 keeps
    /// every triangle marching tetrahedra gives. [default: 0.25]
    #[arg(long, value_parser = parse_max_error)]
    pub max_error: Option<f32>,
    /// Keep about this fraction (0..1] of the triangles, whatever the error, instead of
    /// bounding the error.
    #[arg(long, value_parser = parse_ratio, conflicts_with = "max_error")]
    pub decimate: Option<f32>,
    /// Mesh the whole zero set of u, closed at the root cube. Without `--closed` or `--open`
    /// the capture decides: when most of a few of its depth maps see their content against
    /// empty background (invalid pixels all around: an object seen from all around), the mesh
    /// is watertight, every piece of the zero set that holds observed surface closed where no
    /// map measured it (crevices, undersides) and pieces without observed surface dropped;
    /// otherwise (a room, a street, an aerial capture) only the observed surface, with open
    /// borders where the cameras stopped and nothing invented behind walls or under
    /// furniture. Use it when a watertight mesh matters more than honest borders (hidden parts
    /// are then filled in).
    #[arg(long, conflicts_with = "open")]
    pub closed: bool,
    /// Only the observed surface, with open borders where the cameras stopped, whatever the
    /// capture.
    #[arg(long)]
    pub open: bool,
}

/// The surface `--closed` and `--open` ask for: neither lets the capture decide.
pub(super) fn surface_of(closed: bool, open: bool) -> SurfaceChoice {
    match (closed, open) {
        (true, _) => SurfaceChoice::Whole,
        (false, true) => SurfaceChoice::Observed,
        (false, false) => SurfaceChoice::Auto,
    }
}

/// Arguments of `octstore divide`.
#[derive(Args, Debug)]
pub struct DivideArgs {
    /// Point clouds: PLY (ASCII or binary, any scalar vertex properties), XYZ or TXT (x y z,
    /// optionally nx ny nz, then red green blue); PTX or E57 scans (their returns in world
    /// coordinates); an octstore store's folder (its depth maps' samples, with normals and
    /// radii). All must have the same properties.
    #[arg(required_unless_present = "synthetic")]
    pub inputs: Vec<PathBuf>,
    /// The folder of subspace PLYs and subspaces.json; one that holds a division already gets
    /// the new points added.
    #[arg(short, long)]
    pub output: PathBuf,
    /// The most points in a subspace's core (default 10000000, or the folder's).
    #[arg(long)]
    pub max_points: Option<u64>,
    /// How far grown cubes reach beyond each face of their core, as a fraction of its side
    /// (default 0.1, or the folder's).
    #[arg(long, value_parser = parse_overlap)]
    pub overlap: Option<f64>,
    /// Octree levels counted in one pass (default: enough for the points and --max-points
    /// where they spread evenly, plus 3, within --memory-budget); nodes at that depth that
    /// still hold too many points are divided again from their own points. 1 to 10.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=10))]
    pub max_depth: Option<u32>,
    /// Divide a generated cloud of this many points instead of files (benchmarks: nothing is
    /// read from disk).
    #[arg(long, hide = true)]
    pub synthetic: Option<u64>,
}

/// Arguments of `octstore merge`.
#[derive(Args, Debug)]
pub struct MergeArgs {
    /// The division's subspaces.json.
    pub manifest: PathBuf,
    /// One mesh per subspace, named after its file (L2_0_1_3.ply takes L2_0_1_3.mesh.ply).
    #[arg(required = true)]
    pub meshes: Vec<PathBuf>,
    /// The merged mesh (PLY, or OBJ by extension).
    #[arg(short, long, value_parser = parse_mesh_path)]
    pub output: PathBuf,
}

/// Arguments of `octstore query`.
#[derive(Args, Debug)]
pub struct QueryArgs {
    /// The store's folder.
    pub store: PathBuf,
    /// x,y,z in world coordinates.
    #[arg(long, value_parser = parse_point, required_unless_present_any = ["levels", "leaves", "cubes"])]
    pub point: Option<[f64; 3]>,
    /// List the cubes of the finest level cut (or `--level`) that meet this box, with u, the
    /// seen flag and the vote histogram (JSON): minx,miny,minz,maxx,maxy,maxz.
    #[arg(long, value_parser = parse_region)]
    pub cubes: Option<BoundingBox>,
    /// The level cut `--cubes` lists (default: the finest solved level).
    #[arg(long, requires = "cubes")]
    pub level: Option<u8>,
    /// Read this version instead of the latest.
    #[arg(long)]
    pub version: Option<u64>,
    /// Print the point's value as JSON.
    #[arg(long)]
    pub json: bool,
    /// List the solved levels (JSON).
    #[arg(long)]
    pub levels: bool,
    /// List the treetop leaves: key, depth, min corner, size, cubes (JSON).
    #[arg(long)]
    pub leaves: bool,
}

/// Arguments of `octstore render`.
#[derive(Args, Debug)]
pub struct RenderArgs {
    /// The mesh to draw (PLY, OFF or OBJ, optionally .gz).
    pub mesh: PathBuf,
    /// The PNG to write.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Picture width in pixels.
    #[arg(long, default_value_t = 800)]
    pub width: u32,
    /// Picture height in pixels.
    #[arg(long, default_value_t = 600)]
    pub height: u32,
    /// Take the picture from this camera instead of the fitted 3/4 view: a text file of 16
    /// numbers, the camera-to-world 4x4 matrix row by row, OpenCV axes (a 7-Scenes
    /// `frame-*.pose.txt` as is).
    #[arg(long)]
    pub pose: Option<PathBuf>,
    /// Focal length in pixels for `--pose` (principal point at the image centre).
    #[arg(long, default_value_t = 525.0, requires = "pose")]
    pub focal: f64,
}

/// Arguments of `octstore info`.
#[derive(Args, Debug)]
pub struct InfoArgs {
    /// The store; not needed with --devices.
    #[arg(required_unless_present = "devices")]
    pub store: Option<PathBuf>,
    /// List the GPU adapters wgpu finds (and which one `--device auto` would take).
    #[arg(long)]
    pub devices: bool,
    /// Print the summary as JSON.
    #[arg(long)]
    pub json: bool,
    /// Show this version instead of the latest.
    #[arg(long)]
    pub version: Option<u64>,
}

/// Arguments of `octstore verify`.
#[derive(Args, Debug)]
pub struct VerifyArgs {
    /// The store's folder.
    pub store: PathBuf,
}

/// Arguments of `octstore log`.
#[derive(Args, Debug)]
pub struct LogArgs {
    /// The store's folder.
    pub store: PathBuf,
    /// Print the versions as JSON.
    #[arg(long)]
    pub json: bool,
}

/// Arguments of `octstore gc`.
#[derive(Args, Debug)]
pub struct GcArgs {
    /// The store's folder.
    pub store: PathBuf,
    /// Versions to keep readable, counting the latest (at least 1).
    #[arg(long, default_value_t = 1, value_parser = parse_positive::<u64>)]
    pub keep: u64,
}

#[cfg(feature = "testing")]
/// Arguments of `octstore debug-synthetic`.
#[derive(Args, Debug)]
pub struct DebugSyntheticArgs {
    /// The store's folder (created if absent).
    pub store: PathBuf,
    /// Units of work of the synthetic stage.
    #[arg(long, default_value_t = 8)]
    pub units: u32,
    /// Rows each unit writes.
    #[arg(long, default_value_t = 2000)]
    pub rows: u32,
    /// Seed of the generated keys and values.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Sleep per unit, in milliseconds (lets the kill tests stop a run midway).
    #[arg(long, default_value_t = 0)]
    pub delay_ms: u64,
    /// Resume an interrupted run of the stage.
    #[arg(long)]
    pub resume: bool,
}

/// The simplification `--decimate` and `--max-error` ask for (they conflict), or the default.
pub(super) fn simplify_of(decimate: Option<f32>, max_error: Option<f32>) -> Simplify {
    match (decimate, max_error) {
        (Some(fraction), _) => Simplify::Fraction(fraction),
        (None, Some(0.0)) => Simplify::Full,
        (None, Some(error)) => Simplify::MaxError(error),
        (None, None) => Simplify::default(),
    }
}
