//! `histograms`: votes of every depth map into per-cube histograms (paper 3.4, 4.4, Algorithm 1).
//!
//! Per treetop unit, only depth maps whose frustum meets the unit's cube are read, a batch at a
//! time with their mipmap pyramids (`kernels::votes::vote_maps`). Votes are additive and exact
//! (weights are multiples of 1/16 and sums stay far below 2^24 / 16 in f32), so after an
//! incremental ingest a unit whose octree part is unchanged only receives the new depth maps'
//! votes, and the result equals a from-scratch run.

use redb::ReadableTable;
use std::collections::{BTreeMap, BTreeSet};
use std::sync::Arc;

use glam::{DVec3, Vec4};
use redb::WriteTransaction;
use serde::{Deserialize, Serialize};

mod pyramid_cache;

pub use self::pyramid_cache::DEFAULT_PYRAMID_CACHE_BYTES;
use self::pyramid_cache::PyramidCache;
use super::ingest::DepthMapRecord;
use super::octree::LEAVES_IN_FLIGHT;
use super::treetop::Treetop;
use super::{HISTOGRAMS, OCTREE};
use crate::format::{Column, ColumnValues, CubeKey, Scene};
use crate::inputs::DepthMapSource;
use crate::kernels::votes::{
    BINS, Chunk, ChunkedCubes, FrustumTest, MAPS_AT_ONCE, MapVote, Pyramid, UnitView, band_floor, chunks,
    cube_geometry, cube_offsets, quantized_weight, relayout_for_lanes, vote_maps,
};
use crate::store::StageError;
use crate::store::catalog::{self, META, UNIT_STATE, UnitRecord};
use crate::store::{Plan, Replace, Result, Snapshot, Stage, StoreError, UnitOutput, UnitSpec};

/// What a unit's histograms were computed from; kept in `unit_state` for incremental runs.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq, Eq)]
pub struct HistogramState {
    pub octree_digest: u64,
    /// The set of depth maps that voted, by [`catalog::map_set_digest`]; the ids themselves
    /// are stored once per distinct set (`catalog::map_set_key`), not once per unit, so the
    /// catalog grows with units plus maps rather than with their product.
    pub map_set: u64,
}

/// A unit's record in `units_done`: its members' states and votes, and the map sets they
/// refer to (each distinct set once; nearly always just the run's whole set).
#[derive(Serialize, Deserialize)]
struct UnitExtra {
    members: Vec<(CubeKey, HistogramState, u64)>,
    map_sets: Vec<(u64, Vec<u64>)>,
}

struct UnitPlan {
    octree_segment: String,
    key: CubeKey,
    /// Previous histogram segment to add to, and the maps already in it (shared by every unit
    /// with the same set).
    previous: Option<(String, Arc<BTreeSet<u64>>)>,
}

pub struct HistogramsStage {
    pub scene: Scene,
    /// All registered depth maps, by id.
    pub depth_maps: Vec<(u64, DepthMapRecord)>,
    units: std::sync::OnceLock<Vec<UnitPlan>>,
    /// Treetop units voted together, by group id (the first member's index).
    groups: std::sync::OnceLock<BTreeMap<u64, Vec<usize>>>,
    cache: PyramidCache,
    /// A group's cubes, in largest leaves in flight ([`GROUP_LEAVES`]).
    group_leaves: u64,
    /// Depth maps whose file this run has found to be the one ingested (content hash = id).
    verified: std::sync::Mutex<std::collections::BTreeSet<u64>>,
    /// Where the votes are cast; `None` is the CPU.
    gpu: Option<std::sync::Arc<crate::gpu::Gpu>>,
}

/// A histogram group holds at most this many times [`LEAVES_IN_FLIGHT`] times the largest
/// treetop leaf's cubes, and the stage votes one group at a time, its maps decoded and its
/// chunks voted on every thread. A cube costs the vote loop 56 bytes (f32 offset and radius
/// 16, 8 bins 32, distance sums 8; its key is read again from the octree segment only when
/// the group's segments are written), so 9 leaves' cubes take under the 512 bytes the solver
/// budgets per leaf cube (`stages::octree::BYTES_PER_LEAF_CUBE`): a group fits where the
/// solver's leaves in flight do. The cap does not follow the thread count or the memory
/// budget's share, so neither do the groups nor the catalog's records of them, and a cluster
/// plans the same groups as one process. Larger groups decode each depth map fewer times:
/// RedKitchen, 1000 frames at 512 MiB, voted 14 groups of 4 leaves, then 3 groups of 7 leaves
/// two at a time (2,946 decodes), then 2 groups of 14 (2,000 decodes, 72 bytes a cube with
/// its key), and now one group of 18 largest leaves' cubes (1,000 decodes).
pub const GROUP_LEAVES: u64 = 9;

impl HistogramsStage {
    pub fn new(scene: Scene, depth_maps: Vec<(u64, DepthMapRecord)>) -> HistogramsStage {
        HistogramsStage {
            scene,
            depth_maps,
            units: std::sync::OnceLock::new(),
            groups: std::sync::OnceLock::new(),
            cache: PyramidCache::new(DEFAULT_PYRAMID_CACHE_BYTES),
            group_leaves: GROUP_LEAVES,
            verified: std::sync::Mutex::default(),
            gpu: None,
        }
    }

    /// An error unless `source`'s file still hashes to `id`, the id its ingest recorded: a file
    /// replaced after ingest would otherwise vote other data, silently. Hashed once per map and
    /// run (the cache decodes a map again for each group that sees it).
    fn check_unchanged(&self, id: u64, source: &crate::inputs::DepthMapSource, unit: &str) -> Result<()> {
        let seen = |verified: &std::sync::Mutex<std::collections::BTreeSet<u64>>| {
            verified
                .lock()
                .unwrap_or_else(|poisoned| poisoned.into_inner())
                .contains(&id)
        };
        if seen(&self.verified) {
            return Ok(());
        }
        let stage_error = |error: StageError| StoreError::Stage {
            stage: HISTOGRAMS.into(),
            unit: unit.to_string(),
            error: Box::new(error),
        };
        let found = super::ingest::depth_map_id(source).map_err(|e| stage_error(StageError::Input(Box::new(e))))?;
        if found != id {
            return Err(stage_error(StageError::FileChanged {
                path: source.path.clone(),
                found,
                recorded: id,
            }));
        }
        self.verified
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
            .insert(id);
        Ok(())
    }

    /// Casts the votes on `gpu` (falling back to the CPU per group on a GPU failure).
    pub fn with_gpu(mut self, gpu: Option<std::sync::Arc<crate::gpu::Gpu>>) -> HistogramsStage {
        self.gpu = gpu;
        self
    }

    /// Bounds the bytes of decoded pyramids kept between units (0 keeps none).
    pub fn with_cache_bytes(mut self, bytes: u64) -> HistogramsStage {
        self.cache.capacity = bytes;
        self
    }

    /// Groups of `leaves` times [`LEAVES_IN_FLIGHT`] largest leaves' cubes rather than
    /// [`GROUP_LEAVES`] times (a group holds at least one unit): they change how often each
    /// map is decoded, never a vote.
    pub fn with_group_leaves(mut self, leaves: u64) -> HistogramsStage {
        self.group_leaves = leaves;
        self
    }

    fn all_ids(&self) -> BTreeSet<u64> {
        self.depth_maps.iter().map(|(id, _)| *id).collect()
    }
}

/// The map sets of earlier runs, read from the catalog once per distinct set.
#[derive(Default)]
struct MapSets(BTreeMap<u64, Arc<BTreeSet<u64>>>);

impl MapSets {
    fn get(&mut self, base: &Snapshot<'_>, digest: u64) -> Result<Arc<BTreeSet<u64>>> {
        if let Some(set) = self.0.get(&digest) {
            return Ok(set.clone());
        }
        let txn = base.store().catalog().begin_read()?;
        let meta = txn.open_table(META)?;
        let key = catalog::map_set_key(digest);
        let ids: Vec<u64> = match meta.get(key.as_bytes())? {
            Some(v) => catalog::unseal_decode("meta", key.as_str(), v.value())?,
            None => {
                return Err(StoreError::CatalogCorruption {
                    table: "meta",
                    reason: format!("histogram state refers to {key}, which is missing"),
                });
            }
        };
        let set: Arc<BTreeSet<u64>> = Arc::new(ids.into_iter().collect());
        if catalog::map_set_digest(set.iter()) != digest {
            return Err(StoreError::CatalogCorruption {
                table: "meta",
                reason: format!("{key} holds ids of another digest"),
            });
        }
        self.0.insert(digest, set.clone());
        Ok(set)
    }
}

fn unit_state(base: &Snapshot<'_>, key: CubeKey) -> Result<Option<HistogramState>> {
    let txn = base.store().catalog().begin_read()?;
    let table = txn.open_table(UNIT_STATE)?;
    match table.get((HISTOGRAMS.as_bytes(), key))? {
        Some(v) => Ok(Some(catalog::unseal_decode(
            "unit_state",
            &(HISTOGRAMS, key),
            v.value(),
        )?)),
        None => Ok(None),
    }
}

impl Stage for HistogramsStage {
    fn name(&self) -> &'static str {
        HISTOGRAMS
    }

    fn params(&self) -> Vec<u8> {
        catalog::encode(&self.all_ids().into_iter().collect::<Vec<_>>())
    }

    fn input_digest(&self, base: &Snapshot<'_>) -> Vec<u8> {
        base.digest(OCTREE).to_le_bytes().to_vec()
    }

    fn plan(&self, base: &Snapshot<'_>) -> Result<Plan> {
        let treetop = Treetop::of(base)?;
        let previous: BTreeMap<u128, String> = base
            .segments(HISTOGRAMS)
            .iter()
            .map(|(name, r)| (r.first_key, name.clone()))
            .collect();
        let all = self.all_ids();
        let mut map_sets = MapSets::default();
        let mut plans = Vec::new();
        let mut pending = Vec::new();
        let mut replaced = BTreeSet::new();
        let mut kept = BTreeSet::new();
        for (index, unit) in treetop.units.iter().enumerate() {
            let state = unit_state(base, unit.key)?;
            let prior = match (previous.get(&unit.record.first_key), state) {
                (Some(name), Some(state)) if state.octree_digest == unit.record.content_digest => {
                    Some((name.clone(), map_sets.get(base, state.map_set)?))
                }
                _ => None,
            };
            let up_to_date = prior.as_ref().is_some_and(|(_, maps)| **maps == all);
            if up_to_date {
                if let Some((name, _)) = &prior {
                    kept.insert(name.clone());
                }
            } else {
                pending.push(index);
            }
            plans.push(UnitPlan {
                octree_segment: unit.segment.clone(),
                key: unit.key,
                previous: prior,
            });
        }
        for name in previous.into_values() {
            if !kept.contains(&name) {
                replaced.insert(name);
            }
        }
        // Consecutive pending units share one pass over the depth maps: each map is decoded
        // once per group, not once per unit.
        let largest = treetop.units.iter().map(|u| u.record.rows).max().unwrap_or(0).max(64);
        let cap = largest * self.group_leaves * LEAVES_IN_FLIGHT;
        let mut groups: Vec<Vec<usize>> = Vec::new();
        let mut load = 0u64;
        for index in pending {
            let rows = treetop.units.get(index).map_or(0, |u| u.record.rows);
            match groups.last_mut() {
                Some(group) if load + rows <= cap => {
                    group.push(index);
                    load += rows;
                }
                _ => {
                    groups.push(vec![index]);
                    load = rows;
                }
            }
        }
        let label = |members: &[usize], cubes: u64| -> Option<String> {
            let key = |i: usize| treetop.units.get(i).map(|u| u.key);
            Some(match members {
                [only] => format!("leaf {:?} ({cubes} cubes)", key(*only)?),
                _ => format!(
                    "leaves {:?} to {:?} ({} units, {cubes} cubes)",
                    key(*members.first()?)?,
                    key(*members.last()?)?,
                    members.len()
                ),
            })
        };
        let units = groups
            .iter()
            .filter_map(|members| {
                let cubes = members
                    .iter()
                    .filter_map(|&i| treetop.units.get(i))
                    .map(|u| u.record.rows)
                    .sum();
                Some(UnitSpec {
                    id: *members.first()? as u64,
                    label: label(members, cubes)?,
                    cubes,
                })
            })
            .collect();
        let by_id = groups
            .into_iter()
            .filter_map(|members| Some((*members.first()? as u64, members)));
        let _ = self.groups.set(by_id.collect());
        let _ = self.units.set(plans);
        Ok(Plan {
            units,
            replace: Replace::Names(replaced),
        })
    }

    /// One group at a time ([`GROUP_LEAVES`]): a group is sized for the memory of the leaves in
    /// flight, and votes on every thread.
    fn units_in_flight(&self) -> usize {
        1
    }

    fn run_unit(&self, base: &Snapshot<'_>, unit: &UnitSpec) -> Result<UnitOutput> {
        let plans = self.units.get().ok_or_else(|| StoreError::Stage {
            stage: HISTOGRAMS.into(),
            unit: unit.label.clone(),
            error: Box::new(StageError::internal("units run before planning")),
        })?;
        let members = self
            .groups
            .get()
            .and_then(|groups| groups.get(&unit.id))
            .cloned()
            .unwrap_or_else(|| vec![unit.id as usize]);
        // The members' cubes are read and placed in parallel: a group runs alone (one unit in
        // flight, see `GROUP_LEAVES`), and this is most of its setup.
        let mut voters = {
            use rayon::prelude::*;
            members
                .par_iter()
                .map(|&member| {
                    let plan = plans.get(member).ok_or_else(|| StoreError::Stage {
                        stage: HISTOGRAMS.into(),
                        unit: unit.label.clone(),
                        error: Box::new(StageError::internal("unit out of range")),
                    })?;
                    self.voter(base, plan)
                })
                .collect::<Result<Vec<_>>>()?
        };
        let evicted_before = self.cache.evictions();
        let on_gpu = match self.gpu.as_deref() {
            Some(gpu) if !gpu.is_lost() => match self.vote_on_gpu(gpu, &mut voters, unit)? {
                Ok(()) => true,
                Err(error) => {
                    tracing::warn!("{error}; {} votes on the CPU", unit.label);
                    false
                }
            },
            _ => false,
        };
        if let Some(gpu) = self.gpu.as_deref() {
            gpu.count(on_gpu);
        }
        if !on_gpu {
            // The voting loop reads and writes whole blocks of cubes in lane layout.
            for voter in &mut voters {
                relayout_for_lanes(&mut voter.offsets, &mut voter.hist, &mut voter.distance, true);
            }
            self.pass_over_maps(&mut voters, unit, |voters, batch| {
                for (index, voter) in voters.iter_mut().enumerate() {
                    voter.vote_batch(index, batch);
                }
                Ok(true)
            })?;
            for voter in &mut voters {
                relayout_for_lanes(&mut voter.offsets, &mut voter.hist, &mut voter.distance, false);
            }
        }
        // A pass that evicted pyramids leaves the cache holding its last maps, which the next
        // group's pass (in id order) reaches last, long after evicting them: they would only
        // take memory while the segments are built (RedKitchen at 512 MiB: 64 MiB beside the
        // 270 MiB of the group's columns, in one group). A pass that evicted none leaves every
        // map it used for the next group (an incremental run's few new maps).
        if self.cache.evictions() > evicted_before {
            self.cache.clear();
        }
        let mut segments = Vec::with_capacity(voters.len());
        let mut extra = UnitExtra {
            members: Vec::with_capacity(voters.len()),
            map_sets: Vec::new(),
        };
        for voter in voters {
            let keys = voter.keys(base)?;
            let map_set = catalog::map_set_digest(voter.voted.iter());
            if !extra.map_sets.iter().any(|(digest, _)| *digest == map_set) {
                extra.map_sets.push((map_set, voter.voted.into_iter().collect()));
            }
            extra.members.push((
                voter.key,
                HistogramState {
                    octree_digest: voter.octree_digest,
                    map_set,
                },
                voter.votes,
            ));
            segments.push(
                vec![
                    Column::keys(keys),
                    Column::new("hist", BINS as u16, ColumnValues::F32(voter.hist)),
                    Column::new("distance", 2, ColumnValues::F32(voter.distance)),
                ]
                .into(),
            );
        }
        Ok(UnitOutput {
            segments,
            extra: catalog::encode(&extra),
            block_rows: 0,
        })
    }

    fn finish(&self, txn: &WriteTransaction, _base: &Snapshot<'_>, units: &[(u64, UnitRecord)]) -> Result<String> {
        let mut table = txn.open_table(UNIT_STATE)?;
        let mut meta = txn.open_table(META)?;
        let mut votes = 0u64;
        for (_, record) in units {
            let extra: UnitExtra = catalog::decode("units_done", &record.extra)?;
            for (digest, ids) in extra.map_sets {
                let key = catalog::map_set_key(digest);
                if meta.get(key.as_bytes())?.is_none() {
                    meta.insert(
                        key.as_bytes(),
                        catalog::seal_encode("meta", key.as_str(), &ids).as_slice(),
                    )?;
                }
            }
            for (key, state, unit_votes) in extra.members {
                table.insert(
                    (HISTOGRAMS.as_bytes(), key),
                    catalog::seal_encode("unit_state", &(HISTOGRAMS, key), &state).as_slice(),
                )?;
                votes += unit_votes;
            }
        }
        // States of leaves the octree no longer has are dropped, then the sets that no state
        // refers to any more (every unit was voted by newer maps since).
        // Without a plan (never the case: every run plans first) nothing counts as an orphan.
        let leaves: Option<BTreeSet<CubeKey>> = self
            .units
            .get()
            .map(|plans| plans.iter().map(|plan| plan.key).collect());
        let mut referenced = BTreeSet::new();
        let mut orphans = Vec::new();
        for entry in table.range(
            (HISTOGRAMS.as_bytes(), CubeKey::from_raw(0))..=(HISTOGRAMS.as_bytes(), CubeKey::from_raw(u128::MAX)),
        )? {
            let (key, value) = entry?;
            let key = key.value().1;
            if leaves.as_ref().is_none_or(|leaves| leaves.contains(&key)) {
                let state: HistogramState = catalog::unseal_decode("unit_state", &(HISTOGRAMS, key), value.value())?;
                referenced.insert(state.map_set);
            } else {
                orphans.push(key);
            }
        }
        for key in orphans {
            table.remove((HISTOGRAMS.as_bytes(), key))?;
        }
        let mut unreferenced = Vec::new();
        for entry in meta.range(catalog::META_MAP_SET_PREFIX.as_bytes()..)? {
            let (key, _) = entry?;
            let key = catalog::key_text("meta", key.value())?;
            let Some(digest) = catalog::map_set_of_key(key) else {
                break;
            };
            if !referenced.contains(&digest) {
                unreferenced.push(key.to_string());
            }
        }
        for key in unreferenced {
            meta.remove(key.as_bytes())?;
        }
        // Logged, not recorded: the counts depend on scheduling, and the catalog must not.
        let (hits, misses) = self.cache.counts();
        tracing::info!("histograms: {misses} depth-map decodes, {hits} reused from the cache");
        Ok(format!(
            "{} unit(s) voted by {} depth map(s): {votes} votes",
            units.len(),
            self.depth_maps.len()
        ))
    }
}

/// One treetop unit of a group being voted: its cubes, its histograms so far, and the maps
/// that have voted into it.
struct Voter {
    key: CubeKey,
    /// The unit's octree segment, where its keys are read again for its histogram segment.
    octree_segment: String,
    /// The cubes as they are voted, on the CPU and the GPU: offsets from `center` and voting
    /// radii, in f32 ([`cube_offsets`]).
    offsets: Vec<Vec4>,
    hist: Vec<f32>,
    /// Two per cube: the weighted sum of its votes' truncated distances
    /// ([`crate::kernels::votes::truncated_distance`]) and the sum of their weights.
    distance: Vec<f32>,
    /// The least band of the distance sums ([`crate::kernels::votes::band_floor`]).
    band_floor: f64,
    already: Arc<BTreeSet<u64>>,
    voted: BTreeSet<u64>,
    votes: u64,
    octree_digest: u64,
    /// The unit's bounding ball, for the frustum test; its centre (the unit cube's) is also
    /// the origin of `offsets` and of the GPU's cube offsets.
    center: DVec3,
    radius: f64,
    /// Runs of Morton-consecutive cubes with their bounding balls, tested against each map's
    /// frustum before any of their cubes is projected.
    chunks: Vec<Chunk>,
}

impl Voter {
    /// The unit's keys, read again from its octree segment.
    fn keys(&self, base: &Snapshot<'_>) -> Result<Vec<CubeKey>> {
        let file = base.open_segment(&self.octree_segment)?;
        file.reader()?.read_keys().map_err(|e| file.corruption(e))
    }

    /// Votes the maps of `batch` that member `index` may see into its cubes, in the batch's
    /// order ([`vote_maps`]).
    fn vote_batch(&mut self, index: usize, batch: &[ReadyMap]) {
        let maps: Vec<MapVote<'_>> = batch
            .iter()
            .filter_map(|map| {
                let (_, seen) = map.needed.iter().find(|(member, _)| *member == index)?;
                let view = UnitView::new(&map.pyramid.source, &map.world_to_camera, self.center, self.band_floor);
                Some(MapVote::new(&map.pyramid, view, map.weight, seen))
            })
            .collect();
        if maps.is_empty() {
            return;
        }
        let cubes = ChunkedCubes {
            offsets: &self.offsets,
            chunks: &self.chunks,
        };
        self.votes += vote_maps(&cubes, &mut self.hist, &mut self.distance, &maps);
    }
}

/// What [`HistogramsStage::pass_over_maps`] hands each decoded map's voting: the members
/// that may see it, each with the chunks that may.
type Needed = Vec<(usize, Vec<usize>)>;

/// A decoded map that votes next (its source is `pyramid.source`), with what it needs.
struct ReadyMap {
    pyramid: Arc<Pyramid>,
    world_to_camera: glam::DMat4,
    weight: f32,
    needed: Needed,
}

impl HistogramsStage {
    /// One pass over the depth maps for the whole group, in id order. Every member a map has
    /// not voted into yet records it; the maps that may see some member's chunks are decoded
    /// (once per group, or taken from the cache) a batch at a time ([`Self::maps_per_batch`])
    /// and handed to `vote` in order, each with the members and chunks it may see. `vote`
    /// returns false to end the pass early.
    ///
    /// The next batch is decoded, its maps in parallel, while the last one votes
    /// (`rayon::join`): a group that runs alone (the last of a stage with more groups than
    /// threads) kept one core idle for each decode, about 3 ms a RedKitchen frame. The maps
    /// still vote in id order.
    fn pass_over_maps(
        &self,
        voters: &mut [Voter],
        unit: &UnitSpec,
        mut vote: impl FnMut(&mut [Voter], &[ReadyMap]) -> Result<bool> + Send,
    ) -> Result<()> {
        use rayon::prelude::*;
        let per_batch = self.maps_per_batch();
        let mut maps = self.depth_maps.iter();
        let mut ready: Vec<ReadyMap> = Vec::new();
        // The members' chunks, for the occlusion tests made beside the votes (which hold the
        // voters mutably).
        let chunk_lists: Vec<Vec<Chunk>> = voters.iter().map(|voter| voter.chunks.clone()).collect();
        loop {
            // The next maps that may see some member's chunks.
            let mut pending: Vec<(u64, &DepthMapSource, glam::DMat4, Needed)> = Vec::with_capacity(per_batch);
            for (id, record) in maps.by_ref() {
                let source = &record.source;
                let world_to_camera = source.pose().inverse();
                let needed = may_see(voters, *id, source, &world_to_camera);
                if !needed.is_empty() {
                    pending.push((*id, source, world_to_camera, needed));
                    if pending.len() == per_batch {
                        break;
                    }
                }
            }
            if pending.is_empty() {
                break;
            }
            let previous = std::mem::take(&mut ready);
            // Each map is decoded, and the chunks it sees only from far behind its surfaces
            // (which cast no vote) are dropped, in parallel.
            let load = || {
                pending
                    .par_iter()
                    .map(|(id, source, world_to_camera, needed)| {
                        let pyramid = self.load_pyramid(*id, source, &unit.label)?;
                        let needed: Needed = needed
                            .iter()
                            .filter_map(|(index, seen)| {
                                let chunks = chunk_lists.get(*index)?;
                                let seen: Vec<usize> = seen
                                    .iter()
                                    .copied()
                                    .filter(|&c| {
                                        chunks.get(c).is_some_and(|chunk| {
                                            !pyramid.farthest.hides(source, world_to_camera, chunk)
                                        })
                                    })
                                    .collect();
                                (!seen.is_empty()).then_some((*index, seen))
                            })
                            .collect();
                        Ok((pyramid, needed))
                    })
                    .collect::<Vec<Result<_>>>()
            };
            let cast = || {
                if previous.is_empty() {
                    Ok(true)
                } else {
                    vote(voters, &previous)
                }
            };
            let (pyramids, went_on) = rayon::join(load, cast);
            if !went_on? {
                return Ok(());
            }
            for ((_, source, world_to_camera, _), loaded) in pending.into_iter().zip(pyramids) {
                let (pyramid, needed) = loaded?;
                if !needed.is_empty() {
                    ready.push(ReadyMap {
                        weight: quantized_weight(source.weight),
                        pyramid,
                        world_to_camera,
                        needed,
                    });
                }
            }
        }
        if !ready.is_empty() {
            vote(voters, &ready)?;
        }
        Ok(())
    }

    /// Maps decoded and voted together: as many as keep two batches of the group (the one
    /// voting and the one decoding) within the pyramid cache's bytes, where the batches' maps
    /// stay as the most recently used (so batches add no memory to the cache's), and at most
    /// [`MAPS_AT_ONCE`]. RedKitchen at 512 MiB: 64 MiB of cache and 1.6 MB maps, 20 maps a
    /// batch. One map a batch without a cache.
    fn maps_per_batch(&self) -> usize {
        let largest = self
            .depth_maps
            .iter()
            .map(|(_, record)| u64::from(record.source.width) * u64::from(record.source.height))
            .max()
            .unwrap_or(1);
        // A pyramid's levels take 4/3 of the full level's 4 bytes a pixel, its farthest-depth
        // blocks a little more: 6 bytes a pixel bounds both.
        let pyramid_bytes = largest.max(1) * 6;
        let maps = self.cache.capacity / (2 * pyramid_bytes);
        usize::try_from(maps).unwrap_or(MAPS_AT_ONCE).clamp(1, MAPS_AT_ONCE)
    }

    /// Map `id`'s pyramid, from the cache or decoded (checking the file is the one ingested).
    fn load_pyramid(&self, id: u64, source: &DepthMapSource, unit: &str) -> Result<Arc<Pyramid>> {
        self.cache.get_or_load(id, || {
            self.check_unchanged(id, source, unit)?;
            let mut image = source.load().map_err(|e| StoreError::Stage {
                stage: HISTOGRAMS.into(),
                unit: unit.to_string(),
                error: Box::new(StageError::Input(Box::new(e))),
            })?;
            // A map that sees its content against nothing votes free space there.
            crate::kernels::background::mark_background(&mut image, &source.projection);
            Ok(Pyramid::new(source.clone(), image))
        })
    }

    /// The group's votes on `gpu` (`shaders/votes.wgsl`): the members' cubes and rows stay on
    /// the GPU for the whole pass and come back at the end. The outer error is the store's (a
    /// depth map that fails to load); the inner one is the GPU's, after which the members'
    /// rows are untouched and the caller votes on the CPU.
    fn vote_on_gpu(
        &self,
        gpu: &crate::gpu::Gpu,
        voters: &mut [Voter],
        unit: &UnitSpec,
    ) -> Result<std::result::Result<(), crate::gpu::GpuError>> {
        let mut store_error = None;
        let outcome = gpu.scoped(|| {
            // Each member's cubes in batches that fit one binding: (first cube, end, batch).
            let per_batch = gpu.vote_batch_cubes();
            let units = voters
                .iter()
                .map(|v| {
                    (0..v.offsets.len())
                        .step_by(per_batch)
                        .map(|start| {
                            let end = (start + per_batch).min(v.offsets.len());
                            let hist = v.hist.get(start * BINS..end * BINS).unwrap_or(&[]);
                            let distance = v.distance.get(2 * start..2 * end).unwrap_or(&[]);
                            let offsets = v.offsets.get(start..end).unwrap_or(&[]);
                            gpu.upload_unit(v.center, offsets, hist, distance, v.band_floor)
                                .map(|batch| (start, end, batch))
                        })
                        .collect::<std::result::Result<Vec<_>, _>>()
                })
                .collect::<std::result::Result<Vec<_>, _>>()?;
            let mut failure = None;
            let pass = self.pass_over_maps(voters, unit, |voters, batch| {
                let attempt = batch.iter().try_for_each(|ready| {
                    let (source, world_to_camera, weight) =
                        (&ready.pyramid.source, &ready.world_to_camera, ready.weight);
                    let map = gpu.upload_pyramid(&ready.pyramid)?;
                    for (index, seen) in &ready.needed {
                        let (Some(batches), Some(voter)) = (units.get(*index), voters.get(*index)) else {
                            continue;
                        };
                        for (start, end, on_gpu) in batches {
                            // Only batches holding a chunk that may see the map: the others
                            // cannot vote, as on the CPU.
                            let seen_here = seen
                                .iter()
                                .filter_map(|&c| voter.chunks.get(c))
                                .any(|chunk| chunk.start < *end && chunk.end > *start);
                            if seen_here {
                                gpu.vote(on_gpu, &map, source, world_to_camera, weight)?;
                            }
                        }
                    }
                    Ok(())
                });
                match attempt {
                    Ok(()) => Ok(true),
                    Err(error) => {
                        failure = Some(error);
                        Ok(false)
                    }
                }
            });
            if let Err(error) = pass {
                store_error = Some(error);
                return Ok(Vec::new());
            }
            if let Some(error) = failure {
                return Err(error);
            }
            units
                .iter()
                .map(|batches| {
                    let mut rows = (Vec::new(), Vec::new(), 0u64);
                    for (_, _, batch) in batches {
                        let voted = gpu.finish_unit(batch)?;
                        rows.0.extend(voted.hist);
                        rows.1.extend(voted.distance);
                        rows.2 += voted.votes;
                    }
                    Ok(rows)
                })
                .collect()
        });
        if let Some(error) = store_error {
            return Err(error);
        }
        Ok(outcome.map(|rows| {
            for (voter, (hist, distance, votes)) in voters.iter_mut().zip(rows) {
                voter.hist = hist;
                voter.distance = distance;
                voter.votes += votes;
            }
        }))
    }

    fn voter(&self, base: &Snapshot<'_>, plan: &UnitPlan) -> Result<Voter> {
        let file = base.open_segment(&plan.octree_segment)?;
        let reader = file.reader()?;
        let keys = reader.read_keys().map_err(|e| file.corruption(e))?;
        let (_, sums) = reader.read_u64("radius_sum").map_err(|e| file.corruption(e))?;
        let (_, counts) = reader.read_u32("radius_count").map_err(|e| file.corruption(e))?;
        let (centers, radii) = cube_geometry(&self.scene, &keys, &sums, &counts);
        let fresh = || {
            (
                written_zeros(keys.len() * BINS),
                written_zeros(2 * keys.len()),
                Arc::default(),
            )
        };
        let (hist, distance, already) = match &plan.previous {
            Some((name, maps)) => {
                let previous = base.open_segment(name)?;
                let reader = previous.reader()?;
                if reader.column("distance").is_ok() {
                    let (_, hist) = reader.read_f32("hist").map_err(|e| previous.corruption(e))?;
                    let (_, distance) = reader.read_f32("distance").map_err(|e| previous.corruption(e))?;
                    if hist.len() != keys.len() * BINS || distance.len() != 2 * keys.len() {
                        return Err(previous.corruption(crate::format::DecodeError::MissingColumn(
                            "hist and distance rows matching the octree unit".into(),
                        )));
                    }
                    (hist, distance, maps.clone())
                } else {
                    // Written before the distance column existed: every map votes again, so
                    // the distances cover the same votes as the bins.
                    fresh()
                }
            }
            None => fresh(),
        };
        let center = self.scene.cube_center(plan.key);
        let radius = self.scene.cube_side(plan.key.depth()) * 0.87 + radii.iter().copied().fold(0.0, f64::max);
        Ok(Voter {
            chunks: chunks(&centers, &radii),
            offsets: cube_offsets(center, &centers, &radii),
            key: plan.key,
            octree_segment: plan.octree_segment.clone(),
            hist,
            distance,
            band_floor: band_floor(&self.scene),
            voted: (*already).clone(),
            already,
            votes: 0,
            octree_digest: file_digest(base, &plan.octree_segment),
            center,
            radius,
        })
    }
}

/// The members map `id` has not voted into yet, each with the chunks the map's frustum may see
/// (none when it sees none of them); every such member records the map as voted. The members'
/// chunks are tested on every thread: the maps' tests run between the batches' votes, where
/// they kept a core idle (RedKitchen: 72 members, 15,400 chunks, 1000 maps).
fn may_see(voters: &mut [Voter], id: u64, source: &DepthMapSource, world_to_camera: &glam::DMat4) -> Needed {
    use rayon::prelude::*;
    let frustum = FrustumTest::new(source);
    let mut candidates = Vec::new();
    for (index, voter) in voters.iter_mut().enumerate() {
        if voter.already.contains(&id) {
            continue;
        }
        voter.voted.insert(id);
        if frustum.may_see_ball(world_to_camera, voter.center, voter.radius, voter.radius) {
            candidates.push((index, &voter.chunks));
        }
    }
    candidates
        .into_par_iter()
        .filter_map(|(index, chunks)| {
            let seen: Vec<usize> = chunks
                .iter()
                .enumerate()
                .filter(|(_, chunk)| {
                    frustum.may_see_ball(world_to_camera, chunk.center, chunk.radius, chunk.max_radius)
                })
                .map(|(chunk, _)| chunk)
                .collect();
            (!seen.is_empty()).then_some((index, seen))
        })
        .collect()
}

fn file_digest(base: &Snapshot<'_>, segment: &str) -> u64 {
    base.segments(OCTREE)
        .iter()
        .find(|(n, _)| n == segment)
        .map_or(0, |(_, r)| r.content_digest)
}

/// `len` zeros in memory written to, not merely allocated zeroed. The vote loop reads each
/// row before it writes it: in memory fresh from the system, the read maps the kernel's
/// shared page of zeros and the write then faults again to copy it, which on a process
/// running on several cores flushes the other cores' address translations by interrupt
/// (RedKitchen's histogram step: 3 % of its samples in that path). Written here first (in
/// parallel), each page faults once, straight to a page of its own.
fn written_zeros(len: usize) -> Vec<f32> {
    use rayon::prelude::*;
    let mut zeros = vec![0f32; len];
    zeros.par_chunks_mut(1 << 16).for_each(|chunk| chunk.fill(0.0));
    zeros
}
