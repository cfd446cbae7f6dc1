//! A level's segments (`solution-LL`): the solver's state and what the data says about each
//! cube, one row per cut cube, as format-spec.md lays them out.

use std::collections::BTreeMap;

use super::cut::WindowTest;
use crate::format::{Column, ColumnValues, CubeKey};
use crate::store::{Result, Snapshot};

/// A unit's cut values at one level.
pub struct LevelValues {
    pub keys: Vec<CubeKey>,
    pub u: Vec<f32>,
    pub v: Vec<[f32; 3]>,
    pub p: Vec<[f32; 3]>,
    pub q: Vec<[f32; 6]>,
}

impl LevelValues {
    pub fn find(&self, key: CubeKey) -> Option<usize> {
        self.keys.binary_search(&key).ok()
    }
}

/// Which of the solver's state a level segment keeps.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Kept {
    /// u, v and the duals p and q: the next level starts from all four.
    WithDuals,
    /// u and v only: the finest level (the octree's maximum depth), which no level reads from.
    /// p and q are 9 of the state's 13 floats and hardly compress (`with_raw_literals`); left
    /// out there, the 415 M-sample city's store loses about a quarter of its bytes.
    Solution,
}

/// The level segment's columns: the solver's state (`kept`), then what the data says about each
/// cube (`stages::observed`).
pub(super) fn columns_of(values: &LevelValues, observed: ObservedColumns, kept: Kept) -> Vec<Column> {
    let flat = |rows: &[[f32; 3]]| rows.iter().flatten().copied().collect::<Vec<f32>>();
    let mut columns = vec![
        Column::keys(values.keys.clone()),
        Column::new("u", 1, ColumnValues::F32(values.u.clone())),
        Column::new("v", 3, ColumnValues::F32(flat(&values.v))).with_raw_literals(),
    ];
    if kept == Kept::WithDuals {
        columns.push(Column::new("p", 3, ColumnValues::F32(flat(&values.p))).with_raw_literals());
        columns.push(
            Column::new("q", 6, ColumnValues::F32(values.q.iter().flatten().copied().collect())).with_raw_literals(),
        );
    }
    columns.extend([
        Column::new("seen", 1, ColumnValues::F32(observed.seen)),
        Column::new("sampled", 1, ColumnValues::U32(observed.sampled)),
        Column::new("surface_offset", 1, ColumnValues::F32(observed.offset)),
        Column::new("measured", 1, ColumnValues::F32(observed.measured)),
    ]);
    columns
}

/// A level segment's columns from `stages::observed`, one row per cube.
pub(super) struct ObservedColumns {
    pub(super) seen: Vec<f32>,
    pub(super) sampled: Vec<u32>,
    pub(super) offset: Vec<f32>,
    pub(super) measured: Vec<f32>,
}

/// Reads a level segment below the finest: the finest keeps no duals ([`Kept::Solution`]),
/// and its u is read with [`read_level_u`].
pub fn read_level_values(snapshot: &Snapshot<'_>, segment: &str) -> Result<LevelValues> {
    read_level_values_where(snapshot, segment, None)
}

/// [`read_level_values`] of the blocks whose cubes may meet `window` (all when `None`).
pub(super) fn read_level_values_where(
    snapshot: &Snapshot<'_>,
    segment: &str,
    window: Option<&WindowTest>,
) -> Result<LevelValues> {
    let file = snapshot.open_segment(segment)?;
    let whole = file.reader()?;
    let reader = whole.with_blocks_where(|first, last| window.is_none_or(|w| w.may_meet_cut_between(first, last)));
    let c = |e| file.corruption(e);
    let keys = reader.read_keys().map_err(c)?;
    let (_, u) = reader.read_f32("u").map_err(c)?;
    let (_, v) = reader.read_f32("v").map_err(c)?;
    let (_, p) = reader.read_f32("p").map_err(c)?;
    let (_, q) = reader.read_f32("q").map_err(c)?;
    let n = keys.len();
    if u.len() != n || v.len() != 3 * n || p.len() != 3 * n || q.len() != 6 * n {
        return Err(file.corruption(crate::format::DecodeError::MissingColumn(
            "u, v, p, q of matching lengths".into(),
        )));
    }
    let triple = |x: &[f32]| x.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
    Ok(LevelValues {
        keys,
        u,
        v: triple(&v),
        p: triple(&p),
        q: q.chunks_exact(6)
            .map(|c| [c[0], c[1], c[2], c[3], c[4], c[5]])
            .collect(),
    })
}

/// A level's segments by group. A level unit solves a group of consecutive treetop units (small
/// leaves are batched); its id is the index of its first treetop unit, so treetop unit i's values
/// are in the last group starting at or before i (or nowhere: then that group lacks its keys).
pub struct LevelSegments {
    by_first_unit: BTreeMap<u64, String>,
}

impl LevelSegments {
    pub fn of(snapshot: &Snapshot<'_>, stage: &str) -> LevelSegments {
        LevelSegments {
            by_first_unit: snapshot
                .segments(stage)
                .iter()
                .map(|(name, record)| (record.unit, name.clone()))
                .collect(),
        }
    }

    /// The group that may hold treetop unit `unit`: its id and segment.
    pub fn group_of(&self, unit: usize) -> Option<(u64, &str)> {
        self.by_first_unit
            .range(..=unit as u64)
            .next_back()
            .map(|(id, name)| (*id, name.as_str()))
    }
}
