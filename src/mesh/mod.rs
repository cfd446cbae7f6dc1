//! Meshes: the crate's one [`Mesh`] type, the named pieces extraction produces
//! ([`UnitMesh`]), reading and writing mesh files, clipping at a box, decimation, and the
//! shaded preview. Nothing here knows the store: extraction (`stages::extract`) builds the
//! pieces, and everything after that works on plain vertices and triangles.

use std::collections::HashMap;

use glam::DVec3;

mod clip;
mod decimate;
mod io;
mod preview;
mod write;

pub use clip::clip;
pub use decimate::{DECIMATE_MAX_ERROR, decimate_units};
pub use io::{MeshReadError, read_mesh};
pub use preview::{View, render, render_view};
pub use write::{ply_header, write_mesh};

/// Identity of a dual-cell corner, as extraction names it: a leaf key, or a virtual exterior
/// cell (bit 127 set, bits 124..127 the mirrored axes, then the key of the leaf it mirrors).
pub type CornerId = u128;

/// A surface vertex's identity: the cut edge it lies on, as its sorted corner pair. Two pieces
/// that produce a vertex of the same name produce the same vertex, which is how pieces weld.
pub type VertexId = (CornerId, CornerId);

/// The surface piece of one treetop unit: named vertices (so pieces weld exactly across
/// units) and triangles over them.
#[derive(Default, Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct UnitMesh {
    /// Name, position and (unnormalised) normal of each vertex.
    pub vertices: Vec<(VertexId, DVec3, DVec3)>,
    /// Triangles as indices into `vertices`.
    pub triangles: Vec<[u32; 3]>,
}

/// A triangle mesh: welded vertices with normals, and triangles.
#[derive(Default, Debug, Clone)]
pub struct Mesh {
    /// Vertex positions.
    pub positions: Vec<[f32; 3]>,
    /// One unit normal per vertex, or none at all (a mesh read from a file without normals).
    pub normals: Vec<[f32; 3]>,
    /// Triangles as indices into `positions`.
    pub triangles: Vec<[u32; 3]>,
}

/// Counts the boundary edges (used by one triangle) and the non-manifold edges (used by more
/// than two) of a mesh: (boundary, non-manifold).
pub fn edge_defects(mesh: &Mesh) -> (usize, usize) {
    let mut count: HashMap<(u32, u32), u32> = HashMap::new();
    for t in &mesh.triangles {
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            *count.entry((a.min(b), a.max(b))).or_insert(0) += 1;
        }
    }
    let boundary = count.values().filter(|&&c| c == 1).count();
    let non_manifold = count.values().filter(|&&c| c > 2).count();
    (boundary, non_manifold)
}

/// Counts of a written mesh.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct MeshSummary {
    /// Vertices written.
    pub vertices: u64,
    /// Triangles written.
    pub triangles: u64,
    /// Edges of one triangle (0 for a closed mesh).
    pub boundary_edges: u64,
    /// Edges of more than two triangles.
    pub non_manifold_edges: u64,
}
