//! Depth maps of a ground-truth mesh, for measuring reconstructions against known truth.
//!
//! Cameras sit on a ring or a sphere around the mesh's bounding-box centre, at a distance in
//! units of its diagonal, looking at the centre. Each view is z-buffered (pinhole z-depth,
//! perspective-correct), then a noise model is applied: Gaussian depth noise relative to the
//! depth, outlier pixels, and missing regions (discs of invalid pixels). An optional room (walls
//! seen from inside, centred on the mesh) fills the background: rays that miss the object would
//! otherwise carry no free-space evidence.

use std::path::{Path, PathBuf};

use glam::{DMat4, DVec3};

use super::synthetic_scenes::{Noise, Shape, add_noise, look_at, write_pinhole_views};
use crate::inputs::DepthImage;
use crate::kernels::random::uniform;
use crate::mesh::Mesh;

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Layout {
    /// Alternately above and below the centre, evenly around it.
    Ring,
    /// Spread evenly over a sphere (Fibonacci lattice).
    Sphere,
    /// Inside the mesh, looking outwards: on a horizontal circle of radius `distance`
    /// diagonals around the centre, each facing away from it, alternately tilted down and up,
    /// turning once around over the views (a camera walking around inside a room).
    Interior,
}

#[derive(Clone, Debug)]
pub struct Rig {
    pub views: usize,
    pub layout: Layout,
    /// Camera distance from the centre, in bounding-box diagonals.
    pub distance: f64,
    /// The farthest camera distance (ring and sphere): view i stands at a distance between
    /// `distance` and this, spread evenly over the views in a scrambled order (golden-ratio
    /// steps), so near and far views both see every side. `None`: all at `distance`.
    pub far: Option<f64>,
    pub width: u32,
    pub height: u32,
    /// Horizontal field of view in degrees.
    pub fov_degrees: f64,
}

#[derive(Clone, Debug, Default)]
pub struct NoiseModel {
    /// Gaussian depth noise, as a fraction of the depth (0.005 = 0.5 %).
    pub depth_sigma: f64,
    /// Fraction of valid pixels replaced by a random depth between 0.2 and 2 times the true one.
    pub outliers: f64,
    /// Discs of missing pixels per view.
    pub missing_regions: usize,
    /// Radius of each disc, as a fraction of the image width.
    pub missing_radius: f64,
    pub seed: u64,
}

pub struct GroundTruth {
    pub mesh: Mesh,
    pub center: DVec3,
    pub diagonal: f64,
    /// Half-size of the room around the centre, in diagonals.
    pub room: Option<f64>,
}

impl GroundTruth {
    pub fn new(mesh: Mesh, room: Option<f64>) -> Result<GroundTruth, super::QualityError> {
        let (lo, hi) = bounds(&mesh).ok_or(super::QualityError::NoTriangles)?;
        Ok(GroundTruth {
            center: (lo + hi) * 0.5,
            diagonal: (hi - lo).length(),
            mesh,
            room,
        })
    }

    pub fn focal(&self, rig: &Rig) -> f64 {
        f64::from(rig.width) * 0.5 / (rig.fov_degrees.to_radians() * 0.5).tan()
    }

    pub fn poses(&self, rig: &Rig) -> Vec<DMat4> {
        let n = rig.views.max(1);
        (0..n)
            .map(|i| {
                let direction = match rig.layout {
                    Layout::Ring => {
                        let angle = std::f64::consts::TAU * i as f64 / n as f64;
                        let elevation: f64 = if i % 2 == 0 { 0.45 } else { -0.25 };
                        DVec3::new(
                            angle.cos() * elevation.cos(),
                            angle.sin() * elevation.cos(),
                            elevation.sin(),
                        )
                    }
                    Layout::Interior => {
                        let angle = std::f64::consts::TAU * i as f64 / n as f64;
                        let outwards = DVec3::new(angle.cos(), angle.sin(), 0.0);
                        let tilt: f64 = if i % 2 == 0 { -0.35 } else { 0.1 };
                        let eye = self.center + outwards * rig.distance * self.diagonal;
                        let looking = DVec3::new(angle.cos() * tilt.cos(), angle.sin() * tilt.cos(), tilt.sin());
                        return look_at(eye, eye + looking);
                    }
                    Layout::Sphere => {
                        let z = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
                        let angle = std::f64::consts::PI * (3.0 - 5f64.sqrt()) * i as f64;
                        let r = (1.0 - z * z).sqrt();
                        // Keep off the poles, where "up" is undefined for the camera.
                        DVec3::new(r * angle.cos(), r * angle.sin(), z.clamp(-0.95, 0.95)).normalize()
                    }
                };
                let distance = match rig.far {
                    Some(far) => rig.distance + (far - rig.distance) * (i as f64 * 0.618_033_988_749_895).fract(),
                    None => rig.distance,
                };
                look_at(self.center + direction * distance * self.diagonal, self.center)
            })
            .collect()
    }

    /// The noise-free z-depth of view `pose`; NaN where nothing is hit.
    pub fn render_exact(&self, rig: &Rig, pose: &DMat4) -> DepthImage {
        self.render_exact_with_faces(rig, pose).0
    }

    /// Which triangles of the mesh some view of the rig sees (in at least one pixel).
    pub fn seen_faces(&self, rig: &Rig) -> Vec<bool> {
        let mut seen = vec![false; self.mesh.triangles.len()];
        for pose in self.poses(rig) {
            for face in self.render_exact_with_faces(rig, &pose).1 {
                if let Some(flag) = seen.get_mut(face as usize) {
                    *flag = true;
                }
            }
        }
        seen
    }

    /// [`GroundTruth::render_exact`], and per pixel the triangle it sees (`u32::MAX` for none
    /// or the room).
    fn render_exact_with_faces(&self, rig: &Rig, pose: &DMat4) -> (DepthImage, Vec<u32>) {
        let (w, h) = (rig.width as usize, rig.height as usize);
        let f = self.focal(rig);
        let (cx, cy) = (f64::from(rig.width) * 0.5, f64::from(rig.height) * 0.5);
        let world_to_camera = pose.inverse();
        let camera: Vec<DVec3> = self
            .mesh
            .positions
            .iter()
            .map(|p| world_to_camera.transform_point3(DVec3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]))))
            .collect();
        let near = 1e-3 * self.diagonal;
        let mut depth = vec![f64::INFINITY; w * h];
        let mut faces = vec![u32::MAX; w * h];
        for (index, t) in self.mesh.triangles.iter().enumerate() {
            let [Some(a), Some(b), Some(c)] = t.map(|v| camera.get(v as usize).copied()) else {
                continue;
            };
            if a.z <= near || b.z <= near || c.z <= near {
                continue;
            }
            let screen = |p: DVec3| (f * p.x / p.z + cx, f * p.y / p.z + cy, 1.0 / p.z);
            let (s0, s1, s2) = (screen(a), screen(b), screen(c));
            let area = (s1.0 - s0.0) * (s2.1 - s0.1) - (s2.0 - s0.0) * (s1.1 - s0.1);
            if area.abs() < 1e-12 {
                continue;
            }
            let min_x = s0.0.min(s1.0).min(s2.0).ceil().max(0.0) as usize;
            let max_x = s0.0.max(s1.0).max(s2.0).floor().min(w as f64 - 1.0);
            let min_y = s0.1.min(s1.1).min(s2.1).ceil().max(0.0) as usize;
            let max_y = s0.1.max(s1.1).max(s2.1).floor().min(h as f64 - 1.0);
            if max_x < 0.0 || max_y < 0.0 {
                continue;
            }
            for j in min_y..=max_y as usize {
                for i in min_x..=max_x as usize {
                    let (x, y) = (i as f64, j as f64);
                    let w0 = ((s1.0 - x) * (s2.1 - y) - (s2.0 - x) * (s1.1 - y)) / area;
                    let w1 = ((s2.0 - x) * (s0.1 - y) - (s0.0 - x) * (s2.1 - y)) / area;
                    let w2 = 1.0 - w0 - w1;
                    if w0 < 0.0 || w1 < 0.0 || w2 < 0.0 {
                        continue;
                    }
                    // 1/z is linear in screen space.
                    let z = 1.0 / (w0 * s0.2 + w1 * s1.2 + w2 * s2.2);
                    if let Some(d) = depth.get_mut(j * w + i)
                        && z < *d
                    {
                        *d = z;
                        if let Some(face) = faces.get_mut(j * w + i) {
                            *face = index as u32;
                        }
                    }
                }
            }
        }
        let room = self.room.map(|half| Shape::Box {
            min: self.center - DVec3::splat(half * self.diagonal),
            max: self.center + DVec3::splat(half * self.diagonal),
        });
        let origin = pose.w_axis.truncate();
        for j in 0..h {
            for i in 0..w {
                let Some(d) = depth.get_mut(j * w + i) else { continue };
                if d.is_finite() {
                    continue;
                }
                if let Some(room) = &room {
                    let local = DVec3::new((i as f64 - cx) / f, (j as f64 - cy) / f, 1.0);
                    let world = pose.transform_vector3(local);
                    let length = world.length();
                    if let Some(t) = room.hit(origin, world / length) {
                        *d = t / length;
                    }
                }
            }
        }
        let image = DepthImage {
            width: rig.width,
            height: rig.height,
            depth: depth
                .into_iter()
                .map(|d| if d.is_finite() { d as f32 } else { f32::NAN })
                .collect(),
        };
        (image, faces)
    }

    /// View `index` with the noise model applied (deterministic in the seed and the index).
    pub fn render(&self, rig: &Rig, pose: &DMat4, index: usize, noise: &NoiseModel) -> DepthImage {
        let mut image = self.render_exact(rig, pose);
        let mut state = noise.seed ^ (index as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15);
        let pixel_noise = Noise {
            relative_sigma: noise.depth_sigma,
            outliers: noise.outliers,
            seed: noise.seed,
        };
        for d in &mut image.depth {
            if d.is_finite() {
                *d = add_noise(f64::from(*d), &pixel_noise, &mut state) as f32;
            }
        }
        let radius = noise.missing_radius * f64::from(rig.width);
        for _ in 0..noise.missing_regions {
            let (ci, cj) = (
                uniform(&mut state) * f64::from(rig.width),
                uniform(&mut state) * f64::from(rig.height),
            );
            for j in 0..rig.height {
                for i in 0..rig.width {
                    let (di, dj) = (f64::from(i) - ci, f64::from(j) - cj);
                    if di * di + dj * dj <= radius * radius
                        && let Some(d) = image.depth.get_mut(j as usize * rig.width as usize + i as usize)
                    {
                        *d = f32::NAN;
                    }
                }
            }
        }
        image
    }

    /// Renders every view into `dir` (PFM files plus the manifest `scene.json`, which it
    /// returns).
    pub fn write_dataset(&self, rig: &Rig, noise: &NoiseModel, dir: &Path) -> std::io::Result<PathBuf> {
        let poses = self.poses(rig);
        let views = poses
            .iter()
            .enumerate()
            .map(|(index, pose)| (self.render(rig, pose, index, noise), *pose));
        write_pinhole_views(dir, views, self.focal(rig))
    }

    /// Renders every view into `dir` as a 7-Scenes folder (`frame-XXXXXX.depth.png` in
    /// thousandths of a scene unit, 0 where nothing is seen; `frame-XXXXXX.pose.txt`;
    /// `camera-intrinsics.txt`), the layout an RGB-D capture comes in. Depths past 65.534 units
    /// cannot be written and are refused.
    pub fn write_seven_scenes(&self, rig: &Rig, noise: &NoiseModel, dir: &Path) -> std::io::Result<PathBuf> {
        std::fs::create_dir_all(dir)?;
        let f = self.focal(rig);
        let (cx, cy) = (f64::from(rig.width) * 0.5, f64::from(rig.height) * 0.5);
        std::fs::write(
            dir.join("camera-intrinsics.txt"),
            format!("{f} 0 {cx}\n0 {f} {cy}\n0 0 1\n"),
        )?;
        for (index, pose) in self.poses(rig).iter().enumerate() {
            let image = self.render(rig, pose, index, noise);
            let mut pixels = Vec::with_capacity(image.depth.len());
            for d in &image.depth {
                let millis = if d.is_finite() && *d > 0.0 {
                    (f64::from(*d) * 1000.0).round()
                } else {
                    0.0
                };
                if millis >= 65535.0 {
                    return Err(std::io::Error::other(format!(
                        "view {index}: depth {d} is past a 16-bit PNG's 65.534 units"
                    )));
                }
                pixels.push(millis as u16);
            }
            let png = image::ImageBuffer::<image::Luma<u16>, Vec<u16>>::from_raw(image.width, image.height, pixels)
                .ok_or_else(|| std::io::Error::other("image size"))?;
            png.save(dir.join(format!("frame-{index:06}.depth.png")))
                .map_err(std::io::Error::other)?;
            let rows: String = (0..4)
                .map(|r| {
                    let row = pose.row(r);
                    format!("{} {} {} {}\n", row.x, row.y, row.z, row.w)
                })
                .collect();
            std::fs::write(dir.join(format!("frame-{index:06}.pose.txt")), rows)?;
        }
        Ok(dir.to_path_buf())
    }
}

/// Axis-aligned bounds of the vertices that triangles use.
pub fn bounds(mesh: &Mesh) -> Option<(DVec3, DVec3)> {
    let mut used = mesh
        .triangles
        .iter()
        .flatten()
        .filter_map(|&v| mesh.positions.get(v as usize))
        .map(|p| DVec3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2])));
    let first = used.next()?;
    Some(used.fold((first, first), |(lo, hi), p| (lo.min(p), hi.max(p))))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A unit cube as 12 triangles.
    fn cube() -> Mesh {
        let positions: Vec<[f32; 3]> = (0..8)
            .map(|i| [(i & 1) as f32, ((i >> 1) & 1) as f32, ((i >> 2) & 1) as f32])
            .collect();
        let quads = [
            [0, 1, 3, 2],
            [4, 5, 7, 6],
            [0, 1, 5, 4],
            [2, 3, 7, 6],
            [0, 2, 6, 4],
            [1, 3, 7, 5],
        ];
        let triangles = quads
            .iter()
            .flat_map(|q| [[q[0], q[1], q[2]], [q[0], q[2], q[3]]])
            .collect();
        Mesh {
            positions,
            normals: Vec::new(),
            triangles,
        }
    }

    #[test]
    fn rendered_depths_back_project_onto_the_mesh() {
        let truth = GroundTruth::new(cube(), Some(2.0)).unwrap();
        let rig = Rig {
            views: 6,
            layout: Layout::Sphere,
            distance: 1.5,
            far: None,
            width: 64,
            height: 48,
            fov_degrees: 50.0,
        };
        let f = truth.focal(&rig);
        let half_room = 2.0 * truth.diagonal;
        for pose in truth.poses(&rig) {
            let image = truth.render_exact(&rig, &pose);
            let mut on_cube = 0;
            for j in 0..rig.height {
                for i in 0..rig.width {
                    let z = f64::from(image.get(i, j));
                    assert!(z.is_finite(), "the room leaves no pixel empty");
                    let local = DVec3::new((f64::from(i) - 32.0) / f, (f64::from(j) - 24.0) / f, 1.0) * z;
                    let p = pose.transform_point3(local);
                    let cube_distance = Shape::Box {
                        min: DVec3::ZERO,
                        max: DVec3::ONE,
                    }
                    .signed_distance(p)
                    .abs();
                    let wall_distance = (half_room - (p - truth.center).abs().max_element()).abs();
                    assert!(cube_distance.min(wall_distance) < 1e-6, "pixel ({i}, {j}) at {p:?}");
                    on_cube += usize::from(cube_distance < 1e-6);
                }
            }
            assert!(on_cube > 200, "{on_cube} pixels see the cube");
        }
    }

    #[test]
    fn noise_is_deterministic_and_has_the_asked_rates() {
        let truth = GroundTruth::new(cube(), Some(2.0)).unwrap();
        let rig = Rig {
            views: 2,
            layout: Layout::Ring,
            distance: 1.5,
            far: None,
            width: 100,
            height: 80,
            fov_degrees: 50.0,
        };
        let noise = NoiseModel {
            depth_sigma: 0.0,
            outliers: 0.1,
            missing_regions: 2,
            missing_radius: 0.1,
            seed: 3,
        };
        let pose = truth.poses(&rig)[0];
        let exact = truth.render_exact(&rig, &pose);
        let a = truth.render(&rig, &pose, 0, &noise);
        let b = truth.render(&rig, &pose, 0, &noise);
        assert!(a.depth.iter().zip(&b.depth).all(|(x, y)| x.to_bits() == y.to_bits()));
        let missing = a.depth.iter().filter(|d| d.is_nan()).count();
        assert!(missing > 300, "{missing} missing pixels");
        let changed = a
            .depth
            .iter()
            .zip(&exact.depth)
            .filter(|(x, y)| x.is_finite() && x != y)
            .count();
        let kept = a.depth.iter().filter(|d| d.is_finite()).count();
        let rate = changed as f64 / kept as f64;
        assert!((0.08..0.12).contains(&rate), "outlier rate {rate}");
    }
}
