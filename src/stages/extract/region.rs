//! Streaming the cut at `--region`: the welded (and simplified) mesh, as it is written, clipped
//! against the box triangle by triangle ([`crate::mesh::clip_triangle`]) and passed on.
//!
//! A triangle is clipped once its three vertices have their final positions; until then it
//! waits on one of them. Cut points are welded by the input edge they lie on and their
//! position, and forgotten once no later triangle can have that edge. So memory holds the
//! vertices still open (those the weld has not retired or a simplification batch still holds),
//! the triangles waiting on them, and the edges around them: the same bound as the weld's and
//! the simplifier's, not the region's mesh. Counts of boundary and non-manifold edges are the
//! output's, counted when both ends can get no more triangles.

use glam::{DVec3, Vec3};

use super::weld::MeshWriter;
use super::{FastMap, MeshSummary};
use crate::format::BoundingBox;
use crate::mesh::{Corner, clip_triangle};

/// A vertex given to the cut and still open.
struct Open {
    position: Vec3,
    normal: DVec3,
    /// Its position and normal are final.
    fixed: bool,
    /// No triangle will name it any more.
    done: bool,
    /// Triangles naming it that wait (on it or on another vertex).
    waiting: u32,
    /// Triangles that wait on this vertex to be fixed.
    waiters: Vec<[u32; 3]>,
    /// Its index in the output, once written.
    written: Option<u32>,
}

/// A polygon corner's output vertex: written, or to be written from the corner of this index.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Slot {
    Written(u32),
    New(usize),
}

/// What keeps an output vertex open: later triangles may name it while these input vertices are.
#[derive(Clone, Copy)]
enum Owner {
    Vertex(u32),
    OnEdge(u32, u32),
}

/// A [`MeshWriter`] that passes on the part of what it is given inside a box (module
/// documentation), counting the output itself.
pub(super) struct RegionWriter<W: MeshWriter> {
    pub(super) inner: W,
    lo: Vec3,
    hi: Vec3,
    /// Index the next input vertex gets.
    incoming: u32,
    open: FastMap<u32, Open>,
    /// Output index of each cut point by the input edge it lies on and its position's bits.
    cuts: FastMap<(u32, u32, [u32; 3]), u32>,
    /// Output vertices that later triangles may still name, with what keeps them open.
    owners: FastMap<u32, Owner>,
    /// Uses of output edges so far; counted once an end is closed.
    edges: FastMap<(u32, u32), u32>,
    /// Input vertices closed since the last sweep of `cuts`, `owners` and `edges`.
    closed_since_sweep: usize,
    summary: MeshSummary,
    /// Most input vertices and output edges held open at once (reported).
    pub(super) most_open: (usize, usize),
}

/// Input vertices closed between two sweeps, at least: a sweep walks every open cut, owner and
/// edge, so it runs once as many vertices closed as a quarter of the open edges (amortised
/// constant work per vertex).
const SWEEP_AFTER_LEAST: usize = 1 << 12;

impl<W: MeshWriter> RegionWriter<W> {
    pub(super) fn new(inner: W, region: BoundingBox) -> Self {
        RegionWriter {
            inner,
            lo: region.min.as_vec3(),
            hi: region.max.as_vec3(),
            incoming: 0,
            open: FastMap::default(),
            cuts: FastMap::default(),
            owners: FastMap::default(),
            edges: FastMap::default(),
            closed_since_sweep: 0,
            summary: MeshSummary::default(),
            most_open: (0, 0),
        }
    }

    /// Counts every edge left and returns the inner writer and the output's counts (an error
    /// if a triangle still waits: every vertex must be fixed by now).
    pub(super) fn finish(mut self) -> (W, std::io::Result<MeshSummary>) {
        let checked = self.check_nothing_waits();
        self.open.clear();
        self.sweep();
        (self.inner, checked.map(|()| self.summary))
    }

    fn check_nothing_waits(&self) -> std::io::Result<()> {
        let mut waiting: Vec<u32> = self
            .open
            .iter()
            .filter(|(_, v)| !v.waiters.is_empty())
            .map(|(&i, _)| i)
            .collect();
        waiting.sort_unstable();
        for index in waiting {
            if self.open.get(&index).is_some_and(|v| !v.fixed) {
                return Err(std::io::Error::other(
                    "region: triangles left with vertices the weld never settled",
                ));
            }
        }
        Ok(())
    }

    /// Writes triangle `triangle` (input indices, every vertex fixed) as far as it lies inside.
    fn cut(&mut self, triangle: [u32; 3]) -> std::io::Result<()> {
        let corner = |open: &FastMap<u32, Open>, i: u32| {
            let v = open.get(&i);
            (
                i,
                v.map_or(Vec3::ZERO, |v| v.position),
                v.map_or(Vec3::ZERO, |v| v.normal.as_vec3()),
            )
        };
        let polygon = clip_triangle(triangle.map(|i| corner(&self.open, i)), self.lo, self.hi);
        if polygon.len() < 3 {
            return Ok(());
        }
        // Each corner's output vertex if it has one already; a corner at the same point as an
        // earlier corner of this polygon (a cut exactly through another) is that corner, as
        // welding by position makes it.
        let bits = |p: Vec3| p.to_array().map(f32::to_bits);
        let mut slots: Vec<Slot> = Vec::with_capacity(polygon.len());
        for (k, &(position, _, what)) in polygon.iter().enumerate() {
            let earlier = polygon.iter().take(k).position(|c| bits(c.0) == bits(position));
            slots.push(match earlier.and_then(|j| slots.get(j).copied()) {
                Some(slot) => slot,
                None => self.known(position, what).map_or(Slot::New(k), Slot::Written),
            });
        }
        // Fan triangles with three distinct corners; a vertex is written when a triangle first
        // uses it, so none is written unused.
        for j in 1..polygon.len().saturating_sub(1) {
            let corners = [0, j, j + 1].map(|c| slots.get(c).copied().unwrap_or(Slot::New(c)));
            if corners[0] == corners[1] || corners[1] == corners[2] || corners[0] == corners[2] {
                continue;
            }
            let mut t = [0u32; 3];
            for (slot_index, corner) in [0, j, j + 1].into_iter().zip(&mut t) {
                let slot = slots.get(slot_index).copied().unwrap_or(Slot::New(slot_index));
                *corner = match slot {
                    Slot::Written(id) => id,
                    Slot::New(k) => {
                        let Some(&(position, normal, what)) = polygon.get(k) else {
                            continue;
                        };
                        let id = self.write_vertex(position, normal, what)?;
                        for s in slots.iter_mut().filter(|s| **s == Slot::New(k)) {
                            *s = Slot::Written(id);
                        }
                        id
                    }
                };
            }
            self.inner.triangle(t)?;
            self.summary.triangles += 1;
            for (x, y) in [(t[0], t[1]), (t[1], t[2]), (t[2], t[0])] {
                *self.edges.entry((x.min(y), x.max(y))).or_insert(0) += 1;
            }
        }
        Ok(())
    }

    /// The output vertex of a polygon corner, if an earlier triangle wrote it.
    fn known(&self, position: Vec3, what: Corner) -> Option<u32> {
        match what {
            Corner::Vertex(i) => self.open.get(&i).and_then(|v| v.written),
            Corner::OnEdge(a, b) => self.cuts.get(&(a, b, position.to_array().map(f32::to_bits))).copied(),
            Corner::Inside => None,
        }
    }

    /// Writes a polygon corner's vertex and remembers it for the triangles that may share it.
    fn write_vertex(&mut self, position: Vec3, normal: Vec3, what: Corner) -> std::io::Result<u32> {
        let index = u32::try_from(self.summary.vertices)
            .map_err(|_| std::io::Error::other("more than 2^32 vertices: the PLY indices would overflow"))?;
        let normal = match what {
            Corner::Vertex(i) => self.open.get(&i).map_or(DVec3::ZERO, |v| v.normal),
            _ => normal.as_dvec3(),
        };
        self.inner
            .vertex(position.as_dvec3(), normal.normalize_or_zero(), true)?;
        self.summary.vertices += 1;
        match what {
            Corner::Vertex(i) => {
                if let Some(v) = self.open.get_mut(&i) {
                    v.written = Some(index);
                }
                self.owners.insert(index, Owner::Vertex(i));
            }
            Corner::OnEdge(a, b) => {
                self.cuts.insert((a, b, position.to_array().map(f32::to_bits)), index);
                self.owners.insert(index, Owner::OnEdge(a, b));
            }
            Corner::Inside => {}
        }
        Ok(index)
    }

    /// Marks vertices fixed and done (both callers mean that no later triangle names them),
    /// cutting the triangles that waited on them.
    fn fix(&mut self, indices: impl Iterator<Item = (u32, Option<(DVec3, DVec3)>)>) -> std::io::Result<()> {
        let mut released: Vec<[u32; 3]> = Vec::new();
        let mut closing: Vec<u32> = Vec::new();
        for (index, value) in indices {
            let Some(v) = self.open.get_mut(&index) else { continue };
            if let Some((position, normal)) = value {
                v.position = position.as_vec3();
                v.normal = normal;
            }
            v.fixed = true;
            v.done = true;
            released.append(&mut v.waiters);
            closing.push(index);
        }
        for triangle in released {
            self.offer(triangle, true)?;
        }
        for index in closing {
            self.close_if_spent(index);
        }
        self.sweep_if_due();
        Ok(())
    }

    /// Cuts a triangle if its vertices are fixed; otherwise it waits on one that is not.
    /// `waited`: it was waiting already (its vertices count it).
    fn offer(&mut self, triangle: [u32; 3], waited: bool) -> std::io::Result<()> {
        let unfixed = triangle
            .iter()
            .copied()
            .find(|i| self.open.get(i).is_some_and(|v| !v.fixed));
        match unfixed {
            Some(on) => {
                if !waited {
                    for i in triangle {
                        if let Some(v) = self.open.get_mut(&i) {
                            v.waiting += 1;
                        }
                    }
                }
                if let Some(v) = self.open.get_mut(&on) {
                    v.waiters.push(triangle);
                }
            }
            None => {
                self.cut(triangle)?;
                if waited {
                    for i in triangle {
                        if let Some(v) = self.open.get_mut(&i) {
                            v.waiting = v.waiting.saturating_sub(1);
                        }
                        self.close_if_spent(i);
                    }
                }
            }
        }
        Ok(())
    }

    /// Forgets an input vertex that no triangle will name and none waits with.
    fn close_if_spent(&mut self, index: u32) {
        if self.open.get(&index).is_some_and(|v| v.done && v.waiting == 0) {
            self.open.remove(&index);
            self.closed_since_sweep += 1;
        }
    }

    fn sweep_if_due(&mut self) {
        self.most_open = (
            self.most_open.0.max(self.open.len()),
            self.most_open.1.max(self.edges.len()),
        );
        if self.closed_since_sweep >= SWEEP_AFTER_LEAST.max(self.edges.len() / 4) {
            self.sweep();
        }
    }

    /// Drops the cut points and output vertices that no later triangle can name, and counts
    /// the edges that have such an end.
    fn sweep(&mut self) {
        let open = &self.open;
        let is_open = |i: &u32| open.contains_key(i);
        self.cuts.retain(|(a, b, _), _| is_open(a) && is_open(b));
        self.owners.retain(|_, owner| match *owner {
            Owner::Vertex(i) => is_open(&i),
            Owner::OnEdge(a, b) => is_open(&a) && is_open(&b),
        });
        let owners = &self.owners;
        let summary = &mut self.summary;
        self.edges.retain(|(a, b), uses| {
            let still = owners.contains_key(a) && owners.contains_key(b);
            if !still {
                summary.boundary_edges += u64::from(*uses == 1);
                summary.non_manifold_edges += u64::from(*uses > 2);
            }
            still
        });
        self.closed_since_sweep = 0;
    }
}

impl<W: MeshWriter> MeshWriter for RegionWriter<W> {
    fn vertex(&mut self, position: DVec3, normal: DVec3, settled: bool) -> std::io::Result<()> {
        self.open.insert(
            self.incoming,
            Open {
                position: position.as_vec3(),
                normal,
                fixed: settled,
                done: false,
                waiting: 0,
                waiters: Vec::new(),
                written: None,
            },
        );
        self.incoming = self
            .incoming
            .checked_add(1)
            .ok_or_else(|| std::io::Error::other("more than 2^32 vertices"))?;
        Ok(())
    }

    fn triangle(&mut self, triangle: [u32; 3]) -> std::io::Result<()> {
        self.offer(triangle, false)
    }

    fn fix_vertices(&mut self, fixes: &[(u32, DVec3, DVec3)]) -> std::io::Result<()> {
        self.fix(fixes.iter().map(|&(i, p, n)| (i, Some((p, n)))))
    }

    /// The writer after the cut's: the cut's own vertices, waiting for their triangles, are
    /// those of one batch (it takes what the simplification writes), not the seams'.
    fn held_bytes(&self) -> u64 {
        self.inner.held_bytes()
    }

    fn settle(&mut self, indices: &[u32]) -> std::io::Result<()> {
        self.fix(indices.iter().map(|&i| (i, None)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::{Mesh, clip, edge_defects};

    /// A vertex-sharing grid of `n` x `n` squares, two triangles each, on a wavy sheet.
    fn sheet(n: u32) -> Mesh {
        let mut mesh = Mesh::default();
        for j in 0..=n {
            for i in 0..=n {
                let (x, y) = (i as f32 / n as f32 * 2.0 - 1.0, j as f32 / n as f32 * 2.0 - 1.0);
                mesh.positions.push([x, y, 0.2 * (3.0 * x).sin() * (2.0 * y).cos()]);
                mesh.normals.push([0.0, 0.0, 1.0]);
            }
        }
        let at = |i: u32, j: u32| j * (n + 1) + i;
        for j in 0..n {
            for i in 0..n {
                mesh.triangles.push([at(i, j), at(i + 1, j), at(i + 1, j + 1)]);
                mesh.triangles.push([at(i, j), at(i + 1, j + 1), at(i, j + 1)]);
            }
        }
        mesh
    }

    /// The triangles as sorted triples of position bits (comparable whatever the numbering).
    fn shape(mesh: &Mesh) -> Vec<[[u32; 3]; 3]> {
        let mut out: Vec<[[u32; 3]; 3]> = mesh
            .triangles
            .iter()
            .map(|t| {
                let mut c = t.map(|i| mesh.positions[i as usize].map(f32::to_bits));
                // Rotate so the smallest corner comes first (orientation kept).
                let k = (0..3).min_by_key(|&k| c[k]).unwrap_or(0);
                c.rotate_left(k);
                c
            })
            .collect();
        out.sort_unstable();
        out
    }

    #[derive(Default)]
    struct Collect(Vec<DVec3>, Vec<DVec3>, Vec<[u32; 3]>);
    impl MeshWriter for Collect {
        fn vertex(&mut self, position: DVec3, normal: DVec3, _settled: bool) -> std::io::Result<()> {
            self.0.push(position);
            self.1.push(normal);
            Ok(())
        }
        fn triangle(&mut self, triangle: [u32; 3]) -> std::io::Result<()> {
            self.2.push(triangle);
            Ok(())
        }
        fn fix_vertices(&mut self, _fixes: &[(u32, DVec3, DVec3)]) -> std::io::Result<()> {
            Ok(())
        }
    }

    /// Streams `mesh` into a region writer: every vertex given unfixed (position zero) and
    /// fixed in `fix_every` triangles' time if `fix_every > 0` (as the weld's seam vertices),
    /// else given fixed and settled after the last triangle naming it (as the simplifier's).
    fn streamed(mesh: &Mesh, region: BoundingBox, fix_every: usize) -> (Mesh, MeshSummary) {
        let mut writer = RegionWriter::new(Collect::default(), region);
        let last_use = {
            let mut last = vec![0usize; mesh.positions.len()];
            for (k, t) in mesh.triangles.iter().enumerate() {
                for &v in t {
                    last[v as usize] = k;
                }
            }
            last
        };
        let p = |i: usize| DVec3::from(mesh.positions[i].map(f64::from));
        let n = |i: usize| DVec3::from(mesh.normals[i].map(f64::from));
        for i in 0..mesh.positions.len() {
            if fix_every > 0 {
                writer.vertex(DVec3::ZERO, DVec3::ZERO, false).unwrap();
            } else {
                writer.vertex(p(i), n(i), true).unwrap();
            }
        }
        for (k, t) in mesh.triangles.iter().enumerate() {
            writer.triangle(*t).unwrap();
            let due: Vec<u32> = (0..mesh.positions.len())
                .filter(|&i| last_use[i] == k)
                .map(|i| i as u32)
                .collect();
            if fix_every > 0 {
                if k % fix_every == fix_every - 1 || k + 1 == mesh.triangles.len() {
                    let spent: Vec<(u32, DVec3, DVec3)> = (0..mesh.positions.len())
                        .filter(|&i| last_use[i] <= k && writer.open.get(&(i as u32)).is_some_and(|v| !v.fixed))
                        .map(|i| (i as u32, p(i), n(i)))
                        .collect();
                    writer.fix_vertices(&spent).unwrap();
                }
            } else {
                writer.settle(&due).unwrap();
            }
        }
        let (collect, summary) = writer.finish();
        let summary = summary.unwrap();
        let mesh = Mesh {
            positions: collect.0.iter().map(|p| p.as_vec3().to_array()).collect(),
            normals: collect.1.iter().map(|n| n.as_vec3().to_array()).collect(),
            triangles: collect.2,
        };
        (mesh, summary)
    }

    #[test]
    fn streamed_cut_equals_the_cut_in_memory_and_forgets_what_is_done() {
        let mesh = sheet(40);
        let boxes = [
            // One plane through the middle, one through vertex columns exactly (x = 0).
            (DVec3::new(-0.37, -2.0, -2.0), DVec3::new(2.0, 2.0, 2.0)),
            (DVec3::new(0.0, -2.0, -2.0), DVec3::new(2.0, 2.0, 2.0)),
            // A corner of the box inside the sheet: cuts of cuts.
            (DVec3::new(-0.31, -0.43, -0.05), DVec3::new(0.52, 0.61, 2.0)),
            // Nothing inside.
            (DVec3::new(5.0, 5.0, 5.0), DVec3::new(6.0, 6.0, 6.0)),
        ];
        for (min, max) in boxes {
            let region = BoundingBox { min, max };
            let reference = clip(&mesh, region);
            for fix_every in [0, 1, 37] {
                let (cut, summary) = streamed(&mesh, region, fix_every);
                let (streamed, in_memory) = (shape(&cut), shape(&reference));
                let only: Vec<_> = streamed
                    .iter()
                    .filter(|t| in_memory.binary_search(t).is_err())
                    .collect();
                assert!(
                    streamed.len() == in_memory.len() && only.is_empty(),
                    "{min} {max} fixing every {fix_every}: {} triangles against {}; first only streamed {:?}",
                    streamed.len(),
                    in_memory.len(),
                    only.first().map(|t| t.map(|c| c.map(f32::from_bits)))
                );
                assert_eq!(summary.triangles as usize, cut.triangles.len());
                assert_eq!(summary.vertices as usize, cut.positions.len());
                let (boundary, non_manifold) = edge_defects(&cut);
                assert_eq!(summary.boundary_edges as usize, boundary);
                assert_eq!(summary.non_manifold_edges as usize, non_manifold);
                // Every vertex written is used, and none is written twice for a shared point.
                let used = |m: &Mesh| {
                    let mut used: Vec<u32> = m.triangles.iter().flatten().copied().collect();
                    used.sort_unstable();
                    used.dedup();
                    used.len()
                };
                assert_eq!(used(&cut), cut.positions.len(), "{min} {max}");
                assert_eq!(used(&cut), used(&reference), "{min} {max}");
            }
        }
    }

    #[test]
    fn memory_holds_only_the_open_front() {
        // Vertices settled after their last triangle, in row order: what stays open is about
        // one row of the grid, not the mesh.
        let n = 120;
        let mesh = sheet(n);
        let region = BoundingBox {
            min: DVec3::new(-0.5, -2.0, -2.0),
            max: DVec3::new(0.5, 2.0, 2.0),
        };
        let mut writer = RegionWriter::new(Collect::default(), region);
        for (p, nrm) in mesh.positions.iter().zip(&mesh.normals) {
            writer
                .vertex(DVec3::from(p.map(f64::from)), DVec3::from(nrm.map(f64::from)), true)
                .unwrap();
        }
        let mut last = vec![0usize; mesh.positions.len()];
        for (k, t) in mesh.triangles.iter().enumerate() {
            for &v in t {
                last[v as usize] = k;
            }
        }
        let mut by_last: Vec<Vec<u32>> = vec![Vec::new(); mesh.triangles.len()];
        for (v, &k) in last.iter().enumerate() {
            by_last[k].push(v as u32);
        }
        let mut most = (0, 0, 0);
        for (k, t) in mesh.triangles.iter().enumerate() {
            writer.triangle(*t).unwrap();
            writer.settle(&by_last[k]).unwrap();
            if k > mesh.triangles.len() / 2 {
                most = (
                    most.0.max(writer.cuts.len()),
                    most.1.max(writer.owners.len()),
                    most.2.max(writer.edges.len()),
                );
            }
        }
        // All vertices were given at the start, so the open input vertices are what is left
        // of the grid; the cut's own state is what matters: a few rows' worth at most.
        let row = (n as usize + 1) * 3;
        assert!(
            most.0 < row && most.1 < SWEEP_AFTER_LEAST + row && most.2 < 3 * (SWEEP_AFTER_LEAST + row),
            "{most:?}"
        );
        let (collect, summary) = writer.finish();
        let summary = summary.unwrap();
        assert_eq!(summary.triangles as usize, collect.2.len());
        assert!(summary.triangles > 0);
    }
}
