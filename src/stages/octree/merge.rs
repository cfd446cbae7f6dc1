//! The octree's first step: merging every ingest run into one sorted list of the requested
//! cubes with their radius statistics summed (paper 4.1), split by key range over the
//! workers, and grouped into scratch runs first where more runs than memory allows would be
//! open at once.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use rayon::prelude::*;

use super::OCTREE;
use super::external_sort::{self, CubeRecord, LoserTree, RecordReader, RecordWriter};
use crate::format::segment::SegmentDirectory;
use crate::format::{ColumnValues, CubeKey};
use crate::stages::INGEST;
use crate::stages::ingest::SPIKE_COUNT;
use crate::store::StageError;
use crate::store::catalog;
use crate::store::{Result, SegmentChunks, Snapshot, StoreError};

/// An ingest run with its directory, parsed once per merge that reads it: cursors read the
/// chunks they decode with positioned reads. Mapping, parsing and unmapping the run for every block
/// (RedKitchen's 1000 runs hold 66,000) cost the merge a sixth of its time in TLB shootdowns,
/// parsing and directory checksums.
struct IndexedRun {
    path: PathBuf,
    directory: SegmentDirectory,
    /// Runs ingested before spikes were counted lack the column: no sample counts as one.
    spikes: bool,
}

impl IndexedRun {
    fn open(path: PathBuf, record: &catalog::SegmentRecord) -> Result<IndexedRun> {
        let file = crate::store::SegmentFile::open(path.clone(), record)?;
        let reader = file.reader()?;
        Ok(IndexedRun {
            spikes: reader.column(SPIKE_COUNT).is_ok(),
            directory: reader.directory(),
            path,
        })
    }
}

/// Streams one ingest run block by block, holding one decoded block.
struct RunCursor<'a> {
    run: &'a IndexedRun,
    file: SegmentChunks,
    chunk: Vec<u8>,
    block: usize,
    buffer: Vec<CubeRecord>,
    position: usize,
}

impl<'a> RunCursor<'a> {
    /// The run's records from the first whose key is not below `from`.
    fn open(run: &'a IndexedRun, from: Option<CubeKey>) -> Result<RunCursor<'a>> {
        let mut cursor = RunCursor {
            run,
            file: SegmentChunks::open(run.path.clone())?,
            chunk: Vec::new(),
            block: from.map_or(0, |key| run.directory.first_block_reaching(key)),
            buffer: Vec::new(),
            position: 0,
        };
        cursor.load_block()?;
        if let Some(key) = from {
            // The block's last key is not below `key`, so the position stays inside it.
            cursor.position = cursor.buffer.partition_point(|r| r.key < key);
        }
        Ok(cursor)
    }

    fn load_block(&mut self) -> Result<()> {
        self.buffer.clear();
        self.position = 0;
        if self.block >= self.run.directory.block_count() {
            return Ok(());
        }
        let mut read = |name: &str| {
            self.file
                .decode_block(&self.run.directory, name, self.block, &mut self.chunk)
        };
        let (keys, sums, counts) = (read("key")?, read("radius_sum")?, read("radius_count")?);
        let spikes = if self.run.spikes {
            read(SPIKE_COUNT)?
        } else {
            ColumnValues::U32(vec![0; counts.len()])
        };
        match (keys, sums, counts, spikes) {
            (ColumnValues::Key(k), ColumnValues::U64(s), ColumnValues::U32(c), ColumnValues::U32(sp))
                if k.len() == s.len() && k.len() == c.len() && k.len() == sp.len() =>
            {
                self.buffer.extend(
                    k.into_iter()
                        .zip(s)
                        .zip(c)
                        .zip(sp)
                        .map(|(((k, s), c), sp)| CubeRecord::new(k, s, c, sp)),
                );
            }
            _ => {
                return Err(self.file.corruption(crate::format::DecodeError::MissingColumn(
                    "radius_sum (u64) / radius_count (u32) / spike_count (u32) of an ingest run".into(),
                )));
            }
        }
        Ok(())
    }

    fn peek(&self) -> Option<CubeRecord> {
        self.buffer.get(self.position).copied()
    }

    fn advance(&mut self) -> Result<()> {
        self.position += 1;
        if self.position >= self.buffer.len() {
            self.block += 1;
            self.load_block()?;
        }
        Ok(())
    }
}

/// Runs merged at once. Each open ingest run holds one decoded block (1024 records, 32 KiB)
/// and its compressed chunk, and each scratch run a 64 KiB read buffer, so a merge holds a few
/// MiB however many depth maps there are. More runs at once would mean fewer rounds, but
/// their blocks would leave the caches: RedKitchen's 1000 runs merged in 3.8 s all at once,
/// 2.8 s 256 at a time, 2.6 s by 128 and 2.4 to 2.6 s by 64.
pub const MERGE_FAN_IN: usize = 64;
const SCRATCH_READ_BUFFER: usize = 64 << 10;

/// A sorted run of cube records, as merge rounds pass them on: an ingest segment or a scratch
/// file of an earlier round. Only the runs of one merge are opened at a time, so however many
/// depth maps there are, their directories are never all held.
enum PendingRun {
    Ingest(PathBuf, catalog::SegmentRecord),
    Scratch(PathBuf),
}

impl PendingRun {
    fn open(&self) -> Result<OpenRun> {
        Ok(match self {
            PendingRun::Ingest(path, record) => OpenRun::Ingest(IndexedRun::open(path.clone(), record)?),
            PendingRun::Scratch(path) => OpenRun::Scratch(path.clone()),
        })
    }
}

/// A run of a merge: an ingest run with its directory, or a scratch run.
enum OpenRun {
    Ingest(IndexedRun),
    Scratch(PathBuf),
}

impl OpenRun {
    /// Keys of the run at about even steps: an ingest run's block first keys, a scratch
    /// run's every 1/[`SCRATCH_KEY_SAMPLES`]th record.
    fn sample_keys(&self) -> Result<Vec<CubeKey>> {
        match self {
            OpenRun::Ingest(run) => Ok((0..run.directory.block_count())
                .filter_map(|b| run.directory.block_key_range(b))
                .map(|(first, _)| first)
                .collect()),
            OpenRun::Scratch(path) => {
                let records = external_sort::record_count::<CubeRecord>(path)?;
                (0..SCRATCH_KEY_SAMPLES)
                    .map(|k| k * records / SCRATCH_KEY_SAMPLES)
                    .map(|index| {
                        let mut reader = RecordReader::<CubeRecord>::open_buffered(path, index, 1, 64)?;
                        Ok(reader.next_record()?.map(|r| r.key))
                    })
                    .filter_map(Result::transpose)
                    .collect()
            }
        }
    }
}

/// Keys read from each scratch run to split the last round by key range.
const SCRATCH_KEY_SAMPLES: u64 = 64;

enum RunReader<'a> {
    Segment(RunCursor<'a>),
    Scratch {
        path: PathBuf,
        reader: RecordReader<CubeRecord>,
        head: Option<CubeRecord>,
    },
}

impl<'a> RunReader<'a> {
    /// The run's records from the first whose key is not below `from`.
    fn open(run: &'a OpenRun, from: Option<CubeKey>) -> Result<RunReader<'a>> {
        Ok(match run {
            OpenRun::Ingest(run) => RunReader::Segment(RunCursor::open(run, from)?),
            OpenRun::Scratch(path) => {
                let first = match from {
                    Some(key) => external_sort::partition_point(path, |r: &CubeRecord| r.key < key)?,
                    None => 0,
                };
                let mut reader = RecordReader::open_buffered(path, first, u64::MAX, SCRATCH_READ_BUFFER)?;
                let head = reader.next_record()?;
                RunReader::Scratch {
                    path: path.clone(),
                    reader,
                    head,
                }
            }
        })
    }

    fn peek(&self) -> Option<CubeRecord> {
        match self {
            RunReader::Segment(cursor) => cursor.peek(),
            RunReader::Scratch { head, .. } => *head,
        }
    }

    fn advance(&mut self) -> Result<()> {
        match self {
            RunReader::Segment(cursor) => cursor.advance(),
            RunReader::Scratch { reader, head, .. } => {
                *head = reader.next_record()?;
                Ok(())
            }
        }
    }

    fn path(&self) -> &Path {
        match self {
            RunReader::Segment(cursor) => &cursor.run.path,
            RunReader::Scratch { path, .. } => path,
        }
    }
}

/// k-way merge of sorted runs over the keys in `from..to` (unbounded where `None`): every
/// distinct key once, in order, with the radius statistics of all its occurrences summed.
fn merge_sorted(
    runs: &[OpenRun],
    (from, to): (Option<CubeKey>, Option<CubeKey>),
    mut emit: impl FnMut(CubeRecord) -> Result<()>,
) -> Result<()> {
    let in_range = |r: &CubeRecord| to.is_none_or(|to| r.key < to);
    let mut readers: Vec<RunReader> = runs
        .iter()
        .map(|run| RunReader::open(run, from))
        .collect::<Result<_>>()?;
    let malformed = |reader: &RunReader, key: CubeKey| StoreError::Stage {
        stage: OCTREE.into(),
        unit: reader.path().display().to_string(),
        error: Box::new(StageError::internal(format!("a run holds the malformed key {key:?}"))),
    };
    let mut heads: Vec<Option<CubeKey>> = Vec::with_capacity(readers.len());
    for reader in &readers {
        let head = reader.peek().filter(in_range).map(|r| r.key);
        if let Some(key) = head.filter(|k| !LoserTree::takes(*k)) {
            return Err(malformed(reader, key));
        }
        heads.push(head);
    }
    let mut tree = LoserTree::new(&heads);
    let mut current: Option<CubeRecord> = None;
    while let Some((index, key)) = tree.winner() {
        let Some(reader) = readers.get_mut(index) else { break };
        let Some(record) = reader.peek() else { break };
        match current.as_mut() {
            Some(c) if c.key == key => {
                c.radius_sum += record.radius_sum;
                c.radius_count += record.radius_count;
                c.spike_count += record.spike_count;
            }
            _ => {
                if let Some(done) = current.replace(record) {
                    emit(done)?;
                }
            }
        }
        reader.advance()?;
        let next = reader.peek();
        if next.is_some_and(|next| next.key <= key) {
            return Err(StoreError::Stage {
                stage: OCTREE.into(),
                unit: reader.path().display().to_string(),
                error: Box::new(StageError::internal("run keys are not increasing")),
            });
        }
        let head = next.filter(in_range).map(|r| r.key);
        if let Some(key) = head.filter(|k| !LoserTree::takes(*k)) {
            return Err(malformed(reader, key));
        }
        tree.replace_winner(head);
    }
    if let Some(done) = current.take() {
        emit(done)?;
    }
    Ok(())
}

/// Keys that split the runs' records into about `ranges` key ranges of similar size: their
/// [`sample keys`](OpenRun::sample_keys) at even steps. A key's records all fall in one range,
/// so the ranges merge independently and in parallel; where they split changes only the time.
fn key_splitters(runs: &[OpenRun], ranges: usize) -> Result<Vec<CubeKey>> {
    let mut samples = Vec::new();
    for run in runs {
        samples.extend(run.sample_keys()?);
    }
    samples.sort_unstable();
    let mut splitters: Vec<CubeKey> = (1..ranges)
        .filter_map(|k| samples.get(k * samples.len() / ranges).copied())
        .collect();
    splitters.dedup();
    Ok(splitters)
}

/// Removes the scratch files among `runs`.
fn remove_scratch_runs(runs: &[PendingRun]) -> Result<()> {
    for run in runs {
        if let PendingRun::Scratch(path) = run {
            std::fs::remove_file(path).map_err(crate::store::io_error("remove", path))?;
        }
    }
    Ok(())
}

/// Merges the ingest runs into per-depth request files; returns the requested cube count.
/// At most [`MERGE_FAN_IN`] runs are open at once per worker: more are first merged group by
/// group into scratch runs, so memory does not grow with the number of depth maps. The
/// last round is split by key range over the workers, each range into its own scratch
/// file, read back in key order. Radius sums are integers, so neither the grouping nor the
/// ranges change a single bit of the result.
pub(super) fn merge_runs(
    base: &Snapshot<'_>,
    scratch: &Path,
    request_files: &mut BTreeMap<u8, (PathBuf, RecordWriter<CubeRecord>)>,
) -> Result<u64> {
    let threads = rayon::current_num_threads().max(1);
    let mut runs: Vec<PendingRun> = base
        .segments(INGEST)
        .iter()
        .map(|(name, record)| PendingRun::Ingest(base.store().segment_path(name), record.clone()))
        .collect();
    let mut round = 0;
    while runs.len() > MERGE_FAN_IN {
        // Groups are independent: merge them in parallel, collecting the outputs in group
        // order, so the next round is the same whatever the threads.
        let groups: Vec<&[PendingRun]> = runs.chunks(MERGE_FAN_IN).collect();
        let merged: Vec<PendingRun> = groups
            .par_iter()
            .enumerate()
            .map(|(index, group)| {
                let group: Vec<OpenRun> = group.iter().map(PendingRun::open).collect::<Result<_>>()?;
                let path = scratch.join(format!("merge-{round}-{index:05}.bin"));
                let mut writer = RecordWriter::create(&path)?;
                merge_sorted(&group, (None, None), |record| writer.push(&record))?;
                writer.finish()?;
                Ok(PendingRun::Scratch(path))
            })
            .collect::<Result<_>>()?;
        remove_scratch_runs(&runs)?;
        runs = merged;
        round += 1;
    }
    let open: Vec<OpenRun> = runs.par_iter().map(PendingRun::open).collect::<Result<_>>()?;
    let splitters = key_splitters(&open, 4 * threads)?;
    let bounds: Vec<(Option<CubeKey>, Option<CubeKey>)> = (0..=splitters.len())
        .map(|k| {
            (
                k.checked_sub(1).and_then(|k| splitters.get(k)).copied(),
                splitters.get(k).copied(),
            )
        })
        .collect();
    let ranges: Vec<PathBuf> = bounds
        .par_iter()
        .enumerate()
        .map(|(index, range)| {
            let path = scratch.join(format!("merge-range-{index:05}.bin"));
            let mut writer = RecordWriter::create(&path)?;
            merge_sorted(&open, *range, |record| writer.push(&record))?;
            writer.finish()?;
            Ok(path)
        })
        .collect::<Result<_>>()?;
    drop(open);
    remove_scratch_runs(&runs)?;
    let mut requested = 0u64;
    for path in ranges {
        let mut reader = RecordReader::<CubeRecord>::open(&path)?;
        while let Some(record) = reader.next_record()? {
            requested += 1;
            let depth = record.key.depth();
            if let std::collections::btree_map::Entry::Vacant(e) = request_files.entry(depth) {
                let path = scratch.join(format!("requests-{depth:02}.bin"));
                let writer = RecordWriter::create(&path)?;
                e.insert((path, writer));
            }
            if let Some((_, writer)) = request_files.get_mut(&depth) {
                writer.push(&record)?;
            }
        }
        std::fs::remove_file(&path).map_err(crate::store::io_error("remove", &path))?;
    }
    Ok(requested)
}
