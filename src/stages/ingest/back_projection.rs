//! Depth maps to samples, row by row (paper 4.1): a sample's radius, spike flag and normal
//! need only its 4-neighbours, so a window of three rows of camera-frame points is all the
//! back-projection holds, whatever the image's size (format-spec.md, "Ingest runs").
//!
//! The normals (`for_each`, for the SSD sums only) are fitted to a window of
//! 2 [`NORMAL_WINDOW_RADIUS`] + 1 rows of depths, which the stream reads that many rows ahead.
//!
//! A pass over a map: the exact median of its valid depths (two passes of a radix select over
//! the depths' bits, for the absurd-depth limit), then one pass that back-projects each row
//! once its lower neighbour row is read. Small maps are read into memory once and every pass
//! reads that copy; large ones are decoded again per pass (`inputs::DepthRows`). Either way
//! the samples, and their order (row-major), are the same.

use glam::{DMat3, DVec3};

use super::SampleStats;
use super::noise::NoiseSurvey;
use crate::inputs::{DepthImage, DepthMapSource, DepthRows, InputError, Projection};

/// A depth is absurd when it exceeds this multiple of the map's median depth.
const ABSURD_DEPTH_FACTOR: f32 = 1.0e4;

/// A sample with fewer than two 4-neighbours within this many pixel footprints is a spike (an
/// isolated wrong depth, or a pair of them). Surfaces seen at up to about 80 degrees from
/// head-on keep their neighbours within it; random outlier depths almost never have two.
/// Spikes do not size the root, and spikes outside the root are dropped without complaint.
const SPIKE_SPACING: f64 = 8.0;

/// A sample's normal is fitted to the depths within this many pixels of it (a window of 7 x 7):
/// sensors' depth noise is often larger than a pixel's footprint (the Kinect's at 2 m is about
/// two footprints), and the difference to one neighbour then points the normal almost anywhere,
/// while a least-squares slope over 7 x 7 pixels has 14 times less noise. The wider the window,
/// the more it rounds off creases; 3 halves the noise of 2 at 2 times the cost.
const NORMAL_WINDOW_RADIUS: usize = 3;

/// Depth rows, from the top, in as many passes as needed.
pub trait DepthRowSource {
    /// Width in pixels.
    fn width(&self) -> u32;
    /// Height in pixels.
    fn height(&self) -> u32;
    /// Starts again from the top row.
    fn rewind(&mut self) -> Result<(), InputError>;
    /// The next row into `out` (NaN where invalid); `false` after the last.
    fn next_row(&mut self, out: &mut [f32]) -> Result<bool, InputError>;
}

impl DepthRowSource for DepthRows<'_> {
    fn width(&self) -> u32 {
        DepthRows::width(self)
    }
    fn height(&self) -> u32 {
        DepthRows::height(self)
    }
    fn rewind(&mut self) -> Result<(), InputError> {
        DepthRows::rewind(self)
    }
    fn next_row(&mut self, out: &mut [f32]) -> Result<bool, InputError> {
        DepthRows::next_row(self, out)
    }
}

/// The rows of a depth image in memory.
pub struct ImageRows<I> {
    image: I,
    next: u32,
}

impl<I: std::borrow::Borrow<DepthImage>> ImageRows<I> {
    pub fn new(image: I) -> Self {
        ImageRows { image, next: 0 }
    }
}

impl<I: std::borrow::Borrow<DepthImage>> DepthRowSource for ImageRows<I> {
    fn width(&self) -> u32 {
        self.image.borrow().width
    }
    fn height(&self) -> u32 {
        self.image.borrow().height
    }
    fn rewind(&mut self) -> Result<(), InputError> {
        self.next = 0;
        Ok(())
    }
    fn next_row(&mut self, out: &mut [f32]) -> Result<bool, InputError> {
        let image = self.image.borrow();
        if self.next >= image.height {
            return Ok(false);
        }
        let width = image.width as usize;
        let start = self.next as usize * width;
        for (o, index) in out.iter_mut().zip(start..start + width) {
            *o = image.depth.get(index).copied().unwrap_or(f32::NAN);
        }
        self.next += 1;
        Ok(true)
    }
}

/// `source`'s rows: read into memory once when its depths take at most `memory` bytes, else
/// decoded again for each pass.
pub fn open_rows(source: &DepthMapSource, memory: u64) -> Result<Box<dyn DepthRowSource + '_>, InputError> {
    let bytes = u64::from(source.width) * u64::from(source.height) * 4;
    if bytes <= memory {
        Ok(Box::new(ImageRows::new(source.load()?)))
    } else {
        Ok(Box::new(DepthRows::open_streaming(source)?))
    }
}

/// One back-projected sample: its world position, radius r_x (paper 4.1: half the 3D distance
/// to the nearest valid 4-neighbour, robust at depth discontinuities, widened by the map's
/// noise model), whether it is a spike, its world-frame unit normal from the local depth
/// gradient facing the camera (zero where an axis has no valid neighbour), and the surface area
/// it stands for (the squared distance to its nearest valid 4-neighbour).
#[derive(Clone, Copy, Debug)]
pub struct Sample {
    pub point: DVec3,
    pub radius: f64,
    pub spike: bool,
    pub normal: DVec3,
    pub area: f64,
}

/// A map's median valid depth and its number of valid pixels ([`SampleStream::median`]).
pub type DepthMedian = (f32, u64);

/// A map's samples, produced row by row.
pub struct SampleStream<'r> {
    source: &'r DepthMapSource,
    rows: Box<dyn DepthRowSource + 'r>,
    median: DepthMedian,
    /// Depths beyond it are absurd.
    limit: f32,
}

impl<'r> SampleStream<'r> {
    /// Measures the median depth of `rows` (two passes) and stands ready for the samples.
    pub fn new(source: &'r DepthMapSource, mut rows: Box<dyn DepthRowSource + 'r>) -> Result<Self, InputError> {
        let median = exact_median(rows.as_mut(), |_| ())?;
        rows.rewind()?;
        Ok(SampleStream::with_median(source, rows, median))
    }

    /// As [`SampleStream::new`] on rows not yet read, whose map's [`SampleStream::median`] an
    /// earlier pass over the same map measured (root sizing reads every new map before ingest
    /// does: the median is a function of the map alone).
    pub fn with_median(source: &'r DepthMapSource, rows: Box<dyn DepthRowSource + 'r>, median: DepthMedian) -> Self {
        SampleStream {
            source,
            rows,
            median,
            limit: median.0 * ABSURD_DEPTH_FACTOR,
        }
    }

    /// The map's median valid depth and its number of valid pixels.
    pub fn median(&self) -> DepthMedian {
        self.median
    }

    /// Pixels with a valid (finite, positive) depth.
    pub fn valid_pixels(&self) -> u64 {
        self.median.1
    }

    /// Calls `each` with every sample, in row-major order, and returns the map's statistics.
    pub fn for_each(self, each: impl FnMut(&Sample)) -> Result<SampleStats, InputError> {
        self.each_sample::<true>(1, each)
    }

    /// As [`for_each`](Self::for_each), but every sample's normal is zero: passes that need
    /// only positions and spike flags skip the normals' arithmetic.
    pub fn for_each_without_normals(self, each: impl FnMut(&Sample)) -> Result<SampleStats, InputError> {
        self.each_sample::<false>(1, each)
    }

    /// As [`for_each_without_normals`](Self::for_each_without_normals), on the rows `j` with
    /// `j % row_step == row_step / 2` only: each of those samples is the one `for_each` gives
    /// at its pixel (it has the same neighbours), and only the rows beside them are
    /// back-projected. The statistics count those rows' samples only (root sizing).
    pub fn for_each_on_rows(self, row_step: usize, each: impl FnMut(&Sample)) -> Result<SampleStats, InputError> {
        self.each_sample::<false>(row_step.max(1), each)
    }

    fn each_sample<const NORMALS: bool>(
        mut self,
        row_step: usize,
        mut each: impl FnMut(&Sample),
    ) -> Result<SampleStats, InputError> {
        let (width, height) = (self.rows.width() as usize, self.rows.height() as usize);
        let mut stats = SampleStats {
            pixels: (width * height) as u64,
            invalid: (width * height) as u64 - self.median.1,
            ..SampleStats::default()
        };
        let wraps = matches!(self.source.projection, Projection::Spherical);
        let pose = self.source.pose();
        let rotation = DMat3::from_mat4(pose);
        let pixel_angle = self.source.pixel_angle();
        let mut depths = DepthRing::new(width, if NORMALS { NORMAL_WINDOW_RADIUS } else { 0 });
        let fit = NormalFit::new(self.source, NORMAL_WINDOW_RADIUS, height);
        let mut window = Window {
            rows: [vec![None; width], vec![None; width], vec![None; width]],
            vertical: [vec![None; width], vec![None; width]],
            horizontal: vec![None; width],
            wraps,
        };
        // A row's samples are handed on once the row is done: `each` reads a sample long after
        // it was written, not right after its fields' stores, which it read back as wider
        // loads that cannot be forwarded from them (a stall on every sample, a tenth of ingest).
        let mut row_samples: Vec<Sample> = Vec::with_capacity(width);
        // A sampled row needs its own camera points and its neighbours', and the steps down
        // from the row above; rows that are neither hold stale points nobody reads.
        let sampled = |j: usize| j % row_step == row_step / 2;
        let beside_sampled = |j: usize| sampled(j) || sampled(j + 1) || j.checked_sub(1).is_some_and(sampled);
        if height > 0 {
            self.camera_row(0, &mut depths, &mut stats, &mut window.rows[1])?;
        }
        for j in 0..height {
            if j + 1 < height {
                if beside_sampled(j + 1) {
                    self.camera_row(j + 1, &mut depths, &mut stats, &mut window.rows[2])?;
                } else {
                    self.read_through(j + 1, &mut depths)?;
                }
                if sampled(j) || sampled(j + 1) {
                    window.steps_down();
                }
            } else {
                window.vertical[1].fill(None);
            }
            if !sampled(j) {
                window.rows.rotate_left(1);
                window.vertical.swap(0, 1);
                continue;
            }
            window.steps_along();
            for i in 0..width {
                let Some(p) = window.rows[1].get(i).copied().flatten() else {
                    continue;
                };
                let steps = window.steps(i);
                let reach = SPIKE_SPACING * pixel_angle * p.length();
                let (mut nearest, mut close) = (f64::INFINITY, 0);
                for step in steps.iter().flatten() {
                    nearest = nearest.min(step.length);
                    close += usize::from(step.length <= reach);
                }
                if !nearest.is_finite() || nearest <= 0.0 {
                    stats.isolated += 1;
                    continue;
                }
                let along_ray = match self.source.projection {
                    Projection::Pinhole { .. } => p.z,
                    Projection::Spherical => p.length(),
                };
                let normal = if NORMALS {
                    fit.normal_direction(self.source, &depths, i, j, p)
                        .or_else(|| normal_direction(p, &steps))
                        .map_or(DVec3::ZERO, |n| (rotation * n).normalize_or_zero())
                } else {
                    DVec3::ZERO
                };
                stats.samples += 1;
                row_samples.push(Sample {
                    point: pose.transform_point3(p),
                    radius: self.source.noise.radius(nearest * 0.5, along_ray),
                    spike: close < 2,
                    normal,
                    area: nearest * nearest,
                });
            }
            row_samples.iter().for_each(&mut each);
            row_samples.clear();
            window.rows.rotate_left(1);
            // The steps down from this row are the next row's steps up.
            window.vertical.swap(0, 1);
        }
        Ok(stats)
    }

    /// Reads the rows up to row `j` and the ring's look-ahead past it (to the image's last row).
    fn read_through(&mut self, j: usize, depths: &mut DepthRing) -> Result<(), InputError> {
        let last = (j + depths.ahead).min((self.rows.height() as usize).saturating_sub(1));
        while depths.read <= last {
            let row = depths.read;
            let (depth, inverse) = depths.slot(row);
            if !self.rows.next_row(depth)? {
                return Err(crate::inputs::bad(
                    &self.source.path,
                    format!("depth image ended before row {row}"),
                ));
            }
            // Empty without a look-ahead.
            for (w, d) in inverse.iter_mut().zip(depth.iter()) {
                *w = if d.is_finite() && *d > 0.0 && *d <= self.limit {
                    1.0 / f64::from(*d)
                } else {
                    f64::NAN
                };
            }
            depths.read += 1;
        }
        Ok(())
    }

    /// Row `j`'s camera-frame points (`None` where invalid or absurd).
    fn camera_row(
        &mut self,
        j: usize,
        depths: &mut DepthRing,
        stats: &mut SampleStats,
        out: &mut [Option<DVec3>],
    ) -> Result<(), InputError> {
        self.read_through(j, depths)?;
        for (i, (d, point)) in depths.depths(j).iter().zip(out.iter_mut()).enumerate() {
            let valid = d.is_finite() && *d > 0.0;
            if valid && *d > self.limit {
                stats.absurd += 1;
            }
            *point = if valid && *d <= self.limit {
                Some(self.source.ray(i as f64, j as f64) * f64::from(*d))
            } else {
                None
            };
        }
        Ok(())
    }
}

/// The exact median (the element at index n / 2 of the sorted values) of a map's valid depths,
/// and their count: positive finite floats order as their bits, so a histogram of the upper 16
/// bits finds the median's bucket and one of the lower 16 bits within it finds the value.
/// `first_pass` sees every row of the first of its two passes.
fn exact_median(rows: &mut dyn DepthRowSource, mut first_pass: impl FnMut(&[f32])) -> Result<(f32, u64), InputError> {
    let mut row = vec![f32::NAN; rows.width() as usize];
    let mut upper = vec![0u64; 1 << 16];
    let mut valid = 0u64;
    rows.rewind()?;
    while rows.next_row(&mut row)? {
        first_pass(&row);
        for d in row.iter().filter(|d| d.is_finite() && **d > 0.0) {
            if let Some(count) = upper.get_mut((d.to_bits() >> 16) as usize) {
                *count += 1;
            }
            valid += 1;
        }
    }
    if valid == 0 {
        return Ok((0.0, 0));
    }
    let rank = valid / 2;
    let Some((bucket, before)) = select_bucket(&upper, rank) else {
        return Ok((0.0, valid));
    };
    let mut lower = vec![0u64; 1 << 16];
    rows.rewind()?;
    while rows.next_row(&mut row)? {
        for d in row.iter().filter(|d| d.is_finite() && **d > 0.0) {
            let bits = d.to_bits();
            if (bits >> 16) as usize == bucket
                && let Some(count) = lower.get_mut((bits & 0xffff) as usize)
            {
                *count += 1;
            }
        }
    }
    let Some((low, _)) = select_bucket(&lower, rank - before) else {
        return Ok((0.0, valid));
    };
    Ok((f32::from_bits(((bucket as u32) << 16) | low as u32), valid))
}

/// A map's median depth ([`SampleStream::median`]) and the second differences of its rows
/// ([`NoiseSurvey`]), in the median's two passes over `rows` (the survey rides on the first).
pub fn survey(
    source: &DepthMapSource,
    rows: &mut dyn DepthRowSource,
) -> Result<(DepthMedian, NoiseSurvey), InputError> {
    let mut noise = NoiseSurvey::new(source.pixel_angle());
    let median = exact_median(rows, |row| noise.add_row(row))?;
    Ok((median, noise))
}

/// The bucket holding the value of rank `rank` and the count before it.
fn select_bucket(histogram: &[u64], rank: u64) -> Option<(usize, u64)> {
    let mut before = 0u64;
    for (bucket, count) in histogram.iter().enumerate() {
        if before + count > rank {
            return Some((bucket, before));
        }
        before += count;
    }
    None
}

/// What [`NormalFit::normal_direction`] needs of a map, worked out once per map.
struct NormalFit {
    /// The depth gate's reach per pixel of distance, over the inverse depth: 8 footprints.
    spacing: f64,
    /// Spherical maps wrap around horizontally.
    wraps: bool,
    height: usize,
    /// The sums of 1, u, v, u u, u v and v v over a whole window of the radius.
    full_window: [f64; 6],
}

impl NormalFit {
    fn new(source: &DepthMapSource, radius: usize, height: usize) -> NormalFit {
        let side = (2 * radius + 1) as f64;
        let squares: f64 = (0..=radius).map(|u| 2.0 * (u * u) as f64).sum();
        NormalFit {
            spacing: SPIKE_SPACING * source.pixel_angle(),
            wraps: matches!(source.projection, Projection::Spherical),
            height,
            full_window: [side * side, 0.0, 0.0, side * squares, 0.0, side * squares],
        }
    }

    /// The camera-frame normal direction at pixel (i, j), whose point is `p`, from the plane
    /// fitted to the depths of its window (`NORMAL_WINDOW_RADIUS`): a least-squares fit of the
    /// inverse depth w as w0 + a du + b dv over the window's valid pixels (du, dv) whose depth
    /// is within 8 footprints a pixel of distance, plus 3 sigma of the map's noise, of the
    /// centre's (a fit across a depth edge would tilt it). A plane n . x = c holds
    /// n . ray = c w along every ray, so n solves [ray; ray_i; ray_j] n = c [w0; a; b]
    /// (`DepthMapSource::ray_derivatives`): n = w0 ray_i x ray_j + a ray_j x ray + b ray x ray_i,
    /// exact for pinhole maps (a plane's inverse depth is linear in their pixels); spherical
    /// maps' is not, and where the window is cut off to one side the fit tilts by a little
    /// (`normals_of_spherical_maps_are_the_planes`). Oriented towards the
    /// camera, not normalised ([`normal_direction`]). `None` without a look-ahead, or where the
    /// kept pixels do not span both axes.
    fn normal_direction(
        &self,
        source: &DepthMapSource,
        depths: &DepthRing,
        i: usize,
        j: usize,
        p: DVec3,
    ) -> Option<DVec3> {
        let radius = depths.ahead as isize;
        if radius == 0 {
            return None;
        }
        let centre = depths.inverses(j)?.get(i).copied().filter(|w| w.is_finite())?;
        let width = depths.depths(j).len() as isize;
        let (height, wraps) = (self.height, self.wraps);
        let per_pixel = self.spacing / centre;
        let noise = 3.0 * std::f64::consts::SQRT_2 * source.noise.sigma(1.0 / centre);
        // Sums over the kept pixels of 1, u, v, u u, u v and v v (the whole window's, less the
        // pixels left out: most windows keep all), and of y, y u and y v with y = w - centre.
        let mut design = self.full_window;
        let mut leave_out = |u: f64, v: f64| {
            for (sum, term) in design.iter_mut().zip([1.0, u, v, u * u, u * v, v * v]) {
                *sum -= term;
            }
        };
        let (mut sy, mut syu, mut syv) = (0.0, 0.0, 0.0);
        for dv in -radius..=radius {
            let v = dv as f64;
            let row = j
                .checked_add_signed(dv)
                .filter(|r| *r < height)
                .and_then(|r| depths.inverses(r));
            let (mut row_y, mut row_yu) = (0.0, 0.0);
            // |1/w - 1/centre| <= reach, without a division; NaN (invalid) is left out.
            let mut add = |du: isize, w: f64| {
                let u = du as f64;
                let reach = per_pixel * du.abs().max(dv.abs()) as f64 + noise;
                if (w - centre).abs() <= reach * w * centre {
                    row_y += w - centre;
                    row_yu += (w - centre) * u;
                } else {
                    leave_out(u, v);
                }
            };
            let first = i as isize - radius;
            // Most windows lie inside the image: their row is one slice.
            match row.and_then(|row| row.get(usize::try_from(first).ok()?..i + 1 + radius as usize)) {
                Some(window) if !wraps => (-radius..).zip(window).for_each(|(du, w)| add(du, *w)),
                _ => {
                    for du in -radius..=radius {
                        let column = if wraps {
                            (i as isize + du).rem_euclid(width)
                        } else {
                            i as isize + du
                        };
                        let w = row
                            .zip(usize::try_from(column).ok())
                            .and_then(|(row, c)| row.get(c))
                            .copied()
                            .unwrap_or(f64::NAN);
                        add(du, w);
                    }
                }
            }
            sy += row_y;
            syu += row_yu;
            syv += row_y * v;
        }
        let [n, su, sv, suu, suv, svv] = design;
        if n < 6.0 {
            return None;
        }
        let (cuu, cuv, cvv) = (suu - su * su / n, suv - su * sv / n, svv - sv * sv / n);
        let (cuy, cvy) = (syu - su * sy / n, syv - sv * sy / n);
        let det = cuu * cvv - cuv * cuv;
        if cuu < 0.5 || cvv < 0.5 || det <= 0.1 * cuu * cvv {
            return None;
        }
        let a = (cvv * cuy - cuv * cvy) / det;
        let b = (cuu * cvy - cuv * cuy) / det;
        let w0 = centre + (sy - a * su - b * sv) / n;
        let ray = source.ray(i as f64, j as f64);
        let (ray_i, ray_j) = source.ray_derivatives(i as f64, j as f64);
        let normal = w0 * ray_i.cross(ray_j) + a * ray_j.cross(ray) + b * ray.cross(ray_i);
        if !normal.is_finite() || normal == DVec3::ZERO {
            return None;
        }
        Some(if normal.dot(p) > 0.0 { -normal } else { normal })
    }
}

/// The depth rows a stream holds: its look-ahead `ahead` rows past the row being sampled, as
/// many before it, and the row being read, each row `r` in slot `r % (2 ahead + 2)`. With a
/// look-ahead, also each row's inverse depths (NaN where invalid or absurd), which a plane's
/// are linear in along a pinhole map's pixels.
struct DepthRing {
    depths: Vec<Vec<f32>>,
    inverses: Vec<Vec<f64>>,
    ahead: usize,
    /// Rows read so far: rows `read - slots ..= read - 1` are held.
    read: usize,
}

impl DepthRing {
    fn new(width: usize, ahead: usize) -> Self {
        let slots = 2 * ahead + 2;
        DepthRing {
            depths: vec![vec![f32::NAN; width]; slots],
            inverses: vec![vec![f64::NAN; if ahead > 0 { width } else { 0 }]; slots],
            ahead,
            read: 0,
        }
    }

    /// The slot of row `r`, to read it into.
    fn slot(&mut self, r: usize) -> (&mut [f32], &mut [f64]) {
        let index = r % self.depths.len();
        match (self.depths.get_mut(index), self.inverses.get_mut(index)) {
            (Some(depth), Some(inverse)) => (depth, inverse),
            _ => (&mut [], &mut []),
        }
    }

    fn held(&self, r: usize) -> bool {
        r < self.read && r + self.depths.len() >= self.read
    }

    /// Row `r`'s depths; empty if it is not held.
    fn depths(&self, r: usize) -> &[f32] {
        match self.depths.get(r % self.depths.len()) {
            Some(row) if self.held(r) => row,
            _ => &[],
        }
    }

    /// Row `r`'s inverse depths, if it is held.
    fn inverses(&self, r: usize) -> Option<&[f64]> {
        self.inverses
            .get(r % self.inverses.len())
            .filter(|_| self.held(r))
            .map(Vec::as_slice)
    }
}

/// The vector from one valid pixel's point to a neighbour's, and its length.
#[derive(Clone, Copy)]
struct Step {
    vector: DVec3,
    length: f64,
}

impl Step {
    fn between(from: Option<DVec3>, to: Option<DVec3>) -> Option<Step> {
        let vector = to? - from?;
        Some(Step {
            vector,
            length: vector.length(),
        })
    }
}

/// Three rows of camera-frame points, above (0), current (1) and below (2), and the steps
/// between neighbouring points, each computed once although two samples use it (a step's
/// length is the same from either end: negating a vector is exact).
struct Window {
    rows: [Vec<Option<DVec3>>; 3],
    /// Column by column, from row 0 to row 1 (`vertical[0]`) and from row 1 to row 2
    /// (`vertical[1]`); `None` where either point is invalid or its row is outside the image.
    vertical: [Vec<Option<Step>>; 2],
    /// From column `i` to column `i + 1` of row 1; the last column's step wraps around to
    /// column 0 for spherical maps and is `None` otherwise.
    horizontal: Vec<Option<Step>>,
    /// Spherical maps wrap around horizontally.
    wraps: bool,
}

impl Window {
    /// Steps from row 1 to row 2, once row 2 holds the next row.
    fn steps_down(&mut self) {
        let [_, current, below] = &self.rows;
        for ((step, p), q) in self.vertical[1].iter_mut().zip(current).zip(below) {
            *step = Step::between(*p, *q);
        }
    }

    /// Steps along row 1.
    fn steps_along(&mut self) {
        let row = &self.rows[1];
        for (step, pair) in self.horizontal.iter_mut().zip(row.windows(2)) {
            *step = match *pair {
                [p, q] => Step::between(p, q),
                _ => None,
            };
        }
        if let Some(last) = self.horizontal.last_mut() {
            *last = match (self.wraps, row.last(), row.first()) {
                (true, Some(p), Some(q)) => Step::between(*p, *q),
                _ => None,
            };
        }
    }

    /// Column `i`'s steps: from its left neighbour, to its right one, from the one above and
    /// to the one below (each vector points down or to the right).
    #[inline]
    fn steps(&self, i: usize) -> [Option<Step>; 4] {
        let left = match i.checked_sub(1) {
            Some(before) => self.horizontal.get(before),
            None if self.wraps => self.horizontal.last(),
            None => None,
        };
        let at = |steps: &[Option<Step>]| steps.get(i).copied().flatten();
        [
            left.copied().flatten(),
            at(&self.horizontal),
            at(&self.vertical[0]),
            at(&self.vertical[1]),
        ]
    }
}

/// The camera-frame normal direction at a point `p` from its steps [left, right, up, down]
/// ([`Window::steps`]): the cross product of the depth gradient along the row and along the
/// column, each taken towards the neighbour nearer to `p` (a difference across a depth edge
/// would tilt it), oriented towards the camera. Not normalised: the caller normalises once,
/// after turning it into the world frame (a rotation keeps its length; a square root and a
/// division per sample were a tenth of ingest). `None` when an axis has no valid neighbour or
/// the two gradients are parallel.
fn normal_direction(p: DVec3, [left, right, up, down]: &[Option<Step>; 4]) -> Option<DVec3> {
    let along = |before: &Option<Step>, after: &Option<Step>| match (before, after) {
        (Some(b), Some(a)) if a.length <= b.length => Some(a.vector),
        (Some(b), _) => Some(b.vector),
        (None, Some(a)) => Some(a.vector),
        (None, None) => None,
    };
    let n = along(left, right)?.cross(along(up, down)?);
    if n == DVec3::ZERO {
        return None;
    }
    Some(if n.dot(p) > 0.0 { -n } else { n })
}

/// Back-projected samples of one depth map, as columns.
pub struct Samples {
    pub points: Vec<DVec3>,
    pub radii: Vec<f64>,
    pub spikes: Vec<bool>,
    pub normals: Vec<DVec3>,
    pub areas: Vec<f64>,
    pub stats: SampleStats,
}

/// Every sample of a depth image in memory (tests and tools; ingest streams them).
pub fn back_project(source: &DepthMapSource, image: &DepthImage) -> Result<Samples, InputError> {
    let stream = SampleStream::new(source, Box::new(ImageRows::new(image)))?;
    let valid = stream.valid_pixels() as usize;
    let mut samples = Samples {
        points: Vec::with_capacity(valid),
        radii: Vec::with_capacity(valid),
        spikes: Vec::with_capacity(valid),
        normals: Vec::with_capacity(valid),
        areas: Vec::with_capacity(valid),
        stats: SampleStats::default(),
    };
    samples.stats = stream.for_each(|s| {
        samples.points.push(s.point);
        samples.radii.push(s.radius);
        samples.spikes.push(s.spike);
        samples.normals.push(s.normal);
        samples.areas.push(s.area);
    })?;
    Ok(samples)
}

/// About `count` of a map's samples, evenly strided over its image, for sizing the root
/// cube. Spikes are left out: a few percent of wild depths would otherwise stretch the root far
/// beyond the scene and cost every cube resolution (with `--max-depth` fixed, the finest cube
/// grows with the root); a map of nothing but spikes (pure noise) still bounds the scene
/// through all its samples. Spikes still spawn cubes and vote like any other sample inside the
/// root.
///
/// The strides are two: rows (every `sqrt(valid / count)`-th, so that only the rows beside them
/// are back-projected: for RedKitchen's 200 samples a map, about a twelfth of its rows) and
/// samples along those rows.
pub fn bounds_sample(stream: SampleStream<'_>, count: usize) -> Result<Vec<DVec3>, InputError> {
    let valid = stream.valid_pixels();
    let overall = (valid / count.max(1) as u64).max(1);
    let row_step = (overall as f64).sqrt() as u64;
    let step = (overall / row_step.max(1)).max(1);
    let (mut consistent, mut all) = (Vec::new(), Vec::new());
    let (mut seen_consistent, mut seen) = (0u64, 0u64);
    stream.for_each_on_rows(row_step as usize, |s| {
        if seen % step == 0 {
            all.push(s.point);
        }
        seen += 1;
        if !s.spike {
            if seen_consistent % step == 0 {
                consistent.push(s.point);
            }
            seen_consistent += 1;
        }
    })?;
    Ok(if consistent.is_empty() { all } else { consistent })
}

/// How many times the typical spread a map's centre may lie from the others' before
/// [`far_off_maps`] leaves it out of the root: far beyond any scene's own extent.
pub const FAR_OFF_SPREADS: f64 = 20.0;

/// The maps (indices into `per_map`, each a map's root-sizing sample) that lie far off the
/// rest: a map's centre is its per-axis median point, the scene's centre the per-axis median of
/// those, and the typical spread the larger of the median distance of the maps' centres from
/// the scene's and the median of each map's median distance from its own centre. A map whose
/// centre is more than [`FAR_OFF_SPREADS`] typical spreads from the scene's is far off: a pose
/// in other units or with a wrong translation, which would otherwise stretch the root's
/// quantiles (a third of the samples of three maps) until the scene is a few cubes. With fewer
/// than three maps there is no majority to tell which is off, and none is.
pub fn far_off_maps(per_map: &[Vec<DVec3>]) -> Vec<usize> {
    fn median(mut values: Vec<f64>) -> f64 {
        values.sort_by(f64::total_cmp);
        values.get(values.len() / 2).copied().unwrap_or(0.0)
    }
    fn median_point(points: &[DVec3]) -> DVec3 {
        let axis = |a: usize| median(points.iter().map(|p| p[a]).collect());
        DVec3::new(axis(0), axis(1), axis(2))
    }
    let centres: Vec<(usize, DVec3, f64)> = per_map
        .iter()
        .enumerate()
        .filter(|(_, points)| !points.is_empty())
        .map(|(i, points)| {
            let centre = median_point(points);
            (i, centre, median(points.iter().map(|p| p.distance(centre)).collect()))
        })
        .collect();
    if centres.len() < 3 {
        return Vec::new();
    }
    let points: Vec<DVec3> = centres.iter().map(|(_, c, _)| *c).collect();
    let scene_centre = median_point(&points);
    let spread = median(points.iter().map(|c| c.distance(scene_centre)).collect())
        .max(median(centres.iter().map(|(_, _, r)| *r).collect()));
    centres
        .iter()
        .filter(|(_, c, _)| c.distance(scene_centre) > FAR_OFF_SPREADS * spread)
        .map(|(i, _, _)| *i)
        .collect()
}

/// A box robust to stray points: per axis, the 0.1 % and 99.9 % quantiles. None without points.
pub fn robust_bounds(points: &[DVec3]) -> Option<(DVec3, DVec3)> {
    if points.is_empty() {
        return None;
    }
    let quantile = |axis: usize, q: f64| -> f64 {
        let mut v: Vec<f64> = points.iter().map(|p| p[axis]).collect();
        v.sort_by(f64::total_cmp);
        let index = ((v.len() - 1) as f64 * q).round() as usize;
        v.get(index).copied().unwrap_or(0.0)
    };
    let lo = DVec3::new(quantile(0, 0.001), quantile(1, 0.001), quantile(2, 0.001));
    let hi = DVec3::new(quantile(0, 0.999), quantile(1, 0.999), quantile(2, 0.999));
    Some((lo, hi))
}
