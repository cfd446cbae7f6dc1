//! Immutable column segments: one contiguous key range, many named columns, each split into
//! zstd-compressed, checksummed blocks. The byte layout is specified in `format-spec.md`
//! ("Segment files"); the constants below are that specification.
//!
//! Invariant of every valid segment: the header, the blocks, the directory and the footer tile
//! the file exactly, and each of them is covered by a magic/version match or a checksum, so any
//! single flipped byte and any truncation is detected.

#![deny(clippy::unwrap_used, clippy::expect_used, clippy::indexing_slicing)]

use xxhash_rust::xxh3::{Xxh3, xxh3_64};

use super::bytes::ByteReader;
use super::key::CubeKey;
use super::{DecodeError, SegmentPart};

/// First and last eight bytes of every segment file.
pub const MAGIC: [u8; 8] = *b"OCTSEG\x00\x01";
/// Version of the segment layout written by this build.
pub const FORMAT_VERSION: u32 = 1;

/// Header: magic, format version, flags (always 0 in version 1).
pub const HEADER_LEN: usize = MAGIC.len() + size_of::<u32>() + size_of::<u32>();

/// Footer fields before the footer checksum: directory offset, directory length, row count,
/// directory checksum, nominal block rows, format version.
pub const FOOTER_FIELDS_LEN: usize = 4 * size_of::<u64>() + 2 * size_of::<u32>();
/// Footer: fields, xxh3 of the fields, magic.
pub const FOOTER_LEN: usize = FOOTER_FIELDS_LEN + size_of::<u64>() + MAGIC.len();

/// Per-block entry of the block table: row count, first key, last key.
pub const BLOCK_ENTRY_LEN: usize = size_of::<u32>() + 2 * size_of::<u128>();
/// Per-column, per-block entry: offset, compressed length, xxh3 of the compressed bytes.
pub const CHUNK_ENTRY_LEN: usize = size_of::<u64>() + size_of::<u32>() + size_of::<u64>();

/// Rows per block written by this build (readers accept any value recorded in the file).
pub const DEFAULT_BLOCK_ROWS: u32 = 1 << 16;
/// zstd level: fast enough to write at several hundred MB/s per core.
pub const ZSTD_LEVEL: i32 = 1;
/// Name of the mandatory first column.
pub const KEY_COLUMN: &str = "key";

const MAX_COLUMNS: usize = 255;
const MAX_NAME_LEN: usize = 255;

mod encoder;

pub use encoder::{ColumnShape, encode_segment, encode_segment_streamed, encode_segment_with_block_rows};

/// Element type of a column (its code in the directory).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub enum ElementType {
    /// `CubeKey` as a little-endian u128.
    Key = 1,
    /// 32-bit float.
    F32 = 2,
    /// 32-bit unsigned integer.
    U32 = 3,
    /// 64-bit unsigned integer.
    U64 = 4,
}

impl ElementType {
    /// Bytes per element.
    pub fn size(self) -> usize {
        match self {
            ElementType::Key => size_of::<u128>(),
            ElementType::F32 | ElementType::U32 => size_of::<u32>(),
            ElementType::U64 => size_of::<u64>(),
        }
    }

    fn from_code(code: u8) -> Option<ElementType> {
        match code {
            1 => Some(ElementType::Key),
            2 => Some(ElementType::F32),
            3 => Some(ElementType::U32),
            4 => Some(ElementType::U64),
            _ => None,
        }
    }
}

/// A column's decoded values.
#[derive(Clone, Debug, PartialEq)]
pub enum ColumnValues {
    /// Cube keys (the key column).
    Key(Vec<CubeKey>),
    /// 32-bit floats.
    F32(Vec<f32>),
    /// 32-bit unsigned integers.
    U32(Vec<u32>),
    /// 64-bit unsigned integers.
    U64(Vec<u64>),
}

impl ColumnValues {
    /// The element type.
    pub fn element_type(&self) -> ElementType {
        match self {
            ColumnValues::Key(_) => ElementType::Key,
            ColumnValues::F32(_) => ElementType::F32,
            ColumnValues::U32(_) => ElementType::U32,
            ColumnValues::U64(_) => ElementType::U64,
        }
    }

    /// Number of elements.
    pub fn len(&self) -> usize {
        match self {
            ColumnValues::Key(v) => v.len(),
            ColumnValues::F32(v) => v.len(),
            ColumnValues::U32(v) => v.len(),
            ColumnValues::U64(v) => v.len(),
        }
    }

    /// Whether there are no elements.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The values' raw bytes, as a block holds them before compression.
    pub fn as_bytes(&self) -> &[u8] {
        match self {
            ColumnValues::Key(v) => bytemuck::cast_slice(v),
            ColumnValues::F32(v) => bytemuck::cast_slice(v),
            ColumnValues::U32(v) => bytemuck::cast_slice(v),
            ColumnValues::U64(v) => bytemuck::cast_slice(v),
        }
    }
}

/// One named column: `width` elements per row, row-major.
#[derive(Clone, Debug, PartialEq)]
pub struct Column {
    /// The column's name (format-spec.md, "Columns used by stages").
    pub name: String,
    /// Elements per row.
    pub width: u16,
    /// `rows * width` values, row by row.
    pub values: ColumnValues,
    /// How the writer compresses the column's chunks.
    pub compression: Compression,
}

/// How a column's chunks are compressed. Readers need not know: every chunk is a plain zstd
/// frame (format-spec.md, "Segment files").
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Compression {
    /// At zstd level 1, and again with raw literals where Huffman coding kept more than three
    /// quarters of the bytes.
    #[default]
    Adaptive,
    /// With raw literals straight away: for values whose bytes look random (the solver's v, p
    /// and q, whose every chunk of RedKitchen's finest level the adaptive rule sent to raw
    /// literals after compressing it at level 1 first, at twice the time).
    RawLiterals,
}

impl Column {
    /// A column of `width` values per row.
    pub fn new(name: &str, width: u16, values: ColumnValues) -> Column {
        Column {
            name: name.to_string(),
            width,
            values,
            compression: Compression::Adaptive,
        }
    }

    /// The column, its chunks compressed with raw literals ([`Compression::RawLiterals`]).
    pub fn with_raw_literals(self) -> Column {
        Column {
            compression: Compression::RawLiterals,
            ..self
        }
    }

    /// The key column.
    pub fn keys(keys: Vec<CubeKey>) -> Column {
        Column::new(KEY_COLUMN, 1, ColumnValues::Key(keys))
    }

    /// Rows of the column.
    pub fn rows(&self) -> usize {
        self.values.len() / usize::from(self.width.max(1))
    }
}

/// What the writer learned about the segment it wrote; recorded in the catalog.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SegmentSummary {
    /// Rows written.
    pub rows: u64,
    /// Bytes written.
    pub bytes: u64,
    /// xxh3 of the whole file.
    pub file_checksum: u64,
    /// xxh3 of the decoded content (column names, types, widths and raw values); independent of
    /// compression and block size.
    pub content_digest: u64,
    /// The first row's key.
    pub first_key: CubeKey,
    /// The last row's key.
    pub last_key: CubeKey,
}

/// Hashes decoded column content the same way on write and on verify.
pub fn content_digest_update(hasher: &mut Xxh3, name: &str, ty: ElementType, width: u16, raw: &[u8]) {
    hasher.update(&(name.len() as u64).to_le_bytes());
    hasher.update(name.as_bytes());
    hasher.update(&[ty as u8]);
    hasher.update(&width.to_le_bytes());
    hasher.update(&(raw.len() as u64).to_le_bytes());
    hasher.update(raw);
}

/// The content digest of columns, exactly as [`encode_segment`] records it.
pub fn content_digest(columns: &[Column]) -> u64 {
    let mut hasher = Xxh3::new();
    for column in columns {
        content_digest_update(
            &mut hasher,
            &column.name,
            column.values.element_type(),
            column.width,
            column.values.as_bytes(),
        );
    }
    hasher.digest()
}

#[derive(Clone, Copy, Debug)]
struct BlockInfo {
    /// Its place in the segment's block table (a view of some blocks keeps it for errors).
    number: u32,
    rows: u32,
    first_key: CubeKey,
    last_key: CubeKey,
}

#[derive(Clone, Copy, Debug)]
struct ChunkInfo {
    offset: u64,
    len: u32,
    checksum: u64,
}

/// A column as the directory describes it.
#[derive(Clone, Debug)]
pub struct ColumnInfo {
    /// The column's name.
    pub name: String,
    /// Its element type.
    pub element_type: ElementType,
    /// Elements per row.
    pub width: u16,
    chunks: Vec<ChunkInfo>,
}

/// A validated view of one segment's bytes. Parsing checks the header, footer and directory;
/// each block is checked against its checksum when it is read.
#[derive(Debug)]
pub struct SegmentReader<'a> {
    bytes: &'a [u8],
    rows: u64,
    blocks: Vec<BlockInfo>,
    columns: Vec<ColumnInfo>,
}

/// A segment's parsed directory without its bytes: its block table and column chunks, so a
/// caller that reads many short pieces of many segments can fetch only the chunks it decodes
/// (the samples stage, which mapped and parsed every ingest run once per unit).
#[derive(Clone, Debug)]
pub struct SegmentDirectory {
    blocks: Vec<BlockInfo>,
    columns: Vec<ColumnInfo>,
}

impl SegmentDirectory {
    /// Number of blocks.
    pub fn block_count(&self) -> usize {
        self.blocks.len()
    }

    /// The first and last key of block `block`.
    pub fn block_key_range(&self, block: usize) -> Option<(CubeKey, CubeKey)> {
        self.blocks.get(block).map(|b| (b.first_key, b.last_key))
    }

    /// The first block whose last key is not below `key` (the block count if none is).
    pub fn first_block_reaching(&self, key: CubeKey) -> usize {
        self.blocks.partition_point(|b| b.last_key < key)
    }

    fn column(&self, name: &str) -> Result<&ColumnInfo, DecodeError> {
        find_column(&self.columns, name)
    }

    /// Where block `block` of column `name` lies in the segment: its offset and length.
    pub fn chunk_range(&self, name: &str, block: usize) -> Result<(u64, usize), DecodeError> {
        let column = self.column(name)?;
        column
            .chunks
            .get(block)
            .map(|c| (c.offset, c.len as usize))
            .ok_or_else(|| corrupt(block_region(&self.blocks, column, block), "no such block"))
    }

    /// Decodes block `block` of column `name` from its compressed bytes (the segment's bytes
    /// at [`chunk_range`](Self::chunk_range)), checking them against the directory's checksum.
    pub fn decode_block(&self, name: &str, block: usize, compressed: &[u8]) -> Result<ColumnValues, DecodeError> {
        decode_block_values(&self.blocks, self.column(name)?, block, compressed)
    }
}

/// The column named `name`.
fn find_column<'c>(columns: &'c [ColumnInfo], name: &str) -> Result<&'c ColumnInfo, DecodeError> {
    columns
        .iter()
        .find(|c| c.name == name)
        .ok_or_else(|| DecodeError::MissingColumn(name.to_string()))
}

/// The part of the file block `block` of `column` is, for errors.
fn block_region(blocks: &[BlockInfo], column: &ColumnInfo, block: usize) -> SegmentPart {
    let info = blocks.get(block);
    SegmentPart::Block {
        column: column.name.clone(),
        block: info.map_or(block as u32, |b| b.number),
        first_key: info.map(|b| b.first_key).unwrap_or_default(),
        last_key: info.map(|b| b.last_key).unwrap_or_default(),
    }
}

/// Checks a chunk's compressed bytes against its checksum and decompresses them into `out`,
/// which must be exactly the block's raw size.
fn decode_chunk_into(
    blocks: &[BlockInfo],
    column: &ColumnInfo,
    block: usize,
    chunk: ChunkInfo,
    compressed: &[u8],
    out: &mut [u8],
) -> Result<(), DecodeError> {
    let region = || block_region(blocks, column, block);
    let got = xxh3_64(compressed);
    if got != chunk.checksum {
        return Err(DecodeError::ChecksumMismatch {
            part: region(),
            got,
            expected: chunk.checksum,
        });
    }
    let n = decompress_to_buffer(compressed, out).map_err(|e| corrupt(region(), format!("zstd: {e}")))?;
    if n != out.len() {
        return Err(corrupt(region(), format!("decoded {n} bytes, expected {}", out.len())));
    }
    Ok(())
}

/// Block `block` of `column` decoded from its compressed bytes.
fn decode_block_values(
    blocks: &[BlockInfo],
    column: &ColumnInfo,
    block: usize,
    compressed: &[u8],
) -> Result<ColumnValues, DecodeError> {
    let (chunk, info) = match (column.chunks.get(block), blocks.get(block)) {
        (Some(c), Some(b)) => (*c, *b),
        _ => return Err(corrupt(block_region(blocks, column, block), "no such block")),
    };
    if compressed.len() != chunk.len as usize {
        return Err(corrupt(
            block_region(blocks, column, block),
            "block of the wrong length",
        ));
    }
    let len = info.rows as usize * usize::from(column.width);
    let decode = |out: &mut [u8]| decode_chunk_into(blocks, column, block, chunk, compressed, out);
    Ok(match column.element_type {
        ElementType::Key => {
            let mut v = vec![CubeKey::default(); len];
            decode(bytemuck::cast_slice_mut(&mut v))?;
            ColumnValues::Key(v)
        }
        ElementType::F32 => {
            let mut v = vec![0f32; len];
            decode(bytemuck::cast_slice_mut(&mut v))?;
            ColumnValues::F32(v)
        }
        ElementType::U32 => {
            let mut v = vec![0u32; len];
            decode(bytemuck::cast_slice_mut(&mut v))?;
            ColumnValues::U32(v)
        }
        ElementType::U64 => {
            let mut v = vec![0u64; len];
            decode(bytemuck::cast_slice_mut(&mut v))?;
            ColumnValues::U64(v)
        }
    })
}

fn corrupt(part: SegmentPart, reason: impl Into<String>) -> DecodeError {
    DecodeError::Corrupt {
        part,
        reason: reason.into(),
    }
}

impl<'a> SegmentReader<'a> {
    // long function parse: validates the format in file order (header, footer, directory, blocks), each check beside the bytes it reads, as format-spec.md lays them out.
    /// Checks the header, footer and directory of a segment's bytes (blocks are checked as they
    /// are read, or all at once by [`SegmentReader::verify`]).
    pub fn parse(bytes: &'a [u8]) -> Result<SegmentReader<'a>, DecodeError> {
        if bytes.len() < HEADER_LEN + FOOTER_LEN {
            return Err(DecodeError::Truncated {
                what: "segment",
                needed: HEADER_LEN + FOOTER_LEN,
                available: bytes.len(),
            });
        }
        let mut header = ByteReader::new(bytes);
        if header.array::<8>()? != MAGIC {
            return Err(DecodeError::BadMagic {
                part: SegmentPart::Header,
            });
        }
        let version = header.u32()?;
        if version != FORMAT_VERSION {
            return Err(DecodeError::UnsupportedVersion {
                found: version,
                supported: FORMAT_VERSION,
            });
        }
        if header.u32()? != 0 {
            return Err(corrupt(SegmentPart::Header, "flags must be 0"));
        }

        let footer_start = bytes.len() - FOOTER_LEN;
        let footer_bytes = bytes
            .get(footer_start..)
            .ok_or_else(|| corrupt(SegmentPart::Footer, "missing"))?;
        let mut footer = ByteReader::new(footer_bytes);
        let fields = footer.take(FOOTER_FIELDS_LEN)?;
        let footer_checksum = footer.u64()?;
        if footer.array::<8>()? != MAGIC {
            return Err(DecodeError::BadMagic {
                part: SegmentPart::Footer,
            });
        }
        let got = xxh3_64(fields);
        if got != footer_checksum {
            return Err(DecodeError::ChecksumMismatch {
                part: SegmentPart::Footer,
                got,
                expected: footer_checksum,
            });
        }
        let mut f = ByteReader::new(fields);
        let dir_offset = f.u64()?;
        let dir_len = f.u64()?;
        let rows = f.u64()?;
        let dir_checksum = f.u64()?;
        let _block_rows = f.u32()?;
        let footer_version = f.u32()?;
        if footer_version != FORMAT_VERSION {
            return Err(DecodeError::UnsupportedVersion {
                found: footer_version,
                supported: FORMAT_VERSION,
            });
        }
        let dir_end = dir_offset.checked_add(dir_len);
        if dir_offset < HEADER_LEN as u64 || dir_end != Some(footer_start as u64) {
            return Err(corrupt(
                SegmentPart::Footer,
                format!("directory at {dir_offset}+{dir_len} does not end where the footer starts ({footer_start})"),
            ));
        }
        let dir = bytes
            .get(dir_offset as usize..footer_start)
            .ok_or_else(|| corrupt(SegmentPart::Footer, "directory out of bounds"))?;
        let got = xxh3_64(dir);
        if got != dir_checksum {
            return Err(DecodeError::ChecksumMismatch {
                part: SegmentPart::Directory,
                got,
                expected: dir_checksum,
            });
        }

        let mut d = ByteReader::new(dir);
        let block_count = d.u32()? as usize;
        if block_count.saturating_mul(BLOCK_ENTRY_LEN) > d.remaining() {
            return Err(corrupt(SegmentPart::Directory, "block table longer than the directory"));
        }
        let mut blocks = Vec::with_capacity(block_count);
        let mut row_sum = 0u64;
        for _ in 0..block_count {
            let block_rows = d.u32()?;
            let first_key = CubeKey::from_raw(d.u128()?);
            let last_key = CubeKey::from_raw(d.u128()?);
            if block_rows == 0 || first_key > last_key {
                return Err(corrupt(SegmentPart::Directory, "empty block or inverted key range"));
            }
            row_sum += u64::from(block_rows);
            blocks.push(BlockInfo {
                number: blocks.len() as u32,
                rows: block_rows,
                first_key,
                last_key,
            });
        }
        if row_sum != rows || rows == 0 {
            return Err(corrupt(
                SegmentPart::Directory,
                format!("blocks hold {row_sum} rows, footer says {rows}"),
            ));
        }
        let column_count = usize::from(d.u16()?);
        let mut columns: Vec<ColumnInfo> = Vec::with_capacity(column_count);
        // Blocks must tile [HEADER_LEN, dir_offset) in write order so every byte is checksummed.
        let mut expected_offset = HEADER_LEN as u64;
        for _ in 0..column_count {
            let name_len = usize::from(d.u8()?);
            let name = std::str::from_utf8(d.take(name_len)?)
                .map_err(|_| corrupt(SegmentPart::Directory, "column name is not UTF-8"))?
                .to_string();
            let element_type = ElementType::from_code(d.u8()?).ok_or_else(|| {
                corrupt(
                    SegmentPart::Directory,
                    format!("column '{name}' has an unknown element type"),
                )
            })?;
            let width = d.u16()?;
            if width == 0 {
                return Err(corrupt(SegmentPart::Directory, format!("column '{name}' has width 0")));
            }
            let mut chunks = Vec::with_capacity(block_count);
            for _ in 0..block_count {
                let chunk = ChunkInfo {
                    offset: d.u64()?,
                    len: d.u32()?,
                    checksum: d.u64()?,
                };
                if chunk.offset != expected_offset {
                    return Err(corrupt(
                        SegmentPart::Directory,
                        format!(
                            "column '{name}' block at {} where {expected_offset} was expected",
                            chunk.offset
                        ),
                    ));
                }
                expected_offset += u64::from(chunk.len);
                chunks.push(chunk);
            }
            if columns.iter().any(|c| c.name == name) {
                return Err(corrupt(
                    SegmentPart::Directory,
                    format!("column '{name}' appears twice"),
                ));
            }
            columns.push(ColumnInfo {
                name,
                element_type,
                width,
                chunks,
            });
        }
        if d.remaining() != 0 {
            return Err(corrupt(SegmentPart::Directory, "trailing bytes"));
        }
        if expected_offset != dir_offset {
            return Err(corrupt(
                SegmentPart::Directory,
                format!("blocks end at {expected_offset}, directory starts at {dir_offset}"),
            ));
        }
        match columns.first() {
            Some(c) if c.name == KEY_COLUMN && c.element_type == ElementType::Key && c.width == 1 => {}
            _ => {
                return Err(corrupt(SegmentPart::Directory, "first column is not the key column"));
            }
        }
        Ok(SegmentReader {
            bytes,
            rows,
            blocks,
            columns,
        })
    }

    /// Rows of the segment.
    pub fn rows(&self) -> u64 {
        self.rows
    }

    /// The columns, the key column first.
    pub fn columns(&self) -> &[ColumnInfo] {
        &self.columns
    }

    /// The first row's key.
    pub fn first_key(&self) -> CubeKey {
        self.blocks.first().map(|b| b.first_key).unwrap_or_default()
    }

    /// The last row's key.
    pub fn last_key(&self) -> CubeKey {
        self.blocks.last().map(|b| b.last_key).unwrap_or_default()
    }

    /// The same segment with only the blocks whose first and last keys `keep` accepts: its
    /// reads decode only their chunks, and the other blocks' rows are absent (extraction reads
    /// a neighbour unit's cubes along the shared face only). Its `verify` digests the kept
    /// rows alone, so it matches the recorded digest only when every block is kept.
    pub fn with_blocks_where(&self, keep: impl Fn(CubeKey, CubeKey) -> bool) -> SegmentReader<'a> {
        let kept: Vec<bool> = self.blocks.iter().map(|b| keep(b.first_key, b.last_key)).collect();
        let blocks: Vec<BlockInfo> = self
            .blocks
            .iter()
            .zip(&kept)
            .filter(|(_, k)| **k)
            .map(|(b, _)| *b)
            .collect();
        let columns = self.columns.iter().map(|column| ColumnInfo {
            chunks: column
                .chunks
                .iter()
                .zip(&kept)
                .filter(|(_, k)| **k)
                .map(|(c, _)| *c)
                .collect(),
            ..column.clone()
        });
        SegmentReader {
            bytes: self.bytes,
            rows: blocks.iter().map(|b| u64::from(b.rows)).sum(),
            blocks,
            columns: columns.collect(),
        }
    }

    /// The column called `name`.
    pub fn column(&self, name: &str) -> Result<&ColumnInfo, DecodeError> {
        find_column(&self.columns, name)
    }

    fn block_region(&self, column: &ColumnInfo, block: usize) -> SegmentPart {
        block_region(&self.blocks, column, block)
    }

    /// Decompresses one column into `out` (whose length must be rows x width elements) as raw
    /// bytes, verifying every block checksum.
    fn decode_into(&self, column: &ColumnInfo, out: &mut [u8]) -> Result<(), DecodeError> {
        let row_bytes = usize::from(column.width) * column.element_type.size();
        let mut pos = 0usize;
        for (index, (chunk, block)) in column.chunks.iter().zip(&self.blocks).enumerate() {
            let want = block.rows as usize * row_bytes;
            let target = out
                .get_mut(pos..pos + want)
                .ok_or_else(|| corrupt(self.block_region(column, index), "block larger than the column"))?;
            self.decode_chunk(column, index, *chunk, target)?;
            pos += want;
        }
        if pos != out.len() {
            return Err(corrupt(self.block_region(column, 0), "column shorter than the segment"));
        }
        Ok(())
    }

    fn typed<T: bytemuck::Pod + bytemuck::Zeroable>(
        &self,
        name: &str,
        wanted: ElementType,
    ) -> Result<(u16, Vec<T>), DecodeError> {
        let column = self.column(name)?;
        if column.element_type != wanted {
            return Err(DecodeError::TypeMismatch {
                column: name.to_string(),
                found: column.element_type,
                wanted,
            });
        }
        let len = usize::try_from(self.rows)
            .ok()
            .and_then(|r| r.checked_mul(usize::from(column.width)))
            .ok_or_else(|| corrupt(SegmentPart::Directory, "row count overflows"))?;
        let mut values = vec![T::zeroed(); len];
        self.decode_into(column, bytemuck::cast_slice_mut(&mut values))?;
        Ok((column.width, values))
    }

    /// Blocks per column.
    pub fn block_count(&self) -> usize {
        self.blocks.len()
    }

    /// Rows in block `block` (0 past the end).
    pub fn block_rows(&self, block: usize) -> usize {
        self.blocks.get(block).map_or(0, |b| b.rows as usize)
    }

    /// The first and last keys of block `block`, from the directory (nothing is decoded);
    /// `None` past the end.
    pub fn block_key_range(&self, block: usize) -> Option<(CubeKey, CubeKey)> {
        self.blocks.get(block).map(|b| (b.first_key, b.last_key))
    }

    /// Decodes one block of one column: bounded memory for streaming merges.
    pub fn read_block(&self, name: &str, block: usize) -> Result<ColumnValues, DecodeError> {
        let column = self.column(name)?;
        let chunk = column.chunks.get(block).copied();
        let region = || block_region(&self.blocks, column, block);
        let compressed = chunk
            .and_then(|c| self.bytes.get(c.offset as usize..c.offset as usize + c.len as usize))
            .ok_or_else(|| corrupt(region(), "block out of bounds"))?;
        decode_block_values(&self.blocks, column, block, compressed)
    }

    fn decode_chunk(
        &self,
        column: &ColumnInfo,
        block: usize,
        chunk: ChunkInfo,
        out: &mut [u8],
    ) -> Result<(), DecodeError> {
        let start = chunk.offset as usize;
        let compressed = self
            .bytes
            .get(start..start + chunk.len as usize)
            .ok_or_else(|| corrupt(block_region(&self.blocks, column, block), "block out of bounds"))?;
        decode_chunk_into(&self.blocks, column, block, chunk, compressed, out)
    }

    /// The directory, detached from the bytes: to read blocks of the segment later from
    /// bytes fetched elsewhere ([`SegmentDirectory::decode_block`]).
    pub fn directory(&self) -> SegmentDirectory {
        SegmentDirectory {
            blocks: self.blocks.clone(),
            columns: self.columns.clone(),
        }
    }

    /// Decodes the key column.
    pub fn read_keys(&self) -> Result<Vec<CubeKey>, DecodeError> {
        let (_, keys) = self.typed::<CubeKey>(KEY_COLUMN, ElementType::Key)?;
        Ok(keys)
    }

    /// Decodes a float column: its width and values.
    pub fn read_f32(&self, name: &str) -> Result<(u16, Vec<f32>), DecodeError> {
        self.typed(name, ElementType::F32)
    }

    /// Decodes a u32 column: its width and values.
    pub fn read_u32(&self, name: &str) -> Result<(u16, Vec<u32>), DecodeError> {
        self.typed(name, ElementType::U32)
    }

    /// Decodes a u64 column: its width and values.
    pub fn read_u64(&self, name: &str) -> Result<(u16, Vec<u64>), DecodeError> {
        self.typed(name, ElementType::U64)
    }

    /// Decodes a column whatever its type.
    pub fn read_column(&self, name: &str) -> Result<Column, DecodeError> {
        let column = self.column(name)?;
        let values = match column.element_type {
            ElementType::Key => ColumnValues::Key(self.read_keys()?),
            ElementType::F32 => ColumnValues::F32(self.read_f32(name)?.1),
            ElementType::U32 => ColumnValues::U32(self.read_u32(name)?.1),
            ElementType::U64 => ColumnValues::U64(self.read_u64(name)?.1),
        };
        Ok(Column::new(name, column.width, values))
    }

    /// Decodes everything, checks key order and block key ranges, and returns the content
    /// digest (see [`SegmentSummary::content_digest`]).
    pub fn verify(&self) -> Result<u64, DecodeError> {
        let keys = self.read_keys()?;
        let mut start = 0usize;
        for (index, block) in self.blocks.iter().enumerate() {
            let region = || self.block_region(self.columns.first().unwrap_or(&self.columns_fallback()), index);
            let slice = keys
                .get(start..start + block.rows as usize)
                .ok_or_else(|| corrupt(region(), "block beyond the key column"))?;
            if slice.first() != Some(&block.first_key) || slice.last() != Some(&block.last_key) {
                return Err(corrupt(region(), "keys disagree with the block's key range"));
            }
            start += block.rows as usize;
        }
        if let Some(pair) = keys.windows(2).find(|w| w.first() >= w.get(1)) {
            return Err(corrupt(
                SegmentPart::Directory,
                format!("keys are not strictly increasing: {pair:?}"),
            ));
        }
        if let Some(bad) = keys.iter().find(|k| !k.is_well_formed()) {
            return Err(corrupt(SegmentPart::Directory, format!("malformed key {bad}")));
        }
        let mut content = Xxh3::new();
        for column in &self.columns {
            let decoded = self.read_column(&column.name)?;
            content_digest_update(
                &mut content,
                &column.name,
                column.element_type,
                column.width,
                decoded.values.as_bytes(),
            );
        }
        Ok(content.digest())
    }

    fn columns_fallback(&self) -> ColumnInfo {
        ColumnInfo {
            name: KEY_COLUMN.to_string(),
            element_type: ElementType::Key,
            width: 1,
            chunks: Vec::new(),
        }
    }
}

thread_local! {
    /// Each thread's zstd decompression context, made on its first decode. A context costs
    /// an allocation and its tables' set-up: made per block, as `zstd::bulk::decompress_to_buffer`
    /// does, it was 14 % of an SSD solve's CPU on RedKitchen's 1000 frames, whose samples stage
    /// decodes many small blocks of the ingest runs.
    static DECOMPRESSOR: std::cell::RefCell<Option<zstd::bulk::Decompressor<'static>>> =
        const { std::cell::RefCell::new(None) };
}

/// Decompresses one zstd frame into `out`, with the thread's reused context.
fn decompress_to_buffer(compressed: &[u8], out: &mut [u8]) -> std::io::Result<usize> {
    DECOMPRESSOR.with(|slot| {
        // A decode never decodes another inside it, so the slot is always free; were it not,
        // a fresh context does the same work.
        let Ok(mut slot) = slot.try_borrow_mut() else {
            return zstd::bulk::decompress_to_buffer(compressed, out);
        };
        let decompressor = match slot.as_mut() {
            Some(decompressor) => decompressor,
            None => slot.insert(zstd::bulk::Decompressor::new()?),
        };
        decompressor.decompress_to_buffer(compressed, out)
    })
}

#[cfg(test)]
mod tests;
