//! The TUM RGB-D benchmark's layout: `depth.txt` lists `timestamp path` of 16-bit depth PNGs
//! (5000 units per metre), `groundtruth.txt` lists `timestamp tx ty tz qx qy qz qw`, the pose
//! of the colour camera's optical centre in the world (camera-to-world, OpenCV axes); the
//! depth images are registered to the colour camera. Lines starting with `#` are comments.
//! Each depth frame takes the ground-truth pose nearest in time, if it lies within
//! [`MAX_TIME_DIFFERENCE`]; frames without one are left out and counted.

use std::path::{Path, PathBuf};

use glam::{DMat4, DQuat, DVec3};

use super::depth_map::{DepthMapSource, InputError, Projection, bad, check_pose};

/// Metres per unit of a TUM depth PNG.
pub const TUM_DEPTH_SCALE: f64 = 1.0 / 5000.0;

/// The largest gap in seconds between a depth frame and the pose it takes: the benchmark's
/// own association script (`associate.py`) matches within 0.02 s.
pub const MAX_TIME_DIFFERENCE: f64 = 0.02;

/// Whether `dir` is laid out as a TUM RGB-D sequence.
pub fn is_tum_folder(dir: &Path) -> bool {
    dir.join("depth.txt").is_file() && dir.join("groundtruth.txt").is_file()
}

/// The published intrinsics of the colour camera of the benchmark's Freiburg 1, 2 and 3
/// sensors, which the depth is registered to, when the folder's name says which sensor
/// (`rgbd_dataset_freiburg1_xyz`, ...).
pub fn freiburg_intrinsics(dir: &Path) -> Option<Projection> {
    let name = std::path::absolute(dir)
        .ok()?
        .file_name()?
        .to_string_lossy()
        .to_lowercase();
    let [fx, fy, cx, cy] = if name.contains("freiburg1") {
        [517.3, 516.5, 318.6, 255.3]
    } else if name.contains("freiburg2") {
        [520.9, 521.0, 325.1, 249.7]
    } else if name.contains("freiburg3") {
        [535.4, 539.2, 320.1, 247.6]
    } else {
        return None;
    };
    Some(Projection::Pinhole { fx, fy, cx, cy })
}

/// The lines of a TUM list file that are not comments, with their line numbers, split into
/// exactly `fields` fields.
fn records(path: &Path, fields: usize, what: &str) -> Result<Vec<(usize, Vec<String>)>, InputError> {
    let text = std::fs::read_to_string(path).map_err(|source| InputError::Io {
        file: path.to_path_buf(),
        source,
    })?;
    text.lines()
        .enumerate()
        .filter(|(_, line)| !line.trim().is_empty() && !line.trim_start().starts_with('#'))
        .map(|(index, line)| {
            let parts: Vec<String> = line.split_whitespace().map(str::to_string).collect();
            if parts.len() != fields {
                return Err(bad(
                    path,
                    format!(
                        "line {}: expected {what} ({fields} fields), found {}",
                        index + 1,
                        parts.len()
                    ),
                ));
            }
            Ok((index + 1, parts))
        })
        .collect()
}

fn number(path: &Path, line: usize, text: &str) -> Result<f64, InputError> {
    text.parse::<f64>()
        .ok()
        .filter(|v| v.is_finite())
        .ok_or_else(|| bad(path, format!("line {line}: '{text}' is not a finite number")))
}

/// The sequence's depth frames with their poses, every `stride`-th of those that have one, at
/// most `limit`; and how many frames had no pose within [`MAX_TIME_DIFFERENCE`].
pub fn tum_frames(
    dir: &Path,
    projection: Projection,
    stride: usize,
    limit: Option<usize>,
) -> Result<(Vec<DepthMapSource>, usize), InputError> {
    let truth_path = dir.join("groundtruth.txt");
    let mut poses: Vec<(f64, DMat4)> = records(&truth_path, 8, "timestamp tx ty tz qx qy qz qw")?
        .into_iter()
        .map(|(line, fields)| {
            let values = fields
                .iter()
                .map(|f| number(&truth_path, line, f))
                .collect::<Result<Vec<f64>, _>>()?;
            let &[time, tx, ty, tz, qx, qy, qz, qw] = values.as_slice() else {
                return Err(bad(&truth_path, format!("line {line}: expected 8 numbers")));
            };
            let rotation = DQuat::from_xyzw(qx, qy, qz, qw);
            if (rotation.length() - 1.0).abs() > 1e-3 {
                return Err(bad(
                    &truth_path,
                    format!("line {line}: the quaternion has length {}, not 1", rotation.length()),
                ));
            }
            let pose = DMat4::from_rotation_translation(rotation.normalize(), DVec3::new(tx, ty, tz));
            check_pose(&truth_path, &pose)?;
            Ok((time, pose))
        })
        .collect::<Result<_, _>>()?;
    if poses.is_empty() {
        return Err(bad(&truth_path, "no poses"));
    }
    poses.sort_by(|a, b| a.0.total_cmp(&b.0));
    let depth_list = dir.join("depth.txt");
    let mut frames: Vec<(PathBuf, DMat4)> = Vec::new();
    let mut without_pose = 0;
    for (line, fields) in records(&depth_list, 2, "timestamp path")? {
        let (Some(time), Some(file)) = (fields.first(), fields.get(1)) else {
            continue;
        };
        let time = number(&depth_list, line, time)?;
        let after = poses.partition_point(|(t, _)| *t < time);
        let nearest = [after.checked_sub(1), Some(after)]
            .into_iter()
            .flatten()
            .filter_map(|i| poses.get(i))
            .min_by(|a, b| (a.0 - time).abs().total_cmp(&(b.0 - time).abs()));
        match nearest {
            Some((t, pose)) if (t - time).abs() <= MAX_TIME_DIFFERENCE => frames.push((dir.join(file), *pose)),
            _ => without_pose += 1,
        }
    }
    let sources = frames
        .into_iter()
        .step_by(stride.max(1))
        .take(limit.unwrap_or(usize::MAX))
        .map(|(path, pose)| {
            let size = image::image_dimensions(&path).map_err(|e| bad(&path, format!("unreadable PNG: {e}")))?;
            DepthMapSource::rgbd_png(&path, TUM_DEPTH_SCALE, size, projection, &pose)
        })
        .collect::<Result<Vec<_>, InputError>>()?;
    Ok((sources, without_pose))
}
