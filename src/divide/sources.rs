//! What `divide` reads besides PLY and XYZ files: the returns of LIDAR scans (PTX, E57) and
//! the samples of an octstore store's depth maps, each turned into a stream of point records.
//!
//! - Scans: every valid return of every scan, in world (file) coordinates, as `double x, y, z`
//!   (a scan's coordinates can be far from the origin, where floats lose millimetres).
//!   Intensities and colours are not carried.
//! - A store: the back-projected samples of its registered depth maps, in the order of their
//!   ids, as ingest makes them (spikes left out): `double x, y, z`, `float nx, ny, nz` (the
//!   unit normal from the map's depth gradient, facing its camera; zero where it has none) and
//!   `float radius` (the sample's footprint, paper section 4.1).
//!
//! Both are read again on every pass, in the same order, so the division stays deterministic.

use std::path::{Path, PathBuf};

use glam::DVec3;

use super::{DivideError, PointSource, Result};
use super::{PointLayout, open_point_cloud};
use crate::format::ply_header::PlyScalar;
use crate::inputs::{extension_of, scan_points_in_world};
use crate::stages::ingest::{DepthMapRecord, SampleStream, open_rows, registered_depth_maps};
use crate::store::{CATALOG_FILE, Store};

/// Opens one input of `divide`: a store's folder, a PTX or E57 scan file, or a point cloud
/// file (PLY, XYZ, TXT).
pub fn open_input(path: &Path, memory_budget: u64) -> Result<Box<dyn PointSource>> {
    if path.is_dir() {
        if path.join(CATALOG_FILE).is_file() {
            return Ok(Box::new(StoreSamples::open(path, memory_budget)?));
        }
        return Err(DivideError::NotAStore {
            path: path.to_path_buf(),
        });
    }
    let extension = extension_of(path);
    match extension.as_str() {
        "ptx" | "e57" => Ok(Box::new(ScanPoints::new(path))),
        _ => Ok(Box::new(open_point_cloud(path).map_err(DivideError::PointCloud)?)),
    }
}

fn layout(properties: &[(&str, PlyScalar)]) -> PointLayout {
    let properties = properties.iter().map(|(n, s)| (n.to_string(), *s)).collect();
    // x, y and z, once each: always a layout.
    PointLayout::new(properties).unwrap_or_else(|_| unreachable!())
}

/// Fills blocks of `block_points` records and hands each full one to `each`; keeps the first
/// error `each` returns.
struct Blocks<'a> {
    bytes: Vec<u8>,
    limit: usize,
    each: &'a mut dyn FnMut(&[u8]) -> Result<()>,
    failed: Option<DivideError>,
}

impl<'a> Blocks<'a> {
    fn new(record_len: usize, block_points: usize, each: &'a mut dyn FnMut(&[u8]) -> Result<()>) -> Self {
        let limit = record_len * block_points.max(1);
        Blocks {
            bytes: Vec::with_capacity(limit),
            limit,
            each,
            failed: None,
        }
    }

    /// Adds one record; false once `each` has failed.
    fn push(&mut self, record: &[u8]) -> bool {
        self.bytes.extend_from_slice(record);
        if self.bytes.len() >= self.limit {
            self.flush();
        }
        self.failed.is_none()
    }

    fn flush(&mut self) {
        if self.failed.is_none()
            && !self.bytes.is_empty()
            && let Err(e) = (self.each)(&self.bytes)
        {
            self.failed = Some(e);
        }
        self.bytes.clear();
    }

    fn finish(mut self) -> Result<()> {
        self.flush();
        self.failed.map_or(Ok(()), Err)
    }
}

/// The returns of a PTX or E57 file's scans, in world coordinates.
pub struct ScanPoints {
    path: PathBuf,
    layout: PointLayout,
}

impl ScanPoints {
    /// The scans of `path` (read when the passes stream them).
    pub fn new(path: &Path) -> ScanPoints {
        ScanPoints {
            path: path.to_path_buf(),
            layout: layout(&[("x", PlyScalar::F64), ("y", PlyScalar::F64), ("z", PlyScalar::F64)]),
        }
    }
}

impl PointSource for ScanPoints {
    fn describe(&self) -> String {
        self.path.display().to_string()
    }

    fn layout(&self) -> &PointLayout {
        &self.layout
    }

    fn announced_points(&self) -> Option<u64> {
        None
    }

    fn for_each_block(&self, block_points: usize, each: &mut dyn FnMut(&[u8]) -> Result<()>) -> Result<u64> {
        let mut blocks = Blocks::new(self.layout.record_len(), block_points, each);
        let points = scan_points_in_world(&self.path, |p| {
            blocks.push([p.x.to_le_bytes(), p.y.to_le_bytes(), p.z.to_le_bytes()].as_flattened())
        })
        .map_err(DivideError::PointCloud)?;
        blocks.finish()?;
        Ok(points)
    }
}

/// The samples of a store's depth maps.
pub struct StoreSamples {
    path: PathBuf,
    maps: Vec<DepthMapRecord>,
    layout: PointLayout,
    memory_budget: u64,
}

impl StoreSamples {
    /// The registered depth maps of the store at `path` (opened for reading only).
    pub fn open(path: &Path, memory_budget: u64) -> Result<StoreSamples> {
        let store = Store::open_read_only(path)?;
        let maps: Vec<DepthMapRecord> = registered_depth_maps(&store)?.into_iter().map(|(_, r)| r).collect();
        if maps.is_empty() {
            return Err(DivideError::EmptyStore {
                path: path.to_path_buf(),
            });
        }
        Ok(StoreSamples {
            path: path.to_path_buf(),
            maps,
            layout: layout(&[
                ("x", PlyScalar::F64),
                ("y", PlyScalar::F64),
                ("z", PlyScalar::F64),
                ("nx", PlyScalar::F32),
                ("ny", PlyScalar::F32),
                ("nz", PlyScalar::F32),
                ("radius", PlyScalar::F32),
            ]),
            memory_budget,
        })
    }
}

pub(super) fn record_of(point: DVec3, normal: DVec3, radius: f64) -> [u8; 40] {
    let doubles = [point.x, point.y, point.z].map(f64::to_le_bytes);
    let floats = [normal.x, normal.y, normal.z, radius].map(|v| (v as f32).to_le_bytes());
    let mut record = [0u8; 40];
    for (slot, byte) in record
        .iter_mut()
        .zip(doubles.as_flattened().iter().chain(floats.as_flattened()))
    {
        *slot = *byte;
    }
    record
}

impl PointSource for StoreSamples {
    fn describe(&self) -> String {
        format!("the samples of store {}", self.path.display())
    }

    fn layout(&self) -> &PointLayout {
        &self.layout
    }

    fn announced_points(&self) -> Option<u64> {
        // Spikes among them are left out: the bars may end short of this.
        Some(self.maps.iter().map(|m| m.stats.samples).sum())
    }

    fn for_each_block(&self, block_points: usize, each: &mut dyn FnMut(&[u8]) -> Result<()>) -> Result<u64> {
        let mut blocks = Blocks::new(self.layout.record_len(), block_points, each);
        let mut points = 0u64;
        // A map's depths in memory when they take at most a quarter of the budget.
        let memory = self.memory_budget / 4;
        for map in &self.maps {
            let source = &map.source;
            let rows = open_rows(source, memory).map_err(DivideError::PointCloud)?;
            let stream = SampleStream::new(source, rows).map_err(DivideError::PointCloud)?;
            let mut going = true;
            stream
                .for_each(|sample| {
                    if going && !sample.spike {
                        points += 1;
                        going = blocks.push(&record_of(sample.point, sample.normal, sample.radius));
                    }
                })
                .map_err(DivideError::PointCloud)?;
            if !going {
                break;
            }
        }
        blocks.finish()?;
        Ok(points)
    }
}
