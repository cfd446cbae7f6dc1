//! Point clouds read as a stream of fixed-size records: PLY (ASCII or binary, either
//! endianness, any scalar vertex properties: normals, colours, intensities, ...) and XYZ / TXT
//! (3, 6 or 9 numbers a line: `x y z`, then `nx ny nz`, then `red green blue`).
//!
//! Whatever the file, each point comes out as one record of the file's vertex properties,
//! binary little-endian, in the file's property order ([`PointLayout`]); `divide` writes these
//! records into its subspace files unchanged, so every attribute survives. Nothing here holds
//! more than one block of records, whatever the file's size.

use std::fs::File;
use std::io::{BufRead, BufReader, Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

use crate::format::ply_header::{PlyEncoding, PlyProperty, PlyScalar, parse_ply_header};

use crate::inputs::{InputError, bad, extension_of};

/// The vertex properties of a point record, in order; records are binary little-endian.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PointLayout {
    properties: Vec<(String, PlyScalar)>,
    offsets: Vec<usize>,
    record_len: usize,
    /// Offsets and types of x, y and z.
    position: [(usize, PlyScalar); 3],
    /// Whether x, y and z are all floats, or all doubles: read without the general decoder.
    all_f32: bool,
    all_f64: bool,
    /// Whether the records are float x, y, z, in that order, and nothing else.
    packed_f32: bool,
}

impl PointLayout {
    /// The layout of `properties` (name, type), which must name `x`, `y` and `z` once each.
    pub fn new(properties: Vec<(String, PlyScalar)>) -> Result<PointLayout, String> {
        let mut offsets = Vec::with_capacity(properties.len());
        let mut record_len = 0;
        for (_, scalar) in &properties {
            offsets.push(record_len);
            record_len += scalar.size();
        }
        let find = |axis: &str| -> Result<(usize, PlyScalar), String> {
            let mut found = properties.iter().zip(&offsets).filter(|((name, _), _)| name == axis);
            let ((_, scalar), offset) = found
                .next()
                .ok_or_else(|| format!("the vertices have no '{axis}' property"))?;
            if found.next().is_some() {
                return Err(format!("the vertices have two '{axis}' properties"));
            }
            Ok((*offset, *scalar))
        };
        let position = [find("x")?, find("y")?, find("z")?];
        let all_f32 = position.iter().all(|(_, s)| *s == PlyScalar::F32);
        Ok(PointLayout {
            packed_f32: all_f32 && record_len == 12 && position.map(|(offset, _)| offset) == [0, 4, 8],
            all_f32,
            all_f64: position.iter().all(|(_, s)| *s == PlyScalar::F64),
            properties,
            offsets,
            record_len,
            position,
        })
    }

    /// Property names and types, in record order.
    pub fn properties(&self) -> &[(String, PlyScalar)] {
        &self.properties
    }

    /// Bytes of one record.
    pub fn record_len(&self) -> usize {
        self.record_len
    }

    /// The position of a record (at least [`record_len`](Self::record_len) bytes).
    #[inline]
    pub fn position(&self, record: &[u8]) -> [f64; 3] {
        if self.all_f32 {
            return self.position.map(|(offset, _)| {
                record
                    .get(offset..offset + 4)
                    .and_then(|b| b.try_into().ok())
                    .map_or(0.0, |b| f64::from(f32::from_le_bytes(b)))
            });
        }
        if self.all_f64 {
            return self.position.map(|(offset, _)| {
                record
                    .get(offset..offset + 8)
                    .and_then(|b| b.try_into().ok())
                    .map_or(0.0, f64::from_le_bytes)
            });
        }
        self.position
            .map(|(offset, scalar)| scalar.read_le(record.get(offset..).unwrap_or_default()))
    }

    /// Calls `each(first, positions)` with the positions of consecutive runs of the records
    /// of `block`, in order (`first`: the record of `positions[0]`): the hot loop of every
    /// pass over points. The layout's kind is decided once per block, and a run's positions
    /// are decoded in one tight loop into a small buffer that stays in the L1 cache, so the
    /// caller's loop over them reads plain arrays (a per-record call that returns a position
    /// goes through memory and stalls on store forwarding). Always inlined, so that a caller
    /// compiled for AVX2 (`crate::sys::with_wide_vectors`) decodes in AVX2 as well.
    #[inline(always)]
    pub fn for_each_positions(&self, block: &[u8], mut each: impl FnMut(usize, &[[f64; 3]])) {
        const RUN: usize = 1024;
        let len = self.record_len.max(1);
        let [x, y, z] = self.position.map(|(offset, _)| offset);
        let mut positions = [[0.0f64; 3]; RUN];
        for (run, records) in block.chunks(RUN * len).enumerate() {
            let decoded = positions.iter_mut().zip(records.chunks_exact(len));
            if self.packed_f32 {
                // Float x, y, z and nothing else: offsets known at compile time, so the loop
                // has no bounds checks.
                for (p, record) in positions.iter_mut().zip(records.chunks_exact(12)) {
                    if let &[x0, x1, x2, x3, y0, y1, y2, y3, z0, z1, z2, z3] = record {
                        *p = [[x0, x1, x2, x3], [y0, y1, y2, y3], [z0, z1, z2, z3]]
                            .map(|b| f64::from(f32::from_le_bytes(b)));
                    }
                }
            } else if self.all_f32 {
                let read = |record: &[u8], offset: usize| {
                    record
                        .get(offset..offset + 4)
                        .and_then(|b| b.try_into().ok())
                        .map_or(0.0, |b| f64::from(f32::from_le_bytes(b)))
                };
                for (p, record) in decoded {
                    *p = [read(record, x), read(record, y), read(record, z)];
                }
            } else if self.all_f64 {
                let read = |record: &[u8], offset: usize| {
                    record
                        .get(offset..offset + 8)
                        .and_then(|b| b.try_into().ok())
                        .map_or(0.0, f64::from_le_bytes)
                };
                for (p, record) in decoded {
                    *p = [read(record, x), read(record, y), read(record, z)];
                }
            } else {
                for (p, record) in decoded {
                    *p = self.position(record);
                }
            }
            let count = (records.len() / len).min(RUN);
            each(run * RUN, positions.get(..count).unwrap_or_default());
        }
    }

    /// The `property` lines of a PLY header for these records.
    pub fn ply_properties(&self) -> String {
        self.properties
            .iter()
            .map(|(name, scalar)| format!("property {} {name}\n", scalar.name()))
            .collect()
    }
}

/// How a point cloud file's records are stored.
#[derive(Clone, Debug)]
enum Body {
    /// `count` binary records from byte `offset`.
    Binary { offset: u64, count: u64, big_endian: bool },
    /// `count` lines of numbers after `skip_lines` lines (header and earlier elements).
    AsciiPly { skip_lines: u64, count: u64 },
    /// Lines of 3, 6 or 9 numbers; blank lines and lines starting with `#` or `//` skipped.
    Xyz,
}

/// An opened point cloud file: its layout, and its records read block by block.
#[derive(Clone, Debug)]
pub struct PointCloudFile {
    path: PathBuf,
    layout: PointLayout,
    body: Body,
}

/// The longest header read before a file is declared not to be PLY.
const MAX_HEADER_BYTES: u64 = 1 << 20;

/// Opens a point cloud by its extension: `.ply`, or `.xyz` / `.txt` / `.pts`-like text.
pub fn open_point_cloud(path: &Path) -> Result<PointCloudFile, InputError> {
    let io = |e| InputError::Io {
        file: path.to_path_buf(),
        source: e,
    };
    let extension = extension_of(path);
    match extension.as_str() {
        "ply" => open_ply(path),
        "xyz" | "txt" => {
            let mut lines = BufReader::new(File::open(path).map_err(io)?).lines();
            let mut number = 0u64;
            let columns = loop {
                number += 1;
                let Some(line) = lines.next() else {
                    return Err(bad(path, "no points in the file"));
                };
                let line = line.map_err(io)?;
                if let Some(columns) = data_columns(&line) {
                    break columns;
                }
            };
            let layout = xyz_layout(columns).ok_or_else(|| {
                bad(
                    path,
                    format!("line {number}: {columns} numbers (expected 3: x y z, 6: with nx ny nz, or 9: and red green blue)"),
                )
            })?;
            Ok(PointCloudFile {
                path: path.to_path_buf(),
                layout,
                body: Body::Xyz,
            })
        }
        _ => Err(bad(path, "unknown point cloud format (expected .ply, .xyz or .txt)")),
    }
}

/// Columns of a data line of an XYZ file (`None` for blank and comment lines).
fn data_columns(line: &str) -> Option<usize> {
    let line = line.trim();
    if line.is_empty() || line.starts_with('#') || line.starts_with("//") {
        return None;
    }
    Some(
        line.split(|c: char| c.is_whitespace() || c == ',')
            .filter(|t| !t.is_empty())
            .count(),
    )
}

fn xyz_layout(columns: usize) -> Option<PointLayout> {
    let mut properties: Vec<(String, PlyScalar)> = ["x", "y", "z"].map(|n| (n.to_string(), PlyScalar::F64)).into();
    if columns >= 6 {
        properties.extend(["nx", "ny", "nz"].map(|n| (n.to_string(), PlyScalar::F32)));
    }
    if columns == 9 {
        properties.extend(["red", "green", "blue"].map(|n| (n.to_string(), PlyScalar::U8)));
    }
    (matches!(columns, 3 | 6 | 9))
        .then(|| PointLayout::new(properties).ok())
        .flatten()
}

fn open_ply(path: &Path) -> Result<PointCloudFile, InputError> {
    let io = |e| InputError::Io {
        file: path.to_path_buf(),
        source: e,
    };
    let mut head = Vec::new();
    File::open(path)
        .map_err(io)?
        .take(MAX_HEADER_BYTES)
        .read_to_end(&mut head)
        .map_err(io)?;
    let header = parse_ply_header(&head).map_err(|problem| bad(path, problem))?;
    let file_len = std::fs::metadata(path).map_err(io)?.len();
    // Elements before the vertices are skipped: by their size in a binary body (lists cannot
    // be skipped without reading them), by their line count in an ASCII one.
    let mut before_bytes = 0u64;
    let mut before_lines = 0u64;
    for element in &header.elements {
        let properties: Vec<(String, PlyScalar)> = element
            .properties
            .iter()
            .map(|p| match p {
                PlyProperty::Scalar(name, scalar) => Ok((name.clone(), *scalar)),
                PlyProperty::List(name, ..) => Err(name.clone()),
            })
            .collect::<Result<_, _>>()
            .map_err(|list| {
                bad(
                    path,
                    format!(
                        "element '{}' has the list property '{list}' {}",
                        element.name,
                        if element.name == "vertex" {
                            "(point clouds have scalar vertex properties only)"
                        } else {
                            "before the vertices (not supported)"
                        }
                    ),
                )
            })?;
        let record_len: u64 = properties.iter().map(|(_, s)| s.size() as u64).sum();
        if element.name != "vertex" {
            before_bytes = element
                .count
                .checked_mul(record_len)
                .and_then(|b| b.checked_add(before_bytes))
                .ok_or_else(|| bad(path, format!("element '{}' is implausibly large", element.name)))?;
            before_lines += element.count;
            continue;
        }
        let layout = PointLayout::new(properties).map_err(|problem| bad(path, problem))?;
        let body = match header.encoding {
            PlyEncoding::Ascii => Body::AsciiPly {
                skip_lines: before_lines,
                count: element.count,
            },
            encoding => {
                let offset = header.body_offset as u64 + before_bytes;
                let need = element
                    .count
                    .checked_mul(layout.record_len() as u64)
                    .and_then(|b| b.checked_add(offset));
                if need.is_none_or(|need| need > file_len) {
                    let held = file_len.saturating_sub(offset) / layout.record_len().max(1) as u64;
                    return Err(bad(
                        path,
                        format!(
                            "truncated: the header announces {} vertices, the file holds {held}",
                            element.count
                        ),
                    ));
                }
                Body::Binary {
                    offset,
                    count: element.count,
                    big_endian: encoding == PlyEncoding::BigEndian,
                }
            }
        };
        return Ok(PointCloudFile {
            path: path.to_path_buf(),
            layout,
            body,
        });
    }
    Err(bad(path, "no vertex element"))
}

impl PointCloudFile {
    /// The file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Its records' layout.
    pub fn layout(&self) -> &PointLayout {
        &self.layout
    }

    /// Points announced by the header (PLY), `None` for text files.
    pub fn announced_points(&self) -> Option<u64> {
        match self.body {
            Body::Binary { count, .. } | Body::AsciiPly { count, .. } => Some(count),
            Body::Xyz => None,
        }
    }

    /// Calls `each` with consecutive blocks of at most `block_points` records, in file order,
    /// and returns the number of points. A point whose position is not finite, a short body or
    /// a malformed line is an error naming the file and the point or line.
    pub fn for_each_block<E: From<InputError>>(
        &self,
        block_points: usize,
        mut each: impl FnMut(&[u8]) -> Result<(), E>,
    ) -> Result<u64, E> {
        let block_points = block_points.max(1);
        let len = self.layout.record_len();
        let io = |e| InputError::Io {
            file: self.path.clone(),
            source: e,
        };
        let mut block = Vec::with_capacity(block_points * len);
        let mut done = 0u64;
        if let Some(blocks) = self.random_access_blocks(block_points) {
            // The same blocks, read the same way, as the workers of a parallel pass read.
            for index in 0..blocks {
                self.read_block(block_points, index, &mut block)?;
                done += (block.len() / len) as u64;
                each(&block)?;
            }
            return Ok(done);
        }
        let mut flush = |block: &mut Vec<u8>, done: &mut u64| -> Result<(), E> {
            self.check_finite(block, *done)?;
            *done += (block.len() / len) as u64;
            each(block)?;
            block.clear();
            Ok(())
        };
        match &self.body {
            // Read by block above: `random_access_blocks` is `Some` for every binary body.
            Body::Binary { .. } => {}
            Body::AsciiPly { skip_lines, count } => {
                let mut lines = BufReader::new(File::open(&self.path).map_err(io)?).lines();
                let header_lines = self.ascii_header_lines()?;
                for _ in 0..header_lines + skip_lines {
                    lines.next().transpose().map_err(io)?;
                }
                for row in 0..*count {
                    let number = header_lines + skip_lines + row + 1;
                    let line = lines
                        .next()
                        .transpose()
                        .map_err(io)?
                        .ok_or_else(|| bad(&self.path, format!("truncated: {row} of {count} vertices")))?;
                    self.parse_line(&line, number, &mut block)?;
                    if block.len() >= block_points * len {
                        flush(&mut block, &mut done)?;
                    }
                }
            }
            Body::Xyz => {
                let lines = BufReader::new(File::open(&self.path).map_err(io)?).lines();
                for (index, line) in lines.enumerate() {
                    let line = line.map_err(io)?;
                    if data_columns(&line).is_none() {
                        continue;
                    }
                    self.parse_line(&line, index as u64 + 1, &mut block)?;
                    if block.len() >= block_points * len {
                        flush(&mut block, &mut done)?;
                    }
                }
            }
        }
        if !block.is_empty() {
            flush(&mut block, &mut done)?;
        }
        Ok(done)
    }

    /// The number of blocks of `block_points` records that [`read_block`](Self::read_block)
    /// reads independently of each other (in any order, on any thread): binary files only,
    /// `None` for text, whose records lie at offsets only reading the lines before finds.
    pub fn random_access_blocks(&self, block_points: usize) -> Option<u64> {
        match self.body {
            Body::Binary { count, .. } => Some(count.div_ceil(block_points.max(1) as u64)),
            Body::AsciiPly { .. } | Body::Xyz => None,
        }
    }

    /// Reads block `index` of [`random_access_blocks`](Self::random_access_blocks) into
    /// `block` (replacing what it held): the records [`for_each_block`](Self::for_each_block)
    /// hands over as its block `index`, with the same errors.
    pub fn read_block(&self, block_points: usize, index: u64, block: &mut Vec<u8>) -> Result<(), InputError> {
        let Body::Binary {
            offset,
            count,
            big_endian,
        } = self.body
        else {
            return Err(bad(&self.path, "a text file is read in order, not by blocks"));
        };
        let len = self.layout.record_len();
        let first = index.saturating_mul(block_points.max(1) as u64);
        let records = count.saturating_sub(first).min(block_points.max(1) as u64);
        let io = |e| InputError::Io {
            file: self.path.clone(),
            source: e,
        };
        block.resize(records as usize * len, 0);
        // Each block opens the file on its own: no cursor is shared between the threads.
        let mut file = File::open(&self.path).map_err(io)?;
        file.seek(SeekFrom::Start(offset + first * len as u64)).map_err(io)?;
        file.read_exact(block).map_err(io)?;
        if big_endian {
            self.swap_to_little_endian(block);
        }
        self.check_finite(block, first)
    }

    /// An error naming the first record of `block` (the file's record `first` onwards) whose
    /// position is not finite.
    fn check_finite(&self, block: &[u8], first: u64) -> Result<(), InputError> {
        let len = self.layout.record_len().max(1);
        match block
            .chunks_exact(len)
            .position(|record| self.layout.position(record).iter().any(|c| !c.is_finite()))
        {
            Some(i) => Err(bad(
                &self.path,
                format!("point {} has a position that is not finite", first + i as u64),
            )),
            None => Ok(()),
        }
    }

    fn swap_to_little_endian(&self, block: &mut [u8]) {
        for record in block.chunks_exact_mut(self.layout.record_len()) {
            for (offset, (_, scalar)) in self.layout.offsets.iter().zip(&self.layout.properties) {
                if let Some(value) = record.get_mut(*offset..*offset + scalar.size()) {
                    value.reverse();
                }
            }
        }
    }

    /// Lines of an ASCII PLY's header, `end_header` included.
    fn ascii_header_lines(&self) -> Result<u64, InputError> {
        let mut head = Vec::new();
        File::open(&self.path)
            .and_then(|f| f.take(MAX_HEADER_BYTES).read_to_end(&mut head))
            .map_err(|e| InputError::Io {
                file: self.path.clone(),
                source: e,
            })?;
        let header = parse_ply_header(&head).map_err(|problem| bad(&self.path, problem))?;
        let header_bytes = head.get(..header.body_offset).unwrap_or_default();
        Ok(header_bytes.iter().filter(|b| **b == b'\n').count() as u64)
    }

    /// Appends the record of one text line (line `number`, for errors) to `block`.
    fn parse_line(&self, line: &str, number: u64, block: &mut Vec<u8>) -> Result<(), InputError> {
        let start = block.len();
        block.resize(start + self.layout.record_len(), 0);
        let record = block.get_mut(start..).unwrap_or_default();
        let mut tokens = line
            .split(|c: char| c.is_whitespace() || c == ',')
            .filter(|t| !t.is_empty());
        for (offset, (name, scalar)) in self.layout.offsets.iter().zip(&self.layout.properties) {
            let token = tokens
                .next()
                .ok_or_else(|| bad(&self.path, format!("line {number}: no value for '{name}'")))?;
            let value: f64 = token
                .parse()
                .map_err(|_| bad(&self.path, format!("line {number}: '{token}' is not a number")))?;
            scalar
                .write_le(value, record.get_mut(*offset..).unwrap_or_default())
                .ok_or_else(|| {
                    bad(
                        &self.path,
                        format!("line {number}: {value} does not fit '{name}' ({})", scalar.name()),
                    )
                })?;
        }
        if tokens.next().is_some() {
            return Err(bad(
                &self.path,
                format!("line {number}: more than {} values", self.layout.properties.len()),
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn records(file: &PointCloudFile) -> Result<Vec<[f64; 3]>, InputError> {
        let mut out = Vec::new();
        file.for_each_block::<InputError>(2, |block| {
            out.extend(
                block
                    .chunks_exact(file.layout().record_len())
                    .map(|r| file.layout().position(r)),
            );
            Ok(())
        })?;
        Ok(out)
    }

    #[test]
    fn ply_and_xyz_files_give_the_same_points_and_bad_ones_name_the_problem() -> Result<(), InputError> {
        let dir = tempfile::tempdir().map_err(|e| bad(Path::new("."), e.to_string()))?;
        let write = |name: &str, bytes: &[u8]| {
            let path = dir.path().join(name);
            std::fs::write(&path, bytes).map(|()| path)
        };
        let io = |e: std::io::Error| bad(Path::new("."), e.to_string());
        let expected = vec![[0.0, 1.0, 2.0], [3.0, 4.0, 5.5], [-1.0, 0.25, 8.0]];
        let ascii = write(
            "a.ply",
            b"ply\nformat ascii 1.0\nelement camera 1\nproperty float f\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nend_header\n7\n0 1 2 255\n3 4 5.5 0\n-1 0.25 8 9\n",
        )
        .map_err(io)?;
        assert_eq!(records(&open_point_cloud(&ascii)?)?, expected);
        let mut big = b"ply\nformat binary_big_endian 1.0\nelement vertex 3\nproperty double z\nproperty float x\nproperty float y\nend_header\n".to_vec();
        for p in &expected {
            big.extend(p[2].to_be_bytes());
            big.extend((p[0] as f32).to_be_bytes());
            big.extend((p[1] as f32).to_be_bytes());
        }
        let binary = write("b.ply", &big).map_err(io)?;
        let file = open_point_cloud(&binary)?;
        assert_eq!(file.announced_points(), Some(3));
        assert_eq!(records(&file)?, expected);
        let xyz = write(
            "c.xyz",
            b"# a comment\n0 1 2 0 0 1 1 2 3\n\n3,4,5.5,0,0,1,4,5,6\n-1 0.25 8 0 0 1 7 8 9\n",
        )
        .map_err(io)?;
        let file = open_point_cloud(&xyz)?;
        assert_eq!(file.layout().record_len(), 3 * 8 + 3 * 4 + 3);
        assert_eq!(records(&file)?, expected);

        let truncated = write("t.ply", big.get(..big.len() - 3).unwrap_or_default()).map_err(io)?;
        let message = open_point_cloud(&truncated).map(|_| ()).unwrap_err().to_string();
        assert!(message.contains("t.ply") && message.contains("truncated"), "{message}");
        let no_z = write(
            "n.ply",
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 2\n",
        )
        .map_err(io)?;
        let message = open_point_cloud(&no_z).map(|_| ()).unwrap_err().to_string();
        assert!(message.contains("n.ply") && message.contains("'z'"), "{message}");
        let short = write("s.ply", b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n1 2 3\n").map_err(io)?;
        let message = records(&open_point_cloud(&short)?).map(|_| ()).unwrap_err().to_string();
        assert!(message.contains("s.ply") && message.contains("1 of 2"), "{message}");
        let words = write("w.txt", b"1 2 3\n4 five 6\n").map_err(io)?;
        let message = records(&open_point_cloud(&words)?).map(|_| ()).unwrap_err().to_string();
        assert!(
            message.contains("w.txt") && message.contains("line 2") && message.contains("five"),
            "{message}"
        );
        let nan = write("nan.xyz", b"1 2 3\nnan 1 1\n").map_err(io)?;
        let message = records(&open_point_cloud(&nan)?).map(|_| ()).unwrap_err().to_string();
        assert!(
            message.contains("point 1") && message.contains("not finite"),
            "{message}"
        );
        let four = write("f.xyz", b"1 2 3 4\n").map_err(io)?;
        let message = open_point_cloud(&four).map(|_| ()).unwrap_err().to_string();
        assert!(message.contains("line 1") && message.contains("4 numbers"), "{message}");
        Ok(())
    }

    /// The run decoder's fast paths (float x, y, z alone; floats among other properties or out
    /// of order; doubles) give what the general decoder gives, record by record, across runs.
    #[test]
    fn run_decoding_agrees_with_the_record_decoder() -> Result<(), String> {
        let layouts = [
            vec![("x", PlyScalar::F32), ("y", PlyScalar::F32), ("z", PlyScalar::F32)],
            vec![("y", PlyScalar::F32), ("x", PlyScalar::F32), ("z", PlyScalar::F32)],
            vec![
                ("x", PlyScalar::F32),
                ("y", PlyScalar::F32),
                ("z", PlyScalar::F32),
                ("k", PlyScalar::U8),
            ],
            vec![("x", PlyScalar::F64), ("y", PlyScalar::F64), ("z", PlyScalar::F64)],
            vec![("x", PlyScalar::F64), ("y", PlyScalar::F32), ("z", PlyScalar::I32)],
        ];
        for properties in layouts {
            let layout = PointLayout::new(properties.iter().map(|(n, s)| (n.to_string(), *s)).collect())?;
            // 2500 records: two whole runs and part of a third; bytes that give odd values.
            let block: Vec<u8> = (0..2500 * layout.record_len())
                .map(|i| (i * 37 % 251) as u8 ^ 0x3C)
                .collect();
            let mut decoded = Vec::new();
            layout.for_each_positions(&block, |first, positions| {
                assert_eq!(first, decoded.len());
                decoded.extend_from_slice(positions);
            });
            let expected: Vec<[f64; 3]> = block
                .chunks_exact(layout.record_len())
                .map(|r| layout.position(r))
                .collect();
            assert_eq!(decoded.len(), expected.len());
            for (d, e) in decoded.iter().zip(&expected) {
                assert_eq!(d.map(f64::to_bits), e.map(f64::to_bits), "{properties:?}");
            }
        }
        Ok(())
    }

    /// Binary files are read by blocks on any thread: each block must be the one the ordered
    /// reader hands over, and a bad point must be named by its number in the file.
    #[test]
    fn blocks_read_by_number_are_the_ordered_readers_blocks() -> Result<(), InputError> {
        let dir = tempfile::tempdir().map_err(|e| bad(Path::new("."), e.to_string()))?;
        let io = |e: std::io::Error| bad(Path::new("."), e.to_string());
        let points: Vec<[f64; 3]> = (0..11)
            .map(|i| [f64::from(i), 0.5 * f64::from(i), -f64::from(i)])
            .collect();
        for (name, format) in [("le.ply", "binary_little_endian"), ("be.ply", "binary_big_endian")] {
            let mut bytes = format!("ply\nformat {format} 1.0\nelement vertex 11\nproperty uchar k\nproperty double x\nproperty float y\nproperty double z\nend_header\n").into_bytes();
            for (k, p) in points.iter().enumerate() {
                bytes.push(k as u8);
                let big = format == "binary_big_endian";
                bytes.extend(if big { p[0].to_be_bytes() } else { p[0].to_le_bytes() });
                bytes.extend(if big {
                    (p[1] as f32).to_be_bytes()
                } else {
                    (p[1] as f32).to_le_bytes()
                });
                bytes.extend(if big { p[2].to_be_bytes() } else { p[2].to_le_bytes() });
            }
            let path = dir.path().join(name);
            std::fs::write(&path, &bytes).map_err(io)?;
            let file = open_point_cloud(&path)?;
            let mut ordered = Vec::new();
            file.for_each_block::<InputError>(4, |block| {
                ordered.push(block.to_vec());
                Ok(())
            })?;
            assert_eq!(file.random_access_blocks(4), Some(3));
            let mut block = vec![7u8; 100];
            for (index, expected) in ordered.iter().enumerate().rev() {
                file.read_block(4, index as u64, &mut block)?;
                assert_eq!(&block, expected, "{name}, block {index}");
            }
            let mut decoded = Vec::new();
            file.layout()
                .for_each_positions(ordered.concat().as_slice(), |first, positions| {
                    assert_eq!(first, decoded.len());
                    decoded.extend_from_slice(positions);
                });
            assert_eq!(decoded, points, "{name}");

            // Point 9 (block 2) becomes NaN: x's first byte in either order sets the exponent.
            let at = bytes.len() - 2 * 21 + 1;
            if let Some(b) = bytes.get_mut(at..at + 8) {
                b.copy_from_slice(&if format == "binary_big_endian" {
                    f64::NAN.to_be_bytes()
                } else {
                    f64::NAN.to_le_bytes()
                });
            }
            std::fs::write(&path, &bytes).map_err(io)?;
            let file = open_point_cloud(&path)?;
            file.read_block(4, 1, &mut block)?;
            let message = file.read_block(4, 2, &mut block).map(|_| ()).unwrap_err().to_string();
            assert!(
                message.contains(name) && message.contains("point 9") && message.contains("not finite"),
                "{message}"
            );
            let message = file
                .for_each_block::<InputError>(4, |_| Ok(()))
                .map(|_| ())
                .unwrap_err()
                .to_string();
            assert!(message.contains(name) && message.contains("point 9"), "{message}");
        }
        let xyz = dir.path().join("c.xyz");
        std::fs::write(&xyz, b"1 2 3\n").map_err(io)?;
        assert_eq!(open_point_cloud(&xyz)?.random_access_blocks(4), None);
        Ok(())
    }
}
