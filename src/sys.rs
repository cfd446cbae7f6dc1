//! The only module with `unsafe` code: memory-mapping immutable segment files, asking the C
//! allocator to return freed memory, and calling code compiled for AVX2 once the processor has
//! it. (The histogram votes' vectors come from `fearless_simd`, whose tokens prove the
//! processor's features, so their code needs no `unsafe` here.)

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

/// Work for [`with_wide_vectors`]: a hot loop and what it reads.
pub trait WideWork {
    /// What the work gives.
    type Output;

    /// Does the work. Implementations mark it `#[inline(always)]`: only code inlined into
    /// [`with_wide_vectors`]'s AVX2 function gets AVX2. (A closure or a function item is
    /// called through a shim of its own, which the compiler may leave out of line, compiled
    /// for the baseline.)
    fn run(self) -> Self::Output;
}

/// Runs `work` compiled for AVX2 where the processor has it, else as compiled for the
/// baseline (SSE2 on x86-64; every other architecture runs `work` as it is). The per-point
/// loops that `work` inlines then run eight 32-bit lanes at a time, with the 32-bit integer
/// multiplies that SSE2 lacks and emulates.
///
/// Results are bit for bit those of the baseline: AVX2 adds integer and IEEE float
/// instructions of the same results, and fused multiply-adds, which round differently, stay
/// off (they are a separate feature).
#[inline(always)]
pub fn with_wide_vectors<W: WideWork>(work: W) -> W::Output {
    #[cfg(target_arch = "x86_64")]
    {
        #[target_feature(enable = "avx2")]
        fn wide<W: WideWork>(work: W) -> W::Output {
            work.run()
        }
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: `wide` needs only AVX2, and the processor was just found to have it.
            return unsafe { wide(work) };
        }
    }
    work.run()
}
