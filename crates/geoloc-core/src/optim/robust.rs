//! Robust kernels ρ(s) of the *squared* normalized residual s = ‖r‖²/σ² (or rᵀS⁻¹r), as
//! PoseLib and Ceres define them, with the IRLS weight w(s) = ρ'(s):
//!
//! | kernel | ρ(s) | w(s) |
//! |---|---|---|
//! | none   | s | 1 |
//! | Huber  | s for s ≤ k², 2k√s − k² beyond | 1, then k/√s |
//! | Cauchy | k² ln(1 + s/k²) | 1/(1 + s/k²) |
//!
//! The width k is in units of σ (so with σ = 1 px, Huber k = 1 is the paper's 1 px kernel).

use crate::error::{GeolocError, Result};

/// A robust loss for iteratively reweighted least squares.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum RobustLoss {
    /// Plain least squares.
    None,
    /// Huber with width k (quadratic inside, linear outside).
    Huber {
        /// Width k in units of σ.
        width: f64,
    },
    /// Cauchy (Lorentzian) with width k.
    Cauchy {
        /// Width k in units of σ.
        width: f64,
    },
}

impl RobustLoss {
    /// A loss by name ("none", "huber", "cauchy") and width.
    ///
    /// # Errors
    /// Unknown name, or a width that is not finite and positive (named `name_arg`).
    pub fn from_name(kind: &str, width: f64, name_arg: &str) -> Result<Self> {
        let checked = |w: f64| {
            if w.is_finite() && w > 0.0 {
                Ok(w)
            } else {
                Err(GeolocError::invalid(name_arg, format!("expected a finite number > 0 (the kernel width), got {w}")))
            }
        };
        match kind {
            "none" => Ok(Self::None),
            "huber" => Ok(Self::Huber { width: checked(width)? }),
            "cauchy" => Ok(Self::Cauchy { width: checked(width)? }),
            other => Err(GeolocError::invalid(
                "loss",
                format!("expected one of \"huber\", \"cauchy\", \"none\", got {other:?}"),
            )),
        }
    }

    /// ρ(s) for the squared normalized residual s ≥ 0.
    #[inline]
    pub fn cost(&self, s: f64) -> f64 {
        match *self {
            Self::None => s,
            Self::Huber { width: k } => {
                if s <= k * k {
                    s
                } else {
                    2.0 * k * s.sqrt() - k * k
                }
            }
            Self::Cauchy { width: k } => k * k * (s / (k * k)).ln_1p(),
        }
    }

    /// The IRLS weight w(s) = ρ'(s) ∈ (0, 1].
    #[inline]
    pub fn weight(&self, s: f64) -> f64 {
        match *self {
            Self::None => 1.0,
            Self::Huber { width: k } => {
                if s <= k * k {
                    1.0
                } else {
                    k / s.sqrt()
                }
            }
            Self::Cauchy { width: k } => 1.0 / (1.0 + s / (k * k)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// w = dρ/ds, checked by central differences away from the Huber kink.
    #[test]
    fn weight_is_the_derivative_of_the_cost() {
        let h = 1e-6;
        for loss in [RobustLoss::None, RobustLoss::Huber { width: 1.3 }, RobustLoss::Cauchy { width: 0.7 }] {
            for &s in &[0.01, 0.5, 1.0, 2.5, 10.0, 400.0] {
                if (s - 1.69_f64).abs() < 1e-3 {
                    continue;
                }
                let numeric = (loss.cost(s + h) - loss.cost(s - h)) / (2.0 * h);
                assert!((numeric - loss.weight(s)).abs() < 1e-7, "{loss:?} at {s}");
            }
        }
    }

    #[test]
    fn huber_known_values_at_the_kink() {
        let huber = RobustLoss::Huber { width: 2.0 };
        // continuous in value and slope at s = k² = 4
        assert!((huber.cost(4.0 - 1e-12) - huber.cost(4.0 + 1e-12)).abs() < 1e-9);
        assert!((huber.weight(4.0 - 1e-9) - 1.0).abs() < 1e-12);
        assert!((huber.weight(4.0 + 1e-9) - 1.0).abs() < 1e-9);
        assert!((huber.cost(16.0) - (2.0 * 2.0 * 4.0 - 4.0)).abs() < 1e-12);
        assert!((huber.weight(16.0) - 0.5).abs() < 1e-15);
        assert!((RobustLoss::Cauchy { width: 1.0 }.weight(1.0) - 0.5).abs() < 1e-15);
    }

    #[test]
    fn names_and_bad_widths() {
        assert_eq!(RobustLoss::from_name("huber", 1.0, "huber").ok(), Some(RobustLoss::Huber { width: 1.0 }));
        assert!(RobustLoss::from_name("huber", 0.0, "huber").is_err());
        assert!(RobustLoss::from_name("huber", f64::NAN, "huber").is_err());
        assert!(RobustLoss::from_name("tukey", 1.0, "huber").is_err());
    }
}
