//! One function per single-machine verb. Each opens the store as it needs (writable, or for
//! reading), calls the pipeline, and prints what the user asked for.

use std::process::ExitCode;
use std::time::Instant;

use super::args::{
    DemoArgs, ExtractArgs, GcArgs, GlobalOptions, InfoArgs, IngestArgs, LogArgs, QueryArgs, RenderArgs, SolveArgs,
    VerifyArgs,
};
use super::error::{CliError, Result};
use super::report::{info, print_extract_summary, summary};
use super::{open_or_create, run_options};
use crate::IndicatorField;
use crate::inputs::DiscoverOptions;
use crate::mesh::{View, read_mesh, render_view};
use crate::pipeline::{self, DemoOptions, save_png};
use crate::stages::extract::ExtractOptions;
use crate::stages::ingest::{IngestOptions, scene_at};
use crate::store::{RunOptions, Store};

/// What `octstore ingest` passes to [`pipeline::ingest`]: discovery, ingest and run options.
pub(super) fn ingest_options(
    global: &GlobalOptions,
    args: &IngestArgs,
) -> (DiscoverOptions, IngestOptions, RunOptions) {
    let discover = DiscoverOptions {
        format: args.format,
        stride: args.stride,
        limit: args.limit,
        intrinsics: args.intrinsics.clone(),
        depth_noise: args.depth_noise,
        noise_sigmas: args.noise_sigmas,
    };
    let options = IngestOptions {
        root: args.root,
        root_margin: args.root_margin,
        max_depth: args.max_depth,
        memory_budget: global.memory_budget,
        sample_sums: args.sample_sums,
        ..IngestOptions::default()
    };
    (discover, options, run_options(global, args.resume))
}

pub(super) fn ingest(global: &GlobalOptions, args: IngestArgs) -> Result<()> {
    let (discover, options, run) = ingest_options(global, &args);
    let store = open_or_create(&args.store)?;
    let report = pipeline::ingest(&store, &args.inputs, &discover, &options, &run)?;
    summary(&report);
    Ok(())
}

/// What `octstore solve` passes to [`pipeline::solve`].
pub(super) fn solve_options(global: &GlobalOptions, args: &SolveArgs) -> pipeline::SolveOptions {
    pipeline::SolveOptions {
        until: args.until,
        leaf_cubes: args.leaf_cubes,
        memory_budget: global.memory_budget,
        params: args.solver.params(),
        method: args.solver.method(),
        run: run_options(global, args.resume),
        device: args.device,
    }
}

pub(super) fn solve(global: &GlobalOptions, args: SolveArgs) -> Result<()> {
    let store = Store::open(&args.store)?;
    let options = solve_options(global, &args);
    pipeline::solve(&store, &options, summary)?;
    Ok(())
}

pub(super) fn demo(global: &GlobalOptions, args: DemoArgs) -> Result<()> {
    let started = Instant::now();
    let options = DemoOptions {
        out: args.out,
        iterations: args.iterations,
        memory_budget: global.memory_budget,
        run: run_options(global, false),
        device: args.device,
    };
    let output = pipeline::demo(&options, summary)?;
    let scene = &output.scene;
    println!(
        "demo: rendered {} depth maps of {}x{} into {}",
        scene.cameras,
        scene.width,
        scene.height,
        output.input.display()
    );
    print_extract_summary(&output.summary, &output.mesh, output.extract_started);
    println!("demo: wrote {} and {}", output.mesh.display(), output.preview.display());
    println!(
        "demo: done in {:.1}s; store at {}",
        started.elapsed().as_secs_f64(),
        output.store.display()
    );
    Ok(())
}

pub(super) fn extract(global: &GlobalOptions, args: ExtractArgs) -> Result<()> {
    let started = Instant::now();
    let store = Store::open_for_reading(&args.store)?;
    let options = ExtractOptions {
        region: args.region,
        simplify: super::args::simplify_of(args.decimate, args.max_error),
        surface: super::args::surface_of(args.closed, args.open),
    };
    let summary = pipeline::extract(&store, &args.output, &options, args.version, global.memory_budget)?;
    print_extract_summary(&summary, &args.output, started);
    Ok(())
}

pub(super) fn query(args: QueryArgs) -> Result<()> {
    let store = Store::open_for_reading(&args.store)?;
    let snapshot = match args.version {
        Some(v) => store.snapshot(v)?,
        None => store.latest()?,
    };
    if args.leaves || args.levels {
        let value = serde_json::json!({
            "version": snapshot.version(),
            "levels": snapshot.levels(),
            "leaves": if args.leaves { Some(snapshot.leaves()?) } else { None },
        });
        println!("{}", serde_json::to_string_pretty(&value).unwrap_or_default());
        return Ok(());
    }
    if let Some(region) = args.cubes {
        let level = match args.level.or_else(|| snapshot.finest_level()) {
            Some(level) => level,
            None => {
                return Err(CliError::Usage {
                    verb: "query",
                    problem: "nothing is solved yet: run `octstore solve` first",
                });
            }
        };
        let cubes = snapshot.cubes_in(&region, level)?;
        let value = serde_json::json!({"version": snapshot.version(), "level": level, "cubes": cubes});
        println!("{}", serde_json::to_string_pretty(&value).unwrap_or_default());
        return Ok(());
    }
    let Some(point) = args.point else {
        return Err(CliError::Usage {
            verb: "query",
            problem: "give --point x,y,z (or --levels / --leaves)",
        });
    };
    if let Some((solved, deepest)) = crate::query::unfinished_solve(&snapshot)? {
        tracing::warn!("{}", crate::query::unfinished_solve_note(solved, deepest));
    }
    let u = snapshot.indicator_at(glam::DVec3::from_array(point))?;
    let seen = snapshot.seen_at(glam::DVec3::from_array(point))?;
    let method = snapshot.method()?;
    if args.json {
        let value = serde_json::json!({"version": snapshot.version(), "point": point, "u": u, "seen": seen, "level": snapshot.finest_level(), "method": method});
        println!("{value}");
    } else {
        // Under SSD u is a signed distance in units of the root side: say it in world units.
        let signed_distance = match (method, scene_at(&store, snapshot.version())?) {
            (Some("ssd" | "hybrid"), Some(scene)) => {
                u.map(|u| format!(", signed distance {:.6}", f64::from(u) * scene.root_side))
            }
            _ => None,
        };
        match u {
            Some(u) => println!(
                "u = {u:.6} ({}{}, {}) at version {}",
                if u < 0.0 { "inside" } else { "outside" },
                signed_distance.unwrap_or_default(),
                if seen == Some(true) {
                    "seen"
                } else {
                    "not seen by any depth map"
                },
                snapshot.version()
            ),
            None => println!("no value: the point is outside the root cube, or nothing is solved yet"),
        }
    }
    Ok(())
}

/// The camera of `render --pose`: a 4x4 camera-to-world matrix, row-major, OpenCV axes.
fn pose_view(path: &std::path::Path, focal: f64) -> Result<View> {
    let pose_error = |problem: String| CliError::Pose {
        path: path.to_path_buf(),
        problem,
    };
    let text = std::fs::read_to_string(path).map_err(|e| pose_error(e.to_string()))?;
    let numbers = text
        .split_whitespace()
        .map(str::parse::<f64>)
        .collect::<std::result::Result<Vec<f64>, _>>()
        .map_err(|e| pose_error(format!("not a 4x4 matrix of numbers: {e}")))?;
    let rows: [f64; 16] = numbers
        .try_into()
        .map_err(|n: Vec<f64>| pose_error(format!("expected 16 numbers (a 4x4 matrix), found {}", n.len())))?;
    let camera_to_world = glam::DMat4::from_cols_array(&rows).transpose();
    if camera_to_world.determinant().abs().is_nan() || camera_to_world.determinant().abs() <= 1e-9 {
        return Err(pose_error("the pose is not invertible".into()));
    }
    Ok(View::Pinhole { camera_to_world, focal })
}

pub(super) fn render(args: RenderArgs) -> Result<()> {
    let view = match &args.pose {
        None => View::Fitted,
        Some(path) => pose_view(path, args.focal)?,
    };
    let mesh = read_mesh(&args.mesh)?;
    Ok(save_png(
        &render_view(&mesh, args.width, args.height, view),
        &args.output,
    )?)
}

fn devices(json: bool) {
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

pub(super) fn info_verb(args: InfoArgs) -> Result<()> {
    if args.devices {
        devices(args.json);
        return Ok(());
    }
    let store = args.store.ok_or(CliError::Usage {
        verb: "info",
        problem: "give a store, or --devices",
    })?;
    let store = Store::open_for_reading(&store)?;
    let info = info(&store, args.version)?;
    if args.json {
        println!("{}", serde_json::to_string_pretty(&info).unwrap_or_default());
        return Ok(());
    }
    println!("store          {}", info.store);
    println!("version        {}", info.version);
    println!("depth maps     {}", info.depth_maps);
    for (noise, maps) in &info.depth_noise {
        println!("  depth noise  {noise}: {maps}");
    }
    if let Some(capture) = &info.capture {
        println!(
            "capture        {} ({} of {} depth map(s) read see their content against empty background)",
            if capture.object {
                "an object (defaults: solve by ssd, a watertight mesh)"
            } else {
                "a scene (defaults: solve by tgv, the observed surface)"
            },
            capture.against_background,
            capture.read
        );
    }
    println!("cubes          {}", info.cubes);
    println!("treetop leaves {}", info.treetop_leaves);
    println!("segments       {} ({} bytes)", info.segments, info.bytes);
    if let Some(side) = info.root_side {
        println!("root side      {side}");
    }
    if let (Some(level), Some(side)) = (info.finest_level, info.finest_cube_side) {
        println!("finest level   {level} (cubes of side {side})");
        if let Some(deepest) = info.octree_deepest_level.filter(|&deepest| deepest > level) {
            println!("               {}", crate::query::unfinished_solve_note(level, deepest));
        }
    }
    if let Some(solver) = &info.solver {
        println!("solver         {solver}");
    }
    match info.sample_sums {
        Some(true) => println!("sample sums    yes (solve --method tgv, ssd or hybrid)"),
        Some(false) => {
            println!("sample sums    no (solve --method ssd or hybrid reads the depth maps again once to add them)")
        }
        None => {}
    }
    for (stage, digest) in &info.digest {
        println!("digest         {stage:<12} {digest}");
    }
    Ok(())
}

pub(super) fn verify(args: VerifyArgs) -> Result<ExitCode> {
    // A reader, so it runs beside a writer; writable only when the catalog needs recovery
    // after a crash. Crash debris (files no commit references) is not checked: the next
    // writable open removes it.
    let store = Store::open_for_reading(&args.store)?;
    let report = store.verify(&[crate::stages::octree::verify_octree])?;
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
    Ok(ExitCode::SUCCESS)
}

pub(super) fn log(args: LogArgs) -> Result<()> {
    let store = Store::open_for_reading(&args.store)?;
    let log = store.log()?;
    if args.json {
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
    Ok(())
}

pub(super) fn gc(args: GcArgs) -> Result<()> {
    let store = Store::open(&args.store)?;
    let (files, bytes) = store.gc(args.keep)?;
    println!("gc: removed {files} segment file(s), {bytes} bytes");
    Ok(())
}

#[cfg(feature = "testing")]
pub(super) fn debug_synthetic(global: &GlobalOptions, args: super::args::DebugSyntheticArgs) -> Result<()> {
    let store = open_or_create(&args.store)?;
    let stage = crate::stages::exercise::ExerciseStage {
        units: args.units,
        rows_per_unit: args.rows,
        seed: args.seed,
        delay_ms: args.delay_ms,
    };
    let report = store.run_stage(&stage, &run_options(global, args.resume))?;
    println!(
        "{}: version {:?}, {} unit(s) ({} resumed), {} rows, {:.2}s",
        report.stage, report.version, report.units, report.resumed_units, report.rows, report.seconds
    );
    Ok(())
}
