//! Quality tools: synthetic scenes rendered into depth maps ([`synthetic_scenes`], the demo's
//! input), depth maps of ground-truth meshes with noise ([`ground_truth_views`]), a furnished
//! room seen from inside ([`interior_scene`]), and
//! reconstructions measured against the truth ([`evaluate`]), and meshes checked for triangles
//! that cross each other ([`self_intersection`]). The binaries in `tools/`
//! (`octstore-gt-render`, `octstore-evaluate`) are thin command lines over these.

// A private layer: its `pub` items are the crate's own API and, with the `testing` feature, its
// integration tests' and benches' (`octstore::testing`). Some exist only for those (reference
// kernels, the GPU tests' reading helpers), so a build without the feature sees them unused.
#![cfg_attr(not(feature = "testing"), allow(dead_code, unused_imports))]
// `octstore::testing` is not the documented public surface: its items need no docs there.
#![cfg_attr(feature = "testing", allow(missing_docs))]

pub mod evaluate;
pub mod ground_truth_views;
pub mod interior_scene;
pub mod self_intersection;
pub mod synthetic_scenes;

/// Errors of the quality tools' library calls.
#[derive(Debug, thiserror::Error, PartialEq)]
#[non_exhaustive]
pub enum QualityError {
    /// The distance threshold tau must be positive.
    #[error("tau must be positive, is {0}")]
    NonPositiveTau(f64),
    /// A ground-truth mesh without area cannot be sampled.
    #[error("the ground-truth mesh has no area")]
    NoArea,
    /// A ground-truth mesh without triangles has no bounds.
    #[error("the mesh has no triangles")]
    NoTriangles,
    /// A list of seen ground-truth faces must have one entry per triangle.
    #[error("the seen-faces list covers {listed} triangles, the ground truth has {triangles}")]
    SeenFacesMismatch {
        /// Entries in the list.
        listed: usize,
        /// Triangles in the ground-truth mesh.
        triangles: usize,
    },
}
