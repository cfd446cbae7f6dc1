//! `octstore-gt-render MESH --out DIR`: depth maps of a ground-truth mesh (OFF, PLY, OBJ, each
//! optionally .gz) from a ring or sphere of cameras, with noise, written as PFM files plus the
//! manifest `DIR/scene.json` for `octstore ingest`, and `DIR/seen-faces.txt`, the indices of the
//! triangles some camera saw (for `octstore-evaluate --gt-faces`).
//!
//! `octstore-gt-render --layout interior --out DIR` needs no mesh: it renders the built-in
//! furnished room from inside and writes its ground truth to `DIR/ground-truth.ply`.

use std::path::PathBuf;
use std::process::ExitCode;

use crate::mesh::{read_mesh, write_mesh};
use crate::quality::ground_truth_views::{GroundTruth, Layout, NoiseModel, Rig};
use crate::quality::interior_scene::interior_room;
use clap::Parser;

#[derive(Parser)]
#[command(version, about = "Render depth maps of a ground-truth mesh, with noise")]
struct Args {
    /// The ground-truth mesh (not with `--layout interior`, which has its own room).
    #[arg(required_unless_present = "layout")]
    mesh: Option<PathBuf>,
    #[arg(long)]
    out: PathBuf,
    #[arg(long, default_value_t = 24)]
    views: usize,
    /// Sphere or ring: cameras around the mesh; interior: inside the built-in room.
    #[arg(long, value_enum)]
    layout: Option<Layout>,
    /// Camera distance from the mesh's centre, in bounding-box diagonals (interior: radius of
    /// the circle the cameras walk; default 0.08).
    #[arg(long)]
    distance: Option<f64>,
    /// The farthest camera distance, in diagonals: views stand between `--distance` and this
    /// (sphere and ring layouts).
    #[arg(long)]
    far: Option<f64>,
    /// Scale the mesh (and so the whole scene) by this factor first.
    #[arg(long, default_value_t = 1.0)]
    scale: f64,
    /// Write a 7-Scenes folder (16-bit PNG depths in thousandths of a unit, pose files,
    /// camera-intrinsics.txt) instead of PFM files and a manifest.
    #[arg(long)]
    seven_scenes: bool,
    #[arg(long, default_value_t = 320)]
    width: u32,
    #[arg(long, default_value_t = 240)]
    height: u32,
    /// Horizontal field of view, degrees.
    #[arg(long, default_value_t = 55.0)]
    fov: f64,
    /// Gaussian depth noise, a fraction of the depth (0.005 = 0.5 %).
    #[arg(long, default_value_t = 0.0)]
    noise: f64,
    /// Fraction of pixels replaced by random depths (0.1 = 10 %).
    #[arg(long, default_value_t = 0.0)]
    outliers: f64,
    /// Discs of missing pixels per view.
    #[arg(long, default_value_t = 0)]
    missing: usize,
    /// Radius of each missing disc, a fraction of the image width.
    #[arg(long, default_value_t = 0.08)]
    missing_radius: f64,
    /// Half-size of a room around the mesh, in diagonals (0: no room, misses stay empty; the
    /// interior layout has none).
    #[arg(long, default_value_t = 1.6)]
    room: f64,
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

/// The `octstore-gt-render` command: parses its arguments, runs, and reports an error on stderr.
pub fn gt_render_main() -> ExitCode {
    let args = Args::parse();
    let run = || -> Result<PathBuf, Box<dyn std::error::Error>> {
        let layout = args.layout.unwrap_or(Layout::Sphere);
        let interior = layout == Layout::Interior;
        let distance = args.distance.unwrap_or(if interior { 0.08 } else { 1.2 });
        let truth = match (&args.mesh, interior) {
            (Some(path), false) => {
                let mut mesh = read_mesh(path)?;
                if !(args.scale.is_finite() && args.scale > 0.0) {
                    return Err(format!("--scale {} must be a positive number", args.scale).into());
                }
                for p in &mut mesh.positions {
                    *p = p.map(|c| (f64::from(c) * args.scale) as f32);
                }
                GroundTruth::new(mesh, (args.room > 0.0).then_some(args.room))
                    .map_err(|e| format!("{}: {e}", path.display()))?
            }
            (None, true) => {
                let truth = GroundTruth::new(interior_room(), None)?;
                std::fs::create_dir_all(&args.out).map_err(|e| format!("{}: {e}", args.out.display()))?;
                let path = args.out.join("ground-truth.ply");
                write_mesh(&path, &truth.mesh).map_err(|e| format!("{}: {e}", path.display()))?;
                truth
            }
            (Some(_), true) => return Err("--layout interior renders its own room: give no mesh".into()),
            (None, false) => return Err("give a ground-truth mesh, or --layout interior".into()),
        };
        if !interior && args.room > 0.0 && args.room <= distance {
            return Err(format!(
                "--room {} must exceed --distance {}: the cameras stand inside the room",
                args.room, distance
            )
            .into());
        }
        let rig = Rig {
            views: args.views,
            layout,
            distance,
            far: args.far,
            width: args.width,
            height: args.height,
            fov_degrees: args.fov,
        };
        let noise = NoiseModel {
            depth_sigma: args.noise,
            outliers: args.outliers,
            missing_regions: args.missing,
            missing_radius: args.missing_radius,
            seed: args.seed,
        };
        let written = if args.seven_scenes {
            truth.write_seven_scenes(&rig, &noise, &args.out)
        } else {
            truth.write_dataset(&rig, &noise, &args.out)
        };
        let manifest = written.map_err(|e| format!("{}: {e}", args.out.display()))?;
        let seen: String = truth
            .seen_faces(&rig)
            .iter()
            .enumerate()
            .filter(|(_, seen)| **seen)
            .map(|(index, _)| format!("{index}\n"))
            .collect();
        let faces = args.out.join("seen-faces.txt");
        std::fs::write(&faces, seen).map_err(|e| format!("{}: {e}", faces.display()))?;
        Ok(manifest)
    };
    match run() {
        Ok(manifest) => {
            println!("{}", manifest.display());
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("octstore-gt-render: {e}");
            ExitCode::FAILURE
        }
    }
}
