//! `octstore-evaluate`: measure a reconstructed mesh against a ground-truth mesh (its code is
//! `octstore::cli::evaluate_main`, beside the `octstore` command line).

fn main() -> std::process::ExitCode {
    octstore::die_quietly_on_closed_pipe();
    octstore::cli::evaluate_main()
}
