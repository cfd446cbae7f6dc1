//! The GPU solver against its CPU twins and the CPU kernel. The shaders run on whatever adapter
//! `--device gpu` would take; CI installs llvmpipe (Debian's mesa-vulkan-drivers), so these
//! tests fail, rather than skip, on a machine with no Vulkan adapter at all.

use glam::Vec4;
use octstore::gpu::{DeviceChoice, Gpu, twins};
use octstore::stages::tgv::{self, Kernel, Operator, Packed, Problem, State};

/// A g x g x g grid of cubes with D's terms to the `+` neighbour, frozen neighbours on part of
/// the boundary, rows of four finer terms here and there (level jumps), random weights,
/// histograms and starting state.
fn grid_problem(g: usize, seed: u64) -> (Problem, State) {
    let mut seed = seed;
    let mut uniform = move || {
        seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (seed >> 11) as f32 / (1u64 << 53) as f32
    };
    let n = g * g * g;
    let index = |x: usize, y: usize, z: usize| (x + g * (y + g * z)) as u32;
    let mut start = vec![0u32];
    let mut terms = Vec::new();
    let mut frozen = 0u32;
    for z in 0..g {
        for y in 0..g {
            for x in 0..g {
                for axis in 0..3 {
                    let at = [x, y, z];
                    if at[axis] + 1 < g {
                        let mut next = at;
                        next[axis] += 1;
                        if uniform() < 0.1 {
                            // Four finer neighbours: the mean, each a quarter.
                            for _ in 0..4 {
                                let t = (uniform() * n as f32) as u32 % n as u32;
                                terms.push((t, 0.25 * 8.0));
                            }
                        } else {
                            terms.push((index(next[0], next[1], next[2]), 8.0));
                        }
                    } else if uniform() < 0.5 {
                        terms.push((n as u32 + frozen, 8.0));
                        frozen += 1;
                    }
                    start.push(terms.len() as u32);
                }
            }
        }
    }
    let hist = (0..n)
        .map(|_| {
            std::array::from_fn(|_| {
                if uniform() < 0.4 {
                    (uniform() * 8.0).round()
                } else {
                    0.0
                }
            })
        })
        .collect();
    let problem = Problem {
        n,
        start,
        terms,
        frozen_u: (0..frozen).map(|_| uniform() * 2.0 - 1.0).collect(),
        frozen_v: (0..frozen)
            .map(|_| [uniform() - 0.5, uniform() - 0.5, uniform() - 0.5])
            .collect(),
        hist,
        alpha1: (0..n).map(|_| 0.125 * (0.5 + uniform())).collect(),
        alpha0: (0..n).map(|_| 2.0 * 0.015625 * (0.5 + uniform())).collect(),
        lambda: 0.1,
    };
    let mut state = State::zeros(n);
    for c in 0..n {
        state.u[c] = uniform() * 2.0 - 1.0;
        state.v[c] = [uniform() - 0.5, uniform() - 0.5, uniform() - 0.5];
    }
    (problem, state)
}

fn open_gpu() -> Gpu {
    match Gpu::open(DeviceChoice::Gpu) {
        Ok(Some(gpu)) => gpu,
        Ok(None) => panic!("--device gpu opened nothing"),
        Err(error) => panic!("{error}"),
    }
}

/// Largest difference relative to 1 + |reference|, over every lane of every value.
fn worst(reference: &[Vec4], other: &[Vec4]) -> f32 {
    assert_eq!(reference.len(), other.len());
    reference
        .iter()
        .zip(other)
        .map(|(a, b)| ((*a - *b).abs() / (Vec4::ONE + a.abs())).max_element())
        .fold(0.0, f32::max)
}

#[test]
fn twins_are_the_cpu_kernel_bit_for_bit() {
    let (problem, state) = grid_problem(9, 3);
    let op = Operator::new(&problem);
    let kernel = Kernel::new(&op).expect("short gather lists");
    let mut cpu = Packed::of(&state);
    kernel.iterate(&mut cpu, 40);
    let mut twin = Packed::of(&state);
    twins::iterate(&kernel, &mut twin, 40);
    assert_eq!(cpu, twin);
    assert_ne!(cpu, Packed::of(&state), "the iterations moved the state");
}

/// What the GPU may differ by after 100 iterations: it may fuse multiply-adds and reorder
/// nothing else, so differences stay near float rounding, amplified a little by the iteration.
const GPU_TOLERANCE: f32 = 1e-4;

#[test]
fn gpu_iterations_match_the_twins() {
    let gpu = open_gpu();
    for (g, seed) in [(1, 1), (7, 5), (23, 9)] {
        let (problem, state) = grid_problem(g, seed);
        let op = Operator::new(&problem);
        let kernel = Kernel::new(&op).expect("short gather lists");
        let mut twin = Packed::of(&state);
        twins::iterate(&kernel, &mut twin, 100);
        let mut on_gpu = Packed::of(&state);
        octstore::gpu::tgv::iterate(&gpu, &kernel, &mut on_gpu, 100).expect("the GPU runs the unit");
        for (name, a, b) in [
            ("uv", &twin.uv, &on_gpu.uv),
            ("p", &twin.p, &on_gpu.p),
            ("q_diag", &twin.q_diag, &on_gpu.q_diag),
            ("q_off", &twin.q_off, &on_gpu.q_off),
        ] {
            let w = worst(a, b);
            eprintln!("{g}^3 cubes, {name}: worst relative difference {w:e}");
            assert!(
                w <= GPU_TOLERANCE,
                "{g}^3 cubes on {}: {name} differs by {w}",
                gpu.adapter.name
            );
        }
    }
}

#[test]
fn a_unit_over_the_gpu_limits_runs_on_the_cpu_with_the_same_result() {
    let (problem, state) = grid_problem(8, 7);
    let mut cpu = state.clone();
    let cpu_energy = tgv::solve(&problem, &mut cpu, 30);
    // Bindings of 1 KiB: every buffer of a 512-cube unit is larger.
    let gpu = open_gpu().with_binding_limit(1024);
    let mut fallback = state.clone();
    let fallback_energy = tgv::solve_on(Some(&gpu), &problem, &mut fallback, 30);
    assert_eq!(cpu, fallback);
    assert_eq!(cpu_energy, fallback_energy);
    assert_eq!(gpu.counts(), (0, 1), "the unit fell back");
    let too_large = octstore::gpu::tgv::iterate(
        &gpu,
        &Kernel::new(&Operator::new(&problem)).expect("short gather lists"),
        &mut Packed::of(&state),
        1,
    );
    assert!(
        matches!(too_large, Err(octstore::gpu::GpuError::TooLarge { .. })),
        "{too_large:?}"
    );
}

#[test]
fn solve_on_the_gpu_lowers_the_energy_like_the_cpu() {
    let gpu = open_gpu();
    let (problem, state) = grid_problem(12, 11);
    let mut cpu = state.clone();
    let (cpu_before, cpu_after) = tgv::solve(&problem, &mut cpu, 60);
    let mut on_gpu = state.clone();
    let (gpu_before, gpu_after) = tgv::solve_on(Some(&gpu), &problem, &mut on_gpu, 60);
    assert_eq!(cpu_before, gpu_before);
    assert!(gpu_after < gpu_before);
    assert!(
        (gpu_after - cpu_after).abs() <= 1e-4 * cpu_after.abs(),
        "energy after: GPU {gpu_after}, CPU {cpu_after}"
    );
    let worst_u = cpu
        .u
        .iter()
        .zip(&on_gpu.u)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f32::max);
    assert!(worst_u <= GPU_TOLERANCE, "u differs by {worst_u}");
}

/// The host structs the shaders read, checked against the WGSL's own layout (naga's reflection):
/// a field added on one side only fails here, not as garbage on a GPU.
#[test]
fn shared_structs_match_the_shader_layout() {
    use octstore::gpu::tgv::{DUAL_SHADER, PRIMAL_SHADER, Params};
    use octstore::stages::tgv::{DualConstants, Gather, PrimalConstants};
    use std::mem::{offset_of, size_of};
    use wgpu::naga;

    fn layout(source: &str, name: &str) -> (u32, Vec<(String, u32)>) {
        let module = naga::front::wgsl::parse_str(source).expect("the shader parses");
        let mut layouter = naga::proc::Layouter::default();
        layouter.update(module.to_ctx()).expect("layouts");
        for (handle, ty) in module.types.iter() {
            if ty.name.as_deref() == Some(name)
                && let naga::TypeInner::Struct { members, span } = &ty.inner
            {
                assert_eq!(layouter[handle].size, *span);
                let members = members
                    .iter()
                    .map(|m| (m.name.clone().unwrap_or_default(), m.offset))
                    .collect();
                return (*span, members);
            }
        }
        panic!("no struct {name} in the shader");
    }
    let offsets = |pairs: &[(&str, usize)]| -> Vec<(String, u32)> {
        pairs.iter().map(|(n, o)| (n.to_string(), *o as u32)).collect()
    };
    let params = offsets(&[
        ("n", offset_of!(Params, n)),
        ("lambda", offset_of!(Params, lambda)),
        ("row_stride", offset_of!(Params, row_stride)),
        ("_padding", offset_of!(Params, padding)),
    ]);
    let gather = offsets(&[
        ("index", offset_of!(Gather, index)),
        ("weight", offset_of!(Gather, weight)),
    ]);
    for source in [DUAL_SHADER, PRIMAL_SHADER] {
        assert_eq!(layout(source, "Params"), (size_of::<Params>() as u32, params.clone()));
        assert_eq!(layout(source, "Gather"), (size_of::<Gather>() as u32, gather.clone()));
    }
    assert_eq!(
        layout(DUAL_SHADER, "DualConstants"),
        (
            size_of::<DualConstants>() as u32,
            offsets(&[
                ("sigma_p", offset_of!(DualConstants, sigma_p)),
                ("sigma_q_diag", offset_of!(DualConstants, sigma_q_diag)),
                ("sigma_q_off", offset_of!(DualConstants, sigma_q_off)),
            ])
        )
    );
    assert_eq!(
        layout(PRIMAL_SHADER, "PrimalConstants"),
        (
            size_of::<PrimalConstants>() as u32,
            offsets(&[
                ("tau", offset_of!(PrimalConstants, tau)),
                ("own", offset_of!(PrimalConstants, own)),
            ])
        )
    );
    // The slopes are read as a flat array of 9 floats per cube.
    assert_eq!(size_of::<tgv::Slopes>(), 9 * size_of::<f32>());
}

/// The whole pipeline on a noisy sphere, solved with `--device gpu` and `--device cpu`: the
/// indicator fields agree within the stated tolerance at every cube, and so the meshes have
/// the same triangles with vertices within a small fraction of a cube.
#[test]
fn gpu_and_cpu_solves_give_the_same_field_and_mesh() {
    use octstore::pipeline::{SolveOptions, ingest, solve_with_gpu};
    use octstore::scenes::{Noise, SceneSpec, Shape};
    use octstore::stages::extract::{ExtractOptions, extract};
    use octstore::stages::ingest::{IngestOptions, read_scene};
    use octstore::stages::inputs::DiscoverOptions;
    use octstore::stages::octree_max_depth;
    use octstore::stages::solve::{LEVEL_STAGES, SolveParams, read_level_values};
    use octstore::store::RunOptions;

    let dir = tempfile::tempdir().unwrap();
    let center = glam::DVec3::new(0.2, -0.1, 0.3);
    let spec = SceneSpec {
        shapes: vec![Shape::Sphere { center, radius: 0.5 }],
        cameras: 12,
        distance: 2.2,
        target: center,
        width: 48,
        height: 36,
        fov_degrees: 45.0,
        noise: Some(Noise {
            relative_sigma: 0.005,
            outliers: 0.05,
            seed: 3,
        }),
        room: Some(3.0),
    };
    let manifest = spec.write(&dir.path().join("input")).unwrap();
    let run = RunOptions {
        resume: false,
        threads: 2,
        progress: false,
    };
    let mut results = Vec::new();
    let gpu = std::sync::Arc::new(open_gpu());
    for device in [DeviceChoice::Cpu, DeviceChoice::Gpu] {
        let store = octstore::Store::create(dir.path().join(format!("{device:?}"))).unwrap();
        let options = IngestOptions {
            max_depth: 7,
            ..IngestOptions::default()
        };
        ingest(
            &store,
            std::slice::from_ref(&manifest),
            &DiscoverOptions::default(),
            &options,
            &run,
        )
        .unwrap();
        let solve_options = SolveOptions {
            leaf_cubes: 3000,
            memory_budget: 256 << 20,
            params: SolveParams {
                iterations: 60,
                ..SolveParams::default()
            },
            run: run.clone(),
            device,
            ..SolveOptions::default()
        };
        let on = (device == DeviceChoice::Gpu).then(|| gpu.clone());
        solve_with_gpu(&store, &solve_options, on, |_| {}).unwrap();
        let scene = read_scene(&store).unwrap().unwrap();
        let finest = octree_max_depth(&store).unwrap();
        let snap = store.latest().unwrap();
        let mut field = Vec::new();
        for (name, _) in snap.segments(LEVEL_STAGES[usize::from(finest)]) {
            let values = read_level_values(&snap, name).unwrap();
            field.extend(values.keys.iter().copied().zip(values.u.iter().copied()));
        }
        field.sort_by_key(|(key, _)| *key);
        let mesh = extract(&snap, &scene, finest, &ExtractOptions::default()).unwrap();
        results.push((field, mesh, scene.cube_side(finest)));
    }
    let (units, fallbacks) = gpu.counts();
    assert!(
        units > 0 && fallbacks == 0,
        "{units} units on the GPU, {fallbacks} fell back"
    );
    let (cpu_field, cpu_mesh, side) = &results[0];
    let (gpu_field, gpu_mesh, _) = &results[1];
    assert_eq!(cpu_field.len(), gpu_field.len());
    let mut worst = 0f32;
    for ((key_cpu, u_cpu), (key_gpu, u_gpu)) in cpu_field.iter().zip(gpu_field) {
        assert_eq!(key_cpu, key_gpu);
        worst = worst.max((u_cpu - u_gpu).abs());
    }
    eprintln!("{} cubes: worst |u_gpu - u_cpu| = {worst:e}", cpu_field.len());
    assert!(worst <= 1e-3, "fields differ by {worst}");
    assert_eq!(cpu_mesh.triangles.len(), gpu_mesh.triangles.len());
    let shift = cpu_mesh
        .positions
        .iter()
        .zip(&gpu_mesh.positions)
        .map(|(a, b)| (glam::Vec3::from(*a) - glam::Vec3::from(*b)).length())
        .fold(0f32, f32::max);
    assert!(
        f64::from(shift) <= 0.01 * side,
        "a vertex moved by {shift} (cube side {side})"
    );
}
