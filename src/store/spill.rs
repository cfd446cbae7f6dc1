//! Segments too large for memory: a stage appends rows batch by batch to one scratch file per
//! column, and the store encodes the segment from those files when it writes the unit's parts
//! (`format::segment::encode_segment_streamed`: a few blocks' worth of memory whatever the size).
//!
//! The scratch files are unlinked at creation (`tempfile::tempfile_in`), so a killed process
//! leaves nothing behind, and the segment's bytes are exactly those of the same rows held in
//! memory: whether a unit spilled never shows in the store.

use std::fs::File;
use std::io::{BufReader, BufWriter, Seek, SeekFrom, Write};
use std::path::Path;

use crate::format::{Column, ColumnShape};

use super::{Result, StoreError, io_error};

/// One segment of a unit's output: columns in memory, or rows spilled to scratch files.
pub enum SegmentContent {
    /// Every row in memory.
    Columns(Vec<Column>),
    /// Rows appended to scratch files.
    Spilled(SegmentSpill),
}

impl From<Vec<Column>> for SegmentContent {
    fn from(columns: Vec<Column>) -> Self {
        SegmentContent::Columns(columns)
    }
}

/// A segment being built on disk: its column shapes and one scratch file per column holding
/// the raw values appended so far.
pub struct SegmentSpill {
    shapes: Vec<ColumnShape>,
    files: Vec<BufWriter<File>>,
    rows: u64,
}

impl SegmentSpill {
    /// An empty spill of columns shaped `shapes`, its scratch files in `dir` (created if
    /// missing).
    pub fn new_in(dir: &Path, shapes: Vec<ColumnShape>) -> Result<SegmentSpill> {
        std::fs::create_dir_all(dir).map_err(io_error("create scratch", dir))?;
        let files = shapes
            .iter()
            .map(|_| {
                tempfile::tempfile_in(dir)
                    .map(|file| BufWriter::with_capacity(1 << 16, file))
                    .map_err(io_error("create scratch file in", dir))
            })
            .collect::<Result<_>>()?;
        Ok(SegmentSpill { shapes, files, rows: 0 })
    }

    /// Appends the rows of `columns`, which must have the spill's shapes in order. Keys are
    /// checked when the segment is encoded (strictly increasing across every append).
    pub fn append(&mut self, columns: &[Column]) -> Result<()> {
        let invalid = |message: String| StoreError::Encode(crate::format::EncodeError::Invalid(message));
        if columns.len() != self.shapes.len() {
            return Err(invalid(format!(
                "{} columns appended to a spill of {}",
                columns.len(),
                self.shapes.len()
            )));
        }
        let rows = columns.first().map_or(0, Column::rows);
        for ((column, shape), file) in columns.iter().zip(&self.shapes).zip(&mut self.files) {
            if ColumnShape::of(column) != *shape || column.rows() != rows {
                return Err(invalid(format!(
                    "column '{}' appended with another shape or row count than the spill's",
                    column.name
                )));
            }
            file.write_all(column.values.as_bytes())
                .map_err(|source| StoreError::Io {
                    action: "write scratch for",
                    path: column.name.clone().into(),
                    source,
                })?;
        }
        self.rows += rows as u64;
        Ok(())
    }

    /// Rows appended so far.
    pub fn rows(&self) -> u64 {
        self.rows
    }

    /// The column shapes and a reader of each column's values from its start.
    pub(crate) fn into_sources(self) -> std::io::Result<(Vec<ColumnShape>, u64, Vec<BufReader<File>>)> {
        let readers = self
            .files
            .into_iter()
            .map(|writer| {
                let mut file = writer.into_inner().map_err(|e| e.into_error())?;
                file.seek(SeekFrom::Start(0))?;
                Ok(BufReader::with_capacity(1 << 16, file))
            })
            .collect::<std::io::Result<_>>()?;
        Ok((self.shapes, self.rows, readers))
    }
}
