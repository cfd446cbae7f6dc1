//! Division tests on small clouds: every point in exactly one core and in every grown cube
//! that holds it (checked by counting records), the limit, byte-identical output for any
//! thread count and input order, incremental updates, errors, and merging.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use super::manifest::{MANIFEST, Manifest, read_manifest_file};
use super::open_point_cloud;
use super::{DivideOptions, PointSource, SyntheticCloud, divide, merge::merge};
use crate::inputs::InputError;
use crate::mesh::{Mesh, edge_defects, read_mesh, write_mesh};

type TestResult = Result<(), Box<dyn std::error::Error>>;

/// Records of a cloud: the synthetic terrain plus a tight cluster of `cluster` points (dense
/// enough that the counted depth cannot separate it, so it is divided again).
fn cloud(points: u64, seed: u64, cluster: u64) -> Result<Vec<Vec<u8>>, Box<dyn std::error::Error>> {
    let source = SyntheticCloud::new(points, seed);
    let mut records = Vec::new();
    source.for_each_block(1000, &mut |block| {
        records.extend(block.chunks_exact(12).map(<[u8]>::to_vec));
        Ok(())
    })?;
    for i in 0..cluster {
        let t = i as f32 / cluster as f32;
        let p = [
            300.0 + t * 0.5,
            200.0 + (t * 37.0).fract() * 0.5,
            5.0 + (t * 91.0).fract() * 0.5,
        ];
        records.push(p.iter().flat_map(|c| c.to_le_bytes()).collect());
    }
    Ok(records)
}

fn write_ply(path: &Path, records: &[Vec<u8>]) -> std::io::Result<()> {
    let mut bytes = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nend_header\n",
        records.len()
    )
    .into_bytes();
    for r in records {
        bytes.extend_from_slice(r);
    }
    std::fs::write(path, bytes)
}

fn position(record: &[u8]) -> [f64; 3] {
    let c = |i: usize| {
        record
            .get(i * 4..i * 4 + 4)
            .and_then(|b| b.try_into().ok())
            .map_or(f64::NAN, |b| f64::from(f32::from_le_bytes(b)))
    };
    [c(0), c(1), c(2)]
}

fn file_records(path: &Path) -> Result<Vec<Vec<u8>>, InputError> {
    let file = open_point_cloud(path)?;
    let mut out = Vec::new();
    file.for_each_block::<InputError>(4096, |block| {
        out.extend(block.chunks_exact(file.layout().record_len()).map(<[u8]>::to_vec));
        Ok(())
    })?;
    Ok(out)
}

/// Checks the division in `dir` against all the points given to it (float x, y, z first).
fn check_division(dir: &Path, points: &[Vec<u8>], max_points: u64) -> Result<Manifest, Box<dyn std::error::Error>> {
    check_division_of(dir, points, max_points, position)
}

/// The position of a record that starts with double x, y, z.
fn position_f64(record: &[u8]) -> [f64; 3] {
    [0, 1, 2].map(|i| {
        record
            .get(i * 8..i * 8 + 8)
            .and_then(|b| b.try_into().ok())
            .map_or(f64::NAN, f64::from_le_bytes)
    })
}

/// [`check_division`] of records whose position `position` reads.
fn check_division_of(
    dir: &Path,
    points: &[Vec<u8>],
    max_points: u64,
    position: fn(&[u8]) -> [f64; 3],
) -> Result<Manifest, Box<dyn std::error::Error>> {
    let manifest = read_manifest_file(&dir.join(MANIFEST))?;
    let mut core_total = 0;
    for subspace in &manifest.subspaces {
        assert!(subspace.core_points <= max_points, "{} over the limit", subspace.file);
        core_total += subspace.core_points;
        let mut expected: Vec<&Vec<u8>> = points.iter().filter(|r| subspace.grown.contains(position(r))).collect();
        let mut got = file_records(&dir.join(&subspace.file))?;
        assert_eq!(got.len() as u64, subspace.points, "{}", subspace.file);
        expected.sort();
        got.sort();
        assert!(
            expected.iter().copied().eq(got.iter()),
            "{}: its records are not the points of its grown cube",
            subspace.file
        );
        let in_core = points.iter().filter(|r| subspace.core.contains(position(r))).count() as u64;
        assert_eq!(in_core, subspace.core_points, "{}", subspace.file);
    }
    assert_eq!(core_total, points.len() as u64);
    for r in points {
        let cores = manifest
            .subspaces
            .iter()
            .filter(|s| s.core.contains(position(r)))
            .count();
        assert_eq!(cores, 1, "{:?} lies in {cores} cores", position(r));
    }
    Ok(manifest)
}

fn options(max_points: u64, max_depth: u32) -> DivideOptions {
    DivideOptions {
        max_points,
        overlap: 0.1,
        max_depth: Some(max_depth),
        memory_budget: 64 << 20,
        progress: false,
    }
}

fn folder_bytes(dir: &Path) -> std::io::Result<BTreeMap<String, Vec<u8>>> {
    let mut out = BTreeMap::new();
    for entry in std::fs::read_dir(dir)? {
        let entry = entry?;
        out.insert(
            entry.file_name().to_string_lossy().into_owned(),
            std::fs::read(entry.path())?,
        );
    }
    Ok(out)
}

#[test]
fn every_point_lies_in_one_core_and_in_each_grown_cube_that_holds_it() -> TestResult {
    let temp = tempfile::tempdir()?;
    let points = cloud(20_000, 3, 3_000)?;
    let input = temp.path().join("cloud.ply");
    write_ply(&input, &points)?;
    let dir = temp.path().join("division");
    // Leftovers of a killed run go; other files stay.
    std::fs::create_dir_all(&dir)?;
    std::fs::write(dir.join("L9_1_2_3.g4.ply"), b"partial")?;
    std::fs::write(dir.join("notes.txt"), b"mine")?;
    // Two levels a pass: the cluster needs the recursion.
    let report = divide(&[input], &dir, &options(1_000, 2))?;
    assert_eq!(report.input_points, points.len() as u64);
    assert!(
        report.divided_again > 0,
        "the cluster was not divided again: {report:?}"
    );
    assert!(report.over_limit.is_empty());
    let manifest = check_division(&dir, &points, 1_000)?;
    assert_eq!(manifest.subspaces.len(), report.subspaces);
    // Only the subspaces, the manifest and the user's file are left in the folder.
    assert_eq!(std::fs::read_dir(&dir)?.count(), manifest.subspaces.len() + 2);
    assert!(dir.join("notes.txt").exists() && !dir.join("L9_1_2_3.g4.ply").exists());
    Ok(())
}

#[test]
fn the_files_are_the_same_for_any_thread_count_and_input_order() -> TestResult {
    let temp = tempfile::tempdir()?;
    let points = cloud(12_000, 5, 0)?;
    let (first, second) = points.split_at(5_000);
    let a = temp.path().join("a.ply");
    let b = temp.path().join("b.ply");
    write_ply(&a, first)?;
    write_ply(&b, second)?;
    let one = temp.path().join("one");
    let two = temp.path().join("two");
    rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()?
        .install(|| divide(&[a.clone(), b.clone()], &one, &options(800, 3)))?;
    rayon::ThreadPoolBuilder::new()
        .num_threads(3)
        .build()?
        .install(|| divide(&[b.clone(), a.clone()], &two, &options(800, 3)))?;
    let (one, two) = (folder_bytes(&one)?, folder_bytes(&two)?);
    assert!(one.len() > 3);
    assert_eq!(one.keys().collect::<Vec<_>>(), two.keys().collect::<Vec<_>>());
    for (name, bytes) in &one {
        assert!(Some(bytes) == two.get(name), "{name} differs");
    }
    Ok(())
}

#[test]
fn a_later_divide_rewrites_only_the_subspaces_its_points_touch() -> TestResult {
    let temp = tempfile::tempdir()?;
    let old = cloud(10_000, 7, 0)?;
    let first = temp.path().join("first.ply");
    write_ply(&first, &old)?;
    let dir = temp.path().join("division");
    divide(&[first], &dir, &options(1_000, 3))?;
    check_division(&dir, &old, 1_000)?;
    let before = folder_bytes(&dir)?;
    // New points around the corner of four cubes of level 1 and 2: dense enough to split the
    // subspaces they land in, and inside the grown cubes of their neighbours.
    let new: Vec<Vec<u8>> = (0..1_500)
        .map(|i| {
            let t = i as f32 / 1_500.0;
            [
                500.0 + t * 20.0,
                500.0 + (t * 13.0).fract() * 20.0,
                1.0 + (t * 7.0).fract(),
            ]
            .iter()
            .flat_map(|c| c.to_le_bytes())
            .collect()
        })
        .collect();
    let second = temp.path().join("second.ply");
    write_ply(&second, &new)?;
    let report = divide(&[second], &dir, &options(1_000, 3))?;
    assert_eq!(report.input_points, 1_500);
    let all: Vec<Vec<u8>> = old.iter().chain(&new).cloned().collect();
    let manifest = check_division(&dir, &all, 1_000)?;
    let after = folder_bytes(&dir)?;
    let kept = manifest
        .subspaces
        .iter()
        .filter(|s| before.get(&s.file) == after.get(&s.file))
        .count();
    assert!(report.files_written > 0 && report.files_written < manifest.subspaces.len());
    assert_eq!(kept + report.files_written, manifest.subspaces.len());
    // The replaced files are gone.
    assert_eq!(after.len(), manifest.subspaces.len() + 1);

    // Points beyond the root, or with other properties, are refused and change nothing.
    let far = temp.path().join("far.ply");
    write_ply(
        &far,
        &[[5000.0f32, 0.0, 0.0].iter().flat_map(|c| c.to_le_bytes()).collect()],
    )?;
    let message = divide(&[far], &dir, &options(1_000, 3))
        .map(|_| ())
        .unwrap_err()
        .to_string();
    assert!(message.contains("beyond the root cube"), "{message}");
    let xyz = temp.path().join("more.xyz");
    std::fs::write(&xyz, "1 2 3\n")?;
    let message = divide(&[xyz], &dir, &options(1_000, 3))
        .map(|_| ())
        .unwrap_err()
        .to_string();
    assert!(
        message.contains("more.xyz") && message.contains("properties"),
        "{message}"
    );
    assert!(folder_bytes(&dir)? == after);
    Ok(())
}

#[test]
fn a_later_divide_that_splits_most_subspaces_divides_everything_afresh() -> TestResult {
    let temp = tempfile::tempdir()?;
    let old = cloud(10_000, 7, 0)?;
    let first = temp.path().join("first.ply");
    write_ply(&first, &old)?;
    let dir = temp.path().join("division");
    divide(std::slice::from_ref(&first), &dir, &options(1_000, 3))?;
    let before = folder_bytes(&dir)?;
    // As many points again, each a little nearer the middle than an old one (so inside the
    // root): every core doubles past the limit.
    let middle = old
        .iter()
        .map(|r| position(r))
        .fold([0.0; 3], |a, p| [a[0] + p[0], a[1] + p[1], a[2] + p[2]]);
    let middle = middle.map(|c| c / old.len() as f64);
    let new: Vec<Vec<u8>> = old
        .iter()
        .map(|r| {
            let p = position(r);
            (0..3)
                .flat_map(|a| ((middle[a] + (p[a] - middle[a]) * 0.999) as f32).to_le_bytes())
                .collect()
        })
        .collect();
    let second = temp.path().join("second.ply");
    write_ply(&second, &new)?;
    let report = divide(std::slice::from_ref(&second), &dir, &options(1_000, 3))?;
    let all: Vec<Vec<u8>> = old.iter().chain(&new).cloned().collect();
    let manifest = check_division(&dir, &all, 1_000)?;
    // Every file is new, and the subspaces are those of dividing all the points at once.
    assert_eq!(report.files_written, manifest.subspaces.len());
    assert!(manifest.subspaces.iter().all(|s| !before.contains_key(&s.file)));
    let fresh = temp.path().join("fresh");
    divide(&[first, second], &fresh, &options(1_000, 3))?;
    let fresh = read_manifest_file(&fresh.join(MANIFEST))?;
    assert_eq!(fresh.division.root, manifest.division.root);
    let nodes = |m: &Manifest| {
        m.subspaces
            .iter()
            .map(|s| (s.node, s.core_points))
            .collect::<std::collections::BTreeSet<_>>()
    };
    assert_eq!(nodes(&fresh), nodes(&manifest));
    Ok(())
}

#[test]
fn a_truncated_input_names_its_file_and_writes_no_division() -> TestResult {
    let temp = tempfile::tempdir()?;
    let points = cloud(100, 1, 0)?;
    let good = temp.path().join("good.ply");
    write_ply(&good, &points)?;
    let mut bytes = std::fs::read(&good)?;
    bytes.truncate(bytes.len() - 5);
    let bad = temp.path().join("cut.ply");
    std::fs::write(&bad, bytes)?;
    let dir = temp.path().join("division");
    let message = divide(&[good, bad], &dir, &options(10, 3))
        .map(|_| ())
        .unwrap_err()
        .to_string();
    assert!(
        message.contains("cut.ply") && message.contains("truncated"),
        "{message}"
    );
    assert!(!dir.join(MANIFEST).exists());
    Ok(())
}

/// The triangles of the lattice z = 1 (spacing `step`) whose cells meet `bounds`, with
/// vertices at the lattice points: meshes of neighbouring subspaces share them exactly.
fn plane_mesh(min: [f64; 3], max: [f64; 3], step: f64) -> Mesh {
    let mut mesh = Mesh::default();
    let cells = |lo: f64, hi: f64| ((lo / step).floor() as i64, (hi / step).ceil() as i64);
    let (x0, x1) = cells(min[0].max(0.0), max[0].min(1000.0));
    let (y0, y1) = cells(min[1].max(0.0), max[1].min(1000.0));
    let mut index = BTreeMap::new();
    let mut vertex = |mesh: &mut Mesh, i: i64, j: i64| {
        *index.entry((i, j)).or_insert_with(|| {
            mesh.positions
                .push([(i as f64 * step) as f32, (j as f64 * step) as f32, 1.0]);
            mesh.positions.len() as u32 - 1
        })
    };
    for i in x0..x1 {
        for j in y0..y1 {
            let a = vertex(&mut mesh, i, j);
            let b = vertex(&mut mesh, i + 1, j);
            let c = vertex(&mut mesh, i + 1, j + 1);
            let d = vertex(&mut mesh, i, j + 1);
            mesh.triangles.push([a, b, c]);
            mesh.triangles.push([a, c, d]);
        }
    }
    mesh
}

#[test]
fn merging_keeps_each_triangle_once_and_welds_the_cuts() -> TestResult {
    let temp = tempfile::tempdir()?;
    // A flat square of points at z = 1 spanning [0, 1000)^2.
    let points: Vec<Vec<u8>> = (0..4_000)
        .map(|i| {
            let (u, v) = ((i % 64) as f32 / 64.0, (i / 64) as f32 / 63.0);
            [u * 999.0, v * 999.0, 1.0f32]
                .iter()
                .flat_map(|c| c.to_le_bytes())
                .collect()
        })
        .collect();
    let input = temp.path().join("plane.ply");
    write_ply(&input, &points)?;
    let dir = temp.path().join("division");
    divide(&[input], &dir, &options(500, 3))?;
    let manifest = read_manifest_file(&dir.join(MANIFEST))?;
    assert!(manifest.subspaces.len() >= 8);
    let step = 1000.0 / 64.0;
    let mut meshes: Vec<PathBuf> = Vec::new();
    for subspace in &manifest.subspaces {
        let g = subspace.grown;
        let mesh = plane_mesh(g.min, g.min.map(|m| m + g.size), step);
        let stem = subspace.file.trim_end_matches(".ply");
        let path = temp.path().join(format!("{stem}.mesh.ply"));
        write_mesh(&path, &mesh)?;
        meshes.push(path);
    }
    let output = temp.path().join("merged.ply");
    let report = merge(&dir.join(MANIFEST), &meshes, &output)?;
    let whole = plane_mesh([0.0; 3], [1000.0; 3], step);
    let merged = read_mesh(&output)?;
    assert!(report.missing.is_empty());
    assert_eq!(merged.triangles.len(), whole.triangles.len());
    assert_eq!(merged.positions.len(), whole.positions.len());
    assert_eq!(report.boundary_edges, edge_defects(&whole).0);
    assert!(report.welded > 0 && report.cut > 0);

    // A mesh named after no subspace is refused.
    let stray = temp.path().join("stray.ply");
    write_mesh(&stray, &whole)?;
    let message = merge(&dir.join(MANIFEST), &[stray], &output)
        .map(|_| ())
        .unwrap_err()
        .to_string();
    assert!(message.contains("stray.ply"), "{message}");
    Ok(())
}

#[test]
fn scans_are_divided_as_their_returns_in_world_coordinates() -> TestResult {
    use glam::{DMat4, DQuat, DVec3};
    let temp = tempfile::tempdir()?;
    let path = temp.path().join("scans.ptx");
    let mut text = Vec::new();
    let mut expected = Vec::new();
    let mut e57 = e57::E57Writer::from_file(temp.path().join("scans.e57"), "octstore-divide-test")?;
    for (scan, pose) in [
        DMat4::from_rotation_translation(DQuat::from_rotation_z(0.3), DVec3::new(1000.0, -20.0, 3.0)),
        DMat4::from_rotation_translation(DQuat::from_rotation_x(-1.1), DVec3::new(1004.5, -18.0, 2.5)),
    ]
    .iter()
    .enumerate()
    {
        let (columns, rows) = (9, 7);
        let points: Vec<Option<DVec3>> = (0..columns * rows)
            .map(|i| {
                // Every seventh return missing.
                (i % 7 != 3).then(|| DVec3::new(1.0 + (i % 5) as f64, (i / 5) as f64 * 0.37, 0.25 * scan as f64 - 0.5))
            })
            .collect();
        crate::inputs::write_ptx_scan(&mut text, columns, rows, pose, &points)?;
        write_e57_scan(&mut e57, scan, pose, &points)?;
        for p in points.iter().flatten() {
            let w = pose.transform_point3(*p);
            expected.push(
                [w.x, w.y, w.z]
                    .iter()
                    .flat_map(|c| c.to_le_bytes())
                    .collect::<Vec<u8>>(),
            );
        }
    }
    std::fs::write(&path, text)?;
    let dir = temp.path().join("division");
    let report = divide(&[path], &dir, &options(10, 4))?;
    assert_eq!(report.input_points, expected.len() as u64);
    assert!(report.subspaces > 4, "{report:?}");
    let manifest = check_division_of(&dir, &expected, 10, position_f64)?;
    let names: Vec<&str> = manifest.division.properties.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(names, ["x", "y", "z"]);
    // The same scans as E57: the same points, up to the rounding of the poses' quaternions.
    e57.finalize()?;
    let dir = temp.path().join("division-e57");
    let report = divide(&[temp.path().join("scans.e57")], &dir, &options(10, 4))?;
    assert_eq!(report.input_points, expected.len() as u64);
    let manifest = read_manifest_file(&dir.join(MANIFEST))?;
    let mut cores = Vec::new();
    for subspace in &manifest.subspaces {
        let records = file_records(&dir.join(&subspace.file))?;
        cores.extend(
            records
                .iter()
                .map(|r| position_f64(r))
                .filter(|p| subspace.core.contains(*p)),
        );
    }
    assert_eq!(cores.len(), expected.len());
    for e in &expected {
        let e = position_f64(e);
        assert!(
            cores.iter().any(|c| (0..3).all(|a| (c[a] - e[a]).abs() < 1e-9)),
            "{e:?} missing from the E57 division"
        );
    }
    Ok(())
}

/// One scan of `points` (sensor frame; `None` missing) with its pose, in an E57 file.
fn write_e57_scan(
    writer: &mut e57::E57Writer<std::fs::File>,
    scan: usize,
    pose: &glam::DMat4,
    points: &[Option<glam::DVec3>],
) -> Result<(), Box<dyn std::error::Error>> {
    use e57::{Quaternion, Record, RecordDataType, RecordName, RecordValue, Transform, Translation};
    let prototype = [RecordName::CartesianX, RecordName::CartesianY, RecordName::CartesianZ]
        .map(|name| Record {
            name,
            data_type: RecordDataType::F64,
        })
        .to_vec();
    let mut cloud = writer.add_pointcloud(&format!("scan-{scan}"), prototype)?;
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
    for p in points.iter().flatten() {
        cloud.add_point(vec![
            RecordValue::Double(p.x),
            RecordValue::Double(p.y),
            RecordValue::Double(p.z),
        ])?;
    }
    cloud.finalize()?;
    Ok(())
}

#[test]
fn a_store_is_divided_as_its_depth_maps_samples() -> TestResult {
    use crate::stages::ingest::{SampleStream, open_rows, registered_depth_maps};
    let temp = tempfile::tempdir()?;
    let scene = crate::SceneSpec::demo();
    let manifest_path = scene.write(&temp.path().join("input"))?;
    let store_path = temp.path().join("store");
    let store = crate::Store::create(&store_path)?;
    let ingest_options = crate::IngestOptions {
        max_depth: 6,
        root_margin: 0.05,
        ..crate::IngestOptions::default()
    };
    let sources = crate::inputs::discover(&[manifest_path], &crate::DiscoverOptions::default())?;
    let stage = crate::stages::ingest::IngestStage::prepare(&store, sources, &ingest_options)?;
    store.run_stage(&stage, &Default::default())?;
    // The samples the store's depth maps give, read here without `divide`.
    let mut expected = Vec::new();
    for (_, map) in registered_depth_maps(&store)? {
        let rows = open_rows(&map.source, 1 << 30)?;
        SampleStream::new(&map.source, rows)?.for_each(|s| {
            if !s.spike {
                expected.push(super::sources::record_of(s.point, s.normal, s.radius).to_vec());
            }
        })?;
    }
    drop(store);
    let dir = temp.path().join("division");
    let report = divide(&[store_path], &dir, &options(20_000, 4))?;
    assert_eq!(report.input_points, expected.len() as u64);
    let manifest = check_division_of(&dir, &expected, 20_000, position_f64)?;
    let names: Vec<&str> = manifest.division.properties.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(names, ["x", "y", "z", "nx", "ny", "nz", "radius"]);
    // Normals are unit (or zero where a map has none) and radii positive.
    let float = |r: &[u8], i: usize| {
        r.get(24 + 4 * i..28 + 4 * i)
            .and_then(|b| b.try_into().ok())
            .map_or(f32::NAN, f32::from_le_bytes)
    };
    for r in &expected {
        let length = (0..3).map(|i| float(r, i).powi(2)).sum::<f32>().sqrt();
        assert!(length == 0.0 || (length - 1.0).abs() < 1e-4, "normal length {length}");
        assert!(float(r, 3) > 0.0);
    }
    // A folder that is not a store is refused by name.
    let error = divide(
        &[temp.path().join("input")],
        &temp.path().join("other"),
        &options(10, 4),
    )
    .err()
    .ok_or("a plain folder was divided")?;
    assert!(error.to_string().contains("not an octstore store"), "{error}");
    Ok(())
}

/// A block counted by [`super::CountBlock`] compiled for AVX2 gives the counts it gives
/// compiled for the baseline. (On a processor without AVX2 both run the baseline.)
#[test]
fn a_block_counts_alike_in_avx2_and_in_the_baseline() -> Result<(), Box<dyn std::error::Error>> {
    use super::CountBlock;
    use super::grid::{Counts, Node, Root};
    use crate::sys::WideWork;

    let cloud = SyntheticCloud::new(40_000, 3);
    let mut block = Vec::new();
    cloud.read_block(40_000, 0, &mut block)?;
    let root = Root::around([0.0; 3], [1000.0; 3]).ok_or("no root")?;
    let keep = super::Bounds {
        min: [100.0, 0.0, 0.0],
        max: [900.0, 1000.0, 1000.0],
    };
    let count = |wide: bool| {
        let mut counts = Counts::new(Node::ROOT, 5, 0);
        let locator = root.locator(counts.level());
        let cells = counts.cells();
        counts.add_with(|adder| {
            let work = CountBlock {
                layout: cloud.layout(),
                block: &block,
                keep: Some(&keep),
                locator,
                cells,
                adder,
            };
            if wide {
                crate::sys::with_wide_vectors(work)
            } else {
                work.run()
            }
        });
        counts.finish();
        let mut cells = Vec::new();
        for x in 0..32 {
            for y in 0..32 {
                for z in 0..32 {
                    cells.push(counts.of(Node {
                        level: 5,
                        index: [x, y, z],
                    }));
                }
            }
        }
        cells
    };
    let wide = count(true);
    assert_eq!(wide, count(false));
    // Most of the points, not all: `keep` leaves some out.
    let counted: u64 = wide.iter().sum();
    assert!(counted > 20_000 && counted < 40_000, "{counted}");
    Ok(())
}
