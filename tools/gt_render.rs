//! `octstore-gt-render MESH --out DIR`: depth maps of a ground-truth mesh (OFF, PLY, OBJ, each
//! optionally .gz) from a ring or sphere of cameras, with noise, written as PFM files plus the
//! manifest `DIR/scene.json` for `octstore ingest`.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::Parser;
use octstore::mesh::read_mesh;
use octstore::quality::ground_truth_views::{GroundTruth, Layout, NoiseModel, Rig};

#[derive(Parser)]
#[command(version, about = "Render depth maps of a ground-truth mesh, with noise")]
struct Args {
    mesh: PathBuf,
    #[arg(long)]
    out: PathBuf,
    #[arg(long, default_value_t = 24)]
    views: usize,
    #[arg(long, value_enum, default_value_t = Layout::Sphere)]
    layout: Layout,
    /// Camera distance from the mesh's centre, in bounding-box diagonals.
    #[arg(long, default_value_t = 1.2)]
    distance: f64,
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
    /// Half-size of a room around the mesh, in diagonals (0: no room, misses stay empty).
    #[arg(long, default_value_t = 1.6)]
    room: f64,
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

fn main() -> ExitCode {
    let args = Args::parse();
    let run = || -> Result<PathBuf, Box<dyn std::error::Error>> {
        let mesh = read_mesh(&args.mesh)?;
        let truth = GroundTruth::new(mesh, (args.room > 0.0).then_some(args.room))
            .map_err(|e| format!("{}: {e}", args.mesh.display()))?;
        if args.room > 0.0 && args.room <= args.distance {
            return Err(format!(
                "--room {} must exceed --distance {}: the cameras stand inside the room",
                args.room, args.distance
            )
            .into());
        }
        let rig = Rig {
            views: args.views,
            layout: args.layout,
            distance: args.distance,
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
        Ok(truth
            .write_dataset(&rig, &noise, &args.out)
            .map_err(|e| format!("{}: {e}", args.out.display()))?)
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
