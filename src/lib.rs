//! octstore: an embedded storage engine for one huge adaptive octree, and the out-of-core
//! surface reconstruction pipeline that runs on it (Poliarnyi 2021, global TGV minimisation).
//!
//! Architecture, bottom up:
//! - [`format`]: cube keys and the immutable segment file format (byte slices in, values out);
//! - [`store`]: the versioned store: redb catalog, segment files, commit protocol, snapshots,
//!   the stage runner, verify and gc;
//! - [`stages`]: the pipeline stages that run on the store;
//! - [`pipeline`]: ingest and solve as library calls;
//! - [`quality`]: ground-truth rendering and mesh evaluation (the quality tools);
//! - [`cli`]: the `octstore` command line.

pub mod cli;
pub mod format;
pub mod gpu;
pub mod pipeline;
pub mod quality;
pub mod render;
pub mod scenes;
pub mod stages;
pub mod store;
mod sys;

pub use format::CubeKey;
pub use stages::query::IndicatorField;
pub use store::{Snapshot, Store, StoreError};
