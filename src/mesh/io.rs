//! Reading ground-truth and reconstructed meshes: OFF, PLY (ASCII or binary, either
//! endianness, any extra properties and elements), OBJ, each optionally gzip-compressed
//! (`.gz`). Polygons are split into triangle fans. Every malformed input is an error that names
//! the file, never a panic.

use std::io::Read;
use std::path::Path;

use super::Mesh;
use crate::format::ply_header::{
    PlyEncoding as Encoding, PlyHeader, PlyProperty as Property, PlyScalar as Scalar, parse_ply_header,
};

/// A mesh file that cannot be read: the file and the problem.
#[derive(Debug, thiserror::Error)]
#[error("{}: {problem}", path.display())]
pub struct MeshReadError {
    /// The file.
    pub path: std::path::PathBuf,
    /// What is wrong with it.
    pub problem: String,
}

fn err(path: &Path, problem: impl std::fmt::Display) -> MeshReadError {
    MeshReadError {
        path: path.to_path_buf(),
        problem: problem.to_string(),
    }
}

/// Reads a mesh by its extension (`.off`, `.ply`, `.obj`, each optionally followed by `.gz`).
pub fn read_mesh(path: &Path) -> Result<Mesh, MeshReadError> {
    let raw = std::fs::read(path).map_err(|e| err(path, e))?;
    let name = path.to_string_lossy().to_lowercase();
    let (bytes, name) = match name.strip_suffix(".gz") {
        Some(inner) => {
            let mut out = Vec::new();
            flate2::read::GzDecoder::new(raw.as_slice())
                .read_to_end(&mut out)
                .map_err(|e| err(path, format!("bad gzip data: {e}")))?;
            (out, inner.to_string())
        }
        None => (raw, name),
    };
    let mesh = if name.ends_with(".off") {
        read_off(path, &bytes)?
    } else if name.ends_with(".ply") {
        read_ply_bytes(path, &bytes)?
    } else if name.ends_with(".obj") {
        read_obj(path, &bytes)?
    } else {
        return Err(err(
            path,
            "unknown mesh format (expected .off, .ply or .obj, optionally .gz)",
        ));
    };
    let count = mesh.positions.len();
    if let Some(bad) = mesh.triangles.iter().flatten().find(|&&v| v as usize >= count) {
        return Err(err(path, format!("a face refers to vertex {bad} of {count}")));
    }
    if !mesh.positions.iter().flatten().all(|v| v.is_finite()) {
        return Err(err(path, "a vertex has a non-finite coordinate"));
    }
    Ok(mesh)
}

fn fan(polygon: &[u32], triangles: &mut Vec<[u32; 3]>) {
    if let Some((&first, rest)) = polygon.split_first() {
        for pair in rest.windows(2) {
            triangles.push([first, pair[0], pair[1]]);
        }
    }
}

fn read_off(path: &Path, bytes: &[u8]) -> Result<Mesh, MeshReadError> {
    let text = std::str::from_utf8(bytes).map_err(|_| err(path, "OFF file is not text"))?;
    let mut tokens = text
        .lines()
        .map(|l| l.split('#').next().unwrap_or_default())
        .flat_map(str::split_whitespace);
    if tokens.next() != Some("OFF") {
        return Err(err(path, "not an OFF file (no OFF magic)"));
    }
    let mut number = |what: &str| -> Result<f64, MeshReadError> {
        let t = tokens
            .next()
            .ok_or_else(|| err(path, format!("truncated OFF: missing {what}")))?;
        t.parse::<f64>()
            .map_err(|_| err(path, format!("{what}: '{t}' is not a number")))
    };
    let (nv, nf) = (number("vertex count")?, number("face count")?);
    number("edge count")?;
    let remaining = bytes.len() as f64;
    if !(0.0..=remaining).contains(&nv) || !(0.0..=remaining).contains(&nf) {
        return Err(err(path, format!("implausible counts: {nv} vertices, {nf} faces")));
    }
    let mut mesh = Mesh::default();
    for _ in 0..nv as usize {
        mesh.positions
            .push([number("x")? as f32, number("y")? as f32, number("z")? as f32]);
    }
    let mut polygon = Vec::new();
    for _ in 0..nf as usize {
        let n = number("face size")?;
        if !(3.0..=1e6).contains(&n) {
            return Err(err(path, format!("face size {n} is not plausible")));
        }
        polygon.clear();
        for _ in 0..n as usize {
            polygon.push(number("vertex index")? as u32);
        }
        fan(&polygon, &mut mesh.triangles);
    }
    Ok(mesh)
}

fn read_obj(path: &Path, bytes: &[u8]) -> Result<Mesh, MeshReadError> {
    let text = std::str::from_utf8(bytes).map_err(|_| err(path, "OBJ file is not text"))?;
    let mut mesh = Mesh::default();
    let mut polygon = Vec::new();
    for (index, line) in text.lines().enumerate() {
        let mut tokens = line.split_whitespace();
        match tokens.next() {
            Some("v") => {
                let mut p = [0f32; 3];
                for v in &mut p {
                    *v = tokens
                        .next()
                        .and_then(|t| t.parse().ok())
                        .ok_or_else(|| err(path, format!("line {}: bad vertex", index + 1)))?;
                }
                mesh.positions.push(p);
            }
            Some("f") => {
                polygon.clear();
                for t in tokens {
                    let v: i64 = t
                        .split('/')
                        .next()
                        .and_then(|v| v.parse().ok())
                        .ok_or_else(|| err(path, format!("line {}: bad face index '{t}'", index + 1)))?;
                    let resolved = if v < 0 { mesh.positions.len() as i64 + v } else { v - 1 };
                    polygon.push(
                        u32::try_from(resolved).map_err(|_| err(path, format!("line {}: bad index {v}", index + 1)))?,
                    );
                }
                fan(&polygon, &mut mesh.triangles);
            }
            _ => {}
        }
    }
    Ok(mesh)
}

/// Values of a PLY body, one at a time, in ASCII or binary.
struct PlyValues<'a> {
    path: &'a Path,
    encoding: Encoding,
    bytes: &'a [u8],
    pos: usize,
}

impl PlyValues<'_> {
    fn next(&mut self, scalar: Scalar) -> Result<f64, MeshReadError> {
        if self.encoding == Encoding::Ascii {
            while self.bytes.get(self.pos).is_some_and(u8::is_ascii_whitespace) {
                self.pos += 1;
            }
            let start = self.pos;
            while self.bytes.get(self.pos).is_some_and(|b| !b.is_ascii_whitespace()) {
                self.pos += 1;
            }
            let token = std::str::from_utf8(self.bytes.get(start..self.pos).unwrap_or_default()).unwrap_or_default();
            if token.is_empty() {
                return Err(err(self.path, "truncated PLY body"));
            }
            return token
                .parse::<f64>()
                .map_err(|_| err(self.path, format!("'{token}' is not a number")));
        }
        let size = scalar.size();
        let raw = self
            .bytes
            .get(self.pos..self.pos + size)
            .ok_or_else(|| err(self.path, "truncated PLY body"))?;
        self.pos += size;
        let mut buf = [0u8; 8];
        buf[..size].copy_from_slice(raw);
        if self.encoding == Encoding::BigEndian {
            buf[..size].reverse();
        }
        Ok(scalar.read_le(&buf))
    }
}

fn read_ply_bytes(path: &Path, bytes: &[u8]) -> Result<Mesh, MeshReadError> {
    let PlyHeader {
        encoding,
        elements,
        body_offset: body,
    } = parse_ply_header(bytes).map_err(|problem| err(path, problem))?;
    let mut values = PlyValues {
        path,
        encoding,
        bytes,
        pos: body,
    };
    let mut mesh = Mesh::default();
    let mut polygon = Vec::new();
    for element in &elements {
        // Each row needs at least one byte (binary) or two (ASCII): a count beyond that is a lie.
        if element.count > bytes.len() as u64 {
            return Err(err(
                path,
                format!("element {} claims {} rows", element.name, element.count),
            ));
        }
        let is_vertex = element.name == "vertex";
        let has = |name: &str| {
            element
                .properties
                .iter()
                .any(|p| matches!(p, Property::Scalar(n, _) if n == name))
        };
        // Normals are kept when the vertices carry all three components (octstore's own PLY).
        let with_normals = is_vertex && has("nx") && has("ny") && has("nz");
        for _ in 0..element.count {
            let mut position = [0f32; 3];
            let mut normal = [0f32; 3];
            for property in &element.properties {
                match property {
                    Property::Scalar(name, scalar) => {
                        let v = values.next(*scalar)?;
                        if element.name == "vertex" {
                            match name.as_str() {
                                "x" => position[0] = v as f32,
                                "y" => position[1] = v as f32,
                                "z" => position[2] = v as f32,
                                "nx" => normal[0] = v as f32,
                                "ny" => normal[1] = v as f32,
                                "nz" => normal[2] = v as f32,
                                _ => {}
                            }
                        }
                    }
                    Property::List(name, count, item) => {
                        let n = values.next(*count)?;
                        if !(0.0..=1e6).contains(&n) {
                            return Err(err(path, format!("list of {n} items is not plausible")));
                        }
                        polygon.clear();
                        for _ in 0..n as usize {
                            polygon.push(values.next(*item)?);
                        }
                        if element.name == "face" && (name == "vertex_indices" || name == "vertex_index") {
                            let indices: Vec<u32> = polygon.iter().map(|&v| v.max(0.0) as u32).collect();
                            if polygon.iter().any(|&v| v < 0.0) {
                                return Err(err(path, "negative vertex index"));
                            }
                            fan(&indices, &mut mesh.triangles);
                        }
                    }
                }
            }
            if is_vertex {
                mesh.positions.push(position);
                if with_normals {
                    mesh.normals.push(normal);
                }
            }
        }
    }
    Ok(mesh)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ply_ascii_and_binary_with_extra_properties() {
        let dir = tempfile::tempdir().unwrap();
        let ascii = dir.path().join("a.ply");
        std::fs::write(
            &ascii,
            "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\nproperty uchar red\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0 1\n1 0 0 2\n1 1 0 3\n0 1 0 4\n4 0 1 2 3\n",
        )
        .unwrap();
        let mesh = read_mesh(&ascii).unwrap();
        assert_eq!(mesh.positions.len(), 4);
        assert_eq!(mesh.triangles, vec![[0, 1, 2], [0, 2, 3]]);

        let mut binary = b"ply\nformat binary_big_endian 1.0\nelement vertex 3\nproperty double x\nproperty double y\nproperty double z\nelement face 1\nproperty list uchar uint vertex_indices\nend_header\n".to_vec();
        for v in [0.0f64, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.5] {
            binary.extend(v.to_be_bytes());
        }
        binary.push(3);
        for i in [0u32, 1, 2] {
            binary.extend(i.to_be_bytes());
        }
        let path = dir.path().join("b.ply");
        std::fs::write(&path, &binary).unwrap();
        let mesh = read_mesh(&path).unwrap();
        assert_eq!(mesh.positions[2], [0.0, 1.0, 0.5]);
        assert_eq!(mesh.triangles, vec![[0, 1, 2]]);
        // Every truncation is an error, never a panic.
        for cut in 0..binary.len() - 1 {
            std::fs::write(&path, &binary[..cut]).unwrap();
            assert!(read_mesh(&path).is_err(), "cut at {cut}");
        }
    }

    #[test]
    fn off_and_bad_indices() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("t.off");
        std::fs::write(&path, "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n").unwrap();
        assert_eq!(read_mesh(&path).unwrap().triangles, vec![[0, 1, 2]]);
        std::fs::write(&path, "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 7\n").unwrap();
        assert!(read_mesh(&path).unwrap_err().to_string().contains("vertex 7 of 3"));
    }
}
