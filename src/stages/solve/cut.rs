//! Reading a solved level: the values of each cut cube ([`CutValue`]) and which cut cube
//! holds a point ([`LevelCut`]), for extraction and queries.

use std::collections::BTreeMap;
use std::sync::Arc;

use super::{LEVEL_STAGES, LevelSegments};
use crate::format::key::{axis_bits, corner_axis_bits};
use crate::format::segment::SegmentReader;
use crate::format::{CubeKey, MAX_DEPTH};
use crate::stages::treetop::Treetop;
use crate::store::{Result, Snapshot};

/// The side of `cube` in finest cells.
fn full_resolution_side(cube: CubeKey) -> u64 {
    1u64 << (u32::from(MAX_DEPTH) - u32::from(cube.depth().min(MAX_DEPTH)))
}

/// Whether a cube meets a box of full-resolution cells, `[low, high)` per axis, tested on the
/// cube's Morton code: spreading a coordinate's bits keeps its order, so the corner's bits
/// compare with the bounds' as the corner does with the bounds. Decoding the corner of every
/// key of every neighbour group a unit's extraction reads took about a tenth of extraction's
/// CPU (`perf` on RedKitchen: 17 K samples before, 15 K after).
pub(super) struct WindowTest {
    /// Per axis, the bits of `high` (`None` past the largest corner: every corner is below).
    below: [Option<u128>; 3],
    /// Per depth and axis, the bits of the least corner of a cube of that depth that reaches
    /// `low` (`corner + side > low`).
    least: [[u128; 3]; MAX_DEPTH as usize + 1],
}

impl WindowTest {
    /// The box of the cubes of treetop units `units` grown by one finest cell: it meets every
    /// cube that touches one of them.
    pub(super) fn around_units(treetop: &Treetop, units: &[usize]) -> WindowTest {
        let (mut low, mut high) = ([u64::MAX; 3], [0u64; 3]);
        for unit in units.iter().filter_map(|&u| treetop.units.get(u)) {
            let corner = unit.key.corner_full_resolution().map(u64::from);
            let side = full_resolution_side(unit.key);
            for axis in 0..3 {
                low[axis] = low[axis].min(corner[axis].saturating_sub(1));
                high[axis] = high[axis].max(corner[axis] + side + 1);
            }
        }
        WindowTest::new(low, high)
    }

    fn new(low: [u64; 3], high: [u64; 3]) -> WindowTest {
        let bits = |c: u64| u32::try_from(c).ok().map(axis_bits);
        WindowTest {
            below: high.map(bits),
            least: std::array::from_fn(|depth| {
                let side = 1u64 << (u32::from(MAX_DEPTH) - depth as u32);
                // low <= 2^32, so the least corner fits in 32 bits.
                low.map(|low| bits(low.saturating_add(1).saturating_sub(side)).unwrap_or(u128::MAX))
            }),
        }
    }

    fn meets(&self, key: CubeKey) -> bool {
        let least = self
            .least
            .get(usize::from(key.depth().min(MAX_DEPTH)))
            .unwrap_or(&[0; 3]);
        least.iter().zip(&self.below).enumerate().all(|(axis, (least, below))| {
            let corner = corner_axis_bits(key, axis);
            corner >= *least && below.is_none_or(|below| corner < below)
        })
    }

    /// Whether a cube of a cut (no key is another's ancestor) whose keys run from `first` to
    /// `last` may meet the window. The cut's cubes between them lie in the Morton interval from
    /// `first`'s corner to the end of `last`'s cube; that interval is covered by aligned cubes,
    /// those it holds whole tested as cubes, those at its two ends split again down to
    /// [`RANGE_SPLIT_LEVELS`] below the smallest cube holding the interval (beyond, they count
    /// as meeting: the answer errs only towards `true`).
    pub(super) fn may_meet_cut_between(&self, first: CubeKey, last: CubeKey) -> bool {
        self.may_meet_codes(first.morton(), last.subtree_last().morton())
    }

    /// [`WindowTest::may_meet_cut_between`] for any sorted keys, a whole octree's among them:
    /// the keys between `first` and `last` may then include ancestors of `last`, and the
    /// interval reaches the end of the largest of them that does not sort before `first`.
    pub(super) fn may_meet_keys_between(&self, first: CubeKey, last: CubeKey) -> bool {
        let mut widest = last;
        while let Some(parent) = widest.parent().filter(|parent| *parent >= first) {
            widest = parent;
        }
        self.may_meet_codes(first.morton(), widest.subtree_last().morton())
    }

    /// Whether a cube whose Morton codes lie in `[low, high]` may meet the window.
    fn may_meet_codes(&self, low: u128, high: u128) -> bool {
        // The smallest aligned cube holding [low, high]: the bits above their highest
        // differing one, rounded to whole levels.
        let varying = (u128::BITS - (low ^ high).leading_zeros()).div_ceil(3);
        let depth = u32::from(MAX_DEPTH).saturating_sub(varying) as u8;
        let code = low & !span_of(depth);
        self.may_meet_interval(low, high, code, depth, RANGE_SPLIT_LEVELS)
    }

    fn may_meet_interval(&self, low: u128, high: u128, code: u128, depth: u8, splits: u32) -> bool {
        let end = code | span_of(depth);
        if end < low || code > high || !self.meets(CubeKey::from_morton(code, depth)) {
            return false;
        }
        if (low <= code && end <= high) || splits == 0 || depth >= MAX_DEPTH {
            return true;
        }
        let child_span = span_of(depth + 1) + 1;
        (0..8u128).any(|child| self.may_meet_interval(low, high, code | (child * child_span), depth + 1, splits - 1))
    }
}

/// How far [`WindowTest::may_meet_cut_between`] splits the ends of a key interval: enough to
/// tell a block along a unit's face from one behind it, at a few hundred tests a block.
const RANGE_SPLIT_LEVELS: u32 = 6;

/// The Morton codes a cube of `depth` spans beyond its corner's: all bits below its size.
fn span_of(depth: u8) -> u128 {
    let bits = 3 * u32::from(MAX_DEPTH - depth.min(MAX_DEPTH));
    (1u128 << bits) - 1
}

/// The indicator of a cut cube and what the data says about it (`stages::observed`). Equal
/// values are bit for bit equal (a missing offset is NaN, which equals itself here).
#[derive(Clone, Copy, Debug)]
pub struct CutValue {
    pub u: f32,
    /// [`seen_weight`](crate::stages::observed::seen_weight): the cube's whole vote weight.
    pub votes: f32,
    /// [`measured_weight`](crate::stages::observed::measured_weight): the part of `votes` that measured a distance to a surface.
    pub measured: f32,
    /// Samples spawned the cube or a descendant, or samples other than spikes an ancestor
    /// ([`sampled_nodes`](crate::stages::observed::sampled_nodes)).
    pub sampled: bool,
    /// [`surface_offset`](crate::stages::observed::surface_offset), in world units: NaN when no vote measured a distance.
    pub offset: f32,
}

impl CutValue {
    /// Whether a depth map saw the cube: it has votes.
    pub fn seen(&self) -> bool {
        self.votes > 0.0
    }
}

impl PartialEq for CutValue {
    fn eq(&self, other: &CutValue) -> bool {
        self.u.to_bits() == other.u.to_bits()
            && self.votes.to_bits() == other.votes.to_bits()
            && self.measured.to_bits() == other.measured.to_bits()
            && self.sampled == other.sampled
            && self.offset.to_bits() == other.offset.to_bits()
    }
}

/// Sorted cut keys of a unit at one level and their values.
pub type LeafValues = (Vec<CubeKey>, Vec<CutValue>);

/// Reads a level segment's keys, u and what the data says about each cube ([`CutValue`]) only:
/// what the indicator field needs (extraction and queries), without decoding v, p and q, which
/// are 3.4 times the bytes. A segment written before those columns existed reads as seen,
/// measured and sampled everywhere, with no offsets (extraction then gives the closed
/// surface).
pub fn read_level_u(snapshot: &Snapshot<'_>, segment: &str) -> Result<LeafValues> {
    read_level_u_where(snapshot, segment, |_, _| true)
}

/// [`read_level_u`] of the blocks whose first and last keys `keep` accepts (level segments
/// have blocks of [`FACE_READ_BLOCK_ROWS`](crate::stages::FACE_READ_BLOCK_ROWS) rows).
fn read_level_u_where(
    snapshot: &Snapshot<'_>,
    segment: &str,
    keep: impl Fn(CubeKey, CubeKey) -> bool,
) -> Result<LeafValues> {
    let file = snapshot.open_segment(segment)?;
    let whole = file.reader()?;
    let reader: SegmentReader<'_> = whole.with_blocks_where(keep);
    let c = |e| file.corruption(e);
    let keys = reader.read_keys().map_err(c)?;
    let (_, u) = reader.read_f32("u").map_err(c)?;
    let optional = |name: &str, missing: f32| -> Result<Vec<f32>> {
        if reader.column(name).is_ok() {
            Ok(reader.read_f32(name).map_err(c)?.1)
        } else {
            Ok(vec![missing; keys.len()])
        }
    };
    let seen = optional("seen", 1.0)?;
    let offset = optional("surface_offset", f32::NAN)?;
    let measured = if reader.column("measured").is_ok() {
        reader.read_f32("measured").map_err(c)?.1
    } else {
        seen.clone()
    };
    let sampled = if reader.column("sampled").is_ok() {
        reader.read_u32("sampled").map_err(c)?.1
    } else {
        vec![1; keys.len()]
    };
    let n = keys.len();
    if [seen.len(), offset.len(), sampled.len(), measured.len(), u.len()]
        .iter()
        .any(|len| *len != n)
    {
        return Err(file.corruption(crate::format::DecodeError::MissingColumn(
            "u, seen, sampled, surface_offset and measured of the keys' length".into(),
        )));
    }
    let values = u
        .into_iter()
        .zip(seen)
        .zip(sampled)
        .zip(offset)
        .zip(measured)
        .map(|((((u, votes), sampled), offset), measured)| CutValue {
            u,
            votes,
            measured,
            sampled: sampled > 0,
            offset,
        })
        .collect();
    Ok((keys, values))
}

/// The values of one solved level, unit by unit, loaded on demand; answers "which cut cube
/// contains this point".
pub struct LevelCut<'a, 's> {
    snapshot: &'a Snapshot<'s>,
    treetop: &'a Treetop,
    segments: LevelSegments,
    /// When set, only points in this box (full-resolution cells) are asked about, and groups
    /// keep only the cubes that meet it.
    window: Option<WindowTest>,
    groups: BTreeMap<u64, Arc<LeafValues>>,
    units: BTreeMap<usize, Option<Arc<LeafValues>>>,
}

impl<'a, 's> LevelCut<'a, 's> {
    pub fn new(snapshot: &'a Snapshot<'s>, treetop: &'a Treetop, level: u8) -> LevelCut<'a, 's> {
        LevelCut {
            snapshot,
            treetop,
            segments: LevelSegments::of(snapshot, LEVEL_STAGES[usize::from(level.min(MAX_DEPTH))]),
            window: None,
            groups: BTreeMap::new(),
            units: BTreeMap::new(),
        }
    }

    /// A cut that is only asked about points within one finest cell of `cube` (its cube, the
    /// cubes touching it and its own units): a group decoded for a neighbour then keeps only
    /// the cubes that reach that shell, so memory follows `cube`'s surface, not the neighbours'
    /// volumes. Asking about a point outside gives `None` or a cube that does not hold it.
    pub fn around(snapshot: &'a Snapshot<'s>, treetop: &'a Treetop, level: u8, cube: CubeKey) -> LevelCut<'a, 's> {
        let corner = cube.corner_full_resolution().map(u64::from);
        let side = full_resolution_side(cube);
        LevelCut {
            window: Some(WindowTest::new(
                corner.map(|c| c.saturating_sub(1)),
                corner.map(|c| c + side + 1),
            )),
            ..LevelCut::new(snapshot, treetop, level)
        }
    }

    /// The values of the group that may hold treetop unit `unit`.
    fn group(&mut self, unit: usize) -> Result<Option<Arc<LeafValues>>> {
        let Some((id, name)) = self.segments.group_of(unit) else {
            return Ok(None);
        };
        if let Some(values) = self.groups.get(&id) {
            return Ok(Some(values.clone()));
        }
        let window = self.window.as_ref();
        let mut loaded = read_level_u_where(self.snapshot, name, |first, last| {
            window.is_none_or(|window| window.may_meet_cut_between(first, last))
        })?;
        if let Some(window) = window {
            // Only a cube that meets the window can hold a point of it, and dropping the others
            // leaves that cube the last key at or before such a point (the cut has no keys
            // between a cube and its descendants).
            let (keys, values) = loaded;
            loaded = keys
                .into_iter()
                .zip(values)
                .filter(|(key, _)| window.meets(*key))
                .unzip();
        }
        let loaded = Arc::new(loaded);
        self.groups.insert(id, loaded.clone());
        Ok(Some(loaded))
    }

    /// The cut cubes of treetop unit `unit` and their u; `None` when it has none.
    pub fn unit(&mut self, unit: usize) -> Result<Option<Arc<LeafValues>>> {
        if let Some(v) = self.units.get(&unit) {
            return Ok(v.clone());
        }
        let own = match self.group(unit)? {
            // A leaf unit's keys are one range in key order (its subtree's), so when the
            // group's first and last keys are the unit's, all are, and the group itself is the
            // answer, without a copy. The top unit's keys are scattered between the leaves'.
            Some(group)
                if self.treetop.units.get(unit).is_some_and(|u| !u.top)
                    && group.0.first().is_some_and(|k| self.treetop.unit_of(*k) == unit)
                    && group.0.last().is_some_and(|k| self.treetop.unit_of(*k) == unit) =>
            {
                Some(group)
            }
            Some(group) => {
                let (keys, values): (Vec<CubeKey>, Vec<CutValue>) = group
                    .0
                    .iter()
                    .zip(&group.1)
                    .filter(|(key, _)| self.treetop.unit_of(**key) == unit)
                    .map(|(key, value)| (*key, *value))
                    .unzip();
                (!keys.is_empty()).then(|| Arc::new((keys, values)))
            }
            None => None,
        };
        self.units.insert(unit, own.clone());
        Ok(own)
    }

    /// The cut cube containing the finest cell at full-resolution coordinates `cell`, and its
    /// values.
    pub fn cube_at(&mut self, cell: [u32; 3]) -> Result<Option<(CubeKey, CutValue)>> {
        self.cube_containing(CubeKey::new(MAX_DEPTH, cell[0], cell[1], cell[2]))
    }

    /// The cut cube that is `probe` or an ancestor of it, and its values.
    pub fn cube_containing(&mut self, probe: CubeKey) -> Result<Option<(CubeKey, CutValue)>> {
        let unit = self.treetop.unit_of(probe);
        // The group's cut tiles its units' cubes, so the one ancestor of the probe among its
        // keys is the answer.
        let Some(values) = self.group(unit)? else {
            return Ok(None);
        };
        let (keys, cut_values) = (&values.0, &values.1);
        Ok(cut_cube_ending_at(
            keys,
            cut_values,
            keys.partition_point(|k| *k <= probe),
            probe,
        ))
    }
}

/// The cube of a sorted cut (`keys`, their values) just before `position`, the cut's first key
/// after `probe`, when it contains `probe`: the cut tiles what it covers, so that cube is the
/// only candidate.
fn cut_cube_ending_at<T: Copy>(
    keys: &[CubeKey],
    values: &[T],
    position: usize,
    probe: CubeKey,
) -> Option<(CubeKey, T)> {
    position
        .checked_sub(1)
        .and_then(|i| keys.get(i).zip(values.get(i)))
        .filter(|(k, _)| k.is_ancestor_or_self_of(probe))
        .map(|(k, value)| (*k, *value))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A repeatable stream of 64-bit numbers.
    fn xorshift(mut state: u64) -> impl FnMut() -> u64 {
        move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        }
    }

    #[test]
    fn the_window_test_on_morton_codes_agrees_with_decoded_corners() {
        let mut next = xorshift(0x9E37_79B9_7F4A_7C15u64);
        let (mut inside, mut outside) = (0, 0);
        for _ in 0..200 {
            // Windows as `LevelCut::around` makes them, around cubes of any depth, the root's
            // faces included.
            let depth = (next() % u64::from(MAX_DEPTH + 1)) as u8;
            let coordinate = |r: u64| (r % (1u64 << depth)) as u32;
            let cube = CubeKey::new(depth, coordinate(next()), coordinate(next()), coordinate(next()));
            let corner = cube.corner_full_resolution().map(u64::from);
            let side = full_resolution_side(cube);
            let (low, high) = (corner.map(|c| c.saturating_sub(1)), corner.map(|c| c + side + 1));
            let window = WindowTest::new(low, high);
            for _ in 0..200 {
                // Keys near the window: its cube's neighbours at other depths, and any.
                let depth = (next() % u64::from(MAX_DEPTH + 1)) as u8;
                let shift = u32::from(MAX_DEPTH - depth);
                let near = |axis: usize, r: u64| {
                    let jitter = (r % 5) as i64 - 2;
                    let c = (corner[axis] as i64 + jitter * side.min(1 << 20) as i64).clamp(0, u32::MAX as i64);
                    ((c as u64) >> shift) as u32
                };
                let any = |r: u64| (r % (1u64 << depth)) as u32;
                let key = if next().is_multiple_of(4) {
                    CubeKey::new(depth, any(next()), any(next()), any(next()))
                } else {
                    CubeKey::new(depth, near(0, next()), near(1, next()), near(2, next()))
                };
                let key_corner = key.corner_full_resolution().map(u64::from);
                let key_side = full_resolution_side(key);
                let expected = (0..3).all(|a| key_corner[a] < high[a] && key_corner[a] + key_side > low[a]);
                assert_eq!(window.meets(key), expected, "{key:?} in [{low:?}, {high:?})");
                if expected {
                    inside += 1;
                } else {
                    outside += 1;
                }
            }
        }
        assert!(inside > 1000 && outside > 1000, "{inside} inside, {outside} outside");
    }

    /// A cut of mixed depths (random subdivisions of the root, down to depth 8) and the whole
    /// octree above it, their keys in runs as a segment's blocks hold them: a run with a cube
    /// that meets a window always may meet it, and most runs far from the window are told
    /// apart.
    #[test]
    fn a_key_run_that_holds_a_cube_in_the_window_may_meet_it() {
        let mut next = xorshift(0x2545_F491_4F6C_DD1Du64);
        let (mut cut, mut octree) = (Vec::new(), Vec::new());
        let mut open = vec![CubeKey::new(0, 0, 0, 0)];
        while let Some(cube) = open.pop() {
            octree.push(cube);
            let depth = cube.depth();
            // Deep along a plane (a surface), shallow elsewhere, as an octree is.
            let z = u64::from(cube.corner_full_resolution()[2]);
            let on_plane = (z..z + full_resolution_side(cube)).contains(&0x5555_5555);
            if depth < 8 && (depth < 3 || (on_plane && !next().is_multiple_of(8)) || next().is_multiple_of(4)) {
                let [x, y, z] = cube.coords();
                for child in 0..8u32 {
                    open.push(CubeKey::new(
                        depth + 1,
                        2 * x + (child & 1),
                        2 * y + (child >> 1 & 1),
                        2 * z + (child >> 2),
                    ));
                }
            } else {
                cut.push(cube);
            }
        }
        cut.sort();
        octree.sort();
        type RangeTest = fn(&WindowTest, CubeKey, CubeKey) -> bool;
        let sets: [(&[CubeKey], RangeTest); 2] = [
            (&cut, WindowTest::may_meet_cut_between),
            (&octree, WindowTest::may_meet_keys_between),
        ];
        for (keys, may_meet) in sets {
            let (mut kept, mut told_apart, mut not_told) = (0, 0, 0);
            for _ in 0..100 {
                let cube = cut[(next() % cut.len() as u64) as usize];
                let corner = cube.corner_full_resolution().map(u64::from);
                let side = full_resolution_side(cube);
                let (low, high) = (corner.map(|c| c.saturating_sub(1)), corner.map(|c| c + side + 1));
                let window = WindowTest::new(low, high);
                let run = 1 + (next() % 64) as usize;
                for block in keys.chunks(run) {
                    let (first, last) = (block[0], block[block.len() - 1]);
                    let may = may_meet(&window, first, last);
                    if block.iter().any(|k| window.meets(*k)) {
                        assert!(may, "{first:?}..={last:?} holds a cube in [{low:?}, {high:?})");
                        kept += 1;
                    } else if may {
                        not_told += 1;
                    } else {
                        told_apart += 1;
                    }
                }
            }
            assert!(
                kept > 300 && told_apart > 4 * not_told,
                "{kept} kept, {told_apart} told apart, {not_told} not"
            );
        }
    }
}
