//! What the command line prints: one summary line per stage, the extraction's line, `info`.

use std::path::Path;
use std::time::Instant;

use serde::Serialize;

use crate::mesh::MeshSummary;
use crate::stages;
use crate::store::{RunReport, Store, StoreError};

/// What `octstore info` reports (`--json` prints it as is).
#[derive(Serialize, Debug)]
pub struct InfoJson {
    /// The store's folder.
    pub store: String,
    /// The version described.
    pub version: u64,
    /// Depth maps registered up to that version.
    pub depth_maps: u64,
    /// Those depth maps by the noise model that sized their samples' cubes (measured models
    /// that differ in their numbers alone as one entry with their ranges).
    pub depth_noise: std::collections::BTreeMap<String, u64>,
    /// Cubes of the octree.
    pub cubes: u64,
    /// Treetop leaves.
    pub treetop_leaves: u64,
    /// Segment files the version sees.
    pub segments: u64,
    /// Their bytes.
    pub bytes: u64,
    /// Content digest per stage (hex), equal for equal content however it was produced.
    pub digest: std::collections::BTreeMap<String, String>,
    /// The root cube's lowest corner in world units (absent before the first ingest); with
    /// `root_side`, what `ingest --root` takes to give another store the same cubes.
    pub root_min: Option<[f64; 3]>,
    /// Side of the root cube in world units (absent before the first ingest).
    pub root_side: Option<f64>,
    /// The deepest solved level and the side of its cubes in world units (absent before a solve).
    pub finest_level: Option<u8>,
    /// The side of the finest level's cubes, in world units.
    pub finest_cube_side: Option<f64>,
    /// The octree's deepest level (absent before the octree is built). A `finest_level` below
    /// it means a solve stopped part way: `octstore solve --resume` finishes it.
    pub octree_deepest_level: Option<u8>,
    /// The solver of the finest level: `tgv`, `ssd` or `hybrid` (absent before a solve).
    pub solver: Option<String>,
    /// Whether the store's ingests gather the sample sums `--method ssd|hybrid` needs (`ingest
    /// --sample-sums` at its first ingest; absent before the first ingest).
    pub sample_sums: Option<bool>,
    /// What the defaults of `solve` and `extract` take the capture for (absent without depth
    /// maps).
    pub capture: Option<CaptureJson>,
}

/// The capture as the defaults see it (`stages::capture`).
#[derive(serde::Serialize, Debug, Clone, PartialEq, Eq)]
pub struct CaptureJson {
    /// An object seen against empty background (`ssd`, watertight mesh), else a scene (`tgv`,
    /// the observed surface).
    pub object: bool,
    /// Depth maps read that see their content against empty background.
    pub against_background: usize,
    /// Depth maps read: up to 9, evenly spread.
    pub read: usize,
}

/// The `info` report of the latest version, or of `version`.
pub fn info(store: &Store, version: Option<u64>) -> Result<InfoJson, StoreError> {
    use crate::IndicatorField;
    let snapshot = match version {
        Some(v) => store.snapshot(v)?,
        None => store.latest()?,
    };
    let digest = snapshot
        .stages()
        .map(|stage| (stage.to_string(), format!("{:016x}", snapshot.digest(stage))))
        .collect();
    let scene = stages::ingest::read_scene(store)?;
    let finest_level = snapshot.finest_level();
    let maps: Vec<_> = stages::ingest::depth_maps_at(&snapshot)?
        .into_iter()
        .map(|(_, record)| record)
        .collect();
    Ok(InfoJson {
        root_min: scene.map(|s| s.root_min),
        root_side: scene.map(|s| s.root_side),
        finest_level,
        finest_cube_side: scene.zip(finest_level).map(|(s, level)| s.cube_side(level)),
        octree_deepest_level: if snapshot.segments(stages::OCTREE).is_empty() {
            None
        } else {
            Some(stages::octree_max_depth(store)?)
        },
        solver: snapshot.method()?.map(str::to_string),
        capture: if maps.is_empty() {
            None
        } else {
            let capture = stages::capture::Capture::of(&snapshot, "info")?;
            Some(CaptureJson {
                object: capture.is_object(),
                against_background: capture.against_background,
                read: capture.read,
            })
        },
        sample_sums: scene.map(|_| stages::ingest::records_sample_sums(store)).transpose()?,
        store: store.root().display().to_string(),
        version: snapshot.version(),
        depth_maps: maps.len() as u64,
        depth_noise: noise_models(maps.iter().map(|record| record.source.noise)),
        cubes: snapshot.rows(stages::OCTREE),
        treetop_leaves: {
            // One segment per treetop leaf, plus one for the treetop's internal nodes when the
            // root is not itself the only leaf.
            let n = snapshot.segments(stages::OCTREE).len() as u64;
            if n > 1 { n - 1 } else { n }
        },
        segments: snapshot.all_segments().count() as u64,
        bytes: snapshot.all_segments().map(|(_, r)| r.bytes).sum(),
        digest,
    })
}

/// Peak resident memory of this process so far, in bytes (Linux; 0 elsewhere).
pub fn peak_rss_bytes() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1).and_then(|v| v.parse::<u64>().ok()))
        })
        .map_or(0, |kb| kb * 1024)
}

pub(crate) fn summary(report: &RunReport) {
    println!(
        "{:<10} {} | units {} ({} resumed) | rows {} | {:.2}s | peak memory {:.0} MB",
        report.stage,
        match report.version {
            Some(v) => format!("version {v}: {}", report.summary),
            None => report.summary.clone(),
        },
        report.units,
        report.resumed_units,
        report.rows,
        report.seconds,
        peak_rss_bytes() as f64 / 1e6
    );
}

pub(crate) fn print_extract_summary(summary: &MeshSummary, output: &Path, started: Instant) {
    println!(
        "extract    {} vertices, {} triangles, {} boundary edges, {} non-manifold edges -> {} | {:.2}s | peak memory {:.0} MB",
        summary.vertices,
        summary.triangles,
        summary.boundary_edges,
        summary.non_manifold_edges,
        output.display(),
        started.elapsed().as_secs_f64(),
        peak_rss_bytes() as f64 / 1e6
    );
    if summary.triangles == 0 {
        tracing::warn!(
            "the mesh is empty: no surface was found in the region extracted (`octstore info` shows the scene's root and the depth maps' samples; a region outside the scene, or a root far larger than the samples, gives nothing to mesh)"
        );
    }
}

/// The maps' noise models as `info` lists them, with how many maps have each. Axial models
/// that differ only in their constant and quadratic terms (each map's measured model differs
/// a little from the next one's) share one entry that gives the range of both.
fn noise_models(models: impl Iterator<Item = crate::inputs::DepthNoise>) -> std::collections::BTreeMap<String, u64> {
    use crate::inputs::DepthNoise;
    /// The lowest and highest constant and quadratic terms, and the maps.
    type Ranges = ([f64; 2], [f64; 2], u64);
    let mut axial: std::collections::BTreeMap<[u64; 3], Ranges> = Default::default();
    let mut counts: std::collections::BTreeMap<String, u64> = Default::default();
    for noise in models {
        let Some([constant, quadratic, offset, sigmas, footprints]) = noise.parts() else {
            *counts.entry(noise.to_string()).or_default() += 1;
            continue;
        };
        let (c, q, maps) =
            axial
                .entry([offset, sigmas, footprints].map(f64::to_bits))
                .or_insert(([constant; 2], [quadratic; 2], 0));
        *c = [c[0].min(constant), c[1].max(constant)];
        *q = [q[0].min(quadratic), q[1].max(quadratic)];
        *maps += 1;
    }
    for (shape, (c, q, maps)) in axial {
        let [offset, sigmas, footprints] = shape.map(f64::from_bits);
        let text = if c[0] == c[1] && q[0] == q[1] {
            DepthNoise::from_parts([c[0], q[0], offset, sigmas, footprints]).to_string()
        } else {
            format!(
                "radius >= min({sigmas} x (c + q (d - {offset})^2), {footprints} footprints), measured per map: c {:.2e} to {:.2e}, q {:.2e} to {:.2e}",
                c[0], c[1], q[0], q[1]
            )
        };
        *counts.entry(text).or_default() += maps;
    }
    counts
}
