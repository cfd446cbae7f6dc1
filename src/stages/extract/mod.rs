//! `extract`: the surface u = 0 over the finest level cut (paper 4.6).
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
//!
//! Observed surface only. The zero set of u is closed: where no depth map looked (behind the
//! walls of a room, under furniture) the solver still decides inside or outside, and the
//! mirrored exterior closes every surface at the root cube. By default a tetrahedron is meshed
//! only when the data supports a surface there: depth maps voted into all four of its cells
//! (the level segment's `seen`), samples lie in at least one of its dual cell's eight cells
//! (`sampled`: samples spawned the cube or a descendant, or samples other than spikes its
//! parent, an ancestor or a sibling; `stages::observed::sampled_nodes`), and at least a tenth of the dual
//! cell's votes measured a distance to a surface (`measured`, the votes in histogram bins 1
//! to 6). The first drops the space no map reached (virtual exterior cells are never seen);
//! the other two drop the boundary between occluded space (which votes "inside" up to eta
//! behind a surface) and free space, the sheets that would hang behind a plate or under a
//! counter, where no sample lies and the votes are all clamped. A cell of coarse cubes passes
//! these tests with one sample anywhere in it, so each tetrahedron must also be supported by
//! its own four corners: the votes at one of them place the surface within the tetrahedron's
//! span of it, or samples reached two of them and a tenth of their own votes measured a
//! distance (`dual_cells::tetrahedron_supported`); that drops the fringes past depth edges and
//! the bridges across crevices. Noise leaves a few tetrahedra of well-seen surfaces short of
//! that support too, and dropping them would open pinholes in closed objects; so the unit's
//! unsupported cut tetrahedra are held, and a group of at most 8 of them joined by shared
//! polygon edges comes back when every other edge of theirs is an edge of the unit's kept
//! surface (a hole the surface surrounds), while a fringe, which borders nothing kept on one
//! side, stays out (`dual_cells::pinholes`). Each tetrahedron is meshed only by the unit
//! that generates its dual cell, and the fill reads only the surface that unit meshes, so the
//! pieces stay seamless and the result does not depend on the order units run in (a pinhole
//! whose rim lies partly in another unit stays open). That is what a capture from inside a
//! scene gets. A capture that looks at objects against empty background gets the watertight
//! surface instead, by default (`surface`: most of a few depth maps have their border mostly
//! invalid): every cut tetrahedron is meshed, and each connected part of a unit's piece is kept
//! if it holds a vertex of what the observed surface would keep or reaches another unit
//! (`dual_cells::watertight`), so an object comes out closed where no map measured it while
//! bubbles of the zero set in free space go, and so do noise blobs (closed parts at most 8
//! cells across within 4 cells of a larger part: folds of the zero set in the depth noise).
//! Its simplification keeps the topology, so a bump on a thin neck is not pinched off
//! (`simplify`). `--closed` keeps the whole zero set (hidden parts filled in, closed at the
//! root cube).
//!
//! Vertices inside cubes. u's L1 data term snaps it to histogram bin centres, and linear
//! interpolation of u between cell centres then leaves terraces about one bin (near one finest
//! cube) high on smooth surfaces. Where both ends of a cut edge have a measured surface offset
//! (the level segment's `surface_offset`, the mean truncated signed distance of the cube's
//! votes: a TSDF value at its centre), the vertex sits where those offsets cross zero, held
//! inside the edge u chose; u alone decides which edges are cut, so outliers cannot move the
//! surface by more than an edge. That still pins vertices to their edges: where u's choice of
//! edges and the offsets disagree by a cube (a plane passing near a layer of cell centres),
//! vertices sit at edge ends and the surface shows ridges along the grid. So each vertex then
//! moves to the mean of its projections onto the offset planes of the dual cells around it
//! (the offsets of a cell's 8 corners fitted by a linear function: the TSDF's surface inside
//! the cell, off the edges as well as on them), at most half its edge from where it was. A
//! vertex only its unit produces gets every share at once; a seam vertex gets each unit's
//! share through the weld, which places it when the last unit that can produce it is done, so
//! the pieces weld and the streamed mesh equals the one welded in memory. Then `relax` smooths
//! the vertices only their unit produces (Taubin's steps, each vertex within half its edge of
//! where it was; seam vertices stay).
//!
//! Files: `surface` (what to mesh, and the default's decision from the capture), `dual_cells`
//! (a unit's piece; `dual_cells/pinholes` fills its pinholes, `dual_cells/watertight` drops
//! the watertight piece's parts without observed surface), `relax`
//! (smoothing a piece's private vertices), `order` (the order units are meshed and welded in:
//! a wide scene column by column), `weld` (streaming weld in that order), `simplify`
//! (streaming simplification of the welded mesh; `carried` holds its triangles waiting at open
//! seams), `region` (the cut at `--region`), `mesh_file` (the temporary vertex and face files
//! and the final PLY), `in_order` (workers compute pieces ahead while the weld consumes them
//! in order).

mod carried;
mod dual_cells;
mod in_order;
mod mesh_file;
mod order;
mod region;
mod relax;
mod simplify;
mod surface;
mod weld;

use std::collections::HashMap;
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};

use glam::DVec3;
use rayon::prelude::*;

use self::dual_cells::{drop_unobserved_pieces, dual_cells_of_unit};
use self::in_order::{Window, in_order_while_computing};
use self::mesh_file::{MemoryMesh, MeshFile};
use self::order::UnitOrder;
use self::region::RegionWriter;
use self::relax::smooth_private_vertices;
use self::simplify::{SimplifyingWriter, Target};
pub use self::surface::{Surface, SurfaceChoice};
use self::weld::{MeshWriter, StreamingWeld, private_to};
use super::solve::{LEVEL_STAGES, LevelCut};
use super::treetop::Treetop;
use crate::format::{BoundingBox, CubeKey, Scene};
pub use crate::mesh::MeshSummary;
use crate::mesh::{Mesh, UnitMesh};
use crate::store::StageError;
use crate::store::{Result, Snapshot, StoreError};

/// Hash tables keyed by surface-vertex and edge names: nothing depends on their iteration
/// order, so a fast fixed-seed hasher replaces SipHash.
type FastMap<K, V> = HashMap<K, V, foldhash::fast::FixedState>;

/// Bytes a hash table with room for `capacity` entries of type `T` takes (hashbrown: a power
/// of two of buckets, at most 7/8 full, each a `T` and a control byte): what the open seams'
/// tables report of themselves.
fn table_bytes<T>(capacity: usize) -> u64 {
    if capacity == 0 {
        return 0;
    }
    let buckets = (capacity.saturating_mul(8) / 7).max(4).next_power_of_two();
    (buckets * (std::mem::size_of::<T>() + 1)) as u64
}

/// The second values of pairs grouped by their first (a key below a bound), each group sorted,
/// in one list with each key's start in it: a counting sort, linear in the pairs, where a list
/// or a hash table entry per key missed the cache on every pair. A piece's edges, grouped by
/// vertex, give both the smoothing's neighbours (`relax`) and the weld's edge counts.
struct Grouped {
    /// Key `k`'s values are `values[starts[k]..starts[k + 1]]`.
    starts: Vec<usize>,
    values: Vec<u32>,
}

impl Grouped {
    /// The pairs `pairs()` yields (asked for twice: to count, then to place), those whose key
    /// is `keys` or more left out.
    fn of<I: Iterator<Item = (u32, u32)>>(keys: usize, pairs: impl Fn() -> I) -> Grouped {
        let mut starts = vec![0usize; keys + 1];
        for (key, _) in pairs() {
            if let Some(count) = starts.get_mut(key as usize + 1) {
                *count += 1;
            }
        }
        let mut total = 0;
        for start in starts.iter_mut() {
            total += *start;
            *start = total;
        }
        let mut values = vec![0u32; total];
        let mut next = starts.clone();
        for (key, value) in pairs() {
            if let Some(at) = next.get_mut(key as usize)
                && let Some(slot) = values.get_mut(*at)
            {
                *slot = value;
                *at += 1;
            }
        }
        let mut grouped = Grouped { starts, values };
        for key in 0..keys {
            if let Some(group) = grouped.range(key).and_then(|range| grouped.values.get_mut(range)) {
                group.sort_unstable();
            }
        }
        grouped
    }

    fn range(&self, key: usize) -> Option<std::ops::Range<usize>> {
        Some(*self.starts.get(key)?..*self.starts.get(key + 1)?)
    }

    /// Key `key`'s values, ascending.
    fn of_key(&self, key: usize) -> Option<&[u32]> {
        self.values.get(self.range(key)?)
    }

    fn keys(&self) -> usize {
        self.starts.len().saturating_sub(1)
    }
}

/// What to extract and how.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ExtractOptions {
    /// Only what lies in this box, cut at its faces.
    pub region: Option<BoundingBox>,
    /// How far to simplify the mesh (`simplify` module).
    pub simplify: Simplify,
    /// How much of the zero set to mesh; by default decided from the capture.
    pub surface: SurfaceChoice,
}

/// How far extraction simplifies the welded mesh: quadric edge collapses, streamed in batches
/// across treetop leaf borders, never moving a vertex the file already holds.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub enum Simplify {
    /// Every triangle marching tetrahedra gives.
    Full,
    /// Collapse while the geometric error stays within this many finest cube sides.
    MaxError(f32),
    /// Keep about this fraction of the triangles (0..1], whatever the error.
    Fraction(f32),
}

/// The default error bound of [`Simplify::MaxError`], in finest cube sides.
pub const DEFAULT_MAX_ERROR: f32 = 0.25;

impl Default for Simplify {
    fn default() -> Self {
        Simplify::MaxError(DEFAULT_MAX_ERROR)
    }
}

impl Simplify {
    /// The simplification target, errors in scene units: none for the full mesh.
    fn target(self, scene: &Scene, finest: u8) -> Option<Target> {
        match self {
            Simplify::MaxError(error) if error > 0.0 => {
                Some(Target::MaxError(f64::from(error) * scene.cube_side(finest)))
            }
            Simplify::Fraction(fraction) if fraction < 1.0 => Some(Target::Fraction(fraction.max(0.0))),
            _ => None,
        }
    }
}

/// Bytes a buffered triangle of the simplification holds with its share of vertices and of
/// meshoptimizer's working memory, about (its half of a vertex map entry, the batch's local
/// arrays and their copies for a second round, the quadrics and collapse lists): when batches
/// ended only between pieces, the interior scene's pieces of about 450,000 triangles raised
/// the peak by 130 to 150 MB over the full mesh's.
const SIMPLIFY_BYTES_PER_TRIANGLE: u64 = 512;

/// Most triangles a simplification batch gathers. Batches end after the same units at any
/// budget from 128 MiB, so the mesh does not depend on the budget there. Larger batches gain
/// nothing: on RedKitchen (1000 frames, `--max-depth 10`, 3.0 M triangles in full) batches of
/// 2^15 to 2^18 triangles kept 180,884 to 182,776 triangles, and the smaller ones were faster
/// (a batch that breaks an edge is simplified again whole, `simplify::simplify_manifold`).
const SIMPLIFY_BATCH_MOST: u64 = 1 << 16;

/// Triangles a simplification batch gathers at `memory_budget`: the share that finished
/// pieces may hold ([`PIECES_AHEAD_SHARE`]).
fn simplify_batch(memory_budget: u64) -> usize {
    let fits = memory_budget / PIECES_AHEAD_SHARE / SIMPLIFY_BYTES_PER_TRIANGLE;
    fits.clamp(1 << 12, SIMPLIFY_BATCH_MOST) as usize
}

/// Extracts the surface u = 0 of the latest solution in memory, optionally only what lies in a
/// region, simplified as `options` say (batches as at a 1 GiB budget).
pub fn extract(snapshot: &Snapshot<'_>, scene: &Scene, finest: u8, options: &ExtractOptions) -> Result<Mesh> {
    let treetop = Treetop::of(snapshot)?;
    let units = extract_units(snapshot, &treetop, scene, finest, options.region)?;
    let surface = options.surface.resolve(snapshot)?;
    let pieces: Vec<(usize, CubeKey, UnitMesh)> = units
        .par_iter()
        .map(|&unit| piece(snapshot, &treetop, scene, finest, unit, surface))
        .collect::<Result<_>>()?;
    let simplification = Simplification {
        target: options.simplify.target(scene, finest),
        batch: simplify_batch(1 << 30),
        keep_topology: surface == Surface::Watertight,
    };
    let pieces = pieces.into_iter().map(Ok);
    let io = |source: std::io::Error| StoreError::Io {
        action: "weld mesh",
        path: std::path::PathBuf::new(),
        source,
    };
    let welded = match options.region {
        Some(region) => {
            let cut = RegionWriter::new(MemoryMesh::default(), region);
            finish_cut(weld_pieces(pieces, &treetop, cut, simplification, &|_| {}, &io), &io)
        }
        None => weld_pieces(pieces, &treetop, MemoryMesh::default(), simplification, &|_| {}, &io),
    };
    match welded {
        (Some(memory), Ok(_)) => Ok(memory.into_mesh()),
        (_, result) => Err(result
            .err()
            .unwrap_or_else(|| io(std::io::Error::other("weld lost its mesh")))),
    }
}

/// The writer inside a region's cut and the cut's counts, once the weld into it is done (the
/// writer also after an error, to be abandoned, if there is one).
fn finish_cut<W: MeshWriter>(
    welded: (Option<RegionWriter<W>>, Result<MeshSummary>),
    io: &dyn Fn(std::io::Error) -> StoreError,
) -> (Option<W>, Result<MeshSummary>) {
    match welded {
        (Some(cut), Ok(full)) => {
            let most_open = cut.most_open;
            let (inner, summary) = cut.finish();
            if let Ok(summary) = &summary {
                tracing::info!(
                    "extract: cut {} triangles to {} inside the region, holding at most {} vertices and {} edges open",
                    full.triangles,
                    summary.triangles,
                    most_open.0,
                    most_open.1
                );
            }
            (Some(inner), summary.map_err(io))
        }
        (cut, result) => (
            cut.map(|cut| cut.inner),
            Err(result
                .err()
                .unwrap_or_else(|| io(std::io::Error::other("weld lost its mesh")))),
        ),
    }
}

/// The units of `treetop` (the snapshot's) whose dual cells can reach the region (all leaves
/// without one), in extraction order (`order`: the weld takes their pieces in it).
pub fn extract_units(
    snapshot: &Snapshot<'_>,
    treetop: &Treetop,
    scene: &Scene,
    finest: u8,
    region: Option<BoundingBox>,
) -> Result<Vec<usize>> {
    let stage = LEVEL_STAGES[usize::from(finest)];
    if snapshot.segments(stage).is_empty() {
        return Err(StoreError::Stage {
            stage: "extract".into(),
            unit: "-".into(),
            error: Box::new(StageError::NoSolution { level: finest }),
        });
    }
    Ok(UnitOrder::of(treetop)
        .leaves()
        .iter()
        .copied()
        .filter(|&i| {
            let Some(unit) = treetop.units.get(i) else { return false };
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

/// The surface pieces that treetop unit `unit` generates, as much of them as `surface` says.
pub fn unit_mesh(
    snapshot: &Snapshot<'_>,
    treetop: &Treetop,
    scene: &Scene,
    finest: u8,
    unit: usize,
    surface: Surface,
) -> Result<UnitMesh> {
    let Some(key) = treetop.units.get(unit).map(|u| u.key) else {
        return Ok(UnitMesh::default());
    };
    // Every probe of the unit's dual cells lies within one finest cell of its cube.
    let mut level = LevelCut::around(snapshot, treetop, finest, key);
    let Some(values) = level.unit(unit)? else {
        return Ok(UnitMesh::default());
    };
    let (mut mesh, mut guides) = dual_cells_of_unit(scene, &mut level, &values.0, &values.1, surface)?;
    let private = private_to(key);
    if surface == Surface::Watertight {
        drop_unobserved_pieces(&mut mesh, &mut guides, &private);
    }
    let movable: Vec<bool> = mesh.vertices.iter().map(|v| private(&v.0)).collect();
    // A private vertex has all its cells here, so its planes are all there are; other units add
    // theirs to a seam vertex's in the weld.
    for (share, (vertex, &private)) in guides.moves.iter().zip(mesh.vertices.iter_mut().zip(&movable)) {
        if private {
            vertex.1 = share.place(vertex.1, vertex.1);
        } else if share.count > 0 {
            mesh.seam_moves.push(*share);
        }
    }
    smooth_private_vertices(&mut mesh, &guides.ends, &movable);
    Ok(mesh)
}

/// How the welded mesh is simplified.
#[derive(Clone, Copy)]
struct Simplification {
    /// Towards what; none for the full mesh.
    target: Option<Target>,
    /// Triangles a batch gathers.
    batch: usize,
    /// Whether a batch keeps the mesh's topology (`SimplifyingWriter::keeping_topology`): for
    /// the watertight surface, which promises each object one closed piece.
    keep_topology: bool,
}

/// Welds pieces (unit index, treetop cube, mesh), in increasing unit order, into `writer`,
/// simplified as `simplification` says: the writer (also after an error while adding pieces,
/// to be abandoned) and the counts of what it was given.
fn weld_pieces<W: MeshWriter>(
    pieces: impl Iterator<Item = Result<(usize, CubeKey, UnitMesh)>>,
    treetop: &Treetop,
    writer: W,
    simplification: Simplification,
    on_held: &dyn Fn(u64),
    io: &dyn Fn(std::io::Error) -> StoreError,
) -> (Option<W>, Result<MeshSummary>) {
    fn add_all<X: MeshWriter>(
        weld: &mut StreamingWeld<'_, X>,
        pieces: impl Iterator<Item = Result<(usize, CubeKey, UnitMesh)>>,
        on_held: &dyn Fn(u64),
        io: &dyn Fn(std::io::Error) -> StoreError,
    ) -> Result<()> {
        // The most held, and the weld's own share of it then.
        let (mut most_held, mut weld_share) = (0, 0);
        for piece in pieces {
            let (unit, key, mesh) = piece?;
            weld.add(unit, key, &mesh).map_err(io)?;
            let held = weld.held_bytes();
            if held > most_held {
                (most_held, weld_share) = (held, weld.own_held_bytes());
            }
            on_held(held);
        }
        tracing::info!(
            "extract: at most {} seam vertices and {} seam edges open at once; the weld and the simplification \
             held at most {:.0} MB along the open seams (the weld {:.0} MB of it)",
            weld.most_open,
            weld.most_open_edges,
            most_held as f64 / 1e6,
            weld_share as f64 / 1e6
        );
        Ok(())
    }
    let Simplification {
        target,
        batch,
        keep_topology,
    } = simplification;
    match target {
        None => {
            let mut weld = StreamingWeld::new(writer, treetop);
            if let Err(e) = add_all(&mut weld, pieces, on_held, io) {
                return (Some(weld.writer), Err(e));
            }
            match weld.finish() {
                Ok((writer, summary)) => (Some(writer), Ok(summary)),
                Err(e) => (None, Err(io(e))),
            }
        }
        Some(target) => {
            let simplifying = SimplifyingWriter::new(writer, target, batch).keeping_topology(keep_topology);
            let mut weld = StreamingWeld::new(simplifying, treetop);
            if let Err(e) = add_all(&mut weld, pieces, on_held, io) {
                return (Some(weld.writer.inner), Err(e));
            }
            let finished = weld
                .finish()
                .and_then(|(simplifying, full)| Ok((simplifying.finish()?, full)));
            match finished {
                Ok(((writer, summary), full)) => {
                    let bound = match target {
                        Target::MaxError(distance) => {
                            format!("moving the surface by at most {distance:.3e} scene units")
                        }
                        Target::Fraction(fraction) => format!("aiming at {:.1} % of them", 100.0 * fraction),
                    };
                    tracing::info!(
                        "extract: simplified {} triangles to {} ({bound})",
                        full.triangles,
                        summary.triangles
                    );
                    if let Target::Fraction(fraction) = target {
                        let kept = summary.triangles as f64 / (full.triangles.max(1)) as f64;
                        if kept > 1.1 * f64::from(fraction) {
                            tracing::warn!(
                                "extract --decimate {fraction}: kept {:.1} % of the triangles; collapsing more would \
                                 change the surface's topology (thin parts, small holes) or leave edges of more \
                                 than two triangles",
                                100.0 * kept
                            );
                        }
                    }
                    (Some(writer), Ok(summary))
                }
                Err(e) => (None, Err(io(e))),
            }
        }
    }
}

/// Writes pieces (unit index, treetop cube, mesh), in increasing unit order, into the mesh file
/// at `path`, simplified and cut to the region as `options` say. Without a region, memory holds
/// the pieces computed ahead, the open seams and one simplification batch
/// ([`simplify_batch`] of `memory_budget`); a region's cut is streamed too (`region`).
/// `on_held` hears, after each piece, how many bytes the weld and the simplification hold
/// along the open seams.
#[expect(
    clippy::too_many_arguments,
    reason = "the stream, where it goes and how, and the memory it may use: each a caller's own (extract_to_file, the cluster's commit)"
)]
pub fn write_pieces(
    pieces: impl Iterator<Item = Result<(usize, CubeKey, UnitMesh)>>,
    treetop: &Treetop,
    scene: &Scene,
    finest: u8,
    options: &ExtractOptions,
    path: &Path,
    memory_budget: u64,
    on_held: &dyn Fn(u64),
) -> Result<MeshSummary> {
    // The caller resolved the surface (`extract_to_file`, the cluster's plan).
    let simplification = Simplification {
        target: options.simplify.target(scene, finest),
        batch: simplify_batch(memory_budget),
        keep_topology: options.surface == SurfaceChoice::Watertight,
    };
    let io = |source: std::io::Error| StoreError::Io {
        action: "write mesh",
        path: path.to_path_buf(),
        source,
    };
    let file = MeshFile::create(path).map_err(io)?;
    let written = match options.region {
        Some(region) => {
            let cut = RegionWriter::new(file, region);
            finish_cut(weld_pieces(pieces, treetop, cut, simplification, on_held, &io), &io)
        }
        None => weld_pieces(pieces, treetop, file, simplification, on_held, &io),
    };
    match written {
        (Some(file), Ok(summary)) => {
            file.finish(&summary).map_err(io)?;
            Ok(summary)
        }
        (file, result) => {
            if let Some(file) = file {
                file.abandon();
            }
            Err(result
                .err()
                .unwrap_or_else(|| io(std::io::Error::other("weld lost its mesh file"))))
        }
    }
}

/// The share of `--memory-budget` that finished pieces waiting for the weld may hold.
/// Pieces differ by orders of magnitude (RedKitchen's treetop leaves give 0 to 210,000
/// triangles, about 9 MB at most), so a window counted in pieces either idled the workers
/// behind a large piece (4 pieces on 2 cores: extract 2.31 to 2.71 s) or risked memory on
/// scenes of larger pieces; one counted in bytes lets small pieces run far ahead (1.96 to
/// 2.04 s against 2.35 to 2.64 s). An eighth: about what 4 large pieces held at 256 MiB, where
/// the 53 M-cube city's extraction peaked just within the budget with them (BENCHMARKS.md,
/// "Scale"); RedKitchen's peak at 256 MiB went from 227-245 MB to 248-250 MB.
pub const PIECES_AHEAD_SHARE: u64 = 8;

/// The share of `--memory-budget` that the weld's and the simplification's state along the
/// open seams may hold before the finished pieces waiting for the weld give way to it, byte
/// for byte, down to [`PIECES_AHEAD_LEAST_SHARE`]. The open seams grow with the scene's
/// cross-section (on the 415 M-sample city, 1.2 M seam vertices and 2.3 M triangles held back
/// along them), while the pieces ahead only smooth the weld's pace: there extraction peaked at
/// 1,038 MB in 656 s with this, 1,133 MB in 628 s without (separate runs, budget 1 GiB).
const OPEN_SEAMS_SHARE: u64 = 4;

/// The share of `--memory-budget` that finished pieces may hold however much the open seams
/// hold: a few of the city's pieces (8 MB each at 415 M samples), which keeps both workers busy.
const PIECES_AHEAD_LEAST_SHARE: u64 = 32;

/// Pieces computed ahead of the weld, at most, whatever their sizes: the weld's state per
/// piece is a map entry.
const PIECES_AHEAD_MOST: usize = 64;

/// Extracts the surface into a mesh file: one worker per thread computes units' pieces, ahead
/// of the weld by at most `memory_budget / PIECES_AHEAD_SHARE` bytes of finished pieces (and
/// one piece per worker), while the calling thread welds, simplifies and writes them in unit
/// order ([`write_pieces`]), so memory does not grow with the surface.
pub fn extract_to_file(
    snapshot: &Snapshot<'_>,
    scene: &Scene,
    finest: u8,
    options: &ExtractOptions,
    path: &Path,
    memory_budget: u64,
) -> Result<MeshSummary> {
    let treetop = Treetop::of(snapshot)?;
    let units = extract_units(snapshot, &treetop, scene, finest, options.region)?;
    let leaf_rows = treetop.units.iter().filter(|u| !u.top).map(|u| u.record.rows);
    if let Some((largest, fits)) = leaves_over_budget(leaf_rows, memory_budget) {
        tracing::warn!(
            "the store's treetop leaves hold up to {largest} cubes, sized by a solve at a larger --memory-budget \
             (at this budget a solve makes leaves of fewer than {fits}); extraction holds one leaf's piece whole \
             and may use more than this budget (`octstore solve --memory-budget` with this budget rebuilds the \
             octree into smaller leaves)"
        );
    }
    let threads = rayon::current_num_threads().max(1);
    let yielded = AtomicU64::new(0);
    let window = Window {
        pieces: PIECES_AHEAD_MOST,
        bytes: memory_budget / PIECES_AHEAD_SHARE,
        yielded: &yielded,
        least: memory_budget / PIECES_AHEAD_LEAST_SHARE,
    };
    let allowance = memory_budget / OPEN_SEAMS_SHARE;
    let on_held = |held: u64| yielded.store(held.saturating_sub(allowance), Ordering::Relaxed);
    let weigh = |(_, _, mesh): &(usize, CubeKey, UnitMesh)| mesh.heap_bytes();
    let surface = options.surface.resolve(snapshot)?;
    let compute = |unit: usize| piece(snapshot, &treetop, scene, finest, unit, surface);
    let options = ExtractOptions {
        surface: surface.into(),
        ..*options
    };
    in_order_while_computing(&units, threads, window, weigh, compute, |pieces| {
        write_pieces(pieces, &treetop, scene, finest, &options, path, memory_budget, &on_held)
    })
}

/// The largest treetop leaf (in octree cubes) and the most a solve at `memory_budget` puts in
/// one, when the first exceeds the second. Extraction holds a leaf's piece whole: its surface
/// vertices with their names, moves and edge ends, its triangles and the leaf's level cut, about
/// 300 MB for the interior scene's largest leaf of a solve at 1 GiB (a heap profile of
/// `extract --threads 1`), so leaves made for a larger budget take it past a smaller one; leaves
/// made at the same budget keep it within (the interior at 256 MiB: 247 to 264 MB over two bench runs, BENCHMARKS.md).
fn leaves_over_budget(leaf_rows: impl Iterator<Item = u64>, memory_budget: u64) -> Option<(u64, u64)> {
    let fits = super::octree::effective_leaf_cubes(u64::MAX, memory_budget);
    let largest = leaf_rows.max()?;
    (largest >= fits).then_some((largest, fits))
}

/// Unit `unit`'s piece with its index and treetop cube.
fn piece(
    snapshot: &Snapshot<'_>,
    treetop: &Treetop,
    scene: &Scene,
    finest: u8,
    unit: usize,
    surface: Surface,
) -> Result<(usize, CubeKey, UnitMesh)> {
    let key = treetop
        .units
        .get(unit)
        .map(|u| u.key)
        .ok_or_else(|| StoreError::Stage {
            stage: "extract".into(),
            unit: unit.to_string(),
            error: Box::new(StageError::internal("no such treetop unit")),
        })?;
    Ok((unit, key, unit_mesh(snapshot, treetop, scene, finest, unit, surface)?))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::stages::octree::effective_leaf_cubes;

    #[test]
    fn leaves_made_at_a_larger_budget_are_named() {
        const MIB: u64 = 1 << 20;
        let small = effective_leaf_cubes(u64::MAX, 256 * MIB);
        let large = effective_leaf_cubes(u64::MAX, 1024 * MIB);
        assert!(small < large);
        // A solve makes leaves of fewer cubes than its budget's limit: at that budget, or any
        // larger one, extraction says nothing.
        let made_at_256 = [10, small - 1, 3];
        assert_eq!(leaves_over_budget(made_at_256.into_iter(), 256 * MIB), None);
        assert_eq!(leaves_over_budget(made_at_256.into_iter(), 1024 * MIB), None);
        let made_at_1024 = [small + 1, large - 1, 5];
        assert_eq!(leaves_over_budget(made_at_1024.into_iter(), 1024 * MIB), None);
        assert_eq!(
            leaves_over_budget(made_at_1024.into_iter(), 256 * MIB),
            Some((large - 1, small))
        );
        assert_eq!(leaves_over_budget(std::iter::empty(), 256 * MIB), None);
    }
}
