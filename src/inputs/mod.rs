//! Inputs: discovering depth maps (7-Scenes / RGB-D folders, TUM RGB-D sequences, JSON
//! manifests, COLMAP dense workspaces, PTX / E57 LIDAR scans) and reading them into
//! [`DepthImage`]s.
//!
//! Conventions (README, "Inputs"): poses are camera-to-world with OpenCV camera axes (x right,
//! y down, z forward); pinhole depth is the z coordinate in the camera frame, pixel (i, j) has
//! its centre at image coordinates (i, j); spherical (LIDAR) depth is the range along the ray.
//!
//! `depth_map` holds the types every reader shares and imports no reader; the readers
//! (`image_files`, `colmap`, `lidar`, `tum`) import only `depth_map`; this file dispatches to them.

mod colmap;
mod depth_map;
mod discover;
mod image_files;
mod lidar;
mod tum;

pub use colmap::{WorkspaceWriter, write_colmap_depth};
pub use depth_map::{
    DEFAULT_NOISE_FOOTPRINTS, DEFAULT_NOISE_SIGMAS, DepthImage, DepthMapSource, DepthNoise, ImageFormat, InputError,
    Kind, Projection, bad, check_pose,
};
pub use discover::{DiscoverOptions, InputFormat, discover};
pub use image_files::{read_npy, read_pfm, read_png16, write_pfm};
pub use lidar::write_ptx_scan;
pub use tum::{MAX_TIME_DIFFERENCE, TUM_DEPTH_SCALE};

impl DepthMapSource {
    /// Reads the depth image, and checks that its size is the registered one.
    pub fn load(&self) -> Result<DepthImage, InputError> {
        let image = match &self.format {
            ImageFormat::Png16 { scale } => image_files::read_png16(&self.path, *scale)?,
            ImageFormat::Pfm => image_files::read_pfm(&self.path)?,
            ImageFormat::NpyF32 => image_files::read_npy(&self.path)?,
            ImageFormat::ColmapBin => colmap::read_colmap_depth(&self.path)?,
            ImageFormat::Ptx { .. } | ImageFormat::E57 { .. } => lidar::read_scan(self)?,
        };
        if image.width != self.width || image.height != self.height {
            return Err(bad(
                &self.path,
                format!(
                    "image is {}x{}, the registered size is {}x{}",
                    image.width, image.height, self.width, self.height
                ),
            ));
        }
        Ok(image)
    }
}
