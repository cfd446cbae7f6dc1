//! A registered depth map read row by row, from the top, as often as needed: what lets ingest
//! work on an image of any size in a few rows of memory (format-spec.md, "Ingest runs").
//!
//! PNG16, PFM, NPY and COLMAP files are decoded a row at a time (an interlaced PNG is the one
//! exception: its passes are decoded whole); a LIDAR scan's grid is built in memory (its width
//! is capped, `lidar::MAX_GRID_WIDTH`). Every pass gives the same values
//! [`DepthMapSource::load`] does, which is these rows collected.

use std::path::Path;

use super::depth_map::{DepthImage, DepthMapSource, ImageFormat, InputError, bad};
use super::image_files::{FloatRows, PngRows, npy_layout, pfm_layout};
use super::{colmap, lidar};

enum Reader {
    Png(Box<PngRows>),
    Floats(FloatRows),
    Memory(DepthImage),
}

/// The rows of one depth map; [`DepthRows::rewind`] starts another pass from the top.
pub struct DepthRows<'a> {
    source: &'a DepthMapSource,
    reader: Reader,
    next: u32,
}

impl<'a> DepthRows<'a> {
    /// Opens `source` to read it whole ([`DepthMapSource::load`]), and checks that its size is
    /// the registered one.
    pub fn open(source: &'a DepthMapSource) -> Result<DepthRows<'a>, InputError> {
        DepthRows::open_as(source, false)
    }

    /// Opens `source`, too large for the memory it may use, to read it a row at a time: a file
    /// that cannot be decoded that way (an interlaced PNG) is refused by name.
    pub fn open_streaming(source: &'a DepthMapSource) -> Result<DepthRows<'a>, InputError> {
        DepthRows::open_as(source, true)
    }

    fn open_as(source: &'a DepthMapSource, streaming: bool) -> Result<DepthRows<'a>, InputError> {
        let path = source.path.as_path();
        let (reader, (width, height)) = match &source.format {
            ImageFormat::Png16 { scale } => {
                let rows = PngRows::open(path, *scale, streaming)?;
                let size = rows.size();
                (Reader::Png(Box::new(rows)), size)
            }
            ImageFormat::Pfm | ImageFormat::NpyF32 | ImageFormat::ColmapBin => {
                let layout = match &source.format {
                    ImageFormat::Pfm => pfm_layout(path)?,
                    ImageFormat::NpyF32 => npy_layout(path)?,
                    _ => colmap::colmap_depth_layout(path)?,
                };
                (
                    Reader::Floats(FloatRows::open(path, layout)?),
                    (layout.width, layout.height),
                )
            }
            ImageFormat::Ptx { .. } | ImageFormat::E57 { .. } => {
                let image = lidar::read_scan(source)?;
                let size = (image.width, image.height);
                (Reader::Memory(image), size)
            }
        };
        if (width, height) != (source.width, source.height) {
            return Err(size_mismatch(path, (width, height), source));
        }
        Ok(DepthRows {
            source,
            reader,
            next: 0,
        })
    }

    /// Width in pixels.
    pub fn width(&self) -> u32 {
        self.source.width
    }

    /// Height in pixels.
    pub fn height(&self) -> u32 {
        self.source.height
    }

    /// Starts again from the top row.
    pub fn rewind(&mut self) -> Result<(), InputError> {
        if self.next == 0 {
            return Ok(());
        }
        match &mut self.reader {
            Reader::Memory(_) | Reader::Floats(_) => {}
            Reader::Png(_) => {
                let ImageFormat::Png16 { scale } = self.source.format else {
                    return Err(bad(&self.source.path, "PNG reader for a file that is not a PNG"));
                };
                // A rewind opens the file again; the first open refused what streaming cannot read.
                self.reader = Reader::Png(Box::new(PngRows::open(&self.source.path, scale, false)?));
            }
        }
        self.next = 0;
        Ok(())
    }

    /// The next row into `out` (`width` values; NaN where invalid), or `false` after the last.
    pub fn next_row(&mut self, out: &mut [f32]) -> Result<bool, InputError> {
        let row = self.next;
        if row >= self.source.height {
            return Ok(false);
        }
        let path = self.source.path.as_path();
        match &mut self.reader {
            Reader::Png(rows) => rows.read_row(path, row, out)?,
            Reader::Floats(rows) => rows.read_row(path, row, out)?,
            Reader::Memory(image) => {
                let width = image.width as usize;
                let values = image
                    .depth
                    .get(row as usize * width..(row as usize + 1) * width)
                    .ok_or_else(|| bad(path, format!("depth image has no row {row}")))?;
                for (o, v) in out.iter_mut().zip(values) {
                    *o = *v;
                }
            }
        }
        self.next += 1;
        Ok(true)
    }
}

fn size_mismatch(path: &Path, found: (u32, u32), source: &DepthMapSource) -> InputError {
    bad(
        path,
        format!(
            "image is {}x{}, the registered size is {}x{}",
            found.0, found.1, source.width, source.height
        ),
    )
}

impl DepthMapSource {
    /// Reads the whole depth image, and checks that its size is the registered one.
    pub fn load(&self) -> Result<DepthImage, InputError> {
        let mut rows = DepthRows::open(self)?;
        let width = self.width as usize;
        let mut depth = vec![f32::NAN; width * self.height as usize];
        for out in depth.chunks_exact_mut(width.max(1)) {
            rows.next_row(out)?;
        }
        Ok(DepthImage {
            width: self.width,
            height: self.height,
            depth,
        })
    }
}
