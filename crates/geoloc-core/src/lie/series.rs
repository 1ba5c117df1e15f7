//! The scalar coefficients of the SO(3)/SE(3) closed forms, each with a Taylor branch.
//!
//! Every closed form in Barfoot (2017, §7.1.3–7.1.5) is a polynomial in φ^ whose
//! coefficients are ratios like (θ − sin θ)/θ³ that lose all their digits to cancellation as
//! θ = ‖φ‖ → 0. Below [`TAYLOR_THRESHOLD_RAD`] each coefficient is evaluated from its
//! Maclaurin series in θ² (six terms, Horner form); the truncation error there is below
//! 1e-17 relative, while the closed forms above the threshold lose at most ~1e-12.

/// Below this angle (radians) the coefficients use their Taylor series.
///
/// At θ = 0.2 the six-term series truncates at θ¹² ≈ 4e-9 times a coefficient ≤ 1e-9, and
/// the worst closed form above it, (2θ − 3 sin θ + θ cos θ)/(2θ⁵), carries a cancellation
/// error of about 60·ε/θ⁴ ≈ 4e-12 relative.
pub const TAYLOR_THRESHOLD_RAD: f64 = 0.2;

/// Maclaurin coefficients in powers of θ² (exact rationals from the sin/cos series).
const SERIES_SIN_OVER_T: [f64; 6] = [1.0, -1.0 / 6.0, 1.0 / 120.0, -1.0 / 5040.0, 1.0 / 362_880.0, -1.0 / 39_916_800.0];
const SERIES_ONE_MINUS_COS_OVER_T2: [f64; 6] =
    [0.5, -1.0 / 24.0, 1.0 / 720.0, -1.0 / 40320.0, 1.0 / 3_628_800.0, -1.0 / 479_001_600.0];
const SERIES_T_MINUS_SIN_OVER_T3: [f64; 6] =
    [1.0 / 6.0, -1.0 / 120.0, 1.0 / 5040.0, -1.0 / 362_880.0, 1.0 / 39_916_800.0, -1.0 / 6_227_020_800.0];
const SERIES_Q_SECOND: [f64; 6] =
    [1.0 / 24.0, -1.0 / 720.0, 1.0 / 40320.0, -1.0 / 3_628_800.0, 1.0 / 479_001_600.0, -1.0 / 87_178_291_200.0];
const SERIES_Q_THIRD: [f64; 6] =
    [1.0 / 120.0, -1.0 / 2520.0, 1.0 / 120_960.0, -1.0 / 9_979_200.0, 1.0 / 1_245_404_160.0, -1.0 / 217_945_728_000.0];
/// 1/θ² − (1 + cos θ)/(2θ sin θ) = Σ B₂ₖ-related terms: 1/12 + θ²/720 + θ⁴/30240 + …
const SERIES_JINV: [f64; 6] =
    [1.0 / 12.0, 1.0 / 720.0, 1.0 / 30240.0, 1.0 / 1_209_600.0, 1.0 / 47_900_160.0, 691.0 / 1_307_674_368_000.0];

#[inline]
fn horner(coefficients: &[f64; 6], t2: f64) -> f64 {
    coefficients.iter().rev().fold(0.0, |acc, c| acc * t2 + c)
}

/// (θ − sin θ)/θ³.
#[inline]
pub fn t_minus_sin_over_t3(theta: f64) -> f64 {
    if theta < TAYLOR_THRESHOLD_RAD {
        horner(&SERIES_T_MINUS_SIN_OVER_T3, theta * theta)
    } else {
        (theta - theta.sin()) / (theta * theta * theta)
    }
}

/// (θ² + 2 cos θ − 2)/(2θ⁴): the second coefficient of Barfoot's Q block (eq. 7.86).
#[inline]
pub fn q_second(theta: f64) -> f64 {
    if theta < TAYLOR_THRESHOLD_RAD {
        horner(&SERIES_Q_SECOND, theta * theta)
    } else {
        let t2 = theta * theta;
        (t2 + 2.0 * theta.cos() - 2.0) / (2.0 * t2 * t2)
    }
}

/// (2θ − 3 sin θ + θ cos θ)/(2θ⁵): the third coefficient of Barfoot's Q block (eq. 7.86).
#[inline]
pub fn q_third(theta: f64) -> f64 {
    if theta < TAYLOR_THRESHOLD_RAD {
        horner(&SERIES_Q_THIRD, theta * theta)
    } else {
        let t2 = theta * theta;
        (2.0 * theta - 3.0 * theta.sin() + theta * theta.cos()) / (2.0 * t2 * t2 * theta)
    }
}

/// 1/θ² − (1 + cos θ)/(2θ sin θ) = 1/θ² − 1/(2θ tan(θ/2)): the φ^² coefficient of J⁻¹.
///
/// The tan form stays finite at θ = π (where sin θ = 0); it is singular at θ = 2π, where the
/// Jacobian itself is singular.
#[inline]
pub fn jacobian_inverse_second(theta: f64) -> f64 {
    if theta < TAYLOR_THRESHOLD_RAD {
        horner(&SERIES_JINV, theta * theta)
    } else {
        1.0 / (theta * theta) - 1.0 / (2.0 * theta * (0.5 * theta).tan())
    }
}

/// The coefficients of exp and J_l that share one sin/cos evaluation:
/// cos θ, A = sin θ/θ, B = (1 − cos θ)/θ², C = (θ − sin θ)/θ³.
#[derive(Clone, Copy, Debug)]
pub struct ExpCoefficients {
    /// cos θ.
    pub cos: f64,
    /// sin θ / θ.
    pub a: f64,
    /// (1 − cos θ)/θ².
    pub b: f64,
    /// (θ − sin θ)/θ³.
    pub c: f64,
}

impl ExpCoefficients {
    /// All four from one `sin_cos` (above the threshold; there the cancellation in B and C
    /// costs at most ~2e-14 relative) or from their series (below; cos θ = 1 − θ²B).
    #[inline]
    pub fn new(theta: f64) -> Self {
        if theta < TAYLOR_THRESHOLD_RAD {
            let t2 = theta * theta;
            let b = horner(&SERIES_ONE_MINUS_COS_OVER_T2, t2);
            Self { cos: 1.0 - t2 * b, a: horner(&SERIES_SIN_OVER_T, t2), b, c: horner(&SERIES_T_MINUS_SIN_OVER_T3, t2) }
        } else {
            let (sin, cos) = theta.sin_cos();
            let t2 = theta * theta;
            Self { cos, a: sin / theta, b: (1.0 - cos) / t2, c: (theta - sin) / (t2 * theta) }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each coefficient on both sides of the threshold agrees with its closed form evaluated
    /// in a regime where the closed form is accurate, and the two branches meet.
    #[test]
    fn branches_meet_at_threshold() {
        let below = TAYLOR_THRESHOLD_RAD * (1.0 - 1e-12);
        let above = TAYLOR_THRESHOLD_RAD * (1.0 + 1e-12);
        for f in [
            |t| ExpCoefficients::new(t).cos,
            |t| ExpCoefficients::new(t).a,
            |t| ExpCoefficients::new(t).b,
            |t| ExpCoefficients::new(t).c,
            t_minus_sin_over_t3,
            q_second,
            q_third,
            jacobian_inverse_second,
        ] {
            let (a, b) = (f(below), f(above));
            assert!((a - b).abs() <= 1e-10 * a.abs(), "{a} vs {b}");
        }
    }

    /// Against cancellation-free forms: A = sin θ/θ, B = ½(sin(θ/2)/(θ/2))², and C from
    /// its own Taylor-or-closed-form function.
    #[test]
    fn exp_coefficients_match_independent_forms() {
        for &t in &[1e-9, 0.1, 0.199_999, 0.2, 0.7, 2.0, std::f64::consts::PI - 1e-6] {
            let k = ExpCoefficients::new(t);
            let half = 0.5 * t;
            let b = 0.5 * (half.sin() / half).powi(2);
            assert!((k.cos - t.cos()).abs() < 1e-15);
            assert!((k.a - t.sin() / t).abs() < 1e-15);
            assert!((k.b - b).abs() < 2e-14 * b, "{t}: {} vs {b}", k.b);
            assert!((k.c - t_minus_sin_over_t3(t)).abs() < 5e-14 * k.c);
        }
        let k = ExpCoefficients::new(0.0);
        assert!((k.cos - 1.0).abs() < f64::EPSILON && (k.a - 1.0).abs() < f64::EPSILON);
        assert!((k.b - 0.5).abs() < f64::EPSILON);
    }

    #[test]
    fn limits_at_zero() {
        assert!((t_minus_sin_over_t3(0.0) - 1.0 / 6.0).abs() < f64::EPSILON);
        assert!((q_second(0.0) - 1.0 / 24.0).abs() < f64::EPSILON);
        assert!((q_third(0.0) - 1.0 / 120.0).abs() < f64::EPSILON);
        assert!((jacobian_inverse_second(0.0) - 1.0 / 12.0).abs() < f64::EPSILON);
    }

    /// Against the closed forms at moderate angles, where they are accurate to ~1e-13.
    #[test]
    fn series_match_closed_forms() {
        for &t in &[0.15_f64, 0.19] {
            let t2 = t * t;
            let cases = [
                (horner(&SERIES_SIN_OVER_T, t2), t.sin() / t),
                (horner(&SERIES_ONE_MINUS_COS_OVER_T2, t2), (1.0 - t.cos()) / t2),
                (horner(&SERIES_T_MINUS_SIN_OVER_T3, t2), (t - t.sin()) / (t2 * t)),
                (horner(&SERIES_Q_SECOND, t2), (t2 + 2.0 * t.cos() - 2.0) / (2.0 * t2 * t2)),
                (horner(&SERIES_Q_THIRD, t2), (2.0 * t - 3.0 * t.sin() + t * t.cos()) / (2.0 * t2 * t2 * t)),
                (horner(&SERIES_JINV, t2), 1.0 / t2 - (1.0 + t.cos()) / (2.0 * t * t.sin())),
            ];
            for (series, closed) in cases {
                assert!((series - closed).abs() <= 1e-10 * closed.abs(), "{series} vs {closed}");
            }
        }
    }
}
