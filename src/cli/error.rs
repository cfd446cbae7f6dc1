//! The command line's errors: what the pipeline reports, and the few mistakes only a command
//! line can make. `main` prints them as `error: ...` and exits non-zero.

use std::path::PathBuf;

use crate::StoreError;
use crate::mesh::MeshReadError;
use crate::pipeline::PipelineError;

/// Errors of `octstore` verbs.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum CliError {
    /// The pipeline (and through it the store) failed.
    #[error(transparent)]
    Pipeline(#[from] PipelineError),
    /// The arguments do not say what to do.
    #[error("{verb}: {problem}")]
    Usage {
        /// The verb.
        verb: &'static str,
        /// What is missing.
        problem: &'static str,
    },
    /// `render --pose` names a file that is not a usable camera pose.
    #[error("render: pose {path}: {problem}")]
    Pose {
        /// The pose file.
        path: PathBuf,
        /// What is wrong with it.
        problem: String,
    },
}

impl From<StoreError> for CliError {
    fn from(error: StoreError) -> Self {
        CliError::Pipeline(error.into())
    }
}

impl From<MeshReadError> for CliError {
    fn from(error: MeshReadError) -> Self {
        CliError::Pipeline(error.into())
    }
}

/// The result of verbs.
pub type Result<T, E = CliError> = std::result::Result<T, E>;

impl From<crate::divide::DivideError> for CliError {
    fn from(error: crate::divide::DivideError) -> Self {
        CliError::Pipeline(error.into())
    }
}
