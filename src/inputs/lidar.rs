//! Terrestrial LIDAR scans (PTX and E57) as 360-degree depth maps.
//!
//! Each scan's points, in its sensor frame (z up), are resampled into the equirectangular grid of
//! [`Projection::Spherical`]: a pixel keeps the nearest return that falls in it. The grid's
//! angular step is the scan's own (the median angle between consecutive returns, measured on the
//! first [`STEP_SAMPLE_POINTS`] valid points) times [`GRID_STEP_FACTOR`], so that most pixels get
//! a return and few get two; its width is capped at [`MAX_GRID_WIDTH`] so that one scan's image
//! stays under 128 MiB. The store keeps the file and scan index, and the same resampling is
//! repeated whenever the depth map is read again, so it must be (and is) deterministic.
//!
//! PTX (Leica's text format): per scan, the column and row counts, the sensor position and axes
//! (3 lines, ignored in favour of the matrix), a 4x4 row-vector transform to world coordinates
//! (translation in the last row), then `columns * rows` lines `x y z intensity [r g b]` in the
//! sensor frame; `0 0 0` marks a missing return.
//!
//! E57: every `data3D` point cloud is a scan; its pose (quaternion and translation) maps sensor
//! coordinates to file coordinates. Cartesian and spherical point records are both accepted.

use std::io::{BufRead, BufReader};
use std::path::Path;

use glam::{DMat4, DQuat, DVec3};

use super::depth_map::{
    DepthImage, DepthMapSource, ImageFormat, InputError, Kind, Projection, bad, check_pose, extension_of,
};

/// Valid returns measured per scan to estimate its angular step.
pub const STEP_SAMPLE_POINTS: usize = 200_000;
/// Grid step relative to the scan's own step: a bit coarser, so that the grid has few holes.
pub const GRID_STEP_FACTOR: f64 = 1.25;
/// Widest grid (height is half the width).
pub const MAX_GRID_WIDTH: u32 = 8192;
const MIN_GRID_WIDTH: u32 = 64;

fn io_error(path: &Path) -> impl Fn(std::io::Error) -> InputError + '_ {
    move |source| InputError::Io {
        file: path.to_path_buf(),
        source,
    }
}

/// Estimates the angular step between neighbouring returns from consecutive valid points.
struct StepEstimator {
    previous: Option<DVec3>,
    angles: Vec<f64>,
}

impl StepEstimator {
    fn new() -> Self {
        StepEstimator {
            previous: None,
            angles: Vec::new(),
        }
    }

    fn full(&self) -> bool {
        self.angles.len() >= STEP_SAMPLE_POINTS
    }

    fn add(&mut self, p: DVec3) {
        let direction = p.normalize_or_zero();
        if direction == DVec3::ZERO {
            return;
        }
        if let Some(previous) = self.previous.replace(direction)
            && !self.full()
        {
            let angle = previous.angle_between(direction);
            if angle > 1e-9 {
                self.angles.push(angle);
            }
        }
    }

    /// Grid width for the measured step, or an error if the scan has too few returns.
    fn grid_width(mut self, path: &Path, scan: usize) -> Result<u32, InputError> {
        if self.angles.len() < 16 {
            return Err(bad(path, format!("scan {scan} has fewer than 16 valid returns")));
        }
        let mid = self.angles.len() / 2;
        let step = *self.angles.select_nth_unstable_by(mid, f64::total_cmp).1 * GRID_STEP_FACTOR;
        let width = (std::f64::consts::TAU / step)
            .round()
            .clamp(f64::from(MIN_GRID_WIDTH), f64::from(MAX_GRID_WIDTH));
        Ok((width as u32) & !1)
    }
}

/// Accumulates returns into the spherical grid, nearest return per pixel.
struct GridBuilder<'a> {
    source: &'a DepthMapSource,
    image: DepthImage,
}

impl<'a> GridBuilder<'a> {
    fn new(source: &'a DepthMapSource) -> Self {
        GridBuilder {
            source,
            image: DepthImage {
                width: source.width,
                height: source.height,
                depth: vec![f32::NAN; source.width as usize * source.height as usize],
            },
        }
    }

    fn add(&mut self, p: DVec3) {
        let Some((i, j, range)) = self.source.project(p) else {
            return;
        };
        let (w, h) = (i64::from(self.image.width), i64::from(self.image.height));
        let column = (i.round() as i64).rem_euclid(w);
        let row = (j.round() as i64).clamp(0, h - 1);
        if let Some(pixel) = self.image.depth.get_mut((row * w + column) as usize) {
            let range = range as f32;
            if range > 0.0 && (pixel.is_nan() || range < *pixel) {
                *pixel = range;
            }
        }
    }
}

fn lidar_source(path: &Path, format: ImageFormat, width: u32, camera_to_world: DMat4) -> DepthMapSource {
    DepthMapSource {
        path: std::path::absolute(path).unwrap_or(path.to_path_buf()),
        format,
        width,
        height: width / 2,
        projection: Projection::Spherical,
        camera_to_world: camera_to_world.to_cols_array(),
        kind: Kind::Lidar,
        weight: Kind::Lidar.default_weight(),
        noise: Kind::Lidar.default_noise(),
    }
}

/// A PTX reader that walks scans header by header, streaming the points.
struct PtxReader<'a> {
    path: &'a Path,
    lines: std::io::Lines<BufReader<std::fs::File>>,
    line: usize,
}

struct PtxHeader {
    points: u64,
    camera_to_world: DMat4,
}

impl<'a> PtxReader<'a> {
    fn open(path: &'a Path) -> Result<Self, InputError> {
        let file = std::fs::File::open(path).map_err(io_error(path))?;
        Ok(PtxReader {
            path,
            lines: BufReader::new(file).lines(),
            line: 0,
        })
    }

    fn next_line(&mut self) -> Result<Option<String>, InputError> {
        self.line += 1;
        self.lines.next().transpose().map_err(io_error(self.path))
    }

    fn numbers(&mut self, n: usize, what: &str) -> Result<Vec<f64>, InputError> {
        let line = self
            .next_line()?
            .ok_or_else(|| bad(self.path, format!("line {}: truncated PTX, expected {what}", self.line)))?;
        let values: Vec<f64> = line
            .split_whitespace()
            .map(|t| t.parse::<f64>())
            .collect::<Result<_, _>>()
            .map_err(|_| {
                bad(
                    self.path,
                    format!("line {}: {what}: '{}' is not numbers", self.line, line.trim()),
                )
            })?;
        if values.len() < n || !values.iter().all(|v| v.is_finite()) {
            return Err(bad(
                self.path,
                format!(
                    "line {}: {what}: expected {n} finite numbers, found '{}'",
                    self.line,
                    line.trim()
                ),
            ));
        }
        Ok(values)
    }

    /// The next scan's header, or None at the end of the file.
    fn header(&mut self) -> Result<Option<PtxHeader>, InputError> {
        let columns = loop {
            match self.next_line()? {
                None => return Ok(None),
                Some(line) if line.trim().is_empty() => continue,
                Some(line) => {
                    break line.trim().parse::<u64>().map_err(|_| {
                        bad(
                            self.path,
                            format!("line {}: expected the column count, found '{}'", self.line, line.trim()),
                        )
                    })?;
                }
            }
        };
        let rows = self.numbers(1, "row count")?[0];
        if rows < 0.0 || rows.fract() != 0.0 {
            return Err(bad(
                self.path,
                format!("line {}: row count {rows} is not a count", self.line),
            ));
        }
        for what in ["sensor position", "sensor x axis", "sensor y axis", "sensor z axis"] {
            self.numbers(3, what)?;
        }
        let mut rows_of_matrix = Vec::with_capacity(16);
        for _ in 0..4 {
            rows_of_matrix.extend(self.numbers(4, "4x4 transform row")?.into_iter().take(4));
        }
        // Row-vector convention: p_world = p_local^T M, so the column-major array of M^T is M's
        // row-major array.
        let mut transposed = [0.0; 16];
        transposed.copy_from_slice(&rows_of_matrix);
        let camera_to_world = DMat4::from_cols_array(&transposed);
        check_pose(self.path, &camera_to_world)?;
        Ok(Some(PtxHeader {
            points: columns.saturating_mul(rows as u64),
            camera_to_world,
        }))
    }

    /// Calls `f` with every point of the current scan (missing returns excluded), stopping
    /// early when `f` returns false; the rest of the scan is skipped.
    fn points(&mut self, count: u64, mut f: impl FnMut(DVec3) -> bool) -> Result<(), InputError> {
        let mut wanted = true;
        for _ in 0..count {
            let line = self.next_line()?.ok_or_else(|| {
                bad(
                    self.path,
                    format!("line {}: truncated PTX: the scan has {count} points", self.line),
                )
            })?;
            if !wanted {
                continue;
            }
            let mut tokens = line.split_whitespace().map(str::parse::<f64>);
            let (Some(Ok(x)), Some(Ok(y)), Some(Ok(z))) = (tokens.next(), tokens.next(), tokens.next()) else {
                return Err(bad(
                    self.path,
                    format!(
                        "line {}: expected 'x y z intensity', found '{}'",
                        self.line,
                        line.trim()
                    ),
                ));
            };
            let p = DVec3::new(x, y, z);
            if p != DVec3::ZERO && p.is_finite() {
                wanted = f(p);
            }
        }
        Ok(())
    }
}

/// Every scan of a PTX file as a spherical depth map.
pub fn ptx_scans(path: &Path) -> Result<Vec<DepthMapSource>, InputError> {
    let mut reader = PtxReader::open(path)?;
    let mut sources = Vec::new();
    while let Some(header) = reader.header()? {
        let mut estimator = StepEstimator::new();
        reader.points(header.points, |p| {
            estimator.add(p);
            !estimator.full()
        })?;
        let scan = sources.len();
        let width = estimator.grid_width(path, scan)?;
        sources.push(lidar_source(
            path,
            ImageFormat::Ptx { scan: scan as u32 },
            width,
            header.camera_to_world,
        ));
    }
    if sources.is_empty() {
        return Err(bad(path, "PTX file has no scans"));
    }
    Ok(sources)
}

fn read_ptx_scan(source: &DepthMapSource, scan: u32) -> Result<DepthImage, InputError> {
    let mut reader = PtxReader::open(&source.path)?;
    for index in 0..=scan {
        let header = reader.header()?.ok_or_else(|| {
            bad(
                &source.path,
                format!("PTX file has no scan {scan} (it changed since it was ingested?)"),
            )
        })?;
        if index < scan {
            reader.points(header.points, |_| false)?;
        } else {
            let mut grid = GridBuilder::new(source);
            reader.points(header.points, |p| {
                grid.add(p);
                true
            })?;
            return Ok(grid.image);
        }
    }
    Err(bad(&source.path, format!("PTX file has no scan {scan}")))
}

fn e57_error(path: &Path) -> impl Fn(e57::Error) -> InputError + '_ {
    move |e| bad(path, format!("unreadable E57: {e}"))
}

fn e57_pose(path: &Path, cloud: &e57::PointCloud) -> Result<DMat4, InputError> {
    let pose = match &cloud.transform {
        None => DMat4::IDENTITY,
        Some(t) => {
            let q = &t.rotation;
            let rotation = DQuat::from_xyzw(q.x, q.y, q.z, q.w);
            if !(rotation.is_finite() && (rotation.length() - 1.0).abs() < 1e-3) {
                return Err(bad(
                    path,
                    format!("scan pose quaternion {q:?} is not a unit quaternion"),
                ));
            }
            DMat4::from_rotation_translation(
                rotation.normalize(),
                DVec3::new(t.translation.x, t.translation.y, t.translation.z),
            )
        }
    };
    check_pose(path, &pose)?;
    Ok(pose)
}

/// Calls `f` with every valid point of scan `cloud` in its sensor frame, until `f` returns false.
fn e57_points(
    path: &Path,
    reader: &mut e57::E57Reader<BufReader<std::fs::File>>,
    cloud: &e57::PointCloud,
    mut f: impl FnMut(DVec3) -> bool,
) -> Result<(), InputError> {
    let mut points = reader.pointcloud_simple(cloud).map_err(e57_error(path))?;
    points.apply_pose(false);
    points.spherical_to_cartesian(true);
    for point in points {
        let point = point.map_err(e57_error(path))?;
        if let e57::CartesianCoordinate::Valid { x, y, z } = point.cartesian {
            let p = DVec3::new(x, y, z);
            if p != DVec3::ZERO && p.is_finite() && !f(p) {
                break;
            }
        }
    }
    Ok(())
}

/// Every point cloud of an E57 file as a spherical depth map.
pub fn e57_scans(path: &Path) -> Result<Vec<DepthMapSource>, InputError> {
    let mut reader = e57::E57Reader::from_file(path).map_err(e57_error(path))?;
    let clouds = reader.pointclouds();
    if clouds.is_empty() {
        return Err(bad(path, "E57 file has no point clouds"));
    }
    let mut sources = Vec::with_capacity(clouds.len());
    for (scan, cloud) in clouds.iter().enumerate() {
        if !cloud.has_cartesian() && !cloud.has_spherical() {
            return Err(bad(
                path,
                format!("E57 scan {scan} has neither Cartesian nor spherical coordinates"),
            ));
        }
        let pose = e57_pose(path, cloud)?;
        let mut estimator = StepEstimator::new();
        e57_points(path, &mut reader, cloud, |p| {
            estimator.add(p);
            !estimator.full()
        })?;
        let width = estimator.grid_width(path, scan)?;
        sources.push(lidar_source(path, ImageFormat::E57 { scan: scan as u32 }, width, pose));
    }
    Ok(sources)
}

fn read_e57_scan(source: &DepthMapSource, scan: u32) -> Result<DepthImage, InputError> {
    let path = source.path.as_path();
    let mut reader = e57::E57Reader::from_file(path).map_err(e57_error(path))?;
    let clouds = reader.pointclouds();
    let cloud = clouds.get(scan as usize).ok_or_else(|| {
        bad(
            path,
            format!("E57 file has no scan {scan} (it changed since it was ingested?)"),
        )
    })?;
    let mut grid = GridBuilder::new(source);
    e57_points(path, &mut reader, cloud, |p| {
        grid.add(p);
        true
    })?;
    Ok(grid.image)
}

/// Calls `each` with every valid return of every scan of a PTX or E57 file, in world (file)
/// coordinates, scan by scan in file order, until it returns false; returns the returns read.
/// (`divide` reads LIDAR files as point clouds through it.)
pub fn scan_points_in_world(path: &Path, mut each: impl FnMut(DVec3) -> bool) -> Result<u64, InputError> {
    let extension = extension_of(path);
    let mut points = 0u64;
    // After `each` says stop, the rest is read through without calling it.
    let mut wanted = true;
    let mut posed = |to_world: &DMat4, p: DVec3| {
        points += 1;
        wanted = wanted && each(to_world.transform_point3(p));
        wanted
    };
    match extension.as_str() {
        "ptx" => {
            let mut reader = PtxReader::open(path)?;
            let mut scans = 0;
            while let Some(header) = reader.header()? {
                scans += 1;
                reader.points(header.points, |p| posed(&header.camera_to_world, p))?;
            }
            if scans == 0 {
                return Err(bad(path, "PTX file has no scans"));
            }
        }
        "e57" => {
            let mut reader = e57::E57Reader::from_file(path).map_err(e57_error(path))?;
            let clouds = reader.pointclouds();
            if clouds.is_empty() {
                return Err(bad(path, "E57 file has no point clouds"));
            }
            for cloud in &clouds {
                let to_world = e57_pose(path, cloud)?;
                e57_points(path, &mut reader, cloud, |p| posed(&to_world, p))?;
            }
        }
        _ => return Err(bad(path, "not a LIDAR scan file (.ptx or .e57)")),
    }
    Ok(points)
}

/// Reads a registered LIDAR scan back as its spherical depth image.
pub fn read_scan(source: &DepthMapSource) -> Result<DepthImage, InputError> {
    match source.format {
        ImageFormat::Ptx { scan } => read_ptx_scan(source, scan),
        ImageFormat::E57 { scan } => read_e57_scan(source, scan),
        _ => Err(bad(&source.path, "not a LIDAR scan")),
    }
}

/// Writes one structured scan as PTX (tests and tools produce inputs with it): `points` is
/// column-major (`columns` columns of `rows` points) in the sensor frame, `None` for a missing
/// return.
pub fn write_ptx_scan(
    out: &mut impl std::io::Write,
    columns: usize,
    rows: usize,
    camera_to_world: &DMat4,
    points: &[Option<DVec3>],
) -> std::io::Result<()> {
    writeln!(out, "{columns}\n{rows}")?;
    let t = camera_to_world.w_axis;
    writeln!(out, "{} {} {}", t.x, t.y, t.z)?;
    for axis in [camera_to_world.x_axis, camera_to_world.y_axis, camera_to_world.z_axis] {
        writeln!(out, "{} {} {}", axis.x, axis.y, axis.z)?;
    }
    for column in [
        camera_to_world.x_axis,
        camera_to_world.y_axis,
        camera_to_world.z_axis,
        camera_to_world.w_axis,
    ] {
        writeln!(out, "{} {} {} {}", column.x, column.y, column.z, column.w)?;
    }
    for p in points {
        match p {
            Some(p) => writeln!(out, "{} {} {} 0.5", p.x, p.y, p.z)?,
            None => writeln!(out, "0 0 0 0.5")?,
        }
    }
    Ok(())
}
