//! Quality tools: ground-truth meshes in ([`meshio`]), depth maps rendered from them with noise
//! ([`gt_render`]), and reconstructions measured against them ([`evaluate`]). The binaries in
//! `tools/` (`octstore-gt-render`, `octstore-evaluate`) are thin command lines over these.

pub mod evaluate;
pub mod gt_render;
pub mod meshio;
