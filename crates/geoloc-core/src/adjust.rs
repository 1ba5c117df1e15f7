//! Bundle adjustment of a map whose keyframe poses come from another sensor (SLAM, odometry,
//! a depth camera's tracker): the labels enter as robust priors, not as the truth.
//!
//! Unknowns: per keyframe k the adjusted label-convention pose B_k (world_from_label, the
//! frame the labels are given in), the points P_j (world), and one fixed offset
//! X = label_from_cam shared by all keyframes (a hand-eye calibration: the labels need not be
//! the camera's pose). The camera of keyframe k sits at T_k = B_k X (world_from_cam). With
//! observations u_o of point j(o) in keyframe k(o), labels L_k and the minimized cost
//!
//!   Σ_o ρ_px(‖π(K, T_k⁻¹ P_j) − u_o‖² / (σ_px s_o)²) + Σ_k ρ_label(e_kᵀ Λ e_k) + e_Xᵀ Λ_X e_X,
//!   e_k = log(L_k⁻¹ B_k)^∨,   e_X = log(X)^∨,
//!
//! with s_o the observation's keypoint σ ([`Observation::sigma`], 1 for a map's own
//! problem: see `Map::label_adjustment_problem`),
//! Λ = diag(σ_t⁻², σ_t⁻², σ_t⁻², σ_r⁻², σ_r⁻², σ_r⁻²) the label prior's information
//! (right perturbation, translation first) and Λ_X a weak prior that keeps the offset's
//! translation defined where the data do not determine it. The priors carry the gauge and
//! the scale. Perturbations are right ones: B_k ← B_k Exp(δ_k), X ← X Exp(δ_X), P_j ← P_j + δ_j.
//! With q = B_k⁻¹ P_j (label frame) and p = X⁻¹ q (camera frame):
//!
//!   ∂p/∂δ_k = R_Xᵀ [−I | q^],   ∂p/∂δ_X = [−I | p^],   ∂p/∂P_j = R_Xᵀ R_Bᵀ.
//!
//! Levenberg–Marquardt with IRLS weights; the points are eliminated (Schur complement) and
//! the reduced system over the keyframes (and the offset, last) is solved by the block-envelope
//! Cholesky of [`crate::optim::envelope`], keyframes in capture order. The marginal
//! covariances are the blocks of the reduced system's selected inverse at the solution.
//!
//! When σ_t, σ_r are not given they are estimated: a first adjustment with wide priors
//! ([`WIDE_LABEL_SIGMA`]) lets the images shape the trajectory; the robust scale of its label
//! corrections, σ² = median(‖e‖²) / median(χ²₃), sets the priors of the next pass, and so on
//! until σ changes by less than 10 % (at most [`SCALE_PASSES`] passes): a run of wrong labels
//! inflates the first scale, and each robust pass pulls less towards it. Label errors drift
//! (neighbouring keyframes share them), so the final σ is that scatter times √τ, τ the
//! corrections' integrated autocorrelation time ([`correlation_lengths`]): n i.i.d. priors
//! of the scatter would hold the trajectory's slow shape as if they were n independent
//! measurements of it, where they are about n/τ.
//!
//! After the first pass and again before the last adjustment every observation is classified
//! afresh at the current state: used when its reprojection error is at most `outlier_px`. The
//! *candidates* ([`bundle_adjust_with_candidates`]) are observations left out of the start —
//! a map's views that the triangulation from the labels rejected — and join only when they
//! reproject within `readmit_px`: where a run of labels is displaced, the triangulation keeps
//! the views on one side of the displacement and rejects the other side's, which are exactly
//! the ones that tie the run to the rest; once the first pass has moved the run most of the
//! way, they fit again and pull it the rest of the way (a synthetic run displaced by
//! 20 cm / 5°: 1–3.5 cm / 0.1–0.55° off after the adjustment without them, 0.1–0.8 cm /
//! 0.01–0.13° with them).
//!
//! Every sum runs in a fixed order (per point, then the points in order): the same input gives
//! the same bits with any thread count.

use nalgebra::{Matrix3, Matrix6, Vector2, Vector3, Vector6};

use crate::camera::Camera;
use crate::error::{GeolocError, Result};
use crate::lie::SE3;
use crate::optim::RobustLoss;

/// The label priors of the first, shape-finding adjustment when σ is estimated: wide
/// against any plausible label error (10 cm, 3°), still fixing the gauge and scale.
pub const WIDE_LABEL_SIGMA: LabelSigma = LabelSigma { translation_m: 0.1, rotation_rad: 0.052_359_877_559_829_89 };

/// Most passes of the label-σ estimate.
const SCALE_PASSES: usize = 6;

/// The σ an adjustment can whiten by (px for pixels, m and rad for poses): the residuals are
/// scaled by σ⁻¹ and the normal equations by σ⁻², which beyond this range over- or
/// underflow (a keypoint σ of 1e-200 px makes every cost infinite).
pub const SIGMA_RANGE: (f64, f64) = (1e-9, 1e9);

/// Whether `sigma` is finite and within [`SIGMA_RANGE`].
fn usable_sigma(sigma: f64) -> bool {
    (SIGMA_RANGE.0..=SIGMA_RANGE.1).contains(&sigma)
}

/// The error naming `name`, a σ outside [`SIGMA_RANGE`].
fn sigma_error(name: impl Into<String>, sigma: f64) -> GeolocError {
    GeolocError::invalid(name, format!("σ must lie in [{:e}, {:e}], got {sigma}", SIGMA_RANGE.0, SIGMA_RANGE.1))
}

/// Standard deviations of a label's error (right perturbation of world_from_label).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LabelSigma {
    /// σ_t per translation axis (m).
    pub translation_m: f64,
    /// σ_r per rotation axis (rad).
    pub rotation_rad: f64,
}

impl LabelSigma {
    fn information(&self) -> Vector6<f64> {
        let (t, r) = (self.translation_m.powi(-2), self.rotation_rad.powi(-2));
        Vector6::new(t, t, t, r, r, r)
    }

    fn check(&self, name: &str) -> Result<()> {
        match [self.translation_m, self.rotation_rad].into_iter().find(|v| !usable_sigma(*v)) {
            Some(v) => Err(sigma_error(name, v)),
            None => Ok(()),
        }
    }
}

/// How the map is adjusted (see the module doc).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AdjustmentOptions {
    /// σ of a keypoint (px, default 1).
    pub pixel_sigma_px: f64,
    /// Kernel of the reprojection residuals, width in σ (default Huber 2).
    pub pixel_loss: RobustLoss,
    /// The labels' σ; None (the default) estimates it from the data.
    pub label_sigma: Option<LabelSigma>,
    /// Kernel of the label priors, width in σ (default Cauchy 3: a run of labels far from
    /// the images loses its pull instead of bending the trajectory).
    pub label_loss: RobustLoss,
    /// Whether the label-to-camera offset X is estimated (default true; else X = I).
    pub estimate_offset: bool,
    /// The offset's prior around the identity (default 0.2 m, 0.2 rad per axis).
    pub offset_sigma: LabelSigma,
    /// Levenberg–Marquardt iterations per round (default 40).
    pub max_iterations: usize,
    /// Observations whose reprojection error exceeds this (px) after a round are dropped
    /// before the next (default 4).
    pub outlier_px: f64,
    /// Candidate observations join when they reproject within this (px, default 2: the
    /// Huber kernel's width, where a good observation lies; at 4 px the views the labels'
    /// triangulation rejected on 7-Scenes brought mismatches in with them, 0.31 → 0.38°
    /// median off the reference on frames 115–699).
    pub readmit_px: f64,
}

impl Default for AdjustmentOptions {
    fn default() -> Self {
        Self {
            pixel_sigma_px: 1.0,
            pixel_loss: RobustLoss::Huber { width: 2.0 },
            label_sigma: None,
            label_loss: RobustLoss::Cauchy { width: 3.0 },
            estimate_offset: true,
            offset_sigma: LabelSigma { translation_m: 0.2, rotation_rad: 0.2 },
            max_iterations: 40,
            outlier_px: 4.0,
            readmit_px: 2.0,
        }
    }
}

impl AdjustmentOptions {
    /// Checks the options.
    ///
    /// # Errors
    /// A σ outside [`SIGMA_RANGE`], an outlier threshold that is not finite and > 0, or no
    /// iteration (each named).
    pub fn check(&self) -> Result<()> {
        if !usable_sigma(self.pixel_sigma_px) {
            return Err(sigma_error("pixel_sigma_px", self.pixel_sigma_px));
        }
        for (name, px) in [("outlier_px", self.outlier_px), ("readmit_px", self.readmit_px)] {
            if !(px.is_finite() && px > 0.0) {
                return Err(GeolocError::invalid(name, format!("must be finite and > 0, got {px}")));
            }
        }
        if let Some(s) = &self.label_sigma {
            s.check("label_sigma")?;
        }
        self.offset_sigma.check("offset_sigma")?;
        if self.max_iterations == 0 {
            return Err(GeolocError::invalid("max_iterations", "must be ≥ 1"));
        }
        Ok(())
    }
}

/// One observation: keyframe `keyframe` sees point `point` at `pixel` (undistorted px), a
/// keypoint of relative σ `sigma` (its detector scale, ORB 1.2^level; 1 for a keypoint of the
/// finest level): its residual is whitened by `pixel_sigma_px`·`sigma`; it is an outlier
/// beyond `outlier_px` whatever its σ.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Observation {
    /// The observing keyframe.
    pub keyframe: usize,
    /// The point.
    pub point: usize,
    /// The pixel.
    pub pixel: Vector2<f64>,
    /// The keypoint's σ relative to `pixel_sigma_px` (> 0; times `pixel_sigma_px` within [`SIGMA_RANGE`]).
    pub sigma: f64,
}

/// The adjusted map (see the module doc).
#[derive(Clone, Debug, PartialEq)]
pub struct Adjustment {
    /// B_k: the adjusted world_from_label poses, one per keyframe.
    pub label_poses: Vec<SE3>,
    /// X = label_from_cam.
    pub offset: SE3,
    /// The points, adjusted.
    pub points: Vec<Vector3<f64>>,
    /// Marginal covariance of each B_k (right perturbation, translation first).
    pub label_pose_covariances: Vec<Matrix6<f64>>,
    /// Per keyframe k, the covariance of the mean error of its neighbours' B_a seen from k
    /// (right perturbation of B_k): the part of the map's error a frame localized beside k
    /// shares (see `neighbourhood_covariances` in the adjustment's problem).
    pub label_neighbourhood_covariances: Vec<Matrix6<f64>>,
    /// Marginal covariance of each camera pose T_k = B_k X (right perturbation).
    pub camera_pose_covariances: Vec<Matrix6<f64>>,
    /// Covariance of X (zero when not estimated).
    pub offset_covariance: Matrix6<f64>,
    /// Marginal covariance of each point (m², world axes).
    pub point_covariances: Vec<Matrix3<f64>>,
    /// Per observation, then per candidate: whether the last round used it.
    pub inliers: Vec<bool>,
    /// The labels' σ the final round used (given, or estimated: the corrections' scatter
    /// times √τ).
    pub label_sigma: LabelSigma,
    /// τ of the corrections (translation, rotation; keyframes) when σ was estimated, else 1.
    pub correlation_keyframes: (f64, f64),
    /// The final robust cost and its start.
    pub cost: (f64, f64),
    /// RMS reprojection error of the inlier observations (px) at the start and the end.
    pub rms_px: (f64, f64),
    /// Levenberg–Marquardt iterations over all rounds.
    pub iterations: usize,
}

impl Adjustment {
    /// The camera poses T_k = B_k X (world_from_cam).
    pub fn camera_poses(&self) -> Vec<SE3> {
        self.label_poses.iter().map(|b| *b * self.offset).collect()
    }

    /// Per keyframe: e_k = log(L_k⁻¹ B_k), the correction of label k, and its significance
    /// e_kᵀ Σ_k⁻¹ e_k under the adjustment's marginal covariance Σ_k.
    pub fn corrections(&self, labels: &[SE3]) -> Vec<(Vector6<f64>, f64)> {
        labels
            .iter()
            .zip(&self.label_poses)
            .zip(&self.label_pose_covariances)
            .map(|((l, b), c)| correction(l, b, c))
            .collect()
    }
}

/// The correction of label `label` (world_from_label) to `adjusted`, e = log(L⁻¹ B) (right
/// perturbation, translation first), and its significance eᵀ Σ⁻¹ e under `covariance` Σ
/// (infinite when Σ is singular).
pub fn correction(label: &SE3, adjusted: &SE3, covariance: &Matrix6<f64>) -> (Vector6<f64>, f64) {
    let e = (label.inverse() * *adjusted).log();
    let m = covariance.try_inverse().map_or(f64::INFINITY, |i| (e.transpose() * i * e)[0]);
    (e, m)
}

/// Adjusts the map: labels `labels` (world_from_label), points `points` (world, a start), the
/// observations and the (nominal, keypoints corrected) camera; see the module doc.
///
/// # Errors
/// Bad options; no label; a label or point that is not finite; an observation naming a
/// keyframe or point out of range (`observations[i]`); a system that stays singular
/// (`observations`: a keyframe or point that nothing constrains).
pub fn bundle_adjust(
    camera: &Camera,
    labels: &[SE3],
    points: &[Vector3<f64>],
    observations: &[Observation],
    options: &AdjustmentOptions,
) -> Result<Adjustment> {
    bundle_adjust_from(camera, labels, (labels, &SE3::identity()), points, observations, options)
}

/// [`bundle_adjust`] starting from the label-convention poses and offset `start` instead of
/// the labels and the identity (a map re-adjusted after its keypoints were corrected).
///
/// # Errors
/// As [`bundle_adjust`]; `start` with another number of poses than `labels`.
pub fn bundle_adjust_from(
    camera: &Camera,
    labels: &[SE3],
    start: (&[SE3], &SE3),
    points: &[Vector3<f64>],
    observations: &[Observation],
    options: &AdjustmentOptions,
) -> Result<Adjustment> {
    bundle_adjust_with_candidates(camera, labels, start, points, observations, &[], options)
}

/// [`bundle_adjust_from`] with `candidates`: observations left out of the start that join
/// the adjustment when they reproject within `readmit_px` after its first pass or before its
/// last adjustment (see the module doc). [`Adjustment::inliers`] lists the observations, then
/// the candidates.
///
/// # Errors
/// As [`bundle_adjust_from`]; a candidate naming a keyframe or point out of range
/// (`candidates[i]`).
pub fn bundle_adjust_with_candidates(
    camera: &Camera,
    labels: &[SE3],
    start: (&[SE3], &SE3),
    points: &[Vector3<f64>],
    observations: &[Observation],
    candidates: &[Observation],
    options: &AdjustmentOptions,
) -> Result<Adjustment> {
    options.check()?;
    check_inputs(labels, points, observations, options.pixel_sigma_px, "observations")?;
    check_inputs(labels, points, candidates, options.pixel_sigma_px, "candidates")?;
    if start.0.len() != labels.len() {
        return Err(GeolocError::invalid("start", format!("{} poses for {} labels", start.0.len(), labels.len())));
    }
    let mut state = State { labels: start.0.to_vec(), offset: *start.1, points: points.to_vec() };
    check_start(camera, &state, observations, options.pixel_sigma_px)?;
    let given = observations.len();
    let all: Vec<Observation> = observations.iter().chain(candidates).copied().collect();
    let observations = &all[..];
    let classify = |state: &State, inliers: &mut [bool]| {
        classify_observations(camera, state, observations, given, options, inliers);
    };
    let mut inliers: Vec<bool> = (0..observations.len()).map(|i| i < given).collect();
    let start_rms = rms_px(camera, &state, observations, &inliers);
    let mut iterations = 0;
    let mut start_cost = None;
    let mut correlation = (1.0, 1.0);
    let label_sigma = match options.label_sigma {
        Some(s) => s,
        None => {
            // scale re-estimation: each pass's corrections set the next pass's σ, until σ
            // settles (a run of wrong labels inflates the first, wide pass's scale)
            let mut sigma = WIDE_LABEL_SIGMA;
            for pass in 0..SCALE_PASSES {
                let problem = Problem::new(camera, labels, observations, &inliers, options, sigma);
                let (s, its, c0) = problem.minimize(state)?;
                iterations += its;
                start_cost.get_or_insert(c0);
                state = s;
                if pass == 0 {
                    classify(&state, &mut inliers);
                }
                let next = estimate_label_sigma(labels, &state.labels);
                let settled = (next.translation_m / sigma.translation_m - 1.0).abs() < 0.1
                    && (next.rotation_rad / sigma.rotation_rad - 1.0).abs() < 0.1;
                sigma = next;
                if settled {
                    break;
                }
            }
            // the corrections of neighbouring keyframes are correlated (labels drift): an
            // i.i.d. prior of the scatter σ would hold the trajectory's slow shape τ times
            // too tightly, so σ grows by √τ
            let inflated = |sigma: LabelSigma, tau: (f64, f64)| LabelSigma {
                translation_m: sigma.translation_m * tau.0.sqrt(),
                rotation_rad: sigma.rotation_rad * tau.1.sqrt(),
            };
            // ... but neither τ nor the scatter counts the corrections that prior holds as
            // outliers (a run of wrong labels is the kernel's, not drift nor noise)
            let prior = inflated(sigma, correlation_lengths(labels, &state.labels));
            correlation = correlation_lengths_within(labels, &state.labels, Some(prior));
            inflated(estimate_label_sigma_within(labels, &state.labels, Some(prior)), correlation)
        }
    };
    let problem = Problem::new(camera, labels, observations, &inliers, options, label_sigma);
    let (s, its, c0) = problem.minimize(state)?;
    iterations += its;
    state = s;
    classify(&state, &mut inliers);
    let problem = Problem::new(camera, labels, observations, &inliers, options, label_sigma);
    let (s, its, _) = problem.minimize(state)?;
    iterations += its;
    state = s;
    let final_cost = problem.cost(&state);
    let covariances = problem.covariances(&state)?;
    let end_rms = rms_px(camera, &state, observations, &inliers);
    Ok(Adjustment {
        camera_pose_covariances: covariances.camera_poses(&state.offset),
        label_pose_covariances: covariances.label_poses,
        label_neighbourhood_covariances: covariances.label_neighbourhoods,
        offset_covariance: covariances.offset,
        point_covariances: covariances.points,
        label_poses: state.labels,
        offset: state.offset,
        points: state.points,
        inliers,
        label_sigma,
        correlation_keyframes: correlation,
        cost: (start_cost.unwrap_or(c0), final_cost),
        rms_px: (start_rms, end_rms),
        iterations,
    })
}

/// The covariance of the camera pose T = B X that a label pose B with covariance `covariance`
/// (right perturbation) implies with X = `offset` held: Ad_{X⁻¹} Σ Ad_{X⁻¹}ᵀ (exactly symmetric).
///
/// What a keyframe's camera pose is known to *relative to the labels' frame*: the offset's own
/// uncertainty Σ_X moves every camera pose and the points triangulated from them together,
/// and a pose located against them and reported in the labels' convention, T X⁻¹, takes the
/// same X back off — so Σ_X is no part of the error of that answer (it is added where a
/// result is given as the camera's own pose).
pub(crate) fn camera_frame_covariance(offset: &SE3, covariance: &Matrix6<f64>) -> Matrix6<f64> {
    let a = offset.inverse().adjoint();
    let c = a * covariance * a.transpose();
    (c + c.transpose()) * 0.5
}

/// Labels and points finite; each observation's keyframe and point in range, its pixel
/// finite and its whitening σ (`pixel_sigma_px` × its σ) usable.
fn check_inputs(
    labels: &[SE3],
    points: &[Vector3<f64>],
    observations: &[Observation],
    pixel_sigma_px: f64,
    name: &str,
) -> Result<()> {
    if labels.is_empty() {
        return Err(GeolocError::invalid("labels", "the adjustment needs at least one keyframe"));
    }
    if let Some(k) = labels.iter().position(|l| !(l.translation.iter().all(|v| v.is_finite()))) {
        return Err(GeolocError::NonFinite { name: "labels".into(), index: k });
    }
    if let Some(j) = points.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
        return Err(GeolocError::NonFinite { name: "points".into(), index: j });
    }
    for (i, o) in observations.iter().enumerate() {
        if o.keyframe >= labels.len()
            || o.point >= points.len()
            || !o.pixel.iter().all(|v| v.is_finite())
            || !usable_sigma(o.sigma * pixel_sigma_px)
        {
            return Err(GeolocError::invalid(
                format!("{name}[{i}]"),
                format!(
                    "keyframe {} (of {} labels), point {} (of {} points), pixel {:?}, σ {}",
                    o.keyframe,
                    labels.len(),
                    o.point,
                    points.len(),
                    o.pixel,
                    o.sigma
                ),
            ));
        }
    }
    Ok(())
}

/// Every observation's whitened residual at the start has a finite square (a pixel 1e300 px
/// from its point's projection would make the cost infinite before the first step).
fn check_start(camera: &Camera, state: &State, observations: &[Observation], pixel_sigma_px: f64) -> Result<()> {
    for (i, o) in observations.iter().enumerate() {
        if let Some(r) = state.residual_px(camera, o)
            && !(r / (pixel_sigma_px * o.sigma)).norm_squared().is_finite()
        {
            return Err(GeolocError::invalid(
                format!("observations[{i}]"),
                format!(
                    "pixel {:?} lies {:e} px from its point's projection at the start (the points, start and offset given)",
                    o.pixel,
                    r.norm()
                ),
            ));
        }
    }
    Ok(())
}

mod problem;
mod scale;

use problem::{Problem, State, classify_observations, rms_px};
pub use scale::{CORRELATION_SPACING, correlation_lengths, correlation_lengths_within, robust_sigma, skeleton};
use scale::{estimate_label_sigma, estimate_label_sigma_within};

#[cfg(test)]
mod tests;
