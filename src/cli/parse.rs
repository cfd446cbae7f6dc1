//! Value parsers of the command line's arguments (clap calls them; their errors are shown as
//! clap's usage errors).

use crate::format::BoundingBox;

/// A command-line value that does not parse: what is wrong with it, and what is expected.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct ArgumentError(String);

/// Comma-separated numbers.
fn numbers(text: &str) -> Result<Vec<f64>, ArgumentError> {
    text.split(',')
        .map(|t| {
            t.trim()
                .parse::<f64>()
                .map_err(|_| ArgumentError(format!("'{t}' is not a number")))
        })
        .collect()
}

/// `auto`, `none`, `kinect`, `lidar`, a sigma, or `constant,quadratic,offset`
/// (`DepthNoise::named`, `DepthNoise::from_numbers`), spanning the default number of standard
/// deviations.
pub(crate) fn parse_depth_noise(text: &str) -> Result<crate::inputs::DepthNoise, ArgumentError> {
    let text = text.trim();
    if let Some(noise) = crate::inputs::DepthNoise::named(text, None) {
        return Ok(noise);
    }
    let numbers = numbers(text)?;
    crate::inputs::DepthNoise::from_numbers(&numbers, crate::inputs::DEFAULT_NOISE_SIGMAS).map_err(ArgumentError)
}

/// A finite number of standard deviations in [0, 100] (`inputs::check_noise_sigmas`, the
/// manifest's rule too).
pub(crate) fn parse_noise_sigmas(text: &str) -> Result<f64, ArgumentError> {
    let sigmas = text
        .trim()
        .parse::<f64>()
        .map_err(|_| ArgumentError(format!("'{text}' is not a number of standard deviations")))?;
    crate::inputs::check_noise_sigmas(sigmas).map_err(ArgumentError)
}

/// Worker threads: at least 1 and at most [`MAX_THREADS_PER_CORE`] times the cores (more only
/// switch between each other: 1000 threads on 2 cores made a 0.9 s solve take 77 s).
pub(crate) fn parse_threads(text: &str) -> Result<usize, ArgumentError> {
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let most = MAX_THREADS_PER_CORE * cores;
    match text.trim().parse::<usize>() {
        Ok(n) if (1..=most).contains(&n) => Ok(n),
        _ => Err(ArgumentError(format!(
            "'{text}' threads: give 1 to {most} ({MAX_THREADS_PER_CORE} times this machine's {cores} cores)"
        ))),
    }
}

/// The most worker threads per core [`parse_threads`] takes.
pub(crate) const MAX_THREADS_PER_CORE: usize = 4;

/// A count of at least 1 (`--stride`, `gc --keep`).
pub(crate) fn parse_positive<T: std::str::FromStr + PartialOrd + From<u8>>(text: &str) -> Result<T, ArgumentError> {
    match text.trim().parse::<T>() {
        Ok(n) if n >= T::from(1) => Ok(n),
        _ => Err(ArgumentError(format!("'{text}' is not a whole number of at least 1"))),
    }
}

/// A finite, non-negative weight of the solver's energy.
pub(crate) fn parse_weight(text: &str) -> Result<f32, ArgumentError> {
    match text.trim().parse::<f32>() {
        Ok(w) if w.is_finite() && w >= 0.0 => Ok(w),
        _ => Err(ArgumentError(format!("'{text}' is not a finite weight >= 0"))),
    }
}

/// A finite, positive SSD weight (`solve --ssd-normal-weight`, `--ssd-smoothness`): with no
/// normal term f = 0 everywhere minimises the energy, and with no smoothness the cubes far from
/// samples are free.
pub(crate) fn parse_ssd_weight(text: &str) -> Result<f64, ArgumentError> {
    match text.trim().parse::<f64>() {
        Ok(w) if w.is_finite() && w > 0.0 && w <= 1e6 => Ok(w),
        _ => Err(ArgumentError(format!("'{text}' is not a weight in (0, 1e6]"))),
    }
}

/// An SSD residual target (`solve --ssd-tolerance`): a fraction of |b| in (0, 1).
pub(crate) fn parse_ssd_tolerance(text: &str) -> Result<f64, ArgumentError> {
    match text.trim().parse::<f64>() {
        Ok(t) if t > 0.0 && t < 1.0 => Ok(t),
        _ => Err(ArgumentError(format!("'{text}' is not a residual target in (0, 1)"))),
    }
}

/// A finite, non-negative fraction of the scene's extent.
pub(crate) fn parse_margin(text: &str) -> Result<f64, ArgumentError> {
    match text.trim().parse::<f64>() {
        Ok(m) if m.is_finite() && (0.0..=10.0).contains(&m) => Ok(m),
        _ => Err(ArgumentError(format!(
            "'{text}' is not a margin in [0, 10] (a fraction of the largest extent)"
        ))),
    }
}

/// The least memory budget: below it the leaf cap makes leaves of a few cubes, and every
/// stage runs many times slower instead of within the budget.
pub(crate) const LEAST_MEMORY_BUDGET: u64 = 32 << 20;

/// A size ([`parse_size`]) of at least [`LEAST_MEMORY_BUDGET`].
pub(crate) fn parse_memory_budget(text: &str) -> Result<u64, ArgumentError> {
    let size = parse_size(text)?;
    if size < LEAST_MEMORY_BUDGET {
        return Err(ArgumentError(format!(
            "a memory budget of '{text}' is below the least one octstore works in, 32MiB"
        )));
    }
    Ok(size)
}

/// `x,y,z`, finite.
pub(crate) fn parse_point(text: &str) -> Result<[f64; 3], ArgumentError> {
    let v = numbers(text)?;
    match v[..] {
        [x, y, z] if [x, y, z].iter().all(|c| c.is_finite()) => Ok([x, y, z]),
        [_, _, _] => Err(ArgumentError(format!("'{text}': a point's coordinates must be finite"))),
        _ => Err(ArgumentError("expected x,y,z".into())),
    }
}

/// `minx,miny,minz,maxx,maxy,maxz` with min < max.
pub(crate) fn parse_region(text: &str) -> Result<BoundingBox, ArgumentError> {
    let v = numbers(text)?;
    match v[..] {
        [a, b, c, d, e, f] if a < d && b < e && c < f => Ok(BoundingBox {
            min: glam::DVec3::new(a, b, c),
            max: glam::DVec3::new(d, e, f),
        }),
        _ => Err(ArgumentError(
            "expected minx,miny,minz,maxx,maxy,maxz with min < max".into(),
        )),
    }
}

/// A fraction in (0, 1].
pub(crate) fn parse_ratio(text: &str) -> Result<f32, ArgumentError> {
    match text.trim().parse::<f32>() {
        Ok(r) if r > 0.0 && r <= 1.0 => Ok(r),
        _ => Err(ArgumentError(format!("'{text}' is not a ratio in (0, 1]"))),
    }
}

/// A simplification error bound: finite and not negative.
pub(crate) fn parse_max_error(text: &str) -> Result<f32, ArgumentError> {
    match text.trim().parse::<f32>() {
        Ok(e) if e.is_finite() && e >= 0.0 => Ok(e),
        _ => Err(ArgumentError(format!(
            "'{text}' is not an error bound (a number of finest cube sides, 0 or more)"
        ))),
    }
}

/// A finite fraction in [0, 1).
/// An iteration cap of at least 1: with none, a level would be its starting guess, labelled
/// solved.
pub(crate) fn parse_iterations(text: &str) -> Result<u32, ArgumentError> {
    match text.trim().parse::<u32>() {
        Ok(n) if n >= 1 => Ok(n),
        _ => Err(ArgumentError(format!(
            "'{text}' is not an iteration count of at least 1"
        ))),
    }
}

pub(crate) fn parse_tolerance(text: &str) -> Result<f32, ArgumentError> {
    match text.trim().parse::<f32>() {
        Ok(t) if (0.0..1.0).contains(&t) => Ok(t),
        _ => Err(ArgumentError(format!(
            "'{text}' is not a tolerance in [0, 1) (0 runs every iteration)"
        ))),
    }
}

/// `minx,miny,minz,side` with side > 0.
pub(crate) fn parse_root(text: &str) -> Result<([f64; 3], f64), ArgumentError> {
    let v = numbers(text)?;
    match v[..] {
        [x, y, z, side] if side > 0.0 && side.is_finite() => Ok(([x, y, z], side)),
        _ => Err(ArgumentError("expected minx,miny,minz,side with side > 0".into())),
    }
}

/// Parses sizes like `512MiB`, `1GiB`, `1.5G`, `4096`.
pub(crate) fn parse_size(text: &str) -> Result<u64, ArgumentError> {
    let text = text.trim();
    let split = text
        .find(|c: char| !(c.is_ascii_digit() || c == '.'))
        .unwrap_or(text.len());
    let (number, unit) = text.split_at(split);
    let value: f64 = number
        .parse()
        .map_err(|_| ArgumentError(format!("'{text}' is not a size (examples: 512MiB, 1GiB, 1000000)")))?;
    let scale: f64 = match unit.trim().to_ascii_lowercase().as_str() {
        "" | "b" => 1.0,
        "k" | "kb" => 1e3,
        "kib" => 1024.0,
        "m" | "mb" => 1e6,
        "mib" => 1024.0 * 1024.0,
        "g" | "gb" => 1e9,
        "gib" => 1024.0 * 1024.0 * 1024.0,
        other => {
            return Err(ArgumentError(format!(
                "unknown size unit '{other}' (use B, KiB, MiB, GiB, KB, MB, GB)"
            )));
        }
    };
    Ok((value * scale) as u64)
}

/// `divide --overlap`: a fraction in [0, 1).
pub(crate) fn parse_overlap(text: &str) -> Result<f64, ArgumentError> {
    match text.parse::<f64>() {
        Ok(v) if (0.0..1.0).contains(&v) => Ok(v),
        _ => Err(ArgumentError(format!(
            "'{text}' is not an overlap in [0, 1) (the default is 0.1)"
        ))),
    }
}

/// A mesh file to write: `.ply` or `.obj` (any case). Any other name would get a PLY's bytes
/// under a name that promises another format.
pub(crate) fn parse_mesh_path(text: &str) -> Result<std::path::PathBuf, ArgumentError> {
    let path = std::path::PathBuf::from(text);
    match crate::inputs::extension_of(&path).as_str() {
        "ply" | "obj" | "glb" => Ok(path),
        other => Err(ArgumentError(format!(
            "'{text}': a mesh is written as .ply (binary), .glb (glTF binary) or .obj, not {}",
            if other.is_empty() {
                "a name without an extension".to_string()
            } else {
                format!(".{other}")
            }
        ))),
    }
}
