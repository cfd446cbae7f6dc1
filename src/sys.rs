//! The only module with `unsafe` code: memory-mapping immutable segment files, and asking the C
//! allocator to return freed memory.

use std::fs::File;

use memmap2::Mmap;

/// Maps a whole segment file read-only.
///
/// Callers hand the bytes to the segment decoder, which validates everything before use.
pub fn map_segment(file: &File) -> std::io::Result<Mmap> {
    // SAFETY: segment files are immutable once renamed into place (format-spec.md, "Commit
    // protocol"): octstore never opens them for writing again, and `gc` only unlinks them, which
    // leaves existing mappings intact on POSIX systems. A foreign process truncating the file
    // would violate this contract; that is outside what any mmap-based reader can defend against.
    unsafe { Mmap::map(file) }
}

/// Hands memory that the C allocator holds free back to the operating system.
pub fn return_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: malloc_trim only walks the allocator's own free lists under its locks; it takes
    // no pointers from us and is safe to call from any thread at any time.
    unsafe {
        libc::malloc_trim(0);
    }
}

/// Lets a closed pipe end the process quietly, as it ends other command-line tools:
/// `octstore info STORE | head -1` otherwise panicked in `println!` once `head` had exited
/// (Rust ignores SIGPIPE, so every write after that fails with EPIPE). Only the binary calls it,
/// first thing; a library user keeps its own handling.
pub fn die_quietly_on_closed_pipe() {
    #[cfg(unix)]
    // SAFETY: called at the start of `main`, before any other thread exists; restoring the
    // default disposition of SIGPIPE installs no handler and touches no memory of ours.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}
