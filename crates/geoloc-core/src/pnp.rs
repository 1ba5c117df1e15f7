//! Backward intersection: the world_from_cam pose of a camera from 2D–3D correspondences
//! (the paper's Eq. back_projection), with a 6×6 covariance in the right-perturbation
//! tangent space (translation first).
//!
//! 1. Start: the given `init` pose, or P3P RANSAC ([`p3p`]) with MSAC scoring, an adaptive
//!    iteration count (confidence 0.9999 by default) and local optimization of every new
//!    best hypothesis (LO-RANSAC).
//! 2. LM on SE(3) (T ⊞ δ = T exp(δ^)) with a robust kernel on the Mahalanobis residual
//!    sⱼ = rⱼᵀWⱼrⱼ, rⱼ = π(T, Xⱼ) − zⱼ; correspondences with ‖rⱼ‖ > η_r are dropped and the
//!    pose re-solved until the inlier set is stable. When the points carry uncertainty the
//!    gate is rⱼᵀSⱼ⁻¹rⱼ ≤ (η_r/σ)² instead (the same for Sⱼ = σ²I), so points whose
//!    predicted error exceeds η_r are not thrown away for it. Either gate is widened to
//!    4.29σ ([`gate_px`]) when the pixel noise is too large for η_r. With the propagated
//!    covariance, a last solve on the stable inlier set is plain weighted least squares
//!    (outliers are gone; it is the efficient estimator, and the one the covariance is for).
//! 3. Covariance, one of [`CovarianceModel`]:
//!    * `Paper`: C = σ̂² (Σ wⱼ JⱼᵀJⱼ)⁻¹ with σ̂² = Σ‖rⱼ‖²/(2p − 1) and Huber weights wⱼ — the
//!      paper's formula; it ignores the error of the points and is over-confident.
//!    * `Propagated` (default; σ is the query's known pixel noise). Without point
//!      uncertainty: a last least-squares solve on the inliers and C = σ²(ΣJⱼᵀJⱼ)⁻¹.
//!      With independent point covariances Σⱼ: maximum likelihood over the pose and the
//!      point corrections jointly (`joint`), C the pose block of its inverse information.
//!      With keyframe-pose errors shared by the points (D_jk = ∂Xⱼ/∂δ_k, C_k): the same
//!      joint solve, the shared part kept in the residual weights
//!      Wⱼ = (σ²I + J_X,j Σⱼ^shared J_X,jᵀ)⁻¹, and the first-order sandwich covariance
//!      C = H⁻¹ (Σⱼ JⱼᵀWⱼ Sⱼ^ind WⱼJⱼ) H⁻¹ + Σ_k M_k C_k M_kᵀ with
//!      H = Σⱼ JⱼᵀWⱼJⱼ and M_k = −H⁻¹ Σⱼ JⱼᵀWⱼ J_X,j D_jk (Wⱼ here from the marginal
//!      Sⱼ = σ²I + J_X,j Σⱼ^marg J_X,jᵀ), where Sⱼ^ind holds the errors independent between
//!      points and the M_k terms those all points share.
//!
//! Geometry that is merely bad (too few points, no consensus, a singular information
//! matrix) gives `success = false` with a reason, never an error.

mod joint;
pub mod p3p;
mod ransac;

use nalgebra::{Matrix2, Matrix2x3, Matrix3, Matrix3x6, Matrix6, Vector2, Vector3, Vector6};

use crate::camera::{Camera, j_uv_point, j_uv_pose, project};
use crate::error::{GeolocError, Result};
use crate::lie::SE3;
use crate::optim::covariance::inverse_information;
pub use crate::optim::covariance::isometric_sigmas;
use crate::optim::{
    LeastSquares, LmOptions, LmReport, RobustLoss, levenberg_marquardt, levenberg_marquardt_with_information,
};

/// How the returned covariance is computed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CovarianceModel {
    /// Point errors (and keyframe-pose errors) propagated; calibrated. The default.
    Propagated,
    /// The paper's σ̂²(ΣJᵀJ)⁻¹ with σ̂² = ‖r‖²/(2p − 1); for comparison.
    Paper,
}

/// RANSAC settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RansacOptions {
    /// At least this many samples (default 100).
    pub min_iterations: usize,
    /// At most this many samples (default 10 000).
    pub max_iterations: usize,
    /// Probability of having drawn one all-inlier sample before stopping (default 0.9999).
    pub confidence: f64,
    /// Seed of the sampler (default 0): results are reproducible.
    pub seed: u64,
}

impl Default for RansacOptions {
    fn default() -> Self {
        Self { min_iterations: 100, max_iterations: 10_000, confidence: 0.9999, seed: 0 }
    }
}

/// Options of [`solve_pnp`]; defaults follow the paper (Huber 1 px, η_r = 5 px).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PnpOptions {
    /// Robust kernel on the Mahalanobis residual (default Huber, width 1).
    pub loss: RobustLoss,
    /// Pixel noise σ of the query keypoints (default 1 px).
    pub pixel_sigma: f64,
    /// η_r: correspondences with a larger residual are outliers (default 5 px); also the
    /// RANSAC inlier threshold.
    pub max_residual_px: f64,
    /// RANSAC settings (used when no initial pose is given).
    pub ransac: RansacOptions,
    /// Covariance model (default propagated).
    pub covariance: CovarianceModel,
    /// LM settings.
    pub lm: LmOptions,
    /// Rounds of drop-outliers-and-re-solve (default 5).
    pub max_refits: usize,
}

impl Default for PnpOptions {
    fn default() -> Self {
        Self {
            loss: RobustLoss::Huber { width: 1.0 },
            pixel_sigma: 1.0,
            max_residual_px: 5.0,
            ransac: RansacOptions::default(),
            covariance: CovarianceModel::Propagated,
            lm: LmOptions::default(),
            max_refits: 5,
        }
    }
}

/// Uncertainty of the 3D points, as triangulation provides it.
#[derive(Clone, Copy, Debug)]
pub struct PointUncertainty<'a> {
    /// Per point: the covariance part independent between points (pixel noise), m².
    pub covariances: &'a [Matrix3<f64>],
    /// Errors shared through the keyframe poses, if known.
    pub shared: Option<SharedPoseUncertainty<'a>>,
}

/// Keyframe-pose errors shared by the points.
#[derive(Clone, Copy, Debug)]
pub struct SharedPoseUncertainty<'a> {
    /// Row-major N × K: `jacobians[j * K + k]` = D_jk = ∂X_j/∂δ_k.
    pub jacobians: &'a [Matrix3x6<f64>],
    /// The K keyframe-pose covariances C_k (right perturbation of world_from_cam).
    pub pose_covariances: &'a [Matrix6<f64>],
}

/// The outcome of [`solve_pnp`].
#[derive(Clone, Debug, PartialEq)]
pub struct PnpResult {
    /// Whether a pose was found.
    pub success: bool,
    /// "ok" or why not.
    pub reason: String,
    /// The estimate (identity when nothing was found).
    pub world_from_cam: SE3,
    /// 6×6 covariance in the right-perturbation tangent space, translation first.
    pub covariance: Matrix6<f64>,
    /// Per correspondence: used in the final solve.
    pub inliers: Vec<bool>,
    /// RMS reprojection error of the inliers (pixels).
    pub rms_px: f64,
    /// The paper's isometric position σ: mean of √diag(C_ρ) (m).
    pub sigma_p: f64,
    /// The paper's isometric rotation σ: Θ(exp(√diag(C_φ))) (rad).
    pub sigma_r: f64,
    /// RANSAC samples drawn (0 with an initial pose).
    pub ransac_iterations: usize,
    /// The last LM run.
    pub lm: Option<LmReport>,
}

impl PnpResult {
    fn failure(n: usize, reason: impl Into<String>, ransac_iterations: usize) -> Self {
        Self {
            success: false,
            reason: reason.into(),
            world_from_cam: SE3::identity(),
            covariance: Matrix6::zeros(),
            inliers: vec![false; n],
            rms_px: f64::NAN,
            sigma_p: f64::NAN,
            sigma_r: f64::NAN,
            ransac_iterations,
            lm: None,
        }
    }
}

/// Relative cost decrease that ends a robust round when a final least-squares solve follows.
const ROBUST_ROUND_COST_TOLERANCE: f64 = 1e-4;

/// Fewest correspondences RANSAC needs (a 3-point sample plus one to check it).
pub const MIN_POINTS_RANSAC: usize = 4;
/// Fewest inliers a pose (6 DoF) is accepted from.
pub const MIN_INLIERS: usize = 4;
/// Estimates world_from_cam from `points` (world) and their undistorted `pixels`; see the
/// module doc.
///
/// # Errors
/// Only for invalid input: mismatched lengths, non-finite values, bad options or
/// uncertainty arrays of the wrong size.
pub fn solve_pnp(
    camera: &Camera,
    points: &[Vector3<f64>],
    pixels: &[Vector2<f64>],
    init: Option<&SE3>,
    uncertainty: Option<&PointUncertainty<'_>>,
    options: &PnpOptions,
) -> Result<PnpResult> {
    validate(points, pixels, uncertainty, options)?;
    let n = points.len();
    let (start, ransac_iterations) = match init {
        Some(pose) => (*pose, 0),
        None => {
            if n < MIN_POINTS_RANSAC {
                return Ok(PnpResult::failure(n, format!("too few correspondences: {n} < {MIN_POINTS_RANSAC}"), 0));
            }
            match ransac::ransac(camera, points, pixels, options) {
                (Some(pose), iterations) => (pose, iterations),
                (None, iterations) => {
                    return Ok(PnpResult::failure(n, "RANSAC found no pose with enough inliers", iterations));
                }
            }
        }
    };
    if n < MIN_INLIERS {
        return Ok(PnpResult::failure(n, format!("too few correspondences: {n} < {MIN_INLIERS}"), ransac_iterations));
    }
    // With an initial pose the first solve is robust over everything; after RANSAC it
    // starts from the consensus set.
    let mut subset: Vec<usize> = if init.is_some() {
        (0..n).filter(|&j| project(camera, &start, &points[j]).p_cam.z > 0.0).collect()
    } else {
        inlier_indices(camera, points, pixels, &start, options.max_residual_px)
    };
    let mut pose = start;
    let mut report = None;
    for _ in 0..options.max_refits.max(1) {
        if subset.len() < MIN_INLIERS {
            break;
        }
        let w = weighting(camera, points, &pose, &subset, uncertainty, options.pixel_sigma);
        let problem = w.problem(camera, points, pixels, &subset, options.loss);
        // with the propagated model a final least-squares solve follows: the robust rounds
        // only have to settle the inlier set
        let final_solve_follows = options.covariance == CovarianceModel::Propagated && options.loss != RobustLoss::None;
        let lm = if final_solve_follows {
            LmOptions { cost_tolerance: ROBUST_ROUND_COST_TOLERANCE, ..options.lm }
        } else {
            options.lm
        };
        let (next, r) = levenberg_marquardt(&problem, pose, &lm);
        pose = next;
        report = Some(r);
        let next_subset = gated_indices(camera, points, pixels, &pose, uncertainty, options);
        if next_subset == subset {
            break;
        }
        subset = next_subset;
    }
    if subset.len() < MIN_INLIERS {
        return Ok(PnpResult::failure(
            n,
            format!("too few inliers: {} < {MIN_INLIERS}", subset.len()),
            ransac_iterations,
        ));
    }
    let mut joint_covariance = None;
    let mut least_squares = None;
    if options.covariance == CovarianceModel::Propagated
        && let Some(u) = uncertainty
    {
        // Outliers are gone: maximum likelihood over the pose and the independent point
        // corrections. Shared keyframe-pose errors stay in the residual weights
        // (Wⱼ = (σ²I + J_X Σⱼ^shared J_Xᵀ)⁻¹) and in the sandwich covariance below.
        let shared_weights = u.shared.is_some().then(|| {
            subset
                .iter()
                .map(|&j| {
                    let p = project(camera, &pose, &points[j]);
                    let j_x = j_uv_point(camera, &pose, &p);
                    let shared =
                        point_covariance(j, uncertainty, true).unwrap_or_else(Matrix3::zeros) - u.covariances[j];
                    let s = Matrix2::identity() * (options.pixel_sigma * options.pixel_sigma)
                        + j_x * shared * j_x.transpose();
                    s.try_inverse().unwrap_or_else(|| Matrix2::identity() / (options.pixel_sigma * options.pixel_sigma))
                })
                .collect::<Vec<_>>()
        });
        let problem = joint::JointProblem::new(
            camera,
            points,
            pixels,
            &subset,
            u,
            options.pixel_sigma,
            shared_weights.as_deref(),
        );
        let (next, cov, r) = problem.solve(pose, &options.lm);
        pose = next;
        report = Some(r);
        if u.shared.is_none() {
            joint_covariance = Some(cov);
        }
    } else if options.covariance == CovarianceModel::Propagated && options.loss != RobustLoss::None {
        // Outliers are gone: the efficient estimator for the remaining Gaussian errors is
        // plain weighted least squares, whose covariance the propagation below is exact for.
        let w = weighting(camera, points, &pose, &subset, uncertainty, options.pixel_sigma);
        let problem = w.problem(camera, points, pixels, &subset, RobustLoss::None);
        let (next, r, h) = final_least_squares(&problem, pose, &options.lm);
        pose = next;
        report = Some(r);
        if uncertainty.is_none() {
            // exact points: C = (Σ JⱼᵀJⱼ/σ²)⁻¹ is the information of this very solve, and its
            // cost is Σ‖rⱼ‖²/σ²
            least_squares = Some((h, r.final_cost));
        }
    }
    let mut inliers = vec![false; n];
    for &j in &subset {
        inliers[j] = true;
    }
    let sum_sq: f64 = match least_squares {
        Some((_, cost)) => cost * options.pixel_sigma * options.pixel_sigma,
        None => subset.iter().map(|&j| (project(camera, &pose, &points[j]).uv - pixels[j]).norm_squared()).sum(),
    };
    let rms_px = (sum_sq / subset.len() as f64).sqrt();
    let covariance = match options.covariance {
        CovarianceModel::Paper => paper_covariance(camera, points, pixels, &pose, &subset, options.loss),
        CovarianceModel::Propagated => match joint_covariance {
            Some(cov) => cov.filter(|c| inverse_information(c).is_some()),
            None => match least_squares {
                Some((h, _)) => inverse_information(&h),
                None => propagated_covariance(camera, points, &pose, &subset, uncertainty, options.pixel_sigma),
            },
        },
    };
    let Some(covariance) = covariance else {
        let mut failed = PnpResult::failure(
            n,
            "degenerate geometry: the pose is not observable from these points",
            ransac_iterations,
        );
        failed.world_from_cam = pose;
        failed.inliers = inliers;
        return Ok(failed);
    };
    let (sigma_p, sigma_r) = isometric_sigmas(&covariance);
    let converged = report.is_some_and(|r| r.converged());
    Ok(PnpResult {
        success: true,
        reason: if converged { "ok".into() } else { "ok (LM stopped at its iteration cap)".into() },
        world_from_cam: pose,
        covariance,
        inliers,
        rms_px,
        sigma_p,
        sigma_r,
        ransac_iterations,
        lm: report,
    })
}

/// The last least-squares solve, which starts at the robust optimum: when the Gauss–Newton
/// step from there is small in the metric of the information (δᵀHδ ≤ 1, i.e. the
/// least-squares optimum is within about one standard deviation), that single step — exact to
/// second order — is taken without a second pass over the data, and the predicted cost
/// stands for the final one; otherwise a full LM. Returns the pose, the report and H.
fn final_least_squares(problem: &PoseProblem<'_>, pose: SE3, lm: &LmOptions) -> (SE3, LmReport, Matrix6<f64>) {
    let (h, g, cost) = problem.normal_equations(&pose);
    if let Some(chol) = h.cholesky() {
        let step = chol.solve(&(-g));
        let metric = step.dot(&(h * step));
        if metric <= ONE_STEP_MAX_METRIC {
            // the cost is Σ rᵀWr and g its half-gradient: cost + 2gᵀδ + δᵀHδ = cost + gᵀδ at Hδ = −g
            let predicted = cost + g.dot(&step);
            let report = LmReport {
                iterations: 1,
                initial_cost: cost,
                final_cost: predicted,
                termination: crate::optim::Termination::CostConverged,
            };
            return (pose * SE3::exp(&step), report, h);
        }
    }
    levenberg_marquardt_with_information(problem, pose, lm)
}

/// δᵀHδ below which the final least-squares solve is a single Gauss–Newton step.
const ONE_STEP_MAX_METRIC: f64 = 1.0;

fn validate(
    points: &[Vector3<f64>],
    pixels: &[Vector2<f64>],
    uncertainty: Option<&PointUncertainty<'_>>,
    options: &PnpOptions,
) -> Result<()> {
    let n = points.len();
    if pixels.len() != n {
        return Err(GeolocError::invalid("pixels", format!("has {} entries but points3d has {n}", pixels.len())));
    }
    if let Some(j) = points.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
        return Err(GeolocError::NonFinite { name: "points3d".into(), index: j });
    }
    if let Some(j) = pixels.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
        return Err(GeolocError::NonFinite { name: "pixels".into(), index: j });
    }
    for (name, v) in [("pixel_sigma", options.pixel_sigma), ("max_residual", options.max_residual_px)] {
        if !(v.is_finite() && v > 0.0) {
            return Err(GeolocError::invalid(name, format!("must be finite and > 0, got {v}")));
        }
    }
    let r = &options.ransac;
    if !(r.confidence > 0.0 && r.confidence < 1.0) {
        return Err(GeolocError::invalid("confidence", format!("must be in (0, 1), got {}", r.confidence)));
    }
    if r.max_iterations == 0 || r.min_iterations > r.max_iterations {
        return Err(GeolocError::invalid("max_iterations", "need 0 < min_iterations ≤ max_iterations"));
    }
    if let Some(u) = uncertainty {
        if u.covariances.len() != n {
            return Err(GeolocError::invalid(
                "point_covariances",
                format!("has {} entries for {n} points", u.covariances.len()),
            ));
        }
        if let Some(s) = &u.shared
            && s.jacobians.len() != n * s.pose_covariances.len()
        {
            return Err(GeolocError::invalid(
                "point_pose_jacobians",
                format!(
                    "has {} entries; expected points × poses = {n} × {}",
                    s.jacobians.len(),
                    s.pose_covariances.len()
                ),
            ));
        }
    }
    Ok(())
}

/// √χ²₂(0.9999): a correct 2D residual exceeds this many σ with probability 1e-4.
pub const CHI2_2DOF_9999_SQRT: f64 = 4.291_932_052_578_985;

/// The refit gate: η_r, widened to 4.29σ when σ is large enough that η_r would cut into
/// correct correspondences — a hard cut at ~2.5σ inflates the estimator's variance beyond
/// what its covariance says (a "skipped" M-estimator).
pub fn gate_px(max_residual_px: f64, sigma: f64) -> f64 {
    max_residual_px.max(CHI2_2DOF_9999_SQRT * sigma)
}

/// Correspondences kept by the refits: in front of the camera with rᵀS⁻¹r ≤ (η_r/σ)², S the
/// predicted residual covariance — exactly ‖r‖ ≤ η_r when the points carry no uncertainty,
/// and no stricter than the points' own uncertainty allows when they do.
fn gated_indices(
    camera: &Camera,
    points: &[Vector3<f64>],
    pixels: &[Vector2<f64>],
    pose: &SE3,
    uncertainty: Option<&PointUncertainty<'_>>,
    options: &PnpOptions,
) -> Vec<usize> {
    let sigma = options.pixel_sigma;
    let eta = gate_px(options.max_residual_px, sigma);
    if uncertainty.is_none() {
        return inlier_indices(camera, points, pixels, pose, eta);
    }
    let gate = (eta / sigma).powi(2);
    (0..points.len())
        .filter(|&j| {
            let p = project(camera, pose, &points[j]);
            if p.p_cam.z <= 0.0 {
                return false;
            }
            let (s, bias) = residual_moments(camera, points, pose, j, uncertainty, sigma, true);
            let r = p.uv - bias - pixels[j];
            s.try_inverse().is_some_and(|s_inv| r.dot(&(s_inv * r)) <= gate)
        })
        .collect()
}

fn inlier_indices(
    camera: &Camera,
    points: &[Vector3<f64>],
    pixels: &[Vector2<f64>],
    pose: &SE3,
    threshold: f64,
) -> Vec<usize> {
    let t2 = threshold * threshold;
    (0..points.len())
        .filter(|&j| {
            let p = project(camera, pose, &points[j]);
            p.p_cam.z > 0.0 && (p.uv - pixels[j]).norm_squared() <= t2
        })
        .collect()
}

/// Per correspondence of a subset: the weight Wⱼ = Sⱼ⁻¹ and the projection bias bⱼ.
struct Weighting {
    weights: Vec<Matrix2<f64>>,
    biases: Vec<Vector2<f64>>,
}

impl Weighting {
    /// The pose problem over `subset` with these weights and biases.
    fn problem<'a>(
        &'a self,
        camera: &'a Camera,
        points: &'a [Vector3<f64>],
        pixels: &'a [Vector2<f64>],
        subset: &'a [usize],
        loss: RobustLoss,
    ) -> PoseProblem<'a> {
        PoseProblem { camera, points, pixels, subset, weights: &self.weights, biases: &self.biases, loss }
    }
}

/// Wⱼ and bⱼ for the correspondences in `subset` at `pose` (marginal point covariances).
fn weighting(
    camera: &Camera,
    points: &[Vector3<f64>],
    pose: &SE3,
    subset: &[usize],
    uncertainty: Option<&PointUncertainty<'_>>,
    sigma: f64,
) -> Weighting {
    let (weights, biases) = subset
        .iter()
        .map(|&j| {
            let (s, bias) = residual_moments(camera, points, pose, j, uncertainty, sigma, true);
            (s.try_inverse().unwrap_or_else(|| Matrix2::identity() / (sigma * sigma)), bias)
        })
        .unzip();
    Weighting { weights, biases }
}

/// Point j's covariance: the independent part, plus (if `marginal`) the shared
/// keyframe-pose part Σ_k D_jk C_k D_jkᵀ. None without uncertainty.
fn point_covariance(j: usize, uncertainty: Option<&PointUncertainty<'_>>, marginal: bool) -> Option<Matrix3<f64>> {
    let u = uncertainty?;
    let mut cov = u.covariances[j];
    if marginal && let Some(shared) = &u.shared {
        let k_count = shared.pose_covariances.len();
        for (k, c_k) in shared.pose_covariances.iter().enumerate() {
            let d = &shared.jacobians[j * k_count + k];
            cov += d * c_k * d.transpose();
        }
    }
    Some(cov)
}

/// Mean and covariance of correspondence j's residual π(T, X̂ⱼ) − zⱼ when X̂ⱼ = Xⱼ + e,
/// e ~ N(0, Σⱼ) and the pixel has noise σ:
///   Sⱼ = σ²I + J_X Σⱼ J_Xᵀ,
///   bⱼ = ½ tr(∇²π Σⱼ) = (f_x (x Σ_zz/z − Σ_xz), f_y (y Σ_zz/z − Σ_yz)) / z²
/// with Σ in camera coordinates. The bias is the second-order effect of the perspective
/// division on an uncertain point; it has the same sign for many points, so unlike their
/// noise it does not average out, and ignoring it leaves the pose covariance over-confident
/// along the translation–rotation ambiguity.
fn residual_moments(
    camera: &Camera,
    points: &[Vector3<f64>],
    pose: &SE3,
    j: usize,
    uncertainty: Option<&PointUncertainty<'_>>,
    sigma: f64,
    marginal: bool,
) -> (Matrix2<f64>, Vector2<f64>) {
    let mut s = Matrix2::identity() * (sigma * sigma);
    let Some(cov) = point_covariance(j, uncertainty, marginal) else { return (s, Vector2::zeros()) };
    let p = project(camera, pose, &points[j]);
    let j_x = j_uv_point(camera, pose, &p);
    s += j_x * cov * j_x.transpose();
    let r = pose.rotation.matrix();
    let c = r.transpose() * cov * r;
    let (x, y, z) = (p.p_cam.x, p.p_cam.y, p.p_cam.z);
    let bias = Vector2::new(camera.fx * (x * c[(2, 2)] / z - c[(0, 2)]), camera.fy * (y * c[(2, 2)] / z - c[(1, 2)]))
        / (z * z);
    (s, bias)
}

struct PoseProblem<'a> {
    camera: &'a Camera,
    points: &'a [Vector3<f64>],
    pixels: &'a [Vector2<f64>],
    subset: &'a [usize],
    weights: &'a [Matrix2<f64>],
    /// Projection biases, aligned with `subset` (zeros when points are exact).
    biases: &'a [Vector2<f64>],
    loss: RobustLoss,
}

impl LeastSquares<6> for PoseProblem<'_> {
    type State = SE3;

    fn normal_equations(&self, pose: &SE3) -> (Matrix6<f64>, Vector6<f64>, f64) {
        // The hot loop of every PnP: the two rows of ∂π/∂δ in closed form and only the upper
        // triangle of H accumulated (H is symmetric).
        let cam_from_world = pose.inverse();
        let r_cw = cam_from_world.rotation.matrix();
        let t_cw = cam_from_world.translation;
        let (fx, fy) = (self.camera.fx, self.camera.fy);
        let mut upper = [0.0_f64; 21];
        let mut g = Vector6::zeros();
        let mut cost = 0.0;
        for (&j, (w, b)) in self.subset.iter().zip(self.weights.iter().zip(self.biases)) {
            let p = r_cw * self.points[j] + t_cw;
            let inv_z = 1.0 / p.z;
            let (xz, yz) = (p.x * inv_z, p.y * inv_z);
            let r = Vector2::new(fx * xz + self.camera.cx, fy * yz + self.camera.cy) - b - self.pixels[j];
            let wr = w * r;
            let s = r.dot(&wr);
            let robust = self.loss.weight(s);
            cost += self.loss.cost(s);
            let (a, c) = (fx * inv_z, fy * inv_z);
            // ∂u/∂δ and ∂v/∂δ for the right perturbation of world_from_cam (camera::j_uv_pose)
            let ju = [-a, 0.0, a * xz, a * xz * p.y, -a * (p.z + p.x * xz), a * p.y];
            let jv = [0.0, -c, c * yz, c * (p.z + p.y * yz), -c * p.x * yz, -c * p.x];
            let (w00, w01, w11) = (robust * w[(0, 0)], robust * w[(0, 1)], robust * w[(1, 1)]);
            let mut k = 0;
            for i in 0..6 {
                let (ui, vi) = (w00 * ju[i] + w01 * jv[i], w01 * ju[i] + w11 * jv[i]);
                g[i] += ju[i] * wr[0] * robust + jv[i] * wr[1] * robust;
                for l in i..6 {
                    upper[k] += ui * ju[l] + vi * jv[l];
                    k += 1;
                }
            }
        }
        let mut h = Matrix6::zeros();
        let mut k = 0;
        for i in 0..6 {
            for l in i..6 {
                h[(i, l)] = upper[k];
                h[(l, i)] = upper[k];
                k += 1;
            }
        }
        (h, g, cost)
    }

    fn retract(&self, pose: &SE3, delta: &Vector6<f64>) -> SE3 {
        *pose * SE3::exp(delta)
    }
}

fn paper_covariance(
    camera: &Camera,
    points: &[Vector3<f64>],
    pixels: &[Vector2<f64>],
    pose: &SE3,
    subset: &[usize],
    loss: RobustLoss,
) -> Option<Matrix6<f64>> {
    let mut info = Matrix6::zeros();
    let mut sum_sq = 0.0;
    for &j in subset {
        let p = project(camera, pose, &points[j]);
        let r = p.uv - pixels[j];
        let jac = j_uv_pose(camera, &p);
        info += loss.weight(r.norm_squared()) * jac.transpose() * jac;
        sum_sq += r.norm_squared();
    }
    let sigma2 = sum_sq / (2.0 * subset.len() as f64 - 1.0);
    inverse_information(&info).map(|c| c * sigma2)
}

fn propagated_covariance(
    camera: &Camera,
    points: &[Vector3<f64>],
    pose: &SE3,
    subset: &[usize],
    uncertainty: Option<&PointUncertainty<'_>>,
    sigma: f64,
) -> Option<Matrix6<f64>> {
    let mut h = Matrix6::zeros();
    let mut meat = Matrix6::zeros();
    // JⱼᵀWⱼ J_X,j per point, needed for the shared part
    let mut couplings: Vec<(usize, nalgebra::Matrix6x3<f64>)> = Vec::new();
    for &j in subset {
        let p = project(camera, pose, &points[j]);
        let (s_marginal, _) = residual_moments(camera, points, pose, j, uncertainty, sigma, true);
        let w = s_marginal.try_inverse()?;
        let jac = j_uv_pose(camera, &p);
        let jt_w = jac.transpose() * w;
        h += jt_w * jac;
        let (s_ind, _) = residual_moments(camera, points, pose, j, uncertainty, sigma, false);
        meat += jt_w * s_ind * jt_w.transpose();
        if uncertainty.is_some_and(|u| u.shared.is_some()) {
            let j_x: Matrix2x3<f64> = j_uv_point(camera, pose, &p);
            couplings.push((j, jt_w * j_x));
        }
    }
    let h_inv = inverse_information(&h)?;
    let mut c = h_inv * meat * h_inv;
    if let Some(shared) = uncertainty.and_then(|u| u.shared.as_ref()) {
        let k_count = shared.pose_covariances.len();
        for (k, c_k) in shared.pose_covariances.iter().enumerate() {
            let mut m = Matrix6::zeros();
            for (j, coupling) in &couplings {
                m -= coupling * shared.jacobians[j * k_count + k];
            }
            let m = h_inv * m;
            c += m * c_k * m.transpose();
        }
    }
    Some(0.5 * (c + c.transpose()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::SplitMix64;

    /// The one-step shortcut lands where the full LM does (to far below the noise).
    #[test]
    fn single_final_step_matches_full_least_squares() {
        let camera = Camera::new(525.0, 525.0, 320.0, 240.0).expect("valid");
        let mut rng = SplitMix64::new(4);
        for _ in 0..20 {
            let truth = rng.pose(3.0);
            let points: Vec<Vector3<f64>> = (0..100)
                .map(|_| {
                    truth * Vector3::new(rng.uniform_in(-2.0, 2.0), rng.uniform_in(-1.5, 1.5), rng.uniform_in(3.0, 8.0))
                })
                .collect();
            let pixels: Vec<Vector2<f64>> = points
                .iter()
                .map(|x| project(&camera, &truth, x).uv + Vector2::new(rng.normal(), rng.normal()))
                .collect();
            let subset: Vec<usize> = (0..points.len()).collect();
            let weights = vec![Matrix2::identity(); subset.len()];
            let biases = vec![Vector2::zeros(); subset.len()];
            let problem = PoseProblem {
                camera: &camera,
                points: &points,
                pixels: &pixels,
                subset: &subset,
                weights: &weights,
                biases: &biases,
                loss: RobustLoss::None,
            };
            let (full, full_report, _) = levenberg_marquardt_with_information(&problem, truth, &LmOptions::default());
            // start half a standard deviation or so away from the optimum, as after Huber
            let start = full * SE3::exp(&Vector6::new(3e-4, -3e-4, 2e-4, 5e-5, -3e-5, 3e-5));
            let (one, report, _) = final_least_squares(&problem, start, &LmOptions::default());
            assert_eq!(report.iterations, 1, "the single-step path was taken");
            // the estimate's own σ is ~2e-3 here: 1e-6 is far below it
            assert!((one.inverse() * full).log().norm() < 1e-6, "{:?}", (one.inverse() * full).log());
            // the predicted cost only feeds the reported RMS
            assert!((report.final_cost - full_report.final_cost).abs() < 1e-4 * full_report.final_cost);
        }
    }
}
