//! Covariance helpers shared by the solvers: the input check every entry point that takes a
//! covariance runs, the inverse of an information matrix, and the paper's isometric σ.
//!
//! Conventions: pose covariances are 6×6 in the right-perturbation tangent space of
//! world_from_cam (T ⊞ δ = T exp(δ^)), translation first; point covariances are 3×3 in
//! world coordinates (m²).

use nalgebra::{DMatrix, Matrix6, SMatrix, Vector3, Vector6};

use crate::error::{GeolocError, Result};
use crate::lie::SO3;

/// Relative asymmetry max|M − Mᵀ| / max|M| above which a covariance is refused.
pub const SYMMETRY_TOLERANCE: f64 = 1e-9;
/// Relative negative eigenvalue λ_min / max|λ| below −this refuses a covariance as not
/// positive semi-definite (rounding of a PSD matrix stays far above it).
pub const PSD_TOLERANCE: f64 = 1e-9;
/// Reciprocal condition number of an information matrix below which it is singular (the
/// pose is not observable: collinear points, a single point cluster seen head-on, …).
pub const MIN_RECIPROCAL_CONDITION: f64 = 1e-12;

/// Checks that `m` is a covariance: finite, symmetric (|M − Mᵀ| ≤ 1e-9·max|M|) and positive
/// semi-definite (λ_min ≥ −1e-9·max|λ|). A zero matrix (an exact quantity) passes.
/// The one covariance check of the crate (map building and map files, PnP, triangulation,
/// the motion model, fusion). The eigenvalue tolerance is relative to the spectral radius
/// max|λ| — the scale of the eigensolver's rounding — not to the largest entry.
///
/// # Errors
/// [`GeolocError::NonFinite`] (index = flat row-major position of the first bad value) or
/// [`GeolocError::InvalidInput`] naming `name`.
///
/// ```
/// use geoloc_core::optim::covariance::check_covariance;
/// use nalgebra::Matrix3;
/// assert!(check_covariance("cov", &Matrix3::<f64>::identity()).is_ok());
/// assert!(check_covariance("cov", &(-Matrix3::<f64>::identity())).is_err());
/// ```
pub fn check_covariance<const D: usize>(name: &str, m: &SMatrix<f64, D, D>) -> Result<()> {
    if let Some(flat) = m.transpose().iter().position(|v| !v.is_finite()) {
        return Err(GeolocError::NonFinite { name: name.into(), index: flat });
    }
    let scale = m.abs().max();
    let asymmetry = (m - m.transpose()).abs().max();
    if asymmetry > SYMMETRY_TOLERANCE * scale {
        return Err(GeolocError::invalid(name, format!("is not symmetric (max |M − Mᵀ| = {asymmetry:.3e})")));
    }
    let symmetric = 0.5 * (m + m.transpose());
    // positive definite, the usual case, needs no eigenvalues: a Cholesky factor exists only
    // when λ_min ≥ −c·D·ε·max|M| (its backward stability), far inside the tolerance below.
    // Semi-definite and indefinite matrices take the eigenvalues (a PnP checks each of its
    // points' 3×3 covariances: the eigenvalues of all of them were ≈ 6 % of a model-locator
    // frame)
    if symmetric.cholesky().is_some() {
        return Ok(());
    }
    let eigenvalues = DMatrix::from_column_slice(D, D, symmetric.as_slice()).symmetric_eigenvalues();
    let lo = eigenvalues.min();
    let hi = eigenvalues.abs().max();
    if lo < -PSD_TOLERANCE * hi {
        return Err(GeolocError::invalid(
            name,
            format!("is not positive semi-definite (smallest eigenvalue {lo:.3e})"),
        ));
    }
    Ok(())
}

/// [`check_covariance`] for each matrix of a batch; errors name `name[i]`.
///
/// # Errors
/// The first failing item's error.
pub fn check_covariances<const D: usize>(name: &str, items: &[SMatrix<f64, D, D>]) -> Result<()> {
    for (i, m) in items.iter().enumerate() {
        check_covariance(name, m).map_err(|e| match e {
            GeolocError::NonFinite { .. } => GeolocError::NonFinite { name: name.into(), index: i },
            other => other.at(name, i),
        })?;
    }
    Ok(())
}

/// M⁻¹ for a symmetric positive definite M (Cholesky), for turning covariances into
/// information matrices.
///
/// # Errors
/// [`GeolocError::InvalidInput`] naming `name` when M is not finite, not symmetric
/// (1e-9 relative) or not positive definite.
pub fn spd_inverse(m: &Matrix6<f64>, name: &str) -> Result<Matrix6<f64>> {
    if !m.iter().all(|v| v.is_finite()) {
        return Err(GeolocError::invalid(name, "holds non-finite values"));
    }
    if (m - m.transpose()).abs().max() > SYMMETRY_TOLERANCE * m.abs().max().max(f64::MIN_POSITIVE) {
        return Err(GeolocError::invalid(name, "is not symmetric"));
    }
    let inverse =
        m.cholesky().map(|c| c.inverse()).ok_or_else(|| GeolocError::invalid(name, "is not positive definite"))?;
    if !inverse.iter().all(|v| v.is_finite()) {
        return Err(GeolocError::invalid(name, "is too small to invert (its inverse overflows)"));
    }
    Ok(inverse)
}

/// C = H⁻¹ for an information matrix H = Σ w JᵀWJ, or None when the pose is not observable
/// (λ_min(H) ≤ 1e-12 λ_max(H), or non-finite).
pub fn inverse_information(h: &Matrix6<f64>) -> Option<Matrix6<f64>> {
    if !h.iter().all(|v| v.is_finite()) {
        return None;
    }
    let eig = h.symmetric_eigen();
    let (lo, hi) = eig.eigenvalues.iter().fold((f64::INFINITY, 0.0_f64), |(lo, hi), &v| (lo.min(v), hi.max(v)));
    if lo.is_nan() || lo <= MIN_RECIPROCAL_CONDITION * hi {
        return None;
    }
    h.try_inverse()
}

/// The paper's isometric σ of a pose covariance: σ_p = mean √diag(C_ρ) (m) and
/// σ_r = Θ(exp(√diag(C_φ))) (rad), translation first.
pub fn isometric_sigmas(c: &Matrix6<f64>) -> (f64, f64) {
    let sd = Vector6::from_fn(|i, _| c[(i, i)].max(0.0).sqrt());
    let sigma_p = (sd[0] + sd[1] + sd[2]) / 3.0;
    let sigma_r = SO3::exp(&Vector3::new(sd[3], sd[4], sd[5])).angle();
    (sigma_p, sigma_r)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::SplitMix64;
    use nalgebra::{Matrix3, Matrix6};

    fn random_spd(rng: &mut SplitMix64) -> Matrix6<f64> {
        let a = Matrix6::from_fn(|_, _| rng.normal());
        a * a.transpose() + Matrix6::identity() * 0.1
    }

    #[test]
    fn spd_inverse_times_matrix_is_identity() {
        let mut rng = SplitMix64::new(1);
        for _ in 0..20 {
            let m = random_spd(&mut rng);
            let inv = spd_inverse(&m, "m").expect("spd");
            // reference: the LU inverse
            let lu = m.lu().try_inverse().expect("invertible");
            assert!((inv - lu).abs().max() < 1e-9 * lu.abs().max());
            assert!((inv * m - Matrix6::identity()).abs().max() < 1e-9);
        }
        let mut asym = Matrix6::identity();
        asym[(0, 1)] = 0.5;
        assert!(matches!(spd_inverse(&asym, "c"), Err(GeolocError::InvalidInput { name, .. }) if name == "c"));
        assert!(
            matches!(spd_inverse(&Matrix6::zeros(), "c"), Err(GeolocError::InvalidInput { name, .. }) if name == "c")
        );
    }

    #[test]
    fn inverse_information_refuses_rank_deficiency() {
        let mut rng = SplitMix64::new(2);
        let h = random_spd(&mut rng);
        let c = inverse_information(&h).expect("observable");
        assert!((c * h - Matrix6::identity()).abs().max() < 1e-9);
        // rank 5: one direction unobservable
        let v = Vector6::from_fn(|_, _| rng.normal()).normalize();
        let deficient = h - (h * v) * (h * v).transpose() / v.dot(&(h * v));
        assert!(inverse_information(&deficient).is_none());
        assert!(inverse_information(&Matrix6::from_element(f64::NAN)).is_none());
    }

    /// Against the closed form for a diagonal covariance: σ_p is the mean standard deviation
    /// and σ_r the angle of the rotation vector (s₃, s₄, s₅), i.e. its norm.
    #[test]
    fn isometric_sigmas_closed_form() {
        let d = [1e-4, 4e-4, 9e-4, 1e-6, 4e-6, 4e-6];
        let c = Matrix6::from_diagonal(&Vector6::from_row_slice(&d));
        let (sp, sr) = isometric_sigmas(&c);
        assert!((sp - 0.02).abs() < 1e-15);
        assert!((sr - 3e-3).abs() < 1e-15, "{sr}");
    }

    #[test]
    fn check_covariance_accepts_psd_and_refuses_the_rest() {
        let mut rng = SplitMix64::new(3);
        for _ in 0..20 {
            let m = random_spd(&mut rng);
            check_covariance("c", &m).expect("spd");
            // rank-deficient PSD (an exact direction) is a covariance too
            let v = Vector6::from_fn(|_, _| rng.normal());
            check_covariance("c", &(v * v.transpose())).expect("psd");
        }
        check_covariance("c", &Matrix3::<f64>::zeros()).expect("zero is psd");
        let negative = -Matrix3::<f64>::identity() * 1e-4;
        assert!(matches!(check_covariance("c", &negative), Err(GeolocError::InvalidInput { name, .. }) if name == "c"));
        // indefinite but with a positive diagonal: only the eigenvalues tell
        let indefinite = Matrix3::new(1.0, 2.0, 0.0, 2.0, 1.0, 0.0, 0.0, 0.0, 1.0);
        assert!(check_covariance("c", &indefinite).is_err());
        let mut asym = Matrix3::<f64>::identity();
        asym[(0, 2)] = 1e-3;
        assert!(check_covariance("c", &asym).is_err());
        let mut nan = Matrix3::<f64>::identity();
        nan[(1, 2)] = f64::NAN;
        assert!(
            matches!(check_covariance("c", &nan), Err(GeolocError::NonFinite { name, index }) if name == "c" && index == 5)
        );
        let batch = [Matrix3::identity(), negative];
        assert!(
            matches!(check_covariances("point_covariances", &batch), Err(GeolocError::InvalidInput { name, .. }) if name == "point_covariances[1]")
        );
    }

    /// The rule by eigenvalues alone (λ_min ≥ −1e-9·max|λ| of the symmetric part), as a
    /// reference for the Cholesky shortcut.
    fn psd_by_eigenvalues<const D: usize>(m: &SMatrix<f64, D, D>) -> bool {
        let symmetric = 0.5 * (m + m.transpose());
        let eigenvalues = DMatrix::from_column_slice(D, D, symmetric.as_slice()).symmetric_eigenvalues();
        eigenvalues.min() >= -PSD_TOLERANCE * eigenvalues.abs().max()
    }

    /// Q diag(λ) Qᵀ for a random rotation-like Q (orthonormalized Gaussian) and the given λ.
    fn with_eigenvalues<const D: usize>(rng: &mut SplitMix64, lambda: [f64; D]) -> SMatrix<f64, D, D> {
        let q = DMatrix::from_fn(D, D, |_, _| rng.normal()).qr().q();
        let m = &q * DMatrix::from_diagonal(&nalgebra::DVector::from_column_slice(&lambda)) * q.transpose();
        let m = SMatrix::<f64, D, D>::from_column_slice(m.as_slice());
        0.5 * (m + m.transpose())
    }

    #[test]
    fn the_cholesky_shortcut_decides_as_the_eigenvalues_do() {
        let mut rng = SplitMix64::new(11);
        let mut decided = [0usize; 2];
        for trial in 0..4000_usize {
            let scale = 10f64.powi((trial % 13) as i32 - 8); // 1e-8 … 1e4 (m², rad²)
            // the smallest eigenvalue from well inside to well outside the tolerance, through
            // zero and the tolerance itself (±1e-9 relative)
            let rel = [1.0, 1e-3, 1e-8, 2e-9, 1e-9, 5e-10, 1e-12, 0.0, -1e-12, -5e-10, -1e-9, -2e-9, -1e-8, -1e-3]
                [trial % 14];
            let wiggle = 1.0 + 0.1 * rng.uniform();
            let m3 = with_eigenvalues::<3>(&mut rng, [scale * wiggle, 0.5 * scale, rel * scale]);
            let m6 = with_eigenvalues::<6>(
                &mut rng,
                [scale, 0.3 * scale, 2.0 * scale, scale * wiggle, 0.1 * scale, rel * scale],
            );
            for ok in [check_covariance("c", &m3).is_ok(), check_covariance("c", &m6).is_ok()] {
                decided[usize::from(ok)] += 1;
            }
            assert_eq!(check_covariance("c", &m3).is_ok(), psd_by_eigenvalues(&m3), "3×3, λ_min {rel:e}·{scale:e}");
            assert_eq!(check_covariance("c", &m6).is_ok(), psd_by_eigenvalues(&m6), "6×6, λ_min {rel:e}·{scale:e}");
        }
        // both outcomes are exercised in quantity
        assert!(decided[0] > 1000 && decided[1] > 1000, "{decided:?}");
    }
}
