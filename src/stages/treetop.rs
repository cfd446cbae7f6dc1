//! The treetop as later stages see it: units are the octree's segments (one per treetop leaf,
//! plus one for the treetop's internal nodes), and every cube key belongs to exactly one unit.

use crate::format::CubeKey;
use crate::store::StageError;
use crate::store::catalog::SegmentRecord;
use crate::store::{Result, Snapshot, StoreError};

use super::OCTREE;
use super::octree::children;

#[derive(Clone, Debug)]
pub struct TreetopUnit {
    /// The leaf cube (root key for the internal-node unit).
    pub key: CubeKey,
    pub segment: String,
    pub record: SegmentRecord,
    pub top: bool,
}

/// Units in a fixed order: the internal-node unit first (if any), then leaves by key.
#[derive(Clone, Debug)]
pub struct Treetop {
    pub units: Vec<TreetopUnit>,
}

impl Treetop {
    pub fn of(snapshot: &Snapshot<'_>) -> Result<Treetop> {
        let segments = snapshot.segments(OCTREE);
        if segments.is_empty() {
            return Err(StoreError::Stage {
                stage: OCTREE.into(),
                unit: "-".into(),
                error: Box::new(StageError::NoOctree),
            });
        }
        let root = CubeKey::new(0, 0, 0, 0);
        let mut units: Vec<TreetopUnit> = segments
            .iter()
            .map(|(name, record)| TreetopUnit {
                key: CubeKey::from_raw(record.first_key),
                segment: name.clone(),
                record: record.clone(),
                top: segments.len() > 1 && record.first_key == root.raw(),
            })
            .collect();
        units.sort_by_key(|u| (!u.top, u.key));
        Ok(Treetop { units })
    }

    /// Index of the unit holding `key` (existing or not): the leaf whose subtree contains it,
    /// else the internal-node unit.
    pub fn unit_of(&self, key: CubeKey) -> usize {
        let leaves_start = usize::from(self.units.first().is_some_and(|u| u.top));
        let leaves = self.units.get(leaves_start..).unwrap_or(&[]);
        let position = leaves.partition_point(|u| u.key <= key);
        if position > 0
            && let Some(unit) = leaves.get(position - 1)
            && unit.key.is_ancestor_or_self_of(key)
        {
            return leaves_start + position - 1;
        }
        0
    }
}

#[cfg(test)]
impl TreetopUnit {
    /// A unit of cube `key` with no segment behind it: treetops for tests of what depends on
    /// the keys alone.
    pub(crate) fn blank(key: CubeKey, top: bool) -> TreetopUnit {
        TreetopUnit {
            key,
            segment: String::new(),
            record: SegmentRecord {
                stage: String::new(),
                unit: 0,
                part: 0,
                rows: 0,
                bytes: 0,
                file_checksum: 0,
                content_digest: 0,
                first_key: 0,
                last_key: 0,
                created: 0,
                dropped: None,
            },
            top,
        }
    }
}

/// Sorted keys of one unit, with the octree's leaf test.
pub struct UnitKeys {
    pub keys: Vec<CubeKey>,
    pub top: bool,
}

impl UnitKeys {
    pub fn contains(&self, key: CubeKey) -> bool {
        self.keys.binary_search(&key).is_ok()
    }

    /// Whether an existing node of this unit is a leaf of the octree. Nodes of the internal
    /// unit never are; in a leaf unit a node is internal iff the next key is its descendant.
    pub fn is_leaf(&self, index: usize) -> bool {
        if self.top {
            return false;
        }
        match (self.keys.get(index), self.keys.get(index + 1)) {
            (Some(k), Some(next)) => !k.is_ancestor_or_self_of(*next),
            (Some(_), None) => true,
            _ => false,
        }
    }
}

/// Children of `key` that touch its face on the `-` side of `axis` (the 4 finer neighbours seen
/// from a cube on that side).
pub fn children_on_min_face(key: CubeKey, axis: usize) -> [CubeKey; 4] {
    let all = children(key);
    let mut out = [key; 4];
    let mut n = 0;
    for (i, child) in all.iter().enumerate() {
        if (i >> axis) & 1 == 0 {
            if let Some(slot) = out.get_mut(n) {
                *slot = *child;
            }
            n += 1;
        }
    }
    out
}
