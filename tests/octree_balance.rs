//! 2:1 balance and completeness of the octree built from random requested cubes.

use octstore::Scene;
use octstore::Store;
use octstore::format::{Column, ColumnValues, CubeKey};
use octstore::store::{Plan, Replace, Result, RunOptions, Snapshot, Stage, UnitOutput, UnitSpec};
use octstore::testing::stages::octree::{OctreeStage, check_octree_keys};
use octstore::testing::stages::{INGEST, OCTREE};
use proptest::prelude::*;

/// Stands in for ingest: writes given sorted runs of requested cubes.
struct Runs(Vec<Vec<CubeKey>>);

impl Stage for Runs {
    fn name(&self) -> &'static str {
        INGEST
    }
    fn plan(&self, _: &Snapshot<'_>) -> Result<Plan> {
        Ok(Plan {
            units: (0..self.0.len() as u64)
                .map(|id| UnitSpec {
                    id,
                    label: format!("run {id}"),
                    cubes: 0,
                })
                .collect(),
            replace: Replace::Nothing,
        })
    }
    fn run_unit(&self, _: &Snapshot<'_>, unit: &UnitSpec) -> Result<UnitOutput> {
        let keys = self.0[unit.id as usize].clone();
        let n = keys.len();
        Ok(UnitOutput {
            segments: vec![
                vec![
                    Column::keys(keys),
                    Column::new("radius_sum", 1, ColumnValues::U64(vec![7; n])),
                    Column::new("radius_count", 1, ColumnValues::U32(vec![1; n])),
                ]
                .into(),
            ],
            extra: Vec::new(),
            block_rows: 16,
        })
    }
}

fn cube() -> impl Strategy<Value = CubeKey> {
    (1u8..9, any::<u32>(), any::<u32>(), any::<u32>()).prop_map(|(d, x, y, z)| {
        let m = (1u32 << d) - 1;
        CubeKey::new(d, x & m, y & m, z & m)
    })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]
    #[test]
    fn random_requests_give_a_complete_balanced_octree(
        runs in prop::collection::vec(prop::collection::vec(cube(), 1..40), 1..4),
        leaf_cubes in 8u64..400,
    ) {
        let runs: Vec<Vec<CubeKey>> = runs.into_iter().map(|mut r| { r.sort(); r.dedup(); r }).collect();
        let dir = tempfile::tempdir().unwrap();
        let store = Store::create(dir.path()).unwrap();
        let options = RunOptions { resume: false, threads: 2, progress: false };
        store.run_stage(&Runs(runs.clone()), &options).unwrap();
        let scene = Scene { root_min: [0.0; 3], root_side: 1.0, max_depth: 12 };
        // A tiny sort memory forces the external sorter to spill and merge.
        let stage = OctreeStage::new(scene, leaf_cubes, 64, store.scratch_dir(OCTREE).unwrap());
        store.run_stage(&stage, &options).unwrap();
        let snap = store.latest().unwrap();
        let mut keys = Vec::new();
        for (name, record) in snap.segments(OCTREE) {
            let file = snap.open_segment(name).unwrap();
            let reader = file.reader().unwrap();
            let (_, counts) = reader.read_u32("radius_count").unwrap();
            let node_keys = reader.read_keys().unwrap();
            prop_assert!(record.rows < leaf_cubes || node_keys[0].depth() == 0);
            for (k, c) in node_keys.iter().zip(&counts) {
                let requests = runs.iter().filter(|r| r.binary_search(k).is_ok()).count() as u32;
                prop_assert_eq!(*c, requests, "radius count of {:?}", k);
            }
            keys.extend(node_keys);
        }
        keys.sort();
        prop_assert_eq!(check_octree_keys(&keys), Vec::<String>::new());
        for run in &runs {
            for k in run {
                prop_assert!(keys.binary_search(k).is_ok(), "requested {:?} missing", k);
            }
        }
        prop_assert!(store.verify(&[octstore::testing::stages::octree::verify_octree]).unwrap().is_ok());
    }
}

#[test]
fn the_checker_catches_an_unbalanced_tree() {
    // Root, its 8 children, the 8 children of child 0 and the 8 children of a grandchild at the
    // far corner of child 0: the grandchild's neighbours across the root's inner faces are
    // missing at depth 2.
    let root = CubeKey::new(0, 0, 0, 0);
    let mut keys = vec![root];
    let c = octstore::testing::stages::octree::children(root);
    keys.extend(c);
    let g = octstore::testing::stages::octree::children(c[0]);
    keys.extend(g);
    keys.extend(octstore::testing::stages::octree::children(g[7]));
    keys.sort();
    let problems = check_octree_keys(&keys);
    assert!(problems.iter().any(|p| p.contains("not 2:1 balanced")), "{problems:?}");
}
