//! The GPU solver against its CPU twins and the CPU kernel. The shaders run on whatever adapter
//! `--device gpu` would take. CI installs llvmpipe (Debian's mesa-vulkan-drivers) and sets
//! OCTSTORE_REQUIRE_GPU=1, so there a missing adapter fails these tests; elsewhere a test that
//! needs an adapter says on stderr that it did not run, and passes.

mod common;

use glam::Vec4;
use octstore::testing::gpu::{DeviceChoice, Gpu, twins};
use octstore::testing::kernels::tgv::{self, Kernel, Operator, Packed, Problem, State, Stopping};

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

/// The adapter `--device gpu` takes; `None` (after saying so) where there is none and
/// OCTSTORE_REQUIRE_GPU is not 1.
fn open_gpu() -> Option<Gpu> {
    match Gpu::open(DeviceChoice::Gpu) {
        Ok(Some(gpu)) => Some(gpu),
        Ok(None) => panic!("--device gpu opened nothing"),
        Err(error) if std::env::var("OCTSTORE_REQUIRE_GPU").as_deref() != Ok("1") => {
            eprintln!("NOT RUN: {error} (install mesa-vulkan-drivers, or set OCTSTORE_REQUIRE_GPU=1 to fail)");
            None
        }
        Err(error) => panic!("{error}"),
    }
}

#[test]
fn probing_for_a_gpu_prints_no_error_line() {
    // Without a Wayland session (no XDG_RUNTIME_DIR), Mesa's device-select layer made libwayland
    // print "error: XDG_RUNTIME_DIR is invalid or not set" on every adapter probe, so a normal
    // `solve` looked like a failure. The command switches the layer off.
    if open_gpu().is_none() {
        return;
    }
    let out = std::process::Command::new(common::octstore_bin())
        .args(["info", "--devices"])
        .env_remove("XDG_RUNTIME_DIR")
        .env_remove("NODEVICE_SELECT")
        .output()
        .expect("run octstore");
    let stderr = common::stderr(&out);
    assert!(out.status.success(), "{stderr}");
    assert!(
        common::stdout(&out).contains("0: "),
        "an adapter is listed: {}",
        common::stdout(&out)
    );
    assert!(
        !stderr.lines().any(|line| line.starts_with("error:")),
        "a successful run printed an error line:\n{stderr}"
    );
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
    let mut kernel = Kernel::new(&op).expect("short gather lists");
    let constants = |k: &Kernel| {
        (
            bytemuck::cast_slice::<_, u8>(&k.dual_constants).to_vec(),
            bytemuck::cast_slice::<_, u8>(&k.primal_constants).to_vec(),
            bytemuck::cast_slice::<_, u8>(&k.slopes).to_vec(),
        )
    };
    let before = constants(&kernel);
    let mut cpu = Packed::of(&state);
    kernel.iterate(&mut cpu, 40);
    // The CPU kernel works on a lane layout of its constants and puts them back.
    assert!(
        before == constants(&kernel),
        "iterate left the kernel's constants changed"
    );
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
    let Some(gpu) = open_gpu() else { return };
    for (g, seed) in [(1, 1), (7, 5), (23, 9)] {
        let (problem, state) = grid_problem(g, seed);
        let op = Operator::new(&problem);
        let kernel = Kernel::new(&op).expect("short gather lists");
        let mut twin = Packed::of(&state);
        twins::iterate(&kernel, &mut twin, 100);
        let mut on_gpu = Packed::of(&state);
        octstore::testing::gpu::tgv_dispatch::iterate(&gpu, &kernel, &mut on_gpu, 100).expect("the GPU runs the unit");
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

/// A split unit, iterated chunk by chunk with halo exchanges (on the twins), is the whole
/// kernel bit for bit, whatever the chunk size; runs on every machine, GPU or not.
#[test]
fn split_units_with_halo_exchanges_are_the_kernel_bit_for_bit() {
    use octstore::testing::gpu::tgv_dispatch::split;
    let (problem, state) = grid_problem(9, 3);
    let op = Operator::new(&problem);
    let mut kernel = Kernel::new(&op).expect("short gather lists");
    let mut whole = Packed::of(&state);
    kernel.iterate(&mut whole, 30);
    for cubes in [1, 7, 100, 364, 729, 1000] {
        let chunks = split(&kernel, cubes);
        assert_eq!(chunks.len(), kernel.n.div_ceil(cubes));
        if chunks.len() > 1 {
            assert!(chunks.iter().any(|c| !c.bar_halo.is_empty() && !c.row_halo.is_empty()));
        }
        let mut chunked = Packed::of(&state);
        twins::iterate_chunks(&chunks, &mut chunked, 30);
        assert_eq!(whole, chunked, "chunks of {cubes} cubes");
    }
}

#[test]
fn a_unit_over_one_binding_runs_in_chunks_with_the_same_result() {
    let Some(gpu) = open_gpu() else { return };
    let (problem, state) = grid_problem(8, 7);
    let kernel = Kernel::new(&Operator::new(&problem)).expect("short gather lists");
    let mut whole = Packed::of(&state);
    octstore::testing::gpu::tgv_dispatch::iterate(&gpu, &kernel, &mut whole, 30).expect("the GPU runs the unit");
    // Bindings of 1 KiB: most buffers of the 512-cube unit are larger (dual constants alone are
    // 48 bytes a cube), so it runs in chunks of a few cubes, with halos between them.
    let gpu = gpu.with_binding_limit(1024);
    let mut chunked = Packed::of(&state);
    octstore::testing::gpu::tgv_dispatch::iterate(&gpu, &kernel, &mut chunked, 30).expect("the chunks fit");
    assert_eq!(whole, chunked, "the same shaders on the same values");
    let mut solved = state.clone();
    octstore::testing::gpu::solve_on(Some(&gpu), &problem, &mut solved, Stopping::after(30));
    assert_eq!(gpu.counts(), (1, 0), "the unit ran on the GPU");
}

#[test]
fn a_unit_over_the_gpu_limits_runs_on_the_cpu_with_the_same_result() {
    let (problem, state) = grid_problem(8, 7);
    let mut cpu = state.clone();
    let cpu_energy = tgv::solve(&problem, &mut cpu, 30);
    // Bindings of 32 bytes: not even one cube's dual constants (48 bytes) fit.
    let Some(gpu) = open_gpu() else { return };
    let gpu = gpu.with_binding_limit(32);
    let mut fallback_state = state.clone();
    let fallback = octstore::testing::gpu::solve_on(Some(&gpu), &problem, &mut fallback_state, Stopping::after(30));
    let fallback_energy = (fallback.energy_before, fallback.energy_after);
    assert_eq!(cpu, fallback_state);
    assert_eq!(cpu_energy, fallback_energy);
    assert_eq!(gpu.counts(), (0, 1), "the unit fell back");
    let too_large = octstore::testing::gpu::tgv_dispatch::iterate(
        &gpu,
        &Kernel::new(&Operator::new(&problem)).expect("short gather lists"),
        &mut Packed::of(&state),
        1,
    );
    assert!(
        matches!(too_large, Err(octstore::testing::gpu::GpuError::TooLarge { .. })),
        "{too_large:?}"
    );
}

#[test]
fn solve_on_the_gpu_lowers_the_energy_like_the_cpu() {
    let Some(gpu) = open_gpu() else { return };
    let (problem, state) = grid_problem(12, 11);
    let mut cpu = state.clone();
    let (cpu_before, cpu_after) = tgv::solve(&problem, &mut cpu, 60);
    let mut on_gpu = state.clone();
    let solved = octstore::testing::gpu::solve_on(Some(&gpu), &problem, &mut on_gpu, Stopping::after(60));
    let (gpu_before, gpu_after) = (solved.energy_before, solved.energy_after);
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
    use octstore::testing::gpu::tgv_dispatch::{DUAL_SHADER, PRIMAL_SHADER, Params};
    use octstore::testing::kernels::tgv::{DualConstants, Gather, PrimalConstants};
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
    {
        use octstore::testing::gpu::tgv_dispatch::{HALO_SHADER, HaloParams};
        assert_eq!(
            layout(HALO_SHADER, "HaloParams"),
            (
                size_of::<HaloParams>() as u32,
                offsets(&[
                    ("count", offset_of!(HaloParams, count)),
                    ("offset", offset_of!(HaloParams, offset)),
                    ("row_stride", offset_of!(HaloParams, row_stride)),
                    ("_padding", offset_of!(HaloParams, padding)),
                ])
            )
        );
    }
    // The slopes are read as a flat array of 9 floats per cube.
    assert_eq!(size_of::<tgv::Slopes>(), 9 * size_of::<f32>());
}

/// The whole pipeline on a noisy sphere, solved with `--device gpu` (votes and iterations on
/// the GPU) and `--device cpu`: at most 1 % of cubes move by more than 1e-3 and 0.1 % change
/// sign, and the meshes lie within half a cube of each other (F-score 0.99).
#[test]
fn gpu_and_cpu_solves_give_the_same_field_and_mesh() {
    use octstore::pipeline::SolveOptions;
    use octstore::testing::quality::synthetic_scenes::{Noise, SceneSpec, Shape};
    use octstore::testing::solve_with_gpu;
    use octstore::testing::stages::extract::{ExtractOptions, Simplify, extract};
    // Every triangle: the test compares solutions through their surfaces.
    let full_mesh = || ExtractOptions {
        simplify: Simplify::Full,
        ..ExtractOptions::default()
    };
    use octstore::testing::stages::ingest::read_scene;
    use octstore::testing::stages::octree_max_depth;
    use octstore::testing::stages::solve::{LEVEL_STAGES, SolveParams, read_level_u};

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
    let run = two_threads();
    let mut results = Vec::new();
    let Some(gpu) = open_gpu() else { return };
    let gpu = std::sync::Arc::new(gpu);
    for device in [DeviceChoice::Cpu, DeviceChoice::Gpu] {
        let store = ingested(dir.path().join(format!("{device:?}")), &manifest, 7);
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
            let (keys, values) = read_level_u(&snap, name).unwrap();
            field.extend(keys.iter().copied().zip(values.iter().map(|value| value.u)));
        }
        field.sort_by_key(|(key, _)| *key);
        let mesh = extract(&snap, &scene, finest, &full_mesh()).unwrap();
        results.push((field, mesh, scene.cube_side(finest)));
    }
    let (units, fallbacks) = gpu.counts();
    assert!(
        units > 0 && fallbacks == 0,
        "{units} units on the GPU, {fallbacks} fell back"
    );
    let (cpu_field, cpu_mesh, side) = &results[0];
    let (gpu_field, gpu_mesh, _) = &results[1];
    // The votes are cast in f32 on the GPU (f64 on the CPU), so a cube whose value sits on a
    // bin or pixel boundary may vote differently; the solve then moves u a little nearby.
    assert_eq!(cpu_field.len(), gpu_field.len());
    let (mut moved, mut flipped, mut worst) = (0usize, 0usize, 0f32);
    for ((key_cpu, u_cpu), (key_gpu, u_gpu)) in cpu_field.iter().zip(gpu_field) {
        assert_eq!(key_cpu, key_gpu);
        let du = (u_cpu - u_gpu).abs();
        worst = worst.max(du);
        moved += usize::from(du > 1e-3);
        flipped += usize::from((*u_cpu < 0.0) != (*u_gpu < 0.0));
    }
    let n = cpu_field.len();
    eprintln!("{n} cubes: {moved} move by more than 1e-3, {flipped} change sign, worst |du| {worst:e}");
    assert!(moved * 100 <= n, "{moved} of {n} cubes moved by more than 1e-3");
    assert!(flipped * 1000 <= n, "{flipped} of {n} cubes changed sign");
    let options = octstore::testing::quality::evaluate::EvaluateOptions {
        tau: 0.5 * side,
        spacing: Some(0.5 * side),
        crop_margin: None,
        seen_faces: None,
        seed: 1,
    };
    let report = octstore::testing::quality::evaluate::evaluate(gpu_mesh, cpu_mesh, &options).unwrap();
    eprintln!(
        "GPU mesh against the CPU mesh: F {:.4} at half a cube, Chamfer {:.2e} (cube side {side:.2e})",
        report.f_score, report.chamfer
    );
    assert!(report.f_score >= 0.99 && report.chamfer <= 0.05 * side, "{report:?}");
}

/// A depth map seen from far off the origin (pinhole or 360-degree), with holes, and cubes of
/// many sizes around its surface and outside its view; with the unit origin near the cubes.
struct VoteCase {
    pyramid: octstore::testing::kernels::votes::Pyramid,
    world_to_camera: glam::DMat4,
    centers: Vec<glam::DVec3>,
    radii: Vec<f64>,
    origin: glam::DVec3,
    /// The distance band's floor: above 2 delta for the smaller half of the radii.
    band_floor: f64,
}

fn vote_case(spherical: bool, seed: u64) -> VoteCase {
    use glam::{DMat4, DVec3};
    use octstore::inputs::{DepthImage, DepthMapSource, ImageFormat, Kind, Projection};
    let mut seed = seed;
    let mut uniform = move || {
        seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (seed >> 11) as f64 / (1u64 << 53) as f64
    };
    let (width, height) = if spherical { (160u32, 80u32) } else { (97, 61) };
    let projection = if spherical {
        Projection::Spherical
    } else {
        Projection::Pinhole {
            fx: 80.0,
            fy: 70.0,
            cx: 48.0,
            cy: 30.5,
        }
    };
    let camera_to_world = DMat4::from_translation(DVec3::new(1000.0, -2000.0, 500.0))
        * DMat4::from_rotation_y(0.4)
        * DMat4::from_rotation_x(-0.3);
    let source = DepthMapSource {
        path: "case.pfm".into(),
        format: ImageFormat::Pfm,
        width,
        height,
        projection,
        camera_to_world: camera_to_world.to_cols_array(),
        kind: if spherical { Kind::Lidar } else { Kind::Photo },
        weight: 1.0,
        noise: octstore::inputs::DepthNoise::Footprint,
    };
    let depth_at = |i: u32, j: u32| 3.0 + 0.02 * f64::from(i) + 0.5 * (f64::from(j) * 0.1).sin();
    let mut depth = Vec::new();
    for j in 0..height {
        for i in 0..width {
            depth.push(if uniform() < 0.05 {
                f32::NAN
            } else {
                depth_at(i, j) as f32
            });
        }
    }
    // The camera-space direction through pixel (u, v), unit length.
    let ray = |u: f64, v: f64| -> DVec3 {
        match projection {
            Projection::Pinhole { fx, fy, cx, cy } => DVec3::new((u - cx) / fx, (v - cy) / fy, 1.0).normalize(),
            Projection::Spherical => {
                let azimuth = u / f64::from(width) * std::f64::consts::TAU;
                let elevation = std::f64::consts::FRAC_PI_2 - (v + 0.5) / f64::from(height) * std::f64::consts::PI;
                DVec3::new(
                    elevation.cos() * azimuth.cos(),
                    elevation.cos() * azimuth.sin(),
                    elevation.sin(),
                )
            }
        }
    };
    let mut centers = Vec::new();
    let mut radii = Vec::new();
    for _ in 0..20_000 {
        let (u, v) = (
            uniform() * f64::from(width + 20) - 10.0,
            uniform() * f64::from(height + 20) - 10.0,
        );
        let surface = depth_at(
            u.clamp(0.0, f64::from(width - 1)) as u32,
            v.clamp(0.0, f64::from(height - 1)) as u32,
        );
        let direction = ray(u, v);
        // Along the ray to the surface's depth (z for a pinhole, range for a 360-degree map).
        let scale = if spherical { 1.0 } else { 1.0 / direction.z };
        let distance = surface + (uniform() - 0.5) * 0.6;
        centers.push(camera_to_world.transform_point3(direction * distance * scale));
        radii.push(0.001 * 300f64.powf(uniform()));
    }
    let origin = centers.iter().copied().sum::<DVec3>() / centers.len() as f64 + DVec3::splat(0.37);
    VoteCase {
        pyramid: octstore::testing::kernels::votes::Pyramid::new(source, DepthImage { width, height, depth }),
        world_to_camera: camera_to_world.inverse(),
        centers,
        radii,
        origin,
        band_floor: 0.2,
    }
}

/// The bin each cube's row received (each row gets at most one vote per map).
fn voted_bins(hist: &[f32]) -> Vec<Option<usize>> {
    hist.chunks(8).map(|row| row.iter().position(|h| *h != 0.0)).collect()
}

/// The twin's histogram rows and distance sums.
fn twin_votes(case: &VoteCase) -> (Vec<f32>, Vec<f32>) {
    use octstore::testing::gpu::votes_dispatch::{cube_offsets, pyramid_arrays, vote_map};
    let n = case.centers.len();
    let (levels, depths) = pyramid_arrays(&case.pyramid);
    let map = octstore::testing::gpu::votes_dispatch::VoteMap {
        levels: levels.len() as u32,
        ..vote_map(
            &case.pyramid.source,
            &case.world_to_camera,
            case.origin,
            1.0,
            n as u32,
            case.band_floor,
        )
    };
    let cubes = cube_offsets(case.origin, &case.centers, &case.radii);
    let mut hist = vec![0f32; 8 * n];
    let mut votes = vec![0u32; n];
    let mut distance = vec![0f32; 2 * n];
    for c in 0..n {
        twins::votes(c, &map, &cubes, &levels, &depths, &mut hist, &mut votes, &mut distance);
    }
    (hist, distance)
}

/// The votes twin (f32, unit-relative) against the CPU reference (f64, world coordinates):
/// they may differ only where a value sits on a bin, level or pixel boundary.
#[test]
fn votes_twin_matches_the_cpu_reference() {
    for spherical in [false, true] {
        let case = vote_case(spherical, 17);
        let with_distance: Vec<Option<(usize, Option<f64>)>> = case
            .centers
            .iter()
            .zip(&case.radii)
            .map(|(c, r)| {
                case.pyramid
                    .vote_with_distance(&case.world_to_camera, *c, *r, case.band_floor)
            })
            .collect();
        let reference: Vec<Option<usize>> = with_distance.iter().map(|v| v.map(|(bin, _)| bin)).collect();
        let (twin_hist, twin_distance) = twin_votes(&case);
        let twin = voted_bins(&twin_hist);
        let differ = reference.iter().zip(&twin).filter(|(a, b)| a != b).count();
        // Where both voted into the same measuring bin, they added the same truncated distance to
        // f32 precision of unit-relative coordinates (1e-3 of the voting distance delta), unless
        // they read neighbouring pixels whose depths fall into one bin: as rare as bins that
        // differ.
        let mut compared = 0;
        let mut distances_differ = 0;
        for (((reference, twin), sums), radius) in with_distance
            .iter()
            .zip(&twin)
            .zip(twin_distance.chunks(2))
            .zip(&case.radii)
        {
            if let (Some((bin, Some(d))), Some(twin_bin), [sum, weight]) = (reference, twin, sums)
                && bin == twin_bin
                && octstore::testing::kernels::votes::measures(*bin)
            {
                assert_eq!(*weight, 1.0);
                compared += 1;
                distances_differ += usize::from((f64::from(*sum) - d).abs() > 1e-3 * 6.0 * radius);
            }
        }
        assert!(
            distances_differ * 1000 <= reference.len(),
            "{distances_differ} of {compared} distances differ"
        );
        assert!(compared > 1000, "{compared} measured distances compared");
        let voted = reference.iter().filter(|b| b.is_some()).count();
        let bins: std::collections::BTreeSet<usize> = reference.iter().flatten().copied().collect();
        eprintln!(
            "spherical {spherical}: {voted} of {} cubes vote, {differ} differ",
            reference.len()
        );
        assert!(
            voted > 5_000 && bins.len() == 8,
            "the case exercises every bin: {bins:?}"
        );
        assert!(
            differ * 1000 <= reference.len(),
            "{differ} of {} cubes differ",
            reference.len()
        );
    }
}

/// `shaders/votes.wgsl` against its twin, on the adapter `--device gpu` takes.
#[test]
fn votes_shader_matches_the_twin() {
    let Some(gpu) = open_gpu() else { return };
    for spherical in [false, true] {
        let case = vote_case(spherical, 23);
        let (twin, twin_distance) = twin_votes(&case);
        let n = case.centers.len();
        let previous: Vec<f32> = (0..8 * n).map(|i| (i % 3) as f32 * 0.5).collect();
        let previous_distance: Vec<f32> = (0..2 * n).map(|i| (i % 5) as f32 * 0.25).collect();
        let unit = gpu
            .upload_unit(
                case.origin,
                &octstore::testing::gpu::votes_dispatch::cube_offsets(case.origin, &case.centers, &case.radii),
                &previous,
                &previous_distance,
                case.band_floor,
            )
            .expect("upload");
        let map = gpu.upload_pyramid(&case.pyramid).expect("upload");
        gpu.vote(&unit, &map, &case.pyramid.source, &case.world_to_camera, 1.0)
            .expect("vote");
        let voted = gpu.finish_unit(&unit).expect("read back");
        let votes = voted.votes;
        let on_gpu: Vec<f32> = voted.hist.iter().zip(&previous).map(|(h, p)| h - p).collect();
        // Where the shader and the twin chose the same bin, the distance sums agree to f32
        // arithmetic (1e-3 of delta; the previous sums add exactly representable values),
        // unless they read neighbouring pixels whose depths fall into one bin. The distance
        // interpolates between pixels, so an error in the projected position moves it by the
        // depth's slope: WGSL's atan2 and asin may be off by 4096 ulp, which llvmpipe uses,
        // and put a 360-degree map's points up to about 0.01 pixel off (the case's depths
        // change by at most 0.05 from one pixel to the next).
        let position_slack = if spherical { 0.02 * 0.05 } else { 0.0 };
        let same_bin = voted_bins(&twin)
            .into_iter()
            .zip(voted_bins(&on_gpu))
            .map(|(a, b)| a == b);
        let mut distances_differ = 0;
        for (c, same) in same_bin.enumerate() {
            let tolerance = 1e-3 * 6.0 * case.radii[c] as f32 + position_slack;
            let differs = (2 * c..2 * c + 2).any(|k| {
                let (gpu_sum, twin_sum, before) = (voted.distance[k], twin_distance[k], previous_distance[k]);
                ((gpu_sum - before) - twin_sum).abs() > tolerance
            });
            distances_differ += usize::from(same && differs);
        }
        let expected_votes = twin.iter().filter(|h| **h != 0.0).count() as u64;
        let differ = voted_bins(&twin)
            .iter()
            .zip(voted_bins(&on_gpu))
            .filter(|(a, b)| **a != *b)
            .count();
        eprintln!("spherical {spherical}: {differ} of {n} cubes differ, {votes} votes (twin {expected_votes})");
        // WGSL lets atan2 and asin be far less exact than Rust's (llvmpipe moves 0.08 % of a
        // 360-degree map's cubes across a pixel or bin boundary); the pinhole path has no
        // transcendental function.
        let allowed = if spherical { n / 500 } else { n / 10_000 };
        assert!(differ <= allowed, "{differ} of {n} cubes differ");
        assert!(
            distances_differ <= allowed,
            "{distances_differ} of {n} distance sums differ"
        );
        assert!(votes.abs_diff(expected_votes) as usize <= allowed);
    }
}

#[test]
fn vote_map_matches_the_shader_layout() {
    use octstore::testing::gpu::votes_dispatch::{VOTES_SHADER, VoteMap};
    use std::mem::{offset_of, size_of};
    use wgpu::naga;
    let module = naga::front::wgsl::parse_str(VOTES_SHADER).expect("the shader parses");
    let (members, span) = module
        .types
        .iter()
        .find_map(|(_, ty)| match (&ty.name, &ty.inner) {
            (Some(name), naga::TypeInner::Struct { members, span }) if name == "VoteMap" => {
                Some((members.clone(), *span))
            }
            _ => None,
        })
        .expect("VoteMap in the shader");
    assert_eq!(span as usize, size_of::<VoteMap>());
    let offsets: Vec<(String, usize)> = members
        .iter()
        .map(|m| (m.name.clone().unwrap_or_default(), m.offset as usize))
        .collect();
    let expected = [
        ("unit_to_camera", offset_of!(VoteMap, unit_to_camera)),
        ("intrinsics", offset_of!(VoteMap, intrinsics)),
        ("width", offset_of!(VoteMap, width)),
        ("height", offset_of!(VoteMap, height)),
        ("levels", offset_of!(VoteMap, levels)),
        ("spherical", offset_of!(VoteMap, spherical)),
        ("weight", offset_of!(VoteMap, weight)),
        ("n", offset_of!(VoteMap, n)),
        ("row_stride", offset_of!(VoteMap, row_stride)),
        ("band_per_delta", offset_of!(VoteMap, band_per_delta)),
        ("band_floor", offset_of!(VoteMap, band_floor)),
        ("padding0", offset_of!(VoteMap, padding)),
        ("padding1", offset_of!(VoteMap, padding) + 4),
        ("padding2", offset_of!(VoteMap, padding) + 8),
    ];
    let expected: Vec<(String, usize)> = expected.iter().map(|(n, o)| (n.to_string(), *o)).collect();
    assert_eq!(offsets, expected);
}

/// Histograms voted on the GPU with bindings too small for a unit (8 KiB: room for a 40 x 30
/// pyramid, and for batches of 256 cubes' rows) are the histograms voted with whole units, bit for bit: batches share their unit's
/// origin, so each cube computes the same f32 values.
#[test]
fn votes_in_batches_that_fit_a_binding_are_the_whole_units_votes() {
    use octstore::pipeline::{SolveOptions, SolveUntil};
    use octstore::testing::solve_with_gpu;

    let Some(gpu) = open_gpu() else { return };
    let dir = tempfile::tempdir().unwrap();
    let manifest = small_sphere(glam::DVec3::new(0.1, 0.0, -0.2), None)
        .write(&dir.path().join("input"))
        .unwrap();
    let run = two_threads();
    let full = std::sync::Arc::new(gpu);
    let batched = std::sync::Arc::new(
        Gpu::open(DeviceChoice::Gpu)
            .unwrap()
            .expect("a second device on the same adapter")
            .with_binding_limit(8 << 10),
    );
    let mut digests = Vec::new();
    for (name, gpu) in [("full", &full), ("batched", &batched)] {
        let store = ingested(dir.path().join(name), &manifest, 6);
        let solve_options = SolveOptions {
            until: SolveUntil::Histograms,
            leaf_cubes: 3000,
            memory_budget: 256 << 20,
            run: run.clone(),
            device: DeviceChoice::Gpu,
            ..SolveOptions::default()
        };
        solve_with_gpu(&store, &solve_options, Some(gpu.clone()), |_| {}).unwrap();
        digests.push(store.latest().unwrap().digest(octstore::testing::stages::HISTOGRAMS));
    }
    for gpu in [&full, &batched] {
        let (units, fallbacks) = gpu.counts();
        assert!(units > 0 && fallbacks == 0, "{units} on the GPU, {fallbacks} fell back");
    }
    assert_eq!(digests[0], digests[1]);
}

/// Cluster workers with `--device gpu` (`octstore work`) give the store a single `solve
/// --device gpu` gives, byte for byte: the same shaders on the same units.
#[test]
fn cluster_workers_on_the_gpu_equal_a_single_gpu_solve() {
    use common::{assert_same_store, fingerprint, octstore, stderr};

    if open_gpu().is_none() {
        return;
    }
    let run = |args: &[&str]| {
        let out = octstore(args, &[]);
        assert!(out.status.success(), "{args:?}: {}", stderr(&out));
    };
    let dir = tempfile::tempdir().unwrap();
    let manifest = small_sphere(glam::DVec3::new(0.2, -0.1, 0.3), Some(2.6))
        .write(&dir.path().join("input"))
        .unwrap();
    let (cluster, single) = (dir.path().join("cluster"), dir.path().join("single"));
    let (c, s) = (cluster.to_str().unwrap(), single.to_str().unwrap());
    for store in [c, s] {
        run(&[
            "ingest",
            store,
            manifest.to_str().unwrap(),
            "--max-depth",
            "5",
            "--quiet",
        ]);
        run(&["solve", store, "--until", "octree", "--leaf-cubes", "300", "--quiet"]);
    }
    run(&[
        "solve",
        s,
        "--iterations",
        "20",
        "--leaf-cubes",
        "300",
        "--device",
        "gpu",
        "--quiet",
    ]);
    let mut stages = vec!["histograms".to_string()];
    stages.extend((0..=5).map(|l| format!("solution-{l:02}")));
    for stage in &stages {
        run(&["plan", c, "--stage", stage, "--chunks", "2", "--iterations", "20"]);
        let mut lines = String::new();
        for chunk in ["0", "1"] {
            let out = octstore(&["work", c, "--stage", stage, "--chunk", chunk, "--device", "gpu"], &[]);
            assert!(out.status.success(), "{stage} chunk {chunk}: {}", stderr(&out));
            lines += &common::stdout(&out);
        }
        // Each line: "N unit(s) (M on ADAPTER, F fell back to the CPU)".
        let on_gpu = lines.lines().any(|l| l.contains(" on ") && !l.contains("(0 on "));
        assert!(
            on_gpu && lines.matches(" 0 fell back").count() == 2,
            "{stage} ran on the GPU:\n{lines}"
        );
        run(&["commit", c, "--stage", stage, "--quiet"]);
    }
    assert_same_store(
        &fingerprint(&single),
        &fingerprint(&cluster),
        "GPU workers vs a single GPU solve",
    );
}

/// A device lost between stages (destroyed after the histograms, as a driver reset would):
/// every later unit falls back to the CPU with a warning, and the run completes with the store
/// of a run whose later stages ran on the CPU, byte for byte.
#[test]
fn a_lost_device_sends_the_rest_of_the_run_to_the_cpu() {
    use common::{assert_same_store, fingerprint};
    use octstore::pipeline::{SolveOptions, SolveUntil, solve};
    use octstore::testing::solve_with_gpu;

    let Some(healthy) = open_gpu() else { return };
    let healthy = std::sync::Arc::new(healthy);
    let lost = std::sync::Arc::new(Gpu::open(DeviceChoice::Gpu).unwrap().expect("a second device"));
    let dir = tempfile::tempdir().unwrap();
    let manifest = small_sphere(glam::DVec3::new(-0.1, 0.2, 0.0), Some(2.6))
        .write(&dir.path().join("input"))
        .unwrap();
    let run = two_threads();
    let options = SolveOptions {
        leaf_cubes: 300,
        memory_budget: 256 << 20,
        params: octstore::testing::stages::solve::SolveParams {
            iterations: 20,
            ..Default::default()
        },
        run: run.clone(),
        device: DeviceChoice::Gpu,
        ..SolveOptions::default()
    };
    let mut stores = Vec::new();
    for name in ["reference", "lost"] {
        let path = dir.path().join(name);
        let store = ingested(&path, &manifest, 5);
        if name == "reference" {
            let histograms = SolveOptions {
                until: SolveUntil::Histograms,
                ..options.clone()
            };
            solve_with_gpu(&store, &histograms, Some(healthy.clone()), |_| {}).unwrap();
            let on_cpu = SolveOptions {
                device: DeviceChoice::Cpu,
                ..options.clone()
            };
            solve(&store, &on_cpu, |_| {}).unwrap();
        } else {
            solve_with_gpu(&store, &options, Some(lost.clone()), |report| {
                if report.stage == octstore::testing::stages::HISTOGRAMS {
                    lost.destroy();
                }
            })
            .unwrap();
        }
        drop(store);
        stores.push(path);
    }
    let (units, fallbacks) = lost.counts();
    assert!(lost.is_lost(), "the device reports its loss");
    assert!(
        units > 0 && fallbacks > 0,
        "{units} units on the GPU, {fallbacks} fell back"
    );
    assert_same_store(
        &fingerprint(&stores[0]),
        &fingerprint(&stores[1]),
        "lost device vs CPU levels",
    );
}

/// A sphere of radius 0.5 seen by 6 views of 40 x 30, in a room of half-side `room` if given:
/// small enough for a whole pipeline in a few seconds on llvmpipe.
fn small_sphere(center: glam::DVec3, room: Option<f64>) -> octstore::SceneSpec {
    octstore::SceneSpec {
        shapes: vec![octstore::testing::quality::synthetic_scenes::Shape::Sphere { center, radius: 0.5 }],
        cameras: 6,
        distance: 2.0,
        target: center,
        width: 40,
        height: 30,
        fov_degrees: 50.0,
        noise: None,
        room,
    }
}

fn two_threads() -> octstore::store::RunOptions {
    octstore::store::RunOptions {
        resume: false,
        threads: 2,
        progress: false,
    }
}

/// A new store at `path` with `manifest` ingested at `max_depth`, on two threads.
fn ingested(path: impl AsRef<std::path::Path>, manifest: &std::path::Path, max_depth: u8) -> octstore::Store {
    use octstore::IngestOptions;
    let store = octstore::Store::create(path).unwrap();
    let options = IngestOptions {
        max_depth,
        ..IngestOptions::default()
    };
    octstore::pipeline::ingest(
        &store,
        std::slice::from_ref(&manifest.to_path_buf()),
        &octstore::DiscoverOptions::default(),
        &options,
        &two_threads(),
    )
    .unwrap();
    store
}
