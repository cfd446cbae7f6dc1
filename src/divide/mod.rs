//! `divide`: the octree space division of huge point clouds into overlapping subspaces of at
//! most N points (Kuhn and Mayer 2015, Algorithm 2), so that any reconstructor can process
//! the parts in parallel and `merge` fuses the results by cutting the overlaps.
//!
//! Three streaming passes over the points, as in the paper: their bounds (the root cube),
//! their counts per node down to a depth the memory budget allows (counters only, never the
//! points), and the writes: each point goes to the file of every subspace whose grown cube
//! holds it. A node at the counted depth that still holds more than N points is written to a
//! scratch file in the same pass and divided again from it (the paper's recursion), which reads
//! only its own points. Memory is the counters, the lookup and the write buffers, bounded by
//! `--memory-budget` whatever the input's size.
//!
//! Deterministic: the sources are taken in the order of their content's hash (not the order
//! they were named in), blocks are cut at fixed record counts, and the results of the blocks
//! processed in parallel are consumed in block order, so the files are byte-identical for any
//! thread count and input order. A later `divide` into the same folder updates only the
//! subspaces the new points touch (`incremental.rs`).

mod error;
mod grid;
mod incremental;
mod manifest;
pub mod merge;
mod point_clouds;
mod sources;
mod subspace_files;
mod synthetic;

use std::path::{Path, PathBuf};

use indicatif::ProgressBar;
use rayon::prelude::*;

pub use error::DivideError;
pub use grid::{Bounds, GRID_BITS, Node, Root};
pub use manifest::{Cube, Division, MANIFEST, Manifest, Subspace, read_manifest_file};
pub use sources::{ScanPoints, StoreSamples, open_input};
pub use synthetic::SyntheticCloud;

/// The division's results.
pub type Result<T> = std::result::Result<T, DivideError>;

use crate::sys::WideWork;
use grid::{CellAdder, CountCells, Counts, Lookup, NodeLocator, choose_leaves, counts_bytes};
pub use point_clouds::{PointCloudFile, PointLayout, open_point_cloud};
use subspace_files::Appenders;

/// What `divide` is asked for.
#[derive(Clone, Debug)]
pub struct DivideOptions {
    /// No subspace's core holds more points.
    pub max_points: u64,
    /// Grown cubes reach this fraction of their side beyond each face of the core.
    pub overlap: f64,
    /// The deepest level counted in one pass (fewer when the budget allows less).
    pub max_depth: Option<u32>,
    /// Bytes of memory the division may use.
    pub memory_budget: u64,
    /// Progress bars on stderr.
    pub progress: bool,
}

impl Default for DivideOptions {
    fn default() -> Self {
        DivideOptions {
            max_points: 10_000_000,
            overlap: 0.1,
            max_depth: None,
            memory_budget: 1 << 30,
            progress: false,
        }
    }
}

/// What a division did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct DivideReport {
    /// Points read from the inputs.
    pub input_points: u64,
    /// Subspaces in the folder afterwards.
    pub subspaces: usize,
    /// Subspace files written by this run (new or rewritten).
    pub files_written: usize,
    /// Points written into them, overlaps included.
    pub points_written: u64,
    /// The most points in one core.
    pub largest_core: u64,
    /// Levels counted in one pass.
    pub counting_depth: u32,
    /// Nodes that still held too many points at the counted depth and were divided again from
    /// their own points.
    pub divided_again: usize,
    /// Cores over the limit: points that no division of the grid separates (duplicates).
    pub over_limit: Vec<String>,
}

/// A stream of point records of one layout, read block by block in a fixed order.
pub trait PointSource: Sync {
    /// Names it in messages: the file.
    fn describe(&self) -> String;
    /// Its records' layout.
    fn layout(&self) -> &PointLayout;
    /// Its points, when known in advance (for progress bars).
    fn announced_points(&self) -> Option<u64>;
    /// Calls `each` with consecutive blocks of at most `block_points` records.
    fn for_each_block(&self, block_points: usize, each: &mut dyn FnMut(&[u8]) -> Result<()>) -> Result<u64>;
    /// The number of blocks of `block_points` records that [`PointSource::read_block`] reads
    /// independently of each other (on any thread, in any order), `None` when the source is
    /// read in order only.
    fn random_access_blocks(&self, _block_points: usize) -> Option<u64> {
        None
    }
    /// Reads block `index` of [`PointSource::random_access_blocks`] into `block`, replacing
    /// what it held: the records [`PointSource::for_each_block`] hands over as its block
    /// `index`.
    fn read_block(&self, _block_points: usize, _index: u64, _block: &mut Vec<u8>) -> Result<()> {
        Err(DivideError::Internal(format!(
            "{} is read in order, not by blocks",
            self.describe()
        )))
    }
}

impl PointSource for PointCloudFile {
    fn describe(&self) -> String {
        self.path().display().to_string()
    }

    fn layout(&self) -> &PointLayout {
        PointCloudFile::layout(self)
    }

    fn announced_points(&self) -> Option<u64> {
        PointCloudFile::announced_points(self)
    }

    fn for_each_block(&self, block_points: usize, each: &mut dyn FnMut(&[u8]) -> Result<()>) -> Result<u64> {
        PointCloudFile::for_each_block::<DivideError>(self, block_points, |block| each(block))
    }

    fn random_access_blocks(&self, block_points: usize) -> Option<u64> {
        PointCloudFile::random_access_blocks(self, block_points)
    }

    fn read_block(&self, block_points: usize, index: u64, block: &mut Vec<u8>) -> Result<()> {
        PointCloudFile::read_block(self, block_points, index, block).map_err(DivideError::PointCloud)
    }
}

/// A source, and the box its points are taken from (all of them when `None`).
#[derive(Clone, Copy)]
struct Feed<'a> {
    source: &'a dyn PointSource,
    keep: Option<Bounds>,
}

/// Records per block: the unit of parallel work and of the determinism argument (blocks are
/// cut at fixed record counts, whatever the thread count).
const BLOCK_BYTES: usize = 1 << 18;

/// Blocks a thread works on in a batch of [`stream`]. The threads meet at the end of every
/// batch, where one waits for the other's last block: with two blocks of 1 MiB a thread the
/// write pass kept about 86 % of 2 cores busy, with eight of 256 KiB (the same bytes in
/// flight) about 94 % (3 * 10^8 generated points, alternating: 15.4 and 14.1 s against 16.0
/// and 14.5 s; the same files).
const BATCH_PER_THREAD: usize = 8;

/// The scratch folder inside a division's folder; removed at the start and end of a run.
const STAGING: &str = ".divide-staging";

fn io<'a>(action: &'static str, path: &'a Path) -> impl Fn(std::io::Error) -> DivideError + 'a {
    move |source| DivideError::Io {
        action,
        path: path.to_path_buf(),
        source,
    }
}

/// Divides the point clouds `inputs` (PLY, XYZ, TXT files, PTX or E57 scans, octstore stores:
/// [`open_input`]) into the folder `dir`; a folder that already holds a division gets the new
/// points added to it.
pub fn divide(inputs: &[PathBuf], dir: &Path, options: &DivideOptions) -> Result<DivideReport> {
    divide_inputs(inputs, dir, options)
}

fn divide_inputs(inputs: &[PathBuf], dir: &Path, options: &DivideOptions) -> Result<DivideReport> {
    let opened = inputs
        .iter()
        .map(|path| open_input(path, options.memory_budget))
        .collect::<Result<Vec<_>>>()?;
    let sources: Vec<&dyn PointSource> = opened.iter().map(|s| s.as_ref()).collect();
    divide_sources_as_given(&sources, dir, options)
}

/// [`divide`] of any point sources (files, or generated clouds for benchmarks).
pub fn divide_sources(sources: &[&dyn PointSource], dir: &Path, options: &DivideOptions) -> Result<DivideReport> {
    divide_sources_as_given(sources, dir, options)
}

fn divide_sources_as_given(sources: &[&dyn PointSource], dir: &Path, options: &DivideOptions) -> Result<DivideReport> {
    if options.max_points == 0 {
        return Err(DivideError::MaxPointsZero);
    }
    if !(0.0..1.0).contains(&options.overlap) {
        return Err(DivideError::OverlapOutOfRange {
            overlap: options.overlap,
        });
    }
    let Some(first) = sources.first() else {
        return Err(DivideError::NoInputs);
    };
    for source in sources {
        if source.layout() != first.layout() {
            return Err(DivideError::PropertiesDiffer {
                input: source.describe(),
                properties: property_list(source.layout()),
                other: first.describe(),
                other_properties: property_list(first.layout()),
            });
        }
    }
    std::fs::create_dir_all(dir).map_err(io("create", dir))?;
    let staging = dir.join(STAGING);
    remove_staging(&staging)?;
    std::fs::create_dir_all(&staging).map_err(io("create", &staging))?;
    let existing = manifest::read_manifest(dir)?;
    remove_leftovers(dir, existing.as_ref())?;
    let result = match existing {
        Some(manifest) => incremental::divide_more(sources, dir, manifest, options),
        None => divide_fresh(sources, dir, options),
    };
    // On success and on failure: the folder keeps only what its manifest lists.
    remove_staging(&staging)?;
    result
}

/// Whether `name` is a subspace file's: `L{level}_{x}_{y}_{z}.ply`, optionally with
/// `.g{generation}` before `.ply`.
fn is_subspace_file(name: &str) -> bool {
    let Some(stem) = name.strip_prefix('L').and_then(|n| n.strip_suffix(".ply")) else {
        return false;
    };
    let node = stem.split_once(".g").map_or(stem, |(node, generation)| {
        if !generation.is_empty() && generation.bytes().all(|b| b.is_ascii_digit()) {
            node
        } else {
            ""
        }
    });
    let parts: Vec<&str> = node.split('_').collect();
    parts.len() == 4
        && parts
            .iter()
            .all(|p| !p.is_empty() && p.bytes().all(|b| b.is_ascii_digit()))
}

/// Removes the subspace files of killed runs: those the manifest does not name.
fn remove_leftovers(dir: &Path, manifest: Option<&Manifest>) -> Result<()> {
    let named: std::collections::HashSet<&str> = manifest
        .map(|m| m.subspaces.iter().map(|s| s.file.as_str()).collect())
        .unwrap_or_default();
    for entry in std::fs::read_dir(dir).map_err(io("read", dir))? {
        let entry = entry.map_err(io("read", dir))?;
        let name = entry.file_name().to_string_lossy().into_owned();
        if is_subspace_file(&name) && !named.contains(name.as_str()) {
            let path = entry.path();
            std::fs::remove_file(&path).map_err(io("remove", &path))?;
        }
    }
    Ok(())
}

fn remove_staging(staging: &Path) -> Result<()> {
    match std::fs::remove_dir_all(staging) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(io("remove", staging)(e)),
        _ => Ok(()),
    }
}

fn property_list(layout: &PointLayout) -> String {
    layout
        .properties()
        .iter()
        .map(|(name, scalar)| format!("{} {name}", scalar.name()))
        .collect::<Vec<_>>()
        .join(", ")
}

fn divide_fresh(sources: &[&dyn PointSource], dir: &Path, options: &DivideOptions) -> Result<DivideReport> {
    let layout = sources
        .first()
        .map(|s| s.layout().clone())
        .ok_or(DivideError::NoInputs)?;
    let feeds: Vec<Feed<'_>> = sources.iter().map(|&source| Feed { source, keep: None }).collect();
    let scan = scan(&feeds, &layout, options)?;
    let root = Root::around(scan.low, scan.high).ok_or(DivideError::NoPoints)?;
    let feeds: Vec<Feed<'_>> = scan.order.iter().filter_map(|&i| feeds.get(i).copied()).collect();
    let mut division = Division {
        version: manifest::FORMAT_VERSION,
        root,
        overlap: options.overlap,
        max_points: options.max_points,
        properties: Division::properties_of(&layout),
        generation: 0,
    };
    let mut report = DivideReport {
        input_points: scan.points,
        ..DivideReport::default()
    };
    let mut subspaces = Vec::new();
    let mut context = Context {
        dir,
        layout,
        division: &division,
        options,
        report: &mut report,
    };
    context.divide_node(Node::ROOT, scan.points, &feeds, &mut subspaces)?;
    division.generation = 1;
    commit(dir, subspaces, division, &mut report)?;
    Ok(report)
}

/// Moves the new files from the staging folder into `dir` and writes the manifest, which makes
/// them the division.
fn commit(dir: &Path, subspaces: Vec<Subspace>, division: Division, report: &mut DivideReport) -> Result<()> {
    let staging = dir.join(STAGING);
    for subspace in &subspaces {
        let staged = staging.join(&subspace.file);
        if staged.exists() {
            std::fs::rename(&staged, dir.join(&subspace.file)).map_err(io("move", &staged))?;
        }
    }
    report.subspaces = subspaces.len();
    report.largest_core = subspaces.iter().map(|s| s.core_points).max().unwrap_or(0);
    let manifest = Manifest { subspaces, division };
    manifest::write_manifest(dir, &manifest).map_err(io("write", &dir.join(MANIFEST)))?;
    std::fs::File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(io("sync", dir))
}

/// What the first pass learns: the points' bounds, their number, and the order of the sources
/// by content.
struct Scan {
    low: [f64; 3],
    high: [f64; 3],
    points: u64,
    order: Vec<usize>,
}

fn scan(feeds: &[Feed<'_>], layout: &PointLayout, options: &DivideOptions) -> Result<Scan> {
    let bar = progress(options, "bounds", feeds);
    let mut low = [f64::INFINITY; 3];
    let mut high = [f64::NEG_INFINITY; 3];
    // One source has one order: its blocks are not hashed (xxh3 took about a seventh of
    // the pass's CPU in a profile of 3 * 10^8 generated points) and it has no digest.
    let order_by_content = feeds.len() > 1;
    let mut digests: Vec<xxhash_rust::xxh3::Xxh3> = match order_by_content {
        true => feeds.iter().map(|_| xxhash_rust::xxh3::Xxh3::new()).collect(),
        false => Vec::new(),
    };
    let points = stream(
        feeds,
        layout,
        &bar,
        |block, _| {
            let mut lo = [f64::INFINITY; 3];
            let mut hi = [f64::NEG_INFINITY; 3];
            // Comparisons rather than `f64::min`, which also handles NaN: positions are finite.
            // Not compiled for AVX2 (`crate::sys::with_wide_vectors`): its code for these
            // three-wide rows took twice the time.
            layout.for_each_positions(block, |_, positions| {
                for p in positions {
                    for a in 0..3 {
                        lo[a] = if p[a] < lo[a] { p[a] } else { lo[a] };
                        hi[a] = if p[a] > hi[a] { p[a] } else { hi[a] };
                    }
                }
            });
            (lo, hi, order_by_content.then(|| xxhash_rust::xxh3::xxh3_64(block)))
        },
        |feed, (lo, hi, digest)| {
            for a in 0..3 {
                low[a] = low[a].min(lo[a]);
                high[a] = high[a].max(hi[a]);
            }
            if let (Some(d), Some(digest)) = (digests.get_mut(feed), digest) {
                d.update(&digest.to_le_bytes());
            }
            Ok(())
        },
    )?;
    bar.finish_and_clear();
    // Sources of equal digests hold the same records: their order does not matter.
    let digests: Vec<u128> = digests.iter().map(|d| d.digest128()).collect();
    let mut order: Vec<usize> = (0..feeds.len()).collect();
    order.sort_by_key(|&i| digests.get(i).copied());
    Ok(Scan {
        low,
        high,
        points,
        order,
    })
}

/// The counting pass's work on one block: each record's finest counted cell, added with
/// `adder`, ignoring records outside `keep` or outside the counted node. Run through
/// [`crate::sys::with_wide_vectors`], which decodes the positions in AVX2; the loop over a
/// run of them is a closure that the compiler keeps out of line, for the baseline. (The pass
/// took 2.94, 2.99, 2.99 s on 3 * 10^8 points against 3.14, 2.96, 4.04 s all baseline,
/// alternating.)
struct CountBlock<'a, 'b> {
    layout: &'a PointLayout,
    block: &'a [u8],
    keep: Option<&'a Bounds>,
    locator: NodeLocator,
    cells: CountCells,
    adder: &'a mut CellAdder<'b>,
}

impl WideWork for CountBlock<'_, '_> {
    type Output = ();

    #[inline(always)]
    fn run(self) {
        let (keep, locator, cells, adder) = (self.keep, self.locator, self.cells, self.adder);
        self.layout.for_each_positions(self.block, |_, positions| {
            for &p in positions {
                if keep.is_none_or(|k| k.contains(p))
                    && let Some(cell) = cells.of_index(locator.index(p))
                {
                    adder.add(cell);
                }
            }
        });
    }
}

fn progress(options: &DivideOptions, pass: &str, feeds: &[Feed<'_>]) -> ProgressBar {
    let bar = if options.progress {
        let total: Option<u64> = feeds.iter().map(|f| f.source.announced_points()).sum();
        let bar = total.map_or_else(ProgressBar::no_length, ProgressBar::new);
        bar.set_style(
            indicatif::ProgressStyle::with_template(
                "{prefix:>12} [{bar:40}] {human_pos}/{human_len} points, {elapsed} (eta {eta})",
            )
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
            .progress_chars("=> "),
        );
        bar
    } else {
        ProgressBar::hidden()
    };
    bar.set_prefix(pass.to_string());
    bar
}

/// Runs `work` on every block of every feed, in parallel over a batch of blocks, and
/// `consume` on the results in feed and block order while the next batch is worked on;
/// returns the number of records read.
fn stream<T: Send>(
    feeds: &[Feed<'_>],
    layout: &PointLayout,
    bar: &ProgressBar,
    work: impl Fn(&[u8], Option<&Bounds>) -> T + Sync,
    mut consume: impl FnMut(usize, T) -> Result<()> + Send,
) -> Result<u64> {
    let record_len = layout.record_len().max(1);
    let block_points = (BLOCK_BYTES / record_len).max(1);
    let batch = rayon::current_num_threads() * BATCH_PER_THREAD;
    let started = std::time::Instant::now();
    let mut points = 0;
    // The results of the last batch, not consumed yet, and their feed.
    let mut waiting: Option<(usize, Vec<T>)> = None;
    // Works on the next batch while the last one is consumed.
    let mut overlap = |index: usize, batch: &mut (dyn FnMut() -> Result<Vec<T>> + Send)| -> Result<()> {
        let before = waiting.take();
        let (results, consumed) = rayon::join(batch, || match before {
            Some((index, results)) => results.into_iter().try_for_each(|result| consume(index, result)),
            None => Ok(()),
        });
        consumed?;
        waiting = Some((index, results?));
        Ok(())
    };
    for (index, feed) in feeds.iter().enumerate() {
        let keep = feed.keep.as_ref();
        if let Some(blocks) = feed.source.random_access_blocks(block_points) {
            // Each worker reads its block and works on it while it is in its cache; nothing
            // is copied on one thread.
            let mut buffers: Vec<Vec<u8>> = (0..batch).map(|_| Vec::new()).collect();
            let mut first = 0;
            while first < blocks {
                let last = (first + batch as u64).min(blocks);
                overlap(index, &mut || {
                    let worked = buffers
                        .par_iter_mut()
                        .take((last - first) as usize)
                        .enumerate()
                        .map(|(offset, block)| {
                            feed.source.read_block(block_points, first + offset as u64, block)?;
                            Ok((block.len() / record_len, work(block, keep)))
                        })
                        .collect::<Result<Vec<(usize, T)>>>()?;
                    Ok(worked
                        .into_iter()
                        .map(|(records, result)| {
                            points += records as u64;
                            bar.inc(records as u64);
                            result
                        })
                        .collect())
                })?;
                first = last;
            }
            continue;
        }
        let mut pending: Vec<Vec<u8>> = Vec::with_capacity(batch);
        let mut spare: Vec<Vec<u8>> = Vec::new();
        let mut run = |pending: &mut Vec<Vec<u8>>, spare: &mut Vec<Vec<u8>>| -> Result<()> {
            overlap(index, &mut || {
                Ok(pending.par_iter().map(|block| work(block, keep)).collect())
            })?;
            spare.append(pending);
            Ok(())
        };
        points += feed.source.for_each_block(block_points, &mut |block| {
            let mut owned = spare.pop().unwrap_or_default();
            owned.clear();
            owned.extend_from_slice(block);
            pending.push(owned);
            bar.inc((block.len() / record_len) as u64);
            if pending.len() >= batch {
                run(&mut pending, &mut spare)?;
            }
            Ok(())
        })?;
        run(&mut pending, &mut spare)?;
    }
    // Consumes the last batch.
    overlap(usize::MAX, &mut || Ok(Vec::new()))?;
    tracing::debug!(
        "{}: {points} points in {:.2} s",
        bar.prefix(),
        started.elapsed().as_secs_f64()
    );
    Ok(points)
}

/// [`place_block`] for one record length.
type Placer = fn(&[u8], &PointLayout, &Lookup, &[Bounds], Option<&Bounds>, &mut Bins);

/// [`place_block`] for records of `record_len` bytes: common lengths get copies of a known
/// size (a call to memmove per record costs more than the rest of the placement).
fn placer(record_len: usize) -> Placer {
    match record_len {
        12 => place_block::<12>,
        15 => place_block::<15>,
        24 => place_block::<24>,
        27 => place_block::<27>,
        _ => place_block::<0>,
    }
}

/// The write pass's work on one block: its records, in `bins`, grouped by the targets whose
/// grown cube holds them (a record goes to each of them, in block order), ignoring records
/// outside `keep`. `LEN`, when not 0, is the layout's record length known at compile time.
/// Compiled for the baseline only: in AVX2 (`crate::sys::with_wide_vectors`) the placement
/// took more CPU, 26.5, 24.6, 26.3 s of a whole run of 3 * 10^8 points against 23.9, 23.7,
/// 23.8 s, alternating.
fn place_block<const LEN: usize>(
    block: &[u8],
    layout: &PointLayout,
    lookup: &Lookup,
    grown: &[Bounds],
    keep: Option<&Bounds>,
    bins: &mut Bins,
) {
    let len = if LEN > 0 { LEN } else { layout.record_len() };
    bins.targets.resize_with(grown.len(), Vec::new);
    let targets = &mut bins.targets;
    let mut put = |record: usize, target: u32| {
        if let (Some(bin), Some(bytes)) = (
            targets.get_mut(target as usize),
            block.get(record * len..(record + 1) * len),
        ) {
            bin.extend_from_slice(bytes);
        }
    };
    layout.for_each_positions(block, |first, positions| match keep {
        None => lookup.place_run(positions, grown, |i, target| put(first + i, target)),
        Some(keep) => {
            for (i, &p) in (first..).zip(positions) {
                if keep.contains(p) {
                    lookup.place(p, grown, |target| put(i, target));
                }
            }
        }
    });
}

/// The write pass's records of one block grouped by target: one buffer a target, in the
/// order of the targets' files. A worker fills a set and the pass's consumer empties it into
/// the files; the sets go round a [`BinsPool`] and keep their capacity, so the steady state
/// allocates nothing. (The block's records were first listed as (target, record) pairs and
/// then sorted into one fresh, zeroed buffer a block: the bins skip the list, one copy and
/// the zeroing.)
#[derive(Default)]
struct Bins {
    targets: Vec<Vec<u8>>,
}

/// Bytes the write pass's blocks in flight hold at most, about: [`stream`] works on a batch
/// of [`BATCH_PER_THREAD`] blocks a thread while the last batch's results wait, and a
/// block's [`Bins`] hold its records (once for each target they go to, about 1.4 times with
/// an overlap of 0.1) and up to as much again of spare capacity: three blocks' bytes for each.
fn placing_bytes() -> u64 {
    (rayon::current_num_threads() * BATCH_PER_THREAD * 2 * 3 * BLOCK_BYTES) as u64
}

/// The [`Bins`] not in use.
#[derive(Default)]
struct BinsPool {
    spare: std::sync::Mutex<Vec<Bins>>,
}

impl BinsPool {
    fn take(&self) -> Bins {
        self.spare
            .lock()
            .ok()
            .and_then(|mut spare| spare.pop())
            .unwrap_or_default()
    }

    /// Takes back emptied bins.
    fn give_back(&self, mut bins: Bins) {
        for bin in &mut bins.targets {
            // At most twice what the bin took this time: a run of records that all went to
            // one target (a sorted input sends a block to few targets) does not leave every
            // target holding a block's capacity, and bins of about the same use each time
            // keep theirs.
            bin.shrink_to(2 * bin.len());
            bin.clear();
        }
        if let Ok(mut spare) = self.spare.lock() {
            spare.push(bins);
        }
    }
}

/// What dividing one node needs.
struct Context<'a> {
    dir: &'a Path,
    layout: PointLayout,
    division: &'a Division,
    options: &'a DivideOptions,
    report: &'a mut DivideReport,
}

/// The deepest count grid, at most `wanted` levels, whose counters and lookup fit in half the
/// budget.
fn counting_depth(budget: u64, wanted: u32) -> u32 {
    (1..=wanted.min(10))
        .rev()
        .find(|&d| counts_bytes(d) * 3 / 2 <= budget / 2)
        .unwrap_or(1)
}

/// The lookup's levels: its offsets take 4 bytes a cell.
const MAX_LOOKUP_DEPTH: u32 = 7;

/// The write pass's lookup levels under a node counted `counted` levels deep: one more than
/// counted where that fits half the budget (the counts are gone by then), so that more cells
/// lie wholly inside the grown cubes that reach them and fewer points need a test (measured:
/// one more level took the write pass from 4.0 to 3.7 s on 10^8 points; two more gained
/// nothing, the lookup no longer fitting the cache).
fn lookup_depth(counted: u32, budget: u64) -> u32 {
    // An entry and about two listed targets a cell, 4 bytes each.
    let bytes = |depth: u32| 12 * 8u64.pow(depth);
    let finer = (counted + 1).min(MAX_LOOKUP_DEPTH);
    if bytes(finer) <= budget / 2 {
        finer
    } else {
        counted.min(MAX_LOOKUP_DEPTH)
    }
}

impl Context<'_> {
    /// Levels to count under a node of `points` points: enough for subspaces of about an
    /// eighth of the limit where the points spread evenly, and three more for uneven density
    /// (deeper grids cost cache misses on every point, and the recursion reaches any depth).
    fn wanted_depth(&self, points: u64) -> u32 {
        let parts = points.div_ceil(self.division.max_points.max(1)).max(1);
        let even = (64 - (parts - 1).leading_zeros()).div_ceil(3);
        self.options.max_depth.unwrap_or(even + 3).clamp(1, 10)
    }

    fn file_name(&self, node: Node) -> String {
        match self.division.generation {
            0 => format!("{}.ply", node.name()),
            g => format!("{}.g{g}.ply", node.name()),
        }
    }

    /// Divides the points of `feeds` inside `top`'s core into subspaces under `top`, writing
    /// their files (each with the points of its grown cube among `feeds`) into the staging
    /// folder; appends them to `out`.
    fn divide_node(&mut self, top: Node, top_points: u64, feeds: &[Feed<'_>], out: &mut Vec<Subspace>) -> Result<()> {
        let root = self.division.root;
        let depth =
            counting_depth(self.options.memory_budget, self.wanted_depth(top_points)).min(GRID_BITS - top.level);
        self.report.counting_depth = self.report.counting_depth.max(depth);
        let layout = &self.layout;
        let spare = self.options.memory_budget / 8;
        let mut counts = Counts::new(top, depth, spare);
        let bar = progress(self.options, "counts", feeds);
        stream(
            feeds,
            layout,
            &bar,
            |block, keep| {
                let locator = root.locator(counts.level());
                let cells = counts.cells();
                counts.add_with(|adder| {
                    crate::sys::with_wide_vectors(CountBlock {
                        layout,
                        block,
                        keep,
                        locator,
                        cells,
                        adder,
                    });
                });
            },
            |_, ()| Ok(()),
        )?;
        bar.finish_and_clear();
        counts.finish();
        let (leaves, again) = choose_leaves(&counts, self.division.max_points);
        drop(counts);
        let staging = self.dir.join(STAGING);
        let mut files = Vec::new();
        let mut grown = Vec::new();
        for (node, count) in leaves.iter().chain(&again) {
            let is_leaf = files.len() < leaves.len();
            let name = if is_leaf {
                self.file_name(*node)
            } else {
                format!("again-{}.ply", node.name())
            };
            let core = root.core(*node);
            files.push((
                staging.join(name),
                format!(
                    "core min {:?} size {:?}, overlap {}, {count} core points",
                    core.min,
                    core.max[0] - core.min[0],
                    self.division.overlap
                ),
            ));
            grown.push(root.grown(*node, self.division.overlap));
        }
        let written = self.write_targets(top, depth, feeds, files.clone(), &grown)?;
        for (((node, count), (path, _)), points) in leaves.iter().zip(&files).zip(&written) {
            if *count > self.division.max_points {
                self.report.over_limit.push(node.name());
            }
            self.report.files_written += 1;
            self.report.points_written += points;
            out.push(Subspace {
                file: path
                    .file_name()
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_default(),
                core: Cube::of(&root.core(*node)),
                grown: Cube::of(&root.grown(*node, self.division.overlap)),
                points: *points,
                core_points: *count,
                node: *node,
            });
        }
        for ((node, count), (path, _)) in again.iter().zip(files.iter().skip(leaves.len())) {
            self.report.divided_again += 1;
            let scratch = open_point_cloud(path).map_err(DivideError::PointCloud)?;
            self.divide_node(
                *node,
                *count,
                &[Feed {
                    source: &scratch,
                    keep: None,
                }],
                out,
            )?;
            std::fs::remove_file(path).map_err(io("remove", path))?;
        }
        Ok(())
    }

    /// The write pass: every point of `feeds` goes to each target whose grown cube holds it.
    /// Returns the points each target received.
    fn write_targets(
        &self,
        top: Node,
        depth: u32,
        feeds: &[Feed<'_>],
        files: Vec<(PathBuf, String)>,
        grown: &[Bounds],
    ) -> Result<Vec<u64>> {
        let root = self.division.root;
        let layout = &self.layout;

        let lookup = Lookup::new(&root, top, lookup_depth(depth, self.options.memory_budget), grown);
        // Buffers take at most twice their limit: half of what the lookup leaves, so with the
        // lookup (at most half the budget) at most three quarters of it. Larger buffers make
        // larger writes, which the disk takes faster and with less of the kernel's CPU (10^9
        // points at 256 MiB, four writer threads: with an eighth of the budget, 62.6 and
        // 70.4 s, 12 s in the kernel; with this, 54.4 and 52.7 s, 5 s in the kernel).
        // What the pass's blocks in flight hold is set aside first ([`placing_bytes`]).
        let buffer_limit = usize::try_from(
            self.options
                .memory_budget
                .saturating_sub(lookup.bytes())
                .saturating_sub(placing_bytes())
                / 4,
        )
        .unwrap_or(usize::MAX);
        let mut appenders =
            Appenders::new(layout.clone(), files, buffer_limit).map_err(io("write", &self.dir.join(STAGING)))?;
        let bar = progress(self.options, "writes", feeds);
        let pool = BinsPool::default();
        let place = placer(layout.record_len());
        stream(
            feeds,
            layout,
            &bar,
            |block, keep| {
                let mut bins = pool.take();
                place(block, layout, &lookup, grown, keep, &mut bins);
                bins
            },
            |_, bins: Bins| {
                for (target, bytes) in bins.targets.iter().enumerate() {
                    if !bytes.is_empty() {
                        appenders
                            .append(target, bytes)
                            .map_err(io("write", &self.dir.join(STAGING)))?;
                    }
                }
                pool.give_back(bins);
                Ok(())
            },
        )?;
        bar.finish_and_clear();
        appenders.finish().map_err(io("write", &self.dir.join(STAGING)))
    }
}

#[cfg(test)]
mod tests;
