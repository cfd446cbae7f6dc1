//! Solver throughput: cube-iterations per second of the preconditioned primal-dual TGV steps on
//! a uniform grid of N^3 free cubes with histograms (`cargo bench --bench solver`;
//! OCTSTORE_BENCH_GRID sets N, default 100, i.e. 1 million cubes), on the CPU (the whole solve,
//! then the kernel's iterations alone) and then on
//! every GPU adapter wgpu finds (software ones included, marked as such). A GPU figure counts
//! the iterations only: the time of one iteration (upload, one step, read-back) is subtracted
//! from the time of all of them.

mod common;

use common::setting;
use std::time::Instant;

use octstore::testing::gpu::{Gpu, adapters};
use octstore::testing::kernels::tgv::{Kernel, Operator, Packed, Problem, State, solve};

fn main() {
    let n: usize = setting("OCTSTORE_BENCH_GRID", 100);
    let cubes = n * n * n;
    let index = |x: usize, y: usize, z: usize| (x + n * (y + n * z)) as u32;
    let h = 1.0 / n as f32;
    let mut start = vec![0u32];
    let mut terms = Vec::new();
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                for (axis, next) in [
                    (x + 1 < n, index(x + 1, y, z)),
                    (y + 1 < n, index(x, y + 1, z)),
                    (z + 1 < n, index(x, y, z + 1)),
                ]
                .into_iter()
                .enumerate()
                {
                    let _ = axis;
                    if next.0 {
                        terms.push((next.1, 1.0 / h));
                    }
                    start.push(terms.len() as u32);
                }
            }
        }
    }
    // A plane through the grid: votes inside below, outside above.
    let hist = (0..cubes)
        .map(|i| {
            let z = i / (n * n);
            let mut h = [0f32; 8];
            h[if z < n / 2 { 1 } else { 6 }] = 3.0;
            h
        })
        .collect();
    let problem = Problem {
        n: cubes,
        start,
        terms,
        frozen_u: Vec::new(),
        frozen_v: Vec::new(),
        hist,
        alpha1: vec![h; cubes],
        alpha0: vec![2.0 * h * h; cubes],
        lambda: 0.1,
    };
    let state = State::zeros(cubes);
    let iterations: usize = setting("OCTSTORE_BENCH_ITERATIONS", 200);
    let started = Instant::now();
    let (before, after) = solve(&problem, &mut state.clone(), iterations);
    let seconds = started.elapsed().as_secs_f64();
    println!(
        "solver: {cubes} cubes x {iterations} iterations in {seconds:.2}s on {} threads: {:.2} million cube-iterations/s (energy {before:.3e} -> {after:.3e})",
        rayon::current_num_threads(),
        (cubes * iterations) as f64 / seconds / 1e6
    );
    let op = Operator::new(&problem);
    let Some(mut kernel) = Kernel::new(&op) else {
        println!("solver: gather lists too long for the kernel; no GPU figures");
        return;
    };
    // The same iterations without the per-unit setup (step sizes, the kernel's columns) and the
    // energy evaluations, which a solve pays once per unit.
    let mut packed = Packed::of(&state);
    let started = Instant::now();
    kernel.iterate(&mut packed, iterations);
    let seconds = started.elapsed().as_secs_f64();
    println!(
        "solver iterations only: {cubes} cubes x {iterations} iterations in {seconds:.2}s on {} threads: {:.2} million cube-iterations/s",
        rayon::current_num_threads(),
        (cubes * iterations) as f64 / seconds / 1e6
    );
    let found = adapters();
    if found.is_empty() {
        println!("solver: no GPU adapter found (WGPU_BACKEND chooses backends)");
    }
    for (index, adapter) in found.iter().enumerate() {
        let kind = if adapter.software { "software" } else { "hardware" };
        let gpu = match Gpu::open_adapter(index) {
            Ok(gpu) => gpu,
            Err(error) => {
                println!("solver on {} ({kind}): {error}", adapter.name);
                continue;
            }
        };
        let time = |steps: usize| {
            let mut packed = Packed::of(&state);
            let started = Instant::now();
            octstore::testing::gpu::tgv_dispatch::iterate(&gpu, &kernel, &mut packed, steps)
                .map(|()| started.elapsed().as_secs_f64())
        };
        match (time(1), time(iterations)) {
            (Ok(one), Ok(all)) => println!(
                "solver on {} ({kind}, {}): {cubes} cubes x {iterations} iterations in {all:.2}s ({one:.2}s for one with upload and read-back): {:.2} million cube-iterations/s",
                adapter.name,
                adapter.backend,
                (cubes * (iterations - 1)) as f64 / (all - one).max(1e-9) / 1e6
            ),
            (Err(error), _) | (_, Err(error)) => println!("solver on {} ({kind}): {error}", adapter.name),
        }
    }
}
