//! How sure the labels are: the robust scale of the adjustment's label corrections, their
//! correlation along the trajectory, and the skeleton of keyframes both are measured over.

use nalgebra::Vector6;

use super::LabelSigma;
use crate::lie::{SE3, se3};
use crate::stats::chi2::{CHI2_3_MEDIAN, CHI2_6_999};
use crate::stats::{EvenMedian, median};

/// Smallest estimated label σ (1 mm, 0.05°): labels that agree with the images to the
/// last bit still get a finite prior.
const MIN_LABEL_SIGMA: LabelSigma = LabelSigma { translation_m: 1e-3, rotation_rad: 8.726_646_259_971_648e-4 };

/// σ² = median(‖e‖²) / median(χ²₃) of the translation and rotation parts of the label
/// corrections e_k = log(L_k⁻¹ B_k), floored at [`MIN_LABEL_SIGMA`] ([`robust_sigma`]).
pub(super) fn estimate_label_sigma(labels: &[SE3], adjusted: &[SE3]) -> LabelSigma {
    estimate_label_sigma_within(labels, adjusted, None)
}

/// [`estimate_label_sigma`] over the corrections a label prior of σ `prior` holds inside its
/// 99.9 % region ([`held_by`]); all of them for None. The median of ‖e‖² is robust to the
/// others but not unmoved by them: a run of m wrong labels among n puts the median at the
/// (n/2)-th of the n − m others, their 0.5 n/(n − m) quantile (12 of 160 labels displaced by
/// 20 cm: σ 4 % high in a synthetic map with 3 mm of noise, 8–11 % with the adjusted poses'
/// own error; over the held ones 0–2 %).
pub(super) fn estimate_label_sigma_within(labels: &[SE3], adjusted: &[SE3], prior: Option<LabelSigma>) -> LabelSigma {
    let corrections: Vec<Vector6<f64>> = labels
        .iter()
        .zip(adjusted)
        .map(|(l, b)| (l.inverse() * *b).log())
        .filter(|e| prior.is_none_or(|p| held_by(e, &p)))
        .collect();
    robust_sigma(&corrections)
}

/// Whether a label prior of σ `prior` holds the correction `e` inside its 99.9 % region:
/// eᵀ Λ e ≤ χ²₆(0.999), Λ = diag(σ_t⁻², σ_r⁻²).
fn held_by(e: &Vector6<f64>, prior: &LabelSigma) -> bool {
    let m = se3::rho(e).norm_squared() / prior.translation_m.powi(2)
        + se3::phi(e).norm_squared() / prior.rotation_rad.powi(2);
    m <= CHI2_6_999
}

/// The robust per-axis scale of twists e (right perturbation, translation first):
/// σ_t² = median(‖ρ‖²) / median(χ²₃), σ_r² = median(‖φ‖²) / median(χ²₃) — exact for
/// isotropic Gaussian parts, unmoved by up to half of the twists being outliers — floored at
/// [`MIN_LABEL_SIGMA`] (also the value for no twists).
pub fn robust_sigma(errors: &[Vector6<f64>]) -> LabelSigma {
    let (mut t, mut r): (Vec<f64>, Vec<f64>) =
        errors.iter().map(|e| (se3::rho(e).norm_squared(), se3::phi(e).norm_squared())).unzip();
    let median = |v: &mut [f64]| median(v, EvenMedian::Upper).unwrap_or(0.0);
    LabelSigma {
        translation_m: (median(&mut t) / CHI2_3_MEDIAN).sqrt().max(MIN_LABEL_SIGMA.translation_m),
        rotation_rad: (median(&mut r) / CHI2_3_MEDIAN).sqrt().max(MIN_LABEL_SIGMA.rotation_rad),
    }
}

/// Spacing of the skeleton the labels are adjusted on, and of the keyframes the correlation
/// length is measured over (the same keyframes, so τ counts the priors the adjustment has):
/// each at least this far (m) or this much turned (rad) from the last one taken. Keyframes
/// much closer than that see the same images: the adjustment moves them together whatever
/// their labels did, and counting them would measure its own smoothing. 2.5 cm / 1.5° keeps
/// one 7-Scenes frame in 3.6; 5 cm / 3° keeps one in 6.7, with fewer observations and
/// revisit pairs (7-fold mean single-image error against the SfM reference, revisits in
/// both: 1.64 cm / 0.44°, recall 91.6 % at 2.5 cm; 1.73 cm / 0.47°, 87.9 % at 5 cm); a
/// 1.25 cm / 0.75° skeleton is no better and slower.
pub const CORRELATION_SPACING: (f64, f64) = (0.025, 0.026_179_938_779_914_945);

/// τ = 1 + 2 Σ_{l ≥ 1} r(l), the integrated autocorrelation time of the label corrections
/// e_k = log(L_k⁻¹ B_k) along the trajectory, for the translation and the rotation axes: over
/// the keyframes thinned to [`CORRELATION_SPACING`] in capture order, r(l) the lag-l
/// autocorrelation averaged over the three axes, summed while positive (Geyer's initial
/// positive sequence), τ ≥ 1 (in thinned keyframes).
pub fn correlation_lengths(labels: &[SE3], adjusted: &[SE3]) -> (f64, f64) {
    correlation_lengths_within(labels, adjusted, None)
}

/// [`correlation_lengths`] over the corrections a label prior of σ `prior` holds inside its
/// 99.9 % region (eᵀ Λ e ≤ χ²₆(0.999), Λ = diag(σ_t⁻², σ_r⁻²)); all of them for None. The
/// others are the robust kernel's outliers — a run of wrong labels the images pulled away —
/// not the drift τ measures: counted, a run of m keyframes displaced together reads as a
/// correlation length of about m, though the other labels' noise is independent (a synthetic
/// map with 12 of 160 labels displaced by 20 cm / 5°: τ ≈ 11 over all, ≈ 1 without them).
/// r(l) is then taken over the pairs (k, k + l) whose corrections both count, around the
/// mean of those that count.
pub fn correlation_lengths_within(labels: &[SE3], adjusted: &[SE3], prior: Option<LabelSigma>) -> (f64, f64) {
    let kept = skeleton(adjusted);
    let e: Vec<Vector6<f64>> = kept.iter().map(|&k| (labels[k].inverse() * adjusted[k]).log()).collect();
    let counts: Vec<bool> = e.iter().map(|v| prior.is_none_or(|p| held_by(v, &p))).collect();
    let n = e.len();
    let used = counts.iter().filter(|c| **c).count();
    if used == 0 {
        return (1.0, 1.0);
    }
    let tau = |axes: std::ops::Range<usize>| {
        let series: Vec<Vec<f64>> = axes
            .map(|a| {
                let mean = e.iter().zip(&counts).filter(|(_, c)| **c).map(|(v, _)| v[a]).sum::<f64>() / used as f64;
                e.iter().zip(&counts).map(|(v, c)| if *c { v[a] - mean } else { 0.0 }).collect()
            })
            .collect();
        let autocorrelation = |l: usize| {
            let r: Vec<f64> = series
                .iter()
                .filter_map(|x| {
                    let var: f64 = x.iter().map(|v| v * v).sum();
                    (var > 0.0).then(|| x.iter().zip(&x[l..]).map(|(a, b)| a * b).sum::<f64>() / var)
                })
                .collect();
            if r.is_empty() { 0.0 } else { r.iter().sum::<f64>() / r.len() as f64 }
        };
        let mut t = 1.0;
        for l in 1..n / 2 {
            let r = autocorrelation(l);
            if r <= 0.0 {
                break;
            }
            t += 2.0 * r;
        }
        t
    };
    (tau(0..3), tau(3..6))
}

/// The skeleton of a trajectory in capture order: the first pose, then each pose at least
/// [`CORRELATION_SPACING`] (translation or rotation) from the last one taken, and the last.
pub fn skeleton(poses: &[SE3]) -> Vec<usize> {
    let (min_m, min_rad) = CORRELATION_SPACING;
    let mut kept: Vec<usize> = Vec::new();
    for (k, p) in poses.iter().enumerate() {
        let far = kept.last().is_none_or(|&j| {
            let d = poses[j].inverse() * *p;
            d.translation.norm() >= min_m || d.rotation.angle() >= min_rad
        });
        if far {
            kept.push(k);
        }
    }
    if let (Some(&last), Some(n)) = (kept.last(), poses.len().checked_sub(1))
        && last != n
    {
        kept.push(n);
    }
    kept
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::SplitMix64;

    /// CHI2_3_MEDIAN against the sample median of ‖z‖² for 400 000 standard normal 3-vectors.
    #[test]
    fn chi2_3_median_matches_sampling() {
        let mut rng = SplitMix64::new(17);
        let mut v: Vec<f64> = (0..400_000).map(|_| (0..3).map(|_| rng.normal().powi(2)).sum::<f64>()).collect();
        v.sort_by(f64::total_cmp);
        let median = v[v.len() / 2];
        assert!((median - CHI2_3_MEDIAN).abs() < 0.01, "{median}");
    }
}
