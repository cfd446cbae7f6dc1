//! Decimation of units' pieces with meshopt, never moving a vertex that another unit shares.

use std::collections::HashMap;

use glam::DVec3;
use rayon::prelude::*;

use super::{UnitMesh, VertexId};

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
pub fn decimate_units(meshes: &mut [UnitMesh], ratio: f32) {
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
    // Seam vertices are locked, so every one with a share survives; only its index changes.
    mesh.seam_moves
        .retain_mut(|share| match remap.get(share.vertex as usize) {
            Some(&index) if index != u32::MAX => {
                share.vertex = index;
                true
            }
            _ => false,
        });
}
