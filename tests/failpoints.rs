//! Crash at every step of the commit protocol, then resume: the result equals an uninterrupted
//! run byte for byte. A separate test binary because every case aborts a real process.

mod common;

use common::*;
use octstore::testing::failpoint::FAILPOINTS;

const UNITS: &str = "6";
const ROWS: &str = "400";

fn run(store: &std::path::Path, resume: bool, failpoint: Option<&str>) -> std::process::Output {
    let mut args = vec![
        "debug-synthetic",
        store.to_str().unwrap(),
        "--units",
        UNITS,
        "--rows",
        ROWS,
        "--threads",
        "2",
    ];
    if resume {
        args.push("--resume");
    }
    match failpoint {
        Some(fp) => octstore(&args, &[("OCTSTORE_FAILPOINT", fp)]),
        None => octstore(&args, &[]),
    }
}

#[test]
fn every_failpoint_then_resume_equals_an_uninterrupted_run() {
    let root = tempfile::tempdir().unwrap();
    let reference = root.path().join("reference");
    // An earlier version underneath, so recovery has committed data to preserve.
    let out = octstore(
        &[
            "debug-synthetic",
            reference.to_str().unwrap(),
            "--units",
            "2",
            "--seed",
            "9",
        ],
        &[],
    );
    assert!(out.status.success(), "{}", stderr(&out));
    let out = run(&reference, false, None);
    assert!(out.status.success(), "{}", stderr(&out));
    let expected = fingerprint(&reference);

    for failpoint in FAILPOINTS {
        // Hit the unit-level points at the first, a middle and the last unit.
        let hits: &[u32] = if failpoint.starts_with("stage.") {
            &[1]
        } else {
            &[1, 3, 6]
        };
        for nth in hits {
            let spec = format!("{failpoint}:{nth}");
            let store = root.path().join(spec.replace([':', '.'], "_"));
            let out = octstore(
                &[
                    "debug-synthetic",
                    store.to_str().unwrap(),
                    "--units",
                    "2",
                    "--seed",
                    "9",
                ],
                &[],
            );
            assert!(out.status.success(), "{}", stderr(&out));
            let crashed = run(&store, false, Some(&spec));
            assert!(!crashed.status.success(), "{spec}: the failpoint did not fire");
            assert!(stderr(&crashed).contains("failpoint"), "{spec}: {}", stderr(&crashed));

            let verify = octstore(&["verify", store.to_str().unwrap()], &[]);
            assert!(
                verify.status.success(),
                "{spec}: verify after the crash: {}",
                stderr(&verify)
            );

            let resumed = run(&store, true, None);
            assert!(resumed.status.success(), "{spec}: resume failed: {}", stderr(&resumed));
            let got = fingerprint(&store);
            // After stage.after_finish the run is complete; a resume finds nothing to do.
            assert_same_store(&expected, &got, &spec);
        }
    }
}

/// A full disk in the octree step fails the solve with a clear error, and its scratch files
/// (sorted runs under `STORE/tmp`) go with it instead of staying until the next writable open.
#[test]
fn a_full_disk_in_the_octree_step_leaves_no_scratch_behind() {
    let Some(_) = shared_data("7scenes-redkitchen") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let store = dir.path().join("store");
    let frame = shared_path("7scenes-redkitchen/frame-000000.depth.png");
    let out = octstore(
        &[
            "ingest",
            store.to_str().unwrap(),
            frame.to_str().unwrap(),
            "--max-depth",
            "7",
            "--quiet",
        ],
        &[],
    );
    assert!(out.status.success(), "{}", stderr(&out));
    let out = octstore(
        &["solve", store.to_str().unwrap(), "--until", "octree", "--quiet"],
        &[("OCTSTORE_INJECT_ENOSPC_AFTER", "1")],
    );
    assert!(!out.status.success(), "the octree was written on a full disk");
    assert!(stderr(&out).contains("no storage space"), "{}", stderr(&out));
    assert!(!store.join("tmp").exists(), "scratch left behind");
    let out = octstore(&["solve", store.to_str().unwrap(), "--until", "octree", "--quiet"], &[]);
    assert!(out.status.success(), "{}", stderr(&out));
}
