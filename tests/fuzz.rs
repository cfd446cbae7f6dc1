//! Mutation fuzzing of every decoder of bytes from disk: segments, catalog records, and every
//! input format (PNG16, PFM, NPY, scene manifests, 7-Scenes and TUM folders, COLMAP
//! workspaces, PTX and E57 scans) and mesh files. Each target starts from valid files and, for
//! `OCTSTORE_FUZZ_SECONDS` (default 2) per target, flips bits, overwrites bytes, truncates,
//! inserts and splices in troublesome numbers, then decodes. Errors are what bad bytes must
//! give; a panic fails the test and leaves the input in `OCTSTORE_FUZZ_CRASHES` (default the
//! system temporary folder) with the seed that made it (docs/store.md, "Fuzzing").
//!
//! Integer overflow while decoding must be an error too, so CI runs this file a second time
//! with overflow checks on in the release profile (`.ci/run`). The long run:
//! `OCTSTORE_FUZZ_SECONDS=600 cargo test --release --locked --config
//! 'profile.release.package.octstore.overflow-checks=true' --test fuzz -- --test-threads 2`.

mod common;

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use glam::{DMat4, DVec3};
use octstore::format::segment::SegmentReader;
use octstore::inputs::{DepthImage, DiscoverOptions, discover, read_npy, read_pfm, read_png16, write_pfm};
use octstore::testing::catalog::{self, SegmentRecord, StageRun, UnitRecord, VersionRecord};

fn budget() -> Duration {
    let seconds = std::env::var("OCTSTORE_FUZZ_SECONDS")
        .ok()
        .and_then(|s| s.parse::<f64>().ok())
        .unwrap_or(2.0);
    Duration::from_secs_f64(seconds)
}

/// splitmix64: the same mutations on every machine for a given seed.
fn next(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

fn below(state: &mut u64, n: usize) -> usize {
    (next(state) % n.max(1) as u64) as usize
}

const TOKENS: [&[u8]; 10] = [
    b"nan",
    b"-1",
    b"0",
    b"1e308",
    b"-inf",
    b"4294967296",
    b"99999999999",
    b"\xff\xff\xff\xff",
    b"\x00\x00\x00\x00\x00\x00\xf0\x7f",
    b"",
];

/// One to four mutations of `input`.
fn mutate(input: &[u8], state: &mut u64) -> Vec<u8> {
    let mut bytes = input.to_vec();
    for _ in 0..1 + below(state, 4) {
        let at = below(state, bytes.len() + 1);
        match below(state, 6) {
            0 if !bytes.is_empty() => {
                let i = at.min(bytes.len() - 1);
                bytes[i] ^= 1 << below(state, 8);
            }
            1 if !bytes.is_empty() => {
                let i = at.min(bytes.len() - 1);
                bytes[i] = next(state) as u8;
            }
            2 => bytes.truncate(at),
            3 => {
                let token = TOKENS[below(state, TOKENS.len())];
                let end = (at + below(state, 12)).min(bytes.len());
                bytes.splice(at..end, token.iter().copied());
            }
            4 => {
                let extra: Vec<u8> = (0..1 + below(state, 16)).map(|_| next(state) as u8).collect();
                bytes.splice(at..at, extra);
            }
            _ => {
                // Duplicate a span: repeated records, lengths that no longer add up.
                let len = below(state, 64).min(bytes.len() - at.min(bytes.len()));
                let span: Vec<u8> = bytes[at..at + len].to_vec();
                bytes.splice(at..at, span);
            }
        }
    }
    bytes
}

/// Runs `decode` on mutations of one of `files` (restored after each try) until the budget is
/// spent; panics with the seed and the saved input if `decode` panics.
fn fuzz_files(name: &str, files: &[PathBuf], decode: &dyn Fn()) -> u64 {
    let originals: Vec<Vec<u8>> = files.iter().map(|f| std::fs::read(f).unwrap()).collect();
    let seed = 0x6F63_7473_746F_7265 ^ name.bytes().fold(0u64, |h, b| h.rotate_left(5) ^ u64::from(b));
    let mut state = seed;
    let started = Instant::now();
    let mut tries = 0u64;
    // Panics are the finding, not noise: keep the default hook's message out of the way.
    while started.elapsed() < budget() || tries < 50 {
        let which = below(&mut state, files.len());
        let mutated = mutate(&originals[which], &mut state);
        std::fs::write(&files[which], &mutated).unwrap();
        let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(decode));
        std::fs::write(&files[which], &originals[which]).unwrap();
        if outcome.is_err() {
            let dir = std::env::var_os("OCTSTORE_FUZZ_CRASHES")
                .map(PathBuf::from)
                .unwrap_or_else(std::env::temp_dir);
            let saved = dir.join(format!("octstore-fuzz-{name}-{tries}.bin"));
            std::fs::write(&saved, &mutated).unwrap();
            panic!(
                "{name}: decoding mutation {tries} of {} panicked (seed {seed:#x}); input saved to {}",
                files[which].display(),
                saved.display()
            );
        }
        tries += 1;
    }
    println!(
        "{name}: {tries} inputs in {:.1} s, no panic",
        started.elapsed().as_secs_f64()
    );
    tries
}

fn plane_depth(width: u32, height: u32) -> DepthImage {
    let depth = (0..width * height)
        .map(|i| 1.0 + 0.001 * (i % width) as f32 + if i % 17 == 0 { f32::NAN } else { 0.0 })
        .collect();
    DepthImage { width, height, depth }
}

fn pose() -> DMat4 {
    DMat4::from_translation(DVec3::new(0.1, -0.2, 0.3))
}

fn load_all(inputs: &[PathBuf]) {
    if let Ok(sources) = discover(inputs, &DiscoverOptions::default()) {
        for source in sources {
            let _ = source.load();
        }
    }
}

#[test]
fn segments() {
    let dir = tempfile::tempdir().unwrap();
    let store = octstore::Store::create(dir.path()).unwrap();
    let stage = octstore::testing::stages::exercise::ExerciseStage {
        units: 1,
        rows_per_unit: 300,
        seed: 3,
        delay_ms: 0,
    };
    store.run_stage(&stage, &octstore::RunOptions::default()).unwrap();
    let snapshot = store.latest().unwrap();
    let (name, _) = &snapshot.segments(octstore::testing::stages::exercise::NAME)[0];
    let file = store.segment_path(name);
    let copy = dir.path().join("fuzzed.seg");
    std::fs::copy(&file, &copy).unwrap();
    fuzz_files("segment", std::slice::from_ref(&copy), &|| {
        let bytes = std::fs::read(&copy).unwrap();
        if let Ok(reader) = SegmentReader::parse(&bytes) {
            let _ = reader.verify();
            for column in reader.columns() {
                let _ = reader.read_column(&column.name);
            }
            for block in 0..reader.block_count() {
                let _ = reader.read_block("key", block);
            }
        }
    });
}

#[test]
fn catalog_records() {
    let dir = tempfile::tempdir().unwrap();
    let records: Vec<(&'static str, Vec<u8>)> = vec![
        (
            "versions",
            catalog::seal_encode(
                "versions",
                &7u64,
                &VersionRecord {
                    parent: 6,
                    kind: "ingest".into(),
                    summary: "3 depth map(s)".into(),
                },
            ),
        ),
        (
            "stage_runs",
            catalog::seal_encode(
                "stage_runs",
                &7u64,
                &StageRun {
                    target_version: 8,
                    params: vec![1, 2, 3],
                    units: 4,
                },
            ),
        ),
        (
            "units_done",
            catalog::seal_encode(
                "units_done",
                &7u64,
                &UnitRecord {
                    segments: vec!["a.seg".into(), "b.seg".into()],
                    extra: vec![9; 20],
                },
            ),
        ),
        (
            "segments",
            catalog::seal_encode(
                "segments",
                &7u64,
                &SegmentRecord {
                    stage: "octree".into(),
                    unit: 1,
                    part: 0,
                    rows: 10,
                    bytes: 100,
                    file_checksum: 5,
                    content_digest: 6,
                    first_key: 1,
                    last_key: 2,
                    created: 3,
                    dropped: Some(4),
                },
            ),
        ),
        (
            "meta",
            catalog::seal_encode(
                "meta",
                &7u64,
                &octstore::format::Scene {
                    root_min: [0.0; 3],
                    root_side: 2.0,
                    max_depth: 9,
                },
            ),
        ),
    ];
    let files: Vec<PathBuf> = records
        .iter()
        .map(|(table, bytes)| {
            let path = dir.path().join(table);
            std::fs::write(&path, bytes).unwrap();
            path
        })
        .collect();
    fuzz_files("catalog", &files, &|| {
        let read = |table: &'static str| std::fs::read(dir.path().join(table)).unwrap();
        let _ = catalog::unseal_decode::<_, VersionRecord>("versions", &7u64, &read("versions"));
        let _ = catalog::unseal_decode::<_, StageRun>("stage_runs", &7u64, &read("stage_runs"));
        let _ = catalog::unseal_decode::<_, UnitRecord>("units_done", &7u64, &read("units_done"));
        let _ = catalog::unseal_decode::<_, SegmentRecord>("segments", &7u64, &read("segments"));
        let _ = catalog::unseal_decode::<_, octstore::format::Scene>("meta", &7u64, &read("meta"));
        // Decoded as the other tables' records too: a value under the wrong key or table.
        let _ = catalog::decode::<octstore::testing::stages::ingest::DepthMapRecord>("depth_maps", &read("segments"));
    });
}

#[test]
fn depth_images() {
    let dir = tempfile::tempdir().unwrap();
    let image = plane_depth(24, 18);
    let pfm = dir.path().join("d.pfm");
    write_pfm(&pfm, &image).unwrap();
    let png = dir.path().join("d.png");
    let pixels: Vec<u16> = image
        .depth
        .iter()
        .map(|d| if d.is_finite() { (d * 1000.0) as u16 } else { 0 })
        .collect();
    image::ImageBuffer::<image::Luma<u16>, _>::from_raw(24, 18, pixels)
        .unwrap()
        .save(&png)
        .unwrap();
    let npy = dir.path().join("d.npy");
    let header = "{'descr': '<f4', 'fortran_order': False, 'shape': (18, 24), }";
    let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
    let padded = format!("{header:<width$}\n", width = 118 - 10 - 1);
    bytes.extend((padded.len() as u16).to_le_bytes());
    bytes.extend(padded.as_bytes());
    image.depth.iter().for_each(|d| bytes.extend(d.to_le_bytes()));
    std::fs::write(&npy, bytes).unwrap();
    assert!(read_npy(&npy).is_ok(), "the NPY seed does not decode");
    fuzz_files("pfm", std::slice::from_ref(&pfm), &|| drop(read_pfm(&pfm)));
    fuzz_files("png16", std::slice::from_ref(&png), &|| drop(read_png16(&png, 0.001)));
    fuzz_files("npy", std::slice::from_ref(&npy), &|| drop(read_npy(&npy)));
}

#[test]
fn scene_manifests() {
    let dir = tempfile::tempdir().unwrap();
    let views = (0..2).map(|i| (plane_depth(16, 12), pose() * DMat4::from_rotation_y(0.3 * f64::from(i))));
    let manifest = octstore::testing::quality::synthetic_scenes::write_pinhole_views(dir.path(), views, 14.0).unwrap();
    let files = vec![manifest.clone(), dir.path().join("view-000.pfm")];
    fuzz_files("manifest", &files, &|| load_all(std::slice::from_ref(&manifest)));
}

fn write_pose(path: &Path, m: &DMat4) {
    let rows: Vec<String> = (0..4)
        .map(|r| {
            let row = m.row(r);
            format!("{} {} {} {}", row.x, row.y, row.z, row.w)
        })
        .collect();
    std::fs::write(path, rows.join("\n")).unwrap();
}

#[test]
fn seven_scenes_and_tum_folders() {
    let dir = tempfile::tempdir().unwrap();
    let frames = dir.path().join("frames");
    std::fs::create_dir_all(&frames).unwrap();
    std::fs::write(frames.join("camera-intrinsics.txt"), "29 0 16\n0 29 12\n0 0 1\n").unwrap();
    let image = plane_depth(32, 24);
    let pixels: Vec<u16> = image
        .depth
        .iter()
        .map(|d| if d.is_finite() { (d * 1000.0) as u16 } else { 0 })
        .collect();
    let png = frames.join("frame-000000.depth.png");
    image::ImageBuffer::<image::Luma<u16>, _>::from_raw(32, 24, pixels.clone())
        .unwrap()
        .save(&png)
        .unwrap();
    write_pose(&frames.join("frame-000000.pose.txt"), &pose());
    let files = vec![
        frames.join("camera-intrinsics.txt"),
        frames.join("frame-000000.pose.txt"),
        png,
    ];
    fuzz_files("seven-scenes", &files, &|| load_all(std::slice::from_ref(&frames)));

    let tum = dir.path().join("rgbd_dataset_freiburg1_desk");
    std::fs::create_dir_all(tum.join("depth")).unwrap();
    image::ImageBuffer::<image::Luma<u16>, _>::from_raw(32, 24, pixels.iter().map(|p| p * 5).collect::<Vec<_>>())
        .unwrap()
        .save(tum.join("depth/1.000000.png"))
        .unwrap();
    std::fs::write(tum.join("depth.txt"), "# depth maps\n1.000000 depth/1.000000.png\n").unwrap();
    std::fs::write(tum.join("groundtruth.txt"), "# poses\n1.001 0.1 0.2 0.3 0 0 0 1\n").unwrap();
    std::fs::write(tum.join("intrinsics.txt"), "29 29 16 12\n").unwrap();
    let files = vec![tum.join("depth.txt"), tum.join("groundtruth.txt")];
    fuzz_files("tum", &files, &|| {
        let options = DiscoverOptions {
            intrinsics: Some(tum.join("intrinsics.txt")),
            ..DiscoverOptions::default()
        };
        if let Ok(sources) = discover(std::slice::from_ref(&tum), &options) {
            sources.iter().for_each(|s| drop(s.load()));
        }
    });
}

#[test]
fn colmap_workspaces() {
    let dir = tempfile::tempdir().unwrap();
    let writer = octstore::inputs::WorkspaceWriter {
        root: dir.path().join("dense"),
    };
    let views = vec![("a.jpg".to_string(), 16, 12, [14.0, 14.0, 8.0, 6.0], pose())];
    writer.write_model(&views, true).unwrap();
    let depth = writer.root.join("stereo/depth_maps/a.jpg.geometric.bin");
    octstore::inputs::write_colmap_depth(&depth, &plane_depth(16, 12)).unwrap();
    let files = vec![
        writer.root.join("sparse/cameras.bin"),
        writer.root.join("sparse/images.bin"),
        depth,
    ];
    fuzz_files("colmap", &files, &|| load_all(std::slice::from_ref(&writer.root)));
}

/// A 20 x 10 scan of a wall, every fifth point missing.
fn wall_points() -> Vec<Option<DVec3>> {
    (0..200)
        .map(|i| (i % 5 != 0).then(|| DVec3::new(2.0, f64::from(i / 10) * 0.1 - 1.0, f64::from(i % 10) * 0.1 - 0.5)))
        .collect()
}

#[test]
fn lidar_scans() {
    let dir = tempfile::tempdir().unwrap();
    let ptx = dir.path().join("scan.ptx");
    let mut out = Vec::new();
    octstore::inputs::write_ptx_scan(&mut out, 20, 10, &pose(), &wall_points()).unwrap();
    std::fs::write(&ptx, out).unwrap();
    fuzz_files("ptx", std::slice::from_ref(&ptx), &|| {
        load_all(std::slice::from_ref(&ptx))
    });

    let e57 = dir.path().join("scan.e57");
    {
        use e57::{Record, RecordDataType, RecordName, RecordValue};
        let mut writer = e57::E57Writer::from_file(&e57, "octstore-fuzz").unwrap();
        let prototype = [RecordName::CartesianX, RecordName::CartesianY, RecordName::CartesianZ]
            .into_iter()
            .map(|name| Record {
                name,
                data_type: RecordDataType::F64,
            })
            .collect();
        let mut cloud = writer.add_pointcloud("scan-0", prototype).unwrap();
        for p in wall_points().into_iter().flatten() {
            cloud
                .add_point(vec![
                    RecordValue::Double(p.x),
                    RecordValue::Double(p.y),
                    RecordValue::Double(p.z),
                ])
                .unwrap();
        }
        cloud.finalize().unwrap();
        writer.finalize().unwrap();
    }
    fuzz_files("e57", std::slice::from_ref(&e57), &|| {
        load_all(std::slice::from_ref(&e57))
    });
}

#[test]
fn mesh_files() {
    let dir = tempfile::tempdir().unwrap();
    let mesh = octstore::mesh::Mesh {
        positions: vec![[0.0; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        normals: Vec::new(),
        triangles: vec![[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]],
    };
    let mut files = Vec::new();
    for name in ["m.ply", "m.obj"] {
        let path = dir.path().join(name);
        octstore::mesh::write_mesh(&path, &mesh).unwrap();
        files.push(path);
    }
    let off = dir.path().join("m.off");
    std::fs::write(
        &off,
        "OFF\n4 4 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 1 2\n3 0 2 3\n3 0 3 1\n3 1 3 2\n",
    )
    .unwrap();
    files.push(off);
    let paths = files.clone();
    fuzz_files("mesh", &files, &|| {
        for path in &paths {
            let _ = octstore::mesh::read_mesh(path);
        }
    });
}

/// A small real store (ingest, solve, extract of a sphere seen by six views) made by the CLI.
fn small_real_store(dir: &Path) -> PathBuf {
    let spec = octstore::SceneSpec {
        shapes: vec![octstore::testing::quality::synthetic_scenes::Shape::Sphere {
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
    };
    let manifest = spec.write(&dir.join("views")).unwrap();
    let store = dir.join("store");
    let (s, m) = (store.to_str().unwrap(), manifest.to_str().unwrap());
    for args in [
        vec!["ingest", s, m, "--max-depth", "6"],
        vec!["solve", s],
        vec!["extract", s, "-o", dir.join("mesh.ply").to_str().unwrap()],
    ] {
        let out = common::octstore(&args, &[]);
        assert!(out.status.success(), "{args:?}: {}", common::stderr(&out));
    }
    store
}

/// Where a flipped bit of `catalog.redb` leaves a reader: it must never panic, and the flip is
/// either reported (an open or `verify` error, or a `verify` problem) or harmless (the
/// catalog's canonical content unchanged).
#[derive(Debug, PartialEq, Eq)]
enum FlipOutcome {
    Reported,
    Harmless,
    SilentlyChanged,
}

fn read_flipped(store: &Path, original_dump: &[u8]) -> FlipOutcome {
    let Ok(opened) = octstore::Store::open_read_only(store) else {
        return FlipOutcome::Reported;
    };
    match opened.verify(&[octstore::testing::stages::octree::verify_octree]) {
        Ok(report) if report.is_ok() => {}
        _ => return FlipOutcome::Reported,
    }
    match opened.canonical_dump() {
        Ok(dump) if dump == original_dump => FlipOutcome::Harmless,
        Ok(_) => FlipOutcome::SilentlyChanged,
        Err(_) => FlipOutcome::Reported,
    }
}

/// Bit flips in a real store's `catalog.redb`, one at a time: first at every byte that is
/// printable text (table names, type names, segment names, meta keys and stage names, where a
/// flip used to panic inside redb), then at the other nonzero bytes (page headers, offsets,
/// numbers, checksums), then at the zeros (mostly free pages), each group in a shuffled order,
/// until the budget is spent (a long run reaches every position; docs/store.md, "Fuzzing").
#[test]
fn catalog_bit_flips() {
    let dir = tempfile::tempdir().unwrap();
    let store = small_real_store(dir.path());
    let catalog_path = store.join("catalog.redb");
    let original = std::fs::read(&catalog_path).unwrap();
    let original_dump = octstore::Store::open_read_only(&store)
        .unwrap()
        .canonical_dump()
        .unwrap();
    let mut state = 0x00ca_7a10_9f11_b175_u64;
    let mut order = |positions: Vec<usize>| {
        let mut positions = positions;
        for i in (1..positions.len()).rev() {
            positions.swap(i, below(&mut state, i + 1));
        }
        positions
    };
    let tier = |byte: u8| match byte {
        b if b.is_ascii_graphic() => 0,
        0 => 2,
        _ => 1,
    };
    let tiers: Vec<Vec<usize>> = (0..3)
        .map(|t| (0..original.len()).filter(|&i| tier(original[i]) == t).collect())
        .collect();
    let sizes: Vec<usize> = tiers.iter().map(Vec::len).collect();
    let positions: Vec<usize> = tiers.into_iter().flat_map(&mut order).collect();
    let started = Instant::now();
    let mut counts = std::collections::BTreeMap::new();
    let mut silent = Vec::new();
    let mut tries = 0usize;
    for (n, &at) in positions.iter().enumerate() {
        if started.elapsed() >= budget() && tries >= 200 {
            break;
        }
        let bit = (n * 5 + at) % 8;
        let mut flipped = original.clone();
        flipped[at] ^= 1 << bit;
        std::fs::write(&catalog_path, &flipped).unwrap();
        let outcome = std::panic::catch_unwind(|| read_flipped(&store, &original_dump));
        std::fs::write(&catalog_path, &original).unwrap();
        tries += 1;
        match outcome {
            Ok(outcome) => {
                if outcome == FlipOutcome::SilentlyChanged {
                    silent.push(format!("byte {at} bit {bit}"));
                }
                *counts.entry(format!("{outcome:?}")).or_insert(0usize) += 1;
            }
            Err(_) => panic!("catalog: flipping bit {bit} of byte {at} of catalog.redb panicked a reader"),
        }
    }
    println!(
        "catalog: {tries} of {} positions ({} text, {} other nonzero, {} zero) in {:.1} s: {counts:?}",
        positions.len(),
        sizes[0],
        sizes[1],
        sizes[2],
        started.elapsed().as_secs_f64()
    );
    assert!(
        silent.is_empty(),
        "flips that changed the content without a report: {silent:?}"
    );
}

/// The fuzzer's first find, kept as a regression: a catalog record whose string length
/// prefix was damaged to about 3.8 * 10^18 made bincode allocate that much and abort.
#[test]
fn a_damaged_length_prefix_is_an_error_not_an_abort() {
    let record = VersionRecord {
        parent: 1,
        kind: "ingest".into(),
        summary: "1 depth map(s)".into(),
    };
    let mut bytes = catalog::encode(&record);
    // After `parent` (8 bytes): the u64 length of `kind`.
    bytes[8..16].copy_from_slice(&0x34A5_7C1F_0E2D_8B05u64.to_le_bytes());
    let error = catalog::decode::<VersionRecord>("versions", &bytes).expect_err("a damaged record decoded");
    assert!(error.to_string().contains("versions"), "{error}");
}
