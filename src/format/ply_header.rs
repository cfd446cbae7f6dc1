//! The header of a PLY file (ASCII or binary, either endianness): its elements, their
//! properties and where the body starts. Mesh files (`mesh::io`) and point clouds
//! (`divide::point_clouds`) both read it; a malformed header is an error message, never a panic.

/// How a PLY body is encoded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PlyEncoding {
    /// Whitespace-separated numbers.
    Ascii,
    /// Binary, least significant byte first.
    LittleEndian,
    /// Binary, most significant byte first.
    BigEndian,
}

/// A PLY scalar type.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PlyScalar {
    /// `char` / `int8`.
    I8,
    /// `uchar` / `uint8`.
    U8,
    /// `short` / `int16`.
    I16,
    /// `ushort` / `uint16`.
    U16,
    /// `int` / `int32`.
    I32,
    /// `uint` / `uint32`.
    U32,
    /// `float` / `float32`.
    F32,
    /// `double` / `float64`.
    F64,
}

impl PlyScalar {
    /// The type named `name` in a header (both the old and the sized names).
    pub fn parse(name: &str) -> Option<PlyScalar> {
        Some(match name {
            "char" | "int8" => PlyScalar::I8,
            "uchar" | "uint8" => PlyScalar::U8,
            "short" | "int16" => PlyScalar::I16,
            "ushort" | "uint16" => PlyScalar::U16,
            "int" | "int32" => PlyScalar::I32,
            "uint" | "uint32" => PlyScalar::U32,
            "float" | "float32" => PlyScalar::F32,
            "double" | "float64" => PlyScalar::F64,
            _ => return None,
        })
    }

    /// The name octstore writes.
    pub fn name(self) -> &'static str {
        match self {
            PlyScalar::I8 => "char",
            PlyScalar::U8 => "uchar",
            PlyScalar::I16 => "short",
            PlyScalar::U16 => "ushort",
            PlyScalar::I32 => "int",
            PlyScalar::U32 => "uint",
            PlyScalar::F32 => "float",
            PlyScalar::F64 => "double",
        }
    }

    /// Bytes of one value in a binary body.
    pub fn size(self) -> usize {
        match self {
            PlyScalar::I8 | PlyScalar::U8 => 1,
            PlyScalar::I16 | PlyScalar::U16 => 2,
            PlyScalar::I32 | PlyScalar::U32 | PlyScalar::F32 => 4,
            PlyScalar::F64 => 8,
        }
    }

    /// The value of little-endian `bytes` (at least [`size`](Self::size) of them; missing
    /// bytes read as zero).
    pub fn read_le(self, bytes: &[u8]) -> f64 {
        let mut b = [0u8; 8];
        for (to, from) in b.iter_mut().zip(bytes.iter().take(self.size())) {
            *to = *from;
        }
        match self {
            PlyScalar::I8 => f64::from(b[0] as i8),
            PlyScalar::U8 => f64::from(b[0]),
            PlyScalar::I16 => f64::from(i16::from_le_bytes([b[0], b[1]])),
            PlyScalar::U16 => f64::from(u16::from_le_bytes([b[0], b[1]])),
            PlyScalar::I32 => f64::from(i32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            PlyScalar::U32 => f64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            PlyScalar::F32 => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            PlyScalar::F64 => f64::from_le_bytes(b),
        }
    }

    /// Writes `value` as this type, little-endian, into `out` (its first [`size`](Self::size)
    /// bytes). Integers saturate; `None` when the text of an ASCII body does not fit the type
    /// (a fraction in an integer property, or a value out of range).
    pub fn write_le(self, value: f64, out: &mut [u8]) -> Option<()> {
        let integer = |lo: f64, hi: f64| (value.fract() == 0.0 && (lo..=hi).contains(&value)).then_some(value);
        let bytes: ([u8; 8], usize) = match self {
            PlyScalar::I8 => (widen(&(integer(-128.0, 127.0)? as i8).to_le_bytes()), 1),
            PlyScalar::U8 => (widen(&[integer(0.0, 255.0)? as u8]), 1),
            PlyScalar::I16 => (widen(&(integer(-32768.0, 32767.0)? as i16).to_le_bytes()), 2),
            PlyScalar::U16 => (widen(&(integer(0.0, 65535.0)? as u16).to_le_bytes()), 2),
            PlyScalar::I32 => (widen(&(integer(-2147483648.0, 2147483647.0)? as i32).to_le_bytes()), 4),
            PlyScalar::U32 => (widen(&(integer(0.0, 4294967295.0)? as u32).to_le_bytes()), 4),
            PlyScalar::F32 => (widen(&(value as f32).to_le_bytes()), 4),
            PlyScalar::F64 => (value.to_le_bytes(), 8),
        };
        for (to, from) in out.iter_mut().zip(bytes.0.iter().take(bytes.1)) {
            *to = *from;
        }
        Some(())
    }
}

fn widen(bytes: &[u8]) -> [u8; 8] {
    let mut out = [0u8; 8];
    for (to, from) in out.iter_mut().zip(bytes) {
        *to = *from;
    }
    out
}

/// One property of an element.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum PlyProperty {
    /// A single value: its name and type.
    Scalar(String, PlyScalar),
    /// A list: its name, the count's type and the items' type.
    List(String, PlyScalar, PlyScalar),
}

/// One element of the header: its name, row count and properties.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PlyElement {
    /// `vertex`, `face`, ...
    pub name: String,
    /// Rows in the body.
    pub count: u64,
    /// In the order of the body.
    pub properties: Vec<PlyProperty>,
}

/// A parsed header.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct PlyHeader {
    /// How the body is encoded.
    pub encoding: PlyEncoding,
    /// In the order of the body.
    pub elements: Vec<PlyElement>,
    /// Offset of the body's first byte (just after `end_header` and its line break).
    pub body_offset: usize,
}

/// The header at the start of `bytes` (which must hold at least the whole header).
pub fn parse_ply_header(bytes: &[u8]) -> Result<PlyHeader, String> {
    let marker = b"end_header";
    let at = bytes
        .windows(marker.len())
        .position(|w| w == marker)
        .ok_or("not a PLY file (no end_header)")?;
    let mut body = at + marker.len();
    if bytes.get(body) == Some(&b'\r') {
        body += 1;
    }
    body += 1; // the newline
    let header = String::from_utf8_lossy(bytes.get(..at).unwrap_or_default()).into_owned();
    let mut lines = header.lines().map(str::trim);
    if lines.next() != Some("ply") {
        return Err("not a PLY file (no ply magic)".into());
    }
    let mut encoding = None;
    let mut elements: Vec<PlyElement> = Vec::new();
    for line in lines {
        let tokens: Vec<&str> = line.split_whitespace().collect();
        match tokens.as_slice() {
            ["format", "ascii", _] => encoding = Some(PlyEncoding::Ascii),
            ["format", "binary_little_endian", _] => encoding = Some(PlyEncoding::LittleEndian),
            ["format", "binary_big_endian", _] => encoding = Some(PlyEncoding::BigEndian),
            ["element", name, count] => elements.push(PlyElement {
                name: (*name).to_string(),
                count: count.parse().map_err(|_| format!("bad element count '{count}'"))?,
                properties: Vec::new(),
            }),
            ["property", "list", count, item, name] => {
                let (Some(c), Some(i)) = (PlyScalar::parse(count), PlyScalar::parse(item)) else {
                    return Err(format!("unknown list types in '{line}'"));
                };
                elements
                    .last_mut()
                    .ok_or("property before any element")?
                    .properties
                    .push(PlyProperty::List((*name).to_string(), c, i));
            }
            ["property", kind, name] => {
                let scalar = PlyScalar::parse(kind).ok_or_else(|| format!("unknown property type '{kind}'"))?;
                elements
                    .last_mut()
                    .ok_or("property before any element")?
                    .properties
                    .push(PlyProperty::Scalar((*name).to_string(), scalar));
            }
            ["comment", ..] | ["obj_info", ..] | [] => {}
            _ => return Err(format!("unexpected header line '{line}'")),
        }
    }
    let encoding = encoding.ok_or("PLY header has no format line")?;
    Ok(PlyHeader {
        encoding,
        elements,
        body_offset: body,
    })
}

#[cfg(test)]
#[expect(
    clippy::expect_used,
    clippy::indexing_slicing,
    reason = "tests: a panic is the failure report"
)]
mod tests {
    use super::*;

    #[test]
    fn headers_parse_and_malformed_ones_are_errors() {
        let text = b"ply\r\nformat binary_little_endian 1.0\r\ncomment x\r\nelement vertex 2\r\nproperty float x\r\nproperty list uchar int idx\r\nend_header\r\nBODY";
        let header = parse_ply_header(text).expect("a valid header");
        assert_eq!(header.encoding, PlyEncoding::LittleEndian);
        assert_eq!(&text[header.body_offset..], b"BODY");
        assert_eq!(header.elements[0].count, 2);
        assert_eq!(
            header.elements[0].properties,
            vec![
                PlyProperty::Scalar("x".into(), PlyScalar::F32),
                PlyProperty::List("idx".into(), PlyScalar::U8, PlyScalar::I32)
            ]
        );
        for bad in [
            &b"ply\nformat ascii 1.0\nelement vertex -1\nend_header\n"[..],
            b"ply\nelement vertex 1\nend_header\n",
            b"ply\nformat ascii 1.0\nproperty float x\nend_header\n",
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty half x\nend_header\n",
            b"plyx\nformat ascii 1.0\nend_header\n",
            b"ply\nformat ascii 1.0\n",
        ] {
            assert!(parse_ply_header(bad).is_err(), "{}", String::from_utf8_lossy(bad));
        }
    }

    #[test]
    fn scalars_round_trip_and_reject_what_does_not_fit() {
        let mut out = [0u8; 8];
        for scalar in [
            PlyScalar::I8,
            PlyScalar::U8,
            PlyScalar::I16,
            PlyScalar::U16,
            PlyScalar::I32,
            PlyScalar::U32,
            PlyScalar::F32,
            PlyScalar::F64,
        ] {
            assert_eq!(PlyScalar::parse(scalar.name()), Some(scalar));
            scalar.write_le(100.0, &mut out).expect("100 fits every type");
            assert_eq!(scalar.read_le(&out), 100.0);
        }
        assert!(PlyScalar::U8.write_le(256.0, &mut out).is_none());
        assert!(PlyScalar::I32.write_le(1.5, &mut out).is_none());
        assert!(PlyScalar::U16.write_le(-1.0, &mut out).is_none());
    }
}
