//! `octstore divide` and `octstore merge`: the point cloud division and the fusion of the
//! meshes reconstructed from its parts.

use std::time::Instant;

use super::args::{DivideArgs, GlobalOptions, MergeArgs};
use super::error::Result;
use super::report::peak_rss_bytes;
use crate::divide::{self, DivideOptions, MANIFEST, PointSource, SyntheticCloud, divide_sources, read_manifest_file};

pub(super) fn divide(global: &GlobalOptions, args: DivideArgs) -> Result<()> {
    let started = Instant::now();
    // A folder that holds a division keeps its limit and overlap unless they are given.
    let existing = args.output.join(MANIFEST);
    let recorded = if existing.exists() {
        read_manifest_file(&existing).ok().map(|m| m.division)
    } else {
        None
    };
    let defaults = DivideOptions::default();
    let options = DivideOptions {
        max_points: args
            .max_points
            .or(recorded.as_ref().map(|d| d.max_points))
            .unwrap_or(defaults.max_points),
        overlap: args
            .overlap
            .or(recorded.as_ref().map(|d| d.overlap))
            .unwrap_or(defaults.overlap),
        max_depth: args.max_depth,
        memory_budget: global.memory_budget,
        progress: !global.quiet,
    };
    let report = match args.synthetic {
        Some(points) => {
            let cloud = SyntheticCloud::new(points, 1);
            let sources: [&dyn PointSource; 1] = [&cloud];
            divide_sources(&sources, &args.output, &options)?
        }
        None => divide::divide(&args.inputs, &args.output, &options)?,
    };
    let seconds = started.elapsed().as_secs_f64();
    println!(
        "divide     {} points -> {} subspaces in {} ({} files written, {} points with overlaps; largest core {} points; counted {} levels a pass, {} nodes divided again) | {:.2}s, {:.1} M points/s | peak memory {:.0} MB",
        report.input_points,
        report.subspaces,
        args.output.display(),
        report.files_written,
        report.points_written,
        report.largest_core,
        report.counting_depth,
        report.divided_again,
        seconds,
        report.input_points as f64 / seconds.max(1e-9) / 1e6,
        peak_rss_bytes() as f64 / 1e6
    );
    if !report.over_limit.is_empty() {
        tracing::warn!(
            "{} subspaces hold more than --max-points {} points that no finer cube separates (duplicate points): {}",
            report.over_limit.len(),
            options.max_points,
            report.over_limit.join(", ")
        );
    }
    Ok(())
}

pub(super) fn merge(args: MergeArgs) -> Result<()> {
    let started = Instant::now();
    let report = divide::merge::merge(&args.manifest, &args.meshes, &args.output)?;
    println!(
        "merge      {} meshes -> {} vertices, {} triangles ({} cut away, {} vertices welded), {} boundary edges -> {} | {:.2}s",
        report.meshes,
        report.vertices,
        report.triangles,
        report.cut,
        report.welded,
        report.boundary_edges,
        args.output.display(),
        started.elapsed().as_secs_f64()
    );
    if !report.missing.is_empty() {
        tracing::warn!(
            "no mesh was given for {} subspaces (holes in the result): {}",
            report.missing.len(),
            report.missing.join(", ")
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use clap::Parser;

    use super::super::args::Cli;

    fn run(args: &[&str]) -> Result<std::process::ExitCode, super::super::CliError> {
        let cli = Cli::try_parse_from(std::iter::once("octstore").chain(args.iter().copied())).map_err(|e| {
            super::super::CliError::Usage {
                verb: "test",
                problem: Box::leak(e.to_string().into_boxed_str()),
            }
        })?;
        super::super::run(cli)
    }

    #[test]
    fn divide_keeps_the_folders_limit_unless_told_otherwise() -> Result<(), Box<dyn std::error::Error>> {
        let temp = tempfile::tempdir()?;
        let cloud = temp.path().join("cloud.xyz");
        let lines: String = (0..300)
            .map(|i| format!("{} {} {}\n", i % 17, i / 17, (i * 7) % 5))
            .collect();
        std::fs::write(&cloud, lines)?;
        let dir = temp.path().join("parts");
        let (cloud, dir) = (cloud.to_string_lossy().into_owned(), dir.to_string_lossy().into_owned());
        run(&["--quiet", "divide", &cloud, "-o", &dir, "--max-points", "100"])?;
        let manifest = super::read_manifest_file(&std::path::Path::new(&dir).join(super::MANIFEST))?;
        assert_eq!(manifest.division.max_points, 100);
        assert!(manifest.subspaces.len() >= 3);
        // The same points again: the recorded limit holds without --max-points.
        run(&["--quiet", "divide", &cloud, "-o", &dir])?;
        let again = super::read_manifest_file(&std::path::Path::new(&dir).join(super::MANIFEST))?;
        assert!(again.subspaces.iter().all(|s| s.core_points <= 100));
        let message = run(&["--quiet", "divide", &cloud, "-o", &dir, "--max-points", "50"])
            .map(|_| ())
            .unwrap_err()
            .to_string();
        assert!(message.contains("--max-points 100"), "{message}");
        Ok(())
    }
}
