//! Ingest and octree build: inputs, bad input, incremental and order-independent builds.

mod common;

use std::path::{Path, PathBuf};

use common::*;
use glam::{DMat4, DVec3};
use octstore::RunOptions;
use octstore::Store;
use octstore::inputs::{DepthImage, ImageFormat, write_pfm};
use octstore::inputs::{DiscoverOptions, discover};
use octstore::testing::quality::synthetic_scenes::{SceneSpec, Shape};
use octstore::testing::stages::ingest::{IngestOptions, IngestStage, back_project};
use octstore::testing::stages::octree::{OctreeStage, check_octree_keys};
use octstore::testing::stages::{INGEST, OCTREE};

fn kitchen() -> PathBuf {
    shared_path("7scenes-redkitchen")
}

fn frame(n: u32) -> String {
    kitchen()
        .join(format!("frame-{n:06}.depth.png"))
        .to_string_lossy()
        .into_owned()
}

fn options() -> RunOptions {
    RunOptions {
        resume: false,
        threads: 2,
        progress: false,
    }
}

fn small_scene() -> SceneSpec {
    SceneSpec {
        shapes: vec![Shape::Sphere {
            center: DVec3::new(0.1, -0.2, 0.3),
            radius: 0.5,
        }],
        cameras: 6,
        distance: 2.0,
        target: DVec3::new(0.1, -0.2, 0.3),
        width: 48,
        height: 36,
        fov_degrees: 45.0,
        noise: None,
        room: None,
    }
}

/// Ingest + octree through the library; returns the store.
fn build(dir: &Path, inputs: &[Vec<PathBuf>], root: Option<([f64; 3], f64)>, max_depth: u8, leaf_cubes: u64) -> Store {
    build_with_runs_of(
        dir,
        inputs,
        root,
        max_depth,
        leaf_cubes,
        IngestOptions::default().maps_per_run,
    )
}

/// [`build`], with `maps_per_run` depth maps a run.
fn build_with_runs_of(
    dir: &Path,
    inputs: &[Vec<PathBuf>],
    root: Option<([f64; 3], f64)>,
    max_depth: u8,
    leaf_cubes: u64,
    maps_per_run: usize,
) -> Store {
    let store = Store::create(dir).unwrap();
    for batch in inputs {
        let sources = discover(batch, &DiscoverOptions::default()).unwrap();
        let stage = IngestStage::prepare(
            &store,
            sources,
            &IngestOptions {
                root,
                root_margin: 0.1,
                max_depth,
                maps_per_run,
                ..IngestOptions::default()
            },
        )
        .unwrap();
        store.run_stage(&stage, &options()).unwrap();
    }
    let scene = octstore::testing::stages::ingest::read_scene(&store).unwrap().unwrap();
    let scratch = store.scratch_dir(OCTREE).unwrap();
    let stage = OctreeStage::new(scene, leaf_cubes, 1 << 20, scratch);
    store.run_stage(&stage, &options()).unwrap();
    store
}

fn octree_keys(store: &Store) -> Vec<octstore::CubeKey> {
    let snap = store.latest().unwrap();
    let mut keys = Vec::new();
    for (name, _) in snap.segments(OCTREE) {
        keys.extend(snap.open_segment(name).unwrap().reader().unwrap().read_keys().unwrap());
    }
    keys.sort();
    keys
}

#[test]
fn redkitchen_frames_give_a_complete_balanced_octree() {
    let Some(_) = shared_data("7scenes-redkitchen") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let inputs = vec![vec![PathBuf::from(frame(0)), PathBuf::from(frame(500))]];
    let store = build(dir.path(), &inputs, None, 9, 3000);
    let snap = store.latest().unwrap();
    assert_eq!(snap.segments(INGEST).len(), 1, "the two maps share a run");
    let keys = octree_keys(&store);
    assert!(keys.len() > 1000, "{} cubes", keys.len());
    assert_eq!(check_octree_keys(&keys), Vec::<String>::new());
    // The treetop: every leaf segment below the limit, and ranges are contiguous.
    assert!(snap.segments(OCTREE).len() > 2);
    assert!(snap.segments(OCTREE).iter().all(|(_, r)| r.rows < 3000));
    let report = store
        .verify(&[octstore::testing::stages::octree::verify_octree])
        .unwrap();
    assert!(report.is_ok(), "{:?}", report.problems);
    // Every requested cube is a node with its radius sums.
    let requested: u64 = snap.rows(INGEST);
    assert!(requested > 0);
}

#[test]
fn manifest_formats_and_pose_conventions_back_project_onto_the_surface() {
    let dir = tempfile::tempdir().unwrap();
    let spec = small_scene();
    let pose = spec.poses()[1];
    let image = spec.render(1, &pose);
    write_pfm(&dir.path().join("a.pfm"), &image).unwrap();
    write_npy(&dir.path().join("a.npy"), &image);
    write_png16(&dir.path().join("a.png"), &image, 0.0001);
    let f = spec.focal();
    let k = serde_json::json!({"fx": f, "fy": f, "cx": 24.0, "cy": 18.0});
    let row_major = |m: DMat4| m.transpose().to_cols_array().to_vec();
    // The same camera expressed four ways.
    let gl = pose * DMat4::from_diagonal(glam::DVec4::new(1.0, -1.0, -1.0, 1.0));
    let entries = serde_json::json!({"depth_maps": [
        {"image": "a.pfm", "width": 48, "height": 36, "intrinsics": k, "kind": "photo",
         "pose": {"camera_to_world": row_major(pose), "axes": "opencv"}},
        {"image": "a.npy", "width": 48, "height": 36, "intrinsics": k, "kind": "rgbd",
         "pose": {"world_to_camera": row_major(pose.inverse()), "axes": "opencv"}},
        {"image": "a.png", "depth_scale": 0.0001, "width": 48, "height": 36, "intrinsics": k, "kind": "lidar",
         "pose": {"camera_to_world": row_major(gl), "axes": "opengl"}},
    ]});
    let manifest = dir.path().join("m.json");
    std::fs::write(&manifest, entries.to_string()).unwrap();
    let sources = discover(&[manifest], &DiscoverOptions::default()).unwrap();
    assert_eq!(sources.len(), 3);
    assert_eq!(sources[2].weight, 5.0, "LIDAR votes weigh 5 by default");
    assert!(matches!(sources[2].format, ImageFormat::Png16 { .. }));
    for source in &sources {
        let samples = back_project(source, &source.load().unwrap()).unwrap();
        assert!(samples.points.len() > 300, "{}", source.path.display());
        for p in &samples.points {
            let d = spec.signed_distance(*p).abs();
            assert!(
                d < 2e-3,
                "{}: sample {p:?} is {d} from the sphere",
                source.path.display()
            );
        }
    }
}

fn write_npy(path: &Path, image: &DepthImage) {
    let mut header = format!(
        "{{'descr': '<f4', 'fortran_order': False, 'shape': ({}, {}), }}",
        image.height, image.width
    );
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    for d in &image.depth {
        out.extend_from_slice(&d.to_le_bytes());
    }
    std::fs::write(path, out).unwrap();
}

#[test]
fn bad_input_gives_a_clear_error_and_leaves_the_store_unchanged() {
    let Some(_) = shared_data("7scenes-redkitchen") else {
        return;
    };
    let root = tempfile::tempdir().unwrap();
    let store_dir = root.path().join("store");
    let scene = small_scene().write(&root.path().join("scene")).unwrap();
    let out = octstore(
        &[
            "ingest",
            store_dir.to_str().unwrap(),
            scene.to_str().unwrap(),
            "--quiet",
        ],
        &[],
    );
    assert!(out.status.success(), "{}", stderr(&out));
    let before = fingerprint(&store_dir);

    let bad = root.path().join("bad");
    std::fs::create_dir_all(&bad).unwrap();
    std::fs::write(bad.join("camera-intrinsics.txt"), "585 0 320\n0 585 240\n0 0 1\n").unwrap();
    std::fs::copy(frame(0), bad.join("frame-000000.depth.png")).unwrap();
    let expect_error = |args: &[&str], needle: &str| {
        let mut all = vec!["ingest", store_dir.to_str().unwrap()];
        all.extend_from_slice(args);
        let out = octstore(&all, &[]);
        assert!(!out.status.success(), "{args:?} should fail");
        let err = stderr(&out);
        assert!(err.contains(needle), "{args:?}: expected '{needle}' in: {err}");
        assert_same_store(&before, &fingerprint(&store_dir), &format!("{args:?}"));
    };
    // Missing pose.
    let png = bad.join("frame-000000.depth.png");
    expect_error(&[png.to_str().unwrap()], "missing pose");
    // Non-invertible pose.
    std::fs::write(
        bad.join("frame-000000.pose.txt"),
        "0 0 0 1\n0 0 0 2\n0 0 0 3\n0 0 0 1\n",
    )
    .unwrap();
    expect_error(&[png.to_str().unwrap()], "not invertible");
    // Unparseable pose.
    std::fs::write(bad.join("frame-000000.pose.txt"), "1 0 0 0\n0 1 0 zero\n").unwrap();
    expect_error(&[png.to_str().unwrap()], "frame-000000.pose.txt");
    std::fs::copy(
        kitchen().join("frame-000000.pose.txt"),
        bad.join("frame-000000.pose.txt"),
    )
    .unwrap();
    // Size that does not match the intrinsics.
    std::fs::write(bad.join("camera-intrinsics.txt"), "585 0 900\n0 585 240\n0 0 1\n").unwrap();
    expect_error(&[png.to_str().unwrap()], "do not match");
    std::fs::write(bad.join("camera-intrinsics.txt"), "585 0 320\n0 585 240\n0 0 1\n").unwrap();
    // Truncated image.
    let bytes = std::fs::read(frame(0)).unwrap();
    std::fs::write(&png, &bytes[..bytes.len() / 2]).unwrap();
    expect_error(&[png.to_str().unwrap()], "frame-000000.depth.png");
    // So far outside the root cube that growing it would take more than the doublings one
    // ingest may apply.
    std::fs::write(&png, &bytes).unwrap();
    std::fs::write(
        bad.join("frame-000000.pose.txt"),
        "1 0 0 1e9\n0 1 0 0\n0 0 1 0\n0 0 0 1\n",
    )
    .unwrap();
    expect_error(&[png.to_str().unwrap()], "doublings of the store's root cube");
    // Unknown format: no guessing.
    let odd = root.path().join("scan.xyz");
    std::fs::write(&odd, "1 2 3").unwrap();
    expect_error(&[odd.to_str().unwrap()], "cannot tell the input format");
}

#[test]
fn invalid_depths_are_skipped_and_counted() {
    let root = tempfile::tempdir().unwrap();
    let spec = small_scene();
    let pose = spec.poses()[0];
    let mut image = spec.render(0, &pose);
    let valid_before = image.depth.iter().filter(|d| d.is_finite()).count();
    image.depth[100] = f32::NAN;
    image.depth[101] = -1.0;
    image.depth[102] = f32::INFINITY;
    image.depth[103] = 1.0e9;
    let _ = valid_before;
    write_pfm(&root.path().join("v.pfm"), &image).unwrap();
    let source = octstore::inputs::DepthMapSource {
        path: root.path().join("v.pfm"),
        format: ImageFormat::Pfm,
        width: spec.width,
        height: spec.height,
        projection: octstore::inputs::Projection::Pinhole {
            fx: spec.focal(),
            fy: spec.focal(),
            cx: 24.0,
            cy: 18.0,
        },
        camera_to_world: pose.to_cols_array(),
        kind: octstore::inputs::Kind::Photo,
        weight: 1.0,
        noise: octstore::inputs::DepthNoise::Footprint,
    };
    let loaded = source.load().unwrap();
    let samples = back_project(&source, &loaded).unwrap();
    assert_eq!(samples.stats.absurd, 1, "{:?}", samples.stats);
    let invalid_expected = loaded.depth.iter().filter(|d| !d.is_finite()).count() as u64;
    assert_eq!(samples.stats.invalid, invalid_expected);
    assert!(samples.points.iter().all(|p| p.is_finite()));
}

#[test]
fn incremental_ingest_equals_all_at_once_in_any_order() {
    let Some(_) = shared_data("7scenes-redkitchen") else {
        return;
    };
    let root = tempfile::tempdir().unwrap();
    let (a, b, c) = (
        PathBuf::from(frame(10)),
        PathBuf::from(frame(400)),
        PathBuf::from(frame(800)),
    );
    // A fixed root so that the first ingest does not decide it differently.
    let fixed = Some(([-3.0, -3.0, -3.0], 8.0));
    let all = build(
        &root.path().join("all"),
        &[vec![a.clone(), b.clone(), c.clone()]],
        fixed,
        9,
        2000,
    );
    let incremental = build(
        &root.path().join("inc"),
        &[vec![c.clone(), a.clone()], vec![b.clone()]],
        fixed,
        9,
        2000,
    );
    let reordered = build(
        &root.path().join("reordered"),
        &[vec![c.clone(), b.clone(), a.clone()]],
        fixed,
        9,
        2000,
    );
    let (sa, si) = (all.latest().unwrap(), incremental.latest().unwrap());
    assert_eq!(sa.digest(OCTREE), si.digest(OCTREE));
    // The same maps in one ingest write the same runs in any order; split over two ingests
    // they are grouped otherwise (runs are per ingest), and the octree is the same.
    assert_eq!(sa.digest(INGEST), reordered.latest().unwrap().digest(INGEST));
    assert_eq!(sa.digest(OCTREE), reordered.latest().unwrap().digest(OCTREE));
    // Byte-identical octree segment content, leaf by leaf.
    let contents = |snap: &octstore::Snapshot<'_>| -> Vec<Vec<u8>> {
        snap.segments(OCTREE)
            .iter()
            .map(|(name, _)| snap.open_segment(name).unwrap().bytes().to_vec())
            .collect()
    };
    assert_eq!(contents(&sa), contents(&si));

    // A second solve with nothing new does nothing; a new depth map rewrites only the leaves
    // whose cubes changed.
    let scene = octstore::testing::stages::ingest::read_scene(&incremental)
        .unwrap()
        .unwrap();
    let again = OctreeStage::new(scene, 2000, 1 << 20, incremental.scratch_dir(OCTREE).unwrap());
    assert_eq!(incremental.run_stage(&again, &options()).unwrap().version, None);
    let leaves_before = si.segments(OCTREE).len();
    drop(si);
    let sources = discover(&[PathBuf::from(frame(830))], &DiscoverOptions::default()).unwrap();
    let stage = IngestStage::prepare(&incremental, sources, &IngestOptions::default()).unwrap();
    incremental.run_stage(&stage, &options()).unwrap();
    let rebuild = OctreeStage::new(scene, 2000, 1 << 20, incremental.scratch_dir(OCTREE).unwrap());
    let report = incremental.run_stage(&rebuild, &options()).unwrap();
    let leaves_after = incremental.latest().unwrap().segments(OCTREE).len();
    assert!(report.units > 0, "the new frame changed nothing");
    assert!(
        report.units < leaves_after.max(leaves_before),
        "all {} leaves were rewritten for one new frame",
        report.units
    );
    assert!(
        incremental
            .verify(&[octstore::testing::stages::octree::verify_octree])
            .unwrap()
            .is_ok()
    );
}

#[test]
fn ingest_cli_reports_and_info_counts() {
    let Some(_) = shared_data("7scenes-redkitchen") else {
        return;
    };
    let root = tempfile::tempdir().unwrap();
    let store = root.path().join("s");
    let out = octstore(
        &[
            "ingest",
            store.to_str().unwrap(),
            &frame(0),
            &frame(1),
            "--max-depth",
            "8",
            "--memory-budget",
            "256MiB",
        ],
        &[],
    );
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(stdout(&out).contains("2 depth map(s)"), "{}", stdout(&out));
    let out = octstore(
        &[
            "solve",
            store.to_str().unwrap(),
            "--until",
            "octree",
            "--leaf-cubes",
            "5000",
        ],
        &[],
    );
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(stdout(&out).contains("treetop leaves"), "{}", stdout(&out));
    let info = octstore(&["info", store.to_str().unwrap(), "--json"], &[]);
    let json: serde_json::Value = serde_json::from_str(&stdout(&info)).unwrap();
    assert_eq!(json["depth_maps"], 2);
    assert!(json["cubes"].as_u64().unwrap() > 100);
    assert!(json["treetop_leaves"].as_u64().unwrap() >= 1);
    assert!(json["digest"]["octree"].is_string());
    // Ingested without --sample-sums: `solve --method ssd` would need a new store.
    assert_eq!(json["sample_sums"], false);
    let verify = octstore(&["verify", store.to_str().unwrap()], &[]);
    assert!(verify.status.success(), "{}", stderr(&verify));
    let with_sums = root.path().join("with-sums");
    let s = with_sums.to_str().unwrap();
    let out = octstore(&["ingest", s, &frame(0), "--max-depth", "6", "--sample-sums"], &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    let info = octstore(&["info", s], &[]);
    assert!(stdout(&info).contains("sample sums    yes"), "{}", stdout(&info));
}

/// Key -> (radius sum, radius count) of every cube of `stage`'s segments, summed over segments.
fn radius_stats(
    snap: &octstore::Snapshot<'_>,
    stage: &str,
) -> std::collections::BTreeMap<octstore::CubeKey, (u64, u32)> {
    let mut stats = std::collections::BTreeMap::new();
    for (name, _) in snap.segments(stage) {
        let file = snap.open_segment(name).unwrap();
        let reader = file.reader().unwrap();
        let keys = reader.read_keys().unwrap();
        let (_, sums) = reader.read_u64("radius_sum").unwrap();
        let (_, counts) = reader.read_u32("radius_count").unwrap();
        for ((key, sum), count) in keys.into_iter().zip(sums).zip(counts) {
            let entry = stats.entry(key).or_insert((0u64, 0u32));
            entry.0 += sum;
            entry.1 += count;
        }
    }
    stats
}

#[test]
fn merging_more_runs_than_the_fan_in_keeps_every_radius_sum() {
    use octstore::testing::stages::octree::MERGE_FAN_IN;
    let dir = tempfile::tempdir().unwrap();
    let spec = SceneSpec {
        cameras: 2 * MERGE_FAN_IN + 7,
        width: 16,
        height: 12,
        ..small_scene()
    };
    let manifest = spec.write(&dir.path().join("views")).unwrap();
    let store = build_with_runs_of(&dir.path().join("store"), &[vec![manifest]], None, 8, 500, 1);
    let snap = store.latest().unwrap();
    assert_eq!(snap.segments(INGEST).len(), spec.cameras, "one run per depth map");
    let requested = radius_stats(&snap, INGEST);
    let nodes = radius_stats(&snap, OCTREE);
    assert!(requested.len() > 500, "{} requested cubes", requested.len());
    for (key, stats) in &requested {
        assert_eq!(nodes.get(key), Some(stats), "cube {key:?}");
    }
    let with_radius = nodes.values().filter(|(_, count)| *count > 0).count();
    assert_eq!(
        with_radius,
        requested.len(),
        "nodes the runs never requested carry radii"
    );
    assert!(
        store
            .scratch_dir(OCTREE)
            .unwrap()
            .read_dir()
            .unwrap()
            .all(|e| { !e.unwrap().file_name().to_string_lossy().starts_with("merge-") }),
        "merge rounds leave no scratch files"
    );
}

/// Maps grouped into runs of 16 (the default), 3 or 1 give fewer run rows the more share a run,
/// and the same octree, byte for byte: the grouping only decides which maps' cubes are summed
/// first.
#[test]
fn grouping_depth_maps_into_runs_changes_the_runs_not_the_octree() {
    let dir = tempfile::tempdir().unwrap();
    let spec = SceneSpec {
        cameras: 20,
        ..small_scene()
    };
    let manifest = spec.write(&dir.path().join("views")).unwrap();
    let stores: Vec<(usize, Store)> = [16, 3, 1]
        .into_iter()
        .map(|per_run| {
            let store = build_with_runs_of(
                &dir.path().join(format!("runs-of-{per_run}")),
                &[vec![manifest.clone()]],
                None,
                8,
                500,
                per_run,
            );
            (per_run, store)
        })
        .collect();
    let contents = |snap: &octstore::Snapshot<'_>| -> Vec<Vec<u8>> {
        snap.segments(OCTREE)
            .iter()
            .map(|(name, _)| snap.open_segment(name).unwrap().bytes().to_vec())
            .collect()
    };
    let snaps: Vec<(usize, octstore::Snapshot<'_>)> = stores
        .iter()
        .map(|(per_run, store)| (*per_run, store.latest().unwrap()))
        .collect();
    let (_, one_each) = snaps.last().unwrap();
    let rows = |snap: &octstore::Snapshot<'_>| snap.rows(INGEST);
    for (per_run, snap) in &snaps {
        assert_eq!(
            snap.segments(INGEST).len(),
            spec.cameras.div_ceil(*per_run),
            "runs of {per_run}"
        );
        assert_eq!(contents(snap), contents(one_each), "octree from runs of {per_run}");
        assert_eq!(radius_stats(snap, OCTREE), radius_stats(one_each, OCTREE));
    }
    let (_, by_sixteen) = snaps.first().unwrap();
    assert!(
        rows(by_sixteen) < rows(one_each),
        "runs of 16 hold {} rows, runs of 1 {}",
        rows(by_sixteen),
        rows(one_each)
    );
}

/// RGB-D frames whose intrinsics file lies elsewhere (as many published captures ship it, one
/// level up): `--intrinsics` names it, as a 3x3 matrix or as fx fy cx cy; without it the
/// error says what to pass; a malformed file is named.
#[test]
fn frames_without_their_own_intrinsics_take_them_from_intrinsics_file() {
    let Some(_) = shared_data("7scenes-redkitchen") else {
        return;
    };
    let root = tempfile::tempdir().unwrap();
    let frames = root.path().join("capture").join("frames");
    std::fs::create_dir_all(&frames).unwrap();
    for n in [0u32, 10] {
        for suffix in ["depth.png", "pose.txt"] {
            std::fs::copy(
                kitchen().join(format!("frame-{n:06}.{suffix}")),
                frames.join(format!("frame-{n:06}.{suffix}")),
            )
            .unwrap();
        }
    }
    let matrix = root.path().join("capture").join("camera-intrinsics.txt");
    std::fs::copy(kitchen().join("camera-intrinsics.txt"), &matrix).unwrap();
    let four = root.path().join("intrinsics-4.txt");
    std::fs::write(&four, "585 585 320 240\n").unwrap();
    let seven = root.path().join("intrinsics-7.txt");
    std::fs::write(&seven, "585 0 320 0 585 240 0\n").unwrap();
    let (f, m, s) = (
        frames.to_str().unwrap(),
        matrix.to_str().unwrap(),
        seven.to_str().unwrap(),
    );
    let ingest = |store: &str, extra: &[&str]| {
        let store = root.path().join(store);
        octstore(
            &[&["ingest", store.to_str().unwrap(), f, "--quiet"][..], extra].concat(),
            &[],
        )
    };
    let out = ingest("without", &[]);
    assert!(!out.status.success());
    let err = stderr(&out);
    assert!(
        err.contains("--intrinsics FILE") && err.matches(f).count() == 1,
        "{err}"
    );
    for (store, file) in [("matrix", m), ("four", four.to_str().unwrap())] {
        let out = ingest(store, &["--intrinsics", file]);
        assert!(out.status.success(), "{store}: {}", stderr(&out));
    }
    // Both forms give the same store: the same intrinsics, the same samples.
    let info = |store: &str| {
        let path = root.path().join(store);
        stdout(&octstore(&["info", path.to_str().unwrap(), "--json"], &[]))
    };
    let (a, b): (serde_json::Value, serde_json::Value) = (
        serde_json::from_str(&info("matrix")).unwrap(),
        serde_json::from_str(&info("four")).unwrap(),
    );
    assert_eq!(a["digest"], b["digest"]);
    assert_eq!(a["depth_maps"], 2, "{a}");
    let out = ingest("seven", &["--intrinsics", s]);
    assert!(!out.status.success());
    let err = stderr(&out);
    assert!(
        err.contains("intrinsics-7.txt") && err.contains("found 7 values"),
        "{err}"
    );
    // A skewed matrix, or one whose last row is not 0 0 1, is refused naming the file: the
    // pinhole has no place for them.
    for (name, matrix, expected) in [
        ("skewed.txt", "585 2 320\n0 585 240\n0 0 1\n", "skew 2"),
        (
            "projective.txt",
            "585 0 320\n0 585 240\n0.1 0 1\n",
            "last row is 0.1 0 1",
        ),
    ] {
        let file = root.path().join(name);
        std::fs::write(&file, matrix).unwrap();
        let out = ingest(&format!("store-{name}"), &["--intrinsics", file.to_str().unwrap()]);
        assert!(!out.status.success(), "{name} was accepted");
        let err = stderr(&out);
        assert!(err.contains(name) && err.contains(expected), "{err}");
    }
}

/// RGB-D frames measure their noise by default: the Kinect's depths are a staircase of
/// disparity steps (quantized), so the measured model spans two sigmas, and on RedKitchen it
/// makes as many cubes as the Kinect table at one sigma (within a tenth), fewer than the pixel
/// footprint alone (`--depth-noise none`). The tables stay as choices (`kinect`, fewer cubes
/// still at two sigmas); every model is recorded with its map; the CLI's numbers equal to the
/// table give the same store; malformed models are refused with what is expected.
#[test]
fn rgbd_frames_measure_their_noise_unless_told_otherwise() {
    let Some(_) = shared_data("7scenes-redkitchen") else {
        return;
    };
    let root = tempfile::tempdir().unwrap();
    let (a, b) = (frame(0), frame(500));
    let ingest = |store: &str, extra: &[&str]| {
        let path = root.path().join(store);
        let out = octstore(
            &[&["ingest", path.to_str().unwrap(), &a, &b, "--quiet"][..], extra].concat(),
            &[],
        );
        (path, out)
    };
    let recorded = |path: &Path| {
        let store = Store::open_read_only(path).unwrap();
        let maps = octstore::testing::stages::ingest::registered_depth_maps(&store).unwrap();
        assert_eq!(maps.len(), 2);
        let cubes: u64 = maps.iter().map(|(_, r)| r.stats.cubes).sum();
        (maps[0].1.source.noise, cubes)
    };
    let digest = |path: &Path| {
        let info: serde_json::Value =
            serde_json::from_str(&stdout(&octstore(&["info", path.to_str().unwrap(), "--json"], &[]))).unwrap();
        info["digest"].clone()
    };
    let kinect = octstore::inputs::DepthNoise::STRUCTURED_LIGHT;
    let mut cubes = Vec::new();
    let mut paths = Vec::new();
    for (store, extra, noise) in [
        (
            "none",
            &["--depth-noise", "none"][..],
            Some(octstore::inputs::DepthNoise::Footprint),
        ),
        ("default", &[][..], None),
        ("kinect", &["--depth-noise", "kinect"][..], Some(kinect)),
        (
            "two",
            &["--depth-noise", "kinect", "--noise-sigmas", "2"][..],
            Some(kinect.with_sigmas(2.0)),
        ),
        (
            "explicit",
            &["--depth-noise", "0.0012,0.0019,0.4", "--noise-sigmas", "1"][..],
            Some(kinect),
        ),
    ] {
        let (path, out) = ingest(store, extra);
        assert!(out.status.success(), "{store}: {}", stderr(&out));
        let (recorded_noise, count) = recorded(&path);
        match noise {
            Some(noise) => assert_eq!(recorded_noise, noise, "{store}"),
            None => match recorded_noise {
                octstore::inputs::DepthNoise::Axial {
                    quadratic,
                    offset,
                    sigmas,
                    ..
                } => {
                    assert!(quadratic > 0.0 && offset == 0.0, "{recorded_noise:?}");
                    assert_eq!(sigmas, octstore::testing::stages::ingest::noise::QUANTIZED_SIGMAS);
                }
                other => panic!("the default recorded {other:?}"),
            },
        }
        cubes.push(count);
        paths.push(path);
    }
    let (none, measured, table, two) = (cubes[0], cubes[1], cubes[2], cubes[3]);
    assert!(
        none > table * 5 / 4 && table > two * 11 / 10,
        "cubes with none, the table at 1 and 2 sigmas: {cubes:?}"
    );
    assert!(
        measured.abs_diff(table) * 10 <= table,
        "measured against the table: {cubes:?}"
    );
    assert_eq!(cubes[2], cubes[4]);
    assert_eq!(digest(&paths[2]), digest(&paths[4]));

    for (extra, expected) in [
        (&["--depth-noise", "1,2"][..], "1 number (sigma) or 3"),
        (&["--depth-noise=-0.001"][..], "not negative"),
        (&["--noise-sigmas", "nan"][..], "standard deviations in [0, 100]"),
    ] {
        let (path, out) = ingest("bad", extra);
        assert!(!out.status.success(), "{extra:?}");
        assert!(stderr(&out).contains(expected), "{extra:?}: {}", stderr(&out));
        assert!(!path.exists(), "{extra:?} created a store");
    }
}

/// Numbers out of range are refused with what is expected, before any store is written:
/// a key depth past the keys' limit (40 once committed keys that `verify` called malformed),
/// NaN or negative weights (NaN solutions), a memory budget or leaf size that would build
/// one-cube leaves, and a manifest weight that overflows the vote sums.
#[test]
fn numbers_out_of_range_are_refused_before_anything_is_written() {
    let Some(_) = shared_data("7scenes-redkitchen") else {
        return;
    };
    let root = tempfile::tempdir().unwrap();
    let store = root.path().join("store");
    let s = store.to_str().unwrap();
    let a = frame(0);
    for (args, expected) in [
        (vec!["ingest", s, &a, "--max-depth", "40"], "40 is not in 1..=32"),
        (vec!["ingest", s, &a, "--max-depth", "0"], "0 is not in 1..=32"),
        (vec!["ingest", s, &a, "--root-margin", "nan"], "not a margin"),
        (vec!["ingest", s, &a, "--memory-budget", "0"], "below the least"),
        (vec!["ingest", s, &a, "--memory-budget", "1KB"], "below the least"),
        (vec!["solve", s, "--alpha1", "nan"], "not a finite weight"),
        (vec!["solve", s, "--lambda=-1"], "not a finite weight"),
        (
            vec!["solve", s, "--method", "ssd", "--ssd-normal-weight", "0"],
            "not a weight in (0, 1e6]",
        ),
        (
            vec!["solve", s, "--method", "ssd", "--ssd-smoothness", "inf"],
            "not a weight in (0, 1e6]",
        ),
        (
            vec!["solve", s, "--method", "ssd", "--ssd-tolerance", "1"],
            "not a residual target in (0, 1)",
        ),
        (vec!["solve", s, "--alpha0", "inf"], "not a finite weight"),
        (vec!["solve", s, "--leaf-cubes", "0"], "0 is not in 64.."),
        (
            vec!["solve", s, "--iterations", "0"],
            "not an iteration count of at least 1",
        ),
    ] {
        let out = octstore(&args, &[]);
        assert!(!out.status.success(), "{args:?} succeeded");
        assert!(stderr(&out).contains(expected), "{args:?}: {}", stderr(&out));
        assert!(!store.exists(), "{args:?} created the store");
    }
    let golden = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/golden-v2-ingest/input");
    std::fs::copy(golden.join("plane.pfm"), root.path().join("plane.pfm")).unwrap();
    let manifest = std::fs::read_to_string(golden.join("scene.json"))
        .unwrap()
        .replace("\"kind\": \"rgbd\"", "\"kind\": \"rgbd\", \"weight\": 1e38");
    let path = root.path().join("scene.json");
    std::fs::write(&path, manifest).unwrap();
    let out = octstore(&["ingest", s, path.to_str().unwrap()], &[]);
    assert!(!out.status.success());
    let err = stderr(&out);
    assert!(
        err.contains("scene.json") && err.contains("depth_maps[0]") && err.contains("is not in [0, 1000]"),
        "{err}"
    );
}

/// Depth images whose geometry does not match: 320x240 and 640x400 frames with the 640x480
/// intrinsics beside them (principal point at the corner, or a tenth off centre), and PFM headers with a NaN or fractional size or
/// a NaN scale, are refused naming the file.
#[test]
fn images_of_the_wrong_geometry_are_refused() {
    let Some(_) = shared_data("7scenes-redkitchen") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let frames = dir.path().join("frames");
    std::fs::create_dir_all(&frames).unwrap();
    std::fs::copy(
        kitchen().join("camera-intrinsics.txt"),
        frames.join("camera-intrinsics.txt"),
    )
    .unwrap();
    std::fs::copy(
        kitchen().join("frame-000000.pose.txt"),
        frames.join("frame-000000.pose.txt"),
    )
    .unwrap();
    // A quarter-size frame (principal point at its corner) and a 640x400 crop (40 pixels, a
    // tenth of its height, off its centre).
    for (width, height) in [(320u32, 240u32), (640, 400)] {
        let small = DepthImage {
            width,
            height,
            depth: vec![1.5; (width * height) as usize],
        };
        write_png16(&frames.join("frame-000000.depth.png"), &small, 0.001);
        let store = dir.path().join(format!("store-{width}x{height}"));
        let out = octstore(
            &["ingest", store.to_str().unwrap(), frames.to_str().unwrap(), "--quiet"],
            &[],
        );
        assert!(!out.status.success(), "{width}x{height} was ingested");
        let err = stderr(&out);
        assert!(
            err.contains("frame-000000.depth.png") && err.contains("lies far from its centre"),
            "{width}x{height}: {err}"
        );
    }

    for (header, expected) in [
        ("Pf\nnan 3\n-1.0\n", "bad PFM width 'nan'"),
        ("Pf\n4 2.5\n-1.0\n", "bad PFM height '2.5'"),
        ("Pf\n4 3\nnan\n", "bad PFM scale 'nan'"),
    ] {
        let path = dir.path().join("bad.pfm");
        let mut bytes = header.as_bytes().to_vec();
        bytes.extend(std::iter::repeat_n(0u8, 4 * 12));
        std::fs::write(&path, bytes).unwrap();
        let Err(err) = octstore::inputs::read_pfm(&path) else {
            panic!("{header:?} was read");
        };
        let err = err.to_string();
        assert!(err.contains("bad.pfm") && err.contains(expected), "{header:?}: {err}");
    }
}

/// Focal lengths that are not positive are the intrinsics file's error, named as such, whether
/// it is a folder's camera-intrinsics.txt or a file given with --intrinsics.
#[test]
fn bad_focal_lengths_name_the_intrinsics_file() {
    let Some(_) = shared_data("7scenes-redkitchen") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let frames = dir.path().join("frames");
    std::fs::create_dir_all(&frames).unwrap();
    for suffix in ["depth.png", "pose.txt"] {
        std::fs::copy(
            kitchen().join(format!("frame-000000.{suffix}")),
            frames.join(format!("frame-000000.{suffix}")),
        )
        .unwrap();
    }
    let own = frames.join("camera-intrinsics.txt");
    std::fs::write(&own, "0 0 320\n0 585 240\n0 0 1\n").unwrap();
    let given = dir.path().join("intrinsics.txt");
    std::fs::write(&given, "585 -585 320 240\n").unwrap();
    let store = dir.path().join("store");
    for (extra, file) in [(vec![], &own), (vec!["--intrinsics", given.to_str().unwrap()], &given)] {
        let args = [
            &["ingest", store.to_str().unwrap(), frames.to_str().unwrap(), "--quiet"][..],
            &extra,
        ]
        .concat();
        let out = octstore(&args, &[]);
        assert!(!out.status.success());
        let err = stderr(&out);
        assert!(
            err.contains(file.to_str().unwrap())
                && err.contains("focal lengths must be positive")
                && !err.contains("depth.png"),
            "{err}"
        );
    }
}

/// One depth map whose pose is off by 10^4 (a translation in other units) among six: the root
/// is sized by the others, and the far one is refused by name, where it used to stretch the
/// root until the whole scene was a few cubes and every command succeeded with an empty mesh.
#[test]
fn a_far_off_pose_is_named_and_does_not_collapse_the_root() {
    let dir = tempfile::tempdir().unwrap();
    let manifest_path = small_scene().write(&dir.path().join("views")).unwrap();
    let mut manifest: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&manifest_path).unwrap()).unwrap();
    let pose = &mut manifest["depth_maps"][2]["pose"]["camera_to_world"];
    pose[3] = serde_json::json!(pose[3].as_f64().unwrap() + 1e4);
    std::fs::write(&manifest_path, manifest.to_string()).unwrap();
    let store = dir.path().join("store");
    let out = octstore(
        &[
            "ingest",
            store.to_str().unwrap(),
            manifest_path.to_str().unwrap(),
            "--max-depth",
            "7",
        ],
        &[],
    );
    let text = stderr(&out);
    assert!(
        !out.status.success(),
        "the far map's samples were dropped silently: {text}"
    );
    assert!(
        text.contains("view-002.pfm") && text.contains("far from every other depth map"),
        "{text}"
    );
    assert!(text.contains("outside the store's root cube"), "{text}");
    // Without the far map, the same scene's root fits the sphere.
    let mut kept = manifest.clone();
    kept["depth_maps"].as_array_mut().unwrap().remove(2);
    std::fs::write(&manifest_path, kept.to_string()).unwrap();
    let out = octstore(
        &[
            "ingest",
            store.to_str().unwrap(),
            manifest_path.to_str().unwrap(),
            "--max-depth",
            "7",
        ],
        &[],
    );
    assert!(out.status.success(), "{}", stderr(&out));
    let scene = octstore::testing::stages::ingest::read_scene(&Store::open_read_only(&store).unwrap())
        .unwrap()
        .unwrap();
    assert!(scene.root_side < 3.0, "root side {}", scene.root_side);
}

/// Two first ingests into the same new store at once: one creates it, the other is told the
/// store is in use (it used to fail with "rename catalog.redb.tmp: No such file", or replace
/// the winner's catalog), and the store is whole.
#[test]
fn two_first_ingests_at_once_leave_one_store_and_a_clear_message() {
    let dir = tempfile::tempdir().unwrap();
    let manifest = small_scene().write(&dir.path().join("views")).unwrap();
    for trial in 0..4 {
        let store = dir.path().join(format!("store-{trial}"));
        let spawn = || {
            std::process::Command::new(octstore_bin())
                .args([
                    "ingest",
                    store.to_str().unwrap(),
                    manifest.to_str().unwrap(),
                    "--max-depth",
                    "6",
                    "--quiet",
                ])
                .stdout(std::process::Stdio::null())
                .stderr(std::process::Stdio::piped())
                .spawn()
                .unwrap()
        };
        let (first, second) = (spawn(), spawn());
        let outcomes = [first.wait_with_output().unwrap(), second.wait_with_output().unwrap()];
        assert!(
            outcomes.iter().any(|o| o.status.success()),
            "trial {trial}: neither ingest succeeded"
        );
        for out in outcomes.iter().filter(|o| !o.status.success()) {
            assert!(
                stderr(out).contains("in use by another octstore process"),
                "trial {trial}: {}",
                stderr(out)
            );
        }
        let out = octstore(&["verify", store.to_str().unwrap()], &[]);
        assert!(out.status.success(), "trial {trial}: {}", stderr(&out));
    }
}
