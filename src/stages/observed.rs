//! What the data says about each cube of a level cut, beside u: whether a depth map saw it,
//! whether samples reached it, and where its votes put the surface. The solve stage writes them
//! as the level segment's `seen`, `sampled` and `offset` columns (format-spec.md, "Columns used
//! by stages"); extraction reads them to mesh only observed surface and to place vertices
//! inside cubes (module docs of `stages::extract`).

use std::collections::BTreeMap;

use super::ingest::SPIKE_COUNT;
use super::treetop::Treetop;
use crate::format::CubeKey;
use crate::format::key::find_sorted_from;
use crate::kernels::votes::BINS;
use crate::store::{Result, Snapshot};

/// The vote weight that says a depth map saw a cube: all its votes, near a surface, in free
/// space in front of one, or up to eta behind one.
pub fn seen_weight(hist: &[f32; BINS]) -> f32 {
    hist.iter().sum()
}

/// The vote weight that measured a distance to a surface: bins 1 to 6, not clamped to free
/// space (bin 7) or far behind (bin 0). Around a surface the maps saw, a good share of a
/// cube's votes; where u only separates free space one map saw from space behind another
/// map's surface (occluded space no map looked into), almost none.
pub fn measured_weight(hist: &[f32; BINS]) -> f32 {
    hist.iter().take(BINS - 1).skip(1).sum()
}

/// Where the votes put the surface relative to a cube's centre, in world units (positive: the
/// centre is outside): the mean truncated signed distance of its votes, a TSDF value at the
/// centre, from the histogram segment's `distance` sums (weighted sum, weight), each measured
/// to the surface interpolated where the centre projects (`kernels::surface_depth`). NaN when
/// no vote measured one. u decides where the surface is, robustly; this places it inside the
/// cube, where u's L1 data term snaps to bin centres and would leave terraces one bin high.
pub fn surface_offset([sum, weight]: [f32; 2]) -> f32 {
    if weight > 0.0 { sum / weight } else { f32::NAN }
}

/// The sample counts of a unit's octree nodes: all samples that spawned each node, and how
/// many of them were spikes (isolated samples, `stages::ingest`).
pub struct SpawnCounts<'a> {
    pub samples: &'a [u32],
    pub spikes: &'a [u32],
}

impl SpawnCounts<'_> {
    fn spawned(&self, i: usize) -> bool {
        self.samples.get(i).is_some_and(|c| *c > 0)
    }

    /// Whether samples other than spikes spawned node i.
    fn vouched(&self, i: usize) -> bool {
        let samples = self.samples.get(i).copied().unwrap_or(0);
        samples > self.spikes.get(i).copied().unwrap_or(0)
    }
}

/// For each node of a unit's sorted octree keys (an ancestor sorts just before its
/// descendants): whether samples spawned the node or one of its descendants, or samples other
/// than spikes spawned one of its ancestors in the unit or one of its siblings. A measured
/// surface passes through such cubes only.
///
/// Siblings count because a surface sampled at about the cube size (a low-resolution view, a
/// grazing one) leaves cubes between its samples that no sample spawned, and a dual cell of
/// only those would tear the mesh. Spikes vouch for their own cube alone: a spike (a flying
/// pixel between a foreground edge and the background, or an outlier) gets a radius as large
/// as the gap to its neighbours and so spawns a coarse cube, and its subtree would count the
/// space behind objects as sampled.
pub fn sampled_nodes(keys: &[CubeKey], counts: &SpawnCounts<'_>) -> Vec<bool> {
    // parents[i]: the index of node i's parent, when the unit holds it (the octree is complete,
    // so every node but the unit's root has its parent in the unit).
    let mut parents = Vec::with_capacity(keys.len());
    let mut stack: Vec<usize> = Vec::new();
    for (i, key) in keys.iter().enumerate() {
        while stack
            .last()
            .is_some_and(|a| !keys.get(*a).is_some_and(|a| a.is_ancestor_or_self_of(*key)))
        {
            stack.pop();
        }
        parents.push(stack.last().copied().filter(|p| keys.get(*p).copied() == key.parent()));
        stack.push(i);
    }
    // Children sort after their parent, so one pass from the end sees a node's whole subtree
    // before the node: spawned_below[i] (samples spawned a descendant) and vouched_child[i]
    // (samples other than spikes spawned a child).
    let mut spawned_below = vec![false; keys.len()];
    let mut vouched_child = vec![false; keys.len()];
    for (i, parent) in parents.iter().enumerate().rev() {
        let Some(p) = *parent else { continue };
        let below = counts.spawned(i) || spawned_below.get(i).copied().unwrap_or(false);
        if let (Some(flag), Some(child)) = (spawned_below.get_mut(p), vouched_child.get_mut(p)) {
            *flag |= below;
            *child |= counts.vouched(i);
        }
    }
    // vouched_from_above[i]: samples other than spikes spawned node i or an ancestor.
    let mut vouched_from_above: Vec<bool> = Vec::with_capacity(keys.len());
    let mut sampled = Vec::with_capacity(keys.len());
    for (i, parent) in parents.iter().enumerate() {
        let parent_vouched = parent.and_then(|p| vouched_from_above.get(p).copied()).unwrap_or(false);
        let sibling_vouched = parent.and_then(|p| vouched_child.get(p).copied()).unwrap_or(false);
        vouched_from_above.push(counts.vouched(i) || parent_vouched);
        let from_below = spawned_below.get(i).copied().unwrap_or(false);
        sampled.push(counts.spawned(i) || parent_vouched || sibling_vouched || from_below);
    }
    sampled
}

/// A unit's octree keys, sample counts and spike counts (zero for segments written before
/// spikes were counted).
fn nodes_of(base: &Snapshot<'_>, segment: &str) -> Result<(Vec<CubeKey>, Vec<u32>, Vec<u32>)> {
    let file = base.open_segment(segment)?;
    let reader = file.reader()?;
    let nodes = reader.read_keys().map_err(|e| file.corruption(e))?;
    let (_, counts) = reader.read_u32("radius_count").map_err(|e| file.corruption(e))?;
    let spikes = if reader.column(SPIKE_COUNT).is_ok() {
        reader.read_u32(SPIKE_COUNT).map_err(|e| file.corruption(e))?.1
    } else {
        vec![0; counts.len()]
    };
    Ok((nodes, counts, spikes))
}

/// A unit's octree nodes and their [`sampled_nodes`] flags.
pub type UnitSampled = (Vec<CubeKey>, Vec<bool>);

/// A treetop unit's octree nodes and their [`sampled_nodes`] flags, read from its octree
/// segment. Samples other than spikes that spawned a node of the treetop's internal unit, an
/// ancestor of a whole leaf unit, mark that unit's every node too. `top` holds the internal
/// unit's nodes and counts once a leaf unit has needed them.
pub fn unit_sampled(
    base: &Snapshot<'_>,
    treetop: &Treetop,
    unit: usize,
    top: &mut Option<(Vec<CubeKey>, Vec<u32>, Vec<u32>)>,
) -> Result<Option<UnitSampled>> {
    let Some(info) = treetop.units.get(unit) else {
        return Ok(None);
    };
    let (nodes, samples, spikes) = nodes_of(base, &info.segment)?;
    let mut flags = sampled_nodes(
        &nodes,
        &SpawnCounts {
            samples: &samples,
            spikes: &spikes,
        },
    );
    if !info.top {
        if top.is_none()
            && let Some(internal) = treetop.units.iter().find(|u| u.top)
        {
            *top = Some(nodes_of(base, &internal.segment)?);
        }
        let vouched_above = top.as_ref().is_some_and(|(top_nodes, top_samples, top_spikes)| {
            let top_counts = SpawnCounts {
                samples: top_samples,
                spikes: top_spikes,
            };
            std::iter::successors(Some(info.key), |k| k.parent()).any(|ancestor| {
                top_nodes
                    .binary_search(&ancestor)
                    .is_ok_and(|at| top_counts.vouched(at))
            })
        });
        if vouched_above {
            flags.iter_mut().for_each(|flag| *flag = true);
        }
    }
    Ok(Some((nodes, flags)))
}

/// [`unit_sampled`] for the cubes `keys` of a level cut.
pub fn sampled_of(base: &Snapshot<'_>, treetop: &Treetop, keys: &[CubeKey]) -> Result<Vec<bool>> {
    // Per unit, its nodes and flags, and where the last key was found among its nodes: the cut
    // keys come in order, so each search starts there.
    let mut units: BTreeMap<usize, (Option<UnitSampled>, usize)> = BTreeMap::new();
    let mut top = None;
    // The leaf unit the keys are in. Leaf units are disjoint key ranges and the keys ascend, so
    // a unit the keys have left is never asked again: it is dropped, and a group of many units
    // (a coarse level's) holds the nodes of one leaf unit and the internal unit, not of all
    // (415 M samples: 1,990 units in 5 groups at level 8, whose nodes kept 1.7 GB resident).
    let mut current_leaf = None;
    let mut out = Vec::with_capacity(keys.len());
    for key in keys {
        let unit = treetop.unit_of(*key);
        if let std::collections::btree_map::Entry::Vacant(slot) = units.entry(unit) {
            slot.insert((unit_sampled(base, treetop, unit, &mut top)?, 0));
            if treetop.units.get(unit).is_some_and(|u| !u.top)
                && let Some(left) = current_leaf.replace(unit)
            {
                units.remove(&left);
            }
        }
        let flag = units.get_mut(&unit).and_then(|(entry, last)| {
            let (nodes, flags) = entry.as_ref()?;
            let at = find_sorted_from(nodes, *last, *key)?;
            *last = at;
            flags.get(at).copied()
        });
        out.push(flag.unwrap_or(false));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn samples_mark_their_cube_ancestors_descendants_and_siblings() {
        // Root, two children, grandchildren under the first; samples spawned one grandchild.
        let root = CubeKey::new(0, 0, 0, 0);
        let a = CubeKey::new(1, 0, 0, 0);
        let a0 = CubeKey::new(2, 0, 0, 0);
        let a1 = CubeKey::new(2, 1, 0, 0);
        let b = CubeKey::new(1, 1, 0, 0);
        let b0 = CubeKey::new(2, 2, 0, 0);
        let b00 = CubeKey::new(3, 4, 0, 0);
        let mut keys = vec![root, a, a0, a1, b, b0, b00];
        keys.sort();
        let none = vec![0u32; keys.len()];
        let flags_of = |samples: &[u32], spikes: &[u32]| -> BTreeMap<CubeKey, bool> {
            let flags = sampled_nodes(&keys, &SpawnCounts { samples, spikes });
            keys.iter().copied().zip(flags).collect()
        };
        let counts: Vec<u32> = keys.iter().map(|k| u32::from(*k == a1)).collect();
        let flags = flags_of(&counts, &none);
        assert!(flags[&a1], "spawned");
        assert_eq!((flags[&a], flags[&root]), (true, true), "ancestors");
        assert!(flags[&a0], "a sibling");
        assert_eq!((flags[&b], flags[&b0]), (false, false), "another branch");
        // A spawned coarse node marks its whole subtree.
        let counts: Vec<u32> = keys.iter().map(|k| u32::from(*k == b)).collect();
        let flags = flags_of(&counts, &none);
        assert_eq!(
            (flags[&b], flags[&b0], flags[&b00], flags[&a0]),
            (true, true, true, false)
        );
        assert!(flags[&a], "b's sibling");
        // Unless only spikes spawned it: then it marks itself and its ancestors alone.
        let flags = flags_of(&counts, &counts);
        assert_eq!(
            (flags[&b], flags[&root], flags[&b0], flags[&a]),
            (true, true, false, false)
        );
        // One sample besides the spikes vouches for the whole subtree again.
        let samples: Vec<u32> = counts.iter().map(|c| c * 3).collect();
        let spikes: Vec<u32> = counts.iter().map(|c| c * 2).collect();
        assert!(flags_of(&samples, &spikes)[&b00]);
    }

    #[test]
    fn offsets_average_the_truncated_distances() {
        let mut hist = [0f32; BINS];
        assert!(surface_offset([0.0, 0.0]).is_nan(), "no votes");
        assert_eq!(surface_offset([0.5, 2.0]), 0.25);
        hist[0] = 5.0;
        hist[7] = 3.0;
        hist[3] = 1.0;
        hist[4] = 1.0;
        assert_eq!(seen_weight(&hist), 10.0);
        assert_eq!(measured_weight(&hist), 2.0);
    }
}
