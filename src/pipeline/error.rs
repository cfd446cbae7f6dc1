//! The pipeline layer's errors. Store errors pass through unchanged; the rest name the step
//! and say what to do.

use std::path::PathBuf;

use crate::StoreError;
use crate::gpu::GpuError;
use crate::inputs::InputError;
use crate::mesh::MeshReadError;

/// Errors of [`crate::pipeline`] calls (and of the command line, which reports them).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum PipelineError {
    /// The store failed: I/O, corruption, a second writer, a failed unit of a stage. Boxed:
    /// the store's errors are large, and every pipeline call returns this type.
    #[error(transparent)]
    Store(Box<StoreError>),
    /// An input path could not be turned into depth maps.
    #[error("ingest: {0}")]
    Inputs(#[from] InputError),
    /// A step needs the scene, which the first ingest fixes.
    #[error("{step}: the store has no depth maps yet: run `octstore ingest` first")]
    NotIngested {
        /// The step that needed it.
        step: String,
    },
    /// `--device gpu` was asked for and no GPU opened.
    #[error("--device gpu: {0}")]
    NoGpu(GpuError),
    /// A cluster step named a stage that cluster runs do not run.
    #[error("stage '{stage}': {hint}")]
    NotAClusterStage {
        /// The name given.
        stage: String,
        /// What to run instead.
        hint: &'static str,
    },
    /// A cluster step found no plan for its stage.
    #[error("stage '{stage}': no cluster plan: run `octstore plan` first")]
    NoPlan {
        /// The stage.
        stage: String,
    },
    /// The store moved on after the extraction plan was made.
    #[error("stage 'extract': the store changed since the plan was made: run `octstore plan` again")]
    StalePlan,
    /// `divide` or `merge` cannot go on: what is wrong, naming the file or folder.
    #[error("divide: {0}")]
    Divide(#[from] crate::divide::DivideError),
    /// A mesh file could not be read.
    #[error(transparent)]
    Mesh(#[from] MeshReadError),
    /// Reading or writing a file outside the store failed.
    #[error("{action} {path}: {source}")]
    Io {
        /// What was being done.
        action: &'static str,
        /// The file.
        path: PathBuf,
        /// The system's error.
        source: std::io::Error,
    },
    /// `sbatch` refused a job of the chain.
    #[error("slurm: job {job}: sbatch failed: {message}")]
    Sbatch {
        /// The job's name.
        job: String,
        /// What sbatch said.
        message: String,
    },
}

impl From<StoreError> for PipelineError {
    fn from(error: StoreError) -> Self {
        PipelineError::Store(Box::new(error))
    }
}

/// The result of pipeline calls.
pub type Result<T, E = PipelineError> = std::result::Result<T, E>;

/// Writes `image` as PNG at `path`, atomically (`mesh::write_atomically`); the image crate's
/// error becomes an I/O error on the file.
pub(crate) fn save_png(image: &image::RgbImage, path: &std::path::Path) -> Result<()> {
    let mut encoded = std::io::Cursor::new(Vec::new());
    image
        .write_to(&mut encoded, image::ImageFormat::Png)
        .map_err(|e| io_error("encode image", path)(std::io::Error::other(e.to_string())))?;
    crate::mesh::output_target(path)
        .and_then(|target| crate::mesh::remove_leftovers(&target))
        .map_err(io_error("write image", path))?;
    crate::mesh::write_atomically(path, |out| std::io::Write::write_all(out, encoded.get_ref()))
        .map_err(io_error("write image", path))
}

/// `map_err` adapter: an I/O error of `action` on `path`.
pub(crate) fn io_error(action: &'static str, path: &std::path::Path) -> impl FnOnce(std::io::Error) -> PipelineError {
    let path = path.to_path_buf();
    move |source| PipelineError::Io { action, path, source }
}
