//! The `octstore` command line: [`args`] declares it, [`run`] dispatches each verb to one
//! function (`verbs` for one machine, `cluster` for cluster runs), and every verb reports
//! typed errors ([`CliError`]) that `main` prints.

mod args;
mod cluster;
mod error;
mod parse;
mod report;
mod verbs;

use std::path::Path;
use std::process::ExitCode;

pub use self::args::{Cli, Command, GlobalOptions};
pub use self::error::CliError;
pub use self::report::{InfoJson, info, peak_rss_bytes};
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
        Command::Extract(args) => verbs::extract(args)?,
        Command::Query(args) => verbs::query(args)?,
        Command::Render(args) => verbs::render(args)?,
        Command::Info(args) => verbs::info_verb(args)?,
        Command::Verify(args) => return verbs::verify(args),
        Command::Log(args) => verbs::log(args)?,
        Command::Gc(args) => verbs::gc(args)?,
        Command::DebugSynthetic(args) => verbs::debug_synthetic(&global, args)?,
    }
    Ok(ExitCode::SUCCESS)
}
