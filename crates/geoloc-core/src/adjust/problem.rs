//! The adjustment problem with a fixed observation set: the residuals and their Jacobians,
//! the normal equations with the points eliminated (Schur complement), Levenberg–Marquardt
//! and the marginal covariances at the solution (see the parent module's doc).

use nalgebra::{Matrix2x3, Matrix3, Matrix6, SMatrix, Vector2, Vector3, Vector6};

use super::{AdjustmentOptions, LabelSigma, Observation, camera_frame_covariance};
use crate::camera::Camera;
use crate::error::{GeolocError, Result};
use crate::lie::{SE3, se3, so3};
use crate::optim::envelope::BlockEnvelope;
use crate::parallel::map_slice;

pub(super) type Matrix6x3 = SMatrix<f64, 6, 3>;
pub(super) type Matrix2x6 = SMatrix<f64, 2, 6>;

/// Classifies every observation afresh at `state`: the first `given` are used when their
/// reprojection error is at most `outlier_px`, the rest (the candidates) when it is at most
/// `readmit_px`; none behind the camera. In pixels, whatever the keypoint's σ (a threshold of
/// 4σ kept the coarse keypoints' gross matches and moved the 7-Scenes skeleton of frames
/// 0–599 further from the SfM reference, 0.22 → 0.26° median).
pub(super) fn classify_observations(
    camera: &Camera,
    state: &State,
    observations: &[Observation],
    given: usize,
    options: &AdjustmentOptions,
    inliers: &mut [bool],
) {
    for (i, (o, inlier)) in observations.iter().zip(inliers.iter_mut()).enumerate() {
        let max_px = if i < given { options.outlier_px } else { options.readmit_px };
        *inlier = state.residual_px(camera, o).is_some_and(|r| r.norm() <= max_px);
    }
}

pub(super) fn rms_px(camera: &Camera, state: &State, observations: &[Observation], inliers: &[bool]) -> f64 {
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
pub(super) struct State {
    /// B_k.
    pub(super) labels: Vec<SE3>,
    /// X.
    pub(super) offset: SE3,
    /// P_j.
    pub(super) points: Vec<Vector3<f64>>,
}

/// Smallest depth (m) of a point in front of a camera.
pub(super) const MIN_DEPTH_M: f64 = 1e-3;

impl State {
    /// (q, p): the point in the label frame and in the camera frame.
    pub(super) fn frames(&self, o: &Observation) -> (Vector3<f64>, Vector3<f64>) {
        let b = &self.labels[o.keyframe];
        let q = b.rotation.matrix().tr_mul(&(self.points[o.point] - b.translation));
        let p = self.offset.rotation.matrix().tr_mul(&(q - self.offset.translation));
        (q, p)
    }

    /// π(K, T_k⁻¹ P_j) − u, None behind the camera.
    pub(super) fn residual_px(&self, camera: &Camera, o: &Observation) -> Option<Vector2<f64>> {
        let (_, p) = self.frames(o);
        (p.z > MIN_DEPTH_M).then(|| camera.project_cam(&p) - o.pixel)
    }
}

/// One observation's linearization: the whitened residual r, its robust weight, and the
/// Jacobians of r (2×6 keyframe, 2×6 offset, 2×3 point).
pub(super) struct Linearized {
    pub(super) r: Vector2<f64>,
    pub(super) weight: f64,
    pub(super) j_label: Matrix2x6,
    pub(super) j_offset: Matrix2x6,
    pub(super) j_point: Matrix2x3<f64>,
}

/// One observation's camera-side blocks: (keyframe k, U_kk, U_Xk, g_k).
pub(super) type CameraBlocks = (usize, Matrix6<f64>, Matrix6<f64>, Vector6<f64>);

/// Per point: V_j, g_j, and the couplings with its observers (keyframe order) and the offset.
pub(super) struct PointBlock {
    pub(super) v: Matrix3<f64>,
    pub(super) g: Vector3<f64>,
    /// (keyframe, W_kj = Σ w J_kᵀ J_j).
    pub(super) couplings: Vec<(usize, Matrix6x3)>,
    /// W_Xj.
    pub(super) offset: Matrix6x3,
    /// The camera-side blocks this point adds: per observer, (keyframe, U_kk, U_Xk, g_k),
    /// and the offset's (U_XX, g_X).
    pub(super) camera: Vec<CameraBlocks>,
    pub(super) offset_block: (Matrix6<f64>, Vector6<f64>),
    pub(super) cost: f64,
}

impl PointBlock {
    pub(super) fn empty(capacity: usize) -> Self {
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
pub(super) const MIN_POINT_CONDITION: f64 = 1e-8;

/// Whether V_j is positive definite with λ_min ≥ [`MIN_POINT_CONDITION`] λ_max.
pub(super) fn well_conditioned(v: &Matrix3<f64>) -> bool {
    let e = v.symmetric_eigenvalues();
    let (lo, hi) = (e.min(), e.max());
    lo.is_finite() && hi > 0.0 && lo >= MIN_POINT_CONDITION * hi
}

/// The adjustment problem with a fixed observation set.
pub(super) struct Problem<'a> {
    pub(super) camera: &'a Camera,
    pub(super) labels: &'a [SE3],
    pub(super) observations: &'a [Observation],
    /// Per point: its inlier observations, in keyframe order.
    pub(super) by_point: Vec<Vec<usize>>,
    pub(super) options: &'a AdjustmentOptions,
    pub(super) label_information: Vector6<f64>,
    /// Size of the reduced system in blocks: keyframes, then the offset if estimated.
    pub(super) blocks: usize,
    /// The reduced system's envelope.
    pub(super) first: Vec<usize>,
    /// (pixel, label) factors κ on the kernels' IRLS weights w, each term weighing min(1, κ w):
    /// 1 while minimizing, the kernels'
    /// [`crate::optim::robust::RobustLoss::information_scale`] for the covariances ([`Problem::for_covariances`]).
    pub(super) weight_scale: (f64, f64),
}

/// The reduced (camera-side) normal equations and what back-substitution needs.
pub(super) struct Reduced {
    pub(super) s: BlockEnvelope,
    pub(super) rhs: Vec<f64>,
    pub(super) points: Vec<PointBlock>,
    /// (V_j + λ diag V_j)⁻¹ per point, None where singular.
    pub(super) v_inv: Vec<Option<Matrix3<f64>>>,
}

/// Marginal covariances at the solution.
pub(super) struct Covariances {
    pub(super) label_poses: Vec<Matrix6<f64>>,
    /// Per keyframe, the covariance of its neighbourhood's mean error ([`neighbourhood_covariances`]).
    pub(super) label_neighbourhoods: Vec<Matrix6<f64>>,
    /// Cov(δ_k, δ_X) per keyframe.
    pub(super) label_offset: Vec<Matrix6<f64>>,
    pub(super) offset: Matrix6<f64>,
    pub(super) points: Vec<Matrix3<f64>>,
}

impl Covariances {
    /// Σ_T of T_k = B_k X: δT = Ad_{X⁻¹} δ_k + δ_X, so Σ_T is the label pose's covariance
    /// with X held ([`camera_frame_covariance`]) plus the offset's terms
    /// Ad_{X⁻¹} Σ_kX + Σ_Xk Ad_{X⁻¹}ᵀ + Σ_X.
    pub(super) fn camera_poses(&self, offset: &SE3) -> Vec<Matrix6<f64>> {
        let a = offset.inverse().adjoint();
        self.label_poses
            .iter()
            .zip(&self.label_offset)
            .map(|(c, cx)| {
                let cross = a * cx;
                let offset_terms = cross + cross.transpose() + self.offset;
                camera_frame_covariance(offset, c) + (offset_terms + offset_terms.transpose()) * 0.5
            })
            .collect()
    }
}

/// Marquardt damping: the first λ, and its growth and shrink factors.
pub(super) const INITIAL_LAMBDA: f64 = 1e-4;
pub(super) const LAMBDA_UP: f64 = 10.0;
pub(super) const LAMBDA_DOWN: f64 = 0.3;
/// Relative cost decrease below which the minimization has converged.
pub(super) const COST_TOLERANCE: f64 = 1e-6;

impl<'a> Problem<'a> {
    pub(super) fn new(
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
            weight_scale: (1.0, 1.0),
        }
    }

    /// This problem with each robust term's weight w scaled to the information it gives the
    /// estimate, min(1, κ w) (κ = [`crate::optim::robust::RobustLoss::information_scale`]: 2
    /// dimensions for a pixel, 6 for a label prior), the normal equations its covariances are
    /// taken from. The IRLS weights alone are Gauss–Newton's information of the weighted
    /// problem, not the estimate's: the kernel down-weights inliers too, and with the label
    /// priors' Cauchy kernel (k = 3, mean weight 0.63 over χ²₆) they claim 1.59 times the
    /// variance the estimate has (1.048 times least squares'). Capped at 1: no term gives more
    /// than least squares would — labels whose σ was widened for their correlation
    /// ([`super::scale::correlation_lengths`]) sit well inside it, where κ w would exceed 1 —
    /// so over χ²₆ inliers the claim is 1.12 times. A synthetic map with labels of 3 mm /
    /// 0.11° on an offset sensor shows it: the error its neighbourhoods share is 0.1–0.25
    /// mrad per rotation axis, the weights alone claim 0.22–0.26 (scaled: 0.19–0.21), and
    /// queries beside the path fall inside their χ²₆ 95 % region for 98.3 % of 1600 (scaled:
    /// 97.25 % of 400).
    pub(super) fn for_covariances(&self) -> Problem<'a> {
        Problem {
            camera: self.camera,
            labels: self.labels,
            observations: self.observations,
            by_point: self.by_point.clone(),
            options: self.options,
            label_information: self.label_information,
            blocks: self.blocks,
            first: self.first.clone(),
            weight_scale: (self.options.pixel_loss.information_scale(2), self.options.label_loss.information_scale(6)),
        }
    }

    /// Linearizes observation `o` at `state` (None behind the camera).
    pub(super) fn linearize(&self, state: &State, o: &Observation) -> Option<Linearized> {
        let (q, p) = state.frames(o);
        if p.z <= MIN_DEPTH_M {
            return None;
        }
        let sigma = self.options.pixel_sigma_px * o.sigma;
        let r = (self.camera.project_cam(&p) - o.pixel) / sigma;
        let weight = (self.options.pixel_loss.weight(r.norm_squared()) * self.weight_scale.0).min(1.0);
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
    pub(super) fn behind_cost(&self) -> f64 {
        self.options.pixel_loss.cost(1e4)
    }

    pub(super) fn point_block(&self, state: &State, obs: &[usize]) -> PointBlock {
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

    pub(super) fn accumulate(&self, state: &State, obs: &[usize], block: &mut PointBlock) {
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
    pub(super) fn label_prior(&self, state: &State, k: usize) -> (f64, Matrix6<f64>, Vector6<f64>) {
        let e = (self.labels[k].inverse() * state.labels[k]).log();
        let lam = Matrix6::from_diagonal(&self.label_information);
        let s = (e.transpose() * lam * e)[0];
        let w = (self.options.label_loss.weight(s) * self.weight_scale.1).min(1.0);
        let j = se3::right_jacobian_inverse(&e);
        (self.options.label_loss.cost(s), j.transpose() * lam * j * w, j.transpose() * lam * e * w)
    }

    /// The offset prior: (cost, H, g).
    pub(super) fn offset_prior(&self, state: &State) -> (f64, Matrix6<f64>, Vector6<f64>) {
        let e = state.offset.log();
        let lam = Matrix6::from_diagonal(&self.options.offset_sigma.information());
        let j = se3::right_jacobian_inverse(&e);
        ((e.transpose() * lam * e)[0], j.transpose() * lam * j, j.transpose() * lam * e)
    }

    pub(super) fn cost(&self, state: &State) -> f64 {
        let points: f64 = map_slice(&self.by_point, 64, |obs| {
            obs.iter()
                .map(|&i| match state.residual_px(self.camera, &self.observations[i]) {
                    Some(r) => self
                        .options
                        .pixel_loss
                        .cost((r / (self.options.pixel_sigma_px * self.observations[i].sigma)).norm_squared()),
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

    /// A point's couplings W_kj with its observers, and W_Xj with the offset (its block last)
    /// when the offset is estimated.
    fn members(&self, p: &PointBlock) -> Vec<(usize, Matrix6x3)> {
        let mut members = p.couplings.clone();
        if self.options.estimate_offset {
            members.push((self.labels.len(), p.offset));
        }
        members
    }

    /// The normal equations at `state` with the points eliminated and damping λ (on U and V).
    pub(super) fn reduce(&self, state: &State, lambda: f64) -> Reduced {
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
        let v_inv: Vec<Option<Matrix3<f64>>> = points.iter().map(|p| damped_inverse(&p.v, lambda)).collect();
        for (p, v_inv) in points.iter().zip(&v_inv) {
            let Some(v_inv) = *v_inv else { continue };
            let members = self.members(p);
            let y: Vec<Matrix6x3> = members.iter().map(|(_, w)| w * v_inv).collect();
            for (a, (ka, _)) in members.iter().enumerate() {
                let ya = &y[a];
                add_rhs(&mut rhs, *ka, &(ya * -p.g));
                for (kb, wb) in &members[..=a] {
                    *u.block_mut(*ka, *kb) -= ya * wb.transpose();
                }
            }
        }
        Reduced { s: u, rhs, points, v_inv }
    }

    /// Levenberg–Marquardt from `state`: (the minimum, iterations, the start cost).
    pub(super) fn minimize(&self, mut state: State) -> Result<(State, usize, f64)> {
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
            let candidate = self.retract(&state, &delta, &reduced);
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
            return Err(GeolocError::invalid(
                "observations",
                "the adjustment diverged (its cost is not finite; label_sigma and pixel_sigma_px weigh its terms)",
            ));
        }
        Ok((state, iterations, start))
    }

    /// state ⊞ δ: keyframes and the offset from the reduced solution, each point by
    /// back-substitution δ_j = −V_j⁻¹ (g_j + Σ W_kjᵀ δ_k).
    pub(super) fn retract(&self, state: &State, delta: &[f64], reduced: &Reduced) -> State {
        let n = self.labels.len();
        let d = |b: usize| Vector6::from_column_slice(&delta[6 * b..6 * b + 6]);
        let labels = state.labels.iter().enumerate().map(|(k, b)| *b * SE3::exp(&d(k))).collect();
        let offset = if self.options.estimate_offset { state.offset * SE3::exp(&d(n)) } else { state.offset };
        let mut new_points = state.points.clone();
        for (j, (p, v_inv)) in reduced.points.iter().zip(&reduced.v_inv).enumerate() {
            if p.couplings.is_empty() {
                continue;
            }
            let Some(v_inv) = *v_inv else { continue };
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

    /// The marginal covariances at `state` (undamped normal equations of
    /// [`Problem::for_covariances`]).
    pub(super) fn covariances(&self, state: &State) -> Result<Covariances> {
        let n = self.labels.len();
        let reduced = self.for_covariances().reduce(state, 0.0);
        let factor = reduced.s.cholesky().ok_or_else(|| {
            GeolocError::invalid(
                "observations",
                "the adjusted map's normal equations are singular: the observations and the label priors \
                 (label_sigma weighed against pixel_sigma_px; a start far beyond label_sigma from its label \
                 loses its prior's pull) do not fix every keyframe, point and the gauge",
            )
        })?;
        let z = factor.selected_inverse();
        let label_poses = (0..n).map(|k| *z.block(k, k)).collect();
        let label_neighbourhoods = neighbourhood_covariances(&z, &state.labels);
        let (label_offset, offset) = if self.options.estimate_offset {
            ((0..n).map(|k| z.block(n, k).transpose()).collect(), *z.block(n, n))
        } else {
            (vec![Matrix6::zeros(); n], Matrix6::zeros())
        };
        let blocks: Vec<(&PointBlock, &Option<Matrix3<f64>>)> = reduced.points.iter().zip(&reduced.v_inv).collect();
        let points = map_slice(&blocks, 64, |&(p, v_inv)| {
            let Some(v_inv) = *v_inv else { return Matrix3::zeros() };
            if p.couplings.is_empty() {
                return Matrix3::zeros();
            }
            let members = self.members(p);
            let mut m = Matrix3::zeros();
            for (ka, wa) in &members {
                for (kb, wb) in &members {
                    m += wa.transpose() * z.symmetric_block(*ka, *kb) * wb;
                }
            }
            let c = v_inv + v_inv * m * v_inv;
            (c + c.transpose()) * 0.5
        });
        Ok(Covariances { label_poses, label_neighbourhoods, label_offset, offset, points })
    }
}

/// Keyframes on either side of keyframe k in its neighbourhood ([`neighbourhood_covariances`]):
/// eleven skeleton keyframes, ≈ 25 cm of a 7-Scenes path at the skeleton's 2.5 cm spacing —
/// about the stretch of path whose keyframes see the points a frame beside k sees.
pub const NEIGHBOURHOOD_KEYFRAMES: usize = 5;

/// Per keyframe k of the adjusted poses `labels` (B_a, the first blocks of the selected
/// inverse `z`), the covariance of the mean error of its neighbourhood N_k, seen from k:
///
///   ē_k = (1/m) Σ_{a ∈ N_k} Ad_{B_k⁻¹ B_a} ε_a,   Cov(ē_k) = (1/m²) Σ_{a,b ∈ N_k} A_a Z_ab A_bᵀ,
///
/// ε_a the right perturbation of B_a (B_a exp(ε_a) = B_k exp(A_a ε_a) B_k⁻¹B_a, A_a =
/// Ad_{B_k⁻¹ B_a}), N_k = k − h … k + h with the largest h ≤ [`NEIGHBOURHOOD_KEYFRAMES`]
/// whose pairs all lie in the envelope (every cross-covariance Z_ab known; h = 0 leaves the
/// marginal Z_kk).
///
/// What a frame localized beside keyframe k shares of the map's error: it rests on the
/// points its neighbours triangulated, whose common error is their poses' common error —
/// each keyframe's own, independent part averages out over the points and is not shared,
/// the correlated part (the gauge, a slow bend of the trajectory the labels' priors hold)
/// is. The marginal Z_kk counts both (a synthetic map whose keyframes' errors are mostly
/// their own: one keyframe 1.3–1.4 mm off the truth per translation axis, the mean of ten
/// neighbours 0.4–0.8 mm).
pub(super) fn neighbourhood_covariances(z: &BlockEnvelope, labels: &[SE3]) -> Vec<Matrix6<f64>> {
    let n = labels.len();
    (0..n)
        .map(|k| {
            let window = (0..=NEIGHBOURHOOD_KEYFRAMES.min(n - 1))
                .rev()
                .map(|h| (k.saturating_sub(h), (k + h).min(n - 1)))
                .find(|&(lo, hi)| (lo..=hi).all(|i| z.first(i) <= lo))
                .unwrap_or((k, k));
            let members: Vec<(usize, Matrix6<f64>)> =
                (window.0..=window.1).map(|a| (a, (labels[k].inverse() * labels[a]).adjoint())).collect();
            let mut c = Matrix6::zeros();
            for (a, aa) in &members {
                for (b, ab) in &members {
                    c += aa * z.symmetric_block(*a, *b) * ab.transpose();
                }
            }
            let c = c / (members.len() * members.len()) as f64;
            (c + c.transpose()) * 0.5
        })
        .collect()
}

/// (V + λ diag V)⁻¹ of a point block, None when singular.
pub(super) fn damped_inverse(v: &Matrix3<f64>, lambda: f64) -> Option<Matrix3<f64>> {
    let mut d = *v;
    for i in 0..3 {
        d[(i, i)] += lambda * d[(i, i)];
    }
    let inv = d.cholesky()?.inverse();
    inv.iter().all(|x| x.is_finite()).then_some(inv)
}
