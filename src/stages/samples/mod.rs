//! `samples`: what the depth maps' samples say to the SSD solver (`kernels::ssd`), per octree
//! node: the weight, centroid and normal sums of the samples that spawned it.
//!
//! Ingest writes each sample's share into its depth map's run, beside the radius sums, as
//! fixed-point integers relative to the spawned cube ([`Moments`]); this stage adds the runs
//! up per treetop unit, one segment aligned row for row with the unit's octree segment. The
//! sums are integers, so their order, and with it the order of the inputs and the thread
//! count, cannot change a bit. Only `solve --method ssd` runs it; it is rebuilt whole when the
//! octree or the set of depth maps changes (format-spec.md, "Columns used by stages").

use std::sync::{Arc, Mutex};

use glam::DVec3;

use super::treetop::Treetop;
use super::{INGEST, OCTREE};
use crate::format::segment::SegmentDirectory;
use crate::format::{Column, ColumnValues, CubeKey, Scene, round_half_away_from_zero};
use crate::store::catalog::{self, UnitRecord};
use crate::store::{
    Plan, Replace, Result, SegmentChunks, SegmentFile, Snapshot, Stage, StageError, StoreError, UnitOutput, UnitSpec,
};

/// The stage's name.
pub const SAMPLES: &str = "samples";

/// Columns of ingest runs and of this stage's segments (U64 columns holding i64 values).
pub const SAMPLE_WEIGHT: &str = "sample_weight";
pub const SAMPLE_OFFSET: &str = "sample_offset";
pub const SAMPLE_NORMAL: &str = "sample_normal";

/// Fixed-point scale of [`Moments`]: a sample whose area equals its cube's face weighs 2^24.
pub const FIXED_POINT: f64 = 16_777_216.0;

/// The samples of one cube, relative to it: with h its side and c its centre, the sums over
/// its samples of a = area / h^2 (times the map's weight), a (x - c) / h and a n, each
/// rounded to 1 / [`FIXED_POINT`] per sample.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Moments {
    pub weight: i64,
    pub offset: [i64; 3],
    pub normal: [i64; 3],
}

fn fixed(x: f64) -> i64 {
    round_half_away_from_zero(x * FIXED_POINT) as i64
}

impl Moments {
    /// One sample's share: `area` in world units squared, `normal` a unit vector.
    pub fn of_sample(scene: &Scene, key: CubeKey, point: DVec3, area: f64, normal: DVec3) -> Moments {
        let side = scene.cube_side(key.depth());
        // One division, not five: ingest computes this for every sample.
        let per_side = 1.0 / side;
        let a = area * (per_side * per_side);
        let offset = (point - scene.cube_center(key)) * per_side;
        Moments {
            weight: fixed(a),
            offset: [fixed(a * offset.x), fixed(a * offset.y), fixed(a * offset.z)],
            normal: [fixed(a * normal.x), fixed(a * normal.y), fixed(a * normal.z)],
        }
    }

    pub fn add(&mut self, other: &Moments) {
        self.weight = self.weight.saturating_add(other.weight);
        for k in 0..3 {
            self.offset[k] = self.offset[k].saturating_add(other.offset[k]);
            self.normal[k] = self.normal[k].saturating_add(other.normal[k]);
        }
    }

    /// In root units for a node `key`: its weight (root units squared), its samples'
    /// centroid (root units, inside the node's cube) and weighted normal sum; `None` without
    /// weight.
    pub fn in_root_units(&self, key: CubeKey) -> Option<(f64, [f64; 3], [f64; 3])> {
        if self.weight <= 0 {
            return None;
        }
        let side = key.side();
        let area = side * side / FIXED_POINT;
        let centre = cube_centre(key);
        let w = self.weight as f64;
        let centroid = std::array::from_fn(|k| centre[k] + side * (self.offset[k] as f64 / w).clamp(-0.5, 0.5));
        Some((w * area, centroid, self.normal.map(|n| n as f64 * area)))
    }
}

/// How much the normals of the samples in one node disagree, taken over a whole samples
/// segment: the lower quartile ([`DISAGREEMENT_QUANTILE`]), by sample weight, of each node's
/// 1 - |sum a n| / sum a (1 - cos t/2 for two halves t apart), over the nodes where it is not 0
/// (a single sample, or exactly one normal, says nothing about the noise); with the weight it
/// is taken over, `None` without such nodes. A node's own samples spawned it at their radius,
/// so it spans a few of their pixel footprints whatever the scene's scale, and what turns
/// their normals is the normal fit's noise, which grows with the depth maps' noise, and the
/// surface's curvature where it has fine detail ([`crate::kernels::ssd`]'s normal weight
/// follows the first).
pub fn normal_disagreement(moments: &[Moments]) -> Option<(f64, f64)> {
    let mut nodes: Vec<(f64, f64)> = moments
        .iter()
        .filter(|m| m.weight > 0)
        .map(|m| {
            let w = m.weight as f64;
            let length = m.normal.map(|n| n as f64).iter().map(|n| n * n).sum::<f64>().sqrt();
            ((1.0 - length / w).clamp(0.0, 1.0), w)
        })
        .filter(|(value, _)| *value > 1e-9)
        .collect();
    nodes.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.total_cmp(&b.1)));
    let total: f64 = nodes.iter().map(|(_, w)| w).sum();
    let mut below = 0.0;
    nodes.into_iter().find_map(|(value, w)| {
        below += w;
        (below >= DISAGREEMENT_QUANTILE * total).then_some((value, total))
    })
}

/// The quantile [`normal_disagreement`] takes. Curved fine detail disagrees in places whatever
/// the noise, and the lower quartile leaves it out where the median did not: the groundtruth
/// dragon at 0.2 % depth noise had units at 0.012 to 0.033 by the median (the bunny at 1 %
/// noise 0.013 to 0.025), at most 0.0062 by the lower quartile (the bunny at 1 %: 0.0077 to
/// 0.0128; docs/parameters.md, "Solvers").
pub const DISAGREEMENT_QUANTILE: f64 = 0.25;

/// A cube's centre in root units.
pub fn cube_centre(key: CubeKey) -> [f64; 3] {
    let side = key.side();
    key.coords().map(|c| (f64::from(c) + 0.5) * side)
}

/// The three columns of `moments`: each as u32 holding i32 when every one of its values fits
/// (a run's per-map sums nearly always do), else as u64 holding i64. The narrow columns are
/// half the bytes to decompress, and decompression was most of the samples stage's CPU: over
/// 100 of RedKitchen's runs their moments decoded in 0.29 s instead of 0.51 s.
pub fn moment_columns(moments: &[Moments]) -> [Column; 3] {
    let column = |name: &str, width: u16, values: Vec<i64>| {
        let narrow: Option<Vec<u32>> = values
            .iter()
            .map(|v| i32::try_from(*v).ok().map(|v| v as u32))
            .collect();
        let values = match narrow {
            Some(narrow) => ColumnValues::U32(narrow),
            None => ColumnValues::U64(values.into_iter().map(|v| v as u64).collect()),
        };
        Column::new(name, width, values)
    };
    [
        column(SAMPLE_WEIGHT, 1, moments.iter().map(|m| m.weight).collect()),
        column(SAMPLE_OFFSET, 3, moments.iter().flat_map(|m| m.offset).collect()),
        column(SAMPLE_NORMAL, 3, moments.iter().flat_map(|m| m.normal).collect()),
    ]
}

/// A moment column's values, whichever width [`moment_columns`] chose.
enum MomentColumn {
    Narrow(Vec<u32>),
    Wide(Vec<u64>),
}

impl MomentColumn {
    /// `None` for a column of another type.
    fn of(values: ColumnValues) -> Option<MomentColumn> {
        match values {
            ColumnValues::U32(values) => Some(MomentColumn::Narrow(values)),
            ColumnValues::U64(values) => Some(MomentColumn::Wide(values)),
            _ => None,
        }
    }

    fn len(&self) -> usize {
        match self {
            MomentColumn::Narrow(values) => values.len(),
            MomentColumn::Wide(values) => values.len(),
        }
    }

    /// The bytes its values take.
    fn bytes(&self) -> u64 {
        match self {
            MomentColumn::Narrow(values) => 4 * values.len() as u64,
            MomentColumn::Wide(values) => 8 * values.len() as u64,
        }
    }

    /// Value `i`, as the signed integer it holds.
    fn get(&self, i: usize) -> i64 {
        match self {
            MomentColumn::Narrow(values) => values.get(i).map_or(0, |v| i64::from(*v as i32)),
            MomentColumn::Wide(values) => values.get(i).map_or(0, |v| *v as i64),
        }
    }
}

/// A samples segment's rows as they decoded, read row by row: building every row's
/// [`Moments`] first wrote and read 56 bytes a row again.
pub struct SampleRows(RunBlock);

impl SampleRows {
    /// Each row's key and moments, in key order.
    pub fn iter(&self) -> impl Iterator<Item = (CubeKey, Moments)> + '_ {
        self.0
            .keys
            .iter()
            .enumerate()
            .map(|(row, key)| (*key, self.0.moments(row)))
    }
}

/// A unit's rows from its samples segment.
pub fn read_sample_rows(snapshot: &Snapshot<'_>, segment: &str) -> Result<SampleRows> {
    let file = snapshot.open_segment(segment)?;
    let reader = file.reader()?;
    let c = |e| file.corruption(e);
    let keys = reader.read_keys().map_err(c)?;
    let moment = |name: &str| -> Result<Option<MomentColumn>> {
        Ok(MomentColumn::of(reader.read_column(name).map_err(c)?.values))
    };
    let (weight, offset, normal) = (moment(SAMPLE_WEIGHT)?, moment(SAMPLE_OFFSET)?, moment(SAMPLE_NORMAL)?);
    weight
        .zip(offset)
        .zip(normal)
        .and_then(|((weight, offset), normal)| RunBlock::new(keys, weight, offset, normal))
        .map(SampleRows)
        .ok_or_else(|| {
            file.corruption(crate::format::DecodeError::MissingColumn(
                "sample_weight, sample_offset, sample_normal of the keys' length".into(),
            ))
        })
}

/// A unit's keys and moments from its samples segment.
pub fn read_samples(snapshot: &Snapshot<'_>, segment: &str) -> Result<(Vec<CubeKey>, Vec<Moments>)> {
    let SampleRows(rows) = read_sample_rows(snapshot, segment)?;
    let moments = rows.all_moments();
    Ok((rows.keys, moments))
}

/// How many of a unit's keys [`add_by_tiles`] adds into at a time: with their sums, 72 bytes a
/// key, they stay in a core's L2 cache while every block's rows among them are added. At most
/// `u16::MAX`, for [`TileIndex`].
const TILE_KEYS: usize = 4096;

/// A tile's keys by hash, so that finding a row's cube neither waits on the row before nor
/// mispredicts a search's branches: open addressing with linear probing, at most half full,
/// each slot 0 (empty) or a key's index in the tile plus one. 16 KB, in the L1 cache.
struct TileIndex {
    slots: Vec<u16>,
}

impl TileIndex {
    const SLOT_BITS: u32 = (2 * TILE_KEYS).trailing_zeros();
    const MASK: usize = (1 << Self::SLOT_BITS) - 1;

    fn new() -> TileIndex {
        TileIndex {
            slots: vec![0; 1 << Self::SLOT_BITS],
        }
    }

    fn slot_of(key: CubeKey) -> usize {
        let raw = key.raw();
        let folded = (raw as u64) ^ ((raw >> 64) as u64).rotate_left(29);
        (folded.wrapping_mul(0x9E37_79B9_7F4A_7C15) >> (64 - Self::SLOT_BITS)) as usize
    }

    /// Indexes `tile` (at most [`TILE_KEYS`] distinct keys) instead of what it held.
    fn fill(&mut self, tile: &[CubeKey]) {
        self.slots.fill(0);
        for (index, key) in tile.iter().enumerate().take(TILE_KEYS) {
            let mut slot = Self::slot_of(*key);
            while let Some(entry) = self.slots.get_mut(slot) {
                if *entry == 0 {
                    *entry = index as u16 + 1;
                    break;
                }
                slot = (slot + 1) & Self::MASK;
            }
        }
    }

    /// `key`'s index in the `tile` last filled in.
    fn find(&self, tile: &[CubeKey], key: CubeKey) -> Option<usize> {
        let mut slot = Self::slot_of(key);
        loop {
            let index = usize::from(*self.slots.get(slot)?).checked_sub(1)?;
            if tile.get(index) == Some(&key) {
                return Some(index);
            }
            slot = (slot + 1) & Self::MASK;
        }
    }
}

/// Adds the rows of `blocks` (each sorted by key) whose keys are among `keys` (sorted and
/// distinct) into the matching `sums`, one tile of [`TILE_KEYS`] keys at a time. A leaf's keys
/// and sums are a few MB and each of RedKitchen's 1000 runs meets about 950 of them, so adding
/// a run at a time missed the cache at nearly every row (87 ns a row). Every cube's adds keep
/// the blocks' order, so the saturating sums do not depend on the tile size.
fn add_by_tiles(keys: &[CubeKey], blocks: &[Arc<RunBlock>], sums: &mut [Moments]) {
    let Some(&low) = keys.first() else {
        return;
    };
    let mut cursors: Vec<usize> = blocks.iter().map(|b| b.keys.partition_point(|k| *k < low)).collect();
    let mut index = TileIndex::new();
    for (tile_keys, tile_sums) in keys.chunks(TILE_KEYS).zip(sums.chunks_mut(TILE_KEYS)) {
        let Some(&last) = tile_keys.last() else {
            continue;
        };
        index.fill(tile_keys);
        for (block, cursor) in blocks.iter().zip(cursors.iter_mut()) {
            while let Some(key) = block.keys.get(*cursor) {
                if *key > last {
                    break;
                }
                if let Some(sum) = index.find(tile_keys, *key).and_then(|at| tile_sums.get_mut(at)) {
                    sum.add(&block.moments(*cursor));
                }
                *cursor += 1;
            }
        }
    }
}

/// An ingest run, where it lies, its directory, and how many leaf units read each block. Every
/// unit opens the runs it overlaps by path, without searching the version's segment list or
/// parsing them.
struct RunIndex {
    name: String,
    path: std::path::PathBuf,
    /// The run's directory, parsed once: units read its chunks without mapping the file.
    directory: SegmentDirectory,
    /// Per block, the leaf units whose key range meets it and that have not yet read it.
    readers_left: Vec<std::sync::atomic::AtomicUsize>,
}

/// One decoded block of an ingest run (or a whole samples segment): its keys and its moment
/// columns as they decoded, of matching lengths. A row's [`Moments`] are built as the row is added: building them all
/// first wrote and read 56 bytes a row again (7 % of the stage's CPU in `perf`).
struct RunBlock {
    keys: Vec<CubeKey>,
    weight: MomentColumn,
    offset: MomentColumn,
    normal: MomentColumn,
}

/// A unit's open file of one run and the buffer its chunks are read into.
struct RunChunks<'a> {
    run: &'a RunIndex,
    file: SegmentChunks,
    buffer: Vec<u8>,
}

impl RunChunks<'_> {
    /// Block `block` of column `name`.
    fn read_block(&mut self, name: &str, block: usize) -> Result<ColumnValues> {
        self.file
            .decode_block(&self.run.directory, name, block, &mut self.buffer)
    }
}

impl RunBlock {
    fn decode(chunks: &mut RunChunks<'_>, block: usize) -> Result<RunBlock> {
        let run = chunks.run;
        let (ColumnValues::Key(keys), Some(w), Some(o), Some(n)) = (
            chunks.read_block("key", block)?,
            MomentColumn::of(chunks.read_block(SAMPLE_WEIGHT, block)?),
            MomentColumn::of(chunks.read_block(SAMPLE_OFFSET, block)?),
            MomentColumn::of(chunks.read_block(SAMPLE_NORMAL, block)?),
        ) else {
            return Err(SamplesStage::error(
                &run.name,
                StageError::internal("sample columns of the wrong type"),
            ));
        };
        RunBlock::new(keys, w, o, n)
            .ok_or_else(|| SamplesStage::error(&run.name, StageError::internal("sample columns of unequal lengths")))
    }

    /// `None` unless there are one weight and three offsets and normals per key.
    fn new(keys: Vec<CubeKey>, weight: MomentColumn, offset: MomentColumn, normal: MomentColumn) -> Option<RunBlock> {
        let rows = keys.len();
        (weight.len() == rows && offset.len() == 3 * rows && normal.len() == 3 * rows).then_some(RunBlock {
            keys,
            weight,
            offset,
            normal,
        })
    }

    /// The bytes its keys and columns take: narrow blocks (every RedKitchen run's) about 44
    /// a row, wide ones 72.
    fn bytes(&self) -> u64 {
        16 * self.keys.len() as u64 + self.weight.bytes() + self.offset.bytes() + self.normal.bytes()
    }

    /// Every row's moments, in order.
    fn all_moments(&self) -> Vec<Moments> {
        (0..self.keys.len()).map(|row| self.moments(row)).collect()
    }

    /// Row `row`'s moments.
    fn moments(&self, row: usize) -> Moments {
        Moments {
            weight: self.weight.get(row),
            offset: std::array::from_fn(|k| self.offset.get(3 * row + k)),
            normal: std::array::from_fn(|k| self.normal.get(3 * row + k)),
        }
    }
}

/// The decoded run blocks that leaf units still to come will read, by (run, block), and how
/// many bytes of them may be held at once. A run's 1024-row blocks are few beside the
/// treetop's leaves (RedKitchen's 1000 runs hold 66 blocks each, spread over up to 71
/// leaves), so without sharing every block was decoded 2.05 times on average, and zstd was
/// half the stage's CPU.
struct SharedBlocks {
    /// The entry's lock is held while its block decodes: a second reader waits for the first
    /// instead of decoding it again.
    entries: Mutex<std::collections::HashMap<(usize, usize), SharedSlot>>,
    /// The bytes of decoded blocks ([`RunBlock::bytes`]) that may be held. A new entry is
    /// made only below it, so the blocks being decoded into new entries, one per worker, are
    /// all it can pass by. Counted as one 72-byte-a-row block each, the cache held 61 % of
    /// its bound in RedKitchen's narrow blocks.
    capacity: u64,
    /// The bytes of the decoded blocks held.
    held: Arc<std::sync::atomic::AtomicU64>,
}

/// A shared block: empty until its first reader has decoded it.
type SharedSlot = Arc<Mutex<Option<HeldBlock>>>;

/// A decoded block in a shared entry, counted in [`SharedBlocks::held`] until the entry is
/// gone: whichever reader drops the entry last, the count comes down once.
struct HeldBlock {
    block: Arc<RunBlock>,
    held: Arc<std::sync::atomic::AtomicU64>,
}

impl HeldBlock {
    fn new(block: Arc<RunBlock>, held: Arc<std::sync::atomic::AtomicU64>) -> HeldBlock {
        held.fetch_add(block.bytes(), std::sync::atomic::Ordering::SeqCst);
        HeldBlock { block, held }
    }
}

impl Drop for HeldBlock {
    fn drop(&mut self) {
        self.held
            .fetch_sub(self.block.bytes(), std::sync::atomic::Ordering::SeqCst);
    }
}

/// What a unit's keys and summed moments are shown to as the unit is summed.
type UnitSums = Box<dyn Fn(u64, &[CubeKey], &[Moments]) + Send + Sync>;

pub struct SamplesStage {
    /// Shown each unit's sums, so that later stages in the process need not decode them.
    on_unit: Option<UnitSums>,
    /// How many bytes of decoded blocks a unit holds to add them tile by tile.
    group_bytes: u64,
    /// Built by the first unit that needs it: every run's block boundaries.
    runs: Mutex<Option<Arc<Vec<RunIndex>>>>,
    shared: SharedBlocks,
    /// Run blocks decoded so far, by every unit.
    decoded: std::sync::atomic::AtomicU64,
    treetop: std::sync::OnceLock<Treetop>,
}

impl Default for SamplesStage {
    fn default() -> Self {
        SamplesStage::new()
    }
}

impl SamplesStage {
    /// The stage holding up to 64 MiB of decoded run blocks that several units read.
    pub fn new() -> SamplesStage {
        SamplesStage {
            on_unit: None,
            group_bytes: 16 << 20,
            runs: Mutex::new(None),
            shared: SharedBlocks {
                entries: Mutex::new(std::collections::HashMap::new()),
                capacity: 0,
                held: Arc::new(std::sync::atomic::AtomicU64::new(0)),
            },
            decoded: std::sync::atomic::AtomicU64::new(0),
            treetop: std::sync::OnceLock::new(),
        }
        .with_cache_bytes(64 << 20)
    }

    /// Holds up to `bytes` of decoded run blocks that several units read. A unit that finds
    /// the cache full decodes the block itself, so the bound costs time, never a result.
    pub fn with_cache_bytes(mut self, bytes: u64) -> SamplesStage {
        self.shared.capacity = bytes;
        self
    }

    /// Each unit holds up to `bytes` of the blocks it reads (at least one), to add them tile
    /// by tile ([`add_by_tiles`]); 16 MiB unless set. Beyond a few dozen blocks a group
    /// gains little: each tile's keys and sums are loaded once per group.
    pub fn with_group_bytes(mut self, bytes: u64) -> SamplesStage {
        self.group_bytes = bytes;
        self
    }

    /// Shows `on_unit` each unit's id, keys and summed moments (a unit resumed from an
    /// earlier run is not summed, so not shown).
    pub fn with_unit_sums(
        mut self,
        on_unit: impl Fn(u64, &[CubeKey], &[Moments]) + Send + Sync + 'static,
    ) -> SamplesStage {
        self.on_unit = Some(Box::new(on_unit));
        self
    }

    /// How many ingest run blocks this stage's units have decoded (a block several units read
    /// counts once when they shared it).
    pub fn blocks_decoded(&self) -> u64 {
        self.decoded.load(std::sync::atomic::Ordering::Relaxed)
    }

    fn error(unit: &str, error: StageError) -> StoreError {
        StoreError::Stage {
            stage: SAMPLES.into(),
            unit: unit.into(),
            error: Box::new(error),
        }
    }

    fn runs(&self, base: &Snapshot<'_>) -> Result<Arc<Vec<RunIndex>>> {
        let mut slot = self
            .runs
            .lock()
            .map_err(|_| Self::error("-", StageError::WorkerPanicked))?;
        if let Some(runs) = slot.as_ref() {
            return Ok(runs.clone());
        }
        // Leaf units' key ranges, in key order and disjoint: a node of the treetop's internal
        // unit sorts before its subtree, so it never falls inside a leaf's range.
        let leaves: Vec<(CubeKey, CubeKey)> = self
            .treetop
            .get()
            .map(|t| {
                t.units
                    .iter()
                    .filter(|u| !u.top)
                    .map(|u| {
                        (
                            CubeKey::from_raw(u.record.first_key),
                            CubeKey::from_raw(u.record.last_key),
                        )
                    })
                    .collect()
            })
            .unwrap_or_default();
        let mut runs = Vec::new();
        for (name, record) in base.segments(INGEST) {
            let path = base.store().segment_path(name);
            let file = SegmentFile::open(path.clone(), record)?;
            let reader = file.reader()?;
            if reader.column(SAMPLE_WEIGHT).is_err() {
                return Err(Self::error(name, StageError::NoSampleSums));
            }
            // The directory holds each block's key range; decoding the key columns of
            // RedKitchen's 1000 runs for it, under this lock, cost the stage 0.8 of its 11.8 s.
            let directory = reader.directory();
            let readers_left = (0..directory.block_count())
                .filter_map(|block| directory.block_key_range(block))
                .map(|(first, last)| {
                    let readers = leaves.partition_point(|(low, _)| *low <= last)
                        - leaves.partition_point(|(_, high)| *high < first);
                    std::sync::atomic::AtomicUsize::new(readers)
                })
                .collect();
            runs.push(RunIndex {
                name: name.clone(),
                path,
                directory,
                readers_left,
            });
        }
        let runs = Arc::new(runs);
        *slot = Some(runs.clone());
        Ok(runs)
    }

    /// Block `block` of `run` (the `index`th) for a leaf unit: kept in [`SharedBlocks`] while
    /// leaf units still to come read it. Every leaf reader counts down the block's readers,
    /// whether it found the block there or not, and the last one drops it.
    fn leaf_block(
        &self,
        index: usize,
        run: &RunIndex,
        block: usize,
        decode: impl FnOnce() -> Result<RunBlock>,
    ) -> Result<Arc<RunBlock>> {
        use std::sync::atomic::Ordering;
        let poisoned = || Self::error(&run.name, StageError::WorkerPanicked);
        let left = run
            .readers_left
            .get(block)
            .and_then(|n| {
                n.fetch_update(Ordering::SeqCst, Ordering::SeqCst, |n| Some(n.saturating_sub(1)))
                    .ok()
            })
            .map_or(0, |before| before.saturating_sub(1));
        let entry = {
            let mut entries = self.shared.entries.lock().map_err(|_| poisoned())?;
            if left == 0 {
                entries.remove(&(index, block))
            } else if self.shared.held.load(Ordering::SeqCst) < self.shared.capacity {
                Some(entries.entry((index, block)).or_default().clone())
            } else {
                entries.get(&(index, block)).cloned()
            }
        };
        let Some(entry) = entry else {
            return decode().map(Arc::new);
        };
        let mut slot = entry.lock().map_err(|_| poisoned())?;
        match slot.as_ref() {
            Some(held) => Ok(held.block.clone()),
            None => {
                let decoded = Arc::new(decode()?);
                *slot = Some(HeldBlock::new(decoded.clone(), self.shared.held.clone()));
                Ok(decoded)
            }
        }
    }

    /// Adds every run's moments of the unit's `keys` (sorted) into `sums`; `leaf` for a
    /// treetop leaf's unit, whose keys fill one key range.
    fn add_runs(&self, base: &Snapshot<'_>, keys: &[CubeKey], leaf: bool, sums: &mut [Moments]) -> Result<()> {
        let (Some(&low), Some(&high)) = (keys.first(), keys.last()) else {
            return Ok(());
        };
        // Blocks are added a group at a time, in (run, block) order, which is the order of
        // every cube's adds whatever the groups' size.
        let mut group: Vec<Arc<RunBlock>> = Vec::new();
        let mut held = 0u64;
        for (index, run) in self.runs(base)?.iter().enumerate() {
            let blocks = run.directory.block_count();
            let (Some((first, _)), Some((_, last))) = (
                run.directory.block_key_range(0),
                run.directory.block_key_range(blocks.saturating_sub(1)),
            ) else {
                continue;
            };
            if first > high || last < low {
                continue;
            }
            let mut chunks = RunChunks {
                run,
                file: SegmentChunks::open(run.path.clone())?,
                buffer: Vec::new(),
            };
            let start = run.directory.first_block_reaching(low);
            for (block, (block_first, block_last)) in
                (start..blocks).filter_map(|b| run.directory.block_key_range(b).map(|range| (b, range)))
            {
                if block_first > high {
                    break;
                }
                // Skip blocks that hold none of the unit's keys (the top unit's keys are
                // scattered between the leaves').
                let from = keys.partition_point(|k| *k < block_first);
                if keys.get(from).is_none_or(|k| *k > block_last) {
                    continue;
                }
                let decoded = if leaf {
                    self.leaf_block(index, run, block, || {
                        self.decoded.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        RunBlock::decode(&mut chunks, block)
                    })?
                } else {
                    // The top unit's few nodes are rarely in a block its key range meets: its
                    // keys tell, before the moments are decoded.
                    let ColumnValues::Key(block_keys) = chunks.read_block("key", block)? else {
                        return Err(Self::error(
                            &run.name,
                            StageError::internal("a key column of the wrong type"),
                        ));
                    };
                    if !block_keys.iter().any(|k| keys.binary_search(k).is_ok()) {
                        continue;
                    }
                    self.decoded.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                    Arc::new(RunBlock::decode(&mut chunks, block)?)
                };
                held += decoded.bytes();
                group.push(decoded);
                if held >= self.group_bytes {
                    add_by_tiles(keys, &group, sums);
                    group.clear();
                    held = 0;
                }
            }
        }
        add_by_tiles(keys, &group, sums);
        Ok(())
    }
}

impl Stage for SamplesStage {
    fn name(&self) -> &'static str {
        SAMPLES
    }

    fn input_digest(&self, base: &Snapshot<'_>) -> Vec<u8> {
        let mut digest = base.digest(OCTREE).to_le_bytes().to_vec();
        digest.extend_from_slice(&base.digest(INGEST).to_le_bytes());
        digest
    }

    fn plan(&self, base: &Snapshot<'_>) -> Result<Plan> {
        let treetop = Treetop::of(base)?;
        let units = treetop
            .units
            .iter()
            .enumerate()
            .map(|(index, unit)| UnitSpec {
                id: index as u64,
                label: if unit.top {
                    "the treetop's internal nodes".into()
                } else {
                    format!("leaf {:?}", unit.key)
                },
                cubes: unit.record.rows,
            })
            .collect();
        let _ = self.treetop.set(treetop);
        Ok(Plan {
            units,
            replace: Replace::All,
        })
    }

    fn run_unit(&self, base: &Snapshot<'_>, unit: &UnitSpec) -> Result<UnitOutput> {
        let info = self
            .treetop
            .get()
            .and_then(|t| t.units.get(unit.id as usize))
            .ok_or_else(|| Self::error(&unit.label, StageError::internal("no such treetop unit")))?;
        let file = base.open_segment(&info.segment)?;
        let keys = file.reader()?.read_keys().map_err(|e| file.corruption(e))?;
        let mut sums = vec![Moments::default(); keys.len()];
        self.add_runs(base, &keys, !info.top, &mut sums)?;
        if let Some(on_unit) = &self.on_unit {
            on_unit(unit.id, &keys, &sums);
        }
        let with_samples = sums.iter().filter(|m| m.weight > 0).count() as u64;
        let mut columns = vec![Column::keys(keys)];
        columns.extend(moment_columns(&sums));
        Ok(UnitOutput {
            segments: vec![columns.into()],
            extra: catalog::encode(&with_samples),
            block_rows: 0,
        })
    }

    fn finish(
        &self,
        _txn: &redb::WriteTransaction,
        _base: &Snapshot<'_>,
        units: &[(u64, UnitRecord)],
    ) -> Result<String> {
        let mut nodes = 0u64;
        for (_, record) in units {
            nodes += catalog::decode::<u64>("units_done", &record.extra)?;
        }
        let line = format!("{nodes} octree nodes hold samples, in {} unit(s)", units.len());
        tracing::info!("{line}");
        Ok(line)
    }
}

#[cfg(test)]
mod tests;
