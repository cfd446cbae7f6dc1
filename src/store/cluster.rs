//! Cluster runs: a stage's pending units split into chunks that independent worker processes
//! (Slurm array tasks on nodes sharing the store's filesystem) compute, and one commit that
//! records them as a version.
//!
//! - `plan` (the only writer besides `commit`) records a [`ClusterPlan`] in `meta` under
//!   `cluster_plan/STAGE`: the base version, the stage's input fingerprint, its units in plan
//!   order and the chunk count.
//! - `work` opens the catalog read-only, checks that the store is still at the plan's base, and
//!   computes its chunk's units. Each unit's segments are written into `chunks/STAGE-vTARGET/`
//!   under their final names (temporary name, fsync, rename, directory fsync), then a unit
//!   manifest `uUNIT.unit` (same protocol) that lists them with their records and the unit's
//!   extra bytes. A unit whose manifest is present and whose files verify is skipped, so a
//!   retried or duplicated chunk is harmless: stages are deterministic, so two workers write
//!   identical bytes.
//! - `commit` checks every unit's manifest and every segment's checksums, reports the chunks
//!   that are missing or damaged (and then changes nothing), or else moves the files into
//!   `segments/` and commits them through the stage runner, unit by unit, exactly as a
//!   single-process run would: the result is byte-identical to `octstore solve`.
//!
//! Manifest file: magic `OCTUNIT1` (8 bytes), bincode [`UnitManifest`], xxh3-64 of everything
//! before it (8 bytes LE).

use std::collections::BTreeMap;
use std::fs;
use std::path::{Path, PathBuf};

use redb::ReadableTable;
use serde::{Deserialize, Serialize};

use super::StageError;
use super::catalog::{self, META, SegmentRecord};
use super::runner::{ProducedUnit, Stage, UnitSpec};
use super::{CHUNKS_DIR, Result, RunOptions, RunReport, Store, StoreError, io_error, sync_dir};
use crate::format::segment::SegmentReader;

const MANIFEST_MAGIC: &[u8; 8] = b"OCTUNIT1";
const CHECKSUM_LEN: usize = size_of::<u64>();

/// The work of one cluster run of a stage.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct ClusterPlan {
    /// The stage's name.
    pub stage: String,
    /// The version the workers read; the commit creates `base_version + 1`.
    pub base_version: u64,
    /// The stage's params followed by its input digest at the base version.
    pub fingerprint: Vec<u8>,
    /// Unit ids in plan order; chunk i takes a contiguous slice.
    pub units: Vec<u64>,
    /// Chunks the units are split into, one per worker task.
    pub chunks: u32,
    /// Opaque to the store: what the caller needs to rebuild the same stage (solver params).
    pub args: Vec<u8>,
}

impl ClusterPlan {
    /// The version the commit creates.
    pub fn target(&self) -> u64 {
        self.base_version + 1
    }

    /// The units of chunk `chunk` (empty past the last chunk).
    pub fn chunk_units(&self, chunk: u32) -> &[u64] {
        let (n, k) = (self.units.len() as u64, u64::from(self.chunks.max(1)));
        let (lo, hi) = (n * u64::from(chunk) / k, n * (u64::from(chunk) + 1) / k);
        self.units.get(lo as usize..hi.min(n) as usize).unwrap_or_default()
    }

    /// The error of a commit that found chunks missing or damaged.
    /// The error of a commit that found chunks `missing` or damaged: names them and the first of
    /// the `files` at fault (missing, or not decoding).
    pub fn missing_chunks_error(&self, missing: &std::collections::BTreeSet<u32>, files: &[PathBuf]) -> StoreError {
        cluster_error(
            &self.stage,
            "commit",
            StageError::ChunksMissing {
                stage: self.stage.clone(),
                missing: missing.iter().copied().collect(),
                chunks: self.chunks,
                files: files.to_vec(),
            },
        )
    }

    /// Checks that `chunk` is one of the plan's.
    pub fn check_chunk(&self, chunk: u32) -> Result<()> {
        if chunk >= self.chunks {
            return Err(cluster_error(
                &self.stage,
                format!("chunk {chunk}"),
                StageError::NoSuchChunk { chunks: self.chunks },
            ));
        }
        Ok(())
    }

    /// The chunk that holds `unit`.
    pub fn chunk_of(&self, unit: u64) -> u32 {
        (0..self.chunks)
            .find(|&c| self.chunk_units(c).contains(&unit))
            .unwrap_or(0)
    }
}

/// What a worker wrote for one unit.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
struct UnitManifest {
    unit: u64,
    segments: Vec<(String, SegmentRecord)>,
    extra: Vec<u8>,
}

/// What one worker did with its chunk.
#[derive(Clone, Debug, PartialEq)]
pub struct WorkReport {
    /// Units of the chunk.
    pub units: usize,
    /// Units already complete from an earlier attempt.
    pub skipped: usize,
}

fn plan_key(stage: &str) -> String {
    format!("cluster_plan/{stage}")
}

fn manifest_name(unit: u64) -> String {
    format!("u{unit:010}.unit")
}

fn cluster_error(stage: &str, unit: impl Into<String>, error: StageError) -> StoreError {
    StoreError::Stage {
        stage: stage.into(),
        unit: unit.into(),
        error: Box::new(error),
    }
}

/// A chunk file: an 8-byte magic, the bincode payload, and the xxh3-64 of both (u64 LE).
pub fn encode_chunk_file<T: Serialize>(magic: &[u8; 8], payload: &T) -> Vec<u8> {
    let mut bytes = magic.to_vec();
    bytes.extend(catalog::encode(payload));
    let checksum = xxhash_rust::xxh3::xxh3_64(&bytes);
    bytes.extend(checksum.to_le_bytes());
    bytes
}

/// Decodes a chunk file; `None` for anything damaged (a worker that died mid-write leaves no
/// file at all, thanks to the rename, but disks fail too).
pub fn decode_chunk_file<T: serde::de::DeserializeOwned>(magic: &[u8; 8], bytes: &[u8]) -> Option<T> {
    let split = bytes.len().checked_sub(CHECKSUM_LEN)?;
    let (body, tail) = (bytes.get(..split)?, bytes.get(split..)?);
    let expected = u64::from_le_bytes(tail.try_into().ok()?);
    if xxhash_rust::xxh3::xxh3_64(body) != expected || body.get(..magic.len())? != magic {
        return None;
    }
    catalog::decode("chunk file", body.get(magic.len()..)?).ok()
}

fn encode_manifest(manifest: &UnitManifest) -> Vec<u8> {
    encode_chunk_file(MANIFEST_MAGIC, manifest)
}

fn decode_manifest(bytes: &[u8]) -> Option<UnitManifest> {
    decode_chunk_file(MANIFEST_MAGIC, bytes)
}

/// Whether a written segment file matches its record: length, file checksum, every block.
fn segment_is_intact(path: &Path, record: &SegmentRecord) -> bool {
    let Ok(bytes) = fs::read(path) else { return false };
    if bytes.len() as u64 != record.bytes || xxhash_rust::xxh3::xxh3_64(&bytes) != record.file_checksum {
        return false;
    }
    SegmentReader::parse(&bytes).and_then(|r| r.verify()).is_ok()
}

impl Store {
    /// Where the workers of `plan` write.
    pub fn chunk_dir(&self, plan: &ClusterPlan) -> PathBuf {
        self.root()
            .join(CHUNKS_DIR)
            .join(format!("{}-v{:08}", plan.stage, plan.target()))
    }

    /// The recorded cluster plan of `stage`, if any.
    pub fn cluster_plan(&self, stage: &str) -> Result<Option<ClusterPlan>> {
        let txn = self.catalog().begin_read()?;
        let meta = txn.open_table(META)?;
        let value = meta.get(plan_key(stage).as_bytes())?;
        let key = plan_key(stage);
        value
            .map(|v| catalog::unseal_decode("meta", key.as_str(), v.value()))
            .transpose()
    }

    /// Plans a cluster run of `stage` in `chunks` chunks and records it (replacing an earlier
    /// plan of the stage). An up-to-date stage gets a plan with no units. Also gives each
    /// unit's cubes ([`UnitSpec::cubes`]) in plan order, which the catalog does not record.
    pub fn plan_cluster_run(&self, stage: &dyn Stage, chunks: u32, args: Vec<u8>) -> Result<(ClusterPlan, Vec<u64>)> {
        self.writable()?;
        let name = stage.name();
        if self.run_in_progress(name)? {
            // A single-process run was interrupted: the cluster run replaces it.
            self.abandon_run(name)?;
        }
        let base = self.latest()?;
        let mut fingerprint = stage.params();
        fingerprint.extend(stage.input_digest(&base));
        let up_to_date = self.stage_fingerprint(name)?.as_deref() == Some(fingerprint.as_slice());
        let planned = if up_to_date {
            Vec::new()
        } else {
            stage.plan(&base)?.units
        };
        let units = planned.iter().map(|u| u.id).collect();
        let cubes = planned.iter().map(|u| u.cubes).collect();
        let plan = ClusterPlan {
            stage: name.to_string(),
            base_version: base.version(),
            fingerprint,
            units,
            chunks: chunks.max(1),
            args,
        };
        self.record_cluster_plan(&plan)?;
        Ok((plan, cubes))
    }

    /// Records `plan` (replacing an earlier plan of its stage) and prepares its chunk folder.
    pub fn record_cluster_plan(&self, plan: &ClusterPlan) -> Result<()> {
        let db = self.writable()?;
        let name = plan.stage.as_str();
        // Chunk folders of other plans of this stage are stale.
        let current = self.chunk_dir(plan);
        let root = self.root().join(CHUNKS_DIR);
        if let Ok(entries) = fs::read_dir(&root) {
            for entry in entries.flatten() {
                let path = entry.path();
                let file_name = entry.file_name().to_string_lossy().into_owned();
                if path != current && file_name.starts_with(&format!("{name}-v")) {
                    fs::remove_dir_all(&path).map_err(io_error("remove stale chunks", &path))?;
                }
            }
        }
        fs::create_dir_all(&current).map_err(io_error("create directory", &current))?;
        let txn = db.begin_write()?;
        txn.open_table(META)?.insert(
            plan_key(name).as_bytes(),
            catalog::seal_encode("meta", plan_key(name).as_str(), plan).as_slice(),
        )?;
        txn.commit()?;
        Ok(())
    }

    /// Forgets the plan of `stage` and its chunk folder (after its commit).
    pub fn remove_cluster_plan(&self, plan: &ClusterPlan) -> Result<()> {
        let txn = self.writable()?.begin_write()?;
        txn.open_table(META)?.remove(plan_key(&plan.stage).as_bytes())?;
        txn.commit()?;
        // The files are spent; a failure to remove them costs only disk.
        let _ = fs::remove_dir_all(self.chunk_dir(plan));
        Ok(())
    }

    /// Writes a chunk file: temporary name unique to this process, fsync, rename, dir fsync.
    pub fn write_chunk_file(&self, dir: &Path, name: &str, bytes: &[u8]) -> Result<()> {
        let temp = dir.join(format!("{name}.{}.tmp", std::process::id()));
        let path = dir.join(name);
        let write = || -> std::io::Result<()> {
            let file = fs::File::create(&temp)?;
            std::io::Write::write_all(&mut &file, bytes)?;
            file.sync_all()
        };
        write().map_err(io_error("write chunk file", &temp))?;
        fs::rename(&temp, &path).map_err(io_error("rename", &temp))?;
        sync_dir(dir)
    }

    /// Checks that the store is still where `plan` was made; returns the base snapshot's units.
    fn check_plan(&self, stage: &dyn Stage, plan: &ClusterPlan) -> Result<BTreeMap<u64, UnitSpec>> {
        let name = stage.name();
        let base = self.latest()?;
        let mut fingerprint = stage.params();
        fingerprint.extend(stage.input_digest(&base));
        if base.version() != plan.base_version || fingerprint != plan.fingerprint {
            return Err(cluster_error(
                name,
                "plan",
                StageError::PlanOutdated {
                    now: base.version(),
                    then: plan.base_version,
                },
            ));
        }
        if plan.units.is_empty() {
            return Ok(BTreeMap::new());
        }
        Ok(stage.plan(&base)?.units.into_iter().map(|u| (u.id, u)).collect())
    }

    /// The recorded plan of `name`, or an error that says to plan first.
    pub fn recorded_plan(&self, name: &str) -> Result<ClusterPlan> {
        self.cluster_plan(name)?
            .ok_or_else(|| cluster_error(name, "plan", StageError::NoPlan))
    }

    /// Computes chunk `chunk` of the recorded plan into the chunk folder. Needs only read access
    /// to the catalog; safe to repeat and to run twice at once.
    pub fn work_cluster_chunk(&self, stage: &dyn Stage, chunk: u32) -> Result<WorkReport> {
        let name = stage.name();
        let plan = self.recorded_plan(name)?;
        plan.check_chunk(chunk)?;
        let specs = self.check_plan(stage, &plan)?;
        let dir = self.chunk_dir(&plan);
        fs::create_dir_all(&dir).map_err(io_error("create directory", &dir))?;
        let base = self.latest()?;
        let mut skipped = 0;
        let units = plan.chunk_units(chunk);
        for &unit in units {
            if self.read_unit_manifest(&dir, unit).is_ok() {
                skipped += 1;
                continue;
            }
            let spec = specs
                .get(&unit)
                .ok_or_else(|| cluster_error(name, format!("unit {unit}"), StageError::NotInPlan))?;
            let output = stage.run_unit(&base, spec)?;
            let mut segments = Vec::with_capacity(output.segments.len());
            for (part, content) in output.segments.into_iter().enumerate() {
                let file = super::runner::segment_name(name, plan.target(), unit, part);
                let summary = self.write_segment_in(&dir, &file, content, output.block_rows)?;
                let record = SegmentRecord::written(name, unit, part, &summary, plan.target());
                segments.push((file, record));
            }
            let manifest = UnitManifest {
                unit,
                segments,
                extra: output.extra,
            };
            self.write_unit_manifest(&dir, &manifest)?;
        }
        Ok(WorkReport {
            units: units.len(),
            skipped,
        })
    }

    fn write_unit_manifest(&self, dir: &Path, manifest: &UnitManifest) -> Result<()> {
        self.write_chunk_file(dir, &manifest_name(manifest.unit), &encode_manifest(manifest))
    }

    /// A unit's manifest, if it is intact and every segment it lists is too.
    /// A unit's worker output, or the file at fault: its manifest, missing or not decoding, or
    /// the first segment it lists that is missing or damaged.
    fn read_unit_manifest(&self, dir: &Path, unit: u64) -> std::result::Result<UnitManifest, PathBuf> {
        let path = dir.join(manifest_name(unit));
        let manifest = fs::read(&path)
            .ok()
            .and_then(|bytes| decode_manifest(&bytes))
            .filter(|m| m.unit == unit)
            .ok_or_else(|| path.clone())?;
        match manifest
            .segments
            .iter()
            .find(|(file, record)| !segment_is_intact(&dir.join(file), record))
        {
            Some((file, _)) => Err(dir.join(file)),
            None => Ok(manifest),
        }
    }

    /// Records the recorded plan's chunk outputs as one version. Fails, changing nothing, when
    /// a chunk is missing or damaged, and names those chunks.
    pub fn commit_cluster_run(&self, stage: &dyn Stage, options: &RunOptions) -> Result<RunReport> {
        let name = stage.name();
        self.writable()?;
        let plan = self.recorded_plan(name)?;
        self.check_plan(stage, &plan)?;
        let dir = self.chunk_dir(&plan);
        // Units that an interrupted commit already adopted are in the catalog, not the folder.
        let adopted = if self.run_in_progress(name)? {
            self.units_done(name)?
        } else {
            Default::default()
        };
        let mut manifests = BTreeMap::new();
        let mut missing = std::collections::BTreeSet::new();
        let mut at_fault = Vec::new();
        for &unit in plan.units.iter().filter(|u| !adopted.contains(u)) {
            match self.read_unit_manifest(&dir, unit) {
                Ok(m) => {
                    manifests.insert(unit, m);
                }
                Err(file) => {
                    missing.insert(plan.chunk_of(unit));
                    at_fault.push(file);
                }
            }
        }
        if !missing.is_empty() {
            return Err(plan.missing_chunks_error(&missing, &at_fault));
        }
        let adopt = |_: &super::Snapshot<'_>, target: u64, unit: &UnitSpec| -> Result<ProducedUnit> {
            let manifest = manifests
                .get(&unit.id)
                .ok_or_else(|| cluster_error(name, unit.label.clone(), StageError::NoWorkerOutput))?;
            if target != plan.target() {
                return Err(cluster_error(name, unit.label.clone(), StageError::TargetMoved));
            }
            for (file, _) in &manifest.segments {
                let from = dir.join(file);
                let to = self.segment_path(file);
                fs::rename(&from, &to).map_err(io_error("adopt segment", &from))?;
            }
            sync_dir(&self.segments_dir())?;
            Ok((unit.id, manifest.segments.clone(), manifest.extra.clone()))
        };
        let run = RunOptions {
            // An interrupted commit continues where it stopped.
            resume: true,
            threads: 1,
            progress: options.progress,
        };
        let report = self.run_stage_with(stage, &run, &adopt)?;
        self.remove_cluster_plan(&plan)?;
        Ok(report)
    }
}

#[cfg(test)]
#[expect(clippy::indexing_slicing, reason = "tests: a panic is the failure report")]
mod tests {
    use super::*;

    #[test]
    fn chunks_partition_the_units_in_order() {
        for (n, k) in [(0usize, 3u32), (1, 4), (10, 3), (17, 17), (5, 8)] {
            let plan = ClusterPlan {
                stage: "s".into(),
                base_version: 1,
                fingerprint: Vec::new(),
                units: (0..n as u64).collect(),
                chunks: k,
                args: Vec::new(),
            };
            let all: Vec<u64> = (0..k).flat_map(|c| plan.chunk_units(c).to_vec()).collect();
            assert_eq!(all, plan.units, "{n} units in {k} chunks");
            assert!(plan.chunk_units(k).is_empty());
        }
    }

    #[test]
    fn damaged_manifests_are_rejected() {
        let manifest = UnitManifest {
            unit: 3,
            segments: Vec::new(),
            extra: vec![1, 2, 3],
        };
        let bytes = encode_manifest(&manifest);
        assert_eq!(decode_manifest(&bytes), Some(manifest));
        for i in 0..bytes.len() {
            let mut flipped = bytes.clone();
            flipped[i] ^= 0x10;
            assert_eq!(decode_manifest(&flipped), None, "flip at {i}");
        }
        for cut in 0..bytes.len() {
            assert_eq!(decode_manifest(&bytes[..cut]), None, "cut at {cut}");
        }
    }
}
