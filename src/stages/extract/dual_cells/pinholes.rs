//! Pinholes: the unsupported cut tetrahedra of a unit that a hole in its kept surface would
//! leave, added back once the unit's kept surface is known.

use glam::DVec3;

use super::{Corner, Piece, mesh_tetrahedron, polygon_edges, vertex_name};
use crate::mesh::{DisjointSets, VertexId};

/// A cut tetrahedron of an observed dual cell that its own corners do not support
/// ([`super::tetrahedron_supported`]), held until the unit's kept surface is known
/// ([`fill_pinholes`]).
pub(super) struct HeldTetrahedron {
    pub(super) corners: [Corner; 4],
    pub(super) gradient: DVec3,
}

/// The most held tetrahedra a pinhole may span to be filled.
const PINHOLE_TETRAHEDRA: usize = 8;

/// Adds back the held tetrahedra that fill pinholes in the unit's kept surface: groups of at
/// most [`PINHOLE_TETRAHEDRA`] held tetrahedra joined by shared polygon edges whose every
/// other polygon edge is an edge of a kept triangle. A fringe (held surface at the edge of
/// what samples reached) has edges that nothing else shares and stays out; a hole that the
/// kept surface surrounds, where noise left a few cells short of support, closes. A polygon
/// edge lies on a face shared by exactly two tetrahedra, so sharing is decided by the two
/// vertex names; edges kept by another unit are not seen, so pinholes on a seam stay open
/// (each tetrahedron is meshed by the one unit that generates its cell, so both sides agree).
pub(super) fn fill_pinholes(piece: &mut Piece) {
    let held = std::mem::take(&mut piece.held);
    if held.is_empty() {
        return;
    }
    type EdgeName = (VertexId, VertexId);
    let edge_name = |a: VertexId, b: VertexId| -> EdgeName { if a <= b { (a, b) } else { (b, a) } };
    let polygons: Vec<Vec<VertexId>> = held
        .iter()
        .map(|h| {
            polygon_edges(&h.corners.each_ref())
                .into_iter()
                .map(|(a, b)| vertex_name(&h.corners[a], &h.corners[b]))
                .collect()
        })
        .collect();
    let ring = |polygon: &[VertexId]| -> Vec<EdgeName> {
        (0..polygon.len())
            .filter_map(|i| Some(edge_name(*polygon.get(i)?, *polygon.get((i + 1) % polygon.len())?)))
            .collect()
    };
    // Held polygons joined by shared edges.
    let mut sets = DisjointSets::new(held.len());
    let mut held_edges: crate::stages::extract::FastMap<EdgeName, (usize, u32)> =
        crate::stages::extract::FastMap::default();
    for (i, polygon) in polygons.iter().enumerate() {
        for edge in ring(polygon) {
            let entry = held_edges.entry(edge).or_insert((i, 0));
            entry.1 += 1;
            sets.union(entry.0 as u32, i as u32);
        }
    }
    // Edges of kept triangles between vertices that held polygons use.
    let names: std::collections::HashSet<VertexId, foldhash::fast::FixedState> =
        polygons.iter().flatten().copied().collect();
    let name_of = |i: u32| piece.mesh.vertices.get(i as usize).map(|v| v.0);
    let mut kept_edges: std::collections::HashSet<EdgeName, foldhash::fast::FixedState> = Default::default();
    for tri in &piece.mesh.triangles {
        for k in 0..3 {
            let (Some(a), Some(b)) = (name_of(tri[k]), name_of(tri[(k + 1) % 3])) else {
                continue;
            };
            if names.contains(&a) && names.contains(&b) {
                kept_edges.insert(edge_name(a, b));
            }
        }
    }
    // A group fills a pinhole if each of its edges is shared within it or kept.
    let mut group_size: crate::stages::extract::FastMap<u32, usize> = crate::stages::extract::FastMap::default();
    let mut group_closed: crate::stages::extract::FastMap<u32, bool> = crate::stages::extract::FastMap::default();
    for (i, polygon) in polygons.iter().enumerate() {
        let root = sets.find(i as u32);
        *group_size.entry(root).or_insert(0) += 1;
        let closed = ring(polygon)
            .iter()
            .all(|edge| kept_edges.contains(edge) || held_edges.get(edge).is_some_and(|&(_, uses)| uses >= 2));
        let slot = group_closed.entry(root).or_insert(true);
        *slot = *slot && closed;
    }
    for (i, h) in held.iter().enumerate() {
        let root = sets.find(i as u32);
        let size = group_size.get(&root).copied().unwrap_or(usize::MAX);
        if size <= PINHOLE_TETRAHEDRA && group_closed.get(&root).copied().unwrap_or(false) {
            mesh_tetrahedron(&h.corners.each_ref(), h.gradient, piece);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::{Surface, cell_gradient, mesh_cell};
    use super::*;

    /// Meshes the dual cells with lower corners `cells` of a lattice of finest cubes, two
    /// layers deep, cut by the plane z = 0.4 sides; the lattice points in `unmeasured` had
    /// samples but measured nothing. Returns the triangle count before and after
    /// [`fill_pinholes`], and the held tetrahedra.
    fn lattice_mesh(cells: &[(u32, u32)], unmeasured: &[[u32; 3]], closed: bool) -> (usize, usize, usize) {
        let side = 0.0057;
        let corner = |p: [u32; 3]| {
            let center = DVec3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2])) * side;
            let offset = center.z - 0.4 * side;
            let measured = !unmeasured.contains(&p);
            Corner {
                id: u128::from(p[0] + 16 * p[1] + 256 * p[2]),
                center,
                u: if offset > 0.0 { 0.5 } else { -0.5 },
                offset: if measured { offset } else { f64::NAN },
                votes: 1.0,
                measured: if measured { 1.0 } else { 0.0 },
                sampled: true,
            }
        };
        let mut piece = Piece::default();
        for &(i, j) in cells {
            let corners: [Corner; 8] = std::array::from_fn(|b| {
                let b = b as u32;
                corner([i + (b & 1), j + ((b >> 1) & 1), (b >> 2) & 1])
            });
            let surface = if closed { Surface::Whole } else { Surface::Observed };
            mesh_cell(&corners, cell_gradient(&corners), surface, &mut piece);
        }
        let (before, held_count) = (piece.mesh.triangles.len(), piece.held.len());
        fill_pinholes(&mut piece);
        (before, piece.mesh.triangles.len(), held_count)
    }

    #[test]
    fn pinholes_in_kept_surface_fill_but_fringes_stay_open() {
        // One Kuhn tetrahedron of cell (2, 2) has four corners that measured nothing: its own
        // corners do not support the surface, so it is held.
        let hole = [[2, 2, 0], [3, 2, 0], [3, 3, 0], [3, 3, 1]];
        let all: Vec<(u32, u32)> = (0..4).flat_map(|i| (0..4).map(move |j| (i, j))).collect();
        let (_, closed, _) = lattice_mesh(&all, &hole, true);
        let (before, after, held) = lattice_mesh(&all, &hole, false);
        assert_eq!(held, 1);
        assert!(before < closed, "the held tetrahedron is cut");
        // Kept surface surrounds it on every side: a pinhole, filled.
        assert_eq!(after, closed);
        // Alone, its cell's neighbours not meshed, the same tetrahedron is a fringe: its
        // polygon's edge on the cell's face borders nothing kept.
        let (_, alone_closed, _) = lattice_mesh(&[(2, 2)], &hole, true);
        let (alone_before, alone_after, alone_held) = lattice_mesh(&[(2, 2)], &hole, false);
        assert_eq!(alone_held, 1);
        assert!(alone_before < alone_closed);
        assert_eq!(alone_after, alone_before);
    }
}
