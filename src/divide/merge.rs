//! `merge`: fuses meshes reconstructed per subspace by cutting the overlaps (Kuhn and Mayer
//! 2015, section 4): each subspace keeps the triangles whose centroid lies in its core cube, so
//! every place of the scene is taken from exactly one reconstruction, the one that saw it with
//! the widest margin. Vertices of different meshes that coincide (within a millionth of the
//! root's side) are welded, so surfaces that agree at a cut join; the boundary edges left show
//! where they do not.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use super::Result;
use super::manifest::{Manifest, read_manifest_file};
use super::{DivideError, io};
use crate::mesh::{Mesh, edge_defects, read_mesh, write_mesh};

/// What a merge did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct MergeReport {
    /// Meshes read, one per subspace.
    pub meshes: usize,
    /// Subspaces that no mesh was given for (their cores are holes in the result).
    pub missing: Vec<String>,
    /// Triangles kept.
    pub triangles: usize,
    /// Triangles cut away (their centroid lies in another subspace's core).
    pub cut: usize,
    /// Vertices of the merged mesh.
    pub vertices: usize,
    /// Vertices welded to a vertex of another mesh.
    pub welded: usize,
    /// Edges of one triangle in the merged mesh.
    pub boundary_edges: usize,
}

/// The subspace each mesh belongs to: the one whose file name, without `.ply`, starts the
/// mesh's file name (`L2_1_0_3.ply` takes `L2_1_0_3.mesh.ply` or `out/L2_1_0_3.ply`).
fn match_meshes<'a>(manifest: &Manifest, meshes: &'a [PathBuf]) -> Result<Vec<Option<&'a PathBuf>>> {
    let stems: Vec<String> = manifest
        .subspaces
        .iter()
        .map(|s| s.file.strip_suffix(".ply").unwrap_or(&s.file).to_string())
        .collect();
    let mut matched: Vec<Option<&PathBuf>> = vec![None; stems.len()];
    for mesh in meshes {
        let name = mesh
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        // The longest stem that starts the name and ends at a dot or the name's end.
        let best = stems
            .iter()
            .enumerate()
            .filter(|(_, stem)| {
                name.strip_prefix(stem.as_str())
                    .is_some_and(|rest| rest.is_empty() || rest.starts_with('.'))
            })
            .max_by_key(|(_, stem)| stem.len());
        let Some((index, _)) = best else {
            return Err(DivideError::UnmatchedMesh {
                mesh: mesh.to_path_buf(),
            });
        };
        match matched.get_mut(index) {
            Some(Some(other)) => {
                return Err(DivideError::TwoMeshes {
                    first: other.to_path_buf(),
                    second: mesh.to_path_buf(),
                    subspace: stems.get(index).map_or("", String::as_str).to_string(),
                });
            }
            Some(slot) => *slot = Some(mesh),
            None => {}
        }
    }
    Ok(matched)
}

/// Merges `meshes` of the subspaces listed in `manifest_path` into `output`.
pub fn merge(manifest_path: &Path, meshes: &[PathBuf], output: &Path) -> Result<MergeReport> {
    merge_meshes(manifest_path, meshes, output)
}

fn merge_meshes(manifest_path: &Path, meshes: &[PathBuf], output: &Path) -> Result<MergeReport> {
    let manifest = read_manifest_file(manifest_path)?;
    let matched = match_meshes(&manifest, meshes)?;
    let tolerance = manifest.division.root.size * 1e-6;
    let mut report = MergeReport::default();
    let mut merged = Mesh::default();
    let mut normals_everywhere = true;
    let mut welds: HashMap<[i64; 3], (u32, usize)> = HashMap::new();
    for (index, (subspace, mesh_path)) in manifest.subspaces.iter().zip(&matched).enumerate() {
        let Some(mesh_path) = mesh_path else {
            report.missing.push(subspace.file.clone());
            continue;
        };
        let mesh = read_mesh(mesh_path)?;
        report.meshes += 1;
        let has_normals = mesh.normals.len() == mesh.positions.len();
        normals_everywhere &= has_normals;
        let mut local: Vec<Option<u32>> = vec![None; mesh.positions.len()];
        for triangle in &mesh.triangles {
            let corners = triangle.map(|v| mesh.positions.get(v as usize).copied());
            let [Some(a), Some(b), Some(c)] = corners else {
                return Err(DivideError::MissingVertex {
                    mesh: mesh_path.to_path_buf(),
                });
            };
            let centroid = [0, 1, 2].map(|k| (f64::from(a[k]) + f64::from(b[k]) + f64::from(c[k])) / 3.0);
            if !subspace.core.contains(centroid) {
                report.cut += 1;
                continue;
            }
            let mut kept = [0u32; 3];
            for (slot, &v) in kept.iter_mut().zip(triangle) {
                let Some(entry) = local.get_mut(v as usize) else {
                    continue;
                };
                if let Some(id) = entry {
                    *slot = *id;
                    continue;
                }
                let p = mesh.positions.get(v as usize).copied().unwrap_or_default();
                let key = p.map(|c| (f64::from(c) / tolerance).round() as i64);
                let id = match welds.get(&key) {
                    Some(&(id, owner)) if owner != index => {
                        report.welded += 1;
                        id
                    }
                    _ => {
                        let id = merged.positions.len() as u32;
                        merged.positions.push(p);
                        merged.normals.push(
                            mesh.normals
                                .get(v as usize)
                                .copied()
                                .filter(|_| has_normals)
                                .unwrap_or_default(),
                        );
                        welds.entry(key).or_insert((id, index));
                        id
                    }
                };
                *entry = Some(id);
                *slot = id;
            }
            merged.triangles.push(kept);
        }
    }
    if !normals_everywhere {
        merged.normals.clear();
    }
    report.triangles = merged.triangles.len();
    report.vertices = merged.positions.len();
    report.boundary_edges = edge_defects(&merged).0;
    write_mesh(output, &merged).map_err(io("write", output))?;
    Ok(report)
}
