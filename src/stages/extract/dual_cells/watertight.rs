//! The watertight surface's pieces without observed surface, its voids and its noise blobs,
//! dropped.

use std::collections::{HashMap, HashSet};

use glam::DVec3;

use super::VertexGuides;
use crate::mesh::{UnitMesh, VertexId, edge_parts};

/// Drops from a unit's watertight piece the connected parts (triangles joined by shared
/// edges, so two parts that touch at one vertex are two) that lie wholly in the unit (no vertex
/// that another unit may also produce, `private`) and either hold no anchor (a vertex of the
/// observed surface, [`VertexGuides::anchors`]) or enclose free space (negative signed volume:
/// triangles face positive u, outwards from the solid). The first are bubbles of the zero set
/// in free space, where outliers pulled u below zero; the second are voids inside an object,
/// where outliers behind its surface voted free space: no camera outside the object could see
/// into either. Of the rest, the noise blobs go too ([`noise_blobs`]). A part that reaches
/// another unit is kept whole, so both sides of a seam agree without knowing each other's
/// anchors. A vertex stays while a kept triangle uses it; the kept vertices keep their order,
/// renumbered, and their guides follow them.
pub(in crate::stages::extract) fn drop_unobserved_pieces(
    mesh: &mut UnitMesh,
    guides: &mut VertexGuides,
    private: &dyn Fn(&VertexId) -> bool,
) {
    let parts = edge_parts(mesh.triangles.as_flattened());
    let t = mesh.triangles.len();
    // Per part (by its root triangle): anchored, reaching another unit, and six times the
    // signed volume, summed about a vertex of the root triangle (a closed part's volume does
    // not depend on the point; one near it keeps the sum precise far from the origin).
    let mut anchor = vec![false; mesh.vertices.len()];
    for &vertex in &guides.anchors {
        if let Some(slot) = anchor.get_mut(vertex as usize) {
            *slot = true;
        }
    }
    let (mut anchored, mut reaches_seam, mut volume) = (vec![false; t], vec![false; t], vec![0.0f64; t]);
    for (&[a, b, c], &root) in mesh.triangles.iter().zip(&parts) {
        let r = root as usize;
        let corners = [a, b, c];
        if corners
            .iter()
            .any(|&v| anchor.get(v as usize).copied().unwrap_or(false))
            && let Some(slot) = anchored.get_mut(r)
        {
            *slot = true;
        }
        if corners
            .iter()
            .any(|&v| mesh.vertices.get(v as usize).is_none_or(|v| !private(&v.0)))
            && let Some(slot) = reaches_seam.get_mut(r)
        {
            *slot = true;
        }
        let origin = mesh.triangles.get(r).map_or(DVec3::ZERO, |t| mesh.position(t[0]));
        let (pa, pb, pc) = (
            mesh.position(a) - origin,
            mesh.position(b) - origin,
            mesh.position(c) - origin,
        );
        if let Some(slot) = volume.get_mut(r) {
            *slot += pa.dot(pb.cross(pc));
        }
    }
    let kept_so_far = |root: usize| {
        reaches_seam.get(root).copied().unwrap_or(true)
            || (anchored.get(root).copied().unwrap_or(false) && volume.get(root).copied().unwrap_or(0.0) > 0.0)
    };
    let blobs = noise_blobs(mesh, guides, &parts, &|root| {
        kept_so_far(root) && !reaches_seam.get(root).copied().unwrap_or(true)
    });
    let kept_triangle: Vec<bool> = parts
        .iter()
        .map(|&root| kept_so_far(root as usize) && blobs.binary_search(&root).is_err())
        .collect();
    if kept_triangle.iter().all(|&k| k) {
        guides.anchors = Vec::new();
        return;
    }
    let mut keep = vec![false; mesh.vertices.len()];
    for (triangle, _) in mesh.triangles.iter().zip(&kept_triangle).filter(|(_, k)| **k) {
        for &v in triangle {
            if let Some(slot) = keep.get_mut(v as usize) {
                *slot = true;
            }
        }
    }
    // New index of each kept vertex (u32::MAX for a dropped one).
    let mut renumbered = vec![u32::MAX; keep.len()];
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
    let mut index = 0;
    mesh.triangles.retain(|_| {
        index += 1;
        kept_triangle.get(index - 1).copied().unwrap_or(false)
    });
    for t in &mut mesh.triangles {
        *t = t.map(|v| renumbered.get(v as usize).copied().unwrap_or(u32::MAX));
    }
    guides.anchors = Vec::new();
}

/// How close to a larger part, and how small, a part of a watertight piece is a noise blob
/// ([`noise_blobs`]), in sides of the largest dual cell it crosses.
const NOISE_BLOB_SIDES: f64 = 4.0;

/// The parts (by root, sorted; `parts` gives each triangle's, [`edge_parts`]) that are noise
/// blobs: parts that `candidate` allows (kept so far and wholly in the unit), at most twice
/// [`NOISE_BLOB_SIDES`] cells across, each of whose vertices lies within [`NOISE_BLOB_SIDES`]
/// cells of a vertex of a larger part (more triangles; of two as large, the one with the
/// lesser root).
///
/// Why. Where the depths are noisy the zero set folds: SSD's position term follows each
/// cube's sample centroid, and a fold that closes on itself beside the surface is a blob a
/// few cubes across, within the noise of it (the noisy bunny and dragon at 3 units with the
/// smoothness of `stages::solve::ssd` capped at 10 times the base: 11 to 170 parts of 4 to 154
/// vertices, each within 0.5 to 2.7 mesh edges of the object and at most 7.8 across, some
/// touching it at one vertex). A real part of the object that small and that close is below
/// what the cubes resolve, so it cannot be told from the noise either. A part as large as the
/// object is never one: its vertices are not all near another's.
fn noise_blobs(mesh: &UnitMesh, guides: &VertexGuides, parts: &[u32], candidate: &dyn Fn(usize) -> bool) -> Vec<u32> {
    let mut size = vec![0u32; parts.len()];
    for &root in parts {
        if let Some(c) = size.get_mut(root as usize) {
            *c += 1;
        }
    }
    // Per candidate part: the bounds of its vertices, the largest cell side they cross (the
    // distance between the centres of their edge's cells), and its vertices.
    let mut bounds: HashMap<u32, (DVec3, DVec3, f64, Vec<u32>)> = HashMap::new();
    for (triangle, &root) in mesh.triangles.iter().zip(parts) {
        if !candidate(root as usize) {
            continue;
        }
        for &v in triangle {
            let p = mesh.position(v);
            let side = guides.ends.get(v as usize).map_or(0.0, |(a, b)| a.distance(*b));
            let entry = bounds.entry(root).or_insert((p, p, side, Vec::new()));
            (entry.0, entry.1, entry.2) = (entry.0.min(p), entry.1.max(p), entry.2.max(side));
            entry.3.push(v);
        }
    }
    bounds.retain(|_, (lo, hi, side, _)| *side > 0.0 && (*hi - *lo).max_element() <= 2.0 * NOISE_BLOB_SIDES * *side);
    if bounds.is_empty() {
        return Vec::new();
    }
    // A grid as fine as the largest candidate's reach: a vertex's neighbours within the reach
    // lie in the 27 grid cells around it. It holds the vertices of the triangles near a
    // candidate, each with its triangle's part.
    let reach = bounds.values().map(|b| NOISE_BLOB_SIDES * b.2).fold(0.0, f64::max);
    let cell = |p: DVec3| (p / reach).floor().as_i64vec3().to_array();
    let around = |[x, y, z]: [i64; 3]| {
        (-1..=1).flat_map(move |dx| (-1..=1).flat_map(move |dy| (-1..=1).map(move |dz| [x + dx, y + dy, z + dz])))
    };
    let near_candidates: HashSet<[i64; 3]> = bounds
        .values()
        .flat_map(|b| b.3.iter().flat_map(|&v| around(cell(mesh.position(v)))))
        .collect();
    let mut grid: HashMap<[i64; 3], Vec<(u32, u32)>> = HashMap::new();
    for (triangle, &root) in mesh.triangles.iter().zip(parts) {
        for &v in triangle {
            let c = cell(mesh.position(v));
            if near_candidates.contains(&c) {
                grid.entry(c).or_default().push((v, root));
            }
        }
    }
    let larger = |a: u32, b: u32| {
        let (sa, sb) = (size.get(a as usize), size.get(b as usize));
        sa > sb || (sa == sb && a < b)
    };
    let mut blobs: Vec<u32> = bounds.keys().copied().collect();
    blobs.sort_unstable();
    blobs.retain(|blob| {
        let Some((_, _, side, members)) = bounds.get(blob) else {
            return false;
        };
        let within = NOISE_BLOB_SIDES * side;
        members.iter().all(|&v| {
            let p = mesh.position(v);
            around(cell(p)).any(|c| {
                grid.get(&c).is_some_and(|near| {
                    near.iter()
                        .any(|&(w, root)| larger(root, *blob) && mesh.position(w).distance(p) <= within)
                })
            })
        })
    });
    blobs
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
                guides
                    .ends
                    .push((DVec3::splat(f64::from(i)), DVec3::splat(f64::from(i)) + DVec3::X * 0.1));
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

    /// Adds a closed part to `mesh`: a tetrahedron (`octahedron` false) or an octahedron with
    /// corners `size` from `centre`, facing outwards, its vertices' cells `side` across; the
    /// vertices are named from `first`. Returns the first new vertex index.
    fn add_part(
        mesh: &mut UnitMesh,
        guides: &mut VertexGuides,
        centre: DVec3,
        size: f64,
        side: f64,
        octahedron: bool,
    ) -> u32 {
        let base = mesh.vertices.len() as u32;
        let corners: Vec<DVec3> = if octahedron {
            vec![DVec3::X, -DVec3::X, DVec3::Y, -DVec3::Y, DVec3::Z, -DVec3::Z]
        } else {
            vec![DVec3::ZERO, DVec3::X, DVec3::Y, DVec3::Z]
        };
        for (k, corner) in corners.iter().enumerate() {
            let name = u128::from(base) + k as u128;
            let position = centre + *corner * size;
            mesh.vertices.push(((name, name + 1000), position, DVec3::Z));
            guides.ends.push((position, position + DVec3::X * side));
            guides.moves.push(VertexMove::empty(base + k as u32, 0.0));
            guides.anchors.push(base + k as u32);
        }
        let faces: &[[u32; 3]] = if octahedron {
            &[
                [0, 2, 4],
                [2, 1, 4],
                [1, 3, 4],
                [3, 0, 4],
                [2, 0, 5],
                [1, 2, 5],
                [3, 1, 5],
                [0, 3, 5],
            ]
        } else {
            &[[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]
        };
        mesh.triangles.extend(faces.iter().map(|f| f.map(|v| base + v)));
        base
    }

    #[test]
    fn small_parts_within_a_few_cells_of_a_larger_one_go_as_noise_blobs() {
        let (mut mesh, mut guides) = (UnitMesh::default(), VertexGuides::default());
        // An object 20 cells across; a blob half a cell across one cell off its +x corner;
        // one as small, 20 cells away; and a part 10 cells across, one cell off its -x corner.
        add_part(&mut mesh, &mut guides, DVec3::ZERO, 10.0, 1.0, true);
        let near = add_part(&mut mesh, &mut guides, DVec3::X * 11.0, 0.5, 1.0, false);
        let far = add_part(&mut mesh, &mut guides, DVec3::X * 30.0, 0.5, 1.0, false);
        let large = add_part(&mut mesh, &mut guides, -DVec3::X * 16.0, 5.0, 1.0, true);
        drop_unobserved_pieces(&mut mesh, &mut guides, &|_| true);
        let kept: Vec<u128> = mesh.vertices.iter().map(|v| v.0.0).collect();
        let expected: Vec<u128> = (0..6)
            .chain(far..far + 4)
            .chain(large..large + 6)
            .map(u128::from)
            .collect();
        assert_eq!(kept, expected, "the blob of vertices {near}.. goes");
        assert_eq!(mesh.triangles.len(), 8 + 4 + 8);
        // The same blob with cells a tenth as large is 10 of them away: it stays.
        let (mut mesh, mut guides) = (UnitMesh::default(), VertexGuides::default());
        add_part(&mut mesh, &mut guides, DVec3::ZERO, 10.0, 0.1, true);
        add_part(&mut mesh, &mut guides, DVec3::X * 11.0, 0.5, 0.1, false);
        drop_unobserved_pieces(&mut mesh, &mut guides, &|_| true);
        assert_eq!(mesh.triangles.len(), 12);
    }

    #[test]
    fn a_blob_that_touches_the_object_at_one_vertex_is_a_part_of_its_own() {
        let (mut mesh, mut guides) = (UnitMesh::default(), VertexGuides::default());
        add_part(&mut mesh, &mut guides, DVec3::ZERO, 10.0, 1.0, true);
        let blob = add_part(&mut mesh, &mut guides, DVec3::X * 10.0, 0.5, 1.0, false);
        // The blob's first corner is the object's +x corner (vertex 0): joined by it alone.
        for t in mesh.triangles.iter_mut().skip(8) {
            *t = t.map(|v| if v == blob { 0 } else { v });
        }
        drop_unobserved_pieces(&mut mesh, &mut guides, &|_| true);
        assert_eq!(mesh.triangles.len(), 8);
        assert_eq!(mesh.vertices.len(), 6);
        // A seam vertex keeps the blob: the unit beside may see more of it.
        let (mut mesh, mut guides) = (UnitMesh::default(), VertexGuides::default());
        add_part(&mut mesh, &mut guides, DVec3::ZERO, 10.0, 1.0, true);
        let blob = add_part(&mut mesh, &mut guides, DVec3::X * 11.0, 0.5, 1.0, false);
        let seam = u128::from(blob) + 1;
        drop_unobserved_pieces(&mut mesh, &mut guides, &|name| name.0 != seam);
        assert_eq!(mesh.triangles.len(), 12);
    }
}
