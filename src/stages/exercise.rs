//! A deterministic synthetic stage over generated keys: it exercises the stage runner, the
//! commit protocol and crash recovery with the same machinery the real stages use.

use serde::{Deserialize, Serialize};

use crate::format::{Column, ColumnValues, CubeKey};
use crate::store::{Plan, Replace, Result, Snapshot, Stage, UnitOutput, UnitSpec};

pub const NAME: &str = "synthetic";
/// Depth of the cube each unit covers; at most 8^UNIT_DEPTH units.
const UNIT_DEPTH: u8 = 4;
const ROW_DEPTH: u8 = 14;

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq, Eq)]
pub struct ExerciseStage {
    pub units: u32,
    pub rows_per_unit: u32,
    pub seed: u64,
    /// Sleep per unit, so tests can kill a run in the middle. Not a parameter of the output.
    #[serde(skip)]
    pub delay_ms: u64,
}

fn splitmix64(state: &mut u64) -> u64 {
    *state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut z = *state;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

impl ExerciseStage {
    /// The columns of one unit: keys inside the unit's cube, and every column kind a real stage
    /// writes (radius sum and count, histogram, u, v, p, q).
    pub fn unit_columns(&self, unit: u64) -> Vec<Column> {
        let side = 1u32 << UNIT_DEPTH;
        let (ux, uy, uz) = (
            (unit as u32) % side,
            (unit as u32 / side) % side,
            unit as u32 / (side * side),
        );
        let mut state = self.seed ^ unit.wrapping_mul(0xA24B_AED4_963E_E407);
        let span = 1u32 << (ROW_DEPTH - UNIT_DEPTH);
        let mut keys: Vec<CubeKey> = (0..self.rows_per_unit)
            .map(|_| {
                let r = splitmix64(&mut state);
                let (x, y, z) = ((r as u32) % span, ((r >> 21) as u32) % span, ((r >> 42) as u32) % span);
                CubeKey::new(ROW_DEPTH, ux * span + x, uy * span + y, uz * span + z)
            })
            .collect();
        keys.sort_unstable();
        keys.dedup();
        let n = keys.len();
        let mut floats = |width: usize| -> ColumnValues {
            ColumnValues::F32(
                (0..n * width)
                    .map(|_| (splitmix64(&mut state) % 2001) as f32 / 1000.0 - 1.0)
                    .collect(),
            )
        };
        let hist = floats(8);
        let u = floats(1);
        let v = floats(3);
        let p = floats(3);
        let q = floats(6);
        let radius_sum = floats(1);
        vec![
            Column::keys(keys),
            Column::new("radius_sum", 1, radius_sum),
            Column::new(
                "radius_count",
                1,
                ColumnValues::U32((0..n as u32).map(|i| i % 7 + 1).collect()),
            ),
            Column::new("hist", 8, hist),
            Column::new("u", 1, u),
            Column::new("v", 3, v),
            Column::new("p", 3, p),
            Column::new("q", 6, q),
        ]
    }
}

impl Stage for ExerciseStage {
    fn name(&self) -> &'static str {
        NAME
    }

    fn params(&self) -> Vec<u8> {
        crate::store::catalog::encode(self)
    }

    fn plan(&self, _base: &Snapshot<'_>) -> Result<Plan> {
        let max_units = 1u32 << (3 * UNIT_DEPTH);
        Ok(Plan {
            units: (0..u64::from(self.units.min(max_units)))
                .map(|id| UnitSpec {
                    id,
                    label: format!("unit {id}"),
                    cubes: 0,
                })
                .collect(),
            replace: Replace::All,
        })
    }

    fn run_unit(&self, _base: &Snapshot<'_>, unit: &UnitSpec) -> Result<UnitOutput> {
        if self.delay_ms > 0 {
            std::thread::sleep(std::time::Duration::from_millis(self.delay_ms));
        }
        Ok(UnitOutput {
            segments: vec![self.unit_columns(unit.id).into()],
            extra: Vec::new(),
            block_rows: 0,
        })
    }
}
