//! Pipeline stages, in pipeline order: `ingest`, `octree` (merge, balance, treetop, with its
//! external sorter), `histograms`, `solve` (one stage per level), `extract`; and `exercise`, a
//! stage over generated keys that tests the runner. Each is a [`Stage`](crate::store::Stage)
//! run by the store's stage runner, or (extract) reads a pinned snapshot.

// A private layer: its `pub` items are the crate's own API and, with the `testing` feature, its
// integration tests' and benches' (`octstore::testing`). Some exist only for those (reference
// kernels, the GPU tests' reading helpers), so a build without the feature sees them unused.
#![cfg_attr(not(feature = "testing"), allow(dead_code, unused_imports))]
// `octstore::testing` is not the documented public surface: its items need no docs there.
#![cfg_attr(feature = "testing", allow(missing_docs))]

pub mod capture;
#[cfg(any(test, feature = "testing"))]
pub mod exercise;
pub mod extract;
pub mod histograms;
pub mod ingest;
pub mod observed;
pub mod octree;
pub mod samples;
pub mod solve;
pub mod treetop;

/// Stage names, in pipeline order. They name segments and catalog entries: changing one is a
/// format change.
pub const INGEST: &str = "ingest";
pub const OCTREE: &str = "octree";
pub const HISTOGRAMS: &str = "histograms";
pub const SOLUTION: &str = "solution";

/// Rows per block of the octree's and the levels' segments (format-spec.md, "Columns used by
/// stages"), which units read across their faces: small enough that a unit decodes only the
/// blocks of a neighbour's segment whose key range can reach it (`stages::solve::cut`).
/// Measured on RedKitchen's extraction: 512, 1024, 2048 and 4096 rows alike, 65536 a fifth
/// slower.
pub const FACE_READ_BLOCK_ROWS: u32 = 2048;

/// Meta key: deepest level of the latest octree (u8), written by the octree stage.
pub const META_OCTREE_MAX_DEPTH: &str = "octree_max_depth";

/// Deepest level of the latest octree.
pub fn octree_max_depth(store: &crate::store::Store) -> crate::store::Result<u8> {
    let txn = store.catalog().begin_read()?;
    let meta = txn.open_table(crate::store::catalog::META)?;
    let value =
        crate::store::catalog::meta_bytes(&meta, META_OCTREE_MAX_DEPTH)?.map(|v| v.first().copied().unwrap_or(0));
    value.ok_or_else(|| crate::store::StoreError::Stage {
        stage: OCTREE.into(),
        unit: "-".into(),
        error: Box::new(crate::store::StageError::NoOctree),
    })
}
