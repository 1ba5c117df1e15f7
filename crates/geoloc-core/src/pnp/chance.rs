//! The acceptance test of a PnP pose (step 4 of the driver in [`super`]): at least
//! [`MIN_ACCEPTED_INLIERS`] inliers, and an inlier count that uniformly random pixels would
//! give with probability below [`MAX_CHANCE_PROBABILITY`] after a Bonferroni correction for
//! the hypotheses RANSAC scored:
//!
//!   P = min(1, H · P(Bin(N − 3, p̄) ≥ k − 3)),  p̄ = min(1, π r̄²/A).

use nalgebra::Vector2;

use super::{Correspondences, gate_px};

/// Fewest inliers a pose is *accepted* from: six beyond the three any 6-DoF pose fits exactly.
pub const MIN_ACCEPTED_INLIERS: usize = 9;
/// A pose is accepted only if random pixels would give its inlier count with probability
/// below this, corrected for the number of hypotheses RANSAC tried ([`chance_probability`]).
pub const MAX_CHANCE_PROBABILITY: f64 = 1e-3;

impl Correspondences<'_> {
    /// Why the inlier set cannot be told from chance, if it cannot: fewer than
    /// [`MIN_ACCEPTED_INLIERS`], or a [`chance_probability`] above [`MAX_CHANCE_PROBABILITY`].
    pub(super) fn chance_rejection(&self, subset: &[usize], ransac_iterations: usize) -> Option<String> {
        let k = subset.len();
        if k < MIN_ACCEPTED_INLIERS {
            return Some(format!("too few inliers to tell the pose from chance: {k} < {MIN_ACCEPTED_INLIERS}"));
        }
        let o = self.options;
        let gate = gate_px(o.max_residual_px, o.pixel_sigma);
        let mean_gate_sq = match self.noise.scales {
            None => gate * gate,
            Some(_) => {
                (0..self.points.len()).map(|j| gate_px(o.max_residual_px, self.noise.at(j)).powi(2)).sum::<f64>()
                    / self.points.len() as f64
            }
        };
        // The area within the gate of a projection, π·gate², gate = η_r (widened to 4.29σ):
        // exactly the inlier region for exact points. Uncertain points are gated in the
        // Mahalanobis metric of S = σ²I + J_X Σ J_Xᵀ, a wider region; measured against it,
        // well-determined poses from poorly triangulated points (label noise of 3 cm / 1°, σ
        // of the projected points ≈ 12 px) read as chance, so the test uses the pixel-noise
        // gate for them too: it is lenient for uncertain points, exact for exact ones.
        let mean_radius_sq = mean_gate_sq;
        let hypotheses = 1 + 4 * ransac_iterations;
        let p = chance_probability(self.pixels, mean_radius_sq, k, hypotheses);
        (p > MAX_CHANCE_PROBABILITY).then(|| {
            format!("the inliers cannot be told from chance: {k} of {} (chance probability {p:.2e})", self.points.len())
        })
    }
}

/// The probability that uniformly random pixels give `inliers` inliers, corrected for the
/// search: N pixels spread over their bounding box of area A, each falls within the gate
/// (mean squared radius r̄²) of its projection with probability p̄ = min(1, π r̄²/A); any
/// 6-DoF pose fits 3 correspondences exactly, so the count beyond those is binomial,
///
///   P = min(1, H · P(Bin(N − 3, p̄) ≥ k − 3)),
///
/// with H the number of pose hypotheses scored (Bonferroni: RANSAC keeps the best of H).
pub fn chance_probability(pixels: &[Vector2<f64>], mean_radius_sq: f64, inliers: usize, hypotheses: usize) -> f64 {
    let n = pixels.len();
    if n <= 3 || inliers <= 3 {
        return 1.0;
    }
    let (lo, hi) =
        pixels.iter().fold((Vector2::repeat(f64::INFINITY), Vector2::repeat(f64::NEG_INFINITY)), |(lo, hi), p| {
            (lo.inf(p), hi.sup(p))
        });
    let area = (hi.x - lo.x) * (hi.y - lo.y);
    let p = (std::f64::consts::PI * mean_radius_sq / area).min(1.0);
    let tail = binomial_tail_ln(n - 3, p, inliers - 3);
    (tail + (hypotheses.max(1) as f64).ln()).exp().min(1.0)
}

/// Terms of the binomial tail more than e⁴⁰ below its largest one are not summed.
const TAIL_CUTOFF_LN: f64 = 40.0;

/// ln P(X ≥ m) for X ~ Bin(n, p), summed in log space (exact to rounding).
fn binomial_tail_ln(n: usize, p: f64, m: usize) -> f64 {
    if m == 0 || p >= 1.0 || p.is_nan() {
        return 0.0;
    }
    if m > n || p <= 0.0 {
        return f64::NEG_INFINITY;
    }
    let (nf, mf) = (n as f64, m as f64);
    // ln C(n, m) = Σⱼ ln((n − m + j)/j)
    let ln_choose: f64 = (1..=m).map(|j| ((nf - mf + j as f64) / j as f64).ln()).sum();
    let mut term = ln_choose + mf * p.ln() + (nf - mf) * (-p).ln_1p();
    let ratio = p.ln() - (-p).ln_1p();
    let (mut max, mut terms) = (term, vec![term]);
    for i in m..n {
        let step = ((nf - i as f64) / (i as f64 + 1.0)).ln() + ratio;
        term += step;
        max = max.max(term);
        terms.push(term);
        // past the mode the terms fall geometrically: stop once they are below e⁻⁴⁰ of the
        // largest (the rest adds less than 1e-17 relative)
        if step < 0.0 && term < max - TAIL_CUTOFF_LN {
            break;
        }
    }
    max + terms.iter().map(|t| (t - max).exp()).sum::<f64>().ln()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Binomial tail against a brute-force sum of the pmf, and the chance probability of a
    /// few inliers among random pixels against the hand computation of the doc.
    #[test]
    fn binomial_tail_and_chance_probability() {
        let (n, p) = (30_usize, 0.07_f64);
        for m in [0, 1, 3, 10, 30] {
            let brute: f64 = (m..=n)
                .map(|i| {
                    let ln_choose: f64 = (1..=i).map(|j| ((n - i + j) as f64 / j as f64).ln()).sum();
                    (ln_choose + i as f64 * p.ln() + (n - i) as f64 * (1.0 - p).ln()).exp()
                })
                .sum();
            let tail = binomial_tail_ln(n, p, m).exp();
            assert!((tail - brute).abs() <= 1e-12 * brute.max(1e-300), "m = {m}: {tail} vs {brute}");
        }
        assert!(binomial_tail_ln(10, 0.5, 11).is_infinite() && binomial_tail_ln(10, 0.5, 11) < 0.0);
        // 200 pixels over 640 × 480, gate 5 px: p = 25π/307200; 6 inliers after one hypothesis
        let pixels: Vec<Vector2<f64>> = (0..200)
            .map(|i| Vector2::new(if i == 0 { 0.0 } else { 640.0 }, if i == 1 { 0.0 } else { 480.0 }))
            .collect();
        let radii = 25.0;
        let p1 = 25.0 * std::f64::consts::PI / 307_200.0;
        let expected = (binomial_tail_ln(197, p1, 3)).exp();
        assert!((chance_probability(&pixels, radii, 6, 1) - expected).abs() < 1e-12 * expected);
        assert!((chance_probability(&pixels, radii, 6, 10) - 10.0 * expected).abs() < 1e-11 * expected);
        assert!((chance_probability(&pixels, radii, 3, 1) - 1.0).abs() < f64::EPSILON);
    }
}
