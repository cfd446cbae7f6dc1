//! A root that grows (format-spec.md, "Growing the root"): a kitchen store built from frames
//! 0, 10 and 20 takes frames 400, 500 and 900, which see beyond its root; the grown store gives
//! the mesh a batch build in the same root gives; older versions keep their own scene; a
//! killed growing ingest resumes to the same bytes; a root given with `--root` never grows.

mod common;

use std::path::{Path, PathBuf};

use common::*;
use octstore::mesh::read_mesh;
use octstore::testing::quality::evaluate::{EvaluateOptions, evaluate};
use octstore::testing::stages::ingest::{read_scene, scene_at};

fn frame(n: u32) -> String {
    shared_path("7scenes-redkitchen")
        .join(format!("frame-{n:06}.depth.png"))
        .to_string_lossy()
        .into_owned()
}

fn frames(numbers: &[u32]) -> Vec<String> {
    numbers.iter().map(|&n| frame(n)).collect()
}

const FIRST: [u32; 3] = [0, 10, 20];
const LATER: [u32; 3] = [400, 500, 900];

fn run(args: &[String]) -> String {
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let out = octstore(&args, &[]);
    assert!(out.status.success(), "octstore {args:?}: {}", stderr(&out));
    stdout(&out)
}

fn ingest(store: &Path, numbers: &[u32], extra: &[&str]) -> String {
    let mut args = vec!["ingest".to_string(), store.display().to_string(), "--quiet".into()];
    args.extend(frames(numbers));
    args.extend(extra.iter().map(|s| s.to_string()));
    run(&args)
}

/// Solves and extracts; returns the mesh path.
fn solve_and_extract(store: &Path) -> PathBuf {
    run(&["solve".into(), store.display().to_string(), "--quiet".into()]);
    let mesh = store.with_extension("ply");
    run(&[
        "extract".into(),
        store.display().to_string(),
        "-o".into(),
        mesh.display().to_string(),
    ]);
    mesh
}

fn f_score(a: &Path, b: &Path, tau_fraction: f64) -> f64 {
    let (a, b) = (read_mesh(a).unwrap(), read_mesh(b).unwrap());
    let (lo, hi) = octstore::testing::quality::ground_truth_views::bounds(&b).unwrap();
    let options = EvaluateOptions {
        tau: (hi - lo).length() * tau_fraction,
        spacing: None,
        crop_margin: None,
        seen_faces: None,
        seed: 1,
    };
    evaluate(&a, &b, &options).unwrap().f_score
}

#[test]
fn a_kitchen_store_grows_to_take_frames_beyond_its_root() {
    let Some(_) = shared_data("7scenes-redkitchen") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let grown = dir.path().join("grown");
    ingest(&grown, &FIRST, &["--max-depth", "7"]);
    let first = read_scene(&octstore::Store::open(&grown).unwrap()).unwrap().unwrap();
    // The surface before growth, and the version it was solved in.
    let before = solve_and_extract(&grown);
    let before_bytes = std::fs::read(&before).unwrap();
    let solved = octstore::Store::open(&grown).unwrap().current_version().unwrap();
    let summary = ingest(&grown, &LATER, &[]);
    assert!(summary.contains("root grown"), "{summary}");

    let store = octstore::Store::open(&grown).unwrap();
    let scene = read_scene(&store).unwrap().unwrap();
    let doublings = scene.max_depth - first.max_depth;
    assert!(doublings >= 1, "{summary}");
    assert_eq!(scene.root_side, first.root_side * f64::from(1u32 << doublings));
    assert_eq!(scene.cube_side(scene.max_depth), first.cube_side(first.max_depth));
    // Earlier versions keep the scene their cubes were keyed in.
    assert_eq!(scene_at(&store, 1).unwrap(), Some(first));
    assert_eq!(scene_at(&store, solved).unwrap(), Some(first));
    assert_eq!(scene_at(&store, solved + 1).unwrap(), Some(scene));
    drop(store);
    run(&["verify".into(), grown.display().to_string()]);
    // The pre-growth version still extracts to the very same mesh.
    let again = dir.path().join("before-again.ply");
    run(&[
        "extract".into(),
        grown.display().to_string(),
        "--version".into(),
        solved.to_string(),
        "-o".into(),
        again.display().to_string(),
    ]);
    assert!(
        std::fs::read(&again).unwrap() == before_bytes,
        "version {solved} reads differently after growth"
    );

    // A batch build of the six frames in the grown root (same cubes, so the same surface up
    // to the rounding of re-keyed radius sums).
    let same_root = dir.path().join("same-root");
    let root = format!(
        "--root={},{},{},{}",
        scene.root_min[0], scene.root_min[1], scene.root_min[2], scene.root_side
    );
    let all: Vec<u32> = FIRST.iter().chain(&LATER).copied().collect();
    ingest(&same_root, &all, &[&root, "--max-depth", &scene.max_depth.to_string()]);
    let grown_mesh = solve_and_extract(&grown);
    let same_root_mesh = solve_and_extract(&same_root);
    let f = f_score(&grown_mesh, &same_root_mesh, 0.005);
    assert!(f >= 0.999, "grown vs batch in the same root: F@0.5 % {f}");

    // A batch build that sizes its own root: the same frames, another grid. Two batch builds
    // whose roots differ only by a translation disagree by about as much on these six noisy
    // frames (docs/store.md, "Growing scenes"), so this bound is looser.
    let batch = dir.path().join("batch");
    ingest(
        &batch,
        &all,
        &["--max-depth", &(scene.max_depth - doublings + 1).to_string()],
    );
    let batch_mesh = solve_and_extract(&batch);
    let f = f_score(&grown_mesh, &batch_mesh, 0.005);
    assert!(f >= 0.95, "grown vs batch: F@0.5 % {f}");
}

#[test]
fn a_root_given_at_the_first_ingest_never_grows() {
    let Some(_) = shared_data("7scenes-redkitchen") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    // The root a first ingest of these frames would choose, given explicitly.
    let sized = dir.path().join("sized");
    ingest(&sized, &FIRST, &["--max-depth", "7"]);
    let scene = read_scene(&octstore::Store::open(&sized).unwrap()).unwrap().unwrap();
    let root = format!(
        "--root={},{},{},{}",
        scene.root_min[0], scene.root_min[1], scene.root_min[2], scene.root_side
    );
    let store = dir.path().join("fixed");
    ingest(&store, &FIRST, &[&root, "--max-depth", "7"]);
    let mut args = vec!["ingest".to_string(), store.display().to_string(), "--quiet".into()];
    args.extend(frames(&LATER));
    let args: Vec<&str> = args.iter().map(String::as_str).collect();
    let out = octstore(&args, &[]);
    assert!(!out.status.success());
    let message = stderr(&out);
    assert!(
        message.contains("fixed by --root") && message.contains("frame-000"),
        "{message}"
    );
    let opened = octstore::Store::open(&store).unwrap();
    assert_eq!(opened.latest().unwrap().version(), 1, "the refused ingest committed");
}

#[test]
fn frames_inside_the_root_leave_it_as_it_was() {
    let Some(_) = shared_data("7scenes-redkitchen") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    ingest(&store, &[0, 20], &["--max-depth", "7"]);
    let before = read_scene(&octstore::Store::open(&store).unwrap()).unwrap();
    let summary = ingest(&store, &[10], &[]);
    assert!(!summary.contains("root grown"), "{summary}");
    let opened = octstore::Store::open(&store).unwrap();
    assert_eq!(read_scene(&opened).unwrap(), before);
    // One run for the first ingest's two maps (a group of up to 16), one for the later map.
    assert_eq!(opened.latest().unwrap().segments("ingest").len(), 2);
}

#[test]
fn sigkill_during_a_growing_ingest_then_resume() {
    let Some(_) = shared_data("7scenes-redkitchen") else {
        return;
    };
    let root = tempfile::tempdir().unwrap();
    KillTrials {
        root: root.path(),
        trials: 6,
        seed: 0x9E37_79B9_7F4A_7C15,
        window_percent: 110,
        prepare: &|store| {
            ingest(store, &FIRST, &["--max-depth", "7", "--threads", "1"]);
        },
        args: &|store, resume| {
            let mut args = vec![
                "ingest".to_string(),
                store.display().to_string(),
                "--quiet".into(),
                "--threads".into(),
                "1".into(),
            ];
            args.extend(frames(&LATER));
            if resume {
                args.push("--resume".into());
            }
            args
        },
    }
    .run();
}
