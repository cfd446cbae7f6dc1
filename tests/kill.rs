//! SIGKILL a real `octstore` process at random moments of a multi-unit stage; `verify` passes
//! afterwards and a resumed run equals an uninterrupted one, byte for byte.

mod common;

use common::*;

const TRIALS: u64 = 20;

fn args(store: &std::path::Path, resume: bool) -> Vec<String> {
    let mut args: Vec<String> = [
        "debug-synthetic",
        store.to_str().unwrap(),
        "--units",
        "10",
        "--rows",
        "3000",
        "--threads",
        "2",
        "--delay-ms",
        "15",
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
fn sigkill_at_random_moments_then_resume() {
    let root = tempfile::tempdir().unwrap();
    KillTrials {
        root: root.path(),
        trials: TRIALS,
        seed: 0x2545_F491_4F6C_DD1D,
        // From process start to a little past the expected end.
        window_percent: 110,
        prepare: &|_| {},
        args: &args,
    }
    .run();
}
