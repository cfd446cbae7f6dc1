//! A depth map's noise, measured from its own pixels (`--depth-noise auto`, the default).
//!
//! The noise model bounds how small a sample's cube may be (`DepthNoise::radius`). A table per
//! sensor kind fits one sensor at one scale: a Kinect's table read on an object a few units
//! away, or on a scene in millimetres, gives cubes of the wrong size. So each map's noise is
//! measured where it is ingested, from the pixels alone, in a way that scales with the scene.
//!
//! Derivation. Along a row, three neighbouring depths of a smooth surface lie on a line to
//! within the surface's curvature over two pixels (negligible at a pixel's footprint), so the
//! second difference r = d(i-1) - 2 d(i) + d(i+1) is the noise's: for independent noise of
//! deviation sigma, r has deviation sqrt(6) sigma. Measured in units of the pixel spacing at
//! that depth (s = depth x pixel angle), t = |r| / s is the same number for a scene in metres,
//! millimetres or scaled units. Triples across a depth edge or an outlier pixel are left out:
//! either step |d(i) - d(i-1)|, |d(i+1) - d(i)| longer than [`STEP_LIMIT`] spacings is not one
//! surface (noise of a few spacings passes). What is left may still hold a few wild triples,
//! so each depth class takes the root mean square of t below its 90th percentile (a trimmed
//! mean, times [`TRIMMED_GAUSSIAN`] to undo the trim for Gaussian noise). That also measures a
//! quantized sensor: a Kinect's depths are a staircase of disparity steps (at 3 m, 25 mm steps
//! with runs of equal depths between), where the median of |r| is 0 but the trimmed RMS is
//! about a step over sqrt(12), the error of the staircase against the surface.
//!
//! How many deviations a sample's radius spans depends on whether the error averages out.
//! Independent noise does: a cube of radius r holds about (2 r / s)^2 of a map's pixels, and
//! every map that sees it votes, so cubes of a footprint or two already place the surface well
//! inside the noise; [`INDEPENDENT_SIGMAS`] (0.5) sigma keeps the cubes near the 1.5 footprints
//! where object captures with 0.5 % noise measured best (F at 1 % of the diagonal 0.99 to 1.0
//! against 0.91 to 0.99 at 1 sigma on the bunny and the dragon). A quantized sensor's error
//! does not: a Kinect's staircase holds one error over a run of pixels, and the same
//! disparity step repeats in the next frame, so cubes finer than the steps resolve the
//! staircase. Its signature is the share of second differences that are exactly zero (the
//! runs of equal depths): RedKitchen's frames have 50 to 72 %, noisy float depths none. A map
//! with at least [`QUANTIZED_ZERO_SHARE`] of them spans [`QUANTIZED_SIGMAS`] (2) sigma, which
//! on RedKitchen gives the Kinect table's radii within 5 % from 1 to 3 m (the measured noise
//! is half the table's, which was measured against planes and includes what a frame's own
//! pixels cannot show) and the same cubes (3.83 M against 3.85 M at 100 frames).
//!
//! Depth classes are half octaves of depth. Each class with at least [`MIN_TRIPLES`] triples
//! gives sigma at its mean depth; a least-squares fit of sigma(d) = constant + quadratic d^2
//! (both non-negative, weighted by the triples) over the classes is the map's model, recorded
//! with it in the catalog (`info` shows it). A map too sparse to measure gets no model (the
//! pixel footprint alone, eq. 4).

use std::collections::BTreeMap;

use crate::inputs::{DEFAULT_NOISE_FOOTPRINTS, DepthNoise};

/// The longest step between neighbouring depths, in pixel spacings, of a triple that counts.
pub const STEP_LIMIT: f64 = 8.0;

/// The fewest triples a depth class needs to give an estimate.
pub const MIN_TRIPLES: u64 = 200;

/// Deviations a radius spans for independent noise (module docs).
pub const INDEPENDENT_SIGMAS: f64 = 0.5;

/// Deviations a radius spans for a quantized sensor's correlated error (module docs).
pub const QUANTIZED_SIGMAS: f64 = 2.0;

/// The least share of exactly zero second differences that marks a quantized sensor.
pub const QUANTIZED_ZERO_SHARE: f64 = 0.3;

/// The share of a class's triples its trimmed mean keeps (the smallest).
const KEPT: f64 = 0.9;

/// sqrt(6): the deviation of a second difference of independent noise, over the noise's.
const SECOND_DIFFERENCE: f64 = 2.449_489_742_783_178;

/// 1 / sqrt(E[x^2 | |x| <= q] / E[x^2]) for Gaussian x and q its 90 % quantile of |x|
/// (1.6449 deviations): the trimmed root mean square is 0.789 of the whole one.
const TRIMMED_GAUSSIAN: f64 = 1.267;

/// Bins of t per octave, and the octaves below t = 2^TOP_OCTAVE that the bins span.
const BINS_PER_OCTAVE: usize = 4;
const OCTAVES: usize = 24;
const TOP_OCTAVE: i32 = 4;
/// Bin 0 holds t = 0 (and t below the lowest octave); bins 1.. the octaves, the last one up
/// to t = 2 STEP_LIMIT = 2^4.
const T_BINS: usize = 1 + BINS_PER_OCTAVE * OCTAVES;

/// Second differences of one depth class: a histogram of t, and the sum of depths.
#[derive(Clone)]
struct DepthClass {
    counts: Vec<u64>,
    depth_sum: f64,
}

/// The second differences of a map's rows, gathered row by row ([`NoiseSurvey::add_row`])
/// while another pass reads the map, then turned into a model ([`NoiseSurvey::model`]).
#[derive(Clone)]
pub struct NoiseSurvey {
    /// The angle one pixel spans (radians): the spacing at depth d is d x this.
    pixel_angle: f64,
    classes: BTreeMap<i32, DepthClass>,
    /// Triples whose second difference is exactly zero.
    zeros: u64,
}

/// floor(4 log2 x) for a positive normal x, from its bits: the exponent, and which quarter of
/// its octave the mantissa lies in (no libm call: the survey runs on every pixel).
fn quarter_octaves(x: f64) -> i64 {
    const QUARTERS: [f64; 3] = [1.189_207_115_002_721, std::f64::consts::SQRT_2, 1.681_792_830_507_429];
    let bits = x.to_bits();
    let exponent = ((bits >> 52) & 0x7ff) as i64 - 1023;
    let mantissa = f64::from_bits((bits & 0x000f_ffff_ffff_ffff) | 0x3ff0_0000_0000_0000);
    4 * exponent + QUARTERS.iter().filter(|q| mantissa >= **q).count() as i64
}

/// The bin of t > 0: bin 1 starts at t = 2^(TOP_OCTAVE - OCTAVES), a quarter octave a bin.
fn t_bin(t: f64) -> usize {
    let quarters = quarter_octaves(t) - 4 * i64::from(TOP_OCTAVE - OCTAVES as i32);
    if quarters < 0 {
        return 0;
    }
    (1 + quarters as usize).min(T_BINS - 1)
}

/// The representative t of bin `b` (its geometric centre; 0 for bin 0).
fn t_of_bin(b: usize) -> f64 {
    if b == 0 {
        return 0.0;
    }
    let octave = (b as f64 - 0.5) / BINS_PER_OCTAVE as f64;
    (octave + f64::from(TOP_OCTAVE - OCTAVES as i32)).exp2()
}

impl NoiseSurvey {
    /// An empty survey of a map whose pixels span `pixel_angle` radians.
    pub fn new(pixel_angle: f64) -> NoiseSurvey {
        NoiseSurvey {
            // A map's pixel angle is positive (its intrinsics are checked); the guard keeps a
            // spacing of zero out of the divisions below all the same.
            pixel_angle: if pixel_angle > 0.0 {
                pixel_angle
            } else {
                f64::MIN_POSITIVE
            },
            classes: BTreeMap::new(),
            zeros: 0,
        }
    }

    /// Adds a row's triples (depths; invalid ones are NaN, zero or negative). A spherical
    /// map's row wraps around, but its two seam triples are left out: a few pixels of a row
    /// change nothing.
    pub fn add_row(&mut self, row: &[f32]) {
        for window in row.windows(3) {
            let [a, b, c] = [window[0], window[1], window[2]].map(f64::from);
            if !(a.is_finite() && b.is_finite() && c.is_finite() && a > 0.0 && b > 0.0 && c > 0.0) {
                continue;
            }
            let spacing = b * self.pixel_angle;
            if (b - a).abs() > STEP_LIMIT * spacing || (c - b).abs() > STEP_LIMIT * spacing {
                continue;
            }
            let t = (a - 2.0 * b + c).abs() / spacing;
            // Half octaves of depth: floor(2 log2 b).
            let class = quarter_octaves(b).div_euclid(2) as i32;
            let entry = self.classes.entry(class).or_insert_with(|| DepthClass {
                counts: vec![0; T_BINS],
                depth_sum: 0.0,
            });
            let bin = if t > 0.0 {
                t_bin(t)
            } else {
                self.zeros += 1;
                0
            };
            if let Some(count) = entry.counts.get_mut(bin) {
                *count += 1;
            }
            entry.depth_sum += b;
        }
    }

    /// Each measurable class's (mean depth, sigma, triples).
    fn class_sigmas(&self) -> Vec<(f64, f64, u64)> {
        self.classes
            .values()
            .filter_map(|class| {
                let total: u64 = class.counts.iter().sum();
                if total < MIN_TRIPLES {
                    return None;
                }
                let keep = (KEPT * total as f64).ceil() as u64;
                let (mut kept, mut sum_t2) = (0u64, 0.0f64);
                for (b, &count) in class.counts.iter().enumerate() {
                    let take = count.min(keep - kept);
                    sum_t2 += take as f64 * t_of_bin(b).powi(2);
                    kept += take;
                    if kept >= keep {
                        break;
                    }
                }
                let sigma_t = (sum_t2 / kept.max(1) as f64).sqrt() / SECOND_DIFFERENCE * TRIMMED_GAUSSIAN;
                let depth = class.depth_sum / total as f64;
                Some((depth, sigma_t * depth * self.pixel_angle, total))
            })
            .collect()
    }

    /// Whether the map's depths look quantized: at least [`QUANTIZED_ZERO_SHARE`] of its
    /// triples have a second difference of exactly zero.
    pub fn quantized(&self) -> bool {
        let total: u64 = self
            .classes
            .values()
            .map(|class| class.counts.iter().sum::<u64>())
            .sum();
        total > 0 && self.zeros as f64 >= QUANTIZED_ZERO_SHARE * total as f64
    }

    /// The map's noise model, spanning `sigmas` deviations, or by default as many as its kind
    /// of error needs (module docs); no model where no depth class could be measured.
    pub fn model(&self, sigmas: Option<f64>) -> DepthNoise {
        let classes = self.class_sigmas();
        if classes.is_empty() {
            return DepthNoise::Footprint;
        }
        let sigmas = sigmas.unwrap_or(if self.quantized() {
            QUANTIZED_SIGMAS
        } else {
            INDEPENDENT_SIGMAS
        });
        // Weighted least squares of sigma = c + q d^2 over the classes, each weighted by its
        // share of the triples (x = d^2).
        let total: f64 = classes.iter().map(|(_, _, n)| *n as f64).sum();
        let (mut sw, mut sx, mut sxx, mut sy, mut sxy) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for &(depth, sigma, n) in &classes {
            let (w, x) = (n as f64 / total, depth * depth);
            sw += w;
            sx += w * x;
            sxx += w * x * x;
            sy += w * sigma;
            sxy += w * x * sigma;
        }
        let determinant = sw * sxx - sx * sx;
        let (mut constant, mut quadratic) = if determinant > 1e-12 * sxx * sw {
            ((sxx * sy - sx * sxy) / determinant, (sw * sxy - sx * sy) / determinant)
        } else {
            (sy / sw, 0.0)
        };
        if quadratic < 0.0 {
            (constant, quadratic) = (sy / sw, 0.0);
        } else if constant < 0.0 {
            (constant, quadratic) = (0.0, sxy / sxx);
        }
        DepthNoise::Axial {
            constant,
            quadratic,
            offset: 0.0,
            sigmas,
            footprints: DEFAULT_NOISE_FOOTPRINTS,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::random::{gaussian, uniform};

    const PIXEL_ANGLE: f64 = 1.0 / 300.0;

    /// Rows of a slanted plane seen by a 320-pixel-wide camera (depth from `near` to `far`
    /// across a row), each depth passed through `noisy`.
    fn survey_of(near: f64, far: f64, rows: usize, mut noisy: impl FnMut(f64) -> f64) -> NoiseSurvey {
        let mut survey = NoiseSurvey::new(PIXEL_ANGLE);
        for _ in 0..rows {
            // Inverse depth is linear in the pixel across a plane.
            let row: Vec<f32> = (0..320)
                .map(|i| {
                    let w = i as f64 / 319.0;
                    let depth = 1.0 / ((1.0 - w) / near + w / far);
                    noisy(depth) as f32
                })
                .collect();
            survey.add_row(&row);
        }
        survey
    }

    fn sigma_at(noise: &DepthNoise, depth: f64) -> f64 {
        noise.sigma(depth)
    }

    #[test]
    fn gaussian_noise_is_measured_within_a_tenth_at_every_scale() {
        for scale in [0.001, 1.0, 10.0, 1000.0] {
            let mut state = 7;
            let survey = survey_of(4.0 * scale, 8.0 * scale, 200, |d| {
                d + 0.03 * scale * gaussian(&mut state)
            });
            let model = survey.model(Some(1.0));
            for depth in [4.5, 6.0, 7.5] {
                let measured = sigma_at(&model, depth * scale) / scale;
                assert!(
                    (measured / 0.03 - 1.0).abs() < 0.1,
                    "scale {scale} depth {depth}: {measured}"
                );
            }
        }
    }

    #[test]
    fn noise_growing_with_depth_follows_it_and_outliers_barely_move_it() {
        let mut state = 3;
        // 0.5 % of the depth, a tenth of the pixels wild (0.2 to 2 times the depth).
        let survey = survey_of(4.0, 8.0, 300, |d| {
            if uniform(&mut state) < 0.1 {
                d * (0.2 + 1.8 * uniform(&mut state))
            } else {
                d * (1.0 + 0.005 * gaussian(&mut state))
            }
        });
        assert!(!survey.quantized());
        assert!(matches!(survey.model(None), DepthNoise::Axial { sigmas, .. } if sigmas == INDEPENDENT_SIGMAS));
        let model = survey.model(Some(1.0));
        for depth in [4.5, 6.0, 7.5] {
            let ratio = sigma_at(&model, depth) / (0.005 * depth);
            assert!((0.85..1.35).contains(&ratio), "depth {depth}: {ratio}");
        }
    }

    #[test]
    fn a_quantized_staircase_measures_its_steps_and_clean_depths_measure_nothing() {
        // 4 mm steps at about 1.2 m, the plane at a slant that crosses a step every few pixels.
        let survey = survey_of(1.1, 1.3, 200, |d| (d / 0.004).round() * 0.004);
        assert!(survey.quantized());
        assert!(matches!(survey.model(None), DepthNoise::Axial { sigmas, .. } if sigmas == QUANTIZED_SIGMAS));
        let sigma = sigma_at(&survey.model(Some(1.0)), 1.2);
        let uniform_error = 0.004 / 12f64.sqrt();
        assert!((0.5..2.0).contains(&(sigma / uniform_error)), "{sigma}");
        let clean = survey_of(4.0, 8.0, 200, |d| d).model(Some(1.0));
        // The plane's own curvature over two pixels is about 0.002 spacings.
        assert!(sigma_at(&clean, 6.0) < 1e-2 * 6.0 * PIXEL_ANGLE, "{clean:?}");
    }

    #[test]
    fn quarter_octaves_match_the_logarithm() {
        let mut state = 11;
        for _ in 0..10_000 {
            let x = (uniform(&mut state) * 60.0 - 30.0).exp2();
            let exact = (4.0 * x.log2()).floor() as i64;
            // Within rounding of the logarithm at the quarter boundaries.
            let near_boundary = ((4.0 * x.log2()) - (4.0 * x.log2()).round()).abs() < 1e-9;
            assert!(near_boundary || quarter_octaves(x) == exact, "{x}");
        }
        assert_eq!(quarter_octaves(1.0), 0);
        assert_eq!(quarter_octaves(2.0), 4);
        assert_eq!(quarter_octaves(0.5), -4);
        assert_eq!(quarter_octaves(std::f64::consts::SQRT_2 * 8.0), 14);
    }

    #[test]
    fn too_few_triples_give_no_model() {
        let mut survey = NoiseSurvey::new(PIXEL_ANGLE);
        survey.add_row(&[1.0, 1.0, 1.0, f32::NAN, 0.0, 2.0, 2.0]);
        assert_eq!(survey.model(Some(1.0)), DepthNoise::Footprint);
    }
}
