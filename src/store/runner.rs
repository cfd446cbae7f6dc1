//! The stage runner: every pipeline stage is a named pass over units of work (treetop-keyed
//! ranges), each unit committed on its own, the stage as a whole finished by one version.
//!
//! Invariants:
//! - a unit's segments are named from (stage, target version, unit id, part), so a re-run of a
//!   unit after a crash rewrites the same names with the same bytes;
//! - units are committed in whatever order workers finish, but the catalog holds them as a set
//!   keyed by name, so its content does not depend on thread count or timing;
//! - nothing a run writes is visible to readers before the finishing transaction, which creates
//!   the target version, drops the segments the run replaces and clears the run's progress.

use std::collections::BTreeSet;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use redb::{ReadableTable, WriteTransaction};

use super::catalog::{
    self, META, META_CURRENT_VERSION, SEGMENTS, STAGE_RUNS, SegmentRecord, StageRun, UNITS_DONE, UnitRecord,
    VERSION_TIMES, VERSIONS, VersionRecord,
};
use super::{Result, SegmentContent, Snapshot, Store, StoreError, failpoint};

/// One unit of work of a stage run.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct UnitSpec {
    /// Stable within the run; part of segment names.
    pub id: u64,
    /// For messages: a depth map's file name, a leaf's key range.
    pub label: String,
    /// The cubes the unit works on (for a solution level, its cut's bound), 0 where the stage
    /// does not count them: the measure by which `octstore plan` weighs a cluster run's chunks.
    pub cubes: u64,
}

/// Which previously visible segments of the stage a finished run replaces.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Replace {
    /// Exactly these segments (by file name): a stage that rewrites only what changed.
    Names(BTreeSet<String>),
    /// All of them: the stage's output is rebuilt whole.
    All,
    /// Those whose unit id is among the run's units.
    SameUnits,
    /// None: the run only adds (ingest).
    Nothing,
}

/// What a stage run will do: its units and what its segments replace.
pub struct Plan {
    /// The units, in commit order.
    pub units: Vec<UnitSpec>,
    /// Which earlier segments of the stage the new ones replace.
    pub replace: Replace,
}

/// What a unit produces: segments (each a list of columns) and a small stage-specific record
/// handed to [`Stage::finish`].
#[derive(Default)]
pub struct UnitOutput {
    /// One segment per entry, each as its columns (the key column first), in memory or
    /// spilled to scratch files.
    pub segments: Vec<SegmentContent>,
    /// Stage-specific bytes recorded with the unit (its catalog state).
    pub extra: Vec<u8>,
    /// Rows per compressed block of the unit's segments (0: the format's default).
    pub block_rows: u32,
}

/// A pipeline stage as the runner sees it: it plans units over a pinned version and turns each
/// unit into segments; the runner commits them one unit at a time (format-spec.md, "Commit
/// protocol").
pub trait Stage: Sync {
    /// The stage's name: it names its segments and catalog entries.
    fn name(&self) -> &'static str;

    /// The run's parameters; recorded with the run, and a resume with others is refused.
    fn params(&self) -> Vec<u8> {
        Vec::new()
    }

    /// Digest of everything the stage reads from the store (other stages' content digests).
    /// With [`Stage::params`] it decides whether the stage's output is up to date.
    fn input_digest(&self, _base: &Snapshot<'_>) -> Vec<u8> {
        Vec::new()
    }

    /// The units of this run, in a deterministic order, from the committed state.
    fn plan(&self, base: &Snapshot<'_>) -> Result<Plan>;

    /// The most units the runner computes at once, whatever its thread count: a stage whose
    /// units each use every thread, and whose plan sizes them for the memory of several units,
    /// asks for one.
    fn units_in_flight(&self) -> usize {
        usize::MAX
    }

    /// Computes one unit. Must depend only on `base` and `unit` so that a re-run gives the same
    /// bytes.
    fn run_unit(&self, base: &Snapshot<'_>, unit: &UnitSpec) -> Result<UnitOutput>;

    /// Stage-specific catalog updates in the finishing transaction; returns the version summary.
    fn finish(&self, _txn: &WriteTransaction, _base: &Snapshot<'_>, units: &[(u64, UnitRecord)]) -> Result<String> {
        Ok(format!("{} unit(s)", units.len()))
    }
}

/// How a stage run runs.
#[derive(Clone, Debug)]
pub struct RunOptions {
    /// Continue a run in progress; without it, a run in progress is discarded and restarted.
    pub resume: bool,
    /// Worker threads (units in flight at once).
    pub threads: usize,
    /// Draw a progress bar (only on a terminal).
    pub progress: bool,
}

impl Default for RunOptions {
    fn default() -> Self {
        RunOptions {
            resume: false,
            threads: rayon::current_num_threads(),
            progress: true,
        }
    }
}

/// What a finished stage run did.
#[derive(Clone, Debug, PartialEq)]
pub struct RunReport {
    /// The stage's name.
    pub stage: String,
    /// The version created, or `None` when there was nothing to do.
    pub version: Option<u64>,
    /// Units the run covered.
    pub units: usize,
    /// Units found committed by an earlier, interrupted run.
    pub resumed_units: usize,
    /// Rows written.
    pub rows: u64,
    /// Wall time.
    pub seconds: f64,
    /// The stage's one-line summary (also recorded with the version).
    pub summary: String,
}

/// What the finishing transaction needs to know about the run.
struct FinishingRun<'a> {
    target: u64,
    plan: &'a Plan,
    fingerprint: &'a [u8],
    resumed_units: usize,
    started: Instant,
}

/// A unit whose segments are written and fsynced, waiting for its catalog commit.
pub(crate) type ProducedUnit = (u64, Vec<(String, SegmentRecord)>, Vec<u8>);

/// Makes a unit's segment files in the segments folder: by running it, or (cluster commit) by
/// adopting files that workers wrote. Arguments: the base snapshot, the target version, the unit.
pub(crate) type Producer<'p> = dyn Fn(&Snapshot<'_>, u64, &UnitSpec) -> Result<ProducedUnit> + Sync + 'p;

/// The name of part `part` of unit `unit`'s segment of `stage` at `version`.
pub fn segment_name(stage: &str, version: u64, unit: u64, part: usize) -> String {
    format!("{stage}-v{version:08}-u{unit:010}-p{part:03}.seg")
}

impl Store {
    /// Runs (or resumes) one stage over its units and commits it as a new version.
    pub fn run_stage(&self, stage: &dyn Stage, options: &RunOptions) -> Result<RunReport> {
        self.run_stage_with(stage, options, &|base, target, unit| {
            self.produce_unit(stage, base, target, unit)
        })
    }

    /// [`Store::run_stage`] with the units' segment files made by `producer`.
    pub(crate) fn run_stage_with(
        &self,
        stage: &dyn Stage,
        options: &RunOptions,
        producer: &Producer<'_>,
    ) -> Result<RunReport> {
        let started = Instant::now();
        let db = self.writable()?;
        let name = stage.name();
        let base = self.latest()?;
        let target = base.version() + 1;
        let params = stage.params();
        let fingerprint = {
            let mut f = params.clone();
            f.extend_from_slice(&stage.input_digest(&base));
            f
        };
        if self.stage_fingerprint(name)?.as_deref() == Some(fingerprint.as_slice()) && !self.run_in_progress(name)? {
            return Ok(RunReport {
                stage: name.to_string(),
                version: None,
                units: 0,
                resumed_units: 0,
                rows: 0,
                seconds: started.elapsed().as_secs_f64(),
                summary: "up to date".into(),
            });
        }
        let plan = stage.plan(&base)?;

        // Begin, or pick up, the run record.
        let mut done: BTreeSet<u64> = BTreeSet::new();
        let mut discarded = false;
        {
            let txn = db.begin_write()?;
            {
                let mut runs = txn.open_table(STAGE_RUNS)?;
                let existing: Vec<(String, StageRun)> = runs
                    .iter()?
                    .map(|e| {
                        let (k, v) = e?;
                        let run = catalog::unseal_decode("stage_runs", k.value(), v.value())?;
                        Ok((catalog::key_text("stage_runs", k.value())?.to_string(), run))
                    })
                    .collect::<Result<_>>()?;
                for (other, run) in existing {
                    let same = other == name
                        && run.target_version == target
                        && run.params == params
                        && run.units == plan.units.len() as u64;
                    if same && options.resume {
                        continue;
                    }
                    if other == name && options.resume {
                        tracing::warn!(
                            "stage '{name}': the interrupted run had other parameters or inputs; starting over"
                        );
                    } else if other != name || !same || !options.resume {
                        tracing::info!("stage '{other}': discarding an interrupted run (use --resume to continue it)");
                    }
                    discard_run(&txn, &other)?;
                    discarded = true;
                    runs.remove(other.as_bytes())?;
                }
                if runs.get(name.as_bytes())?.is_none() {
                    let run = StageRun {
                        target_version: target,
                        params: params.clone(),
                        units: plan.units.len() as u64,
                    };
                    runs.insert(
                        name.as_bytes(),
                        catalog::seal_encode("stage_runs", name, &run).as_slice(),
                    )?;
                }
            }
            {
                let units_done = txn.open_table(UNITS_DONE)?;
                for entry in units_done.range((name.as_bytes(), 0)..=(name.as_bytes(), u64::MAX))? {
                    done.insert(entry?.0.value().1);
                }
            }
            txn.commit()?;
        }
        if discarded {
            self.remove_debris()?;
        }

        let pending: Vec<&UnitSpec> = plan.units.iter().filter(|u| !done.contains(&u.id)).collect();
        let resumed_units = plan.units.len() - pending.len();
        if resumed_units > 0 {
            tracing::info!(
                "stage '{name}': resuming, {resumed_units} of {} unit(s) already committed",
                plan.units.len()
            );
        }
        let bar = progress_bar(options.progress, name, plan.units.len() as u64, resumed_units as u64);

        let threads = options.threads.min(stage.units_in_flight()).max(1);
        let outcome = self.run_pending(name, producer, &base, target, &pending, threads, &bar);
        bar.finish_and_clear();
        if let Err(error) = outcome {
            // Bad input cannot be fixed by resuming: abandon the run so the catalog is exactly
            // as it was at the last commit. Other failures (I/O, a full disk) keep the committed
            // units for `--resume`.
            if matches!(error, StoreError::Stage { .. }) {
                self.abandon_run(name)?;
            }
            return Err(error);
        }

        failpoint::hit("stage.before_finish");
        let run = FinishingRun {
            target,
            plan: &plan,
            fingerprint: &fingerprint,
            resumed_units,
            started,
        };
        let report = self.finish_run(stage, &base, &run)?;
        failpoint::hit("stage.after_finish");
        Ok(report)
    }

    #[expect(clippy::too_many_arguments, reason = "one call site; the run's state, spelled out")]
    fn run_pending(
        &self,
        name: &str,
        producer: &Producer<'_>,
        base: &Snapshot<'_>,
        target: u64,
        pending: &[&UnitSpec],
        threads: usize,
        bar: &indicatif::ProgressBar,
    ) -> Result<()> {
        let next = AtomicUsize::new(0);
        let stop = AtomicBool::new(false);
        // Bounded: at most `threads` finished units wait for their commit, which bounds memory.
        let (tx, rx) = mpsc::sync_channel::<Result<ProducedUnit>>(threads);
        std::thread::scope(|scope| -> Result<()> {
            for _ in 0..threads.min(pending.len()) {
                let tx = tx.clone();
                let (next, stop) = (&next, &stop);
                scope.spawn(move || {
                    while !stop.load(Ordering::SeqCst) {
                        let Some(unit) = pending.get(next.fetch_add(1, Ordering::SeqCst)) else {
                            break;
                        };
                        let result = producer(base, target, unit);
                        if tx.send(result).is_err() {
                            break;
                        }
                    }
                });
            }
            drop(tx);
            let mut first_error = None;
            let mut last_trim = Instant::now();
            for result in rx {
                match result.and_then(|(unit, segments, extra)| self.commit_unit(name, unit, segments, extra)) {
                    Ok(()) => {
                        // A unit's buffers are freed by now; without this the C allocator keeps
                        // the pages of its worker arenas, and the process's resident size
                        // creeps up with the number of units (histograms of 13 M -> 53 M cubes
                        // at --memory-budget 256MiB: 210 -> 242 MB; trimming after every unit,
                        // 208 -> 218 MB). At most once a second: returned pages are faulted in
                        // again by the next units, which costs time when units are small.
                        if last_trim.elapsed() >= TRIM_INTERVAL {
                            crate::sys::return_freed_memory();
                            last_trim = Instant::now();
                        }
                        bar.inc(1)
                    }
                    Err(e) => {
                        stop.store(true, Ordering::SeqCst);
                        first_error.get_or_insert(e);
                    }
                }
            }
            first_error.map_or(Ok(()), Err)
        })
    }

    pub(crate) fn produce_unit(
        &self,
        stage: &dyn Stage,
        base: &Snapshot<'_>,
        target: u64,
        unit: &UnitSpec,
    ) -> Result<ProducedUnit> {
        use rayon::prelude::*;
        let output = stage.run_unit(base, unit)?;
        // A unit's parts are files of their own, written on every thread: the histogram
        // step's one RedKitchen unit ended with its 72 parts (55 MB) written one after the
        // other on one core, about half a second. Their records keep the parts' order.
        let written = output
            .segments
            .into_par_iter()
            .enumerate()
            .map(|(part, content)| {
                let file = segment_name(stage.name(), target, unit.id, part);
                let summary = self.write_segment_file(&file, content, output.block_rows)?;
                let record = SegmentRecord::written(stage.name(), unit.id, part, &summary, target);
                Ok((file, record))
            })
            .collect::<Result<Vec<_>>>()?;
        Ok((unit.id, written, output.extra))
    }

    fn commit_unit(
        &self,
        stage: &str,
        unit: u64,
        segments: Vec<(String, SegmentRecord)>,
        extra: Vec<u8>,
    ) -> Result<()> {
        let db = self.writable()?;
        let txn = db.begin_write()?;
        {
            let mut table = txn.open_table(SEGMENTS)?;
            for (name, record) in &segments {
                table.insert(
                    name.as_bytes(),
                    catalog::seal_encode("segments", name.as_str(), record).as_slice(),
                )?;
            }
            let record = UnitRecord {
                segments: segments.into_iter().map(|(n, _)| n).collect(),
                extra,
            };
            txn.open_table(UNITS_DONE)?.insert(
                (stage.as_bytes(), unit),
                catalog::seal_encode("units_done", &(stage, unit), &record).as_slice(),
            )?;
        }
        txn.commit()?;
        failpoint::hit("unit.after_commit");
        Ok(())
    }

    fn finish_run(&self, stage: &dyn Stage, base: &Snapshot<'_>, run: &FinishingRun<'_>) -> Result<RunReport> {
        let name = stage.name();
        let FinishingRun {
            target,
            plan,
            fingerprint,
            resumed_units,
            started,
        } = *run;
        let db = self.writable()?;
        let txn = db.begin_write()?;
        let units: Vec<(u64, UnitRecord)> = {
            let table = txn.open_table(UNITS_DONE)?;
            table
                .range((name.as_bytes(), 0)..=(name.as_bytes(), u64::MAX))?
                .map(|e| {
                    let (k, v) = e?;
                    Ok((
                        k.value().1,
                        catalog::unseal_decode("units_done", &k.value(), v.value())?,
                    ))
                })
                .collect::<Result<_>>()?
        };
        let replaced_units: BTreeSet<u64> = plan.units.iter().map(|u| u.id).collect();
        let mut dropped = 0usize;
        let mut rows = 0u64;
        {
            let mut segments = txn.open_table(SEGMENTS)?;
            let mut updates = Vec::new();
            for entry in segments.iter()? {
                let (file, value) = entry?;
                let mut record: SegmentRecord = catalog::unseal_decode("segments", file.value(), value.value())?;
                let file = catalog::key_text("segments", file.value())?;
                if record.stage != name {
                    continue;
                }
                if record.created == target {
                    rows += record.rows;
                    continue;
                }
                let replaced = match &plan.replace {
                    Replace::Names(names) => names.contains(file),
                    Replace::All => true,
                    Replace::SameUnits => replaced_units.contains(&record.unit),
                    Replace::Nothing => false,
                };
                if replaced && record.visible_at(base.version()) {
                    record.dropped = Some(target);
                    updates.push((file.to_string(), record));
                }
            }
            dropped = dropped.max(updates.len());
            for (file, record) in updates {
                segments.insert(
                    file.as_bytes(),
                    catalog::seal_encode("segments", file.as_str(), &record).as_slice(),
                )?;
            }
        }
        let fingerprint_key = stage_fingerprint_key(name);
        txn.open_table(META)?.insert(
            fingerprint_key.as_bytes(),
            catalog::seal("meta", fingerprint_key.as_str(), fingerprint).as_slice(),
        )?;
        if units.is_empty() && dropped == 0 {
            // Nothing changed: no new version.
            txn.open_table(STAGE_RUNS)?.remove(name.as_bytes())?;
            txn.commit()?;
            return Ok(RunReport {
                stage: name.to_string(),
                version: None,
                units: 0,
                resumed_units,
                rows: 0,
                seconds: started.elapsed().as_secs_f64(),
                summary: "up to date".into(),
            });
        }
        let summary = stage.finish(&txn, base, &units)?;
        {
            let mut done = txn.open_table(UNITS_DONE)?;
            for (unit, _) in &units {
                done.remove((name.as_bytes(), *unit))?;
            }
            txn.open_table(STAGE_RUNS)?.remove(name.as_bytes())?;
            let record = VersionRecord {
                parent: base.version(),
                kind: name.to_string(),
                summary: summary.clone(),
            };
            txn.open_table(VERSIONS)?
                .insert(target, catalog::seal_encode("versions", &target, &record).as_slice())?;
            txn.open_table(VERSION_TIMES)?.insert(target, super::unix_millis())?;
            txn.open_table(META)?.insert(
                META_CURRENT_VERSION.as_bytes(),
                catalog::seal("meta", META_CURRENT_VERSION, &target.to_le_bytes()).as_slice(),
            )?;
        }
        txn.commit()?;
        Ok(RunReport {
            stage: name.to_string(),
            version: Some(target),
            units: units.len(),
            resumed_units,
            rows,
            seconds: started.elapsed().as_secs_f64(),
            summary,
        })
    }
}

fn stage_fingerprint_key(stage: &str) -> String {
    format!("stage_inputs/{stage}")
}

impl Store {
    /// The input fingerprint recorded by the stage's last finished run.
    pub fn stage_fingerprint(&self, stage: &str) -> Result<Option<Vec<u8>>> {
        let txn = self.catalog().begin_read()?;
        let meta = txn.open_table(META)?;
        catalog::meta_bytes(&meta, stage_fingerprint_key(stage).as_str())
    }

    /// Drops a run in progress: its records, then its files.
    pub fn abandon_run(&self, stage: &str) -> Result<()> {
        let txn = self.writable()?.begin_write()?;
        discard_run(&txn, stage)?;
        txn.open_table(STAGE_RUNS)?.remove(stage.as_bytes())?;
        txn.commit()?;
        self.remove_debris()?;
        Ok(())
    }

    /// Units of the stage's run in progress that are committed.
    pub(crate) fn units_done(&self, stage: &str) -> Result<BTreeSet<u64>> {
        let txn = self.catalog().begin_read()?;
        let done = txn.open_table(UNITS_DONE)?;
        let mut units = BTreeSet::new();
        for entry in done.range((stage.as_bytes(), 0)..=(stage.as_bytes(), u64::MAX))? {
            units.insert(entry?.0.value().1);
        }
        Ok(units)
    }

    /// Whether a run of `stage` was begun and not finished (what `--resume` continues).
    pub fn run_in_progress(&self, stage: &str) -> Result<bool> {
        let txn = self.catalog().begin_read()?;
        let runs = txn.open_table(STAGE_RUNS)?;
        Ok(runs.get(stage.as_bytes())?.is_some())
    }
}

/// Removes an interrupted run's progress and the catalog records of its segments; the files
/// themselves become debris, removed after the transaction commits or on the next open.
/// How often the commit loop hands freed memory back to the operating system.
const TRIM_INTERVAL: Duration = Duration::from_secs(1);

pub(crate) fn discard_run(txn: &WriteTransaction, stage: &str) -> Result<()> {
    let mut done = txn.open_table(UNITS_DONE)?;
    let mut segments = txn.open_table(SEGMENTS)?;
    let units: Vec<(u64, UnitRecord)> = done
        .range((stage.as_bytes(), 0)..=(stage.as_bytes(), u64::MAX))?
        .map(|e| {
            let (k, v) = e?;
            Ok((
                k.value().1,
                catalog::unseal_decode("units_done", &k.value(), v.value())?,
            ))
        })
        .collect::<Result<_>>()?;
    for (unit, record) in units {
        for file in &record.segments {
            segments.remove(file.as_bytes())?;
        }
        done.remove((stage.as_bytes(), unit))?;
    }
    Ok(())
}

fn progress_bar(enabled: bool, stage: &str, total: u64, already: u64) -> indicatif::ProgressBar {
    if !enabled {
        return indicatif::ProgressBar::hidden();
    }
    let bar = indicatif::ProgressBar::new(total);
    bar.set_style(
        indicatif::ProgressStyle::with_template("{prefix:>12} [{bar:40}] {pos}/{len} units, {elapsed} (eta {eta})")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    bar.set_prefix(stage.to_string());
    bar.set_position(already);
    bar
}
