//! Occlusion culling for the votes: a chunk of cubes that lies wholly more than eta behind
//! everything a depth map saw where the chunk projects casts no vote (Algorithm 1 drops a
//! vote whose depth is more than eta = 18 r in front of the cube), so the map skips it without
//! projecting its cubes. On RedKitchen a quarter of the vote calls ended there.
//!
//! The bound is exact, not a heuristic: a cube reads its depth from one pixel of the median
//! pyramid ([`super::votes::Pyramid`]), and a median of valid depths is never larger than the
//! largest of them, so the pixel is at most the largest valid depth of the full-resolution
//! pixels its block covers, and invalid (NaN) exactly where they all are. [`FarthestDepths`]
//! keeps those maxima per block, from blocks of 8 x 8 pixels up, so that a chunk's footprint
//! takes a few reads; a chunk is culled only when its nearest point is farther than the
//! largest depth under its whole footprint plus its largest cube's eta.

use super::halving::halve_finite_first;
use super::votes::Chunk;
use crate::inputs::{DepthImage, DepthMapSource, Projection};

/// The finest level [`FarthestDepths`] keeps: blocks of 2^3 = 8 pixels a side (1/64 of the
/// map's memory for all levels together, against 4/3 for the median pyramid).
const FIRST_LEVEL: u32 = 3;

/// A chunk's footprint is read at the finest kept level where it spans at most this many
/// blocks per axis.
const MOST_BLOCKS: f64 = 4.0;

/// The largest valid depth of each block of 2^k x 2^k pixels, for k from [`FIRST_LEVEL`] up
/// (NaN where no pixel of the block is valid), aligned as the median pyramid's levels are.
pub struct FarthestDepths {
    levels: Vec<DepthImage>,
}

/// ceil(log2(x)) for x > 1 from its bits (0 for x <= 1 or NaN, 1024 for infinity): without a
/// libm call, which the culling of every chunk against every map made (about a tenth of its
/// time on RedKitchen).
fn ceil_log2(x: f64) -> u32 {
    if x.is_nan() || x <= 1.0 {
        return 0;
    }
    let bits = x.to_bits();
    let exponent = ((bits >> 52) & 0x7ff) as u32 - 1023;
    exponent + u32::from(bits & ((1 << 52) - 1) != 0)
}

/// `f64::floor` without a libm call (this build's baseline x86-64 has no rounding
/// instruction): the truncation, one lower where it rounded up. Values of 2^52 and more are
/// integers already; NaN, infinities and zeros (either sign) come back as they are.
fn floor(x: f64) -> f64 {
    if x.is_nan() || x.abs() >= 4_503_599_627_370_496.0 || x == 0.0 {
        return x;
    }
    let truncated = x as i64 as f64;
    if truncated > x { truncated - 1.0 } else { truncated }
}

/// [`largest_valid`] of four finite values whose largest is a normal number, without
/// branches.
fn largest_finite([a, b, c, d]: [f32; 4]) -> f32 {
    a.max(b).max(c.max(d))
}

/// The larger of the finite values, NaN when there is none.
fn largest_valid(values: [f32; 4]) -> f32 {
    values
        .into_iter()
        .filter(|v| v.is_finite())
        .fold(f32::NAN, |largest, v| if largest >= v { largest } else { v })
}

impl FarthestDepths {
    /// The maxima of `image`'s blocks.
    pub fn new(image: &DepthImage) -> Self {
        let mut first = halve_finite_first(image, largest_finite, largest_valid);
        for _ in 1..FIRST_LEVEL {
            first = halve_finite_first(&first, largest_finite, largest_valid);
        }
        let mut levels = vec![first];
        while let Some(last) = levels.last() {
            if last.width <= 1 && last.height <= 1 {
                break;
            }
            let next = halve_finite_first(last, largest_finite, largest_valid);
            levels.push(next);
        }
        FarthestDepths { levels }
    }

    /// Bytes the levels take.
    pub fn bytes(&self) -> u64 {
        self.levels
            .iter()
            .map(|level| (level.depth.len() * std::mem::size_of::<f32>()) as u64)
            .sum()
    }

    /// At least the largest valid depth of the full-resolution pixels in columns `cols` and
    /// rows `rows` (inclusive, clipped to the image); None when none of them is valid.
    fn farthest_in(&self, cols: (f64, f64), rows: (f64, f64)) -> Option<f32> {
        let span = (cols.1 - cols.0).max(rows.1 - rows.0).max(1.0);
        // The finest kept level whose blocks, MOST_BLOCKS of them, span the footprint.
        let wanted = ceil_log2(span / MOST_BLOCKS).max(FIRST_LEVEL);
        let index = ((wanted - FIRST_LEVEL) as usize).min(self.levels.len().saturating_sub(1));
        let level = self.levels.get(index)?;
        let block = f64::from(1u32 << (FIRST_LEVEL as usize + index));
        let clip = |lo: f64, hi: f64, size: u32| -> Option<(u32, u32)> {
            let (lo, hi) = (floor(lo / block).max(0.0), floor(hi / block).min(f64::from(size) - 1.0));
            (lo <= hi).then_some((lo as u32, hi as u32))
        };
        let (i0, i1) = clip(cols.0, cols.1, level.width)?;
        let (j0, j1) = clip(rows.0, rows.1, level.height)?;
        let width = level.width as usize;
        let mut farthest: Option<f32> = None;
        for j in j0 as usize..=j1 as usize {
            let row = level
                .depth
                .get(j * width + i0 as usize..=j * width + i1 as usize)
                .unwrap_or(&[]);
            for &d in row {
                if d.is_finite() {
                    farthest = Some(farthest.map_or(d, |f| f.max(d)));
                }
            }
        }
        farthest
    }

    /// Whether no cube of `chunk` (centres and voting balls inside its ball, voting radii at
    /// most its `max_radius`) can vote in the map `source` seen through `world_to_camera`:
    /// every pixel such a cube may read is invalid or lies more than the cube's eta in front
    /// of it. Pinhole maps only (a 360-degree map never culls).
    pub fn hides(&self, source: &DepthMapSource, world_to_camera: &glam::DMat4, chunk: &Chunk) -> bool {
        let Projection::Pinhole { fx, fy, cx, cy } = source.projection else {
            return false;
        };
        let c = world_to_camera.transform_point3(chunk.center);
        let r = chunk.radius;
        let near = c.z - r;
        if near <= 0.0 {
            return false;
        }
        // The projections of the ball's points lie between those of its bounding box's
        // corners (x / z is monotone in x and in z for z > 0).
        let extent = |x: f64, f: f64, principal: f64| {
            let candidates = [(x - r) / near, (x - r) / (c.z + r), (x + r) / near, (x + r) / (c.z + r)];
            let lo = candidates.iter().copied().fold(f64::INFINITY, f64::min);
            let hi = candidates.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            (f * lo + principal, f * hi + principal)
        };
        let ((u0, u1), (v0, v1)) = (extent(c.x, fx, cx), extent(c.y, fy, cy));
        // A cube reads one pixel at level l, whose pixels span s = 2^l full-resolution pixels,
        // s at most max(1, 2 r f / z); that pixel's block holds the full-resolution pixels
        // whose centres lie within s - 0.5 of the projected centre. Half a pixel more for the
        // f32 arithmetic of the vote.
        let footprint = 2.0 * chunk.max_radius * fx.max(fy) / near;
        let reach = footprint.max(1.0) + 0.5;
        let Some(farthest) = self.farthest_in((u0 - reach, u1 + reach), (v0 - reach, v1 + reach)) else {
            return true;
        };
        let eta = 18.0 * chunk.max_radius;
        // Relative slack for the f32 depths and distances of the vote.
        f64::from(farthest) + eta < near * (1.0 - 1e-4) - 1e-4 * eta
    }
}

#[cfg(test)]
mod tests {
    use glam::DVec3;

    use super::*;
    use crate::kernels::halving::halve;

    #[test]
    fn the_fast_largest_is_the_exact_one_wherever_halving_keeps_it() {
        let mut seed = 13u64;
        let mut uniform = move || crate::kernels::random::uniform(&mut seed);
        let (width, height) = (37u32, 22u32);
        for round in 0..40 {
            let depth = (0..width * height)
                .map(|_| {
                    let pick = uniform();
                    match round % 3 {
                        0 if pick < 0.1 => f32::NAN,
                        1 if pick < 0.05 => f32::INFINITY,
                        1 if pick < 0.1 => f32::NEG_INFINITY,
                        2 if pick < 0.2 => 0.0,
                        2 if pick < 0.3 => -0.0,
                        _ if pick < 0.5 => -(uniform() as f32) * 4.0,
                        _ => uniform() as f32 * 4.0,
                    }
                })
                .collect();
            let image = DepthImage { width, height, depth };
            let exact = halve(&image, largest_valid);
            let fast = halve_finite_first(&image, largest_finite, largest_valid);
            let bits = |level: &DepthImage| level.depth.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&fast), bits(&exact), "round {round}");
        }
    }

    #[test]
    fn floor_and_ceil_log2_are_the_libm_ones() {
        let mut seed = 19u64;
        let mut uniform = move || crate::kernels::random::uniform(&mut seed);
        let mut values = vec![
            0.0,
            -0.0,
            0.5,
            -0.5,
            1.0,
            -1.0,
            1.5,
            -1.5,
            2.0,
            4.0,
            8.0 + 1e-12,
            4_503_599_627_370_495.5,
            -4_503_599_627_370_495.5,
            4_503_599_627_370_496.0,
            1e300,
            -1e300,
            f64::MIN_POSITIVE,
            -f64::MIN_POSITIVE,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
        ];
        values.extend((0..10_000).map(|_| (uniform() - 0.5) * 2f64.powf(uniform() * 80.0 - 20.0)));
        for x in values {
            assert_eq!(floor(x).to_bits(), x.floor().to_bits(), "floor({x})");
            let libm = if x > 1.0 { x.log2().ceil() } else { 0.0 };
            // log2 rounds: a value just above a power of two may log2 to the power itself.
            let exact = (0..=1024).find(|&k| 2f64.powi(k) >= x).unwrap_or(1024);
            if x.is_finite() && x > 1.0 {
                assert_eq!(ceil_log2(x), exact as u32, "ceil_log2({x})");
                assert!(f64::from(ceil_log2(x)) >= libm, "ceil_log2({x}) below libm's {libm}");
            } else if x.is_nan() || x <= 1.0 {
                assert_eq!(ceil_log2(x), 0, "ceil_log2({x})");
            }
        }
        assert_eq!(ceil_log2(f64::INFINITY), 1024);
    }

    #[test]
    fn block_maxima_bound_every_pixel_under_them() {
        let (width, height) = (45u32, 29u32);
        let depth: Vec<f32> = (0..width * height)
            .map(|p| {
                if p % 13 == 0 {
                    f32::NAN
                } else {
                    1.0 + ((p * 7919) % 101) as f32 * 0.01
                }
            })
            .collect();
        let image = DepthImage { width, height, depth };
        let farthest = FarthestDepths::new(&image);
        for (index, level) in farthest.levels.iter().enumerate() {
            let block = 1u32 << (FIRST_LEVEL as usize + index);
            assert_eq!(
                (level.width, level.height),
                (width.div_ceil(block), height.div_ceil(block))
            );
            for j in 0..level.height {
                for i in 0..level.width {
                    let pixels: Vec<f32> = (j * block..((j + 1) * block).min(height))
                        .flat_map(|y| (i * block..((i + 1) * block).min(width)).map(move |x| (x, y)))
                        .map(|(x, y)| image.get(x, y))
                        .filter(|d| d.is_finite())
                        .collect();
                    let expected = pixels.iter().copied().fold(f32::NAN, f32::max);
                    assert_eq!(
                        level.get(i, j).to_bits(),
                        expected.to_bits(),
                        "level {index}, block {i}, {j}"
                    );
                }
            }
        }
        assert_eq!(farthest.levels.last().map(|l| (l.width, l.height)), Some((1, 1)));
    }

    #[test]
    fn a_hidden_chunk_has_no_cube_that_votes() {
        use crate::kernels::votes::{Pyramid, UnitView, chunks, cube_offsets, vote_relative};
        // A bumpy, broken surface with holes, seen by a turned camera with unequal focal
        // lengths; runs of cubes in front of it, around it and behind it, with voting radii
        // from 1 mm to 5 cm.
        let (width, height) = (64u32, 48u32);
        let camera_to_world =
            glam::DMat4::from_translation(DVec3::new(0.3, -0.2, 0.1)) * glam::DMat4::from_rotation_y(0.2);
        let source =
            DepthMapSource::test_pinhole("wall.pfm", (width, height), [50.0, 45.0, 31.5, 23.5], camera_to_world);
        let depth = (0..width * height)
            .map(|p| {
                if p % 11 == 0 || (p % width < 9 && p / width < 7) {
                    f32::NAN
                } else {
                    // Checks of 5 x 3 pixels alternately near and far: a coarse pixel's
                    // median mixes both, which only the footprint's reach accounts for.
                    let (x, y) = (p % width, p / width);
                    let near = (x / 5 + y / 3) % 2 == 0;
                    (if near { 1.5 } else { 6.0 }) + 0.05 * ((p * 37) % 17) as f32 / 17.0
                }
            })
            .collect();
        let pyramid = Pyramid::new(source.clone(), DepthImage { width, height, depth });
        let world_to_camera = camera_to_world.inverse();
        let mut seed = 17u64;
        let mut uniform = move || crate::kernels::random::uniform(&mut seed);
        let (mut hidden, mut shown) = (0, 0);
        for _ in 0..3000 {
            let z = 0.5 + uniform() * 8.0;
            let spread = 0.01 + uniform() * 0.2;
            let in_camera = DVec3::new((uniform() * 1.6 - 0.8) * z, (uniform() * 1.4 - 0.7) * z, z);
            let center = camera_to_world.transform_point3(in_camera);
            let largest = 0.001 + uniform() * 0.05;
            let cubes = 1 + (uniform() * 200.0) as usize;
            let centers: Vec<DVec3> = (0..cubes)
                .map(|_| center + DVec3::new(uniform() - 0.5, uniform() - 0.5, uniform() - 0.5) * spread)
                .collect();
            let radii: Vec<f64> = (0..cubes).map(|_| 0.001 + uniform() * largest).collect();
            let origin = center + DVec3::splat(0.1);
            let view = UnitView::new(&source, &world_to_camera, origin, 0.0);
            let offsets = cube_offsets(origin, &centers, &radii);
            for chunk in chunks(&centers, &radii) {
                if !pyramid.farthest.hides(&source, &world_to_camera, &chunk) {
                    shown += 1;
                    continue;
                }
                hidden += 1;
                for cube in chunk.start..chunk.end {
                    let (c, r, offset) = (centers[cube], radii[cube], offsets[cube]);
                    assert_eq!(
                        pyramid.vote_with_distance(&world_to_camera, c, r, 0.0),
                        None,
                        "cube at {c} (r {r})"
                    );
                    assert_eq!(vote_relative(&view, offset, &pyramid), None, "cube at {c} (r {r}), f32");
                }
            }
        }
        // Both outcomes are common in the draw.
        assert!(hidden > 500 && shown > 500, "{hidden} hidden, {shown} shown");
    }
}
