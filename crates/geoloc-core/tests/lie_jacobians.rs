//! Every analytic Jacobian against central differences on the manifold, in every regime.

mod common;

use common::{FD_STEP, central_difference};
use geoloc_core::lie::{SE3, SO3, Twist, se3, so3};
use geoloc_core::testing::{ANGLE_REGIMES_RAD, SplitMix64};
use nalgebra::Vector3;

/// Absolute tolerance on Jacobian entries, relative to max(1, ‖J‖_max).
const JACOBIAN_TOL: f64 = 1e-6;
const TRANSLATIONS_M: [f64; 3] = [0.0, 1.0, 30.0];

fn assert_close<const N: usize>(
    analytic: &nalgebra::SMatrix<f64, N, N>,
    numeric: &nalgebra::SMatrix<f64, N, N>,
    ctx: &str,
) {
    let scale = numeric.abs().max().max(1.0);
    let err = (analytic - numeric).abs().max() / scale;
    assert!(err < JACOBIAN_TOL, "{ctx}: relative error {err:e}\nanalytic {analytic}\nnumeric {numeric}");
}

fn twists() -> Vec<Twist> {
    let mut rng = SplitMix64::new(0xfd);
    let mut out = Vec::new();
    for &angle in &ANGLE_REGIMES_RAD {
        for &t in &TRANSLATIONS_M {
            for _ in 0..20 {
                out.push(rng.twist(angle, t));
            }
        }
    }
    out
}

/// The FD step near π must not carry the perturbed rotation across θ = π (log jumps there).
fn step_for(xi: &Twist) -> f64 {
    let theta = se3::phi(xi).norm();
    FD_STEP.min(0.1 * (std::f64::consts::PI - theta)).max(1e-8)
}

/// exp(φ + δ) ≈ exp(φ) exp(J_r δ) and ≈ exp(J_l δ) exp(φ).
#[test]
fn so3_jacobians_match_central_differences() {
    for xi in twists() {
        let phi = se3::phi(&xi);
        let h = step_for(&xi);
        let r0 = SO3::exp(&phi);
        let j_r =
            central_difference(|d: &Vector3<f64>| (r0.inverse() * SO3::exp(&(phi + d))).log(), &Vector3::zeros(), h);
        let j_l =
            central_difference(|d: &Vector3<f64>| (SO3::exp(&(phi + d)) * r0.inverse()).log(), &Vector3::zeros(), h);
        assert_close::<3>(&so3::right_jacobian(&phi), &j_r, &format!("J_r at {phi:?}"));
        assert_close::<3>(&so3::left_jacobian(&phi), &j_l, &format!("J_l at {phi:?}"));
        // the inverses are the derivatives of log under right / left perturbations
        let j_r_inv = central_difference(|d: &Vector3<f64>| (r0 * SO3::exp(d)).log(), &Vector3::zeros(), h);
        let j_l_inv = central_difference(|d: &Vector3<f64>| (SO3::exp(d) * r0).log(), &Vector3::zeros(), h);
        if phi.norm() < std::f64::consts::PI - 1e-3 {
            assert_close::<3>(&so3::right_jacobian_inverse(&phi), &j_r_inv, &format!("J_r⁻¹ at {phi:?}"));
            assert_close::<3>(&so3::left_jacobian_inverse(&phi), &j_l_inv, &format!("J_l⁻¹ at {phi:?}"));
        }
    }
}

#[test]
fn se3_jacobians_match_central_differences() {
    for xi in twists() {
        let h = step_for(&xi);
        let t0 = SE3::exp(&xi);
        let j_r = central_difference(|d: &Twist| (t0.inverse() * SE3::exp(&(xi + d))).log(), &Twist::zeros(), h);
        let j_l = central_difference(|d: &Twist| (SE3::exp(&(xi + d)) * t0.inverse()).log(), &Twist::zeros(), h);
        assert_close::<6>(&se3::right_jacobian(&xi), &j_r, &format!("𝒥_r at {xi:?}"));
        assert_close::<6>(&se3::left_jacobian(&xi), &j_l, &format!("𝒥_l at {xi:?}"));
        if se3::phi(&xi).norm() < std::f64::consts::PI - 1e-3 {
            let j_r_inv = central_difference(|d: &Twist| (t0 * SE3::exp(d)).log(), &Twist::zeros(), h);
            let j_l_inv = central_difference(|d: &Twist| (SE3::exp(d) * t0).log(), &Twist::zeros(), h);
            assert_close::<6>(&se3::right_jacobian_inverse(&xi), &j_r_inv, &format!("𝒥_r⁻¹ at {xi:?}"));
            assert_close::<6>(&se3::left_jacobian_inverse(&xi), &j_l_inv, &format!("𝒥_l⁻¹ at {xi:?}"));
        }
    }
}

/// Near π the log's derivative is checked by a one-sided difference away from π.
#[test]
fn jacobian_inverses_near_pi() {
    let mut rng = SplitMix64::new(0xbeef);
    for _ in 0..50 {
        let xi = rng.twist(std::f64::consts::PI - 1e-6, 5.0);
        let t0 = SE3::exp(&xi);
        let h = 1e-8;
        let numeric = central_difference(|d: &Twist| (t0 * SE3::exp(d)).log(), &Twist::zeros(), h);
        // the step may cross π for some directions; compare only the columns that did not
        let analytic = se3::right_jacobian_inverse(&xi);
        let mut checked = 0;
        for c in 0..6 {
            let (a, n) = (analytic.column(c), numeric.column(c));
            if n.norm() < 1e3 {
                checked += 1;
                assert!((a - n).norm() / a.norm().max(1.0) < 1e-4, "column {c}: {a} vs {n}");
            }
        }
        assert!(checked >= 1);
    }
}

/// J_l(φ)'s singular values against nalgebra's SVD: 1 and twice |2 sin(θ/2)|/θ, the value
/// [`so3::check_jacobian_invertible`] tests; φ at 2π (the closed-form inverse there gave
/// 1e16 entries and J·J⁻¹ − I = 1) is refused, φ beside it and below π are not.
#[test]
fn a_singular_left_jacobian_is_refused_and_the_singular_value_is_the_svds() {
    let axis = Vector3::new(1.0, -2.0, 0.5).normalize();
    for theta in [0.3, 2.0, 4.0, 6.0, 8.0, 12.0] {
        let svd = so3::left_jacobian(&(axis * theta)).svd(false, false);
        let mut values: Vec<f64> = svd.singular_values.iter().copied().collect();
        values.sort_by(f64::total_cmp);
        let across = (2.0 * (0.5f64 * theta).sin() / theta).abs();
        assert!((values[0] - across).abs() < 1e-12 && (values[1] - across).abs() < 1e-12, "θ {theta}: {values:?}");
        assert!((values[2] - 1.0).abs() < 1e-12, "θ {theta}: {values:?}");
    }
    for turns in [1.0, 2.0, 5.0] {
        let phi = axis * (std::f64::consts::TAU * turns);
        let err = so3::check_jacobian_invertible(&phi).expect_err("singular");
        assert!(err.to_string().starts_with("phi: "), "{err}");
    }
    for theta in [0.0, 1.0, std::f64::consts::PI, 6.0, std::f64::consts::TAU - 1e-6, std::f64::consts::TAU + 1e-6] {
        let phi = axis * theta;
        so3::check_jacobian_invertible(&phi).expect("invertible");
        let product = so3::left_jacobian(&phi) * so3::left_jacobian_inverse(&phi);
        assert!((product - nalgebra::Matrix3::identity()).amax() < 1e-6, "θ {theta}");
    }
}
