//! Meshes: the crate's one [`Mesh`] type, the named pieces extraction produces
//! ([`UnitMesh`]), reading and writing mesh files, clipping at a box, and the
//! shaded preview. Nothing here knows the store: extraction (`stages::extract`) builds the
//! pieces, and everything after that works on plain vertices and triangles.

use std::collections::HashMap;

use glam::DVec3;

mod clip;
mod glb;
mod io;
mod preview;
mod write;

pub use clip::clip;
pub(crate) use clip::{Corner, clip_triangle};
pub(crate) use glb::{GLB_VERTEX_BYTES, is_glb, write_glb_head};
pub use io::{MeshReadError, read_mesh};
pub use preview::{View, render, render_view};
pub use write::{output_target, ply_header, remove_leftovers, temporary_beside, write_atomically, write_mesh};

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
    /// Where this piece's cells would move vertices other pieces may also produce (seam
    /// vertices), which only the weld, holding every piece's share, can place.
    pub seam_moves: Vec<VertexMove>,
}

impl UnitMesh {
    /// The position of vertex `index`; the origin for an index past the end (no triangle of
    /// a well-formed piece has one).
    pub fn position(&self, index: u32) -> DVec3 {
        self.vertices.get(index as usize).map_or(DVec3::ZERO, |v| v.1)
    }

    /// Bytes the piece's lists hold on the heap (their capacities).
    pub fn heap_bytes(&self) -> u64 {
        let bytes = |capacity: usize, each: usize| (capacity * each) as u64;
        bytes(
            self.vertices.capacity(),
            std::mem::size_of::<(VertexId, DVec3, DVec3)>(),
        ) + bytes(self.triangles.capacity(), std::mem::size_of::<[u32; 3]>())
            + bytes(self.seam_moves.capacity(), std::mem::size_of::<VertexMove>())
    }
}

/// A piece's share in placing a vertex: the planes that the piece's cells around the vertex
/// measured the surface on, summed so that the mean of a point's projections onto them can be
/// computed (the projection onto the plane `n . x = d`, n a unit normal, is `x - n n^T x + d n`,
/// affine in x). Every piece that produces the vertex adds its planes; the vertex goes to the
/// mean of its projections, at most `reach` from where extraction put it.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct VertexMove {
    /// Index into the piece's `vertices`.
    pub vertex: u32,
    /// Sum of the planes' `n n^T`, as xx, xy, xz, yy, yz, zz.
    pub normals: [f64; 6],
    /// Sum of the planes' `d n`.
    pub shifts: DVec3,
    /// How many planes.
    pub count: u32,
    /// How far the vertex may move from where extraction put it.
    pub reach: f64,
}

impl VertexMove {
    /// No planes yet, for vertex `vertex`.
    pub fn empty(vertex: u32, reach: f64) -> Self {
        VertexMove {
            vertex,
            normals: [0.0; 6],
            shifts: DVec3::ZERO,
            count: 0,
            reach,
        }
    }

    /// Adds the plane of points x with `normal . x = distance` (`normal` of unit length).
    pub fn add_plane(&mut self, normal: DVec3, distance: f64) {
        let n = normal;
        for (sum, term) in
            self.normals
                .iter_mut()
                .zip([n.x * n.x, n.x * n.y, n.x * n.z, n.y * n.y, n.y * n.z, n.z * n.z])
        {
            *sum += term;
        }
        self.shifts += n * distance;
        self.count += 1;
    }

    /// Adds another piece's share of the same vertex (an empty share may not know its reach).
    pub fn add(&mut self, other: &VertexMove) {
        for (sum, term) in self.normals.iter_mut().zip(other.normals) {
            *sum += term;
        }
        self.shifts += other.shifts;
        self.count += other.count;
        self.reach = self.reach.max(other.reach);
    }

    /// Where the vertex goes from `position`, `origin` being where extraction put it: the mean of
    /// `position`'s projections onto the planes, held within `reach` of `origin`.
    pub fn place(&self, position: DVec3, origin: DVec3) -> DVec3 {
        if self.count == 0 {
            return position;
        }
        let [xx, xy, xz, yy, yz, zz] = self.normals;
        let outer = glam::DMat3::from_cols(DVec3::new(xx, xy, xz), DVec3::new(xy, yy, yz), DVec3::new(xz, yz, zz));
        let target = position + (self.shifts - outer * position) / f64::from(self.count);
        let moved = target - origin;
        let length = moved.length();
        if length > self.reach {
            origin + moved * (self.reach / length)
        } else {
            target
        }
    }
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

/// Counts the connected components of a mesh's triangles: two triangles are connected when
/// they share a vertex (index), directly or through others. Unused vertices count for nothing.
pub fn connected_components(mesh: &Mesh) -> usize {
    let mut sets = DisjointSets::new(mesh.positions.len());
    for t in &mesh.triangles {
        sets.union(t[0], t[1]);
        sets.union(t[0], t[2]);
    }
    let mut roots: Vec<u32> = mesh.triangles.iter().map(|t| sets.find(t[0])).collect();
    roots.sort_unstable();
    roots.dedup();
    roots.len()
}

/// Disjoint sets over `0..n` (union-find with path halving). A union makes the lower of the
/// two roots the parent, so every set's root is its least member, whatever the order of the
/// unions: what is keyed by roots does not depend on it.
pub(crate) struct DisjointSets {
    parent: Vec<u32>,
}

impl DisjointSets {
    /// `n` sets of one member each.
    pub(crate) fn new(n: usize) -> DisjointSets {
        DisjointSets {
            parent: (0..n as u32).collect(),
        }
    }

    /// The root of `v`'s set (`v` itself if it is out of range).
    pub(crate) fn find(&mut self, mut v: u32) -> u32 {
        while let Some(&up) = self.parent.get(v as usize) {
            if up == v {
                break;
            }
            // Path halving: point v at its grandparent.
            let grand = self.parent.get(up as usize).copied().unwrap_or(up);
            if let Some(slot) = self.parent.get_mut(v as usize) {
                *slot = grand;
            }
            v = grand;
        }
        v
    }

    /// Joins the sets of `a` and `b`.
    pub(crate) fn union(&mut self, a: u32, b: u32) {
        let (a, b) = (self.find(a), self.find(b));
        if a != b
            && let Some(slot) = self.parent.get_mut(a.max(b) as usize)
        {
            *slot = a.min(b);
        }
    }
}

/// Each triangle's part in `indices` (three vertex indices per triangle), triangles joined by
/// shared edges (two that share only a vertex are in different parts): the least triangle of
/// the part.
pub(crate) fn edge_parts(indices: &[u32]) -> Vec<u32> {
    let triangles = indices.len() / 3;
    let mut sets = DisjointSets::new(triangles);
    // Each triangle's edges by their lesser and greater end; equal edges sort together.
    let mut edges: Vec<(u32, u32, u32)> = indices
        .chunks_exact(3)
        .enumerate()
        .flat_map(|(i, t)| [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])].map(|(a, b)| (a.min(b), a.max(b), i as u32)))
        .collect();
    edges.sort_unstable();
    for pair in edges.windows(2) {
        if let [x, y] = pair
            && (x.0, x.1) == (y.0, y.1)
        {
            sets.union(x.2, y.2);
        }
    }
    (0..triangles as u32).map(|i| sets.find(i)).collect()
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn components_join_through_shared_vertices_only() {
        let mut mesh = Mesh {
            positions: vec![[0.0; 3]; 8],
            ..Mesh::default()
        };
        assert_eq!(connected_components(&mesh), 0);
        // Two triangles sharing vertex 2, one apart, and vertex 7 unused.
        mesh.triangles = vec![[0, 1, 2], [2, 3, 4], [5, 6, 0]];
        assert_eq!(connected_components(&mesh), 1);
        mesh.triangles = vec![[0, 1, 2], [2, 3, 4], [5, 6, 3], [1, 0, 2]];
        assert_eq!(connected_components(&mesh), 1);
        mesh.triangles = vec![[0, 1, 2], [3, 4, 5], [5, 6, 3]];
        assert_eq!(connected_components(&mesh), 2);
        assert_eq!(edge_defects(&mesh).0, 7);
    }
}
