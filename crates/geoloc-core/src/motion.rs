//! The constant-velocity motion model on SE(3) (the paper's §"motion model"): the
//! per-frame prediction T_M, C_M from the last poses. The statistics of a recorded
//! trajectory that parameterize it (process noise, velocity prior) are estimated at build
//! time by the `estimate` submodule.
//!
//! The last m poses Tᵢ (world_from_cam) at times tᵢ are fitted by a constant body velocity:
//!
//!   T(t) = T_r exp((t − t_r) ξ^),   ξ = (v, ω) ∈ R⁶ per second, t_r = the latest time,
//!
//! by Gauss–Newton on the right-perturbation residuals eᵢ = log(T(tᵢ)⁻¹ Tᵢ)^∨ over the
//! parameters (T_r ⊞ δ, ξ + ε). Timestamps, not frame indices, so irregular spacing and
//! dropped frames are fine. The prediction is T_M = T_r exp((t_q − t_r) ξ^) and its
//! covariance C_M = G Σ Gᵀ with G = [Ad(exp(−τ ξ)), τ J_r(τ ξ)], τ = t_q − t_r, Σ the
//! covariance of (δ, ε):
//!
//! * with the poses' covariances Cᵢ the fit is weighted (Wᵢ = Cᵢ⁻¹) and Σ = (JᵀWJ)⁻¹ —
//!   calibrated when the model holds; when the weighted residual χ² exceeds its 99 %
//!   quantile (6m − 12 dof) the motion is not constant-velocity and Σ is scaled by χ²/dof;
//! * without them (the paper's way) each axis' noise variance is estimated from the fit
//!   residuals, σ_a² = Σᵢ eᵢ,ₐ² / (m − 2) (m poses, 2 parameters per axis), and
//!   Σ = (Jᵀ diag(1/σ²) J)⁻¹; this needs m ≥ 3.
//!
//! With a velocity prior ξ ~ N(μ_v, Σ_v) ([`motion_predict_with_prior`]; μ_v and Σ_v =
//! diag of the mean and variance of the training trajectory's body velocity,
//! [`estimate_velocity_prior`]) the fit minimizes Σ eᵢᵀWᵢeᵢ + (ξ − μ_v)ᵀΣ_v⁻¹(ξ − μ_v): H
//! gains Σ_v⁻¹ in the velocity block, the χ² check gains its 6 dof. Two poses determine ξ
//! exactly and carry no check, so one pose 15 cm off made a 3.6 m/s velocity and a
//! prediction 30 cm off (7-Scenes 200–299); the prior weighs such a velocity against how
//! the camera was carried when the map was recorded (a robot that drives forward keeps its
//! mean: a zero-mean prior would pull every estimate towards standing still).

use nalgebra::{Matrix6, SMatrix, SVector, Vector6};

use crate::error::{GeolocError, Result};
use crate::lie::{SE3, Twist, se3};
use crate::optim::covariance::{check_covariance, check_covariances, spd_inverse};
use crate::optim::{LeastSquares, LmOptions, PoseEstimate, solve};
use crate::stats::chi2;

mod estimate;
pub use estimate::{estimate_acceleration_psd, estimate_velocity_prior};

/// What the motion model adds to its prediction.
#[derive(Clone, Debug, PartialEq)]
pub struct MotionDetails {
    /// The fitted body velocity ξ = (v, ω) per second.
    pub velocity: Twist,
    /// RMS of the fit residuals ‖eᵢ‖.
    pub rms_residual: f64,
}

/// A one-step prediction of the motion model: T_M (world_from_cam) at the query time, C_M
/// (right perturbation, translation first), the Gauss–Newton report of the (last) fit and
/// the fitted velocity.
pub type MotionPrediction = PoseEstimate<MotionDetails>;

/// Gauss–Newton iterations of the fit (it converges in 2–4).
const MAX_ITERATIONS: usize = 20;
/// Stop when the parameter step is below this (metres, radians, per second).
const STEP_TOLERANCE: f64 = 1e-12;
/// Variance floor of the residual-based noise estimate (a perfectly fitted axis would
/// otherwise claim zero uncertainty): (0.1 mm)², (0.0001 rad)².
const MIN_RESIDUAL_VARIANCE: f64 = 1e-8;
/// Largest |t − t_r| (s) between a timestamp or the query and the latest timestamp: beyond
/// it, τξ overflows the exponential map's accuracy (and 1e300 overflows it outright).
pub const MAX_TIME_SPAN_S: f64 = 1e9;

/// Largest |mean| of a velocity prior per axis (m/s, rad/s): far beyond any camera; a mean of
/// 1e300 overflowed the fit and was reported against the poses.
pub const MAX_PRIOR_SPEED: f64 = 1e6;

/// The velocity prior ξ ~ N(mean, diag(variance)) of the motion fit (per twist axis,
/// translation first; m/s and rad/s). All-zero variance: no prior.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct VelocityPrior {
    /// μ_v, the mean body velocity.
    pub mean: Vector6<f64>,
    /// diag(Σ_v), the variance of the body velocity per axis.
    pub variance: Vector6<f64>,
}

impl VelocityPrior {
    /// No prior (the variance all zero).
    pub fn is_none(&self) -> bool {
        self.variance == Vector6::zeros()
    }

    /// Checks the values: the mean within ±[`MAX_PRIOR_SPEED`] per axis, the variance finite
    /// and > 0 with a finite inverse on every axis, or 0 on all (no prior).
    ///
    /// # Errors
    /// `InvalidInput` naming `velocity_mean` or `velocity_variance`.
    pub fn check(&self) -> Result<()> {
        if self.mean.iter().any(|v| v.is_nan() || v.abs() > MAX_PRIOR_SPEED) {
            return Err(GeolocError::invalid(
                "velocity_mean",
                format!("must be finite and within ±{MAX_PRIOR_SPEED:e} per axis"),
            ));
        }
        if !self.is_none() && self.variance.iter().any(|v| !(v.is_finite() && *v > 0.0 && (1.0 / v).is_finite())) {
            return Err(GeolocError::invalid(
                "velocity_variance",
                "must be finite and > 0 (with a finite inverse) on every axis (all 0: no prior)",
            ));
        }
        Ok(())
    }
}

/// Fits the model to `poses` at `timestamps` and predicts at `t_query`; see the module doc.
///
/// # Errors
/// Mismatched lengths, fewer than 2 poses (3 without covariances), non-finite or repeated
/// timestamps, a query or timestamps more than [`MAX_TIME_SPAN_S`] from the latest one,
/// covariances that are not symmetric positive definite, an unobservable velocity.
pub fn motion_predict(
    poses: &[SE3],
    timestamps: &[f64],
    t_query: f64,
    covariances: Option<&[Matrix6<f64>]>,
) -> Result<MotionPrediction> {
    fit_and_predict(poses, timestamps, t_query, covariances, None)
}

/// The fit of [`motion_predict`], with the velocity prior (μ_v, Σ_v⁻¹) if any.
fn fit_and_predict(
    poses: &[SE3],
    timestamps: &[f64],
    t_query: f64,
    covariances: Option<&[Matrix6<f64>]>,
    velocity_information: Option<(Vector6<f64>, Matrix6<f64>)>,
) -> Result<MotionPrediction> {
    let weights = validate(poses, timestamps, t_query, covariances)?;
    let m = poses.len();
    let latest = (0..m).max_by(|&a, &b| timestamps[a].total_cmp(&timestamps[b])).expect("invariant: m ≥ 2");
    let mut fit = Fit { poses, timestamps, t_ref: timestamps[latest], weights, velocity_information };
    let mut state = (poses[latest], initial_velocity(poses, timestamps, latest));
    let options = LmOptions::gauss_newton(MAX_ITERATIONS, STEP_TOLERANCE);
    let (mut next, mut report, mut at_fit) = solve(&fit, state, &options);
    if covariances.is_none() {
        // the paper's way: per-axis noise from the unit-weight fit's residuals, then refit
        fit.weights = residual_weights(&fit, &next);
        state = next;
        (next, report, at_fit) = solve(&fit, state, &options);
    }
    let (reference, velocity) = next;
    let h = at_fit.linearization.map(|l| l.h).ok_or_else(|| GeolocError::invalid("poses", "the fit is not finite"))?;
    let mut sigma = h.try_inverse().ok_or_else(|| GeolocError::invalid("poses", "the velocity is not observable"))?;
    // With given covariances, a fit much worse than they allow means the motion is not
    // constant-velocity: scale Σ by the variance factor χ²/dof when χ² exceeds its 99 %
    // quantile (rarely triggered by noise alone, so a consistent model stays calibrated).
    let dof = 6 * m - 12 + if velocity_information.is_some() { 6 } else { 0 };
    if covariances.is_some() && dof > 0 && at_fit.cost > chi2::quantile_99_wilson_hilferty(dof) {
        sigma *= at_fit.cost / dof as f64;
    }
    let (world_from_cam, covariance) = predict(&reference, &velocity, &sigma, t_query - fit.t_ref);
    // at absurd scales (translations ~1e38 m) rounding swamps the fit and C_M comes out
    // indefinite: refuse rather than return a covariance that is not one
    check_covariance("poses", &covariance).map_err(|_| {
        GeolocError::invalid("poses", "too large for the motion fit: its covariance is not positive semi-definite")
    })?;
    let rms_residual =
        fit.residuals(&reference, &velocity).iter().map(|e| e.norm_squared()).sum::<f64>().sqrt() / (m as f64).sqrt();
    Ok(MotionPrediction {
        world_from_cam,
        covariance,
        report: Some(report),
        details: MotionDetails { velocity, rms_residual },
    })
}

/// The constant-velocity model's process noise for a prediction `tau` seconds past the
/// latest pose of a fit spanning `window_s` seconds, under white body acceleration of power
/// spectral density q (per twist axis, translation first):
///
///   Q(τ) = diag(q) · (|τ|³/3 + τ² T_w/3).
///
/// |τ|³/3 is the position variance an integrated random-walk velocity accumulates over τ
/// (Bar-Shalom et al. 2001, §6.2.2: the continuous white-noise-acceleration model); τ²T_w/3
/// the extrapolated error of a velocity fitted over the window T_w while it random-walks
/// (the velocity's deviation from the window mean, variance q·T_w/3, times τ). Body
/// (right-perturbation) axes, so Q adds to C_M directly.
pub fn process_noise(acceleration_psd: &Vector6<f64>, tau: f64, window_s: f64) -> Matrix6<f64> {
    let t = tau.abs();
    Matrix6::from_diagonal(&(acceleration_psd * (t * t * t / 3.0 + t * t * window_s.max(0.0) / 3.0)))
}

/// [`motion_predict`] with the poses' covariances plus the process noise of white body
/// acceleration of power spectral density `acceleration_psd` ([`process_noise`]), so C_M
/// grows with the prediction horizon: C_M = G Σ Gᵀ + Q(τ).
///
/// # Errors
/// As [`motion_predict`]; `acceleration_psd` not finite and ≥ 0.
pub fn motion_predict_with_noise(
    poses: &[SE3],
    timestamps: &[f64],
    t_query: f64,
    covariances: Option<&[Matrix6<f64>]>,
    acceleration_psd: &Vector6<f64>,
) -> Result<MotionPrediction> {
    motion_predict_with_prior(poses, timestamps, t_query, covariances, acceleration_psd, &VelocityPrior::default())
}

/// [`motion_predict_with_noise`] with the velocity prior ξ ~ N(μ_v, Σ_v) (see the module doc;
/// [`VelocityPrior::is_none`]: none).
///
/// # Errors
/// As [`motion_predict_with_noise`]; a prior refused by [`VelocityPrior::check`].
pub fn motion_predict_with_prior(
    poses: &[SE3],
    timestamps: &[f64],
    t_query: f64,
    covariances: Option<&[Matrix6<f64>]>,
    acceleration_psd: &Vector6<f64>,
    prior: &VelocityPrior,
) -> Result<MotionPrediction> {
    if acceleration_psd.iter().any(|q| !(q.is_finite() && *q >= 0.0)) {
        return Err(GeolocError::invalid("acceleration_psd", "must be finite and ≥ 0"));
    }
    prior.check()?;
    let information =
        (!prior.is_none()).then(|| (prior.mean, Matrix6::from_diagonal(&prior.variance.map(|v| 1.0 / v))));
    let mut p = fit_and_predict(poses, timestamps, t_query, covariances, information)?;
    let first = timestamps.iter().copied().fold(f64::INFINITY, f64::min);
    let latest = timestamps.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    p.covariance += process_noise(acceleration_psd, t_query - latest, latest - first);
    Ok(p)
}

/// Smallest time between two poses of a fit (1 ns): closer timestamps make the velocity's
/// 1/Δt overflow (denormal differences divide to ∞).
pub const MIN_TIME_STEP_S: f64 = 1e-9;

/// The input checks of [`motion_predict`]; returns the fit's weights Wᵢ = Cᵢ⁻¹ (identity
/// without covariances).
fn validate(
    poses: &[SE3],
    timestamps: &[f64],
    t_query: f64,
    covariances: Option<&[Matrix6<f64>]>,
) -> Result<Vec<Matrix6<f64>>> {
    let m = poses.len();
    if timestamps.len() != m {
        return Err(GeolocError::invalid("timestamps", format!("has {} entries but poses has {m}", timestamps.len())));
    }
    let needed = if covariances.is_some() { 2 } else { 3 };
    if m < needed {
        let what = if needed == 3 { " and estimate its noise" } else { "" };
        return Err(GeolocError::invalid(
            "poses",
            format!("need at least {needed} poses to fit a velocity{what}, got {m}"),
        ));
    }
    if let Some(i) = timestamps.iter().position(|t| !t.is_finite()) {
        return Err(GeolocError::NonFinite { name: "timestamps".into(), index: i });
    }
    if !t_query.is_finite() {
        return Err(GeolocError::invalid("t_query", "must be finite"));
    }
    let mut sorted = timestamps.to_vec();
    sorted.sort_by(f64::total_cmp);
    if sorted.windows(2).any(|w| w[1] - w[0] < MIN_TIME_STEP_S) {
        return Err(GeolocError::invalid(
            "timestamps",
            format!("must be distinct, at least {MIN_TIME_STEP_S:e} s apart"),
        ));
    }
    let t_ref = sorted[m - 1];
    if (t_query - t_ref).abs() > MAX_TIME_SPAN_S {
        return Err(GeolocError::invalid(
            "t_query",
            format!("is {:e} s from the latest timestamp; at most {MAX_TIME_SPAN_S:e} s", t_query - t_ref),
        ));
    }
    if t_ref - sorted[0] > MAX_TIME_SPAN_S {
        return Err(GeolocError::invalid("timestamps", format!("span more than {MAX_TIME_SPAN_S:e} s")));
    }
    let Some(c) = covariances else { return Ok(vec![Matrix6::identity(); m]) };
    if c.len() != m {
        return Err(GeolocError::invalid("covariances", format!("has {} entries but poses has {m}", c.len())));
    }
    check_covariances("covariances", c)?;
    c.iter().enumerate().map(|(i, ci)| spd_inverse(ci, &format!("covariances[{i}]"))).collect()
}

/// Per-axis weights 1/σ_a² from the residuals of a unit-weight fit, σ_a² = Σᵢ eᵢ,ₐ²/(m − 2)
/// (floored at [`MIN_RESIDUAL_VARIANCE`]).
fn residual_weights(fit: &Fit<'_>, state: &(SE3, Twist)) -> Vec<Matrix6<f64>> {
    let residuals = fit.residuals(&state.0, &state.1);
    let m = fit.poses.len();
    let dof = (m - 2) as f64;
    let variance =
        Vector6::from_fn(|a, _| (residuals.iter().map(|e| e[a] * e[a]).sum::<f64>() / dof).max(MIN_RESIDUAL_VARIANCE));
    vec![Matrix6::from_diagonal(&variance.map(|v| 1.0 / v)); m]
}

/// T_M = T_r exp(τ ξ^) and C_M = G Σ Gᵀ with G = [Ad(exp(−τ ξ)), τ J_r(τ ξ)].
fn predict(reference: &SE3, velocity: &Twist, sigma: &SMatrix<f64, 12, 12>, tau: f64) -> (SE3, Matrix6<f64>) {
    let step = velocity * tau;
    let mut g = SMatrix::<f64, 6, 12>::zeros();
    g.fixed_view_mut::<6, 6>(0, 0).copy_from(&SE3::exp(&-step).adjoint());
    g.fixed_view_mut::<6, 6>(0, 6).copy_from(&(se3::right_jacobian(&step) * tau));
    let covariance = g * sigma * g.transpose();
    (*reference * SE3::exp(&step), 0.5 * (covariance + covariance.transpose()))
}

/// ξ from the latest pose and the one before it in time: log(T_prev⁻¹ T_latest)/Δt.
fn initial_velocity(poses: &[SE3], timestamps: &[f64], latest: usize) -> Twist {
    let previous = (0..poses.len())
        .filter(|&i| i != latest)
        .max_by(|&a, &b| timestamps[a].total_cmp(&timestamps[b]))
        .expect("invariant: m ≥ 2");
    (poses[previous].inverse() * poses[latest]).log() / (timestamps[latest] - timestamps[previous])
}

/// The constant-velocity fit as a least-squares problem over (T_r ⊞ δ, ξ + ε).
struct Fit<'a> {
    poses: &'a [SE3],
    timestamps: &'a [f64],
    t_ref: f64,
    weights: Vec<Matrix6<f64>>,
    /// (μ_v, Σ_v⁻¹) of the velocity prior, if any.
    velocity_information: Option<(Vector6<f64>, Matrix6<f64>)>,
}

impl Fit<'_> {
    /// eᵢ = log(exp(−τᵢξ) T_r⁻¹ Tᵢ), τᵢ = tᵢ − t_r.
    fn residuals(&self, reference: &SE3, velocity: &Twist) -> Vec<Vector6<f64>> {
        self.poses
            .iter()
            .zip(self.timestamps)
            .map(|(pose, &t)| (SE3::exp(&(-(t - self.t_ref) * velocity)) * reference.inverse() * *pose).log())
            .collect()
    }
}

impl LeastSquares<12> for Fit<'_> {
    type State = (SE3, Twist);

    /// H = Σ Jᵢᵀ Wᵢ Jᵢ, g = Σ Jᵢᵀ Wᵢ eᵢ and the cost for eᵢ = log(exp(−τᵢξ) T_r⁻¹ Tᵢ):
    /// ∂eᵢ/∂δ = −J_r⁻¹(eᵢ) Ad(Bᵢ⁻¹), ∂eᵢ/∂ε = −τᵢ J_r⁻¹(eᵢ) Ad(Bᵢ⁻¹) J_r(−τᵢξ), Bᵢ = T_r⁻¹Tᵢ.
    fn normal_equations(&self, state: &(SE3, Twist)) -> (SMatrix<f64, 12, 12>, SVector<f64, 12>, f64) {
        let (reference, velocity) = state;
        let mut h = SMatrix::<f64, 12, 12>::zeros();
        let mut g = SVector::<f64, 12>::zeros();
        let mut cost = 0.0;
        let reference_inv = reference.inverse();
        for ((pose, &t), w) in self.poses.iter().zip(self.timestamps).zip(&self.weights) {
            let tau = t - self.t_ref;
            let b = reference_inv * *pose;
            let e = (SE3::exp(&(-tau * velocity)) * b).log();
            let common = -se3::right_jacobian_inverse(&e) * b.inverse().adjoint();
            let mut j = SMatrix::<f64, 6, 12>::zeros();
            j.fixed_view_mut::<6, 6>(0, 0).copy_from(&common);
            j.fixed_view_mut::<6, 6>(0, 6).copy_from(&(common * se3::right_jacobian(&(-tau * velocity)) * tau));
            h += j.transpose() * w * j;
            g += j.transpose() * (w * e);
            cost += e.dot(&(w * e));
        }
        if let Some((mean, info)) = &self.velocity_information {
            // the prior's residual ξ − μ_v with weight Σ_v⁻¹ (∂/∂ε = I)
            let r = velocity - mean;
            let gv = info * r;
            let mut hv = h.fixed_view_mut::<6, 6>(6, 6);
            hv += info;
            let mut g_velocity = g.fixed_rows_mut::<6>(6);
            g_velocity += gv;
            cost += r.dot(&gv);
        }
        (h, g, cost)
    }

    fn retract(&self, state: &(SE3, Twist), step: &SVector<f64, 12>) -> (SE3, Twist) {
        (state.0 * SE3::exp(&step.fixed_rows::<6>(0).into_owned()), state.1 + step.fixed_rows::<6>(6))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lie::SO3;
    use crate::testing::{SplitMix64, isotropic_pose_covariance};
    use nalgebra::Vector3;

    /// A body-frame white-acceleration trajectory: the velocity random-walks with PSD `q`
    /// at a fine step `h`; returns the poses every `every` steps, starting at `start`.
    pub(super) fn random_walk(
        rng: &mut SplitMix64,
        q: &Vector6<f64>,
        h: f64,
        samples: usize,
        every: usize,
    ) -> Vec<SE3> {
        let mut pose = SE3::identity();
        let mut v = Vector6::new(0.3, -0.1, 0.2, 0.2, 0.1, -0.3);
        let mut out = vec![pose];
        for _ in 1..samples {
            for _ in 0..every {
                v += Vector6::from_fn(|a, _| (q[a] * h).sqrt() * rng.normal());
                pose = pose * SE3::exp(&(v * h));
            }
            out.push(pose);
        }
        out
    }

    /// Per-axis ratio of the empirical prediction-error variance to diag(C_M) must lie here
    /// (800 trials: the variance's own sampling error is ~5 %; Q(τ) is a first-order model).
    const PROCESS_NOISE_BAND: (f64, f64) = (0.6, 1.5);

    #[test]
    fn process_noise_covers_constant_velocity_extrapolation_under_random_acceleration() {
        let mut rng = SplitMix64::new(23);
        let q = Vector6::new(0.5, 0.5, 0.5, 0.2, 0.2, 0.2);
        let (h, every, trials) = (1.0 / 900.0, 30, 800);
        let mut sum_sq = Vector6::zeros();
        let mut predicted = Vector6::zeros();
        for _ in 0..trials {
            let poses = random_walk(&mut rng, &q, h, 6, every);
            let times: Vec<f64> = (0..6).map(|i| i as f64 / 30.0).collect();
            let covs = vec![isotropic_pose_covariance(1e-6, 1e-6); 4];
            let p = motion_predict_with_noise(&poses[..4], &times[..4], times[5], Some(&covs), &q).expect("valid");
            let e = (p.world_from_cam.inverse() * poses[5]).log();
            sum_sq += e.component_mul(&e);
            predicted += p.covariance.diagonal();
        }
        for a in 0..6 {
            let ratio = sum_sq[a] / predicted[a];
            assert!(ratio > PROCESS_NOISE_BAND.0 && ratio < PROCESS_NOISE_BAND.1, "axis {a}: ratio {ratio}");
        }
        let bad = Vector6::repeat(-1.0);
        assert!(motion_predict_with_noise(&[SE3::identity(); 2], &[0.0, 0.1], 0.2, None, &bad).is_err());
    }

    pub(super) fn trajectory(start: &SE3, velocity: &Twist, times: &[f64]) -> Vec<SE3> {
        times.iter().map(|&t| *start * SE3::exp(&(velocity * t))).collect()
    }

    #[test]
    fn exact_constant_velocity_is_extrapolated_exactly() {
        let mut rng = SplitMix64::new(1);
        for _ in 0..50 {
            let start = rng.pose(5.0);
            let angle = rng.uniform_in(0.0, 2.0);
            let v = rng.twist(angle, 1.0);
            let times = [0.0, 0.033, 0.1, 0.12]; // irregular, with a dropped frame
            let poses = trajectory(&start, &v, &times);
            let covs = vec![Matrix6::identity() * 1e-6; 4];
            let p = motion_predict(&poses, &times, 0.2, Some(&covs)).expect("valid");
            let truth = start * SE3::exp(&(v * 0.2));
            assert!((p.world_from_cam.inverse() * truth).log().norm() < 1e-9);
            assert!((p.details.velocity - v).norm() < 1e-8);
        }
    }

    /// A 180° turn within the window (ω·Δt near π between consecutive poses is fine as long
    /// as consecutive relative motions stay below π).
    #[test]
    fn fast_turns_and_a_stopped_camera() {
        let start = SE3::identity();
        let turning = Twist::new(0.5, 0.0, 0.0, 0.0, std::f64::consts::PI / 0.1, 0.0); // 180° per 0.1 s
        let times = [0.0, 0.03, 0.06, 0.09];
        let poses = trajectory(&start, &turning, &times);
        let covs = vec![Matrix6::identity() * 1e-6; 4];
        let p = motion_predict(&poses, &times, 0.12, Some(&covs)).expect("valid");
        let truth = SE3::exp(&(turning * 0.12));
        assert!((p.world_from_cam.inverse() * truth).log().norm() < 1e-8);
        let stopped = vec![SE3::exp(&Twist::new(1.0, 2.0, 3.0, 0.1, 0.2, 0.3)); 4];
        let p = motion_predict(&stopped, &times, 0.2, None).expect("valid");
        assert!((p.world_from_cam.inverse() * stopped[0]).log().norm() < 1e-12);
        assert!(p.details.velocity.norm() < 1e-12);
    }

    /// With the input covariances given, NEES of the prediction is χ²₆ (95 % inside).
    #[test]
    fn prediction_covariance_is_calibrated() {
        let mut rng = SplitMix64::new(2);
        let (sigma_t, sigma_r) = (0.01, 0.01);
        let cov = isotropic_pose_covariance(sigma_t, sigma_r);
        let covs = vec![cov; 4];
        let times = [0.0, 1.0 / 30.0, 2.0 / 30.0, 4.0 / 30.0];
        let trials = 4000;
        let mut inside = 0;
        for _ in 0..trials {
            let start = rng.pose(3.0);
            let angle = rng.uniform_in(0.0, 1.0);
            let v = rng.twist(angle, 0.5);
            let noisy: Vec<SE3> = trajectory(&start, &v, &times)
                .iter()
                .map(|p| *p * SE3::exp(&rng.pose_noise(sigma_t, sigma_r)))
                .collect();
            let t_q = 5.0 / 30.0;
            let p = motion_predict(&noisy, &times, t_q, Some(&covs)).expect("valid");
            let e = (start * SE3::exp(&(v * t_q))).inverse() * p.world_from_cam;
            let e = e.log();
            let nees = e.dot(&(p.covariance.try_inverse().expect("spd") * e));
            inside += usize::from(nees <= chi2::CHI2_6_95);
        }
        let coverage = inside as f64 / trials as f64;
        assert!((0.93..=0.97).contains(&coverage), "coverage {coverage}");
    }

    /// Gauss–Newton Jacobians against central differences of the residuals.
    #[test]
    fn residual_jacobians_match_central_differences() {
        let mut rng = SplitMix64::new(3);
        let poses: Vec<SE3> = (0..4).map(|_| rng.pose(2.0)).collect();
        let times = [0.0, 0.1, 0.25, 0.3];
        let reference = rng.pose(2.0);
        let v = rng.twist(0.7, 0.5);
        let fit = Fit {
            poses: &poses,
            timestamps: &times,
            t_ref: 0.3,
            weights: vec![Matrix6::identity(); 4],
            velocity_information: None,
        };
        let (h, _, _) = fit.normal_equations(&(reference, v));
        // numeric J stacked over the 4 residuals
        let h_step = 1e-6;
        let mut numeric = SMatrix::<f64, 24, 12>::zeros();
        for k in 0..12 {
            let mut d = SVector::<f64, 12>::zeros();
            d[k] = h_step;
            let eval = |d: &SVector<f64, 12>| {
                let r = reference * SE3::exp(&d.fixed_rows::<6>(0).into_owned());
                let vv = v + d.fixed_rows::<6>(6);
                fit.residuals(&r, &vv)
            };
            let (plus, minus) = (eval(&d), eval(&-d));
            for i in 0..4 {
                numeric.fixed_view_mut::<6, 1>(6 * i, k).copy_from(&((plus[i] - minus[i]) / (2.0 * h_step)));
            }
        }
        let h_numeric = numeric.transpose() * numeric;
        assert!((h - h_numeric).abs().max() < 1e-5 * h.abs().max(), "{}", (h - h_numeric).abs().max());
    }

    /// An accelerating camera with tiny pose covariances: the variance factor widens the
    /// prediction enough to contain the truth.
    #[test]
    fn model_mismatch_widens_the_prediction() {
        let times = [0.0, 0.1, 0.2, 0.3];
        let poses: Vec<SE3> =
            times.iter().map(|&t| SE3::exp(&Twist::new(t * t * 5.0, 0.0, 0.0, 0.0, 0.0, 0.0))).collect();
        let covs = vec![Matrix6::identity() * 1e-8; 4];
        let p = motion_predict(&poses, &times, 0.4, Some(&covs)).expect("valid");
        let truth = SE3::exp(&Twist::new(0.8, 0.0, 0.0, 0.0, 0.0, 0.0));
        let e = (truth.inverse() * p.world_from_cam).log();
        let nees = e.dot(&(p.covariance.try_inverse().expect("spd") * e));
        assert!(nees < 100.0, "NEES {nees}: the prediction ignores the misfit");
    }

    #[test]
    fn without_covariances_needs_three_poses_and_estimates_noise() {
        let times = [0.0, 0.1];
        let poses = vec![SE3::identity(); 2];
        assert!(motion_predict(&poses, &times, 0.2, None).is_err());
        let mut rng = SplitMix64::new(4);
        let v = Twist::new(1.0, 0.0, 0.0, 0.0, 0.0, 0.1);
        let times = [0.0, 0.1, 0.2, 0.3];
        let noisy: Vec<SE3> = trajectory(&SE3::identity(), &v, &times)
            .iter()
            .map(|p| {
                *p * SE3::exp(&Twist::new(0.01 * rng.normal(), 0.01 * rng.normal(), 0.01 * rng.normal(), 0.0, 0.0, 0.0))
            })
            .collect();
        let p = motion_predict(&noisy, &times, 0.4, None).expect("valid");
        assert!(p.covariance[(0, 0)] > 1e-6 && p.covariance[(3, 3)] < p.covariance[(0, 0)]);
    }

    /// A query time that would overflow the extrapolation, and covariances that
    /// are not positive semi-definite, are refused by name.
    #[test]
    fn overflowing_query_and_negative_covariances_are_named() {
        let poses = vec![SE3::identity(); 3];
        let times = [0.0, 0.1, 0.2];
        let name = |r: Result<MotionPrediction>| match r {
            Err(GeolocError::InvalidInput { name, .. }) => name,
            other => panic!("expected InvalidInput, got {other:?}"),
        };
        assert_eq!(name(motion_predict(&poses, &times, 1e300, None)), "t_query");
        assert_eq!(name(motion_predict(&poses, &[0.0, 0.1, 1e300], 1e300, None)), "timestamps");
        let mut covs = vec![Matrix6::identity() * 1e-4; 3];
        covs[2] = -covs[2];
        assert_eq!(name(motion_predict(&poses, &times, 0.3, Some(&covs))), "covariances[2]");
        let ok = motion_predict(&poses, &times, 0.2 + MAX_TIME_SPAN_S, None).expect("at the bound");
        assert!(ok.world_from_cam.matrix().iter().all(|v| v.is_finite()));
    }

    /// A pose 3e38 m from the others (found by the adversarial suite): rounding swamps the
    /// fit and the covariance came out indefinite (smallest eigenvalue −1.7e90); now refused,
    /// naming the poses. The same poses near the origin still predict.
    #[test]
    fn a_fit_swamped_by_rounding_is_refused() {
        let times = [0.0, 0.1, 0.2, 0.3];
        let covs = vec![isotropic_pose_covariance(0.01, 0.003); 4];
        let q = Vector6::repeat(0.1);
        let mut poses: Vec<SE3> = times.iter().map(|&t| SE3::new(SO3::identity(), Vector3::new(t, 0.0, 0.0))).collect();
        assert!(motion_predict_with_noise(&poses, &times, 0.4, Some(&covs), &q).is_ok());
        poses[0].translation.x = 3e38;
        let err = motion_predict_with_noise(&poses, &times, 0.4, Some(&covs), &q).expect_err("indefinite");
        assert!(matches!(&err, GeolocError::InvalidInput { name, .. } if name == "poses"), "{err:?}");
    }

    #[test]
    fn bad_input() {
        let poses = vec![SE3::identity(); 3];
        assert!(motion_predict(&poses, &[0.0, 0.1], 0.2, None).is_err());
        assert!(motion_predict(&poses, &[0.0, 0.1, 0.1], 0.2, None).is_err());
        assert!(motion_predict(&poses, &[0.0, f64::NAN, 0.2], 0.3, None).is_err());
        assert!(motion_predict(&poses, &[0.0, 0.1, 0.2], f64::INFINITY, None).is_err());
        let bad = vec![Matrix6::zeros(); 3];
        assert!(motion_predict(&poses, &[0.0, 0.1, 0.2], 0.3, Some(&bad)).is_err());
    }

    /// The prior against the closed form of the linear problem it becomes for a pure
    /// translation along x (the twist of a rotation-free pose is its translation): two poses
    /// p₁ = 0 at t = 0 and p₂ = 0.1 m at t_r = 0.1 s, σ = 1 cm, prior v ~ N(μ, s) on every
    /// axis: minimize ((p₁ − p_r + 0.1v)² + (p₂ − p_r)²)/σ² + (v − μ)²/s over (p_r, v) by its
    /// 2×2 normal equations; T_M at 0.2 s is p_r + 0.1v, its variance [1 0.1] H⁻¹ [1 0.1]ᵀ.
    #[test]
    fn velocity_prior_matches_the_linear_closed_form() {
        let sigma: f64 = 0.01;
        let at = |x: f64| SE3::new(SO3::identity(), Vector3::new(x, 0.0, 0.0));
        let poses = [at(0.0), at(0.1)];
        let covs = [Matrix6::identity() * sigma * sigma; 2];
        let w = 1.0 / (sigma * sigma);
        for (mu, s) in [(0.0, 0.09), (0.5, 0.09), (-0.2, 0.3)] {
            let mut mean = Vector6::zeros();
            mean[0] = mu;
            let prior = VelocityPrior { mean, variance: Vector6::repeat(s) };
            let p = motion_predict_with_prior(&poses, &[0.0, 0.1], 0.2, Some(&covs), &Vector6::zeros(), &prior)
                .expect("valid");
            // A = [[1, −0.1], [1, 0]] for (p_r, v), y = (p₁, p₂) = (0, 0.1); prior rows on v
            let (h11, h12, h22) = (2.0 * w, -0.1 * w, 0.01 * w + 1.0 / s);
            let (b1, b2) = (w * 0.1, mu / s);
            let det = h11 * h22 - h12 * h12;
            let (pr, v) = ((h22 * b1 - h12 * b2) / det, (h11 * b2 - h12 * b1) / det);
            let expected = pr + 0.1 * v;
            let x = p.world_from_cam.translation.x;
            assert!((x - expected).abs() < 1e-10, "μ {mu}: {x} vs {expected}");
            assert!(p.world_from_cam.translation.yz().norm() < 1e-12);
            assert!(v > 0.3 && v < 0.95, "v = {v}"); // pulled from the data's 1 m/s towards μ
            let var = (h22 - 0.2 * h12 + 0.01 * h11) / det; // [1 0.1] H⁻¹ [1 0.1]ᵀ
            assert!((p.covariance[(0, 0)] - var).abs() < 1e-10, "μ {mu}: {} vs {var}", p.covariance[(0, 0)]);
        }
        // a prior far wider than the motion changes nothing; none is none
        let none = motion_predict(&poses, &[0.0, 0.1], 0.2, Some(&covs)).expect("valid");
        for prior in
            [VelocityPrior { mean: Vector6::repeat(0.3), variance: Vector6::repeat(1e14) }, VelocityPrior::default()]
        {
            let p = motion_predict_with_prior(&poses, &[0.0, 0.1], 0.2, Some(&covs), &Vector6::zeros(), &prior)
                .expect("valid");
            assert!((p.world_from_cam.translation - none.world_from_cam.translation).norm() < 1e-9);
            assert!((p.covariance - none.covariance).abs().max() < 1e-9);
        }
    }
}
