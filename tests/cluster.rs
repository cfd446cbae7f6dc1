//! Cluster runs without a cluster: plan, work and commit as separate processes, with more
//! chunks than cores, a duplicated chunk, a chunk that is missing at the first commit and a
//! damaged chunk output. The result must equal a single-process `solve` byte for byte.

mod common;

use std::path::Path;
use std::process::{Child, Command, Stdio};

use common::*;
use glam::DVec3;
use octstore::testing::quality::synthetic_scenes::{SceneSpec, Shape};

fn scene() -> SceneSpec {
    let center = DVec3::new(0.2, -0.1, 0.3);
    SceneSpec {
        shapes: vec![Shape::Sphere { center, radius: 0.5 }],
        cameras: 8,
        distance: 2.2,
        target: center,
        width: 40,
        height: 30,
        fov_degrees: 45.0,
        noise: None,
        room: Some(2.6),
    }
}

fn run(args: &[&str]) -> String {
    let out = octstore(args, &[]);
    assert!(out.status.success(), "{args:?}: {}", stderr(&out));
    stdout(&out)
}

fn spawn_work(store: &str, stage: &str, chunk: u32) -> Child {
    Command::new(octstore_bin())
        .args([
            "work",
            store,
            "--stage",
            stage,
            "--chunk",
            &chunk.to_string(),
            "--threads",
            "1",
        ])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for entry in std::fs::read_dir(from).unwrap() {
        let entry = entry.unwrap();
        let target = to.join(entry.file_name());
        if entry.file_type().unwrap().is_dir() {
            copy_dir(&entry.path(), &target);
        } else {
            std::fs::copy(entry.path(), target).unwrap();
        }
    }
}

/// The scene ingested (with the SSD sample sums) and its octree built in `dir/cluster`, copied
/// to `dir/single`.
fn ingested_twice(dir: &Path) -> (std::path::PathBuf, std::path::PathBuf) {
    let manifest = scene().write(&dir.join("input")).unwrap();
    let cluster = dir.join("cluster");
    let single = dir.join("single");
    let c = cluster.to_str().unwrap();
    run(&[
        "ingest",
        c,
        manifest.to_str().unwrap(),
        "--max-depth",
        "6",
        "--sample-sums",
        "--quiet",
    ]);
    run(&["solve", c, "--until", "octree", "--leaf-cubes", "400", "--quiet"]);
    copy_dir(&cluster, &single);
    (cluster, single)
}

/// The cubes `octstore info --json` counts in `store`.
fn store_cubes(store: &Path) -> u64 {
    let info: serde_json::Value = serde_json::from_str(&run(&["info", store.to_str().unwrap(), "--json"])).unwrap();
    info["cubes"].as_u64().unwrap()
}

/// Checks `plan`'s chunk lines and critical path: the chunks' cubes add up (to `total` where
/// known: the histogram stage works on every cube), and the critical path names the chunk with
/// the most of them, with its share.
fn check_plan_weights(plan: &str, chunks: u32, total: Option<u64>) {
    let cubes: Vec<u64> = (0..chunks)
        .map(|chunk| {
            let prefix = format!("  chunk {chunk}: ");
            let line = plan
                .lines()
                .find(|l| l.starts_with(&prefix))
                .unwrap_or_else(|| panic!("{plan}"));
            let count = line.rsplit(", ").next().unwrap().trim_end_matches(" cubes");
            count.parse().unwrap_or_else(|_| panic!("{line}"))
        })
        .collect();
    let sum: u64 = cubes.iter().sum();
    assert!(sum > 0, "{plan}");
    if let Some(total) = total {
        assert_eq!(sum, total, "{plan}");
    }
    let most = *cubes.iter().max().unwrap();
    let largest = cubes.iter().position(|&c| c == most).unwrap();
    let share = 100.0 * most as f64 / sum as f64;
    let expected = format!("  critical path: chunk {largest}, {most} of the stage's {sum} cubes: {share:.1} %");
    assert!(plan.contains(&expected), "{expected}\n{plan}");
}

#[test]
fn plan_work_commit_equals_a_single_process_solve() {
    let dir = tempfile::tempdir().unwrap();
    let (cluster, single) = ingested_twice(dir.path());
    let (c, s) = (cluster.to_str().unwrap(), single.to_str().unwrap());
    run(&["solve", s, "--iterations", "30", "--leaf-cubes", "400", "--quiet"]);

    let chunks = 5u32;
    let mut stages = vec!["histograms".to_string()];
    stages.extend((0..=6).map(|l| format!("solution-{l:02}")));
    for (index, stage) in stages.iter().enumerate() {
        let plan = run(&[
            "plan",
            c,
            "--stage",
            stage,
            "--chunks",
            &chunks.to_string(),
            "--iterations",
            "30",
        ]);
        assert!(plan.contains(&format!("in {chunks} chunk(s)")), "{plan}");
        check_plan_weights(&plan, chunks, (index == 0).then(|| store_cubes(&single)));
        // All chunks at once, chunk 1 twice; on the histogram stage chunk 3 comes late.
        let late = (index == 0).then_some(3u32);
        let mut workers: Vec<(u32, Child)> = (0..chunks)
            .filter(|c| Some(*c) != late)
            .map(|chunk| (chunk, spawn_work(c, stage, chunk)))
            .collect();
        workers.push((1, spawn_work(c, stage, 1)));
        for (chunk, worker) in workers {
            let out = worker.wait_with_output().unwrap();
            assert!(
                out.status.success(),
                "{stage} chunk {chunk}: {}",
                String::from_utf8_lossy(&out.stderr)
            );
        }
        if let Some(chunk) = late {
            let before = fingerprint(&cluster);
            let out = octstore(&["commit", c, "--stage", stage], &[]);
            assert!(!out.status.success(), "commit with a missing chunk succeeded");
            assert!(
                stderr(&out).contains(&format!("chunk(s) {chunk} of {chunks}")),
                "{}",
                stderr(&out)
            );
            assert_same_store(&before, &fingerprint(&cluster), "a failed commit changed the store");
            // A retried chunk fills the gap; a repeated one is a no-op.
            run(&["work", c, "--stage", stage, "--chunk", &chunk.to_string()]);
            let again = run(&["work", c, "--stage", stage, "--chunk", &chunk.to_string()]);
            assert!(again.contains("already done"), "{again}");
            assert!(!again.contains(" 0 already done"), "{again}");
        }
        if index == 1 {
            // A damaged output is found and named, then redone.
            let chunk_dir = std::fs::read_dir(cluster.join("chunks"))
                .unwrap()
                .next()
                .unwrap()
                .unwrap()
                .path();
            let segment = std::fs::read_dir(&chunk_dir)
                .unwrap()
                .map(|e| e.unwrap().path())
                .find(|p| p.extension().is_some_and(|e| e == "seg"))
                .unwrap();
            let mut bytes = std::fs::read(&segment).unwrap();
            let middle = bytes.len() / 2;
            bytes[middle] ^= 0x40;
            std::fs::write(&segment, bytes).unwrap();
            let out = octstore(&["commit", c, "--stage", stage], &[]);
            assert!(
                !out.status.success() && stderr(&out).contains("missing or damaged"),
                "{}",
                stderr(&out)
            );
            for chunk in 0..chunks {
                run(&["work", c, "--stage", stage, "--chunk", &chunk.to_string()]);
            }
        }
        run(&["commit", c, "--stage", stage, "--quiet"]);
    }
    assert_same_store(
        &fingerprint(&single),
        &fingerprint(&cluster),
        "cluster vs single process",
    );
    // Chunked extraction welds the same mesh as `extract`, byte for byte.
    let mesh_single = dir.path().join("single.ply");
    let mesh_cluster = dir.path().join("cluster.ply");
    run(&["extract", s, "-o", mesh_single.to_str().unwrap()]);
    run(&[
        "plan",
        c,
        "--stage",
        "extract",
        "--chunks",
        "3",
        "-o",
        mesh_cluster.to_str().unwrap(),
    ]);
    let mut workers: Vec<Child> = (0..3).map(|chunk| spawn_work(c, "extract", chunk)).collect();
    workers.push(spawn_work(c, "extract", 2));
    for worker in workers {
        let out = worker.wait_with_output().unwrap();
        assert!(
            out.status.success(),
            "extract: {}",
            String::from_utf8_lossy(&out.stderr)
        );
    }
    // The observed surface (the default) is open where the cameras stopped; the chunks weld
    // into exactly the single-process mesh, with no edge used three times.
    let committed = run(&["commit", c, "--stage", "extract"]);
    assert!(committed.contains(" 0 non-manifold edges"), "{committed}");
    assert!(std::fs::read(mesh_single).unwrap() == std::fs::read(mesh_cluster).unwrap());
    let out = octstore(&["commit", c, "--stage", "extract"], &[]);
    assert!(
        stderr(&out).contains("no cluster plan"),
        "a spent plan: {}",
        stderr(&out)
    );
}

#[test]
fn cluster_errors_are_clear() {
    let dir = tempfile::tempdir().unwrap();
    let manifest = scene().write(&dir.path().join("input")).unwrap();
    let store = dir.path().join("store");
    let s = store.to_str().unwrap();
    run(&["ingest", s, manifest.to_str().unwrap(), "--max-depth", "5", "--quiet"]);
    run(&["solve", s, "--until", "octree", "--quiet"]);
    let out = octstore(&["work", s, "--stage", "histograms", "--chunk", "0"], &[]);
    assert!(stderr(&out).contains("no cluster plan"), "{}", stderr(&out));
    let out = octstore(&["plan", s, "--stage", "octree"], &[]);
    assert!(stderr(&out).contains("--until octree"), "{}", stderr(&out));
    run(&["plan", s, "--stage", "histograms", "--chunks", "2"]);
    let out = octstore(&["work", s, "--stage", "histograms", "--chunk", "2"], &[]);
    assert!(stderr(&out).contains("chunks 0 to 1"), "{}", stderr(&out));
    // The store moves on under the plan: workers refuse.
    run(&["solve", s, "--until", "histograms", "--quiet"]);
    let out = octstore(&["work", s, "--stage", "histograms", "--chunk", "0"], &[]);
    assert!(stderr(&out).contains("changed since the plan"), "{}", stderr(&out));
    // The generated Slurm chain.
    let out = run(&[
        "slurm",
        s,
        "--chunks",
        "4",
        "--partition",
        "big",
        "--sbatch-arg=--time=01:00:00",
        "--device",
        "gpu",
        "--dry-run",
    ]);
    assert!(
        out.contains("#SBATCH --array=0-3") && out.contains("#SBATCH --partition=big"),
        "{out}"
    );
    assert!(
        out.contains("#SBATCH --time=01:00:00")
            && out.contains("--stage histograms --chunk \"$SLURM_ARRAY_TASK_ID\" --device gpu"),
        "{out}"
    );
    assert!(out.contains("commit") && out.contains("solution-05-plan"), "{out}");
    // Every plan job names the method decided now: a plan left to its default would decide
    // again from the capture, whatever `slurm --method` said.
    let plans: Vec<&str> = out.lines().filter(|line| line.contains(" plan ")).collect();
    assert!(
        !plans.is_empty()
            && plans
                .iter()
                .all(|line| line.contains("--method tgv") || line.contains("--method ssd")),
        "{out}"
    );
}

/// `--method ssd` on a cluster: the samples stage and the SSD levels through plan, work and
/// commit equal a single-process `solve --method ssd` byte for byte, and the Slurm chain runs
/// the samples stage after the octree.
#[test]
fn an_ssd_cluster_run_equals_a_single_process_solve() {
    let dir = tempfile::tempdir().unwrap();
    let (cluster, single) = ingested_twice(dir.path());
    let (c, s) = (cluster.to_str().unwrap(), single.to_str().unwrap());
    run(&["solve", s, "--method", "ssd", "--leaf-cubes", "400", "--quiet"]);
    let mut stages = vec!["samples".to_string(), "histograms".to_string()];
    stages.extend((0..=6).map(|l| format!("solution-{l:02}")));
    for stage in &stages {
        run(&["plan", c, "--stage", stage, "--chunks", "3", "--method", "ssd"]);
        for chunk in 0..3u32 {
            run(&["work", c, "--stage", stage, "--chunk", &chunk.to_string()]);
        }
        run(&["commit", c, "--stage", stage, "--quiet"]);
    }
    assert_same_store(
        &fingerprint(&single),
        &fingerprint(&cluster),
        "ssd cluster vs single process",
    );
    let chain = run(&["slurm", s, "--chunks", "2", "--method", "ssd", "--dry-run"]);
    let samples = chain.find("--stage samples").expect("a samples job");
    assert!(
        chain.find("--until octree").is_some_and(|octree| octree < samples)
            && chain
                .find("--stage histograms")
                .is_some_and(|histograms| samples < histograms),
        "{chain}"
    );
    assert!(
        chain.contains("--stage solution-03 --chunks 2") && chain.contains("--method ssd"),
        "{chain}"
    );
}

/// Every `.mesh` piece a cluster extract's workers wrote under `store`.
fn mesh_pieces(store: &Path) -> Vec<std::path::PathBuf> {
    let mut pieces = Vec::new();
    let mut folders = vec![store.to_path_buf()];
    while let Some(folder) = folders.pop() {
        for entry in std::fs::read_dir(&folder).unwrap() {
            let path = entry.unwrap().path();
            if path.is_dir() {
                folders.push(path);
            } else if path.extension().is_some_and(|e| e == "mesh") {
                pieces.push(path);
            }
        }
    }
    pieces.sort();
    pieces
}

/// A commit that finds a damaged piece names its file and leaves the mesh already at the output
/// path as it was (it used to delete it); a cluster extract of a version whose solve has not
/// caught up with its latest ingest is refused, as `extract` refuses it (it used to mesh the
/// older solution).
#[test]
fn cluster_extract_keeps_the_old_mesh_and_refuses_a_stale_solution() {
    let dir = tempfile::tempdir().unwrap();
    let manifest = scene().write(&dir.path().join("input")).unwrap();
    let store = dir.path().join("store");
    let s = store.to_str().unwrap();
    run(&["ingest", s, manifest.to_str().unwrap(), "--max-depth", "5", "--quiet"]);
    run(&["solve", s, "--leaf-cubes", "200", "--quiet"]);
    let mesh = dir.path().join("mesh.ply");
    let m = mesh.to_str().unwrap();
    let cluster_extract = || {
        run(&["plan", s, "--stage", "extract", "--chunks", "2", "-o", m]);
        for chunk in ["0", "1"] {
            run(&["work", s, "--stage", "extract", "--chunk", chunk]);
        }
    };
    cluster_extract();
    run(&["commit", s, "--stage", "extract"]);
    let committed = std::fs::read(&mesh).unwrap();

    cluster_extract();
    let pieces = mesh_pieces(&store);
    assert!(pieces.len() >= 2, "{pieces:?}");
    let damaged = &pieces[pieces.len() / 2];
    let mut bytes = std::fs::read(damaged).unwrap();
    let middle = bytes.len() / 2;
    bytes[middle] ^= 0x10;
    std::fs::write(damaged, &bytes).unwrap();
    let out = octstore(&["commit", s, "--stage", "extract"], &[]);
    assert!(!out.status.success(), "a damaged piece was committed");
    let name = damaged.file_name().unwrap().to_str().unwrap();
    assert!(
        stderr(&out).contains(name),
        "the damaged file is not named: {}",
        stderr(&out)
    );
    assert!(
        std::fs::read(&mesh).unwrap() == committed,
        "the mesh at the output path changed"
    );

    // More views, then only the histograms: the latest version's solution is stale.
    let more = SceneSpec { cameras: 11, ..scene() }
        .write(&dir.path().join("more"))
        .unwrap();
    run(&["ingest", s, more.to_str().unwrap(), "--quiet"]);
    run(&["solve", s, "--until", "histograms", "--leaf-cubes", "200", "--quiet"]);
    let single = octstore(&["extract", s, "-o", m], &[]);
    assert!(!single.status.success(), "extract meshed a stale solution");
    let planned = octstore(&["plan", s, "--stage", "extract", "--chunks", "2", "-o", m], &[]);
    assert!(!planned.status.success(), "plan accepted a stale solution");
    assert!(
        stderr(&planned).contains("older than its octree or histograms"),
        "{}",
        stderr(&planned)
    );
    assert!(std::fs::read(&mesh).unwrap() == committed);
}
