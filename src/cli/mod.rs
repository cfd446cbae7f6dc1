//! The `octstore` command line: `args` declares it, [`run`] dispatches each verb to one
//! function (`verbs` for one machine, `cluster` for cluster runs), and every verb reports
//! typed errors ([`CliError`]) that `main` prints.

mod args;
mod cluster;
mod divide;
mod error;
mod evaluate;
mod gt_render;
mod parse;
mod report;
mod verbs;

use std::path::Path;
use std::process::ExitCode;

#[cfg(feature = "testing")]
pub use self::args::DebugSyntheticArgs;
pub use self::args::{
    Cli, Command, CommitArgs, DemoArgs, DivideArgs, ExtractArgs, GcArgs, GlobalOptions, InfoArgs, IngestArgs, LogArgs,
    MergeArgs, MethodName, PlanArgs, QueryArgs, RenderArgs, SlurmArgs, SolveArgs, SolverArgs, VerifyArgs, WorkArgs,
};
pub use self::error::CliError;
pub use self::evaluate::evaluate_main;
pub use self::gt_render::gt_render_main;
pub use self::report::{CaptureJson, InfoJson, info, peak_rss_bytes};
use crate::store::{RunOptions, Store, StoreError};

fn run_options(global: &GlobalOptions, resume: bool) -> RunOptions {
    RunOptions {
        resume,
        threads: global.threads.unwrap_or_else(rayon::current_num_threads),
        progress: !global.quiet,
    }
}

fn open_or_create(path: &Path) -> Result<Store, StoreError> {
    if path.join(crate::store::CATALOG_FILE).exists() {
        Store::open(path)
    } else {
        Store::create(path)
    }
}

/// A verb's options as the library takes them, parsed from a command line exactly as
/// `octstore` parses and checks it: for front ends (the Python package) that run the verb on a
/// store they already hold open.
#[derive(Debug)]
#[non_exhaustive]
pub enum LibraryCall {
    /// `octstore ingest`: the inputs, then discovery, ingest and run options.
    Ingest {
        /// Files and folders to discover depth maps in.
        inputs: Vec<std::path::PathBuf>,
        /// How to discover them.
        discover: crate::inputs::DiscoverOptions,
        /// How to ingest them.
        options: crate::stages::ingest::IngestOptions,
        /// Threads, resumption, progress bars.
        run: RunOptions,
    },
    /// `octstore solve`.
    Solve(crate::pipeline::SolveOptions),
}

/// Parses `argv` (`["octstore", "ingest" | "solve", STORE, ...]`) into the library call the
/// command line would make; the error is clap's message, as the command line prints it.
pub fn library_call(argv: &[String]) -> Result<LibraryCall, String> {
    use clap::Parser;
    // clap's message without its "error: " and its closing pointer to --help.
    let cli = Cli::try_parse_from(argv).map_err(|e| {
        let text = e.to_string();
        let first = text.split("\n\n").next().unwrap_or_default();
        first.trim_start_matches("error: ").trim_end().to_string()
    })?;
    match cli.command {
        Command::Ingest(args) => {
            let (discover, options, run) = verbs::ingest_options(&cli.global, &args);
            Ok(LibraryCall::Ingest {
                inputs: args.inputs,
                discover,
                options,
                run,
            })
        }
        Command::Solve(args) => Ok(LibraryCall::Solve(verbs::solve_options(&cli.global, &args))),
        _ => Err("only ingest and solve run as library calls".into()),
    }
}

/// Runs one command line; the exit code is non-zero when `verify` finds problems.
pub fn run(cli: Cli) -> Result<ExitCode, CliError> {
    let global = cli.global;
    if let Some(threads) = global.threads {
        // Only the first call configures the global pool; later calls are harmless.
        let _ = rayon::ThreadPoolBuilder::new().num_threads(threads).build_global();
    }
    match cli.command {
        Command::Ingest(args) => verbs::ingest(&global, args)?,
        Command::Solve(args) => verbs::solve(&global, args)?,
        Command::Plan(args) => cluster::plan(args)?,
        Command::Work(args) => cluster::work(args)?,
        Command::Commit(args) => cluster::commit(&global, args)?,
        Command::Slurm(args) => cluster::slurm(&global, args)?,
        Command::Demo(args) => verbs::demo(&global, args)?,
        Command::Extract(args) => verbs::extract(&global, args)?,
        Command::Query(args) => verbs::query(args)?,
        Command::Render(args) => verbs::render(args)?,
        Command::Info(args) => verbs::info_verb(args)?,
        Command::Verify(args) => return verbs::verify(args),
        Command::Log(args) => verbs::log(args)?,
        Command::Gc(args) => verbs::gc(args)?,
        Command::Divide(args) => divide::divide(&global, args)?,
        Command::Merge(args) => divide::merge(args)?,
        #[cfg(feature = "testing")]
        Command::DebugSynthetic(args) => verbs::debug_synthetic(&global, args)?,
    }
    Ok(ExitCode::SUCCESS)
}
