//! `octstore-evaluate RECONSTRUCTION GROUND_TRUTH`: accuracy, completeness, Chamfer distance,
//! precision, recall and F-score at tau (Tanks and Temples), normal consistency, plus the
//! reconstruction's boundary and non-manifold edge counts (and with `--self-intersections` its
//! self-intersecting triangles). See `src/quality/evaluate.rs`
//! for the definitions. `--gt-faces` (written by `octstore-gt-render`) restricts completeness
//! and recall to the ground-truth faces some camera saw.

use std::path::PathBuf;
use std::process::ExitCode;

use crate::mesh::read_mesh;
use crate::quality::evaluate::{EvaluateOptions, evaluate};
use crate::quality::ground_truth_views::bounds;
use crate::quality::self_intersection::self_intersecting_triangles;
use clap::Parser;

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
    /// Sample spacing as a fraction of the diagonal (default: tau / 5). A coarser spacing
    /// makes small taus on large scenes affordable, at the cost of noisier figures.
    #[arg(long)]
    spacing: Option<f64>,
    /// The ground-truth faces some camera saw: a text file of triangle indices, one per line
    /// (`seen-faces.txt` from `octstore-gt-render`).
    #[arg(long)]
    gt_faces: Option<PathBuf>,
    /// Also count the reconstruction's self-intersecting triangles (those that cross a
    /// triangle with which they share no vertex).
    #[arg(long)]
    self_intersections: bool,
    /// Print the report as JSON.
    #[arg(long)]
    json: bool,
}

/// Reads a list of triangle indices into one flag per ground-truth triangle.
fn read_seen_faces(path: &std::path::Path, triangles: usize) -> Result<Vec<bool>, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut seen = vec![false; triangles];
    for (number, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let index: usize = line.parse().map_err(|e| {
            format!(
                "{} line {}: {line:?} is not a triangle index ({e})",
                path.display(),
                number + 1
            )
        })?;
        let flag = seen.get_mut(index).ok_or_else(|| {
            format!(
                "{} line {}: triangle {index} is beyond the ground truth's {triangles}",
                path.display(),
                number + 1
            )
        })?;
        *flag = true;
    }
    Ok(seen)
}

/// The `octstore-evaluate` command: parses its arguments, runs, and reports an error on stderr.
pub fn evaluate_main() -> ExitCode {
    let args = Args::parse();
    let run = || -> Result<String, Box<dyn std::error::Error>> {
        let reconstruction = read_mesh(&args.reconstruction)?;
        let truth = read_mesh(&args.ground_truth)?;
        let (lo, hi) = bounds(&truth).ok_or_else(|| format!("{}: no triangles", args.ground_truth.display()))?;
        let options = EvaluateOptions {
            tau: args.tau * (hi - lo).length(),
            spacing: args.spacing.map(|fraction| fraction * (hi - lo).length()),
            crop_margin: (!args.no_crop).then_some(args.crop_margin),
            seen_faces: match &args.gt_faces {
                Some(path) => Some(read_seen_faces(path, truth.triangles.len())?),
                None => None,
            },
            seed: 1,
        };
        let r = evaluate(&reconstruction, &truth, &options)?;
        let crossing = args
            .self_intersections
            .then(|| self_intersecting_triangles(&reconstruction));
        Ok(if args.json {
            let mut json = serde_json::to_value(&r)?;
            if let (Some(count), Some(object)) = (crossing, json.as_object_mut()) {
                object.insert("self_intersecting_triangles".into(), count.into());
            }
            serde_json::to_string_pretty(&json).unwrap_or_default()
        } else {
            let crossing = crossing.map_or_else(String::new, |c| format!(" | self-intersecting triangles {c}"));
            format!(
                "tau {:.6} | accuracy {:.6} | completeness {:.6} | chamfer {:.6} | precision {:.4} | recall {:.4} | F-score {:.4} | normal consistency {:.4} | boundary edges {} | non-manifold edges {} | components {}{crossing}",
                r.tau,
                r.accuracy,
                r.completeness,
                r.chamfer,
                r.precision,
                r.recall,
                r.f_score,
                r.normal_consistency,
                r.boundary_edges,
                r.non_manifold_edges,
                r.components
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
