//! `octstore-evaluate RECONSTRUCTION GROUND_TRUTH`: accuracy, completeness, Chamfer distance,
//! precision, recall and F-score at tau (Tanks and Temples), plus the reconstruction's boundary
//! and non-manifold edge counts. See `octstore::quality::evaluate` for the definitions.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::Parser;
use octstore::mesh::read_mesh;
use octstore::quality::evaluate::{EvaluateOptions, evaluate};
use octstore::quality::ground_truth_views::bounds;

#[derive(Parser)]
#[command(version, about = "Measure a reconstructed mesh against a ground-truth mesh")]
struct Args {
    reconstruction: PathBuf,
    ground_truth: PathBuf,
    /// Threshold tau as a fraction of the ground truth's bounding-box diagonal.
    #[arg(long, default_value_t = 0.01)]
    tau: f64,
    /// Keep only reconstruction inside the ground truth's bounds grown by this fraction of its
    /// diagonal.
    #[arg(long, default_value_t = 0.05)]
    crop_margin: f64,
    /// Measure the whole reconstruction, uncropped.
    #[arg(long)]
    no_crop: bool,
    #[arg(long)]
    json: bool,
}

fn main() -> ExitCode {
    let args = Args::parse();
    let run = || -> Result<String, Box<dyn std::error::Error>> {
        let reconstruction = read_mesh(&args.reconstruction)?;
        let truth = read_mesh(&args.ground_truth)?;
        let (lo, hi) = bounds(&truth).ok_or_else(|| format!("{}: no triangles", args.ground_truth.display()))?;
        let options = EvaluateOptions {
            tau: args.tau * (hi - lo).length(),
            spacing: None,
            crop_margin: (!args.no_crop).then_some(args.crop_margin),
            seed: 1,
        };
        let r = evaluate(&reconstruction, &truth, &options)?;
        Ok(if args.json {
            serde_json::to_string_pretty(&r).unwrap_or_default()
        } else {
            format!(
                "tau {:.6} | accuracy {:.6} | completeness {:.6} | chamfer {:.6} | precision {:.4} | recall {:.4} | F-score {:.4} | boundary edges {} | non-manifold edges {}",
                r.tau,
                r.accuracy,
                r.completeness,
                r.chamfer,
                r.precision,
                r.recall,
                r.f_score,
                r.boundary_edges,
                r.non_manifold_edges
            )
        })
    };
    match run() {
        Ok(text) => {
            println!("{text}");
            ExitCode::SUCCESS
        }
        Err(e) => {
            eprintln!("octstore-evaluate: {e}");
            ExitCode::FAILURE
        }
    }
}
