//! octstore: an embedded storage engine for one huge adaptive octree, and the out-of-core
//! surface reconstruction pipeline that runs on it (Poliarnyi 2021, global TGV minimisation).
//!
//! The guide (`docs/` in the repository) is for users; `ARCHITECTURE.md` describes every
//! folder and the invariants a contributor must keep. Bottom up:
//! - [`format`](mod@format): cube keys, the immutable segment format, the root cube (byte slices in,
//!   values out);
//! - [`store`]: the versioned store: redb catalog, segment files, commit protocol, snapshots,
//!   the stage runner, the cluster protocol, verify and gc;
//! - [`inputs`]: finding and reading depth maps (RGB-D folders, manifests, COLMAP, LIDAR);
//! - `kernels` (private): CPU reference kernels that need no store (TGV, votes);
//! - `gpu` (private): the same kernels as wgpu compute shaders, tested against `kernels`;
//! - [`mesh`]: the mesh type, mesh files (PLY, GLB, OBJ), clipping, previews;
//! - `stages` (private): the pipeline stages that run on the store; their options and
//!   reports are re-exported here;
//! - [`query`]: reading the indicator field of a pinned version from code;
//! - [`pipeline`]: ingest, solve, the demo and cluster runs as library calls;
//! - [`divide`]: point clouds into overlapping subspaces (Kuhn and Mayer 2015), and `merge`;
//! - `quality` (private): synthetic scenes, ground-truth rendering and mesh evaluation, run
//!   by the `octstore-gt-render` and `octstore-evaluate` tools;
//! - [`cli`]: the `octstore` command line and those two tools.
//!
//! The crate's own integration tests, benches and Python tests reach the private layers
//! through `octstore::testing`, which exists only with the `testing` cargo feature and is not
//! a stable API.
//!
//! The names most programs need are re-exported here: open a [`Store`], pin a [`Snapshot`],
//! read the field through [`IndicatorField`], or run the pipeline with [`pipeline`]'s calls and
//! their options ([`IngestOptions`], [`DiscoverOptions`], [`SolveParams`]).

// A public signature that names a type of a private layer (stages, kernels, gpu, quality) must
// re-export that type by name (ARCHITECTURE.md, "Public and private"). Checked without the
// `testing` feature, whose re-exports are not the public API.
#![cfg_attr(not(feature = "testing"), deny(unnameable_types))]

pub mod cli;
pub mod divide;
pub mod format;
mod gpu;
pub mod inputs;
mod kernels;
pub mod mesh;
pub mod pipeline;
mod quality;
pub mod query;
mod stages;
pub mod store;
#[expect(
    unsafe_code,
    reason = "memory maps of immutable segment files, malloc_trim, AVX2 code, SSE2 conversions and AVX-512 gathers: see sys.rs"
)]
mod sys;
#[cfg(feature = "testing")]
pub mod testing;

pub use divide::DivideError;
pub use format::{BoundingBox, CubeKey, Scene};
pub use gpu::{AdapterSummary, DeviceChoice, GpuError};
pub use inputs::{DiscoverOptions, InputError, PoseProblem};
pub use mesh::{Mesh, MeshReadError, MeshSummary};
pub use pipeline::{PipelineError, SolveOptions, SolveUntil};
pub use quality::synthetic_scenes::{Noise, SceneSpec, Shape};
pub use query::{CubeInfo, HISTOGRAM_BINS, IndicatorField, LeafInfo};
pub use stages::extract::{DEFAULT_MAX_ERROR, ExtractOptions, Simplify, Surface, SurfaceChoice};
pub use stages::ingest::IngestOptions;
pub use stages::solve::{Method, MethodChoice, SolveParams, SsdParams};
pub use store::{RunOptions, RunReport, Snapshot, StageError, Store, StoreError};
pub use sys::{die_quietly_on_closed_pipe, purge_freed_pages_at_once, set_env_defaults_at_start};

/// The guide's Rust examples (`docs/api.md`), compiled and run by `cargo test --doc` so that
/// they cannot drift from the API.
#[cfg(doctest)]
#[doc = include_str!("../docs/api.md")]
pub struct GuideExamples;
