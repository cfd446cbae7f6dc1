//! Depth maps larger than the memory budget (issue: "bounded ingest"): rows are decoded a few
//! at a time and cube entries spill to sorted runs, so ingest's peak memory does not grow with
//! the image; the store is byte-identical whatever the budget.

mod common;

use std::path::{Path, PathBuf};

use common::{assert_same_store, fingerprint, octstore, stderr, stdout, write_png16};
use glam::DVec3;
use octstore::inputs::{DepthImage, read_pfm, read_png16};
use octstore::testing::quality::synthetic_scenes::SceneSpec;

/// One 2000x1500 view of the demo's sphere and box inside its room, without noise (every
/// pixel valid: 3 M samples).
fn large_view(dir: &Path) -> PathBuf {
    let spec = SceneSpec {
        cameras: 1,
        width: 2000,
        height: 1500,
        noise: None,
        ..SceneSpec::demo()
    };
    spec.write(dir).unwrap()
}

/// The PFM view re-encoded as a 16-bit PNG (0.1 mm units) with its manifest.
fn as_png(manifest: &Path) -> PathBuf {
    let dir = manifest.parent().unwrap();
    let image = read_pfm(&dir.join("view-000.pfm")).unwrap();
    write_png16(&dir.join("view-000.png"), &image, 1e-4);
    let text = std::fs::read_to_string(manifest)
        .unwrap()
        .replace("view-000.pfm", "view-000.png")
        .replace("\"kind\"", "\"depth_scale\": 0.0001, \"kind\"");
    let png_manifest = dir.join("png.json");
    std::fs::write(&png_manifest, text).unwrap();
    png_manifest
}

/// `octstore ingest` at `budget`; returns the peak memory it reports, in MB.
fn ingest(store: &Path, manifest: &Path, budget: &str) -> f64 {
    let out = octstore(
        &[
            "ingest",
            store.to_str().unwrap(),
            manifest.to_str().unwrap(),
            "--max-depth",
            "10",
            "--memory-budget",
            budget,
        ],
        &[],
    );
    assert!(out.status.success(), "ingest at {budget}: {}", stderr(&out));
    let report = stdout(&out);
    report
        .split("peak memory ")
        .nth(1)
        .and_then(|s| s.split(" MB").next())
        .and_then(|s| s.trim().parse::<f64>().ok())
        .unwrap_or_else(|| panic!("no peak memory in {report}"))
}

/// A 3-megapixel map at the least budget (32 MiB: about 80,000 cubes in memory per
/// map) streams its rows and spills several runs, and gives the same store, byte for byte, as
/// the same map ingested whole in memory (8 GiB budget: one buffer, no spill), for PFM
/// (stored bottom-up, read by seeking) and PNG (decoded row by row). Before rows were
/// streamed, this ingest held every pixel's camera point, sample and entry at once: about
/// 0.9 GB whatever the budget.
#[test]
fn a_map_larger_than_the_budget_ingests_in_bounded_memory_into_the_same_store() {
    let dir = tempfile::tempdir().unwrap();
    let manifest = large_view(&dir.path().join("input"));
    let png = as_png(&manifest);
    for (name, input) in [("pfm", &manifest), ("png", &png)] {
        let small = dir.path().join(format!("{name}-small"));
        let large = dir.path().join(format!("{name}-large"));
        let peak_small = ingest(&small, input, "32MiB");
        let peak_large = ingest(&large, input, "8GiB");
        assert_same_store(&fingerprint(&small), &fingerprint(&large), name);
        // The whole-map path holds the map's cubes in one table plus its columns (about 90 MB
        // more than the streaming path's peak: the table keeps 32-byte totals and index slots;
        // with 96-byte sums per slot it was about 0.27 GB); the streaming path a 32 MiB
        // budget's share plus the process itself.
        assert!(
            peak_large > peak_small + 50.0,
            "{name}: the reference did not hold the map in memory ({peak_large} MB, {peak_small} MB at 32 MiB)"
        );
        assert!(peak_small < 150.0, "{name}: {peak_small} MB at a 32 MiB budget");
        // Scratch files are unlinked at creation: nothing is left behind.
        assert!(!small.join("tmp").exists(), "{name}: scratch left behind");
    }
}

/// The row decoders give exactly the whole-image decoders' values: the PNG against the image
/// crate's decoder, the PFM against the values that were written.
#[test]
fn row_decoders_match_whole_image_decoding() {
    let dir = tempfile::tempdir().unwrap();
    let (width, height) = (37u32, 23u32);
    let depth: Vec<f32> = (0..width * height)
        .map(|i| {
            if i % 11 == 0 {
                f32::NAN
            } else {
                0.5 + (i % 97) as f32 * 0.01
            }
        })
        .collect();
    let image = DepthImage { width, height, depth };
    let pfm = dir.path().join("d.pfm");
    octstore::inputs::write_pfm(&pfm, &image).unwrap();
    let read = read_pfm(&pfm).unwrap();
    assert_eq!(read.width, width);
    for (a, b) in read.depth.iter().zip(&image.depth) {
        assert!(a == b || (a.is_nan() && b.is_nan()), "{a} {b}");
    }
    let png = dir.path().join("d.png");
    let raw: Vec<u16> = (0..width * height)
        .map(|i| (i.wrapping_mul(2_654_435_761) >> 16) as u16)
        .collect();
    image::ImageBuffer::<image::Luma<u16>, _>::from_raw(width, height, raw.clone())
        .unwrap()
        .save(&png)
        .unwrap();
    let decoded = image::open(&png).unwrap().into_luma16().into_raw();
    assert_eq!(decoded, raw);
    let rows = read_png16(&png, 0.001).unwrap();
    for (v, d) in raw.iter().zip(&rows.depth) {
        let expected = if *v == 0 || *v == u16::MAX {
            f32::NAN
        } else {
            (f64::from(*v) * 0.001) as f32
        };
        assert!(*d == expected || (d.is_nan() && expected.is_nan()), "{v} -> {d}");
    }
}

/// A 6 KB PTX whose returns lie a hundredth of a milliradian apart: its grid would be 628,000
/// pixels wide at the scan's own step, so the width is capped (8192 x 4096), and the grid is
/// back-projected through the row window. It took 1.19 GB before (every pixel's camera point
/// and sample at once); the grid itself is 128 MiB.
#[test]
fn a_lidar_scan_at_a_tiny_angular_step_stays_within_the_budget() {
    let dir = tempfile::tempdir().unwrap();
    let ptx = dir.path().join("tiny.ptx");
    let (columns, rows) = (20, 10);
    let mut text = format!("{columns}\n{rows}\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n");
    for c in 0..columns {
        for r in 0..rows {
            let (azimuth, elevation) = (f64::from(c) * 1e-5, f64::from(r) * 1e-5);
            let p = DVec3::new(
                elevation.cos() * azimuth.cos(),
                elevation.cos() * azimuth.sin(),
                elevation.sin(),
            ) * 5.0;
            text.push_str(&format!("{} {} {} 0.5\n", p.x, p.y, p.z));
        }
    }
    std::fs::write(&ptx, text).unwrap();
    let peak = ingest(&dir.path().join("store"), &ptx, "256MiB");
    assert!(peak < 300.0, "{peak} MB at a 256 MiB budget");
}

/// A large PNG cut short after its header: ingest reads it row by row, so the damage shows up
/// mid-image; the error names the file and the problem, and the store stays at its last commit
/// with no scratch left.
#[test]
fn a_truncated_large_png_is_a_clear_error_and_changes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let manifest = large_view(&dir.path().join("input"));
    let png = as_png(&manifest);
    let store = dir.path().join("store");
    // A first depth map, so the store has a commit to keep.
    let first = octstore(
        &[
            "ingest",
            store.to_str().unwrap(),
            manifest.to_str().unwrap(),
            "--max-depth",
            "10",
        ],
        &[],
    );
    assert!(first.status.success(), "{}", stderr(&first));
    let before = fingerprint(&store);
    let image = manifest.parent().unwrap().join("view-000.png");
    let bytes = std::fs::read(&image).unwrap();
    std::fs::write(&image, &bytes[..bytes.len() * 2 / 3]).unwrap();
    let out = octstore(
        &[
            "ingest",
            store.to_str().unwrap(),
            png.to_str().unwrap(),
            "--max-depth",
            "10",
            "--memory-budget",
            "32MiB",
        ],
        &[],
    );
    let message = stderr(&out);
    assert!(!out.status.success());
    assert!(
        message.contains("view-000.png") && message.contains("truncated"),
        "{message}"
    );
    assert_same_store(&before, &fingerprint(&store), "after the failed ingest");
    assert!(!store.join("tmp").exists(), "scratch left behind");
}

/// CRC-32 (IEEE) of `bytes`, as PNG chunks carry it.
fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &byte in bytes {
        crc ^= u32::from(byte);
        for _ in 0..8 {
            crc = if crc & 1 == 1 {
                (crc >> 1) ^ 0xEDB8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

/// `image` as an Adam7-interlaced 16-bit grey PNG (values `depth / scale`), written by hand:
/// the image crate's encoder does not interlace. The zlib stream uses stored blocks.
fn write_interlaced_png16(path: &Path, image: &DepthImage, scale: f64) {
    const PASSES: [(usize, usize, usize, usize); 7] = [
        (0, 0, 8, 8),
        (4, 0, 8, 8),
        (0, 4, 4, 8),
        (2, 0, 4, 4),
        (0, 2, 2, 4),
        (1, 0, 2, 2),
        (0, 1, 1, 2),
    ];
    let (width, height) = (image.width as usize, image.height as usize);
    let value = |x: usize, y: usize| -> u16 {
        let d = image.depth[y * width + x];
        if d.is_finite() {
            (f64::from(d) / scale).round() as u16
        } else {
            0
        }
    };
    let mut raw = Vec::new();
    for (x0, y0, dx, dy) in PASSES {
        if x0 >= width || y0 >= height {
            continue;
        }
        for y in (y0..height).step_by(dy) {
            raw.push(0); // filter: none
            for x in (x0..width).step_by(dx) {
                raw.extend_from_slice(&value(x, y).to_be_bytes());
            }
        }
    }
    let mut zlib = vec![0x78, 0x01];
    let blocks: Vec<&[u8]> = raw.chunks(65_535).collect();
    for (i, block) in blocks.iter().enumerate() {
        zlib.push(u8::from(i + 1 == blocks.len()));
        let len = block.len() as u16;
        zlib.extend_from_slice(&len.to_le_bytes());
        zlib.extend_from_slice(&(!len).to_le_bytes());
        zlib.extend_from_slice(block);
    }
    let (mut a, mut b) = (1u32, 0u32);
    for &byte in &raw {
        a = (a + u32::from(byte)) % 65_521;
        b = (b + a) % 65_521;
    }
    zlib.extend_from_slice(&((b << 16) | a).to_be_bytes());
    let mut png = b"\x89PNG\r\n\x1a\n".to_vec();
    let mut chunk = |kind: &[u8], data: &[u8]| {
        png.extend_from_slice(&(data.len() as u32).to_be_bytes());
        let mut body = kind.to_vec();
        body.extend_from_slice(data);
        png.extend_from_slice(&body);
        png.extend_from_slice(&crc32(&body).to_be_bytes());
    };
    let mut header = Vec::new();
    header.extend_from_slice(&image.width.to_be_bytes());
    header.extend_from_slice(&image.height.to_be_bytes());
    header.extend_from_slice(&[16, 0, 0, 0, 1]); // 16 bits, grey, deflate, filter 0, Adam7
    chunk(b"IHDR", &header);
    chunk(b"IDAT", &zlib);
    chunk(b"IEND", &[]);
    std::fs::write(path, png).unwrap();
}

/// An interlaced PNG comes in seven passes and is decoded whole: too large for the budget's
/// share of one map, it is refused naming the file (it used to take 1.5 GB at 256 MiB); where
/// the budget holds it whole, it ingests into the same store as the plain PNG.
#[test]
fn an_interlaced_png_beyond_the_budget_is_refused_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let manifest = large_view(&dir.path().join("input"));
    let png = as_png(&manifest);
    let folder = manifest.parent().unwrap();
    let plain = read_png16(&folder.join("view-000.png"), 1e-4).unwrap();
    write_interlaced_png16(&folder.join("view-000-adam7.png"), &plain, 1e-4);
    assert_eq!(
        read_png16(&folder.join("view-000-adam7.png"), 1e-4)
            .unwrap()
            .depth
            .iter()
            .map(|d| d.to_bits())
            .collect::<Vec<_>>(),
        plain.depth.iter().map(|d| d.to_bits()).collect::<Vec<_>>(),
        "the hand-written interlaced PNG decodes to the plain one"
    );
    let interlaced = folder.join("adam7.json");
    std::fs::write(
        &interlaced,
        std::fs::read_to_string(&png)
            .unwrap()
            .replace("view-000.png", "view-000-adam7.png"),
    )
    .unwrap();
    let store = dir.path().join("refused");
    let out = octstore(
        &[
            "ingest",
            store.to_str().unwrap(),
            interlaced.to_str().unwrap(),
            "--max-depth",
            "10",
            "--memory-budget",
            "32MiB",
        ],
        &[],
    );
    let message = stderr(&out);
    assert!(!out.status.success(), "an interlaced map beyond the budget was read");
    assert!(
        message.contains("view-000-adam7.png") && message.contains("interlaced"),
        "{message}"
    );
    // The same pixels give the same samples and cubes (the stores differ in the maps' ids,
    // which hash the files' bytes).
    let counts = |input: &Path, name: &str| -> String {
        let store = dir.path().join(name);
        let out = octstore(
            &[
                "ingest",
                store.to_str().unwrap(),
                input.to_str().unwrap(),
                "--max-depth",
                "10",
            ],
            &[],
        );
        assert!(out.status.success(), "{name}: {}", stderr(&out));
        let report = stdout(&out);
        report
            .split("depth map(s): ")
            .nth(1)
            .and_then(|s| s.split(" in ").next())
            .unwrap_or_else(|| panic!("{report}"))
            .to_string()
    };
    assert_eq!(counts(&interlaced, "whole"), counts(&png, "reference"));
}
