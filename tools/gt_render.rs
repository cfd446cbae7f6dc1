//! `octstore-gt-render`: depth maps of a ground-truth mesh or of the built-in room, with noise
//! (its code is `octstore::cli::gt_render_main`, beside the `octstore` command line).

fn main() -> std::process::ExitCode {
    octstore::die_quietly_on_closed_pipe();
    octstore::cli::gt_render_main()
}
