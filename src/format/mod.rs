//! On-disk formats: cube keys, immutable column segments (see `format-spec.md`), and the world
//! geometry the catalog records (the root cube).
//!
//! Everything here works on byte slices and in-memory buffers; files are the store's business.

// The layers that decode bytes from disk: a damaged byte must give an error, never a panic
// (format-spec.md), so no unwrap, expect or unchecked index outside tests.
#![deny(clippy::unwrap_used, clippy::expect_used, clippy::indexing_slicing)]

pub(crate) mod bytes;
pub mod key;
pub mod ply_header;
pub mod segment;
mod world;

pub use key::{CubeKey, MAX_DEPTH};
pub use segment::{Column, ColumnShape, ColumnValues, Compression, ElementType, SegmentReader, SegmentSummary};
pub use world::{BoundingBox, META_SCENE, RADIUS_FRACTION_BITS, RadiusDepths, Scene, round_half_away_from_zero};

#[cfg(target_endian = "big")]
compile_error!("octstore stores little-endian columns and reinterprets them in place");

/// Where in a segment a problem was found, for error messages.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum SegmentPart {
    /// The 16-byte header.
    Header,
    /// The 56-byte footer.
    Footer,
    /// The column directory.
    Directory,
    /// One compressed block of one column.
    Block {
        /// The column's name.
        column: String,
        /// The block's index in the column.
        block: u32,
        /// First key of the block's rows.
        first_key: CubeKey,
        /// Last key of the block's rows.
        last_key: CubeKey,
    },
}

impl std::fmt::Display for SegmentPart {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            SegmentPart::Header => write!(f, "header"),
            SegmentPart::Footer => write!(f, "footer"),
            SegmentPart::Directory => write!(f, "column directory"),
            SegmentPart::Block {
                column,
                block,
                first_key,
                last_key,
            } => write!(
                f,
                "column '{column}' block {block}, keys {first_key}..={last_key} ({first_key:?}..={last_key:?})"
            ),
        }
    }
}

/// Errors of decoding bytes. Corruption of any kind is reported, never panicked on.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
#[non_exhaustive]
pub enum DecodeError {
    /// Fewer bytes than the structure needs.
    #[error("truncated {what}: needed {needed} bytes, {available} available")]
    Truncated {
        /// The structure being read.
        what: &'static str,
        /// Bytes it needs.
        needed: usize,
        /// Bytes there are.
        available: usize,
    },
    /// The header or footer does not start with the segment magic.
    #[error("bad magic in {part}: not an octstore segment")]
    BadMagic {
        /// Where.
        part: SegmentPart,
    },
    /// A format version this build does not read.
    #[error("unsupported segment format version {found} (this build reads version {supported})")]
    UnsupportedVersion {
        /// The file's version.
        found: u32,
        /// The version this build reads.
        supported: u32,
    },
    /// Bytes whose xxh3-64 differs from the recorded checksum.
    #[error("checksum mismatch in {part}: got {got:016x}, expected {expected:016x}")]
    ChecksumMismatch {
        /// Where.
        part: SegmentPart,
        /// The checksum of the bytes read.
        got: u64,
        /// The recorded checksum.
        expected: u64,
    },
    /// A structure that breaks a format rule.
    #[error("corrupt {part}: {reason}")]
    Corrupt {
        /// Where.
        part: SegmentPart,
        /// The rule it breaks.
        reason: String,
    },
    /// The segment has no column of that name.
    #[error("segment has no column '{0}'")]
    MissingColumn(String),
    /// The column holds another element type than asked for.
    #[error("column '{column}' holds {found:?}, asked for {wanted:?}")]
    TypeMismatch {
        /// The column.
        column: String,
        /// What it holds.
        found: ElementType,
        /// What was asked for.
        wanted: ElementType,
    },
}

/// Errors of encoding: the caller handed in data that breaks a format invariant.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum EncodeError {
    /// The columns break a format invariant (unsorted keys, unequal lengths, ...).
    #[error("invalid segment content: {0}")]
    Invalid(String),
    /// zstd failed.
    #[error("zstd compression failed: {0}")]
    Compression(std::io::Error),
    /// Writing the encoded bytes failed.
    #[error(transparent)]
    Io(#[from] std::io::Error),
}
