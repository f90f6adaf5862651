use std::process::ExitCode;

use clap::Parser;

fn main() -> ExitCode {
    gangway::logging::init();
    match gangway::cli::Cli::parse().run() {
        Ok(code) => code,
        Err(e) => {
            eprintln!("gangway: {e:#}");
            ExitCode::FAILURE
        }
    }
}
