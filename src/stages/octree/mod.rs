//! `octree`: merges the ingest runs into one linear octree, 2:1-balances and completes it, and
//! indexes its treetop (paper 4.1-4.3). Out of core: runs are merged block by block, level sets
//! go through an external sorter, and each treetop leaf becomes one segment (one unit).
//!
//! The octree is **completed**: every internal node has all 8 children, so the cubes of any
//! level cut (cubes at depth l plus coarser leaves) tile the root cube. It is **2:1 face
//! balanced**: for every node N at depth k >= 1 the face neighbours of parent(N) exist, so a
//! leaf has at most 4 face neighbours across any face. Both are checked by `verify`.
//!
//! Balance as a closure over internal-node sets, coarsening level by level:
//! I(k-1) = parent( requested(k) ∪ I(k) ∪ face_neighbours(I(k)) ), and the nodes are the root
//! plus all children of internal nodes. Nodes keep the radius sums of the samples that
//! requested them (eq. 5); nodes added by balance or completion have none.

pub mod external_sort;
mod merge;

use std::cmp::Reverse;
use std::collections::{BTreeMap, BTreeSet, BinaryHeap};
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use redb::{ReadableTable, WriteTransaction};
use serde::{Deserialize, Serialize};

use self::external_sort::{CubeRecord, KeySorter, RecordReader, RecordWriter};
pub use self::merge::MERGE_FAN_IN;
use super::ingest::SPIKE_COUNT;
use super::{INGEST, OCTREE};
use crate::format::segment::content_digest;
use crate::format::{Column, ColumnValues, CubeKey, Scene};
use crate::store::StageError;
use crate::store::catalog::{self, UNIT_STATE, UnitRecord};
use crate::store::{Plan, Replace, Result, Snapshot, Stage, StoreError, UnitOutput, UnitSpec};

/// Default treetop leaf size (paper: N = 2^24).
pub const DEFAULT_LEAF_CUBES: u64 = 1 << 24;

/// Memory a cube of a treetop leaf may take in the heaviest stage (the solver: fields, duals,
/// histogram, neighbour lists and their copies), used to cap leaf size by the memory budget.
pub const BYTES_PER_LEAF_CUBE: u64 = 512;

/// Treetop leaves of the largest size the memory budget allows that fit in half of it at once.
/// The cap does not follow the thread count: the leaves are the units, and the units shape
/// every level's values (each freezes its borders), so a cap by thread count gave a store
/// solved on one core other bytes than on two. More threads run at most this many such
/// leaves at once ([`leaves_in_flight`]) and work inside them.
pub const LEAVES_IN_FLIGHT: u64 = 2;

/// The treetop leaf size actually used: the requested one, capped so that
/// [`LEAVES_IN_FLIGHT`] leaves fit in half the memory budget.
pub fn effective_leaf_cubes(requested: u64, memory_budget: u64) -> u64 {
    let cap = memory_budget / 2 / BYTES_PER_LEAF_CUBE / LEAVES_IN_FLIGHT;
    requested.min(cap).max(64)
}

/// How many treetop leaves of `leaf_cubes` cubes the stages after ingest run at once: as many
/// as fit in half the memory budget, at most `threads` and at least one.
pub fn leaves_in_flight(leaf_cubes: u64, memory_budget: u64, threads: usize) -> usize {
    let fit = memory_budget / 2 / BYTES_PER_LEAF_CUBE / leaf_cubes.max(1);
    usize::try_from(fit).unwrap_or(usize::MAX).clamp(1, threads.max(1))
}

/// Face neighbours of a cube at its own depth (up to 6, inside the root).
pub fn face_neighbours(key: CubeKey) -> impl Iterator<Item = CubeKey> {
    let depth = key.depth();
    let [x, y, z] = key.coords();
    let max = if depth >= 32 { u32::MAX } else { (1u32 << depth) - 1 };
    let candidates = [
        (x.checked_sub(1), Some(y), Some(z)),
        ((x < max).then(|| x + 1), Some(y), Some(z)),
        (Some(x), y.checked_sub(1), Some(z)),
        (Some(x), (y < max).then(|| y + 1), Some(z)),
        (Some(x), Some(y), z.checked_sub(1)),
        (Some(x), Some(y), (z < max).then(|| z + 1)),
    ];
    candidates.into_iter().filter_map(move |c| match c {
        (Some(x), Some(y), Some(z)) => Some(CubeKey::new(depth, x, y, z)),
        _ => None,
    })
}

pub fn children(key: CubeKey) -> [CubeKey; 8] {
    let [x, y, z] = key.coords();
    let d = key.depth() + 1;
    std::array::from_fn(|i| {
        let i = i as u32;
        CubeKey::new(d, 2 * x + (i & 1), 2 * y + ((i >> 1) & 1), 2 * z + ((i >> 2) & 1))
    })
}

/// Checks completeness and 2:1 face balance of a sorted, complete list of octree keys.
pub fn check_octree_keys(keys: &[CubeKey]) -> Vec<String> {
    let mut problems = Vec::new();
    let has = |k: &CubeKey| keys.binary_search(k).is_ok();
    if keys.windows(2).any(|w| w[0] >= w[1]) {
        problems.push("octree keys are not strictly increasing".to_string());
        return problems;
    }
    for (index, key) in keys.iter().enumerate() {
        let internal = keys
            .get(index + 1)
            .is_some_and(|next| key.is_ancestor_or_self_of(*next));
        if internal {
            for child in children(*key) {
                if !has(&child) {
                    problems.push(format!("octree not complete: {key:?} lacks child {child:?}"));
                }
            }
        }
        if let Some(parent) = key.parent() {
            if !has(&parent) {
                problems.push(format!("octree: {key:?} has no parent"));
            }
            for neighbour in face_neighbours(parent) {
                if !has(&neighbour) {
                    problems.push(format!(
                        "octree not 2:1 balanced: {key:?} exists but {neighbour:?}, a face neighbour of its parent, does not"
                    ));
                }
            }
        }
        if problems.len() > 20 {
            break;
        }
    }
    problems
}

/// `verify` check: key order and balance of the latest octree (loads all keys: O(cubes)).
pub fn verify_octree(snapshot: &Snapshot<'_>) -> Result<Vec<String>> {
    // Leaf segments cover disjoint ranges; the segment of the treetop's internal nodes (first key
    // = the root, when there is more than one segment) spans them by design.
    let segments = snapshot.segments(OCTREE);
    let root = CubeKey::new(0, 0, 0, 0).raw();
    let leaves: Vec<_> = segments
        .iter()
        .filter(|(_, r)| segments.len() == 1 || r.first_key != root)
        .collect();
    let mut problems = Vec::new();
    for pair in leaves.windows(2) {
        if let [(a_name, a), (b_name, b)] = pair
            && a.last_key >= b.first_key
        {
            problems.push(format!(
                "octree: leaf segments {a_name} and {b_name} overlap or are out of order"
            ));
        }
    }
    let mut keys = Vec::new();
    for (name, _) in snapshot.segments(OCTREE) {
        let file = snapshot.open_segment(name)?;
        let reader = file.reader()?;
        keys.extend(reader.read_keys().map_err(|e| file.corruption(e))?);
    }
    keys.sort_unstable();
    if !keys.is_empty() {
        problems.extend(check_octree_keys(&keys));
    }
    Ok(problems)
}

/// A treetop unit: one leaf (a contiguous index range) or the treetop's internal nodes.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, Eq)]
pub struct LeafUnit {
    pub key: CubeKey,
    /// (first index, count) ranges in the node file.
    pub ranges: Vec<(u64, u64)>,
    /// The unit of the treetop's internal nodes rather than a leaf.
    pub top: bool,
}

impl LeafUnit {
    pub fn cubes(&self) -> u64 {
        self.ranges.iter().map(|(_, n)| n).sum()
    }
}

struct Prepared {
    finest: u8,
    nodes: PathBuf,
    units: Vec<LeafUnit>,
    total: u64,
    requested: u64,
}

pub struct OctreeStage {
    pub scene: Scene,
    pub leaf_cubes: u64,
    /// Bytes the external sorter may hold in memory.
    pub sort_memory: u64,
    scratch: PathBuf,
    prepared: OnceLock<Prepared>,
}

#[derive(Serialize, Deserialize)]
struct OctreeUnitExtra {
    key: CubeKey,
    first: u64,
    cubes: u64,
    top: bool,
}

impl OctreeStage {
    pub fn new(scene: Scene, leaf_cubes: u64, sort_memory: u64, scratch: PathBuf) -> OctreeStage {
        OctreeStage {
            scene,
            leaf_cubes: leaf_cubes.max(2),
            sort_memory,
            scratch,
            prepared: OnceLock::new(),
        }
    }

    fn prepared(&self) -> Result<&Prepared> {
        self.prepared.get().ok_or_else(|| StoreError::Stage {
            stage: OCTREE.into(),
            unit: "-".into(),
            error: Box::new(StageError::internal("units run before planning")),
        })
    }

    fn build(&self, base: &Snapshot<'_>) -> Result<Prepared> {
        let started = std::time::Instant::now();
        let mut request_writers = BTreeMap::new();
        let requested = merge::merge_runs(base, &self.scratch, &mut request_writers)?;
        let merged = started.elapsed().as_secs_f64();
        let mut requests: BTreeMap<u8, PathBuf> = BTreeMap::new();
        for (depth, (path, writer)) in request_writers {
            writer.finish()?;
            requests.insert(depth, path);
        }
        // Internal node sets, finest to coarsest.
        let finest = requests.keys().next_back().copied().unwrap_or(0);
        let mut internal: BTreeMap<u8, PathBuf> = BTreeMap::new();
        for depth in (1..=finest).rev() {
            let mut sorter = KeySorter::new(&self.scratch, &format!("internal-{:02}", depth - 1), self.sort_memory);
            let mut any = false;
            if let Some(path) = requests.get(&depth) {
                let mut reader = RecordReader::<CubeRecord>::open(path)?;
                while let Some(r) = reader.next_record()? {
                    if let Some(parent) = r.key.parent() {
                        sorter.push(parent)?;
                        any = true;
                    }
                }
            }
            if let Some(path) = internal.get(&depth) {
                let mut reader = RecordReader::<CubeKey>::open(path)?;
                while let Some(key) = reader.next_record()? {
                    for k in std::iter::once(key).chain(face_neighbours(key)) {
                        if let Some(parent) = k.parent() {
                            sorter.push(parent)?;
                            any = true;
                        }
                    }
                }
            }
            if any {
                let path = self.scratch.join(format!("internal-{:02}.bin", depth - 1));
                sorter.finish_into(&path)?;
                internal.insert(depth - 1, path);
            }
        }

        let balanced = started.elapsed().as_secs_f64();
        // Nodes in key order: the root plus the children of every internal node, joined with
        // the requests' radius sums.
        let nodes_path = self.scratch.join("nodes.bin");
        let mut nodes = RecordWriter::<CubeRecord>::create(&nodes_path)?;
        let mut child_streams: Vec<(RecordReader<CubeKey>, [CubeKey; 8], usize)> = Vec::new();
        let mut heap = BinaryHeap::new();
        for path in internal.values() {
            let mut reader = RecordReader::<CubeKey>::open(path)?;
            if let Some(parent) = reader.next_record()? {
                let kids = children(parent);
                heap.push(Reverse((kids[0], child_streams.len())));
                child_streams.push((reader, kids, 0));
            }
        }
        let mut request_streams: Vec<RecordReader<CubeRecord>> = requests
            .values()
            .map(|p| RecordReader::open(p))
            .collect::<Result<_>>()?;
        let mut request_heap = BinaryHeap::new();
        for (index, stream) in request_streams.iter_mut().enumerate() {
            if let Some(r) = stream.next_record()? {
                request_heap.push(Reverse((r, index)));
            }
        }
        let mut total = 0u64;
        let mut write_node =
            |key: CubeKey, request_heap: &mut BinaryHeap<Reverse<(CubeRecord, usize)>>| -> Result<()> {
                let mut record = CubeRecord::new(key, 0, 0, 0);
                while let Some(Reverse((r, index))) = request_heap.peek().copied() {
                    if r.key > key {
                        break;
                    }
                    request_heap.pop();
                    if r.key == key {
                        record = r;
                    } else {
                        return Err(StoreError::Stage {
                            stage: OCTREE.into(),
                            unit: "balance".into(),
                            error: Box::new(StageError::internal(format!(
                                "requested cube {:?} is missing from the balanced octree",
                                r.key
                            ))),
                        });
                    }
                    if let Some(next) = request_streams
                        .get_mut(index)
                        .map(|s| s.next_record())
                        .transpose()?
                        .flatten()
                    {
                        request_heap.push(Reverse((next, index)));
                    }
                }
                total += 1;
                nodes.push(&record)
            };
        write_node(CubeKey::new(0, 0, 0, 0), &mut request_heap)?;
        while let Some(Reverse((key, stream))) = heap.pop() {
            write_node(key, &mut request_heap)?;
            if let Some((reader, kids, next)) = child_streams.get_mut(stream) {
                *next += 1;
                if *next == 8 {
                    match reader.next_record()? {
                        Some(parent) => {
                            *kids = children(parent);
                            *next = 0;
                        }
                        None => continue,
                    }
                }
                heap.push(Reverse((kids[*next], stream)));
            }
        }
        if let Some(Reverse((r, _))) = request_heap.peek() {
            return Err(StoreError::Stage {
                stage: OCTREE.into(),
                unit: "balance".into(),
                error: Box::new(StageError::internal(format!(
                    "requested cube {:?} is missing from the balanced octree",
                    r.key
                ))),
            });
        }
        nodes.finish()?;
        let noded = started.elapsed().as_secs_f64();
        let units = treetop(&nodes_path, self.leaf_cubes)?;
        tracing::info!(
            "octree: merge {merged:.2}s, balance {:.2}s, nodes {:.2}s, treetop {:.2}s",
            balanced - merged,
            noded - balanced,
            started.elapsed().as_secs_f64() - noded
        );
        Ok(Prepared {
            finest,
            nodes: nodes_path,
            units,
            total,
            requested,
        })
    }

    fn unit_records(&self, nodes: &Path, unit: &LeafUnit) -> Result<Vec<CubeRecord>> {
        let mut records = Vec::with_capacity(unit.cubes() as usize);
        for (first, count) in &unit.ranges {
            let mut reader = RecordReader::<CubeRecord>::open_range(nodes, *first, *count)?;
            while let Some(r) = reader.next_record()? {
                records.push(r);
            }
        }
        Ok(records)
    }
}

/// The treetop over a node file in key (pre-)order: leaves are the maximal subtrees with fewer
/// than `leaf_cubes` nodes; the nodes above them form the `top` unit.
pub fn treetop(nodes: &Path, leaf_cubes: u64) -> Result<Vec<LeafUnit>> {
    struct Open {
        key: CubeKey,
        start: u64,
        candidates: Vec<(CubeKey, u64, u64)>,
    }
    let mut leaves: Vec<(CubeKey, u64, u64)> = Vec::new();
    let mut top: Vec<u64> = Vec::new();
    let mut stack: Vec<Open> = Vec::new();
    let close =
        |open: Open, end: u64, stack: &mut Vec<Open>, leaves: &mut Vec<(CubeKey, u64, u64)>, top: &mut Vec<u64>| {
            let count = end - open.start;
            if count < leaf_cubes {
                match stack.last_mut() {
                    Some(parent) => parent.candidates.push((open.key, open.start, count)),
                    None => leaves.push((open.key, open.start, count)),
                }
            } else {
                leaves.extend(open.candidates);
                top.push(open.start);
            }
        };
    let mut reader = RecordReader::<CubeRecord>::open(nodes)?;
    let mut index = 0u64;
    while let Some(record) = reader.next_record()? {
        while let Some(open) = stack.last() {
            if open.key.is_ancestor_or_self_of(record.key) {
                break;
            }
            if let Some(open) = stack.pop() {
                close(open, index, &mut stack, &mut leaves, &mut top);
            }
        }
        stack.push(Open {
            key: record.key,
            start: index,
            candidates: Vec::new(),
        });
        index += 1;
    }
    while let Some(open) = stack.pop() {
        close(open, index, &mut stack, &mut leaves, &mut top);
    }
    leaves.sort_unstable();
    top.sort_unstable();
    let mut units: Vec<LeafUnit> = Vec::new();
    if !top.is_empty() {
        units.push(LeafUnit {
            key: CubeKey::new(0, 0, 0, 0),
            ranges: top.iter().map(|&t| (t, 1)).collect(),
            top: true,
        });
    }
    units.extend(leaves.into_iter().map(|(key, first, count)| LeafUnit {
        key,
        ranges: vec![(first, count)],
        top: false,
    }));
    Ok(units)
}

fn columns_of(records: &[CubeRecord]) -> Vec<Column> {
    vec![
        Column::keys(records.iter().map(|r| r.key).collect()),
        Column::new(
            "radius_sum",
            1,
            ColumnValues::U64(records.iter().map(|r| r.radius_sum).collect()),
        ),
        Column::new(
            "radius_count",
            1,
            ColumnValues::U32(records.iter().map(|r| r.radius_count).collect()),
        ),
        Column::new(
            SPIKE_COUNT,
            1,
            ColumnValues::U32(records.iter().map(|r| r.spike_count).collect()),
        ),
    ]
}

impl Stage for OctreeStage {
    fn name(&self) -> &'static str {
        OCTREE
    }

    fn params(&self) -> Vec<u8> {
        catalog::encode(&(self.leaf_cubes, self.scene))
    }

    fn input_digest(&self, base: &Snapshot<'_>) -> Vec<u8> {
        base.digest(INGEST).to_le_bytes().to_vec()
    }

    fn plan(&self, base: &Snapshot<'_>) -> Result<Plan> {
        let prepared = match self.prepared.get() {
            Some(p) => p,
            None => {
                let built = self.build(base)?;
                self.prepared.get_or_init(|| built)
            }
        };
        // Leaves whose content equals a visible segment's are kept as they are.
        let existing: BTreeMap<(u128, u64), String> = base
            .segments(OCTREE)
            .iter()
            .map(|(name, r)| ((r.first_key, r.content_digest), name.clone()))
            .collect();
        let mut kept = BTreeSet::new();
        let mut units = Vec::new();
        for (index, unit) in prepared.units.iter().enumerate() {
            let records = self.unit_records(&prepared.nodes, unit)?;
            let digest = content_digest(&columns_of(&records));
            let first = records.first().map(|r| r.key.raw()).unwrap_or(0);
            if let Some(name) = existing.get(&(first, digest)) {
                kept.insert(name.clone());
                continue;
            }
            units.push(UnitSpec {
                id: index as u64,
                label: if unit.top {
                    format!("treetop internal nodes ({} cubes)", unit.cubes())
                } else {
                    format!("leaf {:?} ({} cubes)", unit.key, unit.cubes())
                },
                cubes: unit.cubes(),
            });
        }
        let replaced: BTreeSet<String> = existing.into_values().filter(|name| !kept.contains(name)).collect();
        tracing::info!(
            "octree: {} requested cubes -> {} balanced cubes in {} treetop unit(s); {} changed",
            prepared.requested,
            prepared.total,
            prepared.units.len(),
            units.len()
        );
        Ok(Plan {
            units,
            replace: Replace::Names(replaced),
        })
    }

    fn run_unit(&self, _base: &Snapshot<'_>, unit: &UnitSpec) -> Result<UnitOutput> {
        let prepared = self.prepared()?;
        let leaf = prepared.units.get(unit.id as usize).ok_or_else(|| StoreError::Stage {
            stage: OCTREE.into(),
            unit: unit.label.clone(),
            error: Box::new(StageError::internal("unit out of range")),
        })?;
        let records = self.unit_records(&prepared.nodes, leaf)?;
        let extra = OctreeUnitExtra {
            key: leaf.key,
            first: leaf.ranges.first().map(|r| r.0).unwrap_or(0),
            cubes: records.len() as u64,
            top: leaf.top,
        };
        Ok(UnitOutput {
            segments: vec![columns_of(&records).into()],
            extra: catalog::encode(&extra),
            block_rows: super::FACE_READ_BLOCK_ROWS,
        })
    }

    fn finish(&self, txn: &WriteTransaction, _base: &Snapshot<'_>, units: &[(u64, UnitRecord)]) -> Result<String> {
        // The treetop index in the catalog: leaf key -> (first index, cube count), replacing the
        // previous one.
        let prepared = self.prepared()?;
        let mut table = txn.open_table(UNIT_STATE)?;
        let old: Vec<CubeKey> = table
            .range((OCTREE.as_bytes(), CubeKey::from_raw(0))..=(OCTREE.as_bytes(), CubeKey::from_raw(u128::MAX)))?
            .map(|e| Ok(e?.0.value().1))
            .collect::<Result<_>>()?;
        for key in old {
            table.remove((OCTREE.as_bytes(), key))?;
        }
        txn.open_table(crate::store::catalog::META)?.insert(
            crate::stages::META_OCTREE_MAX_DEPTH.as_bytes(),
            catalog::seal("meta", crate::stages::META_OCTREE_MAX_DEPTH, &[prepared.finest]).as_slice(),
        )?;
        for unit in prepared.units.iter().filter(|u| !u.top) {
            let entry = (unit.ranges.first().map(|r| r.0).unwrap_or(0), unit.cubes());
            table.insert(
                (OCTREE.as_bytes(), unit.key),
                catalog::seal_encode("unit_state", &(OCTREE, unit.key), &entry).as_slice(),
            )?;
        }
        Ok(format!(
            "{} requested cubes -> {} cubes (balanced, complete); {} treetop leaves; {} unit(s) rewritten",
            prepared.requested,
            prepared.total,
            prepared.units.iter().filter(|u| !u.top).count(),
            units.len()
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn children_and_neighbours() {
        let key = CubeKey::new(2, 1, 2, 3);
        let kids = children(key);
        assert!(kids.iter().all(|c| c.parent() == Some(key)));
        assert!(kids.windows(2).all(|w| w[0] < w[1]));
        assert_eq!(face_neighbours(CubeKey::new(1, 0, 0, 0)).count(), 3);
        assert_eq!(
            face_neighbours(key).count(),
            5,
            "z = 3 is on the root boundary at depth 2"
        );
        assert_eq!(face_neighbours(CubeKey::new(2, 1, 2, 2)).count(), 6);
    }
}
