//! SE(3): rigid transforms T = [[R, t], [0, 1]] with the twist ξ = (ρ, φ) ∈ R⁶ as the
//! Lie-algebra coordinate — **translation first** — and poses meant as world_from_cam.
//!
//! * hat:  ξ^ = [[φ^, ρ], [0, 0]];  curly hat (small adjoint) ξ⋏ = ad(ξ) = [[φ^, ρ^], [0, φ^]].
//! * exp:  T = [[exp(φ^), J_l(φ) ρ], [0, 1]] (Barfoot 2017 eq. 7.83).
//! * log:  φ = log(R), ρ = J_l⁻¹(φ) t.
//! * Ad(T) = [[R, t^R], [0, R]], so T exp(ξ^) T⁻¹ = exp((Ad(T) ξ)^) and Ad(exp ξ) = exp(ad ξ).
//! * Jacobians (Barfoot eqs. 7.85–7.86): 𝒥_l(ξ) = [[J_l(φ), Q_l(ξ)], [0, J_l(φ)]],
//!   𝒥_l⁻¹(ξ) = [[J_l⁻¹, −J_l⁻¹ Q_l J_l⁻¹], [0, J_l⁻¹]], 𝒥_r(ξ) = 𝒥_l(−ξ), such that
//!   exp(ξ + δ) ≈ exp(ξ) exp(𝒥_r(ξ) δ) ≈ exp(𝒥_l(ξ) δ) exp(ξ).
//! * Perturbations are on the **right**: T ⊞ δ = T exp(δ^); a pose covariance lives in
//!   that tangent space, translation first.
//! * d(T₁, T₂) = ‖log(T₁⁻¹T₂)^∨‖₂ (mixes metres and radians, as in the paper).

use nalgebra::{Matrix3, Matrix4, Matrix6, Vector3, Vector6};

use super::series;
use super::so3::{self, SO3};
use crate::error::{GeolocError, Result};

/// A twist ξ = (ρ, φ) ∈ R⁶: translation part ρ first, rotation vector φ last.
pub type Twist = Vector6<f64>;

/// A rigid transform; as a pose it maps camera coordinates to world coordinates
/// (world_from_cam): p_world = R p_cam + t.
///
/// ```
/// use geoloc_core::lie::{SE3, Twist};
/// let xi = Twist::new(1.0, -2.0, 0.5, 0.1, 0.2, -0.3);
/// let back = SE3::exp(&xi).log();
/// assert!((back - xi).norm() < 1e-14);
/// ```
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SE3 {
    /// The rotation R.
    pub rotation: SO3,
    /// The translation t (for a world_from_cam pose: the camera centre in the world).
    pub translation: Vector3<f64>,
}

/// ρ of a twist.
#[inline]
pub fn rho(xi: &Twist) -> Vector3<f64> {
    xi.fixed_rows::<3>(0).into_owned()
}

/// φ of a twist.
#[inline]
pub fn phi(xi: &Twist) -> Vector3<f64> {
    xi.fixed_rows::<3>(3).into_owned()
}

/// Stacks (ρ, φ) into a twist.
#[inline]
pub fn twist(rho: &Vector3<f64>, phi: &Vector3<f64>) -> Twist {
    Twist::new(rho.x, rho.y, rho.z, phi.x, phi.y, phi.z)
}

/// ξ^ = [[φ^, ρ], [0, 0]] ∈ se(3).
pub fn hat(xi: &Twist) -> Matrix4<f64> {
    let mut m = Matrix4::zeros();
    m.fixed_view_mut::<3, 3>(0, 0).copy_from(&so3::hat(&phi(xi)));
    m.fixed_view_mut::<3, 1>(0, 3).copy_from(&rho(xi));
    m
}

/// The inverse of [`hat`] (the rotation block is read through its skew-symmetric part).
pub fn vee(m: &Matrix4<f64>) -> Twist {
    let phi = so3::vee(&m.fixed_view::<3, 3>(0, 0).into_owned());
    let rho = m.fixed_view::<3, 1>(0, 3).into_owned();
    twist(&rho, &phi)
}

/// ad(ξ) = ξ⋏ = [[φ^, ρ^], [0, φ^]]: the adjoint of se(3), ad(ξ₁) ξ₂ = [ξ₁, ξ₂]^∨.
pub fn curly_hat(xi: &Twist) -> Matrix6<f64> {
    let p = so3::hat(&phi(xi));
    let mut m = Matrix6::zeros();
    m.fixed_view_mut::<3, 3>(0, 0).copy_from(&p);
    m.fixed_view_mut::<3, 3>(3, 3).copy_from(&p);
    m.fixed_view_mut::<3, 3>(0, 3).copy_from(&so3::hat(&rho(xi)));
    m
}

/// Largest ‖ρ‖ (m) of a twist the checked entry points accept: far below where J_l(φ) ρ
/// (or ρ alone in a 4×4 product) would overflow.
pub const MAX_TRANSLATION_NORM: f64 = 1e150;

/// ‖ρ‖² below which [`check_twist`] accepts at once (strictly inside [`MAX_TRANSLATION_NORM`]²).
const FAST_TRANSLATION_NORM_SQUARED: f64 = 0.99 * MAX_TRANSLATION_NORM * MAX_TRANSLATION_NORM;

/// Checks a twist ξ = (ρ, φ): finite, ‖φ‖ ≤ [`so3::MAX_ROTATION_VECTOR_NORM`] and
/// ‖ρ‖ ≤ [`MAX_TRANSLATION_NORM`].
///
/// # Errors
/// [`GeolocError::NonFinite`] or [`GeolocError::InvalidInput`] named "xi".
#[inline]
pub fn check_twist(xi: &Twist) -> Result<()> {
    // the common case in a few flops: NaN fails both comparisons and ∞ the bounds, which sit
    // strictly inside the limits, so whatever passes here passes the checks below
    if phi(xi).norm_squared() <= so3::FAST_ROTATION_VECTOR_NORM_SQUARED
        && rho(xi).norm_squared() <= FAST_TRANSLATION_NORM_SQUARED
    {
        return Ok(());
    }
    check_twist_in_detail(xi)
}

/// [`check_twist`]'s checks one by one, for the error that names what is wrong.
fn check_twist_in_detail(xi: &Twist) -> Result<()> {
    so3::check_finite(xi.as_slice()).map_err(|e| e.at("xi", 0))?;
    so3::check_rotation_vector(&phi(xi)).map_err(|e| match e {
        GeolocError::InvalidInput { reason, .. } => GeolocError::invalid("xi", reason),
        other => other,
    })?;
    let rho_norm = rho(xi).norm();
    if rho_norm > MAX_TRANSLATION_NORM {
        return Err(GeolocError::invalid(
            "xi",
            format!("‖ρ‖ = {rho_norm:e} exceeds {MAX_TRANSLATION_NORM:e} (the exponential map would overflow)"),
        ));
    }
    Ok(())
}

impl SE3 {
    /// The identity transform.
    #[inline]
    pub fn identity() -> Self {
        Self { rotation: SO3::identity(), translation: Vector3::zeros() }
    }

    /// From a rotation and a translation.
    #[inline]
    pub fn new(rotation: SO3, translation: Vector3<f64>) -> Self {
        Self { rotation, translation }
    }

    /// Accepts a 4×4 homogeneous matrix whose last row is (0, 0, 0, 1) and whose rotation
    /// block is a rotation, both within [`so3::ROTATION_TOLERANCE`].
    ///
    /// # Errors
    /// [`GeolocError::NonFinite`] or [`GeolocError::NotARotation`].
    pub fn from_matrix(m: &Matrix4<f64>) -> Result<Self> {
        so3::check_finite(m.as_slice())?;
        check_last_row(m)?;
        let rotation = SO3::from_matrix(&m.fixed_view::<3, 3>(0, 0).into_owned()).map_err(relabel_rigid)?;
        Ok(Self { rotation, translation: m.fixed_view::<3, 1>(0, 3).into_owned() })
    }

    /// Like [`SE3::from_matrix`] but projects the rotation block onto SO(3)
    /// ([`SO3::from_matrix_projected`]); the last row must still be (0, 0, 0, 1).
    ///
    /// # Errors
    /// Non-finite input, a bad last row, or a rotation block that is not a near-rotation.
    pub fn from_matrix_projected(m: &Matrix4<f64>) -> Result<Self> {
        so3::check_finite(m.as_slice())?;
        check_last_row(m)?;
        let rotation = SO3::from_matrix_projected(&m.fixed_view::<3, 3>(0, 0).into_owned())?;
        Ok(Self { rotation, translation: m.fixed_view::<3, 1>(0, 3).into_owned() })
    }

    /// The 4×4 homogeneous matrix.
    pub fn matrix(&self) -> Matrix4<f64> {
        let mut m = Matrix4::identity();
        m.fixed_view_mut::<3, 3>(0, 0).copy_from(self.rotation.matrix());
        m.fixed_view_mut::<3, 1>(0, 3).copy_from(&self.translation);
        m
    }

    /// exp(ξ^) = [[exp(φ^), J_l(φ) ρ], [0, 1]].
    #[inline]
    pub fn exp(xi: &Twist) -> Self {
        let phi = phi(xi);
        let rho = rho(xi);
        let k = series::ExpCoefficients::new(phi.norm());
        // J_l(φ) ρ = ρ + B φ×ρ + C φ×(φ×ρ), without forming the matrix.
        let phi_x_rho = phi.cross(&rho);
        let translation = rho + k.b * phi_x_rho + k.c * phi.cross(&phi_x_rho);
        Self { rotation: SO3::from_coefficients(&phi, &k), translation }
    }

    /// log(T)^∨ = (J_l⁻¹(φ) t, φ) with ‖φ‖ ∈ [0, π].
    #[inline]
    pub fn log(&self) -> Twist {
        let phi = self.rotation.log();
        // J_l⁻¹(φ) t = t − ½ φ×t + F φ×(φ×t), without forming the matrix.
        let t = &self.translation;
        let phi_x_t = phi.cross(t);
        let rho = t - 0.5 * phi_x_t + series::jacobian_inverse_second(phi.norm()) * phi.cross(&phi_x_t);
        twist(&rho, &phi)
    }

    /// T⁻¹ = [[Rᵀ, −Rᵀt], [0, 1]].
    #[inline]
    pub fn inverse(&self) -> Self {
        let r_inv = self.rotation.inverse();
        Self { rotation: r_inv, translation: -(r_inv * self.translation) }
    }

    /// Ad(T) = [[R, t^R], [0, R]] (translation-first twists).
    pub fn adjoint(&self) -> Matrix6<f64> {
        let r = self.rotation.matrix();
        let mut m = Matrix6::zeros();
        m.fixed_view_mut::<3, 3>(0, 0).copy_from(r);
        m.fixed_view_mut::<3, 3>(3, 3).copy_from(r);
        m.fixed_view_mut::<3, 3>(0, 3).copy_from(&(so3::hat(&self.translation) * r));
        m
    }

    /// d(T₁, T₂) = ‖log(T₁⁻¹T₂)^∨‖₂.
    #[inline]
    pub fn distance(&self, other: &Self) -> f64 {
        (self.inverse() * *other).log().norm()
    }

    /// The geodesic T₁ exp(α log(T₁⁻¹T₂)): T₁ at α = 0, T₂ at α = 1 (constant body twist).
    pub fn interpolate(&self, other: &Self, alpha: f64) -> Self {
        *self * Self::exp(&(alpha * (self.inverse() * *other).log()))
    }

    /// [`SE3::interpolate`] for input from outside: refuses a non-finite `alpha` and one whose
    /// scaled twist α·log(T₁⁻¹T₂) the exponential map cannot represent ([`check_twist`]);
    /// α = 1e300 returned a NaN pose.
    ///
    /// # Errors
    /// [`GeolocError::InvalidInput`] named "alpha".
    pub fn checked_interpolate(&self, other: &Self, alpha: f64) -> Result<Self> {
        if !alpha.is_finite() {
            return Err(GeolocError::invalid("alpha", format!("{alpha} is not finite")));
        }
        let relative = (self.inverse() * *other).log();
        check_twist(&relative).map_err(|_| {
            GeolocError::invalid("T1, T2", "T1⁻¹T2 is beyond the exponential map's finite range".to_string())
        })?;
        let xi = alpha * relative;
        check_twist(&xi).map_err(|e| match e {
            GeolocError::InvalidInput { reason, .. } => GeolocError::invalid("alpha", reason),
            _ => GeolocError::invalid("alpha", format!("{alpha:e} scales the twist beyond the finite range")),
        })?;
        Ok(*self * Self::exp(&xi))
    }
}

impl std::ops::Mul for SE3 {
    type Output = SE3;
    /// Composition T₁T₂ = (R₁R₂, R₁t₂ + t₁).
    #[inline]
    fn mul(self, rhs: SE3) -> SE3 {
        SE3 { rotation: self.rotation * rhs.rotation, translation: self.rotation * rhs.translation + self.translation }
    }
}

impl std::ops::Mul<Vector3<f64>> for SE3 {
    type Output = Vector3<f64>;
    /// Transforms a point: T p = R p + t (e.g. p_world = world_from_cam * p_cam).
    #[inline]
    fn mul(self, p: Vector3<f64>) -> Vector3<f64> {
        self.rotation * p + self.translation
    }
}

/// Barfoot's Q_l(ξ) block (eq. 7.86), the upper-right block of 𝒥_l(ξ):
/// Q = ½ρ^ + C (φ^ρ^ + ρ^φ^ + φ^ρ^φ^) + D (φ^φ^ρ^ + ρ^φ^φ^ − 3φ^ρ^φ^)
///       + E (φ^ρ^φ^φ^ + φ^φ^ρ^φ^),
/// C = (θ − sin θ)/θ³, D = (θ² + 2cos θ − 2)/(2θ⁴), E = (2θ − 3 sin θ + θ cos θ)/(2θ⁵).
pub fn q_block(xi: &Twist) -> Matrix3<f64> {
    let p = so3::hat(&phi(xi));
    let r = so3::hat(&rho(xi));
    let theta = phi(xi).norm();
    let pr = p * r;
    let rp = r * p;
    let prp = pr * p;
    let pp = p * p;
    0.5 * r
        + series::t_minus_sin_over_t3(theta) * (pr + rp + prp)
        + series::q_second(theta) * (pp * r + rp * p - 3.0 * prp)
        + series::q_third(theta) * (prp * p + p * prp)
}

/// 𝒥_l(ξ) = [[J_l(φ), Q_l(ξ)], [0, J_l(φ)]].
pub fn left_jacobian(xi: &Twist) -> Matrix6<f64> {
    let j = so3::left_jacobian(&phi(xi));
    let mut m = Matrix6::zeros();
    m.fixed_view_mut::<3, 3>(0, 0).copy_from(&j);
    m.fixed_view_mut::<3, 3>(3, 3).copy_from(&j);
    m.fixed_view_mut::<3, 3>(0, 3).copy_from(&q_block(xi));
    m
}

/// 𝒥_r(ξ) = 𝒥_l(−ξ).
pub fn right_jacobian(xi: &Twist) -> Matrix6<f64> {
    left_jacobian(&-xi)
}

/// 𝒥_l⁻¹(ξ) = [[J_l⁻¹, −J_l⁻¹ Q_l J_l⁻¹], [0, J_l⁻¹]] (closed form; no matrix inversion).
pub fn left_jacobian_inverse(xi: &Twist) -> Matrix6<f64> {
    let j_inv = so3::left_jacobian_inverse(&phi(xi));
    let mut m = Matrix6::zeros();
    m.fixed_view_mut::<3, 3>(0, 0).copy_from(&j_inv);
    m.fixed_view_mut::<3, 3>(3, 3).copy_from(&j_inv);
    m.fixed_view_mut::<3, 3>(0, 3).copy_from(&(-j_inv * q_block(xi) * j_inv));
    m
}

/// 𝒥_r⁻¹(ξ) = 𝒥_l⁻¹(−ξ).
pub fn right_jacobian_inverse(xi: &Twist) -> Matrix6<f64> {
    left_jacobian_inverse(&-xi)
}

/// Largest deviation of a homogeneous matrix's last row from (0, 0, 0, 1) that is accepted.
const LAST_ROW_TOLERANCE: f64 = 1e-9;

fn check_last_row(m: &Matrix4<f64>) -> Result<()> {
    let deviation = (m.fixed_view::<1, 4>(3, 0) - nalgebra::RowVector4::new(0.0, 0.0, 0.0, 1.0)).abs().max();
    if deviation > LAST_ROW_TOLERANCE {
        return Err(GeolocError::NotARotation {
            name: "T".into(),
            index: None,
            what: "rigid transform",
            reason: format!("last row {:?} is not (0, 0, 0, 1)", m.fixed_view::<1, 4>(3, 0).iter().collect::<Vec<_>>()),
        });
    }
    Ok(())
}

fn relabel_rigid(e: GeolocError) -> GeolocError {
    match e {
        GeolocError::NotARotation { index, reason, .. } => GeolocError::NotARotation {
            name: "T".into(),
            index,
            what: "rigid transform",
            reason: format!("rotation block: {reason}"),
        },
        other => other,
    }
}

#[cfg(test)]
mod check_tests {
    use super::*;

    /// The quick acceptance of [`check_twist`] and [`so3::check_rotation_vector`] agrees with
    /// their detailed checks everywhere: ordinary twists, each limit and its neighbours
    /// (one ulp either side), huge, infinite and NaN entries in every position.
    #[test]
    fn quick_acceptance_agrees_with_the_detailed_checks() {
        let specials = [
            0.0,
            1.0,
            -3.0,
            1e6,
            so3::MAX_ROTATION_VECTOR_NORM,
            so3::MAX_ROTATION_VECTOR_NORM.next_up(),
            so3::MAX_ROTATION_VECTOR_NORM.next_down(),
            so3::MAX_ROTATION_VECTOR_NORM / 3f64.sqrt(),
            MAX_TRANSLATION_NORM,
            MAX_TRANSLATION_NORM.next_up(),
            MAX_TRANSLATION_NORM.next_down(),
            MAX_TRANSLATION_NORM / 3f64.sqrt(),
            1e200,
            f64::MAX,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::NAN,
        ];
        let mut checked = 0;
        for &a in &specials {
            for &b in &specials {
                for position in 0..6 {
                    let mut xi = Twist::from_element(0.5);
                    xi[position] = a;
                    xi[(position + 1) % 6] = b;
                    let (quick, detailed) = (check_twist(&xi), check_twist_in_detail(&xi));
                    assert_eq!(quick.is_ok(), detailed.is_ok(), "{xi:?}");
                    if let (Err(q), Err(d)) = (quick, detailed) {
                        assert_eq!(q.to_string(), d.to_string());
                    }
                    let phi = phi(&xi);
                    let (quick, detailed) =
                        (so3::check_rotation_vector(&phi), so3::check_rotation_vector_in_detail(&phi));
                    assert_eq!(quick.is_ok(), detailed.is_ok(), "{phi:?}");
                    checked += 1;
                }
            }
        }
        assert_eq!(checked, specials.len() * specials.len() * 6);
    }
}
