//! The store: a directory holding a redb catalog and immutable column segments.
//!
//! Layout: `STORE/catalog.redb` and `STORE/segments/NAME.seg`. The catalog is the single source
//! of truth; a segment file exists on its own only as crash debris (removed on the next writable
//! open) or while its unit of work is being committed.
//!
//! Commit protocol of a unit of work (each step is a failpoint, see `failpoint::FAILPOINTS`):
//! write `NAME.seg.tmp`, fsync it, rename it to `NAME.seg`, fsync the directory, then one catalog
//! write transaction that records the unit and its segments.

// The layers that decode bytes from disk: a damaged byte must give an error, never a panic
// (format-spec.md), so no unwrap, expect or unchecked index outside tests.
#![deny(clippy::unwrap_used, clippy::expect_used, clippy::indexing_slicing)]

pub(crate) mod catalog;
pub(crate) mod cluster;
pub(crate) mod failpoint;
mod pins;
pub mod runner;
pub mod snapshot;
mod spill;
mod stage_error;
pub mod verify;

use std::fs::{self, File};
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};

use redb::{ReadableDatabase, ReadableTable};

use crate::format::segment::{DEFAULT_BLOCK_ROWS, encode_segment_streamed, encode_segment_with_block_rows};
use crate::format::{DecodeError, SegmentSummary};
use catalog::{
    CATALOG_FORMAT_VERSION, META, META_CURRENT_VERSION, META_FORMAT_VERSION, META_GC_HORIZON, SEGMENTS, STAGE_RUNS,
    UNIT_STATE, UNITS_DONE, VERSION_TIMES, VERSIONS,
};
pub use catalog::{SegmentRecord, UnitRecord, VersionRecord, contain_redb_panics};
pub use cluster::{ClusterPlan, WorkReport};
pub use failpoint::IoFaults;
pub use pins::ReaderPin;
pub use runner::{Plan, Replace, RunOptions, RunReport, Stage, UnitOutput, UnitSpec};
pub use snapshot::{SegmentChunks, SegmentFile, Snapshot};
pub use spill::{SegmentContent, SegmentSpill};
pub use stage_error::StageError;

/// The catalog's file name inside a store folder.
pub const CATALOG_FILE: &str = "catalog.redb";
/// The folder of segment files inside a store folder.
pub const SEGMENTS_DIR: &str = "segments";
/// Scratch space of stages (sorted runs, level sets); never part of a version, emptied on every
/// writable open.
pub const SCRATCH_DIR: &str = "tmp";
/// Segment files that cluster workers wrote and `commit` has not yet adopted (`cluster.rs`).
pub const CHUNKS_DIR: &str = "chunks";
const SEGMENT_SUFFIX: &str = ".seg";
const TEMP_SUFFIX: &str = ".tmp";

/// Errors of the store layer. Each names the file, table, version or unit it concerns.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum StoreError {
    /// A file operation failed.
    #[error("{action} {path}: {source}")]
    Io {
        /// What was being done.
        action: &'static str,
        /// The file or folder.
        path: PathBuf,
        /// The system's error.
        source: std::io::Error,
    },
    /// Another process holds the catalog for writing.
    #[error(
        "{path} is in use by another octstore process (one writer at a time: run this when it has finished; readers such as info, query, extract and verify run beside it)"
    )]
    InUse {
        /// The store.
        path: PathBuf,
    },
    /// The folder is not a store.
    #[error("{path} is not an octstore store: {reason}")]
    NotAStore {
        /// The folder.
        path: PathBuf,
        /// What is missing or wrong.
        reason: String,
    },
    /// `create` found a store already there.
    #[error("{path} already holds a store")]
    AlreadyExists {
        /// The folder.
        path: PathBuf,
    },
    /// A read-only open found a catalog that a crashed writer left; a writable open repairs it.
    #[error(
        "{path}: the catalog was not closed cleanly; open it for writing once (for example `octstore verify`) to recover it"
    )]
    NeedsRecovery {
        /// The store.
        path: PathBuf,
    },
    /// The catalog is of a newer format than this build reads.
    #[error("catalog format version {found} is not supported by this build (it reads versions up to {supported})")]
    UnsupportedFormat {
        /// The catalog's version.
        found: u32,
        /// The newest version this build reads.
        supported: u32,
    },
    /// redb failed.
    #[error("catalog error: {0}")]
    Catalog(#[from] redb::Error),
    /// A catalog record does not decode.
    #[error("corrupt catalog table '{table}': {reason}")]
    CatalogCorruption {
        /// The table.
        table: &'static str,
        /// What does not decode.
        reason: String,
    },
    /// redb cannot read the catalog's pages: it panicked on them (see
    /// [`catalog::contain_redb_panics`]).
    #[error("catalog.redb is damaged: redb cannot read it ({detail})")]
    DamagedCatalog {
        /// redb's panic message.
        detail: String,
    },
    /// A segment's bytes do not decode.
    #[error("corrupt segment {file}: {detail}")]
    Corruption {
        /// The segment file.
        file: PathBuf,
        /// Where and what the decoder found.
        detail: DecodeError,
    },
    /// A segment file's whole-file checksum differs from the catalog's.
    #[error("segment {file}: checksum mismatch: got {got:016x}, expected {expected:016x}")]
    ChecksumMismatch {
        /// The segment file.
        file: PathBuf,
        /// The checksum of the bytes on disk.
        got: u64,
        /// The catalog's checksum.
        expected: u64,
    },
    /// An fsync failed earlier: nothing more is written until the store is reopened.
    #[error(
        "the store refuses writes after a failed fsync: data may not be durable; reopen it to continue from the last commit"
    )]
    Poisoned,
    /// A write was asked of a read-only handle.
    #[error("the store is open read-only")]
    ReadOnly,
    /// A version after the latest was asked for.
    #[error("version {version} does not exist (the latest is {latest})")]
    NoSuchVersion {
        /// The version asked for.
        version: u64,
        /// The latest version.
        latest: u64,
    },
    /// A version whose segments `gc` removed was asked for.
    #[error("version {version} was garbage-collected (the oldest kept version is {horizon})")]
    VersionGone {
        /// The version asked for.
        version: u64,
        /// The oldest version still readable.
        horizon: u64,
    },
    /// A stage failed on a unit (bad input, a missing earlier stage, an internal check).
    #[error("stage '{stage}', {unit}: {error}")]
    Stage {
        /// The stage.
        stage: String,
        /// The unit (a depth map, a treetop leaf) or `-`.
        unit: String,
        /// What went wrong; its message says what to do (boxed: it is the largest variant's).
        error: Box<StageError>,
    },
    /// A stage produced columns that break the segment format.
    #[error("invalid segment content: {0}")]
    Encode(#[from] crate::format::EncodeError),
}

macro_rules! redb_error {
    ($($t:ty),*) => {$(
        impl From<$t> for StoreError {
            fn from(e: $t) -> Self {
                StoreError::Catalog(e.into())
            }
        }
    )*};
}
redb_error!(
    redb::TransactionError,
    redb::TableError,
    redb::StorageError,
    redb::CommitError
);

/// The result of store calls.
pub type Result<T, E = StoreError> = std::result::Result<T, E>;

/// `map_err` adapter: an I/O error of `action` on `path`.
pub fn io_error(action: &'static str, path: &Path) -> impl FnOnce(std::io::Error) -> StoreError {
    let path = path.to_path_buf();
    move |source| StoreError::Io { action, path, source }
}

/// The redb catalog, opened for writing or read-only.
pub enum Catalog {
    /// Opened by the one writer.
    Writable(redb::Database),
    /// Opened by a reader while a writer may run.
    ReadOnly(redb::ReadOnlyDatabase),
}

impl Catalog {
    /// A read transaction on either kind of handle.
    pub fn begin_read(&self) -> Result<redb::ReadTransaction> {
        Ok(match self {
            Catalog::Writable(db) => db.begin_read()?,
            Catalog::ReadOnly(db) => db.begin_read()?,
        })
    }

    /// Values that are unsealed or fail their seal (`catalog::sealing_problems`).
    pub fn sealing_problems(&self) -> Result<Vec<String>> {
        match self {
            Catalog::Writable(db) => catalog::sealing_problems(db),
            Catalog::ReadOnly(db) => catalog::sealing_problems(db),
        }
    }
}

/// An open store. One process at a time may hold it writable; read-only handles may be opened
/// alongside, and each reads the versions it pins.
pub struct Store {
    root: PathBuf,
    catalog: Catalog,
    faults: IoFaults,
    poisoned: AtomicBool,
}

fn unix_millis() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_millis() as u64)
        .unwrap_or(0)
}

pub(crate) fn sync_dir(path: &Path) -> Result<()> {
    File::open(path)
        .and_then(|dir| dir.sync_all())
        .map_err(io_error("fsync directory", path))
}

/// How processes share the catalog: one writer, and any number of read-only processes that open
/// it while the writer runs and read the versions they pin. Readers and the writer must agree on
/// the mode: it is part of the on-disk protocol (format-spec.md, "Catalog").
pub(crate) fn catalog_builder() -> redb::Builder {
    let mut builder = redb::Builder::new();
    builder.set_concurrency_mode(redb::ConcurrencyMode::SingleWriter);
    builder.set_cache_size(CATALOG_CACHE_BYTES);
    builder
}

/// redb's page cache for the catalog. redb's default (1 GiB) is a ceiling, not a reservation,
/// and a long run creeps towards it: pages of every unit commit and segment lookup stay cached,
/// and the catalog grows with the scene (49 MB after the histograms of a 53-million-cube city).
/// The B-tree's interior pages, which every lookup touches, fit in far less; leaf pages are
/// read about once per unit, from the OS page cache. Part of the fixed overhead outside
/// `--memory-budget`'s shares.
pub const CATALOG_CACHE_BYTES: usize = 32 << 20;

fn map_open_error(path: &Path, e: redb::DatabaseError) -> StoreError {
    match e {
        redb::DatabaseError::DatabaseAlreadyOpen => StoreError::InUse {
            path: path.to_path_buf(),
        },
        redb::DatabaseError::RepairAborted => StoreError::NeedsRecovery {
            path: path.to_path_buf(),
        },
        other => StoreError::Catalog(other.into()),
    }
}

impl Store {
    /// Creates an empty store (version 0) in `path`, which must not hold one already.
    pub fn create(path: impl AsRef<Path>) -> Result<Store> {
        Store::create_with_faults(path, IoFaults::from_env())
    }

    /// [`Store::create`] with injected storage faults (tests of failure handling).
    pub fn create_with_faults(path: impl AsRef<Path>, faults: IoFaults) -> Result<Store> {
        let root = path.as_ref().to_path_buf();
        let catalog_path = root.join(CATALOG_FILE);
        if catalog_path.exists() {
            return Err(StoreError::AlreadyExists { path: root });
        }
        fs::create_dir_all(root.join(SEGMENTS_DIR)).map_err(io_error("create directory", &root))?;
        // The catalog is built under a temporary name of this process's and linked into place
        // only once it is complete, so a crash during creation never leaves a catalog without
        // its tables, and of two processes creating the same store at once one wins and the
        // other is told the store is in use (a rename would replace the winner's catalog).
        let temp_path = root.join(format!("{CATALOG_FILE}.{}{TEMP_SUFFIX}", std::process::id()));
        match fs::remove_file(&temp_path) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                return Err(io_error("remove", &temp_path)(e));
            }
            _ => {}
        }
        {
            let db = catalog_builder()
                .create(&temp_path)
                .map_err(|e| map_open_error(&root, e))?;
            let txn = db.begin_write()?;
            {
                let mut meta = txn.open_table(META)?;
                for (key, value) in [
                    (META_FORMAT_VERSION, CATALOG_FORMAT_VERSION.to_le_bytes().to_vec()),
                    (META_CURRENT_VERSION, 0u64.to_le_bytes().to_vec()),
                    (META_GC_HORIZON, 0u64.to_le_bytes().to_vec()),
                ] {
                    meta.insert(key.as_bytes(), catalog::seal("meta", key, &value).as_slice())?;
                }
                let record = VersionRecord {
                    parent: 0,
                    kind: "create".into(),
                    summary: "empty store".into(),
                };
                txn.open_table(VERSIONS)?
                    .insert(0, catalog::seal_encode("versions", &0u64, &record).as_slice())?;
                txn.open_table(VERSION_TIMES)?.insert(0, unix_millis())?;
                // Create every table so read-only opens find them.
                txn.open_table(SEGMENTS)?;
                txn.open_table(STAGE_RUNS)?;
                txn.open_table(UNITS_DONE)?;
                txn.open_table(UNIT_STATE)?;
            }
            txn.commit()?;
        }
        match fs::hard_link(&temp_path, &catalog_path) {
            Ok(()) => fs::remove_file(&temp_path).map_err(io_error("remove", &temp_path))?,
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                let _ = fs::remove_file(&temp_path);
                return Err(StoreError::InUse { path: root });
            }
            // A file system without hard links: a plain rename (not safe against a second
            // creator at the same moment, which such file systems rarely see).
            Err(_) => fs::rename(&temp_path, &catalog_path).map_err(io_error("rename", &temp_path))?,
        }
        sync_dir(&root)?;
        let db = catalog_builder()
            .open(&catalog_path)
            .map_err(|e| map_open_error(&root, e))?;
        Ok(Store {
            root,
            catalog: Catalog::Writable(db),
            faults,
            poisoned: AtomicBool::new(false),
        })
    }

    /// Opens a store for writing (exclusive), recovering the catalog if needed and removing
    /// segment files that no commit references.
    pub fn open(path: impl AsRef<Path>) -> Result<Store> {
        Store::open_with_faults(path, IoFaults::from_env())
    }

    /// [`Store::open`] with injected storage faults (tests of failure handling).
    pub fn open_with_faults(path: impl AsRef<Path>, faults: IoFaults) -> Result<Store> {
        // redb panics on some damaged pages of the header and directory.
        catalog::contain_redb_panics(|| Store::open_with_faults_unguarded(path.as_ref(), faults))?
    }

    fn open_with_faults_unguarded(path: &Path, faults: IoFaults) -> Result<Store> {
        let root = path.to_path_buf();
        let catalog_path = Store::catalog_path_checked(&root)?;
        let db = catalog_builder()
            .open(&catalog_path)
            .map_err(|e| map_open_error(&root, e))?;
        catalog::check_directory(&db)?;
        let store = Store {
            root,
            catalog: Catalog::Writable(db),
            faults,
            poisoned: AtomicBool::new(false),
        };
        let found = store.check_format()?;
        if found < CATALOG_FORMAT_VERSION {
            store.migrate(found)?;
        }
        store.remove_debris()?;
        let scratch = store.root.join(SCRATCH_DIR);
        if scratch.exists() {
            fs::remove_dir_all(&scratch).map_err(io_error("remove scratch", &scratch))?;
        }
        Ok(store)
    }

    /// Opens a store for reading only. Any number of readers may share it, also while a writer
    /// runs: a snapshot pins its version, whose segments stay until `gc` retires the version.
    pub fn open_read_only(path: impl AsRef<Path>) -> Result<Store> {
        // redb panics on some damaged pages of the header and directory.
        catalog::contain_redb_panics(|| Store::open_read_only_unguarded(path.as_ref()))?
    }

    fn open_read_only_unguarded(path: &Path) -> Result<Store> {
        let root = path.to_path_buf();
        let catalog_path = Store::catalog_path_checked(&root)?;
        let db = catalog_builder()
            .open_read_only(&catalog_path)
            .map_err(|e| map_open_error(&root, e))?;
        catalog::check_directory(&db)?;
        let store = Store {
            root,
            catalog: Catalog::ReadOnly(db),
            faults: IoFaults::none(),
            poisoned: AtomicBool::new(false),
        };
        store.check_format()?;
        Ok(store)
    }

    /// Opens read-only, or for writing when the catalog first needs recovery after a crash.
    pub fn open_for_reading(path: impl AsRef<Path>) -> Result<Store> {
        match Store::open_read_only(path.as_ref()) {
            Err(StoreError::NeedsRecovery { .. }) => Store::open(path),
            other => other,
        }
    }

    fn catalog_path_checked(root: &Path) -> Result<PathBuf> {
        let catalog_path = root.join(CATALOG_FILE);
        if !catalog_path.is_file() {
            return Err(StoreError::NotAStore {
                path: root.to_path_buf(),
                reason: format!("no {CATALOG_FILE} (create one with `octstore ingest` or `octstore demo`)"),
            });
        }
        Ok(catalog_path)
    }

    /// Brings an older catalog to this build's version in one transaction (format-spec.md,
    /// "Version changes"); a crash before its commit leaves the older catalog as it was.
    fn migrate(&self, found: u32) -> Result<()> {
        let db = self.writable()?;
        let txn = db.begin_write()?;
        if found < 2 {
            if txn
                .open_table(STAGE_RUNS)?
                .get(catalog::HISTOGRAMS.as_bytes())?
                .is_some()
            {
                runner::discard_run(&txn, catalog::HISTOGRAMS)?;
                txn.open_table(STAGE_RUNS)?.remove(catalog::HISTOGRAMS.as_bytes())?;
            }
            catalog::migrate_v1(&txn)?;
        }
        if found < 3 {
            catalog::migrate_v2(&txn)?;
        }
        if found < 4 {
            catalog::migrate_v3(&txn)?;
        }
        txn.open_table(META)?.insert(
            META_FORMAT_VERSION.as_bytes(),
            catalog::seal("meta", META_FORMAT_VERSION, &CATALOG_FORMAT_VERSION.to_le_bytes()).as_slice(),
        )?;
        txn.commit()?;
        Ok(())
    }

    /// The version of the catalog's encoding (read-only opens read older ones as they are).
    pub fn catalog_format_version(&self) -> Result<u32> {
        self.check_format()
    }

    /// The catalog's format version, if this build reads it.
    fn check_format(&self) -> Result<u32> {
        let txn = self.catalog.begin_read()?;
        let meta = txn.open_table(META).map_err(|e| StoreError::NotAStore {
            path: self.root.clone(),
            reason: format!("catalog has no meta table ({e})"),
        })?;
        let found = match catalog::meta_bytes(&meta, META_FORMAT_VERSION)? {
            Some(v) => v
                .as_slice()
                .try_into()
                .map(u32::from_le_bytes)
                .map_err(|_| StoreError::CatalogCorruption {
                    table: "meta",
                    reason: "format_version is not 4 bytes".into(),
                })?,
            None => {
                return Err(StoreError::NotAStore {
                    path: self.root.clone(),
                    reason: "catalog has no format_version".into(),
                });
            }
        };
        if !(catalog::OLDEST_CATALOG_FORMAT_VERSION..=CATALOG_FORMAT_VERSION).contains(&found) {
            return Err(StoreError::UnsupportedFormat {
                found,
                supported: CATALOG_FORMAT_VERSION,
            });
        }
        Ok(found)
    }

    /// The store's folder.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// The folder of segment files.
    pub fn segments_dir(&self) -> PathBuf {
        self.root.join(SEGMENTS_DIR)
    }

    /// The path of segment `name`.
    pub fn segment_path(&self, name: &str) -> PathBuf {
        self.segments_dir().join(name)
    }

    /// A stage's scratch folder, created empty.
    pub fn scratch_dir(&self, stage: &str) -> Result<PathBuf> {
        let dir = self.scratch_path(stage);
        if dir.exists() {
            fs::remove_dir_all(&dir).map_err(io_error("remove scratch", &dir))?;
        }
        fs::create_dir_all(&dir).map_err(io_error("create scratch", &dir))?;
        Ok(dir)
    }

    /// Where `stage` keeps scratch files (not created).
    pub fn scratch_path(&self, stage: &str) -> PathBuf {
        self.root.join(SCRATCH_DIR).join(stage)
    }

    /// Whether this handle was opened read-only.
    pub fn is_read_only(&self) -> bool {
        matches!(self.catalog, Catalog::ReadOnly(_))
    }

    /// The catalog, for reads.
    pub fn catalog(&self) -> &Catalog {
        &self.catalog
    }

    /// The catalog for writing; an error on a read-only or poisoned store.
    pub fn writable(&self) -> Result<&redb::Database> {
        if self.poisoned.load(Ordering::SeqCst) {
            return Err(StoreError::Poisoned);
        }
        match &self.catalog {
            Catalog::Writable(db) => Ok(db),
            Catalog::ReadOnly(_) => Err(StoreError::ReadOnly),
        }
    }

    /// Whether a failed fsync has poisoned this handle.
    pub fn is_poisoned(&self) -> bool {
        self.poisoned.load(Ordering::SeqCst)
    }

    /// The oldest version `gc` kept readable.
    pub fn gc_horizon(&self) -> Result<u64> {
        let txn = self.catalog.begin_read()?;
        let meta = txn.open_table(META)?;
        Ok(catalog::meta_u64(&meta, META_GC_HORIZON)?.unwrap_or(0))
    }

    /// The latest committed version.
    pub fn current_version(&self) -> Result<u64> {
        let txn = self.catalog.begin_read()?;
        let meta = txn.open_table(META)?;
        catalog::meta_u64(&meta, META_CURRENT_VERSION)?.ok_or(StoreError::CatalogCorruption {
            table: "meta",
            reason: "no current_version".into(),
        })
    }

    /// A consistent view of the latest committed version.
    pub fn latest(&self) -> Result<Snapshot<'_>> {
        Snapshot::load(self, None)
    }

    /// A consistent view pinned to `version`.
    pub fn snapshot(&self, version: u64) -> Result<Snapshot<'_>> {
        Snapshot::load(self, Some(version))
    }

    /// Every version record, oldest first, with its commit time (ms since the epoch).
    pub fn log(&self) -> Result<Vec<(u64, VersionRecord, Option<u64>)>> {
        let txn = self.catalog.begin_read()?;
        let versions = txn.open_table(VERSIONS)?;
        let times = txn.open_table(VERSION_TIMES)?;
        let mut out = Vec::new();
        for entry in versions.iter()? {
            let (k, v) = entry?;
            let record: VersionRecord = catalog::unseal_decode("versions", &k.value(), v.value())?;
            let time = times.get(k.value())?.map(|t| t.value());
            out.push((k.value(), record, time));
        }
        Ok(out)
    }

    /// The catalog's canonical content (see `catalog::canonical_dump`); a page redb cannot
    /// read is [`StoreError::DamagedCatalog`].
    pub fn canonical_dump(&self) -> Result<Vec<u8>> {
        catalog::contain_redb_panics(|| match &self.catalog {
            Catalog::Writable(db) => catalog::canonical_dump(db),
            Catalog::ReadOnly(db) => catalog::canonical_dump(db),
        })?
    }

    /// Writes one segment through the commit protocol's file steps: temporary name, fsync,
    /// rename, directory fsync. The caller then records it in a catalog transaction.
    pub(crate) fn write_segment_file(
        &self,
        name: &str,
        content: SegmentContent,
        block_rows: u32,
    ) -> Result<SegmentSummary> {
        self.writable()?;
        let final_path = self.segment_path(name);
        let temp_path = self.segment_path(&format!("{name}{TEMP_SUFFIX}"));
        self.write_segment_at(&temp_path, &final_path, content, block_rows)
    }

    /// Writes a segment into `dir` (a cluster chunk folder) through a temporary name unique to
    /// this process and thread, so that two workers given the same chunk never share a file
    /// being written; both rename identical bytes into place.
    pub(crate) fn write_segment_in(
        &self,
        dir: &Path,
        name: &str,
        content: SegmentContent,
        block_rows: u32,
    ) -> Result<SegmentSummary> {
        let temp_name = format!(
            "{name}.{}-{:?}{TEMP_SUFFIX}",
            std::process::id(),
            std::thread::current().id()
        )
        .replace(
            |c: char| !c.is_ascii_alphanumeric() && c != '.' && c != '-' && c != '_',
            "",
        );
        self.write_segment_at(&dir.join(temp_name), &dir.join(name), content, block_rows)
    }

    fn write_segment_at(
        &self,
        temp_path: &Path,
        final_path: &Path,
        content: SegmentContent,
        block_rows: u32,
    ) -> Result<SegmentSummary> {
        let result = self.write_segment_steps(temp_path, final_path, content, block_rows);
        if result.is_err() {
            // Best effort: debris left here is also removed on the next open.
            let _ = fs::remove_file(temp_path);
        }
        result
    }

    fn write_segment_steps(
        &self,
        temp_path: &Path,
        final_path: &Path,
        content: SegmentContent,
        block_rows: u32,
    ) -> Result<SegmentSummary> {
        let file = File::create(temp_path).map_err(io_error("create", temp_path))?;
        let mut writer = BufWriter::with_capacity(
            1 << 20,
            FaultyWriter {
                inner: &file,
                faults: &self.faults,
            },
        );
        let block_rows = if block_rows == 0 {
            DEFAULT_BLOCK_ROWS
        } else {
            block_rows
        };
        let encoded = match content {
            SegmentContent::Columns(columns) => encode_segment_with_block_rows(&columns, block_rows, &mut writer),
            SegmentContent::Spilled(spill) => {
                let (shapes, rows, mut sources) =
                    spill.into_sources().map_err(io_error("read scratch of", temp_path))?;
                encode_segment_streamed(&shapes, rows, &mut sources, block_rows, &mut writer)
            }
        };
        let summary = encoded.map_err(|e| match e {
            crate::format::EncodeError::Io(source) => StoreError::Io {
                action: "write",
                path: temp_path.to_path_buf(),
                source,
            },
            other => StoreError::Encode(other),
        })?;
        writer.flush().map_err(io_error("write", temp_path))?;
        drop(writer);
        failpoint::hit("segment.after_write");
        let synced = self.faults.before_fsync().and_then(|()| file.sync_all());
        if let Err(source) = synced {
            // After a failed fsync the kernel may have dropped dirty pages: nothing written since
            // the last successful sync can be trusted, so the store refuses further writes.
            self.poisoned.store(true, Ordering::SeqCst);
            return Err(StoreError::Io {
                action: "fsync",
                path: temp_path.to_path_buf(),
                source,
            });
        }
        drop(file);
        failpoint::hit("segment.after_fsync");
        fs::rename(temp_path, final_path).map_err(io_error("rename", temp_path))?;
        failpoint::hit("segment.after_rename");
        if let Err(e) = sync_dir(final_path.parent().unwrap_or(&self.root)) {
            self.poisoned.store(true, Ordering::SeqCst);
            return Err(e);
        }
        failpoint::hit("segment.after_dir_fsync");
        Ok(summary)
    }

    /// Removes segment files that no catalog record references: debris of a crash between a
    /// segment's rename and its unit's commit, and temporary files.
    pub(crate) fn remove_debris(&self) -> Result<Vec<String>> {
        let referenced: std::collections::BTreeSet<String> = {
            let txn = self.catalog.begin_read()?;
            let segments = txn.open_table(SEGMENTS)?;
            let mut names = std::collections::BTreeSet::new();
            for entry in segments.iter()? {
                names.insert(catalog::key_text("segments", entry?.0.value())?.to_string());
            }
            names
        };
        let dir = self.segments_dir();
        let mut removed = Vec::new();
        let entries = fs::read_dir(&dir).map_err(io_error("list", &dir))?;
        for entry in entries {
            let entry = entry.map_err(io_error("list", &dir))?;
            let name = entry.file_name().to_string_lossy().into_owned();
            if !referenced.contains(&name) && (name.ends_with(SEGMENT_SUFFIX) || name.ends_with(TEMP_SUFFIX)) {
                fs::remove_file(entry.path()).map_err(io_error("remove debris", &entry.path()))?;
                removed.push(name);
            }
        }
        if !removed.is_empty() {
            tracing::info!(
                "removed {} unreferenced segment file(s) left by an interrupted run",
                removed.len()
            );
            sync_dir(&dir)?;
        }
        Ok(removed)
    }

    /// Drops catalog records and files of segments that no version from `current - keep + 1`
    /// on can see, and of abandoned runs. Returns (files removed, bytes freed).
    ///
    /// Two steps, so that a reader in another process never loses a file it counts on: the new
    /// horizon (held back to the oldest version a reader has open) is committed first, and the
    /// reader pins are listed again before anything goes. A reader pins the horizon it read
    /// and then reads the horizon again (a changed one makes it try again): a pin made before
    /// the second listing keeps its version's files, and one made after it saw the new horizon.
    pub fn gc(&self, keep: u64) -> Result<(usize, u64)> {
        let db = self.writable()?;
        let current = self.current_version()?;
        // Never back: versions behind an earlier horizon have lost their files.
        let earlier = self.gc_horizon()?;
        let oldest_pinned = || -> Result<Option<u64>> {
            let pinned = pins::live_pinned_versions(&self.root)
                .map_err(io_error("list reader pins", &self.root.join(pins::PINS_DIR)))?;
            Ok(pinned.first().copied())
        };
        let kept_from = |horizon: u64, oldest: Option<u64>| match oldest {
            Some(oldest) if oldest < horizon => oldest.max(earlier),
            _ => horizon,
        };
        let asked = current.saturating_sub(keep.max(1) - 1).max(earlier);
        let horizon = kept_from(asked, oldest_pinned()?);
        if horizon > earlier {
            let txn = db.begin_write()?;
            {
                let mut meta = txn.open_table(META)?;
                meta.insert(
                    META_GC_HORIZON.as_bytes(),
                    catalog::seal("meta", META_GC_HORIZON, &horizon.to_le_bytes()).as_slice(),
                )?;
            }
            txn.commit()?;
        }
        // A reader that pinned the old horizon between the first listing and the commit.
        let horizon = kept_from(horizon, oldest_pinned()?);
        if horizon < asked {
            tracing::warn!("gc: keeping versions from {horizon} on: a reader has version {horizon} open");
        }
        let txn = db.begin_write()?;
        let mut doomed = Vec::new();
        {
            let runs = txn.open_table(STAGE_RUNS)?;
            let mut pending_targets = Vec::new();
            for entry in runs.iter()? {
                let (name, value) = entry?;
                let run: catalog::StageRun = catalog::unseal_decode("stage_runs", name.value(), value.value())?;
                pending_targets.push(run.target_version);
            }
            let mut segments = txn.open_table(SEGMENTS)?;
            for entry in segments.iter()? {
                let (name, value) = entry?;
                let record: catalog::SegmentRecord = catalog::unseal_decode("segments", name.value(), value.value())?;
                let dead = record.dropped.is_some_and(|d| d <= horizon);
                let abandoned = record.created > current && !pending_targets.contains(&record.created);
                if dead || abandoned {
                    doomed.push((catalog::key_text("segments", name.value())?.to_string(), record.bytes));
                }
            }
            for (name, _) in &doomed {
                segments.remove(name.as_bytes())?;
            }
        }
        txn.commit()?;
        // Files go only after the commit: a crash in between leaves debris, removed on open.
        let mut freed = 0;
        for (name, bytes) in &doomed {
            let path = self.segment_path(name);
            match fs::remove_file(&path) {
                Ok(()) => freed += bytes,
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
                Err(e) => return Err(io_error("remove", &path)(e)),
            }
        }
        sync_dir(&self.segments_dir())?;
        Ok((doomed.len(), freed))
    }
}

/// Routes segment writes through the injected storage faults.
struct FaultyWriter<'a> {
    inner: &'a File,
    faults: &'a IoFaults,
}

impl Write for FaultyWriter<'_> {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.faults.before_write(buf.len())?;
        let mut file = self.inner;
        file.write(buf)
    }

    fn flush(&mut self) -> std::io::Result<()> {
        let mut file = self.inner;
        file.flush()
    }
}
