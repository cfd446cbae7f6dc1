//! The catalog: redb tables, their records and their encodings (format-spec.md, "Catalog").
//!
//! Values are bincode 2 with a fixed configuration (little-endian, fixed-width integers), so
//! every byte is specified by the struct definitions below, in field order.

// Private to the crate; `octstore::testing` re-exports it for the tests, undocumented there.
#![cfg_attr(feature = "testing", allow(missing_docs))]

use redb::{ReadableDatabase, ReadableTable, ReadableTableMetadata, TableDefinition};
use serde::{Deserialize, Serialize, de::DeserializeOwned};

use super::StoreError;
use crate::format::key::CubeKeyColumn;

/// The key type of the catalog's name-keyed tables. On disk it is redb's `&str` (the same type
/// name, bytes, order and separators, so catalogs of every version open unchanged), but it
/// reads back as bytes: redb's `&str` panics on a key that is not UTF-8, which a flipped bit in
/// a name makes. Callers turn a key into text with [`key_text`], which reports such a key as
/// corruption naming its table.
#[derive(Debug)]
pub enum TextKey {}

impl redb::Value for TextKey {
    type SelfType<'a> = &'a [u8];
    type AsBytes<'a> = &'a [u8];

    fn fixed_width() -> Option<usize> {
        None
    }

    fn from_bytes<'a>(data: &'a [u8]) -> &'a [u8]
    where
        Self: 'a,
    {
        data
    }

    fn as_bytes<'a, 'b: 'a>(value: &'a &'b [u8]) -> &'a [u8]
    where
        Self: 'b,
    {
        value
    }

    fn type_name() -> redb::TypeName {
        <&str as redb::Value>::type_name()
    }
}

impl redb::Key for TextKey {
    /// Byte order: for valid UTF-8 the order of `str`, and a total order for any bytes.
    fn compare(data1: &[u8], data2: &[u8]) -> std::cmp::Ordering {
        data1.cmp(data2)
    }

    /// `&str`'s separators (they cut only at character boundaries and read no bytes as text), so
    /// the tree's pages are those an `&str` table would have.
    fn separator<'a>(left: &'a [u8], right: &'a [u8]) -> std::borrow::Cow<'a, [u8]> {
        <&str as redb::Key>::separator(left, right)
    }

    fn min_encoded_key() -> Option<std::borrow::Cow<'static, [u8]>> {
        <&str as redb::Key>::min_encoded_key()
    }
}

/// A [`TextKey`] of `table` as text; a key that is not UTF-8 is corruption.
pub fn key_text<'k>(table: &'static str, key: &'k [u8]) -> Result<&'k str, StoreError> {
    std::str::from_utf8(key).map_err(|_| StoreError::CatalogCorruption {
        table,
        reason: format!("a key is not UTF-8: '{}'", String::from_utf8_lossy(key)),
    })
}

/// Version of the catalog schema written by this build.
pub const CATALOG_FORMAT_VERSION: u32 = 4;
/// The oldest catalog version this build opens; a writable open migrates it (`migrate`).
pub const OLDEST_CATALOG_FORMAT_VERSION: u32 = 1;

/// Scalar settings: `format_version` (u32 LE), `current_version` (u64 LE), `gc_horizon` (u64 LE),
/// and stage-specific entries (`scene`, ...).
pub const META: TableDefinition<TextKey, &[u8]> = TableDefinition::new("meta");
/// Version number -> [`VersionRecord`].
pub const VERSIONS: TableDefinition<u64, &[u8]> = TableDefinition::new("versions");
/// Version number -> wall-clock commit time (ms since the Unix epoch). Not part of the
/// canonical content: two runs at different times hold the same store otherwise.
pub const VERSION_TIMES: TableDefinition<u64, u64> = TableDefinition::new("version_times");
/// Segment file name -> [`SegmentRecord`].
pub const SEGMENTS: TableDefinition<TextKey, &[u8]> = TableDefinition::new("segments");
/// Stage name -> [`StageRun`] of the run in progress (absent when none is).
pub const STAGE_RUNS: TableDefinition<TextKey, &[u8]> = TableDefinition::new("stage_runs");
/// (stage name, unit id) -> [`UnitRecord`]: units of the run in progress that are committed.
pub const UNITS_DONE: TableDefinition<(TextKey, u64), &[u8]> = TableDefinition::new("units_done");
/// (stage name, first key of a unit) -> [`UnitState`]: per-unit state a stage keeps between
/// runs (the treetop index, dirty marks).
pub const UNIT_STATE: TableDefinition<(TextKey, CubeKeyColumn), &[u8]> = TableDefinition::new("unit_state");

/// Depth map id (content hash) -> bincode `DepthMapRecord` (see `stages::ingest`).
pub const DEPTH_MAPS: TableDefinition<u64, &[u8]> = TableDefinition::new("depth_maps");

pub(crate) const META_FORMAT_VERSION: &str = "format_version";
pub(crate) const META_CURRENT_VERSION: &str = "current_version";
pub(crate) const META_GC_HORIZON: &str = "gc_horizon";
/// `meta` key prefix of a set of depth map ids: `map_set/{digest:016x}` -> bincode `Vec<u64>`,
/// the sorted ids whose [`map_set_digest`] is `digest`.
pub const META_MAP_SET_PREFIX: &str = "map_set/";

pub fn map_set_key(digest: u64) -> String {
    format!("{META_MAP_SET_PREFIX}{digest:016x}")
}

/// The digest in a `map_set/` key; `None` for any other key.
pub fn map_set_of_key(key: &str) -> Option<u64> {
    let hex = key.strip_prefix(META_MAP_SET_PREFIX)?;
    if hex.len() != 16 {
        return None;
    }
    u64::from_str_radix(hex, 16).ok()
}

/// xxh3-64 of the ids in ascending order, each as u64 LE.
pub fn map_set_digest<'a>(ascending_ids: impl Iterator<Item = &'a u64>) -> u64 {
    let mut hasher = xxhash_rust::xxh3::Xxh3::new();
    for id in ascending_ids {
        hasher.update(&id.to_le_bytes());
    }
    hasher.digest()
}

/// The stage whose unit state changed encoding in catalog version 2.
pub(crate) const HISTOGRAMS: &str = "histograms";

/// Catalog version 1 -> 2, in `txn`: each `("histograms", key)` entry of `unit_state` held its
/// own list of depth map ids, bincode `(u64 octree_digest, Vec<u64> ids)`; it becomes `(u64
/// octree_digest, u64 map_set)` with the list stored once under [`map_set_key`]. A histograms
/// run in progress recorded version-1 states in its units; the caller discards it
/// first (the run starts over).
pub(crate) fn migrate_v1(txn: &redb::WriteTransaction) -> Result<(), StoreError> {
    let mut states = txn.open_table(UNIT_STATE)?;
    let mut meta = txn.open_table(META)?;
    let mut converted = Vec::new();
    let low = crate::format::CubeKey::from_raw(0);
    let high = crate::format::CubeKey::from_raw(u128::MAX);
    for entry in states.range((HISTOGRAMS.as_bytes(), low)..=(HISTOGRAMS.as_bytes(), high))? {
        let (key, value) = entry?;
        let (octree_digest, ids): (u64, Vec<u64>) = decode("unit_state", value.value())?;
        let mut sorted = ids.clone();
        sorted.sort_unstable();
        sorted.dedup();
        if sorted != ids {
            return Err(StoreError::CatalogCorruption {
                table: "unit_state",
                reason: "a version-1 histogram state lists its depth maps out of order".into(),
            });
        }
        let digest = map_set_digest(ids.iter());
        converted.push((key.value().1, octree_digest, digest, ids));
    }
    for (key, octree_digest, digest, ids) in converted {
        let set_key = map_set_key(digest);
        if meta.get(set_key.as_bytes())?.is_none() {
            meta.insert(set_key.as_bytes(), encode(&ids).as_slice())?;
        }
        states.insert(
            (HISTOGRAMS.as_bytes(), key),
            encode(&(octree_digest, digest)).as_slice(),
        )?;
    }
    Ok(())
}

/// Bytes at the end of a depth map record after its source: `SampleStats` (7 x u64) and
/// `added_in` (u64).
const DEPTH_MAP_RECORD_TAIL: usize = 64;

/// A version-2 `depth_maps` value in version 3's encoding. Version 3 appended `noise:
/// DepthNoise` to the record's source, that is before the record's last
/// [`DEPTH_MAP_RECORD_TAIL`] bytes; version-2 maps were sized by their pixel footprint alone,
/// `DepthNoise::Footprint`, whose encoding is its tag, u32 0.
pub(crate) fn depth_map_record_v2_to_v3(value: &[u8]) -> Result<Vec<u8>, StoreError> {
    let Some(split) = value.len().checked_sub(DEPTH_MAP_RECORD_TAIL) else {
        return Err(StoreError::CatalogCorruption {
            table: "depth_maps",
            reason: format!("a version-2 record of {} bytes is shorter than its stats", value.len()),
        });
    };
    let (source, tail) = value.split_at(split);
    let mut upgraded = Vec::with_capacity(value.len() + 4);
    upgraded.extend_from_slice(source);
    upgraded.extend_from_slice(&0u32.to_le_bytes());
    upgraded.extend_from_slice(tail);
    Ok(upgraded)
}

/// Catalog version 2 -> 3, in `txn`: every depth map record gains its noise model
/// ([`depth_map_record_v2_to_v3`]).
pub(crate) fn migrate_v2(txn: &redb::WriteTransaction) -> Result<(), StoreError> {
    let mut table = txn.open_table(DEPTH_MAPS)?;
    let mut upgraded = Vec::new();
    for entry in table.iter()? {
        let (id, value) = entry?;
        upgraded.push((id.value(), depth_map_record_v2_to_v3(value.value())?));
    }
    for (id, value) in upgraded {
        table.insert(id, value.as_slice())?;
    }
    Ok(())
}

/// Last bytes of every sealed catalog value (catalog version 4): the 8-byte checksum is
/// followed by these. A value without them was written by an older build.
pub const SEAL_MAGIC: [u8; 4] = *b"OCS\x04";
/// Bytes a seal adds to a value: the checksum (u64 LE) and [`SEAL_MAGIC`].
pub const SEAL_BYTES: usize = 12;

/// A catalog key as the seal's checksum covers it (the bytes of `canonical_dump`), and as an
/// error names it.
pub trait CatalogKey {
    /// The key's bytes: UTF-8 for names, big-endian for numbers, `name 0 number` for pairs.
    fn key_bytes(&self) -> Vec<u8>;
    /// The key as a corruption error names it.
    fn describe(&self) -> String;
    /// The key as an error about a value of `table` names it: depth map ids in hex, as
    /// everywhere else they are printed.
    fn describe_in(&self, table: &str) -> String {
        let _ = table;
        self.describe()
    }
}

impl CatalogKey for str {
    fn key_bytes(&self) -> Vec<u8> {
        self.as_bytes().to_vec()
    }
    fn describe(&self) -> String {
        format!("'{self}'")
    }
}

/// A [`TextKey`] as read back, which may be damaged: its bytes as they are, named lossily.
impl CatalogKey for [u8] {
    fn key_bytes(&self) -> Vec<u8> {
        self.to_vec()
    }
    fn describe(&self) -> String {
        format!("'{}'", String::from_utf8_lossy(self))
    }
}

impl<T: CatalogKey + ?Sized> CatalogKey for &T {
    fn key_bytes(&self) -> Vec<u8> {
        (**self).key_bytes()
    }
    fn describe(&self) -> String {
        (**self).describe()
    }
    fn describe_in(&self, table: &str) -> String {
        (**self).describe_in(table)
    }
}

impl CatalogKey for u64 {
    fn key_bytes(&self) -> Vec<u8> {
        self.to_be_bytes().to_vec()
    }
    fn describe(&self) -> String {
        self.to_string()
    }
    fn describe_in(&self, table: &str) -> String {
        if table == redb::TableHandle::name(&DEPTH_MAPS) {
            format!("{self:016x}")
        } else {
            self.describe()
        }
    }
}

/// A (name, number) key's bytes: the name, a zero byte, the number big-endian.
fn pair_key_bytes(name: &[u8], big_endian: &[u8]) -> Vec<u8> {
    let mut bytes = name.to_vec();
    bytes.push(0);
    bytes.extend_from_slice(big_endian);
    bytes
}

impl CatalogKey for (&str, u64) {
    fn key_bytes(&self) -> Vec<u8> {
        pair_key_bytes(self.0.as_bytes(), &self.1.to_be_bytes())
    }
    fn describe(&self) -> String {
        format!("('{}', {})", self.0, self.1)
    }
}

impl CatalogKey for (&[u8], u64) {
    fn key_bytes(&self) -> Vec<u8> {
        pair_key_bytes(self.0, &self.1.to_be_bytes())
    }
    fn describe(&self) -> String {
        format!("('{}', {})", String::from_utf8_lossy(self.0), self.1)
    }
}

impl CatalogKey for (&[u8], crate::format::CubeKey) {
    fn key_bytes(&self) -> Vec<u8> {
        pair_key_bytes(self.0, &self.1.to_be_bytes())
    }
    fn describe(&self) -> String {
        format!("('{}', {:?})", String::from_utf8_lossy(self.0), self.1)
    }
}

impl CatalogKey for (&str, crate::format::CubeKey) {
    fn key_bytes(&self) -> Vec<u8> {
        pair_key_bytes(self.0.as_bytes(), &self.1.to_be_bytes())
    }
    fn describe(&self) -> String {
        format!("('{}', {:?})", self.0, self.1)
    }
}

/// xxh3-64 of the table's name, a zero byte, the key's length (u64 LE) and bytes, and the
/// payload: a value moved to another key or table fails as a flipped one does.
fn seal_checksum(table: &str, key: &[u8], payload: &[u8]) -> u64 {
    let mut hasher = xxhash_rust::xxh3::Xxh3::new();
    hasher.update(table.as_bytes());
    hasher.update(&[0]);
    hasher.update(&(key.len() as u64).to_le_bytes());
    hasher.update(key);
    hasher.update(payload);
    hasher.digest()
}

/// `payload` sealed for `table` under `key`: payload, checksum, [`SEAL_MAGIC`].
pub fn seal<K: CatalogKey + ?Sized>(table: &str, key: &K, payload: &[u8]) -> Vec<u8> {
    let mut sealed = Vec::with_capacity(payload.len() + SEAL_BYTES);
    sealed.extend_from_slice(payload);
    sealed.extend_from_slice(&seal_checksum(table, &key.key_bytes(), payload).to_le_bytes());
    sealed.extend_from_slice(&SEAL_MAGIC);
    sealed
}

/// [`encode`] then [`seal`].
pub fn seal_encode<K: CatalogKey + ?Sized, T: Serialize>(table: &str, key: &K, value: &T) -> Vec<u8> {
    seal(table, key, &encode(value))
}

/// Whether `value` carries a seal (it may still fail its checksum).
pub fn is_sealed(value: &[u8]) -> bool {
    value.len() >= SEAL_BYTES && value.ends_with(&SEAL_MAGIC)
}

/// The payload of a value read from `table` under `key`. A sealed value whose checksum fails is
/// a corruption error naming the table and the key. A value without a seal is returned whole:
/// catalogs before version 4 have none, and in a version-4 catalog the payload then carries
/// the 12 seal bytes, which every decoder refuses (`verify` also reports it as unsealed).
pub fn unseal<'v, K: CatalogKey + ?Sized>(
    table: &'static str,
    key: &K,
    value: &'v [u8],
) -> Result<&'v [u8], StoreError> {
    if !is_sealed(value) {
        return Ok(value);
    }
    let (payload, seal) = value.split_at(value.len() - SEAL_BYTES);
    let (checksum, _) = seal.split_at(8);
    let expected = u64::from_le_bytes(checksum.try_into().unwrap_or_default());
    if seal_checksum(table, &key.key_bytes(), payload) != expected {
        return Err(StoreError::CatalogCorruption {
            table,
            reason: format!("the value at key {} fails its checksum", key.describe_in(table)),
        });
    }
    Ok(payload)
}

/// [`unseal`] then [`decode`].
pub fn unseal_decode<K: CatalogKey + ?Sized, T: DeserializeOwned>(
    table: &'static str,
    key: &K,
    value: &[u8],
) -> Result<T, StoreError> {
    decode(table, unseal(table, key, value)?)
}

/// Checks one value strictly, as `verify` does in a version-4 catalog: sealed and intact.
pub fn check_sealed<K: CatalogKey + ?Sized>(table: &'static str, key: &K, value: &[u8]) -> Result<(), StoreError> {
    if !is_sealed(value) {
        return Err(StoreError::CatalogCorruption {
            table,
            reason: format!("the value at key {} has no seal", key.describe_in(table)),
        });
    }
    unseal(table, key, value).map(|_| ())
}

/// The payload of META's entry `key`, unsealed.
pub fn meta_bytes(
    table: &impl ReadableTable<TextKey, &'static [u8]>,
    key: &str,
) -> Result<Option<Vec<u8>>, StoreError> {
    match table.get(key.as_bytes())? {
        None => Ok(None),
        Some(guard) => Ok(Some(unseal("meta", key, guard.value())?.to_vec())),
    }
}

/// Catalog version 3 -> 4, in `txn`: every value of every table but `version_times` gets its
/// seal (values some earlier step of the same migration already sealed are left as they are).
pub(crate) fn migrate_v3(txn: &redb::WriteTransaction) -> Result<(), StoreError> {
    // `own` turns a borrowed key into an owned one, `lend` an owned one back into the table's
    // key type.
    macro_rules! seal_table {
        ($def:expr, $name:literal, |$o:ident| $own:expr, |$l:ident| $lend:expr) => {{
            let mut table = txn.open_table($def)?;
            let mut unsealed = Vec::new();
            for entry in table.iter()? {
                let (k, v) = entry?;
                if !is_sealed(v.value()) {
                    let $o = k.value();
                    unsealed.push(($own, seal($name, &$o, v.value())));
                }
            }
            for (owned, value) in &unsealed {
                let $l = owned;
                table.insert($lend, value.as_slice())?;
            }
        }};
    }
    seal_table!(META, "meta", |k| k.to_vec(), |k| k.as_slice());
    seal_table!(VERSIONS, "versions", |k| k, |k| *k);
    seal_table!(DEPTH_MAPS, "depth_maps", |k| k, |k| *k);
    seal_table!(SEGMENTS, "segments", |k| k.to_vec(), |k| k.as_slice());
    seal_table!(STAGE_RUNS, "stage_runs", |k| k.to_vec(), |k| k.as_slice());
    seal_table!(UNITS_DONE, "units_done", |k| (k.0.to_vec(), k.1), |k| (
        k.0.as_slice(),
        k.1
    ));
    seal_table!(UNIT_STATE, "unit_state", |k| (k.0.to_vec(), k.1), |k| (
        k.0.as_slice(),
        k.1
    ));
    Ok(())
}

fn bincode_config() -> impl bincode::config::Config {
    bincode::config::standard()
        .with_little_endian()
        .with_fixed_int_encoding()
}

pub fn encode<T: Serialize>(value: &T) -> Vec<u8> {
    // Encoding plain structs into a Vec cannot fail: no size limit is configured.
    bincode::serde::encode_to_vec(value, bincode_config()).unwrap_or_default()
}

/// The most bytes one decoded value may claim. A damaged length prefix (a string or list of
/// 10^18 elements) is then an error before anything is allocated, not an aborted process;
/// real values stay far below it (a histograms run's parameters list every depth map id, 8
/// bytes each).
const DECODE_LIMIT: usize = 256 << 20;

pub fn decode<T: DeserializeOwned>(table: &'static str, bytes: &[u8]) -> Result<T, StoreError> {
    let config = bincode::config::standard()
        .with_little_endian()
        .with_fixed_int_encoding()
        .with_limit::<DECODE_LIMIT>();
    let (value, used) =
        bincode::serde::decode_from_slice(bytes, config).map_err(|e| StoreError::CatalogCorruption {
            table,
            reason: e.to_string(),
        })?;
    if used != bytes.len() {
        return Err(StoreError::CatalogCorruption {
            table,
            reason: format!("{} trailing bytes after a record", bytes.len() - used),
        });
    }
    Ok(value)
}

/// One committed version of the store (format-spec.md, table `versions`).
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq, Eq)]
pub struct VersionRecord {
    /// The version it was made from.
    pub parent: u64,
    /// What made it: `create`, `ingest`, or a stage name.
    pub kind: String,
    /// One human-readable line.
    pub summary: String,
}

/// What the catalog knows of one segment file (format-spec.md, table `segments`).
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq, Eq)]
pub struct SegmentRecord {
    /// The stage that wrote it.
    pub stage: String,
    /// The unit of work that wrote it.
    pub unit: u64,
    /// Its index among the unit's segments.
    pub part: u32,
    /// Rows (cubes or samples) it holds.
    pub rows: u64,
    /// The file's size in bytes.
    pub bytes: u64,
    /// Checksum of the whole file, checked by `verify`.
    pub file_checksum: u64,
    /// Digest of the decoded columns: equal content gives equal digests.
    pub content_digest: u64,
    /// Its first row's key (a raw [`crate::CubeKey`]).
    pub first_key: u128,
    /// Its last row's key.
    pub last_key: u128,
    /// First version that sees the segment.
    pub created: u64,
    /// First version that no longer sees it.
    pub dropped: Option<u64>,
}

impl SegmentRecord {
    /// The record of a freshly written segment: part `part` of `unit`, first seen by `created`.
    pub fn written(
        stage: &str,
        unit: u64,
        part: usize,
        summary: &crate::format::segment::SegmentSummary,
        created: u64,
    ) -> SegmentRecord {
        SegmentRecord {
            stage: stage.to_string(),
            unit,
            part: part as u32,
            rows: summary.rows,
            bytes: summary.bytes,
            file_checksum: summary.file_checksum,
            content_digest: summary.content_digest,
            first_key: summary.first_key.raw(),
            last_key: summary.last_key.raw(),
            created,
            dropped: None,
        }
    }

    /// Whether version `version` sees the segment.
    pub fn visible_at(&self, version: u64) -> bool {
        self.created <= version && self.dropped.is_none_or(|d| version < d)
    }
}

#[derive(Serialize, Deserialize, Clone, Debug, PartialEq, Eq)]
pub struct StageRun {
    /// The version this run will create when it finishes.
    pub target_version: u64,
    /// The stage's parameters, encoded by the stage; a resume with other parameters is refused.
    pub params: Vec<u8>,
    /// Number of units in the run.
    pub units: u64,
}

/// A finished unit of a stage run (format-spec.md, table `units_done`).
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq, Eq)]
pub struct UnitRecord {
    /// The names of the segments it wrote.
    pub segments: Vec<String>,
    /// Stage-specific result of the unit (counts, a leaf's statistics).
    pub extra: Vec<u8>,
}

/// Reads a little-endian u64 scalar from META.
pub fn meta_u64(table: &impl ReadableTable<TextKey, &'static [u8]>, key: &str) -> Result<Option<u64>, StoreError> {
    match table.get(key.as_bytes())? {
        None => Ok(None),
        Some(guard) => {
            let payload = unseal("meta", key, guard.value())?;
            let bytes: [u8; 8] = payload.try_into().map_err(|_| StoreError::CatalogCorruption {
                table: "meta",
                reason: format!("'{key}' is not 8 bytes"),
            })?;
            Ok(Some(u64::from_le_bytes(bytes)))
        }
    }
}

/// Reads redb's table directory (every table's name and key and value type names) and opens
/// every catalog table, once per open of the catalog: redb decodes those names as UTF-8 with
/// `unwrap`, so a flipped bit in one panics inside redb, which [`contain_redb_panics`] turns into
/// corruption here. The rest of the process reads the names checked here (the catalog's own
/// keys are [`TextKey`]s and never panic).
pub fn check_directory(db: &impl ReadableDatabase) -> Result<(), StoreError> {
    contain_redb_panics(|| -> Result<(), StoreError> {
        let txn = db.begin_read()?;
        for table in txn.list_tables()? {
            std::hint::black_box(redb::TableHandle::name(&table).len());
        }
        macro_rules! open {
            ($($def:expr),*) => {$(
                match txn.open_table($def) {
                    Ok(_) | Err(redb::TableError::TableDoesNotExist(_)) => {}
                    Err(e) => return Err(e.into()),
                }
            )*};
        }
        open!(
            META,
            VERSIONS,
            VERSION_TIMES,
            SEGMENTS,
            STAGE_RUNS,
            UNITS_DONE,
            UNIT_STATE,
            DEPTH_MAPS
        );
        Ok(())
    })?
}

/// The message of the last panic raised inside redb's code, which [`contain_redb_panics`]
/// reports instead of the panic hook.
static REDB_PANIC: std::sync::Mutex<Option<String>> = std::sync::Mutex::new(None);

/// Calls of [`contain_redb_panics`] under way, on any thread: while there are any, a panic inside
/// redb is recorded for them instead of printed (it may be raised on a worker thread that `f`
/// waits for). Outside them redb's panics print as any other.
static ACTIVE_GUARDS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);

/// Runs `f`; a panic raised inside redb (on any thread `f` waits for) becomes
/// [`StoreError::CatalogCorruption`], printed by no panic hook. redb trusts its pages: a damaged
/// page of `catalog.redb` (a flipped bit in an offset, a name that is not UTF-8) makes it index
/// out of bounds or unwrap, and a reader must report that as damage, not abort. Other panics
/// pass through unchanged. A write transaction interrupted this way was never committed, so the
/// catalog stays at its last commit.
pub fn contain_redb_panics<T>(f: impl FnOnce() -> T) -> Result<T, StoreError> {
    static HOOK: std::sync::Once = std::sync::Once::new();
    HOOK.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            let in_redb = info
                .location()
                .is_some_and(|at| at.file().replace('\\', "/").contains("/redb-"));
            if in_redb && ACTIVE_GUARDS.load(std::sync::atomic::Ordering::SeqCst) > 0 {
                let message = info
                    .payload()
                    .downcast_ref::<&str>()
                    .map(|m| (*m).to_string())
                    .or_else(|| info.payload().downcast_ref::<String>().cloned())
                    .unwrap_or_default();
                if let Ok(mut last) = REDB_PANIC.lock() {
                    *last = Some(message);
                }
            } else {
                previous(info);
            }
        }));
    });
    ACTIVE_GUARDS.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
    let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(f));
    ACTIVE_GUARDS.fetch_sub(1, std::sync::atomic::Ordering::SeqCst);
    match outcome {
        Ok(value) => Ok(value),
        Err(payload) => match REDB_PANIC.lock().ok().and_then(|mut last| last.take()) {
            Some(detail) => Err(StoreError::DamagedCatalog { detail }),
            None => std::panic::resume_unwind(payload),
        },
    }
}

/// Every value of every table but `version_times` that is not sealed or fails its seal (a
/// version-4 catalog), one line per value naming the table and the key.
pub fn sealing_problems(db: &impl ReadableDatabase) -> Result<Vec<String>, StoreError> {
    let txn = db.begin_read()?;
    let mut problems = Vec::new();
    // A flipped byte in redb's table directory renames a table: the store would read as if
    // the table were empty (no depth maps, no segments).
    const KNOWN: [&str; 8] = [
        "meta",
        "versions",
        "version_times",
        "segments",
        "stage_runs",
        "units_done",
        "unit_state",
        "depth_maps",
    ];
    for table in txn.list_tables()? {
        let name = redb::TableHandle::name(&table);
        if !KNOWN.contains(&name) {
            problems.push(format!("catalog: an unknown table '{name}' (a damaged table name?)"));
        }
    }
    macro_rules! check {
        ($def:expr, $name:literal) => {{
            match txn.open_table($def) {
                Ok(table) => {
                    let mut entries = 0u64;
                    for entry in table.iter()? {
                        let (k, v) = entry?;
                        entries += 1;
                        if let Err(error) = check_sealed($name, &k.value(), v.value()) {
                            problems.push(format!("catalog: {error}"));
                        }
                    }
                    // The directory keeps each table's length apart from its entries.
                    let recorded = table.len()?;
                    if recorded != entries {
                        problems.push(format!(
                            "catalog: table '{}' records {recorded} entries but holds {entries}",
                            $name
                        ));
                    }
                }
                Err(redb::TableError::TableDoesNotExist(_)) => {}
                Err(e) => return Err(e.into()),
            }
        }};
    }
    check!(META, "meta");
    check!(VERSIONS, "versions");
    check!(DEPTH_MAPS, "depth_maps");
    check!(SEGMENTS, "segments");
    check!(STAGE_RUNS, "stage_runs");
    check!(UNITS_DONE, "units_done");
    check!(UNIT_STATE, "unit_state");
    Ok(problems)
}

/// A canonical byte dump of every table but `version_times`, in table then key order. Two stores
/// with equal dumps hold the same content; `--resume` tests compare these.
pub fn canonical_dump(db: &impl ReadableDatabase) -> Result<Vec<u8>, StoreError> {
    let txn = db.begin_read()?;
    let mut out = Vec::new();
    let mut put = |bytes: &[u8]| {
        out.extend_from_slice(&(bytes.len() as u64).to_le_bytes());
        out.extend_from_slice(bytes);
    };
    macro_rules! dump {
        ($def:expr, $key:expr) => {{
            put(redb::TableHandle::name(&$def).as_bytes());
            match txn.open_table($def) {
                Ok(table) => {
                    put(&table.len()?.to_le_bytes());
                    for entry in table.iter()? {
                        let (k, v) = entry?;
                        let key_bytes: Vec<u8> = $key(k.value());
                        put(&key_bytes);
                        put(v.value());
                    }
                }
                Err(redb::TableError::TableDoesNotExist(_)) => put(&0u64.to_le_bytes()),
                Err(e) => return Err(e.into()),
            }
        }};
    }
    dump!(META, |k: &[u8]| k.key_bytes());
    dump!(VERSIONS, |k: u64| k.key_bytes());
    dump!(DEPTH_MAPS, |k: u64| k.key_bytes());
    dump!(SEGMENTS, |k: &[u8]| k.key_bytes());
    dump!(STAGE_RUNS, |k: &[u8]| k.key_bytes());
    dump!(UNITS_DONE, |k: (&[u8], u64)| k.key_bytes());
    dump!(UNIT_STATE, |k: (&[u8], crate::format::CubeKey)| k.key_bytes());
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A flipped byte fails the seal, and the error names the table and the key as the rest of
    /// octstore prints it: a depth map's id in hex, a version in decimal.
    #[test]
    fn a_broken_seal_names_its_table_and_key() {
        let id = 0x00ab_cdef_0123_4567u64;
        let mut value = seal("depth_maps", &id, b"payload");
        if let Some(byte) = value.first_mut() {
            *byte ^= 1;
        }
        let error = unseal("depth_maps", &id, &value)
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(
            error.contains("depth_maps") && error.contains("00abcdef01234567"),
            "{error}"
        );
        let mut value = seal("versions", &12u64, b"payload");
        if let Some(byte) = value.first_mut() {
            *byte ^= 1;
        }
        let error = unseal("versions", &12u64, &value)
            .err()
            .map(|e| e.to_string())
            .unwrap_or_default();
        assert!(error.contains("key 12 "), "{error}");
        assert_eq!(
            unseal("versions", &12u64, &seal("versions", &12u64, b"ok")).ok(),
            Some(&b"ok"[..])
        );
    }
}
