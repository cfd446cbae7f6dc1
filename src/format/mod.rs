//! On-disk formats: cube keys and immutable column segments (see `format-spec.md`).
//!
//! Everything here works on byte slices and in-memory buffers; files are the store's business.

pub mod bytes;
pub mod key;
pub mod segment;

pub use key::{CubeKey, MAX_DEPTH};
pub use segment::{Column, ColumnValues, ElementType, SegmentReader, SegmentSummary};

#[cfg(target_endian = "big")]
compile_error!("octstore stores little-endian columns and reinterprets them in place");

/// Where in a segment a problem was found, for error messages.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Region {
    Header,
    Footer,
    Directory,
    Block {
        column: String,
        block: u32,
        first_key: CubeKey,
        last_key: CubeKey,
    },
}

impl std::fmt::Display for Region {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Region::Header => write!(f, "header"),
            Region::Footer => write!(f, "footer"),
            Region::Directory => write!(f, "column directory"),
            Region::Block {
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
pub enum DecodeError {
    #[error("truncated {what}: needed {needed} bytes, {available} available")]
    Truncated {
        what: &'static str,
        needed: usize,
        available: usize,
    },
    #[error("bad magic in {region}: not an octstore segment")]
    BadMagic { region: Region },
    #[error("unsupported segment format version {found} (this build reads version {supported})")]
    UnsupportedVersion { found: u32, supported: u32 },
    #[error("checksum mismatch in {region}: got {got:016x}, expected {expected:016x}")]
    ChecksumMismatch { region: Region, got: u64, expected: u64 },
    #[error("corrupt {region}: {reason}")]
    Corrupt { region: Region, reason: String },
    #[error("segment has no column '{0}'")]
    MissingColumn(String),
    #[error("column '{column}' holds {found:?}, asked for {wanted:?}")]
    TypeMismatch {
        column: String,
        found: ElementType,
        wanted: ElementType,
    },
}

/// Errors of encoding: the caller handed in data that breaks a format invariant.
#[derive(Debug, thiserror::Error)]
pub enum EncodeError {
    #[error("invalid segment content: {0}")]
    Invalid(String),
    #[error("zstd compression failed: {0}")]
    Compression(std::io::Error),
    #[error(transparent)]
    Io(#[from] std::io::Error),
}
