//! A reconstruction against a ground-truth mesh, Tanks and Temples style.
//!
//! Both meshes are sampled uniformly by area (a deterministic sampler, spacing a fifth of tau by
//! default). For each sample, the distance to the other mesh is the exact point-to-triangle
//! distance over the triangles of its 8 nearest samples there (a k-d tree finds them), so it
//! does not carry the sampling's own error. Then, for threshold tau:
//! - accuracy: mean distance from reconstruction samples to the ground truth;
//! - completeness: mean distance from ground-truth samples to the reconstruction;
//! - Chamfer distance: the mean of the two;
//! - precision: fraction of reconstruction samples within tau of the ground truth;
//! - recall: fraction of ground-truth samples within tau of the reconstruction;
//! - F-score: their harmonic mean;
//! - normal consistency: the mean of |n_r . n_g| over the samples of both meshes, n_r and n_g the
//!   normals of a sample's own triangle and of the nearest triangle of the other mesh.
//!
//! When only some ground-truth faces were seen by any camera (`seen_faces`), completeness,
//! recall and the ground truth's half of normal consistency use the samples on those faces
//! only: a method cannot be asked to recover what no depth map shows. Accuracy and precision
//! still measure against the whole ground truth.
//!
//! An optional crop keeps only reconstruction samples inside the ground truth's bounding box,
//! grown by a margin (Tanks and Temples crops to a bounding volume too): parts of the
//! reconstruction that the ground truth does not cover, such as a room around an object, then
//! count neither way.

use std::num::NonZeroUsize;

use glam::DVec3;
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rayon::prelude::*;
use serde::Serialize;

use crate::kernels::random::uniform;
use crate::mesh::{Mesh, edge_defects};

use super::QualityError;
use super::ground_truth_views::bounds;

#[derive(Clone, Debug)]
pub struct EvaluateOptions {
    /// The distance threshold, in the meshes' units.
    pub tau: f64,
    /// Sample spacing; a fifth of tau when absent.
    pub spacing: Option<f64>,
    /// Crop the reconstruction to the ground truth's bounds grown by this fraction of its
    /// diagonal.
    pub crop_margin: Option<f64>,
    /// The ground-truth faces some camera saw (by triangle index); all when absent.
    pub seen_faces: Option<Vec<bool>>,
    pub seed: u64,
}

#[derive(Clone, Debug, Serialize)]
pub struct Report {
    pub tau: f64,
    pub accuracy: f64,
    pub completeness: f64,
    pub chamfer: f64,
    pub precision: f64,
    pub recall: f64,
    pub f_score: f64,
    pub normal_consistency: f64,
    pub reconstruction_samples: usize,
    pub ground_truth_samples: usize,
    pub boundary_edges: usize,
    pub non_manifold_edges: usize,
    /// Connected components of the reconstruction's triangles (through shared vertices).
    pub components: usize,
}

/// Samples of a mesh: positions and the triangle each lies on.
struct Samples {
    points: Vec<DVec3>,
    triangles: Vec<u32>,
}

fn corners(mesh: &Mesh, t: &[u32; 3]) -> Option<[DVec3; 3]> {
    let p = |v: u32| {
        mesh.positions
            .get(v as usize)
            .map(|p| DVec3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2])))
    };
    Some([p(t[0])?, p(t[1])?, p(t[2])?])
}

/// Area-uniform samples: each triangle gets floor(area / spacing^2) samples plus one more with
/// the probability of the remainder, at uniformly random barycentric positions.
fn sample(mesh: &Mesh, spacing: f64, seed: u64) -> Samples {
    let mut state = seed;
    let mut out = Samples {
        points: Vec::new(),
        triangles: Vec::new(),
    };
    let density = 1.0 / (spacing * spacing);
    for (index, t) in mesh.triangles.iter().enumerate() {
        let Some([a, b, c]) = corners(mesh, t) else { continue };
        let expected = 0.5 * (b - a).cross(c - a).length() * density;
        let count = expected.floor() as usize + usize::from(uniform(&mut state) < expected.fract());
        for _ in 0..count {
            let (r1, r2) = (uniform(&mut state).sqrt(), uniform(&mut state));
            out.points.push(a * (1.0 - r1) + b * (r1 * (1.0 - r2)) + c * (r1 * r2));
            out.triangles.push(index as u32);
        }
    }
    out
}

/// Closest point of triangle abc to p (Ericson, Real-Time Collision Detection, 5.1.5).
pub fn closest_point_on_triangle(p: DVec3, a: DVec3, b: DVec3, c: DVec3) -> DVec3 {
    let (ab, ac, ap) = (b - a, c - a, p - a);
    let (d1, d2) = (ab.dot(ap), ac.dot(ap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return a;
    }
    let bp = p - b;
    let (d3, d4) = (ab.dot(bp), ac.dot(bp));
    if d3 >= 0.0 && d4 <= d3 {
        return b;
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return a + ab * (d1 / (d1 - d3));
    }
    let cp = p - c;
    let (d5, d6) = (ab.dot(cp), ac.dot(cp));
    if d6 >= 0.0 && d5 <= d6 {
        return c;
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return a + ac * (d2 / (d2 - d6));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        return b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)));
    }
    let denom = va + vb + vc;
    if denom.abs() < f64::MIN_POSITIVE {
        return a;
    }
    let (v, w) = (vb / denom, vc / denom);
    a + ab * v + ac * w
}

const CANDIDATES: usize = 8;

/// The unit normal of a triangle (zero when degenerate).
fn triangle_normal(mesh: &Mesh, triangle: u32) -> DVec3 {
    mesh.triangles
        .get(triangle as usize)
        .and_then(|t| corners(mesh, t))
        .map_or(DVec3::ZERO, |[a, b, c]| (b - a).cross(c - a).normalize_or_zero())
}

/// Distance from each query point to `mesh`, and the nearest triangle, through the k-d tree of
/// its samples.
fn distances(queries: &[DVec3], mesh: &Mesh, samples: &Samples) -> Vec<(f64, u32)> {
    if samples.points.is_empty() {
        return vec![(f64::INFINITY, u32::MAX); queries.len()];
    }
    let entries: Vec<[f64; 3]> = samples.points.iter().map(|p| p.to_array()).collect();
    let tree: ImmutableKdTree<f64, 3> = ImmutableKdTree::new_from_slice(&entries).unwrap_or_default();
    let k = NonZeroUsize::new(CANDIDATES).unwrap_or(NonZeroUsize::MIN);
    queries
        .par_iter()
        .map(|q| {
            tree.query(&q.to_array())
                .nearest_n::<SquaredEuclidean<f64>>(k)
                .execute()
                .iter()
                .filter_map(|hit| {
                    let triangle = samples.triangles.get(hit.item as usize)?;
                    let [a, b, c] = corners(mesh, mesh.triangles.get(*triangle as usize)?)?;
                    Some((q.distance(closest_point_on_triangle(*q, a, b, c)), *triangle))
                })
                .fold(
                    (f64::INFINITY, u32::MAX),
                    |best, next| if next.0 < best.0 { next } else { best },
                )
        })
        .collect()
}

/// Mean |n . n'| between each sample's triangle in `own` and its nearest triangle in `other`.
fn normal_agreement(own: &Mesh, samples: &Samples, other: &Mesh, nearest: &[(f64, u32)]) -> f64 {
    if nearest.is_empty() {
        return 0.0;
    }
    let sum: f64 = samples
        .triangles
        .iter()
        .zip(nearest)
        .map(|(&t, &(_, n))| triangle_normal(own, t).dot(triangle_normal(other, n)).abs())
        .sum();
    sum / nearest.len() as f64
}

/// Mean and the fraction below `tau`, summed in order (the same result for any thread count).
fn summarize(values: &[f64], tau: f64) -> (f64, f64) {
    if values.is_empty() {
        return (f64::INFINITY, 0.0);
    }
    let n = values.len() as f64;
    let mean = values.iter().sum::<f64>() / n;
    let within = values.iter().filter(|d| **d < tau).count() as f64 / n;
    (mean, within)
}

pub fn evaluate(reconstruction: &Mesh, ground_truth: &Mesh, options: &EvaluateOptions) -> Result<Report, QualityError> {
    if !(options.tau > 0.0 && options.tau.is_finite()) {
        return Err(QualityError::NonPositiveTau(options.tau));
    }
    let spacing = options.spacing.unwrap_or(options.tau / 5.0);
    let truth_samples = sample(ground_truth, spacing, options.seed);
    if truth_samples.points.is_empty() {
        return Err(QualityError::NoArea);
    }
    let seen_truth = match &options.seen_faces {
        None => None,
        Some(seen) => {
            if seen.len() != ground_truth.triangles.len() {
                return Err(QualityError::SeenFacesMismatch {
                    listed: seen.len(),
                    triangles: ground_truth.triangles.len(),
                });
            }
            let keep = |t: &u32| seen.get(*t as usize).copied().unwrap_or(false);
            let (points, triangles) = truth_samples
                .points
                .iter()
                .zip(&truth_samples.triangles)
                .filter(|(_, t)| keep(t))
                .map(|(p, t)| (*p, *t))
                .unzip();
            let samples = Samples { points, triangles };
            if samples.points.is_empty() {
                return Err(QualityError::NoArea);
            }
            Some(samples)
        }
    };
    let measured_truth = seen_truth.as_ref().unwrap_or(&truth_samples);
    let mut recon_samples = sample(reconstruction, spacing, options.seed ^ 0x5EED);
    if let Some(margin) = options.crop_margin {
        let (lo, hi) = bounds(ground_truth).ok_or(QualityError::NoTriangles)?;
        let grow = DVec3::splat((hi - lo).length() * margin);
        let (lo, hi) = (lo - grow, hi + grow);
        let keep: Vec<bool> = recon_samples
            .points
            .iter()
            .map(|p| p.cmpge(lo).all() && p.cmple(hi).all())
            .collect();
        let mut index = 0;
        recon_samples.triangles.retain(|_| {
            index += 1;
            keep[index - 1]
        });
        recon_samples.points.retain(|p| p.cmpge(lo).all() && p.cmple(hi).all());
    }
    let to_truth = distances(&recon_samples.points, ground_truth, &truth_samples);
    let to_recon = distances(&measured_truth.points, reconstruction, &recon_samples);
    let normal_consistency = 0.5
        * (normal_agreement(reconstruction, &recon_samples, ground_truth, &to_truth)
            + normal_agreement(ground_truth, measured_truth, reconstruction, &to_recon));
    let to_truth: Vec<f64> = to_truth.into_iter().map(|(d, _)| d).collect();
    let to_recon: Vec<f64> = to_recon.into_iter().map(|(d, _)| d).collect();
    let (accuracy, precision) = summarize(&to_truth, options.tau);
    let (completeness, recall) = summarize(&to_recon, options.tau);
    let f_score = if precision + recall > 0.0 {
        2.0 * precision * recall / (precision + recall)
    } else {
        0.0
    };
    let (boundary_edges, non_manifold_edges) = edge_defects(reconstruction);
    Ok(Report {
        tau: options.tau,
        accuracy,
        completeness,
        chamfer: 0.5 * (accuracy + completeness),
        precision,
        recall,
        f_score,
        normal_consistency,
        reconstruction_samples: recon_samples.points.len(),
        ground_truth_samples: measured_truth.points.len(),
        boundary_edges,
        non_manifold_edges,
        components: crate::mesh::connected_components(reconstruction),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid(n: usize, z: f32) -> Mesh {
        let mut mesh = Mesh::default();
        for j in 0..=n {
            for i in 0..=n {
                mesh.positions.push([i as f32 / n as f32, j as f32 / n as f32, z]);
            }
        }
        let v = |i: usize, j: usize| (j * (n + 1) + i) as u32;
        for j in 0..n {
            for i in 0..n {
                mesh.triangles.push([v(i, j), v(i + 1, j), v(i + 1, j + 1)]);
                mesh.triangles.push([v(i, j), v(i + 1, j + 1), v(i, j + 1)]);
            }
        }
        mesh
    }

    #[test]
    fn closest_point_matches_brute_force() {
        let (a, b, c) = (
            DVec3::new(0.0, 0.0, 0.0),
            DVec3::new(1.0, 0.2, 0.0),
            DVec3::new(0.3, 1.0, 0.4),
        );
        let mut state = 9u64;
        for _ in 0..500 {
            let p = DVec3::new(uniform(&mut state), uniform(&mut state), uniform(&mut state)) * 3.0 - 1.0;
            let exact = p.distance(closest_point_on_triangle(p, a, b, c));
            let mut best = f64::INFINITY;
            for i in 0..=200 {
                for j in 0..=(200 - i) {
                    let (u, v) = (i as f64 / 200.0, j as f64 / 200.0);
                    best = best.min(p.distance(a + (b - a) * u + (c - a) * v));
                }
            }
            assert!(exact <= best + 1e-12 && best - exact < 0.01, "{exact} vs {best}");
        }
    }

    #[test]
    fn identical_meshes_score_one_and_a_shifted_copy_scores_by_its_offset() {
        let truth = grid(10, 0.0);
        let options = EvaluateOptions {
            tau: 0.01,
            spacing: Some(0.01),
            crop_margin: None,
            seen_faces: None,
            seed: 1,
        };
        let same = evaluate(&truth, &truth, &options).unwrap();
        assert!(same.accuracy < 1e-5 && same.completeness < 1e-5, "{same:?}");
        assert_eq!((same.precision, same.recall, same.f_score), (1.0, 1.0, 1.0));
        assert_eq!(same.boundary_edges, 40);

        let shifted = evaluate(&grid(7, 0.02), &truth, &options).unwrap();
        assert!((shifted.accuracy - 0.02).abs() < 1e-6, "{shifted:?}");
        assert!((shifted.chamfer - 0.02).abs() < 1e-6);
        assert_eq!(shifted.f_score, 0.0);
        let close = evaluate(&grid(7, 0.005), &truth, &options).unwrap();
        assert_eq!(close.f_score, 1.0, "{close:?}");
    }

    #[test]
    fn a_missing_half_costs_recall_not_precision() {
        let truth = grid(10, 0.0);
        let mut half = truth.clone();
        half.triangles.truncate(100);
        let options = EvaluateOptions {
            tau: 0.01,
            spacing: Some(0.005),
            crop_margin: Some(0.1),
            seen_faces: None,
            seed: 1,
        };
        let report = evaluate(&half, &truth, &options).unwrap();
        assert_eq!(report.precision, 1.0);
        assert!((report.recall - 0.5).abs() < 0.03, "{report:?}");
        assert!((report.f_score - 2.0 / 3.0).abs() < 0.03);
    }
}
