//! Depth image files: 16-bit PNG, PFM and NPY readers, and a PFM writer for tools and tests.

use std::fs::File;
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::Path;

use super::depth_map::{DepthImage, InputError, bad};

fn io_error(path: &Path) -> impl Fn(std::io::Error) -> InputError + '_ {
    move |source| InputError::Io {
        file: path.to_path_buf(),
        source,
    }
}

/// Up to `limit` bytes from the start of the file: enough for any header.
fn read_head(path: &Path, limit: u64) -> Result<Vec<u8>, InputError> {
    let mut head = Vec::new();
    File::open(path)
        .and_then(|file| file.take(limit).read_to_end(&mut head))
        .map_err(io_error(path))?;
    Ok(head)
}

/// Where the float32 depths of a PFM, NPY or COLMAP file lie, from its header.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FloatLayout {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Offset of the first float.
    pub data_start: u64,
    /// Byte order of the floats.
    pub little_endian: bool,
    /// Rows stored from the bottom row up (PFM).
    pub bottom_up: bool,
}

impl FloatLayout {
    /// Checks that the file holds every float the header announces; `what` names the format.
    pub(super) fn check_length(self, path: &Path, what: &str) -> Result<FloatLayout, InputError> {
        let count = u64::from(self.width) * u64::from(self.height);
        let length = std::fs::metadata(path).map_err(io_error(path))?.len();
        let needed = count
            .checked_mul(4)
            .and_then(|bytes| bytes.checked_add(self.data_start));
        if needed.is_none_or(|needed| length < needed) {
            return Err(bad(path, format!("truncated {what}: {count} floats expected")));
        }
        Ok(self)
    }
}

/// A float32 depth file read row by row, from the top row down; values that are not finite
/// and positive become NaN (invalid). Memory: one row.
pub(super) struct FloatRows {
    file: File,
    layout: FloatLayout,
    /// The file offset the next sequential read starts at.
    position: u64,
    bytes: Vec<u8>,
}

impl FloatRows {
    pub(super) fn open(path: &Path, layout: FloatLayout) -> Result<FloatRows, InputError> {
        Ok(FloatRows {
            file: File::open(path).map_err(io_error(path))?,
            layout,
            position: 0,
            bytes: vec![0; layout.width as usize * 4],
        })
    }

    /// Row `row` (from the top) into `out` (`width` values).
    pub(super) fn read_row(&mut self, path: &Path, row: u32, out: &mut [f32]) -> Result<(), InputError> {
        let stored = if self.layout.bottom_up {
            self.layout.height - 1 - row
        } else {
            row
        };
        let offset = self.layout.data_start + u64::from(stored) * self.bytes.len() as u64;
        if offset != self.position {
            self.file.seek(SeekFrom::Start(offset)).map_err(io_error(path))?;
        }
        self.file.read_exact(&mut self.bytes).map_err(|e| {
            bad(
                path,
                format!("truncated or unreadable depth row {row} of {}: {e}", self.layout.height),
            )
        })?;
        self.position = offset + self.bytes.len() as u64;
        for (value, raw) in out.iter_mut().zip(self.bytes.chunks_exact(4)) {
            let raw = [raw[0], raw[1], raw[2], raw[3]];
            let v = if self.layout.little_endian {
                f32::from_le_bytes(raw)
            } else {
                f32::from_be_bytes(raw)
            };
            *value = if v.is_finite() && v > 0.0 { v } else { f32::NAN };
        }
        Ok(())
    }
}

/// A 16-bit grey PNG read row by row (depth = value * scale, 0 and 65535 invalid). Memory:
/// the decoder's rows, except for interlaced files, whose passes are decoded whole first.
pub(super) struct PngRows {
    reader: png::Reader<BufReader<File>>,
    scale: f64,
    width: u32,
    height: u32,
    /// The whole image's raw big-endian samples, for interlaced files.
    whole: Option<Vec<u8>>,
}

fn png_error(path: &Path) -> impl Fn(png::DecodingError) -> InputError + '_ {
    move |e| bad(path, format!("unreadable or truncated PNG: {e}"))
}

impl PngRows {
    /// Opens the PNG at `path`. An interlaced one is decoded whole here (its rows come in
    /// seven passes); `streaming` callers read a map too large for their memory a row at a
    /// time, and such a file is refused for them, naming what its decode would take.
    pub(super) fn open(path: &Path, scale: f64, streaming: bool) -> Result<PngRows, InputError> {
        let file = File::open(path).map_err(io_error(path))?;
        let mut reader = png::Decoder::new(BufReader::new(file))
            .read_info()
            .map_err(png_error(path))?;
        let info = reader.info();
        let (width, height, interlaced) = (info.width, info.height, info.interlaced);
        if info.color_type != png::ColorType::Grayscale || info.bit_depth != png::BitDepth::Sixteen {
            return Err(bad(
                path,
                format!(
                    "expected a 16-bit grey PNG, found {:?} with {} bits per sample",
                    info.color_type, info.bit_depth as u8
                ),
            ));
        }
        let whole = if interlaced {
            let size = reader
                .output_buffer_size()
                .ok_or_else(|| bad(path, "PNG too large to decode"))?;
            if streaming {
                return Err(bad(
                    path,
                    format!(
                        "an interlaced {width}x{height} PNG is decoded whole ({:.0} MB), more than the memory budget leaves for one depth map; save it without interlacing (for example `convert IN -interlace none OUT`), or give a larger --memory-budget",
                        size as f64 / 1e6
                    ),
                ));
            }
            let mut buffer = vec![0; size];
            reader.next_frame(&mut buffer).map_err(png_error(path))?;
            Some(buffer)
        } else {
            None
        };
        Ok(PngRows {
            reader,
            scale,
            width,
            height,
            whole,
        })
    }

    /// The next row (rows come in order from the top) into `out` (`width` values).
    pub(super) fn read_row(&mut self, path: &Path, row: u32, out: &mut [f32]) -> Result<(), InputError> {
        let row_bytes = self.width as usize * 2;
        let raw = match &self.whole {
            Some(whole) => whole
                .get(row as usize * row_bytes..(row as usize + 1) * row_bytes)
                .ok_or_else(|| bad(path, format!("PNG has no row {row}")))?,
            None => self
                .reader
                .next_row()
                .map_err(png_error(path))?
                .ok_or_else(|| bad(path, format!("truncated PNG: row {row} of {} missing", self.height)))?
                .data(),
        };
        for (value, sample) in out.iter_mut().zip(raw.chunks_exact(2)) {
            let v = u16::from_be_bytes([sample[0], sample[1]]);
            *value = if v == 0 || v == u16::MAX {
                f32::NAN
            } else {
                (f64::from(v) * self.scale) as f32
            };
        }
        Ok(())
    }

    pub(super) fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }
}

/// A whole image from a row reader.
fn collect_rows(
    width: u32,
    height: u32,
    mut read_row: impl FnMut(u32, &mut [f32]) -> Result<(), InputError>,
) -> Result<DepthImage, InputError> {
    let mut depth = vec![f32::NAN; width as usize * height as usize];
    for (row, out) in depth.chunks_exact_mut(width.max(1) as usize).enumerate() {
        read_row(row as u32, out)?;
    }
    Ok(DepthImage { width, height, depth })
}

/// Reads a 16-bit grey PNG; depth = value * `scale`, 0 and 65535 invalid.
pub fn read_png16(path: &Path, scale: f64) -> Result<DepthImage, InputError> {
    let mut rows = PngRows::open(path, scale, false)?;
    let (width, height) = rows.size();
    collect_rows(width, height, |row, out| rows.read_row(path, row, out))
}

/// Reads a grey PFM (either endianness); rows are stored bottom to top.
pub fn read_pfm(path: &Path) -> Result<DepthImage, InputError> {
    read_floats(path, pfm_layout(path)?)
}

/// Reads a 2-D little-endian float32 NPY in C order.
pub fn read_npy(path: &Path) -> Result<DepthImage, InputError> {
    read_floats(path, npy_layout(path)?)
}

/// Reads the floats of a file laid out as `layout` says.
pub(super) fn read_floats(path: &Path, layout: FloatLayout) -> Result<DepthImage, InputError> {
    let mut rows = FloatRows::open(path, layout)?;
    collect_rows(layout.width, layout.height, |row, out| rows.read_row(path, row, out))
}

/// The layout of a grey PFM from its header: `"Pf\n<w> <h>\n<scale>\n"` (whitespace-separated
/// tokens), then float32 rows from the bottom row up; a negative scale means little-endian.
pub fn pfm_layout(path: &Path) -> Result<FloatLayout, InputError> {
    let bytes = read_head(path, 4096)?;
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
    FloatLayout {
        width,
        height,
        data_start: pos as u64,
        little_endian: scale < 0.0,
        bottom_up: true,
    }
    .check_length(path, "PFM")
}

/// The layout of a 2-D little-endian float32 NPY in C order, from its header.
pub fn npy_layout(path: &Path) -> Result<FloatLayout, InputError> {
    let prefix = read_head(path, 12)?;
    if prefix.get(..6) != Some(b"\x93NUMPY".as_slice()) {
        return Err(bad(path, "not a .npy file (bad magic)"));
    }
    let major = prefix.get(6).copied().unwrap_or(0);
    let (header_len, header_start) = match major {
        1 => (
            u16::from_le_bytes([prefix.get(8).copied().unwrap_or(0), prefix.get(9).copied().unwrap_or(0)]) as usize,
            10,
        ),
        2 | 3 => {
            let b = prefix.get(8..12).ok_or_else(|| bad(path, "truncated .npy header"))?;
            (u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize, 12)
        }
        v => return Err(bad(path, format!("unsupported .npy version {v}"))),
    };
    if header_len > 1 << 20 {
        return Err(bad(path, format!(".npy header of {header_len} bytes is not plausible")));
    }
    let bytes = read_head(path, (header_start + header_len) as u64)?;
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
    FloatLayout {
        width,
        height,
        data_start: (header_start + header_len) as u64,
        little_endian: true,
        bottom_up: false,
    }
    .check_length(path, ".npy")
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
