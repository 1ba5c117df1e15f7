//! Every Lie identity, in every angle regime (identity, 1e-9, 1e-8, around the
//! Taylor threshold, ordinary, π − 1e-6), with translations up to 30 m, on seeded samples and
//! as proptest properties.

#![allow(clippy::float_cmp)] // some identities hold exactly (hat∘vee, d(T, T) = 0)

mod common;

use common::{matrix_exp, relative_error};
use geoloc_core::lie::{SE3, SO3, Twist, rotation_angle, se3, so3};
use geoloc_core::testing::{ANGLE_REGIMES_RAD, SplitMix64};
use nalgebra::{Matrix3, Matrix6, Vector3};
use proptest::prelude::*;

/// Round-trip tolerance of exp/log, relative to max(1, |value|).
const ROUND_TRIP_TOL: f64 = 1e-12;
/// Tolerance of identities between 6×6 matrices (products of several closed forms).
const IDENTITY_TOL: f64 = 1e-11;
const TRANSLATIONS_M: [f64; 4] = [0.0, 1e-6, 1.0, 30.0];
const SAMPLES_PER_REGIME: usize = 50;

fn for_each_regime(mut check: impl FnMut(&Twist, &str)) {
    let mut rng = SplitMix64::new(0x5eed);
    for &angle in &ANGLE_REGIMES_RAD {
        for &translation in &TRANSLATIONS_M {
            for _ in 0..SAMPLES_PER_REGIME {
                let xi = rng.twist(angle, translation);
                check(&xi, &format!("angle {angle:e}, |t| ≤ {translation}, ξ = {xi:?}"));
            }
        }
    }
}

#[test]
fn so3_exp_log_round_trips() {
    for_each_regime(|xi, ctx| {
        let phi = se3::phi(xi);
        let back = SO3::exp(&phi).log();
        let err = (back - phi).norm() / phi.norm().max(1e-300);
        // tiny angles must keep their *relative* precision, not just an absolute one
        assert!(err < 1e-9 || (back - phi).norm() < 1e-15, "{ctx}: log(exp φ) = {back:?}");
        let r = SO3::exp(&phi);
        let again = SO3::exp(&r.log());
        assert!(relative_error(again.matrix(), r.matrix()) < ROUND_TRIP_TOL, "{ctx}");
    });
}

#[test]
fn se3_exp_log_round_trips() {
    for_each_regime(|xi, ctx| {
        let back = SE3::exp(xi).log();
        assert!((back - xi).norm() <= 1e-9 * xi.norm().max(1e-6), "{ctx}: {back:?}");
        let t = SE3::exp(xi);
        let again = SE3::exp(&t.log());
        assert!(relative_error(&again.matrix(), &t.matrix()) < ROUND_TRIP_TOL, "{ctx}");
    });
}

#[test]
fn exp_is_orthonormal_with_unit_determinant() {
    for_each_regime(|xi, ctx| {
        let r = *SE3::exp(xi).rotation.matrix();
        assert!((r.transpose() * r - Matrix3::identity()).abs().max() < 1e-14, "{ctx}");
        assert!((r.determinant() - 1.0).abs() < 1e-14, "{ctx}");
    });
}

#[test]
fn adjoint_is_a_homomorphism() {
    let mut rng = SplitMix64::new(1);
    for _ in 0..500 {
        let (a, b) = (rng.pose(30.0), rng.pose(30.0));
        let lhs = (a * b).adjoint();
        let rhs = a.adjoint() * b.adjoint();
        assert!(relative_error(&lhs, &rhs) < IDENTITY_TOL);
        assert!(relative_error(&a.inverse().adjoint(), &a.adjoint().try_inverse().expect("Ad is invertible")) < 1e-10);
    }
}

/// T exp(ξ^) T⁻¹ = exp((Ad(T) ξ)^): the defining property of the adjoint.
#[test]
fn adjoint_moves_twists_across_poses() {
    let mut rng = SplitMix64::new(2);
    for_each_regime(|xi, ctx| {
        let t = rng.pose(10.0);
        let lhs = (t * SE3::exp(xi) * t.inverse()).matrix();
        let rhs = SE3::exp(&(t.adjoint() * xi)).matrix();
        assert!(relative_error(&lhs, &rhs) < IDENTITY_TOL, "{ctx}");
    });
}

/// Ad(exp ξ) = exp(ad ξ), with exp(ad ξ) from an independent matrix exponential.
#[test]
fn adjoint_of_exp_is_exp_of_curly_hat() {
    for_each_regime(|xi, ctx| {
        let lhs = SE3::exp(xi).adjoint();
        let rhs = matrix_exp(&se3::curly_hat(xi));
        assert!(relative_error(&lhs, &rhs) < 1e-10, "{ctx}: {}", relative_error(&lhs, &rhs));
    });
}

/// exp(ξ^) from an independent 4×4 matrix exponential of the hat matrix.
#[test]
fn se3_exp_matches_matrix_exponential() {
    for_each_regime(|xi, ctx| {
        let lhs = SE3::exp(xi).matrix();
        let rhs = matrix_exp(&se3::hat(xi));
        assert!(relative_error(&lhs, &rhs) < 1e-12, "{ctx}: {}", relative_error(&lhs, &rhs));
    });
}

#[test]
fn jacobians_times_inverses_are_identity() {
    for_each_regime(|xi, ctx| {
        let phi = se3::phi(xi);
        let i3 = Matrix3::identity();
        let i6 = Matrix6::identity();
        assert!(
            relative_error(&(so3::left_jacobian(&phi) * so3::left_jacobian_inverse(&phi)), &i3) < IDENTITY_TOL,
            "{ctx}"
        );
        assert!(
            relative_error(&(so3::right_jacobian(&phi) * so3::right_jacobian_inverse(&phi)), &i3) < IDENTITY_TOL,
            "{ctx}"
        );
        let l = se3::left_jacobian(xi) * se3::left_jacobian_inverse(xi);
        let r = se3::right_jacobian(xi) * se3::right_jacobian_inverse(xi);
        // near π the SE(3) blocks grow like |ρ|·θ; relative to that size
        let scale = 1.0 + xi.norm();
        assert!((l - i6).abs().max() < IDENTITY_TOL * scale * scale, "{ctx}: {}", (l - i6).abs().max());
        assert!((r - i6).abs().max() < IDENTITY_TOL * scale * scale, "{ctx}");
    });
}

/// J_r(ξ) = J_l(−ξ) and, independently, J_l(ξ) = Ad(exp ξ) J_r(ξ).
#[test]
fn right_and_left_jacobians_are_related() {
    for_each_regime(|xi, ctx| {
        let phi = se3::phi(xi);
        assert!(relative_error(&so3::right_jacobian(&phi), &so3::left_jacobian(&-phi)) < 1e-15, "{ctx}");
        assert!(relative_error(&se3::right_jacobian(xi), &se3::left_jacobian(&-xi)) < 1e-15, "{ctx}");
        let via_adjoint = SE3::exp(xi).adjoint() * se3::right_jacobian(xi);
        assert!(relative_error(&se3::left_jacobian(xi), &via_adjoint) < IDENTITY_TOL, "{ctx}");
        let so3_via_adjoint = SO3::exp(&phi).adjoint() * so3::right_jacobian(&phi);
        assert!(relative_error(&so3::left_jacobian(&phi), &so3_via_adjoint) < IDENTITY_TOL, "{ctx}");
    });
}

/// 10⁴ compositions of random rotations stay orthonormal without renormalization: the
/// error grows at most linearly, ≈ n·ε ≈ 2e-12, six orders below the acceptance tolerance;
/// one `normalized()` step brings it back to round-off.
#[test]
fn orthonormal_after_ten_thousand_compositions() {
    let mut rng = SplitMix64::new(3);
    let mut t = SE3::identity();
    for _ in 0..10_000 {
        t = t * SE3::new(rng.rotation(), rng.unit_vector());
    }
    let r = *t.rotation.matrix();
    let err = (r.transpose() * r - Matrix3::identity()).abs().max();
    assert!(err < 1e4 * 2.0 * f64::EPSILON, "orthonormality error after 1e4 compositions: {err:e}");
    assert!(SO3::from_matrix(&r).is_ok());
    let fixed = *t.rotation.normalized().matrix();
    let err_fixed = (fixed.transpose() * fixed - Matrix3::identity()).abs().max();
    assert!(err_fixed < 4.0 * f64::EPSILON, "after normalized(): {err_fixed:e}");
    assert!((fixed - r).abs().max() < 2.0 * err, "normalization moved R by more than its error");
}

#[test]
fn rotation_angle_is_stable_at_both_ends() {
    let mut rng = SplitMix64::new(4);
    for &angle in &[0.0, 1e-12, 1e-9, 1e-4, 1.0, 3.0, std::f64::consts::PI - 1e-9, std::f64::consts::PI] {
        let r = SO3::exp(&rng.rotation_vector(angle));
        assert!((r.angle() - angle).abs() < 1e-15 + 1e-13 * angle, "{angle}: {}", r.angle());
    }
    // trace a hair above 3 or below −1 must not give NaN
    let slightly_big = Matrix3::identity() * (1.0 + 1e-12);
    assert_eq!(rotation_angle(&slightly_big), 0.0);
    let flip = Matrix3::from_diagonal(&Vector3::new(1.0, -1.0 - 1e-12, -1.0 - 1e-12));
    assert!((rotation_angle(&flip) - std::f64::consts::PI).abs() < 1e-15);
}

#[test]
fn distance_is_the_twist_norm_and_symmetric() {
    let mut rng = SplitMix64::new(5);
    for_each_regime(|xi, ctx| {
        let a = rng.pose(30.0);
        let b = a * SE3::exp(xi);
        assert!((a.distance(&b) - xi.norm()).abs() < 1e-9 * (1.0 + xi.norm()), "{ctx}");
        assert!((a.distance(&b) - b.distance(&a)).abs() < 1e-9 * (1.0 + xi.norm()), "{ctx}");
        assert_eq!(a.distance(&a), 0.0);
    });
}

#[test]
fn checked_interpolation_refuses_an_overflowing_alpha() {
    // found by tests/adversarial: se3_interpolate(T1, T2, 1e300) returned a NaN pose
    let a = SE3::identity();
    let b = SE3::exp(&Twist::new(0.1, 0.0, 0.0, 0.0, 0.2, 0.0));
    for alpha in [1e300, -1e200, f64::INFINITY, f64::NAN] {
        match a.checked_interpolate(&b, alpha) {
            Err(geoloc_core::GeolocError::InvalidInput { name, .. }) => assert_eq!(name, "alpha"),
            other => panic!("alpha {alpha}: expected InvalidInput naming alpha, got {other:?}"),
        }
    }
    assert!(a.checked_interpolate(&b, 1e6).is_ok(), "a large but representable extrapolation");
    let far = SE3::exp(&Twist::new(1e149, 0.0, 0.0, 0.0, 0.0, 0.0));
    let far = far * far * far * far * far * far * far * far * far * far * far * far; // ρ ≈ 1.2e150
    match far.checked_interpolate(&a, 0.5) {
        Err(geoloc_core::GeolocError::InvalidInput { name, .. }) => assert_eq!(name, "T1, T2"),
        other => panic!("expected InvalidInput naming T1, T2, got {other:?}"),
    }
}

#[test]
fn interpolation_follows_the_geodesic() {
    let mut rng = SplitMix64::new(6);
    for _ in 0..200 {
        let a = rng.pose(30.0);
        let angle = rng.uniform_in(0.0, 3.0);
        let xi = rng.twist(angle, 5.0);
        let b = a * SE3::exp(&xi);
        assert!(relative_error(&a.interpolate(&b, 0.0).matrix(), &a.matrix()) < 1e-12);
        assert!(relative_error(&a.interpolate(&b, 1.0).matrix(), &b.matrix()) < 1e-11);
        assert_eq!(a.checked_interpolate(&b, 0.3).expect("ordinary alpha").matrix(), a.interpolate(&b, 0.3).matrix());
        let mid = a.interpolate(&b, 0.3);
        assert!((a.distance(&mid) - 0.3 * xi.norm()).abs() < 1e-9);
        assert!((mid.distance(&b) - 0.7 * xi.norm()).abs() < 1e-9);
        let (ra, rb) = (a.rotation, b.rotation);
        let rm = ra.interpolate(&rb, 0.5);
        assert!((ra.distance(&rm) - 0.5 * ra.distance(&rb)).abs() < 1e-10);
    }
}

#[test]
fn quaternions_round_trip_through_every_shepperd_branch() {
    let mut rng = SplitMix64::new(7);
    // angles near π with axes along x, y, z exercise the three diagonal pivots
    let mut rotations: Vec<SO3> = (0..300).map(|_| rng.rotation()).collect();
    for axis in [Vector3::x(), Vector3::y(), Vector3::z()] {
        rotations.push(SO3::exp(&(axis * (std::f64::consts::PI - 1e-3))));
        rotations.push(SO3::exp(&(axis * std::f64::consts::PI)));
    }
    for r in rotations {
        let q = r.to_quaternion_wxyz();
        let n: f64 = q.iter().map(|c| c * c).sum();
        assert!((n - 1.0).abs() < 1e-14);
        let back = SO3::from_quaternion_wxyz(q).expect("unit quaternion");
        assert!(relative_error(back.matrix(), r.matrix()) < 1e-14);
    }
    assert!(SO3::from_quaternion_wxyz([0.0; 4]).is_err());
    assert!(SO3::from_quaternion_wxyz([f64::NAN, 0.0, 0.0, 1.0]).is_err());
}

/// Projection equals the polar factor M (MᵀM)^(−1/2), computed by an eigendecomposition.
#[test]
fn projection_onto_so3_is_the_polar_factor() {
    let mut rng = SplitMix64::new(8);
    for _ in 0..200 {
        let r = rng.rotation();
        let noise = Matrix3::from_fn(|_, _| 5e-4 * rng.normal());
        let m = r.matrix() + noise;
        let eig = (m.transpose() * m).symmetric_eigen();
        let inv_sqrt = eig.eigenvectors
            * Matrix3::from_diagonal(&eig.eigenvalues.map(|l| 1.0 / l.sqrt()))
            * eig.eigenvectors.transpose();
        let polar = m * inv_sqrt;
        let projected = SO3::from_matrix_projected(&m).expect("near-rotation");
        assert!(relative_error(projected.matrix(), &polar) < 1e-12);
        assert!(SO3::from_matrix(&m).is_err(), "5e-4 noise must exceed the strict tolerance");
    }
    // reflections, rank-deficient and non-finite matrices are refused
    assert!(SO3::from_matrix_projected(&Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, -1.0))).is_err());
    assert!(SO3::from_matrix_projected(&Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, 0.0))).is_err());
    assert!(SO3::from_matrix_projected(&Matrix3::from_element(f64::NAN)).is_err());
}

#[test]
fn se3_from_matrix_checks_last_row_and_rotation() {
    let mut t = SE3::exp(&Twist::new(1.0, 2.0, 3.0, 0.1, 0.2, 0.3)).matrix();
    assert!(SE3::from_matrix(&t).is_ok());
    t[(3, 0)] = 0.1;
    assert!(SE3::from_matrix(&t).is_err());
    assert!(SE3::from_matrix_projected(&t).is_err());
    t[(3, 0)] = 0.0;
    t[(0, 0)] *= 1.001;
    assert!(SE3::from_matrix(&t).is_err());
    let projected = SE3::from_matrix_projected(&t).expect("near-rigid");
    assert!((projected.translation - Vector3::new(t[(0, 3)], t[(1, 3)], t[(2, 3)])).norm() == 0.0);
}

#[test]
fn hat_and_vee_are_inverse() {
    let mut rng = SplitMix64::new(9);
    for _ in 0..100 {
        let xi = rng.twist(1.0, 3.0);
        assert_eq!(se3::vee(&se3::hat(&xi)), xi);
        let phi = se3::phi(&xi);
        assert_eq!(so3::vee(&so3::hat(&phi)), phi);
        let v = rng.unit_vector();
        assert!((so3::hat(&phi) * v - phi.cross(&v)).norm() < 1e-15);
    }
}

fn twist_strategy() -> impl Strategy<Value = Twist> {
    let angle = prop_oneof![
        Just(0.0),
        (1e-10..1e-7_f64),
        (0.18..0.22_f64),
        (0.0..std::f64::consts::PI - 1e-3),
        (std::f64::consts::PI - 1e-5..std::f64::consts::PI - 1e-7),
    ];
    let axis = (-1.0..1.0_f64, -1.0..1.0_f64, -1.0..1.0_f64)
        .prop_filter("non-zero axis", |(x, y, z)| x * x + y * y + z * z > 1e-4);
    let rho = (-30.0..30.0_f64, -30.0..30.0_f64, -30.0..30.0_f64);
    (angle, axis, rho).prop_map(|(angle, (x, y, z), (a, b, c))| {
        let phi = Vector3::new(x, y, z).normalize() * angle;
        se3::twist(&Vector3::new(a, b, c), &phi)
    })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(512))]

    #[test]
    fn prop_log_of_exp(xi in twist_strategy()) {
        let back = SE3::exp(&xi).log();
        prop_assert!((back - xi).norm() <= 1e-9 * xi.norm().max(1e-6));
    }

    #[test]
    fn prop_exp_of_log(xi in twist_strategy()) {
        let t = SE3::exp(&xi);
        prop_assert!(relative_error(&SE3::exp(&t.log()).matrix(), &t.matrix()) < ROUND_TRIP_TOL);
    }

    #[test]
    fn prop_adjoint_exp(xi in twist_strategy()) {
        let lhs = SE3::exp(&xi).adjoint();
        prop_assert!(relative_error(&lhs, &matrix_exp(&se3::curly_hat(&xi))) < 1e-10);
    }

    #[test]
    fn prop_jacobian_inverse(xi in twist_strategy()) {
        let scale = 1.0 + xi.norm();
        let l = se3::left_jacobian(&xi) * se3::left_jacobian_inverse(&xi);
        prop_assert!((l - Matrix6::identity()).abs().max() < IDENTITY_TOL * scale * scale);
    }

    #[test]
    fn prop_inverse_composes_to_identity(xi in twist_strategy()) {
        let t = SE3::exp(&xi);
        prop_assert!(relative_error(&(t * t.inverse()).matrix(), &nalgebra::Matrix4::identity()) < 1e-13);
    }
}

/// Magnitudes the exponential map cannot take are refused by name; matrices that
/// are no rotation have no angle; projection is immune to the scale of its input.
#[test]
fn overflowing_and_non_rotation_inputs_are_refused() {
    use geoloc_core::GeolocError;
    use geoloc_core::lie::{MAX_ROTATION_VECTOR_NORM, check_twist, try_rotation_angle};
    let huge = Vector3::new(1e300, 0.0, 0.0);
    assert!(matches!(SO3::try_exp(&huge), Err(GeolocError::InvalidInput { name, .. }) if name == "phi"));
    let just_inside = Vector3::new(MAX_ROTATION_VECTOR_NORM, 0.0, 0.0);
    assert!(SO3::try_exp(&just_inside).is_ok_and(|r| r.matrix().iter().all(|v| v.is_finite())));
    let xi = Twist::new(1e200, 0.0, 0.0, 0.0, 0.0, 0.1);
    assert!(matches!(check_twist(&xi), Err(GeolocError::InvalidInput { name, .. }) if name == "xi"));
    let xi = Twist::new(0.0, 0.0, 0.0, 0.0, 1e300, 0.0);
    assert!(matches!(check_twist(&xi), Err(GeolocError::InvalidInput { name, .. }) if name == "xi"));
    assert!(
        matches!(try_rotation_angle(&Matrix3::from_element(1.0)), Err(GeolocError::NotARotation { name, .. }) if name == "R")
    );
    // near-rotations (a real dataset's det ≈ 0.9995) keep their angle
    let r = SO3::exp(&Vector3::new(0.0, 0.0, 0.5)).matrix() * 0.9998;
    assert!((try_rotation_angle(&r).expect("near-rotation") - 0.5).abs() < 1e-3);
    // SVD projection of scaled rotations: 1e200·R and 1e-200·R project to R
    let r = SO3::exp(&Vector3::new(0.3, -0.2, 0.1));
    for scale in [1e200, 1e-200, 3.0] {
        let p = SO3::from_matrix_projected(&(r.matrix() * scale)).expect("scaled rotation");
        assert!((p.matrix() - r.matrix()).abs().max() < 1e-14, "scale {scale}");
    }
    // denormal scales (found by tests/adversarial: 2^1063 overflowed to inf → NaN rotation);
    // the entries keep only a few bits, so the projection is a rotation near R, not R
    for scale in [1e-310, 1e-320] {
        let p = SO3::from_matrix_projected(&(r.matrix() * scale)).expect("denormal rotation");
        let m = p.matrix();
        assert!(m.iter().all(|x| x.is_finite()), "scale {scale}");
        assert!((m.transpose() * m - Matrix3::identity()).abs().max() < 1e-12, "scale {scale}");
        assert!((m - r.matrix()).abs().max() < 0.05, "scale {scale}");
    }
}
