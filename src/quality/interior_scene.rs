//! The interior test scene: a furnished room seen only from inside, the capture people make
//! most and the one where a method can invent surface. Nothing outside the room's walls is
//! ever observed, some furniture hides parts of the walls and floor, and the scene holds the
//! hard cases of a real room: large flat walls, a curved sphere, thin table legs and a thin
//! upright plate. Rendered with [`super::ground_truth_views::Layout::Interior`], whose cameras
//! stand inside the room and look outwards.

use glam::DVec3;

use crate::mesh::Mesh;

/// Half-extents of the room: 6 m by 5 m, 3 m high, centred on the origin at the floor's
/// height 0.
const ROOM_MIN: DVec3 = DVec3::new(-3.0, -2.5, 0.0);
const ROOM_MAX: DVec3 = DVec3::new(3.0, 2.5, 3.0);

/// The largest triangle edge of the flat parts: fine enough that "which faces a camera saw"
/// follows what the furniture hides.
const CELL: f64 = 0.1;

/// The room and its furniture as one triangle mesh, in metres. The room's walls are one box
/// facing inwards; each piece of furniture is a closed box or sphere, resting on the floor or
/// against a wall (the faces that touch are never seen).
pub fn interior_room() -> Mesh {
    let mut mesh = Mesh::default();
    add_box(&mut mesh, ROOM_MIN, ROOM_MAX, true);
    // A table: a 5 cm top on four 5 cm legs.
    add_box(
        &mut mesh,
        DVec3::new(0.8, -1.7, 0.70),
        DVec3::new(2.0, -0.8, 0.75),
        false,
    );
    for (x, y) in [(0.85, -1.65), (1.90, -1.65), (0.85, -0.90), (1.90, -0.90)] {
        add_box(
            &mut mesh,
            DVec3::new(x, y, 0.0),
            DVec3::new(x + 0.05, y + 0.05, 0.70),
            false,
        );
    }
    // A cabinet 10 cm in front of the wall x = -3: the strip of wall behind it is hidden.
    add_box(&mut mesh, DVec3::new(-2.9, 0.5, 0.0), DVec3::new(-2.3, 2.0, 1.8), false);
    // A low sofa against the wall y = -2.5.
    add_box(
        &mut mesh,
        DVec3::new(-1.2, -2.5, 0.0),
        DVec3::new(0.4, -1.7, 0.5),
        false,
    );
    // A thin upright plate, 2 cm thick.
    add_box(&mut mesh, DVec3::new(-0.6, 1.6, 0.0), DVec3::new(0.6, 1.62, 1.2), false);
    add_sphere(&mut mesh, DVec3::new(1.5, 1.3, 0.4), 0.4, 48, 24);
    mesh
}

/// Adds an axis-aligned box split into cells of at most [`CELL`], its faces wound outwards, or
/// inwards for a room seen from inside.
fn add_box(mesh: &mut Mesh, min: DVec3, max: DVec3, inwards: bool) {
    let size = max - min;
    for axis in 0..3 {
        let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
        let (nu, nv) = (cells(size[u]), cells(size[v]));
        for side in [0.0, 1.0] {
            let first = mesh.positions.len() as u32;
            for j in 0..=nv {
                for i in 0..=nu {
                    let mut p = min;
                    p[axis] += side * size[axis];
                    p[u] += size[u] * i as f64 / nu as f64;
                    p[v] += size[v] * j as f64 / nv as f64;
                    mesh.positions.push(p.as_vec3().to_array());
                }
            }
            // (u, v, axis) is right-handed: counter-clockwise in (u, v) faces +axis.
            let outwards_positive = side == 1.0;
            let flip = outwards_positive == inwards;
            let at = |i: usize, j: usize| first + (j * (nu + 1) + i) as u32;
            for j in 0..nv {
                for i in 0..nu {
                    let quad = [at(i, j), at(i + 1, j), at(i + 1, j + 1), at(i, j + 1)];
                    for [a, b, c] in [[quad[0], quad[1], quad[2]], [quad[0], quad[2], quad[3]]] {
                        mesh.triangles.push(if flip { [a, c, b] } else { [a, b, c] });
                    }
                }
            }
        }
    }
}

fn cells(length: f64) -> usize {
    ((length / CELL).ceil() as usize).max(1)
}

/// Adds a UV sphere, wound outwards.
pub(crate) fn add_sphere(mesh: &mut Mesh, center: DVec3, radius: f64, segments: usize, rings: usize) {
    let first = mesh.positions.len() as u32;
    for ring in 0..=rings {
        let polar = std::f64::consts::PI * ring as f64 / rings as f64;
        for segment in 0..segments {
            let azimuth = std::f64::consts::TAU * segment as f64 / segments as f64;
            let direction = DVec3::new(polar.sin() * azimuth.cos(), polar.sin() * azimuth.sin(), polar.cos());
            mesh.positions.push((center + direction * radius).as_vec3().to_array());
        }
    }
    let at = |ring: usize, segment: usize| first + (ring * segments + segment % segments) as u32;
    for ring in 0..rings {
        for segment in 0..segments {
            let (a, b) = (at(ring, segment), at(ring, segment + 1));
            let (c, d) = (at(ring + 1, segment), at(ring + 1, segment + 1));
            if ring > 0 {
                mesh.triangles.push([a, c, b]);
            }
            if ring + 1 < rings {
                mesh.triangles.push([b, c, d]);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::edge_defects;

    #[test]
    fn the_room_is_a_set_of_closed_shells() {
        let mesh = interior_room();
        // Every shell is closed except where box grids meet at their edges (their vertices are
        // not shared), which leaves boundary edges but never an edge used three times.
        let (_, non_manifold) = edge_defects(&mesh);
        assert_eq!(non_manifold, 0);
        let (lo, hi) = super::super::ground_truth_views::bounds(&mesh).unwrap();
        assert_eq!((lo.as_vec3(), hi.as_vec3()), (ROOM_MIN.as_vec3(), ROOM_MAX.as_vec3()));
    }
}
