//! Dual cells of a unit: for every octree corner the unit generates, the cell joining the
//! centres of its incident leaves, split into Kuhn tetrahedra and cut at u = 0 (module docs of
//! `stages::extract` give the construction).

use arrayvec::ArrayVec;
use glam::DVec3;

use super::surface::Surface;
use super::weld::NameIndex;
use crate::format::key::{KeyBlocks, add_axis_bits, axis_bits, corner_axis_bits, sub_axis_bits};
use crate::format::{CubeKey, MAX_DEPTH, Scene};
use crate::mesh::{CornerId, UnitMesh, VertexId, VertexMove};
use crate::stages::solve::{CutValue, LevelCut};
use crate::store::Result;

mod pinholes;
mod watertight;

pub(super) use watertight::drop_unobserved_pieces;

/// Corner ids with this bit set are virtual exterior cells (see [`CornerId`]).
const VIRTUAL: u128 = 1 << 127;

#[derive(Clone, Copy)]
struct Corner {
    id: CornerId,
    center: DVec3,
    u: f32,
    /// The measured offset of the surface from the centre, in world units (a TSDF value);
    /// NaN when no vote measured one.
    offset: f64,
    /// The cell's vote weight (0 for virtual cells: no map sees them).
    votes: f32,
    /// The part of `votes` that measured a distance to a surface.
    measured: f32,
    /// Whether samples reached the cell.
    sampled: bool,
}

/// The leaf (or mirrored virtual cell) a dual cell's octant holds, as the probes find it:
/// enough to decide whether the cube generates the cell and whether u changes sign in it,
/// before any centre is computed.
#[derive(Clone, Copy)]
struct Incident {
    leaf: CubeKey,
    value: CutValue,
    /// Per axis (bit 0 = x), whether the octant lies past the root's faces: a virtual cell,
    /// the mirror image of `leaf`.
    mirrored: u8,
    /// Per axis, whether it lies past the root's low face (else its high one), where mirrored.
    below_root: u8,
}

impl Incident {
    fn u(&self) -> f32 {
        if self.mirrored != 0 { 1.0 } else { self.value.u }
    }

    fn corner(&self, scene: &Scene) -> Corner {
        // A virtual cell's centre is the mirror image of its leaf's across the root's faces it
        // lies past.
        let mut center = scene.cube_center(self.leaf);
        if self.mirrored != 0 {
            let (lo, hi) = (scene.min(), scene.min() + DVec3::splat(scene.root_side));
            for axis in 0..3 {
                if self.mirrored & (1 << axis) != 0 {
                    center[axis] = if self.below_root & (1 << axis) != 0 {
                        2.0 * lo[axis] - center[axis]
                    } else {
                        2.0 * hi[axis] - center[axis]
                    };
                }
            }
            return Corner {
                id: VIRTUAL | (u128::from(self.mirrored) << 124) | self.leaf.raw(),
                center,
                u: 1.0,
                offset: f64::NAN,
                votes: 0.0,
                measured: 0.0,
                sampled: false,
            };
        }
        Corner {
            id: self.leaf.raw(),
            center,
            u: self.value.u,
            offset: f64::from(self.value.offset),
            votes: self.value.votes,
            measured: self.value.measured,
            sampled: self.value.sampled,
        }
    }
}

/// Where on the edge from `lo` to `hi` (as a fraction) the surface crosses. u decides that it
/// crosses (its signs differ): u is robust, but its L1 data term snaps it to histogram bin
/// centres, and its linear interpolation leaves terraces one bin high. So where both ends
/// have a measured offset (the mean truncated signed distance of their votes, a TSDF value),
/// the offsets place the vertex, held inside the edge u chose; otherwise u's interpolation
/// does.
fn crossing(lo: &Corner, hi: &Corner) -> f64 {
    let (a, b) = (lo.offset, hi.offset);
    let by_u = f64::from(lo.u) / (f64::from(lo.u) - f64::from(hi.u));
    if a.is_finite() && b.is_finite() && a != b {
        return (a / (a - b)).clamp(0.05, 0.95);
    }
    by_u
}

/// The least share of a dual cell's votes that must have measured a distance to a surface for
/// the cell to carry observed surface. Around surfaces the maps saw, RedKitchen's cubes have a
/// third to a half of their votes in the measuring bins (the rest are clamped by depth noise);
/// where u's zero set only separates one map's free space from the space behind another map's
/// surface (under counters, behind objects), a few percent, or none. At 0.1 RedKitchen's
/// invented area falls from 29 % to 16 % with no loss of completeness (BENCHMARKS.md); 0.2
/// tears holes in the noisy synthetic bunny, whose votes are a fifth outliers.
const MEASURED_SHARE: f32 = 0.1;

/// How near, in spans of a tetrahedron (the largest coordinate difference of its corners'
/// centres: the cube side where its cells share one size), the votes at one of its corners
/// must place the surface for the tetrahedron to carry surface on that evidence alone.
const NEAR_SURFACE_SPANS: f64 = 1.0;

/// Whether the data supports a surface in a tetrahedron of an observed dual cell: the votes at
/// one of its corners put the surface within [`NEAR_SURFACE_SPANS`] of that corner, or samples
/// reached two of its four cells and its own votes pass the dual cell's [`MEASURED_SHARE`].
/// The dual cell's test (samples in one of eight cells, a tenth of the votes
/// measured) lets a cell of coarse cubes carry surface anywhere in it; at depth edges and in
/// crevices that left fringes and bridges one to three cubes wide beyond every sample
/// (RedKitchen, 100 frames: 2.9 % of the mesh farther than 3 finest cubes from every input
/// pixel; 1.9 % with this test, at the same completeness).
/// Within 1.5 spans it trims less (2.1 %); within 1 span alone (no pinhole fill) it opened
/// holes in the noisy bunnies of `tests/quality.rs`, which [`pinholes::fill_pinholes`] closes; a
/// share of 0.15 opens holes in the clean one.
fn tetrahedron_supported(t: &[&Corner; 4]) -> bool {
    let mut span: f64 = 0.0;
    for (i, a) in t.iter().enumerate() {
        for b in t.iter().skip(i + 1) {
            span = span.max((a.center - b.center).abs().max_element());
        }
    }
    // NaN offsets (nothing measured) compare false.
    if t.iter().any(|c| c.offset.abs() <= NEAR_SURFACE_SPANS * span) {
        return true;
    }
    let sampled = t.iter().filter(|c| c.sampled).count();
    let votes: f32 = t.iter().map(|c| c.votes).sum();
    let measured: f32 = t.iter().map(|c| c.measured).sum();
    sampled >= 2 && measured >= MEASURED_SHARE * votes
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

/// Per child index of a cube in its parent (octant bits x = 1, y = 2, z = 4), the corners
/// (bit `c` for corner `c`) whose dual cell the cube cannot generate, known without a probe:
/// an octant that comes before the cube's own around the corner holds a cell of the parent,
/// so a sibling or a sibling's descendant, at least as deep as the cube (the cut tiles the
/// root, and the parent is not in it), comes first. Along an axis, a corner on the cube's
/// low face looks back one cell (into the parent only if the cube is the high child), and one
/// on its high face looks ahead one cell (only if it is the low child); the other octant of
/// that axis is the cube itself. About 4.6 of a cube's 8 corners go without a probe this way.
const CORNERS_LOST_TO_A_SIBLING: [u8; 8] = {
    let mut table = [0u8; 8];
    let mut child = 0;
    while child < 8 {
        let mut corner = 0;
        while corner < 8 {
            let own = 7 - corner;
            let mut octant = 0;
            while octant < own {
                let mut in_parent = true;
                let mut axis = 0;
                while axis < 3 {
                    let (c, o, i) = ((corner >> axis) & 1, (octant >> axis) & 1, (child >> axis) & 1);
                    if (c == 0 && o == 0 && i == 0) || (c == 1 && o == 1 && i == 1) {
                        in_parent = false;
                    }
                    axis += 1;
                }
                if in_parent {
                    table[child] |= 1 << corner;
                }
                octant += 1;
            }
            corner += 1;
        }
        child += 1;
    }
    table
};

pub(super) fn full_side(depth: u8) -> u64 {
    1u64 << (u32::from(MAX_DEPTH) - u32::from(depth))
}

/// A unit's sorted cut, with its [`KeyBlocks`]: a probe's cube is looked up among the few keys
/// of the probe's block. (A search over the whole cut, galloping outwards from the probing
/// cube, took about 15 comparisons a probe over a megabyte of keys: half of this module's time
/// on RedKitchen.)
struct UnitCut<'k> {
    keys: &'k [CubeKey],
    values: &'k [CutValue],
    blocks: KeyBlocks,
}

impl<'k> UnitCut<'k> {
    fn new(keys: &'k [CubeKey], values: &'k [CutValue]) -> UnitCut<'k> {
        UnitCut {
            keys,
            values,
            blocks: KeyBlocks::of(keys),
        }
    }

    /// The index of the key that is `probe` (a finest cell) or an ancestor of it, if the cut
    /// holds one.
    fn position_of(&self, probe: CubeKey) -> Option<usize> {
        self.blocks.ancestor_or_self(self.keys, probe)
    }

    /// The cut cube containing the finest cell `probe` (a key of depth [`MAX_DEPTH`]), and its
    /// values. The cut tiles the root, so a cube of the unit that contains the cell is the
    /// answer; cells it does not hold go to the level's lookup.
    fn cube_containing(&self, level: &mut LevelCut<'_, '_>, probe: CubeKey) -> Result<Option<(CubeKey, CutValue)>> {
        let found = self
            .position_of(probe)
            .and_then(|position| self.keys.get(position).zip(self.values.get(position)));
        match found {
            Some((key, value)) => Ok(Some((*key, *value))),
            None => level.cube_containing(probe),
        }
    }
}

/// A cell a dual-cell corner probes, along one axis. Outside the root the octree continues as
/// its mirror image across the root's faces, with u = +1: neighbouring dual cells then agree
/// on every virtual cell.
#[derive(Clone, Copy)]
struct ProbeCell {
    /// Whether the cell lies past one of the root's faces (the probe reads its mirror image).
    mirrored: bool,
    /// Whether that face is the root's low one.
    below_root: bool,
    /// The probed coordinate's share of the probe key's Morton code ([`axis_bits`]): the
    /// cell's, or its mirror image's inside the root.
    axis_bits: u128,
}

impl ProbeCell {
    /// The four cells along `axis` that the corners of `cube` (corner coordinate `corner` and
    /// side `side` in full-resolution cells) probe: `corner - 1`, `corner`, `corner + side - 1`
    /// and `corner + side`, their Morton bits by dilated arithmetic from the cube's own
    /// (only cells past the root's faces are encoded anew).
    fn around(cube: CubeKey, axis: usize, corner: u64, side: u64) -> [ProbeCell; 4] {
        let own = corner_axis_bits(cube, axis);
        let one = axis_bits(1);
        // The side is a power of two: one bit of the dilated form (past its 96 bits for the
        // root, whose cells past its faces are encoded anew below).
        let side_bits = 1u128 << (3 * side.trailing_zeros());
        let inside = |axis_bits: u128| ProbeCell {
            mirrored: false,
            below_root: false,
            axis_bits,
        };
        let last = corner + side - 1;
        [
            if corner == 0 {
                ProbeCell::at(-1)
            } else {
                inside(sub_axis_bits(own, one))
            },
            inside(own),
            // The cube's corner is a multiple of its side: its last cell only sets low bits.
            inside(own | sub_axis_bits(side_bits, one)),
            if last + 1 >= 1 << 32 {
                ProbeCell::at((last + 1) as i64)
            } else {
                inside(add_axis_bits(own, side_bits))
            },
        ]
    }

    fn at(cell: i64) -> ProbeCell {
        let limit = 1i64 << 32;
        let (mirrored, inside) = if cell < 0 {
            (true, -1 - cell)
        } else if cell >= limit {
            (true, 2 * limit - 1 - cell)
        } else {
            (false, cell)
        };
        let probe = inside.clamp(0, limit - 1) as u32;
        ProbeCell {
            mirrored,
            below_root: cell < 0,
            axis_bits: axis_bits(probe),
        }
    }
}

/// What the dual cells say about each vertex of a unit's piece, besides its position.
#[derive(Default)]
pub(super) struct VertexGuides {
    /// The centres of the two cells of the vertex's edge.
    pub ends: Vec<(DVec3, DVec3)>,
    /// The offset planes of the cells around the vertex that have one ([`OffsetPlane`]), and
    /// how far they may move it: half its edge's length (smoothing may move it another half).
    pub moves: Vec<VertexMove>,
    /// For the watertight surface, vertices of the surface the observed one keeps (with
    /// repeats), which anchor the pieces they belong to ([`drop_unobserved_pieces`]).
    pub anchors: Vec<u32>,
}

/// The surface offsets of a dual cell's corners fitted by a linear function, `value` at
/// `point` plus `gradient` times the displacement: the TSDF's plane through the cell. Its zero
/// set is where the measured distances put the surface inside the cell, off the cell's edges
/// as well as on them.
#[derive(Clone, Copy)]
struct OffsetPlane {
    point: DVec3,
    value: f64,
    gradient: DVec3,
}

/// The least length of a cell's offset gradient for its plane to be used: the offsets of a
/// cell near one surface grow by one unit of length per unit of length along the normal (more
/// for a map that looks at it obliquely, since they are measured along rays); much less means
/// the corners measured different surfaces (both sides of a thin part) or mostly noise.
const LEAST_OFFSET_GRADIENT: f64 = 0.5;

/// How far (as a share of the cell's extent) an offset plane may put a corner on the other
/// side of the surface than u does before the plane is dropped ([`OffsetPlane::fit`]).
/// Measured (bench cases of `tools/bench`, bunny and dragon at 0.2 % depth noise; RedKitchen,
/// 100 frames, rendered from frame 500): without the test, the bunny with a fifth of its
/// pixels wild has Chamfer 0.00685 (0.00442 with vertices on their edges); at 0.25 of the
/// extent 0.00507, at 0.1 0.00461, at 0.05 0.00452, at 0 0.00447. But at 0.1 and below most
/// planes on RedKitchen's flat surfaces are dropped (u's transition is off by about a cube
/// there, which is what the planes correct) and the grid-aligned grain comes back in the
/// close view, although the table's mean normal deviation reads 5.33 degrees (5.36 at 0.25):
/// the pictures decide, and at 0.25 they match those without the test.
const SIDE_DISAGREEMENT: f64 = 0.25;

impl OffsetPlane {
    /// The least-squares fit to the corners' offsets, if every corner is a real cell with a
    /// measured offset, the centres span space, and the gradient is steep enough.
    fn fit(corners: &[Corner; 8]) -> Option<Self> {
        if corners.iter().any(|c| c.id & VIRTUAL != 0 || !c.offset.is_finite()) {
            return None;
        }
        let point = corners.iter().map(|c| c.center).sum::<DVec3>() / 8.0;
        let value = corners.iter().map(|c| c.offset).sum::<f64>() / 8.0;
        let mut normal_matrix = glam::DMat3::ZERO;
        let mut right = DVec3::ZERO;
        for c in corners {
            let d = c.center - point;
            normal_matrix += glam::DMat3::from_cols(d * d.x, d * d.y, d * d.z);
            right += d * (c.offset - value);
        }
        // Corners that coincide (a coarse leaf in several octants) or lie in a plane leave
        // the fit without a gradient across them. (Centres and offsets are finite here, so the
        // determinant is too.)
        let scale = normal_matrix.x_axis.x + normal_matrix.y_axis.y + normal_matrix.z_axis.z;
        if normal_matrix.determinant() <= 1e-6 * scale * scale * scale {
            return None;
        }
        let gradient = normal_matrix.inverse() * right;
        let length = gradient.length();
        if length < LEAST_OFFSET_GRADIENT {
            return None;
        }
        // u, robust to outliers, says which corners are outside (u > 0) and which inside; the
        // offsets, means of all votes, can be dragged by outliers. A plane that puts a corner
        // clearly on the other side (more than a quarter of the cell's extent) is not used.
        let (lo, hi) = corners.iter().fold(
            (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
            |(lo, hi), c| (lo.min(c.center), hi.max(c.center)),
        );
        let tolerance = SIDE_DISAGREEMENT * (hi - lo).max_element();
        let agrees = corners.iter().all(|c| {
            let distance = (value + gradient.dot(c.center - point)) / length;
            if c.u > 0.0 {
                distance >= -tolerance
            } else {
                distance <= tolerance
            }
        });
        agrees.then_some(Self { point, value, gradient })
    }

    /// The zero set as `normal . x = distance`, `normal` of unit length.
    fn normal_form(&self) -> (DVec3, f64) {
        let length = self.gradient.length();
        let normal = self.gradient / length;
        (normal, normal.dot(self.point) - self.value / length)
    }
}

/// A unit's piece while its dual cells are meshed.
#[derive(Default)]
struct Piece {
    mesh: UnitMesh,
    guides: VertexGuides,
    /// The piece's vertices by name, as indices into `mesh.vertices`.
    vertex_index: NameIndex,
    /// The cut tetrahedra that their own corners do not support, for
    /// [`pinholes::fill_pinholes`].
    held: Vec<pinholes::HeldTetrahedron>,
}

/// The surface pieces of a unit's dual cells, as much of them as `surface` says ([`mesh_cell`]);
/// and what the cells say about each vertex ([`VertexGuides`]).
pub(super) fn dual_cells_of_unit(
    scene: &Scene,
    level: &mut LevelCut<'_, '_>,
    keys: &[CubeKey],
    values: &[CutValue],
    surface: Surface,
) -> Result<(UnitMesh, VertexGuides)> {
    // RedKitchen's pieces have about 0.4 vertices a cube: room for half as many as cubes
    // saves most of the index's growth. (The same room in the piece's lists as well saved
    // little time and raised extraction's peak by 15 to 30 MB: measured 2026-12-02.)
    let mut piece = Piece {
        vertex_index: NameIndex::with_capacity(keys.len() / 2),
        ..Piece::default()
    };
    let cut = UnitCut::new(keys, values);
    for (key, own) in keys.iter().zip(values) {
        let d = key.depth();
        let side = full_side(d);
        let [x, y, z] = key.corner_full_resolution().map(u64::from);
        // The cells the corners' octants probe lie at one of four coordinates per axis (a
        // face's coordinate less one, or itself, at the cube's low or high face): their Morton
        // bits once per cube, not three encodings per probe.
        let probe_cells: [[ProbeCell; 4]; 3] =
            std::array::from_fn(|axis| ProbeCell::around(*key, axis, [x, y, z][axis], side));
        // The root (depth 0) has no parent and no siblings.
        let child = if d == 0 {
            0
        } else {
            let at = side.trailing_zeros();
            ((x >> at) & 1) | ((y >> at) & 1) << 1 | ((z >> at) & 1) << 2
        };
        let lost = CORNERS_LOST_TO_A_SIBLING.get(child as usize).copied().unwrap_or(0);
        for corner in 0..8u64 {
            if lost & (1 << corner) != 0 {
                continue;
            }
            // The 8 octants around V, with the leaf (or virtual exterior cell) in each. This cube
            // fills the octant opposite the corner; it generates V's cell only if no real leaf
            // is deeper and none as deep comes first in octant order, so the probes stop at the
            // first leaf that rules it out (most corners of a uniform region end at octant 0).
            let own_octant = (7 - corner) as usize;
            // Filled in octant order as the probes find them (most corners stop at their first
            // probe, so the eight slots are not written ahead).
            let mut incident = ArrayVec::<Incident, 8>::new();
            for octant in 0..8 {
                if octant == own_octant {
                    incident.push(Incident {
                        leaf: *key,
                        value: *own,
                        mirrored: 0,
                        below_root: 0,
                    });
                    continue;
                }
                let o = octant as u64;
                // Along each axis: the corner's side of the cube, then the octant's side of
                // the corner.
                let cells: [ProbeCell; 3] = std::array::from_fn(|axis| {
                    let at = 2 * ((corner >> axis) & 1) + ((o >> axis) & 1);
                    probe_cells[axis][at as usize]
                });
                let mirrored = (0..3).fold(0u8, |m, axis| m | (u8::from(cells[axis].mirrored) << axis));
                let below_root = (0..3).fold(0u8, |m, axis| m | (u8::from(cells[axis].below_root) << axis));
                let probe = CubeKey::from_morton(
                    cells[0].axis_bits | cells[1].axis_bits << 1 | cells[2].axis_bits << 2,
                    MAX_DEPTH,
                );
                let Some((leaf, value)) = cut.cube_containing(level, probe)? else {
                    break;
                };
                if mirrored == 0 && (leaf.depth() > d || (leaf.depth() == d && octant < own_octant)) {
                    break;
                }
                incident.push(Incident {
                    leaf,
                    value,
                    mirrored,
                    below_root,
                });
            }
            // Most corners fail at their first probe (another leaf generates them), and most
            // that this cube generates have no sign change: their corners' centres are never
            // computed.
            let Ok(incident) = incident.into_inner() else {
                continue;
            };
            // Generated by the deepest real leaf, first in octant order.
            let real = |c: &&Incident| c.mirrored == 0;
            let deepest = incident.iter().filter(real).map(|c| c.leaf.depth()).max();
            let first = incident
                .iter()
                .position(|c| c.mirrored == 0 && Some(c.leaf.depth()) == deepest);
            if first.and_then(|i| incident.get(i)).is_none_or(|c| c.leaf != *key) {
                continue;
            }
            let positive = incident.iter().filter(|c| c.u() > 0.0).count();
            if positive == 0 || positive == 8 {
                continue;
            }
            let corners = incident.map(|c| c.corner(scene));
            let gradient = cell_gradient(&corners);
            mesh_cell(&corners, gradient, surface, &mut piece);
        }
    }
    pinholes::fill_pinholes(&mut piece);
    Ok((piece.mesh, piece.guides))
}

/// Gradient of u over a dual cell (mean difference between opposite faces of the 8 corners,
/// per axis), for vertex normals.
fn cell_gradient(corners: &[Corner; 8]) -> DVec3 {
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
    gradient
}

/// The vertices of a cut tetrahedron's surface polygon, in order around it, as pairs of
/// corner indices (inside, outside) into the tetrahedron: at most four, in a fixed array (a
/// list per cut tetrahedron allocated).
fn polygon_edges(t: &[&Corner; 4]) -> ArrayVec<(usize, usize), 4> {
    // The corners on each side, in order.
    let (mut inside, mut outside) = (ArrayVec::<usize, 4>::new(), ArrayVec::<usize, 4>::new());
    for (i, c) in t.iter().enumerate() {
        // A NaN u is on neither side. Four corners fill either side at most.
        let _ = if c.u <= 0.0 {
            inside.try_push(i)
        } else if c.u > 0.0 {
            outside.try_push(i)
        } else {
            continue;
        };
    }
    match (inside.as_slice(), outside.as_slice()) {
        (&[apex], others) | (others, &[apex]) => others.iter().map(|&other| (apex, other)).collect(),
        (&[i0, i1], &[o0, o1]) => ArrayVec::from([(i0, o0), (i0, o1), (i1, o1), (i1, o0)]),
        _ => ArrayVec::new(),
    }
}

/// The name of the surface vertex on the edge between two corners.
fn vertex_name(a: &Corner, b: &Corner) -> VertexId {
    if a.id <= b.id { (a.id, b.id) } else { (b.id, a.id) }
}

/// Cuts the dual cell's 6 Kuhn tetrahedra at u = 0 and adds the triangles, oriented towards
/// positive u, to `mesh`; vertices are found or added by name through `vertex_index`, and each
/// triangle's vertices accumulate the cell's `gradient` as their normal. For the observed
/// surface, a tetrahedron adds nothing unless depth maps saw all four of its cells and samples
/// reached one of the dual cell's eight; one whose own corners do not support a surface
/// ([`tetrahedron_supported`]) is held for [`pinholes::fill_pinholes`] (module docs of
/// `stages::extract`, "Observed surface only"). The watertight and the whole surface mesh every
/// cut tetrahedron; for the watertight one, the vertices of those the observed surface keeps
/// are its anchors ([`VertexGuides::anchors`]).
fn mesh_cell(corners: &[Corner; 8], gradient: DVec3, surface: Surface, piece: &mut Piece) {
    let every = surface != Surface::Observed;
    let plane = OffsetPlane::fit(corners);
    // Each of the 6 tetrahedra adds at most 4 vertices.
    let mut cell_vertices = ArrayVec::<u32, 24>::new();
    let votes: f32 = corners.iter().map(|c| c.votes).sum();
    let measured: f32 = corners.iter().map(|c| c.measured).sum();
    let cell_observed = corners.iter().any(|c| c.sampled) && measured >= MEASURED_SHARE * votes;
    for tet in KUHN {
        // The corners by reference: a tetrahedron's copy is a quarter of a kilobyte, made
        // six times a cell.
        let t = tet.map(|i| &corners[i]);
        let observed = cell_observed && t.iter().all(|c| c.votes > 0.0);
        if !(every || observed) {
            continue;
        }
        let positive = t.iter().filter(|c| c.u > 0.0).count();
        if positive == 0 || positive == 4 {
            continue;
        }
        let supported = observed && tetrahedron_supported(&t);
        if !(every || supported) {
            piece.held.push(pinholes::HeldTetrahedron {
                corners: t.map(|c| *c),
                gradient,
            });
            continue;
        }
        let polygon = mesh_tetrahedron(&t, gradient, piece);
        if surface == Surface::Watertight && supported {
            piece.guides.anchors.extend_from_slice(&polygon);
        }
        // 6 tetrahedra of at most 4 vertices each fit.
        let _ = cell_vertices.try_extend_from_slice(&polygon);
    }
    let Some(plane) = plane else { return };
    let (normal, distance) = plane.normal_form();
    cell_vertices.sort_unstable();
    let mut last = None;
    for &vi in cell_vertices.iter() {
        if last == Some(vi) {
            continue;
        }
        last = Some(vi);
        if let Some(share) = piece.guides.moves.get_mut(vi as usize) {
            share.add_plane(normal, distance);
        }
    }
}

/// Adds the surface polygon of a cut tetrahedron to the piece (triangles oriented towards
/// positive u, vertices found or added by name) and returns its vertices.
fn mesh_tetrahedron(t: &[&Corner; 4], gradient: DVec3, piece: &mut Piece) -> ArrayVec<u32, 4> {
    let Piece {
        mesh,
        guides,
        vertex_index,
        ..
    } = piece;
    let mut polygon = ArrayVec::<u32, 4>::new();
    for (a, b) in polygon_edges(t) {
        let (ca, cb) = (t[a], t[b]);
        let edge = vertex_name(ca, cb);
        let vertices = &mesh.vertices;
        let index = match vertex_index.entry(edge, |i| vertices.get(i as usize).map(|v| v.0)) {
            hashbrown::hash_table::Entry::Occupied(found) => *found.get(),
            hashbrown::hash_table::Entry::Vacant(slot) => {
                let (lo, hi) = if ca.id <= cb.id { (ca, cb) } else { (cb, ca) };
                let position = lo.center + (hi.center - lo.center) * crossing(lo, hi);
                let index = mesh.vertices.len() as u32;
                mesh.vertices.push((edge, position, DVec3::ZERO));
                guides.ends.push((lo.center, hi.center));
                guides
                    .moves
                    .push(VertexMove::empty(index, 0.5 * (hi.center - lo.center).length()));
                *slot.insert(index).get()
            }
        };
        // At most four edges.
        let _ = polygon.try_push(index);
    }
    for &vi in &polygon {
        if let Some(v) = mesh.vertices.get_mut(vi as usize) {
            v.2 += gradient;
        }
    }
    // Orient towards positive u (outside).
    let centroid = |outside: bool| {
        let (sum, count) = t
            .iter()
            .filter(|c| (c.u > 0.0) == outside)
            .fold((DVec3::ZERO, 0u32), |(sum, count), c| (sum + c.center, count + 1));
        sum / f64::from(count.max(1))
    };
    let to_outside = centroid(true) - centroid(false);
    for k in 1..polygon.len().saturating_sub(1) {
        let (Some(&a), Some(&b), Some(&c)) = (polygon.first(), polygon.get(k), polygon.get(k + 1)) else {
            continue;
        };
        let mut tri = [a, b, c];
        if tri[0] == tri[1] || tri[1] == tri[2] || tri[0] == tri[2] {
            continue;
        }
        let p = tri.map(|i| mesh.position(i));
        let normal = (p[1] - p[0]).cross(p[2] - p[0]);
        if normal.dot(to_outside) < 0.0 {
            tri.swap(1, 2);
        }
        mesh.triangles.push(tri);
    }
    polygon
}

#[cfg(test)]
mod tests;
