//! The watertight surface's pieces without observed surface, and its voids, dropped.

use super::VertexGuides;
use crate::mesh::{DisjointSets, UnitMesh, VertexId};

/// Drops from a unit's watertight piece the connected parts (joined by shared vertices) that
/// lie wholly in the unit (no vertex that another unit may also produce, `private`) and either
/// hold no anchor (a vertex of the observed surface, [`VertexGuides::anchors`]) or enclose
/// free space (negative signed volume: triangles face positive u, outwards from the solid).
/// The first are bubbles of the zero set in free space, where outliers pulled u below zero; the
/// second are voids inside an object, where outliers behind its surface voted free space: no
/// camera outside the object could see into either. A part that reaches another unit is kept
/// whole, so both sides of a seam agree without knowing each other's anchors. The kept
/// vertices keep their order, renumbered; their guides follow them.
pub(in crate::stages::extract) fn drop_unobserved_pieces(
    mesh: &mut UnitMesh,
    guides: &mut VertexGuides,
    private: &dyn Fn(&VertexId) -> bool,
) {
    let n = mesh.vertices.len();
    let mut sets = DisjointSets::new(n);
    for &[a, b, c] in &mesh.triangles {
        sets.union(a, b);
        sets.union(b, c);
    }
    // Per root (each set's least member): anchored, reaching another unit, and six times the
    // signed volume, summed about the root's position (a closed part's volume does not depend
    // on the point; one near it keeps the sum precise far from the origin).
    let mut anchored = vec![false; n];
    for &vertex in &guides.anchors {
        if let Some(slot) = anchored.get_mut(sets.find(vertex) as usize) {
            *slot = true;
        }
    }
    let mut reaches_seam = vec![false; n];
    for (i, vertex) in mesh.vertices.iter().enumerate() {
        if !private(&vertex.0)
            && let Some(slot) = reaches_seam.get_mut(sets.find(i as u32) as usize)
        {
            *slot = true;
        }
    }
    let position = |i: u32| mesh.vertices.get(i as usize).map_or(glam::DVec3::ZERO, |v| v.1);
    let mut volume = vec![0.0f64; n];
    for &[a, b, c] in &mesh.triangles {
        let root = sets.find(a);
        let origin = position(root);
        let (pa, pb, pc) = (position(a) - origin, position(b) - origin, position(c) - origin);
        if let Some(slot) = volume.get_mut(root as usize) {
            *slot += pa.dot(pb.cross(pc));
        }
    }
    let kept_root = |root: usize| {
        reaches_seam.get(root).copied().unwrap_or(true)
            || (anchored.get(root).copied().unwrap_or(false) && volume.get(root).copied().unwrap_or(0.0) > 0.0)
    };
    let keep: Vec<bool> = (0..n as u32).map(|v| kept_root(sets.find(v) as usize)).collect();
    if keep.iter().all(|&k| k) {
        guides.anchors = Vec::new();
        return;
    }
    // New index of each kept vertex (u32::MAX for a dropped one).
    let mut renumbered = vec![u32::MAX; n];
    for (next, (slot, _)) in renumbered.iter_mut().zip(&keep).filter(|(_, k)| **k).enumerate() {
        *slot = next as u32;
    }
    let kept = |i: usize| keep.get(i).copied().unwrap_or(false);
    let mut index = 0;
    mesh.vertices.retain(|_| {
        index += 1;
        kept(index - 1)
    });
    let mut index = 0;
    guides.ends.retain(|_| {
        index += 1;
        kept(index - 1)
    });
    guides.moves.retain(|m| kept(m.vertex as usize));
    for m in &mut guides.moves {
        m.vertex = renumbered.get(m.vertex as usize).copied().unwrap_or(u32::MAX);
    }
    mesh.triangles.retain(|t| kept(t[0] as usize));
    for t in &mut mesh.triangles {
        *t = t.map(|v| renumbered.get(v as usize).copied().unwrap_or(u32::MAX));
    }
    guides.anchors = Vec::new();
}

#[cfg(test)]
mod tests {
    use glam::DVec3;

    use super::*;
    use crate::mesh::VertexMove;

    /// A piece of four separate tetrahedra, vertices 4k to 4k + 3 for part k, 3 apart along x;
    /// part 2 faces inwards (a void). Each vertex's guides are marked with its index.
    fn four_tetrahedra() -> (UnitMesh, VertexGuides) {
        let mut mesh = UnitMesh::default();
        let mut guides = VertexGuides::default();
        let corners = [DVec3::ZERO, DVec3::X, DVec3::Y, DVec3::Z];
        for part in 0..4u32 {
            for (k, corner) in corners.iter().enumerate() {
                let i = 4 * part + k as u32;
                let position = *corner + DVec3::X * f64::from(3 * part);
                mesh.vertices
                    .push(((u128::from(i), u128::from(i) + 100), position, DVec3::Z));
                guides.ends.push((DVec3::splat(f64::from(i)), DVec3::ZERO));
                guides.moves.push(VertexMove::empty(i, f64::from(i)));
            }
            let b = 4 * part;
            // Faces outwards (positive volume), reversed for the void.
            for [x, y, z] in [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]] {
                let face = if part == 2 { [x, z, y] } else { [x, y, z] };
                mesh.triangles.push(face.map(|v| b + v));
            }
        }
        (mesh, guides)
    }

    #[test]
    fn bubbles_and_voids_go_and_the_rest_are_renumbered() {
        let (mut mesh, mut guides) = four_tetrahedra();
        // Part 0 holds observed surface; part 1 none; part 2 does but is a void; part 3 has no
        // anchor but reaches another unit through vertex 13.
        guides.anchors = vec![1, 1, 9];
        let private = |name: &VertexId| name.0 != 13;
        drop_unobserved_pieces(&mut mesh, &mut guides, &private);
        let kept: Vec<u128> = mesh.vertices.iter().map(|v| v.0.0).collect();
        assert_eq!(kept, vec![0, 1, 2, 3, 12, 13, 14, 15]);
        assert_eq!(mesh.triangles.len(), 8);
        assert_eq!(mesh.triangles.get(4), Some(&[4, 6, 5]));
        assert!(mesh.triangles.iter().flatten().all(|&v| v < 8));
        // Guides follow their vertices, and each move names its new index.
        let ends: Vec<f64> = guides.ends.iter().map(|e| e.0.x).collect();
        assert_eq!(ends, vec![0.0, 1.0, 2.0, 3.0, 12.0, 13.0, 14.0, 15.0]);
        let moves: Vec<(u32, f64)> = guides.moves.iter().map(|m| (m.vertex, m.reach)).collect();
        let expected: Vec<(u32, f64)> = (0..8).zip([0.0, 1.0, 2.0, 3.0, 12.0, 13.0, 14.0, 15.0]).collect();
        assert_eq!(moves, expected);
        assert!(guides.anchors.is_empty());
    }

    #[test]
    fn a_piece_whose_parts_are_anchored_solids_or_reach_a_seam_stays_as_it_is() {
        let (mut mesh, mut guides) = four_tetrahedra();
        guides.anchors = vec![0, 4, 12];
        // The void reaches another unit through vertex 8: kept too.
        let before = (mesh.vertices.clone(), mesh.triangles.clone());
        drop_unobserved_pieces(&mut mesh, &mut guides, &|name| name.0 != 8);
        assert_eq!((mesh.vertices.clone(), mesh.triangles.clone()), before);
        assert_eq!(guides.moves.len(), 16);
        // No anchor and no seam vertex: nothing is left.
        let (mut mesh, mut guides) = four_tetrahedra();
        drop_unobserved_pieces(&mut mesh, &mut guides, &|_| true);
        assert!(mesh.vertices.is_empty() && mesh.triangles.is_empty() && guides.moves.is_empty());
    }
}
