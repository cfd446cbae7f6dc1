//! The SSD weights that follow the data: the normal weight from how much the normals within a
//! node disagree, the smoothness from how far neighbouring cubes' sample centroids scatter
//! (docs/parameters.md, "Solvers").

use glam::DVec3;

use crate::format::CubeKey;
use crate::kernels::ssd::CubeSamples;
use crate::stages::samples::cube_centre;

/// The [`normal_disagreement`](super::normal_disagreement) up to which a unit keeps `--ssd-normal-weight`, and from which
/// on it takes [`NOISY_NORMAL_FACTOR`] times it (log-linear between). Measured on the
/// groundtruth bench's views at `--max-depth 9` (docs/parameters.md, "Solvers"): the clean sphere of
/// `tests/ssd.rs` at most 0.0017, the bunny at 0.2 % depth noise 0.0011 to 0.0031, the dragon
/// 0.0020 to 0.0062; at 1 % noise the bunny 0.0077 to 0.0128, the dragon 0.0099 to 0.0162;
/// RedKitchen (Kinect depths, 100 frames, `--max-depth 10`) 0.0052 to 0.055.
const QUIET_DISAGREEMENT: f64 = 0.006;
/// See [`QUIET_DISAGREEMENT`].
const NOISY_DISAGREEMENT: f64 = 0.009;
/// How much a noisy unit raises the normal weight. Each sample's normal is a plane fitted to
/// 7 x 7 pixels, far less noisy than its position where the depths are, so f should follow
/// the normals more there: on the bunny at 1 % depth noise with 5 % outlier pixels (`hybrid`)
/// a normal weight of 0.1 gave F at 1 % 0.980 and Chamfer 0.00378, 0.5 0.994 and 0.00288, 1
/// 0.997 and 0.00262, 3 0.999 and 0.00248 (TGV 0.996 and 0.00288); at 0.2 % noise 0.1 is best
/// (Chamfer 0.00088; 0.00095 at 0.5, 0.00101 at 1, 0.00122 at 3), and on the clean sphere of
/// `tests/ssd.rs` a weight of 1 everywhere doubled the error (0.085 to 0.179 finest cubes).
const NOISY_NORMAL_FACTOR: f64 = 10.0;

/// The normal weight of a unit whose samples' normals disagree by `disagreement`
/// ([`normal_disagreement`](super::normal_disagreement)), from `--ssd-normal-weight` (`base`).
pub fn noise_normal_weight(base: f64, disagreement: f64) -> f64 {
    base * NOISY_NORMAL_FACTOR.powf(share_of_the_way(disagreement, QUIET_DISAGREEMENT, NOISY_DISAGREEMENT))
}

/// Where `x` lies from `quiet` (0) to `noisy` (1), clamped to [0, 1]: how far a unit's noise
/// measure has gone from the level that keeps a weight to the one that takes it whole.
fn share_of_the_way(x: f64, quiet: f64, noisy: f64) -> f64 {
    ((x - quiet) / (noisy - quiet)).clamp(0.0, 1.0)
}

/// How far the sample centroids of neighbouring cubes lie off the surface through them, in
/// cube sides: the median, weighted by the first cube's sample weight, over the unit's free
/// face pairs (c, t) with samples on both sides of |(p_t - p_c) . b| / h_c, where p is a
/// cube's sample centroid and b the bisector of the two cubes' mean normals. On a clean
/// surface the centroids lie on it and the chord between them is perpendicular to b (exactly
/// on a sphere), so the value is near 0 even where the cubes are coarse against the
/// curvature; depth noise moves each centroid by about the noise over the root of the cube's
/// samples, which is what SSD's position term fits. A median, so that edges and the few
/// outlier cubes do not decide it. None without such pairs. `start` and `terms`: the
/// difference rows, as [`SsdProblem`](crate::kernels::ssd::SsdProblem)'s.
pub fn centroid_scatter(keys: &[CubeKey], samples: &[CubeSamples], start: &[u32], terms: &[(u32, f32)]) -> Option<f64> {
    // A cube's centroid (root units), unit normal, side and weight, if it has samples.
    let point = |c: usize| -> Option<(DVec3, DVec3, f64, f64)> {
        let key = keys.get(c)?;
        let s = samples.get(c)?;
        if s.weight <= 0.0 {
            return None;
        }
        let normal = DVec3::from_array(s.normal).try_normalize()?;
        let centre = DVec3::from_array(cube_centre(*key));
        Some((centre + DVec3::from_array(s.centroid), normal, key.side(), s.weight))
    };
    let mut pairs: Vec<(f64, f64)> = Vec::new();
    for c in 0..keys.len() {
        let Some((p_c, n_c, side, weight)) = point(c) else {
            continue;
        };
        for row in 3 * c..3 * c + 3 {
            let (a, b) = (
                start.get(row).copied().unwrap_or(0) as usize,
                start.get(row + 1).copied().unwrap_or(0) as usize,
            );
            for &(t, _) in terms.get(a..b).unwrap_or(&[]) {
                let Some((p_t, n_t, _, _)) = point(t as usize) else {
                    continue;
                };
                // The chord between two points of a circle is perpendicular to the bisector
                // of their normals: curvature adds nothing there, noise does.
                let Some(bisector) = (n_c + n_t).try_normalize() else {
                    continue;
                };
                pairs.push(((p_t - p_c).dot(bisector).abs() / side, weight));
            }
        }
    }
    if pairs.is_empty() {
        return None;
    }
    pairs.sort_by(|x, y| x.0.total_cmp(&y.0));
    let total: f64 = pairs.iter().map(|p| p.1).sum();
    let mut acc = 0.0;
    for (value, weight) in &pairs {
        acc += weight;
        if acc >= 0.5 * total {
            return Some(*value);
        }
    }
    pairs.last().map(|p| p.0)
}

/// The [`centroid_scatter`] up to which a unit keeps `--ssd-smoothness`. Clean captures
/// measure 0.023 to 0.031 at every level (the bunny at 0.3 m and at 3 units, seen from all
/// around); in the groundtruth bench's room at `--max-depth 9` the bunny at 0.2 % depth noise
/// 0.13 (the level of a good sensor, which SSD's position term fits best unchanged), at 1 %
/// 0.31 to 0.32, and the room's far walls 0.32; objects seen from all around with 0.5 % depth
/// noise 0.10 to 0.12 at level 4, rising to 0.36 to 0.44 at the finest level as cubes hold
/// fewer samples.
const QUIET_SCATTER: f64 = 0.13;
/// The scatter from which on the smoothness is the full [`noisy_factor`]; between
/// [`QUIET_SCATTER`] and this it blends in smoothly.
const NOISY_SCATTER: f64 = 0.22;
/// The scatter in whose ratio the full factor is squared ([`noisy_factor`]).
const SCATTER_UNIT: f64 = 0.06;
/// The most [`noise_smoothness`] multiplies `--ssd-smoothness` by. The finest levels of a
/// noisy object read a scatter of 0.36 to 0.44 (cubes finer than the noise), where the square
/// asks 36 to 54 times the base: enough smoothness to close openings that few views look
/// through (the hole through the dragon's coiled body, its mouth; F at 1 % 0.984 on the noisy
/// dragon at 100). Measured with no flags on the noisy objects (0.5 % depth noise, 10 %
/// outlier pixels; docs/parameters.md, "Solvers"): 20 gave the dragon F at 1 % 0.9898 at
/// 0.3 m and 0.9900 at 3 units; 10 gives 0.9922 and 0.9909, one part each once extraction
/// drops the noise blobs beside the surface and simplification keeps the topology (before
/// that, 33 parts on the 3-unit dragon and 170 on the bunny); 5 gave 0.9934 and 0.9895 with 68
/// and 463 parts on the 3-unit objects.
const MOST_SMOOTHNESS_FACTOR: f64 = 10.0;

/// The full factor on `--ssd-smoothness` of a noisy unit: (scatter / [`SCATTER_UNIT`])^2.
fn noisy_factor(scatter: f64) -> f64 {
    let ratio = scatter / SCATTER_UNIT;
    ratio * ratio
}

/// The smoothness of a unit whose centroids scatter by `scatter` ([`centroid_scatter`]), from
/// `--ssd-smoothness` (`base`): base up to [`QUIET_SCATTER`]; base times [`noisy_factor`]
/// from [`NOISY_SCATTER`] on, at most [`MOST_SMOOTHNESS_FACTOR`] times; between them the
/// factor goes from 1 to the full one along a smoothstep.
///
/// Why. SSD's position term pins f's zero set to each cube's sample centroid, so where the
/// centroids scatter by a good part of a cube the zero set follows the noise: bubbles and
/// shards around the surface, the more the finer the cubes are against the noise (the noisy
/// bunny with 10 % outliers under `hybrid`: 12 components at 0.3 m, 596 at 3 units, where the
/// cubes are half as large against the object). The scatter is measured in cube sides, so the
/// rule is the same in metres, millimetres or scaled units, and at each level of a solve. The
/// square follows the energy: the position term grows with the square of the centroids'
/// offsets, the smoothness term must grow as much to hold them. Measured (docs/parameters.md,
/// "Solvers"): the square from 0.06 on (the first rule) kept every noisy object one piece at
/// both scales under both methods, but smoothed the bunny at 0.2 % depth noise (scatter
/// 0.13) from F at 0.2 % 0.96 to 0.83; powers of the scatter over 0.13 to 0.15 (3.3 and 4)
/// kept 0.96 but left holes in the noisy objects or cost them up to 0.08 of F at 0.2 %. The
/// blend keeps the first rule where the noise is (from 0.22 on) and the base where it is not.
pub fn noise_smoothness(base: f64, scatter: Option<f64>) -> f64 {
    let scatter = scatter.unwrap_or(0.0);
    let t = share_of_the_way(scatter, QUIET_SCATTER, NOISY_SCATTER);
    let blend = t * t * (3.0 - 2.0 * t);
    let full = noisy_factor(scatter).clamp(1.0, MOST_SMOOTHNESS_FACTOR);
    base * (1.0 + blend * (full - 1.0))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Keys, samples, and the difference rows' starts and terms.
    type RowOfCubes = (Vec<CubeKey>, Vec<CubeSamples>, Vec<u32>, Vec<(u32, f32)>);

    /// A row of `offsets.len()` cubes along x at depth 6, each with one x neighbour term to
    /// the next (the last one's to a frozen cube), the samples `offsets[i]` cube sides off the
    /// plane through the centres with normal `normal` (x and z only), weights `weights`.
    fn row_of_cubes(offsets: &[f64], weights: &[f64], normal: DVec3) -> RowOfCubes {
        let n = offsets.len();
        let keys: Vec<CubeKey> = (0..n as u32).map(|i| CubeKey::new(6, i, 0, 0)).collect();
        let side = keys[0].side();
        // Centres on the plane z = -(x n_x) / n_z through the first centre, then moved along
        // the normal.
        let samples = (0..n)
            .map(|i| {
                let along = i as f64 * side;
                let onto_plane = DVec3::new(0.0, 0.0, -along * normal.x / normal.z);
                CubeSamples {
                    weight: weights[i],
                    centroid: (onto_plane + normal * offsets[i] * side).to_array(),
                    normal: (normal * weights[i]).to_array(),
                }
            })
            .collect();
        let (mut start, mut terms) = (vec![0u32], Vec::new());
        for c in 0..n {
            for axis in 0..3 {
                if axis == 0 {
                    terms.push(((c + 1) as u32, 1.0f32));
                }
                start.push(terms.len() as u32);
            }
        }
        (keys, samples, start, terms)
    }

    #[test]
    fn centroid_scatter_is_the_weighted_median_offset_across_face_pairs_in_cube_sides() {
        let tilted = DVec3::new(0.6, 0.0, 0.8);
        // Centroids on a tilted plane: nothing scatters, whatever the tilt.
        let (k, s, st, t) = row_of_cubes(&[0.0; 8], &[1.0; 8], tilted);
        assert!(centroid_scatter(&k, &s, &st, &t).unwrap() < 1e-9);
        // Alternating 0.1 cube sides to either side: every pair 0.2 apart.
        let alternating: Vec<f64> = (0..8).map(|i| if i % 2 == 0 { 0.1 } else { -0.1 }).collect();
        let (k, s, st, t) = row_of_cubes(&alternating, &[1.0; 8], tilted);
        assert!((centroid_scatter(&k, &s, &st, &t).unwrap() - 0.2).abs() < 1e-9);
        // One wild cube moves two of the seven pairs, not the median.
        let mut wild = vec![0.05; 8];
        wild[3] = 3.0;
        let (k, s, st, t) = row_of_cubes(&wild, &[1.0; 8], tilted);
        assert!(centroid_scatter(&k, &s, &st, &t).unwrap() < 1e-9);
        // The median is by the first cube's weight: heavy noisy pairs decide it.
        let mut weights = vec![1.0; 8];
        weights[0] = 10.0;
        let mut first_off = vec![0.0; 8];
        first_off[0] = 0.5;
        let (k, s, st, t) = row_of_cubes(&first_off, &weights, tilted);
        assert!((centroid_scatter(&k, &s, &st, &t).unwrap() - 0.5).abs() < 1e-9);
        // Cubes without sample weight and frozen neighbours give no pair; no pair, no value.
        let (k, s, st, t) = row_of_cubes(&[0.3, 0.0], &[1.0, 0.0], tilted);
        assert_eq!(centroid_scatter(&k, &s, &st, &t), None);
        // A scaled cube (depth 7 instead of 6) with offsets in its own sides reads the same.
        let (k, mut s, st, t) = row_of_cubes(&alternating, &[1.0; 8], tilted);
        let k: Vec<CubeKey> = k.iter().map(|key| CubeKey::new(7, key.coords()[0], 0, 0)).collect();
        for x in &mut s {
            x.centroid = x.centroid.map(|v| v * 0.5);
        }
        assert!((centroid_scatter(&k, &s, &st, &t).unwrap() - 0.2).abs() < 1e-9);
    }

    #[test]
    fn the_smoothness_keeps_the_base_for_low_noise_and_rises_with_the_square_to_the_cap() {
        assert_eq!(noise_smoothness(0.1, None), 0.1);
        assert_eq!(noise_smoothness(0.1, Some(0.0)), 0.1);
        // Clean captures and 0.2 % depth noise keep the base.
        assert_eq!(noise_smoothness(0.1, Some(0.03)), 0.1);
        assert_eq!(noise_smoothness(0.1, Some(QUIET_SCATTER)), 0.1);
        // Noisy units: the square of the scatter over 0.06, at most the cap (0.36 would read
        // 36 times; 0.18, inside the blend, 9 times its share of the way).
        assert!((noise_smoothness(0.1, Some(0.36)) - 0.1 * MOST_SMOOTHNESS_FACTOR).abs() < 1e-12);
        let full = noisy_factor(NOISY_SCATTER).min(MOST_SMOOTHNESS_FACTOR);
        assert!((noise_smoothness(0.1, Some(NOISY_SCATTER)) - 0.1 * full).abs() < 1e-12);
        assert!((noise_smoothness(0.1, Some(f64::INFINITY)) - 0.1 * MOST_SMOOTHNESS_FACTOR).abs() < 1e-12);
        let t: f64 = (0.18 - QUIET_SCATTER) / (NOISY_SCATTER - QUIET_SCATTER);
        let blend = t * t * (3.0 - 2.0 * t);
        assert!((noise_smoothness(0.1, Some(0.18)) - 0.1 * (1.0 + blend * 8.0)).abs() < 1e-9);
        // In between it rises, never falls.
        let mut last = 0.1;
        for i in 0..=100 {
            let s = QUIET_SCATTER + (NOISY_SCATTER - QUIET_SCATTER) * f64::from(i) / 100.0;
            let value = noise_smoothness(0.1, Some(s));
            assert!(value >= last, "{s}: {value} < {last}");
            last = value;
        }
    }

    #[test]
    fn the_normal_weight_rises_tenfold_from_quiet_to_noisy_samples() {
        assert_eq!(noise_normal_weight(0.1, 0.0), 0.1);
        assert_eq!(noise_normal_weight(0.1, QUIET_DISAGREEMENT), 0.1);
        assert!((noise_normal_weight(0.1, NOISY_DISAGREEMENT) - 1.0).abs() < 1e-12);
        assert!((noise_normal_weight(0.1, 0.5) - 1.0).abs() < 1e-12);
        let middle = noise_normal_weight(0.1, 0.5 * (QUIET_DISAGREEMENT + NOISY_DISAGREEMENT));
        assert!((middle - 0.1 * 10f64.sqrt()).abs() < 1e-12, "{middle}");
    }
}
