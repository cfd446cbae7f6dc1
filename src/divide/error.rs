//! What stops a `divide` or a `merge`: one variant per problem, each naming the file or folder
//! and saying what to do.

use std::path::PathBuf;

use crate::inputs::InputError;
use crate::store::StoreError;

/// Why `divide` or `merge` cannot go on (the `Divide` variant of [`crate::DivideError`]).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum DivideError {
    /// No input was given.
    #[error("no input point clouds")]
    NoInputs,
    /// The inputs hold no point.
    #[error("the inputs hold no points")]
    NoPoints,
    /// `--max-points` is 0.
    #[error("--max-points must be at least 1")]
    MaxPointsZero,
    /// `--overlap` outside [0, 1).
    #[error("--overlap {overlap} is not in [0, 1)")]
    OverlapOutOfRange {
        /// The overlap asked for.
        overlap: f64,
    },
    /// Inputs whose vertex properties differ cannot share one division.
    #[error(
        "{input}: its vertex properties ({properties}) differ from those of {other} ({other_properties}); divide them separately"
    )]
    PropertiesDiffer {
        /// The input that differs.
        input: String,
        /// Its properties.
        properties: String,
        /// The input or division it differs from.
        other: String,
        /// Those properties.
        other_properties: String,
    },
    /// A later divide asked for other limits than the folder's division.
    #[error(
        "{} was divided with --max-points {max_points} and --overlap {overlap}; a later divide into it keeps them (asked: {asked_max_points} and {asked_overlap})",
        folder.display()
    )]
    LimitsDiffer {
        /// The division's folder.
        folder: PathBuf,
        /// Its `--max-points`.
        max_points: u64,
        /// Its `--overlap`.
        overlap: f64,
        /// The `--max-points` asked for.
        asked_max_points: u64,
        /// The `--overlap` asked for.
        asked_overlap: f64,
    },
    /// New points beyond the root cube of an existing division.
    #[error(
        "the new points reach from {low:?} to {high:?}, beyond the root cube of {} (min {root_min:?}, size {root_size}): divide everything into a new folder",
        folder.display()
    )]
    BeyondRoot {
        /// The division's folder.
        folder: PathBuf,
        /// The new points' low corner.
        low: [f64; 3],
        /// The new points' high corner.
        high: [f64; 3],
        /// The root cube's low corner.
        root_min: [f64; 3],
        /// The root cube's side.
        root_size: f64,
    },
    /// A folder given as input that is not a store.
    #[error("{}: a folder, but not an octstore store (no catalog.redb); give point cloud files, scans or a store", path.display())]
    NotAStore {
        /// The folder.
        path: PathBuf,
    },
    /// A store given as input that has no depth maps.
    #[error("{}: the store has no depth maps", path.display())]
    EmptyStore {
        /// The store.
        path: PathBuf,
    },
    /// `merge`: a mesh whose name matches no subspace's file.
    #[error("{}: its name starts with no subspace's file name in the manifest", mesh.display())]
    UnmatchedMesh {
        /// The mesh.
        mesh: PathBuf,
    },
    /// `merge`: two meshes for one subspace.
    #[error("{} and {} are both meshes of subspace {subspace}", first.display(), second.display())]
    TwoMeshes {
        /// The first mesh.
        first: PathBuf,
        /// The second mesh.
        second: PathBuf,
        /// The subspace's file stem.
        subspace: String,
    },
    /// `merge`: a triangle names a vertex the mesh does not have.
    #[error("{}: a triangle names a missing vertex", mesh.display())]
    MissingVertex {
        /// The mesh.
        mesh: PathBuf,
    },
    /// A division's manifest that cannot be read, parsed or trusted (damaged, hand-edited, or
    /// written by a later octstore).
    #[error("{}: {source}", path.display())]
    BadManifest {
        /// The manifest.
        path: PathBuf,
        /// What is wrong with it.
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// A point cloud or scan could not be read (the error names the file).
    #[error("{0}")]
    PointCloud(#[from] InputError),
    /// Reading or writing a file failed.
    #[error("{action} {}: {source}", path.display())]
    Io {
        /// What was being done.
        action: &'static str,
        /// The file.
        path: PathBuf,
        /// The system's error.
        source: std::io::Error,
    },
    /// `merge`: a mesh could not be read (the error names the file).
    #[error(transparent)]
    Mesh(#[from] crate::mesh::MeshReadError),
    /// A store given as input failed (boxed: the store's errors are large).
    #[error(transparent)]
    Store(Box<StoreError>),
    /// A broken invariant (a bug).
    #[error("internal: {0}")]
    Internal(String),
}

impl From<StoreError> for DivideError {
    fn from(error: StoreError) -> Self {
        DivideError::Store(Box::new(error))
    }
}
