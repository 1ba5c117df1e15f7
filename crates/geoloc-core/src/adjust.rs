//! Bundle adjustment of a map whose keyframe poses come from another sensor (SLAM, odometry,
//! a depth camera's tracker): the labels enter as robust priors, not as the truth.
//!
//! Unknowns: per keyframe k the adjusted label-convention pose B_k (world_from_label, the
//! frame the labels are given in), the points P_j (world), and one fixed offset
//! X = label_from_cam shared by all keyframes (a hand-eye calibration: the labels need not be
//! the camera's pose). The camera of keyframe k sits at T_k = B_k X (world_from_cam). With
//! observations u_o of point j(o) in keyframe k(o), labels L_k and the minimized cost
//!
//!   Σ_o ρ_px(‖π(K, T_k⁻¹ P_j) − u_o‖² / σ_px²) + Σ_k ρ_label(e_kᵀ Λ e_k) + e_Xᵀ Λ_X e_X,
//!   e_k = log(L_k⁻¹ B_k)^∨,   e_X = log(X)^∨,
//!
//! with Λ = diag(σ_t⁻², σ_t⁻², σ_t⁻², σ_r⁻², σ_r⁻², σ_r⁻²) the label prior's information
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
//! measurements of it, where they are about n/τ. Observations whose
//! reprojection error exceeds `outlier_px` are dropped after the first pass and again before
//! the last adjustment.
//!
//! Every sum runs in a fixed order (per point, then the points in order): the same input gives
//! the same bits with any thread count.

use nalgebra::{Matrix2x3, Matrix3, Matrix6, SMatrix, Vector2, Vector3, Vector6};

use crate::camera::Camera;
use crate::error::{GeolocError, Result};
use crate::lie::{SE3, se3, so3};
use crate::optim::RobustLoss;
use crate::optim::envelope::BlockEnvelope;
use crate::parallel::map_slice;

type Matrix6x3 = SMatrix<f64, 6, 3>;
type Matrix2x6 = SMatrix<f64, 2, 6>;

/// The median of the χ²₃ distribution: median(‖e‖²/σ²) of a 3-D isotropic Gaussian.
const CHI2_3_MEDIAN: f64 = 2.365_973_884_375_61;

/// The label priors of the first, shape-finding adjustment when σ is estimated: wide
/// against any plausible label error (10 cm, 3°), still fixing the gauge and scale.
pub const WIDE_LABEL_SIGMA: LabelSigma = LabelSigma { translation_m: 0.1, rotation_rad: 0.052_359_877_559_829_89 };

/// Most passes of the label-σ estimate.
const SCALE_PASSES: usize = 6;

/// Smallest estimated label σ (1 mm, 0.05°): labels that agree with the images to the
/// last bit still get a finite prior.
const MIN_LABEL_SIGMA: LabelSigma = LabelSigma { translation_m: 1e-3, rotation_rad: 8.726_646_259_971_648e-4 };

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
        for v in [self.translation_m, self.rotation_rad] {
            if !(v.is_finite() && v > 0.0) {
                return Err(GeolocError::invalid(name, format!("σ must be finite and > 0, got {v}")));
            }
        }
        Ok(())
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
        }
    }
}

impl AdjustmentOptions {
    /// Checks the options.
    ///
    /// # Errors
    /// A σ or threshold that is not finite and > 0, or no iteration (each named).
    pub fn check(&self) -> Result<()> {
        for (name, v) in [("pixel_sigma_px", self.pixel_sigma_px), ("outlier_px", self.outlier_px)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(GeolocError::invalid(name, format!("must be finite and > 0, got {v}")));
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

/// One observation: keyframe `keyframe` sees point `point` at `pixel` (undistorted px).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Observation {
    /// The observing keyframe.
    pub keyframe: usize,
    /// The point.
    pub point: usize,
    /// The pixel.
    pub pixel: Vector2<f64>,
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
    /// Marginal covariance of each camera pose T_k = B_k X (right perturbation).
    pub camera_pose_covariances: Vec<Matrix6<f64>>,
    /// Covariance of X (zero when not estimated).
    pub offset_covariance: Matrix6<f64>,
    /// Marginal covariance of each point (m², world axes).
    pub point_covariances: Vec<Matrix3<f64>>,
    /// Per observation: whether the last round used it.
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
            .map(|((l, b), c)| {
                let e = (l.inverse() * *b).log();
                let m = c.try_inverse().map_or(f64::INFINITY, |i| (e.transpose() * i * e)[0]);
                (e, m)
            })
            .collect()
    }
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
    options.check()?;
    check_inputs(labels, points, observations)?;
    if start.0.len() != labels.len() {
        return Err(GeolocError::invalid("start", format!("{} poses for {} labels", start.0.len(), labels.len())));
    }
    let mut state = State { labels: start.0.to_vec(), offset: *start.1, points: points.to_vec() };
    let mut inliers = vec![true; observations.len()];
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
                    drop_outliers(camera, &state, observations, options.outlier_px, &mut inliers);
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
            correlation = correlation_lengths(labels, &state.labels);
            LabelSigma {
                translation_m: sigma.translation_m * correlation.0.sqrt(),
                rotation_rad: sigma.rotation_rad * correlation.1.sqrt(),
            }
        }
    };
    let problem = Problem::new(camera, labels, observations, &inliers, options, label_sigma);
    let (s, its, c0) = problem.minimize(state)?;
    iterations += its;
    state = s;
    drop_outliers(camera, &state, observations, options.outlier_px, &mut inliers);
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

fn check_inputs(labels: &[SE3], points: &[Vector3<f64>], observations: &[Observation]) -> Result<()> {
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
        if o.keyframe >= labels.len() || o.point >= points.len() || !o.pixel.iter().all(|v| v.is_finite()) {
            return Err(GeolocError::invalid(
                format!("observations[{i}]"),
                format!(
                    "keyframe {} of {}, point {} of {}, pixel {:?}",
                    o.keyframe,
                    labels.len(),
                    o.point,
                    points.len(),
                    o.pixel
                ),
            ));
        }
    }
    Ok(())
}

/// σ² = median(‖e‖²) / median(χ²₃) of the translation and rotation parts of the label
/// corrections e_k = log(L_k⁻¹ B_k), floored at [`MIN_LABEL_SIGMA`].
fn estimate_label_sigma(labels: &[SE3], adjusted: &[SE3]) -> LabelSigma {
    let (mut t, mut r): (Vec<f64>, Vec<f64>) = labels
        .iter()
        .zip(adjusted)
        .map(|(l, b)| {
            let e = (l.inverse() * *b).log();
            (se3::rho(&e).norm_squared(), se3::phi(&e).norm_squared())
        })
        .unzip();
    let median = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    LabelSigma {
        translation_m: (median(&mut t) / CHI2_3_MEDIAN).sqrt().max(MIN_LABEL_SIGMA.translation_m),
        rotation_rad: (median(&mut r) / CHI2_3_MEDIAN).sqrt().max(MIN_LABEL_SIGMA.rotation_rad),
    }
}

/// Spacing of the keyframes the correlation length is measured over: each at least this far
/// (m) or this much turned (rad) from the last one taken. Keyframes closer than that see the
/// same images: the adjustment moves them together whatever their labels did, and counting
/// them would measure its own smoothing.
pub const CORRELATION_SPACING: (f64, f64) = (0.05, 0.052_359_877_559_829_89);

/// τ = 1 + 2 Σ_{l ≥ 1} r(l), the integrated autocorrelation time of the label corrections
/// e_k = log(L_k⁻¹ B_k) along the trajectory, for the translation and the rotation axes: over
/// the keyframes thinned to [`CORRELATION_SPACING`] in capture order, r(l) the lag-l
/// autocorrelation averaged over the three axes, summed while positive (Geyer's initial
/// positive sequence), τ ≥ 1 (in thinned keyframes).
pub fn correlation_lengths(labels: &[SE3], adjusted: &[SE3]) -> (f64, f64) {
    let kept = skeleton(adjusted);
    let e: Vec<Vector6<f64>> = kept.iter().map(|&k| (labels[k].inverse() * adjusted[k]).log()).collect();
    let n = e.len();
    let tau = |axes: std::ops::Range<usize>| {
        let series: Vec<Vec<f64>> = axes
            .map(|a| {
                let mean = e.iter().map(|v| v[a]).sum::<f64>() / n as f64;
                e.iter().map(|v| v[a] - mean).collect()
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

/// Marks observations whose reprojection error exceeds `max_px` (or that lie behind the
/// camera) as outliers.
fn drop_outliers(camera: &Camera, state: &State, observations: &[Observation], max_px: f64, inliers: &mut [bool]) {
    for (o, inlier) in observations.iter().zip(inliers.iter_mut()) {
        if *inlier {
            *inlier = state.residual_px(camera, o).is_some_and(|r| r.norm() <= max_px);
        }
    }
}

fn rms_px(camera: &Camera, state: &State, observations: &[Observation], inliers: &[bool]) -> f64 {
    let (mut sum, mut n) = (0.0, 0usize);
    for (o, _) in observations.iter().zip(inliers).filter(|(_, i)| **i) {
        if let Some(r) = state.residual_px(camera, o) {
            sum += r.norm_squared();
            n += 1;
        }
    }
    if n == 0 { 0.0 } else { (sum / n as f64).sqrt() }
}

/// The unknowns.
#[derive(Clone, Debug)]
struct State {
    /// B_k.
    labels: Vec<SE3>,
    /// X.
    offset: SE3,
    /// P_j.
    points: Vec<Vector3<f64>>,
}

/// Smallest depth (m) of a point in front of a camera.
const MIN_DEPTH_M: f64 = 1e-3;

impl State {
    /// (q, p): the point in the label frame and in the camera frame.
    fn frames(&self, o: &Observation) -> (Vector3<f64>, Vector3<f64>) {
        let b = &self.labels[o.keyframe];
        let q = b.rotation.matrix().tr_mul(&(self.points[o.point] - b.translation));
        let p = self.offset.rotation.matrix().tr_mul(&(q - self.offset.translation));
        (q, p)
    }

    /// π(K, T_k⁻¹ P_j) − u, None behind the camera.
    fn residual_px(&self, camera: &Camera, o: &Observation) -> Option<Vector2<f64>> {
        let (_, p) = self.frames(o);
        (p.z > MIN_DEPTH_M).then(|| camera.project_cam(&p) - o.pixel)
    }
}

/// One observation's linearization: the whitened residual r, its robust weight, and the
/// Jacobians of r (2×6 keyframe, 2×6 offset, 2×3 point).
struct Linearized {
    r: Vector2<f64>,
    weight: f64,
    j_label: Matrix2x6,
    j_offset: Matrix2x6,
    j_point: Matrix2x3<f64>,
}

/// One observation's camera-side blocks: (keyframe k, U_kk, U_Xk, g_k).
type CameraBlocks = (usize, Matrix6<f64>, Matrix6<f64>, Vector6<f64>);

/// Per point: V_j, g_j, and the couplings with its observers (keyframe order) and the offset.
struct PointBlock {
    v: Matrix3<f64>,
    g: Vector3<f64>,
    /// (keyframe, W_kj = Σ w J_kᵀ J_j).
    couplings: Vec<(usize, Matrix6x3)>,
    /// W_Xj.
    offset: Matrix6x3,
    /// The camera-side blocks this point adds: per observer, (keyframe, U_kk, U_Xk, g_k),
    /// and the offset's (U_XX, g_X).
    camera: Vec<CameraBlocks>,
    offset_block: (Matrix6<f64>, Vector6<f64>),
    cost: f64,
}

impl PointBlock {
    fn empty(capacity: usize) -> Self {
        Self {
            v: Matrix3::zeros(),
            g: Vector3::zeros(),
            couplings: Vec::with_capacity(capacity),
            offset: Matrix6x3::zeros(),
            camera: Vec::with_capacity(capacity),
            offset_block: (Matrix6::zeros(), Vector6::zeros()),
            cost: 0.0,
        }
    }
}

/// Smallest ratio of a point block's eigenvalues for the point to be adjusted.
const MIN_POINT_CONDITION: f64 = 1e-8;

/// Whether V_j is positive definite with λ_min ≥ [`MIN_POINT_CONDITION`] λ_max.
fn well_conditioned(v: &Matrix3<f64>) -> bool {
    let e = v.symmetric_eigenvalues();
    let (lo, hi) = (e.min(), e.max());
    lo.is_finite() && hi > 0.0 && lo >= MIN_POINT_CONDITION * hi
}

/// The adjustment problem with a fixed observation set.
struct Problem<'a> {
    camera: &'a Camera,
    labels: &'a [SE3],
    observations: &'a [Observation],
    /// Per point: its inlier observations, in keyframe order.
    by_point: Vec<Vec<usize>>,
    options: &'a AdjustmentOptions,
    label_information: Vector6<f64>,
    /// Size of the reduced system in blocks: keyframes, then the offset if estimated.
    blocks: usize,
    /// The reduced system's envelope.
    first: Vec<usize>,
}

/// The reduced (camera-side) normal equations and what back-substitution needs.
struct Reduced {
    s: BlockEnvelope,
    rhs: Vec<f64>,
    points: Vec<PointBlock>,
}

/// Marginal covariances at the solution.
struct Covariances {
    label_poses: Vec<Matrix6<f64>>,
    /// Cov(δ_k, δ_X) per keyframe.
    label_offset: Vec<Matrix6<f64>>,
    offset: Matrix6<f64>,
    points: Vec<Matrix3<f64>>,
}

impl Covariances {
    /// Σ_T of T_k = B_k X: δT = Ad_{X⁻¹} δ_k + δ_X.
    fn camera_poses(&self, offset: &SE3) -> Vec<Matrix6<f64>> {
        let a = offset.inverse().adjoint();
        self.label_poses
            .iter()
            .zip(&self.label_offset)
            .map(|(c, cx)| {
                let m = a * c * a.transpose() + a * cx + cx.transpose() * a.transpose() + self.offset;
                (m + m.transpose()) * 0.5
            })
            .collect()
    }
}

/// Marquardt damping: the first λ, and its growth and shrink factors.
const INITIAL_LAMBDA: f64 = 1e-4;
const LAMBDA_UP: f64 = 10.0;
const LAMBDA_DOWN: f64 = 0.3;
/// Relative cost decrease below which the minimization has converged.
const COST_TOLERANCE: f64 = 1e-6;

impl<'a> Problem<'a> {
    fn new(
        camera: &'a Camera,
        labels: &'a [SE3],
        observations: &'a [Observation],
        inliers: &[bool],
        options: &'a AdjustmentOptions,
        label_sigma: LabelSigma,
    ) -> Self {
        let n_points = observations.iter().map(|o| o.point + 1).max().unwrap_or(0);
        let mut by_point: Vec<Vec<usize>> = vec![Vec::new(); n_points];
        for (i, o) in observations.iter().enumerate() {
            if inliers[i] {
                by_point[o.point].push(i);
            }
        }
        for obs in &mut by_point {
            obs.sort_by_key(|&i| (observations[i].keyframe, i));
            // one observation per keyframe: a second one of the same keyframe is dropped
            obs.dedup_by_key(|i| observations[*i].keyframe);
            if obs.len() < 2 {
                obs.clear();
            }
        }
        let n = labels.len();
        let blocks = n + usize::from(options.estimate_offset);
        let mut first: Vec<usize> = (0..blocks).collect();
        if options.estimate_offset {
            first[n] = 0;
        }
        for obs in &by_point {
            if let Some(&lowest) = obs.first() {
                let lowest = observations[lowest].keyframe;
                for &i in obs {
                    let k = observations[i].keyframe;
                    first[k] = first[k].min(lowest);
                }
            }
        }
        Self {
            camera,
            labels,
            observations,
            by_point,
            options,
            label_information: label_sigma.information(),
            blocks,
            first,
        }
    }

    /// Linearizes observation `o` at `state` (None behind the camera).
    fn linearize(&self, state: &State, o: &Observation) -> Option<Linearized> {
        let (q, p) = state.frames(o);
        if p.z <= MIN_DEPTH_M {
            return None;
        }
        let sigma = self.options.pixel_sigma_px;
        let r = (self.camera.project_cam(&p) - o.pixel) / sigma;
        let weight = self.options.pixel_loss.weight(r.norm_squared());
        let j_p = self.camera.j_uv_pcam(&p) / sigma;
        let rx_t = state.offset.rotation.matrix().transpose();
        let j_pr = j_p * rx_t;
        let mut j_label = Matrix2x6::zeros();
        j_label.fixed_view_mut::<2, 3>(0, 0).copy_from(&(-j_pr));
        j_label.fixed_view_mut::<2, 3>(0, 3).copy_from(&(j_pr * so3::hat(&q)));
        let mut j_offset = Matrix2x6::zeros();
        j_offset.fixed_view_mut::<2, 3>(0, 0).copy_from(&(-j_p));
        j_offset.fixed_view_mut::<2, 3>(0, 3).copy_from(&(j_p * so3::hat(&p)));
        let j_point = j_pr * state.labels[o.keyframe].rotation.matrix().transpose();
        Some(Linearized { r, weight, j_label, j_offset, j_point })
    }

    /// The cost of an observation behind the camera: a residual of 100 σ.
    fn behind_cost(&self) -> f64 {
        self.options.pixel_loss.cost(1e4)
    }

    fn point_block(&self, state: &State, obs: &[usize]) -> PointBlock {
        let block = PointBlock::empty(obs.len());
        let mut block = block;
        self.accumulate(state, obs, &mut block);
        if !well_conditioned(&block.v) {
            // a point whose position the observations barely fix (a ray pencil with no
            // parallax): eliminating it would only add rounding to the reduced system
            let cost = block.cost;
            block = PointBlock { cost, ..PointBlock::empty(obs.len()) };
        }
        block
    }

    fn accumulate(&self, state: &State, obs: &[usize], block: &mut PointBlock) {
        for &i in obs {
            let o = &self.observations[i];
            let Some(l) = self.linearize(state, o) else {
                block.cost += self.behind_cost();
                continue;
            };
            let w = l.weight;
            block.cost += self.options.pixel_loss.cost(l.r.norm_squared());
            let jk_t = l.j_label.transpose() * w;
            let jx_t = l.j_offset.transpose() * w;
            block.v += l.j_point.transpose() * w * l.j_point;
            block.g += l.j_point.transpose() * (l.r * w);
            block.couplings.push((o.keyframe, jk_t * l.j_point));
            block.offset += jx_t * l.j_point;
            block.camera.push((o.keyframe, jk_t * l.j_label, jx_t * l.j_label, jk_t * l.r));
            block.offset_block.0 += jx_t * l.j_offset;
            block.offset_block.1 += jx_t * l.r;
        }
    }

    /// The label prior of keyframe k: (cost, H, g) in its right perturbation.
    fn label_prior(&self, state: &State, k: usize) -> (f64, Matrix6<f64>, Vector6<f64>) {
        let e = (self.labels[k].inverse() * state.labels[k]).log();
        let lam = Matrix6::from_diagonal(&self.label_information);
        let s = (e.transpose() * lam * e)[0];
        let w = self.options.label_loss.weight(s);
        let j = se3::right_jacobian_inverse(&e);
        (self.options.label_loss.cost(s), j.transpose() * lam * j * w, j.transpose() * lam * e * w)
    }

    /// The offset prior: (cost, H, g).
    fn offset_prior(&self, state: &State) -> (f64, Matrix6<f64>, Vector6<f64>) {
        let e = state.offset.log();
        let lam = Matrix6::from_diagonal(&self.options.offset_sigma.information());
        let j = se3::right_jacobian_inverse(&e);
        ((e.transpose() * lam * e)[0], j.transpose() * lam * j, j.transpose() * lam * e)
    }

    fn cost(&self, state: &State) -> f64 {
        let points: f64 = map_slice(&self.by_point, 64, |obs| {
            obs.iter()
                .map(|&i| match state.residual_px(self.camera, &self.observations[i]) {
                    Some(r) => self.options.pixel_loss.cost((r / self.options.pixel_sigma_px).norm_squared()),
                    None => self.behind_cost(),
                })
                .sum::<f64>()
        })
        .into_iter()
        .sum();
        let labels: f64 = (0..self.labels.len()).map(|k| self.label_prior(state, k).0).sum();
        let offset = if self.options.estimate_offset { self.offset_prior(state).0 } else { 0.0 };
        points + labels + offset
    }

    /// The normal equations at `state` with the points eliminated and damping λ (on U and V).
    fn reduce(&self, state: &State, lambda: f64) -> Reduced {
        let n = self.labels.len();
        let xo = n; // the offset's block, when estimated
        let mut u = BlockEnvelope::zeros(&self.first);
        let mut rhs = vec![0.0; 6 * self.blocks];
        let add_rhs = |rhs: &mut Vec<f64>, b: usize, v: &Vector6<f64>| {
            for (x, y) in rhs[6 * b..6 * b + 6].iter_mut().zip(v.iter()) {
                *x -= y;
            }
        };
        for k in 0..n {
            let (_, h, g) = self.label_prior(state, k);
            *u.block_mut(k, k) += h;
            add_rhs(&mut rhs, k, &g);
        }
        if self.options.estimate_offset {
            let (_, h, g) = self.offset_prior(state);
            *u.block_mut(xo, xo) += h;
            add_rhs(&mut rhs, xo, &g);
        }
        let points = map_slice(&self.by_point, 64, |obs| self.point_block(state, obs));
        for p in &points {
            for (k, ukk, uxk, gk) in &p.camera {
                *u.block_mut(*k, *k) += ukk;
                add_rhs(&mut rhs, *k, gk);
                if self.options.estimate_offset {
                    *u.block_mut(xo, *k) += uxk;
                }
            }
            if self.options.estimate_offset {
                *u.block_mut(xo, xo) += p.offset_block.0;
                add_rhs(&mut rhs, xo, &p.offset_block.1);
            }
        }
        // damping of the camera-side diagonal
        for b in 0..self.blocks {
            let d = u.block_mut(b, b);
            for i in 0..6 {
                d[(i, i)] += lambda * d[(i, i)].max(1e-9);
            }
        }
        // Schur complement: S = U − Σ_j W_j V_j⁻¹ W_jᵀ, rhs −= Σ_j W_j V_j⁻¹ (−g_j)
        for p in &points {
            let Some(v_inv) = damped_inverse(&p.v, lambda) else { continue };
            let mut members: Vec<(usize, Matrix6x3)> = p.couplings.clone();
            if self.options.estimate_offset {
                members.push((xo, p.offset));
            }
            let y: Vec<Matrix6x3> = members.iter().map(|(_, w)| w * v_inv).collect();
            for (a, (ka, _)) in members.iter().enumerate() {
                let ya = &y[a];
                add_rhs(&mut rhs, *ka, &(ya * -p.g));
                for (kb, wb) in &members[..=a] {
                    *u.block_mut(*ka, *kb) -= ya * wb.transpose();
                }
            }
        }
        Reduced { s: u, rhs, points }
    }

    /// Levenberg–Marquardt from `state`: (the minimum, iterations, the start cost).
    fn minimize(&self, mut state: State) -> Result<(State, usize, f64)> {
        let mut lambda = INITIAL_LAMBDA;
        let mut cost = self.cost(&state);
        let start = cost;
        let mut iterations = 0;
        let mut failures = 0;
        while iterations < self.options.max_iterations && failures < 12 {
            iterations += 1;
            let reduced = self.reduce(&state, lambda);
            let Some(factor) = reduced.s.cholesky() else {
                lambda *= LAMBDA_UP;
                failures += 1;
                continue;
            };
            let delta = factor.solve(&reduced.rhs);
            let candidate = self.retract(&state, &delta, &reduced.points, lambda);
            let new_cost = self.cost(&candidate);
            if new_cost.is_finite() && new_cost < cost {
                let decrease = (cost - new_cost) / cost.max(f64::MIN_POSITIVE);
                state = candidate;
                cost = new_cost;
                lambda = (lambda * LAMBDA_DOWN).max(1e-12);
                failures = 0;
                if decrease < COST_TOLERANCE {
                    break;
                }
            } else {
                lambda *= LAMBDA_UP;
                failures += 1;
            }
        }
        if !cost.is_finite() {
            return Err(GeolocError::invalid("observations", "the adjustment diverged"));
        }
        Ok((state, iterations, start))
    }

    /// state ⊞ δ: keyframes and the offset from the reduced solution, each point by
    /// back-substitution δ_j = −V_j⁻¹ (g_j + Σ W_kjᵀ δ_k).
    fn retract(&self, state: &State, delta: &[f64], points: &[PointBlock], lambda: f64) -> State {
        let n = self.labels.len();
        let d = |b: usize| Vector6::from_column_slice(&delta[6 * b..6 * b + 6]);
        let labels = state.labels.iter().enumerate().map(|(k, b)| *b * SE3::exp(&d(k))).collect();
        let offset = if self.options.estimate_offset { state.offset * SE3::exp(&d(n)) } else { state.offset };
        let mut new_points = state.points.clone();
        for (j, p) in points.iter().enumerate() {
            if p.couplings.is_empty() {
                continue;
            }
            let Some(v_inv) = damped_inverse(&p.v, lambda) else { continue };
            let mut s = p.g;
            for (k, w) in &p.couplings {
                s += w.transpose() * d(*k);
            }
            if self.options.estimate_offset {
                s += p.offset.transpose() * d(n);
            }
            new_points[j] -= v_inv * s;
        }
        State { labels, offset, points: new_points }
    }

    /// The marginal covariances at `state` (undamped normal equations).
    fn covariances(&self, state: &State) -> Result<Covariances> {
        let n = self.labels.len();
        let reduced = self.reduce(state, 0.0);
        let factor = reduced
            .s
            .cholesky()
            .ok_or_else(|| GeolocError::invalid("observations", "the adjusted map's normal equations are singular"))?;
        let z = factor.selected_inverse();
        let label_poses = (0..n).map(|k| *z.block(k, k)).collect();
        let (label_offset, offset) = if self.options.estimate_offset {
            ((0..n).map(|k| z.block(n, k).transpose()).collect(), *z.block(n, n))
        } else {
            (vec![Matrix6::zeros(); n], Matrix6::zeros())
        };
        let points = map_slice(&reduced.points, 64, |p| {
            let Some(v_inv) = damped_inverse(&p.v, 0.0) else { return Matrix3::zeros() };
            if p.couplings.is_empty() {
                return Matrix3::zeros();
            }
            let mut members: Vec<(usize, Matrix6x3)> = p.couplings.clone();
            if self.options.estimate_offset {
                members.push((n, p.offset));
            }
            let mut m = Matrix3::zeros();
            for (ka, wa) in &members {
                for (kb, wb) in &members {
                    m += wa.transpose() * z.symmetric_block(*ka, *kb) * wb;
                }
            }
            let c = v_inv + v_inv * m * v_inv;
            (c + c.transpose()) * 0.5
        });
        Ok(Covariances { label_poses, label_offset, offset, points })
    }
}

/// (V + λ diag V)⁻¹ of a point block, None when singular.
fn damped_inverse(v: &Matrix3<f64>, lambda: f64) -> Option<Matrix3<f64>> {
    let mut d = *v;
    for i in 0..3 {
        d[(i, i)] += lambda * d[(i, i)];
    }
    let inv = d.cholesky()?.inverse();
    inv.iter().all(|x| x.is_finite()).then_some(inv)
}

#[cfg(test)]
mod tests;
