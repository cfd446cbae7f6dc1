//! Back-projection, root sizing, normals and the noise model of `ingest`.

use super::*;
use crate::inputs::DepthImage;

/// The root-sizing sample of an image in memory.
fn sample_of(source: &DepthMapSource, image: &DepthImage, count: usize) -> Vec<DVec3> {
    bounds_sample(
        SampleStream::new(source, Box::new(ImageRows::new(image))).unwrap(),
        count,
    )
    .unwrap()
}

/// Every sample of a `w` x `h` image of depths.
fn samples_of_depths(source: &DepthMapSource, (w, h): (u32, u32), depth: Vec<f32>) -> Samples {
    back_project(
        source,
        &DepthImage {
            width: w,
            height: h,
            depth,
        },
    )
    .unwrap()
}

fn camera(width: u32, height: u32) -> DepthMapSource {
    let (cx, cy) = (f64::from(width) / 2.0, f64::from(height) / 2.0);
    DepthMapSource::test_pinhole(
        "plane.pfm",
        (width, height),
        [100.0, 100.0, cx, cy],
        glam::DMat4::IDENTITY,
    )
}

/// The samples of every third (and every seventh) row are exactly the full stream's samples on
/// those rows (point, radius and spike flag), although the other rows are not back-projected;
/// the image has invalid pixels, a depth edge and spikes.
#[test]
fn samples_on_strided_rows_equal_the_full_streams() {
    // 25 rows: the last (24) is sampled at a step of 7.
    let (w, h) = (23u32, 25u32);
    let source = camera(w, h);
    let mut state = 11u64;
    let depth: Vec<f32> = (0..w * h)
        .map(|i| {
            let r = crate::kernels::random::uniform(&mut state);
            if r < 0.05 {
                f32::NAN
            } else if r < 0.1 {
                (0.2 + 1.8 * crate::kernels::random::uniform(&mut state)) as f32
            } else if i % w < 9 {
                1.0 + 0.01 * (i / w) as f32
            } else {
                2.5
            }
        })
        .collect();
    let image = DepthImage {
        width: w,
        height: h,
        depth,
    };
    let stream = || SampleStream::new(&source, Box::new(ImageRows::new(&image))).unwrap();
    // The camera is at the origin with the identity pose: y / z * f + cy is the pixel row.
    let mut full = Vec::new();
    stream()
        .for_each_without_normals(|s| {
            let row = (s.point.y / s.point.z * 100.0 + f64::from(h) / 2.0).round() as usize;
            full.push((row, s.point, s.radius, s.spike));
        })
        .unwrap();
    for row_step in [3usize, 7] {
        let mut strided = Vec::new();
        stream()
            .for_each_on_rows(row_step, |s| strided.push((s.point, s.radius, s.spike)))
            .unwrap();
        let expected: Vec<_> = full
            .iter()
            .filter(|(j, ..)| j % row_step == row_step / 2)
            .map(|&(_, p, r, spike)| (p, r, spike))
            .collect();
        assert!(expected.len() > 20, "row step {row_step}: {}", expected.len());
        assert_eq!(strided, expected, "row step {row_step}");
    }
}

/// A wall at depth 1 seen head-on, with one pixel in ten replaced by a depth between 0.2 and
/// 2.0 (the synthetic outlier model): the spikes would push the 99.9 % quantile of z to
/// about 1.9; without them the box ends at the wall.
#[test]
fn spikes_do_not_size_the_root() {
    let (w, h) = (64u32, 48u32);
    let source = camera(w, h);
    let mut state = 7u64;
    let depth: Vec<f32> = (0..w * h)
        .map(|_| {
            if crate::kernels::random::uniform(&mut state) < 0.1 {
                (0.2 + 1.8 * crate::kernels::random::uniform(&mut state)) as f32
            } else {
                1.0
            }
        })
        .collect();
    let image = DepthImage {
        width: w,
        height: h,
        depth,
    };
    let all = robust_bounds(&back_project(&source, &image).unwrap().points).unwrap();
    assert!(all.1.z > 1.5, "the outliers reach far behind the wall: {all:?}");
    let kept = sample_of(&source, &image, usize::MAX);
    let (lo, hi) = robust_bounds(&kept).unwrap();
    // Only spikes within the spacing band (8 footprints = 8 % of the depth at f = 100) can
    // pass, and they sit next to the wall anyway.
    assert!(
        (0.9..=1.0).contains(&lo.z) && (1.0..=1.1).contains(&hi.z),
        "{lo:?} {hi:?}"
    );
    // The wall's own extent survives: x spans about +-0.32 at depth 1.
    assert!(lo.x < -0.3 && hi.x > 0.3, "{lo:?} {hi:?}");
    assert!(kept.len() as f64 > 0.85 * f64::from(w * h), "kept {}", kept.len());
}

/// The normals of a wall slanted 40 degrees about the camera's y axis, seen by a camera
/// turned about the world's z axis: the wall's normal in world coordinates, facing the
/// camera, with pixel areas of the squared sample spacing; a depth edge does not tilt them.
#[test]
fn normals_follow_the_depth_gradient_and_face_the_camera() {
    let (w, h) = (64u32, 48u32);
    let turn = glam::DMat4::from_rotation_z(0.7);
    let source = DepthMapSource::test_pinhole("wall.pfm", (w, h), [100.0, 100.0, 32.0, 24.0], turn);
    let slope = 40f64.to_radians().tan();
    // The plane z = 1 + slope x in camera coordinates, and a step of 0.5 at column 40.
    let depth: Vec<f32> = (0..w * h)
        .map(|index| {
            let x = (f64::from(index % w) - 32.0) / 100.0;
            let step = if index % w >= 40 { 0.5 } else { 0.0 };
            (1.0 / (1.0 - slope * x) + step) as f32
        })
        .collect();
    let samples = samples_of_depths(&source, (w, h), depth);
    let expected = (turn.transform_vector3(DVec3::new(slope, 0.0, -1.0))).normalize();
    let mut checked = 0;
    for ((p, n), area) in samples.points.iter().zip(&samples.normals).zip(&samples.areas) {
        let camera = turn.inverse().transform_point3(*p);
        // Column 39 lies beside the step: its normal must come from its left neighbour.
        if (camera.x / camera.z * 100.0 + 32.0).round() <= 39.0 {
            assert!(n.dot(expected) > 0.9999, "{n:?} vs {expected:?}");
            assert!(*area > 0.0 && *area < 0.03 * 0.03);
            checked += 1;
        }
    }
    assert!(checked > 1000, "{checked}");
}

/// A wall slanted 30 degrees, its depths with Gaussian noise of 2.5 pixel footprints (a
/// Kinect at 2.5 m, the bunny suite's 1 % noise): the normal fitted to each pixel's 7 x 7
/// window stays within a few degrees of the wall's (a difference to one neighbour would
/// spread them over the whole hemisphere: its slope noise is 3.5 footprints a footprint).
#[test]
fn normals_of_noisy_depths_are_fitted_to_a_window() {
    let (w, h) = (80u32, 60u32);
    let source = camera(w, h);
    let slope = 30f64.to_radians().tan();
    let mut state = 5u64;
    let depth: Vec<f32> = (0..w * h)
        .map(|index| {
            let x = (f64::from(index % w) - 40.0) / 100.0;
            let z = 1.0 / (1.0 - slope * x);
            (z * (1.0 + 0.025 * crate::kernels::random::gaussian(&mut state))) as f32
        })
        .collect();
    let samples = samples_of_depths(&source, (w, h), depth);
    let expected = DVec3::new(slope, 0.0, -1.0).normalize();
    let angles: Vec<f64> = samples
        .normals
        .iter()
        .map(|n| n.dot(expected).clamp(-1.0, 1.0).acos().to_degrees())
        .collect();
    assert!(angles.len() as u32 > w * h * 9 / 10, "{} samples", angles.len());
    let mean = angles.iter().sum::<f64>() / angles.len() as f64;
    let wild = angles.iter().filter(|a| **a > 45.0).count();
    assert!(mean < 12.0, "mean error {mean} degrees");
    assert!(
        wild * 100 < angles.len(),
        "{wild} of {} normals off by more than 45 degrees",
        angles.len()
    );
}

/// A 360-degree scan (half a degree a pixel) of a tilted plane 2 m away, seen up to 70 degrees
/// from head-on, without noise: the fitted normals of the spherical map are the plane's,
/// facing the scanner. The inverse range is not linear in the angles, so where the window is
/// cut off to one side (at the edge of the seen part) the fit tilts by up to 2 degrees; that
/// error shrinks with the pixel's angle (a scanner's are 10 times finer).
#[test]
fn normals_of_spherical_maps_are_the_planes() {
    let (w, h) = (720u32, 360u32);
    let mut source = camera(w, h);
    source.projection = Projection::Spherical;
    let normal = DVec3::new(-1.0, 0.3, 0.2).normalize();
    let distance = 2.0;
    let depth: Vec<f32> = (0..w * h)
        .map(|index| {
            let ray = source.ray(f64::from(index % w), f64::from(index / w));
            let facing = -ray.dot(normal);
            if facing > 20f64.to_radians().sin() {
                (distance / facing) as f32
            } else {
                f32::NAN
            }
        })
        .collect();
    let samples = samples_of_depths(&source, (w, h), depth);
    assert!(samples.normals.len() > 1000, "{} samples", samples.normals.len());
    let mut errors: Vec<f64> = samples
        .normals
        .iter()
        .map(|n| n.dot(normal).clamp(-1.0, 1.0).acos().to_degrees())
        .collect();
    errors.sort_by(f64::total_cmp);
    let (median, worst) = (errors[errors.len() / 2], errors[errors.len() - 1]);
    assert!(median < 0.01 && worst < 3.0, "median {median}, worst {worst} degrees");
}

/// A wall slanted 75 degrees from head-on is no spike (except the few pixels where it
/// runs off towards grazing view), and a map of pure noise still gives a box.
#[test]
fn slanted_surfaces_and_pure_noise_still_bound_the_scene() {
    let (w, h) = (64u32, 48u32);
    let source = camera(w, h);
    let slope = 75f64.to_radians().tan();
    let depth: Vec<f32> = (0..w * h)
        .map(|index| {
            let x = (f64::from(index % w) - f64::from(w) / 2.0) / 100.0;
            (1.0 / (1.0 - slope * x)).abs() as f32
        })
        .map(|d| if d < 5.0 { d } else { f32::NAN })
        .collect();
    let image = DepthImage {
        width: w,
        height: h,
        depth,
    };
    let kept = sample_of(&source, &image, usize::MAX);
    let samples = back_project(&source, &image).unwrap().points.len();
    assert!(kept.len() * 100 >= samples * 99, "kept {} of {samples}", kept.len());

    let mut state = 3u64;
    let noise: Vec<f32> = (0..w * h)
        .map(|_| (0.2 + 1.8 * crate::kernels::random::uniform(&mut state)) as f32)
        .collect();
    let image = DepthImage {
        width: w,
        height: h,
        depth: noise,
    };
    assert!(!sample_of(&source, &image, 100).is_empty());
}

/// A wall at depths 1 to 3 (f = 100: samples 1 to 3 cm apart, footprint radii 5 to 15 mm):
/// the footprint rule keeps the half spacing; a noise model raises a radius to its floor
/// where that is larger, but to at most its footprint cap.
#[test]
fn noise_models_raise_radii_to_their_floor_within_the_cap() {
    let (w, h) = (64u32, 48u32);
    let depth: Vec<f32> = (0..w * h)
        .map(|index| 1.0 + 2.0 * (index / w) as f32 / h as f32)
        .collect();
    let image = DepthImage {
        width: w,
        height: h,
        depth,
    };
    let footprint = back_project(&camera(w, h), &image).unwrap();
    let noise = DepthNoise::Axial {
        constant: 0.0,
        quadratic: 0.01,
        offset: 1.0,
        sigmas: 2.0,
        footprints: 1.5,
    };
    let noisy = back_project(&DepthMapSource { noise, ..camera(w, h) }, &image).unwrap();
    assert_eq!(footprint.points, noisy.points);
    let (mut kept, mut raised, mut capped) = (0, 0, 0);
    for ((p, before), after) in footprint.points.iter().zip(&footprint.radii).zip(&noisy.radii) {
        let floor = 2.0 * (0.01 * (p.z - 1.0).powi(2));
        let expected = before.max(floor.min(1.5 * before));
        assert!((after - expected).abs() < 1e-12, "z {} {before} {after}", p.z);
        if floor <= *before {
            kept += 1;
        } else if floor < 1.5 * before {
            raised += 1;
        } else {
            capped += 1;
        }
    }
    // The footprint wins near the camera, the floor a little farther, the cap far away
    // (sigma grows with the square of depth, the footprint linearly).
    assert!(kept > 100 && raised > 100 && capped > 100, "{kept} {raised} {capped}");
}

/// The noise model is recorded with a depth map but is not part of its identity.
#[test]
fn the_noise_model_is_not_part_of_a_depth_maps_identity() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("plane.pfm");
    let image = DepthImage {
        width: 4,
        height: 3,
        depth: vec![1.0; 12],
    };
    crate::inputs::write_pfm(&path, &image).unwrap();
    let source = DepthMapSource { path, ..camera(4, 3) };
    let noisy = DepthMapSource {
        noise: DepthNoise::STRUCTURED_LIGHT,
        ..source.clone()
    };
    let heavier = DepthMapSource {
        weight: 2.0,
        ..source.clone()
    };
    let id = depth_map_id(&source).unwrap();
    assert_eq!(depth_map_id(&noisy).unwrap(), id);
    assert_ne!(depth_map_id(&heavier).unwrap(), id);
}
