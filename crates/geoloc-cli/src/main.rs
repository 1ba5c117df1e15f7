//! `geoloc-rs`: geoloc for robots, without Python.
//!
//! Reads a map and per-frame features and writes poses (TUM format) — those commands arrive
//! with the localizer. For now it can verify the Lie-group core on the target machine.

use std::process::ExitCode;

use clap::{Parser, Subcommand};
use geoloc_core::lie::{SE3, se3};
use geoloc_core::testing::{ANGLE_REGIMES_RAD, SplitMix64};
use nalgebra::Matrix6;

/// Camera localization (6-DoF pose + calibrated covariance) on a robot, without Python.
#[derive(Parser, Debug)]
#[command(name = "geoloc-rs", version, about, long_about = None)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Check SE(3) exp/log round trips and Jacobian inverses on this machine.
    Selfcheck {
        /// Random twists per angle regime.
        #[arg(long, default_value_t = 1000, value_parser = clap::value_parser!(u32).range(1..))]
        samples: u32,
    },
}

/// Largest accepted round-trip error, relative to max(1, |ξ|).
const ROUND_TRIP_TOL: f64 = 1e-9;
/// Largest accepted entry of 𝒥_r 𝒥_r⁻¹ − I, relative to (1 + |ξ|)².
const JACOBIAN_TOL: f64 = 1e-10;

fn selfcheck(samples: u32) -> ExitCode {
    let mut rng = SplitMix64::new(0);
    let (mut worst_log, mut worst_jac) = (0.0_f64, 0.0_f64);
    for &angle in &ANGLE_REGIMES_RAD {
        for _ in 0..samples {
            let xi = rng.twist(angle, 30.0);
            let scale = 1.0 + xi.norm();
            worst_log = worst_log.max((SE3::exp(&xi).log() - xi).norm() / scale);
            let product = se3::right_jacobian(&xi) * se3::right_jacobian_inverse(&xi);
            worst_jac = worst_jac.max((product - Matrix6::identity()).abs().max() / (scale * scale));
        }
    }
    let n = samples as usize * ANGLE_REGIMES_RAD.len();
    println!("geoloc-rs {} self-check on {n} twists", env!("CARGO_PKG_VERSION"));
    println!("  log(exp ξ) = ξ      max rel. error {worst_log:.2e} (tolerance {ROUND_TRIP_TOL:.0e})");
    println!("  𝒥_r(ξ) 𝒥_r⁻¹(ξ) = I  max rel. error {worst_jac:.2e} (tolerance {JACOBIAN_TOL:.0e})");
    if worst_log <= ROUND_TRIP_TOL && worst_jac <= JACOBIAN_TOL {
        println!("all checks passed");
        ExitCode::SUCCESS
    } else {
        println!("FAILED");
        ExitCode::FAILURE
    }
}

fn main() -> ExitCode {
    match Cli::parse().command {
        Command::Selfcheck { samples } => selfcheck(samples),
    }
}
