//! The histogram stage's voting loop over a unit's cubes: Morton-consecutive runs of cubes
//! (chunks) with the balls that cull them against each map's frustum, and the batches of maps
//! that vote into them chunk by chunk ([`vote_maps`]), each vote [`vote_relative`] (sixteen
//! cubes at a time in [`vote_block`] for pinhole maps).

use glam::{DVec3, Vec4};

use super::vote_lanes::{LANES, LevelShapes, vote_block};
use super::votes::{BINS, Pyramid, UnitView, vote_relative};

/// Cubes per culling chunk: Morton-consecutive cubes are spatially compact, so a chunk's ball
/// stays small near the surface, where the cubes are.
const CHUNK_CUBES: usize = 256;

// A chunk's whole blocks must be the unit's ([`relayout_for_lanes`]): chunks start at
// multiples of a block.
const _: () = assert!(CHUNK_CUBES.is_multiple_of(LANES), "a chunk must hold whole blocks");

/// Cubes `start..end` of a unit and a ball that holds every one of their voting balls.
#[derive(Clone, Debug)]
pub struct Chunk {
    /// First cube of the run.
    pub start: usize,
    /// One past the last cube of the run.
    pub end: usize,
    /// Centre of the ball that holds the run's voting balls.
    pub center: DVec3,
    /// Radius of that ball.
    pub radius: f64,
    /// The largest voting radius of the run's cubes.
    pub max_radius: f64,
}

pub fn chunks(centers: &[DVec3], radii: &[f64]) -> Vec<Chunk> {
    let mut chunks = Vec::with_capacity(centers.len().div_ceil(CHUNK_CUBES));
    let mut start = 0;
    while start < centers.len() {
        let end = (start + CHUNK_CUBES).min(centers.len());
        let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
        let mut max_radius = 0f64;
        for (center, radius) in centers.iter().zip(radii).take(end).skip(start) {
            lo = lo.min(*center - DVec3::splat(*radius));
            hi = hi.max(*center + DVec3::splat(*radius));
            max_radius = max_radius.max(*radius);
        }
        chunks.push(Chunk {
            start,
            end,
            center: (lo + hi) * 0.5,
            radius: (hi - lo).length() * 0.5,
            max_radius,
        });
        start = end;
    }
    chunks
}

/// The cubes of a unit being voted: offsets from the unit's origin with voting radii
/// ([`cube_offsets`]), and their runs of Morton-consecutive cubes ([`chunks`]).
pub struct ChunkedCubes<'a> {
    /// Offset from the unit's origin (xyz) and voting radius (w) of every cube.
    pub offsets: &'a [Vec4],
    /// The runs, ascending and disjoint.
    pub chunks: &'a [Chunk],
}

/// Votes `pyramid`, seen from the unit as `view`, into `hist` (BINS per cube) and `distance`
/// (two per cube: the weighted sum of the votes' truncated distances, in world units, and
/// the sum of their weights) for the cubes of the chunks listed in `seen` (ascending), and
/// returns the number of votes cast: [`vote_maps`] with one map. The cubes' offsets, `hist`
/// and `distance` hold their whole blocks in lane layout ([`relayout_for_lanes`]).
pub fn vote_chunks(
    cubes: &ChunkedCubes<'_>,
    hist: &mut [f32],
    distance: &mut [f32],
    pyramid: &Pyramid,
    view: &UnitView,
    weight: f32,
    seen: &[usize],
) -> u64 {
    let map = MapVote::new(pyramid, *view, weight, seen);
    vote_maps(cubes, hist, distance, std::slice::from_ref(&map))
}

/// Maps [`vote_maps`] votes at most at once (a chunk records which of them see it in a `u64`).
pub const MAPS_AT_ONCE: usize = 64;

/// One depth map of a [`vote_maps`] batch: its pyramid seen from the unit, its vote weight and
/// the chunks that may see it (ascending).
pub struct MapVote<'a> {
    pub pyramid: &'a Pyramid,
    pub view: UnitView,
    pub shapes: LevelShapes<'a>,
    pub weight: f32,
    pub seen: &'a [usize],
}

impl<'a> MapVote<'a> {
    pub fn new(pyramid: &'a Pyramid, view: UnitView, weight: f32, seen: &'a [usize]) -> MapVote<'a> {
        MapVote {
            pyramid,
            view,
            shapes: LevelShapes::of(pyramid),
            weight,
            seen,
        }
    }
}

/// Votes a batch of maps (at most [`MAPS_AT_ONCE`]; more are ignored) into the unit's `hist`
/// and `distance` rows (as [`vote_chunks`] does one map; whole blocks of cubes, rows and sums
/// in lane layout, [`relayout_for_lanes`]) and returns the number of votes cast.
/// Each vote is [`vote_relative`] (sixteen at a time in [`vote_block`]).
///
/// Chunk by chunk: a chunk's cubes meet every map of the batch that may see them, in the
/// batch's order, while their rows are in cache, where voting one map at a time streamed every
/// seen chunk's cubes and rows (56 bytes a cube) from memory once per map. A group of leaves
/// holds far more than the caches (RedKitchen's two groups: about 140 MB each), and `cargo
/// bench --bench votes` ran 66 to 68 million tests/s over a million cubes against 112 to 118
/// million over 20,000. Each cube still receives the maps in the batch's order, so the sums
/// are those of voting the maps one at a time, to the bit. Chunks own disjoint rows of the
/// histogram, so they vote in parallel: a group of one large leaf still uses every core.
///
/// A chunk's loop runs in the widest vectors the processor has (`fearless_simd::dispatch!`,
/// which compiles it once per x86-64 level and picks one at run time), with the same results
/// bit for bit at every level: the operations are IEEE ones of the same roundings, and fused
/// multiply-adds, which round differently, are never asked for.
pub fn vote_maps(cubes: &ChunkedCubes<'_>, hist: &mut [f32], distance: &mut [f32], maps: &[MapVote<'_>]) -> u64 {
    use rayon::prelude::*;
    let maps = maps.get(..MAPS_AT_ONCE.min(maps.len())).unwrap_or(&[]);
    // Which maps see each chunk, as bits in batch order.
    let mut seen_by = vec![0u64; cubes.chunks.len()];
    for (m, map) in maps.iter().enumerate() {
        for &chunk in map.seen {
            if let Some(bits) = seen_by.get_mut(chunk) {
                *bits |= 1 << m;
            }
        }
    }
    let mut work = Vec::with_capacity(seen_by.len());
    let mut rest: &mut [f32] = hist;
    let mut rest_distance: &mut [f32] = distance;
    let mut consumed = 0;
    let seen_chunks = cubes.chunks.iter().zip(&seen_by).filter(|(_, bits)| **bits != 0);
    for (chunk, &maps_seeing) in seen_chunks {
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
        let offsets = cubes.offsets.get(chunk.start..chunk.end).unwrap_or(&[]);
        work.push((offsets, rows, distances, maps_seeing));
        rest = tail;
        rest_distance = tail_distance;
        consumed = chunk.end;
    }
    let level = fearless_simd::Level::new();
    work.into_par_iter()
        .map(|(offsets, rows, distances, maps_seeing)| {
            fearless_simd::dispatch!(level, simd => chunk_votes(simd, maps, maps_seeing, offsets, rows, distances))
        })
        .sum()
}

/// One chunk's votes of the maps that see it (bit `m` of `maps_seeing` for `maps[m]`), in the
/// batch's order.
#[inline(always)]
fn chunk_votes<S: fearless_simd::Simd>(
    simd: S,
    maps: &[MapVote<'_>],
    maps_seeing: u64,
    offsets: &[Vec4],
    rows: &mut [f32],
    distances: &mut [f32],
) -> u64 {
    let mut votes = 0;
    let mut bits = maps_seeing;
    while bits != 0 {
        let m = bits.trailing_zeros() as usize;
        bits &= bits - 1;
        if let Some(map) = maps.get(m) {
            votes += vote_chunk(simd, map, offsets, rows, distances);
        }
    }
    votes
}

/// One chunk's votes of one map ([`vote_chunks`]): a pinhole map's cubes sixteen at a time
/// ([`vote_block`]); a spherical map, one too large for the lanes (2^24 pixels a side or 2^31
/// pixels) and the chunk's last cubes short of a block, one at a time ([`vote_relative`]).
/// The chunk's whole blocks are in lane layout ([`relayout_for_lanes`]; a chunk starts at a
/// multiple of [`LANES`] cubes), so the one-cube votes read and write them lane by lane.
#[inline(always)]
fn vote_chunk<S: fearless_simd::Simd>(
    simd: S,
    map: &MapVote<'_>,
    offsets: &[Vec4],
    rows: &mut [f32],
    distances: &mut [f32],
) -> u64 {
    let (view, weight) = (&map.view, map.weight);
    let (blocks, tail_offsets) = offsets.as_chunks::<LANES>();
    let (row_blocks, tail_rows) = rows.as_chunks_mut::<{ BINS * LANES }>();
    let (sum_blocks, tail_sums) = distances.as_chunks_mut::<{ 2 * LANES }>();
    let mut votes = 0u64;
    let blocks = blocks.iter().zip(row_blocks).zip(sum_blocks);
    if !view.spherical && map.shapes.fits_lanes() {
        for ((cubes, block_rows), block_sums) in blocks {
            votes += vote_block(simd, view, cubes, &map.shapes, weight).add_to(simd, block_rows, block_sums);
        }
    } else {
        for ((lanes, block_rows), block_sums) in blocks {
            for (lane, cube) in relayout_cubes(lanes, false).into_iter().enumerate() {
                let bin_at = |bin: usize| bin * LANES + lane;
                votes += vote_one(
                    view,
                    cube,
                    map.pyramid,
                    weight,
                    (block_rows, bin_at),
                    (block_sums, lane, lane + LANES),
                );
            }
        }
    }
    let (tail_rows, _) = tail_rows.as_chunks_mut::<BINS>();
    for ((row, sums), cube) in tail_rows
        .iter_mut()
        .zip(tail_sums.chunks_exact_mut(2))
        .zip(tail_offsets)
    {
        votes += vote_one(view, *cube, map.pyramid, weight, (row, |bin| bin), (sums, 0, 1));
    }
    votes
}

/// [`vote_relative`] of one cube added to its histogram row (bin b at `rows.0[rows.1(b)]`)
/// and distance sums (the sum at `sums.0[sums.1]`, its weights' at `sums.0[sums.2]`): the
/// votes cast, 0 or 1.
#[inline(always)]
fn vote_one(
    view: &UnitView,
    cube: Vec4,
    pyramid: &Pyramid,
    weight: f32,
    rows: (&mut [f32], impl Fn(usize) -> usize),
    sums: (&mut [f32], usize, usize),
) -> u64 {
    let Some((bin, distance)) = vote_relative(view, cube, pyramid) else {
        return 0;
    };
    let Some(h) = rows.0.get_mut(rows.1(bin)) else {
        return 0;
    };
    *h += weight;
    if let Some(d) = distance {
        let (sums, sum_at, weight_at) = sums;
        if let Some(sum) = sums.get_mut(sum_at) {
            *sum += weight * d;
        }
        if let Some(total) = sums.get_mut(weight_at) {
            *total += weight;
        }
    }
    1
}

/// A block of [`LANES`] cubes' offsets between the per-cube layout and the lane layout (the x
/// of the sixteen cubes, then y, z and radius; [`relayout_for_lanes`]).
pub fn relayout_cubes(cubes: &[Vec4; LANES], to_lanes: bool) -> [Vec4; LANES] {
    let mut block = *cubes;
    transpose_block::<4>(bytemuck::cast_slice_mut(&mut block), to_lanes);
    block
}

/// Rewrites a block of [`LANES`] rows of `WIDTH` values (at most [`BINS`]) between the
/// per-cube layout (row by row) and the lane layout (value by value, each the sixteen rows').
fn transpose_block<const WIDTH: usize>(block: &mut [f32], to_lanes: bool) {
    const { assert!(WIDTH <= BINS, "a block's rows are at most a histogram row wide") };
    let mut out = [0f32; LANES * BINS];
    // The block as a matrix of `rows` x `columns` values, written out transposed.
    let (columns, rows) = if to_lanes { (WIDTH, LANES) } else { (LANES, WIDTH) };
    for (row, values) in block.chunks_exact(columns).enumerate() {
        for (column, value) in values.iter().enumerate() {
            if let Some(slot) = out.get_mut(column * rows + row) {
                *slot = *value;
            }
        }
    }
    for (slot, value) in block.iter_mut().zip(out) {
        *slot = value;
    }
}

/// Rewrites the whole blocks of [`LANES`] cubes of a unit's `offsets` (xyz and radius),
/// histogram rows (`hist`, [`BINS`] a cube) and distance sums (`distance`, two a cube) between
/// the per-cube layout and the lane layout the voting loop reads and writes ([`vote_maps`],
/// [`vote_chunks`]): a block's offsets as the x of its sixteen cubes, then y, z and radius; its
/// rows as bin 0 of the sixteen cubes, then bin 1, ...; its sums as the sixteen sums, then the
/// sixteen weights. The cubes after the last whole block keep the per-cube layout. Pure data
/// movement, so a round trip gives the same bits; the voting loop then loads each of a block's
/// values as one vector, where the per-cube layout took shuffles and a scalar addition a lane.
pub fn relayout_for_lanes(offsets: &mut [Vec4], hist: &mut [f32], distance: &mut [f32], to_lanes: bool) {
    use rayon::prelude::*;
    let (offset_blocks, _) = offsets.as_chunks_mut::<LANES>();
    offset_blocks
        .par_iter_mut()
        .for_each(|block| transpose_block::<4>(bytemuck::cast_slice_mut(block), to_lanes));
    let (row_blocks, _) = hist.as_chunks_mut::<{ BINS * LANES }>();
    row_blocks
        .par_iter_mut()
        .for_each(|block| transpose_block::<BINS>(block, to_lanes));
    let (sum_blocks, _) = distance.as_chunks_mut::<{ 2 * LANES }>();
    sum_blocks
        .par_iter_mut()
        .for_each(|block| transpose_block::<2>(block, to_lanes));
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::inputs::Projection;
    use crate::kernels::votes::cube_offsets;
    use crate::kernels::votes::tests::{pinhole_source, slanted_wall};

    #[test]
    fn the_lane_layout_moves_whole_blocks_and_leaves_the_tail() {
        let cubes = 2 * LANES + 5;
        let offsets: Vec<Vec4> = (0..cubes)
            .map(|c| Vec4::new(c as f32, 100.0 + c as f32, -(c as f32), 0.5))
            .collect();
        let hist: Vec<f32> = (0..cubes * BINS).map(|i| i as f32).collect();
        let distance: Vec<f32> = (0..cubes * 2).map(|i| -(i as f32)).collect();
        let (mut o, mut h, mut d) = (offsets.clone(), hist.clone(), distance.clone());
        relayout_for_lanes(&mut o, &mut h, &mut d, true);
        for cube in 0..cubes {
            let (block, lane) = (cube / LANES, cube % LANES);
            let flat: &[f32] = bytemuck::cast_slice(&o);
            if block < 2 {
                for (axis, value) in offsets[cube].to_array().into_iter().enumerate() {
                    assert_eq!(
                        flat[block * 4 * LANES + axis * LANES + lane],
                        value,
                        "cube {cube} axis {axis}"
                    );
                }
                for bin in 0..BINS {
                    assert_eq!(h[block * BINS * LANES + bin * LANES + lane], hist[cube * BINS + bin]);
                }
                assert_eq!(d[block * 2 * LANES + lane], distance[cube * 2]);
                assert_eq!(d[block * 2 * LANES + LANES + lane], distance[cube * 2 + 1]);
            } else {
                assert_eq!(o[cube], offsets[cube], "the tail stays per cube");
                assert_eq!(h[cube * BINS..(cube + 1) * BINS], hist[cube * BINS..(cube + 1) * BINS]);
                assert_eq!(d[cube * 2..cube * 2 + 2], distance[cube * 2..cube * 2 + 2]);
            }
        }
        relayout_for_lanes(&mut o, &mut h, &mut d, false);
        assert_eq!((o, h, d), (offsets, hist, distance));
    }

    #[test]
    fn a_batch_of_maps_votes_as_the_maps_one_at_a_time_do_to_the_bit() {
        // Cubes around a wall, seen by five cameras from different places, each map seeing its
        // own subset of the chunks; the fifth map is spherical (one cube at a time).
        let (width, height) = (48u32, 36u32);
        let mut seed = 21u64;
        let mut uniform = move || crate::kernels::random::uniform(&mut seed);
        let sources: Vec<_> = (0..5)
            .map(|m| {
                let pose = glam::DMat4::from_translation(DVec3::new(0.3 * f64::from(m) - 0.6, 0.1, -1.0))
                    * glam::DMat4::from_rotation_y(0.1 * f64::from(m) - 0.2);
                let mut source = pinhole_source("wall.pfm", (width, height), [40.0, 40.0, 23.5, 17.5], pose);
                if m == 4 {
                    source.projection = Projection::Spherical;
                }
                source
            })
            .collect();
        let pyramids: Vec<Pyramid> = sources
            .iter()
            .map(|source| Pyramid::new(source.clone(), slanted_wall((width, height), 23, 1.0, 0.002)))
            .collect();
        let origin = DVec3::new(0.0, 0.0, 0.0);
        let cubes = 3000;
        let centers: Vec<DVec3> = (0..cubes)
            .map(|c| DVec3::new(uniform() - 0.5, uniform() * 0.8 - 0.4, (c % 300) as f64 * 0.003 - 0.4))
            .collect();
        let radii: Vec<f64> = (0..cubes).map(|_| 0.002 + 0.02 * uniform().powi(2)).collect();
        let offsets = cube_offsets(origin, &centers, &radii);
        let chunk_list = chunks(&centers, &radii);
        // The loops read and write whole blocks in lane layout (3000 cubes: 187 blocks and a
        // tail of 8 cubes in the per-cube layout).
        let mut lane_offsets = offsets.clone();
        let (mut no_rows, mut no_sums) = (vec![0f32; cubes * BINS], vec![0f32; cubes * 2]);
        relayout_for_lanes(&mut lane_offsets, &mut no_rows, &mut no_sums, true);
        let chunked = ChunkedCubes {
            offsets: &lane_offsets,
            chunks: &chunk_list,
        };
        let seen: Vec<Vec<usize>> = (0..sources.len())
            .map(|m| (0..chunk_list.len()).filter(|c| (c + m) % 3 != 0).collect())
            .collect();
        let views: Vec<UnitView> = sources
            .iter()
            .map(|source| UnitView::new(source, &source.pose().inverse(), origin, 0.01))
            .collect();
        let weights = [1.0, 0.5, 0.75, 2.0, 1.25];
        let (mut hist, mut distance) = (vec![0f32; cubes * BINS], vec![0f32; cubes * 2]);
        let mut one_at_a_time = 0;
        for m in 0..sources.len() {
            one_at_a_time += vote_chunks(
                &chunked,
                &mut hist,
                &mut distance,
                &pyramids[m],
                &views[m],
                weights[m],
                &seen[m],
            );
        }
        let maps: Vec<MapVote<'_>> = (0..sources.len())
            .map(|m| MapVote::new(&pyramids[m], views[m], weights[m], &seen[m]))
            .collect();
        let (mut batch_hist, mut batch_distance) = (vec![0f32; cubes * BINS], vec![0f32; cubes * 2]);
        let batched = vote_maps(&chunked, &mut batch_hist, &mut batch_distance, &maps);
        assert_eq!(batched, one_at_a_time);
        let mut scratch = lane_offsets.clone();
        relayout_for_lanes(&mut scratch, &mut hist, &mut distance, false);
        relayout_for_lanes(&mut lane_offsets, &mut batch_hist, &mut batch_distance, false);
        assert_eq!(lane_offsets, offsets, "a round trip of the layouts");
        assert!(one_at_a_time > 3_000, "{one_at_a_time} votes: the scene proves little");
        let bits = |values: &[f32]| values.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(&batch_hist), bits(&hist));
        assert_eq!(bits(&batch_distance), bits(&distance));
        // And both are the one-cube vote's, cube by cube: the loops run in the processor's
        // widest vectors, the one-cube vote in scalar code.
        let (mut reference_hist, mut reference_distance) = (vec![0f32; cubes * BINS], vec![0f32; cubes * 2]);
        for m in 0..sources.len() {
            for &c in &seen[m] {
                for cube in chunk_list[c].start..chunk_list[c].end {
                    if let Some((bin, d)) = vote_relative(&views[m], offsets[cube], &pyramids[m]) {
                        reference_hist[cube * BINS + bin] += weights[m];
                        if let Some(d) = d {
                            reference_distance[cube * 2] += weights[m] * d;
                            reference_distance[cube * 2 + 1] += weights[m];
                        }
                    }
                }
            }
        }
        assert_eq!(bits(&reference_hist), bits(&hist));
        assert_eq!(bits(&reference_distance), bits(&distance));
        // Some cubes took votes from several maps, with distances, so the order mattered.
        let several = (0..cubes)
            .filter(|&c| hist[c * BINS..(c + 1) * BINS].iter().filter(|&&h| h > 0.0).count() >= 2)
            .count();
        assert!(
            several > 100 && distance.iter().any(|&d| d != 0.0),
            "{several} cubes with several bins"
        );
    }
}
