//! What went wrong in a stage: the `error` of [`super::StoreError::Stage`], one variant per
//! problem a program may want to tell apart, with the message `octstore` prints.

use std::path::PathBuf;

/// Why a stage (or a read of a store's surface) failed on a unit.
///
/// The message of each variant says what to do. [`StageError::Internal`] is the one variant
/// that carries free text: a broken invariant (a bug, or bytes that decode but contradict each
/// other), which no program is expected to handle other than by reporting it.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum StageError {
    /// The store has no depth maps: nothing to build from or to read.
    #[error("the store has no depth maps yet: run `octstore ingest` first")]
    NotIngested,
    /// The depth maps given hold no valid sample to size a root cube from.
    #[error("no valid depth samples: nothing to build a scene from")]
    NoValidSamples,
    /// The store has depth maps but no octree.
    #[error("no octree yet: run `octstore solve` first")]
    NoOctree,
    /// A level's solution is missing.
    #[error("no solution at level {level}: run `octstore solve` first")]
    NoSolution {
        /// The level asked for.
        level: u8,
    },
    /// A level unit found no histograms to solve with.
    #[error("no histograms for this unit: run the histograms stage first")]
    NoHistograms,
    /// An SSD level unit found no samples segment.
    #[error("no samples for this unit: run the samples stage first")]
    NoSamples,
    /// The version's solution is older than its octree or histograms: a solve has not finished
    /// since the last change.
    #[error(
        "its solution is older than its octree or histograms (a solve has not finished since the last change): run `octstore solve` to finish it{}",
        read_instead(*latest_complete)
    )]
    SolutionBehind {
        /// The latest version whose solution is complete, if any.
        latest_complete: Option<u64>,
    },
    /// A depth map's file no longer has the content it was ingested with.
    #[error(
        "{}: the file changed since it was ingested (its content hash is {found:016x}, the store recorded {recorded:016x}); put the ingested file back, or ingest the new one into a new store",
        path.display()
    )]
    FileChanged {
        /// The depth map's file.
        path: PathBuf,
        /// The hash of its content now.
        found: u64,
        /// The hash recorded at ingest (the map's id).
        recorded: u64,
    },
    /// A depth map could not be read (an [`crate::InputError`], which names the file).
    #[error("{0}")]
    Input(Box<dyn std::error::Error + Send + Sync>),
    /// New depth maps see farther than the root cube can grow in one ingest.
    #[error(
        "its samples reach from {low:?} to {high:?}, beyond what {doublings} doublings of the store's root cube (min {root_min:?}, side {root_side}) can hold; check its pose and depth scale"
    )]
    BeyondRoot {
        /// The low corner of the samples' box.
        low: [f64; 3],
        /// The high corner of the samples' box.
        high: [f64; 3],
        /// The root cube's low corner.
        root_min: [f64; 3],
        /// The root cube's side.
        root_side: f64,
        /// The most doublings one ingest may make.
        doublings: usize,
    },
    /// The root cannot grow: a cube would pass the keys' depth limit.
    #[error("the root cannot grow past the keys' depth limit")]
    RootAtDepthLimit,
    /// `--max-depth` outside what cube keys hold.
    #[error("max depth {max_depth} is outside 1..={limit} (the cube keys' limit)")]
    MaxDepthOutOfRange {
        /// The depth asked for.
        max_depth: u8,
        /// The keys' limit.
        limit: u8,
    },
    /// `ingest --sample-sums` into a store created without them.
    #[error(
        "--sample-sums: this store was created without sample sums, and its depth maps' runs lack them; ingest without --sample-sums (solve --method ssd or hybrid adds the sums to every run once, reading the depth maps again)"
    )]
    SampleSumsNotRecorded,
    /// An ingest run without the sample sums that the SSD solver reads.
    #[error(
        "this depth map's run carries no sample sums (the store was created without `ingest --sample-sums`, or by an octstore older than `--method ssd`): ingest the depth maps into a new store with `--sample-sums` to solve with ssd or hybrid"
    )]
    NoSampleSums,
    /// A cluster stage has no recorded plan.
    #[error("no cluster plan: run `octstore plan` first")]
    NoPlan,
    /// The store changed since the cluster plan was made.
    #[error(
        "the store changed since the plan was made (version {now} now, {then} then, or other inputs): run `octstore plan` again"
    )]
    PlanOutdated {
        /// The latest version now.
        now: u64,
        /// The version the plan was made at.
        then: u64,
    },
    /// A chunk number past the plan's.
    #[error("the plan has chunks 0 to {}", chunks.saturating_sub(1))]
    NoSuchChunk {
        /// The plan's number of chunks.
        chunks: u32,
    },
    /// A commit found chunks missing or damaged.
    #[error(
        "chunk(s) {} of {chunks} are missing or damaged ({}): run `octstore work STORE --stage {stage} --chunk N` for each, then commit again",
        join(missing),
        name_files(files)
    )]
    ChunksMissing {
        /// The stage.
        stage: String,
        /// The chunks missing or damaged.
        missing: Vec<u32>,
        /// The plan's number of chunks.
        chunks: u32,
        /// The files at fault (missing, or not decoding).
        files: Vec<PathBuf>,
    },
    /// A unit the cluster plan does not hold.
    #[error("not part of the stage's plan")]
    NotInPlan,
    /// A unit of the plan whose worker output is missing.
    #[error("no worker output for this unit")]
    NoWorkerOutput,
    /// The version a cluster commit targets moved since the plan.
    #[error("the target version moved")]
    TargetMoved,
    /// A worker thread panicked (the panic's message went to stderr).
    #[error("a worker thread panicked")]
    WorkerPanicked,
    /// A broken invariant: a bug, or stored bytes that decode but contradict each other.
    #[error("internal: {0}")]
    Internal(String),
}

impl StageError {
    /// An [`StageError::Internal`] from anything printable.
    pub fn internal(what: impl Into<String>) -> StageError {
        StageError::Internal(what.into())
    }
}

fn read_instead(latest_complete: Option<u64>) -> String {
    latest_complete.map_or_else(String::new, |v| {
        format!(", or read version {v}, the latest complete one (--version {v})")
    })
}

fn join(chunks: &[u32]) -> String {
    chunks.iter().map(u32::to_string).collect::<Vec<_>>().join(", ")
}

/// The first three files, then how many more.
fn name_files(files: &[PathBuf]) -> String {
    const NAMED: usize = 3;
    let mut named: Vec<String> = files.iter().take(NAMED).map(|f| f.display().to_string()).collect();
    if files.len() > NAMED {
        named.push(format!("and {} more", files.len() - NAMED));
    }
    named.join(", ")
}
