//! Tests of the TGV kernel against its reference and itself.

use super::fused::*;
use super::lanes::{LaneLayout, *};
use super::*;

/// An irregular problem: rows with one, four or no terms, and frozen neighbours.
fn irregular_problem(n: usize) -> Problem {
    let mut start = vec![0u32];
    let mut terms = Vec::new();
    for c in 0..n {
        for axis in 0..3 {
            match (c + axis) % 4 {
                0 => terms.push((((c + 1) % n) as u32, 2.0)),
                1 => {
                    for k in 0..4 {
                        terms.push((((c + 3 + k) % n) as u32, 0.75));
                    }
                }
                2 => terms.push(((n + c % 5) as u32, 1.5)),
                _ => {}
            }
            start.push(terms.len() as u32);
        }
    }
    Problem {
        n,
        start,
        terms,
        frozen_u: (0..5).map(|i| i as f32 * 0.3 - 0.6).collect(),
        frozen_v: (0..5).map(|i| [i as f32 * 0.1, -0.2, 0.05]).collect(),
        hist: (0..n)
            .map(|c| std::array::from_fn(|b| ((c * 7 + b * 3) % 5) as f32))
            .collect(),
        alpha1: (0..n).map(|c| 0.5 + (c % 3) as f32 * 0.25).collect(),
        alpha0: (0..n).map(|c| 0.3 + (c % 2) as f32 * 0.2).collect(),
        lambda: 0.2,
    }
}

#[test]
fn kernel_results_do_not_depend_on_the_thread_count() {
    // More cubes than one parallel chunk, so the chunks' term cursors are exercised.
    let n = 2 * CHUNK + 123;
    let problem = irregular_problem(n);
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("thread pool");
        let mut state = State::zeros(n);
        state
            .u
            .iter_mut()
            .enumerate()
            .for_each(|(i, u)| *u = (i as f32 * 0.11).cos());
        pool.install(|| solve(&problem, &mut state, 15));
        state
    };
    let (one, three) = (run(1), run(3));
    assert!(one == three, "1 and 3 threads gave different iterates");
    // And the chunked kernel still follows the reference on a multi-chunk problem.
    let mut reference = State::zeros(n);
    reference
        .u
        .iter_mut()
        .enumerate()
        .for_each(|(i, u)| *u = (i as f32 * 0.11).cos());
    solve_reference(&problem, &mut reference, 15);
    let worst = one
        .u
        .iter()
        .zip(&reference.u)
        .map(|(a, b)| (a - b).abs())
        .fold(0f32, f32::max);
    assert!(worst < 1e-4, "kernel and reference differ by {worst}");
}

#[test]
fn fused_iteration_matches_the_reference() {
    let n = 40;
    let problem = irregular_problem(n);
    let mut a = State::zeros(n);
    a.u.iter_mut()
        .enumerate()
        .for_each(|(i, u)| *u = (i as f32 * 0.37).sin());
    let mut b = a.clone();
    let (fused_before, _) = solve(&problem, &mut a, 25);
    let (reference_before, _) = solve_reference(&problem, &mut b, 25);
    // The starting energy comes from the kernel's layout, and is the reference's to the bit.
    assert_eq!(fused_before.to_bits(), reference_before.to_bits());
    for c in 0..n {
        assert!((a.u[c] - b.u[c]).abs() < 1e-4, "u[{c}]: {} vs {}", a.u[c], b.u[c]);
        for i in 0..3 {
            assert!((a.v[c][i] - b.v[c][i]).abs() < 1e-4);
            assert!((a.p[c][i] - b.p[c][i]).abs() < 1e-4);
        }
        for k in 0..6 {
            assert!((a.q[c][k] - b.q[c][k]).abs() < 1e-4);
        }
    }
}

/// The lane groups must give exactly the bits of the one-cube steps, projections active or
/// not, with signed zeros among the inputs, so that where a chunk's cubes fall into groups
/// (and so the thread count) changes nothing.
#[test]
fn lane_groups_are_the_one_cube_steps_bit_for_bit() {
    struct Draw(u64);
    impl Draw {
        fn unit(&mut self) -> f32 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (self.0 >> 40) as f32 / (1u64 << 24) as f32
        }
        fn value(&mut self, scale: f32) -> f32 {
            match (self.unit() * 10.0) as u32 {
                0 => 0.0,
                1 => -0.0,
                _ => (self.unit() * 2.0 - 1.0) * scale,
            }
        }
        fn v4(&mut self, scale: f32) -> Vec4 {
            Vec4::new(
                self.value(scale),
                self.value(scale),
                self.value(scale),
                self.value(scale),
            )
        }
        fn v3(&mut self, scale: f32) -> Vec4 {
            Vec4::new(self.value(scale), self.value(scale), self.value(scale), 0.0)
        }
    }
    let mut draw = Draw(99);
    for _ in 0..300 {
        let scale = if draw.unit() < 0.5 { 3.0 } else { 0.2 };
        let bar: Vec<Vec4> = (0..8).map(|_| draw.v4(scale)).collect();
        let rows: Vec<Vec4> = (0..12).map(|_| draw.v4(scale)).collect();
        let lengths: [[u16; 4]; LANES] = std::array::from_fn(|_| std::array::from_fn(|_| (draw.unit() * 4.0) as u16));
        let gathers: Vec<Gather> = (0..64)
            .map(|_| Gather {
                // Some indices past the end: the gathers' fallbacks are part of the twin.
                index: (draw.unit() * 14.0) as u32,
                weight: draw.value(4.0),
            })
            .collect();
        let dual_k: [DualConstants; LANES] = std::array::from_fn(|_| DualConstants {
            sigma_p: draw.v4(2.0).abs(),
            sigma_q_diag: draw.v4(2.0).abs(),
            sigma_q_off: draw.v3(2.0).abs(),
        });
        let primal_k: [PrimalConstants; LANES] = std::array::from_fn(|_| PrimalConstants {
            tau: draw.v4(1.0).abs(),
            own: draw.v3(2.0),
        });
        let slopes: [Slopes; LANES] = std::array::from_fn(|_| Slopes(std::array::from_fn(|_| draw.value(6.0))));
        let centres: [Vec4; LANES] = std::array::from_fn(|_| draw.v4(scale));
        let (p, qd, qo): ([Vec4; LANES], [Vec4; LANES], [Vec4; LANES]) = (
            std::array::from_fn(|_| draw.v3(scale)),
            std::array::from_fn(|_| draw.v3(scale)),
            std::array::from_fn(|_| draw.v3(scale)),
        );
        let bits = |x: &[Vec4]| {
            x.iter()
                .flat_map(|v| v.to_array().map(f32::to_bits))
                .collect::<Vec<_>>()
        };

        // The lane path reads and writes the lane layout that `relayout` makes.
        let (mut lp, mut lqd, mut lqo) = (transpose(p), transpose(qd), transpose(qo));
        let mut lrows = [Vec4::ZERO; 3 * LANES];
        let mut terms = gathers.iter();
        let lane_k = DualLanes::of(&dual_k);
        assert_eq!(
            lane_k
                .cubes()
                .map(|k| bits(&[k.sigma_p, k.sigma_q_diag, k.sigma_q_off])),
            dual_k.map(|k| bits(&[k.sigma_p, k.sigma_q_diag, k.sigma_q_off]))
        );
        dual_lanes(
            &mut terms, &bar, &centres, &lane_k, &lengths, &mut lp, &mut lqd, &mut lqo, &mut lrows,
        );
        let (lp, lqd, lqo) = (transpose(lp), transpose(lqd), transpose(lqo));
        let lanes_left = terms.len();
        let (mut op, mut oqd, mut oqo, mut orows) = (p, qd, qo, [Vec4::ZERO; 3 * LANES]);
        let mut terms = gathers.iter();
        for c in 0..LANES {
            let rows = &mut orows[3 * c..3 * c + 3];
            dual(
                &mut terms,
                &bar,
                centres[c],
                &dual_k[c],
                &lengths[c],
                &mut op[c],
                &mut oqd[c],
                &mut oqo[c],
                rows,
            );
        }
        assert_eq!(lanes_left, terms.len(), "both walk the same terms");
        assert_eq!(bits(&lrows), bits(&orows));
        assert_eq!((bits(&lp), bits(&lqd), bits(&lqo)), (bits(&op), bits(&oqd), bits(&oqo)));

        let uv: [Vec4; LANES] = std::array::from_fn(|_| draw.v4(1.5));
        let (mut luv, mut lbar) = (transpose(uv), [Vec4::ZERO; LANES]);
        let mut terms = gathers.iter();
        let (lane_k, lane_slopes) = (PrimalLanes::of(&primal_k), SlopeLanes::of(&slopes));
        assert_eq!(
            lane_slopes.cubes().map(|s| s.0.map(f32::to_bits)),
            slopes.map(|s| s.0.map(f32::to_bits))
        );
        assert_eq!(
            lane_k.cubes().map(|k| bits(&[k.tau, k.own])),
            primal_k.map(|k| bits(&[k.tau, k.own]))
        );
        primal_lanes(
            &mut terms,
            &rows,
            &lrows,
            &lane_k,
            &lengths,
            &lane_slopes,
            0.3,
            &mut luv,
            &mut lbar,
        );
        let luv = transpose(luv);
        let (mut ouv, mut obar) = (uv, [Vec4::ZERO; LANES]);
        let mut terms = gathers.iter();
        for c in 0..LANES {
            let own = &lrows[3 * c..3 * c + 3];
            primal(
                &mut terms,
                &rows,
                own,
                &primal_k[c],
                &lengths[c],
                &slopes[c],
                0.3,
                &mut ouv[c],
                &mut obar[c],
            );
        }
        assert_eq!((bits(&luv), bits(&lbar)), (bits(&ouv), bits(&obar)));
    }
}

#[test]
fn prox_matches_brute_force() {
    let mut seed = 12345u64;
    let mut rand = || {
        seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (seed >> 33) as f32 / (1u64 << 31) as f32
    };
    for _ in 0..500 {
        let hist: [f32; BINS] = std::array::from_fn(|_| if rand() < 0.4 { 0.0 } else { (rand() * 6.0).round() });
        let u_tilde = rand() * 3.0 - 1.5;
        let tau_lambda = rand() * 0.3;
        let got = prox_histogram(u_tilde, tau_lambda, &hist);
        let objective = |u: f32| {
            (u - u_tilde).powi(2) / 2.0
                + tau_lambda * (0..BINS).map(|b| hist[b] * (u - bin_center(b)).abs()).sum::<f32>()
        };
        let mut best = (f32::INFINITY, 0f32);
        for i in 0..=20000 {
            let u = -1.0 + 2.0 * i as f32 / 20000.0;
            let o = objective(u);
            if o < best.0 {
                best = (o, u);
            }
        }
        assert!(
            objective(got) <= best.0 + 1e-4,
            "prox {got} (objective {}) vs brute force {} ({}) for {hist:?}, u~ {u_tilde}, tl {tau_lambda}",
            objective(got),
            best.1,
            best.0
        );
    }
}

#[test]
fn the_stopping_rule_stops_where_the_energy_settles_whatever_the_thread_count() {
    let n = 2 * CHUNK + 57;
    let problem = irregular_problem(n);
    let start = || {
        let mut state = State::zeros(n);
        state
            .u
            .iter_mut()
            .enumerate()
            .for_each(|(i, u)| *u = (i as f32 * 0.23).sin());
        state
    };
    let stopping = Stopping {
        max_iterations: 2000,
        tolerance: 1e-4,
    };
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .expect("thread pool");
        let mut state = start();
        let solved = pool.install(|| solve_accelerated(&problem, &mut state, stopping, |_, _, _| false));
        (state, solved)
    };
    let ((one, solved), (three, solved_three)) = (run(1), run(3));
    assert!(one == three, "1 and 3 threads stopped at different iterates");
    assert_eq!(solved, solved_three);
    assert!(
        solved.iterations % CHECK_INTERVAL == 0 && solved.iterations > CHECK_INTERVAL && solved.iterations < 2000,
        "stopped after {} iterations",
        solved.iterations
    );
    // Where it stopped, the energy is as low as many more iterations make it, to a small
    // multiple of the tolerance.
    let mut longer = start();
    let (_, settled) = solve(&problem, &mut longer, 2000);
    assert!(settled <= solved.energy_after);
    assert!(
        solved.energy_after - settled <= 20.0 * stopping.tolerance * settled,
        "stopped at {}, 2000 iterations reach {settled}",
        solved.energy_after
    );

    // A tolerance of 0 is the unchecked iteration, bit for bit, however it is batched; so is
    // a tolerance the energy never meets.
    let mut unchecked = start();
    let energies = solve(&problem, &mut unchecked, 60);
    for tolerance in [0.0, 1e-30] {
        let mut state = start();
        let solved = solve_accelerated(
            &problem,
            &mut state,
            Stopping {
                max_iterations: 60,
                tolerance,
            },
            |_, _, _| false,
        );
        assert_eq!(solved.iterations, 60);
        if tolerance == 0.0 {
            assert!(state == unchecked);
            assert_eq!((solved.energy_before, solved.energy_after), energies);
        } else {
            // Batches of 25, 25 and 10 restart the extrapolation: close, not equal.
            let worst = state
                .u
                .iter()
                .zip(&unchecked.u)
                .map(|(a, b)| (a - b).abs())
                .fold(0f32, f32::max);
            assert!(worst < 0.05, "u moved by {worst}");
        }
    }
}

#[test]
fn reference_steps_in_batches_stay_close_to_one_batch() {
    // The reference path (a gather list too long for the kernel) stops by the same rule, in
    // batches that restart the extrapolation; a restart must not throw the iterate off.
    let n = 40;
    let problem = irregular_problem(n);
    let op = Operator::new(&problem);
    let mut state = State::zeros(n);
    let before = start(&op, &mut state);
    let mut batched = state.clone();
    reference_steps(&op, &mut state, 50);
    reference_steps(&op, &mut batched, 25);
    reference_steps(&op, &mut batched, 25);
    let after = energy(&op, &state);
    assert!(after < before);
    let worst = state
        .u
        .iter()
        .zip(&batched.u)
        .map(|(a, b)| (a - b).abs())
        .fold(0f32, f32::max);
    assert!(worst < 0.05, "a restart moved u by {worst}");
}

#[test]
fn the_kernel_energy_is_the_reference_energy_to_the_bit() {
    // Iterates of an irregular problem (frozen neighbours, rows of zero to four terms) after
    // a few batches, active projections and signed zeros among them.
    let n = CHUNK + 77;
    let problem = irregular_problem(n);
    let op = Operator::new(&problem);
    let mut kernel = Kernel::new(&op).expect("short gather lists");
    let mut state = State::zeros(n);
    state
        .u
        .iter_mut()
        .enumerate()
        .for_each(|(i, u)| *u = if i % 9 == 0 { -0.0 } else { (i as f32 * 0.23).sin() });
    let mut packed = Packed::of(&state);
    for batch in [0, 1, 5, 20] {
        kernel.iterate(&mut packed, batch);
        packed.unpack_into(&mut state);
        let (fused, reference) = (kernel.energy(&problem, &packed), energy(&op, &state));
        assert_eq!(
            fused.to_bits(),
            reference.to_bits(),
            "after {batch} more: {fused} vs {reference}"
        );
        assert!(reference > 0.0);
    }
}

#[test]
fn energy_terms_in_lanes_are_the_per_cube_terms_to_the_bit() {
    // Every group of an irregular problem's iterate, with signed zeros in u and v and
    // histograms with empty and full bins: each lane's term is `cube_energy`'s.
    let n = 4 * 61;
    let mut problem = irregular_problem(n);
    for (c, hist) in problem.hist.iter_mut().enumerate() {
        *hist = std::array::from_fn(|b| {
            if (c + b) % 3 == 0 {
                0.0
            } else {
                ((c * 7 + b) % 5) as f32 * 0.5
            }
        });
    }
    let op = Operator::new(&problem);
    let mut kernel = Kernel::new(&op).expect("short gather lists");
    let mut state = State::zeros(n);
    state
        .u
        .iter_mut()
        .enumerate()
        .for_each(|(i, u)| *u = if i % 5 == 0 { -0.0 } else { (i as f32 * 0.31).cos() });
    let mut packed = Packed::of(&state);
    kernel.iterate(&mut packed, 3);
    for (i, uv) in packed.uv.iter_mut().enumerate().filter(|(i, _)| i % 7 == 0) {
        uv.y = if i % 2 == 0 { -0.0 } else { 0.0 };
    }
    for first in (0..n).step_by(LANES) {
        let centres: [Vec4; LANES] = std::array::from_fn(|i| packed.uv[first + i]);
        let differences = std::array::from_fn(|i| kernel.differences(&packed, first + i, centres[i]));
        let lanes = energy_lanes(&problem, first, &centres, &differences);
        for (i, term) in lanes.iter().enumerate() {
            let one = packed_cube_energy(&problem, first + i, centres[i], differences[i]);
            assert_eq!(term.to_bits(), one.to_bits(), "cube {}: {term} vs {one}", first + i);
        }
    }
}
