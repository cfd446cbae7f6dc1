//! The quality bar: the Stanford bunny rendered with 0.5 % depth noise and 10 % outlier pixels,
//! reconstructed end to end through the CLI, reaches F-score >= 0.9 at tau = 1 % of its
//! bounding-box diagonal (Tanks and Temples definition, reconstruction cropped to the bunny's
//! bounds grown by 5 % of the diagonal, which drops the room walls behind it).

mod common;

use common::*;
use octstore::mesh::read_mesh;
use octstore::testing::quality::evaluate::{EvaluateOptions, evaluate};
use octstore::testing::quality::ground_truth_views::{GroundTruth, Layout, NoiseModel, Rig, bounds};

fn bunny() -> octstore::Mesh {
    read_mesh(&shared_path("meshes/bunny00.off")).unwrap()
}

/// The quality bar's capture: 24 views of 160x120 on a sphere 0.9 from the bunny, 0.5 % depth
/// noise and 10 % outlier pixels.
fn quality_bar_capture() -> (Rig, NoiseModel) {
    let rig = Rig {
        far: None,
        views: 24,
        layout: Layout::Sphere,
        distance: 0.9,
        width: 160,
        height: 120,
        fov_degrees: 70.0,
    };
    let noise = NoiseModel {
        depth_sigma: 0.005,
        outliers: 0.1,
        missing_regions: 0,
        missing_radius: 0.0,
        seed: 1,
    };
    (rig, noise)
}

/// Runs the CLI quietly; its standard output.
fn run_quietly(args: &[&str]) -> String {
    let out = octstore(&[args, &["--quiet"]].concat(), &[]);
    assert!(out.status.success(), "{args:?}: {}", stderr(&out));
    stdout(&out)
}

/// Renders the bunny inside a room of half-size `room` diagonals with `noise`, reconstructs it
/// through the CLI (max depth 9, 100 iterations) and measures it at tau = 1 % of its diagonal.
fn reconstruct_bunny(room: f64, rig: &Rig, noise: &NoiseModel) -> octstore::testing::quality::evaluate::Report {
    let truth_mesh = bunny();
    // A room around the bunny, so that every ray ends on a surface and all space is observed.
    let truth = GroundTruth::new(truth_mesh.clone(), Some(room)).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let manifest = truth.write_dataset(rig, noise, &dir.path().join("views")).unwrap();
    let store = dir.path().join("store");
    let s = store.to_str().unwrap();
    let mesh_path = dir.path().join("bunny.ply");
    run_quietly(&["ingest", s, manifest.to_str().unwrap(), "--max-depth", "9"]);
    run_quietly(&["solve", s, "--iterations", "100"]);
    run_quietly(&["extract", s, "-o", mesh_path.to_str().unwrap()]);
    let reconstruction = read_mesh(&mesh_path).unwrap();
    let (lo, hi) = bounds(&truth_mesh).unwrap();
    let report = evaluate(
        &reconstruction,
        &truth_mesh,
        &EvaluateOptions {
            tau: 0.01 * (hi - lo).length(),
            spacing: None,
            crop_margin: Some(0.05),
            seen_faces: None,
            seed: 1,
        },
    )
    .unwrap();
    eprintln!("{report:?}");
    // Seen from all around, the bunny stays closed: no boundary edge near it (the room's walls,
    // seen from one side at a slant, may have small holes).
    assert_eq!(report.non_manifold_edges, 0);
    let grow = (hi - lo).length() * 0.05;
    let near_bunny = |v: u32| {
        let p = reconstruction.positions[v as usize].map(f64::from);
        (0..3).all(|a| p[a] >= lo[a] - grow && p[a] <= hi[a] + grow)
    };
    let mut uses = std::collections::HashMap::new();
    for t in &reconstruction.triangles {
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            *uses.entry((a.min(b), a.max(b))).or_insert(0) += 1;
        }
    }
    let open_near_bunny = uses
        .iter()
        .filter(|((a, b), n)| **n == 1 && near_bunny(*a) && near_bunny(*b))
        .count();
    assert_eq!(open_near_bunny, 0, "{open_near_bunny} boundary edges near the bunny");
    report
}

#[test]
fn noisy_bunny_reaches_f_score_0_9_at_one_percent() {
    let Some(_) = shared_data("meshes/bunny00.off") else {
        return;
    };
    let (rig, noise) = quality_bar_capture();
    let report = reconstruct_bunny(1.05, &rig, &noise);
    assert!(report.f_score >= 0.9, "{report:?}");
    // Measured (2-core dev box): precision 0.965, recall 0.954, F-score 0.960.
}

/// One pixel in five replaced by a random depth between 0.2 and 2 times the true one, in the
/// wide room of `octstore-gt-render`'s defaults. Two failure modes used to show here: outliers
/// beyond the walls stretched the root cube (halving the resolution at a fixed max depth), and
/// a mean mipmap let far outliers drag coarse depths back, eroding the bunny by about 3
/// finest cubes (F-score 0.09).
#[test]
fn bunny_with_a_fifth_of_its_pixels_wild_keeps_its_shape() {
    let Some(_) = shared_data("meshes/bunny00.off") else {
        return;
    };
    let rig = Rig {
        far: None,
        views: 24,
        layout: Layout::Sphere,
        distance: 1.2,
        width: 160,
        height: 120,
        fov_degrees: 55.0,
    };
    let noise = NoiseModel {
        depth_sigma: 0.002,
        outliers: 0.2,
        missing_regions: 0,
        missing_radius: 0.0,
        seed: 1,
    };
    let report = reconstruct_bunny(1.6, &rig, &noise);
    assert!(report.f_score >= 0.9, "{report:?}");
}

/// The stopping rule (`--tolerance`) against every one of the 200 iterations, on the noisy
/// bunny of the quality bar: at a tolerance ten times the default the finest level stops
/// before 200 iterations, and the mesh stays where all 200 put it (F-score >= 0.995 at tau =
/// 0.5 % of the diagonal, issue 23's bar). At `--max-depth 8` (about a quarter of the cubes
/// of the other bunny tests, to keep CI short) the finest level stops after about 100
/// (2026-11-26). (At the default, 1e-4, the bunny's finest level at depth 9 ran all 200: its
/// one large unit does not settle that far; RedKitchen's small warm-started units stop after
/// 50 on average.)
#[test]
fn stopping_early_leaves_the_bunny_where_every_iteration_puts_it() {
    let Some(_) = shared_data("meshes/bunny00.off") else {
        return;
    };
    let truth = GroundTruth::new(bunny(), Some(1.05)).unwrap();
    let (rig, noise) = quality_bar_capture();
    let dir = tempfile::tempdir().unwrap();
    let manifest = truth.write_dataset(&rig, &noise, &dir.path().join("views")).unwrap();
    let store = dir.path().join("store");
    let s = store.to_str().unwrap();
    let (every, early) = (dir.path().join("every.ply"), dir.path().join("early.ply"));
    let run = run_quietly;
    run(&["ingest", s, manifest.to_str().unwrap(), "--max-depth", "8"]);
    let all = run(&["solve", s, "--iterations", "200", "--tolerance", "0"]);
    assert!(
        all.contains("level 8: ") && all.contains("(200 iterations per cube"),
        "{all}"
    );
    run(&["extract", s, "-o", every.to_str().unwrap()]);
    let stopped = run(&["solve", s, "--iterations", "200", "--tolerance", "1e-3"]);
    let finest = stopped
        .lines()
        .find_map(|line| line.split("level 8: ").nth(1))
        .and_then(|rest| rest.split('(').nth(1))
        .and_then(|rest| rest.split(' ').next())
        .and_then(|n| n.parse::<u32>().ok())
        .unwrap_or_else(|| panic!("no iteration count for level 8 in {stopped}"));
    eprintln!("level 8: {finest} iterations per cube");
    assert!(finest < 200, "the finest level ran {finest} iterations per cube");
    run(&["extract", s, "-o", early.to_str().unwrap()]);
    let (every, early) = (read_mesh(&every).unwrap(), read_mesh(&early).unwrap());
    let (lo, hi) = bounds(&every).unwrap();
    let report = evaluate(
        &early,
        &every,
        &EvaluateOptions {
            tau: 0.005 * (hi - lo).length(),
            spacing: None,
            crop_margin: None,
            seen_faces: None,
            seed: 1,
        },
    )
    .unwrap();
    eprintln!("{report:?}");
    assert!(report.f_score >= 0.995, "{report:?}");
}
