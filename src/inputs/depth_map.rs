//! Depth maps: camera models, poses, and the image formats they are read from.
//!
//! Conventions (docs/inputs.md): poses are camera-to-world with OpenCV camera axes (x right,
//! y down, z forward); pinhole depth is the z coordinate in the camera frame, pixel (i, j) has
//! its centre at image coordinates (i, j); spherical (LIDAR) depth is the range along the ray.

use std::path::{Path, PathBuf};

use glam::{DMat3, DMat4, DVec3};
use serde::{Deserialize, Serialize};

/// How far from an image's centre its principal point may lie, as a fraction of the image's
/// width or height (`DepthMapSource::check_intrinsics`).
pub const PRINCIPAL_POINT_REACH: f64 = 0.08;

/// Errors of reading inputs: each names the file and the problem.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum InputError {
    /// The path does not exist.
    #[error("{}: no such file or folder", file.display())]
    NotFound {
        /// The path given.
        file: PathBuf,
    },
    /// The path is a folder, FIFO, socket or device where a file was expected (opening a FIFO
    /// would block).
    #[error("{}: not a regular file ({kind}): name the file itself", file.display())]
    NotARegularFile {
        /// The path given.
        file: PathBuf,
        /// What it is instead: "a folder", or "a FIFO, socket or device".
        kind: &'static str,
    },
    /// `--format auto` cannot tell what the path holds.
    #[error("{}: cannot tell the input format ({expected}); pass --format", file.display())]
    UnknownFormat {
        /// The path given.
        file: PathBuf,
        /// What auto-detection looks for at such a path.
        expected: &'static str,
    },
    /// A camera-to-world pose that is not a rotation and a translation.
    #[error("{}: {problem}", file.display())]
    BadPose {
        /// The file holding the pose.
        file: PathBuf,
        /// What is wrong with it.
        problem: PoseProblem,
    },
    /// The file is not a usable input: the problems programs are not expected to tell apart
    /// (a malformed header, a truncated image, a value out of range, ...), named in words.
    #[error("{}: {problem}", file.display())]
    Bad {
        /// The file.
        file: PathBuf,
        /// What is wrong with it.
        problem: String,
    },
    /// The file cannot be read.
    #[error("{file}: {source}")]
    Io {
        /// The file.
        file: PathBuf,
        /// The system's error.
        source: std::io::Error,
    },
}

/// A file's extension in lower case (empty when it has none): what the readers dispatch on.
pub fn extension_of(path: &Path) -> String {
    path.extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
        .unwrap_or_default()
}

/// An [`InputError::Bad`] for `file`.
pub fn bad(file: &Path, problem: impl Into<String>) -> InputError {
    InputError::Bad {
        file: file.to_path_buf(),
        problem: problem.into(),
    }
}

/// How pixels map to rays.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq)]
pub enum Projection {
    /// A pinhole camera; depth is the z coordinate in the camera frame.
    Pinhole {
        /// Focal length along x, in pixels.
        fx: f64,
        /// Focal length along y, in pixels.
        fy: f64,
        /// Principal point, x (pixel centres at integer coordinates).
        cx: f64,
        /// Principal point, y.
        cy: f64,
    },
    /// Equirectangular 360-degree scan: column i is azimuth 2 pi i / width (counter-clockwise
    /// about +z from +x), row j is elevation pi/2 - pi (j + 0.5) / height. Axes of the sensor
    /// frame: z up.
    Spherical,
}

/// What kind of sensor a depth map comes from (it sets the default vote weight).
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    /// A photogrammetry depth map (COLMAP).
    Photo,
    /// An RGB-D sensor frame.
    Rgbd,
    /// A terrestrial LIDAR scan.
    Lidar,
}

impl Kind {
    /// Default vote weight (Algorithm 1: 5 for noise-free LIDAR).
    pub fn default_weight(self) -> f32 {
        match self {
            Kind::Lidar => 5.0,
            Kind::Photo | Kind::Rgbd => 1.0,
        }
    }

    /// Default depth noise, whatever the kind: measured from each map's pixels when it is
    /// ingested ([`DepthNoise::Auto`]). A kind says nothing of the sensor's noise at the
    /// scene's scale and units; the sensor tables stay as explicit choices.
    pub fn default_noise(self) -> DepthNoise {
        DepthNoise::Auto { sigmas: None }
    }
}

/// How many standard deviations of depth noise a sample's radius spans at least, by default
/// (BENCHMARKS.md, "Cube sizes of RGB-D frames": measured on RedKitchen).
pub const DEFAULT_NOISE_SIGMAS: f64 = 1.0;

/// The most pixel footprints the noise may widen a sample's radius to, by default
/// (BENCHMARKS.md, "Cube sizes of RGB-D frames": measured on RedKitchen).
pub const DEFAULT_NOISE_FOOTPRINTS: f64 = 3.0;

/// A depth map's noise model, which bounds how small its samples' cubes may be.
///
/// Eq. 4 sizes a sample's cube by its pixel footprint alone. An RGB-D sensor's depth noise is
/// several footprints (a Kinect's is about 2 mm at 1 m and 6 mm at 2 m, where a pixel spans
/// 1.7 and 3.4 mm), so cubes at the footprint resolve the noise, not the surface, and cost
/// time. A sample's radius is therefore at least `sigmas` standard deviations of its depth's
/// noise, but never more than `footprints` times its footprint radius: the noise is axial, it
/// blurs a surface along the rays, while edges and silhouettes stay placed to a footprint or
/// two, and cubes many footprints wide round them off and carry surfaces past them (on
/// RedKitchen, without the cap, half the mesh area farther than 15 mm from every sample came
/// from shelf and table edges seen from 2 m or more). The model is recorded with each depth map
/// (format-spec.md, "Catalog"), so a store keeps the rule its maps were ingested with.
#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq)]
pub enum DepthNoise {
    /// No noise model: a sample's radius is half the distance to its nearest neighbour (eq. 4).
    /// Photogrammetry's default, and the rule of every map of a catalog before version 3.
    Footprint,
    /// sigma(d) = constant + quadratic (d - offset)^2 at depth d (scene units, the depth map's
    /// own sense of depth: z for pinhole maps, range for spherical ones).
    Axial {
        /// sigma at `offset`.
        constant: f64,
        /// Growth with the squared depth beyond `offset`.
        quadratic: f64,
        /// Depth of the least noise.
        offset: f64,
        /// A sample's radius is at least this many sigma(d)...
        sigmas: f64,
        /// ... but that floor is at most this many times its footprint radius.
        footprints: f64,
    },
    /// Measured from the map's own pixels at ingest (`stages::ingest::noise`), which records
    /// the measured [`Axial`](Self::Axial) model (or [`Footprint`](Self::Footprint)) in its
    /// place: a registered map never holds `Auto`.
    Auto {
        /// The measured model spans this many standard deviations; by default as many as the
        /// kind of error measured needs (`stages::ingest::noise`).
        sigmas: Option<f64>,
    },
}

impl std::fmt::Display for DepthNoise {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            DepthNoise::Auto { sigmas: Some(sigmas) } => {
                return write!(f, "auto (measured from the pixels, {sigmas} sigma)");
            }
            DepthNoise::Auto { sigmas: None } => return write!(f, "auto (measured from the pixels)"),
            _ => {}
        }
        match self.parts() {
            None => write!(f, "none (pixel footprint)"),
            Some([constant, 0.0, _, sigmas, footprints]) => {
                write!(f, "radius >= min({sigmas} x {constant}, {footprints} footprints)")
            }
            Some([constant, quadratic, offset, sigmas, footprints]) => write!(
                f,
                "radius >= min({sigmas} x ({constant} + {quadratic} (d - {offset})^2), {footprints} footprints)"
            ),
        }
    }
}

impl DepthNoise {
    /// Structured-light and time-of-flight RGB-D sensors (Kinect class): sigma(z) = 0.0012 +
    /// 0.0019 (z - 0.4)^2 metres (Nguyen, Izadi and Lovell 2012, axial noise).
    pub const STRUCTURED_LIGHT: DepthNoise =
        DepthNoise::from_parts([0.0012, 0.0019, 0.4, DEFAULT_NOISE_SIGMAS, DEFAULT_NOISE_FOOTPRINTS]);

    /// Terrestrial laser scanners: about 2 mm of range noise, whatever the range.
    pub const TERRESTRIAL_LIDAR: DepthNoise =
        DepthNoise::from_parts([0.002, 0.0, 0.0, DEFAULT_NOISE_SIGMAS, DEFAULT_NOISE_FOOTPRINTS]);

    /// An axial model from [constant, quadratic, offset, sigmas, footprints].
    pub(crate) const fn from_parts([constant, quadratic, offset, sigmas, footprints]: [f64; 5]) -> DepthNoise {
        DepthNoise::Axial {
            constant,
            quadratic,
            offset,
            sigmas,
            footprints,
        }
    }

    /// [constant, quadratic, offset, sigmas, footprints] of an axial model.
    pub(crate) fn parts(&self) -> Option<[f64; 5]> {
        match *self {
            DepthNoise::Footprint | DepthNoise::Auto { .. } => None,
            DepthNoise::Axial {
                constant,
                quadratic,
                offset,
                sigmas,
                footprints,
            } => Some([constant, quadratic, offset, sigmas, footprints]),
        }
    }

    /// The standard deviation of a depth measured at `depth` (0 without a model).
    pub fn sigma(&self, depth: f64) -> f64 {
        self.parts().map_or(0.0, |[constant, quadratic, offset, ..]| {
            constant + quadratic * (depth - offset).powi(2)
        })
    }

    /// The radius of a sample at `depth` whose footprint radius (half the distance to its
    /// nearest neighbour) is `footprint`.
    pub fn radius(&self, footprint: f64, depth: f64) -> f64 {
        let Some([_, _, _, sigmas, footprints]) = self.parts() else {
            return footprint;
        };
        let floor = sigmas * self.sigma(depth);
        footprint.max(floor.min(footprints * footprint))
    }

    /// The same model spanning `sigmas` standard deviations (no change to [`Footprint`](Self::Footprint)).
    pub fn with_sigmas(self, sigmas: f64) -> DepthNoise {
        if let DepthNoise::Auto { .. } = self {
            return DepthNoise::Auto { sigmas: Some(sigmas) };
        }
        match self.parts() {
            None => DepthNoise::Footprint,
            Some([constant, quadratic, offset, _, footprints]) => {
                DepthNoise::from_parts([constant, quadratic, offset, sigmas, footprints])
            }
        }
    }

    /// A model from its numbers: none (no model), sigma (constant), or constant, quadratic and
    /// offset; `sigmas` per radius, at most [`DEFAULT_NOISE_FOOTPRINTS`].
    pub fn from_numbers(numbers: &[f64], sigmas: f64) -> Result<DepthNoise, String> {
        let noise = match *numbers {
            [] => DepthNoise::Footprint,
            [constant] => DepthNoise::from_parts([constant, 0.0, 0.0, sigmas, DEFAULT_NOISE_FOOTPRINTS]),
            [constant, quadratic, offset] => {
                DepthNoise::from_parts([constant, quadratic, offset, sigmas, DEFAULT_NOISE_FOOTPRINTS])
            }
            _ => {
                return Err(format!(
                    "a depth noise model has 1 number (sigma) or 3 (constant, quadratic, offset: sigma(d) = constant + quadratic (d - offset)^2), not {}",
                    numbers.len()
                ));
            }
        };
        if !noise.is_valid() {
            return Err(format!(
                "depth noise numbers must be finite and not negative: {numbers:?}, sigmas {sigmas}"
            ));
        }
        Ok(noise)
    }

    /// A model by name: `auto`, `none`, `kinect` ([`STRUCTURED_LIGHT`](Self::STRUCTURED_LIGHT))
    /// or `lidar` ([`TERRESTRIAL_LIDAR`](Self::TERRESTRIAL_LIDAR)), spanning `sigmas` (the
    /// tables' default [`DEFAULT_NOISE_SIGMAS`] and auto's own choice when `None`).
    pub fn named(name: &str, sigmas: Option<f64>) -> Option<DepthNoise> {
        let table = |model: DepthNoise| model.with_sigmas(sigmas.unwrap_or(DEFAULT_NOISE_SIGMAS));
        match name {
            "auto" => Some(DepthNoise::Auto { sigmas }),
            "none" => Some(DepthNoise::Footprint),
            "kinect" => Some(table(DepthNoise::STRUCTURED_LIGHT)),
            "lidar" => Some(table(DepthNoise::TERRESTRIAL_LIDAR)),
            _ => None,
        }
    }

    /// Whether every number is finite and none negative.
    pub fn is_valid(&self) -> bool {
        if let DepthNoise::Auto { sigmas } = self {
            return sigmas.is_none_or(|sigmas| sigmas.is_finite() && sigmas >= 0.0);
        }
        self.parts()
            .is_none_or(|parts| parts.iter().all(|v| v.is_finite() && *v >= 0.0))
    }
}

/// The file format of a depth map.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub enum ImageFormat {
    /// 16-bit grey PNG; depth = value * scale; 0 and 65535 are invalid.
    Png16 {
        /// Metres (or scene units) per PNG unit.
        scale: f64,
    },
    /// Portable float map (grey "Pf"), rows bottom to top as the format says.
    Pfm,
    /// NumPy .npy, 2-D little-endian float32 (`<f4`), C order.
    NpyF32,
    /// COLMAP depth map (`stereo/depth_maps/*.bin`): `width&height&1&` then float32 rows.
    ColmapBin,
    /// Scan number `scan` (from 0) of a PTX file, resampled into the spherical grid.
    Ptx {
        /// The scan's index in the file.
        scan: u32,
    },
    /// Point cloud number `scan` (from 0) of an E57 file, resampled into the spherical grid.
    E57 {
        /// The point cloud's index in the file.
        scan: u32,
    },
}

/// Everything needed to read a depth map again later (the store keeps references, not pixels).
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct DepthMapSource {
    /// The file.
    pub path: PathBuf,
    /// How to read it.
    pub format: ImageFormat,
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// The camera model.
    pub projection: Projection,
    /// Camera-to-world, column-major 4x4.
    pub camera_to_world: [f64; 16],
    /// The sensor kind.
    pub kind: Kind,
    /// Weight of each of its votes.
    pub weight: f32,
    /// Its depth noise, which bounds its samples' cube sizes. Not part of its identity
    /// (`stages::ingest::depth_map_id`): a depth map is ingested once, with the model it came with.
    pub noise: DepthNoise,
}

/// Depth values, row-major; NaN marks an invalid pixel.
pub struct DepthImage {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// `width * height` depths, row by row.
    pub depth: Vec<f32>,
}

impl DepthImage {
    /// The depth at column `i`, row `j` (NaN when invalid or outside the image).
    pub fn get(&self, i: u32, j: u32) -> f32 {
        if i >= self.width || j >= self.height {
            return f32::NAN;
        }
        self.depth
            .get(j as usize * self.width as usize + i as usize)
            .copied()
            .unwrap_or(f32::NAN)
    }
}

/// The most standard deviations a sample's radius may span (`--noise-sigmas`, a manifest's
/// `noise_sigmas`).
pub const MAX_NOISE_SIGMAS: f64 = 100.0;

/// The largest depth scale (scene units per PNG unit) a 16-bit depth image may have: a unit
/// of more than a kilometre is no depth scale but a mistake.
pub const MAX_DEPTH_SCALE: f64 = 1000.0;

/// Checks a number of standard deviations (the command line's and the manifest's one rule):
/// finite, in [0, [`MAX_NOISE_SIGMAS`]].
pub fn check_noise_sigmas(sigmas: f64) -> Result<f64, String> {
    if (0.0..=MAX_NOISE_SIGMAS).contains(&sigmas) {
        Ok(sigmas)
    } else {
        Err(format!(
            "{sigmas} is not a number of standard deviations in [0, {MAX_NOISE_SIGMAS}] (0: cubes follow the pixel footprint alone)"
        ))
    }
}

/// Checks a 16-bit image's depth scale: finite, positive, at most [`MAX_DEPTH_SCALE`].
pub fn check_depth_scale(scale: f64) -> Result<f64, String> {
    if scale > 0.0 && scale <= MAX_DEPTH_SCALE {
        Ok(scale)
    } else {
        Err(format!(
            "depth_scale {scale} is not a positive number of scene units per PNG unit of at most {MAX_DEPTH_SCALE} (0.001: millimetres to metres)"
        ))
    }
}

/// What is wrong with a camera-to-world pose ([`InputError::BadPose`]).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[non_exhaustive]
pub enum PoseProblem {
    /// A NaN or infinite entry.
    #[error("pose has non-finite entries")]
    NonFinite,
    /// The last row is not `0 0 0 1`.
    #[error("pose's last row is {0:?}, expected 0 0 0 1")]
    NotAffine([f64; 4]),
    /// The rotation part is singular.
    #[error("pose is not invertible (rotation determinant {0:.3e})")]
    NotInvertible(f64),
    /// The rotation part mirrors (determinant -1).
    #[error(
        "pose's rotation is a reflection (determinant {0:.3}): a camera-to-world pose is a rotation and a translation; check the axes convention (one axis flipped)"
    )]
    Reflection(f64),
    /// The rotation part scales or shears (depth is metric, so no scale is allowed).
    #[error("pose's rotation is not orthonormal (error {0:.3e})")]
    NotOrthonormal(f64),
}

/// Checks that `path` is a regular file (or a link to one) before it is opened: opening a FIFO
/// blocks until something writes to it, and a device or a folder is no depth map.
pub fn check_regular_file(path: &Path) -> Result<(), InputError> {
    match std::fs::metadata(path) {
        Ok(metadata) if metadata.is_file() => Ok(()),
        Ok(metadata) => Err(InputError::NotARegularFile {
            file: path.to_path_buf(),
            kind: if metadata.is_dir() {
                "a folder"
            } else {
                "a FIFO, socket or device"
            },
        }),
        Err(source) => Err(InputError::Io {
            file: path.to_path_buf(),
            source,
        }),
    }
}

/// Checks a camera-to-world matrix: finite, affine, with an invertible, near-orthonormal
/// rotation part (scale is not allowed: depth is metric).
pub fn check_pose(file: &Path, m: &DMat4) -> Result<(), InputError> {
    pose_problem(m).map_or(Ok(()), |problem| {
        Err(InputError::BadPose {
            file: file.to_path_buf(),
            problem,
        })
    })
}

/// What is wrong with a camera-to-world matrix, if anything.
fn pose_problem(m: &DMat4) -> Option<PoseProblem> {
    if !m.to_cols_array().iter().all(|v| v.is_finite()) {
        return Some(PoseProblem::NonFinite);
    }
    let row3 = m.row(3);
    if (row3 - glam::DVec4::new(0.0, 0.0, 0.0, 1.0)).abs().max_element() > 1e-6 {
        return Some(PoseProblem::NotAffine(row3.to_array()));
    }
    let r = DMat3::from_mat4(*m);
    let det = r.determinant();
    if det.abs() < 1e-6 {
        return Some(PoseProblem::NotInvertible(det));
    }
    if det < 0.0 {
        return Some(PoseProblem::Reflection(det));
    }
    let err = (r.transpose() * r - DMat3::IDENTITY)
        .to_cols_array()
        .iter()
        .fold(0f64, |a, b| a.max(b.abs()));
    (err > 1e-3).then_some(PoseProblem::NotOrthonormal(err))
}

impl DepthMapSource {
    /// An RGB-D frame: a 16-bit depth PNG of `size` at `scale` metres per unit, its
    /// intrinsics checked against the size.
    pub fn rgbd_png(
        path: &Path,
        scale: f64,
        size: (u32, u32),
        projection: Projection,
        camera_to_world: &DMat4,
    ) -> Result<Self, InputError> {
        let source = DepthMapSource {
            path: std::path::absolute(path).unwrap_or_else(|_| path.to_path_buf()),
            format: ImageFormat::Png16 { scale },
            width: size.0,
            height: size.1,
            projection,
            camera_to_world: camera_to_world.to_cols_array(),
            kind: Kind::Rgbd,
            weight: Kind::Rgbd.default_weight(),
            noise: Kind::Rgbd.default_noise(),
        };
        source.check_intrinsics()?;
        Ok(source)
    }

    /// A photo-kind pinhole PFM map of `size` with intrinsics fx, fy, cx, cy at
    /// `camera_to_world`: the unit tests' camera.
    #[cfg(test)]
    pub(crate) fn test_pinhole(path: &str, size: (u32, u32), k: [f64; 4], camera_to_world: DMat4) -> DepthMapSource {
        let [fx, fy, cx, cy] = k;
        DepthMapSource {
            path: path.into(),
            format: ImageFormat::Pfm,
            width: size.0,
            height: size.1,
            projection: Projection::Pinhole { fx, fy, cx, cy },
            camera_to_world: camera_to_world.to_cols_array(),
            kind: Kind::Photo,
            weight: 1.0,
            noise: DepthNoise::Footprint,
        }
    }

    /// The camera-to-world pose.
    pub fn pose(&self) -> DMat4 {
        DMat4::from_cols_array(&self.camera_to_world)
    }

    /// Angle one pixel spans (radians) at the image's coarsest direction: a surface at distance
    /// `t` facing the camera has samples `t * pixel_angle()` apart.
    pub fn pixel_angle(&self) -> f64 {
        match self.projection {
            Projection::Pinhole { fx, fy, .. } => 1.0 / fx.min(fy),
            Projection::Spherical => std::f64::consts::TAU / f64::from(self.width.max(1)),
        }
    }

    /// Direction in the camera frame for pixel (i, j), scaled so that `origin + dir * depth`
    /// is the sample: z = 1 for pinhole (depth is z), unit length for spherical (depth is range).
    pub fn ray(&self, i: f64, j: f64) -> DVec3 {
        match self.projection {
            Projection::Pinhole { fx, fy, cx, cy } => DVec3::new((i - cx) / fx, (j - cy) / fy, 1.0),
            Projection::Spherical => {
                let azimuth = std::f64::consts::TAU * i / f64::from(self.width);
                let elevation = std::f64::consts::FRAC_PI_2 - std::f64::consts::PI * (j + 0.5) / f64::from(self.height);
                DVec3::new(
                    elevation.cos() * azimuth.cos(),
                    elevation.cos() * azimuth.sin(),
                    elevation.sin(),
                )
            }
        }
    }

    /// The derivatives of [`ray`](Self::ray) at pixel (i, j) along i and along j.
    pub fn ray_derivatives(&self, i: f64, j: f64) -> (DVec3, DVec3) {
        match self.projection {
            Projection::Pinhole { fx, fy, .. } => (DVec3::new(1.0 / fx, 0.0, 0.0), DVec3::new(0.0, 1.0 / fy, 0.0)),
            Projection::Spherical => {
                let azimuth_step = std::f64::consts::TAU / f64::from(self.width);
                let elevation_step = -std::f64::consts::PI / f64::from(self.height);
                let azimuth = azimuth_step * i;
                let elevation = std::f64::consts::FRAC_PI_2 + elevation_step * (j + 0.5);
                let (sin_a, cos_a) = azimuth.sin_cos();
                let (sin_e, cos_e) = elevation.sin_cos();
                (
                    DVec3::new(-cos_e * sin_a, cos_e * cos_a, 0.0) * azimuth_step,
                    DVec3::new(-sin_e * cos_a, -sin_e * sin_a, cos_e) * elevation_step,
                )
            }
        }
    }

    /// Projects a camera-frame point: (continuous pixel coordinates, depth in this map's sense).
    pub fn project(&self, p: DVec3) -> Option<(f64, f64, f64)> {
        match self.projection {
            Projection::Pinhole { fx, fy, cx, cy } => {
                if p.z <= 0.0 {
                    return None;
                }
                Some((fx * p.x / p.z + cx, fy * p.y / p.z + cy, p.z))
            }
            Projection::Spherical => {
                let range = p.length();
                if range <= 0.0 {
                    return None;
                }
                let azimuth = p.y.atan2(p.x).rem_euclid(std::f64::consts::TAU);
                let elevation = (p.z / range).clamp(-1.0, 1.0).asin();
                let i = azimuth / std::f64::consts::TAU * f64::from(self.width);
                let j = (std::f64::consts::FRAC_PI_2 - elevation) / std::f64::consts::PI * f64::from(self.height) - 0.5;
                Some((i, j, range))
            }
        }
    }

    /// Checks that the image size fits the intrinsics: positive focal lengths, and a principal
    /// point within `PRINCIPAL_POINT_REACH` of the image's size from its centre.
    pub fn check_intrinsics(&self) -> Result<(), InputError> {
        if let Projection::Pinhole { fx, fy, cx, cy } = self.projection {
            let (w, h) = (f64::from(self.width), f64::from(self.height));
            if !(fx > 0.0 && fy > 0.0 && fx.is_finite() && fy.is_finite()) {
                return Err(bad(
                    &self.path,
                    format!("focal lengths must be positive (fx {fx}, fy {fy})"),
                ));
            }
            // Real principal points lie within a few per cent of the centre (TUM's Freiburg 1
            // camera, the farthest we know of: 3.2 % of the height); one farther than
            // PRINCIPAL_POINT_REACH means intrinsics of another image size (640x480 ones put it
            // at a 320x240 frame's corner, and a tenth of the height off a 640x400 crop's centre).
            if (cx - w / 2.0).abs() > w * PRINCIPAL_POINT_REACH || (cy - h / 2.0).abs() > h * PRINCIPAL_POINT_REACH {
                return Err(bad(
                    &self.path,
                    format!(
                        "image is {w}x{h} but the principal point ({cx}, {cy}) lies far from its centre: size and intrinsics do not match"
                    ),
                ));
            }
        }
        Ok(())
    }
}
