//! glTF 2.0 binary (GLB) output: one mesh of positions, normals and 32-bit indices, which
//! browsers (three.js), Blender and trimesh open directly.
//!
//! Layout: the 12-byte header (`glTF`, version 2, total length), a JSON chunk (padded with
//! spaces to 4 bytes) and one BIN chunk holding the vertex records interleaved as the mesh
//! files' temporary vertex file has them (position and normal, 6 little-endian f32, stride 24)
//! and then the triangles' indices (3 little-endian u32 each). Every length in a GLB is a u32,
//! so a GLB holds at most 4 GiB: a larger mesh is refused with that reason (PLY has no limit).

use std::io::Write;

/// Bytes of one interleaved vertex record.
pub(crate) const GLB_VERTEX_BYTES: u64 = 24;
/// Bytes of one triangle's indices.
pub(crate) const GLB_TRIANGLE_BYTES: u64 = 12;

/// Writes everything before the vertex records: the header, the JSON chunk and the BIN chunk's
/// header. The caller then writes `vertices` records and `triangles` index triples, nothing
/// else. `min` and `max` bound the positions (the format requires them).
pub(crate) fn write_glb_head(
    out: &mut impl Write,
    vertices: u64,
    triangles: u64,
    min: [f32; 3],
    max: [f32; 3],
) -> std::io::Result<()> {
    let vertex_bytes = vertices * GLB_VERTEX_BYTES;
    let index_bytes = triangles * GLB_TRIANGLE_BYTES;
    let bin = vertex_bytes + index_bytes;
    let json = serde_json::json!({
        "asset": { "version": "2.0", "generator": concat!("octstore ", env!("CARGO_PKG_VERSION")) },
        "scene": 0,
        "scenes": [{ "nodes": [0] }],
        "nodes": [{ "mesh": 0 }],
        "meshes": [{ "primitives": [{ "attributes": { "POSITION": 0, "NORMAL": 1 }, "indices": 2, "mode": 4 }] }],
        "buffers": [{ "byteLength": bin }],
        "bufferViews": [
            { "buffer": 0, "byteOffset": 0, "byteLength": vertex_bytes, "byteStride": GLB_VERTEX_BYTES, "target": 34962 },
            { "buffer": 0, "byteOffset": vertex_bytes, "byteLength": index_bytes, "target": 34963 }
        ],
        "accessors": [
            { "bufferView": 0, "byteOffset": 0, "componentType": 5126, "count": vertices, "type": "VEC3",
              "min": min, "max": max },
            { "bufferView": 0, "byteOffset": 12, "componentType": 5126, "count": vertices, "type": "VEC3" },
            { "bufferView": 1, "byteOffset": 0, "componentType": 5125, "count": triangles * 3, "type": "SCALAR" }
        ]
    });
    let mut json = serde_json::to_vec(&json).map_err(std::io::Error::other)?;
    while !json.len().is_multiple_of(4) {
        json.push(b' ');
    }
    let total = 12 + 8 + json.len() as u64 + 8 + bin;
    let too_large = || {
        std::io::Error::other(format!(
            "a GLB holds at most 4 GiB (its lengths are 32-bit) and this mesh needs {total} bytes: write .ply instead"
        ))
    };
    let total = u32::try_from(total).map_err(|_| too_large())?;
    let bin = u32::try_from(bin).map_err(|_| too_large())?;
    out.write_all(b"glTF")?;
    out.write_all(&2u32.to_le_bytes())?;
    out.write_all(&total.to_le_bytes())?;
    out.write_all(&(json.len() as u32).to_le_bytes())?;
    out.write_all(b"JSON")?;
    out.write_all(&json)?;
    out.write_all(&bin.to_le_bytes())?;
    out.write_all(b"BIN\0")?;
    Ok(())
}

/// Whether `path` names a GLB file.
pub(crate) fn is_glb(path: &std::path::Path) -> bool {
    path.extension().is_some_and(|e| e.eq_ignore_ascii_case("glb"))
}

/// Componentwise bounds of positions (zeros for none).
pub(crate) fn bounds<'a>(positions: impl Iterator<Item = &'a [f32; 3]>) -> ([f32; 3], [f32; 3]) {
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for p in positions {
        for ((lo, hi), v) in lo.iter_mut().zip(hi.iter_mut()).zip(p) {
            (*lo, *hi) = (lo.min(*v), hi.max(*v));
        }
    }
    if lo[0] > hi[0] {
        return ([0.0; 3], [0.0; 3]);
    }
    (lo, hi)
}
