//! Tests of the division's geometry: exact corners, the locator, counts and the lookup.

use super::*;

#[test]
fn node_corners_are_exact_and_grid_cells_agree_with_them() {
    let root = Root::around([-3.7, 100.25, 1e-3], [12.1, 101.0, 5.0]).expect("a box");
    assert_eq!(root.size, 16.0);
    let node = Node {
        level: 5,
        index: [7, 30, 3],
    };
    let core = root.core(node);
    let side = root.side(5);
    assert_eq!(core.max[0] - core.min[0], side);
    // The corner and the far corner are grid points: the cell of each corner is the node.
    assert_eq!(Node::holding(root.grid(core.min), 5), node);
    let below = core.max.map(|m| m - root.unit() * 0.5);
    assert_eq!(Node::holding(root.grid(below), 5), node);
    let next = Node::holding(root.grid(core.max), 5);
    assert_eq!(next.index, [8, 31, 4]);
    for p in [[-3.7, 100.25, 1e-3], [12.1, 101.0, 5.0], [0.0, 100.5, 2.5]] {
        let g = root.grid(p);
        let n = Node::holding(g, 9);
        assert!(root.core(n).contains(p), "{p:?} in {n:?}");
    }
}

#[test]
fn node_locator_agrees_with_the_exact_grid() {
    let root = Root::around([-3.7, 100.25, 1e-3], [12.1, 101.0, 5.0]).expect("a box");
    let mut points = vec![[-3.7, 100.25, 1e-3], [12.1, 101.0, 5.0], [-50.0, 1e9, -1.0]];
    // Node faces and their neighbouring doubles, where the fast path must step aside.
    for level in [0, 3, 9, 20, 32] {
        let side = root.side(level);
        for k in [1.0, 5.0, 17.0] {
            let face = root.min[0] + (k * side).min(root.size);
            for x in [face, face.next_down(), face.next_up()] {
                points.push([x, 100.5, 2.5]);
            }
        }
    }
    // Just below the root's corner (within a node of it and farther), and no number at all.
    for below in [1e-12, 1e-3, 0.7, 3.0] {
        points.push([root.min[0] - below, root.min[1] - below, 2.5]);
    }
    points.extend([[f64::NAN, 100.5, 2.5], [f64::INFINITY, 100.5, f64::NEG_INFINITY]]);
    let mut state = 1u64;
    for _ in 0..10_000 {
        state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        let unit = |shift: u32| ((state >> shift) & 0xFFFF) as f64 / 65_536.0;
        points.push([-4.0 + 17.0 * unit(0), 100.0 + 1.5 * unit(16), -0.5 + 6.0 * unit(32)]);
    }
    let (mut clear, mut in_root) = (0, 0);
    for p in points {
        for level in [0, 1, 4, 7, 10, 21, 32] {
            assert_eq!(
                root.locator(level).index(p),
                Node::holding(root.grid(p), level).index,
                "{p:?} at level {level}"
            );
            // A clear point lies strictly inside its node (the write pass skips the node's
            // test for it).
            if let Some(index) = root.locator(level).clear_index(p) {
                let cube = root.core(Node { level, index });
                assert!(
                    (0..3).all(|a| cube.min[a] < p[a] && p[a] < cube.max[a]),
                    "{p:?} at level {level}"
                );
                if level <= 10 {
                    clear += 1;
                }
            }
            if level <= 10 && root.contains(p) {
                in_root += 1;
            }
        }
    }
    // Nearly every point inside the root at the levels up to 10 (nodes of at least a
    // thousandth of the root; the finest levels' nodes are a few grid units).
    assert!(clear <= in_root && clear >= in_root * 99 / 100, "{clear} of {in_root}");
}

/// Points added on pool threads with private copies, and on a thread of no pool (one
/// atomic add per run of equal cells), give the same counts.
#[test]
fn counts_with_private_copies_and_shared_adds_agree() -> Result<(), rayon::ThreadPoolBuildError> {
    let root = Root::around([0.0; 3], [1.0; 3]).expect("a box");
    let points: Vec<[f64; 3]> = (0..5000u32)
        .map(|i| {
            let t = f64::from(i) / 5000.0;
            // Runs of equal cells and jumps between them.
            [t, (t * 7.0).fract(), if i % 3 == 0 { 0.9 } else { t * t }]
        })
        .collect();
    let count = |counts: &Counts| {
        let locator = root.locator(counts.level());
        for chunk in points.chunks(700) {
            counts.add_with(|adder| {
                for p in chunk {
                    if let Some(cell) = counts.cells().of_index(locator.index(*p)) {
                        adder.add(cell);
                    }
                }
            });
        }
    };
    let mut shared = Counts::new(Node::ROOT, 3, 0);
    count(&shared);
    shared.finish();
    let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build()?;
    let mut private = pool.install(|| {
        let counts = Counts::new(Node::ROOT, 3, u64::MAX);
        count(&counts);
        counts
    });
    assert_eq!(private.per_thread.len(), 2);
    private.finish();
    assert_eq!(private.of(Node::ROOT), 5000);
    for x in 0..8 {
        for z in 0..8 {
            let node = Node {
                level: 3,
                index: [x, 5, z],
            };
            assert_eq!(private.of(node), shared.of(node), "{node:?}");
        }
    }
    Ok(())
}

#[test]
fn counts_sum_up_and_leaves_respect_the_limit() {
    let root = Root::around([0.0; 3], [1.0; 3]).expect("a box");
    let mut counts = Counts::new(Node::ROOT, 3, 0);
    let mut points = Vec::new();
    for i in 0..1000u32 {
        // Dense near the origin, sparse far away.
        let t = f64::from(i) / 1000.0;
        points.push([t * t, t * t * t, t * 0.5]);
    }
    counts.add_with(|adder| {
        for p in &points {
            let cell = counts
                .cells()
                .of_index(root.locator(counts.level()).index(*p))
                .expect("inside");
            adder.add(cell);
        }
    });
    counts.finish();
    assert_eq!(counts.of(Node::ROOT), 1000);
    let (leaves, again) = choose_leaves(&counts, 100);
    let total: u64 = leaves.iter().chain(&again).map(|(_, c)| c).sum();
    assert_eq!(total, 1000);
    assert!(leaves.iter().all(|(_, c)| *c <= 100));
    assert!(again.iter().all(|(n, c)| *c > 100 && n.level == 3));
    for p in &points {
        let g = root.grid(*p);
        let holders = leaves
            .iter()
            .chain(&again)
            .filter(|(n, _)| n.holds(Node::holding(g, n.level)))
            .count();
        assert_eq!(holders, 1);
    }
}

/// The lookup's answer, with its cells that skip the test, is the brute-force one: for
/// points inside the node, on cell faces, and outside it (a scratch file's overlap).
#[test]
fn lookup_places_each_point_in_exactly_the_grown_cubes_that_hold_it() {
    let root = Root::around([0.0; 3], [1.0; 3]).expect("a box");
    let top = Node {
        level: 1,
        index: [1, 0, 1],
    };
    // Subspaces of two levels under `top`, as a division leaves them.
    let mut nodes = Vec::new();
    for (i, child) in top.children().into_iter().enumerate() {
        if i % 3 == 0 {
            nodes.extend(child.children());
        } else {
            nodes.push(child);
        }
    }
    let grown: Vec<Bounds> = nodes.iter().map(|n| root.grown(*n, 0.1)).collect();
    let core = root.core(top);
    let side = core.max[0] - core.min[0];
    let mut checked_sure = 0;
    for depth in [2, 3, 4] {
        let lookup = Lookup::new(&root, top, depth, &grown);
        // Cells with a sole target skip the test; listed cells skip it for the targets
        // that hold them and test the others.
        let sole = lookup.cells.iter().filter(|e| **e & Lookup::SOLE != 0).count();
        let sure = lookup.lists.iter().filter(|t| **t & Lookup::HOLDS_CELL != 0).count();
        assert!(
            sole > 0 && sole < lookup.cells.len() && sure > 0,
            "depth {depth}: {sole} sole, {sure} sure"
        );
        checked_sure += sole + sure;
        // A lattice finer than the cells, shifted so that some points lie on cell faces,
        // reaching a fifth of the node beyond it on every side.
        let steps = 37;
        let points: Vec<[f64; 3]> = (0..steps * steps * steps)
            .map(|i| {
                let u = [i % steps, (i / steps) % steps, i / (steps * steps)]
                    .map(|k| -0.2 + 1.4 * f64::from(k) / f64::from(steps - 1));
                [0, 1, 2].map(|a| core.min[a] + u[a] * side)
            })
            .collect();
        let mut run_hits = vec![Vec::new(); points.len()];
        lookup.place_run(&points, &grown, |i, t| {
            if let Some(h) = run_hits.get_mut(i) {
                h.push(t);
            }
        });
        for (&p, from_run) in points.iter().zip(&run_hits) {
            let mut hits = Vec::new();
            lookup.place(p, &grown, |t| hits.push(t));
            assert_eq!(
                &hits, from_run,
                "depth {depth}, point {p:?}: one point and a run disagree"
            );
            hits.sort_unstable();
            let expected: Vec<u32> = (0..grown.len() as u32)
                .filter(|&t| grown.get(t as usize).is_some_and(|b| b.contains(p)))
                .collect();
            assert_eq!(hits, expected, "depth {depth}, point {p:?}");
        }
    }
    assert!(checked_sure > 0);
}
