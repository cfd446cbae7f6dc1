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

    fn point(&self, i: u64) -> [f32; 3] {
        let a = splitmix64(self.seed ^ i.wrapping_mul(0x9E37_79B9_7F4A_7C15));
        let b = splitmix64(a);
        let unit = |bits: u64| (bits >> 11) as i64 as f64 * (1.0 / (1u64 << 53) as f64);
        let (u, v) = (unit(a), unit(b));
        // x = 1000 u^2: the density along x falls as 1 / sqrt(x).
        let x = 1000.0 * u * u;
        let y = 1000.0 * v;
        // Truncation is floor here: the arguments are positive.
        let wave = |t: f64| (t - (t as i64) as f64 - 0.5).abs();
        let z = 40.0 * wave(x * (1.0 / 97.0)) * wave(y * (1.0 / 61.0)) + 0.01 * unit(b.rotate_left(17));
        [x as f32, y as f32, z as f32]
    }
}

fn splitmix64(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
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
        let mut first = 0;
        while first < blocks {
            let last = (first + batch).min(blocks);
            let generated: Vec<Vec<u8>> = (first..last)
                .into_par_iter()
                .map(|block| {
                    let from = block * block_points;
                    let to = (from + block_points).min(self.points);
                    let mut bytes = Vec::with_capacity(((to - from) * 12) as usize);
                    for i in from..to {
                        for c in self.point(i) {
                            bytes.extend_from_slice(&c.to_le_bytes());
                        }
                    }
                    bytes
                })
                .collect();
            for bytes in &generated {
                each(bytes)?;
            }
            first = last;
        }
        Ok(self.points)
    }
}
