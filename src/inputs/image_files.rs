//! Depth image files: 16-bit PNG, PFM and NPY readers, and a PFM writer for tools and tests.

use std::path::Path;

use super::depth_map::{DepthImage, InputError, bad};

fn read_file(path: &Path) -> Result<Vec<u8>, InputError> {
    std::fs::read(path).map_err(|source| InputError::Io {
        file: path.to_path_buf(),
        source,
    })
}

/// Reads a 16-bit grey PNG; depth = value * `scale`, 0 and 65535 invalid.
pub fn read_png16(path: &Path, scale: f64) -> Result<DepthImage, InputError> {
    let bytes = read_file(path)?;
    let decoded = image::load_from_memory_with_format(&bytes, image::ImageFormat::Png)
        .map_err(|e| bad(path, format!("unreadable or truncated PNG: {e}")))?;
    let image::DynamicImage::ImageLuma16(grey) = decoded else {
        return Err(bad(
            path,
            format!("expected a 16-bit grey PNG, found {:?}", decoded.color()),
        ));
    };
    let (width, height) = grey.dimensions();
    let depth = grey
        .into_raw()
        .into_iter()
        .map(|v| {
            if v == 0 || v == u16::MAX {
                f32::NAN
            } else {
                (f64::from(v) * scale) as f32
            }
        })
        .collect();
    Ok(DepthImage { width, height, depth })
}

/// Reads a grey PFM (either endianness); rows are stored bottom to top.
pub fn read_pfm(path: &Path) -> Result<DepthImage, InputError> {
    let bytes = read_file(path)?;
    // Header: "Pf\n<w> <h>\n<scale>\n" (whitespace-separated tokens), then float32 rows from the
    // bottom row up; negative scale means little-endian.
    let mut tokens = Vec::new();
    let mut pos = 0usize;
    while tokens.len() < 4 {
        while bytes.get(pos).is_some_and(|b| b.is_ascii_whitespace()) {
            pos += 1;
        }
        let start = pos;
        while bytes.get(pos).is_some_and(|b| !b.is_ascii_whitespace()) {
            pos += 1;
        }
        if start == pos {
            return Err(bad(path, "truncated PFM header"));
        }
        tokens.push(String::from_utf8_lossy(bytes.get(start..pos).unwrap_or_default()).into_owned());
    }
    pos += 1; // the single whitespace byte after the scale
    if tokens[0] != "Pf" {
        return Err(bad(
            path,
            format!("not a grey PFM (magic '{}', expected 'Pf')", tokens[0]),
        ));
    }
    // Sizes are whole numbers: parsed as floats, "nan" passed every range check and became 0.
    let size = |t: &str, what: &str| t.parse::<u32>().map_err(|_| bad(path, format!("bad PFM {what} '{t}'")));
    let (width, height) = (size(&tokens[1], "width")?, size(&tokens[2], "height")?);
    let scale = tokens[3]
        .parse::<f64>()
        .ok()
        .filter(|s| s.is_finite() && *s != 0.0)
        .ok_or_else(|| {
            bad(
                path,
                format!("bad PFM scale '{}' (a finite, non-zero number)", tokens[3]),
            )
        })?;
    if width < 1 || height < 1 || width > 1_000_000 || height > 1_000_000 {
        return Err(bad(path, format!("PFM size {width}x{height} is not plausible")));
    }
    let count = width as usize * height as usize;
    let data = bytes
        .get(pos..pos + count * 4)
        .ok_or_else(|| bad(path, format!("truncated PFM: {count} floats expected")))?;
    let little = scale < 0.0;
    let mut depth = vec![f32::NAN; count];
    for (index, chunk) in data.chunks_exact(4).enumerate() {
        let raw = [chunk[0], chunk[1], chunk[2], chunk[3]];
        let v = if little {
            f32::from_le_bytes(raw)
        } else {
            f32::from_be_bytes(raw)
        };
        let (row_from_bottom, col) = (index / width as usize, index % width as usize);
        let row = height as usize - 1 - row_from_bottom;
        depth[row * width as usize + col] = if v.is_finite() && v > 0.0 { v } else { f32::NAN };
    }
    Ok(DepthImage { width, height, depth })
}

/// Reads a 2-D little-endian float32 NPY in C order.
pub fn read_npy(path: &Path) -> Result<DepthImage, InputError> {
    let bytes = read_file(path)?;
    if bytes.get(..6) != Some(b"\x93NUMPY".as_slice()) {
        return Err(bad(path, "not a .npy file (bad magic)"));
    }
    let major = bytes.get(6).copied().unwrap_or(0);
    let (header_len, header_start) = match major {
        1 => (
            u16::from_le_bytes([bytes.get(8).copied().unwrap_or(0), bytes.get(9).copied().unwrap_or(0)]) as usize,
            10,
        ),
        2 | 3 => {
            let b = bytes.get(8..12).ok_or_else(|| bad(path, "truncated .npy header"))?;
            (u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize, 12)
        }
        v => return Err(bad(path, format!("unsupported .npy version {v}"))),
    };
    let header = bytes
        .get(header_start..header_start + header_len)
        .map(|h| String::from_utf8_lossy(h).into_owned())
        .ok_or_else(|| bad(path, "truncated .npy header"))?;
    if !header.contains("'descr': '<f4'") {
        return Err(bad(
            path,
            format!("expected little-endian float32 ('<f4'), header: {}", header.trim()),
        ));
    }
    if header.contains("'fortran_order': True") {
        return Err(bad(path, "Fortran-order arrays are not supported; save with C order"));
    }
    let shape = header
        .split("'shape':")
        .nth(1)
        .and_then(|s| s.split(')').next())
        .map(|s| s.trim().trim_start_matches('(').to_string())
        .ok_or_else(|| bad(path, "no shape in .npy header"))?;
    let dims: Vec<u32> = shape
        .split(',')
        .filter(|t| !t.trim().is_empty())
        .map(|t| {
            t.trim()
                .parse()
                .map_err(|_| bad(path, format!("bad .npy shape '{shape}'")))
        })
        .collect::<Result<_, _>>()?;
    let [height, width] = dims[..] else {
        return Err(bad(path, format!("expected a 2-D array, shape is ({shape})")));
    };
    let count = width as usize * height as usize;
    let start = header_start + header_len;
    let data = bytes
        .get(start..start + count * 4)
        .ok_or_else(|| bad(path, format!("truncated .npy: {count} floats expected")))?;
    Ok(DepthImage {
        width,
        height,
        depth: depths_from_f32_le(data),
    })
}

/// Little-endian float32 depths; values that are not finite and positive become NaN (invalid).
pub(super) fn depths_from_f32_le(data: &[u8]) -> Vec<f32> {
    data.chunks_exact(4)
        .map(|c| {
            let v = f32::from_le_bytes([c[0], c[1], c[2], c[3]]);
            if v.is_finite() && v > 0.0 { v } else { f32::NAN }
        })
        .collect()
}

/// Writes a little-endian grey PFM (tools and tests use it to produce inputs).
pub fn write_pfm(path: &Path, image: &DepthImage) -> std::io::Result<()> {
    let mut out = format!("Pf\n{} {}\n-1.0\n", image.width, image.height).into_bytes();
    for row in (0..image.height).rev() {
        for col in 0..image.width {
            out.extend_from_slice(&image.get(col, row).to_le_bytes());
        }
    }
    std::fs::write(path, out)
}
