//! Pipeline stages. Each is a [`Stage`](crate::store::Stage) run by the store's stage runner.

pub mod depthmap;
pub mod ingest;
pub mod inputs;
pub mod octree;
pub mod records;
pub mod scene;
pub mod synthetic;

/// Stage names, in pipeline order. They name segments and catalog entries: changing one is a
/// format change.
pub const INGEST: &str = "ingest";
pub const OCTREE: &str = "octree";
pub const HISTOGRAMS: &str = "histograms";
pub const SOLUTION: &str = "solution";
