//! Empty background: the invalid pixels of a map that sees its content against nothing.
//!
//! An invalid pixel usually means "no measurement" (a Kinect's dropouts on black or shiny
//! surfaces, a margin where depth and colour were not registered), and votes nothing. But when
//! a capture looks at an object in empty space (a statue on a turntable with the background
//! masked, a synthetic render, a scanner with a short range), the pixels around the object are
//! invalid because their rays met nothing: they are evidence of free space along the whole
//! ray, the visual hull's evidence. Without it the space beside a silhouette has no data term,
//! and at coarse pyramid levels a pixel across the silhouette takes the object's depth (the
//! median of its valid depths), so cubes beside the object vote a surface where there is none:
//! the reconstruction grows flaps and shards around the object.
//!
//! The rule, decided per map from its pixels alone (so every stage and every thread count
//! sees the same): a pinhole map whose border is at least [`BACKGROUND_BORDER_SHARE`] invalid
//! sees its content against background, and its invalid pixels connected to the border
//! through invalid pixels (4-neighbours) are background. They read as the depth
//! [`BACKGROUND_DEPTH`], farther than anything, so a cube in front of them votes free space
//! (bin 7) and a coarse pyramid pixel that is half background or more is background (the
//! median of its 2 x 2 pixels). Invalid islands inside the content stay unknown. RedKitchen's
//! frames have 23 to 63 % of their border invalid (the registration margin), so a room's
//! dropouts never become free space; an object seen whole has 90 to 100 %.

use crate::inputs::{DepthImage, Projection};

/// The least share of a map's border pixels that must be invalid for its invalid pixels
/// touching the border to count as empty background.
pub const BACKGROUND_BORDER_SHARE: f64 = 0.75;

/// The depth a background pixel reads as: farther than any scene, finite in f32 so that the
/// pyramid's means of two and the bilinear surface reads stay finite (f32::MAX would overflow
/// when two are added).
pub const BACKGROUND_DEPTH: f32 = 1.0e30;

/// Whether a depth is valid (a measurement or background); NaN, zero, negative and infinite
/// depths are not.
fn is_valid(depth: f32) -> bool {
    depth.is_finite() && depth > 0.0
}

/// The share of `image`'s border pixels (each counted once) that are invalid.
pub fn invalid_border_share(image: &DepthImage) -> f64 {
    let mut border = BorderCount::default();
    if image.width > 0 {
        for (j, row) in image.depth.chunks(image.width as usize).enumerate() {
            border.add_row(row, j as u32, image.height);
        }
    }
    border.invalid_share()
}

/// The border pixels of a map read row by row, and how many of them are invalid: what
/// [`invalid_border_share`] counts, for a reader that holds one row at a time.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct BorderCount {
    /// Border pixels seen, each counted once.
    pub pixels: u64,
    /// Those that are invalid.
    pub invalid: u64,
}

impl BorderCount {
    /// Counts row `j` of a map `height` rows tall: all of it on the first and last row, its
    /// two ends (one if it is a single pixel wide) on the others.
    pub fn add_row(&mut self, row: &[f32], j: u32, height: u32) {
        let mut count = |depth: f32| {
            self.pixels += 1;
            self.invalid += u64::from(!is_valid(depth));
        };
        if j == 0 || j + 1 == height {
            row.iter().copied().for_each(count);
        } else if let Some((first, rest)) = row.split_first() {
            count(*first);
            if let Some(last) = rest.last() {
                count(*last);
            }
        }
    }

    /// The invalid share, 0 for a map without pixels.
    pub fn invalid_share(&self) -> f64 {
        if self.pixels == 0 {
            0.0
        } else {
            self.invalid as f64 / self.pixels as f64
        }
    }
}

/// Marks `image`'s empty background as [`BACKGROUND_DEPTH`] when the map sees its content
/// against background (module docs); returns the number of pixels marked. Spherical maps see
/// all around and have no border: they are left as they are.
pub fn mark_background(image: &mut DepthImage, projection: &Projection) -> u64 {
    if matches!(projection, Projection::Spherical) || invalid_border_share(image) < BACKGROUND_BORDER_SHARE {
        return 0;
    }
    let (width, height) = (image.width as usize, image.height as usize);
    let mut stack: Vec<usize> = Vec::new();
    let mut marked = 0u64;
    // Marking a pixel when it is pushed keeps it from being pushed twice.
    let mut visit = |index: usize, depth: &mut [f32], stack: &mut Vec<usize>| {
        if let Some(d) = depth.get_mut(index)
            && !is_valid(*d)
        {
            *d = BACKGROUND_DEPTH;
            marked += 1;
            stack.push(index);
        }
    };
    for i in 0..width {
        visit(i, &mut image.depth, &mut stack);
        visit((height - 1) * width + i, &mut image.depth, &mut stack);
    }
    for j in 0..height {
        visit(j * width, &mut image.depth, &mut stack);
        visit(j * width + width - 1, &mut image.depth, &mut stack);
    }
    while let Some(index) = stack.pop() {
        let (i, j) = (index % width, index / width);
        if i > 0 {
            visit(index - 1, &mut image.depth, &mut stack);
        }
        if i + 1 < width {
            visit(index + 1, &mut image.depth, &mut stack);
        }
        if j > 0 {
            visit(index - width, &mut image.depth, &mut stack);
        }
        if j + 1 < height {
            visit(index + width, &mut image.depth, &mut stack);
        }
    }
    marked
}

#[cfg(test)]
mod tests {
    use super::*;

    const PINHOLE: Projection = Projection::Pinhole {
        fx: 10.0,
        fy: 10.0,
        cx: 4.0,
        cy: 4.0,
    };

    /// A 9 x 9 map: a valid 5 x 5 square in the middle with an invalid pixel at its centre,
    /// everything around it invalid (NaN and 0 alike).
    fn object() -> DepthImage {
        let mut depth = vec![f32::NAN; 81];
        for j in 2..7 {
            for i in 2..7 {
                depth[j * 9 + i] = 2.0;
            }
        }
        depth[4 * 9 + 4] = 0.0;
        depth[0] = 0.0;
        DepthImage {
            width: 9,
            height: 9,
            depth,
        }
    }

    #[test]
    fn an_object_against_nothing_gets_background_and_keeps_its_holes() {
        let mut image = object();
        assert_eq!(invalid_border_share(&image), 1.0);
        let marked = mark_background(&mut image, &PINHOLE);
        assert_eq!(marked, 81 - 25);
        assert_eq!(image.get(0, 0), BACKGROUND_DEPTH);
        assert_eq!(image.get(8, 3), BACKGROUND_DEPTH);
        assert_eq!(image.get(3, 3), 2.0);
        // The hole inside the object is not connected to the border: unknown, not free.
        assert_eq!(image.get(4, 4), 0.0);
    }

    #[test]
    fn a_mostly_valid_border_means_dropouts_not_background() {
        let mut image = object();
        // Three of the border's 32 pixels invalid: a room's margin, not a background.
        image.depth.iter_mut().for_each(|d| *d = 3.0);
        for index in [0, 1, 2] {
            image.depth[index] = f32::NAN;
        }
        assert!((invalid_border_share(&image) - 3.0 / 32.0).abs() < 1e-12);
        assert_eq!(mark_background(&mut image, &PINHOLE), 0);
        assert!(image.get(0, 0).is_nan());
        // Just under the share: 23 of 32 invalid.
        let mut image = object();
        for (index, d) in image.depth.iter_mut().enumerate() {
            let (i, j) = (index % 9, index / 9);
            let on_border = i == 0 || j == 0 || i == 8 || j == 8;
            if on_border && index < 9 * 5 {
                *d = 1.0;
            }
        }
        let share = invalid_border_share(&image);
        assert!(share < BACKGROUND_BORDER_SHARE, "{share}");
        assert_eq!(mark_background(&mut image, &PINHOLE), 0);
        assert_eq!(mark_background(&mut object(), &Projection::Spherical), 0);
    }

    #[test]
    fn background_pyramid_pixels_follow_the_majority() {
        let mut image = object();
        mark_background(&mut image, &PINHOLE);
        let source = crate::inputs::DepthMapSource::test_pinhole(
            "map.pfm",
            (9, 9),
            [10.0, 10.0, 4.0, 4.0],
            glam::DMat4::IDENTITY,
        );
        let pyramid = super::super::votes::Pyramid::new(source, image);
        let level = &pyramid.levels[1];
        // Level 1 pixel (0, 0) covers four background pixels; (1, 1) covers pixels 2..4 of
        // rows 2..4, all object.
        assert_eq!(level.get(0, 0), BACKGROUND_DEPTH);
        assert_eq!(level.get(1, 1), 2.0);
        // A cube in front of background votes free space (bin 7).
        let camera = glam::DMat4::IDENTITY;
        let bin = pyramid.vote(&camera, glam::DVec3::new(-0.35, -0.35, 1.0), 0.001);
        assert_eq!(bin, Some(7));
    }
}
