//! A point cloud generated on the fly, for benchmarks of `divide` at sizes no disk here holds:
//! a rolling terrain 1000 units square whose density falls off along x (a hundredfold from one
//! side to the other), as a photogrammetric cloud's does with the distance to the cameras. Point
//! `i` depends only on `i` and the seed, so every pass sees the same cloud.

use rayon::prelude::*;

use super::PointLayout;
use super::{PointSource, Result};
use crate::format::ply_header::PlyScalar;
use crate::sys::WideWork;

/// `points` generated points of float x, y, z.
pub struct SyntheticCloud {
    points: u64,
    seed: u64,
    layout: PointLayout,
}

impl SyntheticCloud {
    /// A cloud of `points` points; different seeds give different clouds.
    pub fn new(points: u64, seed: u64) -> SyntheticCloud {
        let properties = ["x", "y", "z"].map(|n| (n.to_string(), PlyScalar::F32)).into();
        SyntheticCloud {
            points,
            seed,
            // Three distinct float properties always make a layout.
            layout: PointLayout::new(properties).unwrap_or_else(|_| unreachable!()),
        }
    }

    /// The part of point `i`'s hash input that its high 32 bits and the seed give: the same
    /// for every point of a run of 2^32, so a block computes it once per run.
    fn salt(&self, high: u32) -> u32 {
        let seed = self.seed;
        lowbias32(high ^ seed as u32) ^ (seed >> 32) as u32
    }

    /// Point `i`, from `salt` ([`SyntheticCloud::salt`] of its high bits): two 32-bit hashes
    /// give u and v (24 bits each) and the noise (8 bits from each). The arithmetic is 32-bit
    /// integers and f32 (the records' precision), which AVX2 does eight lanes at a time
    /// ([`GenerateRun`]), so a point costs a few nanoseconds and the benchmark measures the
    /// division rather than the generator. (A 64-bit hash, whose multiplies SSE2 emulates,
    /// took 12 ns a point: a quarter of `divide`'s CPU on 5 * 10^7 points. This one took
    /// 4.8 ns in SSE2's four lanes, whose 32-bit multiplies SSE2 also emulates, and takes
    /// 2.5 ns in AVX2's eight.)
    #[inline(always)]
    fn point(salt: u32, low: u32) -> [f32; 3] {
        let h1 = lowbias32(low ^ salt);
        let h2 = lowbias32(h1 ^ 0x9E37_79B9);
        const UNIT_24: f32 = 1.0 / 16_777_216.0;
        let u = (h1 >> 8) as f32 * UNIT_24;
        let v = (h2 >> 8) as f32 * UNIT_24;
        let noise = ((h1 & 0xFF) | ((h2 & 0xFF) << 8)) as f32 * (1.0 / 65_536.0);
        // x = 1000 u^2: the density along x falls as 1 / sqrt(x).
        let x = 1000.0 * u * u;
        let y = 1000.0 * v;
        let wave = |t: f32| (t - floor_small(t) - 0.5).abs();
        let z = 40.0 * wave(x * (1.0 / 97.0)) * wave(y * (1.0 / 61.0)) + 0.01 * noise;
        [x, y, z]
    }

    /// Writes the records of points `from..` into `bytes` (a whole number of records), one
    /// run of equal high bits at a time (a branch in the loop would keep it from SIMD lanes).
    #[inline(never)]
    fn generate_block(&self, from: u64, bytes: &mut [u8]) {
        let mut first = from;
        let mut rest = bytes;
        while !rest.is_empty() {
            let in_run = (1u64 << 32) - (first & 0xFFFF_FFFF);
            let records = usize::try_from(in_run).unwrap_or(usize::MAX).min(rest.len() / 12);
            // Only a partial record left (never, for whole records).
            if records == 0 {
                break;
            }
            let (run, after) = rest.split_at_mut(records * 12);
            let salt = self.salt((first >> 32) as u32);
            crate::sys::with_wide_vectors(GenerateRun { salt, first, run });
            first += records as u64;
            rest = after;
        }
    }
}

/// The records of points `first..` of one run of equal high bits, whose salt is `salt`, into
/// `run` (a whole number of records): the generator's loop, which
/// [`crate::sys::with_wide_vectors`] runs in AVX2 where the processor has it.
struct GenerateRun<'a> {
    salt: u32,
    first: u64,
    run: &'a mut [u8],
}

impl WideWork for GenerateRun<'_> {
    type Output = ();

    #[inline(always)]
    fn run(self) {
        for (i, record) in (self.first..).zip(self.run.chunks_exact_mut(12)) {
            let [x, y, z] = SyntheticCloud::point(self.salt, i as u32);
            record.copy_from_slice([x.to_le_bytes(), y.to_le_bytes(), z.to_le_bytes()].as_flattened());
        }
    }
}

/// A 32-bit finaliser (Wellons' "lowbias32"): a bijection in which every input bit moves
/// every output bit, with two multiplies.
#[inline]
fn lowbias32(mut x: u32) -> u32 {
    x ^= x >> 16;
    x = x.wrapping_mul(0x7FEB_352D);
    x ^= x >> 15;
    x = x.wrapping_mul(0x846C_A68B);
    x ^ (x >> 16)
}

/// floor(t) for 0 <= t < 2^22, without a libm call or a saturating cast, so that it runs in
/// SIMD lanes: adding and taking away 2^23 rounds to the nearest whole number, and one
/// comparison turns that into the floor.
#[inline]
fn floor_small(t: f32) -> f32 {
    const SHIFT: f32 = 8_388_608.0;
    let nearest = (t + SHIFT) - SHIFT;
    if nearest > t { nearest - 1.0 } else { nearest }
}

impl PointSource for SyntheticCloud {
    fn describe(&self) -> String {
        format!("synthetic cloud of {} points (seed {})", self.points, self.seed)
    }

    fn layout(&self) -> &PointLayout {
        &self.layout
    }

    fn announced_points(&self) -> Option<u64> {
        Some(self.points)
    }

    fn for_each_block(&self, block_points: usize, each: &mut dyn FnMut(&[u8]) -> Result<()>) -> Result<u64> {
        let block_points = block_points.max(1) as u64;
        let blocks = self.points.div_ceil(block_points);
        // Generated a batch at a time on every core; handed over in order.
        let batch = (rayon::current_num_threads() * 2) as u64;
        // Buffers kept between batches: no page faults on every block.
        let mut buffers: Vec<Vec<u8>> = Vec::new();
        let mut first = 0;
        while first < blocks {
            let last = (first + batch).min(blocks);
            buffers.resize_with((last - first) as usize, Vec::new);
            buffers
                .par_iter_mut()
                .enumerate()
                .try_for_each(|(offset, bytes)| self.read_block(block_points as usize, first + offset as u64, bytes))?;
            for bytes in &buffers {
                each(bytes)?;
            }
            first = last;
        }
        Ok(self.points)
    }

    fn random_access_blocks(&self, block_points: usize) -> Option<u64> {
        Some(self.points.div_ceil(block_points.max(1) as u64))
    }

    fn read_block(&self, block_points: usize, index: u64, block: &mut Vec<u8>) -> Result<()> {
        let block_points = block_points.max(1) as u64;
        let from = index.saturating_mul(block_points).min(self.points);
        let to = from.saturating_add(block_points).min(self.points);
        block.resize(((to - from) * 12) as usize, 0);
        self.generate_block(from, block);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The positions of `points` generated records, read back the way `divide` reads them.
    fn records(cloud: &SyntheticCloud, from: u64, points: usize) -> Vec<[f64; 3]> {
        let mut bytes = vec![0u8; points * 12];
        cloud.generate_block(from, &mut bytes);
        let mut read = Vec::with_capacity(points);
        cloud
            .layout()
            .for_each_positions(&bytes, |_, positions| read.extend_from_slice(positions));
        read
    }

    #[test]
    fn a_point_depends_only_on_its_number_across_runs_of_high_bits() {
        let cloud = SyntheticCloud::new(u64::MAX, 7);
        // A block across 2^32 is the two blocks either side of it.
        let from = (1u64 << 32) - 5;
        let whole = records(&cloud, from, 10);
        let mut parts = records(&cloud, from, 5);
        parts.extend(records(&cloud, 1 << 32, 5));
        assert_eq!(whole, parts);
        // Points 2^32 apart differ (the high bits reach the hash).
        assert_ne!(records(&cloud, 3, 4), records(&cloud, (1 << 32) + 3, 4));
        // Another seed, another cloud.
        assert_ne!(records(&cloud, 0, 4), records(&SyntheticCloud::new(u64::MAX, 8), 0, 4));
    }

    /// The generator's loop compiled for AVX2 gives the same bytes as compiled for the
    /// baseline. (On a processor without AVX2 both run the baseline, and the test shows
    /// nothing.)
    #[test]
    fn records_generated_in_avx2_match_the_baseline() {
        let cloud = SyntheticCloud::new(1 << 20, 5);
        let salt = cloud.salt(0);
        // Not a multiple of eight lanes: the loop's tail too.
        let mut wide = vec![0u8; 12 * 1003];
        let mut baseline = wide.clone();
        crate::sys::with_wide_vectors(GenerateRun {
            salt,
            first: 77,
            run: &mut wide,
        });
        GenerateRun {
            salt,
            first: 77,
            run: &mut baseline,
        }
        .run();
        assert_eq!(wide, baseline);
        assert!(wide.iter().any(|&b| b != 0));
    }

    #[test]
    fn points_fill_the_terrain_with_density_falling_along_x() {
        let cloud = SyntheticCloud::new(1 << 20, 1);
        let points = records(&cloud, 0, 1 << 16);
        let mut halves = [0usize; 2];
        for [x, y, z] in &points {
            assert!((0.0..1000.0).contains(x) && (0.0..1000.0).contains(y), "{x} {y}");
            // 40 times two waves of at most 1/2, plus the noise.
            assert!((0.0..=10.01).contains(z), "{z}");
            if let Some(h) = halves.get_mut(usize::from(*x >= 500.0)) {
                *h += 1;
            }
        }
        // x = 1000 u^2: P(x < 500) = sqrt(1/2), 0.707 of the points.
        let share = halves.first().copied().unwrap_or(0) as f64 / points.len() as f64;
        assert!((share - std::f64::consts::FRAC_1_SQRT_2).abs() < 0.01, "{share}");
    }
}
