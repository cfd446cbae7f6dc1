//! SIGKILL `octstore solve` (TGV, and SSD with its samples stage) at random moments of the
//! histogram and level phases: `verify` passes afterwards and `solve --resume` ends byte-identical to an uninterrupted run.

mod common;

use common::*;
use glam::DVec3;
use octstore::testing::quality::synthetic_scenes::{SceneSpec, Shape};

/// Kills of the TGV run, each at a random moment of it (fixed seed), spread over the histogram
/// stage and the levels; fewer than the 20 of `tests/kill.rs` because each trial also resumes a
/// whole solve, and CI has 30 minutes.
const TRIALS: u64 = 12;

fn solve_args(store: &std::path::Path, resume: bool) -> Vec<String> {
    let mut args: Vec<String> = [
        "solve",
        store.to_str().unwrap(),
        "--leaf-cubes",
        "300",
        "--iterations",
        "30",
        "--threads",
        "2",
        "--quiet",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    if resume {
        args.push("--resume".into());
    }
    args
}

#[test]
fn sigkill_during_histograms_and_solve_then_resume() {
    kill_trials_of(TRIALS, &solve_args);
}

/// `solve --method ssd` adds the samples stage and its own levels: the same guarantee.
#[test]
fn sigkill_during_the_ssd_solve_then_resume() {
    let ssd_args = |store: &std::path::Path, resume: bool| {
        let mut args = solve_args(store, resume);
        args.extend(["--method".to_string(), "ssd".to_string()]);
        args
    };
    kill_trials_of(6, &ssd_args);
}

fn kill_trials_of(trials: u64, args: &dyn Fn(&std::path::Path, bool) -> Vec<String>) {
    let root = tempfile::tempdir().unwrap();
    let center = DVec3::new(0.0, 0.0, 0.2);
    let spec = SceneSpec {
        shapes: vec![Shape::Sphere { center, radius: 0.4 }],
        cameras: 8,
        distance: 2.0,
        target: center,
        width: 40,
        height: 30,
        fov_degrees: 45.0,
        noise: None,
        room: Some(2.4),
    };
    let manifest = spec.write(&root.path().join("input")).unwrap();
    let ingested = root.path().join("ingested");
    let out = octstore(
        &[
            "ingest",
            ingested.to_str().unwrap(),
            manifest.to_str().unwrap(),
            "--max-depth",
            "6",
            "--sample-sums",
            "--quiet",
        ],
        &[],
    );
    assert!(out.status.success(), "{}", stderr(&out));
    let copy = |to: &std::path::Path| {
        std::fs::create_dir_all(to.join("segments")).unwrap();
        std::fs::copy(ingested.join("catalog.redb"), to.join("catalog.redb")).unwrap();
        for e in std::fs::read_dir(ingested.join("segments")).unwrap() {
            let e = e.unwrap();
            std::fs::copy(e.path(), to.join("segments").join(e.file_name())).unwrap();
        }
    };
    KillTrials {
        root: root.path(),
        trials,
        seed: 0x9E37_79B9_7F4A_7C15,
        window_percent: 100,
        prepare: &copy,
        args,
    }
    .run();
}

/// A first solve that crashed after some of its levels leaves a store whose finest solved level
/// is a complete, coarser solution: `extract` and `query` read it and say so, `info` names the
/// level reached and the octree's, and `solve --resume` finishes the rest.
#[test]
fn a_solve_stopped_part_way_is_named_by_every_reader() {
    let root = tempfile::tempdir().unwrap();
    let center = DVec3::new(0.0, 0.0, 0.2);
    let spec = SceneSpec {
        shapes: vec![Shape::Sphere { center, radius: 0.4 }],
        cameras: 6,
        distance: 2.0,
        target: center,
        width: 40,
        height: 30,
        fov_degrees: 45.0,
        noise: None,
        room: None,
    };
    let manifest = spec.write(&root.path().join("input")).unwrap();
    let store = root.path().join("store");
    let s = store.to_str().unwrap();
    let out = octstore(&["ingest", s, manifest.to_str().unwrap(), "--max-depth", "6"], &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    // The octree, the histograms and levels 0 to 2 finish; the process dies after the fifth.
    // TGV by name: the default would take this sphere against empty background for an object
    // and solve it by SSD, whose sample stages come first.
    let out = octstore(
        &["solve", s, "--method", "tgv"],
        &[("OCTSTORE_FAILPOINT", "stage.after_finish:5")],
    );
    assert!(!out.status.success(), "the failpoint did not stop the solve");
    let mesh = root.path().join("mesh.ply");
    let out = octstore(&["extract", s, "-o", mesh.to_str().unwrap()], &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    let said = stderr(&out);
    assert!(
        said.contains("reaches level 2 of the octree's ") && said.contains("solve --resume"),
        "{said}"
    );
    let out = octstore(&["info", s], &[]);
    assert!(stdout(&out).contains("a solve stopped part way"), "{}", stdout(&out));
    let out = octstore(&["query", s, "--point", "0,0,0.2"], &[]);
    assert!(stderr(&out).contains("solve --resume"), "{}", stderr(&out));

    let out = octstore(&["solve", s, "--resume", "--method", "tgv"], &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    let out = octstore(&["extract", s, "-o", mesh.to_str().unwrap()], &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(!stderr(&out).contains("part way"), "{}", stderr(&out));
    assert!(!stdout(&octstore(&["info", s], &[])).contains("part way"));

    // Outputs: a symbolic link stays a link and its target gets the mesh; a FIFO is refused
    // and stays a FIFO (both used to become regular files).
    let link = root.path().join("link.ply");
    std::os::unix::fs::symlink("mesh.ply", &link).unwrap();
    std::fs::write(&mesh, b"old").unwrap();
    let out = octstore(&["extract", s, "-o", link.to_str().unwrap()], &[]);
    assert!(out.status.success(), "{}", stderr(&out));
    assert!(std::fs::symlink_metadata(&link).unwrap().file_type().is_symlink());
    assert!(std::fs::read(&mesh).unwrap().starts_with(b"ply\n"));
    let fifo = root.path().join("fifo.ply");
    assert!(
        std::process::Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .unwrap()
            .success()
    );
    let out = octstore(&["extract", s, "-o", fifo.to_str().unwrap()], &[]);
    assert!(!out.status.success());
    assert!(stderr(&out).contains("not a regular file"), "{}", stderr(&out));
    use std::os::unix::fs::FileTypeExt;
    assert!(std::fs::symlink_metadata(&fifo).unwrap().file_type().is_fifo());
}
