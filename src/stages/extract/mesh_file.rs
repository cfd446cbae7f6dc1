//! The temporary vertex and face files a streaming extraction writes beside its output, and
//! their assembly into the final PLY.

use std::io::Write;
use std::path::Path;

use glam::DVec3;

use super::MeshSummary;
use super::weld::MeshWriter;
use crate::mesh::{
    GLB_VERTEX_BYTES, is_glb, output_target, ply_header, remove_leftovers, temporary_beside, write_atomically,
    write_glb_head,
};

/// Writes a mesh file in two passes over temporary files beside it: fixed-size vertex records
/// (so that normals can be fixed in place) and face records, joined under the header at the end.
pub(super) struct MeshFile {
    path: std::path::PathBuf,
    vertices_path: std::path::PathBuf,
    faces_path: std::path::PathBuf,
    vertices: std::io::BufWriter<std::fs::File>,
    faces: std::io::BufWriter<std::fs::File>,
}

/// Bytes of one vertex record: position and normal as little-endian f32.
const VERTEX_RECORD: u64 = 6 * std::mem::size_of::<f32>() as u64;
/// Bytes of one face record in binary PLY: the count byte 3, then three u32 indices.
const FACE_RECORD: usize = 1 + 3 * std::mem::size_of::<u32>();

impl MeshFile {
    pub(super) fn create(path: &Path) -> std::io::Result<MeshFile> {
        // The parts lie beside the file that will be replaced: a link's target.
        let path = &output_target(path)?;
        remove_leftovers(path)?;
        let (vertices_path, faces_path) = (temporary_beside(path, "vertices"), temporary_beside(path, "faces"));
        let open = |p: &Path| -> std::io::Result<std::io::BufWriter<std::fs::File>> {
            Ok(std::io::BufWriter::new(
                std::fs::OpenOptions::new()
                    .read(true)
                    .write(true)
                    .create(true)
                    .truncate(true)
                    .open(p)?,
            ))
        };
        Ok(MeshFile {
            path: path.to_path_buf(),
            vertices: open(&vertices_path)?,
            faces: open(&faces_path)?,
            vertices_path,
            faces_path,
        })
    }

    /// Joins the parts into the mesh file (PLY, or OBJ by extension), atomically
    /// (`write_atomically`), and removes them.
    pub(super) fn finish(self, summary: &MeshSummary) -> std::io::Result<()> {
        use std::io::{Seek, SeekFrom};
        let mut vertices = self.vertices.into_inner().map_err(|e| e.into_error())?;
        let mut faces = self.faces.into_inner().map_err(|e| e.into_error())?;
        vertices.seek(SeekFrom::Start(0))?;
        faces.seek(SeekFrom::Start(0))?;
        let joined = write_atomically(&self.path, |out| join(&self.path, summary, vertices, faces, out));
        std::fs::remove_file(&self.vertices_path)?;
        std::fs::remove_file(&self.faces_path)?;
        joined
    }

    pub(super) fn abandon(self) {
        drop(self.vertices);
        drop(self.faces);
        let _ = std::fs::remove_file(&self.vertices_path);
        let _ = std::fs::remove_file(&self.faces_path);
    }
}

/// Writes the mesh file from its parts: vertex records, then face records.
fn join(
    path: &Path,
    summary: &MeshSummary,
    mut vertices: std::fs::File,
    mut faces: std::fs::File,
    out: &mut std::io::BufWriter<std::fs::File>,
) -> std::io::Result<()> {
    use std::io::Read;
    let is_obj = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("obj"));
    if is_glb(path) {
        use std::io::{Seek, SeekFrom};
        // The positions' bounds first (the JSON needs them), then the records as they are and
        // the faces without their count byte.
        let mut record = [0u8; VERTEX_RECORD as usize];
        let mut reader = std::io::BufReader::new(&mut vertices);
        let (mut min, mut max) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
        for _ in 0..summary.vertices {
            reader.read_exact(&mut record)?;
            let coordinates = record
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]));
            for ((lo, hi), v) in min.iter_mut().zip(max.iter_mut()).zip(coordinates) {
                (*lo, *hi) = (lo.min(v), hi.max(v));
            }
        }
        drop(reader);
        if summary.vertices == 0 {
            (min, max) = ([0.0; 3], [0.0; 3]);
        }
        vertices.seek(SeekFrom::Start(0))?;
        write_glb_head(out, summary.vertices, summary.triangles, min, max)?;
        std::io::copy(&mut (&mut vertices).take(summary.vertices * GLB_VERTEX_BYTES), out)?;
        let mut reader = std::io::BufReader::new(faces);
        let mut face = [0u8; FACE_RECORD];
        for _ in 0..summary.triangles {
            reader.read_exact(&mut face)?;
            out.write_all(&face[1..])?;
        }
    } else if is_obj {
        let mut reader = std::io::BufReader::new(vertices);
        let mut record = [0u8; VERTEX_RECORD as usize];
        for _ in 0..summary.vertices {
            reader.read_exact(&mut record)?;
            let f: Vec<f32> = record
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .collect();
            writeln!(out, "v {} {} {}", f[0], f[1], f[2])?;
            writeln!(out, "vn {} {} {}", f[3], f[4], f[5])?;
        }
        let mut reader = std::io::BufReader::new(faces);
        let mut record = [0u8; FACE_RECORD];
        for _ in 0..summary.triangles {
            reader.read_exact(&mut record)?;
            let v: Vec<u32> = record[1..]
                .chunks_exact(4)
                .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) + 1)
                .collect();
            writeln!(out, "f {0}//{0} {1}//{1} {2}//{2}", v[0], v[1], v[2])?;
        }
    } else {
        write!(out, "{}", ply_header(summary.vertices, summary.triangles))?;
        std::io::copy(&mut vertices, out)?;
        std::io::copy(&mut faces, out)?;
    }
    Ok(())
}

impl MeshWriter for MeshFile {
    fn vertex(&mut self, position: DVec3, normal: DVec3, _settled: bool) -> std::io::Result<()> {
        for v in position.as_vec3().to_array().iter().chain(&normal.as_vec3().to_array()) {
            self.vertices.write_all(&v.to_le_bytes())?;
        }
        Ok(())
    }

    fn triangle(&mut self, triangle: [u32; 3]) -> std::io::Result<()> {
        self.faces.write_all(&[3u8])?;
        for v in triangle {
            self.faces.write_all(&v.to_le_bytes())?;
        }
        Ok(())
    }

    fn fix_vertices(&mut self, fixes: &[(u32, DVec3, DVec3)]) -> std::io::Result<()> {
        use std::io::{Seek, SeekFrom};
        if fixes.is_empty() {
            return Ok(());
        }
        self.vertices.flush()?;
        let file = self.vertices.get_mut();
        for (index, position, normal) in fixes {
            file.seek(SeekFrom::Start(u64::from(*index) * VERTEX_RECORD))?;
            let mut bytes = [0u8; VERTEX_RECORD as usize];
            let values = position
                .as_vec3()
                .to_array()
                .into_iter()
                .chain(normal.as_vec3().to_array());
            for (slot, v) in bytes.chunks_exact_mut(4).zip(values) {
                slot.copy_from_slice(&v.to_le_bytes());
            }
            file.write_all(&bytes)?;
        }
        file.seek(SeekFrom::End(0))?;
        Ok(())
    }
}

/// A streamed mesh kept in memory (a region's, or one a library caller asked for).
#[derive(Default)]
pub(super) struct MemoryMesh {
    positions: Vec<DVec3>,
    normals: Vec<DVec3>,
    triangles: Vec<[u32; 3]>,
}

impl MemoryMesh {
    pub(super) fn into_mesh(self) -> crate::mesh::Mesh {
        crate::mesh::Mesh {
            positions: self.positions.iter().map(|p| p.as_vec3().to_array()).collect(),
            normals: self
                .normals
                .iter()
                .map(|n| n.normalize_or_zero().as_vec3().to_array())
                .collect(),
            triangles: self.triangles,
        }
    }
}

impl MeshWriter for MemoryMesh {
    fn vertex(&mut self, position: DVec3, normal: DVec3, _settled: bool) -> std::io::Result<()> {
        self.positions.push(position);
        self.normals.push(normal);
        Ok(())
    }

    fn triangle(&mut self, triangle: [u32; 3]) -> std::io::Result<()> {
        self.triangles.push(triangle);
        Ok(())
    }

    fn fix_vertices(&mut self, fixes: &[(u32, DVec3, DVec3)]) -> std::io::Result<()> {
        for &(index, position, normal) in fixes {
            if let (Some(p), Some(n)) = (
                self.positions.get_mut(index as usize),
                self.normals.get_mut(index as usize),
            ) {
                *p = position;
                *n = normal;
            }
        }
        Ok(())
    }
}
