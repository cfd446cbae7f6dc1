//! Crash injection for the commit protocol and fault injection for the storage layer.
//!
//! `OCTSTORE_FAILPOINT=name[:nth]` aborts the process (no destructors, no flushes: a crash) the
//! nth time (default 1st) execution reaches the named point. `OCTSTORE_INJECT_ENOSPC_AFTER=BYTES`
//! makes segment writes fail with "no space left on device" once that many bytes were written by
//! this process; `OCTSTORE_INJECT_FSYNC_ERROR=1` makes every segment fsync fail.

// Private to the crate; `octstore::testing` re-exports it for the tests, undocumented there.
#![cfg_attr(feature = "testing", allow(missing_docs))]

use std::sync::OnceLock;
use std::sync::atomic::{AtomicU64, Ordering};

/// Every failpoint, in the order the commit protocol reaches them (the failpoint tests walk
/// this list; the code names each where it is reached).
#[cfg_attr(
    not(feature = "testing"),
    allow(dead_code, reason = "read by the failpoint tests only")
)]
pub const FAILPOINTS: &[&str] = &[
    "segment.after_write",
    "segment.after_fsync",
    "segment.after_rename",
    "segment.after_dir_fsync",
    "unit.after_commit",
    "stage.before_finish",
    "stage.after_finish",
];

struct Armed {
    name: String,
    nth: u64,
    hits: AtomicU64,
}

fn armed() -> &'static Option<Armed> {
    static ARMED: OnceLock<Option<Armed>> = OnceLock::new();
    ARMED.get_or_init(|| {
        let spec = std::env::var("OCTSTORE_FAILPOINT").ok()?;
        let (name, nth) = match spec.split_once(':') {
            Some((name, nth)) => (name.to_string(), nth.parse().unwrap_or(1)),
            None => (spec, 1),
        };
        Some(Armed {
            name,
            nth: nth.max(1),
            hits: AtomicU64::new(0),
        })
    })
}

/// Aborts the process here if this failpoint is armed and this is its nth hit.
pub fn hit(name: &str) {
    if let Some(armed) = armed()
        && armed.name == name
        && armed.hits.fetch_add(1, Ordering::SeqCst) + 1 == armed.nth
    {
        eprintln!("octstore: failpoint {name} reached, aborting");
        std::process::abort();
    }
}

/// Storage faults to inject, read from the environment at store open or set by tests.
#[derive(Debug, Default)]
pub struct IoFaults {
    /// Segment writes fail with ENOSPC after this many bytes in total.
    pub enospc_after_bytes: Option<u64>,
    /// Every segment fsync fails.
    pub fsync_error: bool,
    pub(crate) written: AtomicU64,
}

impl IoFaults {
    /// The faults the environment asks for: `OCTSTORE_INJECT_ENOSPC_AFTER=BYTES` and
    /// `OCTSTORE_INJECT_FSYNC_ERROR=1` (tests of the commit protocol set them).
    pub fn from_env() -> IoFaults {
        IoFaults {
            enospc_after_bytes: std::env::var("OCTSTORE_INJECT_ENOSPC_AFTER")
                .ok()
                .and_then(|v| v.parse().ok()),
            fsync_error: std::env::var("OCTSTORE_INJECT_FSYNC_ERROR").is_ok_and(|v| v == "1"),
            written: AtomicU64::new(0),
        }
    }

    /// No fault: writes and fsyncs go through.
    pub fn none() -> IoFaults {
        IoFaults::default()
    }

    /// Segment writes fail like a full disk once `bytes` were written.
    pub fn disk_full_after(bytes: u64) -> IoFaults {
        IoFaults {
            enospc_after_bytes: Some(bytes),
            ..IoFaults::default()
        }
    }

    /// Every segment fsync fails.
    pub fn failing_fsync() -> IoFaults {
        IoFaults {
            fsync_error: true,
            ..IoFaults::default()
        }
    }

    /// Accounts for `len` more bytes and fails like a full disk once the budget is spent.
    pub(crate) fn before_write(&self, len: usize) -> std::io::Result<()> {
        if let Some(limit) = self.enospc_after_bytes {
            let before = self.written.fetch_add(len as u64, Ordering::SeqCst);
            if before + len as u64 > limit {
                return Err(std::io::Error::from(std::io::ErrorKind::StorageFull));
            }
        }
        Ok(())
    }

    pub(crate) fn before_fsync(&self) -> std::io::Result<()> {
        if self.fsync_error {
            return Err(std::io::Error::other("injected fsync failure"));
        }
        Ok(())
    }
}
