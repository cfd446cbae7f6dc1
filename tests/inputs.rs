//! COLMAP dense workspaces and terrestrial LIDAR scans (PTX, E57), written from analytic scenes
//! whose surfaces are known, then discovered, read and back-projected.

mod common;

use std::path::{Path, PathBuf};

use common::*;
use glam::{DMat3, DMat4, DVec3};
use octstore::inputs::write_ptx_scan;
use octstore::inputs::{DepthImage, ImageFormat, Kind, Projection};
use octstore::inputs::{DiscoverOptions, InputFormat, discover};
use octstore::inputs::{WorkspaceWriter, write_colmap_depth};
use octstore::testing::quality::synthetic_scenes::{SceneSpec, Shape};
use octstore::testing::stages::ingest::back_project;

fn sphere_scene() -> SceneSpec {
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
        room: Some(3.0),
    }
}

/// Distance from `p` to the nearest surface of the scene, room walls included.
fn surface_distance(spec: &SceneSpec, p: DVec3) -> f64 {
    let wall = spec.room.map_or(f64::INFINITY, |half| {
        (half - (p - spec.target).abs().max_element()).abs()
    });
    spec.signed_distance(p).abs().min(wall)
}

fn write_workspace(root: &Path, binary: bool) -> SceneSpec {
    let spec = sphere_scene();
    let f = spec.focal();
    let poses = spec.poses();
    let views: Vec<_> = poses
        .iter()
        .enumerate()
        // COLMAP puts pixel centres at +0.5: our principal point (24, 18) is its (24.5, 18.5).
        .map(|(i, pose)| (format!("img-{i:03}.jpg"), 48, 36, [f, f, 24.5, 18.5], *pose))
        .collect();
    let workspace = WorkspaceWriter {
        root: root.to_path_buf(),
    };
    workspace.write_model(&views, binary).unwrap();
    for (i, pose) in poses.iter().enumerate() {
        let name = &views[i].0;
        let image = spec.render(i, pose);
        match i {
            // Only a photometric map: the fallback must find it.
            1 => write_colmap_depth(&workspace.depth_path(name, "photometric"), &image).unwrap(),
            // Both: the geometric one wins; the photometric one is garbage and would fail the
            // surface check.
            2 => {
                write_colmap_depth(&workspace.depth_path(name, "geometric"), &image).unwrap();
                let garbage = DepthImage {
                    width: 48,
                    height: 36,
                    depth: vec![0.7; 48 * 36],
                };
                write_colmap_depth(&workspace.depth_path(name, "photometric"), &garbage).unwrap();
            }
            // No depth map at all: skipped with a warning.
            5 => {}
            _ => write_colmap_depth(&workspace.depth_path(name, "geometric"), &image).unwrap(),
        }
    }
    spec
}

#[test]
fn colmap_workspaces_binary_and_text_back_project_onto_the_surface() {
    for binary in [true, false] {
        let dir = tempfile::tempdir().unwrap();
        let spec = write_workspace(dir.path(), binary);
        let sources = discover(&[dir.path().to_path_buf()], &DiscoverOptions::default()).unwrap();
        assert_eq!(sources.len(), 5, "binary {binary}: view 5 has no depth map");
        let names: Vec<String> = sources
            .iter()
            .map(|s| s.path.file_name().unwrap().to_string_lossy().into_owned())
            .collect();
        assert_eq!(names[1], "img-001.jpg.photometric.bin");
        assert_eq!(names[2], "img-002.jpg.geometric.bin");
        for source in &sources {
            assert_eq!(source.format, ImageFormat::ColmapBin);
            assert_eq!(source.kind, Kind::Photo);
            assert_eq!(source.weight, 1.0);
            let Projection::Pinhole { cx, cy, .. } = source.projection else {
                panic!("pinhole expected");
            };
            assert_eq!((cx, cy), (24.0, 18.0));
            let samples = back_project(source, &source.load().unwrap()).unwrap();
            assert!(samples.points.len() > 300, "{}", source.path.display());
            for p in &samples.points {
                let d = surface_distance(&spec, *p);
                assert!(
                    d < 2e-3,
                    "binary {binary}, {}: sample {p:?} is {d} from the surface",
                    source.path.display()
                );
            }
        }
    }
}

#[test]
fn colmap_depth_maps_smaller_than_the_camera_scale_the_intrinsics() {
    let dir = tempfile::tempdir().unwrap();
    let pose = sphere_scene().poses()[0];
    let workspace = WorkspaceWriter {
        root: dir.path().to_path_buf(),
    };
    workspace
        .write_model(&[("a.png".into(), 96, 72, [80.0, 80.0, 48.0, 36.0], pose)], false)
        .unwrap();
    let half = DepthImage {
        width: 48,
        height: 36,
        depth: vec![1.0; 48 * 36],
    };
    write_colmap_depth(&workspace.depth_path("a.png", "geometric"), &half).unwrap();
    let sources = discover(&[dir.path().to_path_buf()], &DiscoverOptions::default()).unwrap();
    assert_eq!(
        sources[0].projection,
        Projection::Pinhole {
            fx: 40.0,
            fy: 40.0,
            cx: 23.5,
            cy: 17.5
        }
    );
    let c2w = DMat4::from_cols_array(&sources[0].camera_to_world);
    assert!(
        (c2w - pose).to_cols_array().iter().all(|d| d.abs() < 1e-9),
        "{c2w:?} vs {pose:?}"
    );
}

#[test]
fn bad_colmap_workspaces_name_the_file_and_the_problem() {
    let dir = tempfile::tempdir().unwrap();
    write_workspace(dir.path(), true);
    let images = dir.path().join("sparse/images.bin");
    let bytes = std::fs::read(&images).unwrap();
    std::fs::write(&images, &bytes[..bytes.len() - 30]).unwrap();
    let err = discover(&[dir.path().to_path_buf()], &DiscoverOptions::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("images.bin") && err.contains("truncated"), "{err}");

    let dir = tempfile::tempdir().unwrap();
    write_workspace(dir.path(), false);
    let cameras = dir.path().join("sparse/cameras.txt");
    let text = std::fs::read_to_string(&cameras).unwrap();
    std::fs::write(&cameras, text.replacen("1 PINHOLE 48 36", "1 OPENCV 48 36 0 0 0 0", 1)).unwrap();
    let err = discover(&[dir.path().to_path_buf()], &DiscoverOptions::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("OPENCV") && err.contains("image_undistorter"), "{err}");

    let dir = tempfile::tempdir().unwrap();
    write_workspace(dir.path(), true);
    let depth = dir.path().join("stereo/depth_maps/img-000.jpg.geometric.bin");
    let bytes = std::fs::read(&depth).unwrap();
    std::fs::write(&depth, &bytes[..100]).unwrap();
    // Caught at discovery: the header's size is checked against the file's length.
    let err = discover(&[dir.path().to_path_buf()], &DiscoverOptions::default())
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("img-000.jpg.geometric.bin") && err.contains("truncated"),
        "{err}"
    );
}

/// A structured 360-degree scan of the scene from `pose`: `columns` columns of `rows` returns,
/// column-major, in the sensor frame (z up); every 37th return is missing.
fn scan(spec: &SceneSpec, pose: &DMat4, columns: usize, rows: usize) -> Vec<Option<DVec3>> {
    let origin = pose.w_axis.truncate();
    let mut points = Vec::with_capacity(columns * rows);
    for c in 0..columns {
        let azimuth = std::f64::consts::TAU * c as f64 / columns as f64;
        for r in 0..rows {
            let elevation = (85.0 - 165.0 * r as f64 / rows as f64).to_radians();
            let local = DVec3::new(
                elevation.cos() * azimuth.cos(),
                elevation.cos() * azimuth.sin(),
                elevation.sin(),
            );
            let hit = spec.cast(origin, pose.transform_vector3(local).normalize());
            points.push(hit.filter(|_| (c * rows + r) % 37 != 5).map(|t| local * t));
        }
    }
    points
}

fn sensor_poses(spec: &SceneSpec) -> [DMat4; 2] {
    let tilt = DMat3::from_rotation_z(0.5) * DMat3::from_rotation_x(0.08);
    [
        DMat4::from_mat3_translation(tilt, spec.target + DVec3::new(1.3, 0.4, -0.2)),
        DMat4::from_mat3_translation(DMat3::from_rotation_z(-2.0), spec.target + DVec3::new(-1.1, -1.0, 0.5)),
    ]
}

const COLUMNS: usize = 240;
const ROWS: usize = 110;

fn write_ptx(path: &Path, spec: &SceneSpec) {
    let mut out = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    for pose in sensor_poses(spec) {
        write_ptx_scan(&mut out, COLUMNS, ROWS, &pose, &scan(spec, &pose, COLUMNS, ROWS)).unwrap();
    }
}

fn write_e57(path: &Path, spec: &SceneSpec) {
    use e57::{Quaternion, Record, RecordDataType, RecordName, RecordValue, Transform, Translation};
    let mut writer = e57::E57Writer::from_file(path, "octstore-test-file").unwrap();
    for (index, pose) in sensor_poses(spec).iter().enumerate() {
        let integer = |max: usize| RecordDataType::Integer {
            min: 0,
            max: max as i64,
        };
        let prototype = vec![
            Record {
                name: RecordName::CartesianX,
                data_type: RecordDataType::F64,
            },
            Record {
                name: RecordName::CartesianY,
                data_type: RecordDataType::F64,
            },
            Record {
                name: RecordName::CartesianZ,
                data_type: RecordDataType::F64,
            },
            Record {
                name: RecordName::CartesianInvalidState,
                data_type: integer(2),
            },
            Record {
                name: RecordName::RowIndex,
                data_type: integer(ROWS - 1),
            },
            Record {
                name: RecordName::ColumnIndex,
                data_type: integer(COLUMNS - 1),
            },
        ];
        let mut cloud = writer.add_pointcloud(&format!("scan-{index}"), prototype).unwrap();
        let (_, q, t) = pose.to_scale_rotation_translation();
        cloud.set_transform(Some(Transform {
            rotation: Quaternion {
                w: q.w,
                x: q.x,
                y: q.y,
                z: q.z,
            },
            translation: Translation { x: t.x, y: t.y, z: t.z },
        }));
        for (i, p) in scan(spec, pose, COLUMNS, ROWS).iter().enumerate() {
            let (p, state) = match p {
                Some(p) => (*p, 0),
                None => (DVec3::ZERO, 2),
            };
            cloud
                .add_point(vec![
                    RecordValue::Double(p.x),
                    RecordValue::Double(p.y),
                    RecordValue::Double(p.z),
                    RecordValue::Integer(state),
                    RecordValue::Integer((i % ROWS) as i64),
                    RecordValue::Integer((i / ROWS) as i64),
                ])
                .unwrap();
        }
        cloud.finalize().unwrap();
    }
    writer.finalize().unwrap();
}

#[test]
fn lidar_scans_from_ptx_and_e57_agree_and_back_project_onto_the_surface() {
    let dir = tempfile::tempdir().unwrap();
    let spec = sphere_scene();
    let (ptx, e57) = (dir.path().join("scans.ptx"), dir.path().join("scans.e57"));
    write_ptx(&ptx, &spec);
    write_e57(&e57, &spec);
    let from_ptx = discover(&[ptx], &DiscoverOptions::default()).unwrap();
    let from_e57 = discover(&[e57], &DiscoverOptions::default()).unwrap();
    assert_eq!(from_ptx.len(), 2);
    assert_eq!(from_e57.len(), 2);
    for (scan, (a, b)) in from_ptx.iter().zip(&from_e57).enumerate() {
        assert_eq!(a.format, ImageFormat::Ptx { scan: scan as u32 });
        assert_eq!(b.format, ImageFormat::E57 { scan: scan as u32 });
        assert_eq!(
            (a.kind, a.weight, a.projection),
            (Kind::Lidar, 5.0, Projection::Spherical)
        );
        assert_eq!((a.width, a.height), (b.width, b.height));
        // The scan's own step is 1.5 degrees horizontally: the grid is 1.25 times coarser.
        assert!((150..=250).contains(&a.width), "grid width {}", a.width);
        let pose = sensor_poses(&spec)[scan];
        for source in [a, b] {
            let m = DMat4::from_cols_array(&source.camera_to_world);
            assert!(
                (m - pose).to_cols_array().iter().all(|d| d.abs() < 1e-9),
                "{m:?} vs {pose:?}"
            );
        }
        let (image_a, image_b) = (a.load().unwrap(), b.load().unwrap());
        let same = image_a
            .depth
            .iter()
            .zip(&image_b.depth)
            .all(|(x, y)| x.to_bits() == y.to_bits());
        assert!(same, "scan {scan}: PTX and E57 give different grids");
        let valid = image_a.depth.iter().filter(|d| d.is_finite()).count();
        assert!(
            valid * 10 > image_a.depth.len() * 6,
            "scan {scan}: only {valid} of {} pixels hold a return",
            image_a.depth.len()
        );
        // A return sits on its pixel's central ray: off the surface by at most about its range
        // times the grid's step, more only at grazing angles.
        let step = std::f64::consts::TAU / f64::from(a.width);
        let samples = back_project(a, &image_a).unwrap();
        let origin = pose.w_axis.truncate();
        let mut relative: Vec<f64> = samples
            .points
            .iter()
            .map(|p| surface_distance(&spec, *p) / (step * (*p - origin).length()))
            .collect();
        relative.sort_by(f64::total_cmp);
        let quantile = |q: f64| relative[((relative.len() - 1) as f64 * q) as usize];
        eprintln!(
            "scan {scan}: off-surface / (range * step): median {:.3}, 90% {:.3}, 99% {:.3}",
            quantile(0.5),
            quantile(0.9),
            quantile(0.99)
        );
        assert!(
            quantile(0.5) < 0.2 && quantile(0.9) < 0.45,
            "scan {scan}: off-surface distances / (range * step): median {:.3}, 90% {:.3}",
            quantile(0.5),
            quantile(0.9)
        );
    }
}

#[test]
fn lidar_files_ingest_through_the_cli_and_bad_ones_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let spec = sphere_scene();
    let ptx = dir.path().join("scans.ptx");
    write_ptx(&ptx, &spec);
    let store = dir.path().join("store");
    let out = octstore(
        &[
            "ingest",
            store.to_str().unwrap(),
            ptx.to_str().unwrap(),
            "--max-depth",
            "7",
        ],
        &[],
    );
    assert!(out.status.success(), "{}", stderr(&out));
    let out = octstore(&["info", store.to_str().unwrap(), "--json"], &[]);
    let info: serde_json::Value = serde_json::from_str(&stdout(&out)).unwrap();
    assert_eq!(info["depth_maps"], 2, "{info}");

    let text = std::fs::read_to_string(&ptx).unwrap();
    let lines: Vec<&str> = text.lines().collect();
    let truncated = dir.path().join("truncated.ptx");
    std::fs::write(&truncated, lines[..5000].join("\n")).unwrap();
    let err = discover(&[truncated], &DiscoverOptions::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("truncated.ptx") && err.contains("truncated PTX"), "{err}");
    let garbled = dir.path().join("garbled.ptx");
    let mut bad_lines = lines.clone();
    bad_lines[20] = "1.0 what 2.0";
    std::fs::write(&garbled, bad_lines.join("\n")).unwrap();
    let err = discover(&[garbled], &DiscoverOptions::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("garbled.ptx") && err.contains("line 21"), "{err}");
    let not_e57 = dir.path().join("fake.e57");
    std::fs::write(&not_e57, b"this is not an E57 file").unwrap();
    let err = discover(&[not_e57], &DiscoverOptions::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("fake.e57") && err.contains("unreadable E57"), "{err}");
}

#[test]
fn auto_detection_names_each_format_and_never_guesses() {
    let Some(_) = shared_data("7scenes-redkitchen") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    write_workspace(&dir.path().join("colmap"), true);
    let sources = discover(&[dir.path().join("colmap")], &DiscoverOptions::default()).unwrap();
    assert!(sources.iter().all(|s| s.format == ImageFormat::ColmapBin));
    let forced = DiscoverOptions {
        format: InputFormat::Lidar,
        ..DiscoverOptions::default()
    };
    let err = discover(&[dir.path().join("colmap")], &forced).unwrap_err().to_string();
    assert!(err.contains(".ptx or .e57"), "{err}");
    let unknown: PathBuf = dir.path().join("points.xyz");
    std::fs::write(&unknown, "1 2 3\n").unwrap();
    let err = discover(&[unknown], &DiscoverOptions::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("cannot tell the input format"), "{err}");
}

/// Writes RedKitchen frames `frames` as a TUM RGB-D sequence under `dir`: depth PNGs at 5000
/// units per metre in depth/, depth.txt with one timestamp per frame, groundtruth.txt with
/// quaternion poses 5 ms off the frames' times (and none near the frame at `orphan`).
fn write_tum_copy(dir: &Path, frames: &[u32], orphan: Option<u32>) {
    let kitchen = shared_path("7scenes-redkitchen");
    std::fs::create_dir_all(dir.join("depth")).unwrap();
    let (mut depth_list, mut truth) = (
        String::from("# depth maps\n"),
        String::from("# timestamp tx ty tz qx qy qz qw\n"),
    );
    for &n in frames {
        let time = 1305031102.0 + f64::from(n) / 30.0;
        let png = image::open(kitchen.join(format!("frame-{n:06}.depth.png")))
            .unwrap()
            .into_luma16();
        let scaled = image::ImageBuffer::from_fn(png.width(), png.height(), |x, y| {
            let mm = png.get_pixel(x, y).0[0];
            image::Luma([if mm == u16::MAX { mm } else { mm * 5 }])
        });
        let name = format!("depth/{time:.6}.png");
        scaled.save(dir.join(&name)).unwrap();
        depth_list += &format!("{time:.6} {name}\n");
        if Some(n) == orphan {
            continue;
        }
        let text = std::fs::read_to_string(kitchen.join(format!("frame-{n:06}.pose.txt"))).unwrap();
        let v: Vec<f64> = text.split_whitespace().map(|t| t.parse().unwrap()).collect();
        let pose = DMat4::from_cols_array(&v.try_into().unwrap()).transpose();
        let (_, rotation, translation) = pose.to_scale_rotation_translation();
        truth += &format!(
            "{:.6} {} {} {} {} {} {} {}\n",
            time + 0.005,
            translation.x,
            translation.y,
            translation.z,
            rotation.x,
            rotation.y,
            rotation.z,
            rotation.w
        );
    }
    std::fs::write(dir.join("depth.txt"), depth_list).unwrap();
    std::fs::write(dir.join("groundtruth.txt"), truth).unwrap();
}

/// A TUM RGB-D sequence is found by `--format auto`, its frames take the poses nearest in time
/// (within 0.02 s; a frame without one is left out), and it reads as the same frames in the
/// 7-Scenes layout do: same depths, same poses. Bad lists name the file and the line.
#[test]
fn tum_sequences_read_as_the_same_frames_in_seven_scenes_layout() {
    let Some(_) = shared_data("7scenes-redkitchen") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let kitchen = shared_path("7scenes-redkitchen");
    let sequence = dir.path().join("capture");
    write_tum_copy(&sequence, &[0, 10, 20], Some(20));
    let intrinsics = kitchen.join("camera-intrinsics.txt");
    let options = DiscoverOptions {
        intrinsics: Some(intrinsics.clone()),
        ..DiscoverOptions::default()
    };
    let tum = discover(std::slice::from_ref(&sequence), &options).unwrap();
    assert_eq!(tum.len(), 2, "the frame without a pose is left out");
    let seven: Vec<_> = [0, 10]
        .iter()
        .map(|n| {
            discover(
                &[kitchen.join(format!("frame-{n:06}.depth.png"))],
                &DiscoverOptions::default(),
            )
            .unwrap()
        })
        .map(|mut s| s.remove(0))
        .collect();
    for (t, s) in tum.iter().zip(&seven) {
        assert_eq!(t.projection, s.projection);
        assert_eq!(t.kind, Kind::Rgbd);
        // 7-Scenes rotations carry a scale of about 1 + 5e-5; a quaternion has none.
        for (a, b) in t.camera_to_world.iter().zip(&s.camera_to_world) {
            assert!(
                (a - b).abs() < 1e-4,
                "{:?} vs {:?}",
                t.camera_to_world,
                s.camera_to_world
            );
        }
        let (a, b) = (t.load().unwrap(), s.load().unwrap());
        assert_eq!((a.width, a.height), (b.width, b.height));
        for (x, y) in a.depth.iter().zip(&b.depth) {
            assert!(
                x.is_nan() && y.is_nan() || (x - y).abs() <= 1e-6 * y.abs(),
                "{x} vs {y}"
            );
        }
    }
    // Without --intrinsics, a folder not named after its Freiburg sensor is refused; one that
    // is takes the sensor's published intrinsics.
    let err = discover(std::slice::from_ref(&sequence), &DiscoverOptions::default())
        .unwrap_err()
        .to_string();
    assert!(err.contains("--intrinsics FILE"), "{err}");
    let freiburg = dir.path().join("rgbd_dataset_freiburg1_xyz");
    write_tum_copy(&freiburg, &[0], None);
    let named = discover(std::slice::from_ref(&freiburg), &DiscoverOptions::default()).unwrap();
    assert!(matches!(named[0].projection, Projection::Pinhole { fx, .. } if fx == 517.3));
    // One command ingests it.
    let store = dir.path().join("store");
    let out = octstore(
        &[
            "ingest",
            store.to_str().unwrap(),
            sequence.to_str().unwrap(),
            "--intrinsics",
            intrinsics.to_str().unwrap(),
            "--quiet",
        ],
        &[],
    );
    assert!(out.status.success(), "{}", stderr(&out));
    // A malformed line is named by file and line.
    std::fs::write(
        sequence.join("groundtruth.txt"),
        "# poses\n1305031102.005 0 0 0 0 0 0\n",
    )
    .unwrap();
    let err = discover(std::slice::from_ref(&sequence), &options)
        .unwrap_err()
        .to_string();
    assert!(err.contains("groundtruth.txt") && err.contains("line 2"), "{err}");
    std::fs::write(sequence.join("groundtruth.txt"), "1305031102.005 0 0 0 0 0 0 0\n").unwrap();
    let err = discover(std::slice::from_ref(&sequence), &options)
        .unwrap_err()
        .to_string();
    assert!(err.contains("quaternion has length 0"), "{err}");
}

/// The golden version-2 store's one-map manifest copied into `dir` with its image, and a
/// writer of variants of it: the entry's fields replaced by those given, written to
/// `dir/scene.json`, whose path it returns.
fn golden_manifest(dir: &Path) -> (serde_json::Value, impl Fn(serde_json::Value) -> PathBuf + '_) {
    let golden = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/golden-v2-ingest/input");
    std::fs::copy(golden.join("plane.pfm"), dir.join("plane.pfm")).unwrap();
    let template: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(golden.join("scene.json")).unwrap()).unwrap();
    let entry = template.clone();
    let write = move |fields: serde_json::Value| {
        let mut manifest = entry.clone();
        for (key, value) in fields.as_object().unwrap() {
            manifest["depth_maps"][0][key] = value.clone();
        }
        let path = dir.join("scene.json");
        std::fs::write(&path, manifest.to_string()).unwrap();
        path
    };
    (template, write)
}

/// A manifest entry may name its depth noise: "none", a sigma, or [constant, quadratic,
/// offset], with `noise_sigmas`; without one it takes its kind's; a malformed one is refused
/// with the entry named.
#[test]
fn manifest_entries_name_their_depth_noise() {
    use octstore::inputs::DepthNoise;
    let dir = tempfile::tempdir().unwrap();
    let (_, manifest) = golden_manifest(dir.path());
    let read = |fields: serde_json::Value| {
        discover(&[manifest(fields)], &DiscoverOptions::default()).map(|sources| sources[0].noise)
    };
    let axial = |constant, quadratic, offset, sigmas| DepthNoise::Axial {
        constant,
        quadratic,
        offset,
        sigmas,
        footprints: octstore::inputs::DEFAULT_NOISE_FOOTPRINTS,
    };
    // Every kind measures its noise by default; the tables are there by name.
    assert_eq!(read(serde_json::json!({})).unwrap(), DepthNoise::Auto { sigmas: None });
    assert_eq!(
        read(serde_json::json!({"kind": "photo"})).unwrap(),
        DepthNoise::Auto { sigmas: None }
    );
    assert_eq!(
        read(serde_json::json!({"depth_noise": "kinect"})).unwrap(),
        DepthNoise::STRUCTURED_LIGHT
    );
    assert_eq!(
        read(serde_json::json!({"depth_noise": "lidar", "noise_sigmas": 2.0})).unwrap(),
        DepthNoise::TERRESTRIAL_LIDAR.with_sigmas(2.0)
    );
    assert_eq!(
        read(serde_json::json!({"depth_noise": "auto", "noise_sigmas": 0.5})).unwrap(),
        DepthNoise::Auto { sigmas: Some(0.5) }
    );
    assert_eq!(
        read(serde_json::json!({"depth_noise": "none"})).unwrap(),
        DepthNoise::Footprint
    );
    assert_eq!(
        read(serde_json::json!({"depth_noise": 0.003})).unwrap(),
        axial(0.003, 0.0, 0.0, 1.0)
    );
    assert_eq!(
        read(serde_json::json!({"depth_noise": [0.001, 0.002, 0.5], "noise_sigmas": 2.0})).unwrap(),
        axial(0.001, 0.002, 0.5, 2.0)
    );
    assert_eq!(
        read(serde_json::json!({"noise_sigmas": 3.0})).unwrap(),
        DepthNoise::Auto { sigmas: Some(3.0) }
    );
    for (bad, expected) in [
        (serde_json::json!({"depth_noise": "loud"}), "unknown depth_noise 'loud'"),
        (serde_json::json!({"depth_noise": [1.0, 2.0]}), "1 number (sigma) or 3"),
        (serde_json::json!({"depth_noise": -1.0}), "not negative"),
    ] {
        let error = read(bad.clone())
            .expect_err("a malformed depth_noise was accepted")
            .to_string();
        assert!(
            error.contains("scene.json") && error.contains("depth_maps[0]") && error.contains(expected),
            "{bad}: {error}"
        );
    }
}

/// The manifest's numbers pass the command line's checks (one rule for both), a pose that
/// reflects (determinant -1) is refused naming the file, and a FIFO named as a depth map is
/// refused before it is opened (opening it would wait for a writer forever).
#[test]
fn manifest_numbers_reflections_and_fifos_are_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let (template, manifest) = golden_manifest(dir.path());
    let read = |fields: serde_json::Value| {
        discover(&[manifest(fields)], &DiscoverOptions::default()).map(|sources| sources.len())
    };
    assert_eq!(read(serde_json::json!({})).unwrap(), 1);
    let mut reflected = template["depth_maps"][0]["pose"].clone();
    let key = if reflected.get("camera_to_world").is_some() {
        "camera_to_world"
    } else {
        "world_to_camera"
    };
    // Negate the rotation's first column: a mirror image of the camera.
    for row in 0..3 {
        let v = reflected[key][row * 4].as_f64().unwrap();
        reflected[key][row * 4] = serde_json::json!(-v);
    }
    for (fields, expected) in [
        (serde_json::json!({"depth_scale": 0.0}), "depth_scale 0"),
        (serde_json::json!({"depth_scale": -1.0}), "depth_scale -1"),
        (serde_json::json!({"depth_scale": 1e300}), "depth_scale 1"),
        (serde_json::json!({"noise_sigmas": -1.0}), "standard deviations"),
        (serde_json::json!({"pose": reflected}), "reflection"),
    ] {
        let error = read(fields.clone()).expect_err("accepted").to_string();
        assert!(
            error.contains("scene.json") && error.contains(expected),
            "{fields}: {error}"
        );
    }

    // A FIFO in place of the depth map: refused at once, naming it.
    let fifo = dir.path().join("fifo.pfm");
    let made = std::process::Command::new("mkfifo").arg(&fifo).status().unwrap();
    assert!(made.success());
    let (sender, receiver) = std::sync::mpsc::channel();
    let manifest = {
        let mut manifest = template.clone();
        manifest["depth_maps"][0]["image"] = serde_json::json!("fifo.pfm");
        let path = dir.path().join("fifo.json");
        std::fs::write(&path, manifest.to_string()).unwrap();
        path
    };
    std::thread::spawn(move || {
        let _ = sender.send(discover(&[manifest], &DiscoverOptions::default()).map(|s| s.len()));
    });
    let error = receiver
        .recv_timeout(std::time::Duration::from_secs(20))
        .expect("discovery hung on a FIFO")
        .expect_err("a FIFO was accepted")
        .to_string();
    assert!(
        error.contains("fifo.pfm") && error.contains("not a regular file"),
        "{error}"
    );
}

/// Numbers of the command line that used to be taken as they came: each is refused before
/// anything runs, saying what is allowed.
#[test]
fn command_line_counts_and_points_are_checked() {
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let s = store.to_str().unwrap();
    for (args, expected) in [
        (vec!["--threads", "100000", "info", s], "threads: give 1 to"),
        (vec!["--threads", "0", "info", s], "threads: give 1 to"),
        (vec!["ingest", s, "x", "--stride", "0"], "at least 1"),
        (vec!["gc", s, "--keep", "0"], "at least 1"),
        (vec!["query", s, "--point", "nan,0,0"], "must be finite"),
        (vec!["divide", "x.ply", "-o", s, "--max-depth", "40"], "40"),
        (vec!["divide", "x.ply", "-o", s, "--max-depth", "0"], "0"),
        (vec!["extract", s, "-o", "mesh.stl"], "not .stl"),
    ] {
        let out = octstore(&args, &[]);
        assert!(!out.status.success(), "{args:?} was accepted");
        let err = stderr(&out);
        assert!(err.contains(expected), "{args:?}: {err}");
        assert!(!store.exists(), "{args:?} touched the store");
    }
}
