//! Two-view verification from the images alone: essential-matrix RANSAC with the known
//! pinhole camera, and the relative pose it implies.
//!
//! The epipolar check of [`crate::matching::epipolar_filter`] builds its geometry from the
//! keyframes' pose labels, so it rejects exactly the matches that would correct a wrong
//! label. Here the geometry comes from the matches themselves.
//!
//! Conventions (those of [`crate::matching`]): the relative pose b_from_a = (R, t) maps a
//! point of camera a to camera b, p_b = R p_a + t; with normalized coordinates x = K⁻¹(u, v, 1)
//! every true match satisfies
//!
//!   x_bᵀ E x_a = 0,   E = t^ R,   F = K⁻ᵀ E K⁻¹ (pixels),
//!
//! and a match is an inlier when its Sampson distance
//! (u_bᵀFu_a)² / (‖(Fu_a)₁,₂‖² + ‖(Fᵀu_b)₁,₂‖²) ([`sampson_distance`]) is at most `max_px`².
//! Since u = K x, the algebraic residual u_bᵀFu_a equals x_bᵀEx_a exactly.
//!
//! The estimator:
//! 1. RANSAC over 5-match samples with the five-point solver of Stewénius, Engels & Nistér
//!    (*Recent developments on direct relative orientation*, ISPRS J. 2006): the 4-dimensional
//!    null space of the 5×9 epipolar system gives E = xX + yY + zZ + W; the ten cubic
//!    constraints det E = 0 and 2EEᵀE − tr(EEᵀ)E = 0 (in the 20 monomials of degree ≤ 3 in
//!    x, y, z) are Gauss–Jordan reduced, and the real eigenvalues of the 10×10 action matrix
//!    of multiplication by x, with their eigenvectors, give up to ten solutions. Hypotheses
//!    are ranked by the MSAC score Σ min(d², max_px²) with d the Sampson distance. The number
//!    of samples adapts to the inlier ratio w of the best model so far,
//!    k = ln(1 − 0.999)/ln(1 − w⁵), capped at `iterations`. (The 8-point algorithm needs w⁸:
//!    at 60 % outliers 500 samples contain an all-inlier one with probability 0.28, against
//!    0.994 for five points.)
//! 2. Local optimization (LO-RANSAC) of every hypothesis that beats the best raw score so
//!    far, and of the ten best other hypotheses once the sampling stops; the lowest polished
//!    score wins. Polishing is
//!    * linear refits on the inliers: 8-point least squares on the normalized coordinates,
//!      each row weighted by 1/(‖(Fu_a)₁,₂‖² + ‖(Fᵀu_b)₁,₂‖²) of the current estimate (so the
//!      algebraic error approximates the Sampson error), projected onto the essential
//!      manifold (singular values (1, 1, 0)), the inliers re-classified;
//!    * the decomposition of E (below), then Levenberg–Marquardt on the relative pose
//!      minimizing the squared Sampson distances of the inliers, the inliers re-classified.
//!      The linear refit minimizes an algebraic error, and its projection onto the manifold
//!      moves it further: in the synthetic scenes of the tests it alone left t up to 6° off
//!      where the Sampson optimum is within 0.6°.
//!
//!    Each step is kept only while it lowers the MSAC score.
//! 3. The four-fold decomposition E = U diag(1, 1, 0) Vᵀ (det U = det V = 1),
//!    R ∈ {UWVᵀ, UWᵀVᵀ}, t = ±u₃ with W = [[0, −1, 0], [1, 0, 0], [0, 0, 1]]: the candidate
//!    that puts most inliers in front of both cameras (cheirality) is returned, ‖t‖ = 1, and
//!    the returned essential matrix is exactly t^R. The inlier mask is the threshold rule
//!    applied to that matrix.
//!
//! What the images determine (synthetic scenes, points 2–6 m away, 0.5 px noise, 30–60 %
//! outliers, rotations up to 30°, 400 matches; `tests::statistics`): with baselines of
//! 0.2–0.5 m the inliers are found with precision ≥ 0.98 and recall ≥ 0.95, R within 0.5°
//! and t within 2° in 96 % of the scenes; in the others a few outliers lie within the
//! threshold of a slightly different geometry that MSAC prefers to the truth (t up to 6°
//! off). With 0.05–0.2 m the parallax is comparable to the image motion of a degree of
//! rotation: the inliers are still found and R is within 0.5° in 98 % of the scenes (1.5° at
//! worst), but t is off by a median 1–5°.
//!
//! Degenerate samples (repeated points, rank-deficient systems, NaN from extreme values) are
//! skipped. A pure rotation (t = 0) fits every E = t^R with the true R: the rotation is then
//! still found but the translation direction is meaningless. Everything runs on the calling
//! thread with [`crate::rng::SplitMix64`] seeded from `seed`: the same input gives the same
//! bits.

use nalgebra::{Matrix3, SMatrix, SVD, SVector, Schur, Vector2, Vector3};

use crate::camera::Camera;
use crate::error::{GeolocError, Result};
use crate::lie::{SE3, SO3, so3};
use crate::matching::{Match, sampson_distance};
use crate::optim::{LeastSquares, LmOptions, levenberg_marquardt};
use crate::rng::SplitMix64;

/// Fewest matches the verification runs on (the linear refit needs eight); fewer give an
/// unverified result, not an error.
pub const MIN_MATCHES: usize = 8;
/// Cap of [`TwoViewOptions::iterations`] (a larger request is refused, not run).
pub const MAX_ITERATIONS: usize = 1_000_000;
/// Probability of having drawn one all-inlier sample at which the sampling stops early.
pub const CONFIDENCE: f64 = 0.999;

/// Matches per minimal sample (the five-point solver).
const SAMPLE_SIZE: usize = 5;
/// Runners-up (by raw MSAC score) polished after the sampling.
const EXTRA_POLISHES: usize = 10;
/// Rounds of refit and re-classification at most.
const MAX_REFITS: usize = 10;
/// Iteration cap of the SVD and Schur decompositions (they converge in a few dozen; the
/// cap only turns a pathological input into a skipped sample).
const MAX_DECOMPOSITION_ITERATIONS: usize = 1_000;
/// A system whose k-th singular value is below this times the largest is taken as rank < k.
const RANK_TOLERANCE: f64 = 1e-10;
/// An eigenvalue of the action matrix counts as real when |Im λ| ≤ this · (1 + |Re λ|).
const REAL_EIGENVALUE_TOLERANCE: f64 = 1e-8;

/// Options of [`verify_two_view`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TwoViewOptions {
    /// Inlier threshold on the Sampson distance, in pixels (default 2).
    pub max_px: f64,
    /// Most RANSAC samples (default 500); sampling stops earlier once an all-inlier sample
    /// has been drawn with probability [`CONFIDENCE`].
    pub iterations: usize,
    /// Fewest inliers for [`TwoView::verified`] (default 15, at least [`MIN_MATCHES`]).
    pub min_inliers: usize,
    /// Seed of the sampler (default 0).
    pub seed: u64,
}

impl Default for TwoViewOptions {
    fn default() -> Self {
        Self { max_px: 2.0, iterations: 500, min_inliers: 15, seed: 0 }
    }
}

impl TwoViewOptions {
    /// Checks the options.
    ///
    /// # Errors
    /// [`GeolocError::InvalidInput`] naming the field: `max_px` not finite and > 0,
    /// `iterations` outside 1..=[`MAX_ITERATIONS`], `min_inliers` below [`MIN_MATCHES`].
    pub fn check(&self) -> Result<()> {
        if !(self.max_px.is_finite() && self.max_px > 0.0) {
            return Err(GeolocError::invalid("max_px", format!("must be finite and > 0, got {}", self.max_px)));
        }
        if !(1..=MAX_ITERATIONS).contains(&self.iterations) {
            return Err(GeolocError::invalid(
                "iterations",
                format!("must be in 1..={MAX_ITERATIONS}, got {}", self.iterations),
            ));
        }
        if self.min_inliers < MIN_MATCHES {
            return Err(GeolocError::invalid(
                "min_inliers",
                format!("must be at least {MIN_MATCHES} (the linear refit's minimum), got {}", self.min_inliers),
            ));
        }
        Ok(())
    }
}

/// The result of [`verify_two_view`].
#[derive(Clone, Debug, PartialEq)]
pub struct TwoView {
    /// Per match: Sampson distance to [`TwoView::essential`] (as F = K⁻ᵀEK⁻¹) ≤ `max_px`.
    /// All false when no model was found.
    pub inlier_mask: Vec<bool>,
    /// Number of true entries of the mask.
    pub inliers: usize,
    /// `inliers ≥ min_inliers`.
    pub verified: bool,
    /// E = t^R of [`TwoView::b_from_a`] (‖E‖_F = √2); zero when no model was found.
    pub essential: Matrix3<f64>,
    /// The relative pose p_b = R p_a + t with ‖t‖ = 1 (the scale is not observable);
    /// the identity when no model was found.
    pub b_from_a: SE3,
    /// RANSAC samples drawn.
    pub iterations: usize,
}

impl TwoView {
    /// No model: an all-false mask over `n` matches.
    fn unverified(n: usize, iterations: usize) -> Self {
        Self {
            inlier_mask: vec![false; n],
            inliers: 0,
            verified: false,
            essential: Matrix3::zeros(),
            b_from_a: SE3::identity(),
            iterations,
        }
    }
}

/// Verifies the `matches` between two images taken by the same pinhole `camera` from their
/// (undistorted) keypoints alone; see the module doc. `matches[i].a` indexes `keypoints_a`,
/// `matches[i].b` indexes `keypoints_b`. Fewer than [`MIN_MATCHES`] matches, or no
/// consensus, give `verified: false` (not an error).
///
/// # Errors
/// Bad options (see [`TwoViewOptions::check`]) or intrinsics (`fx`, `fy`, `cx`, `cy`),
/// non-finite keypoints (`keypoints_a` / `keypoints_b`, with the index), a match indexing
/// past the keypoints (`matches`).
pub fn verify_two_view(
    camera: &Camera,
    keypoints_a: &[Vector2<f64>],
    keypoints_b: &[Vector2<f64>],
    matches: &[Match],
    options: &TwoViewOptions,
) -> Result<TwoView> {
    options.check()?;
    let camera = Camera::new(camera.fx, camera.fy, camera.cx, camera.cy)?;
    for (name, keypoints) in [("keypoints_a", keypoints_a), ("keypoints_b", keypoints_b)] {
        if let Some(i) = keypoints.iter().position(|k| !(k.x.is_finite() && k.y.is_finite())) {
            return Err(GeolocError::NonFinite { name: name.into(), index: i });
        }
    }
    if let Some(i) = matches.iter().position(|m| m.a >= keypoints_a.len() || m.b >= keypoints_b.len()) {
        return Err(GeolocError::invalid(
            "matches",
            format!(
                "matches[{i}] = ({}, {}) indexes past the keypoints ({} in a, {} in b)",
                matches[i].a,
                matches[i].b,
                keypoints_a.len(),
                keypoints_b.len()
            ),
        ));
    }
    let n = matches.len();
    if n < MIN_MATCHES {
        return Ok(TwoView::unverified(n, 0));
    }
    let problem = Problem::new(&camera, keypoints_a, keypoints_b, matches, options.max_px);
    let (best, iterations) = problem.ransac(options);
    let Some(pose) = best.and_then(|m| m.pose) else { return Ok(TwoView::unverified(n, iterations)) };
    // the Sampson cost is the same for all four poses of ±E: the cheirality of the pose
    // decomposed before the LM may not hold for the refined one
    let pose = problem.decompose(&pose.essential()).unwrap_or(pose);
    let pose = RelativePose { rotation: pose.rotation.normalized(), translation: pose.translation };
    let essential = pose.essential();
    let inlier_mask = problem.mask(&essential);
    let inliers = inlier_mask.iter().filter(|&&k| k).count();
    Ok(TwoView {
        inlier_mask,
        inliers,
        verified: inliers >= options.min_inliers,
        essential,
        b_from_a: SE3::new(pose.rotation, pose.translation),
        iterations,
    })
}

/// A RANSAC model: E, its MSAC score and inlier count, and its pose once decomposed
/// (then E = t^R).
#[derive(Clone, Copy, Debug)]
struct Model {
    essential: Matrix3<f64>,
    score: f64,
    inliers: usize,
    pose: Option<RelativePose>,
}

/// A relative pose b_from_a = (R, t) with ‖t‖ = 1: the state of the Sampson refinement.
#[derive(Clone, Copy, Debug, PartialEq)]
struct RelativePose {
    rotation: SO3,
    translation: Vector3<f64>,
}

impl RelativePose {
    /// E = t^R.
    fn essential(&self) -> Matrix3<f64> {
        so3::hat(&self.translation) * self.rotation.matrix()
    }
}

/// An orthonormal basis (b₁, b₂) of the plane ⟂ unit `t` (a fixed function of t).
fn tangent_basis(t: &Vector3<f64>) -> (Vector3<f64>, Vector3<f64>) {
    let a = t.abs();
    let axis = if a.x <= a.y && a.x <= a.z {
        Vector3::x()
    } else if a.y <= a.z {
        Vector3::y()
    } else {
        Vector3::z()
    };
    let b1 = t.cross(&axis).normalize();
    (b1, t.cross(&b1))
}

/// Least squares of the signed Sampson residuals rᵢ = x_bᵀEx_a / √denᵢ (pixels) of the
/// matches `subset` over the relative pose, E = t^R, with
/// denᵢ = ((Ex_a)₁² + (Eᵀx_b)₁²)/f_x² + ((Ex_a)₂² + (Eᵀx_b)₂²)/f_y² (the Sampson denominator
/// of F = K⁻ᵀEK⁻¹ at the pixels). Five local parameters δ = (δt₁, δt₂, φ): t ⊞ δ =
/// (t + δt₁b₁ + δt₂b₂)/‖·‖ on the sphere ([`tangent_basis`]), R ⊞ φ = R exp(φ^), so
/// ∂E/∂δtⱼ = bⱼ^R, ∂E/∂φₖ = t^R eₖ^ and ∂rᵢ/∂p = (x_bᵀE_p x_a)/√den − rᵢ ∂den/∂p / (2 den).
struct SampsonProblem<'a> {
    problem: &'a Problem,
    subset: &'a [usize],
}

impl LeastSquares<5> for SampsonProblem<'_> {
    type State = RelativePose;

    fn normal_equations(&self, pose: &RelativePose) -> (SMatrix<f64, 5, 5>, SVector<f64, 5>, f64) {
        let (r, t) = (pose.rotation.matrix(), &pose.translation);
        let e = so3::hat(t) * r;
        let (b1, b2) = tangent_basis(t);
        let derivatives = [
            so3::hat(&b1) * r,
            so3::hat(&b2) * r,
            e * so3::hat(&Vector3::x()),
            e * so3::hat(&Vector3::y()),
            e * so3::hat(&Vector3::z()),
        ];
        let (wx, wy) = (self.problem.inv_fx2, self.problem.inv_fy2);
        let (mut h, mut g, mut cost) = (SMatrix::<f64, 5, 5>::zeros(), SVector::<f64, 5>::zeros(), 0.0);
        for &i in self.subset {
            let (xa, xb) = &self.problem.normalized[i];
            let (ea, eb) = (e * xa, e.tr_mul(xb));
            let den = (ea.x * ea.x + eb.x * eb.x) * wx + (ea.y * ea.y + eb.y * eb.y) * wy;
            if !(den.is_finite() && den > 0.0) {
                continue;
            }
            let root = den.sqrt();
            let residual = xb.dot(&ea) / root;
            let j = SVector::<f64, 5>::from_fn(|p, _| {
                let (da, db) = (derivatives[p] * xa, derivatives[p].tr_mul(xb));
                let d_den = 2.0 * ((ea.x * da.x + eb.x * db.x) * wx + (ea.y * da.y + eb.y * db.y) * wy);
                xb.dot(&da) / root - residual * d_den / (2.0 * den)
            });
            h += j * j.transpose();
            g += j * residual;
            cost += residual * residual;
        }
        (h, g, cost)
    }

    fn retract(&self, pose: &RelativePose, delta: &SVector<f64, 5>) -> RelativePose {
        let (b1, b2) = tangent_basis(&pose.translation);
        let moved = pose.translation + b1 * delta[0] + b2 * delta[1];
        RelativePose {
            rotation: pose.rotation * SO3::exp(&Vector3::new(delta[2], delta[3], delta[4])),
            translation: moved.normalize(),
        }
    }
}

/// The matches of one call: pixels and normalized coordinates of both ends.
struct Problem {
    /// K⁻¹.
    k_inv: Matrix3<f64>,
    /// (u_a, u_b) per match.
    pixels: Vec<(Vector2<f64>, Vector2<f64>)>,
    /// (x_a, x_b) = (K⁻¹u_a, K⁻¹u_b) per match, z = 1.
    normalized: Vec<(Vector3<f64>, Vector3<f64>)>,
    /// The inlier threshold (pixels).
    max_px: f64,
    /// 1/f_x², 1/f_y².
    inv_fx2: f64,
    inv_fy2: f64,
}

impl Problem {
    fn new(camera: &Camera, ka: &[Vector2<f64>], kb: &[Vector2<f64>], matches: &[Match], max_px: f64) -> Self {
        let k_inv = camera.inverse_matrix();
        let pixels: Vec<_> = matches.iter().map(|m| (ka[m.a], kb[m.b])).collect();
        let normalized = pixels.iter().map(|(a, b)| (camera.unproject(a), camera.unproject(b))).collect();
        let (inv_fx2, inv_fy2) = (1.0 / (camera.fx * camera.fx), 1.0 / (camera.fy * camera.fy));
        Self { k_inv, pixels, normalized, max_px, inv_fx2, inv_fy2 }
    }

    /// F = K⁻ᵀ E K⁻¹.
    fn fundamental(&self, e: &Matrix3<f64>) -> Matrix3<f64> {
        self.k_inv.transpose() * e * self.k_inv
    }

    /// Sampson distances (pixels) of all matches to E.
    fn distances<'a>(&'a self, e: &Matrix3<f64>) -> impl Iterator<Item = f64> + 'a {
        let f = self.fundamental(e);
        self.pixels.iter().map(move |(a, b)| sampson_distance(&f, a, b))
    }

    /// The threshold rule d ≤ max_px per match (false for NaN).
    fn mask(&self, e: &Matrix3<f64>) -> Vec<bool> {
        self.distances(e).map(|d| d <= self.max_px).collect()
    }

    /// Indices of the matches with d ≤ max_px.
    fn inlier_indices(&self, e: &Matrix3<f64>) -> Vec<usize> {
        self.distances(e).enumerate().filter(|(_, d)| *d <= self.max_px).map(|(i, _)| i).collect()
    }

    /// MSAC score Σ min(d², max_px²) and inlier count of E; None as soon as the partial
    /// score reaches `bound` (E cannot beat the best).
    fn msac(&self, e: &Matrix3<f64>, bound: f64) -> Option<(f64, usize)> {
        let t2 = self.max_px * self.max_px;
        let (mut score, mut count) = (0.0, 0);
        for d in self.distances(e) {
            if d <= self.max_px {
                count += 1;
                score += d * d;
            } else {
                score += t2;
            }
            if score >= bound {
                return None;
            }
        }
        Some((score, count))
    }

    /// Five-point RANSAC with local optimization: every hypothesis that beats the best raw
    /// (unpolished) MSAC score so far is polished ([`Problem::polish`]), and so are the
    /// [`EXTRA_POLISHES`] best of the others once the sampling stops; the polished model
    /// with the lowest score wins. Returns it and the samples drawn.
    fn ransac(&self, options: &TwoViewOptions) -> (Option<Model>, usize) {
        let n = self.pixels.len();
        let mut rng = SplitMix64::new(options.seed);
        let mut best: Option<Model> = None;
        // raw hypotheses compete with the best raw one, not with the polished best: a polished
        // model in a wrong basin would otherwise keep every later sample from being polished
        let mut best_raw = f64::INFINITY;
        // the runners-up (raw score, E), best first, polished at the end
        let mut runners_up: Vec<(f64, Matrix3<f64>, usize)> = Vec::with_capacity(EXTRA_POLISHES + 1);
        let (mut needed, mut iterations) = (options.iterations, 0);
        while iterations < needed {
            iterations += 1;
            let sample = sample_distinct::<SAMPLE_SIZE>(&mut rng, n);
            let xa = sample.map(|i| self.normalized[i].0);
            let xb = sample.map(|i| self.normalized[i].1);
            for essential in five_point(&xa, &xb) {
                let bound =
                    if runners_up.len() == EXTRA_POLISHES { runners_up[EXTRA_POLISHES - 1].0 } else { f64::INFINITY };
                let Some((score, inliers)) = self.msac(&essential, bound.max(best_raw)) else { continue };
                if score >= best_raw {
                    let at = runners_up.partition_point(|r| r.0 <= score);
                    runners_up.insert(at, (score, essential, inliers));
                    runners_up.truncate(EXTRA_POLISHES);
                    continue;
                }
                best_raw = score;
                let model = self.polish(Model { essential, score, inliers, pose: None });
                if best.as_ref().is_none_or(|b| model.score < b.score) {
                    needed = required_iterations(model.inliers as f64 / n as f64, options.iterations);
                    best = Some(model);
                }
            }
        }
        for (score, essential, inliers) in runners_up {
            let model = self.polish(Model { essential, score, inliers, pose: None });
            if best.as_ref().is_none_or(|b| model.score < b.score) {
                best = Some(model);
            }
        }
        (best, iterations)
    }

    /// The local optimization of a hypothesis (LO-RANSAC): linear refits on its inliers
    /// ([`Problem::refit`]), then the four-fold decomposition ([`Problem::decompose`]) and
    /// rounds of Sampson least squares ([`SampsonProblem`]) on the inliers of the current
    /// pose; every step is kept only if it lowers the MSAC score.
    fn polish(&self, mut model: Model) -> Model {
        for _ in 0..MAX_REFITS {
            let Some(refit) = self.refit(&model.essential) else { break };
            match self.msac(&refit, model.score) {
                Some((score, inliers)) => model = Model { essential: refit, score, inliers, pose: None },
                None => break,
            }
        }
        let Some(mut pose) = self.decompose(&model.essential) else { return model };
        // t^R is ±the refit (to rounding): the model from here on is the pose's
        let Some((mut score, mut inliers)) = self.msac(&pose.essential(), f64::INFINITY) else { return model };
        for _ in 0..MAX_REFITS {
            let subset = self.inlier_indices(&pose.essential());
            if subset.len() < MIN_MATCHES {
                break;
            }
            let sampson = SampsonProblem { problem: self, subset: &subset };
            let (refined, _) = levenberg_marquardt(&sampson, pose, &LmOptions::default());
            match self.msac(&refined.essential(), score) {
                Some((s, c)) => (pose, score, inliers) = (refined, s, c),
                None => break,
            }
        }
        Model { essential: pose.essential(), score, inliers, pose: Some(pose) }
    }

    /// Weighted linear (8-point) refit on the inliers of `e`, projected onto the essential
    /// manifold; None with fewer than eight inliers or a rank-deficient system.
    fn refit(&self, e: &Matrix3<f64>) -> Option<Matrix3<f64>> {
        let f = self.fundamental(e);
        let mut m = SMatrix::<f64, 9, 9>::zeros();
        let mut rows = 0;
        for ((ua, ub), (xa, xb)) in self.pixels.iter().zip(&self.normalized) {
            let d = sampson_distance(&f, ua, ub);
            if d.is_nan() || d > self.max_px {
                continue;
            }
            // the Sampson denominator of the current estimate, in pixels
            let (pa, pb) = (Vector3::new(ua.x, ua.y, 1.0), Vector3::new(ub.x, ub.y, 1.0));
            let (fa, fb) = (f * pa, f.tr_mul(&pb));
            let den = fa.x * fa.x + fa.y * fa.y + fb.x * fb.x + fb.y * fb.y;
            if !(den.is_finite() && den > 0.0) {
                continue;
            }
            let q = epipolar_row(xa, xb);
            m += (q * q.transpose()) / den;
            rows += 1;
        }
        if rows < MIN_MATCHES {
            return None;
        }
        let v = null_vector(m, 8)?;
        project_essential(&Matrix3::new(v[0], v[1], v[2], v[3], v[4], v[5], v[6], v[7], v[8]))
    }

    /// The relative pose of the four-fold decomposition of `e` that puts the most inliers of
    /// `e` in front of both cameras (the first candidate on ties).
    fn decompose(&self, e: &Matrix3<f64>) -> Option<RelativePose> {
        let (u, v) = essential_frames(e)?;
        let w = Matrix3::new(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0);
        let u3 = u.column(2).into_owned();
        let (r1, r2) = (u * w * v.transpose(), u * w.transpose() * v.transpose());
        let inliers: Vec<&(Vector3<f64>, Vector3<f64>)> =
            self.inlier_indices(e).into_iter().map(|i| &self.normalized[i]).collect();
        let mut best: Option<(RelativePose, usize)> = None;
        for (r, t) in [(r1, u3), (r1, -u3), (r2, u3), (r2, -u3)] {
            let in_front = inliers.iter().filter(|(xa, xb)| in_front_of_both(&r, &t, xa, xb)).count();
            if best.as_ref().is_none_or(|b| in_front > b.1) {
                best = Some((RelativePose { rotation: SO3::from_matrix_unchecked(r), translation: t }, in_front));
            }
        }
        best.map(|b| b.0)
    }
}

/// Whether the point seen at x_a and x_b lies in front of both cameras for b_from_a = (R, t):
/// the depths (d_a, d_b) minimizing ‖d_a R x_a + t − d_b x_b‖² are both positive.
fn in_front_of_both(r: &Matrix3<f64>, t: &Vector3<f64>, xa: &Vector3<f64>, xb: &Vector3<f64>) -> bool {
    let a = r * xa;
    let (aa, ab, bb) = (a.dot(&a), a.dot(xb), xb.dot(xb));
    let (at, bt) = (a.dot(t), xb.dot(t));
    let det = aa * bb - ab * ab;
    if det.is_nan() || det <= 1e-12 * aa * bb {
        return false; // parallel rays: no depth
    }
    let d_a = (ab * bt - at * bb) / det;
    let d_b = (aa * bt - ab * at) / det;
    d_a > 0.0 && d_b > 0.0
}

/// The row q of the epipolar system with q · vec(E) = x_bᵀ E x_a, vec row-major.
fn epipolar_row(xa: &Vector3<f64>, xb: &Vector3<f64>) -> SVector<f64, 9> {
    SVector::<f64, 9>::from_fn(|k, _| xb[k / 3] * xa[k % 3])
}

/// The right singular vector of the smallest singular value of the 9×9 `m`, if `m` has
/// rank ≥ `rank` (its `rank`-th singular value above [`RANK_TOLERANCE`] of the largest).
fn null_vector(m: SMatrix<f64, 9, 9>, rank: usize) -> Option<SVector<f64, 9>> {
    if !m.iter().all(|v| v.is_finite()) {
        return None;
    }
    let svd = SVD::try_new(m, false, true, f64::EPSILON, MAX_DECOMPOSITION_ITERATIONS)?;
    let s = &svd.singular_values;
    let full_rank = s[rank - 1] > RANK_TOLERANCE * s[0];
    if !full_rank {
        return None;
    }
    Some(svd.v_t?.row(8).transpose())
}

/// Rotations U, V (det = +1) with E = U diag(σ₁, σ₂, σ₃) Vᵀ, σ₁ ≥ σ₂ ≥ σ₃; None for a
/// non-finite E or one of rank < 2. U is built from V (u₁ ∝ Ev₁, u₂ ∝ Ev₂, u₃ = u₁ × u₂), so
/// the pair is consistent whatever sign conventions the SVD follows.
fn essential_frames(e: &Matrix3<f64>) -> Option<(Matrix3<f64>, Matrix3<f64>)> {
    if !e.iter().all(|v| v.is_finite()) {
        return None;
    }
    let scale = e.norm();
    let svd = SVD::try_new(*e, false, true, f64::EPSILON, MAX_DECOMPOSITION_ITERATIONS)?;
    let v_t = svd.v_t?;
    let (v1, v2) = (v_t.row(0).transpose(), v_t.row(1).transpose());
    let v3 = v1.cross(&v2);
    let u1 = (e * v1).try_normalize(RANK_TOLERANCE * scale)?;
    let ev2 = e * v2;
    let u2 = (ev2 - u1 * u1.dot(&ev2)).try_normalize(RANK_TOLERANCE * scale)?;
    let u3 = u1.cross(&u2);
    Some((Matrix3::from_columns(&[u1, u2, u3]), Matrix3::from_columns(&[v1, v2, v3])))
}

/// The nearest essential matrix U diag(1, 1, 0) Vᵀ (Frobenius norm, up to scale).
fn project_essential(e: &Matrix3<f64>) -> Option<Matrix3<f64>> {
    let (u, v) = essential_frames(e)?;
    Some(u.column(0) * v.column(0).transpose() + u.column(1) * v.column(1).transpose())
}

/// Samples needed so that P(some all-inlier sample) ≥ [`CONFIDENCE`], at most `cap`.
fn required_iterations(inlier_ratio: f64, cap: usize) -> usize {
    let all_good = inlier_ratio.powi(SAMPLE_SIZE as i32);
    if all_good >= 1.0 {
        return 1;
    }
    if all_good.is_nan() || all_good <= 0.0 {
        return cap;
    }
    let k = (1.0 - CONFIDENCE).ln() / (-all_good).ln_1p();
    if k.is_finite() { (k.ceil() as usize).clamp(1, cap) } else { cap }
}

/// `K` distinct indices below `n` (n ≥ K), uniform.
fn sample_distinct<const K: usize>(rng: &mut SplitMix64, n: usize) -> [usize; K] {
    let mut out = [0; K];
    let mut k = 0;
    while k < K {
        let c = ((rng.next_u64() >> 11) as usize) % n;
        if !out[..k].contains(&c) {
            out[k] = c;
            k += 1;
        }
    }
    out
}

// ---------------------------------------------------------------------------------------
// The five-point solver.

/// A polynomial of degree ≤ 3 in (x, y, z): coefficients of the monomials [`MONOMIALS`].
type Poly = [f64; 20];

/// Exponents (of x, y, z) of the 20 monomials of degree ≤ 3, in Stewénius' order: the ten
/// cubics (eliminated by Gauss–Jordan), then the basis of the quotient ring
/// [x², xy, xz, y², yz, z², x, y, z, 1] (indices 10..20; the linear ones at 16..20).
const MONOMIALS: [[u8; 3]; 20] = [
    [3, 0, 0],
    [2, 1, 0],
    [2, 0, 1],
    [1, 2, 0],
    [1, 1, 1],
    [1, 0, 2],
    [0, 3, 0],
    [0, 2, 1],
    [0, 1, 2],
    [0, 0, 3],
    [2, 0, 0],
    [1, 1, 0],
    [1, 0, 1],
    [0, 2, 0],
    [0, 1, 1],
    [0, 0, 2],
    [1, 0, 0],
    [0, 1, 0],
    [0, 0, 1],
    [0, 0, 0],
];

/// Index in [`MONOMIALS`] of the monomial with exponents `e` (a compile-time error if absent:
/// only evaluated in constants).
const fn monomial_index(e: [u8; 3]) -> usize {
    let mut i = 0;
    while i < MONOMIALS.len() {
        let m = MONOMIALS[i];
        if m[0] == e[0] && m[1] == e[1] && m[2] == e[2] {
            return i;
        }
        i += 1;
    }
    panic!("monomial of degree > 3")
}

/// TIMES[m][k]: the index of monomial 10 + m (degree ≤ 2) times x, y, z or 1 (k = 0..4).
const TIMES: [[usize; 4]; 10] = {
    let mut table = [[0; 4]; 10];
    let mut m = 0;
    while m < 10 {
        let e = MONOMIALS[10 + m];
        table[m] = [
            monomial_index([e[0] + 1, e[1], e[2]]),
            monomial_index([e[0], e[1] + 1, e[2]]),
            monomial_index([e[0], e[1], e[2] + 1]),
            monomial_index(e),
        ];
        m += 1;
    }
    table
};

/// p · l for p of degree ≤ 2 and l = l₀x + l₁y + l₂z + l₃.
fn times_linear(p: &Poly, l: &[f64; 4]) -> Poly {
    let mut out = [0.0; 20];
    for m in 0..10 {
        let c = p[10 + m];
        for k in 0..4 {
            out[TIMES[m][k]] += c * l[k];
        }
    }
    out
}

fn add(a: &Poly, b: &Poly) -> Poly {
    std::array::from_fn(|i| a[i] + b[i])
}

fn sub(a: &Poly, b: &Poly) -> Poly {
    std::array::from_fn(|i| a[i] - b[i])
}

/// The essential matrices (up to ten, unit scale not enforced) with x_bᵢᵀ E x_aᵢ = 0 for five
/// correspondences in normalized coordinates; empty for a degenerate sample. See the module
/// doc for the method.
fn five_point(xa: &[Vector3<f64>; 5], xb: &[Vector3<f64>; 5]) -> Vec<Matrix3<f64>> {
    let mut system = SMatrix::<f64, 9, 9>::zeros();
    for i in 0..5 {
        system.set_row(i, &epipolar_row(&xa[i], &xb[i]).transpose());
    }
    if !system.iter().all(|v| v.is_finite()) {
        return Vec::new();
    }
    let Some(svd) = SVD::try_new(system, false, true, f64::EPSILON, MAX_DECOMPOSITION_ITERATIONS) else {
        return Vec::new();
    };
    let Some(v_t) = svd.v_t else { return Vec::new() };
    let rank_five = svd.singular_values[4] > RANK_TOLERANCE * svd.singular_values[0];
    if !rank_five {
        return Vec::new();
    }
    // the null space: E = xX + yY + zZ + W with X, Y, Z, W rows 5..9 of Vᵀ
    let basis: [Matrix3<f64>; 4] = std::array::from_fn(|k| {
        let r = v_t.row(5 + k);
        Matrix3::new(r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7], r[8])
    });
    let lin: [[[f64; 4]; 3]; 3] =
        std::array::from_fn(|i| std::array::from_fn(|j| std::array::from_fn(|k| basis[k][(i, j)])));
    let poly = |l: &[f64; 4]| -> Poly {
        let mut p = [0.0; 20];
        p[16..20].copy_from_slice(l);
        p
    };
    // EEᵀ (degree 2), its trace, and the constraints (degree 3)
    let eet: [[Poly; 3]; 3] = std::array::from_fn(|i| {
        std::array::from_fn(|j| {
            (0..3).fold([0.0; 20], |acc, k| add(&acc, &times_linear(&poly(&lin[i][k]), &lin[j][k])))
        })
    });
    let trace = add(&add(&eet[0][0], &eet[1][1]), &eet[2][2]);
    let mut constraints = SMatrix::<f64, 10, 20>::zeros();
    for i in 0..3 {
        for j in 0..3 {
            let eete = (0..3).fold([0.0; 20], |acc, k| add(&acc, &times_linear(&eet[i][k], &lin[k][j])));
            let c = sub(&add(&eete, &eete), &times_linear(&trace, &lin[i][j]));
            constraints.set_row(1 + 3 * i + j, &SMatrix::<f64, 1, 20>::from_row_slice(&c));
        }
    }
    let minor = |r: usize, s: usize, c: usize, d: usize| {
        sub(&times_linear(&poly(&lin[r][c]), &lin[s][d]), &times_linear(&poly(&lin[r][d]), &lin[s][c]))
    };
    let det = add(
        &sub(&times_linear(&minor(1, 2, 1, 2), &lin[0][0]), &times_linear(&minor(1, 2, 0, 2), &lin[0][1])),
        &times_linear(&minor(1, 2, 0, 1), &lin[0][2]),
    );
    constraints.set_row(0, &SMatrix::<f64, 1, 20>::from_row_slice(&det));
    if !constraints.iter().all(|v| v.is_finite()) {
        return Vec::new();
    }
    // Gauss–Jordan: cubic monomial i = −B[i] · (the basis monomials)
    let leading: SMatrix<f64, 10, 10> = constraints.fixed_view::<10, 10>(0, 0).into_owned();
    let rest: SMatrix<f64, 10, 10> = constraints.fixed_view::<10, 10>(0, 10).into_owned();
    let Some(b) = leading.lu().solve(&rest) else { return Vec::new() };
    if !b.iter().all(|v| v.is_finite()) {
        return Vec::new();
    }
    // multiplication by x on the basis [x², xy, xz, y², yz, z², x, y, z, 1]:
    // x·x², …, x·xz² are the cubics 0..6; x·x = x², x·y = xy, x·z = xz, x·1 = x
    let mut action = SMatrix::<f64, 10, 10>::zeros();
    for r in 0..6 {
        action.set_row(r, &(-b.row(r)));
    }
    for (r, c) in [(6, 0), (7, 1), (8, 2), (9, 6)] {
        action[(r, c)] = 1.0;
    }
    let Some(schur) = Schur::try_new(action, f64::EPSILON, MAX_DECOMPOSITION_ITERATIONS) else {
        return Vec::new();
    };
    let mut solutions = Vec::new();
    for lambda in schur.complex_eigenvalues().iter() {
        let real = lambda.im.abs() <= REAL_EIGENVALUE_TOLERANCE * (1.0 + lambda.re.abs());
        if !real {
            continue;
        }
        let Some((x, y, z)) = action_solution(&action, lambda.re) else { continue };
        let e = basis[0] * x + basis[1] * y + basis[2] * z + basis[3];
        if e.iter().all(|v| v.is_finite()) {
            solutions.push(e);
        }
    }
    solutions
}

/// The solution (x, y, z) of eigenvalue x = `lambda` of the action matrix A: its eigenvector
/// is the basis at the solution, v = [x², xy, xz, y², yz, z², x, y, z, 1]. Rows 6–9 of
/// (A − xI)v = 0 only restate v₀ = x², v₁ = xy, v₂ = xz, v₆ = x; substituted into rows 0–5
/// they leave six linear equations in u = (y², yz, z², y, z), solved by least squares (QR).
/// None for a singular system (a repeated eigenvalue).
fn action_solution(action: &SMatrix<f64, 10, 10>, lambda: f64) -> Option<(f64, f64, f64)> {
    let (l, l2) = (lambda, lambda * lambda);
    let kronecker = |a: usize, b: usize| if a == b { 1.0 } else { 0.0 };
    let mut m = SMatrix::<f64, 6, 5>::zeros();
    let mut rhs = SVector::<f64, 6>::zeros();
    for r in 0..6 {
        let a = |c: usize| action[(r, c)];
        m[(r, 0)] = a(3) - l * kronecker(r, 3);
        m[(r, 1)] = a(4) - l * kronecker(r, 4);
        m[(r, 2)] = a(5) - l * kronecker(r, 5);
        m[(r, 3)] = l * a(1) + a(7) - l2 * kronecker(r, 1);
        m[(r, 4)] = l * a(2) + a(8) - l2 * kronecker(r, 2);
        rhs[r] = -(l2 * a(0) + l * a(6) + a(9) - l2 * l * kronecker(r, 0));
    }
    if !(m.iter().chain(rhs.iter()).all(|v| v.is_finite())) {
        return None;
    }
    let qr = m.qr();
    let u = qr.r().solve_upper_triangular(&(qr.q().transpose() * rhs))?;
    u.iter().all(|v| v.is_finite()).then_some((lambda, u[3], u[4]))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lie::rotation_angle;
    use crate::testing::SplitMix64;

    const DEG: f64 = std::f64::consts::PI / 180.0;

    fn camera() -> Camera {
        Camera::new(525.0, 525.0, 320.0, 240.0).expect("valid")
    }

    /// A synthetic two-view scene: the true relative pose, keypoints (b's in another order
    /// with unmatched extras), the matches and which of them are true.
    struct Scene {
        b_from_a: SE3,
        keypoints_a: Vec<Vector2<f64>>,
        keypoints_b: Vec<Vector2<f64>>,
        matches: Vec<Match>,
        truth: Vec<bool>,
    }

    fn in_image(u: &Vector2<f64>) -> bool {
        (0.0..640.0).contains(&u.x) && (0.0..480.0).contains(&u.y)
    }

    /// `n` matches, a fraction `outliers` of them wrong, for b_from_a with rotation angle
    /// `angle` (random axis) and baseline `baseline` (random direction); true points at
    /// 2–6 m in front of a and seen by b, 0.5 px noise. Outliers pair a real keypoint of a
    /// with a random pixel of b at least 10 px (5 × the default threshold) from its true
    /// epipolar line, so that "outlier" means inconsistent with the true geometry.
    fn scene(rng: &mut SplitMix64, n: usize, outliers: f64, angle: f64, baseline: f64) -> Scene {
        let cam = camera();
        let rotation = SO3::exp(&rng.rotation_vector(angle));
        let t = rng.unit_vector() * baseline;
        let b_from_a = SE3::new(rotation, t);
        let f = crate::matching::fundamental_matrix(&cam, &b_from_a, &SE3::identity());
        let n_out = (n as f64 * outliers).round() as usize;
        let mut pairs = Vec::new();
        while pairs.len() < n - n_out {
            let ua = Vector2::new(rng.uniform_in(0.0, 640.0), rng.uniform_in(0.0, 480.0));
            let pa = cam.unproject(&ua) * rng.uniform_in(2.0, 6.0);
            let pb = b_from_a * pa;
            if pb.z < 0.5 {
                continue;
            }
            let ub = cam.project_cam(&pb);
            if !in_image(&ub) {
                continue;
            }
            let noise = |rng: &mut SplitMix64| Vector2::new(rng.normal(), rng.normal()) * 0.5;
            pairs.push((ua + noise(rng), ub + noise(rng), true));
        }
        while pairs.len() < n {
            let ua = Vector2::new(rng.uniform_in(0.0, 640.0), rng.uniform_in(0.0, 480.0));
            let ub = Vector2::new(rng.uniform_in(0.0, 640.0), rng.uniform_in(0.0, 480.0));
            if sampson_distance(&f, &ua, &ub) >= 10.0 {
                pairs.push((ua, ub, false));
            }
        }
        // shuffle (Fisher–Yates), b's keypoints reversed behind three unmatched ones
        for i in (1..pairs.len()).rev() {
            let j = (rng.next_u64() % (i as u64 + 1)) as usize;
            pairs.swap(i, j);
        }
        let keypoints_a: Vec<_> = pairs.iter().map(|p| p.0).collect();
        let mut keypoints_b = vec![Vector2::new(1.0, 2.0); 3];
        keypoints_b.extend(pairs.iter().rev().map(|p| p.1));
        let matches = (0..n).map(|i| Match { a: i, b: 3 + n - 1 - i, distance: 0.0 }).collect();
        Scene { b_from_a, keypoints_a, keypoints_b, matches, truth: pairs.iter().map(|p| p.2).collect() }
    }

    fn verify(s: &Scene, options: &TwoViewOptions) -> TwoView {
        verify_two_view(&camera(), &s.keypoints_a, &s.keypoints_b, &s.matches, options).expect("valid input")
    }

    /// (precision, recall) of the mask against the truth.
    fn precision_recall(mask: &[bool], truth: &[bool]) -> (f64, f64) {
        let tp = mask.iter().zip(truth).filter(|(m, t)| **m && **t).count() as f64;
        let reported = mask.iter().filter(|m| **m).count() as f64;
        let true_count = truth.iter().filter(|t| **t).count() as f64;
        (tp / reported.max(1.0), tp / true_count.max(1.0))
    }

    /// (rotation error, translation direction error), degrees.
    fn pose_errors(estimate: &SE3, truth: &SE3) -> (f64, f64) {
        let r = estimate.rotation.matrix().transpose() * truth.rotation.matrix();
        let cos = estimate.translation.dot(&truth.translation.normalize()).clamp(-1.0, 1.0);
        (rotation_angle(&r) / DEG, cos.acos() / DEG)
    }

    #[test]
    fn monomial_tables() {
        for (m, row) in TIMES.iter().enumerate() {
            let e = MONOMIALS[10 + m];
            for (k, &i) in row.iter().enumerate() {
                let mut want = e;
                if k < 3 {
                    want[k] += 1;
                }
                assert_eq!(MONOMIALS[i], want);
            }
        }
        // (x + 2y − z + 3)(x − y + 1)(x/2 + 2z − 1) through the tables, evaluated at a point
        let eval = |p: &Poly, v: [f64; 3]| -> f64 {
            MONOMIALS.iter().zip(p).map(|(e, c)| c * (0..3).map(|k| v[k].powi(e[k] as i32)).product::<f64>()).sum()
        };
        let mut a = [0.0; 20];
        a[16..20].copy_from_slice(&[1.0, 2.0, -1.0, 3.0]);
        let ab = times_linear(&a, &[1.0, -1.0, 0.0, 1.0]);
        let abc = times_linear(&ab, &[0.5, 0.0, 2.0, -1.0]);
        let v = [0.3, -1.7, 2.2];
        let want = (v[0] + 2.0 * v[1] - v[2] + 3.0) * (v[0] - v[1] + 1.0) * (0.5 * v[0] + 2.0 * v[2] - 1.0);
        assert!((eval(&abc, v) - want).abs() < 1e-12);
    }

    /// Exact correspondences: one of the solutions is the true E (up to scale and sign), and
    /// every solution satisfies the five epipolar constraints and the essential constraints.
    #[test]
    fn five_point_recovers_the_true_essential_matrix() {
        let mut rng = SplitMix64::new(1);
        for trial in 0..200 {
            let angle = rng.uniform_in(0.0, 0.6);
            let r = SO3::exp(&rng.rotation_vector(angle));
            let t = rng.unit_vector();
            let truth = so3::hat(&t) * r.matrix();
            let truth = truth / truth.norm();
            let mut xa = [Vector3::zeros(); 5];
            let mut xb = [Vector3::zeros(); 5];
            for i in 0..5 {
                let pa = Vector3::new(rng.uniform_in(-1.0, 1.0), rng.uniform_in(-1.0, 1.0), rng.uniform_in(2.0, 6.0));
                let pb = r * pa + t;
                xa[i] = pa / pa.z;
                xb[i] = pb / pb.z;
            }
            let solutions = five_point(&xa, &xb);
            assert!(!solutions.is_empty() && solutions.len() <= 10, "trial {trial}: {}", solutions.len());
            let mut best = f64::INFINITY;
            for e in &solutions {
                let e = e / e.norm();
                for i in 0..5 {
                    assert!((xb[i].transpose() * e * xa[i])[0].abs() < 1e-9, "trial {trial}");
                }
                assert!(e.determinant().abs() < 1e-9, "trial {trial}");
                let eet = e * e.transpose();
                assert!((2.0 * eet * e - eet.trace() * e).norm() < 1e-8, "trial {trial}");
                best = best.min((e - truth).norm().min((e + truth).norm()));
            }
            assert!(best < 1e-8, "trial {trial}: {best}");
        }
    }

    #[test]
    fn decomposition_picks_the_true_pose() {
        let mut rng = SplitMix64::new(2);
        for _ in 0..50 {
            let angle = rng.uniform_in(0.0, 30.0 * DEG);
            let s = scene(&mut rng, 60, 0.0, angle, 1.0);
            let truth = &s.b_from_a;
            let e = so3::hat(&truth.translation) * truth.rotation.matrix();
            let problem = Problem::new(&camera(), &s.keypoints_a, &s.keypoints_b, &s.matches, 2.0);
            let pose = problem.decompose(&e).expect("a pose");
            assert!((pose.rotation.matrix() - truth.rotation.matrix()).norm() < 1e-9);
            assert!((pose.translation - truth.translation).norm() < 1e-9);
        }
    }

    /// What one verification of a synthetic scene got right.
    struct Outcome {
        verified: bool,
        precision: f64,
        recall: f64,
        /// Degrees.
        rotation_error: f64,
        /// Degrees.
        translation_error: f64,
        /// The returned pose's MSAC score is at most the true pose's: the estimator found a
        /// solution the data supports at least as well as the truth.
        as_good_as_truth: bool,
    }

    impl Outcome {
        /// The acceptance criteria of the brief.
        fn meets_all(&self) -> bool {
            self.verified
                && self.precision >= 0.98
                && self.recall >= 0.95
                && self.rotation_error <= 0.5
                && self.translation_error <= 2.0
        }
    }

    /// `count` scenes of `n` matches: outlier fraction uniform in [0.3, 0.6], rotation angle
    /// in [0°, 30°], baseline in `baselines` (m); the first two at the corners (60 %
    /// outliers, 30°, the shortest and the longest baseline).
    fn outcomes(seed: u64, count: usize, n: usize, baselines: (f64, f64)) -> Vec<Outcome> {
        let mut rng = SplitMix64::new(seed);
        (0..count)
            .map(|i| {
                let (outliers, angle, baseline) = match i {
                    0 => (0.6, 30.0, baselines.0),
                    1 => (0.6, 30.0, baselines.1),
                    _ => {
                        (rng.uniform_in(0.3, 0.6), rng.uniform_in(0.0, 30.0), rng.uniform_in(baselines.0, baselines.1))
                    }
                };
                let s = scene(&mut rng, n, outliers, angle * DEG, baseline);
                let v = verify(&s, &TwoViewOptions { seed: i as u64, ..TwoViewOptions::default() });
                assert!((v.b_from_a.translation.norm() - 1.0).abs() < 1e-12);
                let (precision, recall) = precision_recall(&v.inlier_mask, &s.truth);
                let (rotation_error, translation_error) = pose_errors(&v.b_from_a, &s.b_from_a);
                let problem = Problem::new(&camera(), &s.keypoints_a, &s.keypoints_b, &s.matches, 2.0);
                let truth = so3::hat(&s.b_from_a.translation.normalize()) * s.b_from_a.rotation.matrix();
                let score = |e: &Matrix3<f64>| problem.msac(e, f64::INFINITY).map_or(f64::INFINITY, |m| m.0);
                Outcome {
                    verified: v.verified,
                    precision,
                    recall,
                    rotation_error,
                    translation_error,
                    as_good_as_truth: score(&v.essential) <= score(&truth),
                }
            })
            .collect()
    }

    /// (how many of `outcomes` satisfy `f`, the largest / smallest value of `g`).
    fn count(outcomes: &[Outcome], f: impl Fn(&Outcome) -> bool) -> usize {
        outcomes.iter().filter(|o| f(o)).count()
    }

    fn largest(outcomes: &[Outcome], g: impl Fn(&Outcome) -> f64) -> f64 {
        outcomes.iter().map(g).fold(f64::NEG_INFINITY, f64::max)
    }

    fn smallest(outcomes: &[Outcome], g: impl Fn(&Outcome) -> f64) -> f64 {
        outcomes.iter().map(g).fold(f64::INFINITY, f64::min)
    }

    /// The acceptance suite (rotations up to 30°, 30–60 % outliers, 0.5 px noise) where the
    /// data determines the pose: baselines 0.2–0.5 m. The brief's criteria (precision ≥ 0.98,
    /// recall ≥ 0.95, R within 0.5°, t within 2°) hold in 95 % of the scenes; in the others a
    /// few outliers lie within 2 px of a slightly different geometry that scores better than
    /// the truth (MSAC prefers it), and every scene still meets looser bounds.
    #[test]
    fn recovers_inliers_and_pose_of_synthetic_scenes() {
        let outcomes = outcomes(3, 40, 400, (0.2, 0.5));
        let summary = format!(
            "all criteria {}/40, min precision {:.3}, min recall {:.3}, max R {:.3}°, max t {:.3}°",
            count(&outcomes, Outcome::meets_all),
            smallest(&outcomes, |o| o.precision),
            smallest(&outcomes, |o| o.recall),
            largest(&outcomes, |o| o.rotation_error),
            largest(&outcomes, |o| o.translation_error),
        );
        eprintln!("{summary}");
        assert!(count(&outcomes, Outcome::meets_all) >= 38, "{summary}");
        assert!(
            outcomes.iter().all(|o| o.verified
                && o.precision >= 0.95
                && o.recall >= 0.95
                && o.rotation_error <= 0.5
                && o.translation_error <= 6.0),
            "{summary}"
        );
    }

    /// Baselines 0.05–0.2 m: the parallax (5–50 px) is comparable to the flow of a
    /// degree of rotation, and with 0.5 px noise the translation direction is not determined
    /// to 2° (its Cramér–Rao bound alone is 2–5° at 0.05 m with 120–200 inliers). The inliers and
    /// the rotation are still found, and the returned pose mostly scores at least as well as
    /// the truth: its remaining error is the data's, not the search's.
    #[test]
    fn short_baselines_find_the_inliers_and_the_rotation() {
        let outcomes = outcomes(4, 40, 400, (0.05, 0.2));
        let mut t: Vec<f64> = outcomes.iter().map(|o| o.translation_error).collect();
        t.sort_by(f64::total_cmp);
        let summary = format!(
            "all criteria {}/40, R ≤ 0.5° {}/40, precision ≥ 0.98 {}/40, as good as the truth {}/40, \
             min precision {:.3}, min recall {:.3}, max R {:.3}°, t median {:.2}° max {:.2}°",
            count(&outcomes, Outcome::meets_all),
            count(&outcomes, |o| o.rotation_error <= 0.5),
            count(&outcomes, |o| o.precision >= 0.98),
            count(&outcomes, |o| o.as_good_as_truth),
            smallest(&outcomes, |o| o.precision),
            smallest(&outcomes, |o| o.recall),
            largest(&outcomes, |o| o.rotation_error),
            t[20],
            t[39],
        );
        eprintln!("{summary}");
        assert!(outcomes.iter().all(|o| o.verified && o.recall >= 0.95 && o.precision >= 0.9), "{summary}");
        assert!(count(&outcomes, |o| o.rotation_error <= 0.5) >= 36, "{summary}");
        assert!(count(&outcomes, |o| o.as_good_as_truth) >= 32, "{summary}");
        assert!(t[20] <= 5.0, "{summary}");
    }

    /// The mask is exactly the threshold rule on the returned E, and E = t^R of the pose.
    #[test]
    #[allow(clippy::float_cmp)] // E is t^R of the returned pose, bit for bit
    fn mask_is_the_threshold_rule_of_the_returned_matrix() {
        let mut rng = SplitMix64::new(4);
        for trial in 0..20 {
            let s = scene(&mut rng, 40, 0.3, 10.0 * DEG, 0.2);
            let options = TwoViewOptions { max_px: 1.0 + trial as f64 * 0.1, ..TwoViewOptions::default() };
            let v = verify(&s, &options);
            let f = crate::matching::fundamental_matrix(&camera(), &v.b_from_a, &SE3::identity());
            let own = camera();
            let k_inv =
                Matrix3::new(1.0 / own.fx, 0.0, -own.cx / own.fx, 0.0, 1.0 / own.fy, -own.cy / own.fy, 0.0, 0.0, 1.0);
            let f_returned = k_inv.transpose() * v.essential * k_inv;
            for (i, m) in s.matches.iter().enumerate() {
                let (ua, ub) = (&s.keypoints_a[m.a], &s.keypoints_b[m.b]);
                assert_eq!(v.inlier_mask[i], sampson_distance(&f_returned, ua, ub) <= options.max_px, "trial {trial}");
                // the pose's own fundamental matrix agrees away from the threshold
                let d = sampson_distance(&f, ua, ub);
                if (d - options.max_px).abs() > 1e-6 {
                    assert_eq!(v.inlier_mask[i], d <= options.max_px, "trial {trial}");
                }
            }
            assert_eq!(v.inliers, v.inlier_mask.iter().filter(|k| **k).count());
            assert_eq!(v.verified, v.inliers >= options.min_inliers);
            let t_hat_r = so3::hat(&v.b_from_a.translation) * v.b_from_a.rotation.matrix();
            assert_eq!(t_hat_r, v.essential);
        }
    }

    #[test]
    fn deterministic_bit_for_bit() {
        let mut rng = SplitMix64::new(5);
        let s = scene(&mut rng, 200, 0.5, 20.0 * DEG, 0.1);
        let options = TwoViewOptions { seed: 17, ..TwoViewOptions::default() };
        let (v1, v2) = (verify(&s, &options), verify(&s, &options));
        assert_eq!(v1.inlier_mask, v2.inlier_mask);
        assert_eq!(v1.iterations, v2.iterations);
        let bits = |v: &TwoView| -> Vec<u64> {
            v.essential.iter().chain(v.b_from_a.matrix().iter()).map(|x| x.to_bits()).collect()
        };
        assert_eq!(bits(&v1), bits(&v2));
    }

    /// A pure rotation and a tiny baseline give an answer (the rotation is still right), and
    /// degenerate or tiny inputs an unverified one; nothing panics.
    #[test]
    fn degenerate_geometry_does_not_panic() {
        let mut rng = SplitMix64::new(6);
        for baseline in [0.0, 1e-6, 1e-3] {
            let s = scene(&mut rng, 200, 0.4, 15.0 * DEG, baseline);
            let v = verify(&s, &TwoViewOptions::default());
            assert_eq!(v.inlier_mask.len(), 200);
            let (r_err, _) = pose_errors(&v.b_from_a, &s.b_from_a);
            assert!(r_err < 1.0, "baseline {baseline}: R off by {r_err}°");
            let (_, recall) = precision_recall(&v.inlier_mask, &s.truth);
            assert!(recall > 0.9, "baseline {baseline}: recall {recall}");
        }
        let cam = camera();
        let options = TwoViewOptions::default();
        let matches: Vec<Match> = (0..30).map(|i| Match { a: i, b: i, distance: 0.0 }).collect();
        // every keypoint the same; all on a line; the same point everywhere in b
        let same = vec![Vector2::new(100.0, 100.0); 30];
        let line: Vec<_> = (0..30).map(|i| Vector2::new(10.0 * i as f64, 5.0 * i as f64)).collect();
        let huge: Vec<_> = (0..30).map(|i| Vector2::new(1e300 * (i as f64 - 15.0), -1e300)).collect();
        for (ka, kb) in [(&same, &same), (&line, &line), (&line, &same), (&huge, &line), (&huge, &huge)] {
            let v = verify_two_view(&cam, ka, kb, &matches, &options).expect("finite input");
            assert_eq!(v.inlier_mask.len(), 30);
            assert_eq!(v.inliers, v.inlier_mask.iter().filter(|k| **k).count());
        }
        // fewer than eight matches: unverified, no error
        let v = verify_two_view(&cam, &line, &line, &matches[..7], &options).expect("valid");
        assert!(!v.verified && v.inlier_mask == vec![false; 7] && v.iterations == 0);
        let v = verify_two_view(&cam, &line, &line, &[], &options).expect("valid");
        assert!(!v.verified && v.inlier_mask.is_empty());
    }

    #[test]
    fn bad_input_is_refused_by_name() {
        fn name_of<T>(r: Result<T>) -> String {
            match r {
                Err(GeolocError::InvalidInput { name, .. } | GeolocError::NonFinite { name, .. }) => name,
                Err(other) => panic!("expected a named error, got {other:?}"),
                Ok(_) => panic!("expected a named error, got Ok"),
            }
        }
        let cam = camera();
        let k = vec![Vector2::new(1.0, 2.0); 10];
        let matches: Vec<Match> = (0..10).map(|i| Match { a: i, b: i, distance: 0.0 }).collect();
        let d = TwoViewOptions::default();
        let run = |o: TwoViewOptions| verify_two_view(&cam, &k, &k, &matches, &o);
        assert!(run(d).is_ok());
        for (options, name) in [
            (TwoViewOptions { max_px: 0.0, ..d }, "max_px"),
            (TwoViewOptions { max_px: -1.0, ..d }, "max_px"),
            (TwoViewOptions { max_px: f64::NAN, ..d }, "max_px"),
            (TwoViewOptions { max_px: f64::INFINITY, ..d }, "max_px"),
            (TwoViewOptions { iterations: 0, ..d }, "iterations"),
            (TwoViewOptions { iterations: MAX_ITERATIONS + 1, ..d }, "iterations"),
            (TwoViewOptions { min_inliers: 7, ..d }, "min_inliers"),
        ] {
            assert_eq!(name_of(options.check()), name);
            assert_eq!(name_of(run(options)), name);
        }
        let past_a = [Match { a: 10, b: 0, distance: 0.0 }];
        let past_b = [Match { a: 0, b: 10, distance: 0.0 }];
        assert_eq!(name_of(verify_two_view(&cam, &k, &k, &past_a, &d)), "matches");
        assert_eq!(name_of(verify_two_view(&cam, &k, &k, &past_b, &d)), "matches");
        let mut nan = k.clone();
        nan[4].y = f64::NAN;
        assert_eq!(name_of(verify_two_view(&cam, &nan, &k, &matches, &d)), "keypoints_a");
        assert_eq!(name_of(verify_two_view(&cam, &k, &nan, &matches, &d)), "keypoints_b");
        let bad_cam = Camera { fx: 0.0, ..cam };
        assert_eq!(name_of(verify_two_view(&bad_cam, &k, &k, &matches, &d)), "fx");
    }

    #[test]
    fn adaptive_sample_count() {
        assert_eq!(required_iterations(1.0, 500), 1);
        assert_eq!(required_iterations(0.0, 500), 500);
        assert_eq!(required_iterations(f64::NAN, 500), 500);
        // w = 0.5: ln(0.001)/ln(1 − 1/32) = 217.6
        assert_eq!(required_iterations(0.5, 500), 218);
        assert_eq!(required_iterations(0.4, 500), 500);
    }

    /// The statistics behind the thresholds of the two tests above, 200 scenes per range:
    /// `cargo test --release -p geoloc-core --lib essential::tests::statistics -- --ignored --nocapture`.
    #[test]
    #[ignore = "statistics, not a check"]
    fn statistics() {
        for (i, baselines) in [(0.05, 0.1), (0.1, 0.2), (0.2, 0.5)].into_iter().enumerate() {
            let outcomes = outcomes(100 + i as u64, 200, 400, baselines);
            let mut t: Vec<f64> = outcomes.iter().map(|o| o.translation_error).collect();
            t.sort_by(f64::total_cmp);
            eprintln!(
                "baselines {baselines:?} m: all {}, precision ≥ 0.98 {}, recall ≥ 0.95 {}, R ≤ 0.5° {}, t ≤ 2° {}, \
                 as good as the truth {} of 200; min precision {:.3}, min recall {:.3}, max R {:.2}°, \
                 t median {:.2}° p90 {:.2}° max {:.2}°",
                count(&outcomes, Outcome::meets_all),
                count(&outcomes, |o| o.precision >= 0.98),
                count(&outcomes, |o| o.recall >= 0.95),
                count(&outcomes, |o| o.rotation_error <= 0.5),
                count(&outcomes, |o| o.translation_error <= 2.0),
                count(&outcomes, |o| o.as_good_as_truth),
                smallest(&outcomes, |o| o.precision),
                smallest(&outcomes, |o| o.recall),
                largest(&outcomes, |o| o.rotation_error),
                t[100],
                t[180],
                t[199],
            );
        }
    }

    /// Rough time per call for 500 matches with 50 % outliers:
    /// `cargo test --release -p geoloc-core --lib essential::tests::timing -- --ignored --nocapture`.
    #[test]
    #[ignore = "timing, not a check"]
    fn timing() {
        let mut rng = SplitMix64::new(7);
        let scenes: Vec<Scene> = (0..20).map(|_| scene(&mut rng, 500, 0.5, 15.0 * DEG, 0.2)).collect();
        let options = TwoViewOptions::default();
        // the median of five rounds of each measurement (the machine may be shared)
        let median =
            |mut v: Vec<f64>| crate::stats::median(&mut v, crate::stats::EvenMedian::Upper).expect("five rounds");
        let mut samples = 0;
        let per_call = median(
            (0..5)
                .map(|_| {
                    let start = std::time::Instant::now();
                    samples = scenes.iter().map(|s| verify(s, &options).iterations).sum::<usize>();
                    start.elapsed().as_secs_f64() / scenes.len() as f64
                })
                .collect(),
        );
        let mut solutions = 0;
        let per_solve = median(
            (0..5)
                .map(|_| {
                    let start = std::time::Instant::now();
                    solutions = 0;
                    for s in &scenes {
                        for k in 0..50 {
                            let idx: [usize; 5] = std::array::from_fn(|j| (k * 5 + j) % 500);
                            let xa = idx.map(|i| camera().unproject(&s.keypoints_a[s.matches[i].a]));
                            let xb = idx.map(|i| camera().unproject(&s.keypoints_b[s.matches[i].b]));
                            solutions += five_point(&xa, &xb).len();
                        }
                    }
                    start.elapsed().as_secs_f64() / (scenes.len() * 50) as f64
                })
                .collect(),
        );
        eprintln!(
            "500 matches, 50 % outliers: {:.2} ms per call, {:.1} samples per call; five-point solver {:.1} µs, \
             {:.2} solutions",
            per_call * 1e3,
            samples as f64 / scenes.len() as f64,
            per_solve * 1e6,
            solutions as f64 / (scenes.len() * 50) as f64
        );
    }
}
