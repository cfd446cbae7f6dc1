//! Halving a depth image: the next coarser level of the median pyramid the votes read
//! (`kernels::votes`) and of the block maxima occlusion culling reads (`kernels::occlusion`).

use crate::inputs::DepthImage;

/// The next coarser level of `last`: each block of 2 x 2 pixels (fewer at an odd edge, the
/// missing ones NaN) reduced to one by `reduce`.
pub fn halve(last: &DepthImage, reduce: impl Fn([f32; 4]) -> f32) -> DepthImage {
    let (w, h) = (last.width.div_ceil(2), last.height.div_ceil(2));
    let width = last.width as usize;
    let mut depth = Vec::with_capacity((w * h) as usize);
    let row = |j: u32| (j < last.height).then(|| last.depth.get(j as usize * width..(j as usize + 1) * width));
    for j in 0..h {
        match (row(2 * j), row(2 * j + 1)) {
            // Whole rows (all but an odd image's last): pairs of pixels side by side, without
            // a bounds test per pixel (the pyramid and the occlusion maxima halve every map).
            (Some(Some(top)), Some(Some(bottom))) => {
                let ((top_pairs, top_odd), (bottom_pairs, bottom_odd)) =
                    (top.as_chunks::<2>(), bottom.as_chunks::<2>());
                for (t, b) in top_pairs.iter().zip(bottom_pairs) {
                    depth.push(reduce([t[0], t[1], b[0], b[1]]));
                }
                if let (Some(t), Some(b)) = (top_odd.first(), bottom_odd.first()) {
                    depth.push(reduce([*t, f32::NAN, *b, f32::NAN]));
                }
            }
            _ => {
                for i in 0..w {
                    depth.push(reduce([
                        last.get(2 * i, 2 * j),
                        last.get(2 * i + 1, 2 * j),
                        last.get(2 * i, 2 * j + 1),
                        last.get(2 * i + 1, 2 * j + 1),
                    ]));
                }
            }
        }
    }
    DepthImage {
        width: w,
        height: h,
        depth,
    }
}

/// The median of the finite values among four, NaN when none is finite.
pub fn median_of_valid(values: [f32; 4]) -> f32 {
    if values.iter().all(|v| v.is_finite()) {
        // The common case, without a sort: the middle two of four are the larger of the two
        // pairs' minima and the smaller of their maxima (the same two values a sort finds).
        let [a, b, c, d] = values;
        let (low, high) = (a.min(b).max(c.min(d)), a.max(b).min(c.max(d)));
        return ((f64::from(low) + f64::from(high)) * 0.5) as f32;
    }
    let mut valid = [0f32; 4];
    let mut n = 0;
    for v in values {
        if v.is_finite()
            && let Some(slot) = valid.get_mut(n)
        {
            *slot = v;
            n += 1;
        }
    }
    let valid = valid.get_mut(..n).unwrap_or_default();
    valid.sort_unstable_by(f32::total_cmp);
    match *valid {
        [] => f32::NAN,
        [a] => a,
        [a, b] => ((f64::from(a) + f64::from(b)) * 0.5) as f32,
        [_, b, _] => b,
        [_, b, c, _] => ((f64::from(b) + f64::from(c)) * 0.5) as f32,
        _ => f32::NAN,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn halving_by_rows_reads_the_pixels_a_lookup_per_pixel_reads() {
        // Odd and even sizes, a one-pixel image, and NaN (invalid) pixels.
        for (width, height) in [(6, 4), (7, 5), (1, 1), (2, 3), (5, 1)] {
            let depth = (0..width * height)
                .map(|k| if k % 5 == 3 { f32::NAN } else { k as f32 * 0.25 })
                .collect();
            let image = DepthImage { width, height, depth };
            let by_rows = halve(&image, |v| v[0] + 10.0 * v[1] + 100.0 * v[2] + 1000.0 * v[3]);
            let (w, h) = (width.div_ceil(2), height.div_ceil(2));
            assert_eq!((by_rows.width, by_rows.height), (w, h));
            for j in 0..h {
                for i in 0..w {
                    let v = [
                        (2 * i, 2 * j),
                        (2 * i + 1, 2 * j),
                        (2 * i, 2 * j + 1),
                        (2 * i + 1, 2 * j + 1),
                    ]
                    .map(|(x, y)| image.get(x, y));
                    let expected = v[0] + 10.0 * v[1] + 100.0 * v[2] + 1000.0 * v[3];
                    assert_eq!(
                        by_rows.get(i, j).to_bits(),
                        expected.to_bits(),
                        "{width}x{height} at ({i}, {j})"
                    );
                }
            }
        }
    }
}
