//! The histogram stage's voting loop for pinhole maps: sixteen cubes at a time as the lanes
//! of `fearless_simd`'s `f32x16` ([`vote_block`]), in the widest vectors the processor has
//! (one AVX-512 instruction for the sixteen lanes, two AVX2 ones, four SSE ones on an older
//! x86-64 or NEON ones on aarch64), each lane the operations of [`vote_relative`] in their
//! order, so the votes are the same to the bit (tested against it at every vector level the
//! processor has). The crate picks the level at run time and keeps `unsafe` out of this one;
//! the pixel reads' AVX-512 gathers are in `sys` ([`crate::sys::LevelGather`]).
//!
//! Why lanes without branches: the one-cube vote leaves early on each outcome (behind the
//! camera, outside the image, an invalid pixel, far behind the surface, a square across a
//! depth edge), and along a chunk of cubes that straddles a surface those outcomes change
//! from cube to cube. Here every lane computes everything and each outcome is a mask; the
//! work left per lane is the four pixel reads of a 2 x 2 square (which also holds the
//! nearest pixel) and the addition into the cube's histogram row, none of which branches on
//! the outcome. History: the loop it replaced projected four cubes at once but finished each
//! lane with the one-cube branches (`cargo bench --bench votes`: 41 to 84-95 million
//! cube-map tests per second on 2 cores with four lanes of glam's `Vec4`). RedKitchen's
//! histogram step (1000 frames, `--max-depth 10`, a 2-core AMD EPYC VM with AVX-512), the
//! same segments byte for byte throughout: four lanes 10.4-11.6 s, eight lanes with the
//! branch-free read 8.9-9.1 s, and in a faster hour eight lanes 7.9-8.0 s against sixteen
//! 7.3-7.6 s (sixteen in AVX2 alone: 7.9-8.4 s, as fast as eight).
//!
//! [`vote_relative`]: super::votes::vote_relative

use fearless_simd::prelude::*;
use fearless_simd::{f32x16, i32x16, u32x16};
use glam::Vec4;

use super::votes::{BINS, Pyramid, UnitView};

/// Cubes voted at once.
pub const LANES: usize = 16;

/// Pyramid levels a block can address: a level of 2^31 pixels would be wider than any image.
const MAX_LEVELS: usize = 32;

/// Each pyramid level as the lanes read it: its pixels by level, and the full-resolution
/// width and height, from which a lane computes its level's shape (the row stride is the
/// width): [`Pyramid::new`] halves each level rounding up, so level l is ceil(size / 2^l).
pub struct LevelShapes<'a> {
    pixels: [&'a [f32]; MAX_LEVELS],
    width: f32,
    height: f32,
    /// The last level's scale, 2^(levels - 1) (at most 2^(`MAX_LEVELS` - 1)).
    top_scale: f32,
    /// The levels for AVX-512 gathers, where the pyramid has few enough
    /// ([`crate::sys::GATHER_LEVELS`]).
    #[cfg(target_arch = "x86_64")]
    gather: Option<crate::sys::LevelGather<'a>>,
}

/// Sizes the lanes compute exactly in f32 (`ceil(size * 2^-l)`): below 2^24 pixels a side.
const LARGEST_LANE_SIDE: f32 = 16_777_216.0;

/// Pixels a level may hold for the lanes' i32 indices into it: below 2^31.
const LARGEST_LANE_PIXELS: f64 = 2_147_483_648.0;

impl<'a> LevelShapes<'a> {
    /// The shapes of `pyramid`'s levels (made once per map and unit, not per block).
    pub fn of(pyramid: &'a Pyramid) -> LevelShapes<'a> {
        let mut shapes = LevelShapes {
            pixels: [&[]; MAX_LEVELS],
            width: 0.0,
            height: 0.0,
            top_scale: 1.0,
            #[cfg(target_arch = "x86_64")]
            gather: None,
        };
        if let Some(full) = pyramid.levels.first() {
            (shapes.width, shapes.height) = (full.width as f32, full.height as f32);
        }
        for (l, (image, pixels)) in pyramid.levels.iter().zip(&mut shapes.pixels).enumerate() {
            debug_assert_eq!(
                (image.width, image.height),
                (
                    (shapes.width as u32).div_ceil(1 << l),
                    (shapes.height as u32).div_ceil(1 << l)
                ),
                "level {l}"
            );
            *pixels = &image.depth;
        }
        let top = pyramid.levels.len().clamp(1, MAX_LEVELS) as u32 - 1;
        shapes.top_scale = f32::from_bits((top + 127) << 23);
        #[cfg(target_arch = "x86_64")]
        {
            shapes.gather = crate::sys::LevelGather::new(&shapes.pixels);
        }
        shapes
    }

    /// Whether [`vote_block`] may vote this pyramid: it holds a level, its sides are below
    /// [`LARGEST_LANE_SIDE`] and its full level's pixels below [`LARGEST_LANE_PIXELS`] (a
    /// larger map votes one cube at a time, as the reference does).
    pub fn fits_lanes(&self) -> bool {
        let side = |size: f32| (1.0..LARGEST_LANE_SIDE).contains(&size);
        side(self.width) && side(self.height) && f64::from(self.width) * f64::from(self.height) < LARGEST_LANE_PIXELS
    }
}

/// What [`vote_block`] found for each lane.
pub struct BlockVotes {
    /// The bin of each lane (meaningful where it votes), below [`BINS`].
    pub bin: [i32; LANES],
    /// Bit `lane` is set where the lane votes.
    pub voting: u32,
    /// The map's weight where the lane votes, else 0.
    pub weight: [f32; LANES],
    /// The map's weight where the vote measured a distance, else 0.
    pub distance_weight: [f32; LANES],
    /// The vote's truncated distance where it measured one, else 0.
    pub distance: [f32; LANES],
}

impl BlockVotes {
    /// No lane votes.
    const NONE: BlockVotes = BlockVotes {
        bin: [0; LANES],
        voting: 0,
        weight: [0.0; LANES],
        distance_weight: [0.0; LANES],
        distance: [0.0; LANES],
    };

    /// Adds the block's votes to its cubes' histogram rows and distance sums, both in lane
    /// layout ([`super::vote_batches::relayout_for_lanes`]: bin b of the sixteen cubes, then
    /// bin b + 1; the sixteen sums, then the sixteen weights), and returns how many lanes
    /// voted. Each bin's vector adds the weights of the lanes that voted into it and keeps
    /// the other lanes' values as they were (a masked addition): eight vector additions where
    /// the cube-by-cube rows took a scalar addition per lane, with the bin taken out of its
    /// vector, a fifth of the block's instructions. Adding a zero weight to a sum leaves it as
    /// it was (sums start at +0, and a sum of roundings to nearest is -0 only when both terms
    /// are), so a lane that does not vote changes no sum, without a branch on it.
    #[inline(always)]
    pub fn add_to<S: Simd>(&self, simd: S, rows: &mut [f32; BINS * LANES], sums: &mut [f32; 2 * LANES]) -> u64 {
        let bins = i32x16::from_slice(simd, &self.bin);
        let weights = f32x16::from_slice(simd, &self.weight);
        let (by_bin, _) = rows.as_chunks_mut::<LANES>();
        for (bin, row) in (0i32..).zip(by_bin) {
            let values = f32x16::from_slice(simd, row);
            bins.simd_eq(i32x16::splat(simd, bin))
                .select(values + weights, values)
                .store_slice(row);
        }
        let distance_weight = f32x16::simd_from(simd, self.distance_weight);
        let distance = f32x16::simd_from(simd, self.distance);
        let (sum, total) = sums.split_at_mut(LANES);
        (f32x16::from_slice(simd, sum) + distance_weight * distance).store_slice(sum);
        (f32x16::from_slice(simd, total) + distance_weight).store_slice(total);
        u64::from(self.voting.count_ones())
    }
}

/// Sixteen lanes of one value.
#[inline(always)]
fn splat<S: Simd>(simd: S, value: f32) -> f32x16<S> {
    f32x16::splat(simd, value)
}

/// Algorithm 1 for sixteen cubes of a pinhole map (offsets from the unit's origin and voting
/// radii, as [`super::votes::cube_offsets`] makes them, in lane layout:
/// [`super::vote_batches::relayout_cubes`]), with vote weight `weight`, in the
/// vectors of `simd` (AVX-512 where the processor has it: one instruction for the sixteen
/// lanes; AVX2 two, SSE four).
///
/// The operations per lane are [`super::votes::vote_relative`]'s in its order but these,
/// which give the same values: a division by the level's scale 2^l is a multiplication by
/// 2^-l (both exact); the level is the footprint's binary exponent where the reference counts
/// the leading zeros of its integer part (the same for footprints of 1 to 2^31, and both are
/// capped at the top level); the bilinear square lies inside the level where its corner's
/// coordinates lie in `[0, size - 1)` (for an integer size, `trunc(x) + 1 < size` exactly
/// when `x < size - 1`); and the nearest pixel of a lane inside its square is the square's
/// corner that `x + 0.5 >= x0 + 1` picks, the floor's own comparison. Minima and maxima take
/// vector semantics, which differ from `f32::min` only on NaN, and a lane whose values are
/// NaN does not vote or measure either way; so does the truncation to integers, which only
/// lanes inside the image (below 2^31) use.
///
/// `shapes` must [fit the lanes](LevelShapes::fits_lanes); a larger map's lanes would read
/// the wrong pixels (inside the pyramid, but not the reference's).
#[inline(always)]
pub fn vote_block<S: Simd>(
    simd: S,
    view: &UnitView,
    cubes: &[Vec4; LANES],
    shapes: &LevelShapes<'_>,
    weight: f32,
) -> BlockVotes {
    let m = view.unit_to_camera;
    let k = view.intrinsics;
    let (xs, ys, zs, radius) = transposed(simd, cubes);
    let row = |axis: usize| {
        let pick = |column: Vec4| splat(simd, column[axis]);
        pick(m.x_axis) * xs + pick(m.y_axis) * ys + pick(m.z_axis) * zs + pick(m.w_axis)
    };
    let (lx, ly, lz) = (row(0), row(1), row(2));
    let u = splat(simd, k.x) * lx / lz + splat(simd, k.z);
    let v = splat(simd, k.y) * ly / lz + splat(simd, k.w);
    let one = splat(simd, 1.0);
    let footprint = splat(simd, 2.0) * radius * (splat(simd, k.x.max(k.y)) / lz);
    // The level's scale 2^l: the footprint with its mantissa cleared (2 to the footprint's
    // binary exponent), capped at the top level's; 1 where the footprint is at most 1 or NaN.
    let exponent = f32x16::from_bits(footprint.to_bits() & 0x7f80_0000);
    let scale = footprint
        .simd_gt(one)
        .select(exponent.min(splat(simd, shapes.top_scale)), one);
    // 2^-l and l, on the scale's exponent field.
    let inverse_scale = f32x16::from_bits(u32x16::splat(simd, 254 << 23) - scale.to_bits());
    let level = ((scale.to_bits() >> 23) - 127) & (MAX_LEVELS as u32 - 1);
    // ceil(size / 2^l), exact: the size is below 2^24 (`LevelShapes::fits_lanes`) and the
    // scaling is by a power of two.
    let width = (splat(simd, shapes.width) * inverse_scale).ceil();
    let height = (splat(simd, shapes.height) * inverse_scale).ceil();
    let half = splat(simd, 0.5);
    // Level-pixel coordinates, pixel centres at integers.
    let x_level = (u - (scale - one) * half) * inverse_scale;
    let y_level = (v - (scale - one) * half) * inverse_scale;
    // The nearest pixel: floor(x + 0.5), which is the truncation where it is inside.
    let (x, y) = (x_level + half, y_level + half);
    let zero = splat(simd, 0.0);
    let inside = lz.simd_gt(zero) & x.simd_ge(zero) & y.simd_ge(zero) & x.simd_lt(width) & y.simd_lt(height);
    if !inside.any_true() {
        // Along a chunk that a frustum's side crosses, whole blocks fall outside the image
        // (a fifth of RedKitchen's cube-map tests in blocks of four): nothing to read or vote.
        return BlockVotes::NONE;
    }
    // The bilinear square lies inside the level where its corner's coordinates lie in
    // [0, size - 1); elsewhere a lane inside the image votes with its nearest pixel alone.
    let in_square = inside
        & x_level.simd_ge(zero)
        & y_level.simd_ge(zero)
        & x_level.simd_lt(width - one)
        & y_level.simd_lt(height - one);
    let (cx, cy): (i32x16<S>, i32x16<S>) = (x_level.to_int(), y_level.to_int());
    let (x0, y0): (f32x16<S>, f32x16<S>) = (cx.to_float(), cy.to_float());
    let (nx, ny): (i32x16<S>, i32x16<S>) = (x.to_int(), y.to_int());
    // Every lane reads the 2 x 2 pixels at its square's corner moved inside the level: the
    // square itself where it lies inside, and a square that holds the nearest pixel (at most
    // one pixel from it on each axis) at the edges, for a lane inside the image. Reading every
    // lane the same way leaves the loop without branches on the lanes' outcomes, which change
    // from cube to cube along a surface; lanes outside the image read some pixel (or none:
    // NaN) and neither vote nor measure.
    let (width_i, height_i): (i32x16<S>, i32x16<S>) = (width.to_int(), height.to_int());
    let (zero_i, two_i) = (i32x16::splat(simd, 0), i32x16::splat(simd, 2));
    let bx = cx.max(zero_i).min((width_i - two_i).max(zero_i));
    let by = cy.max(zero_i).min((height_i - two_i).max(zero_i));
    let (right, below) = (nx.simd_gt(bx), ny.simd_gt(by));
    let [a00, a10, a01, a11] = squares(simd, shapes, level, by * width_i + bx, width_i);
    // In the square, the nearest pixel is the corner that `x + 0.5 >= x0 + 1` picks, the
    // floor's own comparison; at the edges, the one the truncations of x and y name.
    let depth = below.select(right.select(a11, a01), right.select(a10, a00));
    let delta = splat(simd, 6.0) * radius;
    let eta = splat(simd, 3.0) * delta;
    let a = depth - lz;
    // depth > 0 also rejects the NaN of a lane that read no pixel.
    let voting = inside & depth.simd_gt(zero) & !a.simd_lt(-eta);
    // The bin: (a / delta) clamped to [-1, 1] and mapped to [0, 8], whose truncation is capped
    // at the last bin (the cap taken before truncating, the same for values in [0, 8]).
    let bin = ((a / delta).max(splat(simd, -1.0)).min(one) + one) / splat(simd, 2.0) * splat(simd, 8.0);
    let bin: [i32; LANES] = bin.min(splat(simd, (BINS - 1) as f32)).to_int::<i32x16<S>>().into();
    let band = (splat(simd, view.band_per_delta) * delta).max(splat(simd, view.band_floor));
    let valid = a00.simd_gt(zero) & a10.simd_gt(zero) & a01.simd_gt(zero) & a11.simd_gt(zero);
    let low = a00.min(a10).min(a01.min(a11));
    let high = a00.max(a10).max(a01.max(a11));
    let (fx, fy) = (x_level - x0, y_level - y0);
    let (gx, gy) = (one - fx, one - fy);
    let surface = (a00 * gx + a10 * fx) * gy + (a01 * gx + a11 * fx) * fy;
    let measured = surface - lz;
    let measures = voting & in_square & valid & (high - low).simd_le(band) & measured.simd_ge(-band);
    let weights = splat(simd, weight);
    BlockVotes {
        bin: bin.map(|b| b & (BINS as i32 - 1)),
        voting: voting.to_bitmask() as u32,
        weight: voting.select(weights, zero).into(),
        distance_weight: measures.select(weights, zero).into(),
        distance: measures.select(measured.min(band), zero).into(),
    }
}

/// The depths of each lane's 2 x 2 square: pixels `at`, `at + 1`, `at + stride` and `at +
/// stride + 1` of level `level` (`shapes.pixels[level]`), NaN for each of them the level does
/// not hold (a level one pixel wide or high). Where the processor has AVX-512, the squares the
/// level holds whole are read by gathers, two pixels an element
/// ([`crate::sys::LevelGather::squares`]), and only the others pixel by pixel: RedKitchen's
/// histogram step (1000 frames, `--max-depth 10`, 91.7 M blocks, 2-core AMD EPYC VM) took
/// 5.9-7.2 s alternating with 6.1-7.7 s for reads lane by lane, the same segments.
#[inline(always)]
fn squares<S: Simd>(
    simd: S,
    shapes: &LevelShapes<'_>,
    level: u32x16<S>,
    at: i32x16<S>,
    stride: i32x16<S>,
) -> [f32x16<S>; 4] {
    let mut gathered = 0u16;
    let mut corners = [[f32::NAN; LANES]; 4];
    #[cfg(target_arch = "x86_64")]
    if let (fearless_simd::Level::Avx512(token), Some(gather)) = (simd.level(), &shapes.gather) {
        let avx512 = |lanes: i32x16<S>| i32x16::simd_from(token, <[i32; LANES]>::from(lanes));
        let (square, inside) = gather.squares(token, avx512(level.bitcast()), avx512(at), avx512(stride));
        if inside == u16::MAX {
            return square.map(|depths| f32x16::simd_from(simd, <[f32; LANES]>::from(depths)));
        }
        corners = square.map(<[f32; LANES]>::from);
        gathered = inside;
    }
    let (level, at, stride): ([u32; LANES], [i32; LANES], [i32; LANES]) = (level.into(), at.into(), stride.into());
    for lane in (0..LANES).filter(|lane| gathered & (1 << lane) == 0) {
        let (at, s) = (at[lane] as u32 as usize, stride[lane] as u32 as usize);
        let pixels = shapes.pixels[level[lane] as usize & (MAX_LEVELS - 1)];
        let square = match pixels.get(at..at + s + 2) {
            Some(&[d00, d10, .., d01, d11]) => [d00, d10, d01, d11],
            // A level one pixel wide or high, or a lane outside the image.
            _ => [at, at + 1, at + s, at + s + 1].map(|i| pixels.get(i).copied().unwrap_or(f32::NAN)),
        };
        for (corner, depth) in corners.iter_mut().zip(square) {
            corner[lane] = depth;
        }
    }
    corners.map(|corner| f32x16::simd_from(simd, corner))
}

/// The cubes' x, y, z and radius, each as sixteen lanes, from a block in lane layout
/// ([`super::vote_batches::relayout_for_lanes`]): four loads where the per-cube layout took
/// twelve shuffles a block.
#[inline(always)]
fn transposed<S: Simd>(simd: S, cubes: &[Vec4; LANES]) -> (f32x16<S>, f32x16<S>, f32x16<S>, f32x16<S>) {
    let flat: &[f32; 4 * LANES] = bytemuck::cast_ref(cubes);
    let (quarters, _) = flat.as_chunks::<LANES>();
    let quarter = |q: usize| {
        quarters
            .get(q)
            .map_or(f32x16::splat(simd, f32::NAN), |part| f32x16::from_slice(simd, part))
    };
    (quarter(0), quarter(1), quarter(2), quarter(3))
}

#[cfg(test)]
mod tests {
    use fearless_simd::Level;
    use glam::DVec3;

    use super::*;
    use crate::kernels::votes::{Pyramid, vote_relative};

    /// Every vector level this processor has, by name: the one dispatch picks and each
    /// weaker x86-64 level, whose vectors are narrower (two or four instructions a block).
    pub(crate) fn vector_levels() -> Vec<(&'static str, Level)> {
        let best = Level::new();
        let mut levels = vec![("best", best)];
        #[cfg(target_arch = "x86_64")]
        {
            levels.extend(best.as_sse2().map(|token| ("sse2", Level::Sse2(token))));
            levels.extend(best.as_sse4_2().map(|token| ("sse4.2", Level::Sse4_2(token))));
            levels.extend(best.as_avx2().map(|token| ("avx2", Level::Avx2(token))));
        }
        levels
    }

    /// The test wall's size: odd, so its pyramid rounds up at every level.
    const WALL: (u32, u32) = (53, 41);

    /// A pinhole map of the test wall's size, posed by `pose`.
    fn wall_source(pose: glam::DMat4) -> crate::inputs::DepthMapSource {
        crate::inputs::DepthMapSource::test_pinhole("wall.pfm", WALL, [45.0, 40.0, 26.0, 20.5], pose)
    }

    #[test]
    fn sixteen_cubes_as_lanes_vote_as_one_cube_does_to_the_bit_at_every_vector_level() {
        // A slanted wall with holes, cubes in front, behind, beside the view and behind the
        // camera, of radii from a fraction of a pixel's footprint to many pixels.
        let (width, height) = WALL;
        let source =
            wall_source(glam::DMat4::from_translation(DVec3::new(3.0, -1.0, 2.0)) * glam::DMat4::from_rotation_y(0.3));
        let wall = crate::kernels::votes::tests::slanted_wall((width, height), 17, 2.0, 0.01);
        let pyramid = Pyramid::new(source.clone(), wall);
        let shapes = LevelShapes::of(&pyramid);
        let world_to_camera = source.pose().inverse();
        let origin = DVec3::new(3.5, -0.8, 4.0);
        let view = UnitView::new(&source, &world_to_camera, origin, 0.05);
        for (name, level) in vector_levels() {
            let mut seed = 5u64;
            let mut uniform = move || crate::kernels::random::uniform(&mut seed) as f32;
            let (mut voted, mut refused, mut measured) = (0, 0, 0);
            for _ in 0..10_000 {
                let cubes: [Vec4; LANES] = std::array::from_fn(|_| {
                    Vec4::new(
                        uniform() * 6.0 - 3.0,
                        uniform() * 4.0 - 2.0,
                        uniform() * 6.0 - 3.5,
                        // Up to footprints past the top level's 64 pixels.
                        0.002 * 5000f32.powf(uniform()),
                    )
                });
                let weight = 0.75;
                let block = crate::kernels::vote_batches::relayout_cubes(&cubes, true);
                let lanes = fearless_simd::dispatch!(level, simd => vote_block(simd, &view, &block, &shapes, weight));
                for (lane, cube) in cubes.iter().enumerate() {
                    let one = vote_relative(&view, *cube, &pyramid);
                    let voting = lanes.voting & (1 << lane) != 0;
                    assert_eq!(lanes.weight[lane] != 0.0, voting, "{name}");
                    let got = voting.then(|| {
                        let distance = (lanes.distance_weight[lane] != 0.0).then_some(lanes.distance[lane]);
                        (lanes.bin[lane] as usize, distance.map(f32::to_bits))
                    });
                    assert_eq!(
                        got,
                        one.map(|(bin, d)| (bin, d.map(f32::to_bits))),
                        "{name}: cube {cube}"
                    );
                    match one {
                        Some((_, Some(_))) => measured += 1,
                        Some(_) => voted += 1,
                        None => refused += 1,
                    }
                }
            }
            assert!(
                voted > 1_000 && refused > 5_000 && measured > 5_000,
                "{name}: {voted} voted without a distance, {measured} with one, {refused} refused"
            );
        }
    }

    #[test]
    fn lanes_that_do_not_vote_leave_the_rows_as_they_were() {
        // Lanes 8 to 15 repeat lanes 0 to 7 (so both halves of the vectors are checked).
        let twice = |half: [f32; 8]| -> [f32; LANES] { std::array::from_fn(|lane| half[lane % 8]) };
        let votes = BlockVotes {
            bin: std::array::from_fn(|lane| [3, 0, 7, 7, 1, 2, 0, 5][lane % 8]),
            voting: 0b0110_1101_0110_1101,
            weight: twice([1.0, 0.0, 0.5, 2.0, 0.0, 0.25, 1.5, 0.0]),
            distance_weight: twice([1.0, 0.0, 0.0, 2.0, 0.0, 0.25, 0.0, 0.0]),
            distance: twice([-0.25, 0.0, 0.0, 0.125, 0.0, 4.0, 0.0, 0.0]),
        };
        for (name, level) in vector_levels() {
            let mut rows = [[0f32; BINS]; LANES];
            let mut sums = [[0f32; 2]; LANES];
            for half in [0, 8] {
                rows[half + 1][0] = 4.0;
                sums[half + 1] = [-3.0, 4.0];
                sums[half + 7] = [1.5, 2.0];
            }
            // The block's rows and sums in lane layout, as the voting loop holds them, and back.
            let mut offsets = [Vec4::ZERO; LANES];
            let (mut row_lanes, mut sum_lanes): ([f32; BINS * LANES], [f32; 2 * LANES]) =
                (bytemuck::cast(rows), bytemuck::cast(sums));
            crate::kernels::vote_batches::relayout_for_lanes(&mut offsets, &mut row_lanes, &mut sum_lanes, true);
            let cast = fearless_simd::dispatch!(level, simd => votes.add_to(simd, &mut row_lanes, &mut sum_lanes));
            crate::kernels::vote_batches::relayout_for_lanes(&mut offsets, &mut row_lanes, &mut sum_lanes, false);
            rows = bytemuck::cast(row_lanes);
            sums = bytemuck::cast(sum_lanes);
            assert_eq!(cast, 10, "{name}");
            for half in [0, 8] {
                assert_eq!(rows[half][3], 1.0);
                assert_eq!((rows[half + 1][0], sums[half + 1]), (4.0, [-3.0, 4.0]), "{name}");
                assert_eq!((rows[half + 2][7], sums[half + 2]), (0.5, [0.0, 0.0]), "{name}");
                assert_eq!(sums[half], [-0.25, 1.0], "{name}");
                assert_eq!((rows[half + 3][7], sums[half + 3]), (2.0, [0.25, 2.0]), "{name}");
                assert_eq!((rows[half + 5][2], sums[half + 5]), (0.25, [1.0, 0.25]), "{name}");
                assert_eq!((rows[half + 6][0], sums[half + 6]), (1.5, [0.0, 0.0]), "{name}");
                assert_eq!(sums[half + 7], [1.5, 2.0], "{name}");
            }
            // No lane left a negative zero behind: every untouched value is +0.
            for (row, sum) in rows.iter().zip(&sums) {
                assert!(
                    row.iter().chain(sum).all(|v| *v != 0.0 || v.is_sign_positive()),
                    "{name}"
                );
            }
        }
    }

    #[test]
    fn maps_too_large_for_the_lanes_are_told_apart() {
        let shapes = |width: f32, height: f32| LevelShapes {
            pixels: [&[]; MAX_LEVELS],
            width,
            height,
            top_scale: 1.0,
            #[cfg(target_arch = "x86_64")]
            gather: None,
        };
        assert!(shapes(640.0, 480.0).fits_lanes());
        assert!(shapes(16_777_215.0, 1.0).fits_lanes());
        // A side whose halvings f32 no longer computes exactly, a level whose pixels an i32
        // index cannot reach, no level at all.
        assert!(!shapes(16_777_216.0, 1.0).fits_lanes());
        assert!(!shapes(50_000.0, 50_000.0).fits_lanes());
        assert!(!shapes(0.0, 0.0).fits_lanes());
    }

    #[test]
    fn level_shapes_follow_the_pyramid_s_halving() {
        // Odd sizes: each level is the one above halved, rounding up, down to one pixel.
        let (width, height) = WALL;
        let source = wall_source(glam::DMat4::IDENTITY);
        let pyramid = Pyramid::new(
            source,
            crate::kernels::votes::tests::slanted_wall((width, height), 5, 1.0, 0.0),
        );
        let shapes = LevelShapes::of(&pyramid);
        assert!(shapes.fits_lanes());
        assert_eq!(pyramid.levels.len(), 7);
        assert_eq!(shapes.top_scale, 64.0);
        for (l, image) in pyramid.levels.iter().enumerate() {
            let scale = (1u32 << l) as f32;
            assert_eq!((width as f32 / scale).ceil(), image.width as f32, "level {l}");
            assert_eq!((height as f32 / scale).ceil(), image.height as f32, "level {l}");
            assert_eq!(shapes.pixels[l].len(), image.depth.len());
        }
    }
}
