//! The vote math of the histogram stage (paper 3.4, Algorithm 1): bins, the depth-map
//! pyramid, the projection of a cube into a depth map, and the chunked voting loop. Pure
//! functions of cubes and depth maps: no store, no catalog, so the GPU twins test against them.

use glam::DVec3;

use crate::format::{CubeKey, Scene};
use crate::inputs::{DepthImage, DepthMapSource, Projection};

pub const BINS: usize = 8;

/// Bin of a clamped signed distance a in [-1, 1]: min(7, floor((a + 1) / 2 * 8)) (the paper prints a
/// garbled formula; ARCHITECTURE.md, "Method notes").
pub fn bin_of(a: f64) -> usize {
    // (a + 1) * 4 >= 0, where truncation is the floor (and needs no libm call).
    (((a + 1.0) / 2.0 * 8.0) as usize).min(BINS - 1)
}

/// floor(log2(x)) for x >= 1, read from the exponent bits: exact, and no libm call in the
/// voting loop (which runs billions of times).
fn floor_log2(x: f64) -> usize {
    (((x.to_bits() >> 52) & 0x7ff) as usize).saturating_sub(1023)
}

/// The nearest integer to a finite x, ties upward: floor(x + 0.5) without a libm call.
fn nearest(x: f64) -> f64 {
    let t = x + 0.5;
    let truncated = t as i64 as f64;
    if truncated > t { truncated - 1.0 } else { truncated }
}

/// Bin centres f_b = -1 + (2b + 1) / 8.
pub fn bin_center(b: usize) -> f32 {
    -1.0 + (2.0 * b as f32 + 1.0) / 8.0
}

/// Whether a vote into `bin` measured a distance to the surface: bins 1 to 6, not clamped to
/// free space (7) or far behind (0).
pub fn measures(bin: usize) -> bool {
    (1..BINS - 1).contains(&bin)
}

/// The truncation band of a cube's distance sum, in units of the voting distance delta. The
/// measuring bins alone (|a| < 0.75 delta, about 1.3 finest cubes on RedKitchen) drop most of
/// a surface's votes to depth noise and leave the mean noisy; at 2 delta (3.5 cubes, near a
/// TSDF's usual truncation) the table top's mean normal deviation fell from 17 to 11 degrees.
pub const DISTANCE_BAND_PER_DELTA: f64 = 2.0;

/// The least truncation band, in finest cube sides ([`band_floor`]). delta follows the sample
/// radius, and where `--max-depth` caps the octree (RedKitchen at 10: 1.3 mm samples in
/// 5.8 mm cubes) 2 delta is under 3 finest cubes. A map seeing the surface at a grazing angle
/// (its depth difference is the surface distance over the cosine of that angle) then still
/// counted in front of the surface but was cut off a few millimetres behind it, so the mean
/// bent at the surface and vertices on edges of different lengths and directions disagreed
/// by a fraction of a cube: faint regular ridges. With the floor at 6 sides RedKitchen's table
/// top (100 frames) went from 7.9 to 6.1 degrees (4 delta for every cube gave the same). The
/// cost is on objects seen from all around, whose samples are also finer than their cubes:
/// votes of views on the far side of a thin part now reach the near surface (clean bunny
/// Chamfer 0.00117 to 0.00157, normal consistency 0.974 to 0.959; README, known limitations).
pub const DISTANCE_BAND_FLOOR_SIDES: f64 = 6.0;

/// The least truncation band of a scene's distance sums, in world units:
/// [`DISTANCE_BAND_FLOOR_SIDES`] finest cube sides.
pub fn band_floor(scene: &Scene) -> f64 {
    DISTANCE_BAND_FLOOR_SIDES * scene.cube_side(scene.max_depth)
}

/// What a vote with signed distance a (the depth the map measured minus the voxel's, world
/// units, positive in front of the surface) adds to its cube's distance sum, a truncated
/// signed distance as a TSDF integrates it: a clamped to the band T = max(
/// [`DISTANCE_BAND_PER_DELTA`] x delta, `floor`), nothing when the voxel lies more than T
/// behind the surface.
pub fn truncated_distance(a: f64, delta: f64, floor: f64) -> Option<f64> {
    let band = (DISTANCE_BAND_PER_DELTA * delta).max(floor);
    (a >= -band).then_some(a.min(band))
}

/// Vote weights are rounded to multiples of 1/16 so that sums are exact in any order.
pub fn quantized_weight(weight: f32) -> f32 {
    ((weight * 16.0).round() / 16.0).max(0.0)
}

/// A depth map and its mipmap pyramid: each pixel of level k + 1 is the median of the valid
/// depths among its 2 x 2 pixels of level k (the mean of the middle two when there are four
/// or two), NaN when none is valid.
///
/// A median rather than a mean: a coarse voxel reads one pixel of a coarse level, and a mean
/// lets every wild depth below it shift that pixel. Random outliers lie behind the surface as
/// often as in front, but a depth behind can be arbitrarily far, so means are biased away from
/// the camera and coarse voxels vote the surface deeper into the object (20 % outlier pixels
/// eroded the synthetic bunny by about 3 finest cubes). The median of four ignores one wild
/// value per block, and level by level its errors stay local.
pub struct Pyramid {
    pub source: DepthMapSource,
    pub levels: Vec<DepthImage>,
}

/// The median of the finite values among four, NaN when none is finite.
pub fn median_of_valid(values: [f32; 4]) -> f32 {
    let mut valid = [0f32; 4];
    let mut n = 0;
    for v in values {
        if v.is_finite()
            && let Some(slot) = valid.get_mut(n)
        {
            *slot = v;
            n += 1;
        }
    }
    let valid = valid.get_mut(..n).unwrap_or_default();
    valid.sort_unstable_by(f32::total_cmp);
    match *valid {
        [] => f32::NAN,
        [a] => a,
        [a, b] => ((f64::from(a) + f64::from(b)) * 0.5) as f32,
        [_, b, _] => b,
        [_, b, c, _] => ((f64::from(b) + f64::from(c)) * 0.5) as f32,
        _ => f32::NAN,
    }
}

impl Pyramid {
    pub fn new(source: DepthMapSource, image: DepthImage) -> Pyramid {
        let mut levels = vec![image];
        while let Some(last) = levels.last() {
            if last.width <= 1 && last.height <= 1 {
                break;
            }
            let (w, h) = (last.width.div_ceil(2), last.height.div_ceil(2));
            let mut depth = Vec::with_capacity((w * h) as usize);
            for j in 0..h {
                for i in 0..w {
                    depth.push(median_of_valid([
                        last.get(2 * i, 2 * j),
                        last.get(2 * i + 1, 2 * j),
                        last.get(2 * i, 2 * j + 1),
                        last.get(2 * i + 1, 2 * j + 1),
                    ]));
                }
            }
            levels.push(DepthImage {
                width: w,
                height: h,
                depth,
            });
        }
        Pyramid { source, levels }
    }

    /// Bytes the decoded levels take.
    pub fn bytes(&self) -> u64 {
        self.levels
            .iter()
            .map(|level| (level.depth.len() * std::mem::size_of::<f32>()) as u64)
            .sum()
    }

    /// Algorithm 1 for one voxel: the bin it votes into, if any.
    pub fn vote(&self, world_to_camera: &glam::DMat4, center: DVec3, radius: f64) -> Option<usize> {
        self.vote_with_distance(world_to_camera, center, radius, 0.0)
            .map(|(bin, _)| bin)
    }

    /// [`Pyramid::vote`], with the vote's [`truncated_distance`] (band at least `band_floor`),
    /// if any.
    pub fn vote_with_distance(
        &self,
        world_to_camera: &glam::DMat4,
        center: DVec3,
        radius: f64,
        band_floor: f64,
    ) -> Option<(usize, Option<f64>)> {
        let local = world_to_camera.transform_point3(center);
        let (u, v, distance) = self.source.project(local)?;
        let pixels_per_unit = match self.source.projection {
            Projection::Pinhole { fx, fy, .. } => fx.max(fy) / distance,
            Projection::Spherical => f64::from(self.source.width) / std::f64::consts::TAU / distance,
        };
        let footprint = 2.0 * radius * pixels_per_unit;
        let level = if footprint > 1.0 { floor_log2(footprint) } else { 0 };
        let level = level.min(self.levels.len() - 1);
        let image = self.levels.get(level)?;
        let scale = f64::from(1u32 << level);
        let (i, j) = (
            nearest((u - (scale - 1.0) * 0.5) / scale),
            nearest((v - (scale - 1.0) * 0.5) / scale),
        );
        let i = if matches!(self.source.projection, Projection::Spherical) {
            i.rem_euclid(f64::from(image.width))
        } else {
            i
        };
        if i < 0.0 || j < 0.0 || i >= f64::from(image.width) || j >= f64::from(image.height) {
            return None;
        }
        let depth = f64::from(image.get(i as u32, j as u32));
        if !depth.is_finite() {
            return None;
        }
        let delta = 6.0 * radius;
        let eta = 3.0 * delta;
        let a = depth - distance;
        if a < -eta {
            return None;
        }
        Some((
            bin_of((a / delta).clamp(-1.0, 1.0)),
            truncated_distance(a, delta, band_floor),
        ))
    }

    /// Whether any cube whose centre lies in the ball, and whose voting radius is at most the
    /// ball's radius, may vote: a frustum test that is conservative by construction (LIDAR sees
    /// all around).
    ///
    /// `vote` reads the pixel nearest the projected centre at a level whose pixel spans at most
    /// the cube's footprint `2 r f / z`, and a level's last pixel may reach one level pixel past
    /// the image edge. So a voting centre satisfies `-0.5 <= u < width + 2 r f / z`, that is,
    /// it lies at most `2 r f / n` beyond the side plane `u = width` (n the plane normal's
    /// length), and never beyond `u = -0.5`. A ball is culled only when it lies wholly beyond
    /// such a widened plane (one pixel of slack on every side).
    pub fn may_see(source: &DepthMapSource, world_to_camera: &glam::DMat4, center: DVec3, radius: f64) -> bool {
        match source.projection {
            Projection::Spherical => true,
            Projection::Pinhole { fx, fy, cx, cy } => {
                let p = world_to_camera.transform_point3(center);
                if p.z + radius <= 0.0 {
                    return false;
                }
                let f = fx.max(fy);
                let (w, h) = (f64::from(source.width), f64::from(source.height));
                // Each side: the plane's normal (pointing out of the image) through the
                // camera centre, and the widening allowed beyond it.
                let sides = [
                    (DVec3::new(-fx, 0.0, -(cx + 1.0)), 0.0),
                    (DVec3::new(0.0, -fy, -(cy + 1.0)), 0.0),
                    (DVec3::new(fx, 0.0, cx - w - 1.0), 2.0 * f),
                    (DVec3::new(0.0, fy, cy - h - 1.0), 2.0 * f),
                ];
                sides.iter().all(|(normal, widening)| {
                    let length = normal.length();
                    normal.dot(p) / length <= radius + widening * radius / length
                })
            }
        }
    }
}

/// Centre and radius of every cube of a unit: r_c (eq. 5) where samples spawned it, else the
/// cube's natural radius (half its side).
pub fn cube_geometry(scene: &Scene, keys: &[CubeKey], sums: &[u64], counts: &[u32]) -> (Vec<DVec3>, Vec<f64>) {
    let centers = keys.iter().map(|k| scene.cube_center(*k)).collect();
    let radii = keys
        .iter()
        .zip(sums.iter().zip(counts))
        .map(|(k, (s, c))| {
            if *c > 0 {
                scene.mean_radius(*s, *c)
            } else {
                scene.cube_side(k.depth()) * 0.5
            }
        })
        .collect();
    (centers, radii)
}

/// Cubes per culling chunk: Morton-consecutive cubes are spatially compact, so a chunk's ball
/// stays small near the surface, where the cubes are.
const CHUNK_CUBES: usize = 256;

/// Cubes `start..end` of a unit and a ball that holds every one of their voting balls.
pub struct Chunk {
    /// First cube of the run.
    pub start: usize,
    /// One past the last cube of the run.
    pub end: usize,
    /// Centre of the ball that holds the run's voting balls.
    pub center: DVec3,
    /// Radius of that ball.
    pub radius: f64,
}

pub fn chunks(centers: &[DVec3], radii: &[f64]) -> Vec<Chunk> {
    let mut chunks = Vec::with_capacity(centers.len().div_ceil(CHUNK_CUBES));
    let mut start = 0;
    while start < centers.len() {
        let end = (start + CHUNK_CUBES).min(centers.len());
        let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
        for (center, radius) in centers.iter().zip(radii).take(end).skip(start) {
            lo = lo.min(*center - DVec3::splat(*radius));
            hi = hi.max(*center + DVec3::splat(*radius));
        }
        chunks.push(Chunk {
            start,
            end,
            center: (lo + hi) * 0.5,
            radius: (hi - lo).length() * 0.5,
        });
        start = end;
    }
    chunks
}

/// The cubes of a unit being voted: centres and voting radii, and their runs of
/// Morton-consecutive cubes ([`chunks`]).
pub struct ChunkedCubes<'a> {
    /// Cube centres in world coordinates.
    pub centers: &'a [DVec3],
    /// Voting radii (r_c, or half the cube side).
    pub radii: &'a [f64],
    /// The runs, ascending and disjoint.
    pub chunks: &'a [Chunk],
    /// The least band of the distance sums ([`band_floor`]).
    pub band_floor: f64,
}

/// Votes `pyramid` into `hist` (BINS per cube) and `distance` (two per cube: the weighted sum
/// of the votes' [`truncated_distance`]s, in world units, and the sum of their weights) for
/// the cubes of the chunks listed in `seen` (ascending), and returns the number of votes cast. Chunks own disjoint rows of the
/// histogram, so they vote in parallel: a group of one large leaf still uses every core, and
/// each cube still receives the maps in the order they are voted.
pub fn vote_chunks(
    cubes: &ChunkedCubes<'_>,
    hist: &mut [f32],
    distance: &mut [f32],
    pyramid: &Pyramid,
    world_to_camera: &glam::DMat4,
    weight: f32,
    seen: &[usize],
) -> u64 {
    use rayon::prelude::*;
    let mut work = Vec::with_capacity(seen.len());
    let mut rest: &mut [f32] = hist;
    let mut rest_distance: &mut [f32] = distance;
    let mut consumed = 0;
    for chunk in seen.iter().filter_map(|&c| cubes.chunks.get(c)) {
        let Some((_, tail)) = rest.split_at_mut_checked((chunk.start - consumed) * BINS) else {
            break;
        };
        let Some((rows, tail)) = tail.split_at_mut_checked((chunk.end - chunk.start) * BINS) else {
            break;
        };
        let Some((_, tail_distance)) = rest_distance.split_at_mut_checked((chunk.start - consumed) * 2) else {
            break;
        };
        let Some((distances, tail_distance)) = tail_distance.split_at_mut_checked((chunk.end - chunk.start) * 2) else {
            break;
        };
        work.push((chunk, rows, distances));
        rest = tail;
        rest_distance = tail_distance;
        consumed = chunk.end;
    }
    let (centers, radii, band_floor) = (cubes.centers, cubes.radii, cubes.band_floor);
    work.into_par_iter()
        .map(|(chunk, rows, distances)| {
            let cubes = centers.iter().zip(radii).take(chunk.end).skip(chunk.start);
            let mut votes = 0u64;
            for ((row, sums), (center, radius)) in rows
                .chunks_exact_mut(BINS)
                .zip(distances.chunks_exact_mut(2))
                .zip(cubes)
            {
                if let Some((bin, distance)) = pyramid.vote_with_distance(world_to_camera, *center, *radius, band_floor)
                    && let Some(h) = row.get_mut(bin)
                {
                    *h += weight;
                    if let (Some(d), [sum, total]) = (distance, sums) {
                        *sum += weight * d as f32;
                        *total += weight;
                    }
                    votes += 1;
                }
            }
            votes
        })
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pyramid_levels_take_the_median_of_valid_depths() {
        let nan = f32::NAN;
        assert_eq!(median_of_valid([1.0, 9.0, 2.0, 3.0]), 2.5);
        assert_eq!(median_of_valid([1.0, nan, 7.0, 2.0]), 2.0);
        assert_eq!(median_of_valid([nan, 4.0, nan, 2.0]), 3.0);
        assert_eq!(median_of_valid([nan, nan, 5.0, nan]), 5.0);
        assert!(median_of_valid([nan, nan, nan, nan]).is_nan());

        // A 4 x 2 wall at depth 1 with one wild pixel per 2 x 2 block: level 1 is the wall
        // (a mean would put the left block at 1.75), level 2 keeps it, and a block without
        // valid pixels stays invalid.
        let source = crate::inputs::DepthMapSource {
            path: "wall.pfm".into(),
            format: crate::inputs::ImageFormat::Pfm,
            width: 6,
            height: 2,
            projection: crate::inputs::Projection::Pinhole {
                fx: 10.0,
                fy: 10.0,
                cx: 3.0,
                cy: 1.0,
            },
            camera_to_world: glam::DMat4::IDENTITY.to_cols_array(),
            kind: crate::inputs::Kind::Photo,
            weight: 1.0,
        };
        let depth = vec![4.0, 1.0, 1.0, 0.1, nan, nan, 1.0, 1.0, 1.0, 1.0, nan, nan];
        let pyramid = Pyramid::new(
            source,
            DepthImage {
                width: 6,
                height: 2,
                depth,
            },
        );
        let level1 = &pyramid.levels[1].depth;
        assert_eq!((level1[0], level1[1]), (1.0, 1.0));
        assert!(level1[2].is_nan());
        assert_eq!(pyramid.levels[2].depth[0], 1.0);
        assert_eq!(pyramid.levels.last().map(|l| (l.width, l.height)), Some((1, 1)));
    }

    #[test]
    fn frustum_test_never_culls_a_cube_that_votes() {
        // An odd-sized image, so coarse levels overhang the edges, seen by a camera with
        // unequal focal lengths; depth everywhere far behind the cubes, so every cube that
        // projects into a level votes.
        let (width, height) = (37u32, 33u32);
        let source = crate::inputs::DepthMapSource {
            path: "far.pfm".into(),
            format: crate::inputs::ImageFormat::Pfm,
            width,
            height,
            projection: crate::inputs::Projection::Pinhole {
                fx: 30.0,
                fy: 24.0,
                cx: 17.0,
                cy: 12.5,
            },
            camera_to_world: glam::DMat4::IDENTITY.to_cols_array(),
            kind: crate::inputs::Kind::Photo,
            weight: 1.0,
        };
        let depth = vec![1000.0; (width * height) as usize];
        let pyramid = Pyramid::new(source.clone(), DepthImage { width, height, depth });
        let world_to_camera = glam::DMat4::IDENTITY;
        let mut seed = 11u64;
        let mut uniform = move || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (seed >> 11) as f64 / (1u64 << 53) as f64
        };
        let (mut voted, mut culled) = (0, 0);
        for _ in 0..200_000 {
            let z = 0.05 + uniform() * 10.0;
            let center = DVec3::new((uniform() * 2.4 - 1.2) * z, (uniform() * 2.4 - 1.2) * z, z);
            let radius = uniform().powi(3) * z;
            // A ball holding the cube: its centre anywhere within `slack` of the cube's.
            let slack = if uniform() < 0.5 { 0.0 } else { uniform() * radius };
            let direction = DVec3::new(uniform() - 0.5, uniform() - 0.5, uniform() - 0.5).normalize_or_zero();
            let ball = (center + direction * slack, radius + slack);
            let sees = Pyramid::may_see(&source, &world_to_camera, ball.0, ball.1);
            if pyramid.vote(&world_to_camera, center, radius).is_some() {
                voted += 1;
                assert!(
                    sees,
                    "a voting cube at {center} (r {radius}) was culled by the ball {ball:?}"
                );
            } else if !sees {
                culled += 1;
            }
        }
        // The draw covers both sides of the border.
        assert!(voted > 10_000 && culled > 10_000, "{voted} voted, {culled} culled");
    }

    #[test]
    fn bit_level_helpers_match_libm() {
        let mut seed = 7u64;
        for _ in 0..100_000 {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            let unit = (seed >> 11) as f64 / (1u64 << 53) as f64;
            let x = 1.0 + unit * 5000.0;
            assert_eq!(floor_log2(x), x.log2().floor() as usize, "floor_log2({x})");
            let y = unit * 4000.0 - 2000.0;
            assert_eq!(nearest(y), (y + 0.5).floor(), "nearest({y})");
            let a = unit * 2.0 - 1.0;
            assert_eq!(bin_of(a), (((a + 1.0) / 2.0 * 8.0).floor() as usize).min(BINS - 1));
        }
        assert_eq!(floor_log2(1.0), 0);
        assert_eq!(floor_log2(4.0), 2);
        assert_eq!(floor_log2(7.999_999), 2);
        assert_eq!(nearest(-0.5), 0.0);
        assert_eq!(nearest(2.5), 3.0);
        assert_eq!(nearest(-2.6), -3.0);
    }
}
