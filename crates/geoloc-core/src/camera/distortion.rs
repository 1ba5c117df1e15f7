//! Lens distortion: OpenCV's radial–tangential (Brown–Conrady) model, the five coefficients
//! `(k1, k2, p1, p2, k3)` in OpenCV's order.
//!
//! On normalized image coordinates x = (x, y) = (p_x/p_z, p_y/p_z), r² = x² + y²:
//!
//!   s(r²) = 1 + k1 r² + k2 r⁴ + k3 r⁶
//!   x_d = x s + 2 p1 x y + p2 (r² + 2x²)
//!   y_d = y s + p1 (r² + 2y²) + 2 p2 x y
//!
//! and the distorted pixel is (f_x x_d + c_x, f_y y_d + c_y) (Brown 1966; OpenCV's
//! `projectPoints` with `distCoeffs = (k1, k2, p1, p2, k3)`). The rest of the core works on
//! *undistorted* pixels; this model serves the self-calibration of the intrinsics
//! ([`crate::selfcal`]) and the correction the map applies to keypoints with it.

use nalgebra::{Matrix2, Matrix2x5, Vector2};

use crate::error::{GeolocError, Result};

/// Newton iterations of [`Distortion::undistort`] at most.
const UNDISTORT_MAX_ITERATIONS: usize = 50;
/// [`Distortion::undistort`] stops when the distorted point is matched to this (normalized units).
const UNDISTORT_TOLERANCE: f64 = 1e-14;

/// The radial–tangential distortion coefficients (see the module doc); all zero is none.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Distortion {
    /// Radial, r².
    pub k1: f64,
    /// Radial, r⁴.
    pub k2: f64,
    /// Tangential (decentering), first.
    pub p1: f64,
    /// Tangential (decentering), second.
    pub p2: f64,
    /// Radial, r⁶.
    pub k3: f64,
}

impl Distortion {
    /// From OpenCV's coefficient vector `(k1, k2, p1, p2[, k3])`.
    ///
    /// # Errors
    /// `InvalidInput` naming `distortion` for another length or a non-finite value.
    pub fn from_opencv(coefficients: &[f64]) -> Result<Self> {
        if !(coefficients.len() == 4 || coefficients.len() == 5) {
            return Err(GeolocError::invalid(
                "distortion",
                format!("expected 4 or 5 coefficients (k1, k2, p1, p2[, k3]), got {}", coefficients.len()),
            ));
        }
        if let Some(i) = coefficients.iter().position(|c| !c.is_finite()) {
            return Err(GeolocError::invalid("distortion", format!("coefficient {i} is not finite")));
        }
        let k3 = coefficients.get(4).copied().unwrap_or(0.0);
        Ok(Self { k1: coefficients[0], k2: coefficients[1], p1: coefficients[2], p2: coefficients[3], k3 })
    }

    /// OpenCV's coefficient vector `(k1, k2, p1, p2, k3)`.
    pub fn to_opencv(&self) -> [f64; 5] {
        [self.k1, self.k2, self.p1, self.p2, self.k3]
    }

    /// Whether every coefficient is zero (the identity).
    pub fn is_none(&self) -> bool {
        self.to_opencv().iter().all(|c| *c == 0.0)
    }

    /// The distorted normalized point x_d of the undistorted normalized point `x`.
    #[inline]
    pub fn distort(&self, x: &Vector2<f64>) -> Vector2<f64> {
        let (u, v) = (x.x, x.y);
        let r2 = u * u + v * v;
        let s = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        Vector2::new(
            u * s + 2.0 * self.p1 * u * v + self.p2 * (r2 + 2.0 * u * u),
            v * s + self.p1 * (r2 + 2.0 * v * v) + 2.0 * self.p2 * u * v,
        )
    }

    /// ∂x_d/∂x at `x`: with q = 2k1 + 4k2 r² + 6k3 r⁴ (so ∂s/∂x = q x),
    /// [[s + q x² + 2p1 y + 6p2 x, q x y + 2p1 x + 2p2 y], [q x y + 2p1 x + 2p2 y, s + q y² + 6p1 y + 2p2 x]].
    #[inline]
    pub fn jacobian(&self, x: &Vector2<f64>) -> Matrix2<f64> {
        let (u, v) = (x.x, x.y);
        let r2 = u * u + v * v;
        let s = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        let q = 2.0 * self.k1 + r2 * (4.0 * self.k2 + 6.0 * self.k3 * r2);
        let off = q * u * v + 2.0 * self.p1 * u + 2.0 * self.p2 * v;
        Matrix2::new(
            s + q * u * u + 2.0 * self.p1 * v + 6.0 * self.p2 * u,
            off,
            off,
            s + q * v * v + 6.0 * self.p1 * v + 2.0 * self.p2 * u,
        )
    }

    /// ∂x_d/∂(k1, k2, p1, p2, k3) at `x`: columns (x r², y r²), (x r⁴, y r⁴), (2xy, r² + 2y²),
    /// (r² + 2x², 2xy), (x r⁶, y r⁶).
    #[inline]
    pub fn parameter_jacobian(x: &Vector2<f64>) -> Matrix2x5<f64> {
        let (u, v) = (x.x, x.y);
        let r2 = u * u + v * v;
        let (r4, r6) = (r2 * r2, r2 * r2 * r2);
        Matrix2x5::new(
            u * r2,
            u * r4,
            2.0 * u * v,
            r2 + 2.0 * u * u,
            u * r6,
            v * r2,
            v * r4,
            r2 + 2.0 * v * v,
            2.0 * u * v,
            v * r6,
        )
    }

    /// The undistorted normalized point x with distort(x) = `x_d`, by Newton's method from
    /// x_d; None when it does not converge (a distortion that folds over, or a point far
    /// outside the region the coefficients describe).
    pub fn undistort(&self, x_d: &Vector2<f64>) -> Option<Vector2<f64>> {
        if self.is_none() {
            return Some(*x_d);
        }
        let mut x = *x_d;
        for _ in 0..UNDISTORT_MAX_ITERATIONS {
            let residual = self.distort(&x) - x_d;
            if residual.norm() <= UNDISTORT_TOLERANCE * (1.0 + x_d.norm()) {
                return Some(x);
            }
            x -= self.jacobian(&x).try_inverse()? * residual;
            if !(x.x.is_finite() && x.y.is_finite()) {
                return None;
            }
        }
        let residual = self.distort(&x) - x_d;
        (residual.norm() <= 1e3 * UNDISTORT_TOLERANCE * (1.0 + x_d.norm())).then_some(x)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::SplitMix64;

    const FD_STEP: f64 = 1e-7;
    const JAC_TOL: f64 = 1e-6;

    fn kinect_like() -> Distortion {
        // the order of magnitude of a Kinect v1 colour camera (TUM fr1's calibration)
        Distortion { k1: 0.2624, k2: -0.9531, p1: -0.0054, p2: 0.0026, k3: 1.1633 }
    }

    #[test]
    fn known_values_of_the_opencv_formula() {
        let d = Distortion { k1: 0.1, k2: 0.01, p1: 0.001, p2: 0.002, k3: 0.0005 };
        let x = Vector2::new(0.3, -0.2);
        // r² = 0.13; s = 1 + 0.013 + 0.000169 + 0.0000010985 = 1.0131700985
        let s = 1.013_170_098_5;
        let xd = 0.3 * s + 2.0 * 0.001 * 0.3 * -0.2 + 0.002 * (0.13 + 2.0 * 0.09);
        let yd = -0.2 * s + 0.001 * (0.13 + 2.0 * 0.04) + 2.0 * 0.002 * 0.3 * -0.2;
        assert!((d.distort(&x) - Vector2::new(xd, yd)).norm() < 1e-15);
        assert_eq!(Distortion::default().distort(&x), x);
        assert_eq!(Distortion::from_opencv(&d.to_opencv()).expect("valid"), d);
        assert!(Distortion::from_opencv(&[0.1, 0.01, 0.001, 0.002]).expect("valid").k3.abs() < f64::MIN_POSITIVE);
    }

    #[test]
    fn jacobians_match_central_differences() {
        let mut rng = SplitMix64::new(11);
        for d in [kinect_like(), Distortion { k1: -0.06, k2: 0.01, p1: 0.01, p2: -0.005, k3: 0.0 }] {
            for _ in 0..200 {
                let x = Vector2::new(rng.uniform_in(-0.6, 0.6), rng.uniform_in(-0.45, 0.45));
                let mut numeric = Matrix2::zeros();
                for i in 0..2 {
                    let mut e = Vector2::zeros();
                    e[i] = FD_STEP;
                    numeric.set_column(i, &((d.distort(&(x + e)) - d.distort(&(x - e))) / (2.0 * FD_STEP)));
                }
                assert!((d.jacobian(&x) - numeric).abs().max() < JAC_TOL, "{x}");
                let mut numeric = Matrix2x5::zeros();
                for i in 0..5 {
                    let bump = |h: f64| {
                        let mut c = d.to_opencv();
                        c[i] += h;
                        Distortion::from_opencv(&c).expect("finite").distort(&x)
                    };
                    numeric.set_column(i, &((bump(FD_STEP) - bump(-FD_STEP)) / (2.0 * FD_STEP)));
                }
                assert!((Distortion::parameter_jacobian(&x) - numeric).abs().max() < JAC_TOL, "{x}");
            }
        }
    }

    #[test]
    fn undistort_inverts_distort_over_the_image() {
        let mut rng = SplitMix64::new(12);
        let d = kinect_like();
        for _ in 0..1000 {
            // a 640 × 480 image at f = 525: |x| ≤ 0.61, |y| ≤ 0.46
            let x = Vector2::new(rng.uniform_in(-0.61, 0.61), rng.uniform_in(-0.46, 0.46));
            let back = d.undistort(&d.distort(&x)).expect("converges inside the image");
            assert!((back - x).norm() < 1e-12, "{x} -> {back}");
        }
        assert_eq!(Distortion::default().undistort(&Vector2::new(0.5, 0.5)), Some(Vector2::new(0.5, 0.5)));
    }

    #[test]
    fn bad_coefficients_are_named() {
        for bad in [&[0.1, 0.2, 0.3][..], &[0.0; 6][..], &[0.0, f64::NAN, 0.0, 0.0][..]] {
            assert!(
                matches!(Distortion::from_opencv(bad), Err(GeolocError::InvalidInput { name, .. }) if name == "distortion")
            );
        }
    }
}
