use super::*;

#[test]
fn blocks_add_by_tiles_into_exactly_the_sums_a_search_per_row_gives() {
    let mut state = 0x2545_F491_4F6C_DD1Du64;
    let mut next = move |bound: u64| {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        state % bound
    };
    // Even x only, so odd x are keys the unit lacks; three and a half tiles.
    let mut keys: Vec<CubeKey> = (0..14_500)
        .map(|_| CubeKey::new(10, 2 * next(500) as u32, next(1024) as u32, next(1024) as u32))
        .collect();
    keys.sort_unstable();
    keys.dedup();
    assert!(keys.len() > 3 * TILE_KEYS, "{}", keys.len());
    let huge = i64::MAX / 3;
    let (low, high) = (i64::from(i32::MIN), i64::from(i32::MAX));
    let blocks: Vec<Arc<RunBlock>> = (0..40)
        .map(|b| {
            let mut rows: Vec<CubeKey> = (0..1024)
                .map(|_| match next(4) {
                    0 => CubeKey::new(10, 2 * next(500) as u32 + 1, next(1024) as u32, 0),
                    1 => CubeKey::new(9, next(1000) as u32, 0, 0),
                    _ => keys[next(keys.len() as u64) as usize],
                })
                .collect();
            rows.sort_unstable();
            rows.dedup();
            // Wide blocks with sums that saturate, so that the order of a cube's adds shows;
            // every third block narrow, with i32's extremes, so that their signs show.
            let moments: Vec<Moments> = rows
                .iter()
                .map(|_| match b % 3 {
                    0 => Moments {
                        weight: [high, low, 5][next(3) as usize],
                        offset: [next(9) as i64 - 4, high, low],
                        normal: [-(next(100) as i64), 1, high],
                    },
                    _ => Moments {
                        weight: [huge, -huge, 5][next(3) as usize],
                        offset: [next(9) as i64 - 4, huge, -huge],
                        normal: [-(next(100) as i64), 1, i64::MAX],
                    },
                })
                .collect();
            let [weight, offset, normal] =
                moment_columns(&moments).map(|c| MomentColumn::of(c.values).expect("a moment column"));
            assert_eq!(matches!(weight, MomentColumn::Narrow(_)), b % 3 == 0);
            let block = RunBlock::new(rows, weight, offset, normal);
            Arc::new(block.expect("one row of moments per key"))
        })
        .collect();
    let mut expected = vec![Moments::default(); keys.len()];
    for block in &blocks {
        for (row, key) in block.keys.iter().enumerate() {
            if let Ok(at) = keys.binary_search(key) {
                expected[at].add(&block.moments(row));
            }
        }
    }
    let mut whole = vec![Moments::default(); keys.len()];
    add_by_tiles(&keys, &blocks, &mut whole);
    assert!(whole == expected);
    let mut in_groups = vec![Moments::default(); keys.len()];
    for group in blocks.chunks(7) {
        add_by_tiles(&keys, group, &mut in_groups);
    }
    assert!(in_groups == expected);
    assert!(expected.iter().filter(|m| m.weight != 0).count() > keys.len() / 2);
}

#[test]
fn moment_columns_are_narrow_when_their_values_fit_and_decode_the_same_either_way() {
    let small = Moments {
        weight: i64::from(i32::MAX),
        offset: [-5, i64::from(i32::MIN), 7],
        normal: [0, 1, -1],
    };
    let wide = Moments {
        weight: i64::from(i32::MAX) + 1,
        ..small
    };
    let decode = |columns: [Column; 3]| {
        let [w, o, n] = columns.map(|c| MomentColumn::of(c.values).expect("a moment column"));
        let keys = (0..w.len() as u32).map(|x| CubeKey::new(4, x, 0, 0)).collect();
        RunBlock::new(keys, w, o, n).expect("matching lengths").all_moments()
    };
    let narrow = moment_columns(&[small, small]);
    assert!(narrow.iter().all(|c| matches!(c.values, ColumnValues::U32(_))));
    assert_eq!(decode(narrow), vec![small, small]);
    // One value past i32 widens its own column only.
    let mixed = moment_columns(&[small, wide]);
    assert!(matches!(mixed[0].values, ColumnValues::U64(_)));
    assert!(matches!(mixed[1].values, ColumnValues::U32(_)));
    assert_eq!(decode(mixed), vec![small, wide]);
    assert!(MomentColumn::of(ColumnValues::F32(vec![1.0])).is_none());
}

#[test]
fn a_samples_moments_are_relative_to_its_cube_and_sum_exactly() {
    let scene = Scene {
        root_min: [-1.0, -1.0, -1.0],
        root_side: 2.0,
        max_depth: 8,
    };
    let key = scene.key_at(DVec3::new(0.3, 0.2, -0.4), 3);
    let side = scene.cube_side(3);
    let centre = scene.cube_center(key);
    let point = centre + DVec3::new(0.25, -0.125, 0.0) * side;
    let m = Moments::of_sample(&scene, key, point, 0.5 * side * side, DVec3::Z);
    assert_eq!(m.weight, 1 << 23);
    assert_eq!(m.offset, [1 << 21, -(1 << 20), 0]);
    assert_eq!(m.normal, [0, 0, 1 << 23]);
    // In root units the centroid is the point, and the weight its area over the root's.
    let (w, centroid, normal) = m.in_root_units(key).expect("weight");
    let root = (point - scene.min()) / scene.root_side;
    assert!((w - 0.5 * (side / 2.0).powi(2)).abs() < 1e-15);
    for k in 0..3 {
        assert!((centroid[k] - root[k]).abs() < 1e-12);
    }
    assert!((normal[2] - w).abs() < 1e-15);
    // Integer sums do not depend on their order.
    let other = Moments::of_sample(&scene, key, centre, 0.3 * side * side, DVec3::X);
    let (mut a, mut b) = (m, other);
    a.add(&other);
    b.add(&m);
    assert_eq!(a, b);
}
