//! The versioned store: snapshots, gc, determinism, corruption, disk-full and fsync failures.

mod common;

use common::*;
use octstore::Store;
use octstore::format::{ColumnValues, CubeKey};
use octstore::store::{IoFaults, RunOptions, StoreError};
use octstore::testing::stages::exercise::{self, ExerciseStage};

fn stage(units: u32, seed: u64) -> ExerciseStage {
    ExerciseStage {
        units,
        rows_per_unit: 300,
        seed,
        delay_ms: 0,
    }
}

fn options(threads: usize) -> RunOptions {
    RunOptions {
        resume: false,
        threads,
        progress: false,
    }
}

#[test]
fn stage_output_is_readable_through_a_snapshot() {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::create(dir.path()).unwrap();
    let s = stage(5, 7);
    let report = store.run_stage(&s, &options(2)).unwrap();
    assert_eq!(report.version, Some(1));
    assert_eq!(report.units, 5);
    let snap = store.latest().unwrap();
    let segments = snap.segments(exercise::NAME);
    assert_eq!(segments.len(), 5);
    for (unit, (name, record)) in segments.iter().enumerate() {
        let expected = s.unit_columns(unit as u64);
        let file = snap.open_segment(name).unwrap();
        let reader = file.reader().unwrap();
        assert_eq!(reader.rows(), record.rows);
        for column in &expected {
            assert_eq!(
                &reader.read_column(&column.name).unwrap(),
                column,
                "{name}: {}",
                column.name
            );
        }
    }
    // Key ranges of units are disjoint and increasing.
    for pair in segments.windows(2) {
        assert!(pair[0].1.last_key < pair[1].1.first_key);
    }
}

#[test]
fn pinned_versions_gc_and_version_errors() {
    let dir = tempfile::tempdir().unwrap();
    let store = Store::create(dir.path()).unwrap();
    store.run_stage(&stage(3, 1), &options(2)).unwrap();
    let old_digest = store.snapshot(1).unwrap().digest(exercise::NAME);
    store.run_stage(&stage(2, 2), &options(2)).unwrap();
    assert_eq!(store.current_version().unwrap(), 2);
    {
        let v1 = store.snapshot(1).unwrap();
        let v2 = store.snapshot(2).unwrap();
        assert_eq!(v1.segments(exercise::NAME).len(), 3);
        assert_eq!(v2.segments(exercise::NAME).len(), 2);
        assert_eq!(v1.digest(exercise::NAME), old_digest);
        assert_ne!(v2.digest(exercise::NAME), old_digest);
        // The old version is still fully readable.
        for (name, _) in v1.segments(exercise::NAME) {
            v1.open_segment(name).unwrap().reader().unwrap().verify().unwrap();
        }
    }
    assert!(matches!(
        store.snapshot(9),
        Err(StoreError::NoSuchVersion { version: 9, latest: 2 })
    ));
    let (files, bytes) = store.gc(1).unwrap();
    assert_eq!(files, 3);
    assert!(bytes > 0);
    assert!(matches!(
        store.snapshot(1),
        Err(StoreError::VersionGone { version: 1, horizon: 2 })
    ));
    assert_eq!(std::fs::read_dir(dir.path().join("segments")).unwrap().count(), 2);
    assert!(store.verify(&[]).unwrap().is_ok());
    assert_eq!(store.log().unwrap().len(), 3);
}

#[test]
fn results_do_not_depend_on_thread_count() {
    let a = tempfile::tempdir().unwrap();
    let b = tempfile::tempdir().unwrap();
    Store::create(a.path())
        .unwrap()
        .run_stage(&stage(9, 3), &options(1))
        .unwrap();
    Store::create(b.path())
        .unwrap()
        .run_stage(&stage(9, 3), &options(4))
        .unwrap();
    assert_same_store(&fingerprint(a.path()), &fingerprint(b.path()), "1 vs 4 threads");
}

#[test]
fn a_second_writer_is_refused_with_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let _writer = Store::create(dir.path()).unwrap();
    let err = Store::open(dir.path()).err().expect("second open must fail");
    assert!(matches!(err, StoreError::InUse { .. }), "{err}");
    assert!(err.to_string().contains("in use by another octstore process"));
    // Another process too.
    let out = octstore(&["debug-synthetic", dir.path().to_str().unwrap()], &[]);
    assert!(!out.status.success());
    assert!(
        stderr(&out).contains("in use by another octstore process"),
        "{}",
        stderr(&out)
    );
}

#[test]
fn disk_full_mid_unit_leaves_the_last_commit_intact_and_resume_completes() {
    let reference = tempfile::tempdir().unwrap();
    Store::create(reference.path())
        .unwrap()
        .run_stage(&stage(6, 5), &options(2))
        .unwrap();

    let dir = tempfile::tempdir().unwrap();
    Store::create(dir.path())
        .unwrap()
        .run_stage(&stage(2, 9), &options(2))
        .unwrap();
    let before = fingerprint(dir.path());
    {
        let faults = IoFaults::disk_full_after(40_000);
        let store = Store::open_with_faults(dir.path(), faults).unwrap();
        let err = store.run_stage(&stage(6, 5), &options(2)).unwrap_err();
        assert!(
            matches!(&err, StoreError::Io { source, .. } if source.kind() == std::io::ErrorKind::StorageFull),
            "{err}"
        );
        assert!(
            err.to_string().contains("segments/synthetic-"),
            "error names the file: {err}"
        );
        // Still version 1, still valid.
        assert_eq!(store.current_version().unwrap(), 1);
        assert!(store.verify(&[]).unwrap().is_ok());
        assert_eq!(store.latest().unwrap().digest(exercise::NAME), {
            let other = Store::open_read_only(reference.path());
            drop(other);
            store.snapshot(1).unwrap().digest(exercise::NAME)
        });
    }
    // The committed content of version 1 is untouched (a run in progress is recorded, though).
    {
        let store = Store::open(dir.path()).unwrap();
        let snap = store.snapshot(1).unwrap();
        assert_eq!(snap.segments(exercise::NAME).len(), 2);
        for (name, _) in snap.segments(exercise::NAME) {
            assert_eq!(
                std::fs::read(dir.path().join("segments").join(name)).unwrap(),
                before.segments[name]
            );
        }
        let mut resume = options(2);
        resume.resume = true;
        store.run_stage(&stage(6, 5), &resume).unwrap();
        assert!(store.verify(&[]).unwrap().is_ok());
        let latest = store.latest().unwrap();
        let reference_store = Store::open_read_only(reference.path()).unwrap();
        assert_eq!(
            latest.digest(exercise::NAME),
            reference_store.latest().unwrap().digest(exercise::NAME)
        );
    }
}

#[test]
fn a_failed_fsync_poisons_the_store() {
    let dir = tempfile::tempdir().unwrap();
    let faults = IoFaults::failing_fsync();
    let store = Store::create_with_faults(dir.path(), faults).unwrap();
    let err = store.run_stage(&stage(2, 1), &options(1)).unwrap_err();
    assert!(err.to_string().contains("fsync"), "{err}");
    assert!(store.is_poisoned());
    assert!(matches!(
        store.run_stage(&stage(2, 1), &options(1)),
        Err(StoreError::Poisoned)
    ));
    drop(store);
    // Reopened, the store is at its last commit and works again.
    let store = Store::open(dir.path()).unwrap();
    assert_eq!(store.current_version().unwrap(), 0);
    store.run_stage(&stage(2, 1), &options(1)).unwrap();
    assert!(store.verify(&[]).unwrap().is_ok());
}

#[test]
fn every_flipped_byte_and_truncation_of_a_segment_is_caught() {
    let dir = tempfile::tempdir().unwrap();
    let s = ExerciseStage {
        units: 1,
        rows_per_unit: 40,
        seed: 4,
        delay_ms: 0,
    };
    let store = Store::create(dir.path()).unwrap();
    store.run_stage(&s, &options(1)).unwrap();
    let name = store.latest().unwrap().segments(exercise::NAME)[0].0.clone();
    let path = dir.path().join("segments").join(&name);
    let good = std::fs::read(&path).unwrap();
    for i in 0..good.len() {
        let mut bad = good.clone();
        bad[i] ^= 0x01;
        std::fs::write(&path, &bad).unwrap();
        let report = store.verify(&[]).unwrap();
        assert_eq!(report.problems.len(), 1, "flip at {i} went unnoticed");
        assert!(report.problems[0].contains(&name), "{}", report.problems[0]);
        assert!(
            report.problems[0].contains("keys "),
            "no key range: {}",
            report.problems[0]
        );
        // Reads fail with a corruption error, never a panic, never wrong data.
        let snap = store.latest().unwrap();
        let file = snap.open_segment(&name).unwrap();
        let read = file.reader().map_err(|e| e.to_string()).and_then(|r| {
            let mut all = Vec::new();
            for c in s.unit_columns(0) {
                all.push(r.read_column(&c.name).map_err(|e| file.corruption(e).to_string())?);
            }
            Ok(all)
        });
        if let Ok(columns) = read {
            // A flip outside any column block (the footer's reserved block-rows field is still
            // checksummed) must then have been caught by parse; reaching here means the decoded
            // content must be exactly right.
            assert_eq!(columns, s.unit_columns(0), "flip at {i} returned wrong data");
            panic!("flip at {i} read back without error");
        }
    }
    for len in [0, 1, good.len() / 2, good.len() - 1] {
        std::fs::write(&path, &good[..len]).unwrap();
        let report = store.verify(&[]).unwrap();
        assert_eq!(report.problems.len(), 1, "truncation to {len} went unnoticed");
        assert!(report.problems[0].contains(&name));
    }
    std::fs::write(&path, &good).unwrap();
    assert!(store.verify(&[]).unwrap().is_ok());
}

#[test]
fn verify_cli_names_file_column_and_key_range() {
    let dir = tempfile::tempdir().unwrap();
    let store_path = dir.path().join("s");
    let out = octstore(
        &[
            "debug-synthetic",
            store_path.to_str().unwrap(),
            "--units",
            "2",
            "--rows",
            "500",
        ],
        &[],
    );
    assert!(out.status.success(), "{}", stderr(&out));
    let ok = octstore(&["verify", store_path.to_str().unwrap()], &[]);
    assert!(ok.status.success(), "{}", stderr(&ok));
    let (name, first_key, last_key) = {
        let store = Store::open(&store_path).unwrap();
        let snap = store.latest().unwrap();
        let (name, record) = snap.segments(exercise::NAME)[1].clone();
        (
            name,
            CubeKey::from_raw(record.first_key),
            CubeKey::from_raw(record.last_key),
        )
    };
    let path = store_path.join("segments").join(&name);
    let mut bytes = std::fs::read(&path).unwrap();
    // A byte inside the first column block after the key column ('radius_sum').
    let store = Store::open(&store_path).unwrap();
    let snap = store.latest().unwrap();
    let file = snap.open_segment(&name).unwrap();
    let reader = file.reader().unwrap();
    let keys_len = {
        let (_, k) = (0, reader.read_keys().unwrap());
        k.len()
    };
    assert!(keys_len > 0);
    drop(reader);
    drop(file);
    drop(snap);
    drop(store);
    let target = 16 + 20; // in the key column's first block, right after the header
    bytes[target] ^= 0xff;
    std::fs::write(&path, &bytes).unwrap();
    let out = octstore(&["verify", store_path.to_str().unwrap()], &[]);
    assert!(!out.status.success());
    let err = stderr(&out);
    assert!(err.contains(&name), "{err}");
    assert!(err.contains("column 'key'"), "{err}");
    assert!(
        err.contains(&first_key.to_string()) && err.contains(&last_key.to_string()),
        "{err}"
    );
}

#[test]
fn read_only_snapshot_sees_typed_columns() {
    let dir = tempfile::tempdir().unwrap();
    Store::create(dir.path())
        .unwrap()
        .run_stage(&stage(1, 11), &options(1))
        .unwrap();
    let store = Store::open_read_only(dir.path()).unwrap();
    assert!(store.is_read_only());
    let snap = store.latest().unwrap();
    let (name, _) = &snap.segments(exercise::NAME)[0];
    let file = snap.open_segment(name).unwrap();
    let reader = file.reader().unwrap();
    let (width, hist) = reader.read_f32("hist").unwrap();
    assert_eq!(width, 8);
    assert_eq!(hist.len(), reader.rows() as usize * 8);
    assert!(matches!(reader.read_column("q").unwrap().values, ColumnValues::F32(_)));
    assert!(reader.read_u32("hist").is_err());
    assert!(matches!(
        store.run_stage(&stage(1, 1), &options(1)),
        Err(StoreError::ReadOnly)
    ));
}

#[test]
fn readers_open_the_store_while_a_writer_commits_and_keep_their_pinned_version() {
    let Some(_) = shared_data("7scenes-redkitchen") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().to_str().unwrap();
    let first = octstore(&["debug-synthetic", path, "--units", "3", "--seed", "1"], &[]);
    assert!(first.status.success(), "{}", stderr(&first));
    let pinned_digest = Store::open_read_only(dir.path())
        .unwrap()
        .latest()
        .unwrap()
        .digest(exercise::NAME);

    // A writer that takes a few seconds, committing unit by unit.
    let mut writer = std::process::Command::new(octstore_bin())
        .args([
            "debug-synthetic",
            path,
            "--units",
            "40",
            "--seed",
            "2",
            "--delay-ms",
            "100",
        ])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    std::thread::sleep(std::time::Duration::from_millis(800));
    assert!(
        writer.try_wait().unwrap().is_none(),
        "the writer finished too early to test anything"
    );

    let reader = Store::open_read_only(dir.path()).expect("a reader opens while the writer runs");
    let snapshot = reader.latest().unwrap();
    let version = snapshot.version();
    assert_eq!(
        snapshot.digest(exercise::NAME),
        pinned_digest,
        "the writer's run is not committed yet"
    );
    // Other processes read too: `info`, and `verify`, which once opened the store as a writer.
    let info = octstore(&["info", path, "--json"], &[]);
    assert!(info.status.success(), "{}", stderr(&info));
    let verify = octstore(&["verify", path], &[]);
    assert!(verify.status.success(), "{}", stderr(&verify));
    // A second writer is still refused.
    let second = octstore(&["debug-synthetic", path], &[]);
    assert!(
        stderr(&second).contains("in use by another octstore process"),
        "{}",
        stderr(&second)
    );

    let status = writer.wait().unwrap();
    assert!(status.success());
    // The pinned snapshot still reads its own version, every segment intact.
    assert_eq!(snapshot.digest(exercise::NAME), pinned_digest);
    for (name, _) in snapshot.segments(exercise::NAME) {
        snapshot.open_segment(name).unwrap().reader().unwrap().verify().unwrap();
    }
    // A new snapshot of the same reader sees the writer's version.
    let newer = reader.latest().unwrap();
    assert!(newer.version() > version, "{} vs {version}", newer.version());
    assert_ne!(newer.digest(exercise::NAME), pinned_digest);
}

/// Flips one byte inside every copy of `needle` in the store's `catalog.redb` (redb copies
/// pages on write, so older copies may remain in free pages); returns how many it flipped.
fn flip_in_catalog(store: &std::path::Path, needle: &[u8], offset: usize) -> usize {
    let path = store.join("catalog.redb");
    let mut bytes = std::fs::read(&path).unwrap();
    let mut flipped = 0;
    let mut at = 0;
    while let Some(found) = bytes
        .get(at..)
        .and_then(|rest| rest.windows(needle.len()).position(|w| w == needle))
    {
        bytes[at + found + offset] ^= 0x10;
        flipped += 1;
        at += found + needle.len();
    }
    std::fs::write(&path, bytes).unwrap();
    flipped
}

/// A store holding RedKitchen's frame 0 at `--max-depth 6`, made by the CLI.
fn ingest_one_kitchen_frame(store: &std::path::Path) {
    let frame = shared_path("7scenes-redkitchen/frame-000000.depth.png");
    let out = octstore(
        &[
            "ingest",
            store.to_str().unwrap(),
            frame.to_str().unwrap(),
            "--max-depth",
            "6",
            "--quiet",
        ],
        &[],
    );
    assert!(out.status.success(), "{}", stderr(&out));
}

/// One flipped byte in a live catalog value (a version record; the root cube's minimum, which
/// would shift every extracted vertex) is a corruption error that names the table and the key,
/// on every read and in `verify`, never a wrong answer.
#[test]
fn a_flipped_catalog_value_is_a_corruption_error_naming_table_and_key() {
    let Some(_) = shared_data("7scenes-redkitchen") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    Store::create(&store)
        .unwrap()
        .run_stage(&stage(2, 5), &options(2))
        .unwrap();
    assert!(flip_in_catalog(&store, b"2 unit(s)", 0) > 0);
    let opened = Store::open_read_only(&store).unwrap();
    let error = opened.log().expect_err("a flipped version record was read").to_string();
    assert!(error.contains("versions") && error.contains("key 1"), "{error}");
    let report = opened.verify(&[]).unwrap();
    assert!(
        report
            .problems
            .iter()
            .any(|p| p.contains("versions") && p.contains("key 1")),
        "{:?}",
        report.problems
    );
    drop(opened);

    // The scene of a real ingest: its root minimum's bytes, flipped, stop extraction and verify.
    let ingested = dir.path().join("ingested");
    ingest_one_kitchen_frame(&ingested);
    let scene = octstore::testing::stages::ingest::read_scene(&Store::open(&ingested).unwrap())
        .unwrap()
        .unwrap();
    let bytes = octstore::testing::catalog::encode(&scene);
    assert!(flip_in_catalog(&ingested, &bytes, 3) > 0);
    for args in [vec!["verify"], vec!["solve", "--until", "octree"], vec!["info"]] {
        let mut all = args.clone();
        all.push(ingested.to_str().unwrap());
        let out = octstore(&all, &[]);
        assert!(!out.status.success(), "{args:?} read a flipped scene");
        let text = format!("{}{}", stdout(&out), stderr(&out));
        assert!(text.contains("meta") && text.contains("'scene'"), "{args:?}: {text}");
    }

    // A flip in redb's table directory renames a table, which would read as empty (a store
    // without depth maps): verify names the stranger.
    let renamed = dir.path().join("renamed");
    ingest_one_kitchen_frame(&renamed);
    assert!(flip_in_catalog(&renamed, b"depth_maps", 5) > 0);
    let out = octstore(&["verify", renamed.to_str().unwrap()], &[]);
    assert!(!out.status.success(), "verify passed a renamed table");
    // '_' ^ 0x10 is 'O'.
    assert!(stderr(&out).contains("unknown table 'depthOmaps'"), "{}", stderr(&out));
}

/// A reader in another process pins its version: `gc` keeps it while the reader lives and
/// collects it afterwards; a snapshot that holds no pin (the writer's own) and whose files gc
/// removed says that its version was collected instead of reporting a missing file.
#[test]
fn gc_keeps_versions_readers_have_open_and_a_collected_one_says_so() {
    let dir = tempfile::tempdir().unwrap();
    {
        let store = Store::create(dir.path()).unwrap();
        store.run_stage(&stage(3, 1), &options(2)).unwrap();
        store.run_stage(&stage(2, 2), &options(2)).unwrap();
    }
    let path = dir.path().to_str().unwrap();
    let reader = Store::open_read_only(dir.path()).unwrap();
    let pinned = reader.snapshot(1).unwrap();
    let gc = octstore(&["gc", path, "--keep", "1"], &[]);
    assert!(gc.status.success(), "{}", stderr(&gc));
    for (name, _) in pinned.segments(exercise::NAME) {
        pinned.open_segment(name).unwrap().reader().unwrap().verify().unwrap();
    }
    drop(pinned);
    let gc = octstore(&["gc", path, "--keep", "1"], &[]);
    assert!(gc.status.success(), "{}", stderr(&gc));
    assert!(matches!(
        reader.snapshot(1),
        Err(StoreError::VersionGone { version: 1, horizon: 2 })
    ));
    drop(reader);

    let store = Store::open(dir.path()).unwrap();
    store.run_stage(&stage(2, 3), &options(2)).unwrap();
    let unpinned = store.snapshot(2).unwrap();
    store.gc(1).unwrap();
    let (name, _) = &unpinned.segments(exercise::NAME)[0];
    let error = unpinned.open_segment(name).err().map(|e| e.to_string());
    assert_eq!(
        error.as_deref(),
        Some("version 2 was garbage-collected (the oldest kept version is 3)")
    );
}

/// `verify` beside `gc`: verify pins the oldest version it checks, so `gc` keeps those files,
/// and segments `gc` already retired are not checked. It used to report hundreds of missing
/// segments on a healthy store while `gc` ran. Each round makes a version that drops the last
/// one's segments, then runs `gc --keep 1` while verifying in a loop beside it.
#[test]
fn verify_beside_gc_reports_nothing_missing() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().to_str().unwrap();
    for round in 0..6u32 {
        let seed = round.to_string();
        let out = octstore(
            &[
                "debug-synthetic",
                path,
                "--units",
                "30",
                "--rows",
                "300",
                "--seed",
                &seed,
                "--quiet",
            ],
            &[],
        );
        assert!(out.status.success(), "{}", stderr(&out));
        let done = std::sync::atomic::AtomicBool::new(false);
        let problems = std::thread::scope(|scope| {
            let verifier = scope.spawn(|| {
                let mut problems = Vec::new();
                let mut checks = 0;
                while !done.load(std::sync::atomic::Ordering::SeqCst) || checks == 0 {
                    let store = Store::open_read_only(dir.path()).unwrap();
                    problems.extend(store.verify(&[]).unwrap().problems);
                    checks += 1;
                }
                problems
            });
            let gc = octstore(&["gc", path, "--keep", "1"], &[]);
            assert!(gc.status.success(), "{}", stderr(&gc));
            done.store(true, std::sync::atomic::Ordering::SeqCst);
            verifier.join().unwrap()
        });
        assert!(problems.is_empty(), "round {round}: {problems:?}");
    }
}
