//! Cutting a mesh at an axis-aligned box.
//!
//! One triangle at a time ([`clip_triangle`]): the triangle is clipped against the box's six
//! planes in a fixed order, and every new point is interpolated from a canonical end of the
//! segment it cuts, so the two triangles that share an edge compute bit-identical points on it.
//! [`clip`] welds those points by position over a mesh held in memory; extraction's streaming
//! cut (`stages::extract`) welds them by the edge they lie on, which it can forget once the
//! edge is done.

use std::collections::HashMap;

use glam::Vec3;

use super::Mesh;
use crate::format::BoundingBox;

/// What a corner of a clipped triangle is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Corner {
    /// The triangle's vertex of this index.
    Vertex(u32),
    /// A point on the triangle's edge between these two vertices (lower index first): the
    /// triangle on the other side of that edge has the same point, bit for bit.
    OnEdge(u32, u32),
    /// A point inside the triangle, where two planes of the box meet it: no other triangle has it.
    Inside,
}

/// A corner of a clipped triangle: position, normal and what it is.
pub(crate) type ClippedCorner = (Vec3, Vec3, Corner);

/// The input edge that a segment between two polygon corners lies on, if any.
fn common_edge(a: Corner, b: Corner) -> Option<(u32, u32)> {
    let ends = |x: u32, y: u32| (x.min(y), x.max(y));
    match (a, b) {
        (Corner::Vertex(x), Corner::Vertex(y)) if x != y => Some(ends(x, y)),
        (Corner::Vertex(v), Corner::OnEdge(x, y)) | (Corner::OnEdge(x, y), Corner::Vertex(v)) if v == x || v == y => {
            Some((x, y))
        }
        (Corner::OnEdge(x, y), Corner::OnEdge(z, w)) if (x, y) == (z, w) => Some((x, y)),
        _ => None,
    }
}

/// Clips one triangle (each corner: vertex index, position, normal) against the box `lo`..`hi`:
/// the polygon left, in order; fewer than three corners if nothing is.
pub(crate) fn clip_triangle(triangle: [(u32, Vec3, Vec3); 3], lo: Vec3, hi: Vec3) -> Vec<ClippedCorner> {
    let mut polygon: Vec<ClippedCorner> = triangle
        .iter()
        .map(|&(index, position, normal)| (position, normal, Corner::Vertex(index)))
        .collect();
    for axis in 0..3 {
        for (bound, keep_above) in [(lo[axis], true), (hi[axis], false)] {
            let inside = |p: &Vec3| if keep_above { p[axis] >= bound } else { p[axis] <= bound };
            let mut next = Vec::with_capacity(polygon.len() + 1);
            for (i, &a) in polygon.iter().enumerate() {
                let b = polygon.get(i + 1).or(polygon.first()).copied().unwrap_or(a);
                let (ia, ib) = (inside(&a.0), inside(&b.0));
                if ia {
                    next.push(a);
                }
                if ia != ib {
                    // Interpolate from a canonical end so that both triangles sharing the
                    // edge compute bit-identical points.
                    let bits = |v: &Vec3| v.to_array().map(f32::to_bits);
                    let (s, e) = if bits(&a.0) <= bits(&b.0) { (a, b) } else { (b, a) };
                    let t = (bound - s.0[axis]) / (e.0[axis] - s.0[axis]);
                    let mut p = s.0 + (e.0 - s.0) * t;
                    p[axis] = bound;
                    // A cut exactly at an end is that end (a vertex on the plane).
                    let corner = if bits(&p) == bits(&s.0) {
                        s.2
                    } else if bits(&p) == bits(&e.0) {
                        e.2
                    } else {
                        common_edge(s.2, e.2).map_or(Corner::Inside, |(x, y)| Corner::OnEdge(x, y))
                    };
                    next.push((p, (s.1 + (e.1 - s.1) * t).normalize_or_zero(), corner));
                }
            }
            polygon = next;
            if polygon.is_empty() {
                return polygon;
            }
        }
    }
    polygon
}

/// Cuts a mesh at a box: triangles are clipped against its six planes (new vertices on the box
/// faces are welded by position).
pub fn clip(mesh: &Mesh, region: BoundingBox) -> Mesh {
    let mut out = Mesh::default();
    let mut welded: HashMap<[u32; 3], u32> = HashMap::new();
    let mut add = |p: Vec3, n: Vec3, out: &mut Mesh| -> u32 {
        let key = p.to_array().map(f32::to_bits);
        *welded.entry(key).or_insert_with(|| {
            out.positions.push(p.to_array());
            out.normals.push(n.to_array());
            (out.positions.len() - 1) as u32
        })
    };
    let (lo, hi) = (region.min.as_vec3(), region.max.as_vec3());
    let corner = |i: u32| {
        let at = |list: &[[f32; 3]]| list.get(i as usize).copied().map_or(Vec3::ZERO, Vec3::from);
        (i, at(&mesh.positions), at(&mesh.normals))
    };
    for tri in &mesh.triangles {
        let polygon = clip_triangle(tri.map(corner), lo, hi);
        if polygon.len() < 3 {
            continue;
        }
        let ids: Vec<u32> = polygon.iter().map(|&(p, n, _)| add(p, n, &mut out)).collect();
        for (&b, &c) in ids.iter().skip(1).zip(ids.iter().skip(2)) {
            let t = [ids[0], b, c];
            if t[0] != t[1] && t[1] != t[2] && t[0] != t[2] {
                out.triangles.push(t);
            }
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn corners(points: [[f32; 3]; 3]) -> [(u32, Vec3, Vec3); 3] {
        [0, 1, 2].map(|i| (i as u32 + 10, Vec3::from(points[i]), Vec3::Z))
    }

    #[test]
    fn cut_points_name_the_edge_they_lie_on() {
        // One corner beyond x = 1: the cut points lie on the two edges from it.
        let polygon = clip_triangle(
            corners([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 2.0, 0.0]]),
            Vec3::splat(-5.0),
            Vec3::new(1.0, 5.0, 5.0),
        );
        let kinds: Vec<Corner> = polygon.iter().map(|c| c.2).collect();
        assert_eq!(
            kinds,
            vec![
                Corner::Vertex(10),
                Corner::OnEdge(10, 11),
                Corner::OnEdge(11, 12),
                Corner::Vertex(12)
            ]
        );
        // Two planes: the corner where they meet inside the triangle belongs to it alone.
        let polygon = clip_triangle(
            corners([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 2.0, 0.0]]),
            Vec3::new(0.5, 0.5, -5.0),
            Vec3::splat(5.0),
        );
        assert!(polygon.iter().any(|c| c.2 == Corner::Inside), "{polygon:?}");
        assert!(polygon.iter().all(|c| c.0.x >= 0.5 && c.0.y >= 0.5));
    }

    #[test]
    fn a_vertex_on_a_plane_stays_itself() {
        let polygon = clip_triangle(
            corners([[1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 2.0, 0.0]]),
            Vec3::splat(-5.0),
            Vec3::new(1.0, 5.0, 5.0),
        );
        let vertices = polygon.iter().filter(|c| c.2 == Corner::Vertex(10)).count();
        assert!(vertices >= 1, "{polygon:?}");
        assert!(polygon.iter().all(|c| c.2 != Corner::OnEdge(10, 11)), "{polygon:?}");
    }
}
