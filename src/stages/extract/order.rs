//! The order extraction meshes the treetop's leaves in, and so the order the weld closes their
//! seams in.
//!
//! The weld holds a seam vertex from the first leaf that meshes it until the last leaf that can
//! mesh it is done, so what it holds at once is the surface along the border between the
//! leaves done and the leaves to come. In key (Morton) order that border is a plane through the
//! whole root at the first split: the root is a cube around the scene, and a scene much wider
//! than it is high (a city, a terrain, a floor of a building) is cut by the root's first split
//! across its height, every building at mid-height, and the lower half of the whole scene is
//! meshed before the upper half. The border then holds a ring around every building: it grows
//! with the scene's area (the synthetic city: 29,083 seam vertices open at 10 M samples,
//! 323,033 at 104 M). Here each set of leaves is instead split across its widest extent, at
//! the middle, the lower side first (a k-d order of the leaves' centres): a wide scene is cut
//! into columns before any cut across its height, so the border is a wall across the scene's
//! width and grows with its side; a scene about as high as wide (a room, an object) is split
//! as the octree splits it. The order depends on the treetop alone, so every process that
//! extracts or commits a store derives the same one.

use crate::stages::treetop::Treetop;

use super::dual_cells::full_side;

/// Every treetop unit's rank in the extraction order: the internal-node unit (which meshes
/// nothing) ranks 0, the leaves 1 and up.
pub(super) struct UnitOrder {
    ranks: Vec<u32>,
    /// Leaf unit indices by rank (rank 1 first).
    leaves: Vec<usize>,
}

/// A leaf to order: its unit index and its centre, in half full-resolution cells (so that it is
/// a whole number: up to 2^33).
#[derive(Clone, Copy)]
struct Placed {
    unit: usize,
    centre: [u64; 3],
}

impl UnitOrder {
    pub(super) fn of(treetop: &Treetop) -> UnitOrder {
        let placed: Vec<Placed> = treetop
            .units
            .iter()
            .enumerate()
            .filter(|(_, unit)| !unit.top)
            .map(|(index, unit)| {
                let side = full_side(unit.key.depth());
                Placed {
                    unit: index,
                    centre: unit.key.corner_full_resolution().map(|c| 2 * u64::from(c) + side),
                }
            })
            .collect();
        let mut leaves = Vec::with_capacity(placed.len());
        split_widest(placed, &mut leaves);
        let mut ranks = vec![0u32; treetop.units.len()];
        for (position, &unit) in leaves.iter().enumerate() {
            if let Some(rank) = ranks.get_mut(unit) {
                *rank = u32::try_from(position + 1).unwrap_or(u32::MAX);
            }
        }
        UnitOrder { ranks, leaves }
    }

    /// Unit `unit`'s rank (0 for the internal-node unit, or an index past the treetop).
    pub(super) fn rank(&self, unit: usize) -> u32 {
        self.ranks.get(unit).copied().unwrap_or(0)
    }

    /// The leaf units, in extraction order.
    pub(super) fn leaves(&self) -> &[usize] {
        &self.leaves
    }
}

/// Appends `placed` to `out` in k-d order: split at the middle of the centres' widest extent
/// (the first axis of the widest, x before y before z), the lower side first, each side in
/// turn. Leaves are disjoint cubes, so their centres differ and each split parts a set of two or
/// more: the lowest centre goes below the middle and the highest above. Each split at least
/// halves the extent along its axis, and extents are whole numbers below 2^33, so the
/// recursion is at most about 3 x 34 deep.
fn split_widest(placed: Vec<Placed>, out: &mut Vec<usize>) {
    if placed.len() <= 1 {
        out.extend(placed.iter().map(|p| p.unit));
        return;
    }
    let mut lo = [u64::MAX; 3];
    let mut hi = [0u64; 3];
    for p in &placed {
        for axis in 0..3 {
            let (l, h, c) = (&mut lo[axis], &mut hi[axis], p.centre[axis]);
            *l = (*l).min(c);
            *h = (*h).max(c);
        }
    }
    let extent = |axis: usize| hi[axis] - lo[axis];
    let axis = (0..3).fold(0, |best, axis| if extent(axis) > extent(best) { axis } else { best });
    if extent(axis) == 0 {
        // Not reached for disjoint leaves; keeps the given (key) order if it were.
        out.extend(placed.iter().map(|p| p.unit));
        return;
    }
    let middle = lo[axis] + extent(axis) / 2;
    // `partition` keeps each side in the given order, so the result depends on the set alone.
    let (lower, upper): (Vec<Placed>, Vec<Placed>) = placed.into_iter().partition(|p| p.centre[axis] <= middle);
    split_widest(lower, out);
    split_widest(upper, out);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::format::CubeKey;
    use crate::stages::treetop::TreetopUnit;

    fn treetop_of(leaves: &[CubeKey]) -> Treetop {
        let unit = TreetopUnit::blank;
        let mut sorted = leaves.to_vec();
        sorted.sort();
        let mut units = vec![unit(CubeKey::new(0, 0, 0, 0), true)];
        units.extend(sorted.into_iter().map(|key| unit(key, false)));
        Treetop { units }
    }

    /// A slab 16 leaves wide and deep and 2 high (a city in a root cube): the k-d order meshes
    /// it in columns, so at no point is the border between the leaves done and those to come
    /// wider than a few columns' walls; the key order meshes the whole lower layer first.
    #[test]
    fn a_wide_flat_scene_is_meshed_column_by_column() {
        let depth = 5;
        let leaves: Vec<CubeKey> = (0..16u32)
            .flat_map(|x| (0..16u32).flat_map(move |y| (15..17u32).map(move |z| CubeKey::new(depth, x, y, z))))
            .collect();
        let treetop = treetop_of(&leaves);
        let order = UnitOrder::of(&treetop);
        assert_eq!(order.leaves().len(), leaves.len());
        assert_eq!(order.rank(0), 0);
        let mut ranks: Vec<u32> = (1..treetop.units.len()).map(|u| order.rank(u)).collect();
        ranks.sort_unstable();
        assert_eq!(ranks, (1..=leaves.len() as u32).collect::<Vec<_>>());
        // The most leaf faces between a leaf done and one to come, over the whole sweep.
        let widest_border = |sequence: &[usize]| {
            let step = full_side(depth) as i64;
            let position: std::collections::HashMap<[i64; 3], usize> = sequence
                .iter()
                .enumerate()
                .map(|(i, &u)| (treetop.units[u].key.corner_full_resolution().map(i64::from), i))
                .collect();
            (0..sequence.len())
                .map(|done| {
                    position
                        .iter()
                        .filter(|&(_, &i)| i < done)
                        .map(|(corner, _)| {
                            (0..6)
                                .filter(|&side| {
                                    let mut next = *corner;
                                    next[side / 2] += if side % 2 == 0 { step } else { -step };
                                    position.get(&next).is_some_and(|&j| j >= done)
                                })
                                .count()
                        })
                        .sum::<usize>()
                })
                .max()
                .unwrap_or(0)
        };
        let by_key: Vec<usize> = (1..treetop.units.len()).collect();
        let (kd, keyed) = (widest_border(order.leaves()), widest_border(&by_key));
        // Key order: the whole lower layer (256 faces) is open before the upper layer starts;
        // k-d order: a wall across the slab (16 x 2 faces) and the walls inside the half being
        // meshed (47, as a model of both orders in Python counted).
        assert!(keyed >= 256, "key order: {keyed}");
        assert!(kd <= 48, "k-d order: {kd} faces open at once");
    }

    #[test]
    fn a_cube_of_leaves_is_meshed_octant_by_octant() {
        // A full 4 x 4 x 4 grid of leaves: every split is one of the octree's (x, then y, then
        // z halve the root), so each octant of the root is meshed whole before the next.
        let leaves: Vec<CubeKey> = (0..64u32)
            .map(|i| CubeKey::new(2, i & 3, (i >> 2) & 3, i >> 4))
            .collect();
        let treetop = treetop_of(&leaves);
        let order = UnitOrder::of(&treetop);
        let centres: Vec<[u32; 3]> = order
            .leaves()
            .iter()
            .map(|&u| treetop.units[u].key.corner_full_resolution())
            .collect();
        // The first eight are one octant of the root, the next eight another.
        let octant = |c: &[u32; 3]| c.map(|x| x >> 31);
        for chunk in centres.chunks(8) {
            assert!(chunk.iter().all(|c| octant(c) == octant(&chunk[0])));
        }
    }
}
