//! `texeld`: the Texel daemon and its capture tools.

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

#[derive(Parser)]
#[command(name = "texeld", version, about = "The Texel daemon and capture tools")]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Show what a capture holds: topics, message counts, duration, frame sizes,
    /// calibrations and the sensor JSON; report damage and spec violations.
    Info {
        /// The capture (MCAP) file.
        capture: PathBuf,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match cli.command {
        Command::Info { capture } => match texel_daemon::info::summarize(&capture) {
            Ok(summary) => {
                print!("{summary}");
                if summary.is_clean() {
                    ExitCode::SUCCESS
                } else {
                    ExitCode::FAILURE
                }
            }
            Err(e) => {
                eprintln!("texeld info: {e}");
                ExitCode::FAILURE
            }
        },
    }
}
