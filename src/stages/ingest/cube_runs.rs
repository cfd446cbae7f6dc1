//! One depth map's cubes, merged by key, in bounded memory (format-spec.md, "Ingest runs").
//!
//! Samples' cube entries are summed per cube as they come, in a hash table of at most
//! `capacity` cubes (several samples fall in one cube, so this holds and sorts far less than
//! the entries themselves: sorting every entry took a sixth of RedKitchen's ingest). A map
//! whose cubes fit is sorted by key and written from memory. A larger one writes each full
//! table, sorted, as a run on a scratch file, then merges the runs key by key into a segment
//! spilled to scratch files (`store::SegmentSpill`). Every sum is an integer sum, so the
//! segment's bytes do not depend on where the table was cut, nor on the order of the
//! entries: the store is the same whatever the memory budget.

use std::cmp::Reverse;
use std::collections::BinaryHeap;
use std::fs::File;
use std::io::{BufReader, BufWriter, Read, Seek, SeekFrom, Write};
use std::path::Path;

use super::{RADIUS_SUM, SPIKE_COUNT};
use crate::format::{Column, ColumnShape, ColumnValues, CubeKey};
use crate::stages::samples::{Moments, moment_columns};
use crate::store::{Result, SegmentContent, SegmentSpill, StoreError};

/// Bytes a cube costs in memory while buffered and once merged into columns: its index slot
/// (with a control byte, at the table's 7/8 load), its totals and moments, its place in the
/// sorted order, and its row in the in-memory columns.
pub(super) const BYTES_PER_CUBE: u64 = ((size_of::<(CubeKey, usize)>() + 1) * 8 / 7
    + size_of::<CubeTotals>()
    + size_of::<Moments>()
    + size_of::<(CubeKey, usize)>()
    + 16
    + 8
    + 4
    + 4
    + 7 * 8) as u64;

/// Sample entries per cube the table is first sized for (RedKitchen at `--max-depth 10`: 4.1;
/// the table grows where there are fewer).
const EXPECTED_ENTRIES_PER_CUBE: usize = 4;

/// The per-cube sums being gathered: every cube's totals in the order the cubes first came (and
/// its moments beside them, in runs that carry moments), and each cube's place there by key.
/// An index slot and a cube's totals are 32 bytes each where whole sums were 96, so more of
/// both stays in cache on the lookup every entry makes, and the drain sorts places instead of
/// sums (sorting 96-byte sums was most of a map's drain). The order of the totals is never
/// observed: cubes leave the table sorted by key.
struct SumsTable {
    index: std::collections::HashMap<CubeKey, usize, foldhash::fast::FixedState>,
    totals: Vec<CubeTotals>,
    /// Beside `totals`, when the runs carry moments; else empty.
    moments: Vec<Moments>,
    with_moments: bool,
}

/// A [`CubeSums`] without its moments.
#[derive(Clone, Copy)]
struct CubeTotals {
    key: CubeKey,
    radius_sum: u64,
    count: u32,
    spikes: u32,
}

impl CubeTotals {
    fn with_moments(&self, moments: Moments) -> CubeSums {
        CubeSums {
            key: self.key,
            radius_sum: self.radius_sum,
            count: self.count,
            spikes: self.spikes,
            moments,
        }
    }
}

impl SumsTable {
    fn with_capacity(cubes: usize, with_moments: bool) -> SumsTable {
        SumsTable {
            index: std::collections::HashMap::with_capacity_and_hasher(cubes, foldhash::fast::FixedState::default()),
            totals: Vec::with_capacity(cubes),
            moments: Vec::with_capacity(if with_moments { cubes } else { 0 }),
            with_moments,
        }
    }

    fn len(&self) -> usize {
        self.totals.len()
    }

    fn is_empty(&self) -> bool {
        self.totals.is_empty()
    }

    /// Adds `sums` (with `moments`, in runs that carry them) to its cube's, if the table holds
    /// that cube, and says whether it did.
    fn add_to_existing(&mut self, sums: &CubeTotals, moments: &Moments) -> bool {
        let Some(&at) = self.index.get(&sums.key) else {
            return false;
        };
        if let Some(totals) = self.totals.get_mut(at) {
            totals.radius_sum += sums.radius_sum;
            totals.count += sums.count;
            totals.spikes += sums.spikes;
        }
        if let Some(existing) = self.moments.get_mut(at) {
            existing.add(moments);
        }
        true
    }

    /// Adds a cube the table does not hold.
    fn insert_new(&mut self, sums: CubeTotals, moments: &Moments) {
        self.index.insert(sums.key, self.totals.len());
        self.totals.push(sums);
        if self.with_moments {
            self.moments.push(*moments);
        }
    }

    /// Empties the table into `each` in key order (keys are unique: no two cubes compare
    /// equal), with zero moments in runs without them. The table keeps its memory: a spilling
    /// map holds one table at a time.
    fn drain_in_key_order(&mut self, mut each: impl FnMut(CubeSums) -> Result<()>) -> Result<()> {
        self.index.clear();
        if !self.with_moments {
            // Totals are as small as places: sort them themselves, and read them in order.
            self.totals.sort_unstable_by_key(|totals| totals.key);
            let result = self
                .totals
                .iter()
                .try_for_each(|totals| each(totals.with_moments(Moments::default())));
            self.totals.clear();
            return result;
        }
        let mut order: Vec<(CubeKey, usize)> = self.totals.iter().enumerate().map(|(at, c)| (c.key, at)).collect();
        order.sort_unstable_by_key(|(key, _)| *key);
        let result = order.into_iter().try_for_each(|(_, at)| {
            let Some(totals) = self.totals.get(at) else {
                return Ok(());
            };
            each(totals.with_moments(self.moments.get(at).copied().unwrap_or_default()))
        });
        self.totals.clear();
        self.moments.clear();
        result
    }

    /// Frees the table's memory.
    fn release(&mut self) {
        *self = SumsTable::with_capacity(0, self.with_moments);
    }
}

/// Rows per batch appended to a spilled segment.
const SPILL_BATCH_ROWS: usize = 1 << 16;

/// One cube of a run: the sums of its entries.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct CubeSums {
    key: CubeKey,
    radius_sum: u64,
    count: u32,
    spikes: u32,
    moments: Moments,
}

/// Bytes of a [`CubeSums`] record in a run file (little-endian fields in declaration order).
const RECORD_LEN: usize = 16 + 8 + 4 + 4 + 7 * 8;

impl CubeSums {
    fn add(&mut self, other: &CubeSums) {
        self.radius_sum += other.radius_sum;
        self.count += other.count;
        self.spikes += other.spikes;
        self.moments.add(&other.moments);
    }

    fn encode(&self, out: &mut [u8; RECORD_LEN]) {
        let m = &self.moments;
        let fields = [
            m.weight,
            m.offset[0],
            m.offset[1],
            m.offset[2],
            m.normal[0],
            m.normal[1],
            m.normal[2],
        ];
        let mut bytes = self.key.raw().to_le_bytes().to_vec();
        bytes.extend_from_slice(&self.radius_sum.to_le_bytes());
        bytes.extend_from_slice(&self.count.to_le_bytes());
        bytes.extend_from_slice(&self.spikes.to_le_bytes());
        for f in fields {
            bytes.extend_from_slice(&f.to_le_bytes());
        }
        out.copy_from_slice(&bytes);
    }

    fn decode(bytes: &[u8; RECORD_LEN]) -> CubeSums {
        let mut at = 0usize;
        let mut take = |n: usize| {
            let mut field = [0u8; 16];
            if let (Some(dst), Some(src)) = (field.get_mut(..n), bytes.get(at..at + n)) {
                dst.copy_from_slice(src);
            }
            at += n;
            field
        };
        let key = CubeKey::from_raw(u128::from_le_bytes(take(16)));
        let u64_of = |f: [u8; 16]| u64::from_le_bytes([f[0], f[1], f[2], f[3], f[4], f[5], f[6], f[7]]);
        let u32_of = |f: [u8; 16]| u32::from_le_bytes([f[0], f[1], f[2], f[3]]);
        let radius_sum = u64_of(take(8));
        let count = u32_of(take(4));
        let spikes = u32_of(take(4));
        let mut i = || u64_of(take(8)) as i64;
        let weight = i();
        let offset = [i(), i(), i()];
        let normal = [i(), i(), i()];
        CubeSums {
            key,
            radius_sum,
            count,
            spikes,
            moments: Moments { weight, offset, normal },
        }
    }
}

/// Column builders for cube sums.
#[derive(Default)]
struct CubeColumns {
    /// Whether the run carries the SSD sample moments (the store's `sample_sums` setting).
    with_moments: bool,
    keys: Vec<CubeKey>,
    sums: Vec<u64>,
    counts: Vec<u32>,
    spike_counts: Vec<u32>,
    moments: Vec<Moments>,
}

impl CubeColumns {
    fn push(&mut self, c: CubeSums) {
        self.keys.push(c.key);
        self.sums.push(c.radius_sum);
        self.counts.push(c.count);
        self.spike_counts.push(c.spikes);
        if self.with_moments {
            self.moments.push(c.moments);
        }
    }

    fn len(&self) -> usize {
        self.keys.len()
    }

    fn empty(with_moments: bool) -> CubeColumns {
        CubeColumns {
            with_moments,
            ..CubeColumns::default()
        }
    }

    /// An ingest run's columns (format-spec.md, "Columns used by stages").
    fn into_columns(self) -> Vec<Column> {
        let mut columns = vec![
            Column::keys(self.keys),
            Column::new(RADIUS_SUM, 1, ColumnValues::U64(self.sums)),
            Column::new("radius_count", 1, ColumnValues::U32(self.counts)),
            Column::new(SPIKE_COUNT, 1, ColumnValues::U32(self.spike_counts)),
        ];
        if self.with_moments {
            columns.extend(moment_columns(&self.moments));
        }
        columns
    }
}

fn scratch_error<'a>(dir: &'a Path, action: &'static str) -> impl Fn(std::io::Error) -> StoreError + 'a {
    move |source| StoreError::Io {
        action,
        path: dir.to_path_buf(),
        source,
    }
}

/// A map's cube entries, summed per cube in at most `capacity` cubes of memory.
pub(super) struct CubeRuns<'a> {
    scratch: &'a Path,
    capacity: usize,
    /// Whether the runs' columns carry the entries' moments (they are summed either way).
    with_moments: bool,
    /// The cube of the latest entries, not yet in `table`: a row of pixels falls in one cube
    /// several times in a row, and adding to it here saves a hash lookup each time. Its
    /// moments are apart, in `current_moments` (zero in runs without them): replacing a
    /// 96-byte whole, whose moment fields had just been stored one by one, read them back with
    /// wider loads than the stores and stalled on every new cube of a run without moments.
    current: Option<CubeTotals>,
    current_moments: Moments,
    table: SumsTable,
    /// Sorted, merged runs of earlier full tables.
    runs: Vec<File>,
}

impl<'a> CubeRuns<'a> {
    /// Runs of at most `capacity` cubes; at most `expected` entries are likely (the map's valid
    /// pixels), so the table is sized once for the lesser (grown by doubling, a table costs up
    /// to twice its size, and its moves are paid again). `with_moments`: the segment has the
    /// sample moment columns.
    pub(super) fn new(scratch: &'a Path, capacity: usize, expected: usize, with_moments: bool) -> CubeRuns<'a> {
        let capacity = capacity.max(1);
        CubeRuns {
            scratch,
            capacity,
            with_moments,
            current: None,
            current_moments: Moments::default(),
            table: SumsTable::with_capacity(capacity.min(expected / EXPECTED_ENTRIES_PER_CUBE), with_moments),
            runs: Vec::new(),
        }
    }

    /// Adds one sample's entry. Its fields come as arguments, in registers: an entry built in
    /// memory just before is read back here with wider loads than its fields were stored
    /// with, which stalls each sample.
    pub(super) fn push(&mut self, key: CubeKey, radius_sum: u64, spike: bool, moments: &Moments) -> Result<()> {
        if let Some(current) = &mut self.current
            && current.key == key
        {
            current.radius_sum += radius_sum;
            current.count += 1;
            current.spikes += u32::from(spike);
            // Runs without moment columns are given zero moments: nothing to add.
            if self.with_moments {
                self.current_moments.add(moments);
            }
            return Ok(());
        }
        let totals = CubeTotals {
            key,
            radius_sum,
            count: 1,
            spikes: u32::from(spike),
        };
        let Some(done) = self.current.replace(totals) else {
            self.current_moments = *moments;
            return Ok(());
        };
        if self.with_moments {
            let done_moments = std::mem::replace(&mut self.current_moments, *moments);
            self.add_to_table(done, &done_moments)
        } else {
            self.add_to_table(done, &Moments::default())
        }
    }

    fn add_to_table(&mut self, sums: CubeTotals, moments: &Moments) -> Result<()> {
        if self.table.add_to_existing(&sums, moments) {
            return Ok(());
        }
        if self.table.len() >= self.capacity {
            self.spill()?;
        }
        self.table.insert_new(sums, moments);
        Ok(())
    }

    /// Writes the table as one sorted run, and empties it.
    fn spill(&mut self) -> Result<()> {
        std::fs::create_dir_all(self.scratch).map_err(scratch_error(self.scratch, "create scratch"))?;
        let file =
            tempfile::tempfile_in(self.scratch).map_err(scratch_error(self.scratch, "create scratch file in"))?;
        let mut out = BufWriter::with_capacity(1 << 16, file);
        let mut record = [0u8; RECORD_LEN];
        let error = scratch_error(self.scratch, "write scratch in");
        self.table.drain_in_key_order(|c| {
            c.encode(&mut record);
            out.write_all(&record).map_err(&error)
        })?;
        let mut file = out.into_inner().map_err(|e| error(e.into_error()))?;
        file.seek(SeekFrom::Start(0)).map_err(&error)?;
        self.runs.push(file);
        Ok(())
    }

    /// The map's segment (`None` without cubes) and its cube count.
    pub(super) fn finish(mut self) -> Result<(Option<SegmentContent>, u64)> {
        if let Some(done) = self.current.take() {
            let moments = std::mem::take(&mut self.current_moments);
            self.add_to_table(done, &moments)?;
        }
        if self.runs.is_empty() {
            let mut columns = CubeColumns::empty(self.with_moments);
            self.table.drain_in_key_order(|c| {
                columns.push(c);
                Ok(())
            })?;
            self.table.release();
            let cubes = columns.len() as u64;
            return Ok(((cubes > 0).then(|| columns.into_columns().into()), cubes));
        }
        if !self.table.is_empty() {
            self.spill()?;
        }
        let shapes: Vec<ColumnShape> = CubeColumns::empty(self.with_moments)
            .into_columns()
            .iter()
            .map(ColumnShape::of)
            .collect();
        let mut spill = SegmentSpill::new_in(self.scratch, shapes)?;
        let error = scratch_error(self.scratch, "read scratch in");
        let mut readers: Vec<BufReader<File>> = self
            .runs
            .drain(..)
            .map(|f| BufReader::with_capacity(1 << 16, f))
            .collect();
        let next = |run: usize, readers: &mut [BufReader<File>]| -> Result<Option<CubeSums>> {
            let Some(reader) = readers.get_mut(run) else {
                return Ok(None);
            };
            let mut record = [0u8; RECORD_LEN];
            match reader.read_exact(&mut record) {
                Ok(()) => Ok(Some(CubeSums::decode(&record))),
                Err(e) if e.kind() == std::io::ErrorKind::UnexpectedEof => Ok(None),
                Err(e) => Err(error(e)),
            }
        };
        // Smallest key first; among equal keys, the lower run first (any order sums the same).
        let mut heads: BinaryHeap<Reverse<(CubeKey, usize)>> = BinaryHeap::new();
        let mut pending: Vec<Option<CubeSums>> = Vec::with_capacity(readers.len());
        for run in 0..readers.len() {
            let head = next(run, &mut readers)?;
            if let Some(c) = &head {
                heads.push(Reverse((c.key, run)));
            }
            pending.push(head);
        }
        let mut batch = CubeColumns::empty(self.with_moments);
        let mut current: Option<CubeSums> = None;
        while let Some(Reverse((_, run))) = heads.pop() {
            let Some(c) = pending.get_mut(run).and_then(Option::take) else {
                continue;
            };
            match &mut current {
                Some(cur) if cur.key == c.key => cur.add(&c),
                _ => {
                    if let Some(done) = current.replace(c) {
                        batch.push(done);
                        if batch.len() >= SPILL_BATCH_ROWS {
                            let full = std::mem::replace(&mut batch, CubeColumns::empty(self.with_moments));
                            spill.append(&full.into_columns())?;
                        }
                    }
                }
            }
            let head = next(run, &mut readers)?;
            if let Some(h) = &head {
                heads.push(Reverse((h.key, run)));
            }
            if let Some(slot) = pending.get_mut(run) {
                *slot = head;
            }
        }
        if let Some(done) = current {
            batch.push(done);
        }
        if batch.len() > 0 {
            spill.append(&batch.into_columns())?;
        }
        let cubes = spill.rows();
        Ok(((cubes > 0).then_some(SegmentContent::Spilled(spill)), cubes))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A sample's contribution to its cube: key, quantised radius, spike, SSD moments.
    type Entry = (CubeKey, u64, bool, Moments);

    fn entry(key: u32, radius: u64, spike: bool, weight: i64) -> Entry {
        let moments = Moments {
            weight,
            offset: [weight, -weight, 3],
            normal: [1, 2, -weight],
        };
        (CubeKey::new(10, key, key / 2, 7), radius, spike, moments)
    }

    fn columns_of(content: SegmentContent) -> Vec<Column> {
        let SegmentContent::Columns(columns) = content else {
            panic!("expected columns in memory")
        };
        columns
    }

    /// Spilled runs merge into exactly the columns the in-memory path gives, for any buffer
    /// size (the encoder then writes the same bytes: `store::spill`), with and without the
    /// moment columns.
    #[test]
    fn spilled_runs_sum_to_the_in_memory_columns() {
        let dir = tempfile::tempdir().unwrap();
        let mut state = 3u64;
        let entries: Vec<Entry> = (0..5000)
            .map(|_| {
                let r = crate::kernels::random::splitmix(&mut state);
                entry((r % 700) as u32, r % 1000, r.is_multiple_of(7), (r % 50) as i64 - 20)
            })
            .collect();
        for with_moments in [true, false] {
            let mut whole = CubeRuns::new(dir.path(), usize::MAX, 100, with_moments);
            for e in &entries {
                whole.push(e.0, e.1, e.2, &e.3).unwrap();
            }
            let (content, cubes) = whole.finish().unwrap();
            let expected = columns_of(content.unwrap());
            assert_eq!(cubes as usize, expected[0].rows());
            for capacity in [1, 7, 499, 699] {
                let mut runs = CubeRuns::new(dir.path(), capacity, 100, with_moments);
                for e in &entries {
                    runs.push(e.0, e.1, e.2, &e.3).unwrap();
                }
                let (content, spilled_cubes) = runs.finish().unwrap();
                assert_eq!(spilled_cubes, cubes);
                let Some(SegmentContent::Spilled(spill)) = content else {
                    panic!("capacity {capacity} should spill")
                };
                let mut direct = Vec::new();
                crate::format::segment::encode_segment_with_block_rows(&expected, 1024, &mut direct).unwrap();
                let (shapes, rows, mut sources) = spill.into_sources().unwrap();
                let mut streamed = Vec::new();
                crate::format::segment::encode_segment_streamed(&shapes, rows, &mut sources, 1024, &mut streamed)
                    .unwrap();
                assert!(direct == streamed, "capacity {capacity}: the spilled segment differs");
            }
            // Without moments the run has the four columns the TGV stages read.
            assert_eq!(expected.len(), if with_moments { 7 } else { 4 });
        }
        // Nothing stays in the scratch folder: run and column files are unlinked at creation.
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }

    #[test]
    fn records_round_trip() {
        let c = CubeSums {
            key: CubeKey::new(5, 1, 2, 3),
            radius_sum: u64::MAX - 3,
            count: 9,
            spikes: 2,
            moments: Moments {
                weight: -5,
                offset: [i64::MIN, 0, i64::MAX],
                normal: [-1, 1, 12345],
            },
        };
        let mut bytes = [0u8; RECORD_LEN];
        c.encode(&mut bytes);
        assert_eq!(CubeSums::decode(&bytes), c);
    }
}
