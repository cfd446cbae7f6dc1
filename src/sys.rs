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
