//! Cutting a mesh at an axis-aligned box.

use std::collections::HashMap;

use super::Mesh;
use crate::format::BoundingBox;

/// Cuts a mesh at a box: triangles are clipped against its six planes (new vertices on the box
/// faces are welded by position).
pub fn clip(mesh: &Mesh, region: BoundingBox) -> Mesh {
    let mut out = Mesh::default();
    let mut welded: HashMap<[u32; 3], u32> = HashMap::new();
    let mut add = |p: glam::Vec3, n: glam::Vec3, out: &mut Mesh| -> u32 {
        let key = p.to_array().map(f32::to_bits);
        *welded.entry(key).or_insert_with(|| {
            out.positions.push(p.to_array());
            out.normals.push(n.to_array());
            (out.positions.len() - 1) as u32
        })
    };
    let (lo, hi) = (region.min.as_vec3(), region.max.as_vec3());
    for tri in &mesh.triangles {
        let mut polygon: Vec<(glam::Vec3, glam::Vec3)> = tri
            .iter()
            .map(|&i| {
                (
                    glam::Vec3::from(mesh.positions[i as usize]),
                    glam::Vec3::from(mesh.normals[i as usize]),
                )
            })
            .collect();
        for axis in 0..3 {
            for (bound, keep_above) in [(lo[axis], true), (hi[axis], false)] {
                let inside = |p: &glam::Vec3| if keep_above { p[axis] >= bound } else { p[axis] <= bound };
                let mut next = Vec::new();
                for i in 0..polygon.len() {
                    let (a, b) = (polygon[i], polygon[(i + 1) % polygon.len()]);
                    let (ia, ib) = (inside(&a.0), inside(&b.0));
                    if ia {
                        next.push(a);
                    }
                    if ia != ib {
                        // Interpolate from a canonical end so that both triangles sharing the
                        // edge compute bit-identical points, which then weld.
                        let bits = |v: &glam::Vec3| v.to_array().map(f32::to_bits);
                        let (s, e) = if bits(&a.0) <= bits(&b.0) { (a, b) } else { (b, a) };
                        let t = (bound - s.0[axis]) / (e.0[axis] - s.0[axis]);
                        let mut p = s.0 + (e.0 - s.0) * t;
                        p[axis] = bound;
                        next.push((p, (s.1 + (e.1 - s.1) * t).normalize_or_zero()));
                    }
                }
                polygon = next;
                if polygon.is_empty() {
                    break;
                }
            }
        }
        if polygon.len() < 3 {
            continue;
        }
        let ids: Vec<u32> = polygon.iter().map(|(p, n)| add(*p, *n, &mut out)).collect();
        for k in 1..ids.len() - 1 {
            let t = [ids[0], ids[k], ids[k + 1]];
            if t[0] != t[1] && t[1] != t[2] && t[0] != t[2] {
                out.triangles.push(t);
            }
        }
    }
    out
}
