//! The `octstore` command line (`src/cli` parses and runs each verb).

use std::process::ExitCode;

use clap::Parser;

/// mimalloc rather than the system allocator: the stages allocate and free buffers of a few
/// megabytes per depth map or unit, which glibc returns to the kernel and faults back in page
/// by page (ingest of 1000 RedKitchen frames spent 20 s of its 80 CPU seconds in the kernel).
#[global_allocator]
static ALLOCATOR: mimalloc::MiMalloc = mimalloc::MiMalloc;

/// Environment variables that keep the Vulkan probe of `--device auto` quiet on a normal run:
/// Mesa's device-select layer connects to a Wayland display when the instance enables the
/// Wayland surface extension (wgpu enables every surface extension there is), and libwayland
/// prints "error: XDG_RUNTIME_DIR is invalid or not set" to stderr when there is none, which
/// reads as a failure. octstore presents nothing and ranks adapters itself, so the layer is
/// not needed. A variable the user set is left alone.
const QUIET_VULKAN_PROBES: &[(&str, &str)] = &[("NODEVICE_SELECT", "1")];

fn main() -> ExitCode {
    octstore::die_quietly_on_closed_pipe();
    octstore::set_env_defaults_at_start(QUIET_VULKAN_PROBES);
    // Parsing starts no thread, so the allocator's option still changes before any other
    // thread exists.
    let cli = octstore::cli::Cli::parse();
    if cli.command.extracts() {
        octstore::purge_freed_pages_at_once();
    }
    // `--quiet` keeps warnings and errors; OCTSTORE_LOG, when set, decides instead.
    let level = if cli.global.quiet { "warn" } else { "info" };
    tracing_subscriber::fmt()
        .with_writer(std::io::stderr)
        .with_target(false)
        .with_env_filter(tracing_subscriber::EnvFilter::try_from_env("OCTSTORE_LOG").unwrap_or_else(|_| level.into()))
        .without_time()
        .init();
    // A damaged catalog page makes redb panic; it is reported as the damage it is.
    match octstore::store::contain_redb_panics(|| octstore::cli::run(cli)) {
        Ok(Ok(code)) => code,
        Ok(Err(e)) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
        Err(damaged) => {
            eprintln!("error: {damaged} (`octstore verify` names what it can still read)");
            ExitCode::FAILURE
        }
    }
}
