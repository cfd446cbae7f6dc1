//! Depth maps: camera models, poses, and the image formats they are read from.
//!
//! Conventions (README, "Inputs"): poses are camera-to-world with OpenCV camera axes (x right,
//! y down, z forward); pinhole depth is the z coordinate in the camera frame, pixel (i, j) has
//! its centre at image coordinates (i, j); spherical (LIDAR) depth is the range along the ray.

use std::path::{Path, PathBuf};

use glam::{DMat3, DMat4, DVec3};
use serde::{Deserialize, Serialize};

/// Errors of reading inputs: each names the file and the problem.
#[derive(Debug, thiserror::Error)]
pub enum InputError {
    #[error("{file}: {problem}")]
    Bad { file: PathBuf, problem: String },
    #[error("{file}: {source}")]
    Io { file: PathBuf, source: std::io::Error },
}

pub fn bad(file: &Path, problem: impl Into<String>) -> InputError {
    InputError::Bad {
        file: file.to_path_buf(),
        problem: problem.into(),
    }
}

#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq)]
pub enum Projection {
    Pinhole {
        fx: f64,
        fy: f64,
        cx: f64,
        cy: f64,
    },
    /// Equirectangular 360-degree scan: column i is azimuth 2 pi i / width (counter-clockwise
    /// about +z from +x), row j is elevation pi/2 - pi (j + 0.5) / height. Axes of the sensor
    /// frame: z up.
    Spherical,
}

#[derive(Serialize, Deserialize, Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    Photo,
    Rgbd,
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
}

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub enum ImageFormat {
    /// 16-bit grey PNG; depth = value * scale; 0 and 65535 are invalid.
    Png16 { scale: f64 },
    /// Portable float map (grey "Pf"), rows bottom to top as the format says.
    Pfm,
    /// NumPy .npy, 2-D little-endian float32 (`<f4`), C order.
    NpyF32,
    /// COLMAP depth map (`stereo/depth_maps/*.bin`): `width&height&1&` then float32 rows.
    ColmapBin,
    /// Scan number `scan` (from 0) of a PTX file, resampled into the spherical grid.
    Ptx { scan: u32 },
    /// Point cloud number `scan` (from 0) of an E57 file, resampled into the spherical grid.
    E57 { scan: u32 },
}

/// Everything needed to read a depth map again later (the store keeps references, not pixels).
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct DepthMapSource {
    pub path: PathBuf,
    pub format: ImageFormat,
    pub width: u32,
    pub height: u32,
    pub projection: Projection,
    /// Camera-to-world, column-major 4x4.
    pub camera_to_world: [f64; 16],
    pub kind: Kind,
    pub weight: f32,
}

/// Depth values, row-major; NaN marks an invalid pixel.
pub struct DepthImage {
    pub width: u32,
    pub height: u32,
    pub depth: Vec<f32>,
}

impl DepthImage {
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

/// Checks a camera-to-world matrix: finite, affine, with an invertible, near-orthonormal
/// rotation part (scale is not allowed: depth is metric).
pub fn check_pose(file: &Path, m: &DMat4) -> Result<(), InputError> {
    if !m.to_cols_array().iter().all(|v| v.is_finite()) {
        return Err(bad(file, "pose has non-finite entries"));
    }
    let row3 = m.row(3);
    if (row3 - glam::DVec4::new(0.0, 0.0, 0.0, 1.0)).abs().max_element() > 1e-6 {
        return Err(bad(file, format!("pose's last row is {row3:?}, expected 0 0 0 1")));
    }
    let r = DMat3::from_mat4(*m);
    let det = r.determinant();
    if det.abs() < 1e-6 {
        return Err(bad(
            file,
            format!("pose is not invertible (rotation determinant {det:.3e})"),
        ));
    }
    let err = (r.transpose() * r - DMat3::IDENTITY)
        .to_cols_array()
        .iter()
        .fold(0f64, |a, b| a.max(b.abs()));
    if err > 1e-3 {
        return Err(bad(
            file,
            format!("pose's rotation is not orthonormal (error {err:.3e})"),
        ));
    }
    Ok(())
}

impl DepthMapSource {
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

    /// Checks that the image size fits the intrinsics.
    pub fn check_intrinsics(&self) -> Result<(), InputError> {
        if let Projection::Pinhole { fx, fy, cx, cy } = self.projection {
            let (w, h) = (f64::from(self.width), f64::from(self.height));
            if !(fx > 0.0 && fy > 0.0 && fx.is_finite() && fy.is_finite()) {
                return Err(bad(
                    &self.path,
                    format!("focal lengths must be positive (fx {fx}, fy {fy})"),
                ));
            }
            if !(0.0..=w).contains(&cx) || !(0.0..=h).contains(&cy) {
                return Err(bad(
                    &self.path,
                    format!(
                        "image is {w}x{h} but the principal point ({cx}, {cy}) lies outside it: size and intrinsics do not match"
                    ),
                ));
            }
        }
        Ok(())
    }

    pub fn load(&self) -> Result<DepthImage, InputError> {
        let image = match &self.format {
            ImageFormat::Png16 { scale } => read_png16(&self.path, *scale)?,
            ImageFormat::Pfm => read_pfm(&self.path)?,
            ImageFormat::NpyF32 => read_npy(&self.path)?,
            ImageFormat::ColmapBin => super::colmap::read_colmap_depth(&self.path)?,
            ImageFormat::Ptx { .. } | ImageFormat::E57 { .. } => super::lidar::read_scan(self)?,
        };
        if image.width != self.width || image.height != self.height {
            return Err(bad(
                &self.path,
                format!(
                    "image is {}x{}, the registered size is {}x{}",
                    image.width, image.height, self.width, self.height
                ),
            ));
        }
        Ok(image)
    }
}

fn read_file(path: &Path) -> Result<Vec<u8>, InputError> {
    std::fs::read(path).map_err(|source| InputError::Io {
        file: path.to_path_buf(),
        source,
    })
}

/// Size of a depth image from its header alone (cheap validation before any work).
pub fn image_size(path: &Path, format: &ImageFormat) -> Result<(u32, u32), InputError> {
    match format {
        ImageFormat::Png16 { .. } => {
            image::image_dimensions(path).map_err(|e| bad(path, format!("unreadable PNG: {e}")))
        }
        ImageFormat::Pfm | ImageFormat::NpyF32 => {
            let image = match format {
                ImageFormat::Pfm => read_pfm(path)?,
                _ => read_npy(path)?,
            };
            Ok((image.width, image.height))
        }
        ImageFormat::ColmapBin => super::colmap::colmap_depth_size(path),
        ImageFormat::Ptx { .. } | ImageFormat::E57 { .. } => Err(bad(
            path,
            "the size of a LIDAR scan's grid is decided when it is discovered, not read from a header",
        )),
    }
}

pub fn read_png16(path: &Path, scale: f64) -> Result<DepthImage, InputError> {
    let bytes = read_file(path)?;
    let decoded = image::load_from_memory_with_format(&bytes, image::ImageFormat::Png)
        .map_err(|e| bad(path, format!("unreadable or truncated PNG: {e}")))?;
    let image::DynamicImage::ImageLuma16(grey) = decoded else {
        return Err(bad(
            path,
            format!("expected a 16-bit grey PNG, found {:?}", decoded.color()),
        ));
    };
    let (width, height) = grey.dimensions();
    let depth = grey
        .into_raw()
        .into_iter()
        .map(|v| {
            if v == 0 || v == u16::MAX {
                f32::NAN
            } else {
                (f64::from(v) * scale) as f32
            }
        })
        .collect();
    Ok(DepthImage { width, height, depth })
}

pub fn read_pfm(path: &Path) -> Result<DepthImage, InputError> {
    let bytes = read_file(path)?;
    // Header: "Pf\n<w> <h>\n<scale>\n" (whitespace-separated tokens), then float32 rows from the
    // bottom row up; negative scale means little-endian.
    let mut tokens = Vec::new();
    let mut pos = 0usize;
    while tokens.len() < 4 {
        while bytes.get(pos).is_some_and(|b| b.is_ascii_whitespace()) {
            pos += 1;
        }
        let start = pos;
        while bytes.get(pos).is_some_and(|b| !b.is_ascii_whitespace()) {
            pos += 1;
        }
        if start == pos {
            return Err(bad(path, "truncated PFM header"));
        }
        tokens.push(String::from_utf8_lossy(bytes.get(start..pos).unwrap_or_default()).into_owned());
    }
    pos += 1; // the single whitespace byte after the scale
    if tokens[0] != "Pf" {
        return Err(bad(
            path,
            format!("not a grey PFM (magic '{}', expected 'Pf')", tokens[0]),
        ));
    }
    let parse = |t: &str, what: &str| t.parse::<f64>().map_err(|_| bad(path, format!("bad PFM {what} '{t}'")));
    let (w, h, scale) = (
        parse(&tokens[1], "width")?,
        parse(&tokens[2], "height")?,
        parse(&tokens[3], "scale")?,
    );
    if w < 1.0 || h < 1.0 || w > 1e6 || h > 1e6 {
        return Err(bad(path, format!("PFM size {w}x{h} is not plausible")));
    }
    let (width, height) = (w as u32, h as u32);
    let count = width as usize * height as usize;
    let data = bytes
        .get(pos..pos + count * 4)
        .ok_or_else(|| bad(path, format!("truncated PFM: {count} floats expected")))?;
    let little = scale < 0.0;
    let mut depth = vec![f32::NAN; count];
    for (index, chunk) in data.chunks_exact(4).enumerate() {
        let raw = [chunk[0], chunk[1], chunk[2], chunk[3]];
        let v = if little {
            f32::from_le_bytes(raw)
        } else {
            f32::from_be_bytes(raw)
        };
        let (row_from_bottom, col) = (index / width as usize, index % width as usize);
        let row = height as usize - 1 - row_from_bottom;
        depth[row * width as usize + col] = if v.is_finite() && v > 0.0 { v } else { f32::NAN };
    }
    Ok(DepthImage { width, height, depth })
}

pub fn read_npy(path: &Path) -> Result<DepthImage, InputError> {
    let bytes = read_file(path)?;
    if bytes.get(..6) != Some(b"\x93NUMPY".as_slice()) {
        return Err(bad(path, "not a .npy file (bad magic)"));
    }
    let major = bytes.get(6).copied().unwrap_or(0);
    let (header_len, header_start) = match major {
        1 => (
            u16::from_le_bytes([bytes.get(8).copied().unwrap_or(0), bytes.get(9).copied().unwrap_or(0)]) as usize,
            10,
        ),
        2 | 3 => {
            let b = bytes.get(8..12).ok_or_else(|| bad(path, "truncated .npy header"))?;
            (u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize, 12)
        }
        v => return Err(bad(path, format!("unsupported .npy version {v}"))),
    };
    let header = bytes
        .get(header_start..header_start + header_len)
        .map(|h| String::from_utf8_lossy(h).into_owned())
        .ok_or_else(|| bad(path, "truncated .npy header"))?;
    if !header.contains("'descr': '<f4'") {
        return Err(bad(
            path,
            format!("expected little-endian float32 ('<f4'), header: {}", header.trim()),
        ));
    }
    if header.contains("'fortran_order': True") {
        return Err(bad(path, "Fortran-order arrays are not supported; save with C order"));
    }
    let shape = header
        .split("'shape':")
        .nth(1)
        .and_then(|s| s.split(')').next())
        .map(|s| s.trim().trim_start_matches('(').to_string())
        .ok_or_else(|| bad(path, "no shape in .npy header"))?;
    let dims: Vec<u32> = shape
        .split(',')
        .filter(|t| !t.trim().is_empty())
        .map(|t| {
            t.trim()
                .parse()
                .map_err(|_| bad(path, format!("bad .npy shape '{shape}'")))
        })
        .collect::<Result<_, _>>()?;
    let [height, width] = dims[..] else {
        return Err(bad(path, format!("expected a 2-D array, shape is ({shape})")));
    };
    let count = width as usize * height as usize;
    let start = header_start + header_len;
    let data = bytes
        .get(start..start + count * 4)
        .ok_or_else(|| bad(path, format!("truncated .npy: {count} floats expected")))?;
    Ok(DepthImage {
        width,
        height,
        depth: depths_from_f32_le(data),
    })
}

/// Little-endian float32 depths; values that are not finite and positive become NaN (invalid).
pub(crate) fn depths_from_f32_le(data: &[u8]) -> Vec<f32> {
    data.chunks_exact(4)
        .map(|c| {
            let v = f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
            if v.is_finite() && v > 0.0 { v } else { f32::NAN }
        })
        .collect()
}

/// Writes a little-endian grey PFM (tools and tests use it to produce inputs).
pub fn write_pfm(path: &Path, image: &DepthImage) -> std::io::Result<()> {
    let mut out = format!("Pf\n{} {}\n-1.0\n", image.width, image.height).into_bytes();
    for row in (0..image.height).rev() {
        for col in 0..image.width {
            out.extend_from_slice(&image.get(col, row).to_le_bytes());
        }
    }
    std::fs::write(path, out)
}
