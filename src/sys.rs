//! The only module with `unsafe` code: memory-mapping immutable segment files, asking the C
//! allocator to return freed memory, calling code compiled for AVX2 once the processor has
//! it, and the histogram votes' AVX-512 gathers of depth pixels. (The votes' other vector code
//! comes from `fearless_simd`, whose tokens prove the processor's features, so it needs no
//! `unsafe` here.)

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

/// mimalloc's option index of `mi_option_purge_delay` (mimalloc.h, enum `mi_option_e`: the
/// same in its v2 and v3). The crate's bindings do not name it; a unit test reads its default.
const MI_OPTION_PURGE_DELAY: libmimalloc_sys::mi_option_t = 15;

/// Makes mimalloc hand pages that its heaps no longer use back to the operating system at once,
/// instead of a second later (the default of the mimalloc v3 that libmimalloc-sys builds). The
/// stages free and allocate buffers of a few megabytes per depth map or unit, many of them on
/// worker threads; until the delay passes, every freed page stays resident, so the peak resident
/// size counted about a second's worth of buffers that no stage held any more. Measured figures
/// are in CHANGELOG.md. The price is kernel time spent faulting pages back in (RedKitchen's
/// solve about a quarter slower), so the binary calls it only for the verbs that extract
/// (`cli::Command::extracts`), whose stage runs nearest the budget at scale, right after
/// parsing the command line and before any other thread exists, where mimalloc is the global
/// allocator. `MIMALLOC_PURGE_DELAY` in the environment, when set, decides instead.
pub fn purge_freed_pages_at_once() {
    if std::env::var_os("MIMALLOC_PURGE_DELAY").is_none() {
        // SAFETY: mi_option_set stores a value in mimalloc's option table; it takes no
        // pointers. It is called at the start of `main`, before any other thread exists, so no
        // allocation reads the option while it changes.
        unsafe { libmimalloc_sys::mi_option_set(MI_OPTION_PURGE_DELAY, 0) }
    }
}

/// Reads mimalloc's purge delay in milliseconds (see [`purge_freed_pages_at_once`]).
#[cfg(test)]
fn purge_delay_ms() -> std::ffi::c_long {
    // SAFETY: mi_option_get reads mimalloc's option table (reading the environment the first
    // time); it takes no pointers.
    unsafe { libmimalloc_sys::mi_option_get(MI_OPTION_PURGE_DELAY) }
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

/// Sets each environment variable of `defaults` that is not set already. Only the binary
/// calls it, as the first statement of `main` (before any other thread exists: setting the
/// environment while another thread reads it is undefined behaviour on most platforms).
pub fn set_env_defaults_at_start(defaults: &[(&str, &str)]) {
    for (name, value) in defaults {
        if std::env::var_os(name).is_none() {
            // SAFETY: called at the start of `main`, before any other thread exists, so nothing
            // can read or write the environment concurrently.
            unsafe { std::env::set_var(name, value) };
        }
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

/// The pyramid levels of one depth map, addressed for AVX-512 gathers from the first level's
/// start: each level's start as a byte offset from it (the levels are separate allocations,
/// which may lie anywhere: 64-bit offsets reach them all), and its length. Made where the
/// pyramid has at most [`GATHER_LEVELS`] levels ([`LevelGather::new`]).
#[cfg(target_arch = "x86_64")]
pub struct LevelGather<'a> {
    /// The first level, from whose start the others are addressed.
    base: &'a [f32],
    starts: [i64; GATHER_LEVELS],
    /// Each level's length in pixels, for the 32 levels a lane may name (0 past the top).
    lengths: [i32; 32],
}

/// Levels a [`LevelGather`] addresses: a pyramid of 2^15 pixels a side or less (its top level
/// is level 15 at most).
#[cfg(target_arch = "x86_64")]
pub const GATHER_LEVELS: usize = 16;

#[cfg(target_arch = "x86_64")]
impl<'a> LevelGather<'a> {
    /// The levels (empty ones past the pyramid's top), or `None` where a level past the first
    /// [`GATHER_LEVELS`] holds pixels or a level holds 2^31 pixels or more.
    pub fn new(levels: &[&'a [f32]; 32]) -> Option<LevelGather<'a>> {
        let base = *levels.first()?;
        let mut gather = LevelGather {
            base,
            starts: [0; GATHER_LEVELS],
            lengths: [0; 32],
        };
        for (index, (level, length)) in levels.iter().zip(&mut gather.lengths).enumerate() {
            if level.is_empty() {
                continue;
            }
            *length = i32::try_from(level.len()).ok()?;
            let start = gather.starts.get_mut(index)?;
            // A distance between two allocations, in bytes: an integer, never dereferenced.
            *start = (level.as_ptr() as i64).wrapping_sub(base.as_ptr() as i64);
        }
        Some(gather)
    }

    /// For sixteen lanes, the depths of the 2 x 2 square at pixel `at` of level `level` (a row
    /// `stride` pixels long): pixels `at`, `at + 1`, `at + stride`, `at + stride + 1`, where
    /// the level holds them all (`0 <= at` and `at + stride + 1 <` its length, as a slice's
    /// `get(at..at + stride + 2)` holds them); the second value has bit `lane` set there, and
    /// the other lanes' depths are NaN. `level` is taken modulo 32. `token` proves the
    /// processor has AVX-512.
    #[inline(always)]
    pub fn squares(
        &self,
        token: fearless_simd::Avx512,
        level: fearless_simd::i32x16<fearless_simd::Avx512>,
        at: fearless_simd::i32x16<fearless_simd::Avx512>,
        stride: fearless_simd::i32x16<fearless_simd::Avx512>,
    ) -> ([fearless_simd::f32x16<fearless_simd::Avx512>; 4], u16) {
        use fearless_simd::SimdFrom;
        // SAFETY: the token exists only where the processor has the AVX-512 features
        // (`fearless_simd`'s tokens are made by its run-time detection or by code that already
        // has them), among which `squares_avx512` needs only AVX-512F.
        let (square, inside) = unsafe { self.squares_avx512(level.into(), at.into(), stride.into()) };
        (
            square.map(|depths| fearless_simd::f32x16::simd_from(token, depths)),
            inside,
        )
    }

    #[inline]
    #[target_feature(enable = "avx512f")]
    fn squares_avx512(
        &self,
        level: std::arch::x86_64::__m512i,
        at: std::arch::x86_64::__m512i,
        stride: std::arch::x86_64::__m512i,
    ) -> ([std::arch::x86_64::__m512; 4], u16) {
        use std::arch::x86_64::*;
        // A 128-byte table as two vectors (the 32 lengths, the 16 starts).
        let halves = |table: &[u8; 128]| {
            let (low, high) = table.split_at(64);
            // SAFETY: each half is 64 bytes, what an unaligned load reads.
            unsafe {
                (
                    _mm512_loadu_si512(low.as_ptr().cast()),
                    _mm512_loadu_si512(high.as_ptr().cast()),
                )
            }
        };
        let (lengths_low, lengths_high) = halves(bytemuck::cast_ref(&self.lengths));
        // The lane's level's length, as the low five bits of `level` pick it from the 32.
        let length = _mm512_permutex2var_epi32(lengths_low, level, lengths_high);
        let zero = _mm512_setzero_si512();
        let below = _mm512_add_epi32(at, stride);
        let last = _mm512_add_epi32(below, _mm512_set1_epi32(1));
        // `last > at` rules out a sum that wrapped. A level past the first `GATHER_LEVELS`
        // has length 0 (`LevelGather::new`), so every lane inside names one of those.
        let inside = _mm512_cmpge_epi32_mask(at, zero)
            & _mm512_cmpge_epi32_mask(stride, zero)
            & _mm512_cmpgt_epi32_mask(last, at)
            & _mm512_cmplt_epi32_mask(last, length);
        let (starts_low, starts_high) = halves(bytemuck::cast_ref(&self.starts));
        let nan = _mm512_castps_si512(_mm512_set1_ps(f32::NAN));
        let base: *const i64 = self.base.as_ptr().cast();
        // The pixel pairs at `first` (pixel and the next) of eight lanes: `half` 0 for lanes
        // 0-7, 1 for lanes 8-15.
        let pairs = |first: __m512i, half: u32| {
            let (levels, pixels, mask) = if half == 0 {
                (
                    _mm512_castsi512_si256(level),
                    _mm512_castsi512_si256(first),
                    inside as u8,
                )
            } else {
                (
                    _mm512_extracti64x4_epi64::<1>(level),
                    _mm512_extracti64x4_epi64::<1>(first),
                    (inside >> 8) as u8,
                )
            };
            let start = _mm512_permutex2var_epi64(starts_low, _mm512_cvtepi32_epi64(levels), starts_high);
            let offset = _mm512_add_epi64(start, _mm512_slli_epi64::<2>(_mm512_cvtepi32_epi64(pixels)));
            // SAFETY: the gather reads 8 bytes at each lane of `mask` (lanes of `inside`): the
            // pixel `first` and the next of the lane's level, whose start lies `start` bytes
            // from `base` (`LevelGather::new`; a level below `GATHER_LEVELS`, picked by the
            // low four bits of its index). Both pixels are in that level: `0 <= at`, `at + 1 <=
            // at + stride + 1 < length` (`stride >= 0`, no sum wrapped), and the borrow of the
            // levels keeps them alive. The other lanes read nothing and keep `nan`.
            unsafe { _mm512_mask_i64gather_epi64::<1>(nan, mask, offset, base) }
        };
        let even = _mm512_set_epi32(30, 28, 26, 24, 22, 20, 18, 16, 14, 12, 10, 8, 6, 4, 2, 0);
        let odd = _mm512_set_epi32(31, 29, 27, 25, 23, 21, 19, 17, 15, 13, 11, 9, 7, 5, 3, 1);
        // Each row's sixteen pairs, split into the left pixels and the right ones.
        let row = |first: __m512i| {
            let (low, high) = (
                _mm512_castsi512_ps(pairs(first, 0)),
                _mm512_castsi512_ps(pairs(first, 1)),
            );
            (
                _mm512_permutex2var_ps(low, even, high),
                _mm512_permutex2var_ps(low, odd, high),
            )
        };
        let ((d00, d10), (d01, d11)) = (row(at), row(below));
        ([d00, d10, d01, d11], inside)
    }
}

#[cfg(all(test, target_arch = "x86_64"))]
#[expect(clippy::indexing_slicing, reason = "tests")]
mod tests {
    use fearless_simd::{SimdFrom, i32x16};

    use super::{LevelGather, purge_delay_ms, purge_freed_pages_at_once};

    #[test]
    fn the_purge_delay_option_is_the_one_mimalloc_reads() {
        // The default of the mimalloc v3 that libmimalloc-sys builds is 1000 ms: reading it
        // through the index proves the index names that option (its neighbours,
        // eager_commit_delay and use_numa_nodes, default to 1 and 0), unless the environment
        // set it.
        if std::env::var_os("MIMALLOC_PURGE_DELAY").is_none() {
            assert_eq!(purge_delay_ms(), 1000);
        }
        purge_freed_pages_at_once();
        if std::env::var_os("MIMALLOC_PURGE_DELAY").is_none() {
            assert_eq!(purge_delay_ms(), 0);
        }
    }

    #[test]
    fn gathered_squares_are_the_level_s_pixels_and_only_where_the_level_holds_them() {
        // Levels of odd sizes down to one pixel, as a pyramid halves them; empty past the top.
        let sizes = [(37usize, 23usize), (19, 12), (10, 6), (5, 3), (3, 2), (2, 1), (1, 1)];
        let levels: Vec<Vec<f32>> = sizes
            .iter()
            .enumerate()
            .map(|(l, (w, h))| (0..w * h).map(|i| (l * 1000 + i) as f32).collect())
            .collect();
        let mut slices: [&[f32]; 32] = [&[]; 32];
        for (slice, level) in slices.iter_mut().zip(&levels) {
            *slice = level;
        }
        let gather = LevelGather::new(&slices).expect("seven levels");
        let Some(token) = fearless_simd::Level::new().as_avx512() else {
            // Nothing to gather with here; the votes' tests still check the reads lane by lane.
            return;
        };
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = move |range: i64| {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state % range as u64) as i64
        };
        let (mut read, mut refused) = (0, 0);
        for _ in 0..20_000 {
            // Levels past the top, pixels before, inside and past each level's end, strides
            // of the level's width, other widths, negative, and sums that wrap past i32::MAX.
            let level: [i32; 16] = std::array::from_fn(|_| next(10) as i32);
            let at: [i32; 16] = std::array::from_fn(|lane| match next(8) {
                0 => -(next(5) as i32) - 1,
                1 => i32::MAX - next(3) as i32,
                _ => next(slices[level[lane] as usize].len() as i64 + 3) as i32,
            });
            let stride: [i32; 16] = std::array::from_fn(|lane| match next(6) {
                0 => -1,
                1 => next(40) as i32,
                2 => i32::MAX,
                _ => sizes.get(level[lane] as usize).map_or(7, |(w, _)| *w as i32),
            });
            let lanes = |values: [i32; 16]| i32x16::simd_from(token, values);
            let (square, inside) = gather.squares(token, lanes(level), lanes(at), lanes(stride));
            let square: [[f32; 16]; 4] = square.map(Into::into);
            for lane in 0..16 {
                let pixels = slices[level[lane] as usize];
                let (a, s) = (i64::from(at[lane]), i64::from(stride[lane]));
                let whole = a >= 0 && s >= 0 && a + s + 1 < pixels.len() as i64;
                assert_eq!(
                    inside & (1 << lane) != 0,
                    whole,
                    "level {} at {a} stride {s}",
                    level[lane]
                );
                let got = [0, 1, 2, 3].map(|corner| square[corner][lane]);
                if whole {
                    let (a, s) = (a as usize, s as usize);
                    assert_eq!(got, [pixels[a], pixels[a + 1], pixels[a + s], pixels[a + s + 1]]);
                    read += 1;
                } else {
                    assert!(got.iter().all(|depth| depth.is_nan()));
                    refused += 1;
                }
            }
        }
        assert!(
            read > 40_000 && refused > 40_000,
            "{read} squares read, {refused} refused"
        );
    }
}
