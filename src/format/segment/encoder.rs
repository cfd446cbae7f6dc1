//! Writing segments: from columns in memory, or streamed from one reader per column (a
//! segment far larger than memory in a few blocks' worth of it). Both write the same bytes for
//! the same rows; the layout is specified in `format-spec.md` ("Segment files").

#![deny(clippy::unwrap_used, clippy::expect_used, clippy::indexing_slicing)]

use std::io::{Read, Write};

use xxhash_rust::xxh3::{Xxh3, xxh3_64};

use super::{
    Column, ColumnValues, Compression, DEFAULT_BLOCK_ROWS, ElementType, FOOTER_LEN, FORMAT_VERSION, KEY_COLUMN, MAGIC,
    MAX_COLUMNS, MAX_NAME_LEN, SegmentSummary, ZSTD_LEVEL,
};
use crate::format::{CubeKey, EncodeError};

/// The zstd level of a chunk that [`ZSTD_LEVEL`] leaves at more than `HUFFMAN_WORTH_NUM /
/// HUFFMAN_WORTH_DEN` of its raw bytes. At negative levels zstd stores literals raw, so the
/// high-entropy columns (solver fields, sample moments), which Huffman coding shrank by 7 to 13
/// % at about 1 GB/s a core of decoding, decode at about memory speed: the sample moments of
/// RedKitchen's 1000 depth maps took 1.5 s of a core to decode, now a few hundredths. Either frame is plain zstd: readers do not tell them apart.
const RAW_LITERALS_ZSTD_LEVEL: i32 = -1;
/// See [`RAW_LITERALS_ZSTD_LEVEL`].
const HUFFMAN_WORTH_NUM: usize = 3;
/// See [`RAW_LITERALS_ZSTD_LEVEL`].
const HUFFMAN_WORTH_DEN: usize = 4;

/// The key column of `columns` after checking the shapes, lengths and key order.
fn validate(columns: &[Column]) -> Result<&[CubeKey], EncodeError> {
    let invalid = |msg: String| Err(EncodeError::Invalid(msg));
    let Some(ColumnValues::Key(keys)) = columns.first().map(|c| &c.values) else {
        return invalid("the first column must hold cube keys".into());
    };
    let shapes: Vec<ColumnShape> = columns.iter().map(ColumnShape::of).collect();
    validate_shapes(&shapes, keys.len() as u64, columns.len())?;
    if let Some(pair) = keys.windows(2).find(|w| w.first() >= w.get(1)) {
        return invalid(format!("keys are not strictly increasing: {pair:?}"));
    }
    for column in columns {
        if column.values.len() != keys.len() * usize::from(column.width) {
            return invalid(format!(
                "column '{}' holds {} values, expected {} rows x width {}",
                column.name,
                column.values.len(),
                keys.len(),
                column.width
            ));
        }
    }
    Ok(keys)
}

/// Writes `columns` as one segment to `out`, streaming block by block.
pub fn encode_segment<W: Write>(columns: &[Column], out: &mut W) -> Result<SegmentSummary, EncodeError> {
    encode_segment_with_block_rows(columns, DEFAULT_BLOCK_ROWS, out)
}

struct HashingWriter<'w, W: Write> {
    inner: &'w mut W,
    hasher: Xxh3,
    written: u64,
}

impl<W: Write> HashingWriter<'_, W> {
    fn put(&mut self, bytes: &[u8]) -> std::io::Result<()> {
        self.inner.write_all(bytes)?;
        self.hasher.update(bytes);
        self.written += bytes.len() as u64;
        Ok(())
    }
}

/// [`encode_segment`] with `block_rows` rows per block (tests use small blocks).
pub fn encode_segment_with_block_rows<W: Write>(
    columns: &[Column],
    block_rows: u32,
    out: &mut W,
) -> Result<SegmentSummary, EncodeError> {
    let keys = validate(columns)?;
    let shapes: Vec<ColumnShape> = columns.iter().map(ColumnShape::of).collect();
    let mut sources: Vec<&[u8]> = columns.iter().map(|c| c.values.as_bytes()).collect();
    encode_segment_streamed(&shapes, keys.len() as u64, &mut sources, block_rows, out)
}

/// A column's name, element type and width: what the streaming encoder needs to know of a
/// column before its values.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ColumnShape {
    /// The column's name.
    pub name: String,
    /// Its element type.
    pub element: ElementType,
    /// Elements per row.
    pub width: u16,
    /// How its chunks are compressed.
    pub compression: Compression,
}

impl ColumnShape {
    /// The shape of `column`.
    pub fn of(column: &Column) -> ColumnShape {
        ColumnShape {
            name: column.name.clone(),
            element: column.values.element_type(),
            width: column.width,
            compression: column.compression,
        }
    }

    /// Bytes one row of the column takes.
    pub fn row_bytes(&self) -> usize {
        usize::from(self.width) * self.element.size()
    }
}

fn validate_shapes(shapes: &[ColumnShape], rows: u64, sources: usize) -> Result<(), EncodeError> {
    let invalid = |msg: String| Err(EncodeError::Invalid(msg));
    let Some(first) = shapes.first() else {
        return invalid("a segment needs at least the key column".into());
    };
    if first.name != KEY_COLUMN || first.width != 1 || first.element != ElementType::Key {
        return invalid(format!(
            "the first column must be '{KEY_COLUMN}' of width 1 holding cube keys"
        ));
    }
    if rows == 0 {
        return invalid("a segment holds at least one row".into());
    }
    if shapes.len() > MAX_COLUMNS {
        return invalid(format!("{} columns, at most {MAX_COLUMNS}", shapes.len()));
    }
    if sources != shapes.len() {
        return invalid(format!("{} column shapes but {sources} sources", shapes.len()));
    }
    let mut names = std::collections::BTreeSet::new();
    for shape in shapes {
        if shape.name.is_empty() || shape.name.len() > MAX_NAME_LEN {
            return invalid(format!("column name '{}' must be 1..=255 bytes", shape.name));
        }
        if !names.insert(shape.name.as_str()) {
            return invalid(format!("column '{}' appears twice", shape.name));
        }
        if shape.width == 0 {
            return invalid(format!("column '{}' has width 0", shape.name));
        }
    }
    Ok(())
}

/// Writes one segment of `rows` rows whose columns' raw values (row by row, as
/// [`ColumnValues`] holds them in memory) are read from `sources`, one source per shape, each
/// read once from its start: a segment far larger than memory is encoded in a batch of
/// blocks' worth of memory. The bytes are exactly those [`encode_segment_with_block_rows`] writes for the
/// same columns. Keys must be strictly increasing; a source shorter than `rows` rows is an
/// error.
pub fn encode_segment_streamed<W: Write, R: Read>(
    shapes: &[ColumnShape],
    rows: u64,
    sources: &mut [R],
    block_rows: u32,
    out: &mut W,
) -> Result<SegmentSummary, EncodeError> {
    validate_shapes(shapes, rows, sources.len())?;
    let block_rows = u64::from(block_rows.max(1));
    let block_count = rows.div_ceil(block_rows);
    let block_count_u32 = u32::try_from(block_count)
        .map_err(|_| EncodeError::Invalid(format!("{block_count} blocks, more than a segment can index")))?;

    let mut w = HashingWriter {
        inner: out,
        hasher: Xxh3::new(),
        written: 0,
    };
    w.put(&MAGIC)?;
    w.put(&FORMAT_VERSION.to_le_bytes())?;
    w.put(&0u32.to_le_bytes())?;

    let mut compressors = Compressors::default();
    let mut content = Xxh3::new();
    // Per column, per block: (offset, compressed length, checksum).
    let mut chunks: Vec<Vec<(u64, u32, u64)>> = Vec::with_capacity(shapes.len());
    // Per block: (rows, first key, last key), from the key column (the first).
    let mut blocks: Vec<(u32, CubeKey, CubeKey)> = Vec::with_capacity(block_count as usize);
    let mut previous_key: Option<CubeKey> = None;
    let mut raw: Vec<Vec<u8>> = Vec::new();
    let batch = Compressors::batch();
    for (index, (shape, source)) in shapes.iter().zip(sources.iter_mut()).enumerate() {
        let row_bytes = shape.row_bytes();
        let total = usize::try_from(rows)
            .ok()
            .and_then(|r| r.checked_mul(row_bytes))
            .ok_or_else(|| EncodeError::Invalid(format!("column '{}' is too large to address", shape.name)))?;
        content.update(&(shape.name.len() as u64).to_le_bytes());
        content.update(shape.name.as_bytes());
        content.update(&[shape.element as u8]);
        content.update(&shape.width.to_le_bytes());
        content.update(&(total as u64).to_le_bytes());
        let mut entries = Vec::with_capacity(block_count as usize);
        let mut remaining = rows;
        while remaining > 0 {
            // A few blocks read in order, compressed in parallel, written in order.
            let mut read = 0;
            while read < batch && remaining > 0 {
                let block = remaining.min(block_rows);
                remaining -= block;
                if raw.len() == read {
                    raw.push(Vec::new());
                }
                let Some(bytes) = raw.get_mut(read) else {
                    break;
                };
                bytes.resize(block as usize * row_bytes, 0);
                source.read_exact(bytes).map_err(|e| {
                    EncodeError::Invalid(format!("column '{}' ends before its {rows} rows: {e}", shape.name))
                })?;
                content.update(bytes);
                if index == 0 {
                    blocks.push(key_block(bytes, block as u32, &mut previous_key)?);
                }
                read += 1;
            }
            for compressed in compressors.compress(raw.get(..read).unwrap_or_default(), shape.compression)? {
                let len = u32::try_from(compressed.len())
                    .map_err(|_| EncodeError::Invalid("compressed block larger than 4 GiB".into()))?;
                entries.push((w.written, len, xxh3_64(&compressed)));
                w.put(&compressed)?;
            }
        }
        chunks.push(entries);
    }

    let mut dir = Vec::new();
    dir.extend_from_slice(&block_count_u32.to_le_bytes());
    for (rows, first, last) in &blocks {
        dir.extend_from_slice(&rows.to_le_bytes());
        dir.extend_from_slice(&first.raw().to_le_bytes());
        dir.extend_from_slice(&last.raw().to_le_bytes());
    }
    dir.extend_from_slice(&(shapes.len() as u16).to_le_bytes());
    for (shape, entries) in shapes.iter().zip(&chunks) {
        dir.push(shape.name.len() as u8);
        dir.extend_from_slice(shape.name.as_bytes());
        dir.push(shape.element as u8);
        dir.extend_from_slice(&shape.width.to_le_bytes());
        for (offset, len, checksum) in entries {
            dir.extend_from_slice(&offset.to_le_bytes());
            dir.extend_from_slice(&len.to_le_bytes());
            dir.extend_from_slice(&checksum.to_le_bytes());
        }
    }
    let dir_offset = w.written;
    w.put(&dir)?;

    let mut footer = Vec::with_capacity(FOOTER_LEN);
    footer.extend_from_slice(&dir_offset.to_le_bytes());
    footer.extend_from_slice(&(dir.len() as u64).to_le_bytes());
    footer.extend_from_slice(&rows.to_le_bytes());
    footer.extend_from_slice(&xxh3_64(&dir).to_le_bytes());
    footer.extend_from_slice(&(block_rows as u32).to_le_bytes());
    footer.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    let footer_checksum = xxh3_64(&footer);
    footer.extend_from_slice(&footer_checksum.to_le_bytes());
    footer.extend_from_slice(&MAGIC);
    w.put(&footer)?;

    let (first_key, last_key) = match (blocks.first(), blocks.last()) {
        (Some((_, first, _)), Some((_, _, last))) => (*first, *last),
        _ => return Err(EncodeError::Invalid("empty segment".into())),
    };
    Ok(SegmentSummary {
        rows,
        bytes: w.written,
        file_checksum: w.hasher.digest(),
        content_digest: content.digest(),
        first_key,
        last_key,
    })
}

/// Compresses chunks as [`RAW_LITERALS_ZSTD_LEVEL`] says: at [`ZSTD_LEVEL`], then once more at
/// [`RAW_LITERALS_ZSTD_LEVEL`] for a chunk the first left at more than `HUFFMAN_WORTH_NUM /
/// HUFFMAN_WORTH_DEN` of its bytes. Columns that compress well, every column of a TGV store's
/// ingest, are compressed once, as before.
struct ChunkCompressor {
    huffman: zstd::bulk::Compressor<'static>,
    /// Made on the first high-entropy chunk.
    raw_literals: Option<zstd::bulk::Compressor<'static>>,
}

impl ChunkCompressor {
    fn new() -> Result<ChunkCompressor, EncodeError> {
        Ok(ChunkCompressor {
            huffman: zstd::bulk::Compressor::new(ZSTD_LEVEL).map_err(EncodeError::Compression)?,
            raw_literals: None,
        })
    }

    fn compress(&mut self, raw: &[u8], compression: Compression) -> Result<Vec<u8>, EncodeError> {
        if compression == Compression::Adaptive {
            let huffman = self.huffman.compress(raw).map_err(EncodeError::Compression)?;
            if huffman.len().saturating_mul(HUFFMAN_WORTH_DEN) <= raw.len().saturating_mul(HUFFMAN_WORTH_NUM) {
                return Ok(huffman);
            }
        }
        let fast = match &mut self.raw_literals {
            Some(fast) => fast,
            None => self
                .raw_literals
                .insert(zstd::bulk::Compressor::new(RAW_LITERALS_ZSTD_LEVEL).map_err(EncodeError::Compression)?),
        };
        fast.compress(raw).map_err(EncodeError::Compression)
    }
}

/// A [`ChunkCompressor`] for each block of a batch, which compresses the batch's blocks in
/// parallel (each block is a zstd frame of its own, so the bytes are those of compressing the
/// blocks one by one): segment writes ended RedKitchen's histogram step on one core, about
/// half a second of the 158 MB of its histogram rows.
#[derive(Default)]
struct Compressors {
    each: Vec<ChunkCompressor>,
}

impl Compressors {
    /// Blocks a batch holds: two for each thread, so a thread that finishes first takes
    /// another, and at most eight (a batch's raw blocks are in memory at once).
    fn batch() -> usize {
        (2 * rayon::current_num_threads()).clamp(1, 8)
    }

    /// The compressed blocks, in order.
    fn compress(&mut self, blocks: &[Vec<u8>], compression: Compression) -> Result<Vec<Vec<u8>>, EncodeError> {
        use rayon::prelude::*;
        while self.each.len() < blocks.len() {
            self.each.push(ChunkCompressor::new()?);
        }
        match (blocks, self.each.first_mut()) {
            ([one], Some(compressor)) => Ok(vec![compressor.compress(one, compression)?]),
            _ => blocks
                .par_iter()
                .zip(self.each.par_iter_mut())
                .map(|(block, compressor)| compressor.compress(block, compression))
                .collect(),
        }
    }
}

/// One block of the key column as raw bytes: its directory entry, after checking that its keys
/// continue strictly increasing from `previous`.
fn key_block(raw: &[u8], rows: u32, previous: &mut Option<CubeKey>) -> Result<(u32, CubeKey, CubeKey), EncodeError> {
    let mut first = None;
    for bytes in raw.chunks_exact(size_of::<u128>()) {
        let mut le = [0u8; size_of::<u128>()];
        le.copy_from_slice(bytes);
        let key = CubeKey::from_raw(u128::from_ne_bytes(le));
        if let Some(before) = *previous
            && before >= key
        {
            return Err(EncodeError::Invalid(format!(
                "keys are not strictly increasing: {before:?} then {key:?}"
            )));
        }
        first.get_or_insert(key);
        *previous = Some(key);
    }
    match (first, *previous) {
        (Some(first), Some(last)) => Ok((rows, first, last)),
        _ => Err(EncodeError::Invalid("empty block".into())),
    }
}

#[cfg(test)]
#[expect(clippy::expect_used, clippy::indexing_slicing, reason = "tests")]
mod tests {
    use super::*;
    use crate::format::segment::SegmentReader;

    /// The chunks of column `name`, as the segment holds them.
    fn chunks<'a>(bytes: &'a [u8], reader: &SegmentReader<'_>, name: &str) -> Vec<&'a [u8]> {
        let directory = reader.directory();
        (0..reader.block_count())
            .map(|block| {
                let (offset, len) = directory.chunk_range(name, block).expect("a chunk");
                &bytes[offset as usize..offset as usize + len]
            })
            .collect()
    }

    #[test]
    fn high_entropy_chunks_keep_raw_literals_and_the_rest_huffman_coding() {
        let rows = 3000u32;
        let keys: Vec<CubeKey> = (0..rows).map(|i| CubeKey::new(12, i, 0, 0)).collect();
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let noise: Vec<u32> = (0..rows)
            .map(|_| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                // A zero top byte: Huffman coding saves about a sixth, as on sample moments.
                state as u32 & 0x00ff_ffff
            })
            .collect();
        let ramp: Vec<u32> = (0..rows).map(|i| i / 7).collect();
        let small: Vec<u32> = noise.iter().map(|x| x & 0xff).collect();
        let columns = [
            Column::keys(keys),
            Column::new("noise", 1, ColumnValues::U32(noise.clone())),
            Column::new("ramp", 1, ColumnValues::U32(ramp.clone())),
            // Asked for raw literals: they are used though Huffman coding would shrink it.
            Column::new("small noise asked raw", 1, ColumnValues::U32(small.clone())).with_raw_literals(),
        ];
        let mut bytes = Vec::new();
        encode_segment_with_block_rows(&columns, 1024, &mut bytes).expect("encodes");
        let reader = SegmentReader::parse(&bytes).expect("parses");
        for (name, values, level) in [
            ("noise", &noise, RAW_LITERALS_ZSTD_LEVEL),
            ("ramp", &ramp, ZSTD_LEVEL),
            ("small noise asked raw", &small, RAW_LITERALS_ZSTD_LEVEL),
        ] {
            for (block, chunk) in chunks(&bytes, &reader, name).into_iter().enumerate() {
                let raw = values.chunks(1024).nth(block).expect("a block");
                let expected = zstd::bulk::compress(bytemuck::cast_slice(raw), level).expect("compresses");
                let huffman = zstd::bulk::compress(bytemuck::cast_slice(raw), ZSTD_LEVEL).expect("compresses");
                assert!(name != "noise" || huffman.len() * 4 > raw.len() * 4 * 3 && huffman != expected);
                assert!(name != "small noise asked raw" || huffman.len() * 4 <= raw.len() * 4 * 3);
                assert_eq!(chunk, expected.as_slice(), "{name}, block {block}");
            }
            assert_eq!(reader.read_u32(name).expect("decodes").1, *values);
        }
        // Raw literals: the noise is stored at its own size, the ramp far below it.
        let noise_bytes: usize = chunks(&bytes, &reader, "noise").iter().map(|c| c.len()).sum();
        let ramp_bytes: usize = chunks(&bytes, &reader, "ramp").iter().map(|c| c.len()).sum();
        assert!(noise_bytes >= 4 * rows as usize, "{noise_bytes}");
        assert!(ramp_bytes < rows as usize, "{ramp_bytes}");
    }

    #[test]
    fn blocks_compressed_in_parallel_are_the_bytes_of_compressing_them_one_by_one() {
        // More blocks than a batch of any pool, with a short last block; each chunk is the
        // block's own zstd frame, and the segment the same bytes whatever the threads.
        let rows = 20 * 512 + 77;
        let mut keys: Vec<CubeKey> = (0..rows).map(|i| CubeKey::new(14, i, i % 5, 3)).collect();
        keys.sort();
        let values: Vec<f32> = (0..rows).map(|i| (i as f32 * 0.37).sin()).collect();
        let columns = [
            Column::keys(keys),
            Column::new("u", 1, ColumnValues::F32(values.clone())),
        ];
        let encode_on = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .expect("a pool");
            let mut bytes = Vec::new();
            pool.install(|| encode_segment_with_block_rows(&columns, 512, &mut bytes))
                .expect("encodes");
            bytes
        };
        let one = encode_on(1);
        for threads in [2, 3, 8] {
            assert!(encode_on(threads) == one, "{threads} threads");
        }
        let reader = SegmentReader::parse(&one).expect("parses");
        let chunks = chunks(&one, &reader, "u");
        assert_eq!(chunks.len(), 21);
        let mut compressor = ChunkCompressor::new().expect("a compressor");
        for (block, (chunk, raw)) in chunks.iter().zip(values.chunks(512)).enumerate() {
            let alone = compressor
                .compress(bytemuck::cast_slice(raw), Compression::Adaptive)
                .expect("compresses");
            assert_eq!(*chunk, alone.as_slice(), "block {block}");
        }
        assert_eq!(reader.read_f32("u").expect("decodes").1, values);
    }
}
