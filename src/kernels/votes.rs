//! The vote math of the histogram stage (paper 3.4, Algorithm 1): bins, the depth-map
//! pyramid and the projection of a cube into a depth map (the chunked voting loop is
//! `vote_batches`, re-exported here). Pure functions of cubes and depth maps: no store, no
//! catalog, so the GPU twins test against them.

use glam::{DVec3, Mat4, Vec4};

use super::halving::{halve_finite_first, median_of_finite, median_of_valid};
use super::occlusion::FarthestDepths;
use super::surface_depth::{surface_depth, surface_depth_f32, truncated_surface_distance};
pub use super::vote_batches::{
    Chunk, ChunkedCubes, MAPS_AT_ONCE, MapVote, chunks, relayout_for_lanes, vote_chunks, vote_maps,
};

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
/// Chamfer 0.00117 to 0.00157, normal consistency 0.974 to 0.959).
/// Since distances read the surface bilinearly ([`crate::kernels::surface_depth`]) a floor of
/// 3 sides gives the clean bunny Chamfer 0.00073 instead of 0.00118, but the table's ridges
/// come back (measured 2026-11-25): a band that tells grazing views from views of another
/// surface would need the surface's normal in the vote.
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
    let band = distance_band(delta, floor);
    (a >= -band).then_some(a.min(band))
}

/// The truncation band T of [`truncated_distance`]: [`DISTANCE_BAND_PER_DELTA`] x delta, at
/// least `floor`.
pub fn distance_band(delta: f64, floor: f64) -> f64 {
    (DISTANCE_BAND_PER_DELTA * delta).max(floor)
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
    /// Block maxima of the full-resolution depths, for occlusion culling.
    pub farthest: FarthestDepths,
}

impl Pyramid {
    pub fn new(source: DepthMapSource, image: DepthImage) -> Pyramid {
        let farthest = FarthestDepths::new(&image);
        let mut levels = vec![image];
        while let Some(last) = levels.last() {
            if last.width <= 1 && last.height <= 1 {
                break;
            }
            let next = halve_finite_first(last, median_of_finite, median_of_valid);
            levels.push(next);
        }
        Pyramid {
            source,
            levels,
            farthest,
        }
    }

    /// Bytes the decoded levels take.
    pub fn bytes(&self) -> u64 {
        self.levels
            .iter()
            .map(|level| (level.depth.len() * std::mem::size_of::<f32>()) as u64)
            .sum::<u64>()
            + self.farthest.bytes()
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
        // Level-pixel coordinates, pixel centres at integers.
        let (x_level, y_level) = ((u - (scale - 1.0) * 0.5) / scale, (v - (scale - 1.0) * 0.5) / scale);
        let (i, j) = (nearest(x_level), nearest(y_level));
        let spherical = matches!(self.source.projection, Projection::Spherical);
        let i = if spherical {
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
        // The bin reads the nearest pixel; the distance measures the surface where the centre
        // projects (kernels::surface_depth).
        let band = distance_band(delta, band_floor);
        let measured = surface_depth(image, x_level, y_level, spherical, band)
            .and_then(|surface| truncated_distance(surface - distance, delta, band_floor));
        Some((bin_of((a / delta).clamp(-1.0, 1.0)), measured))
    }

    /// Whether any cube whose centre lies in the ball, and whose voting radius is at most the
    /// ball's radius, may vote: [`Self::may_see_ball`] with the ball's radius for the voting
    /// radii.
    pub fn may_see(source: &DepthMapSource, world_to_camera: &glam::DMat4, center: DVec3, radius: f64) -> bool {
        Self::may_see_ball(source, world_to_camera, center, radius, radius)
    }

    /// Whether any cube whose centre lies in the ball (`center`, `radius`), and whose voting
    /// radius is at most `voting_radius`, may vote: a frustum test that is conservative by
    /// construction (LIDAR sees all around).
    ///
    /// `vote` reads the pixel nearest the projected centre at a level whose pixel spans at most
    /// the cube's footprint `2 r f / z`, and a level's last pixel may reach one level pixel past
    /// the image edge. So a voting centre satisfies `-0.5 <= u < width + 2 r f / z`, that is,
    /// it lies at most `2 r f / n` beyond the side plane `u = width` (n the plane normal's
    /// length), and never beyond `u = -0.5`. A ball is culled only when it lies wholly beyond
    /// such a widened plane (one pixel of slack on every side). The widening follows the
    /// voting radius, not the ball's: a chunk of 256 cubes on a wall spans a ball ten times
    /// its cubes' radius, and widening every side by the ball's footprint kept chunks that
    /// lie wholly outside the image.
    pub fn may_see_ball(
        source: &DepthMapSource,
        world_to_camera: &glam::DMat4,
        center: DVec3,
        radius: f64,
        voting_radius: f64,
    ) -> bool {
        FrustumTest::new(source).may_see_ball(world_to_camera, center, radius, voting_radius)
    }
}

/// [`Pyramid::may_see_ball`] of one map, its four side planes made once: the histogram stage
/// tests every chunk of a unit against every map, and the planes' lengths (square roots) were
/// most of a test. The same operations on the same values, so the same outcomes.
pub enum FrustumTest {
    /// A 360-degree map sees all around.
    Everywhere,
    /// Each side of a pinhole map: the plane's normal (pointing out of the image) through the
    /// camera centre, its length, and the widening allowed beyond it per unit of voting radius.
    Sides([(DVec3, f64, f64); 4]),
}

impl FrustumTest {
    /// The planes of `source`'s frustum.
    pub fn new(source: &DepthMapSource) -> FrustumTest {
        match source.projection {
            Projection::Spherical => FrustumTest::Everywhere,
            Projection::Pinhole { fx, fy, cx, cy } => {
                let f = fx.max(fy);
                let (w, h) = (f64::from(source.width), f64::from(source.height));
                let sides = [
                    (DVec3::new(-fx, 0.0, -(cx + 1.0)), 0.0),
                    (DVec3::new(0.0, -fy, -(cy + 1.0)), 0.0),
                    (DVec3::new(fx, 0.0, cx - w - 1.0), 2.0 * f),
                    (DVec3::new(0.0, fy, cy - h - 1.0), 2.0 * f),
                ];
                FrustumTest::Sides(sides.map(|(normal, widening)| (normal, normal.length(), widening)))
            }
        }
    }

    /// [`Pyramid::may_see_ball`] against these planes.
    pub fn may_see_ball(&self, world_to_camera: &glam::DMat4, center: DVec3, radius: f64, voting_radius: f64) -> bool {
        match self {
            FrustumTest::Everywhere => true,
            FrustumTest::Sides(sides) => {
                let p = world_to_camera.transform_point3(center);
                if p.z + radius <= 0.0 {
                    return false;
                }
                sides.iter().all(|(normal, length, widening)| {
                    normal.dot(p) / length <= radius + widening * voting_radius / length
                })
            }
        }
    }
}

/// A depth-map pyramid as the f32 vote reads it: the CPU's [`Pyramid`], or the flat arrays
/// `shaders/votes.wgsl` binds ([`FlatPyramid`]).
pub trait DepthLevels {
    /// The number of levels.
    fn count(&self) -> u32;
    /// Width and height of `level` (< `count`).
    fn shape(&self, level: u32) -> (u32, u32);
    /// The depth at column `i`, row `j` of `level` (both inside its shape); invalid pixels
    /// read as NaN or a value <= 0.
    fn depth(&self, level: u32, i: u32, j: u32) -> f32;
    /// Pixels (i0, j0), (i1, j0), (i0, j0 + 1), (i1, j0 + 1) of `level` (all inside its shape).
    #[inline]
    fn square(&self, level: u32, i0: u32, i1: u32, j0: u32) -> [f32; 4] {
        [
            self.depth(level, i0, j0),
            self.depth(level, i1, j0),
            self.depth(level, i0, j0 + 1),
            self.depth(level, i1, j0 + 1),
        ]
    }
}

impl DepthLevels for Pyramid {
    fn count(&self) -> u32 {
        self.levels.len() as u32
    }

    fn shape(&self, level: u32) -> (u32, u32) {
        self.levels.get(level as usize).map_or((0, 0), |l| (l.width, l.height))
    }

    #[inline]
    fn depth(&self, level: u32, i: u32, j: u32) -> f32 {
        self.levels.get(level as usize).map_or(f32::NAN, |l| l.get(i, j))
    }

    /// The same values as four `depth` reads, with one level lookup and two row slices: the
    /// distance's square is read on every vote.
    #[inline]
    fn square(&self, level: u32, i0: u32, i1: u32, j0: u32) -> [f32; 4] {
        let Some(image) = self.levels.get(level as usize) else {
            return [f32::NAN; 4];
        };
        let width = image.width as usize;
        let start = j0 as usize * width;
        let (Some(upper), Some(lower)) = (
            image.depth.get(start..start + width),
            image.depth.get(start + width..start + 2 * width),
        ) else {
            return [f32::NAN; 4];
        };
        let read = |row: &[f32], i: u32| row.get(i as usize).copied().unwrap_or(f32::NAN);
        [read(upper, i0), read(upper, i1), read(lower, i0), read(lower, i1)]
    }
}

/// A pyramid as the shader binds it: a (first index, width, height, 0) row per level and all
/// depths in one array, invalid pixels as -1 (the shader tests `depth > 0`, which a GPU
/// compiler may not fold away the way it may fold a NaN test).
pub fn pyramid_arrays(pyramid: &Pyramid) -> (Vec<[u32; 4]>, Vec<f32>) {
    let mut levels = Vec::with_capacity(pyramid.levels.len());
    let mut depths = Vec::new();
    for level in &pyramid.levels {
        levels.push([depths.len() as u32, level.width, level.height, 0]);
        depths.extend(
            level
                .depth
                .iter()
                .map(|d| if d.is_finite() && *d > 0.0 { *d } else { -1.0 }),
        );
    }
    (levels, depths)
}

/// [`pyramid_arrays`]' arrays, read as a pyramid.
pub struct FlatPyramid<'a> {
    pub levels: &'a [[u32; 4]],
    pub depths: &'a [f32],
}

impl DepthLevels for FlatPyramid<'_> {
    fn count(&self) -> u32 {
        self.levels.len() as u32
    }

    fn shape(&self, level: u32) -> (u32, u32) {
        self.levels.get(level as usize).map_or((0, 0), |l| (l[1], l[2]))
    }

    fn depth(&self, level: u32, i: u32, j: u32) -> f32 {
        let first = self.levels.get(level as usize).map_or(0, |l| l[0] as usize);
        let width = self.levels.get(level as usize).map_or(0, |l| l[1] as usize);
        self.depths
            .get(first + j as usize * width + i as usize)
            .copied()
            .unwrap_or(-1.0)
    }
}

/// One depth map as seen from a unit, for the f32 vote: the world-to-camera transform composed
/// with the unit's origin in f64 and rounded to f32 once, so cube offsets from the origin stay
/// small and exact enough (a few metres from the origin, f32 keeps well under a micrometre).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct UnitView {
    pub unit_to_camera: Mat4,
    /// fx, fy, cx, cy of a pinhole map (zero for a spherical one).
    pub intrinsics: Vec4,
    pub spherical: bool,
    pub width: u32,
    pub height: u32,
    /// [`DISTANCE_BAND_PER_DELTA`].
    pub band_per_delta: f32,
    /// The least band, world units ([`band_floor`]).
    pub band_floor: f32,
}

impl UnitView {
    pub fn new(source: &DepthMapSource, world_to_camera: &glam::DMat4, origin: DVec3, band_floor: f64) -> UnitView {
        let unit_to_camera = *world_to_camera * glam::DMat4::from_translation(origin);
        let (intrinsics, spherical) = match source.projection {
            Projection::Pinhole { fx, fy, cx, cy } => (Vec4::new(fx as f32, fy as f32, cx as f32, cy as f32), false),
            Projection::Spherical => (Vec4::ZERO, true),
        };
        UnitView {
            unit_to_camera: unit_to_camera.as_mat4(),
            intrinsics,
            spherical,
            width: source.width,
            height: source.height,
            band_per_delta: DISTANCE_BAND_PER_DELTA as f32,
            band_floor: band_floor as f32,
        }
    }
}

/// A cube's offset from its unit's origin (xyz) and its voting radius (w), in f32.
pub fn cube_offsets(origin: DVec3, centers: &[DVec3], radii: &[f64]) -> Vec<Vec4> {
    centers
        .iter()
        .zip(radii)
        .map(|(c, r)| {
            let d = *c - origin;
            Vec4::new(d.x as f32, d.y as f32, d.z as f32, *r as f32)
        })
        .collect()
}

/// Algorithm 1 for one voxel in f32 on unit-relative coordinates: the bin it votes into and
/// the vote's truncated distance, if any. This is the voting loop's arithmetic and
/// `shaders/votes.wgsl`'s, step for step (its twin, `gpu::twins::votes`, calls it), so CPU and
/// GPU votes differ only by the GPU's rounding. Against the f64 [`Pyramid::vote_with_distance`]
/// it differs only where a value sits on a bin, level or pixel boundary (tests/gpu.rs bounds
/// how often).
#[inline]
#[expect(
    clippy::neg_cmp_op_on_partial_ord,
    reason = "the shader's !(x > 0) tests, which also reject NaN"
)]
pub fn vote_relative(view: &UnitView, cube: Vec4, levels: &impl DepthLevels) -> Option<(usize, Option<f32>)> {
    use std::f32::consts::{PI, TAU};
    let radius = cube.w;
    let local = (view.unit_to_camera * Vec4::new(cube.x, cube.y, cube.z, 1.0)).truncate();
    let (u, v, distance, pixels_per_unit);
    if view.spherical {
        distance = local.length();
        if !(distance > 0.0) {
            return None;
        }
        let mut azimuth = local.y.atan2(local.x);
        if azimuth < 0.0 {
            azimuth += TAU;
        }
        let elevation = (local.z / distance).clamp(-1.0, 1.0).asin();
        u = azimuth / TAU * view.width as f32;
        v = (PI * 0.5 - elevation) / PI * view.height as f32 - 0.5;
        pixels_per_unit = view.width as f32 / TAU / distance;
    } else {
        if !(local.z > 0.0) {
            return None;
        }
        let k = view.intrinsics;
        distance = local.z;
        u = k.x * local.x / local.z + k.z;
        v = k.y * local.y / local.z + k.w;
        pixels_per_unit = k.x.max(k.y) / distance;
    }
    let footprint = 2.0 * radius * pixels_per_unit;
    let mut level = 0u32;
    if footprint > 1.0 {
        level = 31 - (footprint.min(2_147_483_648.0) as u32).leading_zeros();
    }
    let level = level.min(levels.count().saturating_sub(1));
    let (width, height) = levels.shape(level);
    let scale = (1u32 << level) as f32;
    // floor(x + 0.5) of the pixel coordinates; a floor is non-negative and under the size
    // exactly when its argument is, so the bounds are tested before truncating (which is the
    // floor there), without a libm call.
    // Level-pixel coordinates, pixel centres at integers.
    let x_level = (u - (scale - 1.0) * 0.5) / scale;
    let y_level = (v - (scale - 1.0) * 0.5) / scale;
    let mut x = x_level + 0.5;
    let y = y_level + 0.5;
    let width_f = width as f32;
    if view.spherical {
        let i = x.floor();
        x = i - (i / width_f).floor() * width_f;
    }
    if !(x >= 0.0 && y >= 0.0 && x < width_f && y < height as f32) {
        return None;
    }
    let depth = levels.depth(level, x as u32, y as u32);
    if !(depth > 0.0) {
        return None;
    }
    let delta = 6.0 * radius;
    let eta = 3.0 * delta;
    let a = depth - distance;
    if a < -eta {
        return None;
    }
    let bin = ((((a / delta).clamp(-1.0, 1.0) + 1.0) / 2.0 * 8.0) as usize).min(BINS - 1);
    let band = (view.band_per_delta * delta).max(view.band_floor);
    let surface = surface_depth_f32(levels, level, x_level, y_level, view.spherical, band);
    Some((bin, truncated_surface_distance(surface, distance, band)))
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

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    pub(crate) fn pinhole_source(
        path: &str,
        size: (u32, u32),
        k: [f64; 4],
        camera_to_world: glam::DMat4,
    ) -> crate::inputs::DepthMapSource {
        crate::inputs::DepthMapSource::test_pinhole(path, size, k, camera_to_world)
    }

    /// A wall whose depth grows by `slope` a column from `near`, with a hole (NaN) every
    /// `hole_every` pixels.
    pub(crate) fn slanted_wall((width, height): (u32, u32), hole_every: u32, near: f32, slope: f32) -> DepthImage {
        let depth = (0..width * height)
            .map(|p| {
                if p % hole_every == 0 {
                    f32::NAN
                } else {
                    near + slope * (p % width) as f32
                }
            })
            .collect();
        DepthImage { width, height, depth }
    }

    #[test]
    fn pyramid_levels_take_the_median_of_valid_depths() {
        let nan = f32::NAN;
        assert_eq!(median_of_valid([1.0, 9.0, 2.0, 3.0]), 2.5);
        assert_eq!(median_of_valid([1.0, nan, 7.0, 2.0]), 2.0);
        assert_eq!(median_of_valid([nan, 4.0, nan, 2.0]), 3.0);
        assert_eq!(median_of_valid([nan, nan, 5.0, nan]), 5.0);
        assert!(median_of_valid([nan, nan, nan, nan]).is_nan());
        // Four valid values take the sort-free path: the same as sorting, ties included.
        let mut seed = 3u64;
        for _ in 0..20_000 {
            let values: [f32; 4] = std::array::from_fn(|_| {
                let seed = crate::kernels::random::splitmix(&mut seed);
                ((seed >> 40) % 7) as f32 * 0.37 + 1.0
            });
            let mut sorted = values;
            sorted.sort_unstable_by(f32::total_cmp);
            let expected = ((f64::from(sorted[1]) + f64::from(sorted[2])) * 0.5) as f32;
            assert_eq!(median_of_valid(values).to_bits(), expected.to_bits(), "{values:?}");
        }

        // A 4 x 2 wall at depth 1 with one wild pixel per 2 x 2 block: level 1 is the wall
        // (a mean would put the left block at 1.75), level 2 keeps it, and a block without
        // valid pixels stays invalid.
        let source = pinhole_source("wall.pfm", (6, 2), [10.0, 10.0, 3.0, 1.0], glam::DMat4::IDENTITY);
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
        let source = pinhole_source(
            "far.pfm",
            (width, height),
            [30.0, 24.0, 17.0, 12.5],
            glam::DMat4::IDENTITY,
        );
        let depth = vec![1000.0; (width * height) as usize];
        let pyramid = Pyramid::new(source.clone(), DepthImage { width, height, depth });
        let world_to_camera = glam::DMat4::IDENTITY;
        let mut seed = 11u64;
        let mut uniform = move || crate::kernels::random::uniform(&mut seed);
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
            // The same ball, widened by the cube's own voting radius rather than the ball's.
            let tight = Pyramid::may_see_ball(&source, &world_to_camera, ball.0, ball.1, radius);
            if pyramid.vote(&world_to_camera, center, radius).is_some() {
                voted += 1;
                assert!(
                    sees && tight,
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
            let unit = crate::kernels::random::uniform(&mut seed);
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
