//! `geoloc-rs selfcheck`: the Lie-group core's identities, checked on the target machine.

use std::process::ExitCode;

use geoloc_core::lie::{SE3, se3};
use geoloc_core::testing::{ANGLE_REGIMES_RAD, SplitMix64};
use nalgebra::Matrix6;

/// Largest accepted round-trip error, relative to max(1, |ξ|).
const ROUND_TRIP_TOL: f64 = 1e-9;
/// Largest accepted entry of 𝒥_r 𝒥_r⁻¹ − I, relative to (1 + |ξ|)².
const JACOBIAN_TOL: f64 = 1e-10;

/// Checks log(exp ξ) = ξ and 𝒥_r 𝒥_r⁻¹ = I on `samples` random twists per angle regime.
pub fn run(samples: u32) -> ExitCode {
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
