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
use hashbrown::HashTable;

use crate::format::{Column, ColumnShape, ColumnValues, CubeKey};
use crate::stages::samples::{Moments, moment_columns};
use crate::store::{Result, SegmentContent, SegmentSpill, StoreError};

/// Bytes a cube costs in memory while buffered and once merged into columns: its totals' slot
/// and its moments' slot (each with a control byte, at the tables' 7/8 load), its place in the
/// sorted order, and its row in the in-memory columns.
pub(super) const BYTES_PER_CUBE: u64 = ((size_of::<(CubeKey, Totals)>() + 1) * 8 / 7
    + (size_of::<(CubeKey, Moments)>() + 1) * 8 / 7
    + size_of::<(CubeKey, Totals)>()
    + 16
    + 8
    + 4
    + 4
    + 7 * 8) as u64;

/// Sample entries per cube the table is first sized for (RedKitchen at `--max-depth 10`: 4.1;
/// the table grows where there are fewer).
const EXPECTED_ENTRIES_PER_CUBE: usize = 4;

/// The per-cube sums being gathered, by key. A cube's totals live in its index slot (32 bytes
/// with the key): the lookup every entry makes touches one slot, where a place in a separate
/// list of totals cost a second cache miss on each cube a map meets again. Slots are placed
/// by [`brick_hash`], so a map's neighbouring cubes share cache lines. (`perf` of RedKitchen's
/// ingest: the lookups were a third of its CPU, their misses most of that.) Moments, in runs
/// that carry them, have a table of their own, so that runs without them keep 32-byte slots.
/// The tables' order is never observed: cubes leave them sorted by key.
struct SumsTable {
    totals: HashTable<(CubeKey, Totals)>,
    /// Beside `totals`, when the runs carry moments; else empty.
    moments: HashTable<(CubeKey, Moments)>,
    /// The drain's sorted order, kept between drains (a spilling map drains many times).
    order: Vec<(CubeKey, Totals)>,
    with_moments: bool,
}

/// A slot hash for cube keys that keeps the cubes of one 4 x 4 x 4 brick (64 consecutive
/// Morton codes at their depth) together: the brick and depth are mixed into the high bits,
/// the cube's place in its brick is the low 6 bits, which pick the slot among the 64 that
/// follow the brick's, and the top 7 bits (the table's per-slot tag) mix in the place too,
/// so that one brick's cubes have different tags. Samples of neighbouring pixels fall in one
/// brick far more often than in one cube, and the brick's next cube is then a slot or a tag
/// away: ingest of RedKitchen (1000 frames, `--max-depth 10`) took 5 % less CPU than with a
/// uniform hash, the same store.
fn brick_hash(key: CubeKey) -> u64 {
    let cell = key.morton_at_own_depth();
    let (brick, place) = (cell >> 6, (cell & 63) as u64);
    let mix = |x: u64, k: u64| {
        let x = x.wrapping_mul(k);
        x ^ (x >> 31)
    };
    let high = mix(
        brick as u64 ^ ((brick >> 64) as u64).rotate_left(29) ^ (u64::from(key.depth()) << 58),
        0x9E37_79B9_7F4A_7C15,
    );
    let high = mix(high, 0xBF58_476D_1CE4_E5B9);
    ((high & !63) | place) ^ (place.wrapping_mul(0xD6E8_FEB8_6659_FD93) & (0x7f << 57))
}

/// A cube's sums but its moments.
#[derive(Clone, Copy)]
struct Totals {
    radius_sum: u64,
    count: u32,
    spikes: u32,
}

/// A [`Totals`] with its cube's key.
#[derive(Clone, Copy)]
struct CubeTotals {
    key: CubeKey,
    totals: Totals,
}

impl Totals {
    fn add(&mut self, other: &Totals) {
        self.radius_sum += other.radius_sum;
        self.count += other.count;
        self.spikes += other.spikes;
    }

    fn with_moments(&self, key: CubeKey, moments: Moments) -> CubeSums {
        CubeSums {
            key,
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
            totals: HashTable::with_capacity(cubes),
            moments: HashTable::with_capacity(if with_moments { cubes } else { 0 }),
            order: Vec::new(),
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
        let hash = brick_hash(sums.key);
        let Some((_, totals)) = self.totals.find_mut(hash, |(key, _)| *key == sums.key) else {
            return false;
        };
        totals.add(&sums.totals);
        if self.with_moments
            && let Some((_, existing)) = self.moments.find_mut(hash, |(key, _)| *key == sums.key)
        {
            existing.add(moments);
        }
        true
    }

    /// Adds a cube the table does not hold.
    fn insert_new(&mut self, sums: CubeTotals, moments: &Moments) {
        let hash = brick_hash(sums.key);
        self.totals
            .insert_unique(hash, (sums.key, sums.totals), |(key, _)| brick_hash(*key));
        if self.with_moments {
            self.moments
                .insert_unique(hash, (sums.key, *moments), |(key, _)| brick_hash(*key));
        }
    }

    /// Empties the table into `each` in key order (keys are unique: no two cubes compare
    /// equal), with zero moments in runs without them. The table keeps its memory: a spilling
    /// map holds one table at a time.
    fn drain_in_key_order(&mut self, mut each: impl FnMut(CubeSums) -> Result<()>) -> Result<()> {
        let mut order = std::mem::take(&mut self.order);
        order.extend(self.totals.drain());
        order.sort_unstable_by_key(|(key, _)| *key);
        let result = order.iter().try_for_each(|(key, totals)| {
            let moments = if self.with_moments {
                let found = self.moments.find(brick_hash(*key), |(k, _)| k == key);
                found.map(|(_, moments)| *moments).unwrap_or_default()
            } else {
                Moments::default()
            };
            each(totals.with_moments(*key, moments))
        });
        order.clear();
        self.order = order;
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
        let entry = Totals {
            radius_sum,
            count: 1,
            spikes: u32::from(spike),
        };
        if let Some(current) = &mut self.current
            && current.key == key
        {
            current.totals.add(&entry);
            // Runs without moment columns are given zero moments: nothing to add.
            if self.with_moments {
                self.current_moments.add(moments);
            }
            return Ok(());
        }
        let Some(done) = self.current.replace(CubeTotals { key, totals: entry }) else {
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

    /// The table's sums are the plain per-key sums, whatever the depth mix of the keys.
    #[test]
    fn the_table_sums_every_key_as_a_sorted_map_does() {
        let mut state = 11u64;
        let mut expected: std::collections::BTreeMap<CubeKey, (u64, u32, u32)> = Default::default();
        let mut runs = CubeRuns::new(Path::new("/nonexistent"), usize::MAX, 10, false);
        for _ in 0..20_000 {
            let r = crate::kernels::random::splitmix(&mut state);
            let depth = 8 + (r % 4) as u8;
            let key = CubeKey::new(depth, (r >> 8) as u32 % 40, (r >> 20) as u32 % 3, (r >> 32) as u32 % 40);
            let (radius, spike) = (r >> 50, r.is_multiple_of(3));
            runs.push(key, radius, spike, &Moments::default()).unwrap();
            let sums = expected.entry(key).or_default();
            *sums = (sums.0 + radius, sums.1 + 1, sums.2 + u32::from(spike));
        }
        let columns = columns_of(runs.finish().unwrap().0.unwrap());
        let (ColumnValues::Key(keys), ColumnValues::U64(radii), ColumnValues::U32(counts), ColumnValues::U32(spikes)) = (
            &columns[0].values,
            &columns[1].values,
            &columns[2].values,
            &columns[3].values,
        ) else {
            panic!("unexpected column types")
        };
        let got: Vec<_> = (keys.iter().zip(radii).zip(counts.iter().zip(spikes)))
            .map(|((k, r), (c, s))| (*k, (*r, *c, *s)))
            .collect();
        assert_eq!(got, expected.into_iter().collect::<Vec<_>>());
    }

    /// A brick's 64 cubes take consecutive slots from the brick's first, with tags that tell
    /// most of them apart; different bricks and depths start elsewhere.
    #[test]
    fn a_bricks_cubes_hash_to_consecutive_slots() {
        let mut starts = std::collections::BTreeSet::new();
        for (depth, brick) in [
            (10u8, [0u32, 0, 0]),
            (10, [4, 0, 0]),
            (10, [0, 8, 12]),
            (9, [0, 0, 0]),
            (12, [400, 4, 8]),
        ] {
            let mut tags = std::collections::BTreeSet::new();
            let mut start = None;
            for place in 0..64u32 {
                let [x, y, z] = [
                    place & 1 | (place >> 2 & 2),
                    place >> 1 & 1 | (place >> 3 & 2),
                    place >> 2 & 1 | (place >> 4 & 2),
                ];
                let key = CubeKey::new(depth, brick[0] + x, brick[1] + y, brick[2] + z);
                let hash = brick_hash(key);
                assert_eq!(hash & 63, u64::from(place), "{key:?}");
                let high = hash & !63 & !(0x7f << 57);
                assert_eq!(*start.get_or_insert(high), high, "one brick, one start");
                tags.insert(hash >> 57);
            }
            assert!(tags.len() >= 32, "{} tags among a brick's 64 cubes", tags.len());
            starts.extend(start);
        }
        assert_eq!(starts.len(), 5, "every brick starts elsewhere");
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
