//! Built-in synthetic scenes: analytic shapes ray-cast into depth maps from a ring of cameras,
//! with optional noise. Used by `octstore demo`, the tests and the quality tools, so that no
//! input files are needed.

use std::path::Path;

use glam::{DMat4, DVec3, DVec4};
use serde_json::json;

use crate::inputs::{DepthImage, write_pfm};
use crate::kernels::random::{gaussian, uniform};

/// An analytic solid of a [`SceneSpec`].
#[derive(Clone, Copy, Debug)]
pub enum Shape {
    /// A ball.
    Sphere {
        /// Its centre.
        center: DVec3,
        /// Its radius.
        radius: f64,
    },
    /// Axis-aligned box.
    Box {
        /// The corner with the smallest coordinates.
        min: DVec3,
        /// The corner with the largest coordinates.
        max: DVec3,
    },
}

impl Shape {
    /// Distance along a unit ray to the first hit in front of the origin.
    pub fn hit(&self, origin: DVec3, dir: DVec3) -> Option<f64> {
        match *self {
            Shape::Sphere { center, radius } => {
                let oc = origin - center;
                let b = oc.dot(dir);
                let c = oc.length_squared() - radius * radius;
                let disc = b * b - c;
                if disc < 0.0 {
                    return None;
                }
                let s = disc.sqrt();
                [-b - s, -b + s].into_iter().find(|t| *t > 1e-9)
            }
            Shape::Box { min, max } => {
                let inv = dir.recip();
                let t0 = (min - origin) * inv;
                let t1 = (max - origin) * inv;
                let near = t0.min(t1).max_element();
                let far = t0.max(t1).min_element();
                if near > far || far <= 1e-9 {
                    return None;
                }
                Some(if near > 1e-9 { near } else { far })
            }
        }
    }

    /// Signed distance (negative inside); exact for the sphere, exact outside the box.
    pub fn signed_distance(&self, p: DVec3) -> f64 {
        match *self {
            Shape::Sphere { center, radius } => (p - center).length() - radius,
            Shape::Box { min, max } => {
                let c = (min + max) * 0.5;
                let h = (max - min) * 0.5;
                let q = (p - c).abs() - h;
                q.max(DVec3::ZERO).length() + q.max_element().min(0.0)
            }
        }
    }
}

/// Depth noise and outliers added to a [`SceneSpec`]'s depth maps.
#[derive(Clone, Debug)]
pub struct Noise {
    /// Gaussian depth noise, as a fraction of the depth.
    pub relative_sigma: f64,
    /// Fraction of valid pixels replaced by a random depth between 0.2 and 2 times the true one.
    pub outliers: f64,
    /// Seed of the noise and outlier draws: the same seed gives the same depth maps.
    pub seed: u64,
}

/// A synthetic scene made of analytic shapes, and the ring of pinhole cameras that sees it
/// (`octstore demo` renders [`SceneSpec::demo`]).
#[derive(Clone, Debug)]
pub struct SceneSpec {
    /// The shapes; the surface is the boundary of their union.
    pub shapes: Vec<Shape>,
    /// Number of cameras on a ring around `target`, alternating above and below it.
    pub cameras: usize,
    /// The cameras' distance from `target`, in scene units.
    pub distance: f64,
    /// The point every camera looks at.
    pub target: DVec3,
    /// Depth map width in pixels.
    pub width: u32,
    /// Depth map height in pixels.
    pub height: u32,
    /// Horizontal field of view in degrees.
    pub fov_degrees: f64,
    /// Depth noise and outliers; `None` renders exact depths.
    pub noise: Option<Noise>,
    /// Half-size of a room (walls seen from inside, centred on the target) behind the shapes:
    /// without a background, rays that miss the object carry no free-space evidence.
    pub room: Option<f64>,
}

impl SceneSpec {
    /// The demo scene: a sphere resting on a box, seen by a ring of cameras.
    pub fn demo() -> SceneSpec {
        SceneSpec {
            shapes: vec![
                Shape::Sphere {
                    center: DVec3::new(0.0, 0.0, 0.35),
                    radius: 0.35,
                },
                Shape::Box {
                    min: DVec3::new(-0.5, -0.4, -0.3),
                    max: DVec3::new(0.5, 0.4, 0.05),
                },
            ],
            cameras: 16,
            distance: 2.2,
            target: DVec3::new(0.0, 0.0, 0.05),
            width: 160,
            height: 120,
            fov_degrees: 50.0,
            noise: Some(Noise {
                relative_sigma: 0.002,
                outliers: 0.02,
                seed: 7,
            }),
            room: Some(2.6),
        }
    }

    /// Signed distance to the union of the shapes.
    pub fn signed_distance(&self, p: DVec3) -> f64 {
        self.shapes
            .iter()
            .map(|s| s.signed_distance(p))
            .fold(f64::INFINITY, f64::min)
    }

    /// The cameras' focal length in pixels, from the width and the field of view.
    pub fn focal(&self) -> f64 {
        f64::from(self.width) * 0.5 / (self.fov_degrees.to_radians() * 0.5).tan()
    }

    /// Camera-to-world poses (OpenCV axes) looking at the target.
    pub fn poses(&self) -> Vec<DMat4> {
        (0..self.cameras)
            .map(|i| {
                let angle = std::f64::consts::TAU * i as f64 / self.cameras as f64;
                let elevation: f64 = if i % 2 == 0 { 0.45 } else { -0.25 };
                let eye = self.target
                    + DVec3::new(
                        angle.cos() * elevation.cos(),
                        angle.sin() * elevation.cos(),
                        elevation.sin(),
                    ) * self.distance;
                look_at(eye, self.target)
            })
            .collect()
    }

    /// Distance along the unit ray `dir` from `origin` to the first surface: a shape, else the
    /// room's walls (if any).
    pub fn cast(&self, origin: DVec3, dir: DVec3) -> Option<f64> {
        let hit = self
            .shapes
            .iter()
            .filter_map(|s| s.hit(origin, dir))
            .fold(f64::INFINITY, f64::min);
        if hit.is_finite() {
            return Some(hit);
        }
        let half = self.room?;
        let room = Shape::Box {
            min: self.target - DVec3::splat(half),
            max: self.target + DVec3::splat(half),
        };
        room.hit(origin, dir)
    }

    /// Renders camera `index`: z-depth per pixel, NaN where no shape is hit.
    pub fn render(&self, index: usize, pose: &DMat4) -> DepthImage {
        let f = self.focal();
        let (cx, cy) = (f64::from(self.width) * 0.5, f64::from(self.height) * 0.5);
        let origin = pose.w_axis.truncate();
        let mut rng = self
            .noise
            .as_ref()
            .map(|n| n.seed ^ (index as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
        let mut depth = Vec::with_capacity((self.width * self.height) as usize);
        for j in 0..self.height {
            for i in 0..self.width {
                let local = DVec3::new((f64::from(i) - cx) / f, (f64::from(j) - cy) / f, 1.0);
                let dir_world = pose.transform_vector3(local);
                let scale = dir_world.length();
                let dir = dir_world / scale;
                let mut z = self.cast(origin, dir).map_or(f64::NAN, |hit| hit / scale);
                if let (Some(noise), Some(state)) = (&self.noise, rng.as_mut())
                    && z.is_finite()
                {
                    z = add_noise(z, noise, state);
                }
                depth.push(z as f32);
            }
        }
        DepthImage {
            width: self.width,
            height: self.height,
            depth,
        }
    }

    /// Renders every camera into `dir` as PFM files plus `scene.json`, the manifest to ingest.
    pub fn write(&self, dir: &Path) -> std::io::Result<std::path::PathBuf> {
        let views = self
            .poses()
            .into_iter()
            .enumerate()
            .map(|(index, pose)| (self.render(index, &pose), pose));
        write_pinhole_views(dir, views, self.focal())
    }
}

/// Writes depth maps as `view-NNN.pfm` plus the manifest `scene.json` that ingests them:
/// pinhole cameras with focal length `focal` and the principal point at the image centre,
/// camera-to-world poses with OpenCV axes.
pub fn write_pinhole_views(
    dir: &Path,
    views: impl Iterator<Item = (DepthImage, DMat4)>,
    focal: f64,
) -> std::io::Result<std::path::PathBuf> {
    std::fs::create_dir_all(dir)?;
    let mut entries = Vec::new();
    for (index, (image, pose)) in views.enumerate() {
        let name = format!("view-{index:03}.pfm");
        write_pfm(&dir.join(&name), &image)?;
        let m = pose.transpose().to_cols_array(); // row-major
        entries.push(json!({
            "image": name,
            "width": image.width,
            "height": image.height,
            "intrinsics": {"fx": focal, "fy": focal, "cx": f64::from(image.width) * 0.5, "cy": f64::from(image.height) * 0.5},
            "pose": {"camera_to_world": m, "axes": "opencv"},
            "kind": "photo",
        }));
    }
    let manifest = dir.join("scene.json");
    std::fs::write(
        &manifest,
        serde_json::to_string_pretty(&json!({ "depth_maps": entries })).unwrap_or_default(),
    )?;
    Ok(manifest)
}

/// Camera-to-world pose (OpenCV axes) at `eye` looking at `target`, z up.
pub fn look_at(eye: DVec3, target: DVec3) -> DMat4 {
    let forward = (target - eye).normalize();
    let right = forward.cross(DVec3::Z).normalize_or(DVec3::X);
    let down = forward.cross(right);
    DMat4::from_cols(
        right.extend(0.0),
        down.extend(0.0),
        forward.extend(0.0),
        DVec4::new(eye.x, eye.y, eye.z, 1.0),
    )
}

/// Applies a noise model to a depth value: an outlier (a random depth between 0.2 and 2 times
/// the true one) with probability `noise.outliers`, else Gaussian noise relative to the depth.
pub fn add_noise(z: f64, noise: &Noise, state: &mut u64) -> f64 {
    if uniform(state) < noise.outliers {
        z * (0.2 + 1.8 * uniform(state))
    } else {
        z * (1.0 + noise.relative_sigma * gaussian(state))
    }
}
