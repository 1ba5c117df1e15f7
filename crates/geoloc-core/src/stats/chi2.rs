//! The χ² distribution with k degrees of freedom: the one place for the χ² quantiles the
//! crate uses as constants, the CDF P(χ²_k ≤ x) = γ(k/2, x/2)/Γ(k/2) and its quantile
//! function ([`quantile`], bisection on the CDF).
//!
//! A squared Mahalanobis distance eᵀC⁻¹e of a k-dimensional Gaussian error with covariance C
//! is χ²_k: a 6-DoF pose error (NEES) is χ²₆, a 3-D point error χ²₃, a 2-D pixel residual χ²₂.

/// χ²₁ median: median(z²) of a standard normal z (the robust scale of a squared Gaussian).
pub const CHI2_1_MEDIAN: f64 = 0.454_936_423_119_572_8;
/// χ²₃ median: median(‖e‖²/σ²) of a 3-D isotropic Gaussian.
pub const CHI2_3_MEDIAN: f64 = 2.365_973_884_375_61;
/// √χ²₂(0.9999) = √(−2 ln 10⁻⁴): a correct 2-D residual exceeds this many σ with
/// probability 10⁻⁴. (The exact value is 4.291 932 052 578 694 5; this one, 7·10⁻¹⁴ larger,
/// is the value PnP's gate has always used, kept so its inlier sets stay bit-identical.)
pub const CHI2_2_9999_SQRT: f64 = 4.291_932_052_578_985;
/// χ²₃(0.95): the 95 % quantile of a 3-D point's NEES.
pub const CHI2_3_95: f64 = 7.814_727_903_251_178;
/// χ²₃(0.999): a 3-D point error beyond it is significant at 10⁻³.
pub const CHI2_3_999: f64 = 16.266_236_196_238_13;
/// χ²₆(0.95): the 95 % quantile of a 6-DoF pose's NEES.
pub const CHI2_6_95: f64 = 12.591_587_243_743_977;
/// χ²₆(0.999): a 6-DoF correction beyond it is significant at 10⁻³.
pub const CHI2_6_999: f64 = 22.457_744_484_825_32;
/// χ²₁₉(0.999) (a goodness-of-fit test over 20 cells).
pub const CHI2_19_999: f64 = 43.820_195_964_517_53;

/// Bisection steps of [`quantile`] on [0, [`QUANTILE_UPPER`]] (far past f64 resolution).
const QUANTILE_STEPS: usize = 200;
/// Upper end of the bisection of [`quantile`].
const QUANTILE_UPPER: f64 = 1e4;

/// P(χ²_k ≤ x), k ≥ 1. Even k: the closed form 1 − e^{−x/2} Σ_{i<k/2} (x/2)^i / i!
/// (k = 6: 1 − e^{−x/2}(1 + x/2 + x²/8)); odd k: the series of the regularized lower
/// incomplete gamma function γ(a, y)/Γ(a) = e^{−y} y^a Σ_n yⁿ / Γ(a + n + 1), a = k/2,
/// y = x/2. 0 for x ≤ 0.
pub fn cdf(dof: usize, x: f64) -> f64 {
    if x.is_nan() {
        return f64::NAN;
    }
    if x <= 0.0 {
        return 0.0;
    }
    if dof == 0 || x == f64::INFINITY {
        return 1.0;
    }
    if dof.is_multiple_of(2) {
        let (h, mut term, mut sum) = (x / 2.0, 1.0, 1.0);
        for i in 1..dof / 2 {
            term = term * h / i as f64;
            sum += term;
        }
        return 1.0 - (-h).exp() * sum;
    }
    let (a, y) = (dof as f64 / 2.0, x / 2.0);
    if x > dof as f64 + 40.0 * (2.0 * dof as f64).sqrt() + 100.0 {
        return 1.0; // beyond the mean by 40 standard deviations and more: 1 − P < 1e-30
    }
    // ln Γ(a + 1) for half-integer a: Γ(3/2) = √π/2, Γ(b + 1) = b Γ(b)
    let mut ln_gamma = (std::f64::consts::PI.sqrt() / 2.0).ln();
    let mut b = 1.5;
    while b < a + 0.75 {
        ln_gamma += b.ln();
        b += 1.0;
    }
    // the prefactor first, so the terms (which sum to P ≤ 1) cannot overflow
    let mut term = (-y + a * y.ln() - ln_gamma).exp();
    let (mut sum, mut n) = (term, 1.0);
    while n <= y || term > 1e-17 * sum {
        term *= y / (a + n);
        sum += term;
        n += 1.0;
    }
    sum.min(1.0)
}

/// The p-quantile of χ²_k: x with P(χ²_k ≤ x) = p, by 200 bisection steps of [`cdf`] on
/// [0, 10⁴] (to the last bit; the quantile of p ≥ P(χ²_k ≤ 10⁴) is 10⁴).
pub fn quantile(dof: usize, p: f64) -> f64 {
    let (mut lo, mut hi) = (0.0_f64, QUANTILE_UPPER);
    for _ in 0..QUANTILE_STEPS {
        let mid = 0.5 * (lo + hi);
        if cdf(dof, mid) < p { lo = mid } else { hi = mid }
    }
    0.5 * (lo + hi)
}

/// The χ²₆ quantile with the two-sided probability of ±`sigma` of a 1-D Gaussian,
/// erf(σ/√2) (3σ ↔ 99.73 % ↔ 20.06): the gates of the fusion and the localizer.
pub fn chi2_6_quantile_for_sigma(sigma: f64) -> f64 {
    quantile(6, erf(sigma / std::f64::consts::SQRT_2))
}

/// The approximate 99 % quantile of χ²_k by the Wilson–Hilferty cube-root normal
/// approximation, k (1 − c + z √c)³ with c = 2/(9k) and z = Φ⁻¹(0.99) (within 1 % of
/// [`quantile`] for k ≥ 3). The motion model's model-mismatch test uses it (its dof grow with
/// the history); kept rather than [`quantile`] so that test's threshold is unchanged.
pub fn quantile_99_wilson_hilferty(dof: usize) -> f64 {
    let k = dof as f64;
    let z = 2.326_347_874_040_841; // Φ⁻¹(0.99)
    let c = 2.0 / (9.0 * k);
    k * (1.0 - c + z * c.sqrt()).powi(3)
}

/// erf(x) = 2/√π ∫₀ˣ e^{−t²} dt by composite Simpson with 2000 panels (error far below 1e-10
/// for the gate widths in use; std has no erf).
pub fn erf(x: f64) -> f64 {
    let n = 2000;
    let h = x / n as f64;
    let f = |t: f64| (-t * t).exp();
    let mut sum = f(0.0) + f(x);
    for i in 1..n {
        let t = i as f64 * h;
        sum += if i % 2 == 1 { 4.0 * f(t) } else { 2.0 * f(t) };
    }
    sum * h / 3.0 * 2.0 / std::f64::consts::PI.sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// ∫₀ˣ of the χ²_k density x^{k/2−1} e^{−x/2} / (2^{k/2} Γ(k/2)) by composite Simpson in
    /// u = √x (x = u², dx = 2u du: the integrand 2u·f(u²) has no singularity at 0 for k = 1),
    /// with Γ(k/2) from its recursion — independent of [`cdf`]'s series and closed forms.
    fn integrated_cdf(dof: usize, x: f64) -> f64 {
        let a = dof as f64 / 2.0;
        let mut gamma = if dof.is_multiple_of(2) { 1.0 } else { std::f64::consts::PI.sqrt() };
        let mut b = if dof.is_multiple_of(2) { 1.0 } else { 0.5 };
        while b < a - 0.25 {
            gamma *= b;
            b += 1.0;
        }
        // 2u f(u²) = 2 u^{k−1} e^{−u²/2} / (2^{k/2} Γ(k/2)), finite at u = 0 (0⁰ = 1 for k = 1)
        let g = |u: f64| 2.0 * u.powf(2.0 * a - 1.0) * (-u * u / 2.0).exp() / (2f64.powf(a) * gamma);
        let (n, top) = (20_000, x.sqrt());
        let h = top / n as f64;
        let mut sum = g(0.0) + g(top);
        for i in 1..n {
            sum += if i % 2 == 1 { 4.0 } else { 2.0 } * g(i as f64 * h);
        }
        sum * h / 3.0
    }

    /// The constants: closed forms where they exist (χ²₂ quantile −2 ln(1 − p); the χ²₆ CDF
    /// in closed form at the constant), the density integrated numerically otherwise, and
    /// the table values of Abramowitz & Stegun, Table 26.8 (χ²₃(0.95) = 7.8147, χ²₃(0.999) = 16.2662,
    /// χ²₆(0.95) = 12.5916, χ²₆(0.999) = 22.4577, χ²₁₉(0.999) = 43.8202).
    #[test]
    fn constants_match_independent_references() {
        // the closed form, to the 7e-14 the constant has always carried (see its doc)
        assert!((CHI2_2_9999_SQRT - (-2.0 * 1e-4_f64.ln()).sqrt()).abs() < 1e-13 * CHI2_2_9999_SQRT);
        let closed6 = |x: f64| 1.0 - (-x / 2.0).exp() * (1.0 + x / 2.0 + x * x / 8.0);
        assert!((closed6(CHI2_6_95) - 0.95).abs() < 1e-15);
        assert!((closed6(CHI2_6_999) - 0.999).abs() < 1e-15);
        for (dof, x, p, table) in [
            (1, CHI2_1_MEDIAN, 0.5, 0.4549),
            (3, CHI2_3_MEDIAN, 0.5, 2.3660),
            (3, CHI2_3_95, 0.95, 7.8147),
            (3, CHI2_3_999, 0.999, 16.2662),
            (6, CHI2_6_95, 0.95, 12.5916),
            (6, CHI2_6_999, 0.999, 22.4577),
            (19, CHI2_19_999, 0.999, 43.8202),
        ] {
            assert!((integrated_cdf(dof, x) - p).abs() < 1e-9, "k = {dof}: {}", integrated_cdf(dof, x));
            assert!((x - table).abs() < 5e-5, "k = {dof}: {x} vs the table's {table}");
        }
    }

    /// The CDF against the integrated density for odd and even k; the quantile inverts it,
    /// and for k = 2 equals the closed form −2 ln(1 − p).
    #[test]
    fn cdf_and_quantile_match_independent_references() {
        for dof in [1, 2, 3, 4, 5, 6, 7, 12, 19, 30] {
            for x in [0.1, 1.0, 3.5, 10.0, 25.0, 60.0] {
                let (c, want) = (cdf(dof, x), integrated_cdf(dof, x));
                assert!((c - want).abs() < 1e-9, "k = {dof}, x = {x}: {c} vs {want}");
            }
            for p in [0.01, 0.5, 0.95, 0.999] {
                let q = quantile(dof, p);
                assert!((cdf(dof, q) - p).abs() < 1e-13, "k = {dof}, p = {p}");
            }
        }
        for p in [0.05_f64, 0.5, 0.95, 0.9999] {
            let want = -2.0 * (1.0 - p).ln();
            assert!((quantile(2, p) - want).abs() < 1e-12 * want, "p = {p}");
        }
        assert_eq!(
            [cdf(6, 0.0), cdf(6, f64::INFINITY), cdf(3, -1.0)].map(f64::to_bits),
            [0.0, 1.0, 0.0].map(f64::to_bits)
        );
    }

    /// The gate quantile: 3σ two-sided = 0.99730 → 20.062, 1.96σ → 0.95 → χ²₆(0.95); erf
    /// against its closed-form values.
    #[test]
    fn sigma_gates_and_erf() {
        assert!((chi2_6_quantile_for_sigma(3.0) - 20.062).abs() < 2e-3);
        assert!((chi2_6_quantile_for_sigma(1.959_963_984_540_054) - CHI2_6_95).abs() < 1e-8);
        assert!((erf(1.0) - 0.842_700_792_949_714_9).abs() < 1e-12);
        assert!((erf(2.0) - 0.995_322_265_018_952_7).abs() < 1e-12);
    }

    /// The gate quantile is bit for bit the bisection the fusion gate has always run: on
    /// 1 − e^{−x/2}(1 + x/2 + x²/8) over [0, 10⁴], 200 steps.
    #[test]
    fn gate_quantile_is_the_closed_form_bisection_bit_for_bit() {
        let closed = |x: f64| 1.0 - (-x / 2.0).exp() * (1.0 + x / 2.0 + x * x / 8.0);
        for sigma in [0.5, 1.0, 1.96, 2.5, 3.0, 3.5, 5.0] {
            let p = erf(sigma / std::f64::consts::SQRT_2);
            let (mut lo, mut hi) = (0.0_f64, 1e4_f64);
            for _ in 0..200 {
                let mid = 0.5 * (lo + hi);
                if closed(mid) < p { lo = mid } else { hi = mid }
            }
            assert_eq!(chi2_6_quantile_for_sigma(sigma).to_bits(), (0.5 * (lo + hi)).to_bits(), "σ = {sigma}");
        }
        for x in [1e-50, 1e-3, 0.7, 12.5, 300.0, 9999.0] {
            assert_eq!(cdf(6, x).to_bits(), closed(x).to_bits(), "x = {x}");
        }
    }

    /// Wilson–Hilferty against the exact 99 % quantile (and the tabulated 16.812, 26.217,
    /// 50.892 for k = 6, 12, 30): within 1 % for the motion model's dof.
    #[test]
    fn wilson_hilferty_is_within_one_percent() {
        for (dof, table) in [(6, 16.812), (12, 26.217), (30, 50.892)] {
            assert!((quantile(dof, 0.99) - table).abs() < 1e-3, "k = {dof}");
        }
        for dof in (6..=60).step_by(6) {
            let (approx, exact) = (quantile_99_wilson_hilferty(dof), quantile(dof, 0.99));
            assert!((approx - exact).abs() < 0.01 * exact, "k = {dof}: {approx} vs {exact}");
        }
    }
}
