//! Cube keys: the 96-bit Morton code of a cube's minimum corner at full resolution, plus depth.
//!
//! Invariant: the numeric order of [`CubeKey::raw`] is (morton, depth), so an ancestor sorts
//! immediately before its descendants and every subtree is one contiguous key range.

use std::cmp::Ordering;
use std::fmt;

/// Deepest level a cube can have: each axis is addressed with 32 bits.
pub const MAX_DEPTH: u8 = 32;

/// Width of a key's encoding, in bytes (big-endian `u128`).
pub const KEY_BYTES: usize = size_of::<u128>();

#[derive(
    Clone,
    Copy,
    PartialEq,
    Eq,
    PartialOrd,
    Ord,
    Hash,
    Default,
    bytemuck::Pod,
    bytemuck::Zeroable,
    serde::Serialize,
    serde::Deserialize,
)]
/// A cube's key: the 96-bit Morton code of its minimum corner at full resolution, then its
/// depth (format-spec.md, "Cube keys"). Keys order as (Morton code, depth), so an ancestor sorts
/// immediately before its descendants and every subtree is one contiguous key range.
#[repr(transparent)]
pub struct CubeKey(u128);

/// Mask with blocks of `s` set bits every `3 s` bits, over 96 bits.
const fn spread_mask(s: u32) -> u128 {
    let mut mask = 0u128;
    let mut base = 0;
    while base < 96 {
        let mut bit = 0;
        while bit < s {
            mask |= 1u128 << (base + bit);
            bit += 1;
        }
        base += 3 * s;
    }
    mask
}

const SPREAD_MASKS: [(u32, u128); 5] = [
    (16, spread_mask(16)),
    (8, spread_mask(8)),
    (4, spread_mask(4)),
    (2, spread_mask(2)),
    (1, spread_mask(1)),
];

/// The 96 bits of a Morton code.
const MORTON_MASK: u128 = (1u128 << 96) - 1;

/// The Morton code's bits of the x axis (bits 3i); y's and z's are these shifted by 1 and 2.
const AXIS_BITS: u128 = spread_mask(1);

/// One axis's share of a Morton code: bit i of the full-resolution coordinate `v` at bit 3i.
/// A key's code is `axis_bits(x) | axis_bits(y) << 1 | axis_bits(z) << 2`
/// ([`CubeKey::from_morton`]).
pub fn axis_bits(v: u32) -> u128 {
    spread3(v)
}

/// The [`axis_bits`] of a key's minimum corner along `axis` (0, 1, 2 for x, y, z), read off
/// its Morton code without decoding it.
pub fn corner_axis_bits(key: CubeKey, axis: usize) -> u128 {
    (key.morton() >> axis) & AXIS_BITS
}

/// [`axis_bits`] of `a + b` from those of `a` and `b` (dilated addition), wrapping past 2^32.
pub fn add_axis_bits(a: u128, b: u128) -> u128 {
    ((a | !AXIS_BITS).wrapping_add(b)) & AXIS_BITS
}

/// [`axis_bits`] of `a - b` from those of `a` and `b` (dilated subtraction), wrapping below 0.
pub fn sub_axis_bits(a: u128, b: u128) -> u128 {
    (a & AXIS_BITS).wrapping_sub(b) & AXIS_BITS
}

/// The index of the last key at or below `key` in `sorted` (ascending and distinct), searched
/// from `from` on by doubling steps and then bisection: keys asked in ascending order are
/// found near the last one found, where a bisection of the whole slice missed the cache at
/// every step. A key below `sorted[from]` is searched in the whole slice. The same answer as
/// `sorted.partition_point(|k| *k <= key).checked_sub(1)`.
pub fn last_at_or_below_from(sorted: &[CubeKey], from: usize, key: CubeKey) -> Option<usize> {
    if sorted.get(from).is_none_or(|first| key < *first) {
        return sorted.partition_point(|k| *k <= key).checked_sub(1);
    }
    // sorted[low] <= key < sorted[high], with high = len past the end.
    let (mut low, mut step) = (from, 1);
    let high = loop {
        let probe = from.saturating_add(step);
        match sorted.get(probe) {
            Some(k) if *k <= key => {
                low = probe;
                step = step.saturating_mul(2);
            }
            _ => break probe.min(sorted.len()),
        }
    };
    let window = sorted.get(low..high)?;
    (low + window.partition_point(|k| *k <= key)).checked_sub(1)
}

/// The index of `key` in `sorted` (ascending and distinct), searched as
/// [`last_at_or_below_from`] does. The same answer as `sorted.binary_search(&key).ok()`.
pub fn find_sorted_from(sorted: &[CubeKey], from: usize, key: CubeKey) -> Option<usize> {
    last_at_or_below_from(sorted, from, key).filter(|&i| sorted.get(i) == Some(&key))
}

/// Where each block of a sorted key list's Morton range begins in it, so that a key is looked
/// up among the few keys of its block instead of by a search over the whole list. The range is
/// that of the smallest cube holding every key, split into 8^k blocks (cubes of one depth), k
/// the largest with 8^k at most eight times the keys: at most 32 bytes a key. With at most one
/// block a key, a cut along a surface crowds its keys into the blocks the surface passes
/// through, and the lookups were barely faster than a galloping search (RedKitchen's
/// extraction: 4 % of the dual cells' time against 29 % with eight).
#[derive(Clone, Debug, Default)]
pub struct KeyBlocks {
    /// The full-resolution Morton code of the smallest cube holding the keys, and how many
    /// codes that cube spans (0 for no keys).
    base: u128,
    span: u128,
    /// A block spans `1 << block_shift` codes.
    block_shift: u32,
    /// Per block, the index of the first key at or after its start.
    starts: Vec<u32>,
}

impl KeyBlocks {
    /// The blocks of `sorted` (ascending; an unsorted list gives wrong answers, never a panic).
    pub fn of(sorted: &[CubeKey]) -> KeyBlocks {
        let (Some(&first), Some(&last)) = (sorted.first(), sorted.last()) else {
            return KeyBlocks::default();
        };
        let holder = first.smallest_common_ancestor(last);
        let levels = u32::from(MAX_DEPTH - holder.depth());
        // One block (the whole list) where the starts would not fit a u32.
        let block_levels = if u32::try_from(sorted.len()).is_ok() {
            (sorted.len().ilog2() / 3 + 1).min(levels)
        } else {
            0
        };
        let block_shift = 3 * (levels - block_levels);
        let mut starts = Vec::with_capacity(1 << (3 * block_levels));
        let mut next = 0usize;
        for block in 0..1u128 << (3 * block_levels) {
            while sorted
                .get(next)
                .is_some_and(|k| k.morton().saturating_sub(holder.morton()) >> block_shift < block)
            {
                next += 1;
            }
            starts.push(next as u32);
        }
        KeyBlocks {
            base: holder.morton(),
            span: 1 << (3 * levels),
            block_shift,
            starts,
        }
    }

    /// `sorted.partition_point(|k| *k <= key)` for the list the blocks were made of.
    #[inline]
    pub fn partition_point(&self, sorted: &[CubeKey], key: CubeKey) -> usize {
        let Some(offset) = key.morton().checked_sub(self.base) else {
            return 0;
        };
        if offset >= self.span {
            return sorted.len();
        }
        // Keys before the key's block are below it and keys after it above it.
        let block = (offset >> self.block_shift) as usize;
        let start = |block: usize| self.starts.get(block).map_or(sorted.len(), |&s| s as usize);
        let (start, end) = (start(block), start(block + 1));
        start
            + sorted
                .get(start..end)
                .map_or(0, |keys| keys.partition_point(|k| *k <= key))
    }

    /// The index of the key that is `key` or an ancestor of it, if the list holds one.
    #[inline]
    pub fn ancestor_or_self(&self, sorted: &[CubeKey], key: CubeKey) -> Option<usize> {
        let at = self.partition_point(sorted, key).checked_sub(1)?;
        sorted
            .get(at)
            .is_some_and(|k| k.is_ancestor_or_self_of(key))
            .then_some(at)
    }
}

/// Moves bit i of `v` to bit 3i.
fn spread3(v: u32) -> u128 {
    let mut x = u128::from(v);
    for (s, mask) in SPREAD_MASKS {
        x = (x | (x << (2 * s))) & mask;
    }
    x
}

/// `SPREAD_BYTE[b]`: bit i of the byte `b` at bit 3i (24 bits), [`spread3`] of one byte.
#[expect(
    clippy::indexing_slicing,
    reason = "a constant evaluation over 0..256 of a 256-entry table"
)]
const SPREAD_BYTE: [u32; 256] = {
    let mut table = [0u32; 256];
    let mut b = 0;
    while b < 256 {
        let mut bit = 0;
        while bit < 8 {
            table[b] |= ((b as u32 >> bit) & 1) << (3 * bit);
            bit += 1;
        }
        b += 1;
    }
    table
};

/// `spread3(x) | spread3(y) << 1 | spread3(z) << 2`, a byte of each axis at a time from a
/// 1 KiB table: 12 lookups and 64-bit shifts instead of the 30 masked 128-bit shifts of three
/// [`spread3`] calls (ingest encodes a key for every sample; the shifts were a fifth of its
/// per-sample work in `perf annotate`).
#[inline]
fn interleave3(x: u32, y: u32, z: u32) -> u128 {
    // Bytes k of the three coordinates interleave into bits 24k to 24k + 23.
    let bytes = |k: u32| -> u64 {
        #[expect(
            clippy::indexing_slicing,
            reason = "a byte (masked to 0xff) indexes a 256-entry table"
        )]
        let spread = |v: u32| u64::from(SPREAD_BYTE[((v >> (8 * k)) & 0xff) as usize]);
        spread(x) | spread(y) << 1 | spread(z) << 2
    };
    let low = bytes(0) | bytes(1) << 24;
    let high = bytes(2) | bytes(3) << 24;
    u128::from(low) | u128::from(high) << 48
}

/// Inverse of [`spread3`] for the bits at positions 3i.
fn compact3(code: u128) -> u32 {
    let mut x = code & spread_mask(1);
    for s in [1u32, 2, 4, 8, 16] {
        x = (x | (x >> (2 * s))) & spread_mask(2 * s);
    }
    (x & 0xFFFF_FFFF) as u32
}

impl CubeKey {
    /// The key of the cube at `depth` with integer coordinates `(x, y, z)` in `[0, 2^depth)`.
    ///
    /// Panics in debug builds if a coordinate is out of range for the depth.
    pub fn new(depth: u8, x: u32, y: u32, z: u32) -> CubeKey {
        debug_assert!(depth <= MAX_DEPTH);
        let shift = u32::from(MAX_DEPTH - depth);
        let (fx, fy, fz) = if shift >= 32 {
            (0, 0, 0)
        } else {
            (x << shift, y << shift, z << shift)
        };
        CubeKey::from_full_resolution(depth, fx, fy, fz)
    }

    /// Key from the full-resolution (32-bit) minimum corner; low bits below `depth` must be zero.
    pub fn from_full_resolution(depth: u8, fx: u32, fy: u32, fz: u32) -> CubeKey {
        CubeKey((interleave3(fx, fy, fz) << 8) | u128::from(depth))
    }

    /// The key of the cube at `depth` whose minimum corner has the 96-bit Morton code `code`
    /// (see [`axis_bits`]); bits below the cube's size must be zero.
    pub fn from_morton(code: u128, depth: u8) -> CubeKey {
        CubeKey(((code & MORTON_MASK) << 8) | u128::from(depth))
    }

    /// The key with these 128 bits (not checked; see [`CubeKey::is_well_formed`]).
    pub const fn from_raw(raw: u128) -> CubeKey {
        CubeKey(raw)
    }

    /// The key's 128 bits.
    pub const fn raw(self) -> u128 {
        self.0
    }

    /// The cube's depth (0 for the root).
    pub fn depth(self) -> u8 {
        (self.0 & 0xFF) as u8
    }

    /// The cube's side in root units, 2^-depth: built from its bits, where `powi` was a call
    /// per cube in the solver's loops (the same value: a power of two is exact either way).
    pub fn side(self) -> f64 {
        f64::from_bits((1023 - u64::from(self.depth())) << 52)
    }

    /// The 96-bit Morton code of the minimum corner at full resolution.
    pub fn morton(self) -> u128 {
        self.0 >> 8
    }

    /// The Morton code at the cube's own depth: [`CubeKey::morton`] with the finer bits
    /// shifted out, so that the 8 children of a parent, and the 64 cubes of a 4 x 4 x 4
    /// brick, have consecutive codes.
    pub fn morton_at_own_depth(self) -> u128 {
        let finer = 3 * u32::from(MAX_DEPTH.saturating_sub(self.depth()));
        self.morton().checked_shr(finer).unwrap_or(0)
    }

    /// Full-resolution minimum corner.
    pub fn corner_full_resolution(self) -> [u32; 3] {
        let m = self.morton();
        [compact3(m), compact3(m >> 1), compact3(m >> 2)]
    }

    /// Integer coordinates at the key's own depth.
    pub fn coords(self) -> [u32; 3] {
        let shift = u32::from(MAX_DEPTH - self.depth());
        self.corner_full_resolution().map(|c| c.checked_shr(shift).unwrap_or(0))
    }

    /// Whether the depth is valid and the corner is aligned to the cube's size.
    pub fn is_well_formed(self) -> bool {
        let depth = self.depth();
        if depth > MAX_DEPTH || (self.0 >> 104) != 0 {
            return false;
        }
        let shift = u32::from(MAX_DEPTH - depth);
        let low_mask: u32 = if shift >= 32 { u32::MAX } else { (1u32 << shift) - 1 };
        self.corner_full_resolution().iter().all(|c| c & low_mask == 0)
    }

    /// The same cube keyed in a root of twice the side in which the old root is the child
    /// `octant` (per axis 0 or 1): depth + 1, and each full-resolution coordinate becomes
    /// `octant << 31 | c >> 1`. Exact, and order-preserving over any set of keys, because a
    /// cube above [`MAX_DEPTH`] has a zero lowest coordinate bit. `None` at [`MAX_DEPTH`].
    pub fn in_doubled_root(self, octant: [u32; 3]) -> Option<CubeKey> {
        let depth = self.depth();
        if depth >= MAX_DEPTH {
            return None;
        }
        let [x, y, z] = self.corner_full_resolution();
        let widen = |c: u32, o: u32| ((o & 1) << 31) | (c >> 1);
        Some(CubeKey::from_full_resolution(
            depth + 1,
            widen(x, octant[0]),
            widen(y, octant[1]),
            widen(z, octant[2]),
        ))
    }

    /// The parent cube; `None` for the root.
    pub fn parent(self) -> Option<CubeKey> {
        let depth = self.depth();
        if depth == 0 {
            return None;
        }
        if depth > MAX_DEPTH {
            let [x, y, z] = self.coords();
            return Some(CubeKey::new(depth - 1, x >> 1, y >> 1, z >> 1));
        }
        // The parent's corner is the cube's with the Morton bits below the parent's size
        // cleared: the same key as through coordinates, without decoding them.
        Some(CubeKey((self.morton_at_depth(depth - 1) << 8) | u128::from(depth - 1)))
    }

    /// The smallest cube that holds both this one and `other`: their deepest common ancestor
    /// (or either, if one holds the other).
    pub fn smallest_common_ancestor(self, other: CubeKey) -> CubeKey {
        let differing = (self.morton() ^ other.morton()) & MORTON_MASK;
        // Leading 3-bit groups (one per depth) the two codes share, of the code's 96 bits.
        let shared = (differing.leading_zeros() - 32) / 3;
        let depth = u8::try_from(shared)
            .unwrap_or(MAX_DEPTH)
            .min(self.depth())
            .min(other.depth());
        CubeKey((self.morton_at_depth(depth) << 8) | u128::from(depth))
    }

    /// The Morton code's bits that address cubes of `depth` (at most [`MAX_DEPTH`]); finer
    /// bits, and bits past the code's 96, cleared.
    fn morton_at_depth(self, depth: u8) -> u128 {
        let finer = 3 * u32::from(MAX_DEPTH - depth);
        let code = self.morton() & MORTON_MASK;
        if finer >= 96 { 0 } else { code & !((1u128 << finer) - 1) }
    }

    /// The cube of the same size across the `+` face of `axis` (0, 1, 2 for x, y, z), if it
    /// lies inside the root.
    pub fn plus_neighbour(self, axis: usize) -> Option<CubeKey> {
        let depth = self.depth();
        if depth > MAX_DEPTH || axis > 2 {
            let mut c = self.coords();
            let max = if depth >= MAX_DEPTH {
                u32::MAX
            } else {
                (1u32 << depth) - 1
            };
            let slot = c.get_mut(axis)?;
            *slot = slot.checked_add(1).filter(|next| *next <= max)?;
            return Some(CubeKey::new(depth, c[0], c[1], c[2]));
        }
        // One cube added to the axis's coordinate in place in the interleaved code
        // (add_axis_bits), unless every bit of it at the cube's size is set: the last cube
        // along the axis (and the root, which has no such bits).
        let code = self.morton_at_depth(depth);
        let step = 1u128 << (3 * u32::from(MAX_DEPTH - depth));
        let coordinate = (code >> axis) & AXIS_BITS;
        if coordinate == AXIS_BITS & !(step - 1) {
            return None;
        }
        let next = add_axis_bits(coordinate, step) << axis;
        Some(CubeKey(((code & !(AXIS_BITS << axis) | next) << 8) | u128::from(depth)))
    }

    /// The key range `[self, end]` covering this cube and all its descendants.
    pub fn subtree_last(self) -> CubeKey {
        let shift = 3 * u32::from(MAX_DEPTH - self.depth());
        let span: u128 = if shift >= 96 {
            (1u128 << 96) - 1
        } else {
            (1u128 << shift) - 1
        };
        CubeKey(((self.morton() | span) << 8) | u128::from(MAX_DEPTH))
    }

    /// Whether `other` lies in this cube's subtree.
    pub fn is_ancestor_or_self_of(self, other: CubeKey) -> bool {
        other.depth() >= self.depth() && self <= other && other <= self.subtree_last()
    }

    /// Big-endian bytes: byte order equals key order (catalog keys).
    pub fn to_be_bytes(self) -> [u8; KEY_BYTES] {
        self.0.to_be_bytes()
    }

    /// The key of big-endian bytes.
    pub fn from_be_bytes(bytes: [u8; KEY_BYTES]) -> CubeKey {
        CubeKey(u128::from_be_bytes(bytes))
    }
}

impl fmt::Debug for CubeKey {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let [x, y, z] = self.coords();
        write!(f, "d{}:({},{},{})", self.depth(), x, y, z)
    }
}

impl fmt::Display for CubeKey {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:026x}", self.0)
    }
}

/// redb key type that compares cube keys by their numeric order explicitly (format-spec.md, "Cube keys").
#[derive(Debug)]
pub struct CubeKeyColumn;

impl redb::Value for CubeKeyColumn {
    type SelfType<'a> = CubeKey;
    type AsBytes<'a> = [u8; KEY_BYTES];

    fn fixed_width() -> Option<usize> {
        Some(KEY_BYTES)
    }

    fn from_bytes<'a>(data: &'a [u8]) -> CubeKey
    where
        Self: 'a,
    {
        // redb only hands back bytes produced by `as_bytes`; a short slice would be a redb bug,
        // and mapping it to the zero key keeps decoding panic-free.
        let bytes: [u8; KEY_BYTES] = data.try_into().unwrap_or([0; KEY_BYTES]);
        CubeKey::from_be_bytes(bytes)
    }

    fn as_bytes<'a, 'b: 'a>(value: &'a CubeKey) -> [u8; KEY_BYTES]
    where
        Self: 'b,
    {
        value.to_be_bytes()
    }

    fn type_name() -> redb::TypeName {
        redb::TypeName::new("octstore::CubeKey")
    }
}

impl redb::Key for CubeKeyColumn {
    fn compare(data1: &[u8], data2: &[u8]) -> Ordering {
        let a = <Self as redb::Value>::from_bytes(data1);
        let b = <Self as redb::Value>::from_bytes(data2);
        a.cmp(&b)
    }
}

#[cfg(test)]
#[expect(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::indexing_slicing,
    reason = "tests: a panic is the failure report"
)]
mod tests {
    #[test]
    fn a_parents_children_have_consecutive_codes_at_their_depth() {
        let parent = super::CubeKey::new(7, 5, 9, 2);
        let codes: Vec<u128> = (0..8u32)
            .map(|i| super::CubeKey::new(8, 10 + (i & 1), 18 + (i >> 1 & 1), 4 + (i >> 2)).morton_at_own_depth())
            .collect();
        let first = parent.morton_at_own_depth() * 8;
        assert_eq!(codes, (first..first + 8).collect::<Vec<_>>());
        assert_eq!(super::CubeKey::new(0, 0, 0, 0).morton_at_own_depth(), 0);
    }

    use super::*;
    use proptest::prelude::*;

    proptest! {
        #[test]
        fn the_byte_table_interleaves_as_the_bit_spreads_do(x: u32, y: u32, z: u32) {
            prop_assert_eq!(interleave3(x, y, z), spread3(x) | spread3(y) << 1 | spread3(z) << 2);
        }
    }

    #[test]
    fn the_byte_table_interleaves_single_bits_and_extremes() {
        let mut values = vec![0, u32::MAX, 0x8000_0000, 0x7fff_ffff];
        values.extend((0..32).map(|bit| 1u32 << bit));
        for &x in &values {
            for &y in &values {
                for &z in &values {
                    assert_eq!(interleave3(x, y, z), spread3(x) | spread3(y) << 1 | spread3(z) << 2);
                }
            }
        }
    }

    proptest! {
        #[test]
        fn the_smallest_common_ancestor_is_the_deepest_cube_holding_both(
            a in (0u8..=MAX_DEPTH, any::<[u32; 3]>()),
            b in (0u8..=MAX_DEPTH, any::<[u32; 3]>()),
        ) {
            let key = |(depth, [x, y, z]): (u8, [u32; 3])| {
                let keep = |c: u32| c.checked_shr(u32::from(MAX_DEPTH - depth)).unwrap_or(0);
                CubeKey::new(depth, keep(x), keep(y), keep(z))
            };
            let (a, b) = (key(a), key(b));
            let common = a.smallest_common_ancestor(b);
            // By the parent chain: the first ancestor of `a` that holds `b`.
            let mut expected = a;
            while !expected.is_ancestor_or_self_of(b) {
                expected = expected.parent().expect("the root holds every cube");
            }
            prop_assert_eq!(common, expected);
            prop_assert_eq!(b.smallest_common_ancestor(a), expected);
        }
    }

    proptest! {
        #[test]
        fn key_blocks_split_the_search_as_a_whole_list_search_does(
            keys in proptest::collection::vec((0u8..=12, any::<[u32; 3]>()), 0..300),
            probes in proptest::collection::vec((0u8..=MAX_DEPTH, any::<[u32; 3]>()), 1..50),
            corner in any::<[u32; 3]>(),
        ) {
            // Keys at depths 0 to 12 under one cube of depth 8 (or anywhere, for a few), probes at
            // any depth near it or anywhere.
            let key = |(depth, [x, y, z]): (u8, [u32; 3]), near: bool| {
                let place = |c: u32, at: u32| {
                    let c = if near { (at & !0xff_ffff) | (c & 0xff_ffff) } else { c };
                    c.checked_shr(u32::from(MAX_DEPTH - depth)).unwrap_or(0)
                };
                CubeKey::new(depth, place(x, corner[0]), place(y, corner[1]), place(z, corner[2]))
            };
            let mut sorted: Vec<CubeKey> = keys.iter().enumerate().map(|(i, k)| key(*k, i % 16 != 0)).collect();
            sorted.sort();
            sorted.dedup();
            let blocks = KeyBlocks::of(&sorted);
            for (i, probe) in probes.iter().enumerate() {
                let probe = key(*probe, i % 4 != 0);
                prop_assert_eq!(blocks.partition_point(&sorted, probe), sorted.partition_point(|k| *k <= probe));
                let expected = sorted.partition_point(|k| *k <= probe).checked_sub(1)
                    .filter(|&at| sorted.get(at).is_some_and(|k| k.is_ancestor_or_self_of(probe)));
                prop_assert_eq!(blocks.ancestor_or_self(&sorted, probe), expected);
            }
        }
    }

    #[test]
    fn ancestor_sorts_before_descendants() {
        let root = CubeKey::new(0, 0, 0, 0);
        let child = CubeKey::new(1, 0, 0, 0);
        let grandchild = CubeKey::new(2, 1, 1, 1);
        let other = CubeKey::new(1, 1, 0, 0);
        assert!(root < child && child < grandchild && grandchild < other);
        assert!(child.is_ancestor_or_self_of(grandchild));
        assert!(!other.is_ancestor_or_self_of(grandchild));
        assert!(root.is_ancestor_or_self_of(other));
    }

    #[test]
    fn a_side_is_the_power_of_one_half() {
        for depth in 0..=u8::MAX {
            let key = CubeKey::from_raw(u128::from(depth));
            assert_eq!(
                key.side().to_bits(),
                0.5f64.powi(i32::from(depth)).to_bits(),
                "depth {depth}"
            );
        }
    }

    #[test]
    fn a_search_from_a_place_finds_what_bisection_finds() {
        let sorted: Vec<CubeKey> = (0..300u32)
            .map(|i| CubeKey::new(9, 3 * i, i % 7, 0))
            .collect::<std::collections::BTreeSet<_>>()
            .into_iter()
            .collect();
        for probe in (0..400u32)
            .map(|i| CubeKey::new(9, 3 * i / 2, (i / 2) % 7, 0))
            .chain([CubeKey::new(0, 0, 0, 0)])
        {
            for from in [0, 1, 2, 50, 150, 299, 300, 1000] {
                assert_eq!(
                    find_sorted_from(&sorted, from, probe),
                    sorted.binary_search(&probe).ok(),
                    "{probe:?} from {from}"
                );
                assert_eq!(
                    last_at_or_below_from(&sorted, from, probe),
                    sorted.partition_point(|k| *k <= probe).checked_sub(1),
                    "{probe:?} from {from}"
                );
            }
        }
    }

    proptest! {
        #[test]
        fn coordinates_round_trip(depth in 0u8..=32, x: u32, y: u32, z: u32) {
            let mask = if depth == 0 { 0 } else { u32::MAX >> (32 - u32::from(depth)) };
            let (x, y, z) = (x & mask, y & mask, z & mask);
            let key = CubeKey::new(depth, x, y, z);
            prop_assert_eq!(key.coords(), [x, y, z]);
            prop_assert_eq!(key.depth(), depth);
            prop_assert!(key.is_well_formed());
            if let Some(parent) = key.parent() {
                prop_assert!(parent < key);
                prop_assert!(parent.is_ancestor_or_self_of(key));
                prop_assert!(key <= parent.subtree_last());
            }
        }

        #[test]
        fn doubling_the_root_keeps_cubes_order_and_ancestry(
            depths in proptest::array::uniform2(0u8..32),
            coords in proptest::array::uniform6(any::<u32>()),
            octant in proptest::array::uniform3(0u32..2),
        ) {
            let key = |depth: u8, c: &[u32]| {
                let mask = if depth == 0 { 0 } else { u32::MAX >> (32 - u32::from(depth)) };
                CubeKey::new(depth, c[0] & mask, c[1] & mask, c[2] & mask)
            };
            let (a, b) = (key(depths[0], &coords[..3]), key(depths[1], &coords[3..]));
            let (ga, gb) = (a.in_doubled_root(octant).unwrap(), b.in_doubled_root(octant).unwrap());
            prop_assert!(ga.is_well_formed() && gb.is_well_formed());
            prop_assert_eq!(ga.depth(), a.depth() + 1);
            prop_assert_eq!(ga.cmp(&gb), a.cmp(&b));
            prop_assert_eq!(ga.is_ancestor_or_self_of(gb), a.is_ancestor_or_self_of(b));
            // The old root is the new root's child `octant`, and every cube lies inside it.
            let old_root = CubeKey::new(0, 0, 0, 0).in_doubled_root(octant).unwrap();
            prop_assert_eq!(old_root, CubeKey::new(1, octant[0], octant[1], octant[2]));
            prop_assert!(old_root.is_ancestor_or_self_of(ga));
            // Same position inside the old root's cube: coordinates at the new depth, less
            // the octant's offset, are the old ones.
            let offset = |o: u32| o << a.depth();
            let [x, y, z] = ga.coords();
            prop_assert_eq!([x - offset(octant[0]), y - offset(octant[1]), z - offset(octant[2])], a.coords());
        }

        #[test]
        fn parents_and_plus_neighbours_match_their_coordinates(depth in 0u8..=32, x: u32, y: u32, z: u32, low: u8) {
            let mask = if depth == 0 { 0 } else { u32::MAX >> (32 - u32::from(depth)) };
            // Whole coordinates, the last cube of an axis and its neighbour, and unaligned
            // raw bits below the cube's size, which both ways must ignore.
            for [x, y, z] in [[x, y, z], [mask, y, z], [x, mask, z], [x, y, mask], [mask.saturating_sub(1), y, z]] {
                let (x, y, z) = (x & mask, y & mask, z & mask);
                let key = CubeKey::new(depth, x, y, z);
                let finer = 3 * u32::from(32 - depth);
                let noise = u128::from(low) & ((1u128 << finer.min(8)) - 1);
                let unaligned = CubeKey::from_raw(key.raw() | (noise << 8));
                for key in [key, unaligned] {
                    let through_coordinates = (depth > 0).then(|| CubeKey::new(depth - 1, x >> 1, y >> 1, z >> 1));
                    prop_assert_eq!(key.parent(), through_coordinates);
                    for (axis, c) in [x, y, z].into_iter().enumerate() {
                        let mut coords = [x, y, z];
                        coords[axis] = c.wrapping_add(1);
                        let expected = (c < mask).then(|| CubeKey::new(depth, coords[0], coords[1], coords[2]));
                        prop_assert_eq!(key.plus_neighbour(axis), expected);
                    }
                }
            }
        }

        #[test]
        fn dilated_sums_and_differences_match_the_coordinates(a: u32, b: u32, x: u32, y: u32, z: u32, depth in 0u8..=32) {
            prop_assert_eq!(add_axis_bits(axis_bits(a), axis_bits(b)), axis_bits(a.wrapping_add(b)));
            prop_assert_eq!(sub_axis_bits(axis_bits(a), axis_bits(b)), axis_bits(a.wrapping_sub(b)));
            let shift = 32 - u32::from(depth);
            let corner = [x, y, z].map(|c| c.checked_shr(shift).and_then(|c| c.checked_shl(shift)).unwrap_or(0));
            let key = CubeKey::from_full_resolution(depth, corner[0], corner[1], corner[2]);
            for (axis, c) in corner.into_iter().enumerate() {
                prop_assert_eq!(corner_axis_bits(key, axis), axis_bits(c));
            }
        }

        #[test]
        fn big_endian_bytes_order_like_keys(a: u128, b: u128) {
            let (a, b) = (CubeKey::from_raw(a >> 24), CubeKey::from_raw(b >> 24));
            prop_assert_eq!(a.to_be_bytes().cmp(&b.to_be_bytes()), a.cmp(&b));
        }
    }
}
