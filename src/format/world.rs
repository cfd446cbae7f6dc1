//! World space: the scene's fixed root cube, which maps world coordinates to cube keys (its
//! bincode encoding is stored in the catalog's meta table under [`META_SCENE`]), and
//! axis-aligned boxes in world coordinates (extraction regions, cube queries).

use glam::DVec3;
use serde::{Deserialize, Serialize};

use super::{CubeKey, MAX_DEPTH};

/// Meta key holding the bincode-encoded [`Scene`].
pub const META_SCENE: &str = "scene";

/// Fixed-point scale of radii stored in segments: a radius r is stored as
/// round(r / r_root * 2^RADIUS_FRACTION_BITS), so sums are exact integers and independent of
/// the order depth maps are added in.
pub const RADIUS_FRACTION_BITS: i32 = 32;

/// The root cube, fixed at the first ingest. `r_root` (eq. 4) is half its side.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq)]
pub struct Scene {
    /// The root cube's minimum corner in world coordinates.
    pub root_min: [f64; 3],
    /// The root cube's side.
    pub root_side: f64,
    /// Deepest level a sample may spawn a cube at.
    pub max_depth: u8,
}

impl Scene {
    /// The root cube around `[min, max]`, grown by `margin` (a fraction of the largest extent)
    /// on every side.
    pub fn around(min: DVec3, max: DVec3, margin: f64, max_depth: u8) -> Scene {
        let extent = (max - min).max_element().max(f64::MIN_POSITIVE);
        let side = extent * (1.0 + 2.0 * margin);
        let center = (min + max) * 0.5;
        Scene {
            root_min: (center - DVec3::splat(side * 0.5)).to_array(),
            root_side: side,
            max_depth: max_depth.min(MAX_DEPTH),
        }
    }

    /// The root of twice the side in which this root is the child `octant` (per axis 0: the
    /// old root is the lower half, 1: the upper half), one level deeper, so cube sides at every
    /// key depth + 1 equal the old ones ([`CubeKey::in_doubled_root`]). `None` when
    /// `max_depth` is already the keys' limit.
    pub fn doubled(&self, octant: [u32; 3]) -> Option<Scene> {
        if self.max_depth >= MAX_DEPTH {
            return None;
        }
        let mut root_min = self.root_min;
        for (min, o) in root_min.iter_mut().zip(octant) {
            if o == 1 {
                *min -= self.root_side;
            }
        }
        Some(Scene {
            root_min,
            root_side: self.root_side * 2.0,
            max_depth: self.max_depth + 1,
        })
    }

    /// Whether the box `[lo, hi]` lies inside the root cube (its far faces included).
    pub fn contains_box(&self, lo: DVec3, hi: DVec3) -> bool {
        let max = self.min() + DVec3::splat(self.root_side);
        lo.cmpge(self.min()).all() && hi.cmple(max).all()
    }

    /// The doublings that grow this root until it holds `[lo, hi]` widened by `margin` of the
    /// box's largest extent on every side (the first ingest's rule, `Scene::around`): per
    /// doubling, on each axis the root grows towards the side the widened box passes by more.
    /// Empty when the root already holds `[lo, hi]` itself (the margin only shapes growth, it
    /// does not trigger it). `None` when more than `limit` doublings, or more than the keys'
    /// depth limit, would be needed.
    pub fn growth_to_hold(&self, lo: DVec3, hi: DVec3, margin: f64, limit: usize) -> Option<Vec<[u32; 3]>> {
        if self.contains_box(lo, hi) {
            return Some(Vec::new());
        }
        let widen = (hi - lo).max_element().max(0.0) * margin;
        let (lo, hi) = (lo - DVec3::splat(widen), hi + DVec3::splat(widen));
        let mut scene = *self;
        let mut octants = Vec::new();
        while !scene.contains_box(lo, hi) {
            if octants.len() >= limit {
                return None;
            }
            let max = scene.min() + DVec3::splat(scene.root_side);
            let below = scene.min() - lo;
            let above = hi - max;
            let octant = [0, 1, 2].map(|axis| u32::from(below[axis] > above[axis] && below[axis] > 0.0));
            scene = scene.doubled(octant)?;
            octants.push(octant);
        }
        Some(octants)
    }

    /// r_root of eq. 4: half the root's side.
    pub fn root_radius(&self) -> f64 {
        self.root_side * 0.5
    }

    /// The root cube's minimum corner.
    pub fn min(&self) -> DVec3 {
        DVec3::from_array(self.root_min)
    }

    /// `p` as a fraction of the root cube on each axis, in [0, 1) inside it: what
    /// [`Scene::contains`] and [`Scene::key_at`] both compute first, so that a caller asking
    /// both divides once ([`Scene::fraction_inside`], [`Scene::key_at_fraction`]).
    #[inline]
    pub fn root_fraction(&self, p: DVec3) -> DVec3 {
        (p - self.min()) / self.root_side
    }

    /// Whether `p` lies in the root cube.
    pub fn contains(&self, p: DVec3) -> bool {
        Scene::fraction_inside(self.root_fraction(p))
    }

    /// Whether a [`Scene::root_fraction`] lies in the root cube.
    #[inline]
    pub fn fraction_inside(q: DVec3) -> bool {
        q.cmpge(DVec3::ZERO).all() && q.cmplt(DVec3::ONE).all()
    }

    /// Depth of a sample of radius `r` by eq. 4: 0.75 r <= r_root / 2^d < 1.5 r.
    pub fn depth_for_radius(&self, r: f64) -> u8 {
        let t = (self.root_radius() / r).log2();
        let d = (t + 0.75f64.log2().abs()).floor();
        if d.is_nan() || d < 0.0 {
            0
        } else {
            (d as u32).min(u32::from(self.max_depth)) as u8
        }
    }

    /// The key of the cube at `depth` containing `p` (which must be inside the root).
    pub fn key_at(&self, p: DVec3, depth: u8) -> CubeKey {
        Scene::key_at_fraction(self.root_fraction(p), depth)
    }

    /// [`Scene::key_at`] of the point whose [`Scene::root_fraction`] is `q`.
    #[inline]
    pub fn key_at_fraction(q: DVec3, depth: u8) -> CubeKey {
        // Clamped first, the float-to-int cast truncates a non-negative value, which is its
        // floor: the same key as `floor().clamp()`, without a call to libm's floor (the
        // crate's baseline x86-64 has no rounding instruction).
        let full = |c: f64| -> u32 { (c * 4294967296.0).clamp(0.0, 4294967295.0) as u32 };
        let shift = u32::from(MAX_DEPTH - depth);
        let mask = |c: u32| if shift >= 32 { 0 } else { (c >> shift) << shift };
        CubeKey::from_full_resolution(depth, mask(full(q.x)), mask(full(q.y)), mask(full(q.z)))
    }

    /// Side length of a cube at `depth`.
    pub fn cube_side(&self, depth: u8) -> f64 {
        // 2^-depth built from its exponent bits: scaling by a power of two is exact, as the
        // division by 2^depth was, without a division's latency (ingest calls this per sample).
        let scale = f64::from_bits((1023 - u64::from(depth.min(MAX_DEPTH))) << 52);
        self.root_side * scale
    }

    /// World-space centre of a cube.
    pub fn cube_center(&self, key: CubeKey) -> DVec3 {
        self.cube_center_at(key.corner_full_resolution(), key.depth())
    }

    /// World-space centre of the cube at `depth` whose minimum corner is `corner` in
    /// full-resolution cells: [`cube_center`](Self::cube_center) for a caller that knows the
    /// corner, bit for bit.
    pub fn cube_center_at(&self, corner: [u32; 3], depth: u8) -> DVec3 {
        let [x, y, z] = corner;
        let corner = DVec3::new(f64::from(x), f64::from(y), f64::from(z)) / 4294967296.0 * self.root_side + self.min();
        corner + DVec3::splat(self.cube_side(depth) * 0.5)
    }

    /// Fixed-point encoding of a radius (see [`RADIUS_FRACTION_BITS`]).
    pub fn quantize_radius(&self, r: f64) -> u64 {
        const MOST: f64 = (1u64 << 40) as f64;
        let scaled = r / self.root_radius() * 2f64.powi(RADIUS_FRACTION_BITS);
        // Within [1, 2^40] (every sample's radius) the rounding is the clamp's no-op and the
        // truncating cast the floor, with an exact fraction: the same integer as the general
        // path, without its sign handling and float clamp (ingest quantizes every sample).
        if (1.0..=MOST).contains(&scaled) {
            let floor = scaled as u64;
            return floor + u64::from(scaled - floor as f64 >= 0.5);
        }
        round_half_away_from_zero(scaled).clamp(1.0, MOST) as u64
    }

    /// Mean radius r_c (eq. 5) from a fixed-point sum and a count.
    pub fn mean_radius(&self, sum: u64, count: u32) -> f64 {
        if count == 0 {
            return f64::NAN;
        }
        sum as f64 / f64::from(count) / 2f64.powi(RADIUS_FRACTION_BITS) * self.root_radius()
    }
}

/// [`Scene::depth_for_radius`] by comparisons, for a scene's ingest: per depth d from 1 to the
/// scene's max depth, the largest radius to which the formula gives d or deeper, found by
/// bisection over the formula itself. The formula is non-increasing in r (a quotient, a log
/// and a floor, each monotone), so a positive finite radius's depth is the number of
/// thresholds it does not exceed: the formula's depth to the bit, without the division, the
/// libm `log2` and the `floor` it costs on every sample.
#[derive(Clone, Debug)]
pub struct RadiusDepths {
    scene: Scene,
    /// `thresholds[d - 1]`: the largest radius of depth d or deeper; decreasing in d.
    thresholds: Vec<f64>,
    /// `thresholds` and two zeros after them, so that the two thresholds a binade can hold are
    /// there to compare with for every binade (no positive radius is at or below zero).
    padded: Vec<f64>,
    /// Per biased exponent of a normal radius: how many thresholds lie at or above the top of
    /// that binade (all of them count towards its radii's depth), or [`NO_BINADE_COUNT`].
    above_binade: Vec<u8>,
}

/// [`RadiusDepths::above_binade`] of a binade holding more than two thresholds (none, with the
/// formula's factor 2 between depths; the binade then searches them all).
const NO_BINADE_COUNT: u8 = u8::MAX;

impl RadiusDepths {
    /// The thresholds of `scene`'s depths (a few thousand evaluations of the formula).
    pub fn new(scene: &Scene) -> RadiusDepths {
        let thresholds: Vec<f64> = (1..=scene.max_depth)
            .map(|depth| {
                // Bit patterns of positive finite doubles order as the doubles do. The
                // smallest one has the deepest depth there is and the largest one depth 0, so
                // the bisection keeps depth(lo) >= depth > depth(hi).
                let (mut lo, mut hi) = (1u64, f64::MAX.to_bits());
                while hi - lo > 1 {
                    let mid = lo + (hi - lo) / 2;
                    if scene.depth_for_radius(f64::from_bits(mid)) >= depth {
                        lo = mid;
                    } else {
                        hi = mid;
                    }
                }
                f64::from_bits(lo)
            })
            .collect();
        let above_binade = (0..2048u64)
            .map(|exponent| {
                // The binade [2^(e - 1023), 2^(e - 1022)); the top of the last is past f64::MAX.
                let top = f64::from_bits((exponent + 1) << 52);
                let bottom = f64::from_bits(exponent << 52);
                let above = thresholds.iter().filter(|t| **t >= top).count();
                let within = thresholds.iter().filter(|t| **t >= bottom && **t < top).count();
                if within <= 2 { above as u8 } else { NO_BINADE_COUNT }
            })
            .collect();
        let mut padded = thresholds.clone();
        padded.extend([0.0, 0.0]);
        RadiusDepths {
            scene: *scene,
            thresholds,
            padded,
            above_binade,
        }
    }

    /// [`Scene::depth_for_radius`] of `r`: the number of thresholds at or above `r`. Those above
    /// `r`'s binade all are, those below it none is, and a binade holds at most two (consecutive
    /// thresholds are a factor 2 apart), so a table by exponent and two comparisons give it
    /// (a bisection's chain of dependent loads was a twentieth of ingest's per-sample work).
    #[inline]
    pub fn depth(&self, r: f64) -> u8 {
        let exponent = (r.to_bits() >> 52) as usize;
        // Positive normal radii (sign bit clear, exponent neither 0 nor all ones).
        if (1..2047).contains(&exponent)
            && let Some(&above) = self.above_binade.get(exponent)
            && above != NO_BINADE_COUNT
        {
            let above = usize::from(above);
            let at = |k: usize| self.padded.get(k).is_some_and(|t| r <= *t);
            return (above + usize::from(at(above)) + usize::from(at(above + 1))) as u8;
        }
        if r > 0.0 && r <= f64::MAX {
            self.thresholds.partition_point(|t| r <= *t) as u8
        } else {
            self.scene.depth_for_radius(r)
        }
    }
}

/// `x.round()` (halves away from zero), to the bit, without the call to libm's `round` that the
/// crate's baseline x86-64 (no SSE4.1 rounding instruction) makes for it: ingest rounds several
/// values per sample. Below 2^52 in magnitude the truncating cast is exact and so is `x - t`;
/// from there on every double is an integer already. Branch-free below 2^52: which way a
/// sample's value rounds is a coin toss a branch predictor loses.
#[inline]
pub fn round_half_away_from_zero(x: f64) -> f64 {
    if x.abs() < 4_503_599_627_370_496.0 {
        let t = (x as i64) as f64;
        let fraction = x - t;
        let up = f64::from(u8::from(fraction >= 0.5));
        let down = f64::from(u8::from(fraction <= -0.5));
        // The result has x's sign or is zero, and round gives -0.0 for x in (-0.5, -0.0].
        (t + up - down).copysign(x)
    } else {
        x
    }
}

#[cfg(test)]
#[expect(clippy::unwrap_used, reason = "tests: a panic is the failure report")]
mod tests {
    use super::*;

    #[test]
    fn rounding_without_libm_matches_round_to_the_bit() {
        let mut values = vec![
            0.0,
            -0.0,
            0.5,
            -0.5,
            1.5,
            -2.5,
            0.49999999999999994,
            -0.49999999999999994,
            4_503_599_627_370_495.5,
            -4_503_599_627_370_495.5,
            4_503_599_627_370_496.0,
            9.3e18,
            -1.0e300,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::MIN_POSITIVE,
            -f64::MIN_POSITIVE,
        ];
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        for _ in 0..200_000 {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            let scale = 2f64.powi((state >> 58) as i32 - 8);
            let x = (state >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0;
            values.push(x * scale);
            values.push((x * 64.0).trunc() + 0.5);
        }
        for x in values {
            assert_eq!(round_half_away_from_zero(x).to_bits(), x.round().to_bits(), "{x:e}");
        }
        assert!(round_half_away_from_zero(f64::NAN).is_nan());
    }

    #[test]
    fn cube_sides_halve_exactly_per_level() {
        for root_side in [1.0, 5.898861069647787, 1.0e-3, 123_456.789] {
            let scene = Scene {
                root_min: [0.0; 3],
                root_side,
                max_depth: MAX_DEPTH,
            };
            for depth in 0..=MAX_DEPTH {
                let expected = root_side / 2f64.powi(i32::from(depth));
                assert_eq!(
                    scene.cube_side(depth).to_bits(),
                    expected.to_bits(),
                    "{root_side} {depth}"
                );
            }
        }
    }

    #[test]
    fn depth_satisfies_eq4() {
        let scene = Scene::around(DVec3::ZERO, DVec3::splat(10.0), 0.0, 32);
        for r in [0.001, 0.0173, 0.25, 1.0, 3.3] {
            let d = scene.depth_for_radius(r);
            let cube_radius = scene.root_radius() / f64::from(1u32 << d);
            assert!(
                0.75 * r <= cube_radius && cube_radius < 1.5 * r,
                "r {r} d {d} cube {cube_radius}"
            );
        }
    }

    #[test]
    fn quantized_radii_are_the_rounded_clamped_fixed_point_values() {
        let scene = Scene::around(DVec3::ZERO, DVec3::splat(3.7), 0.05, 10);
        let unit = scene.root_radius() / 2f64.powi(RADIUS_FRACTION_BITS);
        let reference = |r: f64| {
            round_half_away_from_zero(r / scene.root_radius() * 2f64.powi(RADIUS_FRACTION_BITS))
                .clamp(1.0, 2f64.powi(40)) as u64
        };
        let mut radii = vec![0.0, -1.0, f64::NAN, f64::INFINITY, f64::MAX, 5e-324, 1e300];
        for k in [
            0.0,
            1.0,
            2.0,
            7.0,
            1e6,
            2f64.powi(40) - 1.0,
            2f64.powi(40),
            2f64.powi(41),
        ] {
            for offset in [0.0, 0.25, 0.5, 0.75] {
                let r = (k + offset) * unit;
                radii.extend((r.to_bits() - 2..=r.to_bits() + 2).map(f64::from_bits));
            }
        }
        let mut state = 5u64;
        for _ in 0..100_000 {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            radii.push(unit * 10f64.powf((state >> 11) as f64 / (1u64 << 53) as f64 * 14.0 - 1.0));
        }
        for r in radii {
            assert_eq!(scene.quantize_radius(r), reference(r), "r {r:e}");
        }
    }

    #[test]
    fn radius_depths_give_the_formulas_depth_at_and_around_every_threshold() {
        for (side, max_depth) in [(10.0, 32u8), (3.7, 10), (0.01, 12), (1e6, 0)] {
            let scene = Scene::around(DVec3::ZERO, DVec3::splat(side), 0.05, max_depth);
            let depths = RadiusDepths::new(&scene);
            let mut radii = vec![
                0.0,
                -0.0,
                -1.0,
                f64::MIN_POSITIVE,
                5e-324,
                1e-310,
                1e-300,
                f64::MAX,
                f64::INFINITY,
                f64::NAN,
            ];
            for t in &depths.thresholds {
                let bits = t.to_bits();
                radii.extend((bits - 3..=bits + 3).map(f64::from_bits));
                // The edges of its binade and the next ones, where the exponent table changes.
                let binade = bits >> 52 << 52;
                for edge in [binade, binade + (1 << 52), binade - (1 << 52)] {
                    radii.extend((edge - 2..=edge + 2).map(f64::from_bits));
                }
            }
            let mut state = 11u64;
            for _ in 0..100_000 {
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                let r = state >> 11;
                // Radii from 1e-12 to 1e4 times the root's side, log-uniform.
                radii.push(side * 10f64.powf((r % 1_000_000) as f64 / 1_000_000.0 * 16.0 - 12.0));
            }
            for r in radii {
                assert_eq!(depths.depth(r), scene.depth_for_radius(r), "side {side} r {r:e}");
            }
        }
    }

    #[test]
    fn a_doubled_root_keeps_every_cube_where_it_was() {
        let scene = Scene::around(DVec3::new(-3.0, 1.0, 2.0), DVec3::new(5.0, 2.0, 4.0), 0.1, 12);
        let p = DVec3::new(1.2345, 1.5, 3.1);
        for octant in [[0, 0, 0], [1, 0, 1], [1, 1, 1]] {
            let grown = scene.doubled(octant).unwrap();
            assert_eq!(grown.max_depth, 13);
            for depth in [0u8, 3, 12] {
                let key = scene.key_at(p, depth);
                let moved = key.in_doubled_root(octant).unwrap();
                assert_eq!(grown.key_at(p, depth + 1), moved, "octant {octant:?} depth {depth}");
                assert_eq!(grown.cube_side(depth + 1), scene.cube_side(depth));
                let shift = (grown.cube_center(moved) - scene.cube_center(key)).abs().max_element();
                assert!(shift < 1e-12 * scene.root_side, "{shift}");
            }
        }
        assert!(Scene { max_depth: 32, ..scene }.doubled([0, 0, 0]).is_none());
    }

    #[test]
    fn growth_reaches_towards_the_new_samples_only_when_they_leave_the_root() {
        let scene = Scene {
            root_min: [0.0; 3],
            root_side: 1.0,
            max_depth: 10,
        };
        let inside = scene.growth_to_hold(DVec3::splat(0.1), DVec3::splat(0.9), 0.1, 8);
        assert_eq!(inside, Some(Vec::new()));
        // Below on x only: one doubling, the old root the upper half in x.
        let octants = scene
            .growth_to_hold(DVec3::new(-0.5, 0.2, 0.2), DVec3::new(0.5, 0.8, 0.8), 0.1, 8)
            .unwrap();
        assert_eq!(octants, vec![[1, 0, 0]]);
        // Far above: several doublings, each growing upwards.
        let octants = scene
            .growth_to_hold(DVec3::splat(0.7), DVec3::splat(6.5), 0.1, 8)
            .unwrap();
        assert_eq!(octants.len(), 3);
        let mut grown = scene;
        for octant in &octants {
            grown = grown.doubled(*octant).unwrap();
        }
        assert!(grown.contains_box(DVec3::splat(0.7), DVec3::splat(6.5)));
        assert_eq!(grown.root_min, [0.0; 3]);
        assert_eq!(scene.growth_to_hold(DVec3::splat(0.5), DVec3::splat(1e6), 0.1, 8), None);
    }

    #[test]
    fn key_contains_point() {
        let scene = Scene::around(DVec3::new(-3.0, 1.0, 2.0), DVec3::new(5.0, 2.0, 4.0), 0.1, 32);
        let p = DVec3::new(1.2345, 1.5, 3.1);
        for depth in [0u8, 1, 5, 13, 20] {
            let key = scene.key_at(p, depth);
            let c = scene.cube_center(key);
            let half = scene.cube_side(depth) * 0.5;
            assert!(((p - c).abs().max_element()) <= half * (1.0 + 1e-9), "depth {depth}");
        }
    }
}

/// An axis-aligned box in world coordinates (an extraction region, a query box).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct BoundingBox {
    /// The corner with the smallest coordinates.
    pub min: DVec3,
    /// The corner with the largest coordinates.
    pub max: DVec3,
}
