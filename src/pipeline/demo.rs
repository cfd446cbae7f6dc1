//! The built-in demo: render the synthetic scene, ingest, solve, extract, and a preview. The
//! same calls as `ingest`, `solve` and `extract`, so the demo shows what a user's run does.

use std::path::{Path, PathBuf};

use super::{Result, SolveOptions, SolveUntil, extract, ingest, io_error, save_png, solve};
use crate::format::BoundingBox;
use crate::gpu::DeviceChoice;
use crate::inputs::DiscoverOptions;
use crate::mesh::{MeshSummary, clip, read_mesh, render};
use crate::quality::synthetic_scenes::SceneSpec;
use crate::stages::ingest::IngestOptions;
use crate::stages::solve::SolveParams;
use crate::store::{RunOptions, RunReport, Store};

/// What the demo runs with.
#[derive(Clone, Debug)]
pub struct DemoOptions {
    /// The folder it writes into: `input/`, `store/`, `demo.ply`, `demo.png`.
    pub out: PathBuf,
    /// Primal-dual iterations per level.
    pub iterations: u32,
    /// Bytes the whole process may use.
    pub memory_budget: u64,
    /// Threads, progress bars.
    pub run: RunOptions,
    /// Where the votes and the iterations run.
    pub device: DeviceChoice,
}

impl Default for DemoOptions {
    fn default() -> Self {
        DemoOptions {
            out: PathBuf::from("octstore-demo"),
            iterations: 100,
            memory_budget: 1 << 30,
            run: RunOptions::default(),
            device: DeviceChoice::Auto,
        }
    }
}

/// What the demo wrote.
#[derive(Clone, Debug)]
pub struct DemoOutput {
    /// The scene it rendered.
    pub scene: SceneSpec,
    /// The folder of its depth maps and manifest.
    pub input: PathBuf,
    /// The store it built.
    pub store: PathBuf,
    /// The mesh and its counts.
    pub mesh: PathBuf,
    /// Counts of the mesh.
    pub summary: MeshSummary,
    /// When the extraction started (for its summary line).
    pub extract_started: std::time::Instant,
    /// The preview picture.
    pub preview: PathBuf,
}

/// Maximum depth of the demo's octree: 137K cubes at the finest level, seconds to solve.
const DEMO_MAX_DEPTH: u8 = 9;
/// Treetop leaves of the demo hold fewer cubes than this, so it has several leaves and seams.
const DEMO_LEAF_CUBES: u64 = 20_000;

/// The part of the demo scene the preview shows: the objects, not the room around them.
const PREVIEW_BOX: BoundingBox = BoundingBox {
    min: glam::DVec3::new(-0.7, -0.6, -0.45),
    max: glam::DVec3::new(0.7, 0.6, 0.85),
};

/// Runs the demo into `options.out` (its store is rebuilt from scratch); `on_report` sees each
/// stage's report as it finishes.
pub fn demo(options: &DemoOptions, mut on_report: impl FnMut(&RunReport)) -> Result<DemoOutput> {
    let out = &options.out;
    let scene = SceneSpec::demo();
    let input = out.join("input");
    let manifest = scene.write(&input).map_err(io_error("write demo input", out))?;
    let store_path = out.join("store");
    if store_path.exists() {
        std::fs::remove_dir_all(&store_path).map_err(io_error("remove", &store_path))?;
    }
    let store = Store::create(&store_path)?;
    let ingest_options = IngestOptions {
        root: None,
        root_margin: 0.05,
        max_depth: DEMO_MAX_DEPTH,
        memory_budget: options.memory_budget,
        sample_sums: false,
        ..IngestOptions::default()
    };
    on_report(&ingest(
        &store,
        &[manifest],
        &DiscoverOptions::default(),
        &ingest_options,
        &options.run,
    )?);
    let solve_options = SolveOptions {
        until: SolveUntil::Solution,
        leaf_cubes: DEMO_LEAF_CUBES,
        memory_budget: options.memory_budget,
        params: SolveParams {
            iterations: options.iterations,
            ..SolveParams::default()
        },
        method: crate::stages::solve::Method::Tgv.into(),
        run: options.run.clone(),
        device: options.device,
    };
    solve(&store, &solve_options, &mut on_report)?;
    let mesh = out.join("demo.ply");
    let extract_started = std::time::Instant::now();
    let summary = extract(&store, &mesh, &Default::default(), None, options.memory_budget)?;
    let preview = out.join("demo.png");
    save_preview(&mesh, &preview)?;
    Ok(DemoOutput {
        scene,
        input,
        store: store_path,
        mesh,
        summary,
        extract_started,
        preview,
    })
}

/// Renders the objects of the demo's mesh file into a PNG.
fn save_preview(mesh: &Path, png: &Path) -> Result<()> {
    let objects = clip(&read_mesh(mesh)?, PREVIEW_BOX);
    save_png(&render(&objects, 800, 600), png)
}
