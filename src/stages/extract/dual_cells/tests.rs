//! Tests of a unit's dual cells: the probes' lookup and skips, the tetrahedron support test,
//! offset planes and vertex moves.

use super::*;

fn random(seed: &mut u64) -> u64 {
    crate::kernels::random::splitmix(seed) >> 33
}

/// A random cut of the cube `top` in key order: each cube splits with a chance of 5 in 8,
/// down to `deepest`; with `gaps`, a quarter of its cubes left out (a unit's cut need not
/// fill the cube that holds it).
fn random_cut(top: CubeKey, deepest: u8, gaps: bool, seed: &mut u64) -> Vec<CubeKey> {
    let mut cut = Vec::new();
    let mut stack = vec![top];
    while let Some(cube) = stack.pop() {
        if cube.depth() < deepest && random(seed) % 8 < 5 {
            let [x, y, z] = cube.coords();
            for child in (0..8u32).rev() {
                let at = |c: u32, bit: u32| 2 * c + (child >> bit & 1);
                stack.push(CubeKey::new(cube.depth() + 1, at(x, 0), at(y, 1), at(z, 2)));
            }
        } else if !(gaps && random(seed).is_multiple_of(4)) {
            cut.push(cube);
        }
    }
    cut.sort();
    cut
}

#[test]
fn a_unit_cut_finds_the_cube_holding_a_probe_as_a_scan_does() {
    let mut seed = 7;
    let value = CutValue {
        u: 0.0,
        votes: 0.0,
        measured: 0.0,
        sampled: false,
        offset: 0.0,
    };
    for (top, deepest, gaps) in [
        (CubeKey::new(0, 0, 0, 0), 0, false),
        (CubeKey::new(0, 0, 0, 0), 5, false),
        (CubeKey::new(3, 5, 2, 7), 9, false),
        (CubeKey::new(3, 5, 2, 7), 9, true),
        (CubeKey::new(27, 1, 2, 3), MAX_DEPTH, true),
    ] {
        let keys = random_cut(top, deepest, gaps, &mut seed);
        let values = vec![value; keys.len()];
        let cut = UnitCut::new(&keys, &values);
        let [x, y, z] = top.corner_full_resolution();
        let side = full_side(top.depth());
        // Finest cells in the top cube, then anywhere in the root, then each key's first.
        let mut probes: Vec<CubeKey> = (0..2000)
            .map(|i| {
                let mut c = |low: u32| {
                    if i < 1500 {
                        low + (random(&mut seed) % side) as u32
                    } else {
                        (random(&mut seed) << 1) as u32
                    }
                };
                CubeKey::from_full_resolution(MAX_DEPTH, c(x), c(y), c(z))
            })
            .collect();
        probes.extend(keys.iter().map(|k| CubeKey::from_morton(k.morton(), MAX_DEPTH)));
        for probe in probes {
            let expected = keys.iter().position(|k| k.is_ancestor_or_self_of(probe));
            assert_eq!(
                cut.position_of(probe),
                expected,
                "{} keys under {top:?}, probe {probe:?}",
                keys.len()
            );
        }
    }
    assert_eq!(
        UnitCut::new(&[], &[]).position_of(CubeKey::new(MAX_DEPTH, 0, 0, 0)),
        None
    );
}

#[test]
fn corners_lost_to_a_sibling_are_those_an_earlier_octant_probes_in_the_parent() {
    // Every child of a parent inside the root: the cells the probes of each corner's
    // earlier octants read, as extraction computes them, against the table.
    let parent = CubeKey::new(5, 9, 20, 13);
    let [px, py, pz] = parent.coords();
    let mut lost_corners = 0;
    for child in 0..8u32 {
        let key = CubeKey::new(
            6,
            2 * px + (child & 1),
            2 * py + (child >> 1 & 1),
            2 * pz + (child >> 2),
        );
        let side = full_side(key.depth());
        let corner_cells = key.corner_full_resolution().map(u64::from);
        let probe_cells: [[ProbeCell; 4]; 3] =
            std::array::from_fn(|axis| ProbeCell::around(key, axis, corner_cells[axis], side));
        for corner in 0..8u64 {
            let in_parent = (0..7 - corner).any(|octant| {
                let cells: [ProbeCell; 3] = std::array::from_fn(|axis| {
                    probe_cells[axis][(2 * ((corner >> axis) & 1) + ((octant >> axis) & 1)) as usize]
                });
                let probe = CubeKey::from_morton(
                    cells[0].axis_bits | cells[1].axis_bits << 1 | cells[2].axis_bits << 2,
                    MAX_DEPTH,
                );
                parent.is_ancestor_or_self_of(probe)
            });
            let table = CORNERS_LOST_TO_A_SIBLING[child as usize] & (1 << corner) != 0;
            assert_eq!(table, in_parent, "child {child}, corner {corner}");
            lost_corners += u32::from(table);
        }
    }
    // 37 of the 64 (child, corner) pairs; the generating corner of the first child is not.
    assert_eq!(lost_corners, 37);
    assert_eq!(CORNERS_LOST_TO_A_SIBLING[0] & (1 << 7), 0);
}

fn cell(offset_at: impl Fn(DVec3) -> f64, side: f64) -> [Corner; 8] {
    std::array::from_fn(|i| {
        let center = DVec3::new((i & 1) as f64, ((i >> 1) & 1) as f64, ((i >> 2) & 1) as f64) * side;
        let offset = offset_at(center);
        Corner {
            id: i as u128,
            center,
            // u on the same side as the offset.
            u: if offset > 0.0 { 0.5 } else { -0.5 },
            offset,
            votes: 1.0,
            measured: 1.0,
            sampled: true,
        }
    })
}

#[test]
fn a_tetrahedron_needs_its_own_corners_to_support_a_surface() {
    let side = 0.0057;
    let tetrahedron = |c: [Corner; 8]| KUHN[0].map(|i| c[i]);
    // The surface crosses the tetrahedron: its corners measured it within a side.
    let through = tetrahedron(cell(|p| p.z - 0.5 * side, side));
    assert!(tetrahedron_supported(&through.each_ref()));
    // A fringe past a depth edge: the votes put the surface two sides away or measured
    // nothing, and samples reached one corner alone.
    let mut fringe = tetrahedron(cell(|p| p.z - 3.0 * side, side));
    fringe[1].offset = f64::NAN;
    for c in fringe.iter_mut().skip(1) {
        c.sampled = false;
    }
    assert!(!tetrahedron_supported(&fringe.each_ref()));
    // Samples in two of its cells and enough measured votes vouch for it...
    fringe[1].sampled = true;
    assert!(tetrahedron_supported(&fringe.each_ref()));
    // ...unless nearly all its votes were clamped (occluded or free space).
    for c in fringe.iter_mut() {
        c.measured = 0.05 * c.votes;
    }
    assert!(!tetrahedron_supported(&fringe.each_ref()));
}

#[test]
fn offset_planes_put_vertices_on_the_measured_surface() {
    // A tilted plane through a cell 5.7 mm wide, its offsets measured along rays that meet
    // it obliquely (distances scaled by 1.4): the fit recovers the plane, and a vertex
    // anywhere near the cell projects onto it.
    let normal = DVec3::new(0.2, -0.3, 0.93).normalize();
    let origin = DVec3::new(0.002, 0.003, 0.0031);
    let plane = OffsetPlane::fit(&cell(|p| 1.4 * normal.dot(p - origin), 0.0057)).expect("a plane");
    let mut share = VertexMove::empty(0, 1.0);
    let (n, d) = plane.normal_form();
    share.add_plane(n, d);
    for p in [DVec3::ZERO, DVec3::splat(0.0057), DVec3::new(0.001, 0.004, 0.0057)] {
        let on = share.place(p, p);
        assert!(normal.dot(on - origin).abs() < 1e-12, "{p} -> {on}");
        assert!(
            (p - on).normalize().dot(normal).abs() > 1.0 - 1e-9,
            "moves along the normal"
        );
    }
    // No plane where the corners measured nothing, mixed surfaces (a flat gradient),
    // coincident centres or a virtual corner.
    let mut unmeasured = cell(|p| normal.dot(p - origin), 0.0057);
    unmeasured[3].offset = f64::NAN;
    assert!(OffsetPlane::fit(&unmeasured).is_none());
    assert!(OffsetPlane::fit(&cell(|p| 0.3 * normal.dot(p - origin), 0.0057)).is_none());
    let mut flat = cell(|p| normal.dot(p - origin), 0.0057);
    for c in flat.iter_mut() {
        c.center.z = 0.0;
    }
    assert!(OffsetPlane::fit(&flat).is_none());
    let mut virtual_corner = cell(|p| normal.dot(p - origin), 0.0057);
    virtual_corner[5].id |= VIRTUAL;
    assert!(OffsetPlane::fit(&virtual_corner).is_none());
    // Nor where u puts a corner well away from the plane on the other side (offsets
    // dragged by outliers); a corner near the plane may disagree.
    let mut disputed = cell(|p| normal.dot(p - origin), 0.0057);
    let far = (0..8)
        .max_by(|&a, &b| disputed[a].offset.abs().total_cmp(&disputed[b].offset.abs()))
        .unwrap_or(0);
    disputed[far].u = -disputed[far].u;
    assert!(OffsetPlane::fit(&disputed).is_none());
    let mut close = cell(|p| normal.dot(p) - 0.0003, 0.0057);
    let near = (0..8)
        .min_by(|&a, &b| close[a].offset.abs().total_cmp(&close[b].offset.abs()))
        .unwrap_or(0);
    assert!(close[near].offset.abs() < SIDE_DISAGREEMENT * 0.0057);
    close[near].u = -close[near].u;
    assert!(OffsetPlane::fit(&close).is_some());
}

#[test]
fn a_vertex_goes_to_the_mean_of_its_projections_within_its_reach() {
    let z = DVec3::Z;
    let start = DVec3::new(1.0, 1.0, 1.0);
    // Units' shares add up; an empty first share (a unit whose cells had no plane) does not
    // know the reach. Planes z = 1.2 and twice z = 1.3: the mean of the projections.
    let mut total = VertexMove::empty(0, 0.0);
    let mut first = VertexMove::empty(0, 0.5);
    first.add_plane(z, 1.2);
    let mut second = VertexMove::empty(0, 0.5);
    second.add_plane(z, 1.3);
    second.add_plane(-z, -1.3);
    total.add(&first);
    total.add(&second);
    assert!((total.place(start, start) - DVec3::new(1.0, 1.0, 1.2666666666666666)).length() < 1e-12);
    // Two crossing planes: the mean of the two projections, not their intersection.
    let mut crossing = VertexMove::empty(0, 5.0);
    crossing.add_plane(DVec3::X, 2.0);
    crossing.add_plane(DVec3::Y, 3.0);
    assert!((crossing.place(start, start) - DVec3::new(1.5, 2.0, 1.0)).length() < 1e-12);
    // Held within its reach of where extraction put it, along the way to the target.
    let mut far = VertexMove::empty(0, 0.5);
    far.add_plane(z, 3.0);
    assert!((far.place(start, start) - DVec3::new(1.0, 1.0, 1.5)).length() < 1e-12);
    let moved = DVec3::new(1.3, 1.0, 1.0);
    let held = start + (DVec3::new(1.3, 1.0, 3.0) - start).normalize() * 0.5;
    assert!((far.place(moved, start) - held).length() < 1e-12);
    assert_eq!(VertexMove::empty(0, 0.5).place(moved, start), moved);
}
