//! Reader pins: a read-only snapshot holds a shared lock on a file in `STORE/pins/` naming its
//! version, and `gc` keeps every version a live pin names (format-spec.md, "Reader pins").
//!
//! Invariants: a pin is taken after the snapshot's catalog read and the horizon is read again
//! after it, so a reader either holds a pin `gc` sees or learns that its version is gone; a pin
//! file whose lock can be taken belongs to a process that died and is removed by `gc`.

use std::fs::{self, File, TryLockError};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// The folder of reader pins inside a store.
pub const PINS_DIR: &str = "pins";

const PIN_SUFFIX: &str = ".pin";

/// Distinguishes the pins of one process.
static NEXT_PIN: AtomicU64 = AtomicU64::new(0);

/// A held pin: its file is locked (shared) while this lives, and removed on drop.
#[derive(Debug)]
pub struct ReaderPin {
    path: PathBuf,
    _file: File,
}

impl Drop for ReaderPin {
    fn drop(&mut self) {
        // Closing the file releases the lock; a file left behind is removed by the next gc.
        let _ = fs::remove_file(&self.path);
        // The folder goes with the last pin (removing a folder that still holds pins fails),
        // so that reading a store leaves its files as they were; `pin` makes it again.
        if let Some(dir) = self.path.parent() {
            let _ = fs::remove_dir(dir);
        }
    }
}

/// How many times [`pin`] makes the folder and its file, where a reader dropping the last pin
/// removed the folder in between.
const PIN_ATTEMPTS: usize = 3;

/// Pins `version` of the store at `root`. `None` where no pin can be written (a read-only
/// file system): the reader then runs unprotected, and learns from a failed segment open
/// that gc collected its version.
pub fn pin(root: &Path, version: u64) -> Option<ReaderPin> {
    let dir = root.join(PINS_DIR);
    let name = format!(
        "v{version:020}-p{}-{}{PIN_SUFFIX}",
        std::process::id(),
        NEXT_PIN.fetch_add(1, Ordering::Relaxed)
    );
    let path = dir.join(name);
    let file = (0..PIN_ATTEMPTS).find_map(|_| {
        fs::create_dir_all(&dir).ok()?;
        File::create(&path).ok()
    })?;
    if file.lock_shared().is_err() {
        let _ = fs::remove_file(&path);
        return None;
    }
    Some(ReaderPin { path, _file: file })
}

fn version_of(name: &str) -> Option<u64> {
    let digits = name.strip_prefix('v')?.get(..20)?;
    digits.parse().ok()
}

/// The versions live readers pin, oldest first; pin files of dead readers are removed.
pub fn live_pinned_versions(root: &Path) -> std::io::Result<Vec<u64>> {
    let dir = root.join(PINS_DIR);
    let entries = match fs::read_dir(&dir) {
        Ok(entries) => entries,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(e),
    };
    let mut versions = Vec::new();
    for entry in entries {
        let entry = entry?;
        let name = entry.file_name().to_string_lossy().into_owned();
        let Some(version) = version_of(&name).filter(|_| name.ends_with(PIN_SUFFIX)) else {
            continue;
        };
        let file = match File::open(entry.path()) {
            Ok(file) => file,
            // Its reader finished between the listing and the open.
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => continue,
            Err(e) => return Err(e),
        };
        match file.try_lock() {
            Err(TryLockError::WouldBlock) => versions.push(version),
            Err(TryLockError::Error(e)) => return Err(e),
            Ok(()) => {
                drop(file);
                let _ = fs::remove_file(entry.path());
            }
        }
    }
    versions.sort_unstable();
    versions.dedup();
    Ok(versions)
}

#[cfg(test)]
#[expect(clippy::unwrap_used, reason = "tests: a panic is the failure report")]
mod tests {
    use super::*;

    #[test]
    fn live_pins_keep_their_versions_and_dead_ones_are_swept() {
        let dir = tempfile::tempdir().unwrap();
        let a = pin(dir.path(), 3).unwrap();
        let b = pin(dir.path(), 7).unwrap();
        // A pin file nobody holds: its process died.
        std::fs::write(dir.path().join(PINS_DIR).join("v00000000000000000001-p1-0.pin"), b"").unwrap();
        assert_eq!(live_pinned_versions(dir.path()).unwrap(), vec![3, 7]);
        assert!(
            !dir.path()
                .join(PINS_DIR)
                .join("v00000000000000000001-p1-0.pin")
                .exists()
        );
        drop(a);
        assert_eq!(live_pinned_versions(dir.path()).unwrap(), vec![7]);
        drop(b);
        assert!(live_pinned_versions(dir.path()).unwrap().is_empty());
        // The last pin took the folder with it: reading a store leaves no trace.
        assert!(!dir.path().join(PINS_DIR).exists());
        let c = pin(dir.path(), 9).unwrap();
        assert_eq!(live_pinned_versions(dir.path()).unwrap(), vec![9]);
        drop(c);
        assert!(!dir.path().join(PINS_DIR).exists());
    }
}
