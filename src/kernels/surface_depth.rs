//! The depth a vote's distance sum measures: the map's surface exactly where the cube's centre
//! projects, bilinear in the 2 x 2 pixels of the vote's pyramid level around that point.
//!
//! The histogram bin reads the nearest pixel (paper, Algorithm 1), which is right for a robust
//! vote but quantizes the depth: on a surface seen obliquely one pixel spans several
//! millimetres of depth, so each cube's distance carried the phase of its centre against the
//! pixel grid. Neighbouring cubes read different phases in a pattern that repeats with the
//! cube grid, and the offsets that place the mesh's vertices ([`crate::stages::observed`])
//! drew ridges one cube apart on flat surfaces (RedKitchen's table top, the demo's box).
//!
//! The four pixels must all be valid and lie within the distance band of each other: across a
//! depth edge, or next to an outlier pixel, the interpolation would measure a surface that is
//! not there, and the vote then adds nothing to the distance sum (its histogram vote stands).
//! That test also keeps wild pixels out of the offsets, which were means of every vote
//! (measured on the bunny with a fifth of its pixels wild: F@0.5 % 0.896 to 0.996).
//!
//! [`surface_depth`] is the f64 reference of [`Pyramid::vote_with_distance`]; [`surface_depth_f32`]
//! is the f32 vote's, step for step `shaders/votes.wgsl`'s `surface_depth`.
//!
//! [`Pyramid::vote_with_distance`]: super::votes::Pyramid::vote_with_distance

use super::votes::DepthLevels;
use crate::inputs::DepthImage;

/// The four pixel columns and the row around level-pixel coordinates `(x, y)` (pixel centres
/// at integers): `(i0, i1, j0)`, the pixels (i0, j0), (i1, j0), (i0, j0 + 1), (i1, j0 + 1);
/// a spherical map wraps around in x. None where the square leaves the image.
fn square_f64(x: f64, y: f64, width: u32, height: u32, spherical: bool) -> Option<(u32, u32, u32)> {
    let (x0, y0) = (x.floor(), y.floor());
    let (w, h) = (f64::from(width), f64::from(height));
    let (i0, i1) = if spherical {
        let i0 = x0 - (x0 / w).floor() * w;
        (i0, if i0 + 1.0 >= w { 0.0 } else { i0 + 1.0 })
    } else {
        (x0, x0 + 1.0)
    };
    (i0 >= 0.0 && i0 < w && i1 < w && y0 >= 0.0 && y0 + 1.0 < h).then_some((i0 as u32, i1 as u32, y0 as u32))
}

/// The bilinear depth of `image` at level-pixel coordinates `(x, y)`, if the four pixels
/// around it are valid and within `band` of each other (module docs).
pub fn surface_depth(image: &DepthImage, x: f64, y: f64, spherical: bool, band: f64) -> Option<f64> {
    let (i0, i1, j0) = square_f64(x, y, image.width, image.height, spherical)?;
    let d = [
        image.get(i0, j0),
        image.get(i1, j0),
        image.get(i0, j0 + 1),
        image.get(i1, j0 + 1),
    ]
    .map(f64::from);
    bilinear(d, x - x.floor(), y - y.floor(), band)
}

/// [`surface_depth`] in f32 on a [`DepthLevels`] (the CPU pyramid or the shader's arrays), the
/// same operations in the same order as the shader.
#[inline(always)]
#[expect(
    clippy::neg_cmp_op_on_partial_ord,
    reason = "the shader's !(x <= band) test, which also rejects the NaN of infinite depths"
)]
pub fn surface_depth_f32(
    levels: &impl DepthLevels,
    level: u32,
    x: f32,
    y: f32,
    spherical: bool,
    band: f32,
) -> Option<f32> {
    let (width, height) = levels.shape(level);
    let (x0, y0) = if spherical {
        (x.floor(), y.floor())
    } else {
        // The floor of a non-negative coordinate is its truncation (a huge one saturates and
        // fails the bounds below, as its floor would); a negative one has its square outside
        // the image. This spares the libm call `floor` is on baseline x86-64, on every vote.
        if !(x >= 0.0 && y >= 0.0) {
            return None;
        }
        ((x as u32) as f32, (y as u32) as f32)
    };
    let (w, h) = (width as f32, height as f32);
    let (i0, i1) = if spherical {
        let i0 = x0 - (x0 / w).floor() * w;
        (i0, if i0 + 1.0 >= w { 0.0 } else { i0 + 1.0 })
    } else {
        (x0, x0 + 1.0)
    };
    if !(i0 >= 0.0 && i0 < w && i1 < w && y0 >= 0.0 && y0 + 1.0 < h) {
        return None;
    }
    let (i0, i1, j0) = (i0 as u32, i1 as u32, y0 as u32);
    let d = levels.square(level, i0, i1, j0);
    if !d.iter().all(|d| *d > 0.0) {
        return None;
    }
    let [a, b, c, e] = d;
    let (low, high) = (a.min(b).min(c.min(e)), a.max(b).max(c.max(e)));
    if !(high - low <= band) {
        return None;
    }
    let (fx, fy) = (x - x0, y - y0);
    Some((a * (1.0 - fx) + b * fx) * (1.0 - fy) + (c * (1.0 - fx) + e * fx) * fy)
}

/// [`truncated_distance`] in f32 of the surface depth a vote read (if any) less the cube's
/// distance `along`, with the band already known: the f32 votes' and the shader's arithmetic.
///
/// [`truncated_distance`]: super::votes::truncated_distance
#[inline(always)]
pub fn truncated_surface_distance(surface: Option<f32>, along: f32, band: f32) -> Option<f32> {
    surface
        .map(|surface| surface - along)
        .filter(|measured| *measured >= -band)
        .map(|measured| measured.min(band))
}

/// Pixels (i0, j0), (i1, j0), (i0, j1), (i1, j1) interpolated at fractions `fx`, `fy`, if all
/// are valid (positive; NaN is not) and within `band` of each other.
#[expect(
    clippy::neg_cmp_op_on_partial_ord,
    reason = "the shader's !(x <= band) test, which also rejects the NaN of infinite depths"
)]
fn bilinear(d: [f64; 4], fx: f64, fy: f64, band: f64) -> Option<f64> {
    if !d.iter().all(|d| *d > 0.0) {
        return None;
    }
    let [a, b, c, e] = d;
    let (low, high) = (a.min(b).min(c.min(e)), a.max(b).max(c.max(e)));
    if !(high - low <= band) {
        return None;
    }
    Some((a * (1.0 - fx) + b * fx) * (1.0 - fy) + (c * (1.0 - fx) + e * fx) * fy)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One image as a one-level pyramid.
    struct SingleLevel<'a>(&'a DepthImage);

    impl DepthLevels for SingleLevel<'_> {
        fn count(&self) -> u32 {
            1
        }

        fn shape(&self, _: u32) -> (u32, u32) {
            (self.0.width, self.0.height)
        }

        fn depth(&self, _: u32, i: u32, j: u32) -> f32 {
            self.0.get(i, j)
        }
    }

    fn image(width: u32, height: u32, depth: impl Fn(u32, u32) -> f32) -> DepthImage {
        DepthImage {
            width,
            height,
            depth: (0..height)
                .flat_map(|j| (0..width).map(move |i| (i, j)))
                .map(|(i, j)| depth(i, j))
                .collect(),
        }
    }

    #[test]
    fn a_tilted_plane_reads_its_depth_between_pixels() {
        // Depth linear in the pixel coordinates: bilinear interpolation is exact, where the
        // nearest pixel is off by up to half a pixel's depth step (5 mm here).
        let plane = |x: f64, y: f64| 1.5 + 0.01 * x + 0.002 * y;
        let img = image(16, 12, |i, j| plane(f64::from(i), f64::from(j)) as f32);
        for (x, y) in [(3.0, 4.0), (3.25, 4.5), (7.9, 0.1), (14.99, 10.99)] {
            let read = surface_depth(&img, x, y, false, 0.1).expect("inside, valid, smooth");
            assert!(
                (read - plane(x, y)).abs() < 1e-6,
                "({x}, {y}): {read} against {}",
                plane(x, y)
            );
            let read32 = surface_depth_f32(&SingleLevel(&img), 0, x as f32, y as f32, false, 0.1)
                .expect("the f32 twin reads it too");
            assert!((f64::from(read32) - plane(x, y)).abs() < 1e-5);
        }
    }

    #[test]
    fn edges_invalid_pixels_and_the_image_border_measure_nothing() {
        let img = image(8, 8, |i, j| match (i, j) {
            (5, 5) => f32::NAN,
            (2, _) => 3.0, // a depth edge between columns 1 and 2
            _ => 1.0,
        });
        let levels = SingleLevel(&img);
        for (x, y, why) in [
            (1.5, 3.5, "across the edge"),
            (4.5, 4.5, "an invalid pixel in the square"),
            (-0.5, 3.0, "left of the first column"),
            (7.2, 3.0, "right of the last column"),
            (3.0, 7.5, "below the last row"),
        ] {
            assert_eq!(surface_depth(&img, x, y, false, 0.5), None, "{why}");
            assert_eq!(
                surface_depth_f32(&levels, 0, x as f32, y as f32, false, 0.5),
                None,
                "{why} (f32)"
            );
        }
        // The edge is measured once the band spans it.
        assert!(surface_depth(&img, 1.5, 3.5, false, 2.5).is_some_and(|d| (d - 2.0).abs() < 1e-9));
    }

    #[test]
    fn a_spherical_map_wraps_around_in_azimuth() {
        let img = image(8, 4, |i, _| 2.0 + 0.01 * i as f32);
        // Between the last column (2.07) and the first (2.00).
        let read = surface_depth(&img, 7.5, 1.0, true, 0.5).expect("wraps");
        assert!((read - 2.035).abs() < 1e-6, "{read}");
        let read = surface_depth(&img, -0.5, 1.0, true, 0.5).expect("wraps from the left");
        assert!((read - 2.035).abs() < 1e-6, "{read}");
        let levels = SingleLevel(&img);
        let read32 = surface_depth_f32(&levels, 0, 7.5, 1.0, true, 0.5).expect("wraps (f32)");
        assert!((read32 - 2.035).abs() < 1e-5, "{read32}");
        assert_eq!(
            surface_depth(&img, 7.5, 1.0, false, 0.5),
            None,
            "a pinhole map does not wrap"
        );
    }

    /// A camera at the origin looking along +z at the plane z = 2 + 0.8 x (tilted 39 degrees),
    /// 64 x 48 pixels, and points on that plane at `(u, v)` pixel positions.
    fn tilted_plane() -> (super::super::votes::Pyramid, impl Fn(f64, f64) -> glam::DVec3) {
        let (fx, cx, cy) = (60.0, 32.0, 24.0);
        let on_plane = move |u: f64, v: f64| {
            let (qx, qy) = ((u - cx) / fx, (v - cy) / fx);
            let z = 2.0 / (1.0 - 0.8 * qx);
            glam::DVec3::new(qx * z, qy * z, z)
        };
        let img = image(64, 48, |i, j| on_plane(f64::from(i), f64::from(j)).z as f32);
        let source =
            crate::inputs::DepthMapSource::test_pinhole("plane", (64, 48), [fx, fx, cx, cy], glam::DMat4::IDENTITY);
        (super::super::votes::Pyramid::new(source, img), on_plane)
    }

    #[test]
    fn cubes_on_an_oblique_plane_measure_no_distance_wherever_they_project() {
        // One pixel spans about 2.7 cm of depth on this plane: the nearest pixel put a cube on
        // the surface up to 1.4 cm in front of or behind it, depending on where its centre fell
        // between pixel centres (the phase that drew ridges).
        let (pyramid, on_plane) = tilted_plane();
        let mut worst = 0f64;
        for k in 0..400 {
            let (u, v) = (4.0 + f64::from(k % 20) * 2.77, 4.0 + f64::from(k / 20) * 1.93);
            let (bin, measured) = pyramid
                .vote_with_distance(&glam::DMat4::IDENTITY, on_plane(u, v), 0.002, 0.2)
                .expect("the cube votes");
            assert!(bin <= 7);
            worst = worst.max(measured.expect("a smooth, valid square measures").abs());
        }
        assert!(worst < 1e-3, "a cube on the surface measured {worst} from it");
    }

    #[test]
    fn a_wild_pixel_keeps_out_of_the_distances_but_not_out_of_the_histogram() {
        let (mut pyramid, on_plane) = tilted_plane();
        if let Some(level) = pyramid.levels.first_mut()
            && let Some(pixel) = level.depth.get_mut(20 * 64 + 30)
        {
            *pixel = 0.7;
        }
        // Cubes whose nearest pixel is a good one, but whose 2 x 2 square holds the wild pixel.
        for (u, v) in [(29.4, 19.4), (30.6, 19.4), (29.4, 20.6)] {
            let vote = pyramid.vote_with_distance(&glam::DMat4::IDENTITY, on_plane(u, v), 0.002, 0.2);
            assert!(matches!(vote, Some((_, None))), "({u}, {v}): {vote:?}");
        }
        let away = pyramid.vote_with_distance(&glam::DMat4::IDENTITY, on_plane(33.5, 20.5), 0.002, 0.2);
        assert!(matches!(away, Some((_, Some(d))) if d.abs() < 1e-3), "{away:?}");
    }
}
