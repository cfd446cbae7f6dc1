//! Stray islands: pieces of surface of a few triangles that touch nothing else, what noise and
//! outliers leave behind where the observed-surface test keeps a tetrahedron or two apart from
//! the surface (a lone triangle floating beside a noisy object). A unit drops the islands that
//! lie wholly inside it: every vertex private to it, so no other unit adds to them and the
//! decision is the same whatever order units run in. An island that reaches a seam is kept (its
//! other part, in another unit, is not seen here).

use crate::mesh::UnitMesh;

/// Islands of fewer triangles than this are dropped: about two cubes' worth of dual-cell
/// surface. The detached pieces of real thin parts (a claw cut off by the resolution) measured
/// 20 triangles and more on the dragon of BENCHMARKS.md, the strays 1 to 12.
pub(super) const ISLAND_TRIANGLES: usize = 16;

fn root(parent: &mut [u32], mut v: u32) -> u32 {
    while let Some(&p) = parent.get(v as usize) {
        if p == v {
            break;
        }
        // Path halving.
        let grand = parent.get(p as usize).copied().unwrap_or(p);
        if let Some(slot) = parent.get_mut(v as usize) {
            *slot = grand;
        }
        v = grand;
    }
    v
}

/// Joins the sets of `a` and `b` under the smaller root (deterministic).
fn union(parent: &mut [u32], a: u32, b: u32) {
    let (ra, rb) = (root(parent, a), root(parent, b));
    if ra != rb {
        let (low, high) = if ra < rb { (ra, rb) } else { (rb, ra) };
        if let Some(slot) = parent.get_mut(high as usize) {
            *slot = low;
        }
    }
}

/// Drops from `mesh` the islands (triangles joined through shared vertices) of fewer than
/// [`ISLAND_TRIANGLES`] triangles whose vertices are all `private`, and the vertices only they
/// used; the other vertices keep their order. Returns the triangles dropped.
pub(super) fn drop_private_islands(mesh: &mut UnitMesh, private: &[bool]) -> usize {
    let n = mesh.vertices.len();
    let mut parent: Vec<u32> = (0..n as u32).collect();
    for t in &mesh.triangles {
        union(&mut parent, t[0], t[1]);
        union(&mut parent, t[0], t[2]);
    }
    // Per island (by root): its triangles, and whether a vertex of it is on a seam.
    let mut triangles = vec![0usize; n];
    let mut on_seam = vec![false; n];
    for t in &mesh.triangles {
        let r = root(&mut parent, t[0]) as usize;
        if let Some(count) = triangles.get_mut(r) {
            *count += 1;
        }
        if t.iter().any(|&v| !private.get(v as usize).copied().unwrap_or(false))
            && let Some(flag) = on_seam.get_mut(r)
        {
            *flag = true;
        }
    }
    let stray = |r: usize| triangles.get(r).is_some_and(|&c| c < ISLAND_TRIANGLES) && on_seam.get(r) == Some(&false);
    let before = mesh.triangles.len();
    let kept: Vec<[u32; 3]> = mesh
        .triangles
        .iter()
        .copied()
        .filter(|t| !stray(root(&mut parent, t[0]) as usize))
        .collect();
    let dropped = before - kept.len();
    if dropped == 0 {
        return 0;
    }
    // Keep every vertex a kept triangle uses and every seam vertex; renumber in order.
    let mut used = vec![false; n];
    for t in &kept {
        for &v in t {
            if let Some(flag) = used.get_mut(v as usize) {
                *flag = true;
            }
        }
    }
    let mut renumber = vec![u32::MAX; n];
    let mut next = 0u32;
    let mut vertices = Vec::with_capacity(n);
    for (i, vertex) in mesh.vertices.iter().enumerate() {
        let keep = used.get(i).copied().unwrap_or(false) || !private.get(i).copied().unwrap_or(false);
        if keep {
            if let Some(slot) = renumber.get_mut(i) {
                *slot = next;
            }
            next += 1;
            vertices.push(*vertex);
        }
    }
    mesh.vertices = vertices;
    mesh.triangles = kept
        .into_iter()
        .map(|t| t.map(|v| renumber.get(v as usize).copied().unwrap_or(u32::MAX)))
        .collect();
    dropped
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec3;

    fn mesh_of(triangles: &[[u32; 3]], vertices: u32) -> UnitMesh {
        UnitMesh {
            vertices: (0..vertices)
                .map(|i| (Default::default(), DVec3::splat(f64::from(i)), DVec3::Z))
                .collect(),
            triangles: triangles.to_vec(),
            seam_moves: Vec::new(),
        }
    }

    /// A lone private triangle goes with its vertices; a lone triangle on a seam and a large
    /// private fan stay; the kept vertices keep their order and their triangles' corners.
    #[test]
    fn private_strays_go_and_the_rest_is_renumbered() {
        // Vertices 0..20: a fan of 18 triangles around vertex 0 (1..=19), a lone triangle
        // 20, 21, 22 (private), a lone triangle 23, 24, 25 (25 on a seam).
        let mut triangles: Vec<[u32; 3]> = (1..19).map(|i| [0, i, i + 1]).collect();
        triangles.push([20, 21, 22]);
        triangles.push([23, 24, 25]);
        let mut mesh = mesh_of(&triangles, 26);
        let mut private = vec![true; 26];
        private[25] = false;
        let positions_before: Vec<[u32; 3]> = vec![[23, 24, 25]];
        assert_eq!(drop_private_islands(&mut mesh, &private), 1);
        assert_eq!(mesh.triangles.len(), 19);
        assert_eq!(mesh.vertices.len(), 23);
        // The seam triangle's corners are the same points as before.
        let last = mesh.triangles.last().copied().unwrap();
        let points: Vec<f64> = last.iter().map(|&v| mesh.vertices[v as usize].1.x).collect();
        let expected: Vec<f64> = positions_before[0].iter().map(|&v| f64::from(v)).collect();
        assert_eq!(points, expected);
    }
}
