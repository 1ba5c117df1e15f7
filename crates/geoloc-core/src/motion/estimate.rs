//! Build-time statistics of a recorded trajectory (poses world_from_cam at increasing
//! timestamps, e.g. a map's training frames) for the motion model of [`super`]: the white
//! body-acceleration PSD q ([`estimate_acceleration_psd`], the process noise of the
//! prediction) and the velocity prior ξ ~ N(μ_v, diag Σ_v) ([`estimate_velocity_prior`]).
//! Both use the mean body velocity over each step, vᵢ = log(Tᵢ₋₁⁻¹Tᵢ)^∨/Δtᵢ (right
//! perturbation, translation first); steps longer than 1 s are breaks in the recording.

use nalgebra::Vector6;

use super::VelocityPrior;
use crate::error::{GeolocError, Result};
use crate::lie::{SE3, Twist};
use crate::stats::chi2::CHI2_1_MEDIAN;
use crate::stats::{EvenMedian, median};

/// Consecutive steps longer than this (s) are a break in the trajectory, not motion.
const MAX_STEP_S: f64 = 1.0;

/// Estimates the power spectral density q of white body acceleration from a trajectory
/// (poses world_from_cam at increasing `timestamps`, e.g. a map's training frames).
///
/// Mean body velocities over consecutive steps, vᵢ = log(Tᵢ₋₁⁻¹Tᵢ)^∨/Δtᵢ, differ by
/// Δvᵢ = vᵢ₊₁ − vᵢ with Var(Δvᵢ,ₐ) = q_a (Δtᵢ + Δtᵢ₊₁)/3 when the velocity is a random walk
/// of rate q (the difference of a Brownian motion's means over adjacent intervals). Per axis
/// q_a = median(Δvᵢ,ₐ² · 3/(Δtᵢ + Δtᵢ₊₁)) / median(χ²₁): robust to the odd glitch in the
/// labels. Pose-label jitter adds to it (a larger q is the conservative side). Steps longer
/// than 1 s are breaks and skipped.
///
/// # Errors
/// Mismatched lengths, non-finite or non-increasing timestamps, fewer than 3 poses (or no
/// usable triple).
pub fn estimate_acceleration_psd(poses: &[SE3], timestamps: &[f64]) -> Result<Vector6<f64>> {
    check_trajectory(poses, timestamps)?;
    let velocity = |i: usize| step_velocity(poses, timestamps, i);
    let mut samples: Vec<Vector6<f64>> = Vec::new();
    for i in 1..poses.len().saturating_sub(1) {
        let (a, b) = (timestamps[i] - timestamps[i - 1], timestamps[i + 1] - timestamps[i]);
        if a > MAX_STEP_S || b > MAX_STEP_S {
            continue;
        }
        let dv = velocity(i + 1) - velocity(i);
        samples.push(dv.component_mul(&dv) * (3.0 / (a + b)));
    }
    if samples.is_empty() {
        return Err(GeolocError::invalid("poses", "need at least 3 poses with steps ≤ 1 s"));
    }
    Ok(Vector6::from_fn(|axis, _| {
        let mut v: Vec<f64> = samples.iter().map(|s| s[axis]).collect();
        let median = median(&mut v, EvenMedian::Mean).expect("invariant: samples is not empty");
        median / CHI2_1_MEDIAN
    }))
}

/// Estimates the velocity prior ([`VelocityPrior`]) from a trajectory (poses world_from_cam at
/// increasing `timestamps`, e.g. a map's training frames): the mean and the variance per twist
/// axis of the body velocities over consecutive steps, vᵢ = log(Tᵢ₋₁⁻¹Tᵢ)^∨/Δtᵢ. The plain
/// mean and variance, not robust ones: the prior must allow the fastest motion the recording
/// has (pose-label jitter widens it, the conservative side). Steps longer than 1 s are breaks
/// and skipped. A trajectory without variation on some axis (a variance below 10⁻¹² of the
/// axis' mean square, i.e. rounding) gives no prior.
///
/// # Errors
/// Mismatched lengths, non-finite or non-increasing timestamps, no step of at most 1 s.
pub fn estimate_velocity_prior(poses: &[SE3], timestamps: &[f64]) -> Result<VelocityPrior> {
    check_trajectory(poses, timestamps)?;
    let velocities: Vec<Vector6<f64>> = (1..poses.len())
        .filter(|&i| timestamps[i] - timestamps[i - 1] <= MAX_STEP_S)
        .map(|i| step_velocity(poses, timestamps, i))
        .collect();
    if velocities.is_empty() {
        return Err(GeolocError::invalid("poses", "need at least 2 poses with a step ≤ 1 s"));
    }
    let n = velocities.len() as f64;
    let mean = velocities.iter().sum::<Vector6<f64>>() / n;
    let variance = velocities.iter().map(|v| (v - mean).component_mul(&(v - mean))).sum::<Vector6<f64>>() / n;
    // no variation on an axis (below rounding of its mean square): no prior
    if variance.iter().zip(mean.iter()).any(|(v, m)| v.is_nan() || *v <= 1e-12 * (v + m * m)) {
        return Ok(VelocityPrior::default());
    }
    Ok(VelocityPrior { mean, variance })
}

/// The mean body velocity over step i of a trajectory: vᵢ = log(Tᵢ₋₁⁻¹Tᵢ)^∨/Δtᵢ (twist per
/// second, translation first).
fn step_velocity(poses: &[SE3], timestamps: &[f64], i: usize) -> Twist {
    (poses[i - 1].inverse() * poses[i]).log() / (timestamps[i] - timestamps[i - 1])
}

/// The input checks of the trajectory estimators: as many timestamps as poses, finite and
/// increasing.
fn check_trajectory(poses: &[SE3], timestamps: &[f64]) -> Result<()> {
    if poses.len() != timestamps.len() {
        return Err(GeolocError::invalid(
            "timestamps",
            format!("has {} entries for {} poses", timestamps.len(), poses.len()),
        ));
    }
    if let Some(i) = timestamps.iter().position(|t| !t.is_finite()) {
        return Err(GeolocError::NonFinite { name: "timestamps".into(), index: i });
    }
    if timestamps.windows(2).any(|w| w[1] <= w[0]) {
        return Err(GeolocError::invalid("timestamps", "must increase"));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::motion::motion_predict_with_prior;
    use crate::motion::tests::{random_walk, trajectory};
    use crate::testing::SplitMix64;
    use nalgebra::Matrix6;

    /// Relative tolerance of the q estimate from ~4000 robust (median) samples: the median's
    /// standard error is about 1.25/√n·(its scale) ≈ 3 %; 15 % leaves room for the
    /// between-axis coupling of the exponential map.
    const PSD_TOLERANCE: f64 = 0.15;

    #[test]
    fn acceleration_psd_is_recovered_from_a_simulated_trajectory() {
        let mut rng = SplitMix64::new(17);
        let q = Vector6::new(0.5, 0.2, 1.0, 0.8, 0.3, 0.05);
        let (h, every) = (1.0 / 3000.0, 100);
        let poses = random_walk(&mut rng, &q, h, 4000, every);
        let times: Vec<f64> = (0..poses.len()).map(|i| i as f64 * h * every as f64).collect();
        let est = estimate_acceleration_psd(&poses, &times).expect("valid");
        for a in 0..6 {
            assert!((est[a] / q[a] - 1.0).abs() < PSD_TOLERANCE, "axis {a}: {} vs {}", est[a], q[a]);
        }
        assert!(estimate_acceleration_psd(&poses[..2], &times[..2]).is_err());
        assert!(estimate_acceleration_psd(&poses, &times[1..]).is_err());
    }

    /// Body velocities alternating v + d and v − d: mean v, variance d² on every axis; a step
    /// over 1 s (a break in the recording) is skipped; a constant velocity has no variation,
    /// so no prior; bad priors are refused by name.
    #[test]
    fn velocity_prior_of_a_trajectory() {
        let v = Vector6::new(0.3, -0.1, 0.2, 0.2, 0.1, -0.3);
        let d = Vector6::new(0.05, 0.02, 0.04, 0.03, 0.01, 0.06);
        // 30 steps, a 5 s break, 30 steps: 30 of each sign
        let mut times: Vec<f64> = (0..31).map(|i| i as f64 / 30.0).collect();
        times.extend((0..31).map(|i| 6.0 + i as f64 / 30.0));
        let mut poses = vec![SE3::identity()];
        for i in 1..times.len() {
            let dt = times[i] - times[i - 1];
            let step = if dt > 1.0 {
                Vector6::repeat(0.7)
            } else if i % 2 == 0 {
                v + d
            } else {
                v - d
            };
            poses.push(poses[i - 1] * SE3::exp(&(step * dt.min(1.0))));
        }
        let prior = estimate_velocity_prior(&poses, &times).expect("valid");
        assert!((prior.mean - v).abs().max() < 1e-9, "{:?}", prior.mean);
        assert!((prior.variance - d.component_mul(&d)).abs().max() < 1e-9, "{:?}", prior.variance);
        let constant = trajectory(&SE3::identity(), &v, &times[..30]);
        assert!(estimate_velocity_prior(&constant, &times[..30]).expect("valid").is_none());
        assert!(estimate_velocity_prior(&poses[..1], &times[..1]).is_err());
        let two = [SE3::identity(), SE3::identity()];
        let err = estimate_velocity_prior(&two, &[0.0, 5.0]).expect_err("only a break");
        assert!(err.to_string().contains("poses"), "{err}");
        let covs = [Matrix6::identity() * 1e-4; 2];
        let bad = [
            (Vector6::zeros(), Vector6::new(0.1, 0.0, 0.1, 0.1, 0.1, 0.1), "velocity_variance"),
            (Vector6::zeros(), Vector6::repeat(f64::NAN), "velocity_variance"),
            (Vector6::zeros(), Vector6::repeat(-1.0), "velocity_variance"),
            (Vector6::repeat(f64::INFINITY), Vector6::repeat(0.1), "velocity_mean"),
            (Vector6::new(1e300, 0.0, 0.0, 0.0, 0.0, 0.0), Vector6::repeat(0.05), "velocity_mean"),
            (Vector6::zeros(), Vector6::repeat(1e-320), "velocity_variance"),
        ];
        for (mean, variance, name) in bad {
            let prior = VelocityPrior { mean, variance };
            let err = motion_predict_with_prior(&two, &[0.0, 0.1], 0.2, Some(&covs), &Vector6::zeros(), &prior)
                .expect_err("refused");
            assert!(err.to_string().contains(name), "{err}");
        }
    }
}
