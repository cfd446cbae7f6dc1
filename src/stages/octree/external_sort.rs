//! Fixed-size record files and an external sorter: the out-of-core building blocks of stages.
//! Scratch files live in the store's `tmp/` folder and are never part of a version.

use std::cmp::Reverse;
use std::collections::BinaryHeap;
use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Seek, SeekFrom, Write};
use std::marker::PhantomData;
use std::path::{Path, PathBuf};

use bytemuck::{Pod, Zeroable};

use crate::format::CubeKey;
use crate::store::{Result, io_error};

/// A cube with its radius statistics; the record of request and node files.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Pod, Zeroable)]
#[repr(C)]
pub struct CubeRecord {
    pub key: CubeKey,
    pub radius_sum: u64,
    pub radius_count: u32,
    /// How many of the `radius_count` samples were spikes (`stages::ingest`): they spawn the
    /// cube but vouch for no surface in its subtree (`stages::observed::sampled_nodes`).
    pub spike_count: u32,
}

impl CubeRecord {
    pub fn new(key: CubeKey, radius_sum: u64, radius_count: u32, spike_count: u32) -> CubeRecord {
        CubeRecord {
            key,
            radius_sum,
            radius_count,
            spike_count,
        }
    }
}

pub struct RecordWriter<T: Pod> {
    path: PathBuf,
    out: BufWriter<File>,
    count: u64,
    _t: PhantomData<T>,
}

impl<T: Pod> RecordWriter<T> {
    pub fn create(path: &Path) -> Result<Self> {
        let file = File::create(path).map_err(io_error("create", path))?;
        Ok(RecordWriter {
            path: path.to_path_buf(),
            out: BufWriter::with_capacity(1 << 20, file),
            count: 0,
            _t: PhantomData,
        })
    }

    pub fn push(&mut self, value: &T) -> Result<()> {
        self.count += 1;
        self.out
            .write_all(bytemuck::bytes_of(value))
            .map_err(io_error("write", &self.path))
    }

    pub fn finish(mut self) -> Result<u64> {
        self.out.flush().map_err(io_error("write", &self.path))?;
        Ok(self.count)
    }
}

/// Sequential reader of a record file.
pub struct RecordReader<T: Pod> {
    path: PathBuf,
    input: BufReader<File>,
    remaining: u64,
    _t: PhantomData<T>,
}

impl<T: Pod> RecordReader<T> {
    pub fn open(path: &Path) -> Result<Self> {
        RecordReader::open_range(path, 0, u64::MAX)
    }

    /// Records `[first, first + count)` (clamped to the file).
    pub fn open_range(path: &Path, first: u64, count: u64) -> Result<Self> {
        RecordReader::open_buffered(path, first, count, 1 << 20)
    }

    /// As [`RecordReader::open_range`], with a read buffer of `buffer_bytes`.
    pub fn open_buffered(path: &Path, first: u64, count: u64, buffer_bytes: usize) -> Result<Self> {
        let mut file = File::open(path).map_err(io_error("open", path))?;
        let size = size_of::<T>() as u64;
        let len = file.metadata().map_err(io_error("stat", path))?.len() / size;
        file.seek(SeekFrom::Start(first.min(len) * size))
            .map_err(io_error("seek", path))?;
        Ok(RecordReader {
            path: path.to_path_buf(),
            input: BufReader::with_capacity(buffer_bytes, file),
            remaining: count.min(len.saturating_sub(first)),
            _t: PhantomData,
        })
    }

    pub fn next_record(&mut self) -> Result<Option<T>> {
        if self.remaining == 0 {
            return Ok(None);
        }
        let mut value = T::zeroed();
        self.input
            .read_exact(bytemuck::bytes_of_mut(&mut value))
            .map_err(io_error("read", &self.path))?;
        self.remaining -= 1;
        Ok(Some(value))
    }
}

/// Sorts and deduplicates keys with bounded memory: sorted runs spill to disk, then merge.
pub struct KeySorter {
    dir: PathBuf,
    name: String,
    buffer: Vec<CubeKey>,
    capacity: usize,
    runs: Vec<PathBuf>,
}

impl KeySorter {
    pub fn new(dir: &Path, name: &str, memory_bytes: u64) -> KeySorter {
        let capacity = (memory_bytes as usize / size_of::<CubeKey>()).max(1024);
        KeySorter {
            dir: dir.to_path_buf(),
            name: name.to_string(),
            buffer: Vec::new(),
            capacity,
            runs: Vec::new(),
        }
    }

    pub fn push(&mut self, key: CubeKey) -> Result<()> {
        self.buffer.push(key);
        if self.buffer.len() >= self.capacity {
            self.spill()?;
        }
        Ok(())
    }

    fn spill(&mut self) -> Result<()> {
        self.buffer.sort_unstable();
        self.buffer.dedup();
        let path = self.dir.join(format!("{}-run{}.bin", self.name, self.runs.len()));
        let mut writer = RecordWriter::create(&path)?;
        for key in &self.buffer {
            writer.push(key)?;
        }
        writer.finish()?;
        self.buffer.clear();
        self.runs.push(path);
        Ok(())
    }

    /// Writes the sorted, deduplicated keys to `out`; returns how many.
    pub fn finish_into(mut self, out: &Path) -> Result<u64> {
        let mut writer = RecordWriter::<CubeKey>::create(out)?;
        if self.runs.is_empty() {
            self.buffer.sort_unstable();
            self.buffer.dedup();
            for key in &self.buffer {
                writer.push(key)?;
            }
            return writer.finish();
        }
        if !self.buffer.is_empty() {
            self.spill()?;
        }
        let mut readers: Vec<RecordReader<CubeKey>> =
            self.runs.iter().map(|p| RecordReader::open(p)).collect::<Result<_>>()?;
        let mut heap = BinaryHeap::new();
        for (index, reader) in readers.iter_mut().enumerate() {
            if let Some(key) = reader.next_record()? {
                heap.push(Reverse((key, index)));
            }
        }
        let mut last: Option<CubeKey> = None;
        while let Some(Reverse((key, index))) = heap.pop() {
            if last != Some(key) {
                writer.push(&key)?;
                last = Some(key);
            }
            if let Some(next) = readers.get_mut(index).map(|r| r.next_record()).transpose()?.flatten() {
                heap.push(Reverse((next, index)));
            }
        }
        for run in &self.runs {
            let _ = std::fs::remove_file(run);
        }
        writer.finish()
    }
}
