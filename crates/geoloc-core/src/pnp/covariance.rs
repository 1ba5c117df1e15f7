//! The covariance of a PnP pose (step 3 of the driver in [`super`]): one of
//! [`CovarianceModel`], in the right-perturbation tangent space of world_from_cam,
//! translation first.
//!
//! * `Paper`: C = σ̂² (Σ wⱼ JⱼᵀJⱼ)⁻¹ with σ̂² = Σ‖rⱼ‖²/(2p − 1) and Huber weights wⱼ — the
//!   paper's formula; it ignores the error of the points and is over-confident.
//! * `Propagated` (default; σ is the query's known pixel noise). Without point
//!   uncertainty: a last least-squares solve on the inliers and C = σ²(ΣJⱼᵀJⱼ)⁻¹.
//!   With independent point covariances Σⱼ: maximum likelihood over the pose and the
//!   point corrections jointly (`joint`), C the pose block of its inverse information.
//!   With keyframe-pose errors shared by the points (D_jk = ∂Xⱼ/∂δ_k, C_k): the same
//!   joint solve over the independent part (the shared errors stay out of the weights:
//!   weights that depend on the label-error realization bias the pose, see `joint`), and
//!   the first-order sandwich covariance
//!   C = H⁻¹ (Σⱼ JⱼᵀWⱼ Sⱼ^ind WⱼJⱼ) H⁻¹ + Σ_k M_k C_k M_kᵀ = H⁻¹ + Σ_k M_k C_k M_kᵀ with
//!   Wⱼ = (Sⱼ^ind)⁻¹, Sⱼ^ind = σ²I + J_X,j Σⱼ^ind J_X,jᵀ the errors independent between
//!   points, H = Σⱼ JⱼᵀWⱼJⱼ and M_k = −H⁻¹ Σⱼ JⱼᵀWⱼ J_X,j D_jk the errors all points share.
//!
//! The propagated covariance is then scaled by max(1, s²), s² = Σⱼ rⱼᵀSⱼ⁻¹rⱼ/(2n − 6) the
//! variance factor of the inliers ([`super::PnpResult::variance_factor`]): it only inflates.

use nalgebra::{Matrix2, Matrix2x3, Matrix3, Matrix6, Vector2, Vector3};

use super::{Correspondences, PixelNoise, PointUncertainty};
use crate::camera::{Camera, j_uv_point, j_uv_pose, project};
use crate::error::{GeolocError, Result};
use crate::lie::SE3;
use crate::optim::RobustLoss;
use crate::optim::covariance::inverse_information;

/// How the returned covariance is computed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CovarianceModel {
    /// Point errors (and keyframe-pose errors) propagated; calibrated. The default.
    Propagated,
    /// The paper's σ̂²(ΣJᵀJ)⁻¹ with σ̂² = ‖r‖²/(2p − 1); for comparison.
    Paper,
}

impl CovarianceModel {
    /// The option string: "propagated" or "paper".
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Propagated => "propagated",
            Self::Paper => "paper",
        }
    }
}

impl std::str::FromStr for CovarianceModel {
    type Err = GeolocError;

    /// Parses [`CovarianceModel::as_str`]; the error names the argument "covariance".
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "propagated" => Ok(Self::Propagated),
            "paper" => Ok(Self::Paper),
            other => {
                Err(GeolocError::invalid("covariance", format!("expected \"propagated\" or \"paper\", got {other:?}")))
            }
        }
    }
}

impl Correspondences<'_> {
    /// s² = Σⱼ rⱼᵀSⱼ⁻¹rⱼ / (2n − 6) over the inliers at `pose`, rⱼ = π(T, Xⱼ) − bⱼ − zⱼ and
    /// Sⱼ = σ²I + J_X,j Σⱼ J_X,jᵀ the predicted residual covariance with the points' marginal
    /// uncertainty (σ²I for exact points). Under the model E[Σ rᵀS⁻¹r] = 2n − 6 (the pose
    /// absorbs 6 of the 2n dimensions), so s² estimates how much larger the real noise is;
    /// NaN for n ≤ 3.
    pub(super) fn variance_factor(&self, pose: &SE3, subset: &[usize]) -> f64 {
        let dof = 2.0 * subset.len() as f64 - 6.0;
        if dof <= 0.0 {
            return f64::NAN;
        }
        let sigma = self.options.pixel_sigma;
        if self.uncertainty.is_none() && self.noise.scales.is_none() {
            // exact points: S = σ²I and no bias, one projection per inlier
            let sum_sq: f64 = subset
                .iter()
                .map(|&j| (project(self.camera, pose, &self.points[j]).uv - self.pixels[j]).norm_squared())
                .sum();
            return sum_sq / (sigma * sigma) / dof;
        }
        let chi2: f64 = subset
            .iter()
            .map(|&j| {
                let sigma = self.noise.at(j);
                let (s, bias) = residual_moments(self.camera, self.points, pose, j, self.uncertainty, sigma, true);
                let r = project(self.camera, pose, &self.points[j]).uv - bias - self.pixels[j];
                s.try_inverse().map_or(r.norm_squared() / (sigma * sigma), |s_inv| r.dot(&(s_inv * r)))
            })
            .sum();
        chi2 / dof
    }
}

/// Point j's covariance: the independent part, plus (if `marginal`) the shared
/// keyframe-pose part Σ_k D_jk C_k D_jkᵀ. None without uncertainty.
pub(super) fn point_covariance(
    j: usize,
    uncertainty: Option<&PointUncertainty<'_>>,
    marginal: bool,
) -> Option<Matrix3<f64>> {
    let u = uncertainty?;
    let mut cov = u.covariances[j];
    if marginal && let Some(shared) = &u.shared {
        for (k, d) in &shared.jacobians[j] {
            cov += d * shared.pose_covariances[*k] * d.transpose();
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
pub(super) fn residual_moments(
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

pub(super) fn paper_covariance(
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

/// The `Propagated` covariance of the module doc at `pose` over the inliers `subset` and its
/// pixel-noise part (both before the variance factor), from one pass over the points.
///
/// The pixel part is the covariance the query's own pixel noise alone gives the pose of the
/// weighted solve, the sandwich
///
///   C_pix = H⁻¹ (Σⱼ JⱼᵀWⱼ σⱼ² Wⱼ Jⱼ) H⁻¹,   H = Σⱼ JⱼᵀWⱼJⱼ,  Wⱼ = (Sⱼ^ind)⁻¹,
///
/// the weights those of the solve ([`residual_moments`]). It is the part of the pose's
/// error that is independent from one frame to the next: the map points' and the keyframe
/// poses' errors are shared by consecutive frames that see the same points, the pixel
/// noise of two images is not. Without point uncertainty C_pix = H⁻¹.
pub(super) fn propagated_covariance(
    camera: &Camera,
    points: &[Vector3<f64>],
    pose: &SE3,
    subset: &[usize],
    uncertainty: Option<&PointUncertainty<'_>>,
    noise: PixelNoise<'_>,
) -> Option<PropagatedCovariance> {
    let (mut h, mut meat) = (Matrix6::zeros(), Matrix6::zeros());
    // JⱼᵀWⱼ J_X,j per point, needed for the shared part
    let mut couplings: Vec<(usize, nalgebra::Matrix6x3<f64>)> = Vec::new();
    for &j in subset {
        let p = project(camera, pose, &points[j]);
        // Wⱼ = (Sⱼ^ind)⁻¹, the weights of the solve (the shared errors are not in them)
        let sigma = noise.at(j);
        let (s_ind, _) = residual_moments(camera, points, pose, j, uncertainty, sigma, false);
        let w = s_ind.try_inverse()?;
        let jac = j_uv_pose(camera, &p);
        let jt_w = jac.transpose() * w;
        h += jt_w * jac;
        meat += jt_w * jt_w.transpose() * (sigma * sigma);
        if uncertainty.is_some_and(|u| u.shared.is_some()) {
            let j_x: Matrix2x3<f64> = j_uv_point(camera, pose, &p);
            couplings.push((j, jt_w * j_x));
        }
    }
    // the independent errors: H⁻¹ (Σ JᵀW Sⁱⁿᵈ W J) H⁻¹ = H⁻¹ since W = (Sⁱⁿᵈ)⁻¹
    let h_inv = inverse_information(&h)?;
    let mut c = h_inv;
    if let Some(shared) = uncertainty.and_then(|u| u.shared.as_ref()) {
        // M_k = −H⁻¹ Σⱼ JⱼᵀWⱼ J_X,j D_jk over the points j that have a D_jk (in subset
        // order for every k, as a sum over all points would take them)
        let mut sums = vec![Matrix6::zeros(); shared.pose_covariances.len()];
        for (j, coupling) in &couplings {
            for (k, d) in &shared.jacobians[*j] {
                sums[*k] -= coupling * d;
            }
        }
        for (sum, c_k) in sums.iter().zip(shared.pose_covariances) {
            let m = h_inv * sum;
            c += m * c_k * m.transpose();
        }
    }
    let pixel = h_inv * meat * h_inv;
    Some(PropagatedCovariance { full: 0.5 * (c + c.transpose()), pixel: 0.5 * (pixel + pixel.transpose()) })
}

/// [`propagated_covariance`]'s result.
pub(super) struct PropagatedCovariance {
    /// C of the module doc: the pixel noise, the points' independent errors and the shared part.
    pub(super) full: Matrix6<f64>,
    /// C_pix: the pixel noise alone.
    pub(super) pixel: Matrix6<f64>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pnp::{PnpOptions, solve_pnp};
    use crate::testing::SplitMix64;

    /// Monte-Carlo: the variance factor s² estimates (σ_true/σ)² — ≈ 1 when the model is
    /// right (exact points, and uncertain points with their true covariances), ≈ 4 when the
    /// pixel noise is twice what PnP is told; the inflated covariance then covers the truth at
    /// the χ²₆ 95 % level, and a right model is not shrunk below itself.
    #[test]
    fn variance_factor_estimates_the_noise_ratio() {
        let camera = Camera::new(525.0, 525.0, 320.0, 240.0).expect("valid");
        let options = PnpOptions { max_residual_px: 20.0, ..PnpOptions::default() };
        let cases: [(f64, f64, f64); 3] = [(1.0, 0.0, 1.0), (2.0, 0.0, 4.0), (1.0, 0.01, 1.0)];
        for (sigma_true, point_sigma, want) in cases {
            let mut rng = SplitMix64::new(11);
            let (trials, mut sum, mut inside) = (300, 0.0, 0);
            for _ in 0..trials {
                let truth = rng.pose(2.0);
                let local = |rng: &mut SplitMix64| {
                    Vector3::new(rng.uniform_in(-2.0, 2.0), rng.uniform_in(-1.5, 1.5), rng.uniform_in(3.0, 8.0))
                };
                let exact: Vec<Vector3<f64>> = (0..60).map(|_| truth * local(&mut rng)).collect();
                let pixels: Vec<Vector2<f64>> = exact
                    .iter()
                    .map(|x| project(&camera, &truth, x).uv + Vector2::new(rng.normal(), rng.normal()) * sigma_true)
                    .collect();
                let noisy: Vec<Vector3<f64>> = exact
                    .iter()
                    .map(|x| x + Vector3::new(rng.normal(), rng.normal(), rng.normal()) * point_sigma)
                    .collect();
                let covs = vec![Matrix3::identity() * point_sigma * point_sigma; exact.len()];
                let u = PointUncertainty { covariances: &covs, shared: None };
                let unc = (point_sigma > 0.0).then_some(&u);
                let res = solve_pnp(&camera, &noisy, &pixels, Some(&truth), unc, &options).expect("valid input");
                assert!(res.success, "{}", res.reason);
                sum += res.variance_factor;
                let e = (truth.inverse() * res.world_from_cam).log();
                let info = res.covariance.try_inverse().expect("invertible");
                inside += usize::from((e.transpose() * info * e)[0] <= crate::stats::chi2::CHI2_6_95);
            }
            let mean = sum / trials as f64;
            // the mean of 300 factors with 114 degrees of freedom: σ ≈ want·0.0076
            assert!((mean - want).abs() < 0.04 * want, "σ_true {sigma_true}, σ_X {point_sigma}: mean s² {mean}");
            let coverage = inside as f64 / trials as f64;
            assert!((0.92..=0.985).contains(&coverage), "σ_true {sigma_true}, σ_X {point_sigma}: coverage {coverage}");
        }
    }

    /// Monte-Carlo: with the map points' errors held at one realization (as consecutive frames
    /// share them) and only the pixel noise drawn anew, the poses scatter about the noise-free
    /// pixels' pose as `pixel_covariance` says (mean NEES ≈ 6), while the full covariance,
    /// which also holds the points' errors, is larger; without point uncertainty the two are
    /// one matrix.
    #[test]
    fn pixel_covariance_is_the_scatter_from_the_pixel_noise_alone() {
        let camera = Camera::new(525.0, 525.0, 320.0, 240.0).expect("valid");
        let options = PnpOptions { max_residual_px: 20.0, ..PnpOptions::default() };
        let mut rng = SplitMix64::new(5);
        let truth = rng.pose(2.0);
        let exact: Vec<Vector3<f64>> = (0..80)
            .map(|_| {
                truth * Vector3::new(rng.uniform_in(-2.0, 2.0), rng.uniform_in(-1.5, 1.5), rng.uniform_in(3.0, 8.0))
            })
            .collect();
        let point_sigma = 0.02;
        let noisy: Vec<Vector3<f64>> =
            exact.iter().map(|x| x + Vector3::new(rng.normal(), rng.normal(), rng.normal()) * point_sigma).collect();
        let covs = vec![Matrix3::identity() * point_sigma * point_sigma; exact.len()];
        let u = PointUncertainty { covariances: &covs, shared: None };
        let clean: Vec<Vector2<f64>> = exact.iter().map(|x| project(&camera, &truth, x).uv).collect();
        let centre = solve_pnp(&camera, &noisy, &clean, Some(&truth), Some(&u), &options).expect("valid input");
        let trials = 400;
        let (mut nees_pixel, mut nees_full) = (0.0, 0.0);
        for _ in 0..trials {
            let pixels: Vec<Vector2<f64>> =
                clean.iter().map(|p| p + Vector2::new(rng.normal(), rng.normal())).collect();
            let res = solve_pnp(&camera, &noisy, &pixels, Some(&truth), Some(&u), &options).expect("valid input");
            assert!(res.success, "{}", res.reason);
            let e = (centre.world_from_cam.inverse() * res.world_from_cam).log();
            nees_pixel += (e.transpose() * res.pixel_covariance.try_inverse().expect("invertible") * e)[0];
            nees_full += (e.transpose() * res.covariance.try_inverse().expect("invertible") * e)[0];
        }
        let (nees_pixel, nees_full) = (nees_pixel / trials as f64, nees_full / trials as f64);
        // the mean of 400 χ²₆: σ ≈ 0.17; the variance factor (≥ 1) can only lower it
        assert!((5.2..=6.6).contains(&nees_pixel), "mean NEES under the pixel covariance {nees_pixel}");
        assert!(nees_full < 0.5 * nees_pixel, "the full covariance holds the points' errors too: {nees_full}");
        let exact_result = solve_pnp(&camera, &exact, &clean, Some(&truth), None, &options).expect("valid input");
        assert_eq!(exact_result.pixel_covariance, exact_result.covariance);
    }
}
