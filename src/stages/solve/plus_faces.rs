//! The cubes across a cut cube's `+` faces, as the level cut's difference terms gather them.

use crate::format::CubeKey;

/// The cubes across one `+` face of a cut cube (none, one, or the four children on its side),
/// each with its position in the cut when already known; no allocation per face.
#[derive(Default)]
pub(super) struct PlusNeighbours {
    cubes: [(CubeKey, Option<u32>); 4],
    len: usize,
}

impl PlusNeighbours {
    pub(super) fn one(cube: CubeKey, position: Option<u32>) -> PlusNeighbours {
        let mut out = PlusNeighbours::default();
        out.cubes[0] = (cube, position);
        out.len = 1;
        out
    }

    pub(super) fn four(cubes: [CubeKey; 4]) -> PlusNeighbours {
        PlusNeighbours {
            cubes: cubes.map(|cube| (cube, None)),
            len: 4,
        }
    }

    pub(super) fn len(&self) -> usize {
        self.len
    }

    pub(super) fn iter(&self) -> impl Iterator<Item = (CubeKey, Option<u32>)> + '_ {
        self.cubes.iter().take(self.len).copied()
    }
}
