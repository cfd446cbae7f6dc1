//! Which part of u's zero set extraction meshes, and the default's decision from the capture.
//!
//! The zero set of u is closed; where no depth map measured a surface the solver still decides
//! inside or outside. A camera inside a room leaves space behind the walls that no map saw,
//! and the zero set there is invented: extraction keeps only the observed surface, with open
//! borders where the cameras stopped. An object seen from all around against empty background
//! is the other case: the background's free-space votes surround it, and the parts no map
//! measured are its own crevices and undersides, which a user expects closed. So by default
//! extraction reads a few of the snapshot's depth maps and meshes the watertight surface when
//! most of them see their content against empty background
//! (`kernels::background`: at least three quarters of the map's border invalid), the observed
//! surface otherwise.

use crate::inputs::Projection;
use crate::kernels::background::{BACKGROUND_BORDER_SHARE, invalid_border_share};
use crate::stages::ingest::{DepthMapRecord, depth_maps_at};
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

/// The most depth maps [`SurfaceChoice::resolve`] reads: evenly spread over the snapshot's
/// maps in id order. An odd count, so that the majority is never a tie.
const CAPTURE_SAMPLE_MAPS: usize = 9;

impl SurfaceChoice {
    /// The surface to mesh at `snapshot`: the choice itself, or for `Auto` the watertight
    /// surface when most of up to 9 of the snapshot's depth maps (evenly spread) see their
    /// content against empty background, else the observed surface. A map that cannot be read
    /// counts as not seeing background (with a warning): extraction does not need the maps
    /// otherwise.
    pub fn resolve(self, snapshot: &Snapshot<'_>) -> Result<Surface> {
        Ok(match self {
            SurfaceChoice::Observed => Surface::Observed,
            SurfaceChoice::Watertight => Surface::Watertight,
            SurfaceChoice::Whole => Surface::Whole,
            SurfaceChoice::Auto => {
                let (against_background, read) = maps_against_background(&depth_maps_at(snapshot)?);
                let surface = if 2 * against_background > read {
                    Surface::Watertight
                } else {
                    Surface::Observed
                };
                tracing::info!(
                    "extract: {against_background} of {read} depth map(s) read see their content against empty \
                     background: meshing the {} surface{}",
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

/// How many of up to [`CAPTURE_SAMPLE_MAPS`] of `maps` (evenly spread) see their content
/// against empty background, and how many were looked at.
fn maps_against_background(maps: &[(u64, DepthMapRecord)]) -> (usize, usize) {
    let take = maps.len().min(CAPTURE_SAMPLE_MAPS);
    let mut against = 0;
    for i in 0..take {
        // Evenly spread: the i-th of `take` equal parts of the list, at its middle.
        let Some((id, record)) = maps.get((2 * i + 1) * maps.len() / (2 * take)) else {
            continue;
        };
        if !matches!(record.source.projection, Projection::Pinhole { .. }) {
            continue;
        }
        match record.source.load() {
            Ok(image) => against += usize::from(invalid_border_share(&image) >= BACKGROUND_BORDER_SHARE),
            Err(e) => tracing::warn!(
                "extract: cannot read depth map {id:016x} ({}) to see whether it shows background, \
                 counted as not: {e}",
                record.source.path.display()
            ),
        }
    }
    (against, take)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::inputs::{DepthImage, DepthMapSource, write_pfm};
    use crate::stages::ingest::SampleStats;

    /// A 16 x 12 map: an object in the middle against an invalid border when `object`, else a
    /// wall filling the frame with a few dropouts on its border (a room's map).
    fn map(dir: &std::path::Path, name: &str, object: bool) -> (u64, DepthMapRecord) {
        let (width, height) = (16u32, 12u32);
        let depth = (0..width * height)
            .map(|index| {
                let (i, j) = (index % width, index / width);
                let inside = (4..12).contains(&i) && (3..9).contains(&j);
                let dropout = j == 0 && i <= 2;
                let valid = if object { inside } else { !dropout };
                if valid { 2.0 } else { 0.0 }
            })
            .collect();
        let path = dir.join(name);
        write_pfm(&path, &DepthImage { width, height, depth }).unwrap();
        let source = DepthMapSource::test_pinhole(
            path.to_str().unwrap(),
            (width, height),
            [20.0, 20.0, 8.0, 6.0],
            glam::DMat4::IDENTITY,
        );
        let record = DepthMapRecord {
            source,
            stats: SampleStats::default(),
            added_in: 1,
        };
        (name.len() as u64, record)
    }

    #[test]
    fn objects_against_background_are_told_from_rooms_by_the_majority_of_maps_read() {
        let dir = tempfile::tempdir().unwrap();
        let objects: Vec<_> = (0..5).map(|i| map(dir.path(), &format!("o{i}.pfm"), true)).collect();
        let rooms: Vec<_> = (0..5).map(|i| map(dir.path(), &format!("r{i}.pfm"), false)).collect();
        assert_eq!(maps_against_background(&objects), (5, 5));
        assert_eq!(maps_against_background(&rooms), (0, 5));
        // Many maps: only CAPTURE_SAMPLE_MAPS are read, spread over the whole list.
        let many: Vec<_> = (0..30)
            .map(|i: usize| map(dir.path(), &format!("m{i:02}.pfm"), !i.is_multiple_of(3)))
            .collect();
        let (against, read) = maps_against_background(&many);
        assert_eq!(read, CAPTURE_SAMPLE_MAPS);
        // The middles of nine equal parts of the thirty: the objects among them.
        let expected = (0..CAPTURE_SAMPLE_MAPS)
            .filter(|i| !((2 * i + 1) * 30 / (2 * CAPTURE_SAMPLE_MAPS)).is_multiple_of(3))
            .count();
        assert_eq!(against, expected);
        assert!(against > 0 && against < read, "{against} of {read}");
        // A map that cannot be read counts as not against background.
        let mut missing = objects.clone();
        if let Some((_, record)) = missing.get_mut(0) {
            record.source.path = dir.path().join("gone.pfm");
        }
        assert_eq!(maps_against_background(&missing), (4, 5));
        assert_eq!(maps_against_background(&[]), (0, 0));
    }
}
