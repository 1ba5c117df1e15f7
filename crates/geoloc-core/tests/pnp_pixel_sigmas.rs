//! Backward intersection with a pixel noise of its own per correspondence
//! (`solve_pnp_with_pixel_sigmas`, σⱼ = pixel_sigma × pixel_sigmas[j]): the same solve as the
//! uniform one when every σⱼ is equal, the covariance against the weighted Gauss–Newton
//! closed form built from central differences, Monte-Carlo calibration and efficiency under
//! heteroscedastic noise (as from keypoints on different pyramid levels), and bad input.

mod common;

use common::{Coverage, FD_STEP, Sample, central_difference, look_at, observe, relative_error};
use geoloc_core::camera::{Camera, project};
use geoloc_core::lie::SE3;
use geoloc_core::pnp::{PnpOptions, PnpResult, PointUncertainty, solve_pnp, solve_pnp_with_pixel_sigmas};
use geoloc_core::testing::SplitMix64;
use nalgebra::{Matrix3, Matrix6, SMatrix, Vector2, Vector3, Vector6};

/// ORB's pyramid scales 1.2^L, L = 0 … 7: the σ of keypoints found on each level.
const LEVEL_SIGMAS: [f64; 8] = [1.0, 1.2, 1.44, 1.728, 2.0736, 2.48832, 2.985984, 3.5831808];

fn camera() -> Camera {
    Camera::new(525.0, 525.0, 320.0, 240.0).expect("valid")
}

/// A camera 5 m from a cloud of `n` points (all in front of it and inside the image), each
/// with a σ drawn from [`LEVEL_SIGMAS`].
fn scene(rng: &mut SplitMix64, n: usize) -> (SE3, Vec<Vector3<f64>>, Vec<f64>) {
    let target = Vector3::new(rng.uniform_in(-0.5, 0.5), rng.uniform_in(-0.5, 0.5), 5.0);
    let centre = Vector3::new(rng.uniform_in(-1.0, 1.0), rng.uniform_in(-0.3, 0.3), rng.uniform_in(-0.3, 0.3));
    let truth = look_at(&centre, &target);
    let cam = camera();
    let mut points = Vec::with_capacity(n);
    while points.len() < n {
        let x = target + Vector3::new(rng.uniform_in(-2.0, 2.0), rng.uniform_in(-1.5, 1.5), rng.uniform_in(-1.0, 1.0));
        let p = project(&cam, &truth, &x);
        if p.p_cam.z > 0.5 && (20.0..620.0).contains(&p.uv.x) && (20.0..460.0).contains(&p.uv.y) {
            points.push(x);
        }
    }
    let sigmas = (0..n).map(|_| LEVEL_SIGMAS[(rng.uniform_in(0.0, 8.0) as usize).min(7)]).collect();
    (truth, points, sigmas)
}

fn noisy_pixels(rng: &mut SplitMix64, truth: &SE3, points: &[Vector3<f64>], sigmas: &[f64]) -> Vec<Vector2<f64>> {
    let cam = camera();
    points.iter().zip(sigmas).map(|(x, &s)| observe(rng, &cam, truth, x, s)).collect()
}

fn pose_error(est: &SE3, truth: &SE3) -> Vector6<f64> {
    (truth.inverse() * *est).log()
}

#[test]
fn equal_pixel_sigmas_are_the_uniform_solve() {
    let mut rng = SplitMix64::new(31);
    let cam = camera();
    for trial in 0..20 {
        let (truth, points, _) = scene(&mut rng, 80);
        let ones = vec![1.0; points.len()];
        let pixels = noisy_pixels(&mut rng, &truth, &points, &ones);
        let covs = vec![Matrix3::identity() * 4e-4; points.len()];
        let unc = PointUncertainty { covariances: &covs, shared: None };
        for uncertainty in [None, Some(&unc)] {
            // σⱼ = 0.5 × 3 everywhere is the uniform solve with σ = 1.5
            let scaled = PnpOptions { pixel_sigma: 0.5, ..Default::default() };
            let threes = vec![3.0; points.len()];
            let a = solve_pnp_with_pixel_sigmas(&cam, &points, &pixels, Some(&threes), None, uncertainty, &scaled)
                .expect("valid");
            let uniform = PnpOptions { pixel_sigma: 1.5, ..Default::default() };
            let b = solve_pnp(&cam, &points, &pixels, None, uncertainty, &uniform).expect("valid");
            assert!(a.success && b.success, "trial {trial}: {} / {}", a.reason, b.reason);
            assert_eq!(a.inliers, b.inliers, "trial {trial}");
            assert!(pose_error(&a.world_from_cam, &b.world_from_cam).norm() < 1e-9, "trial {trial}");
            assert!(relative_error(&(a.covariance * 1e4), &(b.covariance * 1e4)) < 1e-6, "trial {trial}");
            assert!((a.variance_factor - b.variance_factor).abs() < 1e-9 * b.variance_factor.max(1.0));
            assert!((a.rms_px - b.rms_px).abs() < 1e-5, "{} {}", a.rms_px, b.rms_px);
            // None is solve_pnp exactly, bit for bit
            let c =
                solve_pnp_with_pixel_sigmas(&cam, &points, &pixels, None, None, uncertainty, &uniform).expect("valid");
            assert_eq!(c, b);
        }
    }
}

/// Exact points: C = max(1, s²)·(Σⱼ JⱼᵀJⱼ/σⱼ²)⁻¹ with Jⱼ = ∂π(T exp(δ^), Xⱼ)/∂δ from central
/// differences at the returned pose, and s² = Σⱼ‖rⱼ‖²/σⱼ² / (2n − 6). The solver linearizes
/// at the start of its last Gauss–Newton step (at most 1σ from the returned pose), so the
/// two agree to first order: within 1 %, where equal weights would be > 10 % off.
#[test]
fn covariance_is_the_weighted_closed_form() {
    let mut rng = SplitMix64::new(32);
    let cam = camera();
    for trial in 0..10 {
        let (truth, points, sigmas) = scene(&mut rng, 60);
        let pixels = noisy_pixels(&mut rng, &truth, &points, &sigmas);
        let res =
            solve_pnp_with_pixel_sigmas(&cam, &points, &pixels, Some(&sigmas), None, None, &PnpOptions::default())
                .expect("valid");
        assert!(res.success, "{}", res.reason);
        let pose = res.world_from_cam;
        let (mut h, mut h_unweighted, mut chi2, mut n) = (Matrix6::zeros(), Matrix6::zeros(), 0.0, 0);
        for j in (0..points.len()).filter(|&j| res.inliers[j]) {
            let f = |d: &Vector6<f64>| project(&cam, &(pose * SE3::exp(d)), &points[j]).uv;
            let jac: SMatrix<f64, 2, 6> = central_difference(f, &Vector6::zeros(), FD_STEP);
            h += jac.transpose() * jac / (sigmas[j] * sigmas[j]);
            h_unweighted += jac.transpose() * jac / 2.0;
            chi2 += (project(&cam, &pose, &points[j]).uv - pixels[j]).norm_squared() / (sigmas[j] * sigmas[j]);
            n += 1;
        }
        let s2 = chi2 / (2.0 * n as f64 - 6.0);
        assert!((res.variance_factor - s2).abs() < 1e-9 * s2, "trial {trial}: {} vs {s2}", res.variance_factor);
        let want = h.try_inverse().expect("observable") * s2.max(1.0);
        let err = relative_error(&(res.covariance * 1e4), &(want * 1e4));
        assert!(err < 1e-2, "trial {trial}: relative error {err}");
        // the test can tell: the unweighted closed form is far off
        let unweighted = h_unweighted.try_inverse().expect("observable") * s2.max(1.0);
        assert!(relative_error(&(unweighted * 1e4), &(want * 1e4)) > 0.1, "trial {trial}");
    }
}

/// Heteroscedastic pixel noise (σⱼ from the ORB levels); PnP with and without the σⱼ.
fn monte_carlo(seed: u64, trials: usize, with_sigmas: bool) -> Coverage {
    let cam = camera();
    Coverage::run(seed, trials, |rng| {
        let (truth, points, sigmas) = scene(rng, 100);
        let pixels = noisy_pixels(rng, &truth, &points, &sigmas);
        let per_point = with_sigmas.then_some(sigmas.as_slice());
        let res: PnpResult =
            solve_pnp_with_pixel_sigmas(&cam, &points, &pixels, per_point, None, None, &PnpOptions::default())
                .expect("valid");
        res.success.then_some(Sample { truth, estimate: res.world_from_cam, covariance: res.covariance })
    })
}

/// With each keypoint's σ the covariance is calibrated (NEES coverage 93–97 %) and the pose
/// is more accurate than the uniformly weighted one (weighted least squares is the efficient
/// estimator): RMS position error at least 10 % lower on the same data.
#[test]
fn pixel_sigmas_calibrate_and_sharpen_heteroscedastic_pnp() {
    let weighted = monte_carlo(33, 1000, true);
    let uniform = monte_carlo(33, 1000, false);
    assert!(weighted.trials >= 995 && uniform.trials >= 995, "{} / {}", weighted.trials, uniform.trials);
    let coverage = weighted.nees();
    let rms = Coverage::rms_position_m;
    eprintln!(
        "weighted: NEES coverage {coverage:.3}, RMS {:.2} cm; uniform: coverage {:.3}, RMS {:.2} cm",
        rms(&weighted) * 100.0,
        uniform.nees(),
        rms(&uniform) * 100.0
    );
    assert!((0.93..=0.97).contains(&coverage), "NEES coverage {coverage}");
    assert!(rms(&weighted) < 0.9 * rms(&uniform), "{} vs {}", rms(&weighted), rms(&uniform));
}

#[test]
fn bad_pixel_sigmas_are_refused_by_name() {
    let mut rng = SplitMix64::new(34);
    let cam = camera();
    let (truth, points, sigmas) = scene(&mut rng, 20);
    let pixels = noisy_pixels(&mut rng, &truth, &points, &sigmas);
    let name = |s: &[f64]| match solve_pnp_with_pixel_sigmas(
        &cam,
        &points,
        &pixels,
        Some(s),
        None,
        None,
        &PnpOptions::default(),
    ) {
        Err(geoloc_core::GeolocError::InvalidInput { name, .. }) => name,
        other => panic!("expected InvalidInput, got {other:?}"),
    };
    assert_eq!(name(&sigmas[..19]), "pixel_sigmas");
    for bad in [0.0, -1.0, f64::NAN, f64::INFINITY] {
        let mut s = sigmas.clone();
        s[7] = bad;
        assert_eq!(name(&s), "pixel_sigmas", "{bad}");
    }
}
