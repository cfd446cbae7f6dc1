//! The crate's inside, for its own integration tests and benches (cargo feature `testing`).
//!
//! Not a stable API: everything here may change in any release. Programs use the crate root's
//! re-exports and the public layers (`store`, `query`, `pipeline`, `mesh`, `inputs`, `format`).
//! The integration tests enable the feature through the package's dev-dependency on itself
//! (Cargo.toml), so a plain build of the library never exposes these names.

/// The pipeline stages that run on the store (`src/stages`).
pub mod stages {
    pub use crate::stages::*;
}

/// CPU reference kernels (`src/kernels`).
pub mod kernels {
    pub use crate::kernels::*;
}

/// The wgpu compute kernels and their dispatch (`src/gpu`).
pub mod gpu {
    pub use crate::gpu::*;
}

/// Synthetic scenes, ground-truth rendering and mesh evaluation (`src/quality`).
pub mod quality {
    pub use crate::quality::*;
}

/// The catalog's tables and records (`src/store/catalog.rs`).
pub mod catalog {
    pub use crate::store::catalog::*;
}

/// The failpoints of the commit protocol (`src/store/failpoint.rs`).
pub mod failpoint {
    pub use crate::store::failpoint::*;
}

/// [`crate::pipeline::solve`] on an already open GPU (`options.device` unused): the GPU tests
/// open one device, or a deliberately broken one, and share it between runs.
pub fn solve_with_gpu(
    store: &crate::Store,
    options: &crate::SolveOptions,
    gpu: Option<std::sync::Arc<crate::gpu::Gpu>>,
    on_report: impl FnMut(&crate::RunReport),
) -> Result<(), crate::PipelineError> {
    crate::pipeline::solve_with_gpu(store, options, gpu, on_report)
}
