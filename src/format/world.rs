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

    /// r_root of eq. 4: half the root's side.
    pub fn root_radius(&self) -> f64 {
        self.root_side * 0.5
    }

    /// The root cube's minimum corner.
    pub fn min(&self) -> DVec3 {
        DVec3::from_array(self.root_min)
    }

    /// Whether `p` lies in the root cube.
    pub fn contains(&self, p: DVec3) -> bool {
        let q = (p - self.min()) / self.root_side;
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
        let q = (p - self.min()) / self.root_side;
        let full = |c: f64| -> u32 { ((c * 4294967296.0).floor()).clamp(0.0, 4294967295.0) as u32 };
        let shift = u32::from(MAX_DEPTH - depth);
        let mask = |c: u32| if shift >= 32 { 0 } else { (c >> shift) << shift };
        CubeKey::from_full_resolution(depth, mask(full(q.x)), mask(full(q.y)), mask(full(q.z)))
    }

    /// Side length of a cube at `depth`.
    pub fn cube_side(&self, depth: u8) -> f64 {
        self.root_side / f64::from(1u32 << depth.min(31)) / if depth == 32 { 2.0 } else { 1.0 }
    }

    /// World-space centre of a cube.
    pub fn cube_center(&self, key: CubeKey) -> DVec3 {
        let [x, y, z] = key.corner_full_resolution();
        let corner = DVec3::new(f64::from(x), f64::from(y), f64::from(z)) / 4294967296.0 * self.root_side + self.min();
        corner + DVec3::splat(self.cube_side(key.depth()) * 0.5)
    }

    /// Fixed-point encoding of a radius (see [`RADIUS_FRACTION_BITS`]).
    pub fn quantize_radius(&self, r: f64) -> u64 {
        let scaled = (r / self.root_radius() * 2f64.powi(RADIUS_FRACTION_BITS)).round();
        scaled.clamp(1.0, 2f64.powi(40)) as u64
    }

    /// Mean radius r_c (eq. 5) from a fixed-point sum and a count.
    pub fn mean_radius(&self, sum: u64, count: u32) -> f64 {
        if count == 0 {
            return f64::NAN;
        }
        sum as f64 / f64::from(count) / 2f64.powi(RADIUS_FRACTION_BITS) * self.root_radius()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
