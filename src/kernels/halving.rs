//! Halving a depth image: the next coarser level of the median pyramid the votes read
//! (`kernels::votes`) and of the block maxima occlusion culling reads (`kernels::occlusion`).

use crate::inputs::DepthImage;

/// The next coarser level of `last`: each block of 2 x 2 pixels (fewer at an odd edge, the
/// missing ones NaN) reduced to one by `reduce`.
pub fn halve(last: &DepthImage, reduce: impl Fn([f32; 4]) -> f32) -> DepthImage {
    halve_finite_first(last, &reduce, &reduce)
}

/// [`halve`], with `fast` a branch-free form of `reduce` for blocks of four finite pixels.
/// Along whole rows, `fast` reduces every block first, a loop the compiler vectorizes; then
/// each block with a pixel that is not finite, or whose fast value is not a normal number,
/// is reduced again by `reduce`. So the level is `halve`'s wherever `fast` agrees with
/// `reduce` on four finite pixels and a normal result (each caller's pair is tested so).
/// RedKitchen's histogram step spent a tenth of its time halving (pyramids and occlusion
/// maxima, every map once per group of leaves), branching per block on its pixels.
pub fn halve_finite_first(
    last: &DepthImage,
    fast: impl Fn([f32; 4]) -> f32,
    reduce: impl Fn([f32; 4]) -> f32,
) -> DepthImage {
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
                let blocks = || {
                    top_pairs
                        .iter()
                        .zip(bottom_pairs)
                        .map(|(t, b)| [t[0], t[1], b[0], b[1]])
                };
                let start = depth.len();
                depth.extend(blocks().map(&fast));
                let row = depth.get_mut(start..).unwrap_or_default();
                for (value, block) in row.iter_mut().zip(blocks()) {
                    if !(is_normal(*value) && block.iter().fold(true, |all, v| all & is_finite(*v))) {
                        *value = reduce(block);
                    }
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

/// `f32::is_normal` on the exponent bits alone: the std method classifies the number with a
/// branch per category, and the halving checks every block's value (about a tenth of the
/// pyramid's time on RedKitchen).
fn is_normal(value: f32) -> bool {
    let exponent = value.to_bits() & 0x7f80_0000;
    exponent != 0 && exponent != 0x7f80_0000
}

/// `f32::is_finite` on the bits, without a branch: the exponent is not all ones.
fn is_finite(value: f32) -> bool {
    value.to_bits() & 0x7f80_0000 != 0x7f80_0000
}

/// [`median_of_valid`] of four finite values whose median is a normal number, without
/// branches: the middle two are the larger of the pairs' minima and the smaller of their
/// maxima, averaged in f32. The f64 average rounds once to f32, and so does this one: the
/// f32 sum of the middle two rounds once, and halving a normal number is exact. (A sum that
/// f64 holds only rounded has addends 2^29 apart, too far for that rounding to meet an f32
/// midpoint.)
pub fn median_of_finite([a, b, c, d]: [f32; 4]) -> f32 {
    let (low, high) = (a.min(b).max(c.min(d)), a.max(b).min(c.max(d)));
    (low + high) * 0.5
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
    fn the_fast_median_is_the_exact_one_wherever_halving_keeps_it() {
        // Depths of every scale and sign, ties, zeros, invalid pixels and infinities, and
        // pairs far apart in exponent: the pyramid's fast path against the exact median.
        let mut seed = 11u64;
        let mut uniform = move || crate::kernels::random::uniform(&mut seed);
        let (width, height) = (61u32, 40u32);
        for round in 0..40 {
            let depth = (0..width * height)
                .map(|_| {
                    let pick = uniform();
                    let magnitude = (2f64.powf(uniform() * 80.0 - 40.0)) as f32;
                    match round % 4 {
                        0 if pick < 0.05 => f32::NAN,
                        1 if pick < 0.02 => f32::INFINITY,
                        2 if pick < 0.3 => 1.5,
                        3 if pick < 0.05 => 0.0,
                        3 if pick < 0.1 => 1e-39,
                        _ if pick < 0.1 => -magnitude,
                        _ => magnitude,
                    }
                })
                .collect();
            let image = DepthImage { width, height, depth };
            let exact = halve(&image, median_of_valid);
            let fast = halve_finite_first(&image, median_of_finite, median_of_valid);
            let bits = |level: &DepthImage| level.depth.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&fast), bits(&exact), "round {round}");
        }
        // Where the f32 sum overflows, the fast value is infinite and the exact median is kept.
        let image = DepthImage {
            width: 2,
            height: 2,
            depth: vec![3e38, 3e38, 3e38, 3e38],
        };
        assert_eq!(median_of_finite([3e38; 4]), f32::INFINITY);
        assert_eq!(
            halve_finite_first(&image, median_of_finite, median_of_valid).depth,
            vec![3e38]
        );
    }

    #[test]
    fn the_bit_tests_are_the_std_ones() {
        let mut seed = 23u64;
        let mut bits = move || (crate::kernels::random::uniform(&mut seed) * 4_294_967_296.0) as u32;
        let edges = [
            0.0,
            -0.0,
            1e-45,
            -1e-45,
            f32::MIN_POSITIVE,
            -f32::MIN_POSITIVE,
            f32::MIN_POSITIVE * 0.5,
            1.0,
            f32::MAX,
            f32::MIN,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            -f32::NAN,
        ];
        for value in edges.into_iter().chain((0..100_000).map(|_| f32::from_bits(bits()))) {
            assert_eq!(is_normal(value), value.is_normal(), "{value:e}");
            assert_eq!(is_finite(value), value.is_finite(), "{value:e}");
        }
    }

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
