//! Golden files: the stores checked in under tests/data/golden-vN were written by catalog format
//! version N (segment format version 1 in both). Every later build must decode them to the same
//! values, a writable open must migrate an older one to the newest, and encoding the same content
//! again must give the newest one's bytes.

mod common;

use std::path::{Path, PathBuf};

use common::*;
use octstore::RunOptions;
use octstore::Store;
use octstore::format::segment::{self, SegmentReader};
use octstore::format::{ColumnValues, CubeKey};
use octstore::testing::catalog::{CATALOG_FORMAT_VERSION, META};
use octstore::testing::stages::exercise::{self, ExerciseStage};

fn golden(version: u32) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(format!("tests/data/golden-v{version}"))
}

fn golden_stage() -> ExerciseStage {
    ExerciseStage {
        units: 2,
        rows_per_unit: 20,
        seed: 42,
        delay_ms: 0,
    }
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to.join("segments")).unwrap();
    std::fs::copy(from.join("catalog.redb"), to.join("catalog.redb")).unwrap();
    for entry in std::fs::read_dir(from.join("segments")).unwrap() {
        let entry = entry.unwrap();
        std::fs::copy(entry.path(), to.join("segments").join(entry.file_name())).unwrap();
    }
}

#[test]
fn golden_v1_decodes_to_known_values() {
    decodes_to_known_values(1);
}

#[test]
fn golden_v2_decodes_to_known_values() {
    decodes_to_known_values(2);
}

#[test]
fn golden_v3_decodes_to_known_values() {
    decodes_to_known_values(3);
}

#[test]
fn golden_v4_decodes_to_known_values() {
    decodes_to_known_values(4);
}

fn decodes_to_known_values(version: u32) {
    let dir = tempfile::tempdir().unwrap();
    copy_dir(&golden(version), dir.path());
    let store = Store::open_read_only(dir.path()).unwrap();
    assert_eq!(store.current_version().unwrap(), 1);
    let log = store.log().unwrap();
    assert_eq!(log.len(), 2);
    assert_eq!(
        (log[1].1.kind.as_str(), log[1].1.summary.as_str()),
        ("synthetic", "2 unit(s)")
    );
    let snap = store.latest().unwrap();
    assert_eq!(format!("{:016x}", snap.digest(exercise::NAME)), "4b58d934915774dd");
    let segments = snap.segments(exercise::NAME);
    let names: Vec<&str> = segments.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(
        names,
        [
            "synthetic-v00000001-u0000000000-p000.seg",
            "synthetic-v00000001-u0000000001-p000.seg"
        ]
    );
    let (name, record) = &segments[0];
    assert_eq!(
        (record.rows, record.bytes, record.created, record.dropped),
        (20, 2349, 1, None)
    );

    let file = snap.open_segment(name).unwrap();
    let bytes = file.bytes();
    // Header and footer bytes, as format-spec.md lays them out.
    assert_eq!(&bytes[..8], b"OCTSEG\x00\x01");
    assert_eq!(&bytes[8..16], &[1, 0, 0, 0, 0, 0, 0, 0]);
    assert_eq!(&bytes[bytes.len() - 8..], b"OCTSEG\x00\x01");
    let reader = SegmentReader::parse(bytes).unwrap();
    assert_eq!(reader.rows(), 20);
    let names: Vec<&str> = reader.columns().iter().map(|c| c.name.as_str()).collect();
    assert_eq!(names, ["key", "radius_sum", "radius_count", "hist", "u", "v", "p", "q"]);
    let keys = reader.read_keys().unwrap();
    assert_eq!(keys.len(), 20);
    assert!(keys.iter().all(|k| k.depth() == 14));
    assert!(keys.windows(2).all(|w| w[0] < w[1]));
    assert_eq!(reader.first_key(), keys[0]);
    let (_, counts) = reader.read_u32("radius_count").unwrap();
    assert_eq!(counts[..8], [1, 2, 3, 4, 5, 6, 7, 1]);
    let (width, hist) = reader.read_f32("hist").unwrap();
    assert_eq!(width, 8);
    assert!(hist.iter().all(|h| (-1.0..=1.0).contains(h)));
    assert_eq!(reader.verify().unwrap(), record.content_digest);
    // The values are those of the generator that wrote them.
    for column in golden_stage().unit_columns(0) {
        assert_eq!(
            reader.read_column(&column.name).unwrap(),
            column,
            "column {}",
            column.name
        );
    }
    assert!(matches!(reader.read_column("u").unwrap().values, ColumnValues::F32(_)));
    assert_eq!(keys[0], CubeKey::from_raw(keys[0].raw()));
    assert_eq!(segment::FORMAT_VERSION, 1, "a new format version needs golden-v2");
}

#[test]
fn encoding_the_same_content_again_gives_the_same_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::create(dir.path()).unwrap();
    let options = RunOptions {
        resume: false,
        threads: 2,
        progress: false,
    };
    store.run_stage(&golden_stage(), &options).unwrap();
    drop(store);
    let fresh = fingerprint(dir.path());
    let copy = tempfile::tempdir().unwrap();
    copy_dir(&golden(CATALOG_FORMAT_VERSION), copy.path());
    let golden = fingerprint(copy.path());
    assert_same_store(&golden, &fresh, "the newest golden store re-encoded");
}

#[test]
fn a_writable_open_migrates_older_golden_stores_to_the_newest() {
    let newest = tempfile::tempdir().unwrap();
    copy_dir(&golden(CATALOG_FORMAT_VERSION), newest.path());
    let newest_dump = Store::open_read_only(newest.path()).unwrap().canonical_dump().unwrap();
    for version in 1..CATALOG_FORMAT_VERSION {
        let old = tempfile::tempdir().unwrap();
        copy_dir(&golden(version), old.path());
        let old_dump = Store::open_read_only(old.path()).unwrap().canonical_dump().unwrap();
        assert_ne!(old_dump, newest_dump, "golden-v{version} differs in its format version");
        let migrated = Store::open(old.path()).unwrap().canonical_dump().unwrap();
        assert_eq!(migrated, newest_dump, "golden-v{version} migrated");
    }
}

/// A version-2 store holding one RGB-D depth map (`tests/data/golden-v2-ingest`, written by
/// the version-2 build from `input/scene.json`): its map reads with the pixel-footprint rule
/// it was ingested with, read-only and after migration alike, keeps its id although this
/// build's default noise model (measured from the pixels) differs, and a repeated ingest adds nothing.
#[test]
fn version_2_depth_maps_keep_their_ids_and_the_footprint_rule() {
    let golden = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/golden-v2-ingest");
    let dir = tempfile::tempdir().unwrap();
    copy_dir(&golden, dir.path());
    let input = golden.join("input/scene.json");
    let sources = octstore::inputs::discover(std::slice::from_ref(&input), &Default::default()).unwrap();
    // This build measures the noise of every map it ingests.
    assert_eq!(sources[0].noise, octstore::inputs::DepthNoise::Auto { sigmas: None });
    let id = octstore::testing::stages::ingest::depth_map_id(&sources[0]).unwrap();

    let read_only = {
        let store = Store::open_read_only(dir.path()).unwrap();
        assert_eq!(store.catalog_format_version().unwrap(), 2);
        octstore::testing::stages::ingest::registered_depth_maps(&store).unwrap()
    };
    assert_eq!(read_only.len(), 1);
    let (old_id, record) = &read_only[0];
    assert_eq!(*old_id, id);
    assert_eq!(record.source.noise, octstore::inputs::DepthNoise::Footprint);
    assert_eq!(record.source.kind, octstore::inputs::Kind::Rgbd);
    assert_eq!(
        (record.stats.samples, record.stats.cubes, record.added_in),
        (192, 144, 1)
    );

    let store = Store::open(dir.path()).unwrap();
    assert_eq!(store.catalog_format_version().unwrap(), CATALOG_FORMAT_VERSION);
    assert_eq!(
        octstore::testing::stages::ingest::registered_depth_maps(&store).unwrap(),
        read_only
    );
    drop(store);
    let out = octstore(
        &[
            "ingest",
            dir.path().to_str().unwrap(),
            input.to_str().unwrap(),
            "--quiet",
        ],
        &[],
    );
    assert!(out.status.success(), "{}", stderr(&out));
    let store = Store::open_read_only(dir.path()).unwrap();
    assert_eq!(store.current_version().unwrap(), 1, "{}", stdout(&out));
    assert_eq!(
        octstore::testing::stages::ingest::registered_depth_maps(&store).unwrap(),
        read_only
    );
}

#[test]
fn catalogs_newer_than_this_build_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    copy_dir(&golden(CATALOG_FORMAT_VERSION), dir.path());
    {
        let db = redb::Database::open(dir.path().join("catalog.redb")).unwrap();
        let txn = db.begin_write().unwrap();
        txn.open_table(META)
            .unwrap()
            .insert(
                "format_version".as_bytes(),
                (CATALOG_FORMAT_VERSION + 1).to_le_bytes().as_slice(),
            )
            .unwrap();
        txn.commit().unwrap();
    }
    for result in [Store::open_read_only(dir.path()), Store::open(dir.path())] {
        let error = result.err().expect("a newer catalog opened").to_string();
        assert!(error.contains(&(CATALOG_FORMAT_VERSION + 1).to_string()), "{error}");
    }
}

/// A reader of the command's output that goes away early ends it quietly (SIGPIPE), instead
/// of a panic in `println!` (`octstore info STORE | head -1` failed 2 times in 7).
#[test]
fn a_closed_output_pipe_ends_the_command_quietly() {
    let dir = tempfile::tempdir().unwrap();
    copy_dir(&golden(CATALOG_FORMAT_VERSION), dir.path());
    let command = format!("'{}' info '{}' | true", octstore_bin().display(), dir.path().display());
    for _ in 0..5 {
        let out = std::process::Command::new("sh")
            .arg("-c")
            .arg(&command)
            .output()
            .unwrap();
        assert!(out.status.success());
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!err.contains("panicked") && !err.contains("Broken pipe"), "{err}");
    }
}
