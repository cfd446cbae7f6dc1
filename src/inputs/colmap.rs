//! COLMAP dense workspaces: `sparse/` cameras and images (binary `.bin` or text `.txt`) and the
//! per-image depth maps `stereo/depth_maps/NAME.geometric.bin` (falling back to
//! `NAME.photometric.bin` when the geometric one is missing).
//!
//! Conventions: COLMAP poses are world-to-camera (`x_cam = R(q) x_world + t`, quaternion w first)
//! with OpenCV axes, and its image coordinates put the centre of pixel (0, 0) at (0.5, 0.5); ours
//! put it at (0, 0), so the principal point moves by half a pixel. Depth maps may be smaller than
//! the camera (COLMAP's `max_image_size`): the intrinsics are scaled to the depth map's size.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use glam::{DMat3, DMat4, DQuat, DVec3};

use super::depth_map::{DepthImage, DepthMapSource, ImageFormat, InputError, Kind, Projection, bad, check_pose};
use super::image_files::FloatLayout;

/// One camera of `cameras.bin` / `cameras.txt`; only undistorted pinhole models are usable.
#[derive(Clone, Debug, PartialEq)]
struct Camera {
    model: String,
    width: u64,
    height: u64,
    params: Vec<f64>,
}

/// One registered image of `images.bin` / `images.txt`.
#[derive(Clone, Debug, PartialEq)]
struct Image {
    image_id: u32,
    camera_id: u32,
    /// World-to-camera rotation (w, x, y, z) and translation.
    qvec: [f64; 4],
    tvec: [f64; 3],
    name: String,
}

/// (model name, parameter count) by COLMAP model id (colmap/src/colmap/sensor/models.h).
const CAMERA_MODELS: [(&str, usize); 11] = [
    ("SIMPLE_PINHOLE", 3),
    ("PINHOLE", 4),
    ("SIMPLE_RADIAL", 4),
    ("RADIAL", 5),
    ("OPENCV", 8),
    ("OPENCV_FISHEYE", 8),
    ("FULL_OPENCV", 12),
    ("FOV", 5),
    ("SIMPLE_RADIAL_FISHEYE", 4),
    ("RADIAL_FISHEYE", 5),
    ("THIN_PRISM_FISHEYE", 12),
];

/// A little-endian cursor that turns every short read into an error naming the file.
struct Cursor<'a> {
    path: &'a Path,
    bytes: &'a [u8],
    pos: usize,
}

impl<'a> Cursor<'a> {
    fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8], InputError> {
        let slice = self
            .pos
            .checked_add(n)
            .and_then(|end| self.bytes.get(self.pos..end))
            .ok_or_else(|| {
                bad(
                    self.path,
                    format!("truncated file: {what} at byte {} is cut off", self.pos),
                )
            })?;
        self.pos += n;
        Ok(slice)
    }

    fn array<const N: usize>(&mut self, what: &str) -> Result<[u8; N], InputError> {
        let mut out = [0u8; N];
        out.copy_from_slice(self.take(N, what)?);
        Ok(out)
    }

    fn u32(&mut self, what: &str) -> Result<u32, InputError> {
        Ok(u32::from_le_bytes(self.array(what)?))
    }

    fn u64(&mut self, what: &str) -> Result<u64, InputError> {
        Ok(u64::from_le_bytes(self.array(what)?))
    }

    fn f64(&mut self, what: &str) -> Result<f64, InputError> {
        Ok(f64::from_le_bytes(self.array(what)?))
    }

    /// A count that must fit in the rest of the file at `min_item_bytes` per item, so a corrupt
    /// count cannot make us allocate or loop for nothing.
    fn count(&mut self, what: &str, min_item_bytes: usize) -> Result<usize, InputError> {
        let n = self.u64(what)?;
        let remaining = self.bytes.len().saturating_sub(self.pos) as u64;
        if n.saturating_mul(min_item_bytes as u64) > remaining {
            return Err(bad(
                self.path,
                format!("{what} says {n} but only {remaining} bytes follow: truncated or corrupt"),
            ));
        }
        Ok(n as usize)
    }
}

fn read_bytes(path: &Path) -> Result<Vec<u8>, InputError> {
    std::fs::read(path).map_err(|source| InputError::Io {
        file: path.to_path_buf(),
        source,
    })
}

fn model_by_name(path: &Path, name: &str) -> Result<usize, InputError> {
    CAMERA_MODELS
        .iter()
        .find(|(model, _)| *model == name)
        .map(|(_, n)| *n)
        .ok_or_else(|| bad(path, format!("unknown camera model '{name}'")))
}

fn cameras_bin(path: &Path) -> Result<BTreeMap<u32, Camera>, InputError> {
    let bytes = read_bytes(path)?;
    let mut cur = Cursor {
        path,
        bytes: &bytes,
        pos: 0,
    };
    let n = cur.count("camera count", 24)?;
    let mut cameras = BTreeMap::new();
    for _ in 0..n {
        let id = cur.u32("camera id")?;
        let model_id = cur.u32("camera model")?;
        let (model, params) = CAMERA_MODELS
            .get(model_id as usize)
            .ok_or_else(|| bad(path, format!("camera {id}: unknown model id {model_id}")))?;
        let width = cur.u64("camera width")?;
        let height = cur.u64("camera height")?;
        let params = (0..*params)
            .map(|_| cur.f64("camera parameter"))
            .collect::<Result<_, _>>()?;
        cameras.insert(
            id,
            Camera {
                model: (*model).to_string(),
                width,
                height,
                params,
            },
        );
    }
    Ok(cameras)
}

fn images_bin(path: &Path) -> Result<Vec<Image>, InputError> {
    let bytes = read_bytes(path)?;
    let mut cur = Cursor {
        path,
        bytes: &bytes,
        pos: 0,
    };
    let n = cur.count("image count", 64)?;
    let mut images = Vec::with_capacity(n);
    for _ in 0..n {
        let image_id = cur.u32("image id")?;
        let mut qvec = [0.0; 4];
        for q in &mut qvec {
            *q = cur.f64("image rotation")?;
        }
        let mut tvec = [0.0; 3];
        for t in &mut tvec {
            *t = cur.f64("image translation")?;
        }
        let camera_id = cur.u32("image camera id")?;
        let mut name = Vec::new();
        loop {
            match cur.array::<1>("image name")? {
                [0] => break,
                [b] => name.push(b),
            }
        }
        let points = cur.count("image point count", 24)?;
        cur.take(points * 24, "image points")?;
        images.push(Image {
            image_id,
            camera_id,
            qvec,
            tvec,
            name: String::from_utf8(name).map_err(|_| bad(path, format!("image {image_id}: name is not UTF-8")))?,
        });
    }
    Ok(images)
}

fn read_text(path: &Path) -> Result<String, InputError> {
    std::fs::read_to_string(path).map_err(|source| InputError::Io {
        file: path.to_path_buf(),
        source,
    })
}

fn parse<T: std::str::FromStr>(path: &Path, line: usize, token: Option<&str>, what: &str) -> Result<T, InputError> {
    let token = token.ok_or_else(|| bad(path, format!("line {line}: missing {what}")))?;
    token
        .parse()
        .map_err(|_| bad(path, format!("line {line}: {what} '{token}' is not valid")))
}

fn cameras_txt(path: &Path) -> Result<BTreeMap<u32, Camera>, InputError> {
    let mut cameras = BTreeMap::new();
    for (index, line) in read_text(path)?.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let number = index + 1;
        let mut tokens = line.split_whitespace();
        let id = parse(path, number, tokens.next(), "camera id")?;
        let model: String = parse(path, number, tokens.next(), "camera model")?;
        let width = parse(path, number, tokens.next(), "width")?;
        let height = parse(path, number, tokens.next(), "height")?;
        let params: Vec<f64> = tokens
            .map(|t| parse(path, number, Some(t), "camera parameter"))
            .collect::<Result<_, _>>()?;
        let expected = model_by_name(path, &model)?;
        if params.len() != expected {
            return Err(bad(
                path,
                format!(
                    "line {number}: {model} has {expected} parameters, found {}",
                    params.len()
                ),
            ));
        }
        cameras.insert(
            id,
            Camera {
                model,
                width,
                height,
                params,
            },
        );
    }
    Ok(cameras)
}

fn images_txt(path: &Path) -> Result<Vec<Image>, InputError> {
    let text = read_text(path)?;
    let mut lines = text.lines().enumerate();
    let mut images = Vec::new();
    while let Some((index, line)) = lines.next() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let number = index + 1;
        let mut tokens = line.split_whitespace();
        let image_id = parse(path, number, tokens.next(), "image id")?;
        let mut qvec = [0.0; 4];
        for q in &mut qvec {
            *q = parse(path, number, tokens.next(), "rotation")?;
        }
        let mut tvec = [0.0; 3];
        for t in &mut tvec {
            *t = parse(path, number, tokens.next(), "translation")?;
        }
        let camera_id = parse(path, number, tokens.next(), "camera id")?;
        // The name is the rest of the line: COLMAP allows no spaces, but be lenient.
        let name = tokens.collect::<Vec<_>>().join(" ");
        if name.is_empty() {
            return Err(bad(path, format!("line {number}: missing image name")));
        }
        // Every image line is followed by its 2-D points line, which may be empty.
        lines.next();
        images.push(Image {
            image_id,
            camera_id,
            qvec,
            tvec,
            name,
        });
    }
    Ok(images)
}

/// Reads `sparse/cameras.*` and `sparse/images.*`, preferring the binary files.
fn read_model(sparse: &Path) -> Result<(BTreeMap<u32, Camera>, Vec<Image>), InputError> {
    let (bin_cameras, bin_images) = (sparse.join("cameras.bin"), sparse.join("images.bin"));
    if bin_cameras.is_file() && bin_images.is_file() {
        return Ok((cameras_bin(&bin_cameras)?, images_bin(&bin_images)?));
    }
    let (txt_cameras, txt_images) = (sparse.join("cameras.txt"), sparse.join("images.txt"));
    if txt_cameras.is_file() && txt_images.is_file() {
        return Ok((cameras_txt(&txt_cameras)?, images_txt(&txt_images)?));
    }
    Err(bad(
        sparse,
        "no COLMAP model: expected cameras.bin and images.bin, or cameras.txt and images.txt",
    ))
}

/// Reads only the `width&height&channels&` header of a COLMAP array file: (width, height,
/// channels, offset of the first value).
fn depth_header(path: &Path, bytes: &[u8]) -> Result<(u32, u32, u32, usize), InputError> {
    let mut fields = [0u64; 3];
    let mut pos = 0usize;
    for field in &mut fields {
        let start = pos;
        while bytes.get(pos).is_some_and(u8::is_ascii_digit) && pos - start < 12 {
            pos += 1;
        }
        if start == pos || bytes.get(pos) != Some(&b'&') {
            return Err(bad(
                path,
                "not a COLMAP depth map: expected a 'width&height&channels&' header",
            ));
        }
        let digits = std::str::from_utf8(bytes.get(start..pos).unwrap_or_default()).unwrap_or_default();
        *field = digits.parse().unwrap_or(0);
        pos += 1;
    }
    let [width, height, channels] = fields;
    if width == 0 || height == 0 || width > 1 << 20 || height > 1 << 20 {
        return Err(bad(
            path,
            format!("COLMAP depth map size {width}x{height} is not plausible"),
        ));
    }
    if channels != 1 {
        return Err(bad(
            path,
            format!("a depth map has 1 channel, this file has {channels}"),
        ));
    }
    Ok((width as u32, height as u32, channels as u32, pos))
}

/// Where a COLMAP depth map's floats lie: little-endian, row-major after the text header.
pub fn colmap_depth_layout(path: &Path) -> Result<FloatLayout, InputError> {
    use std::io::Read;
    let mut head = Vec::with_capacity(64);
    std::fs::File::open(path)
        .and_then(|f| f.take(64).read_to_end(&mut head))
        .map_err(|source| InputError::Io {
            file: path.to_path_buf(),
            source,
        })?;
    let (width, height, _, start) = depth_header(path, &head)?;
    FloatLayout {
        width,
        height,
        data_start: start as u64,
        little_endian: true,
        bottom_up: false,
    }
    .check_length(path, "COLMAP depth map")
}

/// Writes a COLMAP depth map (tests and tools produce inputs with it).
pub fn write_colmap_depth(path: &Path, image: &DepthImage) -> std::io::Result<()> {
    let mut out = format!("{}&{}&1&", image.width, image.height).into_bytes();
    for v in &image.depth {
        out.extend_from_slice(&v.to_le_bytes());
    }
    std::fs::write(path, out)
}

/// Pinhole intrinsics in COLMAP's pixel convention: (fx, fy, cx, cy).
fn pinhole(sparse: &Path, camera_id: u32, camera: &Camera) -> Result<(f64, f64, f64, f64), InputError> {
    match (camera.model.as_str(), camera.params.as_slice()) {
        ("SIMPLE_PINHOLE", [f, cx, cy]) => Ok((*f, *f, *cx, *cy)),
        ("PINHOLE", [fx, fy, cx, cy]) => Ok((*fx, *fy, *cx, *cy)),
        (model, _) => Err(bad(
            sparse,
            format!(
                "camera {camera_id} uses the distorted model {model}; run COLMAP's image_undistorter and pass the dense workspace it writes"
            ),
        )),
    }
}

/// All depth maps of a COLMAP dense workspace, by image name order.
pub fn workspace(dir: &Path) -> Result<Vec<DepthMapSource>, InputError> {
    let sparse = dir.join("sparse");
    let (cameras, mut images) = read_model(&sparse)?;
    images.sort_by(|a, b| a.name.cmp(&b.name));
    let depth_dir = dir.join("stereo").join("depth_maps");
    let mut sources = Vec::new();
    let mut missing: Vec<String> = Vec::new();
    for image in &images {
        let depth_path = ["geometric", "photometric"]
            .iter()
            .map(|kind| depth_dir.join(format!("{}.{kind}.bin", image.name)))
            .find(|p| p.is_file());
        let Some(depth_path) = depth_path else {
            missing.push(image.name.clone());
            continue;
        };
        let camera = cameras.get(&image.camera_id).ok_or_else(|| {
            bad(
                &sparse,
                format!(
                    "image {} ({}) names camera {} which does not exist",
                    image.image_id, image.name, image.camera_id
                ),
            )
        })?;
        let (fx, fy, cx, cy) = pinhole(&sparse, image.camera_id, camera)?;
        let FloatLayout { width, height, .. } = colmap_depth_layout(&depth_path)?;
        if camera.width == 0 || camera.height == 0 {
            return Err(bad(&sparse, format!("camera {} has zero size", image.camera_id)));
        }
        let (sx, sy) = (
            f64::from(width) / camera.width as f64,
            f64::from(height) / camera.height as f64,
        );
        if (sx / sy - 1.0).abs() > 0.02 {
            return Err(bad(
                &depth_path,
                format!(
                    "depth map is {width}x{height} but camera {} is {}x{}: the aspect ratios differ",
                    image.camera_id, camera.width, camera.height
                ),
            ));
        }
        let [qw, qx, qy, qz] = image.qvec;
        let norm = (qw * qw + qx * qx + qy * qy + qz * qz).sqrt();
        if !(norm.is_finite() && (norm - 1.0).abs() < 1e-3) {
            return Err(bad(
                &sparse,
                format!("image {}: rotation quaternion has norm {norm}, expected 1", image.name),
            ));
        }
        let rotation = DMat3::from_quat(DQuat::from_xyzw(qx / norm, qy / norm, qz / norm, qw / norm));
        let world_to_camera = DMat4::from_mat3_translation(rotation, DVec3::from_array(image.tvec));
        check_pose(&sparse, &world_to_camera)?;
        let camera_to_world = world_to_camera.inverse();
        let source = DepthMapSource {
            path: std::path::absolute(&depth_path).unwrap_or(depth_path.clone()),
            format: ImageFormat::ColmapBin,
            width,
            height,
            projection: Projection::Pinhole {
                fx: fx * sx,
                fy: fy * sy,
                cx: cx * sx - 0.5,
                cy: cy * sy - 0.5,
            },
            camera_to_world: camera_to_world.to_cols_array(),
            kind: Kind::Photo,
            weight: Kind::Photo.default_weight(),
            noise: Kind::Photo.default_noise(),
        };
        source.check_intrinsics()?;
        sources.push(source);
    }
    if !missing.is_empty() {
        tracing::warn!(
            "{}: {} registered images have no depth map in {} (first: {}); they are not ingested",
            dir.display(),
            missing.len(),
            depth_dir.display(),
            missing.first().map(String::as_str).unwrap_or_default()
        );
    }
    if sources.is_empty() {
        return Err(bad(
            &depth_dir,
            format!(
                "none of the {} registered images has a *.geometric.bin or *.photometric.bin depth map",
                images.len()
            ),
        ));
    }
    Ok(sources)
}

/// Paths of a dense workspace, for tests and tools that write one.
pub struct WorkspaceWriter {
    /// The workspace folder (with `sparse/` and `stereo/`).
    pub root: PathBuf,
}

impl WorkspaceWriter {
    /// Writes `sparse/cameras.{bin,txt}` and `sparse/images.{bin,txt}` (binary when `binary`)
    /// for PINHOLE cameras in COLMAP's conventions, one camera per image.
    /// Each view: (name, width, height, fx, fy, cx, cy in COLMAP pixels, camera-to-world).
    pub fn write_model(&self, views: &[(String, u32, u32, [f64; 4], DMat4)], binary: bool) -> std::io::Result<()> {
        let sparse = self.root.join("sparse");
        std::fs::create_dir_all(&sparse)?;
        std::fs::create_dir_all(self.root.join("stereo").join("depth_maps"))?;
        let poses: Vec<(DQuat, DVec3)> = views
            .iter()
            .map(|(.., c2w)| {
                let (_, rotation, translation) = c2w.inverse().to_scale_rotation_translation();
                (rotation, translation)
            })
            .collect();
        if binary {
            let mut cameras = (views.len() as u64).to_le_bytes().to_vec();
            let mut images = (views.len() as u64).to_le_bytes().to_vec();
            for (index, ((name, w, h, k, _), (q, t))) in views.iter().zip(&poses).enumerate() {
                let id = index as u32 + 1;
                cameras.extend(id.to_le_bytes());
                cameras.extend(1u32.to_le_bytes());
                cameras.extend(u64::from(*w).to_le_bytes());
                cameras.extend(u64::from(*h).to_le_bytes());
                k.iter().for_each(|v| cameras.extend(v.to_le_bytes()));
                images.extend(id.to_le_bytes());
                [q.w, q.x, q.y, q.z].iter().for_each(|v| images.extend(v.to_le_bytes()));
                [t.x, t.y, t.z].iter().for_each(|v| images.extend(v.to_le_bytes()));
                images.extend(id.to_le_bytes());
                images.extend(name.as_bytes());
                images.push(0);
                images.extend(0u64.to_le_bytes());
            }
            std::fs::write(sparse.join("cameras.bin"), cameras)?;
            std::fs::write(sparse.join("images.bin"), images)?;
        } else {
            let mut cameras = String::from("# Camera list with one line of data per camera:\n");
            let mut images = String::from("# Image list with two lines of data per image:\n");
            for (index, ((name, w, h, k, _), (q, t))) in views.iter().zip(&poses).enumerate() {
                let id = index + 1;
                cameras.push_str(&format!("{id} PINHOLE {w} {h} {} {} {} {}\n", k[0], k[1], k[2], k[3]));
                images.push_str(&format!(
                    "{id} {} {} {} {} {} {} {} {id} {name}\n\n",
                    q.w, q.x, q.y, q.z, t.x, t.y, t.z
                ));
            }
            std::fs::write(sparse.join("cameras.txt"), cameras)?;
            std::fs::write(sparse.join("images.txt"), images)?;
        }
        Ok(())
    }

    /// The depth map file of image `name` (`kind`: geometric or photometric).
    pub fn depth_path(&self, name: &str, kind: &str) -> PathBuf {
        self.root
            .join("stereo")
            .join("depth_maps")
            .join(format!("{name}.{kind}.bin"))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn header_is_parsed_and_bad_headers_are_rejected() {
        let p = Path::new("d.bin");
        assert_eq!(depth_header(p, b"640&480&1&xxxx").unwrap(), (640, 480, 1, 10));
        assert!(depth_header(p, b"640&480&3&").is_err());
        assert!(depth_header(p, b"640x480&1&").is_err());
        assert!(depth_header(p, b"").is_err());
        assert!(depth_header(p, b"99999999999999&1&1&").is_err());
    }

    #[test]
    fn corrupt_counts_are_errors_not_allocations() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("images.bin");
        std::fs::write(&path, u64::MAX.to_le_bytes()).unwrap();
        let err = images_bin(&path).unwrap_err().to_string();
        assert!(err.contains("image count"), "{err}");
        let path = dir.path().join("cameras.bin");
        let mut bytes = 1u64.to_le_bytes().to_vec();
        bytes.extend(1u32.to_le_bytes());
        bytes.extend(99u32.to_le_bytes());
        bytes.extend([0u8; 16]);
        std::fs::write(&path, bytes).unwrap();
        let err = cameras_bin(&path).unwrap_err().to_string();
        assert!(err.contains("unknown model id 99"), "{err}");
    }
}
