//! What kind of capture a snapshot's depth maps are: an object seen against empty background,
//! or a scene (a room, a street, a city) whose surfaces fill the frames.
//!
//! An object seen from all around in empty space leaves most of each map's border invalid:
//! nothing lies behind it. A camera inside a room or over a city sees surface up to the frame's
//! edges. The defaults that differ between the two read it from here: extraction meshes an
//! object watertight and a scene's observed surface alone (`stages::extract`, `Surface`), and
//! `solve` fits an object by smooth signed distance and a scene by TGV
//! (`stages::solve::MethodChoice`).

use crate::inputs::{DepthMapSource, DepthRows, InputError, Projection};
use crate::kernels::background::{BACKGROUND_BORDER_SHARE, BorderCount};
use crate::stages::ingest::{DepthMapRecord, depth_maps_at};
use crate::store::{Result, Snapshot};

/// The most depth maps [`Capture::of`] reads: evenly spread over the snapshot's maps in id
/// order. An odd count, so that the majority is never a tie.
const CAPTURE_SAMPLE_MAPS: usize = 9;

/// How many of the depth maps looked at see their content against empty background.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Capture {
    /// Maps whose border is at least [`BACKGROUND_BORDER_SHARE`] invalid.
    pub against_background: usize,
    /// Maps looked at: up to [`CAPTURE_SAMPLE_MAPS`], evenly spread.
    pub read: usize,
}

impl Capture {
    /// The capture of `snapshot`'s depth maps, read from up to 9 of them (evenly spread in id
    /// order; spherical maps count as scenes). A map that cannot be read counts as not seeing
    /// background, with a warning that names `verb`: the stages that ask need the maps for
    /// nothing else.
    pub fn of(snapshot: &Snapshot<'_>, verb: &str) -> Result<Capture> {
        Ok(maps_against_background(&depth_maps_at(snapshot)?, verb))
    }

    /// Whether most of the maps read see an object against empty background.
    pub fn is_object(&self) -> bool {
        2 * self.against_background > self.read
    }

    /// The counts, for a log line.
    pub fn describe(&self) -> String {
        format!(
            "{} of {} depth map(s) read see their content against empty background",
            self.against_background, self.read
        )
    }
}

/// How many of up to [`CAPTURE_SAMPLE_MAPS`] of `maps` (evenly spread) see their content
/// against empty background, and how many were looked at.
fn maps_against_background(maps: &[(u64, DepthMapRecord)], verb: &str) -> Capture {
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
        match border_of(&record.source) {
            Ok(border) => against += usize::from(border.invalid_share() >= BACKGROUND_BORDER_SHARE),
            Err(e) => tracing::warn!(
                "{verb}: cannot read depth map {id:016x} ({}) to see whether it shows background, \
                 counted as not: {e}",
                record.source.path.display()
            ),
        }
    }
    Capture {
        against_background: against,
        read: take,
    }
}

/// `source`'s border pixels, read row by row: one row in memory, whatever the map's size
/// (a whole 8000 x 6000 map would take 192 MB).
fn border_of(source: &DepthMapSource) -> Result<BorderCount, InputError> {
    let mut rows = DepthRows::open_streaming(source)?;
    let mut row = vec![f32::NAN; source.width as usize];
    let mut border = BorderCount::default();
    let mut j = 0;
    while rows.next_row(&mut row)? {
        border.add_row(&row, j, source.height);
        j += 1;
    }
    Ok(border)
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
        assert_eq!(
            maps_against_background(&objects, "test"),
            Capture {
                against_background: 5,
                read: 5
            }
        );
        assert_eq!(
            maps_against_background(&rooms, "test"),
            Capture {
                against_background: 0,
                read: 5
            }
        );
        // Many maps: only CAPTURE_SAMPLE_MAPS are read, spread over the whole list.
        let many: Vec<_> = (0..30)
            .map(|i: usize| map(dir.path(), &format!("m{i:02}.pfm"), !i.is_multiple_of(3)))
            .collect();
        let Capture {
            against_background: against,
            read,
        } = maps_against_background(&many, "test");
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
        assert_eq!(
            maps_against_background(&missing, "test"),
            Capture {
                against_background: 4,
                read: 5
            }
        );
        assert_eq!(
            maps_against_background(&[], "test"),
            Capture {
                against_background: 0,
                read: 0
            }
        );
    }

    #[test]
    fn the_border_read_row_by_row_is_the_border_of_the_whole_map() {
        let dir = tempfile::tempdir().unwrap();
        for object in [true, false] {
            let (_, record) = map(dir.path(), &format!("{object}.pfm"), object);
            let streamed = border_of(&record.source).unwrap();
            let whole = record.source.load().unwrap();
            // 16 x 12: two rows of 16 and the two ends of the 10 rows between.
            assert_eq!(streamed.pixels, 2 * 16 + 2 * 10);
            assert_eq!(
                streamed.invalid_share(),
                crate::kernels::background::invalid_border_share(&whole)
            );
            assert_eq!(streamed.invalid_share() >= BACKGROUND_BORDER_SHARE, object);
        }
    }
}
