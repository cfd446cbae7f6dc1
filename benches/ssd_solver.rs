//! SSD throughput: cube-iterations per second of the preconditioned conjugate gradients of
//! `kernels::ssd` on a uniform grid of N^3 free cubes (`cargo bench --bench ssd_solver`;
//! OCTSTORE_BENCH_GRID sets N, default 100, i.e. 1 million cubes) holding a sphere's samples
//! in the cubes it crosses, started from zero (the iterations of a whole solve) and run to the
//! default residual target or OCTSTORE_BENCH_ITERATIONS (default 200), whichever comes first.

mod common;

use common::setting;
use std::time::Instant;

use octstore::testing::kernels::ssd::{CubeSamples, DEFAULT_NORMAL_WEIGHT, DEFAULT_SMOOTHNESS, SsdProblem, solve};

fn main() {
    let n: usize = setting("OCTSTORE_BENCH_GRID", 100);
    let iterations: usize = setting("OCTSTORE_BENCH_ITERATIONS", 200);
    let cubes = n * n * n;
    let index = |x: usize, y: usize, z: usize| (x + n * (y + n * z)) as u32;
    let h = 1.0 / n as f64;
    let mut start = vec![0u32];
    let mut terms = Vec::new();
    let mut samples = vec![CubeSamples::default(); cubes];
    // A sphere of radius 0.3 around the grid's centre: each cube it crosses holds one sample
    // at the nearest point of the sphere, its normal pointing out.
    let radius = 0.3;
    for z in 0..n {
        for y in 0..n {
            for x in 0..n {
                for (inside, next) in [
                    (x + 1 < n, index((x + 1).min(n - 1), y, z)),
                    (y + 1 < n, index(x, (y + 1).min(n - 1), z)),
                    (z + 1 < n, index(x, y, (z + 1).min(n - 1))),
                ] {
                    if inside {
                        terms.push((next, (1.0 / h) as f32));
                    }
                    start.push(terms.len() as u32);
                }
                let centre = [x, y, z].map(|i| (i as f64 + 0.5) * h - 0.5);
                let distance = centre.iter().map(|c| c * c).sum::<f64>().sqrt();
                if (distance - radius).abs() < 0.5 * h {
                    let normal = centre.map(|c| c / distance);
                    let sample = normal.map(|u| u * radius);
                    let s = &mut samples[index(x, y, z) as usize];
                    s.weight = h * h;
                    s.centroid = [0, 1, 2].map(|a| sample[a] - centre[a]);
                    s.normal = normal.map(|u| u * h * h);
                }
            }
        }
    }
    let problem = SsdProblem {
        n: cubes,
        start,
        terms,
        side: vec![h; cubes],
        samples,
        anchor: vec![0.0; cubes],
        frozen_f: Vec::new(),
        frozen_gradient: Vec::new(),
        normal_weight: DEFAULT_NORMAL_WEIGHT,
        smoothness: DEFAULT_SMOOTHNESS,
        ..SsdProblem::default()
    };
    // What a level unit computes besides the iterations, each timed on its own, the fastest of
    // five (a solve computes each once, the energy twice). The first right-hand side also
    // builds the reverse lists, which the later ones and the product reuse.
    let warm: Vec<f64> = (0..cubes).map(|c| (c % 7) as f64 * 1e-3).collect();
    let per_cube = |seconds: f64| seconds * 1e9 / cubes as f64;
    let started = Instant::now();
    std::hint::black_box(problem.rhs());
    println!(
        "ssd right-hand side with the reverse lists: {:.1} ns a cube",
        per_cube(started.elapsed().as_secs_f64())
    );
    let timed = |name: &str, work: &dyn Fn()| {
        let fastest = (0..5)
            .map(|_| {
                let started = Instant::now();
                work();
                started.elapsed().as_secs_f64()
            })
            .fold(f64::INFINITY, f64::min);
        println!("ssd {name}: {:.1} ns a cube", per_cube(fastest));
    };
    timed("right-hand side", &|| {
        std::hint::black_box(problem.rhs());
    });
    timed("diagonal", &|| {
        std::hint::black_box(problem.diagonal());
    });
    timed("energy", &|| {
        std::hint::black_box(problem.energy(&warm));
    });
    timed("product with its packing", &|| {
        std::hint::black_box(problem.apply(&warm));
    });
    let mut f = vec![0.0; cubes];
    let started = Instant::now();
    let solved = solve(&problem, &mut f, 1e-4, iterations);
    let seconds = started.elapsed().as_secs_f64();
    println!(
        "ssd solver: {cubes} cubes x {} iterations in {seconds:.2}s on {} threads: {:.2} million cube-iterations/s (relative residual {:.2e}, energy {:.3e} -> {:.3e})",
        solved.iterations,
        rayon::current_num_threads(),
        (cubes * solved.iterations) as f64 / seconds / 1e6,
        solved.relative_residual,
        solved.energy_before,
        solved.energy_after
    );
}
