//! Which part of u's zero set extraction meshes, and the default's decision from the capture.
//!
//! The zero set of u is closed; where no depth map measured a surface the solver still decides
//! inside or outside. A camera inside a room leaves space behind the walls that no map saw,
//! and the zero set there is invented: extraction keeps only the observed surface, with open
//! borders where the cameras stopped. An object seen from all around against empty background
//! is the other case: the background's free-space votes surround it, and the parts no map
//! measured are its own crevices and undersides, which a user expects closed. So by default
//! extraction meshes the watertight surface when the capture is an object against empty
//! background (`stages::capture`), the observed surface otherwise.

use crate::stages::capture::Capture;
use crate::store::{Result, Snapshot};

/// What to mesh, as asked for (`extract --open`, `--closed`, or neither).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum SurfaceChoice {
    /// Decided from the capture ([`SurfaceChoice::resolve`]).
    #[default]
    Auto,
    /// [`Surface::Observed`].
    Observed,
    /// [`Surface::Watertight`].
    Watertight,
    /// [`Surface::Whole`].
    Whole,
}

/// What extraction meshes (module docs of `stages::extract`, "Observed surface only").
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Surface {
    /// Only the surface depth maps saw, with open borders where they stopped.
    Observed,
    /// Every connected piece of the zero set that holds observed surface, whole: closed where
    /// no map measured the surface. Pieces without observed surface (bubbles of the zero set in
    /// free space, where outliers pulled u below zero) are dropped where the unit that meshes
    /// them holds them whole; a piece that reaches another unit is kept.
    Watertight,
    /// The whole zero set, closed at the root cube.
    Whole,
}

impl From<Surface> for SurfaceChoice {
    fn from(surface: Surface) -> SurfaceChoice {
        match surface {
            Surface::Observed => SurfaceChoice::Observed,
            Surface::Watertight => SurfaceChoice::Watertight,
            Surface::Whole => SurfaceChoice::Whole,
        }
    }
}

impl SurfaceChoice {
    /// The surface to mesh at `snapshot`: the choice itself, or for `Auto` the watertight
    /// surface when the capture is an object against empty background (`stages::capture`), else the
    /// observed surface.
    pub fn resolve(self, snapshot: &Snapshot<'_>) -> Result<Surface> {
        Ok(match self {
            SurfaceChoice::Observed => Surface::Observed,
            SurfaceChoice::Watertight => Surface::Watertight,
            SurfaceChoice::Whole => Surface::Whole,
            SurfaceChoice::Auto => {
                let capture = Capture::of(snapshot, "extract")?;
                let surface = if capture.is_object() {
                    Surface::Watertight
                } else {
                    Surface::Observed
                };
                tracing::info!(
                    "extract: {}: meshing the {} surface{}",
                    capture.describe(),
                    if surface == Surface::Watertight {
                        "watertight"
                    } else {
                        "observed"
                    },
                    if surface == Surface::Watertight {
                        " (--open for only what the maps saw)"
                    } else {
                        " (--closed for the whole zero set)"
                    }
                );
                surface
            }
        })
    }
}
