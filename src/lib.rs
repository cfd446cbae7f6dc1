//! octstore: an embedded storage engine for one huge adaptive octree, and the out-of-core
//! surface reconstruction pipeline that runs on it (Poliarnyi 2021, global TGV minimisation).
//!
//! The guide (`docs/` in the repository) is for users; `ARCHITECTURE.md` describes every
//! folder and the invariants a contributor must keep. Bottom up:
//! - [`format`]: cube keys, the immutable segment format, the root cube (byte slices in,
//!   values out);
//! - [`store`]: the versioned store: redb catalog, segment files, commit protocol, snapshots,
//!   the stage runner, the cluster protocol, verify and gc;
//! - [`inputs`]: finding and reading depth maps (RGB-D folders, manifests, COLMAP, LIDAR);
//! - [`kernels`]: CPU reference kernels that need no store (TGV, votes);
//! - [`gpu`]: the same kernels as wgpu compute shaders, tested against [`kernels`];
//! - [`mesh`]: the mesh type, mesh files (PLY, GLB, OBJ), clipping, previews;
//! - [`stages`]: the pipeline stages that run on the store;
//! - [`query`]: reading the indicator field of a pinned version from code;
//! - [`pipeline`]: ingest, solve, the demo and cluster runs as library calls;
//! - [`divide`]: point clouds into overlapping subspaces (Kuhn and Mayer 2015), and `merge`;
//! - [`quality`]: synthetic scenes, ground-truth rendering and mesh evaluation;
//! - [`cli`]: the `octstore` command line.
//!
//! The names most programs need are re-exported here: open a [`Store`], pin a [`Snapshot`],
//! read the field through [`IndicatorField`], or run the pipeline with [`pipeline`]'s calls and
//! their options ([`IngestOptions`], [`DiscoverOptions`], [`SolveParams`]).

pub mod cli;
pub mod divide;
pub mod format;
#[doc(hidden)]
pub mod gpu;
pub mod inputs;
#[doc(hidden)]
pub mod kernels;
pub mod mesh;
pub mod pipeline;
#[doc(hidden)]
pub mod quality;
pub mod query;
#[doc(hidden)]
pub mod stages;
pub mod store;
#[expect(
    unsafe_code,
    reason = "memory maps of immutable segment files, malloc_trim, AVX2 code, SSE2 conversions and AVX-512 gathers: see sys.rs"
)]
mod sys;

pub use divide::DivideError;
pub use format::{BoundingBox, CubeKey, Scene};
pub use inputs::{DiscoverOptions, InputError, PoseProblem};
pub use mesh::{Mesh, MeshReadError, MeshSummary};
pub use pipeline::{PipelineError, SolveOptions, SolveUntil};
pub use quality::synthetic_scenes::SceneSpec;
pub use query::{CubeInfo, IndicatorField, LeafInfo};
pub use stages::extract::{DEFAULT_MAX_ERROR, ExtractOptions, Simplify};
pub use stages::ingest::IngestOptions;
pub use stages::solve::{Method, SolveParams, SsdParams};
pub use store::{RunOptions, RunReport, Snapshot, StageError, Store, StoreError};
pub use sys::{die_quietly_on_closed_pipe, set_env_defaults_at_start};

/// The guide's Rust examples (`docs/api.md`), compiled and run by `cargo test --doc` so that
/// they cannot drift from the API.
#[cfg(doctest)]
#[doc = include_str!("../docs/api.md")]
pub struct GuideExamples;
