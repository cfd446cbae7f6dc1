//! Self-intersections of a triangle mesh: triangles that cross another triangle with which they
//! share no vertex. Extraction's simplification must not introduce them (tests/extract.rs);
//! `octstore-evaluate --self-intersections` counts them on any mesh.
//!
//! Broad phase: a uniform grid over the mesh's box with cells about twice the mean edge length;
//! each triangle is listed in every cell its box meets, and a pair is tested in the one cell
//! where the lowest corner of the intersection of their boxes lies (so once). Narrow phase: two
//! triangles that share no vertex intersect when an edge of one crosses the other
//! (segment-triangle tests, Möller and Trumbore), which holds for every pair that is not
//! coplanar; coplanar overlaps, which marching tetrahedra and edge collapses do not produce on
//! their own, are not counted.

use std::collections::HashMap;

use glam::DVec3;
use rayon::prelude::*;

use crate::mesh::Mesh;

/// The most grid cells one triangle is listed in: a triangle larger than that (a long sliver
/// across a flat wall after simplification) is listed in the cells of its box's corners'
/// coarser grid instead, by growing the cell size for the whole mesh.
const MAX_CELLS_PER_TRIANGLE: u64 = 4096;

/// The number of triangles of `mesh` that cross another triangle with which they share no
/// vertex.
pub fn self_intersecting_triangles(mesh: &Mesh) -> usize {
    // One entry per triangle, so indices match `mesh.triangles`; a triangle naming a vertex the
    // mesh lacks is NaN and never enters the grid.
    let corners: Vec<[DVec3; 3]> = mesh
        .triangles
        .iter()
        .map(|t| {
            let p = |i: u32| mesh.positions.get(i as usize).map(|v| DVec3::from(v.map(f64::from)));
            match (p(t[0]), p(t[1]), p(t[2])) {
                (Some(a), Some(b), Some(c)) => [a, b, c],
                _ => [DVec3::NAN; 3],
            }
        })
        .collect();
    if corners.len() < 2 {
        return 0;
    }
    let boxes: Vec<(DVec3, DVec3)> = corners
        .iter()
        .map(|[a, b, c]| (a.min(*b).min(*c), a.max(*b).max(*c)))
        .collect();
    let low = boxes
        .iter()
        .filter(|b| b.0.is_finite())
        .fold(DVec3::splat(f64::INFINITY), |l, b| l.min(b.0));
    let perimeters: Vec<f64> = corners
        .iter()
        .map(|[a, b, c]| a.distance(*b) + b.distance(*c) + c.distance(*a))
        .filter(|p| p.is_finite())
        .collect();
    let mean_edge = perimeters.iter().sum::<f64>() / (3.0 * perimeters.len().max(1) as f64);
    let largest = boxes
        .iter()
        .map(|(l, h)| (*h - *l).max_element())
        .filter(|e| e.is_finite())
        .fold(0.0, f64::max);
    // Cells of twice the mean edge, grown until the largest triangle meets few enough cells.
    let mut cell = (2.0 * mean_edge).max(f64::MIN_POSITIVE);
    while ((largest / cell).ceil() as u64 + 1).pow(3) > MAX_CELLS_PER_TRIANGLE {
        cell *= 2.0;
    }
    let cell_of = |p: DVec3| ((p - low) / cell).floor().as_i64vec3();
    let mut grid: HashMap<[i64; 3], Vec<u32>> = HashMap::new();
    for (index, (l, h)) in boxes.iter().enumerate() {
        if !(l.is_finite() && h.is_finite()) {
            continue;
        }
        let (from, to) = (cell_of(*l), cell_of(*h));
        for x in from.x..=to.x {
            for y in from.y..=to.y {
                for z in from.z..=to.z {
                    grid.entry([x, y, z]).or_default().push(index as u32);
                }
            }
        }
    }
    // Cells are independent: test them on every core, then mark what they found.
    let found: Vec<u32> = grid
        .par_iter()
        .flat_map_iter(|(key, members)| {
            let mut found = Vec::new();
            for (at, &i) in members.iter().enumerate() {
                for &j in members.iter().skip(at + 1) {
                    if pair_crosses(mesh, &corners, &boxes, i, j, |l| cell_of(l).to_array() == *key) {
                        found.extend([i, j]);
                    }
                }
            }
            found
        })
        .collect();
    let mut crossing = vec![false; corners.len()];
    for k in found {
        if let Some(flag) = crossing.get_mut(k as usize) {
            *flag = true;
        }
    }
    crossing.iter().filter(|&&c| c).count()
}

/// Whether triangles `i` and `j` share no vertex and cross, tested in the cell that `owns` the
/// low corner of their boxes' intersection (false elsewhere, so each pair counts once).
fn pair_crosses(
    mesh: &Mesh,
    corners: &[[DVec3; 3]],
    boxes: &[(DVec3, DVec3)],
    i: u32,
    j: u32,
    owns: impl Fn(DVec3) -> bool,
) -> bool {
    let (Some(bi), Some(bj)) = (boxes.get(i as usize), boxes.get(j as usize)) else {
        return false;
    };
    let (l, h) = (bi.0.max(bj.0), bi.1.min(bj.1));
    if l.cmpgt(h).any() || !owns(l) {
        return false;
    }
    let (Some(ti), Some(tj)) = (mesh.triangles.get(i as usize), mesh.triangles.get(j as usize)) else {
        return false;
    };
    if ti.iter().any(|v| tj.contains(v)) {
        return false;
    }
    match (corners.get(i as usize), corners.get(j as usize)) {
        (Some(ci), Some(cj)) => triangles_cross(ci, cj),
        _ => false,
    }
}

/// Whether an edge of either triangle crosses the other.
fn triangles_cross(a: &[DVec3; 3], b: &[DVec3; 3]) -> bool {
    let edges = |t: &[DVec3; 3]| [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])];
    edges(a).iter().any(|&(p, q)| segment_crosses(p, q, b)) || edges(b).iter().any(|&(p, q)| segment_crosses(p, q, a))
}

/// Whether the segment p-q passes through the interior of triangle t (Möller-Trumbore, with a
/// margin of a millionth of the triangle's scale so that touching at a corner does not count).
fn segment_crosses(p: DVec3, q: DVec3, t: &[DVec3; 3]) -> bool {
    const MARGIN: f64 = 1e-6;
    let direction = q - p;
    let (e1, e2) = (t[1] - t[0], t[2] - t[0]);
    let h = direction.cross(e2);
    let det = e1.dot(h);
    let scale = e1.length_squared().max(e2.length_squared()) * direction.length();
    if det.abs() <= 1e-12 * scale {
        return false; // parallel or coplanar
    }
    let inverse = 1.0 / det;
    let s = p - t[0];
    let u = inverse * s.dot(h);
    if u <= MARGIN || u >= 1.0 - MARGIN {
        return false;
    }
    let qv = s.cross(e1);
    let v = inverse * direction.dot(qv);
    if v <= MARGIN || u + v >= 1.0 - MARGIN {
        return false;
    }
    let along = inverse * e2.dot(qv);
    along > MARGIN && along < 1.0 - MARGIN
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mesh(positions: &[[f32; 3]], triangles: &[[u32; 3]]) -> Mesh {
        Mesh {
            positions: positions.to_vec(),
            normals: Vec::new(),
            triangles: triangles.to_vec(),
        }
    }

    #[test]
    fn two_crossing_triangles_are_both_counted() {
        let m = mesh(
            &[
                [0.0, 0.0, 0.0],
                [2.0, 0.0, 0.0],
                [0.0, 2.0, 0.0],
                [0.5, 0.5, -1.0],
                [0.5, 0.5, 1.0],
                [1.5, 1.5, 0.0],
            ],
            &[[0, 1, 2], [3, 4, 5]],
        );
        assert_eq!(self_intersecting_triangles(&m), 2);
    }

    #[test]
    fn separated_and_adjacent_triangles_are_not() {
        // Two triangles side by side sharing an edge, and one far above them.
        let m = mesh(
            &[
                [0.0, 0.0, 0.0],
                [1.0, 0.0, 0.0],
                [0.0, 1.0, 0.0],
                [1.0, 1.0, 0.0],
                [0.0, 0.0, 5.0],
                [1.0, 0.0, 5.0],
                [0.0, 1.0, 5.0],
            ],
            &[[0, 1, 2], [1, 3, 2], [4, 5, 6]],
        );
        assert_eq!(self_intersecting_triangles(&m), 0);
    }

    #[test]
    fn a_closed_sphere_has_none_and_a_pushed_vertex_makes_some() {
        let mut sphere = mesh(&[], &[]);
        crate::quality::interior_scene::add_sphere(&mut sphere, DVec3::ZERO, 1.0, 32, 16);
        assert_eq!(self_intersecting_triangles(&sphere), 0);
        // Push one vertex through the opposite side (off the axis, so that its edges do not
        // run along the far side's edges): its triangle now crosses the far surface.
        let mut dented = sphere.clone();
        let top = dented
            .positions
            .iter()
            .enumerate()
            .max_by(|a, b| a.1[2].total_cmp(&b.1[2]))
            .map(|(i, _)| i)
            .expect("vertices");
        if let Some(p) = dented.positions.get_mut(top) {
            *p = [0.05, 0.03, -1.5];
        }
        assert!(self_intersecting_triangles(&dented) > 0);
    }
}
