//! Objects seen from all around in empty space, with no flags: the capture people make most
//! after rooms. No room and no ground behind the object: the pixels around it are invalid (0),
//! as a masked turntable scan or a render gives them. The defaults must measure the noise from
//! the pixels (not assume a Kinect because the folder is laid out as 7-Scenes), take the
//! invalid background as free space, and give one closed component.

mod common;

use std::path::{Path, PathBuf};

use common::*;
use octstore::Mesh;
use octstore::mesh::{connected_components, read_mesh};
use octstore::testing::quality::evaluate::{EvaluateOptions, Report, evaluate};
use octstore::testing::quality::ground_truth_views::{GroundTruth, Layout, NoiseModel, Rig, bounds};

/// The bunny, scaled by `scale` (it is about 1 unit across).
fn bunny(scale: f32) -> Mesh {
    let mut mesh = read_mesh(&shared_path("meshes/bunny00.off")).unwrap();
    for p in &mut mesh.positions {
        *p = p.map(|c| c * scale);
    }
    mesh
}

/// 60 views of 160 x 120 from a sphere around the object, between 0.85 and 1.65 diagonals
/// from its centre (an object 3 units tall seen from 4 to 8 units). With 40 views a spot of
/// the clean bunny's underside is seen by too few of them and the observed surface keeps a
/// hole of 6 edges there.
fn sphere_rig() -> Rig {
    Rig {
        views: 60,
        layout: Layout::Sphere,
        distance: 0.85,
        far: Some(1.65),
        width: 160,
        height: 120,
        fov_degrees: 55.0,
    }
}

fn noise(depth_sigma: f64, outliers: f64) -> NoiseModel {
    NoiseModel {
        depth_sigma,
        outliers,
        missing_regions: 0,
        missing_radius: 0.0,
        seed: 1,
    }
}

/// The bunny 3 units tall seen by [`sphere_rig`] with `noise`, written as a 7-Scenes folder
/// in a new temporary directory: the truth, the directory and the folder; None without the
/// shared data.
fn bunny_in_seven_scenes_folder(noise: &NoiseModel) -> Option<(Mesh, tempfile::TempDir, PathBuf)> {
    shared_data("meshes/bunny00.off")?;
    let truth_mesh = bunny(3.0);
    let truth = GroundTruth::new(truth_mesh.clone(), None).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let frames = truth
        .write_seven_scenes(&sphere_rig(), noise, &dir.path().join("frames"))
        .unwrap();
    Some((truth_mesh, dir, frames))
}

/// Runs the CLI quietly; its standard output.
fn run(args: &[&str]) -> String {
    let out = octstore(&[args, &["--quiet"]].concat(), &[]);
    assert!(out.status.success(), "{args:?}: {}", stderr(&out));
    stdout(&out)
}

/// `ingest`, `solve`, `extract` of `input` into `dir`, no flags; the mesh and the store's
/// `info`.
fn reconstruct(input: &Path, dir: &Path) -> (Mesh, String) {
    reconstruct_with(input, dir, &[])
}

/// [`reconstruct`] with `solve_flags` given to `solve`, in `dir`/store-`solve_flags`.
fn reconstruct_with(input: &Path, dir: &Path, solve_flags: &[&str]) -> (Mesh, String) {
    let name = solve_flags.concat();
    let store = dir.join(format!("store{name}"));
    let s = store.to_str().unwrap();
    let mesh = dir.join(format!("mesh{name}.ply"));
    run(&["ingest", s, input.to_str().unwrap()]);
    run(&[&["solve", s], solve_flags].concat());
    run(&["extract", s, "-o", mesh.to_str().unwrap()]);
    (read_mesh(&mesh).unwrap(), run(&["info", s]))
}

/// The mesh against the truth at tau = `fraction` of the truth's diagonal, uncropped.
fn measure(mesh: &Mesh, truth: &Mesh, fraction: f64) -> Report {
    let (lo, hi) = bounds(truth).unwrap();
    evaluate(
        mesh,
        truth,
        &EvaluateOptions {
            tau: fraction * (hi - lo).length(),
            spacing: None,
            crop_margin: None,
            seen_faces: None,
            seed: 1,
        },
    )
    .unwrap()
}

/// A clean capture written as a 7-Scenes folder (16-bit PNG depths in thousandths of a unit,
/// background 0), the layout that used to be taken for a Kinect at room scale: one closed
/// component, within 1 % of the diagonal everywhere, a measured noise model recorded, and the
/// object's solver chosen.
#[test]
fn a_clean_object_in_a_seven_scenes_folder_comes_out_closed_and_whole() {
    let Some((truth_mesh, dir, frames)) = bunny_in_seven_scenes_folder(&noise(0.0, 0.0)) else {
        return;
    };
    let (mesh, info) = reconstruct(&frames, dir.path());
    let report = measure(&mesh, &truth_mesh, 0.01);
    eprintln!("{report:?}, {} components", connected_components(&mesh));
    assert!(info.contains("depth noise"), "{info}");
    assert!(!info.contains("0.0012 + 0.0019"), "a Kinect table was assumed: {info}");
    // An object against empty background: the default solver is SSD (a room's is TGV,
    // tests/observed.rs).
    assert!(
        info.lines()
            .any(|line| line.trim_start().starts_with("solver") && line.contains("ssd")),
        "{info}"
    );
    assert!(
        info.contains("capture        an object (defaults: solve by ssd"),
        "{info}"
    );
    assert_eq!(report.boundary_edges, 0, "{report:?}");
    assert_eq!(report.non_manifold_edges, 0, "{report:?}");
    assert_eq!(connected_components(&mesh), 1);
    assert!(report.f_score >= 0.99, "{report:?}");
}

/// 0.5 % depth noise and a tenth of the pixels wild, in metres (a 0.3 m object seen from 0.4
/// to 0.8 m, written as PFM files and a manifest): closed, and the noise does not blow the
/// cubes up into a blob.
#[test]
fn a_noisy_object_with_outliers_stays_closed_and_close() {
    let Some(_) = shared_data("meshes/bunny00.off") else {
        return;
    };
    let truth_mesh = bunny(0.3);
    let truth = GroundTruth::new(truth_mesh.clone(), None).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let manifest = truth
        .write_dataset(&sphere_rig(), &noise(0.005, 0.1), &dir.path().join("views"))
        .unwrap();
    let (mesh, _) = reconstruct(&manifest, dir.path());
    let report = measure(&mesh, &truth_mesh, 0.01);
    eprintln!("{report:?}, {} components", connected_components(&mesh));
    assert_eq!(report.boundary_edges, 0, "{report:?}");
    // One piece: a floater made of outliers beside the object would be a second component.
    assert_eq!(report.components, 1, "{report:?}");
    assert!(report.f_score >= 0.99, "{report:?}");
}

/// The second solver on the same kind of capture, 3 units tall in a 7-Scenes folder, where the
/// cubes are small against the noise: its smoothness follows how far the sample centroids
/// scatter, so it leaves no bubbles or shards around the object (with the smoothness fixed,
/// `hybrid` left hundreds of components here, `ssd` 103). One closed component: the maps see
/// the object against empty background, so the default mesh is watertight, and its noise blobs
/// go. `--open` gives the observed surface, which keeps them: at 160 x 120 pixels, with the
/// noise smoothness at most 10 times the base, `ssd` leaves 59 boundary edges in 7 parts
/// (pinholes at the trim and specks of noise beside the surface; 4 edges when the smoothness
/// went up to 100 times), `hybrid` 4 in 5, where an opened or torn object has hundreds.
#[test]
fn ssd_and_hybrid_keep_a_noisy_object_in_one_closed_piece() {
    let Some((truth_mesh, dir, frames)) = bunny_in_seven_scenes_folder(&noise(0.005, 0.1)) else {
        return;
    };
    for method in ["ssd", "hybrid"] {
        let (mesh, _) = reconstruct_with(&frames, dir.path(), &["--method", method]);
        let report = measure(&mesh, &truth_mesh, 0.01);
        eprintln!("{method}: {report:?}");
        assert_eq!(report.components, 1, "{method}: {report:?}");
        assert_eq!(report.boundary_edges, 0, "{method}: {report:?}");
        assert!(report.f_score >= 0.99, "{method}: {report:?}");
        let store = dir.path().join(format!("store--method{method}"));
        let open = dir.path().join(format!("open-{method}.ply"));
        run(&[
            "extract",
            store.to_str().unwrap(),
            "-o",
            open.to_str().unwrap(),
            "--open",
        ]);
        let open = measure(&read_mesh(&open).unwrap(), &truth_mesh, 0.01);
        eprintln!("{method} --open: {open:?}");
        assert!(open.boundary_edges <= 64, "{method} --open: {open:?}");
        assert!(open.f_score >= 0.99, "{method} --open: {open:?}");
    }
}

/// The same scene in units ten times smaller (every depth and position times 10) gives the
/// same mesh times 10: the measured noise, the root and the weights all scale with it.
#[test]
fn a_scene_ten_times_larger_gives_the_same_mesh_ten_times_larger() {
    let Some(_) = shared_data("meshes/bunny00.off") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let mut meshes = Vec::new();
    for (scale, name) in [(1.0, "small"), (10.0, "large")] {
        let truth = GroundTruth::new(bunny(scale), None).unwrap();
        let manifest = truth
            .write_dataset(&sphere_rig(), &noise(0.005, 0.0), &dir.path().join(name).join("views"))
            .unwrap();
        let (mut mesh, _) = reconstruct(&manifest, &dir.path().join(name));
        for p in &mut mesh.positions {
            *p = p.map(|c| c / scale);
        }
        meshes.push(mesh);
    }
    let report = measure(&meshes[1], &meshes[0], 0.002);
    eprintln!("{report:?}");
    assert!(report.f_score >= 0.99, "{report:?}");
}
