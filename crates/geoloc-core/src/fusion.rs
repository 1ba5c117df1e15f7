//! Fusing the geometric pose with the motion prediction (the paper's Eq. fusion).
//!
//! T_F minimizes the two Mahalanobis terms of right-perturbation residuals
//!
//!   f(T) = e_Mᵀ C_M⁻¹ e_M + e_Gᵀ C_G⁻¹ e_G,   e_X = log(T_X⁻¹ T)^∨,
//!
//! by Gauss–Newton with ∂e_X/∂δ = J_r⁻¹(e_X) for T ⊞ δ = T exp(δ^); C_F = H⁻¹ with
//! H = Σ J_r⁻ᵀ C⁻¹ J_r⁻¹ at the optimum. Before that T_G is gated against T_M: with the
//! paper's rule it is a failure when its position or its rotation lies outside `gate_sigma`
//! isometric σ (σ_p = mean √diag C_ρ, σ_r = Θ(exp √diag C_φ)) of the difference of the two,
//! whose covariance is C = C_M + C_G; with the
//! χ² rule when e = log(T_M⁻¹T_G) has eᵀ(C_M + C_G)⁻¹e above the χ²₆ quantile of the same
//! two-sided probability. A failed T_G leaves T_F = T_M, C_F = C_M.

use nalgebra::{Matrix6, Vector6};

use crate::error::{GeolocError, Result};
use crate::lie::{SE3, se3};
use crate::optim::covariance::{check_covariance, isometric_sigmas, spd_inverse};
use crate::optim::{LeastSquares, LmOptions, PoseEstimate, solve};
pub use crate::stats::chi2::chi2_6_quantile_for_sigma;

/// Which gate decides that the geometric pose is a failure.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Gate {
    /// The paper's: position or rotation beyond `gate_sigma` isometric σ of T_M.
    Isometric,
    /// A 6-DoF Mahalanobis test on log(T_M⁻¹T_G) with C_M + C_G.
    ChiSquared,
}

impl Gate {
    /// The option string: "isometric" or "chi2".
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Isometric => "isometric",
            Self::ChiSquared => "chi2",
        }
    }
}

impl std::str::FromStr for Gate {
    type Err = GeolocError;

    /// Parses [`Gate::as_str`]; the error names the argument "gate".
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "isometric" => Ok(Self::Isometric),
            "chi2" => Ok(Self::ChiSquared),
            other => Err(GeolocError::invalid("gate", format!("expected \"isometric\" or \"chi2\", got {other:?}"))),
        }
    }
}

/// Where the fused pose came from.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FusionSource {
    /// Both poses, fused.
    Fused,
    /// The geometric pose failed the gate: the motion prediction alone.
    Motion,
}

impl FusionSource {
    /// "fused" or "motion".
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Fused => "fused",
            Self::Motion => "motion",
        }
    }
}

/// The fused pose T_F, C_F (right perturbation, translation first), the Gauss–Newton report
/// (None when the gate rejected T_G) and the source.
pub type Fusion = PoseEstimate<FusionSource>;

const MAX_ITERATIONS: usize = 20;
const STEP_TOLERANCE: f64 = 1e-13;

/// Gates and fuses; see the module doc.
///
/// # Errors
/// Covariances that are not symmetric positive definite (named), or a non-positive gate.
pub fn fuse(
    pose_m: &SE3,
    cov_m: &Matrix6<f64>,
    pose_g: &SE3,
    cov_g: &Matrix6<f64>,
    gate_sigma: f64,
    gate: Gate,
) -> Result<Fusion> {
    fuse_gated_with(pose_m, cov_m, pose_g, cov_g, &Matrix6::zeros(), gate_sigma, gate)
}

/// [`fuse`] whose gate also allows for an error `gate_extra` that T_G and T_M do not share
/// but the fusion must not weight by: the gate tests T_G − T_M against C_M + C_G + C_extra,
/// the fusion weights by C_M and C_G alone. The localizer passes the map-frame covariance
/// C_map here: the motion history was measured against other keyframe groups than T_G, and
/// the groups' label errors differ by up to C_map (the group-level error), while the
/// fusion, on the measurement parts, must not count C_map at all (it is added once, to
/// the output).
///
/// # Errors
/// As [`fuse`]; `gate_extra` not symmetric positive semi-definite (named "gate_extra").
pub fn fuse_gated_with(
    pose_m: &SE3,
    cov_m: &Matrix6<f64>,
    pose_g: &SE3,
    cov_g: &Matrix6<f64>,
    gate_extra: &Matrix6<f64>,
    gate_sigma: f64,
    gate: Gate,
) -> Result<Fusion> {
    if !(gate_sigma.is_finite() && gate_sigma > 0.0) {
        return Err(GeolocError::invalid("gate_sigma", format!("must be finite and > 0, got {gate_sigma}")));
    }
    check_covariance("cov_m", cov_m)?;
    check_covariance("cov_g", cov_g)?;
    let info_m = spd_inverse(cov_m, "cov_m")?;
    let info_g = spd_inverse(cov_g, "cov_g")?;
    check_covariance("gate_extra", gate_extra)?;
    if gate_rejects(pose_m, cov_m, pose_g, &(cov_g + gate_extra), gate_sigma, gate)? {
        return Ok(Fusion { world_from_cam: *pose_m, covariance: *cov_m, report: None, details: FusionSource::Motion });
    }
    // start at the information-weighted average in the tangent space of T_M
    let e = (pose_m.inverse() * *pose_g).log();
    let start = (info_m + info_g).try_inverse().map_or(*pose_m, |c| *pose_m * SE3::exp(&(c * info_g * e)));
    let problem = FusionProblem { anchors: vec![(*pose_m, info_m), (*pose_g, info_g)] };
    let (pose, report, at_optimum) = solve(&problem, start, &LmOptions::gauss_newton(MAX_ITERATIONS, STEP_TOLERANCE));
    // C_F = H⁻¹ at the optimum (H of the start when the loop could not move)
    let h = at_optimum.linearization.map_or(info_m + info_g, |l| l.h);
    let covariance = spd_inverse(&h, "information")?;
    Ok(Fusion {
        world_from_cam: pose,
        covariance: 0.5 * (covariance + covariance.transpose()),
        report: Some(report),
        details: FusionSource::Fused,
    })
}

/// Whether the gate rejects T_G (see the module doc).
fn gate_rejects(
    pose_m: &SE3,
    cov_m: &Matrix6<f64>,
    pose_g: &SE3,
    cov_g: &Matrix6<f64>,
    gate_sigma: f64,
    gate: Gate,
) -> Result<bool> {
    Ok(match gate {
        Gate::Isometric => {
            // the spread of T_G − T_M is C_M + C_G: a geometric pose far more certain than
            // the prediction is not rejected for the prediction's own uncertainty alone
            let (sigma_p, sigma_r) = isometric_sigmas(&(cov_m + cov_g));
            let position = (pose_g.translation - pose_m.translation).norm();
            let rotation = pose_m.rotation.distance(&pose_g.rotation);
            position > gate_sigma * sigma_p || rotation > gate_sigma * sigma_r
        }
        Gate::ChiSquared => {
            let e = (pose_m.inverse() * *pose_g).log();
            let s = spd_inverse(&(cov_m + cov_g), "cov_m + cov_g")?;
            e.dot(&(s * e)) > chi2_6_quantile_for_sigma(gate_sigma)
        }
    })
}

/// The pose T minimizing Σ_i e_iᵀ C_i⁻¹ e_i, e_i = log(T_i⁻¹ T)^∨ (right perturbation,
/// translation first), over `members` (T_i, C_i) — the information-weighted mean of poses
/// measured of one thing, by the Gauss–Newton of [`fuse`] from the first member's pose
/// (exactly its fusion for two members). Members in a fixed order give the same bits.
///
/// # Errors
/// No member, or a covariance that is not symmetric positive definite (named "members").
pub fn weighted_mean(members: &[(SE3, Matrix6<f64>)]) -> Result<SE3> {
    let Some((first, _)) = members.first() else {
        return Err(GeolocError::invalid("members", "no pose to average"));
    };
    let anchors = members
        .iter()
        .map(|(pose, covariance)| {
            check_covariance("members", covariance)?;
            Ok((*pose, spd_inverse(covariance, "members")?))
        })
        .collect::<Result<Vec<_>>>()?;
    let (pose, _, _) =
        solve(&FusionProblem { anchors }, *first, &LmOptions::gauss_newton(MAX_ITERATIONS, STEP_TOLERANCE));
    Ok(pose)
}

/// f(T) = Σ_i e_iᵀ C_i⁻¹ e_i with e_i = log(T_i⁻¹ T)^∨ and ∂e_i/∂δ = J_r⁻¹(e_i), over the
/// anchors (T_i, C_i⁻¹): T_M and T_G in the fusion.
struct FusionProblem {
    anchors: Vec<(SE3, Matrix6<f64>)>,
}

impl LeastSquares<6> for FusionProblem {
    type State = SE3;

    fn normal_equations(&self, pose: &SE3) -> (Matrix6<f64>, Vector6<f64>, f64) {
        let mut h = Matrix6::zeros();
        let mut g = Vector6::zeros();
        let mut cost = 0.0;
        for (anchor, info) in &self.anchors {
            let e = (anchor.inverse() * *pose).log();
            let j = se3::right_jacobian_inverse(&e);
            h += j.transpose() * info * j;
            g += j.transpose() * (info * e);
            cost += e.dot(&(info * e));
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
    use crate::lie::Twist;
    use crate::testing::SplitMix64;

    fn cost(pose: &SE3, pm: &SE3, im: &Matrix6<f64>, pg: &SE3, ig: &Matrix6<f64>) -> f64 {
        let em = (pm.inverse() * *pose).log();
        let eg = (pg.inverse() * *pose).log();
        em.dot(&(im * em)) + eg.dot(&(ig * eg))
    }

    fn random_spd(rng: &mut SplitMix64, scale: f64) -> Matrix6<f64> {
        let a = Matrix6::from_fn(|_, _| rng.normal());
        (a * a.transpose() + Matrix6::identity()) * scale
    }

    /// The weighted mean of two poses is their fusion; of poses that differ by translations
    /// only (one rotation R, covariances block-diagonal with translation blocks W_i⁻¹) it is
    /// the closed form t = (Σ R W_i Rᵀ)⁻¹ Σ R W_i Rᵀ t_i (rotations held stiff, so J_r⁻¹ does
    /// not couple them in), whatever the members' order (to
    /// rounding); no member or a covariance that is not positive definite is an error naming
    /// "members".
    #[test]
    fn the_weighted_mean_is_the_fusion_and_the_closed_form_for_translations() {
        let mut rng = SplitMix64::new(4);
        for _ in 0..5 {
            let pm = rng.pose(3.0);
            let pg = pm * SE3::exp(&rng.twist(0.05, 0.05));
            let (cm, cg) = (random_spd(&mut rng, 1e-3), random_spd(&mut rng, 1e-3));
            let fused = fuse(&pm, &cm, &pg, &cg, 1e9, Gate::Isometric).expect("valid").world_from_cam;
            let mean = weighted_mean(&[(pm, cm), (pg, cg)]).expect("valid");
            assert!((fused.inverse() * mean).log().norm() < 1e-10);
        }
        let rotation = rng.pose(1.0).rotation;
        let r = rotation.matrix();
        let mut members = Vec::new();
        let (mut a, mut b) = (nalgebra::Matrix3::zeros(), nalgebra::Vector3::zeros());
        for _ in 0..4 {
            let t = nalgebra::Vector3::new(rng.normal(), rng.normal(), rng.normal()) * 0.05;
            let block = {
                let m = nalgebra::Matrix3::from_fn(|_, _| rng.normal());
                m * m.transpose() * 1e-4 + nalgebra::Matrix3::identity() * 1e-5
            };
            let mut c = Matrix6::identity() * 1e-14; // rotation held: its coupling to the translation (J_r⁻¹) vanishes
            c.fixed_view_mut::<3, 3>(0, 0).copy_from(&block);
            let w = r * block.try_inverse().expect("spd") * r.transpose();
            a += w;
            b += w * t;
            members.push((SE3::new(rotation, t), c));
        }
        let want = a.try_inverse().expect("spd") * b;
        let got = weighted_mean(&members).expect("valid");
        assert!((got.translation - want).norm() < 1e-10, "{} vs {want}", got.translation);
        assert!(got.rotation.distance(&rotation) < 1e-10);
        members.reverse();
        let again = weighted_mean(&members).expect("valid");
        assert!((again.inverse() * got).log().norm() < 1e-12);
        assert!(weighted_mean(&[]).expect_err("empty").to_string().contains("members"));
        let flat = (SE3::identity(), Matrix6::zeros());
        assert!(weighted_mean(&[members[0], flat]).expect_err("singular").to_string().contains("members"));
    }

    /// Against an independent minimizer: coordinate-free gradient descent with numerical
    /// gradients of f on the manifold, then the numerical Hessian for the covariance.
    #[test]
    fn matches_an_independent_minimizer() {
        let mut rng = SplitMix64::new(1);
        for _ in 0..10 {
            let pm = rng.pose(3.0);
            let pg = pm * SE3::exp(&rng.twist(0.05, 0.05));
            let (cm, cg) = (random_spd(&mut rng, 1e-3), random_spd(&mut rng, 1e-3));
            let (im, ig) = (cm.try_inverse().expect("spd"), cg.try_inverse().expect("spd"));
            let fused = fuse(&pm, &cm, &pg, &cg, 1e9, Gate::Isometric).expect("valid");
            assert_eq!(fused.details, FusionSource::Fused);
            // Newton with a numerical gradient and Hessian of f (no Jacobian formulas)
            let h = 1e-5;
            let f = |x: &SE3, d: &Vector6<f64>| cost(&(*x * SE3::exp(d)), &pm, &im, &pg, &ig);
            let mut x = pm;
            let mut hess = Matrix6::zeros();
            for _ in 0..30 {
                let mut grad = Vector6::zeros();
                for i in 0..6 {
                    let mut d = Vector6::zeros();
                    d[i] = h;
                    grad[i] = (f(&x, &d) - f(&x, &-d)) / (2.0 * h);
                    for k in 0..6 {
                        let mut dk = Vector6::zeros();
                        dk[k] = h;
                        hess[(i, k)] = (f(&x, &(d + dk)) - f(&x, &(d - dk)) - f(&x, &(dk - d)) + f(&x, &(-d - dk)))
                            / (4.0 * h * h);
                    }
                }
                let step = -(hess.try_inverse().expect("spd") * grad);
                x = x * SE3::exp(&step);
                if step.norm() < 1e-12 {
                    break;
                }
            }
            assert!((x.inverse() * fused.world_from_cam).log().norm() < 1e-7);
            // C_F = (Σ JᵀC⁻¹J)⁻¹ with the residual Jacobians J taken by central differences
            // (the exact Hessian of f also holds residual-curvature terms, zero in expectation)
            let jac = |anchor: &SE3| {
                let mut j = Matrix6::zeros();
                for i in 0..6 {
                    let mut d = Vector6::zeros();
                    d[i] = h;
                    let plus = (anchor.inverse() * x * SE3::exp(&d)).log();
                    let minus = (anchor.inverse() * x * SE3::exp(&-d)).log();
                    j.set_column(i, &((plus - minus) / (2.0 * h)));
                }
                j
            };
            let (jm, jg) = (jac(&pm), jac(&pg));
            let numeric_cov = (jm.transpose() * im * jm + jg.transpose() * ig * jg).try_inverse().expect("spd");
            let rel = (numeric_cov - fused.covariance).abs().max() / fused.covariance.abs().max();
            assert!(rel < 1e-4, "covariance relative error {rel}");
        }
    }

    #[test]
    fn ten_sigma_geometric_pose_is_gated() {
        let pm = SE3::identity();
        let cm = Matrix6::identity() * 1e-4; // σ = 1 cm, 0.01 rad
        let pg = SE3::exp(&Twist::new(0.1, 0.0, 0.0, 0.0, 0.0, 0.0)); // 10σ in position
        for gate in [Gate::Isometric, Gate::ChiSquared] {
            let f = fuse(&pm, &cm, &pg, &cm, 3.0, gate).expect("valid");
            assert_eq!(f.details, FusionSource::Motion);
            assert!(f.report.is_none());
            assert_eq!(f.world_from_cam, pm);
            assert_eq!(f.covariance, cm);
        }
        let near = SE3::exp(&Twist::new(0.01, 0.0, 0.0, 0.0, 0.0, 0.0)); // 1σ
        let f = fuse(&pm, &cm, &near, &cm, 3.0, Gate::Isometric).expect("valid");
        assert_eq!(f.details, FusionSource::Fused);
        assert!(f.report.is_some_and(|r| r.converged()));
        // equal covariances: the midpoint, with half the covariance
        assert!((f.world_from_cam.translation.x - 0.005).abs() < 1e-9);
        assert!((f.covariance - cm * 0.5).abs().max() < 1e-9);
    }

    /// The gate's extra covariance widens the gate only: a 10σ pose that `fuse` rejects is
    /// accepted with C_extra = 100·C (the gate's σ is then √102 cm ≈ 10.1 cm: 0.1 m is inside
    /// 3σ), and the fused pose and covariance
    /// are those of the two covariances alone (`fuse` with an open gate; the midpoint);
    /// zero extra is `fuse`.
    #[test]
    fn gate_extra_widens_the_gate_not_the_weights() {
        let pm = SE3::identity();
        let cm = Matrix6::identity() * 1e-4;
        let pg = SE3::exp(&Twist::new(0.1, 0.0, 0.0, 0.0, 0.0, 0.0));
        for gate in [Gate::Isometric, Gate::ChiSquared] {
            let plain = fuse(&pm, &cm, &pg, &cm, 3.0, gate).expect("valid");
            let zero = fuse_gated_with(&pm, &cm, &pg, &cm, &Matrix6::zeros(), 3.0, gate).expect("valid");
            assert_eq!(plain, zero);
            let wide = fuse_gated_with(&pm, &cm, &pg, &cm, &(cm * 100.0), 3.0, gate).expect("valid");
            assert_eq!(wide.details, FusionSource::Fused, "{gate:?}");
            let open = fuse(&pm, &cm, &pg, &cm, 1e6, gate).expect("valid");
            assert_eq!(open.details, FusionSource::Fused);
            assert_eq!((wide.world_from_cam, wide.covariance), (open.world_from_cam, open.covariance));
            assert!((wide.world_from_cam.translation.x - 0.05).abs() < 1e-9, "{:?}", wide.world_from_cam.translation);
        }
        let bad = Matrix6::identity() * -1.0;
        let err = fuse_gated_with(&pm, &cm, &pg, &cm, &bad, 3.0, Gate::Isometric).expect_err("negative");
        assert!(err.to_string().contains("gate_extra"), "{err}");
    }

    #[test]
    fn option_strings_round_trip() {
        for gate in [Gate::Isometric, Gate::ChiSquared] {
            assert_eq!(gate.as_str().parse::<Gate>(), Ok(gate));
        }
        assert!(matches!("χ²".parse::<Gate>(), Err(GeolocError::InvalidInput { name, .. }) if name == "gate"));
    }

    #[test]
    fn bad_covariances_are_named() {
        let p = SE3::identity();
        let bad = Matrix6::zeros();
        let good = Matrix6::identity();
        assert!(
            matches!(fuse(&p, &bad, &p, &good, 3.0, Gate::Isometric), Err(GeolocError::InvalidInput { name, .. }) if name == "cov_m")
        );
        let mut asym = Matrix6::identity();
        asym[(0, 1)] = 0.5;
        assert!(
            matches!(fuse(&p, &good, &p, &asym, 3.0, Gate::Isometric), Err(GeolocError::InvalidInput { name, .. }) if name == "cov_g")
        );
        assert!(fuse(&p, &good, &p, &good, 0.0, Gate::Isometric).is_err());
        // A negative covariance is refused, not fused
        let negative = -Matrix6::identity();
        assert!(
            matches!(fuse(&p, &good, &p, &negative, 3.0, Gate::Isometric), Err(GeolocError::InvalidInput { name, .. }) if name == "cov_g")
        );
    }
}
