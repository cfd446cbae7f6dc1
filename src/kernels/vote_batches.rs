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
/// returns the number of votes cast: [`vote_maps`] with one map.
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
/// and `distance` rows (as [`vote_chunks`] does one map) and returns the number of votes cast.
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
#[inline(always)]
fn vote_chunk<S: fearless_simd::Simd>(
    simd: S,
    map: &MapVote<'_>,
    offsets: &[Vec4],
    rows: &mut [f32],
    distances: &mut [f32],
) -> u64 {
    let (view, weight) = (&map.view, map.weight);
    let (rows, _) = rows.as_chunks_mut::<BINS>();
    let (sums, _) = distances.as_chunks_mut::<2>();
    let mut votes = 0u64;
    let mut in_blocks = 0;
    if !view.spherical && map.shapes.fits_lanes() {
        let (blocks, _) = offsets.as_chunks::<LANES>();
        let (row_blocks, _) = rows.as_chunks_mut::<LANES>();
        let (sum_blocks, _) = sums.as_chunks_mut::<LANES>();
        for ((cubes, block_rows), block_sums) in blocks.iter().zip(row_blocks).zip(sum_blocks) {
            votes += vote_block(simd, view, cubes, &map.shapes, weight).add_to(simd, block_rows, block_sums);
        }
        in_blocks = blocks.len() * LANES;
    }
    for ((row, [sum, total]), cube) in rows.iter_mut().zip(sums.iter_mut()).zip(offsets).skip(in_blocks) {
        if let Some((bin, distance)) = vote_relative(view, *cube, map.pyramid)
            && let Some(h) = row.get_mut(bin)
        {
            *h += weight;
            if let Some(d) = distance {
                *sum += weight * d;
                *total += weight;
            }
            votes += 1;
        }
    }
    votes
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::inputs::Projection;
    use crate::kernels::votes::cube_offsets;
    use crate::kernels::votes::tests::{pinhole_source, slanted_wall};

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
        let chunked = ChunkedCubes {
            offsets: &offsets,
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
