//! `geoloc-rs`: geoloc for robots, without Python.
//!
//! `geoloc-rs info MAP` says what a `.geoloc` map holds; `geoloc-rs localize --map MAP --input
//! FRAMES` reads per-frame features (the stream of [`geoloc_core::frames`], written by
//! `geoloc.export_frames`) and writes one pose line per frame, flushed as it goes (an
//! `--output` file is replaced atomically when the run ends; see [`localize`]); `geoloc-rs
//! selfcheck` verifies the Lie-group core on the target machine. Inputs must be regular files
//! (or stdin), and an output that is one of the inputs is refused.
//!
//! Errors go to stderr as one line `geoloc-rs: error: …` (naming the frame index for bad
//! frames) with exit status 1; usage errors exit with 2 (clap).

mod info;
mod localize;
mod output;
mod selfcheck;
mod stats;

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{CommandFactory, Parser, Subcommand, ValueEnum};

/// Camera localization (6-DoF pose + calibrated covariance) on a robot, without Python.
#[derive(Parser, Debug)]
#[command(name = "geoloc-rs", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

/// The encoding of the frame stream.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum InputFormat {
    /// Decide from the first byte (`{` is JSON lines, anything else binary).
    Auto,
    /// The versioned, length-prefixed, checksummed binary stream.
    Binary,
    /// JSON lines (for debugging).
    Jsonl,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Say what a map holds (format, camera, keyframes, features, retrieval, file size).
    Info {
        /// The `.geoloc` map file.
        map: PathBuf,
    },
    /// Localize a stream of per-frame features; one line per frame (TUM columns, source, covariance).
    Localize(localize::Args),
    /// Check SE(3) exp/log round trips and Jacobian inverses on this machine.
    Selfcheck {
        /// Random twists per angle regime.
        #[arg(long, default_value_t = 1000, value_parser = clap::value_parser!(u32).range(1..))]
        samples: u32,
    },
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    if let Command::Localize(args) = &cli.command
        && let Some(message) = localize::usage_error(args)
    {
        // the subcommand's own usage line, as clap prints for its other bad values
        let mut cli_command = Cli::command();
        cli_command.build();
        let localize = cli_command.find_subcommand_mut("localize").expect("invariant: localize is a subcommand");
        localize.error(clap::error::ErrorKind::ValueValidation, message).exit();
    }
    if let Some(warning) = geoloc_core::parallel::environment_warning() {
        eprintln!("geoloc-rs: warning: {warning}");
    }
    let result = match cli.command {
        Command::Info { map } => info::run(&map),
        Command::Localize(args) => localize::run(&args),
        Command::Selfcheck { samples } => return selfcheck::run(samples),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(message) => {
            eprintln!("geoloc-rs: error: {message}");
            ExitCode::FAILURE
        }
    }
}
