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

/// How many records of `T` the record file at `path` holds.
pub fn record_count<T: Pod>(path: &Path) -> Result<u64> {
    let bytes = std::fs::metadata(path).map_err(io_error("stat", path))?.len();
    Ok(bytes / size_of::<T>() as u64)
}

/// The index of the first record of the record file at `path` for which `below` is false,
/// the file being partitioned by it (every record for which it holds comes first): a binary
/// search of single-record reads.
pub fn partition_point<T: Pod>(path: &Path, mut below: impl FnMut(&T) -> bool) -> Result<u64> {
    let mut file = File::open(path).map_err(io_error("open", path))?;
    let size = size_of::<T>() as u64;
    let (mut low, mut high) = (0, file.metadata().map_err(io_error("stat", path))?.len() / size);
    while low < high {
        let middle = low + (high - low) / 2;
        file.seek(SeekFrom::Start(middle * size))
            .map_err(io_error("seek", path))?;
        let mut value = T::zeroed();
        file.read_exact(bytemuck::bytes_of_mut(&mut value))
            .map_err(io_error("read", path))?;
        if below(&value) {
            low = middle + 1;
        } else {
            high = middle;
        }
    }
    Ok(low)
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

/// A tournament ("loser") tree over the head keys of k sorted sources: which source holds the
/// smallest, in one comparison per level when that source's head moves on, where a binary
/// heap's sift takes two (the heap was a third of the octree merge of RedKitchen's 1000
/// runs). Each entrant is one `u128`, the key above the source index, and a match is a
/// branch-free min and max: which of two runs' keys is smaller is a coin toss that a branch
/// predictor loses. Ties go to the lower source index; an exhausted source sorts after every
/// key.
pub struct LoserTree {
    /// `nodes[0]` is the winner; `nodes[1..k]` the loser of the match at each inner node of a
    /// heap-shaped tree whose leaf `i` sits at `k + i`.
    nodes: Vec<u128>,
}

/// Bits of an entrant below its key: the source index.
const SOURCE_BITS: u32 = 23;
/// An exhausted source's entrant.
const EXHAUSTED: u128 = u128::MAX;

impl LoserTree {
    /// Whether the tree orders `key`: every well-formed key ([`CubeKey::is_well_formed`] keeps
    /// the bits above 104 clear) is.
    pub fn takes(key: CubeKey) -> bool {
        key.raw() >> (128 - SOURCE_BITS) == 0
    }

    fn entrant(source: usize, head: Option<CubeKey>) -> u128 {
        head.filter(|k| Self::takes(*k))
            .map_or(EXHAUSTED, |k| (k.raw() << SOURCE_BITS) | source as u128)
    }

    /// The tree over sources whose heads are `heads` (`None`: exhausted): fewer than 2^23 of
    /// them (merges open 64), heads that it [`takes`](Self::takes).
    pub fn new(heads: &[Option<CubeKey>]) -> LoserTree {
        let k = heads.len();
        // Winners of every subtree, leaves included, bottom up.
        let mut winners: Vec<u128> = vec![EXHAUSTED; 2 * k];
        for (source, head) in heads.iter().enumerate() {
            if let Some(slot) = winners.get_mut(k + source) {
                *slot = Self::entrant(source, *head);
            }
        }
        let mut nodes = vec![EXHAUSTED; k.max(1)];
        for node in (1..k).rev() {
            let a = winners.get(2 * node).copied().unwrap_or(EXHAUSTED);
            let b = winners.get(2 * node + 1).copied().unwrap_or(EXHAUSTED);
            if let (Some(w), Some(l)) = (winners.get_mut(node), nodes.get_mut(node)) {
                *w = a.min(b);
                *l = a.max(b);
            }
        }
        if let (Some(first), Some(top)) = (nodes.first_mut(), winners.get(if k > 1 { 1 } else { k })) {
            *first = *top;
        }
        LoserTree { nodes }
    }

    /// The source with the smallest head and that head; `None` once every source is exhausted.
    pub fn winner(&self) -> Option<(usize, CubeKey)> {
        self.nodes.first().filter(|w| **w != EXHAUSTED).map(|w| {
            (
                (w & ((1 << SOURCE_BITS) - 1)) as usize,
                CubeKey::from_raw(w >> SOURCE_BITS),
            )
        })
    }

    /// The winner's source moved on to `head` (`None`: exhausted; a head the tree does not
    /// [`take`](Self::takes) counts as exhausted): replays its path to the top.
    pub fn replace_winner(&mut self, head: Option<CubeKey>) {
        let Some(source) = self.winner().map(|(source, _)| source) else {
            return;
        };
        let mut entrant = Self::entrant(source, head);
        let mut node = (self.nodes.len() + source) / 2;
        while node >= 1 {
            if let Some(loser) = self.nodes.get_mut(node) {
                let (low, high) = ((*loser).min(entrant), (*loser).max(entrant));
                *loser = high;
                entrant = low;
            }
            node /= 2;
        }
        if let Some(first) = self.nodes.first_mut() {
            *first = entrant;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_loser_tree_merges_as_a_sort_does() {
        for k in [1usize, 2, 3, 5, 8, 13, 32] {
            // Source s holds the keys s, s + 3, s + 6, ... below 200, some sources empty.
            let sources: Vec<Vec<CubeKey>> = (0..k)
                .map(|s| {
                    if s % 4 == 3 {
                        Vec::new()
                    } else {
                        (s as u32..200).step_by(3).map(|x| CubeKey::new(8, x, 0, 0)).collect()
                    }
                })
                .collect();
            let mut positions = vec![0usize; k];
            let heads: Vec<Option<CubeKey>> = sources.iter().map(|s| s.first().copied()).collect();
            let mut tree = LoserTree::new(&heads);
            let mut merged = Vec::new();
            while let Some((source, key)) = tree.winner() {
                merged.push((key, source));
                positions[source] += 1;
                tree.replace_winner(sources[source].get(positions[source]).copied());
            }
            let mut expected: Vec<(CubeKey, usize)> = sources
                .iter()
                .enumerate()
                .flat_map(|(s, keys)| keys.iter().map(move |k| (*k, s)))
                .collect();
            expected.sort();
            assert_eq!(merged, expected, "{k} sources");
        }
    }
}
