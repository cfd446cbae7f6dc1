//! Surface extraction (paper 4.6): the zero level set of u over the finest level cut.
//!
//! Dual marching tetrahedra. u lives at leaf centres. For every corner point V of the octree,
//! the dual cell joins the centres of the (up to 8) leaves incident to V, one per octant, with
//! repeats where a coarse leaf covers several octants; corners outside the root are virtual
//! exterior cells with u = +1, which closes every surface. Each dual cell is generated exactly
//! once, by the deepest incident leaf that comes first in octant order, and split into the 6
//! Kuhn tetrahedra around its 0-7 diagonal, so neighbouring cells cut their shared faces along
//! the same diagonal and the tetrahedra conform. A surface vertex lies on a tetrahedron edge and
//! is named by the unordered pair of cells at its ends, so the same vertex is produced, and
//! welded, wherever the edge appears: on both sides of a level change and of a treetop border.

use std::collections::HashMap;
use std::hash::BuildHasher;

/// Hash tables keyed by surface-vertex and edge names: nothing depends on their iteration
/// order, so a fast fixed-seed hasher replaces SipHash.
type FastMap<K, V> = HashMap<K, V, foldhash::fast::FixedState>;
use std::io::Write;
use std::path::Path;

use glam::DVec3;
use rayon::prelude::*;

use super::scene::Scene;
use super::solve::{LEVEL_STAGES, LevelCut, cut_cube_ending_at};
use super::treetop::Treetop;
use crate::format::{CubeKey, MAX_DEPTH};
use crate::store::{Result, Snapshot, StoreError};

/// Identity of a dual-cell corner: a leaf key, or a virtual exterior cell (bit 127 set, bits
/// 124..127 the mirrored axes, then the key of the leaf it mirrors).
type CornerId = u128;
const VIRTUAL: u128 = 1 << 127;

#[derive(Clone, Copy)]
struct Corner {
    id: CornerId,
    center: DVec3,
    u: f32,
    depth: u8,
}

/// A triangle soup with welded vertices, per unit.
/// A surface vertex's identity: the cut edge it lies on, as its sorted corner pair.
type VertexId = (CornerId, CornerId);

#[derive(Default, Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct UnitMesh {
    /// Edge identity (sorted corner pair) and position of each vertex.
    pub vertices: Vec<((CornerId, CornerId), DVec3, DVec3)>,
    pub triangles: Vec<[u32; 3]>,
}

/// The Kuhn subdivision of a cube with corners indexed by octant bits (x = 1, y = 2, z = 4):
/// the 6 monotone paths from corner 0 to corner 7.
const KUHN: [[usize; 4]; 6] = [
    [0, 1, 3, 7],
    [0, 1, 5, 7],
    [0, 2, 3, 7],
    [0, 2, 6, 7],
    [0, 4, 5, 7],
    [0, 4, 6, 7],
];

fn full_side(depth: u8) -> u64 {
    1u64 << (u32::from(MAX_DEPTH) - u32::from(depth))
}

/// The cut cube containing the finest cell `cell`, and its u. The unit's own sorted cut
/// (`keys`, `values`) is searched first, outwards from `near` (the cube whose corners are being
/// probed, so the answer is usually a few keys away): the cut tiles the root, so a cube of the
/// unit that contains the cell is the answer. Cells outside the unit go to the level's lookup.
fn cut_cube_near(
    level: &mut LevelCut<'_, '_>,
    keys: &[CubeKey],
    values: &[f32],
    near: usize,
    cell: [u32; 3],
) -> Result<Option<(CubeKey, f32)>> {
    let probe = CubeKey::new(MAX_DEPTH, cell[0], cell[1], cell[2]);
    match cut_cube_ending_at(keys, values, partition_point_near(keys, near, probe), probe) {
        Some(found) => Ok(Some(found)),
        None => level.cube_containing(probe),
    }
}

/// `keys.partition_point(|k| *k <= probe)` for sorted `keys`, found by galloping outwards from
/// `near`: O(log d) comparisons, near the start, for an answer d keys away.
fn partition_point_near(keys: &[CubeKey], near: usize, probe: CubeKey) -> usize {
    let at_or_below = |i: usize| keys.get(i).is_some_and(|k| *k <= probe);
    let near = near.min(keys.len());
    // The answer lies in (low, high]: keys[low] <= probe (or low is the start) and
    // keys[high] > probe (or high is the end).
    let (low, high) = if at_or_below(near) {
        let mut step = 1;
        let mut low = near;
        loop {
            let next = near.saturating_add(step);
            if next >= keys.len() {
                break (low + 1, keys.len());
            }
            if !at_or_below(next) {
                break (low + 1, next);
            }
            low = next;
            step *= 2;
        }
    } else {
        let mut step = 1;
        let mut high = near;
        loop {
            let Some(next) = near.checked_sub(step) else {
                break (0, high);
            };
            if at_or_below(next) {
                break (next + 1, high);
            }
            high = next;
            step *= 2;
        }
    };
    low + keys
        .get(low..high)
        .map_or(0, |range| range.partition_point(|k| *k <= probe))
}

fn dual_cells_of_unit(
    scene: &Scene,
    level: &mut LevelCut<'_, '_>,
    keys: &[CubeKey],
    values: &[f32],
) -> Result<UnitMesh> {
    let mut mesh = UnitMesh::default();
    // The unit's vertices by name, as indices into `mesh.vertices`.
    let mut vertex_index = NameIndex::default();
    let limit = 1u64 << 32;
    for (index, (key, own_u)) in keys.iter().zip(values).enumerate() {
        let d = key.depth();
        let side = full_side(d);
        let [x, y, z] = key.corner_full_resolution().map(u64::from);
        for corner in 0..8u64 {
            let v = [
                x + (corner & 1) * side,
                y + ((corner >> 1) & 1) * side,
                z + ((corner >> 2) & 1) * side,
            ];
            // The 8 octants around V, with the leaf (or virtual exterior cell) in each. This cube
            // fills the octant opposite the corner; it generates V's cell only if no real leaf
            // is deeper and none as deep comes first in octant order, so the probes stop at the
            // first leaf that rules it out (most corners of a uniform region end at octant 0).
            let own_octant = (7 - corner) as usize;
            let mut corners: [Option<Corner>; 8] = [None; 8];
            let mut generator_ok = true;
            for (octant, slot) in corners.iter_mut().enumerate() {
                if octant == own_octant {
                    *slot = Some(Corner {
                        id: key.raw(),
                        center: scene.cube_center(*key),
                        u: *own_u,
                        depth: d,
                    });
                    continue;
                }
                let o = octant as u64;
                let cell = [
                    v[0] as i64 - 1 + (o & 1) as i64,
                    v[1] as i64 - 1 + ((o >> 1) & 1) as i64,
                    v[2] as i64 - 1 + ((o >> 2) & 1) as i64,
                ];
                // Outside the root, the octree continues as its mirror image across the root's
                // faces, with u = +1: neighbouring dual cells then agree on every virtual cell.
                let mut mirrored = 0u128;
                let inside = cell.map(|c| c);
                let mut probe = [0u32; 3];
                for axis in 0..3 {
                    let c = inside[axis];
                    let m = if c < 0 {
                        mirrored |= 1 << axis;
                        -1 - c
                    } else if c >= limit as i64 {
                        mirrored |= 1 << axis;
                        2 * limit as i64 - 1 - c
                    } else {
                        c
                    };
                    probe[axis] = m.clamp(0, limit as i64 - 1) as u32;
                }
                let Some((leaf, u)) = cut_cube_near(level, keys, values, index, probe)? else {
                    generator_ok = false;
                    break;
                };
                if mirrored == 0 && (leaf.depth() > d || (leaf.depth() == d && octant < own_octant)) {
                    generator_ok = false;
                    break;
                }
                let mut center = scene.cube_center(leaf);
                if mirrored != 0 {
                    let (lo, hi) = (scene.min(), scene.min() + DVec3::splat(scene.root_side));
                    for axis in 0..3 {
                        if mirrored & (1 << axis) != 0 {
                            center[axis] = if inside[axis] < 0 {
                                2.0 * lo[axis] - center[axis]
                            } else {
                                2.0 * hi[axis] - center[axis]
                            };
                        }
                    }
                }
                let c = Corner {
                    id: if mirrored != 0 {
                        VIRTUAL | (mirrored << 124) | leaf.raw()
                    } else {
                        leaf.raw()
                    },
                    center,
                    u: if mirrored != 0 { 1.0 } else { u },
                    depth: leaf.depth(),
                };
                *slot = Some(c);
            }
            let corners: [Corner; 8] = corners.map(|c| {
                c.unwrap_or(Corner {
                    id: VIRTUAL,
                    center: DVec3::ZERO,
                    u: 1.0,
                    depth: 0,
                })
            });
            // Generated by the deepest real leaf, first in octant order.
            let deepest = corners.iter().filter(|c| c.id & VIRTUAL == 0).map(|c| c.depth).max();
            let first = corners
                .iter()
                .position(|c| c.id & VIRTUAL == 0 && Some(c.depth) == deepest);
            match first.and_then(|i| corners.get(i)) {
                Some(c) if c.id == key.raw() => {}
                _ => generator_ok = false,
            }
            if !generator_ok {
                continue;
            }
            let positive = corners.iter().filter(|c| c.u > 0.0).count();
            if positive == 0 || positive == 8 {
                continue;
            }
            // Gradient of u over the cell, for vertex normals.
            let mut gradient = DVec3::ZERO;
            for axis in 0..3 {
                let (mut plus, mut minus, mut np, mut nm) = (0f64, 0f64, 0, 0);
                let (mut cp, mut cm) = (0f64, 0f64);
                for (i, c) in corners.iter().enumerate() {
                    if (i >> axis) & 1 == 1 {
                        plus += f64::from(c.u);
                        cp += c.center[axis];
                        np += 1;
                    } else {
                        minus += f64::from(c.u);
                        cm += c.center[axis];
                        nm += 1;
                    }
                }
                let dist = cp / f64::from(np) - cm / f64::from(nm);
                if dist.abs() > 0.0 {
                    gradient[axis] = (plus / f64::from(np) - minus / f64::from(nm)) / dist;
                }
            }
            for tet in KUHN {
                let t = tet.map(|i| corners[i]);
                let inside: Vec<usize> = (0..4).filter(|&i| t[i].u <= 0.0).collect();
                let outside: Vec<usize> = (0..4).filter(|&i| t[i].u > 0.0).collect();
                if inside.is_empty() || outside.is_empty() {
                    continue;
                }
                let mut vertex = |a: usize, b: usize, mesh: &mut UnitMesh| -> u32 {
                    let (ca, cb) = (t[a], t[b]);
                    let edge = if ca.id <= cb.id { (ca.id, cb.id) } else { (cb.id, ca.id) };
                    let vertices = &mesh.vertices;
                    match vertex_index.entry(edge, |i| vertices.get(i as usize).map(|v| v.0)) {
                        hashbrown::hash_table::Entry::Occupied(found) => *found.get(),
                        hashbrown::hash_table::Entry::Vacant(slot) => {
                            let (lo, hi) = if ca.id <= cb.id { (ca, cb) } else { (cb, ca) };
                            let s = f64::from(lo.u) / (f64::from(lo.u) - f64::from(hi.u));
                            let position = lo.center + (hi.center - lo.center) * s;
                            let index = mesh.vertices.len() as u32;
                            mesh.vertices.push((edge, position, DVec3::ZERO));
                            *slot.insert(index).get()
                        }
                    }
                };
                let mut polygon: Vec<u32> = Vec::new();
                if inside.len() == 1 || outside.len() == 1 {
                    let (apex, others) = if inside.len() == 1 {
                        (inside[0], &outside)
                    } else {
                        (outside[0], &inside)
                    };
                    for &o in others.iter() {
                        polygon.push(vertex(apex, o, &mut mesh));
                    }
                } else {
                    let (i0, i1, o0, o1) = (inside[0], inside[1], outside[0], outside[1]);
                    polygon.push(vertex(i0, o0, &mut mesh));
                    polygon.push(vertex(i0, o1, &mut mesh));
                    polygon.push(vertex(i1, o1, &mut mesh));
                    polygon.push(vertex(i1, o0, &mut mesh));
                }
                for &vi in &polygon {
                    if let Some(v) = mesh.vertices.get_mut(vi as usize) {
                        v.2 += gradient;
                    }
                }
                // Orient towards positive u (outside).
                let to_outside = outside.iter().map(|&i| t[i].center).sum::<DVec3>() / outside.len() as f64
                    - inside.iter().map(|&i| t[i].center).sum::<DVec3>() / inside.len() as f64;
                for k in 1..polygon.len() - 1 {
                    let mut tri = [polygon[0], polygon[k], polygon[k + 1]];
                    if tri[0] == tri[1] || tri[1] == tri[2] || tri[0] == tri[2] {
                        continue;
                    }
                    let p = tri.map(|i| mesh.vertices[i as usize].1);
                    let normal = (p[1] - p[0]).cross(p[2] - p[0]);
                    if normal.dot(to_outside) < 0.0 {
                        tri.swap(1, 2);
                    }
                    mesh.triangles.push(tri);
                }
            }
        }
    }
    Ok(mesh)
}

/// An axis-aligned box in world coordinates.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Region {
    pub min: DVec3,
    pub max: DVec3,
}

/// The extracted mesh: welded vertices with normals, and triangles.
#[derive(Default, Debug, Clone)]
pub struct Mesh {
    pub positions: Vec<[f32; 3]>,
    pub normals: Vec<[f32; 3]>,
    pub triangles: Vec<[u32; 3]>,
}

/// What to extract and how.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ExtractOptions {
    /// Only what lies in this box, cut at its faces.
    pub region: Option<Region>,
    /// Keep about this fraction of each treetop leaf's triangles (quadric error simplification;
    /// vertices shared with another leaf never move, so the whole stays seamless).
    pub decimate: Option<f32>,
}

/// Largest error a decimation may introduce, relative to the extent of a leaf's mesh: the
/// triangle target is not reached where reaching it would cost more.
pub const DECIMATE_MAX_ERROR: f32 = 0.01;

/// Rounds of local repair before a unit gives up on decimation.
const DECIMATE_REPAIR_ROUNDS: u32 = 4;

/// Simplifies each unit's mesh with meshopt, locking the vertices other units also have;
/// triangles are kept in the simplifier's deterministic output order.
///
/// meshopt does not promise a manifold result: two sheets of one leaf can be collapsed onto a
/// common edge. Such an edge (more than two triangles) is repaired locally: the unit is
/// simplified again from its original piece with every vertex near the edge locked as well, the
/// neighbourhood doubling each round. A unit still part of such an edge after
/// `DECIMATE_REPAIR_ROUNDS` rounds keeps its original piece, so the result is always manifold
/// wherever the input was.
fn decimate_units(meshes: &mut [UnitMesh], ratio: f32) {
    let originals = meshes.to_vec();
    let shared = shared_vertices(meshes);
    let mut locks: Vec<Vec<bool>> = originals
        .iter()
        .map(|mesh| mesh.vertices.iter().map(|(edge, ..)| shared.contains(edge)).collect())
        .collect();
    meshes
        .par_iter_mut()
        .zip(&locks)
        .for_each(|(mesh, locks)| simplify(mesh, locks, ratio));
    for round in 0..=DECIMATE_REPAIR_ROUNDS {
        let bad = overused_edges(meshes);
        if bad.is_empty() {
            return;
        }
        let mut redo = vec![false; meshes.len()];
        for (unit, [a, b]) in bad {
            let (Some(original), Some(unit_locks), Some(flag)) =
                (originals.get(unit), locks.get_mut(unit), redo.get_mut(unit))
            else {
                continue;
            };
            *flag = true;
            if round == DECIMATE_REPAIR_ROUNDS {
                continue;
            }
            let radius = 4.0 * (a - b).length() * f64::from(1u32 << round);
            for ((_, p, _), lock) in original.vertices.iter().zip(unit_locks.iter_mut()) {
                if (*p - a).length() <= radius || (*p - b).length() <= radius {
                    *lock = true;
                }
            }
        }
        meshes
            .par_iter_mut()
            .zip(originals.par_iter().zip(&locks).zip(&redo))
            .for_each(|(mesh, ((original, locks), redo))| {
                if *redo {
                    *mesh = original.clone();
                    if round < DECIMATE_REPAIR_ROUNDS {
                        simplify(mesh, locks, ratio);
                    }
                }
            });
    }
}

/// Vertices (by edge identity) that more than one unit has: the seams between units.
fn shared_vertices(meshes: &[UnitMesh]) -> std::collections::HashSet<VertexId> {
    let mut owners: HashMap<VertexId, usize> = HashMap::new();
    let mut shared = std::collections::HashSet::new();
    for (unit, mesh) in meshes.iter().enumerate() {
        for (edge, ..) in &mesh.vertices {
            if *owners.entry(*edge).or_insert(unit) != unit {
                shared.insert(*edge);
            }
        }
    }
    shared
}

/// Every (unit, end points) of an edge that more than two triangles use, over all units,
/// sorted so repairs do not depend on hash order.
fn overused_edges(meshes: &[UnitMesh]) -> Vec<(usize, [DVec3; 2])> {
    let mut edge_users: HashMap<[VertexId; 2], (u32, Vec<usize>, [DVec3; 2])> = HashMap::new();
    for (unit, mesh) in meshes.iter().enumerate() {
        for triangle in &mesh.triangles {
            let corners = triangle.map(|v| mesh.vertices.get(v as usize).map(|(edge, p, _)| (*edge, *p)));
            let [Some(a), Some(b), Some(c)] = corners else {
                continue;
            };
            for (x, y) in [(a, b), (b, c), (c, a)] {
                let (x, y) = if x.0 < y.0 { (x, y) } else { (y, x) };
                let entry = edge_users.entry([x.0, y.0]).or_insert((0, Vec::new(), [x.1, y.1]));
                entry.0 += 1;
                entry.1.push(unit);
            }
        }
    }
    let mut bad: Vec<(usize, [VertexId; 2], [DVec3; 2])> = edge_users
        .into_iter()
        .filter(|(_, (count, ..))| *count > 2)
        .flat_map(|(edge, (_, users, ends))| users.into_iter().map(move |unit| (unit, edge, ends)))
        .collect();
    bad.sort_by_key(|x| (x.0, x.1));
    bad.dedup_by(|x, y| (x.0, x.1) == (y.0, y.1));
    bad.into_iter().map(|(unit, _, ends)| (unit, ends)).collect()
}

/// One unit's mesh simplified towards `ratio` of its triangles, `locks` (per vertex) fixed.
fn simplify(mesh: &mut UnitMesh, locks: &[bool], ratio: f32) {
    if mesh.triangles.is_empty() {
        return;
    }
    let positions: Vec<[f32; 3]> = mesh.vertices.iter().map(|(_, p, _)| p.as_vec3().to_array()).collect();
    let indices: Vec<u32> = mesh.triangles.iter().flatten().copied().collect();
    let target = ((indices.len() / 3) as f64 * f64::from(ratio.clamp(0.0, 1.0))) as usize * 3;
    let kept = meshopt::simplify_with_locks_decoder(
        &indices,
        &positions,
        locks,
        target,
        DECIMATE_MAX_ERROR,
        meshopt::SimplifyOptions::LockBorder,
        None,
    );
    mesh.triangles = kept.chunks_exact(3).map(|t| [t[0], t[1], t[2]]).collect();
    // Drop vertices no triangle uses any more, keeping the order of the rest.
    let mut used = vec![false; mesh.vertices.len()];
    mesh.triangles.iter().flatten().for_each(|&v| {
        if let Some(u) = used.get_mut(v as usize) {
            *u = true;
        }
    });
    let mut remap = vec![u32::MAX; mesh.vertices.len()];
    let mut next = 0u32;
    for (slot, keep) in remap.iter_mut().zip(&used) {
        if *keep {
            *slot = next;
            next += 1;
        }
    }
    let mut index = 0;
    mesh.vertices.retain(|_| {
        index += 1;
        used.get(index - 1).copied().unwrap_or(false)
    });
    for t in &mut mesh.triangles {
        *t = t.map(|v| remap.get(v as usize).copied().unwrap_or(u32::MAX));
    }
}

/// Extracts the surface u = 0 of the latest solution, optionally only what lies in a region.
pub fn extract(snapshot: &Snapshot<'_>, scene: &Scene, finest: u8, options: &ExtractOptions) -> Result<Mesh> {
    let units = extract_units(snapshot, scene, finest, options.region)?;
    let treetop = Treetop::of(snapshot)?;
    let meshes: Vec<UnitMesh> = units
        .par_iter()
        .map(|&unit| unit_mesh(snapshot, &treetop, scene, finest, unit))
        .collect::<Result<_>>()?;
    Ok(assemble(meshes, options))
}

/// The treetop units whose dual cells can reach the region (all leaves without one), in order.
pub fn extract_units(snapshot: &Snapshot<'_>, scene: &Scene, finest: u8, region: Option<Region>) -> Result<Vec<usize>> {
    let treetop = Treetop::of(snapshot)?;
    let stage = LEVEL_STAGES[usize::from(finest)];
    if snapshot.segments(stage).is_empty() {
        return Err(StoreError::Stage {
            stage: "extract".into(),
            unit: "-".into(),
            message: format!("no solution at level {finest}: run `octstore solve` first"),
        });
    }
    Ok((0..treetop.units.len())
        .filter(|&i| {
            let Some(unit) = treetop.units.get(i) else { return false };
            if unit.top {
                return false;
            }
            match region {
                None => true,
                Some(r) => {
                    // A dual cell spans the centres of leaves adjacent to its generating leaf,
                    // which are at most twice its size (2:1 balance): grow the unit's cube by
                    // twice its side to catch every cell that can reach into the box.
                    let side = scene.cube_side(unit.key.depth());
                    let lo = scene.cube_center(unit.key) - DVec3::splat(side * 2.5);
                    let hi = lo + DVec3::splat(side * 5.0);
                    lo.cmple(r.max).all() && hi.cmpge(r.min).all()
                }
            }
        })
        .collect())
}

/// The surface pieces that treetop unit `unit` generates.
pub fn unit_mesh(
    snapshot: &Snapshot<'_>,
    treetop: &Treetop,
    scene: &Scene,
    finest: u8,
    unit: usize,
) -> Result<UnitMesh> {
    let Some(key) = treetop.units.get(unit).map(|u| u.key) else {
        return Ok(UnitMesh::default());
    };
    // Every probe of the unit's dual cells lies within one finest cell of its cube.
    let mut level = LevelCut::around(snapshot, treetop, finest, key);
    match level.unit(unit)? {
        Some(values) => dual_cells_of_unit(scene, &mut level, &values.0, &values.1),
        None => Ok(UnitMesh::default()),
    }
}

/// Decimates (if asked), welds the units' pieces in unit order, and cuts at the region.
pub fn assemble(mut meshes: Vec<UnitMesh>, options: &ExtractOptions) -> Mesh {
    if let Some(ratio) = options.decimate {
        decimate_units(&mut meshes, ratio);
    }
    // Weld across units by edge identity, in unit order (deterministic).
    let mut index: HashMap<(CornerId, CornerId), u32> = HashMap::new();
    let mut positions: Vec<DVec3> = Vec::new();
    let mut normals: Vec<DVec3> = Vec::new();
    let mut triangles = Vec::new();
    for mesh in meshes {
        let map: Vec<u32> = mesh
            .vertices
            .iter()
            .map(|(edge, p, n)| match index.get(edge) {
                Some(&i) => {
                    normals[i as usize] += *n;
                    i
                }
                None => {
                    let i = positions.len() as u32;
                    index.insert(*edge, i);
                    positions.push(*p);
                    normals.push(*n);
                    i
                }
            })
            .collect();
        triangles.extend(mesh.triangles.iter().map(|t| t.map(|v| map[v as usize])));
    }
    let mut mesh = Mesh {
        positions: positions.iter().map(|p| p.as_vec3().to_array()).collect(),
        normals: normals
            .iter()
            .map(|n| n.normalize_or_zero().as_vec3().to_array())
            .collect(),
        triangles,
    };
    if let Some(r) = options.region {
        mesh = clip(&mesh, r);
    }
    mesh
}

/// Counts of a written mesh.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct MeshSummary {
    pub vertices: u64,
    pub triangles: u64,
    pub boundary_edges: u64,
    pub non_manifold_edges: u64,
}

/// The low 124 bits of a corner id: the leaf key, or for a virtual cell the key it mirrors.
const CORNER_KEY_MASK: u128 = (1 << 124) - 1;

/// Whether a surface vertex can come from no unit but the one with treetop cube `unit`.
///
/// It can if both cells at the ends of its edge are leaves (or mirrors of leaves) inside the
/// unit's cube that touch none of its faces, except faces on the root's boundary. Every dual
/// cell with that edge surrounds an octree vertex V at a corner of such a leaf; V is then inside
/// the unit's cube or on the root's boundary, so every leaf incident to V, the cell's generator
/// among them, belongs to the unit. Other vertices may be shared with other units.
fn private_to(unit: CubeKey) -> impl Fn(&VertexId) -> bool {
    let lo = unit.corner_full_resolution().map(u64::from);
    let side = full_side(unit.depth());
    let limit = 1u64 << 32;
    move |&(a, b): &VertexId| {
        [a, b].iter().all(|&id| {
            let leaf = CubeKey::from_raw(id & CORNER_KEY_MASK);
            let corner = leaf.corner_full_resolution().map(u64::from);
            let leaf_side = full_side(leaf.depth());
            (0..3).all(|axis| {
                let (u0, u1) = (lo[axis], lo[axis] + side);
                let (l0, l1) = (corner[axis], corner[axis] + leaf_side);
                u0 <= l0 && l1 <= u1 && (l0 != u0 || u0 == 0) && (l1 != u1 || u1 == limit)
            })
        })
    }
}

/// The last unit (in extraction order, which is unit index order) that can produce a vertex on
/// the edge from corner `a`: every dual cell with that edge surrounds an octree vertex V at a
/// corner of `a`'s leaf (or of the leaf a virtual cell mirrors), and is generated by a leaf
/// incident to V, so probing the 8 octants around each of the 8 corners finds every unit that
/// can generate it.
fn last_unit_around(treetop: &Treetop, a: CornerId) -> usize {
    let leaf = CubeKey::from_raw(a & CORNER_KEY_MASK);
    let corner = leaf.corner_full_resolution().map(i64::from);
    let side = full_side(leaf.depth()) as i64;
    let limit = 1i64 << 32;
    let mut last = 0;
    for v in 0..8i64 {
        let vertex = [0, 1, 2].map(|axis| corner[axis] + ((v >> axis) & 1) * side);
        for octant in 0..8i64 {
            let probe = [0, 1, 2].map(|axis| vertex[axis] - 1 + ((octant >> axis) & 1));
            if probe.iter().any(|&c| c < 0 || c >= limit) {
                continue;
            }
            let [x, y, z] = probe.map(|c| c as u32);
            last = last.max(treetop.unit_of(CubeKey::from_full_resolution(MAX_DEPTH, x, y, z)));
        }
    }
    last
}

/// Welds units' pieces into one mesh as they come, in unit order. Only vertices that a later
/// unit may also produce (seam vertices) are held, each until the last unit that can produce
/// it is done, and likewise edges between two of them: the same vertices, normals, triangles
/// and edge counts as welding everything at once, in memory bounded by the seams still open.
struct StreamingWeld<'t, W: MeshWriter> {
    writer: W,
    treetop: &'t Treetop,
    /// Open seam vertices: global index, normal summed so far, last unit that can produce it.
    seam: OpenSeam,
    /// Uses of edges between two open seam vertices (only those can span units).
    seam_edges: FastMap<(u32, u32), u32>,
    /// When each open seam vertex and edge can be retired: after this unit.
    vertex_retirements: std::collections::BTreeMap<usize, Vec<u32>>,
    edge_retirements: std::collections::BTreeMap<usize, Vec<(u32, u32)>>,
    summary: MeshSummary,
    /// Most seam vertices and seam edges open at once (reported: they are what grows with the
    /// scene's cross-section).
    pub most_open: usize,
    pub most_open_edges: usize,
}

/// An open seam vertex.
#[derive(Clone, Copy)]
struct SeamVertex {
    name: VertexId,
    /// Normal summed over the units that produced it so far.
    normal: DVec3,
    /// Global index in the mesh file.
    index: u32,
    /// The last unit that can produce it.
    last: u32,
}

/// Positions of records kept in a list elsewhere, found by the records' vertex names: 4 bytes
/// a bucket, where a map keyed by the 32-byte name takes 48 to 80 (and a table of a million or
/// more buckets doubles at once). `name_of` gives the name of the record at a position; the
/// owner keeps the table and the list in step.
#[derive(Default)]
struct NameIndex {
    table: hashbrown::HashTable<u32>,
    hasher: foldhash::fast::FixedState,
}

impl NameIndex {
    fn len(&self) -> usize {
        self.table.len()
    }

    fn entry(
        &mut self,
        name: VertexId,
        name_of: impl Fn(u32) -> Option<VertexId>,
    ) -> hashbrown::hash_table::Entry<'_, u32> {
        let (table, hasher) = (&mut self.table, &self.hasher);
        table.entry(
            hasher.hash_one(name),
            |&i| name_of(i) == Some(name),
            |&i| name_of(i).map_or(0, |name| hasher.hash_one(name)),
        )
    }

    fn find(&self, name: VertexId, name_of: impl Fn(u32) -> Option<VertexId>) -> Option<u32> {
        self.table
            .find(self.hasher.hash_one(name), |&i| name_of(i) == Some(name))
            .copied()
    }

    /// Adds `position` for a name that is not in the index.
    fn insert_new(&mut self, name: VertexId, position: u32, name_of: impl Fn(u32) -> Option<VertexId>) {
        let (table, hasher) = (&mut self.table, &self.hasher);
        table.insert_unique(hasher.hash_one(name), position, |&i| {
            name_of(i).map_or(0, |name| hasher.hash_one(name))
        });
    }

    /// Removes `position`, filed under `name`; whether it was there.
    fn remove(&mut self, name: VertexId, position: u32) -> bool {
        let found = self.table.find_entry(self.hasher.hash_one(name), |&i| i == position);
        found.map(|entry| entry.remove()).is_ok()
    }
}

/// Open seam vertices: a slab of 64-byte records, whose closed slots are reused, indexed by
/// name (on the 135 M-cube city the seams reach 884,244 vertices).
#[derive(Default)]
struct OpenSeam {
    slots: Vec<SeamVertex>,
    free: Vec<u32>,
    by_name: NameIndex,
}

impl OpenSeam {
    fn len(&self) -> usize {
        self.by_name.len()
    }

    fn get_mut(&mut self, name: &VertexId) -> Option<&mut SeamVertex> {
        let slots = &self.slots;
        let found = self
            .by_name
            .find(*name, |slot| slots.get(slot as usize).map(|open| open.name))?;
        self.slots.get_mut(found as usize)
    }

    /// Adds a vertex that is not open yet; returns its slot.
    fn insert(&mut self, vertex: SeamVertex) -> u32 {
        let slot = match self.free.pop() {
            Some(slot) => {
                if let Some(place) = self.slots.get_mut(slot as usize) {
                    *place = vertex;
                }
                slot
            }
            None => {
                self.slots.push(vertex);
                (self.slots.len() - 1) as u32
            }
        };
        let slots = &self.slots;
        self.by_name.insert_new(vertex.name, slot, |other| {
            slots.get(other as usize).map(|open| open.name)
        });
        slot
    }

    /// Closes the vertex in `slot`, returning it.
    fn remove(&mut self, slot: u32) -> Option<SeamVertex> {
        let open = self.slots.get(slot as usize).copied()?;
        if !self.by_name.remove(open.name, slot) {
            return None;
        }
        self.free.push(slot);
        Some(open)
    }
}

/// Where a streamed mesh goes: vertices in order (normals of seam vertices are fixed later,
/// when every unit sharing them is done), then triangles by global index.
trait MeshWriter {
    fn vertex(&mut self, position: DVec3, normal: DVec3) -> std::io::Result<()>;
    fn triangle(&mut self, triangle: [u32; 3]) -> std::io::Result<()>;
    /// Sets final normals of earlier vertices, given in increasing index order.
    fn fix_normals(&mut self, fixes: &[(u32, DVec3)]) -> std::io::Result<()>;
}

impl<'t, W: MeshWriter> StreamingWeld<'t, W> {
    fn new(writer: W, treetop: &'t Treetop) -> Self {
        StreamingWeld {
            writer,
            treetop,
            seam: OpenSeam::default(),
            seam_edges: FastMap::default(),
            vertex_retirements: Default::default(),
            edge_retirements: Default::default(),
            summary: MeshSummary::default(),
            most_open: 0,
            most_open_edges: 0,
        }
    }

    /// Adds unit `unit`'s piece; units must come in increasing index order.
    fn add(&mut self, unit: usize, key: CubeKey, mesh: &UnitMesh) -> std::io::Result<()> {
        let private = private_to(key);
        // Global index and, for seam vertices, the last unit that can produce them (PRIVATE
        // for the others): 8 bytes per vertex of the largest piece, not 24 with an Option.
        const PRIVATE: u32 = u32::MAX;
        let mut map: Vec<(u32, u32)> = Vec::with_capacity(mesh.vertices.len());
        for (edge, p, n) in &mesh.vertices {
            if private(edge) {
                let index = self.next_index()?;
                self.writer.vertex(*p, n.normalize_or_zero())?;
                map.push((index, PRIVATE));
                continue;
            }
            let (index, last) = match self.seam.get_mut(edge) {
                Some(open) => {
                    open.normal += *n;
                    (open.index, open.last)
                }
                None => {
                    let index = self.next_index()?;
                    self.writer.vertex(*p, DVec3::ZERO)?;
                    let last = last_unit_around(self.treetop, edge.0)
                        .min(last_unit_around(self.treetop, edge.1))
                        .max(unit);
                    let last = u32::try_from(last)
                        .ok()
                        .filter(|&last| last != PRIVATE)
                        .ok_or_else(|| std::io::Error::other("more than 2^32 - 1 treetop units"))?;
                    let slot = self.seam.insert(SeamVertex {
                        name: *edge,
                        normal: *n,
                        index,
                        last,
                    });
                    self.vertex_retirements.entry(last as usize).or_default().push(slot);
                    (index, last)
                }
            };
            map.push((index, last));
        }
        self.most_open = self.most_open.max(self.seam.len());
        let mut local_edges: FastMap<(u32, u32), u32> = FastMap::default();
        for t in &mesh.triangles {
            let [Some(a), Some(b), Some(c)] = t.map(|v| map.get(v as usize).copied()) else {
                continue;
            };
            self.writer.triangle([a.0, b.0, c.0])?;
            self.summary.triangles += 1;
            for (x, y) in [(a, b), (b, c), (c, a)] {
                let edge = (x.0.min(y.0), x.0.max(y.0));
                match (x.1, y.1) {
                    (lx, ly) if lx != PRIVATE && ly != PRIVATE => {
                        let uses = self.seam_edges.entry(edge).or_insert(0);
                        // A unit uses the edge only if it produces both ends, and no unit after
                        // the earlier of their last units produces both.
                        if *uses == 0 {
                            self.edge_retirements.entry(lx.min(ly) as usize).or_default().push(edge);
                        }
                        *uses += 1;
                    }
                    _ => *local_edges.entry(edge).or_insert(0) += 1,
                }
            }
        }
        self.count_edges(local_edges.values());
        self.most_open_edges = self.most_open_edges.max(self.seam_edges.len());
        self.retire_through(unit)
    }

    /// Retires every seam vertex and edge that no unit after `unit` can produce.
    fn retire_through(&mut self, unit: usize) -> std::io::Result<()> {
        let later = self.vertex_retirements.split_off(&(unit + 1));
        let due = std::mem::replace(&mut self.vertex_retirements, later);
        let mut fixes: Vec<(u32, DVec3)> = due
            .into_values()
            .flatten()
            .filter_map(|slot| self.seam.remove(slot))
            .map(|open| (open.index, open.normal.normalize_or_zero()))
            .collect();
        fixes.sort_by_key(|(index, _)| *index);
        self.writer.fix_normals(&fixes)?;
        let later = self.edge_retirements.split_off(&(unit + 1));
        let due = std::mem::replace(&mut self.edge_retirements, later);
        let uses: Vec<u32> = due
            .into_values()
            .flatten()
            .filter_map(|edge| self.seam_edges.remove(&edge))
            .collect();
        self.count_edges(uses.iter());
        Ok(())
    }

    fn next_index(&mut self) -> std::io::Result<u32> {
        let index = u32::try_from(self.summary.vertices)
            .map_err(|_| std::io::Error::other("more than 2^32 vertices: the PLY indices would overflow"))?;
        self.summary.vertices += 1;
        Ok(index)
    }

    fn count_edges<'a>(&mut self, uses: impl Iterator<Item = &'a u32>) {
        for &count in uses {
            self.summary.boundary_edges += u64::from(count == 1);
            self.summary.non_manifold_edges += u64::from(count > 2);
        }
    }

    fn finish(mut self) -> std::io::Result<(W, MeshSummary)> {
        self.retire_through(usize::MAX - 1)?;
        Ok((self.writer, self.summary))
    }
}

/// Writes a mesh file in two passes over temporary files beside it: fixed-size vertex records
/// (so that normals can be fixed in place) and face records, joined under the header at the end.
struct MeshFile {
    path: std::path::PathBuf,
    vertices_path: std::path::PathBuf,
    faces_path: std::path::PathBuf,
    vertices: std::io::BufWriter<std::fs::File>,
    faces: std::io::BufWriter<std::fs::File>,
}

/// Bytes of one vertex record: position and normal as little-endian f32.
const VERTEX_RECORD: u64 = 6 * std::mem::size_of::<f32>() as u64;
/// Bytes of one face record in binary PLY: the count byte 3, then three u32 indices.
const FACE_RECORD: usize = 1 + 3 * std::mem::size_of::<u32>();

impl MeshFile {
    fn create(path: &Path) -> std::io::Result<MeshFile> {
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let beside = |suffix: &str| path.with_file_name(format!(".{name}.{suffix}.tmp"));
        let (vertices_path, faces_path) = (beside("vertices"), beside("faces"));
        let open = |p: &Path| -> std::io::Result<std::io::BufWriter<std::fs::File>> {
            Ok(std::io::BufWriter::new(
                std::fs::OpenOptions::new()
                    .read(true)
                    .write(true)
                    .create(true)
                    .truncate(true)
                    .open(p)?,
            ))
        };
        Ok(MeshFile {
            path: path.to_path_buf(),
            vertices: open(&vertices_path)?,
            faces: open(&faces_path)?,
            vertices_path,
            faces_path,
        })
    }

    /// Joins the parts into the mesh file (PLY, or OBJ by extension) and removes them.
    fn finish(self, summary: &MeshSummary) -> std::io::Result<()> {
        use std::io::{Read, Seek, SeekFrom};
        let mut vertices = self.vertices.into_inner().map_err(|e| e.into_error())?;
        let mut faces = self.faces.into_inner().map_err(|e| e.into_error())?;
        vertices.seek(SeekFrom::Start(0))?;
        faces.seek(SeekFrom::Start(0))?;
        let mut out = std::io::BufWriter::new(std::fs::File::create(&self.path)?);
        let is_obj = self.path.extension().is_some_and(|e| e.eq_ignore_ascii_case("obj"));
        if is_obj {
            let mut reader = std::io::BufReader::new(vertices);
            let mut record = [0u8; VERTEX_RECORD as usize];
            for _ in 0..summary.vertices {
                reader.read_exact(&mut record)?;
                let f: Vec<f32> = record
                    .chunks_exact(4)
                    .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                    .collect();
                writeln!(out, "v {} {} {}", f[0], f[1], f[2])?;
                writeln!(out, "vn {} {} {}", f[3], f[4], f[5])?;
            }
            let mut reader = std::io::BufReader::new(faces);
            let mut record = [0u8; FACE_RECORD];
            for _ in 0..summary.triangles {
                reader.read_exact(&mut record)?;
                let v: Vec<u32> = record[1..]
                    .chunks_exact(4)
                    .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) + 1)
                    .collect();
                writeln!(out, "f {0}//{0} {1}//{1} {2}//{2}", v[0], v[1], v[2])?;
            }
        } else {
            write!(out, "{}", ply_header(summary.vertices, summary.triangles))?;
            std::io::copy(&mut vertices, &mut out)?;
            std::io::copy(&mut faces, &mut out)?;
        }
        out.flush()?;
        std::fs::remove_file(&self.vertices_path)?;
        std::fs::remove_file(&self.faces_path)?;
        Ok(())
    }

    fn abandon(self) {
        drop(self.vertices);
        drop(self.faces);
        let _ = std::fs::remove_file(&self.vertices_path);
        let _ = std::fs::remove_file(&self.faces_path);
    }
}

impl MeshWriter for MeshFile {
    fn vertex(&mut self, position: DVec3, normal: DVec3) -> std::io::Result<()> {
        for v in position.as_vec3().to_array().iter().chain(&normal.as_vec3().to_array()) {
            self.vertices.write_all(&v.to_le_bytes())?;
        }
        Ok(())
    }

    fn triangle(&mut self, triangle: [u32; 3]) -> std::io::Result<()> {
        self.faces.write_all(&[3u8])?;
        for v in triangle {
            self.faces.write_all(&v.to_le_bytes())?;
        }
        Ok(())
    }

    fn fix_normals(&mut self, fixes: &[(u32, DVec3)]) -> std::io::Result<()> {
        use std::io::{Seek, SeekFrom};
        if fixes.is_empty() {
            return Ok(());
        }
        self.vertices.flush()?;
        let file = self.vertices.get_mut();
        for (index, normal) in fixes {
            file.seek(SeekFrom::Start(u64::from(*index) * VERTEX_RECORD + VERTEX_RECORD / 2))?;
            let mut bytes = [0u8; VERTEX_RECORD as usize / 2];
            for (slot, v) in bytes.chunks_exact_mut(4).zip(normal.as_vec3().to_array()) {
                slot.copy_from_slice(&v.to_le_bytes());
            }
            file.write_all(&bytes)?;
        }
        file.seek(SeekFrom::End(0))?;
        Ok(())
    }
}

/// Streams pieces (unit index, treetop cube, mesh), in increasing unit order, into a mesh file
/// without region or decimation; memory holds one piece at a time plus the open seams.
pub fn stream_to_file(
    pieces: impl Iterator<Item = Result<(usize, CubeKey, UnitMesh)>>,
    treetop: &Treetop,
    path: &Path,
) -> Result<MeshSummary> {
    let io = |source: std::io::Error| StoreError::Io {
        action: "write mesh",
        path: path.to_path_buf(),
        source,
    };
    let file = MeshFile::create(path).map_err(io)?;
    let mut weld = StreamingWeld::new(file, treetop);
    let written = || -> Result<()> {
        for piece in pieces {
            let (unit, key, mesh) = piece?;
            weld.add(unit, key, &mesh).map_err(io)?;
        }
        Ok(())
    };
    if let Err(e) = written() {
        weld.writer.abandon();
        return Err(e);
    }
    let (most_open, most_open_edges) = (weld.most_open, weld.most_open_edges);
    let (file, summary) = weld.finish().map_err(io)?;
    file.finish(&summary).map_err(io)?;
    tracing::info!("extract: at most {most_open} seam vertices and {most_open_edges} seam edges open at once");
    Ok(summary)
}

/// Writes a mesh assembled in memory and counts it like the streaming path does.
pub fn write_assembled(path: &Path, mesh: &Mesh) -> Result<MeshSummary> {
    write_mesh(path, mesh).map_err(crate::store::io_error("write mesh", path))?;
    let (boundary, non_manifold) = edge_defects(mesh);
    Ok(MeshSummary {
        vertices: mesh.positions.len() as u64,
        triangles: mesh.triangles.len() as u64,
        boundary_edges: boundary as u64,
        non_manifold_edges: non_manifold as u64,
    })
}

/// Extracts the surface into a mesh file. Without a region or decimation the pieces are
/// streamed: one worker per thread computes units' pieces, at most twice the thread count of
/// them at once, while the calling thread welds them in unit order, so memory does not grow
/// with the surface; with either, the mesh is assembled in memory first.
pub fn extract_to_file(
    snapshot: &Snapshot<'_>,
    scene: &Scene,
    finest: u8,
    options: &ExtractOptions,
    path: &Path,
) -> Result<MeshSummary> {
    if options.region.is_some() || options.decimate.is_some() {
        return write_assembled(path, &extract(snapshot, scene, finest, options)?);
    }
    let units = extract_units(snapshot, scene, finest, None)?;
    let treetop = Treetop::of(snapshot)?;
    let piece = |unit: usize| -> Result<(usize, CubeKey, UnitMesh)> {
        let key = treetop
            .units
            .get(unit)
            .map(|u| u.key)
            .ok_or_else(|| StoreError::Stage {
                stage: "extract".into(),
                unit: unit.to_string(),
                message: "no such treetop unit".into(),
            })?;
        Ok((unit, key, unit_mesh(snapshot, &treetop, scene, finest, unit)?))
    };
    let threads = rayon::current_num_threads().max(1);
    in_order_while_computing(&units, threads, 2 * threads, piece, |pieces| {
        stream_to_file(pieces, &treetop, path)
    })
}

/// Hands `consume` the results of `compute(item)` for every item, as an iterator in item
/// order, while `threads` workers compute the next ones: at most `window` results exist at
/// once (the one being consumed included), so memory stays bounded, and consuming overlaps
/// computing. The order does not depend on the workers' timing.
fn in_order_while_computing<I: Copy + Send + Sync, T: Send, R>(
    items: &[I],
    threads: usize,
    window: usize,
    compute: impl Fn(I) -> Result<T> + Sync,
    consume: impl FnOnce(&mut dyn Iterator<Item = Result<T>>) -> R,
) -> R {
    let window = window.max(2);
    let shared = InOrder {
        state: std::sync::Mutex::new(InOrderState {
            next_item: 0,
            taken: 0,
            done: std::collections::BTreeMap::new(),
            stop: false,
            worker_panicked: false,
        }),
        changed: std::sync::Condvar::new(),
    };
    std::thread::scope(|scope| {
        for _ in 0..threads {
            scope.spawn(|| {
                let _guard = PanicFlag(&shared);
                while let Some(index) = shared.claim(items.len(), window) {
                    let Some(&item) = items.get(index) else {
                        break;
                    };
                    let result = compute(item);
                    shared.lock().done.insert(index, result);
                    shared.changed.notify_all();
                }
            });
        }
        let mut pieces = InOrderPieces {
            shared: &shared,
            count: items.len(),
        };
        consume(&mut pieces)
    })
}

struct InOrder<T> {
    state: std::sync::Mutex<InOrderState<T>>,
    changed: std::sync::Condvar,
}

struct InOrderState<T> {
    /// The next item a worker may claim.
    next_item: usize,
    /// Pieces handed to the consumer so far; piece `taken - 1` may still be in use.
    taken: usize,
    done: std::collections::BTreeMap<usize, Result<T>>,
    stop: bool,
    worker_panicked: bool,
}

impl<T> InOrder<T> {
    /// The state; a worker that panicked holds no lock across its work, so a poisoned lock
    /// still holds consistent state.
    fn lock(&self) -> std::sync::MutexGuard<'_, InOrderState<T>> {
        self.state.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
    }

    /// The next item for a worker, once it is within `window` of the consumer; `None` when
    /// all are claimed or the consumer has stopped.
    fn claim(&self, count: usize, window: usize) -> Option<usize> {
        let mut state = self.lock();
        loop {
            if state.stop || state.next_item >= count {
                return None;
            }
            // Pieces taken - 1 (in use) up to next_item must number at most `window`.
            if state.next_item + 1 < state.taken + window {
                state.next_item += 1;
                return Some(state.next_item - 1);
            }
            state = self
                .changed
                .wait(state)
                .unwrap_or_else(std::sync::PoisonError::into_inner);
        }
    }
}

/// Sets the worker-panicked flag when a worker unwinds, so the consumer does not wait forever.
struct PanicFlag<'a, T>(&'a InOrder<T>);

impl<T> Drop for PanicFlag<'_, T> {
    fn drop(&mut self) {
        if std::thread::panicking() {
            let mut state = self.0.lock();
            state.worker_panicked = true;
            state.stop = true;
            drop(state);
            self.0.changed.notify_all();
        }
    }
}

/// The consumer's side: pieces in item order. Dropping it stops the workers.
struct InOrderPieces<'a, T> {
    shared: &'a InOrder<T>,
    count: usize,
}

impl<T> Iterator for InOrderPieces<'_, T> {
    type Item = Result<T>;

    fn next(&mut self) -> Option<Result<T>> {
        let mut state = self.shared.lock();
        loop {
            let taken = state.taken;
            if let Some(piece) = state.done.remove(&taken) {
                state.taken += 1;
                drop(state);
                self.shared.changed.notify_all();
                return Some(piece);
            }
            if state.worker_panicked {
                return Some(Err(StoreError::Stage {
                    stage: "extract".into(),
                    unit: taken.to_string(),
                    message: "a worker thread panicked".into(),
                }));
            }
            if taken >= self.count {
                return None;
            }
            state = self
                .shared
                .changed
                .wait(state)
                .unwrap_or_else(std::sync::PoisonError::into_inner);
        }
    }
}

impl<T> Drop for InOrderPieces<'_, T> {
    fn drop(&mut self) {
        self.shared.lock().stop = true;
        self.shared.changed.notify_all();
    }
}

/// Cuts a mesh at a box: triangles are clipped against its six planes (new vertices on the box
/// faces are welded by position).
pub fn clip(mesh: &Mesh, region: Region) -> Mesh {
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

/// Edge statistics: (boundary edges, non-manifold edges).
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

fn ply_header(vertices: u64, triangles: u64) -> String {
    format!(
        "ply\nformat binary_little_endian 1.0\ncomment octstore\nelement vertex {vertices}\nproperty float x\nproperty float y\nproperty float z\nproperty float nx\nproperty float ny\nproperty float nz\nelement face {triangles}\nproperty list uchar uint vertex_indices\nend_header\n"
    )
}

/// Writes binary little-endian PLY, or OBJ when the path ends in `.obj`.
pub fn write_mesh(path: &Path, mesh: &Mesh) -> std::io::Result<()> {
    let file = std::fs::File::create(path)?;
    let mut out = std::io::BufWriter::new(file);
    let is_obj = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("obj"));
    if is_obj {
        for (p, n) in mesh.positions.iter().zip(&mesh.normals) {
            writeln!(out, "v {} {} {}", p[0], p[1], p[2])?;
            writeln!(out, "vn {} {} {}", n[0], n[1], n[2])?;
        }
        for t in &mesh.triangles {
            writeln!(out, "f {0}//{0} {1}//{1} {2}//{2}", t[0] + 1, t[1] + 1, t[2] + 1)?;
        }
    } else {
        write!(
            out,
            "{}",
            ply_header(mesh.positions.len() as u64, mesh.triangles.len() as u64)
        )?;
        for (p, n) in mesh.positions.iter().zip(&mesh.normals) {
            for v in p.iter().chain(n) {
                out.write_all(&v.to_le_bytes())?;
            }
        }
        for t in &mesh.triangles {
            out.write_all(&[3u8])?;
            for v in t {
                out.write_all(&v.to_le_bytes())?;
            }
        }
    }
    out.flush()
}

/// Reads a mesh written by [`write_mesh`] (binary little-endian PLY with float positions and
/// normals, uchar/uint face lists).
pub fn read_ply(path: &Path) -> Result<Mesh, String> {
    let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let end = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .ok_or_else(|| format!("{}: not a PLY file (no end_header)", path.display()))?
        + 11;
    let header = String::from_utf8_lossy(&bytes[..end]).into_owned();
    if !header.contains("format binary_little_endian") || !header.contains("property float nx") {
        return Err(format!(
            "{}: only octstore's binary PLY (x y z nx ny nz) is read here",
            path.display()
        ));
    }
    let count = |what: &str| -> Result<usize, String> {
        header
            .split(what)
            .nth(1)
            .and_then(|s| s.split_whitespace().next())
            .and_then(|n| n.parse().ok())
            .ok_or_else(|| format!("{}: no '{what}' in the header", path.display()))
    };
    let (nv, nf) = (count("element vertex ")?, count("element face ")?);
    let float = |o: usize| -> Result<f32, String> {
        bytes
            .get(o..o + 4)
            .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
            .ok_or_else(|| format!("{}: truncated", path.display()))
    };
    let mut mesh = Mesh::default();
    for i in 0..nv {
        let o = end + 24 * i;
        mesh.positions.push([float(o)?, float(o + 4)?, float(o + 8)?]);
        mesh.normals.push([float(o + 12)?, float(o + 16)?, float(o + 20)?]);
    }
    let faces = end + 24 * nv;
    for i in 0..nf {
        let o = faces + 13 * i;
        if bytes.get(o) != Some(&3) {
            return Err(format!("{}: face {i} is not a triangle", path.display()));
        }
        let index = |k: usize| -> Result<u32, String> {
            let v = float(o + 1 + 4 * k)?.to_bits();
            if v as usize >= nv {
                return Err(format!("{}: face {i} refers to vertex {v} of {nv}", path.display()));
            }
            Ok(v)
        };
        mesh.triangles.push([index(0)?, index(1)?, index(2)?]);
    }
    Ok(mesh)
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicUsize, Ordering};

    use super::*;

    fn random(seed: &mut u64) -> u64 {
        *seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        *seed >> 33
    }

    #[test]
    fn galloping_search_agrees_with_binary_search_from_every_start() {
        let mut seed = 7;
        for len in [0usize, 1, 2, 3, 17, 300] {
            // Sorted keys at mixed depths; probes on, between, below and above them.
            let mut keys: Vec<CubeKey> = (0..len)
                .map(|_| {
                    let depth = 1 + (random(&mut seed) % 12) as u8;
                    let mask = (1u64 << depth) as u32 - 1;
                    let mut c = || random(&mut seed) as u32 & mask;
                    CubeKey::new(depth, c(), c(), c())
                })
                .collect();
            keys.sort();
            keys.dedup();
            let cells: Vec<CubeKey> = (0..64)
                .map(|_| {
                    let mut c = || (random(&mut seed) as u32) << 1;
                    CubeKey::new(MAX_DEPTH, c(), c(), c())
                })
                .collect();
            for probe in keys.iter().copied().chain(cells) {
                let expected = keys.partition_point(|k| *k <= probe);
                for near in 0..keys.len() + 2 {
                    assert_eq!(
                        partition_point_near(&keys, near, probe),
                        expected,
                        "{len} keys, from {near}, probe {probe:?}"
                    );
                }
            }
        }
    }

    /// Counts the pieces alive at once.
    struct Piece<'a> {
        item: usize,
        alive: &'a AtomicUsize,
    }

    impl Drop for Piece<'_> {
        fn drop(&mut self) {
            self.alive.fetch_sub(1, Ordering::SeqCst);
        }
    }

    #[test]
    fn open_seam_finds_what_is_open_and_reuses_closed_slots() {
        let name = |i: u128| (i, i * 7 + 1);
        let vertex = |i: u128| SeamVertex {
            name: name(i),
            normal: DVec3::splat(i as f64),
            index: i as u32,
            last: 0,
        };
        let mut seam = OpenSeam::default();
        let mut slots = std::collections::HashMap::new();
        let mut seed = 11u64;
        for round in 0..20_000u128 {
            let i = u128::from(random(&mut seed) % 3000);
            match seam.get_mut(&name(i)) {
                Some(open) => {
                    assert_eq!(open.index, i as u32, "round {round}");
                    let slot = slots.remove(&i).expect("open in the model");
                    let closed = seam.remove(slot).expect("open slot");
                    assert_eq!(closed.name, name(i));
                    assert!(seam.get_mut(&name(i)).is_none());
                }
                None => {
                    assert!(!slots.contains_key(&i), "round {round}: {i} lost");
                    slots.insert(i, seam.insert(vertex(i)));
                }
            }
            assert_eq!(seam.len(), slots.len());
        }
        // Slots of closed vertices are reused: never more slots than were open at once.
        assert!(seam.slots.len() <= 3000);
        assert!(seam.remove(u32::MAX).is_none());
    }

    #[test]
    fn pieces_come_in_item_order_and_at_most_a_window_exist_at_once() {
        let items: Vec<usize> = (0..300).collect();
        let (alive, most) = (AtomicUsize::new(0), AtomicUsize::new(0));
        let window = 4;
        let compute = |item: usize| -> Result<Piece<'_>> {
            let now = alive.fetch_add(1, Ordering::SeqCst) + 1;
            most.fetch_max(now, Ordering::SeqCst);
            // Uneven work, so pieces finish out of order.
            std::thread::sleep(std::time::Duration::from_micros((item * 7919 % 13) as u64 * 50));
            Ok(Piece { item, alive: &alive })
        };
        let seen = in_order_while_computing(&items, 3, window, compute, |pieces| {
            pieces.map(|piece| piece.map(|p| p.item)).collect::<Result<Vec<_>>>()
        })
        .expect("no piece fails");
        assert_eq!(seen, items);
        let most = most.load(Ordering::SeqCst);
        assert!(most <= window, "{most} pieces existed at once, window {window}");
        assert_eq!(alive.load(Ordering::SeqCst), 0);
    }

    #[test]
    fn a_failed_piece_ends_the_stream_with_its_error() {
        let items: Vec<usize> = (0..100).collect();
        let compute = |item: usize| -> Result<usize> {
            if item == 37 {
                return Err(StoreError::Stage {
                    stage: "extract".into(),
                    unit: item.to_string(),
                    message: "bad unit".into(),
                });
            }
            Ok(item)
        };
        let (before, error) = in_order_while_computing(&items, 2, 4, compute, |pieces| {
            let mut before = Vec::new();
            for piece in pieces {
                match piece {
                    Ok(item) => before.push(item),
                    Err(error) => return (before, Some(error.to_string())),
                }
            }
            (before, None)
        });
        assert_eq!(before, (0..37).collect::<Vec<_>>());
        assert!(error.is_some_and(|e| e.contains("bad unit")));
    }
}
