//! A point cloud generated on the fly, for benchmarks of `divide` at sizes no disk here holds:
//! a rolling terrain 1000 units square whose density falls off along x (a hundredfold from one
//! side to the other), as a photogrammetric cloud's does with the distance to the cameras. Point
//! `i` depends only on `i` and the seed, so every pass sees the same cloud.

use rayon::prelude::*;

use super::{PointSource, Result};
use crate::format::ply_header::PlyScalar;
use crate::inputs::PointLayout;

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

    /// Point `i`: one 64-bit hash gives u and v (24 bits each) and the noise (16 bits); the
    /// arithmetic is f32, the precision of the records, so a point costs a few nanoseconds and
    /// the benchmark measures the division rather than the generator.
    #[inline]
    fn point(&self, i: u64) -> [f32; 3] {
        let h = mix64(self.seed ^ i.wrapping_mul(0x9E37_79B9_7F4A_7C15));
        const UNIT_24: f32 = 1.0 / 16_777_216.0;
        let u = (h >> 40) as u32 as f32 * UNIT_24;
        let v = ((h >> 16) as u32 & 0x00FF_FFFF) as f32 * UNIT_24;
        let noise = (h as u32 & 0xFFFF) as f32 * (1.0 / 65_536.0);
        // x = 1000 u^2: the density along x falls as 1 / sqrt(x).
        let x = 1000.0 * u * u;
        let y = 1000.0 * v;
        // Truncation is floor here: the arguments are positive.
        let wave = |t: f32| (t - (t as i32) as f32 - 0.5).abs();
        let z = 40.0 * wave(x * (1.0 / 97.0)) * wave(y * (1.0 / 61.0)) + 0.01 * noise;
        [x, y, z]
    }

    /// Writes the records of points `from..` into `bytes` (a whole number of records).
    #[inline(never)]
    fn generate_block(&self, from: u64, bytes: &mut [u8]) {
        for (i, record) in (from..).zip(bytes.chunks_exact_mut(12)) {
            let [x, y, z] = self.point(i);
            record.copy_from_slice([x.to_le_bytes(), y.to_le_bytes(), z.to_le_bytes()].as_flattened());
        }
    }
}

/// A 64-bit finaliser (splitmix64's): every input bit moves every output bit.
fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
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
