//! The topology a simplified batch must keep: each vertex's fans and each part's triangles
//! joined by shared edges (`SimplifyingWriter::simplify_manifold`).

use super::FastMap;
use crate::mesh::{DisjointSets, edge_parts};

/// Each vertex's part in `indices` ([`edge_parts`]; of a vertex in several, the part of its
/// last triangle), u32::MAX for a vertex no triangle uses.
pub(super) fn vertex_parts(indices: &[u32], vertices: usize) -> Vec<u32> {
    let mut part = vec![u32::MAX; vertices];
    for (t, root) in indices.chunks_exact(3).zip(edge_parts(indices)) {
        for &v in t {
            if let Some(slot) = part.get_mut(v as usize) {
                *slot = root;
            }
        }
    }
    part
}

/// The vertices of the parts of `after` that were cut off a part of the mesh before it
/// (`before`, [`vertex_parts`]): of the parts of `after` whose vertices were in one part
/// before, all but the one with the most triangles (of two as large, the lesser root).
pub(super) fn split_off(before: &[u32], after: &[u32]) -> Vec<u32> {
    let roots = edge_parts(after);
    // Per part of `after`: triangles, and the part before of its first vertex.
    let mut parts: FastMap<u32, (u32, u32)> = FastMap::default();
    for (t, &root) in after.chunks_exact(3).zip(&roots) {
        let origin = before.get(t[0] as usize).copied().unwrap_or(u32::MAX);
        parts.entry(root).or_insert((0, origin)).0 += 1;
    }
    // Per part before: its largest part after.
    let mut largest: FastMap<u32, (u32, u32)> = FastMap::default();
    for (&root, &(size, origin)) in &parts {
        let best = largest.entry(origin).or_insert((size, root));
        if (size, std::cmp::Reverse(root)) > (best.0, std::cmp::Reverse(best.1)) {
            *best = (size, root);
        }
    }
    let cut = |root: u32| {
        parts
            .get(&root)
            .is_some_and(|(_, origin)| largest.get(origin).is_some_and(|best| best.1 != root))
    };
    let mut vertices: Vec<u32> = after
        .chunks_exact(3)
        .zip(&roots)
        .filter(|(_, root)| cut(**root))
        .flat_map(|(t, _)| [t[0], t[1], t[2]])
        .collect();
    vertices.sort_unstable();
    vertices.dedup();
    vertices
}

/// Each vertex's number of fans in `indices` (at most 255): the connected parts of its link,
/// the edges opposite it in its triangles joined at shared ends. An inner vertex of a manifold
/// surface has one (a closed ring), a border vertex one (an open one); a vertex where two
/// sheets touch, two or more. meshoptimizer's collapses do not keep that: a bump on a noisy
/// surface whose neck is thinner than the error bound is pinched off at one vertex (the noisy
/// dragon at 3 units: 10 parts of 6 to 30 triangles hung on the object by one vertex each).
pub(super) fn fans(indices: &[u32], vertices: usize) -> Vec<u8> {
    // Each triangle's opposite edge at each of its corners, grouped by the corner.
    let mut links: Vec<(u32, u32, u32)> = indices
        .chunks_exact(3)
        .flat_map(|t| [(t[0], t[1], t[2]), (t[1], t[2], t[0]), (t[2], t[0], t[1])])
        .collect();
    links.sort_unstable();
    let mut count = vec![0u8; vertices];
    let mut nodes: Vec<u32> = Vec::new();
    for star in links.chunk_by(|x, y| x.0 == y.0) {
        let Some(&(vertex, _, _)) = star.first() else { continue };
        nodes.clear();
        nodes.extend(star.iter().flat_map(|&(_, b, c)| [b, c]));
        nodes.sort_unstable();
        nodes.dedup();
        // The link's nodes joined by its edges, by their place in `nodes`.
        let mut sets = DisjointSets::new(nodes.len());
        for &(_, b, c) in star {
            if let (Ok(i), Ok(j)) = (nodes.binary_search(&b), nodes.binary_search(&c)) {
                sets.union(i as u32, j as u32);
            }
        }
        let parts = (0..nodes.len() as u32).filter(|&i| sets.find(i) == i).count();
        if let Some(slot) = count.get_mut(vertex as usize) {
            *slot = parts.min(255) as u8;
        }
    }
    count
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A closed tetrahedron on vertices 0 to 3.
    const TETRAHEDRON: [u32; 12] = [0, 2, 1, 0, 1, 3, 0, 3, 2, 1, 2, 3];

    #[test]
    fn a_vertex_where_two_sheets_touch_has_two_fans() {
        assert_eq!(fans(&TETRAHEDRON, 4), vec![1, 1, 1, 1]);
        // A second tetrahedron on 3 to 6 touches the first at vertex 3.
        let mut two: Vec<u32> = TETRAHEDRON.to_vec();
        two.extend(TETRAHEDRON.iter().map(|v| v + 3));
        assert_eq!(fans(&two, 8), vec![1, 1, 1, 2, 1, 1, 1, 0]);
        // An open fan of two triangles (a border vertex) is one.
        assert_eq!(fans(&[0, 1, 2, 0, 2, 3], 4), vec![1, 1, 1, 1]);
    }

    #[test]
    fn a_part_cut_off_its_part_is_named_by_its_vertices() {
        // A strip of four triangles 0-1-2, 1-3-2, 2-3-4, 3-5-4, then 4-5-6 and 5-7-6.
        let strip = [0, 1, 2, 1, 3, 2, 2, 3, 4, 3, 5, 4, 4, 5, 6, 5, 7, 6];
        let before = vertex_parts(&strip, 8);
        assert!(before.iter().all(|&p| p == 0));
        assert_eq!(edge_parts(&strip), vec![0; 6]);
        // Without its third and fourth triangles the strip falls in two: 0-1-2-3 and 4-5-6-7.
        let cut = [0, 1, 2, 1, 3, 2, 4, 5, 6, 5, 7, 6];
        assert_eq!(edge_parts(&cut), vec![0, 0, 2, 2]);
        // Of two as large, the one with the lesser root stays.
        assert_eq!(split_off(&before, &cut), vec![4, 5, 6, 7]);
        // Parts that were apart before are not cut off.
        assert!(split_off(&vertex_parts(&cut, 8), &cut).is_empty());
        // A lone triangle cut off a larger part goes, not the part.
        let lone = [0, 1, 2, 1, 3, 2, 2, 3, 4, 5, 7, 6];
        assert_eq!(split_off(&before, &lone), vec![5, 6, 7]);
    }
}
