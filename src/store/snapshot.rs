//! Snapshots: a version's manifest of segments, loaded in one read transaction.

use std::collections::BTreeMap;
use std::fs::File;
use std::path::PathBuf;

use memmap2::Mmap;
use redb::ReadableTable;
use xxhash_rust::xxh3::Xxh3;

use super::catalog::{
    self, META, META_CURRENT_VERSION, META_GC_HORIZON, SEGMENTS, SegmentRecord, VERSIONS, VersionRecord,
};
use super::pins::ReaderPin;
use super::{Result, Store, StoreError};
use crate::format::SegmentReader;

/// A consistent, immutable view of one committed version.
pub struct Snapshot<'s> {
    store: &'s Store,
    version: u64,
    record: VersionRecord,
    /// Visible segments per stage, ordered by (first key, unit, part).
    stages: BTreeMap<String, Vec<(String, SegmentRecord)>>,
    /// A read-only store's pin on `version`, so that `gc` in a writer keeps its segments.
    pin: Option<super::pins::ReaderPin>,
}

impl<'s> Snapshot<'s> {
    pub(crate) fn load(store: &'s Store, version: Option<u64>) -> Result<Snapshot<'s>> {
        let txn = store.catalog().begin_read()?;
        let meta = txn.open_table(META)?;
        let latest = catalog::meta_u64(&meta, META_CURRENT_VERSION)?.unwrap_or(0);
        let horizon = catalog::meta_u64(&meta, META_GC_HORIZON)?.unwrap_or(0);
        let version = version.unwrap_or(latest);
        if version > latest {
            return Err(StoreError::NoSuchVersion { version, latest });
        }
        if version < horizon {
            return Err(StoreError::VersionGone { version, horizon });
        }
        let versions = txn.open_table(VERSIONS)?;
        let record = match versions.get(version)? {
            Some(bytes) => catalog::unseal_decode("versions", &version, bytes.value())?,
            None => return Err(StoreError::NoSuchVersion { version, latest }),
        };
        let mut stages: BTreeMap<String, Vec<(String, SegmentRecord)>> = BTreeMap::new();
        for entry in txn.open_table(SEGMENTS)?.iter()? {
            let (name, value) = entry?;
            let record: SegmentRecord = catalog::unseal_decode("segments", name.value(), value.value())?;
            if record.visible_at(version) {
                stages
                    .entry(record.stage.clone())
                    .or_default()
                    .push((catalog::key_text("segments", name.value())?.to_string(), record));
            }
        }
        for segments in stages.values_mut() {
            segments.sort_by_key(|a| (a.1.first_key, a.1.unit, a.1.part));
        }
        drop(txn);
        // A writer's own snapshots need no pin: gc runs only in the writer.
        let pin = match store.catalog() {
            super::Catalog::ReadOnly(_) => {
                let pin = super::pins::pin(store.root(), version);
                // A gc that committed between the read above and the pin did not see it.
                let txn = store.catalog().begin_read()?;
                let horizon = catalog::meta_u64(&txn.open_table(META)?, META_GC_HORIZON)?.unwrap_or(0);
                if version < horizon {
                    return Err(StoreError::VersionGone { version, horizon });
                }
                pin
            }
            super::Catalog::Writable(_) => None,
        };
        Ok(Snapshot {
            store,
            version,
            record,
            stages,
            pin,
        })
    }

    /// Takes the pin that keeps this version from `gc` (read-only stores; `None` otherwise),
    /// to hold beyond the snapshot: a front end that opens the version again later (the Python
    /// package's `Snapshot`) keeps it readable meanwhile.
    pub fn take_pin(&mut self) -> Option<ReaderPin> {
        self.pin.take()
    }

    /// The store the snapshot reads.
    pub fn store(&self) -> &'s Store {
        self.store
    }

    /// The pinned version.
    pub fn version(&self) -> u64 {
        self.version
    }

    /// The version's catalog record (kind, parent, summary).
    pub fn record(&self) -> &VersionRecord {
        &self.record
    }

    /// Names of the stages that have visible segments.
    pub fn stages(&self) -> impl Iterator<Item = &str> {
        self.stages.keys().map(String::as_str)
    }

    /// Visible segments of a stage, ordered by first key.
    pub fn segments(&self, stage: &str) -> &[(String, SegmentRecord)] {
        self.stages.get(stage).map(Vec::as_slice).unwrap_or(&[])
    }

    /// Every segment the version sees, of every stage.
    pub fn all_segments(&self) -> impl Iterator<Item = &(String, SegmentRecord)> {
        self.stages.values().flatten()
    }

    /// Rows in all visible segments of a stage.
    pub fn rows(&self, stage: &str) -> u64 {
        self.segments(stage).iter().map(|(_, r)| r.rows).sum()
    }

    /// A checksum of a stage's content at this version: equal for equal content, however it was
    /// produced (segment content digests in key order; names and compression do not enter).
    pub fn digest(&self, stage: &str) -> u64 {
        let mut digests: Vec<(u128, u64)> = self
            .segments(stage)
            .iter()
            .map(|(_, r)| (r.first_key, r.content_digest))
            .collect();
        digests.sort_unstable();
        let mut hasher = Xxh3::new();
        hasher.update(stage.as_bytes());
        for (_, digest) in digests {
            hasher.update(&digest.to_le_bytes());
        }
        hasher.digest()
    }

    /// Maps a visible segment after checking its size against the catalog.
    pub fn open_segment(&self, name: &str) -> Result<SegmentFile> {
        let record = self
            .all_segments()
            .find(|(n, _)| n == name)
            .map(|(_, r)| r.clone())
            .ok_or_else(|| StoreError::CatalogCorruption {
                table: "segments",
                reason: format!("segment {name} is not visible at version {}", self.version),
            })?;
        SegmentFile::open(self.store.segment_path(name), &record).map_err(|error| {
            // A missing file of an unpinned snapshot: say so if gc collected the version.
            let missing =
                matches!(&error, StoreError::Io { source, .. } if source.kind() == std::io::ErrorKind::NotFound);
            match self.store.gc_horizon() {
                Ok(horizon) if missing && self.version < horizon => StoreError::VersionGone {
                    version: self.version,
                    horizon,
                },
                _ => error,
            }
        })
    }
}

/// A segment file read chunk by chunk (with its directory parsed beforehand, by
/// `SegmentFile::reader` and `SegmentReader::directory`) rather than mapped: a reader that
/// takes a few short pieces of many files pays a mapping, an unmapping and its TLB shootdowns
/// per file otherwise (a tenth of the samples stage's time, which read RedKitchen's 1000 runs
/// once per unit).
pub struct SegmentChunks {
    path: PathBuf,
    file: File,
}

impl SegmentChunks {
    /// Opens the segment file at `path` for reading.
    pub fn open(path: PathBuf) -> Result<SegmentChunks> {
        let file = File::open(&path).map_err(|source| StoreError::Io {
            action: "open segment",
            path: path.clone(),
            source,
        })?;
        Ok(SegmentChunks { path, file })
    }

    /// The `len` bytes at `offset`, into `buffer` (resized to them).
    pub fn read(&mut self, (offset, len): (u64, usize), buffer: &mut Vec<u8>) -> Result<()> {
        use std::io::{Read, Seek, SeekFrom};
        buffer.resize(len, 0);
        let io = |source| StoreError::Io {
            action: "read segment",
            path: self.path.clone(),
            source,
        };
        self.file.seek(SeekFrom::Start(offset)).map_err(io)?;
        self.file.read_exact(buffer).map_err(io)
    }

    /// Block `block` of column `name`, as `directory` (this file's) places it: its chunk is
    /// read into `buffer` and decoded, its checksum checked.
    pub fn decode_block(
        &mut self,
        directory: &crate::format::segment::SegmentDirectory,
        name: &str,
        block: usize,
        buffer: &mut Vec<u8>,
    ) -> Result<crate::format::ColumnValues> {
        let range = directory.chunk_range(name, block).map_err(|e| self.corruption(e))?;
        self.read(range, buffer)?;
        directory
            .decode_block(name, block, buffer)
            .map_err(|e| self.corruption(e))
    }

    /// A corruption error naming this file.
    pub fn corruption(&self, detail: crate::format::DecodeError) -> StoreError {
        StoreError::Corruption {
            file: self.path.clone(),
            detail,
        }
    }
}

/// A mapped segment file whose length matched its catalog record.
pub struct SegmentFile {
    path: PathBuf,
    map: Mmap,
}

impl SegmentFile {
    pub(crate) fn open(path: PathBuf, record: &SegmentRecord) -> Result<SegmentFile> {
        let file = File::open(&path).map_err(|source| StoreError::Io {
            action: "open segment",
            path: path.clone(),
            source,
        })?;
        let map = crate::sys::map_segment(&file).map_err(|source| StoreError::Io {
            action: "map segment",
            path: path.clone(),
            source,
        })?;
        if map.len() as u64 != record.bytes {
            return Err(StoreError::Corruption {
                file: path,
                detail: crate::format::DecodeError::Truncated {
                    what: "segment file",
                    needed: record.bytes as usize,
                    available: map.len(),
                },
            });
        }
        Ok(SegmentFile { path, map })
    }

    /// The segment file's path.
    pub fn path(&self) -> &std::path::Path {
        &self.path
    }

    /// The file's bytes (memory-mapped).
    pub fn bytes(&self) -> &[u8] {
        &self.map
    }

    /// Parses the segment; each column block is checksummed when read.
    pub fn reader(&self) -> Result<SegmentReader<'_>> {
        SegmentReader::parse(&self.map).map_err(|detail| self.corruption(detail))
    }

    /// A corruption error naming this file.
    pub fn corruption(&self, detail: crate::format::DecodeError) -> StoreError {
        StoreError::Corruption {
            file: self.path.clone(),
            detail,
        }
    }
}
