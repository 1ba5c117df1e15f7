//! Self-calibration of the camera from keyframes of known pose ("refining the focal
//! length and principal point at map-build time from the known poses").
//!
//! The keypoints the core receives are undistorted pixels under the *nominal* intrinsics K
//! (whatever distortion the caller knew of is already removed). The real camera may differ —
//! 7-Scenes publishes no colour intrinsics and fx = fy = 525 is folklore; a residual lens
//! distortion remains. With the keyframe poses known, every track of the map observes one
//! world point from many poses, which constrains the camera. Over θ = (f_x′, f_y′, c_x′, c_y′,
//! k1, k2, p1, p2) and the track points X_p, with the poses T_k fixed (they carry the world
//! frame and the scale),
//!
//!   min Σ_o ρ(‖π_θ(T_k(o), X_p(o)) − u_o‖),   π_θ(T, X) = K′ d(x),  x = (p_x, p_y)/p_z,  p = T⁻¹X
//!
//! with ρ Huber of width `huber_px` on the pixel residual and d the radial–tangential
//! distortion ([`Distortion`]), by Levenberg–Marquardt with the points eliminated (Schur
//! complement, as in bundle adjustment; the points' 3×3 blocks damped too). [`IntrinsicsModel`]
//! says which of θ are free; the others keep their start (K′ = K, no distortion).
//!
//! The result is a **correction of the caller's pixels**: a keypoint u becomes
//!
//!   u_c = K d⁻¹(K′⁻¹ u)
//!
//! — the pixel a pinhole camera with the nominal K would have recorded — so triangulation,
//! PnP, the map file and the robot binary keep the nominal pinhole camera. Pixel noise is
//! carried over unscaled (|K K′⁻¹| differs from 1 by a few per cent).
//!
//! Every sum runs in observation order on one thread: the same input gives the same bits.

use nalgebra::{Matrix2, Matrix2x3, Matrix3, SMatrix, SVector, Vector2, Vector3};

use crate::camera::{Camera, Distortion};
use crate::error::{GeolocError, Result};
use crate::lie::SE3;
use crate::optim::{DampedStep, Evaluation, LeastSquares, Linearization, LmOptions, LmReport, solve};
use crate::stats::{EvenMedian, median};

/// Observed pixels at which [`SelfCalibration::correction_sigma_px`] is evaluated, at most.
const SIGMA_PROBES: usize = 512;

/// The camera parameters θ, in this order: f_x′, f_y′, c_x′, c_y′, k1, k2, p1, p2.
pub const PARAMETERS: usize = 8;
type Theta = SVector<f64, PARAMETERS>;
type ThetaMatrix = SMatrix<f64, PARAMETERS, PARAMETERS>;
type Jacobian2 = SMatrix<f64, 2, PARAMETERS>;

/// Which camera parameters the self-calibration estimates.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum IntrinsicsModel {
    /// f_x′, f_y′, c_x′, c_y′.
    Pinhole,
    /// ... and the radial k1, k2.
    Radial,
    /// ... and the tangential p1, p2 (the default).
    RadialTangential,
}

impl IntrinsicsModel {
    /// Every model, in declaration order.
    pub const ALL: [Self; 3] = [Self::Pinhole, Self::Radial, Self::RadialTangential];

    /// The name: `"pinhole"`, `"radial"` or `"radial-tangential"`.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Pinhole => "pinhole",
            Self::Radial => "radial",
            Self::RadialTangential => "radial-tangential",
        }
    }

    /// How many of θ are free.
    pub fn free_parameters(self) -> usize {
        match self {
            Self::Pinhole => 4,
            Self::Radial => 6,
            Self::RadialTangential => 8,
        }
    }
}

impl std::str::FromStr for IntrinsicsModel {
    type Err = GeolocError;

    fn from_str(s: &str) -> Result<Self> {
        Self::ALL.into_iter().find(|m| m.as_str() == s).ok_or_else(|| {
            GeolocError::invalid(
                "intrinsics_model",
                format!("expected \"pinhole\", \"radial\" or \"radial-tangential\", got {s:?}"),
            )
        })
    }
}

/// Options of [`self_calibrate`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SelfCalibrationOptions {
    /// The free parameters (default radial–tangential).
    pub model: IntrinsicsModel,
    /// Width of the Huber kernel on the pixel residual (px, default 2).
    pub huber_px: f64,
    /// Gaussian priors on θ around the nominal camera (no distortion), each a 1σ: focal
    /// lengths relative to the nominal ones (default 0.05), principal point (px, default
    /// 30), k1 and k2 (default 0.2), p1 and p2 (default 0.02). They keep what the tracks
    /// cannot tell (a short, straight recording) at the nominal values instead of letting
    /// it wander; against real tracks they weigh nothing.
    pub prior_focal_rel: f64,
    /// See `prior_focal_rel`.
    pub prior_principal_px: f64,
    /// See `prior_focal_rel`.
    pub prior_radial: f64,
    /// See `prior_focal_rel`.
    pub prior_tangential: f64,
    /// The correction is applied only when the tracks determine it: the RMS over the
    /// observed pixels of its 1σ (from the posterior covariance of θ) must stay below this
    /// (px, default 0.5).
    pub max_correction_sigma_px: f64,
    /// Fewest observations (default 200) ...
    pub min_observations: usize,
    /// ... of at least this many points (default 50).
    pub min_points: usize,
    /// LM settings (default: at most 100 iterations).
    pub lm: LmOptions,
}

impl Default for SelfCalibrationOptions {
    fn default() -> Self {
        Self {
            model: IntrinsicsModel::RadialTangential,
            huber_px: 2.0,
            prior_focal_rel: 0.05,
            prior_principal_px: 30.0,
            prior_radial: 0.2,
            prior_tangential: 0.02,
            max_correction_sigma_px: 0.5,
            min_observations: 200,
            min_points: 50,
            lm: LmOptions { max_iterations: 100, ..LmOptions::default() },
        }
    }
}

impl SelfCalibrationOptions {
    /// The priors' 1σ per θ for a nominal camera.
    fn prior_sigmas(&self, nominal: &Camera) -> Theta {
        Theta::from_column_slice(&[
            self.prior_focal_rel * nominal.fx,
            self.prior_focal_rel * nominal.fy,
            self.prior_principal_px,
            self.prior_principal_px,
            self.prior_radial,
            self.prior_radial,
            self.prior_tangential,
            self.prior_tangential,
        ])
    }
}

/// One observation of a track: keyframe `keyframe` saw point `point` at `pixel` (the
/// caller's undistorted pixels under the nominal K).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrackObservation {
    /// Index into the poses.
    pub keyframe: usize,
    /// Index into the points.
    pub point: usize,
    /// The keypoint (px).
    pub pixel: Vector2<f64>,
}

/// The estimated camera K′, d as a correction of pixels recorded under the nominal K (see
/// the module doc).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct IntrinsicsCorrection {
    /// K′.
    pub camera: Camera,
    /// d.
    pub distortion: Distortion,
}

impl IntrinsicsCorrection {
    /// u_c = K d⁻¹(K′⁻¹ u); None where the distortion cannot be inverted.
    pub fn correct(&self, nominal: &Camera, u: &Vector2<f64>) -> Option<Vector2<f64>> {
        let k = &self.camera;
        let x_d = Vector2::new((u.x - k.cx) / k.fx, (u.y - k.cy) / k.fy);
        let x = self.distortion.undistort(&x_d)?;
        Some(Vector2::new(nominal.fx * x.x + nominal.cx, nominal.fy * x.y + nominal.cy))
    }

    /// [`Self::correct`] of every pixel.
    ///
    /// # Errors
    /// `InvalidInput` naming `name` and the first pixel the distortion cannot invert.
    pub fn correct_all(&self, nominal: &Camera, name: &str, pixels: &[Vector2<f64>]) -> Result<Vec<Vector2<f64>>> {
        pixels
            .iter()
            .enumerate()
            .map(|(i, u)| {
                self.correct(nominal, u).ok_or_else(|| {
                    GeolocError::invalid(
                        name,
                        format!("pixel {i} lies where the map's lens correction does not invert"),
                    )
                })
            })
            .collect()
    }
}

/// What [`self_calibrate`] found.
#[derive(Clone, Debug, PartialEq)]
pub struct SelfCalibration {
    /// The estimated camera, as a correction of the caller's pixels; None when the tracks
    /// could not give one (`reason` says why).
    pub correction: Option<IntrinsicsCorrection>,
    /// "ok", or why there is no correction.
    pub reason: String,
    /// RMS of the pixel residuals under the nominal camera (at the given points) ...
    pub rms_before_px: f64,
    /// ... and under the estimated one (at the re-estimated points; NaN without one).
    pub rms_after_px: f64,
    /// Median pixel residual before ...
    pub median_before_px: f64,
    /// ... and after.
    pub median_after_px: f64,
    /// Observations used.
    pub observations: usize,
    /// Points they observe.
    pub points: usize,
    /// The RMS over the observed pixels of the correction's 1σ (px; NaN when not computed):
    /// see [`SelfCalibrationOptions::max_correction_sigma_px`].
    pub correction_sigma_px: f64,
    /// The LM report (None when the solve did not run).
    pub report: Option<LmReport>,
}

/// Estimates the camera from tracks of keyframes with known poses (see the module doc).
/// `points` are the tracks' starting positions (e.g. triangulated under the nominal camera).
/// Too few observations (below `min_observations`, or fewer than `min_points` points
/// observed) or a solve that ends in no camera (f ≤ 0, non-finite) or in larger residuals
/// give no correction, with the reason — not an error.
///
/// # Errors
/// `InvalidInput` for observations that name a keyframe or point out of range, `NonFinite`
/// for non-finite pixels or points, bad options.
pub fn self_calibrate(
    nominal: &Camera,
    poses: &[SE3],
    points: &[Vector3<f64>],
    observations: &[TrackObservation],
    options: &SelfCalibrationOptions,
) -> Result<SelfCalibration> {
    check(poses, points, observations, options)?;
    let mut by_point: Vec<Vec<usize>> = vec![Vec::new(); points.len()];
    for (o, obs) in observations.iter().enumerate() {
        by_point[obs.point].push(o);
    }
    let observed = by_point.iter().filter(|o| !o.is_empty()).count();
    let prior_mean = theta_of(nominal, &Distortion::default());
    let problem = Problem {
        poses,
        observations,
        by_point,
        free: options.model.free_parameters(),
        huber: options.huber_px,
        prior_mean,
        prior_information: options.prior_sigmas(nominal).map(|s| 1.0 / (s * s)),
    };
    let start = State { theta: prior_mean, points: points.to_vec() };
    let mut before = problem.residual_norms(&start);
    let mut out = SelfCalibration {
        correction: None,
        reason: String::new(),
        rms_before_px: rms(&before),
        rms_after_px: f64::NAN,
        median_before_px: median(&mut before, EvenMedian::Upper).unwrap_or(f64::NAN),
        median_after_px: f64::NAN,
        observations: observations.len(),
        points: observed,
        correction_sigma_px: f64::NAN,
        report: None,
    };
    if observations.len() < options.min_observations || observed < options.min_points {
        out.reason = format!(
            "{} observations of {observed} points (needs {} of {})",
            observations.len(),
            options.min_observations,
            options.min_points
        );
        return Ok(out);
    }
    let (end, report, _) = solve(&problem, start, &options.lm);
    let mut after = problem.residual_norms(&end);
    out.report = Some(report);
    out.rms_after_px = rms(&after);
    out.median_after_px = median(&mut after, EvenMedian::Upper).unwrap_or(f64::NAN);
    let Some((camera, distortion)) = camera_of(&end.theta) else {
        out.reason = "the estimate is not a camera (f ≤ 0 or not finite)".into();
        return Ok(out);
    };
    let correction = IntrinsicsCorrection { camera, distortion };
    out.correction_sigma_px = problem.correction_sigma(nominal, &end).unwrap_or(f64::INFINITY);
    out.reason = if !report.converged() {
        format!("the solve did not converge ({:?})", report.termination)
    } else if !(out.rms_after_px.is_finite() && report.final_cost <= report.initial_cost) {
        "the estimate did not lower the residuals".into()
    } else if out.correction_sigma_px.is_nan() || out.correction_sigma_px > options.max_correction_sigma_px {
        format!(
            "the tracks do not determine the camera: the correction's 1σ is {:.2} px (limit {} px)",
            out.correction_sigma_px, options.max_correction_sigma_px
        )
    } else {
        out.correction = Some(correction);
        "ok".into()
    };
    Ok(out)
}

fn check(
    poses: &[SE3],
    points: &[Vector3<f64>],
    observations: &[TrackObservation],
    options: &SelfCalibrationOptions,
) -> Result<()> {
    let positive = [
        ("huber_px", options.huber_px),
        ("prior_focal_rel", options.prior_focal_rel),
        ("prior_principal_px", options.prior_principal_px),
        ("prior_radial", options.prior_radial),
        ("prior_tangential", options.prior_tangential),
        ("max_correction_sigma_px", options.max_correction_sigma_px),
    ];
    if let Some((name, v)) = positive.into_iter().find(|(_, v)| !(v.is_finite() && *v > 0.0)) {
        return Err(GeolocError::invalid(name, format!("must be finite and > 0, got {v}")));
    }
    if let Some(i) = points.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
        return Err(GeolocError::NonFinite { name: "points".into(), index: i });
    }
    for (o, obs) in observations.iter().enumerate() {
        if obs.keyframe >= poses.len() || obs.point >= points.len() {
            return Err(GeolocError::invalid(
                "observations",
                format!("observation {o} names keyframe {} / point {} out of range", obs.keyframe, obs.point),
            ));
        }
        if !(obs.pixel.x.is_finite() && obs.pixel.y.is_finite()) {
            return Err(GeolocError::NonFinite { name: "observations".into(), index: o });
        }
    }
    Ok(())
}

fn theta_of(camera: &Camera, d: &Distortion) -> Theta {
    Theta::from_column_slice(&[camera.fx, camera.fy, camera.cx, camera.cy, d.k1, d.k2, d.p1, d.p2])
}

/// The distortion part of θ (k3 is not estimated: 0).
fn distortion_of(theta: &Theta) -> Distortion {
    Distortion { k1: theta[4], k2: theta[5], p1: theta[6], p2: theta[7], k3: 0.0 }
}

fn camera_of(theta: &Theta) -> Option<(Camera, Distortion)> {
    let camera = Camera::new(theta[0], theta[1], theta[2], theta[3]).ok()?;
    let d = distortion_of(theta);
    d.to_opencv().iter().all(|c| c.is_finite()).then_some((camera, d))
}

fn rms(norms: &[f64]) -> f64 {
    (norms.iter().map(|e| e * e).sum::<f64>() / norms.len().max(1) as f64).sqrt()
}

/// The camera parameters and every track point.
#[derive(Clone, Debug)]
struct State {
    theta: Theta,
    points: Vec<Vector3<f64>>,
}

struct Problem<'a> {
    poses: &'a [SE3],
    observations: &'a [TrackObservation],
    /// The observations of each point.
    by_point: Vec<Vec<usize>>,
    /// θ₀..θ_free are estimated, the rest held.
    free: usize,
    huber: f64,
    /// The priors: N(prior_mean, diag(1/prior_information)).
    prior_mean: Theta,
    prior_information: Theta,
}

/// One observation projected at θ (see [`Problem::project`]).
struct Projected {
    p: Vector3<f64>,
    n: Vector2<f64>,
    x_d: Vector2<f64>,
    r: Vector2<f64>,
}

/// One observation linearized: residual r = π_θ − u, ∂r/∂θ, ∂r/∂X, and the IRLS weight.
struct Linearized {
    r: Vector2<f64>,
    j_theta: Jacobian2,
    j_point: Matrix2x3<f64>,
    weight: f64,
}

impl Problem<'_> {
    /// Observation `obs` at θ and `points`: p = T_k⁻¹X_p, x = (p_x, p_y)/p_z, x_d = d(x) and
    /// r = K′x_d − u; None when the point is not in front of the keyframe.
    fn project(&self, theta: &Theta, points: &[Vector3<f64>], obs: &TrackObservation) -> Option<Projected> {
        let pose = &self.poses[obs.keyframe];
        let p = pose.rotation.matrix().tr_mul(&(points[obs.point] - pose.translation));
        if p.z <= 0.0 {
            return None;
        }
        let n = Vector2::new(p.x / p.z, p.y / p.z);
        let x_d = distortion_of(theta).distort(&n);
        let r = Vector2::new(theta[0] * x_d.x + theta[2], theta[1] * x_d.y + theta[3]) - obs.pixel;
        Some(Projected { p, n, x_d, r })
    }

    /// r = π_θ(T_k, X_p) − u, or None when the point is not in front of the keyframe.
    fn residual(&self, theta: &Theta, points: &[Vector3<f64>], obs: &TrackObservation) -> Option<Vector2<f64>> {
        self.project(theta, points, obs).map(|q| q.r)
    }

    /// The residual norms at `x` (∞ for a point behind its keyframe).
    fn residual_norms(&self, x: &State) -> Vec<f64> {
        self.observations
            .iter()
            .map(|o| self.residual(&x.theta, &x.points, o).map_or(f64::INFINITY, |r| r.norm()))
            .collect()
    }

    /// Σ ρ(‖r‖), Huber: ρ(e) = e² for e ≤ δ, 2δe − δ² beyond; ∞ with a point behind a keyframe.
    fn cost(&self, x: &State) -> f64 {
        let delta = self.huber;
        let data: f64 = self
            .residual_norms(x)
            .into_iter()
            .map(|e| if e <= delta { e * e } else { 2.0 * delta * e - delta * delta })
            .sum();
        data + self.prior_cost(&x.theta)
    }

    /// Σ (θᵢ − θ₀ᵢ)²/σᵢ² over the free parameters.
    fn prior_cost(&self, theta: &Theta) -> f64 {
        (0..self.free).map(|i| (theta[i] - self.prior_mean[i]).powi(2) * self.prior_information[i]).sum()
    }

    /// The RMS over the observed pixels (at most [`SIGMA_PROBES`] of them, evenly spaced) of
    /// the 1σ of the corrected pixel u_c(θ) — the square root of the largest eigenvalue of
    /// J P Jᵀ, J = ∂u_c/∂θ by central differences, P = s²·S⁻¹ the posterior covariance of θ
    /// (S the reduced information at `x` with the priors, s² the data residuals' variance
    /// factor Σ‖r‖²/(2n − 3m − free)). None when S is singular.
    fn correction_sigma(&self, nominal: &Camera, x: &State) -> Option<f64> {
        let (s, _, _) = self.reduced(x, 0.0)?;
        let covariance = s.try_inverse()?;
        let points = self.by_point.iter().filter(|o| !o.is_empty()).count();
        let dof = (2 * self.observations.len()).saturating_sub(3 * points + self.free).max(1);
        let data_cost = self.cost(x) - self.prior_cost(&x.theta);
        let covariance = covariance * (data_cost / dof as f64);
        let step = self.observations.len().div_ceil(SIGMA_PROBES).max(1);
        let mut sum = 0.0;
        let mut count = 0usize;
        for o in self.observations.iter().step_by(step) {
            let mut j = Jacobian2::zeros();
            for i in 0..self.free {
                let h = 1e-6 * x.theta[i].abs().max(1e-3);
                let at = |d: f64| {
                    let mut t = x.theta;
                    t[i] += d;
                    let (camera, distortion) = camera_of(&t)?;
                    IntrinsicsCorrection { camera, distortion }.correct(nominal, &o.pixel)
                };
                j.set_column(i, &((at(h)? - at(-h)?) / (2.0 * h)));
            }
            sum += (j * covariance * j.transpose()).symmetric_eigenvalues().max().max(0.0);
            count += 1;
        }
        Some((sum / count.max(1) as f64).sqrt())
    }

    fn linearize(&self, x: &State, obs: &TrackObservation) -> Option<Linearized> {
        let theta = &x.theta;
        let Projected { p, n, x_d, r } = self.project(theta, &x.points, obs)?;
        let r_wc = self.poses[obs.keyframe].rotation.matrix();
        let d = distortion_of(theta);
        let f = Matrix2::new(theta[0], 0.0, 0.0, theta[1]);
        let pj = f * Distortion::parameter_jacobian(&n);
        let mut j_theta = Jacobian2::zeros();
        j_theta[(0, 0)] = x_d.x;
        j_theta[(1, 1)] = x_d.y;
        j_theta[(0, 2)] = 1.0;
        j_theta[(1, 3)] = 1.0;
        // columns k1, k2, p1, p2 of ∂x_d/∂(k1, k2, p1, p2, k3)
        j_theta.fixed_view_mut::<2, 4>(0, 4).copy_from(&pj.fixed_view::<2, 4>(0, 0));
        let inv_z = 1.0 / p.z;
        let j_np = Matrix2x3::new(inv_z, 0.0, -n.x * inv_z, 0.0, inv_z, -n.y * inv_z);
        let j_point = f * d.jacobian(&n) * j_np * r_wc.transpose();
        let e = r.norm();
        let weight = if e <= self.huber { 1.0 } else { self.huber / e };
        Some(Linearized { r, j_theta, j_point, weight })
    }

    /// The reduced system S(λ) δθ = b over θ (points eliminated, their blocks damped by λ
    /// too; the held parameters pinned to δ = 0) and, per point, what the back-substitution
    /// needs: V⁻¹, Wᵀ (3×8) and g_p. None when a point is behind a keyframe or a block is
    /// singular.
    #[allow(clippy::type_complexity)]
    fn reduced(
        &self,
        x: &State,
        lambda: f64,
    ) -> Option<(ThetaMatrix, Theta, Vec<Option<(Matrix3<f64>, SMatrix<f64, 3, PARAMETERS>, Vector3<f64>)>>)> {
        let mut s = ThetaMatrix::zeros();
        let mut g_theta = Theta::zeros();
        let mut back = Vec::with_capacity(self.by_point.len());
        for observations in &self.by_point {
            if observations.is_empty() {
                back.push(None);
                continue;
            }
            let mut v = Matrix3::zeros();
            let mut w_t = SMatrix::<f64, 3, PARAMETERS>::zeros();
            let mut g_p = Vector3::zeros();
            for &o in observations {
                let l = self.linearize(x, &self.observations[o])?;
                let wj = l.j_theta * l.weight;
                s += wj.transpose() * l.j_theta;
                g_theta += wj.transpose() * l.r;
                v += l.j_point.transpose() * l.j_point * l.weight;
                w_t += l.j_point.transpose() * wj;
                g_p += l.j_point.transpose() * l.r * l.weight;
            }
            for i in 0..3 {
                v[(i, i)] *= 1.0 + lambda;
            }
            let v_inv = v.try_inverse()?;
            s -= w_t.transpose() * v_inv * w_t;
            g_theta -= w_t.transpose() * (v_inv * g_p);
            back.push(Some((v_inv, w_t, g_p)));
        }
        // the priors; the point blocks' damping is already in S; damp θ's own diagonal and
        // pin the held parameters
        for i in 0..self.free {
            s[(i, i)] += self.prior_information[i];
            g_theta[i] += self.prior_information[i] * (x.theta[i] - self.prior_mean[i]);
        }
        let mut damped = s;
        for i in 0..PARAMETERS {
            if i < self.free {
                damped[(i, i)] += lambda * s[(i, i)].abs().max(1e-12);
            } else {
                damped.row_mut(i).fill(0.0);
                damped.column_mut(i).fill(0.0);
                damped[(i, i)] = 1.0;
                g_theta[i] = 0.0;
            }
        }
        Some((damped, -g_theta, back))
    }
}

impl LeastSquares<PARAMETERS> for Problem<'_> {
    type State = State;

    /// The reduced (Schur) normal equations in θ, undamped: (S, −b, cost).
    fn normal_equations(&self, x: &State) -> (ThetaMatrix, Theta, f64) {
        let cost = self.cost(x);
        match self.reduced(x, 0.0) {
            Some((s, b, _)) => (s, -b, cost),
            None => (ThetaMatrix::from_element(f64::NAN), Theta::from_element(f64::NAN), cost),
        }
    }

    /// θ only (points unchanged); the driver uses [`Self::damped_step`] instead.
    fn retract(&self, x: &State, delta: &Theta) -> State {
        State { theta: x.theta + delta, points: x.points.clone() }
    }

    /// Only the cost: the damped step forms its own (λ-dependent) Schur system.
    fn evaluate(&self, x: &State) -> Evaluation<PARAMETERS> {
        Evaluation { cost: self.cost(x), linearization: None }
    }

    /// Solves S(λ) δθ = b and back-substitutes δX_p = −V⁻¹(g_p + Wᵀδθ) (W here the 3×8
    /// block Σ J_Xᵀ w J_θ of point p). The predicted decrease is bᵀδθ.
    fn damped_step(&self, x: &State, _: Option<&Linearization<PARAMETERS>>, lambda: f64) -> DampedStep<State> {
        let Some((s, b, back)) = self.reduced(x, lambda) else { return DampedStep::NonFinite };
        let Some(chol) = s.cholesky() else { return DampedStep::NotPositiveDefinite };
        let step = chol.solve(&b);
        let points = x
            .points
            .iter()
            .zip(&back)
            .map(|(p, bs)| match bs {
                Some((v_inv, w_t, g_p)) => p - v_inv * (g_p + w_t * step),
                None => *p,
            })
            .collect();
        DampedStep::Step {
            norm: step.norm(),
            predicted_decrease: b.dot(&step),
            candidate: State { theta: x.theta + step, points },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::SplitMix64;

    /// The "true" camera of the tests: K′ off the nominal by 2–3 %, a Kinect-sized distortion.
    fn truth() -> (Camera, Distortion) {
        (
            Camera::new(516.0, 527.0, 314.0, 243.0).expect("valid"),
            Distortion { k1: -0.06, k2: 0.02, p1: 0.004, p2: -0.003, k3: 0.0 },
        )
    }

    fn nominal() -> Camera {
        Camera::new(525.0, 525.0, 320.0, 240.0).expect("valid")
    }

    /// A camera walking a 2 m arc around 600 points 2–4 m away, glancing left and right; each point seen by every
    /// keyframe it projects into (inside 640 × 480) under the true camera, `noise` px.
    fn scene(rng: &mut SplitMix64, noise: f64) -> (Vec<SE3>, Vec<Vector3<f64>>, Vec<TrackObservation>) {
        let (cam, d) = truth();
        let centre = Vector3::new(0.0, 0.0, 3.0);
        let poses: Vec<SE3> = (0..48)
            .map(|i| {
                let a = -0.7 + 1.4 * i as f64 / 47.0;
                let eye = Vector3::new(2.0 * a.sin(), 0.4 * (5.0 * a).sin(), 3.0 - 2.0 * a.cos());
                crate::testing::look_at(&eye, &(centre + Vector3::new(0.3 * (7.0 * a).sin(), 0.0, 0.0)))
            })
            .collect();
        let points: Vec<Vector3<f64>> = (0..600)
            .map(|_| {
                centre + Vector3::new(rng.uniform_in(-2.0, 2.0), rng.uniform_in(-1.2, 1.2), rng.uniform_in(0.0, 1.5))
            })
            .collect();
        let mut observations = Vec::new();
        for (k, pose) in poses.iter().enumerate() {
            for (p, x) in points.iter().enumerate() {
                let pc = pose.rotation.matrix().tr_mul(&(x - pose.translation));
                if pc.z <= 0.1 {
                    continue;
                }
                let xd = d.distort(&Vector2::new(pc.x / pc.z, pc.y / pc.z));
                let u = Vector2::new(cam.fx * xd.x + cam.cx, cam.fy * xd.y + cam.cy)
                    + Vector2::new(rng.normal(), rng.normal()) * noise;
                if (0.0..640.0).contains(&u.x) && (0.0..480.0).contains(&u.y) {
                    observations.push(TrackObservation { keyframe: k, point: p, pixel: u });
                }
            }
        }
        (poses, points, observations)
    }

    /// Start points: each track triangulated under the nominal camera would be biased; the
    /// truth moved by a few centimetres stands in for that.
    fn perturbed(rng: &mut SplitMix64, points: &[Vector3<f64>]) -> Vec<Vector3<f64>> {
        points.iter().map(|p| p + Vector3::new(rng.normal(), rng.normal(), rng.normal()) * 0.03).collect()
    }

    #[test]
    fn noise_free_tracks_give_back_the_true_camera() {
        let mut rng = SplitMix64::new(21);
        let (poses, points, observations) = scene(&mut rng, 0.0);
        let start = perturbed(&mut rng, &points);
        // priors too wide to matter: the solve itself must find the exact camera
        let flat = SelfCalibrationOptions {
            prior_focal_rel: 1e6,
            prior_principal_px: 1e9,
            prior_radial: 1e6,
            prior_tangential: 1e6,
            ..SelfCalibrationOptions::default()
        };
        let out = self_calibrate(&nominal(), &poses, &start, &observations, &flat).expect("valid input");
        let (cam, d) = truth();
        let c = out.correction.unwrap_or_else(|| panic!("{out:?}"));
        for (got, want) in [(c.camera.fx, cam.fx), (c.camera.fy, cam.fy), (c.camera.cx, cam.cx), (c.camera.cy, cam.cy)]
        {
            assert!((got - want).abs() < 1e-6, "{got} vs {want}");
        }
        for (got, want) in c.distortion.to_opencv().iter().zip(d.to_opencv()) {
            assert!((got - want).abs() < 1e-8, "{got} vs {want}");
        }
        assert!(out.rms_after_px < 1e-6 && out.rms_before_px > 1.0, "{} {}", out.rms_before_px, out.rms_after_px);
        // the correction maps what the true camera records to what the nominal pinhole would
        let x = Vector3::new(0.4, -0.3, 2.5);
        let xd = d.distort(&Vector2::new(x.x / x.z, x.y / x.z));
        let recorded = Vector2::new(cam.fx * xd.x + cam.cx, cam.fy * xd.y + cam.cy);
        let pinhole = nominal().project_cam(&x);
        assert!((c.correct(&nominal(), &recorded).expect("inverts") - pinhole).norm() < 1e-6);
    }

    /// Pixel noise of the noisy-track test (per axis).
    const NOISE_PX: f64 = 0.5;

    #[test]
    fn noisy_tracks_give_the_camera_within_the_noise() {
        let mut rng = SplitMix64::new(22);
        let (poses, points, observations) = scene(&mut rng, NOISE_PX);
        let start = perturbed(&mut rng, &points);
        let out = self_calibrate(&nominal(), &poses, &start, &observations, &SelfCalibrationOptions::default())
            .expect("valid input");
        let estimated = out.correction.unwrap_or_else(|| panic!("{out:?}"));
        let (cam, d) = truth();
        // compare the corrections where the tracks are (a polynomial lens model says little
        // about corners no keypoint reached): nominal-pinhole pixels of estimate and truth
        let exact = IntrinsicsCorrection { camera: cam, distortion: d };
        let differences: Vec<f64> = observations
            .iter()
            .map(|o| {
                let a = estimated.correct(&nominal(), &o.pixel).expect("inverts");
                let b = exact.correct(&nominal(), &o.pixel).expect("inverts");
                (a - b).norm()
            })
            .collect();
        let rms_difference = rms(&differences);
        let worst = differences.iter().copied().fold(0.0, f64::max);
        // the focal lengths, k1 and the track depths trade off along the arc: the estimate is
        // as uncertain as about one pixel of noise (0.09 px rms at 0.1 px noise, 0.45 at 0.5)
        assert!(rms_difference < NOISE_PX && worst < 4.0 * NOISE_PX, "rms {rms_difference} px, worst {worst} px");
        assert!((out.rms_after_px - NOISE_PX * 2f64.sqrt()).abs() < 0.1, "rms {}", out.rms_after_px);
        assert!(out.report.is_some_and(|r| r.converged()), "{:?}", out.report);
    }

    #[test]
    fn the_pinhole_model_holds_the_distortion_at_zero() {
        let mut rng = SplitMix64::new(23);
        let (poses, points, observations) = scene(&mut rng, 0.0);
        let options = SelfCalibrationOptions { model: IntrinsicsModel::Pinhole, ..SelfCalibrationOptions::default() };
        let out = self_calibrate(&nominal(), &poses, &points, &observations, &options).expect("valid input");
        assert!(out.correction.unwrap_or_else(|| panic!("{out:?}")).distortion.is_none());
        assert!(out.rms_after_px < out.rms_before_px);
        let options = SelfCalibrationOptions { model: IntrinsicsModel::Radial, ..SelfCalibrationOptions::default() };
        let out = self_calibrate(&nominal(), &poses, &points, &observations, &options).expect("valid input");
        let d = out.correction.unwrap_or_else(|| panic!("{out:?}")).distortion;
        assert!(d.p1 == 0.0 && d.p2 == 0.0 && d.k1 != 0.0);
    }

    #[test]
    fn bad_input_is_named_and_too_little_is_refused() {
        let mut rng = SplitMix64::new(24);
        let (poses, points, observations) = scene(&mut rng, 0.0);
        let options = SelfCalibrationOptions::default();
        let name_of = |r: Result<SelfCalibration>| match r {
            Err(GeolocError::InvalidInput { name, .. } | GeolocError::NonFinite { name, .. }) => name,
            other => panic!("expected a named error, got {other:?}"),
        };
        let mut bad = observations.clone();
        bad[3].keyframe = poses.len();
        assert_eq!(name_of(self_calibrate(&nominal(), &poses, &points, &bad, &options)), "observations");
        let mut bad = observations.clone();
        bad[5].pixel.x = f64::NAN;
        assert_eq!(name_of(self_calibrate(&nominal(), &poses, &points, &bad, &options)), "observations");
        let mut bad_points = points.clone();
        bad_points[7].z = f64::INFINITY;
        assert_eq!(name_of(self_calibrate(&nominal(), &poses, &bad_points, &observations, &options)), "points");
        let bad_options = SelfCalibrationOptions { huber_px: 0.0, ..options };
        assert_eq!(name_of(self_calibrate(&nominal(), &poses, &points, &observations, &bad_options)), "huber_px");
        let few = self_calibrate(&nominal(), &poses, &points, &observations[..50], &options).expect("valid input");
        assert!(few.correction.is_none() && few.reason.starts_with("50 observations"), "{}", few.reason);
        assert!("fisheye".parse::<IntrinsicsModel>().is_err());
        assert_eq!("radial".parse::<IntrinsicsModel>().expect("known"), IntrinsicsModel::Radial);
    }
}
