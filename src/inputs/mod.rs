//! Inputs: discovering depth maps (7-Scenes / RGB-D folders, TUM RGB-D sequences, JSON
//! manifests, COLMAP dense workspaces, PTX / E57 LIDAR scans) and reading them into
//! [`DepthImage`]s.
//!
//! Conventions (docs/inputs.md): poses are camera-to-world with OpenCV camera axes (x right,
//! y down, z forward); pinhole depth is the z coordinate in the camera frame, pixel (i, j) has
//! its centre at image coordinates (i, j); spherical (LIDAR) depth is the range along the ray.
//!
//! `depth_map` holds the types every reader shares and imports no reader; the readers
//! (`image_files`, `colmap`, `lidar`, `tum`) import only `depth_map` (and `image_files`);
//! `depth_rows` (a registered depth map row by row, and whole) dispatches to them.

mod colmap;
mod depth_map;
mod depth_rows;
mod discover;
mod image_files;
mod lidar;
mod tum;

pub use colmap::{WorkspaceWriter, write_colmap_depth};
pub use depth_map::{
    DEFAULT_NOISE_FOOTPRINTS, DEFAULT_NOISE_SIGMAS, DepthImage, DepthMapSource, DepthNoise, ImageFormat, InputError,
    Kind, MAX_DEPTH_SCALE, MAX_NOISE_SIGMAS, PoseProblem, Projection, bad, check_depth_scale, check_noise_sigmas,
    check_pose, check_regular_file, extension_of,
};
pub use depth_rows::DepthRows;
pub use discover::{DiscoverOptions, InputFormat, discover};
pub use image_files::{FloatLayout, npy_layout, pfm_layout, read_npy, read_pfm, read_png16, write_pfm};
pub use lidar::{scan_points_in_world, write_ptx_scan};
pub use tum::{MAX_TIME_DIFFERENCE, TUM_DEPTH_SCALE};
