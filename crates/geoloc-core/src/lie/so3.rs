//! SO(3): rotations as 3×3 orthonormal matrices, with the rotation vector φ ∈ R³ as the
//! Lie-algebra coordinate (θ = ‖φ‖, axis a = φ/θ).
//!
//! * hat:  φ^ = [[0, −φ₃, φ₂], [φ₃, 0, −φ₁], [−φ₂, φ₁, 0]], so φ^ v = φ × v.
//! * exp:  R = cos θ I + (sin θ/θ) φ^ + ((1 − cos θ)/θ²) φφᵀ (Rodrigues; Barfoot 2017 eq. 7.14).
//! * log:  through the unit quaternion (Shepperd's pivoting), φ = 2 atan2(‖v‖, w) v/‖v‖ —
//!   accurate at θ → 0 and at θ → π, where the textbook θ/(2 sin θ)(R − Rᵀ)^∨ breaks down.
//! * Jacobians (Barfoot eqs. 7.77–7.79; right perturbation convention of the crate):
//!   J_l(φ) = I + ((1 − cos θ)/θ²) φ^ + ((θ − sin θ)/θ³) φ^²,  J_r(φ) = J_l(−φ),
//!   J_l⁻¹(φ) = I − ½ φ^ + (1/θ² − (1 + cos θ)/(2θ sin θ)) φ^²,  J_r⁻¹(φ) = J_l⁻¹(−φ),
//!   so that exp(φ + δ) ≈ exp(φ) exp(J_r(φ) δ) ≈ exp(J_l(φ) δ) exp(φ).

use nalgebra::{Matrix3, Vector3};

use super::series;
use crate::error::{GeolocError, Result};

/// Largest |RᵀR − I| entry (and |det R − 1|) accepted by [`SO3::from_matrix`].
///
/// Round-off from composing thousands of rotations stays many orders of magnitude below
/// this; real datasets that ship rotations with det ≈ 0.9995 (7-Scenes) exceed it and must
/// be projected with [`SO3::from_matrix_projected`].
pub const ROTATION_TOLERANCE: f64 = 1e-6;

/// Largest rotation-vector norm θ = ‖φ‖ (rad) the checked entry points
/// ([`SO3::try_exp`], [`check_rotation_vector`]) accept. Rotations are 2π-periodic, so no
/// meaningful input comes near it; far beyond it θ² overflows (θ > 1.3e154) and Rodrigues'
/// coefficients turn into NaN.
pub const MAX_ROTATION_VECTOR_NORM: f64 = 1e12;

/// Largest |RᵀR − I| entry (and |det R − 1|) of a *near*-rotation, accepted by
/// [`try_rotation_angle`] (and by the projection of real datasets' rotations, det ≈ 0.9995).
pub const NEAR_ROTATION_TOLERANCE: f64 = 1e-2;

/// Below this ‖v‖ (the quaternion's vector part) the log uses φ = (2/w)(1 − ‖v‖²/(3w²)) v.
const QUATERNION_SMALL_VECTOR: f64 = 1e-10;

/// Smallest singular value (relative to the largest) that [`SO3::from_matrix_projected`]
/// accepts: below it the matrix does not determine a rotation.
const PROJECTION_MIN_SINGULAR_RATIO: f64 = 1e-6;

/// A 3D rotation, stored as an orthonormal matrix with det = +1.
///
/// ```
/// use geoloc_core::lie::SO3;
/// use nalgebra::Vector3;
/// let r = SO3::exp(&Vector3::new(0.0, 0.0, std::f64::consts::FRAC_PI_2));
/// let x = r * Vector3::x();
/// assert!((x - Vector3::y()).norm() < 1e-15);
/// ```
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SO3 {
    matrix: Matrix3<f64>,
}

/// φ^: the skew-symmetric matrix with φ^ v = φ × v.
#[inline]
pub fn hat(phi: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -phi.z, phi.y, phi.z, 0.0, -phi.x, -phi.y, phi.x, 0.0)
}

/// The inverse of [`hat`], applied to the skew-symmetric part ½(M − Mᵀ) of `m` (equal to
/// the usual vee for a skew-symmetric `m`).
#[inline]
pub fn vee(m: &Matrix3<f64>) -> Vector3<f64> {
    0.5 * Vector3::new(m[(2, 1)] - m[(1, 2)], m[(0, 2)] - m[(2, 0)], m[(1, 0)] - m[(0, 1)])
}

/// The rotation angle Θ(R) ∈ [0, π] of a (near-)rotation matrix.
///
/// Θ = atan2(‖(R − Rᵀ)^∨‖/2, (tr R − 1)/2): never NaN, also for tr R slightly outside
/// [−1, 3] and for slightly non-orthonormal input, and accurate at both ends of the range
/// (the acos form loses half the digits near 0 and π).
#[inline]
pub fn rotation_angle(r: &Matrix3<f64>) -> f64 {
    let sin_theta = vee(r).norm();
    let cos_theta = 0.5 * (r.trace() - 1.0);
    sin_theta.atan2(cos_theta)
}

/// ‖φ‖² below which [`check_rotation_vector`] (and `se3::check_twist`) accept at once:
/// strictly inside [`MAX_ROTATION_VECTOR_NORM`]², so whatever passes passes the detailed checks.
pub(super) const FAST_ROTATION_VECTOR_NORM_SQUARED: f64 = 0.99 * MAX_ROTATION_VECTOR_NORM * MAX_ROTATION_VECTOR_NORM;

/// Checks that φ is finite with ‖φ‖ ≤ [`MAX_ROTATION_VECTOR_NORM`].
///
/// # Errors
/// [`GeolocError::NonFinite`] or [`GeolocError::InvalidInput`], named "phi" (batch callers
/// re-index with [`GeolocError::at`]).
#[inline]
pub fn check_rotation_vector(phi: &Vector3<f64>) -> Result<()> {
    // the common case: NaN fails the comparison and ∞ the bound, which sits strictly inside
    // the limit, so whatever passes here passes the checks below
    if phi.norm_squared() <= FAST_ROTATION_VECTOR_NORM_SQUARED {
        return Ok(());
    }
    check_rotation_vector_in_detail(phi)
}

/// [`check_rotation_vector`]'s checks one by one, for the error that names what is wrong.
pub(super) fn check_rotation_vector_in_detail(phi: &Vector3<f64>) -> Result<()> {
    check_finite(phi.as_slice()).map_err(|e| e.at("phi", 0))?;
    // the largest entry first: ‖φ‖ itself overflows to ∞ beyond 1e154
    let theta = if phi.amax() > MAX_ROTATION_VECTOR_NORM { phi.amax() } else { phi.norm() };
    if theta > MAX_ROTATION_VECTOR_NORM {
        return Err(GeolocError::invalid(
            "phi",
            format!("‖φ‖ ≥ {theta:e} rad exceeds {MAX_ROTATION_VECTOR_NORM:e} (the exponential map would overflow)"),
        ));
    }
    Ok(())
}

/// Θ(R) ([`rotation_angle`]) of a finite near-rotation (RᵀR = I and det R = 1 within
/// [`NEAR_ROTATION_TOLERANCE`]); a matrix that is no rotation at all has no angle.
///
/// # Errors
/// [`GeolocError::NonFinite`] or [`GeolocError::NotARotation`] named "R".
pub fn try_rotation_angle(r: &Matrix3<f64>) -> Result<f64> {
    check_finite(r.as_slice()).map_err(|e| e.at("R", 0))?;
    let (gram_error, det) = gram_error_and_det(r);
    if gram_error > NEAR_ROTATION_TOLERANCE || (det - 1.0).abs() > NEAR_ROTATION_TOLERANCE {
        return Err(GeolocError::NotARotation {
            name: "R".into(),
            index: None,
            what: "near-rotation",
            reason: format!(
                "max |RᵀR − I| = {gram_error:.3e}, det R = {det:.6} (tolerance {NEAR_ROTATION_TOLERANCE:e})"
            ),
        });
    }
    Ok(rotation_angle(r))
}

/// max |RᵀR − I| over the entries, and det R.
fn gram_error_and_det(matrix: &Matrix3<f64>) -> (f64, f64) {
    let (c0, c1, c2) = (matrix.column(0), matrix.column(1), matrix.column(2));
    let gram_error = [
        c0.norm_squared() - 1.0,
        c1.norm_squared() - 1.0,
        c2.norm_squared() - 1.0,
        c0.dot(&c1),
        c0.dot(&c2),
        c1.dot(&c2),
    ]
    .iter()
    .fold(0.0_f64, |m, e| m.max(e.abs()));
    (gram_error, c0.dot(&c1.cross(&c2)))
}

impl SO3 {
    /// exp(φ^) after [`check_rotation_vector`].
    ///
    /// # Errors
    /// Non-finite φ or ‖φ‖ > [`MAX_ROTATION_VECTOR_NORM`].
    pub fn try_exp(phi: &Vector3<f64>) -> Result<Self> {
        check_rotation_vector(phi)?;
        Ok(Self::exp(phi))
    }

    /// The identity rotation.
    #[inline]
    pub fn identity() -> Self {
        Self { matrix: Matrix3::identity() }
    }

    /// Wraps `matrix` without checking it (the caller guarantees RᵀR = I, det R = 1).
    #[inline]
    pub fn from_matrix_unchecked(matrix: Matrix3<f64>) -> Self {
        Self { matrix }
    }

    /// Accepts `matrix` if it is finite and a rotation within [`ROTATION_TOLERANCE`].
    ///
    /// # Errors
    /// [`GeolocError::NonFinite`] or [`GeolocError::NotARotation`] (no index; batch callers
    /// re-index with [`GeolocError::at`]).
    pub fn from_matrix(matrix: &Matrix3<f64>) -> Result<Self> {
        check_finite(matrix.as_slice())?;
        let (gram_error, det) = gram_error_and_det(matrix);
        if gram_error > ROTATION_TOLERANCE || (det - 1.0).abs() > ROTATION_TOLERANCE {
            return Err(GeolocError::NotARotation {
                name: "R".into(),
                index: None,
                what: "rotation",
                reason: format!(
                    "max |RᵀR − I| = {gram_error:.3e}, det R = {det:.9} \
                     (tolerance {ROTATION_TOLERANCE:e})"
                ),
            });
        }
        Ok(Self { matrix: *matrix })
    }

    /// The rotation nearest to `matrix` in the Frobenius norm: R = U diag(1, 1, det(UVᵀ)) Vᵀ
    /// from the SVD M = UΣVᵀ (the orthogonal Procrustes solution).
    ///
    /// For near-rotations such as the poses of real datasets (det 0.9995–0.9999), whose
    /// rotation angles otherwise come out off by degrees.
    ///
    /// # Errors
    /// Non-finite input, a rank-deficient matrix, or a reflection (det ≤ 0), none of which
    /// is a near-rotation.
    pub fn from_matrix_projected(matrix: &Matrix3<f64>) -> Result<Self> {
        check_finite(matrix.as_slice())?;
        let not_near =
            |reason: String| GeolocError::NotARotation { name: "R".into(), index: None, what: "near-rotation", reason };
        // The polar factor of cM is that of M for c > 0: scale by a power of two (exact in
        // floating point, so near-rotations give the same bits) to keep the SVD from
        // overflowing (1e200·I) or underflowing (1e-200·I).
        let largest = matrix.abs().max();
        if largest == 0.0 {
            return Err(not_near("the zero matrix".into()));
        }
        // In two factors: for denormal entries (largest ≈ 6e-321) 2^1063 alone is inf.
        let exponent = -(largest.log2().round() as i32);
        let matrix = &(matrix * 2f64.powi(exponent / 2) * 2f64.powi(exponent - exponent / 2));
        let det = matrix.determinant();
        if det <= 0.0 {
            return Err(not_near(format!("det = {det:.6e} ≤ 0")));
        }
        let svd = matrix.svd(true, true);
        let s_max = svd.singular_values.max();
        let s_min = svd.singular_values.min();
        if s_min <= PROJECTION_MIN_SINGULAR_RATIO * s_max {
            return Err(not_near(format!("singular values {:?} (rank-deficient)", svd.singular_values.as_slice())));
        }
        let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
            return Err(not_near("SVD did not converge".into()));
        };
        let mut r = u * v_t;
        if r.determinant() < 0.0 {
            let mut d = Matrix3::identity();
            d[(2, 2)] = -1.0;
            r = u * d * v_t;
        }
        Ok(Self { matrix: r })
    }

    /// One Newton step of the polar decomposition, R ← ½ R (3I − RᵀR): removes the
    /// round-off drift that long chains of compositions accumulate (quadratically
    /// convergent; for drift δ the result is off by O(δ²)).
    #[must_use]
    pub fn normalized(&self) -> Self {
        let r = &self.matrix;
        Self { matrix: 0.5 * r * (3.0 * Matrix3::identity() - r.transpose() * r) }
    }

    /// The rotation matrix.
    #[inline]
    pub fn matrix(&self) -> &Matrix3<f64> {
        &self.matrix
    }

    /// exp(φ^) by Rodrigues' formula R = cos θ I + (sin θ/θ) φ^ + ((1 − cos θ)/θ²) φφᵀ.
    #[inline]
    pub fn exp(phi: &Vector3<f64>) -> Self {
        Self::from_coefficients(phi, &series::ExpCoefficients::new(phi.norm()))
    }

    /// Rodrigues' formula with precomputed coefficients of θ = ‖φ‖ (shared with SE(3) exp).
    #[inline]
    pub(crate) fn from_coefficients(phi: &Vector3<f64>, k: &series::ExpCoefficients) -> Self {
        let (c, a, b) = (k.cos, k.a, k.b);
        let (x, y, z) = (phi.x, phi.y, phi.z);
        let matrix = Matrix3::new(
            c + b * x * x,
            b * x * y - a * z,
            b * x * z + a * y,
            b * x * y + a * z,
            c + b * y * y,
            b * y * z - a * x,
            b * x * z - a * y,
            b * y * z + a * x,
            c + b * z * z,
        );
        Self { matrix }
    }

    /// log(R)^∨ = φ with ‖φ‖ ∈ [0, π].
    ///
    /// At exactly θ = π, φ and −φ are both valid; one of them is returned.
    #[inline]
    pub fn log(&self) -> Vector3<f64> {
        let [mut w, x, y, z] = self.to_quaternion_wxyz();
        let mut v = Vector3::new(x, y, z);
        if w < 0.0 {
            w = -w;
            v = -v;
        }
        let n = v.norm();
        let scale = if n < QUATERNION_SMALL_VECTOR {
            // atan2(n, w)/n = (1/w)(1 − n²/(3w²) + O(n⁴)); w ≈ 1 here.
            2.0 / w * (1.0 - n * n / (3.0 * w * w))
        } else {
            2.0 * n.atan2(w) / n
        };
        scale * v
    }

    /// The unit quaternion (w, x, y, z) of this rotation, by Shepperd's method: the
    /// largest of 4w², 4x², 4y², 4z² is taken from the diagonal, the others from
    /// off-diagonal sums/differences divided by it, so no component loses precision.
    pub fn to_quaternion_wxyz(&self) -> [f64; 4] {
        let m = &self.matrix;
        let (m00, m11, m22) = (m[(0, 0)], m[(1, 1)], m[(2, 2)]);
        let trace = m00 + m11 + m22;
        if trace >= m00 && trace >= m11 && trace >= m22 {
            let s = 2.0 * (1.0 + trace).max(0.0).sqrt(); // s = 4w
            [0.25 * s, (m[(2, 1)] - m[(1, 2)]) / s, (m[(0, 2)] - m[(2, 0)]) / s, (m[(1, 0)] - m[(0, 1)]) / s]
        } else if m00 >= m11 && m00 >= m22 {
            let s = 2.0 * (1.0 + m00 - m11 - m22).max(0.0).sqrt(); // s = 4x
            [(m[(2, 1)] - m[(1, 2)]) / s, 0.25 * s, (m[(0, 1)] + m[(1, 0)]) / s, (m[(0, 2)] + m[(2, 0)]) / s]
        } else if m11 >= m22 {
            let s = 2.0 * (1.0 + m11 - m00 - m22).max(0.0).sqrt(); // s = 4y
            [(m[(0, 2)] - m[(2, 0)]) / s, (m[(0, 1)] + m[(1, 0)]) / s, 0.25 * s, (m[(1, 2)] + m[(2, 1)]) / s]
        } else {
            let s = 2.0 * (1.0 + m22 - m00 - m11).max(0.0).sqrt(); // s = 4z
            [(m[(1, 0)] - m[(0, 1)]) / s, (m[(0, 2)] + m[(2, 0)]) / s, (m[(1, 2)] + m[(2, 1)]) / s, 0.25 * s]
        }
    }

    /// The rotation of the unit quaternion (w, x, y, z), normalized first.
    ///
    /// # Errors
    /// Non-finite or zero-norm input.
    pub fn from_quaternion_wxyz(q: [f64; 4]) -> Result<Self> {
        check_finite(&q)?;
        let n = q.iter().map(|c| c * c).sum::<f64>().sqrt();
        if n < f64::MIN_POSITIVE.sqrt() {
            return Err(GeolocError::invalid("q", "zero-norm quaternion"));
        }
        let [w, x, y, z] = q.map(|c| c / n);
        let matrix = Matrix3::new(
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - w * z),
            2.0 * (x * z + w * y),
            2.0 * (x * y + w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - w * x),
            2.0 * (x * z - w * y),
            2.0 * (y * z + w * x),
            1.0 - 2.0 * (x * x + y * y),
        );
        Ok(Self { matrix })
    }

    /// R⁻¹ = Rᵀ.
    #[inline]
    pub fn inverse(&self) -> Self {
        Self { matrix: self.matrix.transpose() }
    }

    /// The rotation angle Θ ∈ [0, π] (see [`rotation_angle`]).
    #[inline]
    pub fn angle(&self) -> f64 {
        rotation_angle(&self.matrix)
    }

    /// The adjoint of SO(3): Ad(R) = R (so that R exp(φ^) Rᵀ = exp((Rφ)^)).
    #[inline]
    pub fn adjoint(&self) -> Matrix3<f64> {
        self.matrix
    }

    /// Θ(R₁ᵀR₂): the geodesic distance between two rotations.
    #[inline]
    pub fn distance(&self, other: &Self) -> f64 {
        rotation_angle(&(self.matrix.transpose() * other.matrix))
    }

    /// The geodesic R₁ exp(α log(R₁ᵀR₂)): R₁ at α = 0, R₂ at α = 1.
    pub fn interpolate(&self, other: &Self, alpha: f64) -> Self {
        *self * Self::exp(&(alpha * (self.inverse() * *other).log()))
    }
}

impl std::ops::Mul for SO3 {
    type Output = SO3;
    /// Composition R₁R₂.
    #[inline]
    fn mul(self, rhs: SO3) -> SO3 {
        SO3 { matrix: self.matrix * rhs.matrix }
    }
}

impl std::ops::Mul<Vector3<f64>> for SO3 {
    type Output = Vector3<f64>;
    /// Rotates a vector: R v.
    #[inline]
    fn mul(self, rhs: Vector3<f64>) -> Vector3<f64> {
        self.matrix * rhs
    }
}

/// J_l(φ) = I + ((1 − cos θ)/θ²) φ^ + ((θ − sin θ)/θ³) φ^² (Barfoot eq. 7.77a).
#[inline]
pub fn left_jacobian(phi: &Vector3<f64>) -> Matrix3<f64> {
    let k = series::ExpCoefficients::new(phi.norm());
    let p = hat(phi);
    Matrix3::identity() + k.b * p + k.c * p * p
}

/// J_r(φ) = J_l(−φ).
#[inline]
pub fn right_jacobian(phi: &Vector3<f64>) -> Matrix3<f64> {
    left_jacobian(&-phi)
}

/// J_l⁻¹(φ) = I − ½ φ^ + (1/θ² − (1 + cos θ)/(2θ sin θ)) φ^² (Barfoot eq. 7.77b).
///
/// Finite for θ < 2π; J_l is singular at θ = 2π.
#[inline]
pub fn left_jacobian_inverse(phi: &Vector3<f64>) -> Matrix3<f64> {
    let theta = phi.norm();
    let p = hat(phi);
    Matrix3::identity() - 0.5 * p + series::jacobian_inverse_second(theta) * p * p
}

/// Smallest singular value of J_l(φ) below which [`check_jacobian_invertible`] refuses φ.
pub const MIN_JACOBIAN_SINGULAR_VALUE: f64 = 1e-9;

/// Err naming `phi` where J_l(φ) (and J_r(φ)) is singular to working precision, so that
/// [`left_jacobian_inverse`] would return noise: J_l's singular values are 1 along φ and
/// |2 sin(θ/2)| / θ twice across it (θ = ‖φ‖; its eigenvalues there are
/// (sin θ ± i(1 − cos θ))/θ), zero at every nonzero multiple of 2π. Refused when that value
/// is below [`MIN_JACOBIAN_SINGULAR_VALUE`]; never for θ < π (it is at least 2/π there).
///
/// # Errors
/// [`GeolocError::InvalidInput`] for `phi`.
pub fn check_jacobian_invertible(phi: &Vector3<f64>) -> Result<()> {
    let theta = phi.norm();
    if theta < std::f64::consts::PI {
        return Ok(());
    }
    let smallest = (2.0 * (0.5 * theta).sin() / theta).abs();
    if smallest < MIN_JACOBIAN_SINGULAR_VALUE {
        let turns = theta / std::f64::consts::TAU;
        return Err(GeolocError::invalid(
            "phi",
            format!(
                "‖φ‖ = {theta} rad is {turns:.0}·2π to within working precision, where J_l(φ) is singular (smallest singular value {smallest:.1e})"
            ),
        ));
    }
    Ok(())
}

/// J_r⁻¹(φ) = J_l⁻¹(−φ).
#[inline]
pub fn right_jacobian_inverse(phi: &Vector3<f64>) -> Matrix3<f64> {
    left_jacobian_inverse(&-phi)
}

/// First non-finite entry of `values`, as an error.
pub(crate) fn check_finite(values: &[f64]) -> Result<()> {
    match values.iter().position(|v| !v.is_finite()) {
        Some(index) => Err(GeolocError::NonFinite { name: "input".into(), index }),
        None => Ok(()),
    }
}
