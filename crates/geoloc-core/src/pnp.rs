//! Backward intersection: the world_from_cam pose of a camera from 2D–3D correspondences
//! (the paper's Eq. back_projection), with a 6×6 covariance in the right-perturbation
//! tangent space (translation first). This module is the driver, the steps in order:
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
//!    (outliers are gone; it is the efficient estimator, and the one the covariance is for),
//!    or with uncertain points the joint maximum-likelihood solve (`joint`).
//! 3. Covariance, one of [`CovarianceModel`] (the models and the variance factor: the
//!    `covariance` submodule).
//! 4. Acceptance: enough inliers, more than random pixels would give (the `chance`
//!    submodule, [`chance_probability`]).
//!
//! Geometry that is merely bad (too few points, no consensus, a singular information
//! matrix) gives `success = false` with a reason, never an error.

mod chance;
mod covariance;
mod joint;
pub mod p3p;
mod ransac;

use nalgebra::{Matrix2, Matrix3, Matrix3x6, Matrix6, Vector2, Vector3, Vector6};

use crate::camera::{Camera, project};
use crate::error::{GeolocError, Result};
use crate::lie::SE3;
pub use crate::optim::covariance::isometric_sigmas;
use crate::optim::covariance::{check_covariances, inverse_information};
use crate::optim::{
    LeastSquares, LmOptions, LmReport, RobustLoss, levenberg_marquardt, levenberg_marquardt_with_information,
};
pub use chance::{MAX_CHANCE_PROBABILITY, MIN_ACCEPTED_INLIERS, chance_probability};
pub use covariance::CovarianceModel;
use covariance::{paper_covariance, propagated_covariance, residual_moments};

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
    /// With an initial pose, also run RANSAC and start from whichever of the two has the
    /// lower MSAC score over all correspondences (default false: the initial pose alone).
    pub ransac_with_init: bool,
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
            ransac_with_init: false,
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
    /// Per point j, the D_jk = ∂X_j/∂δ_k it has ([`PosePartials`]): a point moves with the
    /// poses of the keyframes that observe it only, so a map-wide set of K keyframes costs
    /// what the points' views cost, not N × K blocks.
    pub jacobians: &'a [PosePartials],
    /// The K keyframe-pose covariances C_k (right perturbation of world_from_cam).
    pub pose_covariances: &'a [Matrix6<f64>],
}

/// One point's D_jk = ∂X_j/∂δ_k as (k, D_jk), k increasing; a k it does not list has D_jk = 0.
pub type PosePartials = Vec<(usize, Matrix3x6<f64>)>;

/// The [`PosePartials`] of `points` points from a row-major `points` × `poses` array of
/// D_jk (every entry kept, zero or not: sums over them are those over the array, bit for
/// bit).
///
/// # Errors
/// `dense` not `points` × `poses` long (named `point_pose_jacobians`).
pub fn pose_partials_from_dense(dense: &[Matrix3x6<f64>], points: usize, poses: usize) -> Result<Vec<PosePartials>> {
    if dense.len() != points * poses {
        return Err(GeolocError::invalid(
            "point_pose_jacobians",
            format!("has {} entries; expected points × poses = {points} × {poses}", dense.len()),
        ));
    }
    Ok((0..points).map(|j| (0..poses).map(|k| (k, dense[j * poses + k])).collect()).collect())
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
    /// The part of `covariance` the query's own pixel noise gives (same scaling): independent
    /// from one frame to the next, where the points' and keyframes' errors are shared by
    /// consecutive frames. The paper's covariance model: `covariance` itself.
    pub pixel_covariance: Matrix6<f64>,
    /// Per correspondence: used in the final solve.
    pub inliers: Vec<bool>,
    /// RMS reprojection error of the inliers (pixels).
    pub rms_px: f64,
    /// The variance factor of the inliers, s² = Σⱼ rⱼᵀSⱼ⁻¹rⱼ / (2n − 6) (honest degrees
    /// of freedom: 2 per inlier, 6 taken by the pose); the propagated covariance is scaled by
    /// max(1, s²) — residuals larger than the noise model says inflate it, smaller ones never
    /// shrink it below the model (NaN when nothing was found or n ≤ 3).
    pub variance_factor: f64,
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
            pixel_covariance: Matrix6::zeros(),
            inliers: vec![false; n],
            rms_px: f64::NAN,
            variance_factor: f64::NAN,
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
/// Fewest inliers the solver iterates on (6 DoF: three points fix a pose, one checks it).
pub const MIN_INLIERS: usize = 4;
/// Cap of `RansacOptions::{min,max}_iterations` (a larger request is refused, not run).
pub const MAX_RANSAC_ITERATIONS: usize = 1_000_000;
/// Cap of `LmOptions::max_iterations` in PnP options.
pub const MAX_LM_ITERATIONS: usize = 10_000;
/// Cap of `PnpOptions::max_refits`.
pub const MAX_REFITS: usize = 1_000;

/// Estimates world_from_cam from `points` (world) and their undistorted `pixels`; see the
/// module doc. The steps, in the paper's order: the start (given pose and/or P3P RANSAC),
/// the robust LM rounds that settle the inlier set (η_r), the last solve on the inliers with
/// its covariance (C_G), and the acceptance test (enough inliers, more than chance gives).
///
/// # Errors
/// Only for invalid input: mismatched lengths, non-finite values, bad options (iteration
/// counts above [`MAX_RANSAC_ITERATIONS`] / [`MAX_LM_ITERATIONS`] / [`MAX_REFITS`]), point
/// or pose covariances that are not symmetric positive semi-definite, or uncertainty arrays
/// of the wrong size.
pub fn solve_pnp(
    camera: &Camera,
    points: &[Vector3<f64>],
    pixels: &[Vector2<f64>],
    init: Option<&SE3>,
    uncertainty: Option<&PointUncertainty<'_>>,
    options: &PnpOptions,
) -> Result<PnpResult> {
    solve_pnp_with_pixel_sigmas(camera, points, pixels, None, init, uncertainty, options)
}

/// [`solve_pnp`] with a pixel noise of its own for each correspondence:
/// σⱼ = `options.pixel_sigma` × `pixel_sigmas[j]` (e.g. a keypoint's σ from its detector
/// scale, 1.2^level for ORB), everywhere σ enters — the weights Sⱼ = σⱼ²I + J_X Σⱼ J_Xᵀ,
/// the gate (η_r widened to 4.29σⱼ), the covariance and the variance factor. `None` is
/// [`solve_pnp`] exactly.
///
/// # Errors
/// As [`solve_pnp`], and `pixel_sigmas` of the wrong length or not finite and > 0.
pub fn solve_pnp_with_pixel_sigmas(
    camera: &Camera,
    points: &[Vector3<f64>],
    pixels: &[Vector2<f64>],
    pixel_sigmas: Option<&[f64]>,
    init: Option<&SE3>,
    uncertainty: Option<&PointUncertainty<'_>>,
    options: &PnpOptions,
) -> Result<PnpResult> {
    validate(points, pixels, uncertainty, options)?;
    if let Some(scales) = pixel_sigmas {
        if scales.len() != points.len() {
            return Err(GeolocError::invalid(
                "pixel_sigmas",
                format!("has {} entries but points3d has {}", scales.len(), points.len()),
            ));
        }
        if let Some(j) = scales.iter().position(|v| !(v.is_finite() && *v > 0.0)) {
            return Err(GeolocError::invalid("pixel_sigmas", format!("entry {j} must be finite and > 0")));
        }
    }
    let noise = PixelNoise { sigma: options.pixel_sigma, scales: pixel_sigmas };
    let data = Correspondences { camera, points, pixels, uncertainty, options, noise };
    let start = match data.start(init) {
        Ok(start) => start,
        Err(failed) => return Ok(*failed),
    };
    let (pose, subset, report) = data.refit(start.pose, start.subset);
    if subset.len() < MIN_INLIERS {
        let reason = format!("too few inliers: {} < {MIN_INLIERS}", subset.len());
        return Ok(PnpResult::failure(points.len(), reason, start.ransac_iterations));
    }
    let last = data.final_solve(pose, &subset);
    Ok(data.finish(last, report, &subset, start.ransac_iterations))
}

/// The query's pixel noise: σⱼ = `sigma` × `scales[j]`, or `sigma` for every correspondence.
#[derive(Clone, Copy, Debug)]
struct PixelNoise<'a> {
    sigma: f64,
    scales: Option<&'a [f64]>,
}

impl PixelNoise<'_> {
    /// σⱼ of correspondence `j`.
    #[inline]
    fn at(&self, j: usize) -> f64 {
        self.scales.map_or(self.sigma, |s| self.sigma * s[j])
    }
}

/// The inputs of one PnP, shared by its steps.
struct Correspondences<'a> {
    camera: &'a Camera,
    points: &'a [Vector3<f64>],
    pixels: &'a [Vector2<f64>],
    uncertainty: Option<&'a PointUncertainty<'a>>,
    options: &'a PnpOptions,
    noise: PixelNoise<'a>,
}

/// Where the refits start: a pose, the correspondences of the first round, RANSAC's count.
struct Start {
    pose: SE3,
    subset: Vec<usize>,
    ransac_iterations: usize,
}

/// The last solve: the pose, its report and what the covariance is computed from.
struct FinalSolve {
    pose: SE3,
    report: Option<LmReport>,
    information: Information,
}

/// What the covariance of the last solve comes from.
enum Information {
    /// The joint solve's marginal covariance (independent point errors only).
    Joint(Option<Matrix6<f64>>),
    /// H = Σ JⱼᵀJⱼ/σ² of a plain least-squares solve on exact points, and its cost Σ‖rⱼ‖²/σ².
    LeastSquares(Matrix6<f64>, f64),
    /// Nothing reusable: propagate at the pose ([`propagated_covariance`]).
    Propagate,
}

impl Correspondences<'_> {
    /// Step 1, the start: the given pose (the first round is robust over every point in front
    /// of it), P3P RANSAC (the first round starts from its consensus), or — with
    /// `ransac_with_init` — whichever of the two has the lower MSAC score.
    fn start(&self, init: Option<&SE3>) -> std::result::Result<Start, Box<PnpResult>> {
        let n = self.points.len();
        let fail = |reason: String, iterations| Box::new(PnpResult::failure(n, reason, iterations));
        let from_init = init.map(|pose| Start {
            pose: *pose,
            subset: (0..n).filter(|&j| project(self.camera, pose, &self.points[j]).p_cam.z > 0.0).collect(),
            ransac_iterations: 0,
        });
        let mut ransac_iterations = 0;
        let from_ransac = if init.is_some() && !self.options.ransac_with_init {
            None
        } else if n < MIN_POINTS_RANSAC {
            if from_init.is_none() {
                return Err(fail(format!("too few correspondences: {n} < {MIN_POINTS_RANSAC}"), 0));
            }
            None
        } else {
            let (pose, iterations) = ransac::ransac(self.camera, self.points, self.pixels, self.options);
            ransac_iterations = iterations;
            if pose.is_none() && from_init.is_none() {
                return Err(fail("RANSAC found no pose with enough inliers".into(), iterations));
            }
            pose.map(|pose| {
                let subset = inlier_indices(self.camera, self.points, self.pixels, &pose, self.options.max_residual_px);
                Start { pose, subset, ransac_iterations }
            })
        };
        let mut start = match (from_init, from_ransac) {
            (Some(a), Some(b)) => self.better_start(a, b),
            (Some(a), None) => a,
            (None, Some(b)) => b,
            (None, None) => return Err(fail("no start pose".into(), 0)),
        };
        start.ransac_iterations = ransac_iterations;
        if n < MIN_INLIERS {
            return Err(fail(format!("too few correspondences: {n} < {MIN_INLIERS}"), start.ransac_iterations));
        }
        Ok(start)
    }

    /// The given start or RANSAC's, by MSAC score over all correspondences (ties: the given).
    fn better_start(&self, given: Start, ransac: Start) -> Start {
        let t2 = self.options.max_residual_px * self.options.max_residual_px;
        let score = |pose: &SE3| {
            ransac::msac_score(self.camera, self.points, self.pixels, pose, t2, f64::INFINITY)
                .map_or(f64::INFINITY, |s| s.0)
        };
        if score(&ransac.pose) < score(&given.pose) { ransac } else { given }
    }

    /// Step 2, the robust rounds: LM on SE(3) with the robust kernel over `subset`, then
    /// re-gate every correspondence (η_r, or its Mahalanobis form with uncertain points) and
    /// repeat until the inlier set is stable (at most `max_refits` rounds).
    fn refit(&self, start: SE3, subset: Vec<usize>) -> (SE3, Vec<usize>, Option<LmReport>) {
        let o = self.options;
        // with the propagated model a final least-squares solve follows: the robust rounds
        // only have to settle the inlier set
        let final_solve_follows = o.covariance == CovarianceModel::Propagated && o.loss != RobustLoss::None;
        let lm =
            if final_solve_follows { LmOptions { cost_tolerance: ROBUST_ROUND_COST_TOLERANCE, ..o.lm } } else { o.lm };
        let (mut pose, mut subset, mut report) = (start, subset, None);
        for _ in 0..o.max_refits.max(1) {
            if subset.len() < MIN_INLIERS {
                break;
            }
            let w = weighting(self.camera, self.points, &pose, &subset, self.uncertainty, self.noise);
            let problem = w.problem(self.camera, self.points, self.pixels, &subset, o.loss);
            let (next, r) = levenberg_marquardt(&problem, pose, &lm);
            pose = next;
            report = Some(r);
            let next_subset =
                gated_indices(self.camera, self.points, self.pixels, &pose, self.uncertainty, self.noise, o);
            if next_subset == subset {
                break;
            }
            subset = next_subset;
        }
        (pose, subset, report)
    }

    /// Step 3, the last solve on the stable inliers (propagated model only): with point
    /// uncertainty the joint maximum-likelihood solve over the pose and the point
    /// corrections; without it plain least squares (the outliers are gone: it is the
    /// efficient estimator, and the one the covariance is exact for).
    fn final_solve(&self, pose: SE3, subset: &[usize]) -> FinalSolve {
        let o = self.options;
        let propagate = FinalSolve { pose, report: None, information: Information::Propagate };
        if o.covariance != CovarianceModel::Propagated {
            return propagate;
        }
        if let Some(u) = self.uncertainty {
            // Shared keyframe-pose errors enter the sandwich covariance only (see `joint`).
            let problem = joint::JointProblem::new(self.camera, self.points, self.pixels, subset, u, self.noise);
            let (pose, cov, r) = problem.solve(pose, &o.lm);
            let information = if u.shared.is_none() { Information::Joint(cov) } else { Information::Propagate };
            return FinalSolve { pose, report: Some(r), information };
        }
        if o.loss == RobustLoss::None {
            return propagate;
        }
        let w = weighting(self.camera, self.points, &pose, subset, None, self.noise);
        let problem = w.problem(self.camera, self.points, self.pixels, subset, RobustLoss::None);
        let (pose, r, h) = final_least_squares(&problem, pose, &o.lm);
        // exact points: C = (Σ JⱼᵀJⱼ/σ²)⁻¹ is the information of this very solve, and its cost
        // is Σ‖rⱼ‖²/σ²
        FinalSolve { pose, report: Some(r), information: Information::LeastSquares(h, r.final_cost) }
    }

    /// Step 4: the covariance (C_G) and the isometric σ, the RMS, and the acceptance test —
    /// an observable pose ([`inverse_information`]) from at least [`MIN_ACCEPTED_INLIERS`]
    /// inliers that random pixels would not give ([`chance_probability`]).
    fn finish(
        &self,
        last: FinalSolve,
        report: Option<LmReport>,
        subset: &[usize],
        ransac_iterations: usize,
    ) -> PnpResult {
        let (n, o, pose) = (self.points.len(), self.options, last.pose);
        let report = last.report.or(report);
        let mut inliers = vec![false; n];
        for &j in subset {
            inliers[j] = true;
        }
        let sum_sq: f64 = match last.information {
            Information::LeastSquares(_, cost) if self.noise.scales.is_none() => cost * o.pixel_sigma * o.pixel_sigma,
            _ => subset
                .iter()
                .map(|&j| (project(self.camera, &pose, &self.points[j]).uv - self.pixels[j]).norm_squared())
                .sum(),
        };
        // the pixel part, where propagating C computed it in the same pass
        let mut pixel_part = None;
        let covariance = match (o.covariance, last.information) {
            (CovarianceModel::Paper, _) => {
                paper_covariance(self.camera, self.points, self.pixels, &pose, subset, o.loss)
            }
            (CovarianceModel::Propagated, Information::Joint(cov)) => cov.filter(|c| inverse_information(c).is_some()),
            (CovarianceModel::Propagated, Information::LeastSquares(h, _)) => inverse_information(&h),
            (CovarianceModel::Propagated, Information::Propagate) => {
                propagated_covariance(self.camera, self.points, &pose, subset, self.uncertainty, self.noise).map(|c| {
                    pixel_part = Some(c.pixel);
                    c.full
                })
            }
        };
        let rejection = match covariance {
            None => Some("degenerate geometry: the pose is not observable from these points".to_string()),
            Some(_) => self.chance_rejection(subset, ransac_iterations),
        };
        let variance_factor = self.variance_factor(&pose, subset);
        let covariance = match o.covariance {
            CovarianceModel::Propagated => covariance.map(|c| c * variance_factor.max(1.0)),
            CovarianceModel::Paper => covariance,
        };
        let (Some(covariance), None) = (covariance, &rejection) else {
            let mut failed = PnpResult::failure(n, rejection.unwrap_or_default(), ransac_iterations);
            failed.world_from_cam = pose;
            failed.inliers = inliers;
            failed.lm = report;
            return failed;
        };
        let pixel_covariance = match o.covariance {
            // exact points: the pixel noise is all there is
            CovarianceModel::Propagated if self.uncertainty.is_some() => pixel_part
                .or_else(|| {
                    propagated_covariance(self.camera, self.points, &pose, subset, self.uncertainty, self.noise)
                        .map(|c| c.pixel)
                })
                .map_or(covariance, |c| c * variance_factor.max(1.0)),
            CovarianceModel::Propagated | CovarianceModel::Paper => covariance,
        };
        let (sigma_p, sigma_r) = isometric_sigmas(&covariance);
        let converged = report.is_some_and(|r| r.converged());
        PnpResult {
            success: true,
            reason: if converged { "ok".into() } else { "ok (LM stopped at its iteration cap)".into() },
            world_from_cam: pose,
            covariance,
            pixel_covariance,
            inliers,
            rms_px: (sum_sq / subset.len() as f64).sqrt(),
            variance_factor,
            sigma_p,
            sigma_r,
            ransac_iterations,
            lm: report,
        }
    }
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
    for (name, value, cap) in [
        ("min_iterations", r.min_iterations, MAX_RANSAC_ITERATIONS),
        ("max_iterations", r.max_iterations, MAX_RANSAC_ITERATIONS),
        ("lm_max_iterations", options.lm.max_iterations, MAX_LM_ITERATIONS),
        ("max_refits", options.max_refits, MAX_REFITS),
    ] {
        if value > cap {
            return Err(GeolocError::invalid(name, format!("must be at most {cap}, got {value}")));
        }
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
        check_covariances("point_covariances", u.covariances)?;
        if let Some(s) = &u.shared {
            check_covariances("pose_covariances", s.pose_covariances)?;
        }
        if let Some(s) = &u.shared {
            if s.jacobians.len() != n {
                return Err(GeolocError::invalid(
                    "point_pose_jacobians",
                    format!("has {} rows for {n} points", s.jacobians.len()),
                ));
            }
            let poses = s.pose_covariances.len();
            for (j, row) in s.jacobians.iter().enumerate() {
                let increasing = row.windows(2).all(|w| w[0].0 < w[1].0);
                if !increasing || row.last().is_some_and(|(k, _)| *k >= poses) {
                    return Err(GeolocError::invalid(
                        format!("point_pose_jacobians[{j}]"),
                        format!("expected increasing pose indices below {poses}"),
                    ));
                }
            }
        }
    }
    Ok(())
}

/// √χ²₂(0.9999): a correct 2D residual exceeds this many σ with probability 1e-4.
pub const CHI2_2DOF_9999_SQRT: f64 = crate::stats::chi2::CHI2_2_9999_SQRT;

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
    noise: PixelNoise<'_>,
    options: &PnpOptions,
) -> Vec<usize> {
    if uncertainty.is_none() && noise.scales.is_none() {
        return inlier_indices(camera, points, pixels, pose, gate_px(options.max_residual_px, noise.sigma));
    }
    (0..points.len())
        .filter(|&j| {
            let p = project(camera, pose, &points[j]);
            if p.p_cam.z <= 0.0 {
                return false;
            }
            let sigma = noise.at(j);
            let gate = (gate_px(options.max_residual_px, sigma) / sigma).powi(2);
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
    noise: PixelNoise<'_>,
) -> Weighting {
    let (weights, biases) = subset
        .iter()
        .map(|&j| {
            let sigma = noise.at(j);
            let (s, bias) = residual_moments(camera, points, pose, j, uncertainty, sigma, true);
            (s.try_inverse().unwrap_or_else(|| Matrix2::identity() / (sigma * sigma)), bias)
        })
        .unzip();
    Weighting { weights, biases }
}

/// The two rows ∂u/∂δ, ∂v/∂δ of the projection's Jacobian for the right perturbation
/// T ⊞ δ = T exp(δ^) of world_from_cam, translation first, at p = (x, y, z) in camera
/// coordinates — [`j_uv_pose`] in closed form for PnP's hot loop (checked against it and
/// against central differences in the tests):
///   ∂u/∂δ = (f_x/z) (−1, 0, x/z, xy/z, −(z + x²/z), y),
///   ∂v/∂δ = (f_y/z) (0, −1, y/z, z + y²/z, −xy/z, −x).
#[inline(always)]
fn pose_jacobian_rows(fx: f64, fy: f64, p: &Vector3<f64>) -> ([f64; 6], [f64; 6]) {
    let inv_z = 1.0 / p.z;
    let (xz, yz) = (p.x * inv_z, p.y * inv_z);
    let (a, c) = (fx * inv_z, fy * inv_z);
    let ju = [-a, 0.0, a * xz, a * xz * p.y, -a * (p.z + p.x * xz), a * p.y];
    let jv = [0.0, -c, c * yz, c * (p.z + p.y * yz), -c * p.x * yz, -c * p.x];
    (ju, jv)
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
            let (ju, jv) = pose_jacobian_rows(fx, fy, &p);
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::j_uv_pose;
    use crate::testing::SplitMix64;

    /// The hand-written rows of PoseProblem's hot loop equal camera::j_uv_pose and central
    /// differences of π(T exp(δ^), X) on the manifold.
    #[test]
    fn hand_written_pose_jacobian_matches_j_uv_pose_and_central_differences() {
        let camera = Camera::new(525.0, 520.0, 320.0, 240.0).expect("valid");
        let mut rng = SplitMix64::new(7);
        for _ in 0..100 {
            let pose = rng.pose(3.0);
            let x = pose * Vector3::new(rng.uniform_in(-2.0, 2.0), rng.uniform_in(-1.5, 1.5), rng.uniform_in(1.0, 8.0));
            let p = project(&camera, &pose, &x);
            let (ju, jv) = pose_jacobian_rows(camera.fx, camera.fy, &p.p_cam);
            let analytic = j_uv_pose(&camera, &p);
            let h = 1e-6;
            for i in 0..6 {
                let mut d = Vector6::zeros();
                d[i] = h;
                let plus = project(&camera, &(pose * SE3::exp(&d)), &x).uv;
                let minus = project(&camera, &(pose * SE3::exp(&-d)), &x).uv;
                let numeric = (plus - minus) / (2.0 * h);
                let scale = analytic.abs().max();
                assert!((ju[i] - analytic[(0, i)]).abs() <= 1e-12 * scale, "u, column {i}");
                assert!((jv[i] - analytic[(1, i)]).abs() <= 1e-12 * scale, "v, column {i}");
                assert!((ju[i] - numeric.x).abs() <= 1e-6 * scale, "u vs differences, column {i}");
                assert!((jv[i] - numeric.y).abs() <= 1e-6 * scale, "v vs differences, column {i}");
            }
        }
    }

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
