//! Helpers shared by the integration tests.
#![allow(dead_code, reason = "each test binary uses a different subset")]

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use octstore::Store;

pub fn octstore_bin() -> PathBuf {
    PathBuf::from(env!("CARGO_BIN_EXE_octstore"))
}

/// Runs the CLI with the given arguments and extra environment.
pub fn octstore(args: &[&str], env: &[(&str, &str)]) -> Output {
    let mut cmd = Command::new(octstore_bin());
    cmd.args(args)
        .env("OCTSTORE_LOG", "warn")
        .env_remove("OCTSTORE_FAILPOINT");
    for (k, v) in env {
        cmd.env(k, v);
    }
    cmd.output().expect("run octstore")
}

pub fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

pub fn stdout(out: &Output) -> String {
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// Everything that defines a store's content: the canonical catalog dump and the bytes of every
/// segment file, by name.
#[derive(PartialEq, Eq, Debug)]
pub struct Fingerprint {
    pub catalog: Vec<u8>,
    pub segments: BTreeMap<String, Vec<u8>>,
}

pub fn fingerprint(path: &Path) -> Fingerprint {
    let store = Store::open(path).expect("open store");
    let catalog = store.canonical_dump().expect("dump catalog");
    let mut segments = BTreeMap::new();
    for entry in std::fs::read_dir(path.join("segments")).expect("list segments") {
        let entry = entry.unwrap();
        segments.insert(
            entry.file_name().to_string_lossy().into_owned(),
            std::fs::read(entry.path()).unwrap(),
        );
    }
    Fingerprint { catalog, segments }
}

/// Asserts equality without printing megabytes of bytes on failure.
pub fn assert_same_store(a: &Fingerprint, b: &Fingerprint, context: &str) {
    assert_eq!(
        a.segments.keys().collect::<Vec<_>>(),
        b.segments.keys().collect::<Vec<_>>(),
        "{context}: different segment files"
    );
    for (name, bytes) in &a.segments {
        assert!(bytes == &b.segments[name], "{context}: segment {name} differs");
    }
    assert!(a.catalog == b.catalog, "{context}: catalog content differs");
}
