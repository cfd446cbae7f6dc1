//! Segment round trips, corruption detection and block views.

#![expect(clippy::unwrap_used, clippy::indexing_slicing, reason = "tests")]

use super::*;

fn sample(rows: usize) -> Vec<Column> {
    let keys: Vec<CubeKey> = (0..rows as u32).map(|i| CubeKey::new(16, i, i / 3, 7)).collect();
    let mut sorted = keys.clone();
    sorted.sort();
    vec![
        Column::keys(sorted),
        Column::new("u", 1, ColumnValues::F32((0..rows).map(|i| i as f32 * 0.5).collect())),
        Column::new("v", 3, ColumnValues::F32((0..rows * 3).map(|i| -(i as f32)).collect())),
        Column::new("count", 1, ColumnValues::U32((0..rows as u32).collect())),
    ]
}

fn encode(columns: &[Column], block_rows: u32) -> (Vec<u8>, SegmentSummary) {
    let mut out = Vec::new();
    let summary = encode_segment_with_block_rows(columns, block_rows, &mut out).unwrap();
    (out, summary)
}

#[test]
fn round_trip_and_digest() {
    let columns = sample(1000);
    let (bytes, summary) = encode(&columns, 64);
    assert_eq!(summary.bytes as usize, bytes.len());
    assert_eq!(summary.file_checksum, xxh3_64(&bytes));
    let reader = SegmentReader::parse(&bytes).unwrap();
    for column in &columns {
        assert_eq!(&reader.read_column(&column.name).unwrap(), column);
    }
    assert_eq!(reader.verify().unwrap(), summary.content_digest);
    // The content digest does not depend on block size; the bytes do.
    let (other, other_summary) = encode(&columns, 1000);
    assert_ne!(other, bytes);
    assert_eq!(other_summary.content_digest, summary.content_digest);
}

#[test]
fn every_flipped_byte_and_every_truncation_is_detected() {
    let (bytes, _) = encode(&sample(40), 16);
    for i in 0..bytes.len() {
        let mut bad = bytes.clone();
        bad[i] ^= 0x20;
        let result = SegmentReader::parse(&bad).and_then(|r| r.verify());
        assert!(result.is_err(), "flip at byte {i} of {} went unnoticed", bytes.len());
    }
    for len in 0..bytes.len() {
        let result = SegmentReader::parse(&bytes[..len]).and_then(|r| r.verify());
        assert!(result.is_err(), "truncation to {len} went unnoticed");
    }
}

/// A detached directory decodes every block from the chunk bytes it names as the reader
/// does, and refuses bytes of the wrong length or with a flipped bit.
#[test]
fn a_detached_directory_decodes_blocks_from_their_chunks() {
    let columns = sample(1000);
    let (bytes, _) = encode(&columns, 64);
    let reader = SegmentReader::parse(&bytes).unwrap();
    let directory = reader.directory();
    assert_eq!(directory.block_count(), reader.block_count());
    for column in &columns {
        for block in 0..directory.block_count() {
            assert_eq!(directory.block_key_range(block), reader.block_key_range(block));
            let (offset, len) = directory.chunk_range(&column.name, block).unwrap();
            let chunk = &bytes[offset as usize..offset as usize + len];
            assert_eq!(
                directory.decode_block(&column.name, block, chunk).unwrap(),
                reader.read_block(&column.name, block).unwrap()
            );
            assert!(directory.decode_block(&column.name, block, &chunk[1..]).is_err());
            let mut flipped = chunk.to_vec();
            flipped[len / 2] ^= 1;
            assert!(directory.decode_block(&column.name, block, &flipped).is_err());
        }
    }
    assert!(directory.chunk_range("no such column", 0).is_err());
    assert!(directory.chunk_range("key", directory.block_count()).is_err());
}

#[test]
fn rejects_invalid_content() {
    let mut columns = sample(10);
    columns[1].values = ColumnValues::F32(vec![0.0; 3]);
    assert!(encode_segment(&columns, &mut Vec::new()).is_err());
    let unsorted = vec![Column::keys(vec![CubeKey::new(3, 1, 0, 0), CubeKey::new(3, 0, 0, 0)])];
    assert!(encode_segment(&unsorted, &mut Vec::new()).is_err());
}

#[test]
fn encoding_is_deterministic() {
    let columns = sample(5000);
    assert_eq!(encode(&columns, 1024).0, encode(&columns, 1024).0);
}

/// A view of some blocks reads exactly their rows, in order, and still checks their chunks:
/// a flipped byte in a kept block is an error naming the block's number in the whole segment;
/// one in a dropped block goes unread.
#[test]
fn a_view_of_some_blocks_reads_exactly_their_rows() {
    let columns = sample(1000);
    let (bytes, _) = encode(&columns, 64);
    let reader = SegmentReader::parse(&bytes).unwrap();
    let threshold = reader.block_key_range(5).unwrap().0;
    let kept: Vec<usize> = (0..reader.block_count())
        .filter(|&b| b % 3 == 1 || reader.block_key_range(b).unwrap().0 < threshold)
        .collect();
    let view = reader.with_blocks_where(|first, _| {
        let block = (0..reader.block_count())
            .find(|&b| reader.block_key_range(b).unwrap().0 == first)
            .unwrap();
        block % 3 == 1 || first < threshold
    });
    assert_eq!(view.block_count(), kept.len());
    let mut expected_keys = Vec::new();
    let mut expected_v = Vec::new();
    for &b in &kept {
        let ColumnValues::Key(keys) = reader.read_block("key", b).unwrap() else {
            panic!()
        };
        let ColumnValues::F32(v) = reader.read_block("v", b).unwrap() else {
            panic!()
        };
        expected_keys.extend(keys);
        expected_v.extend(v);
    }
    assert_eq!(view.rows() as usize, expected_keys.len());
    assert_eq!(view.read_keys().unwrap(), expected_keys);
    assert_eq!(view.read_f32("v").unwrap(), (3, expected_v));
    let none = reader.with_blocks_where(|_, _| false);
    assert_eq!((none.rows(), none.read_keys().unwrap().len()), (0, 0));

    let chunk_of = |block: usize| {
        let (offset, len) = reader.directory().chunk_range("u", block).unwrap();
        offset as usize + len / 2
    };
    let mut flipped = bytes.clone();
    flipped[chunk_of(2)] ^= 1;
    let damaged = SegmentReader::parse(&flipped).unwrap();
    assert!(
        damaged
            .with_blocks_where(|first, _| first < threshold)
            .read_f32("u")
            .is_err()
    );
    let error = damaged.with_blocks_where(|first, _| first >= threshold).read_f32("u");
    assert!(error.is_ok());
    let mut flipped = bytes.clone();
    flipped[chunk_of(7)] ^= 1;
    let damaged = SegmentReader::parse(&flipped).unwrap();
    let error = damaged
        .with_blocks_where(|first, _| first >= threshold)
        .read_f32("u")
        .unwrap_err();
    assert!(format!("{error}").contains("block 7"), "{error}");
}
