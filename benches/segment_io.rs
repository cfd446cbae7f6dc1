//! Segment write and read throughput on 16 million cubes of all columns (key, radius sum and
//! count, 8 histogram bins, u, v, p, q: 108 bytes per cube decoded).
//!
//! `cargo bench --bench segment_io` (OCTSTORE_BENCH_CUBES overrides the cube count).
//! Write: encode + zstd + write + fsync, one segment per 1M cubes, single thread.
//! Read: checksum + zstd decode of every column, single thread, then all cores.

mod common;

use common::setting;
use std::time::Instant;

use octstore::format::segment::{SegmentReader, encode_segment};
use octstore::format::{Column, ColumnValues, CubeKey};
use rayon::prelude::*;

const CUBES_PER_SEGMENT: usize = 1 << 20;

/// Plausible solver data: smooth fields over Morton-ordered cubes, sparse histograms.
fn columns(segment: usize, cubes: usize) -> Vec<Column> {
    let base = (segment * CUBES_PER_SEGMENT) as u32;
    let keys: Vec<CubeKey> = (0..cubes as u32)
        .map(|i| {
            let n = base + i;
            CubeKey::new(12, n & 0xFFF, (n >> 12) & 0xFFF, n >> 24)
        })
        .collect::<std::collections::BTreeSet<_>>()
        .into_iter()
        .collect();
    let n = keys.len();
    let smooth = |w: usize, phase: f32| -> ColumnValues {
        ColumnValues::F32((0..n * w).map(|i| ((i as f32) * 0.001 + phase).sin() * 0.8).collect())
    };
    let hist = ColumnValues::F32(
        (0..n * 8)
            .map(|i| if i % 8 == (i / 64) % 8 { (i % 5) as f32 } else { 0.0 })
            .collect(),
    );
    vec![
        Column::keys(keys),
        Column::new("radius_sum", 1, smooth(1, 0.3)),
        Column::new(
            "radius_count",
            1,
            ColumnValues::U32((0..n as u32).map(|i| 1 + i % 13).collect()),
        ),
        Column::new("hist", 8, hist),
        Column::new("u", 1, smooth(1, 0.1)),
        Column::new("v", 3, smooth(3, 0.7)),
        Column::new("p", 3, smooth(3, 1.1)),
        Column::new("q", 6, smooth(6, 1.9)),
    ]
}

fn decoded_bytes(columns: &[Column]) -> u64 {
    columns
        .iter()
        .map(|c| (c.values.len() * c.values.element_type().size()) as u64)
        .sum()
}

fn main() {
    let total: usize = setting("OCTSTORE_BENCH_CUBES", 16 << 20);
    let dir = tempfile::tempdir().expect("temp dir");
    let segments = total.div_ceil(CUBES_PER_SEGMENT);
    let mut write_seconds = 0.0;
    let mut raw_bytes = 0u64;
    let mut file_bytes = 0u64;
    let mut paths = Vec::new();
    for s in 0..segments {
        let cubes = CUBES_PER_SEGMENT.min(total - s * CUBES_PER_SEGMENT);
        let data = columns(s, cubes);
        raw_bytes += decoded_bytes(&data);
        let path = dir.path().join(format!("{s:04}.seg"));
        let started = Instant::now();
        let file = std::fs::File::create(&path).expect("create");
        let mut writer = std::io::BufWriter::with_capacity(1 << 20, &file);
        let summary = encode_segment(&data, &mut writer).expect("encode");
        std::io::Write::flush(&mut writer).expect("flush");
        drop(writer);
        file.sync_all().expect("fsync");
        write_seconds += started.elapsed().as_secs_f64();
        file_bytes += summary.bytes;
        paths.push(path);
    }
    let files: Vec<Vec<u8>> = paths.iter().map(|p| std::fs::read(p).expect("read")).collect();
    let read_all = |bytes: &Vec<u8>| -> u64 {
        let reader = SegmentReader::parse(bytes).expect("parse");
        let mut decoded = 0u64;
        for column in reader.columns().to_vec() {
            let c = reader.read_column(&column.name).expect("decode");
            decoded += (c.values.len() * c.values.element_type().size()) as u64;
        }
        decoded
    };
    let started = Instant::now();
    let decoded: u64 = files.iter().map(read_all).sum();
    let read_seconds = started.elapsed().as_secs_f64();
    let started = Instant::now();
    let decoded_parallel: u64 = files.par_iter().map(read_all).sum();
    let read_parallel_seconds = started.elapsed().as_secs_f64();
    assert_eq!(decoded, raw_bytes);
    assert_eq!(decoded_parallel, raw_bytes);
    let mb = |b: u64, s: f64| b as f64 / 1e6 / s;
    println!(
        "segment_io: {total} cubes, {segments} segments, {:.0} MB decoded, {:.0} MB on disk (ratio {:.2})",
        raw_bytes as f64 / 1e6,
        file_bytes as f64 / 1e6,
        raw_bytes as f64 / file_bytes as f64
    );
    println!(
        "segment_io: write (encode+zstd+fsync, 1 thread): {:.0} MB/s decoded data",
        mb(raw_bytes, write_seconds)
    );
    println!(
        "segment_io: read (checksum+zstd decode, 1 thread): {:.0} MB/s decoded data",
        mb(decoded, read_seconds)
    );
    println!(
        "segment_io: read ({} threads): {:.0} MB/s decoded data",
        rayon::current_num_threads(),
        mb(decoded, read_parallel_seconds)
    );
}
