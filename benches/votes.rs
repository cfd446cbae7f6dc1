//! Histogram votes per second (Algorithm 1): cubes tested against one depth map's pyramid, on
//! the CPU (the histogram stage's `Pyramid::vote`, on every thread) and then on every GPU
//! adapter wgpu finds (`shaders/votes.wgsl`; software adapters are marked as such).
//! `cargo bench --bench votes`; OCTSTORE_BENCH_CUBES sets the cube count (default 1 million),
//! OCTSTORE_BENCH_MAPS how many times the map is voted (default 20), OCTSTORE_BENCH_BATCH how
//! many maps the batched loop votes at once (default 9, as RedKitchen's stage at 512 MiB). A
//! GPU figure counts the votes only: the time of one pass with its uploads and read-back is
//! subtracted.

mod common;

use common::setting;
use std::time::Instant;

use glam::{DMat4, DVec3};
use octstore::inputs::{DepthImage, DepthMapSource, ImageFormat, Kind, Projection};
use octstore::testing::gpu::{Gpu, adapters};
use octstore::testing::kernels::votes::Pyramid;
use rayon::prelude::*;

fn main() {
    let cubes: usize = setting("OCTSTORE_BENCH_CUBES", 1_000_000);
    let maps: usize = setting("OCTSTORE_BENCH_MAPS", 20).max(2);
    // A 640 x 480 view of a wavy wall 3 to 4 m away, and cubes scattered around the wall at
    // the sizes of 1 to 8 pixel footprints, some in front, some behind, some outside the view.
    let (width, height) = (640u32, 480u32);
    let (fx, fy, cx, cy) = (525.0, 525.0, 319.5, 239.5);
    let depth_at = |i: f64, j: f64| 3.0 + 0.5 * (i * 0.02).sin() * (j * 0.03).cos();
    let depth = (0..height)
        .flat_map(|j| (0..width).map(move |i| depth_at(f64::from(i), f64::from(j)) as f32))
        .collect();
    let camera_to_world = DMat4::from_translation(DVec3::new(12.0, -3.0, 1.5)) * DMat4::from_rotation_y(0.3);
    let source = DepthMapSource {
        path: "bench.pfm".into(),
        format: ImageFormat::Pfm,
        width,
        height,
        projection: Projection::Pinhole { fx, fy, cx, cy },
        camera_to_world: camera_to_world.to_cols_array(),
        kind: Kind::Photo,
        weight: 1.0,
        noise: octstore::inputs::DepthNoise::Footprint,
    };
    let pyramid = Pyramid::new(source.clone(), DepthImage { width, height, depth });
    let world_to_camera = camera_to_world.inverse();
    let mut seed = 7u64;
    let mut uniform = move || octstore::testing::kernels::random::uniform(&mut seed);
    let (mut centers, mut radii) = (Vec::with_capacity(cubes), Vec::with_capacity(cubes));
    for _ in 0..cubes {
        let (u, v) = (
            uniform() * f64::from(width + 64) - 32.0,
            uniform() * f64::from(height + 64) - 32.0,
        );
        let z = depth_at(u, v) + (uniform() - 0.5) * 0.2;
        let camera = DVec3::new((u - cx) / fx * z, (v - cy) / fy * z, z);
        centers.push(camera_to_world.transform_point3(camera));
        radii.push(z / fx * 0.5 * 8f64.powf(uniform()));
    }
    let started = Instant::now();
    let mut voted = 0usize;
    for _ in 0..maps {
        voted = centers
            .par_iter()
            .zip(&radii)
            .filter(|(c, r)| pyramid.vote(&world_to_camera, **c, **r).is_some())
            .count();
    }
    let seconds = started.elapsed().as_secs_f64();
    println!(
        "votes, f64 reference (Pyramid::vote): {cubes} cubes x {maps} maps in {seconds:.2}s on {} threads: {:.2} million cube-map tests/s ({:.0} % of the cubes vote)",
        rayon::current_num_threads(),
        (cubes * maps) as f64 / seconds / 1e6,
        100.0 * voted as f64 / cubes as f64
    );
    let origin = centers.iter().copied().sum::<DVec3>() / cubes as f64;
    // The histogram stage's loop: f32 offsets from the unit's origin, 4 cubes as lanes, runs
    // of consecutive cubes in parallel. Its cubes are Morton-ordered, so neighbours in a run
    // read nearby pixels: here the cubes are ordered by 8 x 8 pixel tiles to match.
    let mut order: Vec<usize> = (0..cubes).collect();
    let tile = |c: DVec3| {
        let p = world_to_camera.transform_point3(c);
        let (u, v) = (fx * p.x / p.z + cx, fy * p.y / p.z + cy);
        ((v / 8.0).floor() as i64, (u / 8.0).floor() as i64)
    };
    order.sort_by_key(|&i| tile(centers[i]));
    let (tiled_centers, tiled_radii): (Vec<DVec3>, Vec<f64>) = order.iter().map(|&i| (centers[i], radii[i])).unzip();
    let runs = octstore::testing::kernels::votes::chunks(&tiled_centers, &tiled_radii);
    let mut offsets = octstore::testing::kernels::votes::cube_offsets(origin, &tiled_centers, &tiled_radii);
    let (mut hist, mut distance) = (vec![0f32; 8 * cubes], vec![0f32; 2 * cubes]);
    // The loops read and write whole blocks of cubes in lane layout, as the stage holds them.
    octstore::testing::kernels::votes::relayout_for_lanes(&mut offsets, &mut hist, &mut distance, true);
    let chunked = octstore::testing::kernels::votes::ChunkedCubes {
        offsets: &offsets,
        chunks: &runs,
    };
    let view = octstore::testing::kernels::votes::UnitView::new(&source, &world_to_camera, origin, 0.0);
    let seen: Vec<usize> = (0..runs.len()).collect();
    let started = Instant::now();
    let mut cast = 0u64;
    for _ in 0..maps {
        cast = octstore::testing::kernels::votes::vote_chunks(
            &chunked,
            &mut hist,
            &mut distance,
            &pyramid,
            &view,
            1.0,
            &seen,
        );
    }
    let seconds = started.elapsed().as_secs_f64();
    println!(
        "votes, the stage's loop (vote_chunks, f32 lanes): {cubes} cubes x {maps} maps in {seconds:.2}s on {} threads: {:.2} million cube-map tests/s, {:.2} million votes/s ({:.0} % of the cubes vote)",
        rayon::current_num_threads(),
        (cubes * maps) as f64 / seconds / 1e6,
        (cast as usize * maps) as f64 / seconds / 1e6,
        100.0 * cast as f64 / cubes as f64
    );
    // The same maps voted as the stage votes them: a batch of maps at a time, each chunk of
    // cubes meeting every map of the batch while its rows are in cache (`vote_maps`).
    let per_batch: usize = setting("OCTSTORE_BENCH_BATCH", 9).clamp(1, octstore::testing::kernels::votes::MAPS_AT_ONCE);
    let batch: Vec<octstore::testing::kernels::votes::MapVote<'_>> = (0..per_batch)
        .map(|_| octstore::testing::kernels::votes::MapVote::new(&pyramid, view, 1.0, &seen))
        .collect();
    let started = Instant::now();
    let (mut batched, mut voted_maps) = (0u64, 0usize);
    while voted_maps < maps {
        let take = per_batch.min(maps - voted_maps);
        batched += octstore::testing::kernels::votes::vote_maps(&chunked, &mut hist, &mut distance, &batch[..take]);
        voted_maps += take;
    }
    let seconds = started.elapsed().as_secs_f64();
    println!(
        "votes, the stage's loop in batches of {per_batch} maps (vote_maps): {cubes} cubes x {maps} maps in {seconds:.2}s on {} threads: {:.2} million cube-map tests/s, {:.2} million votes/s",
        rayon::current_num_threads(),
        (cubes * maps) as f64 / seconds / 1e6,
        batched as f64 / seconds / 1e6,
    );
    let found = adapters();
    if found.is_empty() {
        println!("votes: no GPU adapter found (WGPU_BACKEND chooses backends)");
    }
    for (index, adapter) in found.iter().enumerate() {
        let kind = if adapter.software { "software" } else { "hardware" };
        let gpu = match Gpu::open_adapter(index) {
            Ok(gpu) => gpu,
            Err(error) => {
                println!("votes on {} ({kind}): {error}", adapter.name);
                continue;
            }
        };
        let time = |passes: usize| -> Result<(f64, u64), octstore::testing::gpu::GpuError> {
            let started = Instant::now();
            let hist = vec![0f32; cubes * 8];
            let distance = vec![0f32; 2 * cubes];
            // The band floor of a scene whose finest cubes match the largest voting radius.
            let band_floor = octstore::testing::kernels::votes::DISTANCE_BAND_FLOOR_SIDES
                * 2.0
                * radii.iter().copied().fold(0.0, f64::max);
            let unit = gpu.upload_unit(
                origin,
                &octstore::testing::kernels::votes::cube_offsets(origin, &centers, &radii),
                &hist,
                &distance,
                band_floor,
            )?;
            let map = gpu.upload_pyramid(&pyramid)?;
            for _ in 0..passes {
                gpu.vote(&unit, &map, &source, &world_to_camera, 1.0)?;
            }
            let votes = gpu.finish_unit(&unit)?.votes;
            Ok((started.elapsed().as_secs_f64(), votes))
        };
        match (time(1), time(maps)) {
            (Ok((one, _)), Ok((all, votes))) => println!(
                "votes on {} ({kind}, {}): {cubes} cubes x {maps} maps in {all:.2}s ({one:.2}s for one with uploads and read-back): {:.2} million cube-map tests/s ({:.0} % vote)",
                adapter.name,
                adapter.backend,
                (cubes * (maps - 1)) as f64 / (all - one).max(1e-9) / 1e6,
                100.0 * votes as f64 / (cubes * maps) as f64
            ),
            (Err(error), _) | (_, Err(error)) => println!("votes on {} ({kind}): {error}", adapter.name),
        }
    }
}
