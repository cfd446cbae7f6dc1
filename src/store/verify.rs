//! `verify`: every byte of every segment the catalog references, and catalog invariants.

use rayon::prelude::*;
use redb::ReadableTable;
use xxhash_rust::xxh3::xxh3_64;

use super::catalog::{self, SEGMENTS, SegmentRecord};
use super::snapshot::SegmentFile;
use super::{Result, Snapshot, Store, StoreError};
use crate::format::{CubeKey, DecodeError, SegmentPart, SegmentReader};

/// What `verify` checked and found.
#[derive(Debug, Default, Clone)]
pub struct VerifyReport {
    /// Segments checked.
    pub segments: usize,
    /// Bytes checked.
    pub bytes: u64,
    /// Rows checked.
    pub rows: u64,
    /// One line per problem, naming the file and where in it.
    pub problems: Vec<String>,
}

impl VerifyReport {
    /// Whether no problem was found.
    pub fn is_ok(&self) -> bool {
        self.problems.is_empty()
    }
}

/// A stage-specific invariant over a snapshot (key order, 2:1 balance, ...): returns problems.
pub type StageCheck = fn(&Snapshot<'_>) -> Result<Vec<String>>;

fn describe_range(record: &SegmentRecord) -> String {
    let (first, last) = (CubeKey::from_raw(record.first_key), CubeKey::from_raw(record.last_key));
    format!("keys {first}..={last} ({first:?}..={last:?})")
}

/// Describes damage found by the decoder; block damage carries its own column and key range,
/// anything else gets the segment's range from the catalog.
fn damage(shown: &std::path::Display<'_>, record: &SegmentRecord, detail: &DecodeError) -> String {
    let block_level = matches!(
        detail,
        DecodeError::Corrupt {
            part: SegmentPart::Block { .. },
            ..
        } | DecodeError::ChecksumMismatch {
            part: SegmentPart::Block { .. },
            ..
        }
    );
    if block_level {
        format!("corrupt segment {shown}: {detail}")
    } else {
        format!("corrupt segment {shown}: {detail} (segment {})", describe_range(record))
    }
}

/// What is wrong with one segment, as `verify` reports it (file, column, key range).
struct SegmentProblem(String);

/// The first problem of segment `name`, if it has one.
fn segment_problem(store: &Store, name: &str, record: &SegmentRecord) -> Option<String> {
    check_segment(store, name, record)
        .err()
        .map(|SegmentProblem(problem)| problem)
}

fn check_segment(store: &Store, name: &str, record: &SegmentRecord) -> std::result::Result<(), SegmentProblem> {
    let path = store.segment_path(name);
    let shown = path.display();
    let file = SegmentFile::open(path.clone(), record)
        .map_err(|e| SegmentProblem(format!("{e} (segment {})", describe_range(record))))?;
    // Locate the damage first, so the message names the column and key range.
    let located = (|| -> std::result::Result<(), SegmentProblem> {
        let reader =
            SegmentReader::parse(file.bytes()).map_err(|detail| SegmentProblem(damage(&shown, record, &detail)))?;
        let digest = reader
            .verify()
            .map_err(|detail| SegmentProblem(damage(&shown, record, &detail)))?;
        if digest != record.content_digest {
            return Err(SegmentProblem(format!(
                "segment {shown}: content digest {digest:016x} differs from the catalog's {:016x} (segment {})",
                record.content_digest,
                describe_range(record)
            )));
        }
        if reader.rows() != record.rows
            || reader.first_key().raw() != record.first_key
            || reader.last_key().raw() != record.last_key
        {
            return Err(SegmentProblem(format!(
                "segment {shown}: rows or key range differ from the catalog ({} rows, {})",
                record.rows,
                describe_range(record)
            )));
        }
        Ok(())
    })();
    located?;
    let got = xxh3_64(file.bytes());
    if got != record.file_checksum {
        return Err(SegmentProblem(
            StoreError::ChecksumMismatch {
                file: path,
                got,
                expected: record.file_checksum,
            }
            .to_string(),
        ));
    }
    Ok(())
}

/// Segment records by name, and the pin that keeps their files.
type PinnedSegments = (Vec<(String, SegmentRecord)>, Option<super::ReaderPin>);

impl Store {
    /// Checks every segment the catalog references (all kept versions and runs in progress),
    /// then the stage checks on the latest version.
    /// A catalog page that redb cannot read is a finding like a broken seal, not an abort.
    pub fn verify(&self, checks: &[StageCheck]) -> Result<VerifyReport> {
        match super::catalog::contain_redb_panics(|| self.verify_pages_intact(checks)) {
            Ok(report) => report,
            Err(damaged) => Ok(VerifyReport {
                problems: vec![format!("catalog: {damaged}")],
                ..VerifyReport::default()
            }),
        }
    }

    /// The segment records of every version from the gc horizon on, and a reader pin on that
    /// horizon. Records of versions `gc` already retired are left out: their files may go at
    /// any moment.
    fn segments_pinned(&self) -> Result<PinnedSegments> {
        /// Tries before checking without a pin (a `gc` moved the horizon every time).
        const ATTEMPTS: usize = 5;
        let mut attempt = 0;
        loop {
            attempt += 1;
            let horizon = self.gc_horizon()?;
            let pin = super::pins::pin(self.root(), horizon);
            let txn = self.catalog().begin_read()?;
            let meta = txn.open_table(super::catalog::META)?;
            let horizon_now = catalog::meta_u64(&meta, super::catalog::META_GC_HORIZON)?.unwrap_or(0);
            if horizon_now != horizon && attempt < ATTEMPTS {
                continue;
            }
            let table = txn.open_table(SEGMENTS)?;
            let mut records = Vec::new();
            for entry in table.iter()? {
                let (k, v) = entry?;
                let record: SegmentRecord = catalog::unseal_decode("segments", k.value(), v.value())?;
                if record.dropped.is_some_and(|d| d <= horizon_now) {
                    continue;
                }
                records.push((catalog::key_text("segments", k.value())?.to_string(), record));
            }
            return Ok((records, pin));
        }
    }

    /// redb's own check of `catalog.redb`'s page checksums, run on a copy (the check repairs
    /// what it checks, and a reader must not write): a flipped bit that leaves every entry
    /// readable (a table's root pointer cleared, so the table reads as empty) fails there.
    fn catalog_pages_problem(&self) -> Result<Option<String>> {
        let original = self.root().join(super::CATALOG_FILE);
        let copy_dir = tempfile::tempdir().map_err(super::io_error("make a folder for", &original))?;
        let copy = copy_dir.path().join(super::CATALOG_FILE);
        {
            // A read transaction keeps the pages of the version it reads from reuse meanwhile.
            let _held = self.catalog().begin_read()?;
            std::fs::copy(&original, &copy).map_err(super::io_error("copy", &original))?;
        }
        let checked = super::catalog_builder()
            .open(&copy)
            .map_err(redb::Error::from)
            .and_then(|mut db| db.check_integrity().map_err(redb::Error::from));
        Ok(match checked {
            Ok(true) => None,
            Ok(false) => Some("catalog: redb's page checksums do not match: pages of catalog.redb are damaged".into()),
            Err(e) => Some(format!("catalog: redb cannot check catalog.redb: {e}")),
        })
    }

    /// [`Store::verify`], where a damaged catalog page panics inside redb.
    fn verify_pages_intact(&self, checks: &[StageCheck]) -> Result<VerifyReport> {
        // Catalog values first: nothing else can be trusted past a damaged one.
        if self.catalog_format_version()? >= 4 {
            let mut problems = self.catalog().sealing_problems()?;
            problems.extend(self.catalog_pages_problem()?);
            if !problems.is_empty() {
                return Ok(VerifyReport {
                    problems,
                    ..VerifyReport::default()
                });
            }
        }
        // The oldest kept version is pinned, as a reader pins its own, so that a `gc` running
        // beside this check keeps every segment it is about to read.
        let (records, _pin) = self.segments_pinned()?;
        let mut problems: Vec<String> = records
            .par_iter()
            .filter_map(|(name, record)| segment_problem(self, name, record))
            .collect();
        problems.sort();
        let snapshot = self.latest()?;
        for stage in snapshot.stages().map(str::to_string).collect::<Vec<_>>() {
            let segments = snapshot.segments(&stage);
            if segments.iter().any(|(_, r)| r.created > snapshot.version()) {
                problems.push(format!(
                    "stage '{stage}': a segment is newer than the version that sees it"
                ));
            }
        }
        for check in checks {
            problems.extend(check(&snapshot)?);
        }
        Ok(VerifyReport {
            segments: records.len(),
            bytes: records.iter().map(|(_, r)| r.bytes).sum(),
            rows: records.iter().map(|(_, r)| r.rows).sum(),
            problems,
        })
    }
}

/// A stage check: the stage's visible segments cover disjoint, increasing key ranges.
pub fn disjoint_ranges(snapshot: &Snapshot<'_>, stage: &str) -> Vec<String> {
    let mut problems = Vec::new();
    for pair in snapshot.segments(stage).windows(2) {
        if let [(a_name, a), (b_name, b)] = pair
            && a.last_key >= b.first_key
        {
            problems.push(format!(
                "stage '{stage}': segments {a_name} and {b_name} overlap in key range or are out of order"
            ));
        }
    }
    problems
}
