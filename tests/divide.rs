//! `octstore divide` through the command line: the manifest it writes accounts for every point
//! (each in exactly one core, every file holding the points of its grown cube), no core passes
//! `--max-points`, the files do not depend on the thread count, the generated cloud of the
//! benchmarks divides the same way, and a damaged input is an error that names the file. The
//! library's tests (`src/divide/tests.rs`) cover the division's cases one by one.

mod common;

use std::path::Path;

use common::{octstore, stderr, stdout};
use octstore::divide::{Cube, Manifest, read_manifest_file};

/// A cloud of `count` points spread unevenly over [0, 10)^3 (denser towards the origin, so
/// the division is deeper there), as `x y z` lines.
fn cloud_xyz(count: usize) -> String {
    let mut state = 0x2545_F491_4F6C_DD1Du64;
    let mut next = || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 11) as f64 / (1u64 << 53) as f64
    };
    let mut text = String::new();
    for _ in 0..count {
        let [x, y, z] = [next(), next(), next()].map(|u| 10.0 * u * u);
        text.push_str(&format!("{x:.6} {y:.6} {z:.6}\n"));
    }
    text
}

fn points_of(text: &str) -> Vec<[f64; 3]> {
    text.lines()
        .map(|line| {
            let mut values = line.split_whitespace().map(|v| v.parse::<f64>().expect("a number"));
            [0; 3].map(|_| values.next().expect("three numbers"))
        })
        .collect()
}

fn holds(cube: &Cube, p: [f64; 3]) -> bool {
    (0..3).all(|a| cube.min[a] <= p[a] && p[a] < cube.min[a] + cube.size)
}

/// The vertex count a subspace PLY's header announces.
fn ply_vertices(path: &Path) -> u64 {
    let bytes = std::fs::read(path).expect("a subspace file");
    let end = bytes
        .windows(10)
        .position(|w| w == b"end_header")
        .expect("a PLY header");
    let header = String::from_utf8_lossy(bytes.get(..end).unwrap_or_default()).into_owned();
    header
        .lines()
        .find_map(|l| l.strip_prefix("element vertex "))
        .and_then(|n| n.trim().parse().ok())
        .expect("element vertex")
}

fn divide(args: &[&str]) -> Manifest {
    let out = octstore(args, &[]);
    assert!(out.status.success(), "{args:?}: {}", stderr(&out));
    assert!(stdout(&out).starts_with("divide "), "{}", stdout(&out));
    let dir = args
        .iter()
        .position(|a| *a == "-o")
        .and_then(|i| args.get(i + 1))
        .expect("-o DIR");
    read_manifest_file(&Path::new(dir).join("subspaces.json")).expect("the manifest")
}

/// Every subspace's file holds as many points as the manifest says, and no core more than
/// `max_points`; the cores' points add up to `total`.
fn check_files(dir: &Path, manifest: &Manifest, max_points: u64, total: u64) {
    let mut core_points = 0;
    for subspace in &manifest.subspaces {
        assert!(
            subspace.core_points <= max_points,
            "{}: {}",
            subspace.file,
            subspace.core_points
        );
        assert!(subspace.core_points <= subspace.points, "{}", subspace.file);
        assert_eq!(
            ply_vertices(&dir.join(&subspace.file)),
            subspace.points,
            "{}",
            subspace.file
        );
        core_points += subspace.core_points;
    }
    assert_eq!(core_points, total);
}

#[test]
fn a_division_accounts_for_every_point_whatever_the_thread_count() {
    let dir = tempfile::tempdir().expect("a temporary folder");
    let text = cloud_xyz(6000);
    let cloud = dir.path().join("cloud.xyz");
    std::fs::write(&cloud, &text).expect("write the cloud");
    let cloud = cloud.to_string_lossy().into_owned();
    let outputs = ["two", "one"].map(|name| dir.path().join(name).to_string_lossy().into_owned());
    let [two, one] = &outputs;
    let manifest = divide(&[
        "--quiet",
        "--threads",
        "2",
        "divide",
        &cloud,
        "-o",
        two,
        "--max-points",
        "700",
    ]);
    assert!(manifest.subspaces.len() >= 9, "{} subspaces", manifest.subspaces.len());
    check_files(Path::new(two), &manifest, 700, 6000);

    // Each point in exactly one core, and counted in every grown cube that holds it.
    let points = points_of(&text);
    let mut grown_holds = vec![0u64; manifest.subspaces.len()];
    for &p in &points {
        let cores = manifest.subspaces.iter().filter(|s| holds(&s.core, p)).count();
        assert_eq!(cores, 1, "{p:?} lies in {cores} cores");
        for (count, subspace) in grown_holds.iter_mut().zip(&manifest.subspaces) {
            *count += u64::from(holds(&subspace.grown, p));
        }
    }
    for (count, subspace) in grown_holds.iter().zip(&manifest.subspaces) {
        assert_eq!(*count, subspace.points, "{}", subspace.file);
    }

    // One thread writes the same bytes.
    divide(&[
        "--quiet",
        "--threads",
        "1",
        "divide",
        &cloud,
        "-o",
        one,
        "--max-points",
        "700",
    ]);
    for name in manifest
        .subspaces
        .iter()
        .map(|s| s.file.as_str())
        .chain(["subspaces.json"])
    {
        let [a, b] = [two, one].map(|d| std::fs::read(Path::new(d).join(name)).expect("a written file"));
        assert!(a == b, "{name} differs between 2 threads and 1");
    }
}

#[test]
fn the_generated_cloud_of_the_benchmarks_divides_within_the_limit() {
    let dir = tempfile::tempdir().expect("a temporary folder");
    let out = dir.path().join("parts");
    let out = out.to_string_lossy().into_owned();
    let manifest = divide(&[
        "--quiet",
        "divide",
        "--synthetic",
        "200000",
        "-o",
        &out,
        "--max-points",
        "30000",
    ]);
    assert!(manifest.subspaces.len() >= 7, "{} subspaces", manifest.subspaces.len());
    check_files(Path::new(&out), &manifest, 30_000, 200_000);
}

#[test]
fn a_truncated_ply_is_an_error_that_names_it() {
    let dir = tempfile::tempdir().expect("a temporary folder");
    let mut bytes =
        b"ply\nformat binary_little_endian 1.0\nelement vertex 1000\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
            .to_vec();
    bytes.extend((0..500u32 * 3).flat_map(|i| (i as f32 * 0.01).to_le_bytes()));
    let cloud = dir.path().join("short.ply");
    std::fs::write(&cloud, bytes).expect("write the cloud");
    let out = dir.path().join("parts");
    let output = octstore(
        &[
            "--quiet",
            "divide",
            &cloud.to_string_lossy(),
            "-o",
            &out.to_string_lossy(),
            "--max-points",
            "100",
        ],
        &[],
    );
    assert!(!output.status.success(), "a truncated PLY divided");
    let message = stderr(&output);
    assert!(message.contains("short.ply"), "{message}");
    assert!(
        !out.join("subspaces.json").exists(),
        "a manifest was written for a failed division"
    );
}

/// A change made to a manifest's JSON.
type Damage = fn(&mut serde_json::Value);

/// `merge` checks the manifest before trusting it: two subspaces sharing a core, a core of
/// negative side, or a node outside the root are refused naming the manifest, where they used
/// to drop thousands of triangles without a word.
#[test]
fn merge_refuses_a_manifest_whose_cores_do_not_tile_the_root() {
    let dir = tempfile::tempdir().expect("a temporary folder");
    let cloud = dir.path().join("cloud.xyz");
    std::fs::write(&cloud, cloud_xyz(3000)).expect("write the cloud");
    let parts = dir.path().join("parts");
    let (cloud, parts_arg) = (
        cloud.to_string_lossy().into_owned(),
        parts.to_string_lossy().into_owned(),
    );
    let manifest = divide(&["--quiet", "divide", &cloud, "-o", &parts_arg, "--max-points", "700"]);
    assert!(manifest.subspaces.len() >= 3, "{} subspaces", manifest.subspaces.len());
    manifest.check().expect("the written manifest passes");
    let path = parts.join("subspaces.json");
    let original: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&path).expect("the manifest")).expect("JSON");
    let damages: [(&str, Damage); 3] = [
        ("overlap", |m| {
            m["subspaces"][1]["node"] = m["subspaces"][0]["node"].clone()
        }),
        ("is not its node's cube", |m| {
            m["subspaces"][0]["core"]["size"] = (-1.0).into()
        }),
        ("is not inside the root", |m| {
            m["subspaces"][0]["node"]["index"][0] = (1u64 << 20).into()
        }),
    ];
    for (expected, damage) in damages {
        let mut damaged = original.clone();
        damage(&mut damaged);
        // The core of a copied node must still be that node's cube: copy it too.
        if expected == "overlap" {
            damaged["subspaces"][1]["core"] = damaged["subspaces"][0]["core"].clone();
            damaged["subspaces"][1]["grown"] = damaged["subspaces"][0]["grown"].clone();
        }
        std::fs::write(&path, damaged.to_string()).expect("write the damaged manifest");
        let mesh = dir.path().join("merged.ply");
        // The manifest is read first: the piece need not be a mesh.
        let piece = dir.path().join(manifest.subspaces[0].file.replace(".ply", ".mesh.ply"));
        std::fs::write(&piece, b"ply").expect("write a piece");
        let out = octstore(
            &[
                "merge",
                path.to_str().expect("UTF-8"),
                piece.to_str().expect("UTF-8"),
                "-o",
                mesh.to_str().expect("UTF-8"),
            ],
            &[],
        );
        let text = stderr(&out);
        assert!(!out.status.success(), "{expected}: merged anyway");
        assert!(
            text.contains("subspaces.json") && text.contains(expected),
            "{expected}: {text}"
        );
        assert!(!mesh.exists(), "{expected}: wrote a mesh");
    }
}
