//! The carried strip of the streaming simplification (`simplify`): triangles that wait for a
//! vertex to settle, found by vertex. It runs along every open seam, so it grows with the
//! scene's cross-section (2.3 M triangles at 415 M samples): a triangle takes a 24-byte slot
//! and a 4-byte mention at each corner, held inline for the four first triangles at a vertex,
//! where a map of triangles by id and a heap list of ids per vertex took about 150 bytes a
//! triangle.

use smallvec::SmallVec;

use super::FastMap;

/// A carried triangle: its corners (weld indices) and when it was carried.
#[derive(Clone, Copy)]
struct Slot {
    corners: [u32; 3],
    sequence: u64,
}

/// Carried triangles in reusable slots, with the slots at each vertex.
#[derive(Default)]
pub(super) struct CarriedStrip {
    slots: Vec<Slot>,
    /// Slots no triangle holds.
    free: Vec<u32>,
    /// Sequence number of the next triangle carried.
    next_sequence: u64,
    /// The slots of the triangles at each vertex that has any.
    at: FastMap<u32, SmallVec<[u32; 4]>>,
}

impl CarriedStrip {
    /// Triangles carried.
    pub(super) fn len(&self) -> usize {
        self.slots.len() - self.free.len()
    }

    pub(super) fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Bytes it takes, about (lists of more than four triangles at a vertex, on the heap, not
    /// counted).
    pub(super) fn heap_bytes(&self) -> u64 {
        (self.slots.capacity() * std::mem::size_of::<Slot>() + self.free.capacity() * 4) as u64
            + super::table_bytes::<(u32, SmallVec<[u32; 4]>)>(self.at.capacity())
    }

    /// Carries `triangle` (weld indices).
    pub(super) fn carry(&mut self, triangle: [u32; 3]) {
        let slot = Slot {
            corners: triangle,
            sequence: self.next_sequence,
        };
        self.next_sequence += 1;
        let index = match self.free.pop() {
            Some(index) => {
                if let Some(place) = self.slots.get_mut(index as usize) {
                    *place = slot;
                }
                index
            }
            None => {
                self.slots.push(slot);
                (self.slots.len() - 1) as u32
            }
        };
        for corner in triangle {
            self.at.entry(corner).or_default().push(index);
        }
    }

    /// Whether a carried triangle uses `vertex`.
    pub(super) fn holds(&self, vertex: u32) -> bool {
        self.at.contains_key(&vertex)
    }

    /// Uses of the edge between weld vertices `a` and `b` by carried triangles.
    pub(super) fn uses(&self, a: u32, b: u32) -> u32 {
        self.at.get(&a).map_or(0, |slots| {
            slots
                .iter()
                .filter(|&&slot| self.slots.get(slot as usize).is_some_and(|t| t.corners.contains(&b)))
                .count() as u32
        })
    }

    /// Removes the triangles at any of `vertices` and returns them in the order they were
    /// carried.
    pub(super) fn take_at(&mut self, vertices: &[u32]) -> Vec<[u32; 3]> {
        let mut taken: Vec<u32> = vertices
            .iter()
            .filter_map(|v| self.at.get(v))
            .flatten()
            .copied()
            .collect();
        taken.sort_unstable();
        taken.dedup();
        let mut triangles: Vec<Slot> = Vec::with_capacity(taken.len());
        for index in taken {
            let Some(&slot) = self.slots.get(index as usize) else {
                continue;
            };
            for corner in slot.corners {
                if let Some(at) = self.at.get_mut(&corner) {
                    at.retain(|other| *other != index);
                    if at.is_empty() {
                        self.at.remove(&corner);
                    }
                }
            }
            self.free.push(index);
            triangles.push(slot);
        }
        triangles.sort_unstable_by_key(|slot| slot.sequence);
        triangles.into_iter().map(|slot| slot.corners).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn triangles_come_back_in_carry_order_and_slots_are_reused() {
        let mut strip = CarriedStrip::default();
        strip.carry([1, 2, 3]);
        strip.carry([3, 4, 5]);
        strip.carry([5, 6, 1]);
        assert_eq!(strip.len(), 3);
        assert_eq!(
            (strip.uses(1, 3), strip.uses(3, 1), strip.uses(1, 5), strip.uses(2, 4)),
            (1, 1, 1, 0)
        );
        // Vertex 5's triangles, in the order they came, whatever order their slots are in.
        assert_eq!(strip.take_at(&[5, 6]), vec![[3, 4, 5], [5, 6, 1]]);
        assert!(!strip.holds(5) && !strip.holds(4) && strip.holds(1) && strip.holds(3));
        assert_eq!(strip.len(), 1);
        // A later triangle in a freed slot still comes after the earlier one.
        strip.carry([7, 8, 1]);
        assert_eq!(strip.slots.len(), 3);
        assert_eq!(strip.take_at(&[1]), vec![[1, 2, 3], [7, 8, 1]]);
        assert!(strip.is_empty() && strip.at.is_empty());
    }
}
