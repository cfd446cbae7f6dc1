//! SIGKILL a real `octstore` process at random moments of a multi-unit stage; `verify` passes
//! afterwards and a resumed run equals an uninterrupted one, byte for byte.

mod common;

use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

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

/// xorshift: a fixed seed makes the kill moments reproducible from run to run.
fn next(state: &mut u64) -> u64 {
    *state ^= *state << 13;
    *state ^= *state >> 7;
    *state ^= *state << 17;
    *state
}

#[test]
fn sigkill_at_random_moments_then_resume() {
    let root = tempfile::tempdir().unwrap();
    let reference = root.path().join("reference");
    let started = Instant::now();
    let out = Command::new(octstore_bin())
        .args(args(&reference, false))
        .output()
        .unwrap();
    assert!(out.status.success(), "{}", stderr(&out));
    let full_run = started.elapsed();
    let expected = fingerprint(&reference);

    let mut state = 0x2545_F491_4F6C_DD1D_u64;
    let mut killed_mid_run = 0;
    for trial in 0..TRIALS {
        let store = root.path().join(format!("trial-{trial}"));
        // Kill anywhere from process start to a little past the expected end.
        let delay = Duration::from_micros(next(&mut state) % (full_run.as_micros() as u64 * 11 / 10 + 1));
        let mut child = Command::new(octstore_bin())
            .args(args(&store, false))
            .env("OCTSTORE_LOG", "warn")
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap();
        std::thread::sleep(delay);
        child.kill().unwrap(); // SIGKILL on Unix
        let status = child.wait().unwrap();
        if !status.success() {
            killed_mid_run += 1;
        }
        if store.join("catalog.redb").exists() {
            let verify = octstore(&["verify", store.to_str().unwrap()], &[]);
            assert!(
                verify.status.success(),
                "trial {trial}: verify after kill at {delay:?}: {}",
                stderr(&verify)
            );
        }
        let resumed = Command::new(octstore_bin()).args(args(&store, true)).output().unwrap();
        assert!(resumed.status.success(), "trial {trial}: resume: {}", stderr(&resumed));
        assert_same_store(
            &expected,
            &fingerprint(&store),
            &format!("trial {trial}, killed after {delay:?}"),
        );
    }
    assert!(
        killed_mid_run >= TRIALS / 2,
        "only {killed_mid_run} of {TRIALS} kills landed mid-run"
    );
}
