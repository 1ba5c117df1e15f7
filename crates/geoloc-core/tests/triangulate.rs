//! Forward intersection: exact recovery, robustness, rejection reasons, covariance
//! calibration by Monte-Carlo and pose sensitivities by finite differences.

mod common;

use common::{arc_scene, observe};
use geoloc_core::GeolocError;
use geoloc_core::camera::project;
use geoloc_core::lie::{SE3, Twist};
use geoloc_core::stats::chi2::CHI2_3_95;
use geoloc_core::testing::{SplitMix64, isotropic_pose_covariance};
use geoloc_core::triangulate::{TrackStatus, TriangulationOptions, View, triangulate, triangulate_track};
use nalgebra::{Matrix6, Vector2, Vector3};

fn all_views(
    rng: &mut SplitMix64,
    camera: &geoloc_core::camera::Camera,
    poses: &[SE3],
    points: &[Vector3<f64>],
    sigma: f64,
) -> (Vec<usize>, Vec<usize>, Vec<Vector2<f64>>) {
    let (mut cams, mut tracks, mut pix) = (vec![], vec![], vec![]);
    for (t, x) in points.iter().enumerate() {
        for (c, pose) in poses.iter().enumerate() {
            cams.push(c);
            tracks.push(t);
            pix.push(observe(rng, camera, pose, x, sigma));
        }
    }
    (cams, tracks, pix)
}

#[test]
fn noise_free_tracks_are_recovered_exactly() {
    let mut rng = SplitMix64::new(1);
    let (camera, poses, points) = arc_scene(&mut rng, 5, 200);
    let (cams, tracks, pix) = all_views(&mut rng, &camera, &poses, &points, 0.0);
    let tri = triangulate(&camera, &poses, None, &cams, &tracks, &pix, &TriangulationOptions::default())
        .expect("valid input");
    for (p, x) in tri.points.iter().zip(&points) {
        assert_eq!(p.status, TrackStatus::Valid);
        assert!((p.point - x).norm() < 1e-9, "{:?} vs {x:?}", p.point);
        assert!(p.mean_residual_px < 1e-8);
    }
    assert!(tri.observation_inliers.iter().all(|&b| b));
}

#[test]
fn outlier_observations_are_dropped() {
    let mut rng = SplitMix64::new(2);
    let (camera, poses, points) = arc_scene(&mut rng, 6, 300);
    let (cams, tracks, mut pix) = all_views(&mut rng, &camera, &poses, &points, 0.5);
    let mut is_outlier = vec![false; pix.len()];
    for o in 0..pix.len() {
        if rng.uniform() < 0.1 {
            pix[o] += Vector2::new(rng.uniform_in(-80.0, 80.0), rng.uniform_in(-80.0, 80.0));
            is_outlier[o] = pix[o].norm() > 0.0;
        }
    }
    let options = TriangulationOptions { pixel_sigma: 0.5, ..TriangulationOptions::default() };
    let tri = triangulate(&camera, &poses, None, &cams, &tracks, &pix, &options).expect("valid input");
    // accuracy relative to the achievable precision (≈2 cm in depth here): NEES against the
    // pixel covariance stays χ²₃-distributed once the outliers are gone
    let mut valid = 0;
    let mut inside = 0;
    for (p, x) in tri.points.iter().zip(&points) {
        if p.status == TrackStatus::Valid {
            valid += 1;
            let e = p.point - x;
            let nees = (e.transpose() * p.covariance.try_inverse().expect("spd") * e)[0];
            inside += usize::from(nees <= CHI2_3_95);
        }
    }
    assert!(valid >= 295, "valid {valid}");
    assert!(inside as f64 >= 0.9 * valid as f64, "{inside}/{valid} within χ²₃(95 %)");
    let flagged_outliers = is_outlier.iter().zip(&tri.observation_inliers).filter(|(o, i)| **o && !**i).count();
    let total_outliers = is_outlier.iter().filter(|o| **o).count();
    assert!(flagged_outliers as f64 >= 0.95 * total_outliers as f64, "{flagged_outliers}/{total_outliers}");
}

#[test]
fn rejection_reasons() {
    let mut rng = SplitMix64::new(3);
    let (camera, poses, points) = arc_scene(&mut rng, 3, 1);
    let x = points[0];
    let options = TriangulationOptions::default();
    let view = |c: usize, x: &Vector3<f64>| View { camera: c, uv: project(&camera, &poses[c], x).uv };
    // one view, or two views from the same camera
    let one = triangulate_track(&camera, &poses, None, &[view(0, &x)], &options);
    assert_eq!(one.status, TrackStatus::TooFewViews);
    let same = triangulate_track(&camera, &poses, None, &[view(0, &x), view(0, &x)], &options);
    assert_eq!(same.status, TrackStatus::TooFewViews);
    // zero baseline: two cameras at the same centre
    let twin = vec![poses[0], poses[0] * SE3::exp(&Twist::new(0.0, 0.0, 0.0, 0.0, 0.02, 0.0))];
    let v0 = View { camera: 0, uv: project(&camera, &twin[0], &x).uv };
    let v1 = View { camera: 1, uv: project(&camera, &twin[1], &x).uv };
    let degenerate = triangulate_track(&camera, &twin, None, &[v0, v1], &options);
    assert!(matches!(degenerate.status, TrackStatus::Degenerate | TrackStatus::SmallAngle), "{:?}", degenerate.status);
    // a very distant point: tiny angle
    let far = Vector3::new(0.0, 0.0, 5000.0);
    let small = triangulate_track(&camera, &poses, None, &[view(0, &far), view(2, &far)], &options);
    assert_eq!(small.status, TrackStatus::SmallAngle);
    // inconsistent views: residual too large everywhere
    let mut bad = vec![view(0, &x), view(1, &x)];
    bad[1].uv += Vector2::new(0.0, 60.0);
    let large = triangulate_track(&camera, &poses, None, &bad, &options);
    assert!(matches!(large.status, TrackStatus::LargeResidual | TrackStatus::TooFewViews), "{:?}", large.status);
}

/// Monte-Carlo: with σ = 1 px pixel noise the pixel covariance is calibrated: the NEES of X
/// has mean ≈ 3 and falls below χ²₃(95 %) in ≈ 95 % of trials.
#[test]
fn pixel_covariance_is_calibrated() {
    let mut rng = SplitMix64::new(4);
    let (camera, poses, points) = arc_scene(&mut rng, 4, 50);
    let options = TriangulationOptions::default();
    let (mut inside, mut total, mut nees_sum) = (0, 0, 0.0);
    for _ in 0..100 {
        let (cams, tracks, pix) = all_views(&mut rng, &camera, &poses, &points, 1.0);
        let tri = triangulate(&camera, &poses, None, &cams, &tracks, &pix, &options).expect("valid");
        for (p, x) in tri.points.iter().zip(&points) {
            let e = p.point - x;
            let nees = (e.transpose() * p.covariance.try_inverse().expect("spd") * e)[0];
            nees_sum += nees;
            inside += usize::from(nees <= CHI2_3_95);
            total += 1;
        }
    }
    let coverage = inside as f64 / total as f64;
    let mean = nees_sum / total as f64;
    assert!((0.93..=0.97).contains(&coverage), "coverage {coverage}");
    assert!((2.7..=3.3).contains(&mean), "mean NEES {mean}");
}

/// D_k = ∂X/∂δ_k against re-triangulating with perturbed poses (central differences), on
/// noise-free pixels where the Gauss–Newton sensitivity is exact (with residuals it is
/// first-order only).
#[test]
fn pose_jacobians_match_central_differences() {
    let mut rng = SplitMix64::new(5);
    let (camera, poses, points) = arc_scene(&mut rng, 4, 5);
    let options = TriangulationOptions::default();
    let h = 1e-4; // O(h²) truncation ≪ tolerance; LM's stopping noise ≪ h
    for x in &points {
        let views: Vec<View> =
            (0..poses.len()).map(|c| View { camera: c, uv: observe(&mut rng, &camera, &poses[c], x, 0.0) }).collect();
        // D is computed when pose covariances are given; tiny ones leave the weights ≈ 1/σ²
        let covs = vec![Matrix6::identity() * 1e-12; poses.len()];
        let base = triangulate_track(&camera, &poses, Some(&covs), &views, &options);
        assert_eq!(base.pose_jacobians.len(), poses.len());
        for (cam, d) in &base.pose_jacobians {
            for axis in 0..6 {
                let mut delta = Twist::zeros();
                delta[axis] = h;
                let mut plus = poses.clone();
                plus[*cam] = poses[*cam] * SE3::exp(&delta);
                let mut minus = poses.clone();
                minus[*cam] = poses[*cam] * SE3::exp(&-delta);
                let xp = triangulate_track(&camera, &plus, Some(&covs), &views, &options).point;
                let xm = triangulate_track(&camera, &minus, Some(&covs), &views, &options).point;
                let numeric = (xp - xm) / (2.0 * h);
                let analytic = d.column(axis);
                assert!(
                    (numeric - analytic).norm() < 1e-4 * analytic.norm().max(1e-3),
                    "cam {cam} axis {axis}: {numeric} vs {analytic}"
                );
            }
        }
    }
}

/// With noisy keyframe poses and their covariance given, the marginal covariance of X is
/// calibrated (pose noise 1 cm / 0.5° dominates the 1 px pixel noise here).
#[test]
fn pose_noise_is_propagated() {
    let mut rng = SplitMix64::new(6);
    let (camera, poses, points) = arc_scene(&mut rng, 4, 20);
    let (sigma_t, sigma_r) = (0.01, 0.5f64.to_radians());
    let cov = isotropic_pose_covariance(sigma_t, sigma_r);
    let covs = vec![cov; poses.len()];
    let options = TriangulationOptions::default();
    let (mut inside, mut total) = (0, 0);
    for _ in 0..300 {
        let noisy: Vec<SE3> = poses
            .iter()
            .map(|p| {
                let d = rng.pose_noise(sigma_t, sigma_r);
                *p * SE3::exp(&d)
            })
            .collect();
        let (cams, tracks, pix) = all_views(&mut rng, &camera, &poses, &points, 1.0);
        let tri = triangulate(&camera, &noisy, Some(&covs), &cams, &tracks, &pix, &options).expect("valid");
        for (p, x) in tri.points.iter().zip(&points) {
            if p.status != TrackStatus::Valid {
                continue;
            }
            let e = p.point - x;
            let nees = (e.transpose() * p.covariance.try_inverse().expect("spd") * e)[0];
            inside += usize::from(nees <= CHI2_3_95);
            total += 1;
        }
    }
    let coverage = inside as f64 / total as f64;
    assert!(total > 5000);
    assert!((0.92..=0.98).contains(&coverage), "coverage {coverage}");
}

#[test]
fn bad_input_is_an_error_naming_the_argument() {
    let mut rng = SplitMix64::new(7);
    let (camera, poses, _) = arc_scene(&mut rng, 2, 1);
    let options = TriangulationOptions::default();
    let px = vec![Vector2::new(1.0, 2.0); 2];
    let err = triangulate(&camera, &poses, None, &[0], &[0, 0], &px, &options).expect_err("length");
    assert!(matches!(err, GeolocError::InvalidInput { ref name, .. } if name == "cam_ids"));
    let err = triangulate(&camera, &poses, None, &[0, 2], &[0, 0], &px, &options).expect_err("cam id");
    assert!(matches!(err, GeolocError::InvalidInput { ref name, .. } if name == "cam_ids"));
    let nan = vec![Vector2::new(1.0, f64::NAN); 2];
    let err = triangulate(&camera, &poses, None, &[0, 1], &[0, 0], &nan, &options).expect_err("nan");
    assert!(matches!(err, GeolocError::NonFinite { ref name, index: 0 } if name == "pixels"));
    let bad = TriangulationOptions { pixel_sigma: 0.0, ..options };
    assert!(triangulate(&camera, &poses, None, &[0, 1], &[0, 0], &px, &bad).is_err());
    let covs = vec![Matrix6::identity(); 1];
    assert!(triangulate(&camera, &poses, Some(&covs), &[0, 1], &[0, 0], &px, &options).is_err());
    // no observations at all is fine: no points
    let empty = triangulate(&camera, &poses, None, &[], &[], &[], &options).expect("empty is valid");
    assert!(empty.points.is_empty());
}

/// Track ids are labels — huge ids cost no memory (one row per distinct id, in
/// increasing order), and the points equal those of the same tracks numbered 0..P.
#[test]
fn huge_track_ids_are_renumbered_not_allocated() {
    let mut rng = SplitMix64::new(11);
    let (camera, poses, all_points) = arc_scene(&mut rng, 3, 2);
    let points = [all_points[0], all_points[1]];
    let (mut cams, mut dense, mut pix) = (vec![], vec![], vec![]);
    for (t, x) in points.iter().enumerate() {
        for (c, pose) in poses.iter().enumerate() {
            cams.push(c);
            dense.push(t);
            pix.push(project(&camera, pose, x).uv);
        }
    }
    let options = TriangulationOptions::default();
    let reference = triangulate(&camera, &poses, None, &cams, &dense, &pix, &options).expect("valid");
    assert_eq!(reference.track_ids, vec![0, 1]);
    for ids in [[usize::MAX, 7], [1_000_000_000, 0], [1 << 62, 3]] {
        let sparse: Vec<usize> = dense.iter().map(|&t| ids[t]).collect();
        let tri = triangulate(&camera, &poses, None, &cams, &sparse, &pix, &options).expect("valid");
        assert_eq!(tri.points.len(), 2);
        let mut sorted = ids.to_vec();
        sorted.sort_unstable();
        assert_eq!(tri.track_ids, sorted);
        for (t, &id) in ids.iter().enumerate() {
            assert_eq!(tri.point(id), Some(&reference.points[t]));
        }
        assert_eq!(tri.observation_inliers, reference.observation_inliers);
    }
}

/// A pose covariance that is not positive semi-definite is refused by name.
#[test]
fn non_psd_pose_covariances_are_refused() {
    let mut rng = SplitMix64::new(12);
    let (camera, _, _) = arc_scene(&mut rng, 2, 1);
    let poses = vec![SE3::identity(), SE3::exp(&Twist::new(0.5, 0.0, 0.0, 0.0, 0.0, 0.0))];
    let px = [Vector2::new(320.0, 240.0), Vector2::new(300.0, 240.0)];
    let covs = [Matrix6::identity() * 1e-6, -Matrix6::identity() * 1e-6];
    let err = triangulate(&camera, &poses, Some(&covs), &[0, 1], &[0, 0], &px, &TriangulationOptions::default())
        .expect_err("negative covariance");
    assert!(matches!(&err, GeolocError::InvalidInput { name, .. } if name == "pose_covariances[1]"), "{err:?}");
}
