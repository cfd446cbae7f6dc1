//! The files a division writes: binary little-endian PLYs of point records whose header has a
//! fixed length (a padding comment absorbs the digits of the vertex count), so points are
//! appended as they stream in and the count is written in place at the end; each file is a
//! standard PLY that any reader opens.

use std::fs::{File, OpenOptions};
use std::io::{Seek, SeekFrom, Write};
use std::path::PathBuf;

use crate::inputs::PointLayout;

/// Digits of the largest vertex count.
const COUNT_DIGITS: usize = 20;

/// The header of a file of `count` records of `layout`, always of the same length for one
/// layout and note.
pub fn fixed_header(layout: &PointLayout, count: u64, note: &str) -> Vec<u8> {
    let digits = count.to_string().len();
    let padding = " ".repeat(COUNT_DIGITS.saturating_sub(digits));
    format!(
        "ply\nformat binary_little_endian 1.0\ncomment octstore divide: {note}\nelement vertex {count}\n{}comment{padding}\nend_header\n",
        layout.ply_properties()
    )
    .into_bytes()
}

/// Output files filled by appends in the order of the calls: each file's records wait in
/// memory until they pass its share of `buffer_limit`, then go to the file. A buffer keeps
/// its capacity between writes (no page faults on every refill), so the buffers take at most
/// twice the limit.
pub struct Appenders {
    layout: PointLayout,
    paths: Vec<PathBuf>,
    notes: Vec<String>,
    buffers: Vec<Vec<u8>>,
    records: Vec<u64>,
    created: Vec<bool>,
    share: usize,
}

/// The least a buffer holds before it is written: smaller writes cost more in system calls
/// than they save in memory.
const MIN_SHARE: usize = 64 << 10;

impl Appenders {
    /// One appender per path, each with the note its header carries.
    pub fn new(layout: PointLayout, files: Vec<(PathBuf, String)>, buffer_limit: usize) -> Appenders {
        let n = files.len();
        let (paths, notes) = files.into_iter().unzip();
        Appenders {
            layout,
            paths,
            notes,
            buffers: vec![Vec::new(); n],
            records: vec![0; n],
            created: vec![false; n],
            share: (buffer_limit / n.max(1)).max(MIN_SHARE),
        }
    }

    /// Appends whole records to file `target`.
    pub fn append(&mut self, target: usize, records: &[u8]) -> std::io::Result<()> {
        let Some(buffer) = self.buffers.get_mut(target) else {
            return Err(std::io::Error::other(format!("no output file {target}")));
        };
        buffer.extend_from_slice(records);
        let full = buffer.len() >= self.share;
        if let Some(r) = self.records.get_mut(target) {
            *r += (records.len() / self.layout.record_len().max(1)) as u64;
        }
        if full {
            self.write(target)?;
        }
        Ok(())
    }

    /// Writes file `target`'s waiting records.
    fn write(&mut self, target: usize) -> std::io::Result<()> {
        let (Some(buffer), Some(path), Some(created), Some(note)) = (
            self.buffers.get_mut(target),
            self.paths.get(target),
            self.created.get_mut(target),
            self.notes.get(target),
        ) else {
            return Ok(());
        };
        if buffer.is_empty() {
            return Ok(());
        }
        let mut file = if *created {
            OpenOptions::new().append(true).open(path)?
        } else {
            let mut file = File::create(path)?;
            file.write_all(&fixed_header(&self.layout, 0, note))?;
            *created = true;
            file
        };
        file.write_all(buffer)?;
        buffer.clear();
        Ok(())
    }

    /// Writes what waits, sets each file's vertex count, syncs them, and returns the counts.
    /// A file that received no record is created with an empty body.
    pub fn finish(mut self) -> std::io::Result<Vec<u64>> {
        for target in 0..self.buffers.len() {
            self.write(target)?;
        }
        for ((path, note), (records, created)) in self
            .paths
            .iter()
            .zip(&self.notes)
            .zip(self.records.iter().zip(&self.created))
        {
            let mut file = if *created {
                OpenOptions::new().write(true).open(path)?
            } else {
                File::create(path)?
            };
            file.seek(SeekFrom::Start(0))?;
            file.write_all(&fixed_header(&self.layout, *records, note))?;
            file.sync_all()?;
        }
        Ok(self.records)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::format::ply_header::PlyScalar;
    use crate::inputs::open_point_cloud;

    #[test]
    fn appended_files_are_plys_with_their_count() -> Result<(), Box<dyn std::error::Error>> {
        let layout = PointLayout::new(vec![
            ("x".into(), PlyScalar::F32),
            ("y".into(), PlyScalar::F32),
            ("z".into(), PlyScalar::F32),
            ("red".into(), PlyScalar::U8),
        ])?;
        assert_eq!(
            fixed_header(&layout, 0, "n").len(),
            fixed_header(&layout, u64::MAX, "n").len()
        );
        let dir = tempfile::tempdir()?;
        let files = vec![
            (dir.path().join("a.ply"), "a".to_string()),
            (dir.path().join("b.ply"), "b".to_string()),
        ];
        let mut appenders = Appenders::new(layout.clone(), files, 20);
        let record = |x: f32| {
            let mut r = Vec::new();
            for v in [x, 1.0, 2.0] {
                r.extend(v.to_le_bytes());
            }
            r.push(7);
            r
        };
        for i in 0..10 {
            appenders.append(i % 2, &record(i as f32))?;
        }
        assert_eq!(appenders.finish()?, vec![5, 5]);
        let file = open_point_cloud(&dir.path().join("b.ply"))?;
        assert_eq!(file.announced_points(), Some(5));
        assert_eq!(file.layout(), &layout);
        let mut xs = Vec::new();
        file.for_each_block::<crate::inputs::InputError>(3, |block| {
            xs.extend(block.chunks_exact(13).map(|r| layout.position(r)[0]));
            Ok(())
        })?;
        assert_eq!(xs, vec![1.0, 3.0, 5.0, 7.0, 9.0]);
        Ok(())
    }
}
