//! `subspaces.json`: the list of subspaces a division wrote (what reconstructors and `merge`
//! read) and what a later `divide` into the same folder needs to go on (the root, the overlap,
//! the point limit and the record layout). It is written last, atomically: a folder's
//! subspaces are the ones its manifest lists; other files in it are leftovers.

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::DivideError;
use super::PointLayout;
use super::grid::{Bounds, Node, Root};
use crate::format::ply_header::PlyScalar;

/// The manifest's file name in a division's folder.
pub const MANIFEST: &str = "subspaces.json";

/// Version of the `division` block; a folder written by a later version is refused.
pub const FORMAT_VERSION: u32 = 1;

/// A cube as the manifest states it: half-open, `min <= p < min + size`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Cube {
    /// Lowest corner.
    pub min: [f64; 3],
    /// Side.
    pub size: f64,
}

impl Cube {
    /// The cube of a box with equal sides.
    pub fn of(bounds: &Bounds) -> Cube {
        Cube {
            min: bounds.min,
            size: bounds.max[0] - bounds.min[0],
        }
    }

    /// Whether `p` lies inside, as a user of the manifest tests it.
    pub fn contains(&self, p: [f64; 3]) -> bool {
        (0..3).all(|a| self.min[a] <= p[a] && p[a] < self.min[a] + self.size)
    }
}

/// One subspace.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Subspace {
    /// Its PLY, relative to the folder.
    pub file: String,
    /// The cube it owns: every point lies in exactly one subspace's core.
    pub core: Cube,
    /// The core grown by the overlap on every face: its file holds every point in it.
    pub grown: Cube,
    /// Points in its file (the grown cube's).
    pub points: u64,
    /// Points in its core.
    pub core_points: u64,
    /// Its octree node under the root.
    pub node: Node,
}

/// What a later `divide` into the folder needs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Division {
    /// `FORMAT_VERSION`.
    pub version: u32,
    /// The root cube every node lies in.
    pub root: Root,
    /// Grown cubes reach this fraction of their side beyond the core.
    pub overlap: f64,
    /// No subspace's core holds more points (but at the grid's last level).
    pub max_points: u64,
    /// The points' properties, name and PLY type, in record order.
    pub properties: Vec<(String, String)>,
    /// Counts the divides into the folder; new files carry it in their names.
    pub generation: u64,
}

/// The whole `subspaces.json`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// In depth-first Morton order of their nodes.
    pub subspaces: Vec<Subspace>,
    /// How the folder was divided.
    pub division: Division,
}

/// The deepest node level a manifest may name: node indices are u32.
const DEEPEST_LEVEL: u32 = 32;

/// A node's Morton interval at [`DEEPEST_LEVEL`]: the codes of the deepest nodes inside it,
/// `[start, end)`. Octree nodes are disjoint exactly when their intervals are.
fn morton_interval(node: &Node) -> (u128, u128) {
    let shift = DEEPEST_LEVEL - node.level;
    let mut start = 0u128;
    for bit in 0..DEEPEST_LEVEL {
        for (axis, &index) in node.index.iter().enumerate() {
            let deep = u128::from(index) << shift;
            start |= ((deep >> bit) & 1) << (3 * bit + axis as u32);
        }
    }
    (start, start + (1u128 << (3 * shift)))
}

impl Manifest {
    /// What `merge` and a later `divide` rely on, checked: the root is a finite cube; every
    /// subspace's node lies in it and its core is that node's cube; its grown cube holds its
    /// core; no two nodes overlap. (Together the cores tile the part of the root that holds
    /// points; nodes without points have no subspace, so a missing one cannot be told from an
    /// empty one.) A damaged or hand-edited manifest fails here naming the subspace, instead
    /// of dropping triangles in `merge`.
    pub fn check(&self) -> Result<(), String> {
        let root = self.division.root;
        if !(root.size.is_finite() && root.size > 0.0 && root.min.iter().all(|v| v.is_finite())) {
            return Err(format!(
                "the root (min {:?}, side {}) is not a finite cube",
                root.min, root.size
            ));
        }
        let tolerance = root.size * 1e-9;
        let mut intervals = Vec::with_capacity(self.subspaces.len());
        for subspace in &self.subspaces {
            let node = subspace.node;
            let name = &subspace.file;
            if node.level > DEEPEST_LEVEL || node.index.iter().any(|&i| u64::from(i) >= 1u64 << node.level) {
                return Err(format!("subspace {name}: node {node:?} is not inside the root"));
            }
            let side = root.size / f64::from(node.level).exp2();
            let expected_min: Vec<f64> = (0..3)
                .map(|a| {
                    root.min.get(a).copied().unwrap_or(0.0) + f64::from(node.index.get(a).copied().unwrap_or(0)) * side
                })
                .collect();
            let core = subspace.core;
            let core_matches = (core.size - side).abs() <= tolerance
                && core
                    .min
                    .iter()
                    .zip(&expected_min)
                    .all(|(m, e)| (m - e).abs() <= tolerance);
            if !core_matches {
                return Err(format!(
                    "subspace {name}: its core (min {:?}, side {}) is not its node's cube (min {expected_min:?}, side {side})",
                    core.min, core.size
                ));
            }
            let grown = subspace.grown;
            let holds_core = grown.size.is_finite()
                && (0..3).all(|a| {
                    let (g, c) = (grown.min.get(a).copied(), core.min.get(a).copied());
                    matches!((g, c), (Some(g), Some(c)) if g <= c + tolerance && c + core.size <= g + grown.size + tolerance)
                });
            if !holds_core {
                return Err(format!("subspace {name}: its grown cube does not hold its core"));
            }
            intervals.push((morton_interval(&node), name));
        }
        intervals.sort_by_key(|((start, _), _)| *start);
        for pair in intervals.windows(2) {
            if let [((_, end), a), ((start, _), b)] = pair
                && start < end
            {
                return Err(format!("subspaces {a} and {b} overlap"));
            }
        }
        Ok(())
    }
}

impl Division {
    /// The record layout its properties describe.
    pub fn layout(&self) -> Result<PointLayout, String> {
        let properties = self
            .properties
            .iter()
            .map(|(name, scalar)| {
                PlyScalar::parse(scalar)
                    .map(|s| (name.clone(), s))
                    .ok_or_else(|| format!("unknown property type '{scalar}'"))
            })
            .collect::<Result<Vec<_>, _>>()?;
        PointLayout::new(properties)
    }

    /// The properties of `layout` as the manifest records them.
    pub fn properties_of(layout: &PointLayout) -> Vec<(String, String)> {
        layout
            .properties()
            .iter()
            .map(|(name, scalar)| (name.clone(), scalar.name().to_string()))
            .collect()
    }
}

/// The error of a manifest at `path`.
fn bad(path: &Path) -> impl Fn(Box<dyn std::error::Error + Send + Sync>) -> DivideError + '_ {
    move |source| DivideError::BadManifest {
        path: path.to_path_buf(),
        source,
    }
}

/// Reads a folder's manifest; `None` when there is none.
pub fn read_manifest(dir: &Path) -> Result<Option<Manifest>, DivideError> {
    let path = dir.join(MANIFEST);
    let bytes = match std::fs::read(&path) {
        Ok(bytes) => bytes,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(bad(&path)(e.into())),
    };
    let manifest: Manifest = serde_json::from_slice(&bytes).map_err(|e| bad(&path)(e.into()))?;
    if manifest.division.version > FORMAT_VERSION {
        let later = format!(
            "written by a later octstore (division version {})",
            manifest.division.version
        );
        return Err(bad(&path)(later.into()));
    }
    manifest.check().map_err(|e| bad(&path)(e.into()))?;
    Ok(Some(manifest))
}

/// Reads the manifest at `path` (for `merge`, which may name it anywhere).
pub fn read_manifest_file(path: &Path) -> Result<Manifest, DivideError> {
    let bytes = std::fs::read(path).map_err(|e| bad(path)(e.into()))?;
    let manifest: Manifest = serde_json::from_slice(&bytes).map_err(|e| bad(path)(e.into()))?;
    manifest.check().map_err(|e| bad(path)(e.into()))?;
    Ok(manifest)
}

/// Writes the manifest atomically.
pub fn write_manifest(dir: &Path, manifest: &Manifest) -> std::io::Result<()> {
    let json = serde_json::to_vec_pretty(manifest).map_err(std::io::Error::other)?;
    crate::mesh::write_atomically(&dir.join(MANIFEST), |out| {
        use std::io::Write;
        out.write_all(&json)?;
        out.write_all(b"\n")
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn manifest_numbers_read_back_to_the_bit() -> Result<(), Box<dyn std::error::Error>> {
        // serde_json parses floats correctly rounded only with its `float_roundtrip` feature;
        // without it this corner came back one ulp higher, and a point on the root's lowest
        // face fell out of its core.
        let root = Root {
            min: [9.27448272705078e-5, 0.129_282_474_517_822_27, 0.0014805793762207031],
            size: 1024.0,
        };
        let dir = tempfile::tempdir()?;
        let manifest = Manifest {
            subspaces: Vec::new(),
            division: Division {
                version: FORMAT_VERSION,
                root,
                overlap: 0.1,
                max_points: 7,
                properties: vec![("x".into(), "float".into())],
                generation: 1,
            },
        };
        write_manifest(dir.path(), &manifest)?;
        let back = read_manifest(dir.path())?.ok_or("no manifest")?;
        assert_eq!(back.division.root.min.map(f64::to_bits), root.min.map(f64::to_bits));
        // Many doubles of the sizes coordinates have, as the manifest writes and reads them.
        let mut state = 3u64;
        for _ in 0..20_000 {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            let x = f64::from_bits((1013u64 << 52) | (state >> 12)) * 1e3;
            let json = serde_json::to_vec(&[x])?;
            let [back]: [f64; 1] = serde_json::from_slice(&json)?;
            assert_eq!(back.to_bits(), x.to_bits(), "{x:e}");
        }
        Ok(())
    }
}
