//! Forward intersection: triangulating tracks seen by cameras of known pose (the paper's
//! Eq. forward_intersection), with a per-point covariance.
//!
//! For each track: an N-view DLT on centred coordinates, then LM on X with a robust kernel
//! (Huber by default) on r_k = (π(T_k, X) − z_k)/σ. Observations whose residual exceeds
//! `max_residual_px` are dropped and X re-solved; when they spoil the all-view start, every
//! two-view DLT is tried and the one with the largest consensus wins (an LO-RANSAC over the
//! few views of a track). A point is rejected when fewer than two views remain, when only
//! two of three or more views agree (any two views fit *some* point), when it is
//! behind an inlier camera, when its mean inlier residual exceeds `max_residual_px` (the
//! paper's ε_r) or when its largest triangulation angle is below `min_angle_rad`.
//!
//! When keyframe pose covariances C_k are given, view k's residual has covariance
//! S_k = σ²I + J_T,k C_k J_T,kᵀ (J_T,k = ∂r_k/∂δ_k, right perturbation of world_from_cam
//! T_k): the LM is then generalized least squares with W_k = S_k⁻¹, and the outlier gate and
//! ε_r apply to σ·√(rᵀW_k r) — a view is not an outlier for an error its pose explains.
//! After the inlier set is stable a last plain (weighted) least-squares solve removes the
//! Huber kernel's loss of efficiency.
//!
//! Covariance (first-order propagation at the optimum, H = Σ_k J_kᵀ W_k J_k):
//! * pixel noise σ in the training images: Σ_pix = H⁻¹ (Σ_k J_kᵀ W_k σ² W_k J_k) H⁻¹;
//! * keyframe pose noise: δX = Σ_k D_k δ_k with D_k = −H⁻¹ J_kᵀ W_k J_T,k, so
//!   Σ_X = Σ_pix + Σ_k D_k C_k D_kᵀ.
//!
//! The D_k are returned too: pose errors are shared by every point a keyframe sees, so a
//! later PnP must propagate them jointly (see `pnp`), not as independent point errors.

use nalgebra::{Matrix2, Matrix3, Matrix3x6, Matrix6, Vector2, Vector3, Vector4};

use crate::camera::{Camera, j_uv_point, j_uv_pose, project};
use crate::error::{GeolocError, Result};
use crate::lie::SE3;
use crate::optim::covariance::check_covariances;
use crate::optim::{LeastSquares, LmOptions, RobustLoss, levenberg_marquardt};

/// Options of [`triangulate`]; defaults follow the paper.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TriangulationOptions {
    /// Robust kernel on residuals in units of σ (default Huber, width 1).
    pub loss: RobustLoss,
    /// Pixel noise σ of the keypoints (default 1 px, as in the paper).
    pub pixel_sigma: f64,
    /// ε_r: an observation with a larger residual is an outlier, and a point whose mean
    /// inlier residual is larger is rejected (default 5 px).
    pub max_residual_px: f64,
    /// A point whose largest ray angle is smaller is rejected (default 1°).
    pub min_angle_rad: f64,
    /// LM settings.
    pub lm: LmOptions,
}

impl Default for TriangulationOptions {
    fn default() -> Self {
        Self {
            loss: RobustLoss::Huber { width: 1.0 },
            pixel_sigma: 1.0,
            max_residual_px: 5.0,
            min_angle_rad: 1f64.to_radians(),
            lm: LmOptions::default(),
        }
    }
}

/// Why a track did or did not give a point.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub enum TrackStatus {
    /// A valid point.
    Valid = 0,
    /// Fewer than two (inlier) views.
    TooFewViews = 1,
    /// The rays do not meet in a finite point (parallel rays, zero baseline).
    Degenerate = 2,
    /// Behind one of its inlier cameras.
    BehindCamera = 3,
    /// Mean inlier residual above ε_r.
    LargeResidual = 4,
    /// Largest triangulation angle below the minimum.
    SmallAngle = 5,
    /// Only two of three or more views agree: any two views fit a point, so a lone pair
    /// outvoted by the rest cannot be told from an outlier pair.
    Ambiguous = 6,
}

impl TrackStatus {
    /// Every status, in code order.
    pub const ALL: [Self; 7] = [
        Self::Valid,
        Self::TooFewViews,
        Self::Degenerate,
        Self::BehindCamera,
        Self::LargeResidual,
        Self::SmallAngle,
        Self::Ambiguous,
    ];

    /// The numeric code (the `#[repr(u8)]` discriminant).
    pub fn code(self) -> u8 {
        self as u8
    }

    /// A short snake_case name ("valid", "too_few_views", …).
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Valid => "valid",
            Self::TooFewViews => "too_few_views",
            Self::Degenerate => "degenerate",
            Self::BehindCamera => "behind_camera",
            Self::LargeResidual => "large_residual",
            Self::SmallAngle => "small_angle",
            Self::Ambiguous => "ambiguous",
        }
    }

    /// A short human-readable reason.
    pub fn reason(self) -> &'static str {
        match self {
            Self::Valid => "ok",
            Self::TooFewViews => "fewer than two inlier views",
            Self::Degenerate => "rays do not intersect (zero baseline or parallel rays)",
            Self::BehindCamera => "point behind an observing camera",
            Self::LargeResidual => "mean residual above max_residual",
            Self::SmallAngle => "triangulation angle below min_angle",
            Self::Ambiguous => "only two of three or more views agree",
        }
    }
}

/// One triangulated track.
#[derive(Clone, Debug, PartialEq)]
pub struct TriangulatedPoint {
    /// X in world coordinates (meaningful when `status` is valid; else the best attempt or 0).
    pub point: Vector3<f64>,
    /// Valid or why not.
    pub status: TrackStatus,
    /// Mean reprojection residual of the inlier observations (pixels).
    pub mean_residual_px: f64,
    /// Largest angle between two inlier rays (radians).
    pub max_angle_rad: f64,
    /// Marginal covariance of X: pixel noise plus keyframe-pose noise (m²).
    pub covariance: Matrix3<f64>,
    /// The part of `covariance` due to pixel noise alone (independent between points).
    pub pixel_covariance: Matrix3<f64>,
    /// (camera index, D_k = ∂X/∂δ_k) for each camera with inlier observations; computed only
    /// when pose covariances are given (empty otherwise).
    pub pose_jacobians: Vec<(usize, Matrix3x6<f64>)>,
    /// Per observation of the track (in input order): kept as inlier.
    pub inliers: Vec<bool>,
}

/// The whole triangulation of many tracks.
#[derive(Clone, Debug, PartialEq)]
pub struct Triangulation {
    /// The distinct track ids of the input, increasing: `points[i]` is track `track_ids[i]`
    /// (for ids 0..P−1 all present, row i is track i).
    pub track_ids: Vec<usize>,
    /// One entry per distinct track id, aligned with `track_ids`.
    pub points: Vec<TriangulatedPoint>,
    /// Per input observation: kept as inlier of its track.
    pub observation_inliers: Vec<bool>,
}

impl Triangulation {
    /// The point of track `track_id`, if the input had that track.
    pub fn point(&self, track_id: usize) -> Option<&TriangulatedPoint> {
        self.track_ids.binary_search(&track_id).ok().map(|row| &self.points[row])
    }
}

/// Triangulates every track; observation o says "track `track_ids[o]` is seen by camera
/// `camera_ids[o]` at undistorted pixel `pixels[o]`". The result has one row per distinct
/// track id, in increasing order of id ([`Triangulation::track_ids`]); ids are only labels
/// (any values; memory is proportional to the number of observations, not to the ids).
///
/// `pose_covariances`, when given, has one 6×6 covariance per pose (right perturbation of
/// world_from_cam, translation first), symmetric positive semi-definite.
///
/// # Errors
/// Mismatched lengths, out-of-range camera ids, non-finite input, covariances that are not
/// symmetric PSD, bad options.
pub fn triangulate(
    camera: &Camera,
    world_from_cams: &[SE3],
    pose_covariances: Option<&[Matrix6<f64>]>,
    camera_ids: &[usize],
    track_ids: &[usize],
    pixels: &[Vector2<f64>],
    options: &TriangulationOptions,
) -> Result<Triangulation> {
    check_options(options)?;
    let n_obs = pixels.len();
    for (name, len) in [("cam_ids", camera_ids.len()), ("track_ids", track_ids.len())] {
        if len != n_obs {
            return Err(GeolocError::invalid(name, format!("has {len} entries but pixels has {n_obs}")));
        }
    }
    if let Some(covs) = pose_covariances
        && covs.len() != world_from_cams.len()
    {
        return Err(GeolocError::invalid(
            "pose_covariances",
            format!("has {} entries but poses has {}", covs.len(), world_from_cams.len()),
        ));
    }
    if let Some(o) = camera_ids.iter().position(|&c| c >= world_from_cams.len()) {
        return Err(GeolocError::invalid(
            "cam_ids",
            format!("cam_ids[{o}] = {} but there are {} poses", camera_ids[o], world_from_cams.len()),
        ));
    }
    if let Some(o) = pixels.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
        return Err(GeolocError::NonFinite { name: "pixels".into(), index: o });
    }
    if let Some(covs) = pose_covariances {
        check_covariances("pose_covariances", covs)?;
    }
    let (ids, by_track) = group_by_track(track_ids);
    let points: Vec<TriangulatedPoint> = crate::parallel::map_slice(&by_track, 2, |obs| {
        let views: Vec<View> = obs.iter().map(|&o| View { camera: camera_ids[o], uv: pixels[o] }).collect();
        triangulate_track(camera, world_from_cams, pose_covariances, &views, options)
    });
    let mut observation_inliers = vec![false; n_obs];
    for (track, obs) in points.iter().zip(&by_track) {
        for (&o, &inlier) in obs.iter().zip(&track.inliers) {
            observation_inliers[o] = inlier && track.status == TrackStatus::Valid;
        }
    }
    Ok(Triangulation { track_ids: ids, points, observation_inliers })
}

/// The distinct ids (increasing) and, per id, its observation indices in input order —
/// by sorting (id, observation) pairs, so memory is proportional to the input.
fn group_by_track(track_ids: &[usize]) -> (Vec<usize>, Vec<Vec<usize>>) {
    let mut order: Vec<(usize, usize)> = track_ids.iter().copied().zip(0..).collect();
    order.sort_unstable();
    let (mut ids, mut groups): (Vec<usize>, Vec<Vec<usize>>) = (Vec::new(), Vec::new());
    for (t, o) in order {
        match groups.last_mut() {
            Some(group) if ids.last() == Some(&t) => group.push(o),
            _ => {
                ids.push(t);
                groups.push(vec![o]);
            }
        }
    }
    (ids, groups)
}

fn check_options(options: &TriangulationOptions) -> Result<()> {
    let positive = |name: &str, v: f64| {
        if v.is_finite() && v > 0.0 {
            Ok(())
        } else {
            Err(GeolocError::invalid(name, format!("must be finite and > 0, got {v}")))
        }
    };
    positive("pixel_sigma", options.pixel_sigma)?;
    positive("max_residual", options.max_residual_px)?;
    if !(options.min_angle_rad.is_finite() && options.min_angle_rad >= 0.0) {
        return Err(GeolocError::invalid("min_angle", "must be finite and ≥ 0"));
    }
    Ok(())
}

/// One observation of a track.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct View {
    /// Index of the observing camera pose.
    pub camera: usize,
    /// Undistorted pixel.
    pub uv: Vector2<f64>,
}

/// Triangulates one track (see the module doc): (1) a robust start from all views or the
/// best two-view DLT, (2) re-solves on the consensus until it is stable and a last plain
/// least-squares solve, (3) the checks that make a point valid, (4) its covariance.
pub fn triangulate_track(
    camera: &Camera,
    poses: &[SE3],
    pose_covariances: Option<&[Matrix6<f64>]>,
    views: &[View],
    options: &TriangulationOptions,
) -> TriangulatedPoint {
    let mut result = TriangulatedPoint {
        point: Vector3::zeros(),
        status: TrackStatus::TooFewViews,
        mean_residual_px: f64::INFINITY,
        max_angle_rad: 0.0,
        covariance: Matrix3::zeros(),
        pixel_covariance: Matrix3::zeros(),
        pose_jacobians: Vec::new(),
        inliers: vec![false; views.len()],
    };
    if distinct_cameras(views.iter()) < 2 {
        return result;
    }
    if max_baseline(poses, views) <= MIN_BASELINE_M {
        result.status = TrackStatus::Degenerate;
        return result;
    }
    let track = Track { camera, poses, pose_covariances, views, options };
    let Some((x, inliers)) = track.robust_start() else {
        result.status = TrackStatus::Degenerate;
        return result;
    };
    let (x, inliers) = track.settle(x, inliers);
    result.point = x;
    if distinct_cameras(inliers.iter().map(|&i| &views[i])) < 2 {
        result.status = TrackStatus::TooFewViews;
        return result;
    }
    let x = track.refine(&inliers, x, RobustLoss::None);
    result.point = x;
    for &i in &inliers {
        result.inliers[i] = true;
    }
    let weights = track.weights(&x);
    track.classify(&inliers, &weights, &mut result);
    if result.status == TrackStatus::Valid {
        track.propagate_covariance(&inliers, &weights, &mut result);
    }
    result
}

/// One track's data and options, with the per-view weights of its generalized least squares.
struct Track<'a> {
    camera: &'a Camera,
    poses: &'a [SE3],
    pose_covariances: Option<&'a [Matrix6<f64>]>,
    views: &'a [View],
    options: &'a TriangulationOptions,
}

impl Track<'_> {
    /// Step 1: the all-view DLT (+ robust LM unless every observation already fits); if
    /// that left more than one view out, the best two-view DLT seeds the consensus instead
    /// (a single bad view is what the robust start handles by itself). None: no finite start.
    fn robust_start(&self) -> Option<(Vector3<f64>, Vec<usize>)> {
        let views = self.views;
        let all: Vec<usize> = (0..views.len()).collect();
        let mut start = dlt(self.camera, self.poses, views, &all);
        let mut inliers = start.map(|x| self.inlier_set(&x)).unwrap_or_default();
        if let Some(x) = start
            && inliers.len() < views.len()
        {
            let refined = self.refine(&all, x, self.options.loss);
            start = Some(refined);
            inliers = self.inlier_set(&refined);
        }
        if inliers.len() + 1 < views.len()
            && views.len() >= 3
            && let Some((x, set)) = best_pair(self.camera, self.poses, views, self.options.max_residual_px)
            && set.len() > inliers.len()
        {
            start = Some(x);
            inliers = set;
        }
        start.map(|x| (x, inliers))
    }

    /// Step 2: re-solves on the consensus until it is stable (at most a few rounds).
    fn settle(&self, mut x: Vector3<f64>, mut inliers: Vec<usize>) -> (Vector3<f64>, Vec<usize>) {
        for _ in 0..3 {
            if distinct_cameras(inliers.iter().map(|&i| &self.views[i])) < 2 {
                break;
            }
            x = self.refine(&inliers, x, self.options.loss);
            let next = self.inlier_set(&x);
            if next == inliers {
                break;
            }
            inliers = next;
        }
        (x, inliers)
    }

    /// Step 3: the mean normalized residual σ·√(rᵀWr) (ε_r), the widest ray angle and the
    /// status: behind a camera, an outvoted pair, a large residual or a small angle.
    fn classify(&self, inliers: &[usize], weights: &[Matrix2<f64>], result: &mut TriangulatedPoint) {
        let (views, poses, x) = (self.views, self.poses, result.point);
        let sigma = self.options.pixel_sigma;
        let normalized: f64 = inliers
            .iter()
            .map(|&i| {
                let r = project(self.camera, &poses[views[i].camera], &x).uv - views[i].uv;
                sigma * r.dot(&(weights[i] * r)).sqrt()
            })
            .sum();
        result.mean_residual_px = normalized / inliers.len() as f64;
        result.max_angle_rad = max_ray_angle(poses, views, inliers, &x);
        result.status = if inliers.iter().any(|&i| depth(poses, &views[i], &x) <= 0.0) {
            TrackStatus::BehindCamera
        } else if distinct_cameras(inliers.iter().map(|&i| &views[i])) == 2 && distinct_cameras(views.iter()) >= 3 {
            TrackStatus::Ambiguous
        } else if result.mean_residual_px > self.options.max_residual_px {
            TrackStatus::LargeResidual
        } else if result.max_angle_rad < self.options.min_angle_rad {
            TrackStatus::SmallAngle
        } else {
            TrackStatus::Valid
        };
    }

    /// Wₖ = Sₖ⁻¹ of every view at X ([`view_weight`]).
    fn weights(&self, x: &Vector3<f64>) -> Vec<Matrix2<f64>> {
        let sigma = self.options.pixel_sigma;
        self.views
            .iter()
            .map(|v| view_weight(self.camera, self.poses, self.pose_covariances, sigma, v.camera, x))
            .collect()
    }

    /// Observations that fit X: in front of the camera with rᵀWr ≤ (ε_r/σ)² — exactly
    /// ‖r‖ ≤ ε_r without pose covariances (ε_r widened to 4.29σ for large σ, see
    /// `pnp::gate_px`).
    fn inlier_set(&self, x: &Vector3<f64>) -> Vec<usize> {
        let weights = self.weights(x);
        let sigma = self.options.pixel_sigma;
        let gate = (crate::pnp::gate_px(self.options.max_residual_px, sigma) / sigma).powi(2);
        (0..self.views.len())
            .filter(|&i| {
                let v = &self.views[i];
                let r = project(self.camera, &self.poses[v.camera], x).uv - v.uv;
                depth(self.poses, v, x) > 0.0 && r.dot(&(weights[i] * r)) <= gate
            })
            .collect()
    }

    fn refine(&self, subset: &[usize], x: Vector3<f64>, loss: RobustLoss) -> Vector3<f64> {
        let weights = self.weights(&x);
        let problem =
            PointProblem { camera: self.camera, poses: self.poses, views: self.views, subset, weights: &weights, loss };
        levenberg_marquardt(&problem, x, &self.options.lm).0
    }

    /// Σ_X = Σ_pix + Σ D_k C_k D_kᵀ over the inliers ([`point_covariance_terms`]).
    fn propagate_covariance(&self, inliers: &[usize], weights: &[Matrix2<f64>], result: &mut TriangulatedPoint) {
        let views = inliers.iter().map(|&i| (self.views[i].camera, weights[i]));
        let sigma = self.options.pixel_sigma;
        let Some(terms) =
            point_covariance_terms(self.camera, self.poses, self.pose_covariances, sigma, &result.point, views)
        else {
            result.status = TrackStatus::Degenerate;
            return;
        };
        result.pixel_covariance = terms.pixel;
        result.covariance = terms.pixel;
        if let Some(covs) = self.pose_covariances {
            for (cam, d) in &terms.pose_jacobians {
                result.covariance += d * covs[*cam] * d.transpose();
            }
        }
        result.pose_jacobians = terms.pose_jacobians;
    }
}

/// Wₖ = Sₖ⁻¹, Sₖ = σ²I + J_T,k C_k J_T,kᵀ: the covariance of the residual of a view from
/// camera `cam` at X when its pose has covariance C_k (σ²I alone without pose covariances,
/// or when Sₖ is singular).
pub fn view_weight(
    camera: &Camera,
    poses: &[SE3],
    pose_covariances: Option<&[Matrix6<f64>]>,
    pixel_sigma: f64,
    cam: usize,
    x: &Vector3<f64>,
) -> Matrix2<f64> {
    let var = pixel_sigma * pixel_sigma;
    let Some(covs) = pose_covariances else { return Matrix2::identity() / var };
    let p = project(camera, &poses[cam], x);
    let j_t = j_uv_pose(camera, &p);
    let s = Matrix2::identity() * var + j_t * covs[cam] * j_t.transpose();
    s.try_inverse().unwrap_or_else(|| Matrix2::identity() / var)
}

/// The two parts of a triangulated point's covariance that a later PnP needs apart.
#[derive(Clone, Debug, PartialEq)]
pub struct PointCovarianceTerms {
    /// Σ_pix = H⁻¹(Σ_k J_kᵀW_k σ² W_k J_k)H⁻¹: the pixel noise of the views alone (m²).
    pub pixel: Matrix3<f64>,
    /// (camera, D_k = −H⁻¹ Σ J_kᵀW_k J_T,k) per camera, in the order of first view; empty
    /// without pose covariances.
    pub pose_jacobians: Vec<(usize, Matrix3x6<f64>)>,
}

/// First-order covariance terms of the point X from its inlier views (camera, W_k) at X,
/// H = Σ_k J_kᵀ W_k J_k (J_k = ∂π/∂X): see the module doc. The same numbers as the
/// triangulation's, bit for bit, for the same views in the same order — so a map can keep a
/// point and its views and compute the D_k only for the points a query matched. `None` when
/// H is singular.
pub fn point_covariance_terms(
    camera: &Camera,
    poses: &[SE3],
    pose_covariances: Option<&[Matrix6<f64>]>,
    pixel_sigma: f64,
    x: &Vector3<f64>,
    views: impl Iterator<Item = (usize, Matrix2<f64>)>,
) -> Option<PointCovarianceTerms> {
    let var = pixel_sigma * pixel_sigma;
    let mut h = Matrix3::zeros();
    let mut meat = Matrix3::zeros();
    let mut terms = Vec::with_capacity(views.size_hint().0);
    for (cam, w) in views {
        let pose = &poses[cam];
        let p = project(camera, pose, x);
        let j_x = j_uv_point(camera, pose, &p);
        let jt_w = j_x.transpose() * w;
        h += jt_w * j_x;
        meat += var * jt_w * jt_w.transpose();
        terms.push((cam, jt_w, p));
    }
    let h_inv = h.try_inverse()?;
    let pixel = h_inv * meat * h_inv;
    let mut pose_jacobians: Vec<(usize, Matrix3x6<f64>)> = Vec::new();
    if pose_covariances.is_some() {
        for (cam, jt_w, p) in terms {
            let d = -(h_inv * jt_w) * j_uv_pose(camera, &p);
            match pose_jacobians.iter_mut().find(|(c, _)| *c == cam) {
                Some((_, acc)) => *acc += d,
                None => pose_jacobians.push((cam, d)),
            }
        }
    }
    Some(PointCovarianceTerms { pixel, pose_jacobians })
}

/// Camera centres closer than this are one centre: no baseline, no triangulation.
const MIN_BASELINE_M: f64 = 1e-9;

fn max_baseline(poses: &[SE3], views: &[View]) -> f64 {
    let mut best = 0.0_f64;
    for a in views {
        for b in views {
            best = best.max((poses[a.camera].translation - poses[b.camera].translation).norm());
        }
    }
    best
}

fn distinct_cameras<'a>(views: impl Iterator<Item = &'a View>) -> usize {
    let mut cams: Vec<usize> = views.map(|v| v.camera).collect();
    cams.sort_unstable();
    cams.dedup();
    cams.len()
}

fn depth(poses: &[SE3], view: &View, x: &Vector3<f64>) -> f64 {
    let pose = &poses[view.camera];
    pose.rotation.matrix().column(2).dot(&(x - pose.translation))
}

fn residual_px(camera: &Camera, poses: &[SE3], view: &View, x: &Vector3<f64>) -> f64 {
    (project(camera, &poses[view.camera], x).uv - view.uv).norm()
}

/// Every pair of views of distinct cameras seeds a two-view DLT; the largest consensus
/// (ties: smallest truncated squared error) wins.
fn best_pair(camera: &Camera, poses: &[SE3], views: &[View], threshold: f64) -> Option<(Vector3<f64>, Vec<usize>)> {
    let mut best: Option<(Vector3<f64>, Vec<usize>, f64)> = None;
    for i in 0..views.len() {
        for j in i + 1..views.len() {
            if views[i].camera == views[j].camera {
                continue;
            }
            let Some(x) = dlt(camera, poses, views, &[i, j]) else { continue };
            let set: Vec<usize> = (0..views.len())
                .filter(|&k| {
                    depth(poses, &views[k], &x) > 0.0 && residual_px(camera, poses, &views[k], &x) <= threshold
                })
                .collect();
            if set.len() < 2 {
                continue;
            }
            let score: f64 =
                views.iter().map(|v| residual_px(camera, poses, v, &x).powi(2).min(threshold * threshold)).sum();
            let better = match &best {
                None => true,
                Some((_, b, s)) => set.len() > b.len() || (set.len() == b.len() && score < *s),
            };
            if better {
                best = Some((x, set, score));
            }
        }
    }
    best.map(|(x, set, _)| (x, set))
}

/// N-view DLT in normalized camera coordinates, centred on the mean camera centre and solved
/// in inhomogeneous form: each view gives the rows aₖ = x̂ₖ P₃ − P₁, ŷₖ P₃ − P₂ of
/// A (X, 1)ᵀ = 0 (normalized to unit length), and X = −(Σaₓᵧᵤaₓᵧᵤᵀ)⁻¹ Σ aₓᵧᵤ a_w is a 3×3
/// solve (centring keeps the point away from w = 0). None when the rays are (nearly)
/// parallel, i.e. the solution is at infinity.
fn dlt(camera: &Camera, poses: &[SE3], views: &[View], subset: &[usize]) -> Option<Vector3<f64>> {
    let centre = subset.iter().map(|&i| poses[views[i].camera].translation).sum::<Vector3<f64>>() / subset.len() as f64;
    let mut ata = Matrix3::<f64>::zeros();
    let mut atb = Vector3::<f64>::zeros();
    for &i in subset {
        let pose = &poses[views[i].camera];
        let rt = pose.rotation.matrix().transpose();
        let t = -(rt * (pose.translation - centre));
        let xn = camera.unproject(&views[i].uv);
        for (coord, k) in [(xn.x, 0), (xn.y, 1)] {
            let a = Vector4::new(
                coord * rt[(2, 0)] - rt[(k, 0)],
                coord * rt[(2, 1)] - rt[(k, 1)],
                coord * rt[(2, 2)] - rt[(k, 2)],
                coord * t[2] - t[k],
            );
            let a = a / a.norm();
            let axyz = a.fixed_rows::<3>(0);
            ata += axyz * axyz.transpose();
            atb -= axyz * a[3];
        }
    }
    // λ_min ≥ det/(λ_max λ_mid) ≥ 4 det/tr²; compared with λ_max ≤ tr
    let trace = ata.trace();
    let lower_bound = 4.0 * ata.determinant() / (trace * trace);
    if lower_bound.is_nan() || lower_bound <= DLT_MIN_RECIPROCAL_CONDITION * trace {
        return None;
    }
    let x = ata.cholesky()?.solve(&atb) + centre;
    x.iter().all(|v| v.is_finite()).then_some(x)
}

/// Reciprocal condition number of the DLT's 3×3 normal matrix below which the rays are
/// parallel (the point is at infinity).
const DLT_MIN_RECIPROCAL_CONDITION: f64 = 1e-12;

struct PointProblem<'a> {
    camera: &'a Camera,
    poses: &'a [SE3],
    views: &'a [View],
    subset: &'a [usize],
    /// Per view (indexed like `views`): W = S⁻¹.
    weights: &'a [Matrix2<f64>],
    loss: RobustLoss,
}

impl LeastSquares<3> for PointProblem<'_> {
    type State = Vector3<f64>;

    fn normal_equations(&self, x: &Vector3<f64>) -> (Matrix3<f64>, Vector3<f64>, f64) {
        let mut h = Matrix3::zeros();
        let mut g = Vector3::zeros();
        let mut cost = 0.0;
        for &i in self.subset {
            let v = &self.views[i];
            let pose = &self.poses[v.camera];
            let p = project(self.camera, pose, x);
            let r = p.uv - v.uv;
            let wr = self.weights[i] * r;
            let s = r.dot(&wr);
            let robust = self.loss.weight(s);
            let j = j_uv_point(self.camera, pose, &p);
            h += robust * j.transpose() * self.weights[i] * j;
            g += robust * j.transpose() * wr;
            cost += self.loss.cost(s);
        }
        (h, g, cost)
    }

    fn retract(&self, x: &Vector3<f64>, d: &Vector3<f64>) -> Vector3<f64> {
        x + d
    }
}

fn max_ray_angle(poses: &[SE3], views: &[View], subset: &[usize], x: &Vector3<f64>) -> f64 {
    // the largest angle is the smallest cosine: one atan2 at the end, not one per pair
    let rays: Vec<Vector3<f64>> =
        subset.iter().map(|&i| (x - poses[views[i].camera].translation).normalize()).collect();
    let mut widest: Option<(f64, usize, usize)> = None;
    for a in 0..rays.len() {
        for b in a + 1..rays.len() {
            let cos = rays[a].dot(&rays[b]);
            if widest.is_none_or(|(c, _, _)| cos < c) {
                widest = Some((cos, a, b));
            }
        }
    }
    widest.map_or(0.0, |(cos, a, b)| rays[a].cross(&rays[b]).norm().atan2(cos))
}
