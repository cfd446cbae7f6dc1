//! A real single-node Slurm (Debian's slurmctld, slurmd and munge; no cgroups), started under a
//! temporary folder, runs the pipeline after ingest on a few RedKitchen frames as job arrays
//! with more chunks than cores. Every segment and the catalog must equal a single-process solve.
//! `.ci/run` installs the packages; where they are missing the test says so and skips.

mod common;

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use common::*;

const TOOLS: [&str; 6] = ["slurmctld", "slurmd", "munged", "sbatch", "scontrol", "sinfo"];

fn find_tool(name: &str) -> Option<PathBuf> {
    [
        "/usr/sbin",
        "/usr/bin",
        "/sbin",
        "/bin",
        "/usr/local/sbin",
        "/usr/local/bin",
    ]
    .iter()
    .map(|dir| Path::new(dir).join(name))
    .find(|p| p.is_file())
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// The daemons, stopped by their PIDs when the test ends, however it ends.
struct Cluster {
    dir: tempfile::TempDir,
    conf: PathBuf,
    daemons: Vec<Child>,
}

impl Drop for Cluster {
    fn drop(&mut self) {
        for child in self.daemons.iter_mut().rev() {
            let _ = Command::new("kill").arg("-TERM").arg(child.id().to_string()).status();
            let deadline = Instant::now() + Duration::from_secs(5);
            while Instant::now() < deadline && matches!(child.try_wait(), Ok(None)) {
                std::thread::sleep(Duration::from_millis(50));
            }
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

impl Cluster {
    fn command(&self, tool: &str) -> Command {
        let mut command = Command::new(find_tool(tool).unwrap_or_else(|| PathBuf::from(tool)));
        command.env("SLURM_CONF", &self.conf);
        command
    }

    fn log_tail(&self) -> String {
        let mut text = String::new();
        for name in ["slurmctld.log", "slurmd.log", "munged.log"] {
            let content = std::fs::read_to_string(self.dir.path().join(name)).unwrap_or_default();
            let lines: Vec<&str> = content.lines().collect();
            text.push_str(&format!(
                "--- {name}\n{}\n",
                lines[lines.len().saturating_sub(15)..].join("\n")
            ));
        }
        text
    }

    fn start() -> Cluster {
        let dir = tempfile::tempdir().unwrap();
        let root_buf = dir.path().to_path_buf();
        let root = root_buf.as_path();
        for sub in ["state", "spool"] {
            std::fs::create_dir_all(root.join(sub)).unwrap();
        }
        let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
            .unwrap()
            .trim()
            .split('.')
            .next()
            .unwrap()
            .to_string();
        let user = String::from_utf8(Command::new("id").arg("-un").output().unwrap().stdout)
            .unwrap()
            .trim()
            .to_string();
        let mut key = [0u8; 1024];
        std::io::Read::read_exact(&mut std::fs::File::open("/dev/urandom").unwrap(), &mut key).unwrap();
        let key_path = root.join("munge.key");
        std::fs::write(&key_path, key).unwrap();
        // munged refuses a key that others can read.
        std::fs::set_permissions(&key_path, std::os::unix::fs::PermissionsExt::from_mode(0o400)).unwrap();
        let socket = root.join("munge.sock");
        let cpus = std::thread::available_parallelism().map_or(2, |n| n.get());
        let r = root.display();
        let conf = format!(
            "ClusterName=octtest\nSlurmctldHost={host}(127.0.0.1)\nSlurmUser={user}\nSlurmdUser={user}\n\
             SlurmctldPort={}\nSlurmdPort={}\nAuthType=auth/munge\nAuthInfo=socket={}\nCredType=cred/munge\n\
             StateSaveLocation={r}/state\nSlurmdSpoolDir={r}/spool\nSlurmctldPidFile={r}/slurmctld.pid\n\
             SlurmdPidFile={r}/slurmd.pid\nSlurmctldLogFile={r}/slurmctld.log\nSlurmdLogFile={r}/slurmd.log\n\
             ProctrackType=proctrack/linuxproc\nTaskPlugin=task/none\nJobAcctGatherType=jobacct_gather/none\n\
             AccountingStorageType=accounting_storage/none\nSchedulerType=sched/builtin\n\
             SchedulerParameters=sched_interval=1\nSelectType=select/cons_tres\nSelectTypeParameters=CR_CPU\n\
             MpiDefault=none\nReturnToService=2\nMinJobAge=600\n\
             NodeName={host} NodeAddr=127.0.0.1 CPUs={cpus} RealMemory=2000 State=UNKNOWN\n\
             PartitionName=debug Nodes=ALL Default=YES MaxTime=INFINITE State=UP\n",
            free_port(),
            free_port(),
            socket.display(),
        );
        let conf_path = root.join("slurm.conf");
        std::fs::write(&conf_path, conf).unwrap();
        let mut cluster = Cluster {
            dir,
            conf: conf_path.clone(),
            daemons: Vec::new(),
        };
        let quiet = || Stdio::null();
        let munged = Command::new(find_tool("munged").unwrap())
            .args(["--foreground", "--force"])
            .arg(format!("--socket={}", socket.display()))
            .arg(format!("--key-file={}", key_path.display()))
            .arg(format!("--pid-file={r}/munged.pid"))
            .arg(format!("--log-file={r}/munged.log"))
            .arg(format!("--seed-file={r}/munged.seed"))
            .stdout(quiet())
            .stderr(quiet())
            .spawn()
            .unwrap();
        cluster.daemons.push(munged);
        let deadline = Instant::now() + Duration::from_secs(10);
        while !socket.exists() && Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(50));
        }
        for daemon in ["slurmctld", "slurmd"] {
            let child = cluster
                .command(daemon)
                .arg("-D")
                .arg("-f")
                .arg(&conf_path)
                .stdout(quiet())
                .stderr(quiet())
                .spawn()
                .unwrap();
            cluster.daemons.push(child);
        }
        // Wait for the node to come up idle.
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            let out = cluster.command("sinfo").args(["-h", "-o", "%t"]).output().unwrap();
            if String::from_utf8_lossy(&out.stdout).trim() == "idle" {
                break;
            }
            assert!(
                Instant::now() < deadline,
                "the Slurm node did not come up in 60 s\n{}",
                cluster.log_tail()
            );
            std::thread::sleep(Duration::from_millis(250));
        }
        cluster
    }

    /// Waits for job `id`; panics with the job's state and logs if it did not complete.
    /// Waits for job `id`; an error (with the job's state, output and the daemon logs) if it
    /// failed, can never run, or is still running at the deadline.
    fn wait(&self, name: &str, id: &str, deadline: Instant, store: &Path) -> Result<(), String> {
        loop {
            let out = self.command("scontrol").args(["show", "job", id]).output().unwrap();
            let text = String::from_utf8_lossy(&out.stdout).into_owned();
            let states: Vec<&str> = text
                .split_whitespace()
                .filter_map(|f| f.strip_prefix("JobState="))
                .collect();
            let reason = text
                .split_whitespace()
                .find_map(|f| f.strip_prefix("Reason="))
                .unwrap_or("")
                .to_string();
            let failed = [
                "FAILED",
                "CANCELLED",
                "TIMEOUT",
                "NODE_FAIL",
                "OUT_OF_MEMORY",
                "BOOT_FAIL",
                "DEADLINE",
            ];
            if let Some(state) = states.iter().find(|s| failed.contains(s)) {
                return Err(format!(
                    "job {name} ({id}) ended {state}\n{}\n{}",
                    job_outputs(store, name),
                    self.log_tail()
                ));
            }
            if reason == "DependencyNeverSatisfied" {
                return Err(format!(
                    "job {name} ({id}) can never run: an earlier job failed\n{}",
                    self.log_tail()
                ));
            }
            if !states.is_empty() && states.iter().all(|s| *s == "COMPLETED") {
                return Ok(());
            }
            if Instant::now() >= deadline {
                let state = states.first().copied().unwrap_or("UNKNOWN");
                return Err(format!(
                    "job {name} ({id}) still {state} ({reason}) at the deadline\n{}",
                    self.log_tail()
                ));
            }
            std::thread::sleep(Duration::from_millis(200));
        }
    }
}

fn job_outputs(store: &Path, name: &str) -> String {
    let mut text = String::new();
    if let Ok(entries) = std::fs::read_dir(store.join("slurm")) {
        for entry in entries.flatten() {
            let file = entry.file_name().to_string_lossy().into_owned();
            if file.starts_with(&format!("octstore-{name}")) && file.ends_with(".out") {
                text.push_str(&format!(
                    "--- {file}\n{}\n",
                    std::fs::read_to_string(entry.path()).unwrap_or_default()
                ));
            }
        }
    }
    text
}

fn run(args: &[&str]) -> String {
    let out = octstore(args, &[]);
    assert!(out.status.success(), "{args:?}: {}", stderr(&out));
    stdout(&out)
}

#[test]
fn a_slurm_run_equals_a_single_process_solve() {
    let Some(_) = shared_data("7scenes-redkitchen") else {
        return;
    };
    let missing: Vec<&str> = TOOLS.iter().copied().filter(|t| find_tool(t).is_none()).collect();
    if !missing.is_empty() {
        eprintln!(
            "skipped: Slurm is not installed here (missing {}); .ci/run installs slurmctld, slurmd, slurm-client and munge",
            missing.join(", ")
        );
        return;
    }
    let cluster = Cluster::start();
    let work = tempfile::tempdir().unwrap();
    let kitchen = shared_path("7scenes-redkitchen");
    let frames: Vec<String> = [0, 250, 500]
        .iter()
        .map(|n| kitchen.join(format!("frame-{n:06}.depth.png")).display().to_string())
        .collect();
    let store = work.path().join("store");
    let single = work.path().join("single");
    for path in [&store, &single] {
        let s = path.to_str().unwrap();
        let args: Vec<&str> = ["ingest", s]
            .into_iter()
            .chain(frames.iter().map(String::as_str))
            .chain(["--max-depth", "6", "--quiet"])
            .collect();
        run(&args);
    }
    let s = single.to_str().unwrap();
    run(&["solve", s, "--iterations", "20", "--leaf-cubes", "2000", "--quiet"]);

    let c = store.to_str().unwrap();
    let submit = cluster
        .command(octstore_bin().to_str().unwrap())
        .args([
            "slurm",
            c,
            "--chunks",
            "5",
            "--iterations",
            "20",
            "--leaf-cubes",
            "2000",
            "-o",
        ])
        .arg(work.path().join("cluster.ply"))
        .env(
            "PATH",
            format!(
                "{}:{}",
                find_tool("sbatch").unwrap().parent().unwrap().display(),
                std::env::var("PATH").unwrap_or_default()
            ),
        )
        .output()
        .unwrap();
    assert!(submit.status.success(), "octstore slurm: {}", stderr(&submit));
    let jobs: Vec<(String, String)> = stdout(&submit)
        .lines()
        .filter_map(|l| l.split_once(' ').map(|(n, id)| (n.to_string(), id.trim().to_string())))
        .collect();
    assert!(jobs.len() > 10, "{}", stdout(&submit));
    let deadline = Instant::now() + Duration::from_secs(600);
    for (name, id) in &jobs {
        if let Err(message) = cluster.wait(name, id, deadline, &store) {
            panic!("{message}");
        }
    }
    assert_same_store(
        &fingerprint(&single),
        &fingerprint(&store),
        "Slurm run vs single process",
    );
    let single_mesh = work.path().join("single.ply");
    run(&["extract", s, "-o", single_mesh.to_str().unwrap()]);
    let cluster_mesh = std::fs::read(work.path().join("cluster.ply")).expect("the chain's extract job wrote the mesh");
    assert!(
        std::fs::read(single_mesh).unwrap() == cluster_mesh,
        "Slurm mesh vs single-process mesh"
    );

    // A chunk that fails is reported with its output, and what depends on it never hangs.
    let failing = format!("{} work {c} --stage histograms --chunk 0", octstore_bin().display());
    let submitted = cluster
        .command("sbatch")
        .args(["--parsable", "--job-name=octstore-failing"])
        .arg(format!("--output={}/slurm/octstore-failing-%j.out", store.display()))
        .arg(format!("--wrap={failing}"))
        .output()
        .unwrap();
    let id = stdout(&submitted).trim().to_string();
    let dependent = cluster
        .command("sbatch")
        .args(["--parsable", "--job-name=octstore-after", "--wrap=true"])
        .arg(format!("--dependency=afterok:{id}"))
        .output()
        .unwrap();
    let dependent = stdout(&dependent).trim().to_string();
    let deadline = Instant::now() + Duration::from_secs(60);
    let error = cluster
        .wait("failing", &id, deadline, &store)
        .expect_err("a failing chunk passed");
    assert!(
        error.contains("ended FAILED") && error.contains("no cluster plan"),
        "{error}"
    );
    let error = cluster
        .wait("after", &dependent, deadline, &store)
        .expect_err("a job after a failed one passed");
    assert!(error.contains("can never run"), "{error}");
}
