//! SIGKILL `octstore solve` (TGV, and SSD with its samples stage) at random moments of the
//! histogram and level phases: `verify` passes afterwards and `solve --resume` ends byte-identical to an uninterrupted run.

mod common;

use common::*;
use glam::DVec3;
use octstore::quality::synthetic_scenes::{SceneSpec, Shape};

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
