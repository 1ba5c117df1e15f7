//! P3P RANSAC for the initial pose: uniform 3-point samples, Grunert's P3P ([`super::p3p`]),
//! MSAC scoring with early exit, local optimization of every new best hypothesis
//! (LO-RANSAC: least squares on its inliers, kept if it scores better) and an adaptive
//! sample count, k = ln(1 − confidence) / ln(1 − w³) for the best inlier ratio w so far.

use nalgebra::{Matrix2, Vector2, Vector3};

use super::{MIN_INLIERS, PnpOptions, PoseProblem, inlier_indices, p3p};
use crate::camera::Camera;
use crate::lie::SE3;
use crate::optim::{LmOptions, RobustLoss, levenberg_marquardt};
use crate::rng::SplitMix64;

/// P3P RANSAC with MSAC scoring and local optimization; returns the best pose (if it has
/// at least [`MIN_INLIERS`] inliers) and the number of samples drawn.
pub(super) fn ransac(
    camera: &Camera,
    points: &[Vector3<f64>],
    pixels: &[Vector2<f64>],
    options: &PnpOptions,
) -> (Option<SE3>, usize) {
    let n = points.len();
    let opts = &options.ransac;
    let t2 = options.max_residual_px * options.max_residual_px;
    let bearings: Vec<Vector3<f64>> = pixels.iter().map(|uv| camera.unproject(uv).normalize()).collect();
    let mut rng = SplitMix64::new(opts.seed);
    let mut best: Option<(SE3, f64, usize)> = None;
    let mut needed = opts.max_iterations;
    let mut iterations = 0;
    while iterations < opts.max_iterations && (iterations < opts.min_iterations || iterations < needed) {
        iterations += 1;
        let sample = sample_three(&mut rng, n);
        let world = sample.map(|j| points[j]);
        if (world[1] - world[0]).cross(&(world[2] - world[0])).norm_squared() <= f64::EPSILON {
            continue;
        }
        let bear = sample.map(|j| bearings[j]);
        for hypothesis in p3p::p3p(&bear, &world) {
            let bound = best.as_ref().map_or(f64::INFINITY, |b| b.1);
            let Some((score, count)) = msac_score(camera, points, pixels, &hypothesis, t2, bound) else { continue };
            if count < 3 {
                continue;
            }
            let (pose, score, count) = locally_optimize(camera, points, pixels, hypothesis, score, count, options);
            best = Some((pose, score, count));
            let inlier_ratio = count as f64 / n as f64;
            needed = required_iterations(inlier_ratio, opts.confidence, opts.max_iterations);
        }
    }
    (best.filter(|b| b.2 >= MIN_INLIERS).map(|b| b.0), iterations)
}

/// Samples needed so that P(some all-inlier 3-sample) ≥ `confidence`.
fn required_iterations(inlier_ratio: f64, confidence: f64, cap: usize) -> usize {
    let all_good = inlier_ratio.powi(3);
    if all_good >= 1.0 {
        return 1;
    }
    if all_good <= 0.0 {
        return cap;
    }
    let k = (1.0 - confidence).ln() / (1.0 - all_good).ln();
    if k.is_finite() { (k.ceil() as usize).clamp(1, cap) } else { cap }
}

fn sample_three(rng: &mut SplitMix64, n: usize) -> [usize; 3] {
    let pick = |rng: &mut SplitMix64, m: usize| ((rng.next_u64() >> 11) as usize) % m;
    let a = pick(rng, n);
    let mut b = pick(rng, n - 1);
    if b >= a {
        b += 1;
    }
    let (lo, hi) = if a < b { (a, b) } else { (b, a) };
    let mut c = pick(rng, n - 2);
    if c >= lo {
        c += 1;
    }
    if c >= hi {
        c += 1;
    }
    [a, b, c]
}

/// MSAC score Σ min(‖r‖², t²) (behind-camera points count t²) and inlier count; None as
/// soon as the partial score exceeds `bound` (cannot beat the best).
pub(super) fn msac_score(
    camera: &Camera,
    points: &[Vector3<f64>],
    pixels: &[Vector2<f64>],
    world_from_cam: &SE3,
    t2: f64,
    bound: f64,
) -> Option<(f64, usize)> {
    let cam_from_world = world_from_cam.inverse();
    let r = *cam_from_world.rotation.matrix();
    let t = cam_from_world.translation;
    let mut score = 0.0;
    let mut count = 0;
    for (x, uv) in points.iter().zip(pixels) {
        let p = r * x + t;
        let e = if p.z > 0.0 { (camera.project_cam(&p) - uv).norm_squared().min(t2) } else { t2 };
        if e < t2 {
            count += 1;
        }
        score += e;
        if score >= bound {
            return None;
        }
    }
    Some((score, count))
}

/// LO step: plain least squares on the hypothesis' inliers, kept if it scores better.
fn locally_optimize(
    camera: &Camera,
    points: &[Vector3<f64>],
    pixels: &[Vector2<f64>],
    hypothesis: SE3,
    score: f64,
    count: usize,
    options: &PnpOptions,
) -> (SE3, f64, usize) {
    let t2 = options.max_residual_px * options.max_residual_px;
    let subset = inlier_indices(camera, points, pixels, &hypothesis, options.max_residual_px);
    if subset.len() < MIN_INLIERS {
        return (hypothesis, score, count);
    }
    let weights = vec![Matrix2::identity(); subset.len()];
    let biases = vec![Vector2::zeros(); subset.len()];
    let problem = PoseProblem {
        camera,
        points,
        pixels,
        subset: &subset,
        weights: &weights,
        biases: &biases,
        loss: RobustLoss::None,
    };
    let lm = LmOptions { max_iterations: 10, ..options.lm };
    let (refined, _) = levenberg_marquardt(&problem, hypothesis, &lm);
    match msac_score(camera, points, pixels, &refined, t2, score) {
        Some((s, c)) => (refined, s, c),
        None => (hypothesis, score, count),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn iteration_count_formula() {
        // w = 0.5: P(good sample) = 1/8; ln(1e-4)/ln(7/8) = 68.97 → 69
        assert_eq!(required_iterations(0.5, 0.9999, 10_000), 69);
        assert_eq!(required_iterations(1.0, 0.9999, 10_000), 1);
        assert_eq!(required_iterations(0.0, 0.9999, 500), 500);
    }

    #[test]
    fn samples_are_distinct_and_cover_the_range() {
        let mut rng = SplitMix64::new(1);
        let mut seen = [0usize; 5];
        for _ in 0..10_000 {
            let s = sample_three(&mut rng, 5);
            assert!(s[0] != s[1] && s[1] != s[2] && s[0] != s[2]);
            for j in s {
                seen[j] += 1;
            }
        }
        // each index is in 3/5 of the samples
        for count in seen {
            assert!((count as f64 / 10_000.0 - 0.6).abs() < 0.03, "{seen:?}");
        }
    }
}
