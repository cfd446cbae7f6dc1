//! Writing meshes: binary little-endian PLY (with normals) or OBJ.

use std::io::Write;
use std::path::Path;

use super::Mesh;

/// The header of the binary PLY that octstore writes: float positions and normals, then
/// triangles as uchar-counted uint lists.
pub fn ply_header(vertices: u64, triangles: u64) -> String {
    format!(
        "ply\nformat binary_little_endian 1.0\ncomment octstore\nelement vertex {vertices}\nproperty float x\nproperty float y\nproperty float z\nproperty float nx\nproperty float ny\nproperty float nz\nelement face {triangles}\nproperty list uchar uint vertex_indices\nend_header\n"
    )
}

/// Writes binary little-endian PLY, or OBJ when the path ends in `.obj`. A mesh without
/// normals gets zero normals in PLY (whose header always has them) and none in OBJ.
pub fn write_mesh(path: &Path, mesh: &Mesh) -> std::io::Result<()> {
    let file = std::fs::File::create(path)?;
    let mut out = std::io::BufWriter::new(file);
    let is_obj = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("obj"));
    let has_normals = mesh.normals.len() == mesh.positions.len();
    let normal = |i: usize| {
        if has_normals {
            mesh.normals.get(i).copied().unwrap_or_default()
        } else {
            [0.0; 3]
        }
    };
    if is_obj {
        for (i, p) in mesh.positions.iter().enumerate() {
            writeln!(out, "v {} {} {}", p[0], p[1], p[2])?;
            if has_normals {
                let n = normal(i);
                writeln!(out, "vn {} {} {}", n[0], n[1], n[2])?;
            }
        }
        for t in &mesh.triangles {
            if has_normals {
                writeln!(out, "f {0}//{0} {1}//{1} {2}//{2}", t[0] + 1, t[1] + 1, t[2] + 1)?;
            } else {
                writeln!(out, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1)?;
            }
        }
    } else {
        write!(
            out,
            "{}",
            ply_header(mesh.positions.len() as u64, mesh.triangles.len() as u64)
        )?;
        for (i, p) in mesh.positions.iter().enumerate() {
            for v in p.iter().chain(&normal(i)) {
                out.write_all(&v.to_le_bytes())?;
            }
        }
        for t in &mesh.triangles {
            out.write_all(&[3u8])?;
            for v in t {
                out.write_all(&v.to_le_bytes())?;
            }
        }
    }
    out.flush()
}
