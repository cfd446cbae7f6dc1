//! Finding depth maps in user paths: the 7-Scenes / RGB-D folder layout, single 7-Scenes frames,
//! and the generic JSON scene manifest (docs/inputs.md).

use std::path::{Path, PathBuf};

use glam::{DMat4, DVec4};
use serde::Deserialize;

use super::colmap;
use super::depth_map::{
    DEFAULT_NOISE_SIGMAS, DepthMapSource, DepthNoise, ImageFormat, InputError, Kind, Projection, bad,
    check_depth_scale, check_noise_sigmas, check_pose, check_regular_file,
};
use super::image_files::{npy_layout, pfm_layout};
use super::lidar;
use super::tum;

/// How to interpret an input path.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum InputFormat {
    /// Decide from the path; an unrecognised path is an error, never a guess.
    Auto,
    /// A folder with camera-intrinsics.txt, frame-XXXXXX.depth.png and frame-XXXXXX.pose.txt,
    /// or single frame-XXXXXX.depth.png files of such a folder.
    SevenScenes,
    /// A TUM RGB-D benchmark sequence: depth.txt, groundtruth.txt and depth/*.png.
    Tum,
    /// A JSON scene manifest.
    Manifest,
    /// A COLMAP dense workspace.
    Colmap,
    /// Terrestrial LIDAR scans (E57 or PTX).
    Lidar,
}

/// How inputs are discovered.
#[derive(Clone, Debug)]
pub struct DiscoverOptions {
    /// The input format, or `auto` to decide by path.
    pub format: InputFormat,
    /// Take every n-th frame of a folder.
    pub stride: usize,
    /// Take at most this many frames of a folder.
    pub limit: Option<usize>,
    /// Intrinsics of 7-Scenes / RGB-D frames (a 3x3 matrix, or fx fy cx cy), for folders and
    /// frames without a camera-intrinsics.txt beside them; replaces theirs where they have one.
    pub intrinsics: Option<PathBuf>,
    /// A depth noise model for every depth map found, in place of its kind's (or its
    /// manifest entry's).
    pub depth_noise: Option<DepthNoise>,
    /// Standard deviations of noise a sample's radius spans at least, for every depth map
    /// found, in place of [`DEFAULT_NOISE_SIGMAS`] (or its manifest entry's).
    pub noise_sigmas: Option<f64>,
}

impl Default for DiscoverOptions {
    fn default() -> Self {
        DiscoverOptions {
            format: InputFormat::Auto,
            stride: 1,
            limit: None,
            intrinsics: None,
            depth_noise: None,
            noise_sigmas: None,
        }
    }
}

/// Whether `dir` holds depth frames named like 7-Scenes' (`*.depth.png`).
fn has_depth_frames(dir: &Path) -> bool {
    std::fs::read_dir(dir).is_ok_and(|entries| {
        entries
            .filter_map(|e| e.ok())
            .any(|e| e.file_name().to_string_lossy().ends_with(".depth.png"))
    })
}

fn detect(path: &Path, intrinsics_given: bool) -> Result<InputFormat, InputError> {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().to_lowercase())
        .unwrap_or_default();
    if path.is_dir() {
        // TUM first: its lists name the frames, whatever other files lie beside them.
        if tum::is_tum_folder(path) {
            return Ok(InputFormat::Tum);
        }
        if path.join("camera-intrinsics.txt").is_file() {
            return Ok(InputFormat::SevenScenes);
        }
        if path.join("sparse").is_dir() && path.join("stereo").is_dir() {
            return Ok(InputFormat::Colmap);
        }
        if has_depth_frames(path) {
            if intrinsics_given {
                return Ok(InputFormat::SevenScenes);
            }
            return Err(bad(
                path,
                "RGB-D frames (*.depth.png) without camera-intrinsics.txt beside them: name the intrinsics file with --intrinsics FILE",
            ));
        }
        return Err(InputError::UnknownFormat {
            file: path.to_path_buf(),
            expected: "a folder needs camera-intrinsics.txt (7-Scenes/RGB-D), depth.txt and groundtruth.txt (TUM RGB-D) or sparse/ and stereo/ (COLMAP)",
        });
    }
    if !path.exists() {
        return Err(InputError::NotFound {
            file: path.to_path_buf(),
        });
    }
    if name.ends_with(".depth.png") {
        return Ok(InputFormat::SevenScenes);
    }
    if name.ends_with(".json") {
        return Ok(InputFormat::Manifest);
    }
    if name.ends_with(".e57") || name.ends_with(".ptx") {
        return Ok(InputFormat::Lidar);
    }
    Err(InputError::UnknownFormat {
        file: path.to_path_buf(),
        expected: "expected a 7-Scenes folder or frame-*.depth.png, a .json manifest, a COLMAP workspace, .e57 or .ptx",
    })
}

/// All depth maps named by `paths`, validated cheaply (headers, poses, intrinsics).
pub fn discover(paths: &[PathBuf], options: &DiscoverOptions) -> Result<Vec<DepthMapSource>, InputError> {
    let mut sources = Vec::new();
    for path in paths {
        let format = match options.format {
            InputFormat::Auto => detect(path, options.intrinsics.is_some())?,
            other => other,
        };
        match format {
            InputFormat::SevenScenes if path.is_dir() => sources.extend(seven_scenes_folder(path, options)?),
            InputFormat::SevenScenes => sources.push(seven_scenes_frame(path, options)?),
            InputFormat::Tum => sources.extend(tum_folder(path, options)?),
            InputFormat::Manifest => sources.extend(manifest(path)?),
            InputFormat::Colmap => sources.extend(colmap::workspace(path)?),
            InputFormat::Lidar => sources.extend(lidar_file(path)?),
            InputFormat::Auto => unreachable!("detect never returns Auto"),
        }
    }
    if sources.is_empty() {
        return Err(InputError::Bad {
            file: paths.first().cloned().unwrap_or_default(),
            problem: "no depth maps found".into(),
        });
    }
    for source in &mut sources {
        if let Some(noise) = options.depth_noise {
            source.noise = noise;
        }
        if let Some(sigmas) = options.noise_sigmas {
            source.noise = source.noise.with_sigmas(sigmas);
        }
    }
    Ok(sources)
}

fn lidar_file(path: &Path) -> Result<Vec<DepthMapSource>, InputError> {
    let extension = path
        .extension()
        .map(|e| e.to_string_lossy().to_lowercase())
        .unwrap_or_default();
    match extension.as_str() {
        "ptx" => lidar::ptx_scans(path),
        "e57" => lidar::e57_scans(path),
        _ => Err(bad(path, "a LIDAR input is a .ptx or .e57 file")),
    }
}

fn read_text(path: &Path) -> Result<String, InputError> {
    check_regular_file(path)?;
    std::fs::read_to_string(path).map_err(|source| InputError::Io {
        file: path.to_path_buf(),
        source,
    })
}

/// Parses whitespace-separated numbers, exactly `n` of them.
fn numbers(path: &Path, text: &str, n: usize, what: &str) -> Result<Vec<f64>, InputError> {
    let values: Vec<f64> = text
        .split_whitespace()
        .map(|t| {
            t.parse::<f64>()
                .map_err(|_| bad(path, format!("{what}: '{t}' is not a number")))
        })
        .collect::<Result<_, _>>()?;
    if values.len() != n {
        return Err(bad(
            path,
            format!("{what}: expected {n} numbers, found {}", values.len()),
        ));
    }
    Ok(values)
}

fn row_major_4x4(values: &[f64]) -> DMat4 {
    let row = |r: usize| DVec4::new(values[4 * r], values[4 * r + 1], values[4 * r + 2], values[4 * r + 3]);
    DMat4::from_cols(row(0), row(1), row(2), row(3)).transpose()
}

/// The intrinsics of the frames in `dir`: `--intrinsics` if given (a 3x3 matrix, or fx fy cx
/// cy), else the folder's camera-intrinsics.txt (a 3x3 matrix).
fn seven_scenes_intrinsics(dir: &Path, options: &DiscoverOptions) -> Result<Projection, InputError> {
    let Some(path) = &options.intrinsics else {
        let path = dir.join("camera-intrinsics.txt");
        if !path.is_file() {
            return Err(bad(
                &path,
                "no such file: RGB-D frames need camera-intrinsics.txt beside them or --intrinsics FILE",
            ));
        }
        let k = numbers(&path, &read_text(&path)?, 9, "3x3 intrinsics matrix")?;
        return with_positive_focal_lengths(&path, pinhole_of_matrix(&path, &k)?);
    };
    intrinsics_file(path)
}

/// A TUM RGB-D sequence's frames, with `--intrinsics` or the published intrinsics of the
/// Freiburg sensor its folder is named after.
fn tum_folder(dir: &Path, options: &DiscoverOptions) -> Result<Vec<DepthMapSource>, InputError> {
    if !tum::is_tum_folder(dir) {
        return Err(bad(dir, "a TUM RGB-D folder needs depth.txt and groundtruth.txt"));
    }
    let projection = match &options.intrinsics {
        Some(file) => intrinsics_file(file)?,
        None => tum::freiburg_intrinsics(dir).ok_or_else(|| {
            bad(
                dir,
                "a TUM RGB-D folder not named after its sensor (freiburg1, 2 or 3) needs --intrinsics FILE",
            )
        })?,
    };
    let (sources, without_pose) = tum::tum_frames(dir, projection, options.stride, options.limit)?;
    if without_pose > 0 {
        tracing::warn!(
            "{}: {without_pose} depth frame(s) have no ground-truth pose within {} s and are left out",
            dir.display(),
            tum::MAX_TIME_DIFFERENCE
        );
    }
    if sources.is_empty() {
        return Err(bad(dir, "no depth frame has a ground-truth pose"));
    }
    Ok(sources)
}

/// Intrinsics from a file: a 3x3 matrix (9 numbers) or fx fy cx cy (4 numbers).
/// The pinhole of an intrinsics file; focal lengths that are not positive and finite are the
/// file's error (`with_positive_focal_lengths`), not every depth image's that uses it.
fn intrinsics_file(path: &Path) -> Result<Projection, InputError> {
    let text = read_text(path)?;
    let count = text.split_whitespace().count();
    let projection = if count == 4 {
        let k = numbers(path, &text, 4, "intrinsics fx fy cx cy")?;
        Projection::Pinhole {
            fx: k[0],
            fy: k[1],
            cx: k[2],
            cy: k[3],
        }
    } else if count == 9 {
        pinhole_of_matrix(path, &numbers(path, &text, 9, "3x3 intrinsics matrix")?)?
    } else {
        return Err(bad(
            path,
            format!("intrinsics: expected a 3x3 matrix (9 numbers) or fx fy cx cy (4 numbers), found {count} values"),
        ));
    };
    with_positive_focal_lengths(path, projection)
}

/// `projection`, or an error naming the intrinsics file `path` when its focal lengths are not
/// positive and finite.
fn with_positive_focal_lengths(path: &Path, projection: Projection) -> Result<Projection, InputError> {
    if let Projection::Pinhole { fx, fy, .. } = projection
        && !(fx > 0.0 && fy > 0.0 && fx.is_finite() && fy.is_finite())
    {
        return Err(bad(
            path,
            format!("intrinsics: focal lengths must be positive (fx {fx}, fy {fy})"),
        ));
    }
    Ok(projection)
}

/// A pinhole from a row-major 3x3 camera matrix of the file `path`: [fx 0 cx; 0 fy cy; 0 0 1].
/// A skew, or a last row other than 0 0 1, is the file's error: the pinhole has no place for
/// them, and leaving them out would move every sample without a word.
fn pinhole_of_matrix(path: &Path, k: &[f64]) -> Result<Projection, InputError> {
    let at = |i: usize| k.get(i).copied().unwrap_or(f64::NAN);
    let (fx, skew) = (at(0), at(1));
    if skew.is_nan() || skew.abs() > 1e-9 * fx.abs().max(1.0) {
        return Err(bad(
            path,
            format!(
                "intrinsics: skew {skew} (the matrix's first row, second value): only an unskewed pinhole [fx 0 cx; 0 fy cy; 0 0 1] is read"
            ),
        ));
    }
    let last = [at(3), at(6), at(7), at(8) - 1.0];
    if !last.iter().all(|v| v.abs() <= 1e-9) {
        return Err(bad(
            path,
            format!(
                "intrinsics: the matrix is not [fx 0 cx; 0 fy cy; 0 0 1] (its second row starts {}, its last row is {} {} {})",
                at(3),
                at(6),
                at(7),
                at(8)
            ),
        ));
    }
    Ok(Projection::Pinhole {
        fx,
        fy: at(4),
        cx: at(2),
        cy: at(5),
    })
}

fn seven_scenes_source(depth: &Path, projection: Projection) -> Result<DepthMapSource, InputError> {
    let name = depth
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let stem = name
        .strip_suffix(".depth.png")
        .ok_or_else(|| bad(depth, "expected a name like frame-000000.depth.png"))?;
    let pose_path = depth.with_file_name(format!("{stem}.pose.txt"));
    if !pose_path.is_file() {
        return Err(bad(
            depth,
            format!("missing pose: {} does not exist", pose_path.display()),
        ));
    }
    let pose = row_major_4x4(&numbers(&pose_path, &read_text(&pose_path)?, 16, "4x4 pose matrix")?);
    check_pose(&pose_path, &pose)?;
    let scale = 0.001;
    let size = image_size(depth, &ImageFormat::Png16 { scale })?;
    DepthMapSource::rgbd_png(depth, scale, size, projection, &pose)
}

fn seven_scenes_frame(depth: &Path, options: &DiscoverOptions) -> Result<DepthMapSource, InputError> {
    let dir = depth
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    seven_scenes_source(depth, seven_scenes_intrinsics(dir, options)?)
}

fn seven_scenes_folder(dir: &Path, options: &DiscoverOptions) -> Result<Vec<DepthMapSource>, InputError> {
    let projection = seven_scenes_intrinsics(dir, options)?;
    let mut frames: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|source| InputError::Io {
            file: dir.to_path_buf(),
            source,
        })?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.file_name()
                .is_some_and(|n| n.to_string_lossy().ends_with(".depth.png"))
        })
        .collect();
    frames.sort();
    frames
        .into_iter()
        .step_by(options.stride.max(1))
        .take(options.limit.unwrap_or(usize::MAX))
        .map(|frame| seven_scenes_source(&frame, projection))
        .collect()
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct Manifest {
    depth_maps: Vec<ManifestEntry>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ManifestEntry {
    image: PathBuf,
    format: Option<String>,
    depth_scale: Option<f64>,
    width: u32,
    height: u32,
    intrinsics: Option<ManifestIntrinsics>,
    projection: Option<String>,
    pose: ManifestPose,
    kind: String,
    weight: Option<f32>,
    /// "none" (the pixel footprint alone), sigma, or [constant, quadratic, offset]; default:
    /// the kind's model.
    depth_noise: Option<ManifestNoise>,
    /// Standard deviations a sample's radius spans at least (default `DEFAULT_NOISE_SIGMAS`).
    noise_sigmas: Option<f64>,
}

#[derive(Deserialize)]
#[serde(untagged)]
enum ManifestNoise {
    Named(String),
    Sigma(f64),
    Numbers(Vec<f64>),
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ManifestIntrinsics {
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ManifestPose {
    camera_to_world: Option<Vec<f64>>,
    world_to_camera: Option<Vec<f64>>,
    /// "opencv" (x right, y down, z forward) or "opengl" (x right, y up, z backward).
    axes: String,
}

/// The largest vote weight a manifest may give: votes are summed in f32, and a weight near
/// f32's range (1e38 was tried) overflows the sums into infinities and the solution into NaN.
const MAX_WEIGHT: f32 = 1000.0;

fn manifest(path: &Path) -> Result<Vec<DepthMapSource>, InputError> {
    let parsed: Manifest =
        serde_json::from_str(&read_text(path)?).map_err(|e| bad(path, format!("invalid manifest: {e}")))?;
    let base = path.parent().unwrap_or(Path::new("."));
    parsed
        .depth_maps
        .into_iter()
        .enumerate()
        .map(|(index, entry)| {
            let at = |problem: String| bad(path, format!("depth_maps[{index}]: {problem}"));
            let image = if entry.image.is_absolute() {
                entry.image.clone()
            } else {
                base.join(&entry.image)
            };
            let ext = image
                .extension()
                .map(|e| e.to_string_lossy().to_lowercase())
                .unwrap_or_default();
            if let Some(scale) = entry.depth_scale {
                check_depth_scale(scale).map_err(at)?;
            }
            let format = match entry.format.as_deref().unwrap_or(ext.as_str()) {
                "png" | "png16" => ImageFormat::Png16 {
                    scale: entry.depth_scale.unwrap_or(0.001),
                },
                "pfm" => ImageFormat::Pfm,
                "npy" => ImageFormat::NpyF32,
                other => return Err(at(format!("unknown image format '{other}' (png16, pfm, npy)"))),
            };
            let kind = match entry.kind.as_str() {
                "photo" => Kind::Photo,
                "rgbd" => Kind::Rgbd,
                "lidar" => Kind::Lidar,
                other => return Err(at(format!("unknown kind '{other}' (photo, rgbd, lidar)"))),
            };
            let projection = match (entry.projection.as_deref(), entry.intrinsics) {
                (Some("spherical"), None) => Projection::Spherical,
                (None | Some("pinhole"), Some(k)) => Projection::Pinhole {
                    fx: k.fx,
                    fy: k.fy,
                    cx: k.cx,
                    cy: k.cy,
                },
                _ => {
                    return Err(at(
                        "give either pinhole \"intrinsics\" or \"projection\": \"spherical\"".into(),
                    ));
                }
            };
            let matrix = match (&entry.pose.camera_to_world, &entry.pose.world_to_camera) {
                (Some(m), None) => row_major_4x4(&check16(m, at)?),
                (None, Some(m)) => {
                    let w2c = row_major_4x4(&check16(m, at)?);
                    check_pose(path, &w2c).map_err(|e| at(e.to_string()))?;
                    w2c.inverse()
                }
                _ => {
                    return Err(at(
                        "the pose needs exactly one of camera_to_world and world_to_camera".into()
                    ));
                }
            };
            let matrix = match entry.pose.axes.as_str() {
                "opencv" => matrix,
                "opengl" => matrix * DMat4::from_diagonal(DVec4::new(1.0, -1.0, -1.0, 1.0)),
                other => return Err(at(format!("unknown pose axes '{other}' (opencv, opengl)"))),
            };
            check_pose(path, &matrix).map_err(|e| at(e.to_string()))?;
            let (width, height) = image_size(&image, &format)?;
            if (width, height) != (entry.width, entry.height) {
                return Err(bad(
                    &image,
                    format!(
                        "image is {width}x{height} but the manifest says {}x{}",
                        entry.width, entry.height
                    ),
                ));
            }
            let weight = entry.weight.unwrap_or(kind.default_weight());
            if !(0.0..=MAX_WEIGHT).contains(&weight) {
                return Err(at(format!("weight {weight} is not in [0, {MAX_WEIGHT}]")));
            }
            if let Some(sigmas) = entry.noise_sigmas {
                check_noise_sigmas(sigmas).map_err(at)?;
            }
            let sigmas = entry.noise_sigmas.unwrap_or(DEFAULT_NOISE_SIGMAS);
            let noise = match &entry.depth_noise {
                None => Ok(match entry.noise_sigmas {
                    Some(sigmas) => kind.default_noise().with_sigmas(sigmas),
                    None => kind.default_noise(),
                }),
                Some(ManifestNoise::Named(name)) => DepthNoise::named(name, entry.noise_sigmas).ok_or_else(|| {
                    format!(
                        "unknown depth_noise '{name}' (\"auto\", \"none\", \"kinect\", \"lidar\", a number, or three)"
                    )
                }),
                Some(ManifestNoise::Sigma(sigma)) => DepthNoise::from_numbers(&[*sigma], sigmas),
                Some(ManifestNoise::Numbers(numbers)) => DepthNoise::from_numbers(numbers, sigmas),
            }
            .map_err(at)?;
            let source = DepthMapSource {
                path: std::path::absolute(&image).unwrap_or(image),
                format,
                width,
                height,
                projection,
                camera_to_world: matrix.to_cols_array(),
                kind,
                weight,
                noise,
            };
            source.check_intrinsics()?;
            Ok(source)
        })
        .collect()
}

/// The 16 numbers of a pose matrix; `at` names the manifest entry in the error.
fn check16(m: &[f64], at: impl Fn(String) -> InputError) -> Result<Vec<f64>, InputError> {
    if m.len() != 16 {
        return Err(at(format!(
            "a pose matrix has 16 numbers (row-major 4x4), found {}",
            m.len()
        )));
    }
    Ok(m.to_vec())
}

/// Size of a depth image from its header alone (cheap validation before any work).
fn image_size(path: &Path, format: &ImageFormat) -> Result<(u32, u32), InputError> {
    // Before any header is read: opening a FIFO would wait for a writer forever.
    check_regular_file(path)?;
    match format {
        ImageFormat::Png16 { .. } => {
            image::image_dimensions(path).map_err(|e| bad(path, format!("unreadable PNG: {e}")))
        }
        ImageFormat::Pfm => pfm_layout(path).map(|l| (l.width, l.height)),
        ImageFormat::NpyF32 => npy_layout(path).map(|l| (l.width, l.height)),
        ImageFormat::ColmapBin => colmap::colmap_depth_layout(path).map(|l| (l.width, l.height)),
        ImageFormat::Ptx { .. } | ImageFormat::E57 { .. } => Err(bad(
            path,
            "the size of a LIDAR scan's grid is decided when it is discovered, not read from a header",
        )),
    }
}
