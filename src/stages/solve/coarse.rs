//! What the coarse levels of one solve read from every treetop unit, decoded once and shared by
//! their level stages. A coarse level's cut is small, but its one group takes every unit's
//! nodes down to the level, their histograms and their `sampled` flags, and each of those
//! levels decoded every unit's whole octree and histogram segments for them: on RedKitchen's
//! 1000 frames (3.9 M nodes) levels 3 to 7 took about half a second each, whatever the solver.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, PoisonError};

use crate::format::CubeKey;
use crate::kernels::votes::BINS;
use crate::stages::observed::unit_sampled;
use crate::stages::treetop::Treetop;
use crate::store::{Result, Snapshot};

/// The finest level whose cuts read the units through a [`CoarseRowsCache`]. Its nodes are
/// those of depth at most this: a level asks whether a node above it is a leaf, which needs
/// the node's children, so the list must reach the level itself.
pub const COARSE_ROWS_LEVEL: u8 = 7;

/// One unit's octree nodes of depth at most [`COARSE_ROWS_LEVEL`].
pub(super) struct CoarseUnit {
    pub keys: Vec<CubeKey>,
    /// Each node's row in the unit's octree segment, ascending.
    pub rows: Vec<u32>,
    /// Rows of the whole segment.
    pub total: usize,
    /// Each node's `stages::observed::sampled_nodes` flag, computed over the whole unit.
    pub sampled: Vec<bool>,
}

/// A unit's histograms and distance sums at the rows of its [`CoarseUnit`].
pub(super) struct CoarseHistograms {
    pub hist: Vec<[f32; BINS]>,
    pub distance: Vec<[f32; 2]>,
}

impl CoarseHistograms {
    /// The histogram and distance sums of the octree segment's row `row`; zero for a row the
    /// unit's coarse nodes do not hold.
    pub fn at(&self, unit: &CoarseUnit, row: u32) -> ([f32; BINS], [f32; 2]) {
        unit.rows
            .binary_search(&row)
            .ok()
            .and_then(|i| Some((*self.hist.get(i)?, *self.distance.get(i)?)))
            .unwrap_or(([0.0; BINS], [0.0; 2]))
    }
}

/// The coarse rows of a solve's units, by segment name (segments are immutable, so a name is
/// its content; a leaf's `sampled` flags also depend on the treetop's internal unit, so its
/// entry is named by both segments).
#[derive(Clone, Default)]
pub struct CoarseRowsCache(Arc<Mutex<CoarseRows>>);

#[derive(Default)]
struct CoarseRows {
    units: BTreeMap<String, Arc<CoarseUnit>>,
    /// The treetop's internal unit's nodes, sample and spike counts, once a leaf has read them.
    top: Option<(Vec<CubeKey>, Vec<u32>, Vec<u32>)>,
    histograms: BTreeMap<String, Arc<CoarseHistograms>>,
}

impl CoarseRowsCache {
    fn rows(&self) -> std::sync::MutexGuard<'_, CoarseRows> {
        self.0.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Treetop unit `unit`'s coarse nodes; `None` for a unit the treetop does not have.
    pub(super) fn unit(&self, base: &Snapshot<'_>, treetop: &Treetop, unit: usize) -> Result<Option<Arc<CoarseUnit>>> {
        let Some(info) = treetop.units.get(unit) else {
            return Ok(None);
        };
        let top = treetop.units.iter().find(|u| u.top).map_or("", |u| u.segment.as_str());
        let name = format!("{} {top}", info.segment);
        if let Some(found) = self.rows().units.get(&name) {
            return Ok(Some(found.clone()));
        }
        // Two workers may both decode a unit here; either result is the same. The treetop's
        // internal unit, which every leaf's flags consult, is decoded once per solve.
        let mut top = self.rows().top.clone();
        let Some((nodes, flags)) = unit_sampled(base, treetop, unit, &mut top)? else {
            return Ok(None);
        };
        let total = nodes.len();
        let (mut keys, mut rows, mut sampled) = (Vec::new(), Vec::new(), Vec::new());
        for ((key, flag), row) in nodes.into_iter().zip(flags).zip(0u32..) {
            if key.depth() <= COARSE_ROWS_LEVEL {
                keys.push(key);
                rows.push(row);
                sampled.push(flag);
            }
        }
        let coarse = Arc::new(CoarseUnit {
            keys,
            rows,
            total,
            sampled,
        });
        let mut rows = self.rows();
        rows.units.insert(name, coarse.clone());
        if rows.top.is_none() {
            rows.top = top;
        }
        Ok(Some(coarse))
    }

    /// The histograms of `unit`'s coarse nodes from its histogram segment `segment`.
    pub(super) fn histograms(
        &self,
        base: &Snapshot<'_>,
        segment: &str,
        unit: &CoarseUnit,
    ) -> Result<Arc<CoarseHistograms>> {
        if let Some(found) = self.rows().histograms.get(segment) {
            return Ok(found.clone());
        }
        let (hist, distance) = super::read_histograms(base, segment, unit.total)?;
        let pick = |values: &[f32], row: u32, width: usize, at: usize| {
            values.get(row as usize * width + at).copied().unwrap_or(0.0)
        };
        let coarse = Arc::new(CoarseHistograms {
            hist: unit
                .rows
                .iter()
                .map(|&row| std::array::from_fn(|b| pick(&hist, row, BINS, b)))
                .collect(),
            distance: unit
                .rows
                .iter()
                .map(|&row| std::array::from_fn(|k| pick(&distance, row, 2, k)))
                .collect(),
        });
        self.rows().histograms.insert(segment.to_string(), coarse.clone());
        Ok(coarse)
    }

    /// Whether samples reached each of `keys` (nodes of depth at most [`COARSE_ROWS_LEVEL`]):
    /// what `stages::observed::sampled_of` says of them.
    pub(super) fn sampled(&self, base: &Snapshot<'_>, treetop: &Treetop, keys: &[CubeKey]) -> Result<Vec<bool>> {
        let mut units: BTreeMap<usize, Option<Arc<CoarseUnit>>> = BTreeMap::new();
        let mut out = Vec::with_capacity(keys.len());
        for key in keys {
            let unit = treetop.unit_of(*key);
            if let std::collections::btree_map::Entry::Vacant(slot) = units.entry(unit) {
                slot.insert(self.unit(base, treetop, unit)?);
            }
            let flag = units.get(&unit).and_then(|coarse| {
                let coarse = coarse.as_ref()?;
                let at = coarse.keys.binary_search(key).ok()?;
                coarse.sampled.get(at).copied()
            });
            out.push(flag.unwrap_or(false));
        }
        Ok(out)
    }
}
