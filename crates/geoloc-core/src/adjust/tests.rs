use nalgebra::{DMatrix, DVector};

use super::problem::*;
use super::*;
use crate::lie::{SO3, se3};
use crate::testing::{SplitMix64, look_at};

/// A scene for the adjustment: `count` landmarks in a box 3–7 m in front, `n` cameras on a
/// path that turns ±25° and pitches a little (so that a label-to-camera offset is observable),
/// the true camera poses, the landmarks and the observations with `noise_px` Gaussian noise.
fn scene(
    rng: &mut SplitMix64,
    n: usize,
    count: usize,
    noise_px: f64,
) -> (Camera, Vec<SE3>, Vec<Vector3<f64>>, Vec<Observation>) {
    let camera = Camera::new(525.0, 525.0, 320.0, 240.0).expect("valid");
    let landmarks: Vec<Vector3<f64>> = (0..count)
        .map(|_| Vector3::new(rng.uniform_in(-4.0, 4.0), rng.uniform_in(-1.5, 1.5), rng.uniform_in(3.0, 7.0)))
        .collect();
    let cams: Vec<SE3> = (0..n)
        .map(|i| {
            let s = i as f64 / (n - 1).max(1) as f64;
            let c = Vector3::new(-1.5 + 3.0 * s, 0.2 * (5.0 * s).sin(), 0.4 * (3.0 * s).cos());
            let target = Vector3::new(c.x + 2.5 * (4.0 * s).sin(), 0.8 * (6.0 * s).cos(), 5.0);
            look_at(&c, &target)
        })
        .collect();
    let mut observations = Vec::new();
    for (k, pose) in cams.iter().enumerate() {
        for (j, x) in landmarks.iter().enumerate() {
            let p = crate::camera::project(&camera, pose, x);
            if p.p_cam.z > 0.5 && (0.0..640.0).contains(&p.uv.x) && (0.0..480.0).contains(&p.uv.y) {
                let noise = Vector2::new(rng.normal(), rng.normal()) * noise_px;
                observations.push(Observation { keyframe: k, point: j, pixel: p.uv + noise, sigma: 1.0 });
            }
        }
    }
    (camera, cams, landmarks, observations)
}

fn pose_error(a: &SE3, b: &SE3) -> (f64, f64) {
    let d = a.inverse() * *b;
    (d.translation.norm(), d.rotation.angle())
}

fn median(mut v: Vec<f64>) -> f64 {
    crate::stats::median(&mut v, crate::stats::EvenMedian::Upper).expect("not empty")
}

/// The observations with ORB-like keypoint σ: 1.2^level, level 0–7 drawn at random.
fn with_keypoint_sigmas(rng: &mut SplitMix64, observations: &[Observation]) -> Vec<Observation> {
    observations
        .iter()
        .map(|o| Observation { sigma: 1.2_f64.powi((rng.uniform_in(0.0, 8.0)).floor() as i32), ..*o })
        .collect()
}

/// The residual's Jacobians against central differences of the whitened residual
/// (u(state) − pixel) / (σ_px σ_o), each observation with its own keypoint σ.
#[test]
fn jacobians_match_finite_differences() {
    let mut rng = SplitMix64::new(1);
    let (camera, cams, landmarks, observations) = scene(&mut rng, 5, 60, 0.0);
    let observations = with_keypoint_sigmas(&mut rng, &observations);
    let offset = SE3::exp(&rng.twist(0.1, 0.1));
    let labels: Vec<SE3> = cams.iter().map(|c| *c * offset.inverse()).collect();
    let state = State { labels: labels.clone(), offset, points: landmarks.clone() };
    let options = AdjustmentOptions { pixel_sigma_px: 0.7, ..AdjustmentOptions::default() };
    let inliers = vec![true; observations.len()];
    let problem = Problem::new(&camera, &labels, &observations, &inliers, &options, WIDE_LABEL_SIGMA);
    let h = 1e-6;
    for o in observations.iter().step_by(37) {
        let l = problem.linearize(&state, o).expect("in front");
        let r = |s: &State| s.residual_px(&camera, o).expect("in front") / (options.pixel_sigma_px * o.sigma);
        for a in 0..6 {
            let mut e = Vector6::zeros();
            e[a] = h;
            let perturb_label = |sign: f64| {
                let mut s = state.clone();
                s.labels[o.keyframe] = s.labels[o.keyframe] * SE3::exp(&(e * sign));
                r(&s)
            };
            let fd = (perturb_label(1.0) - perturb_label(-1.0)) / (2.0 * h);
            assert!((fd - l.j_label.column(a)).norm() < 1e-5 * fd.norm().max(1.0), "label axis {a}");
            let perturb_offset = |sign: f64| {
                let mut s = state.clone();
                s.offset = s.offset * SE3::exp(&(e * sign));
                r(&s)
            };
            let fd = (perturb_offset(1.0) - perturb_offset(-1.0)) / (2.0 * h);
            assert!((fd - l.j_offset.column(a)).norm() < 1e-5 * fd.norm().max(1.0), "offset axis {a}");
        }
        for a in 0..3 {
            let perturb_point = |sign: f64| {
                let mut s = state.clone();
                s.points[o.point][a] += sign * h;
                r(&s)
            };
            let fd = (perturb_point(1.0) - perturb_point(-1.0)) / (2.0 * h);
            assert!((fd - l.j_point.column(a)).norm() < 1e-5 * fd.norm().max(1.0), "point axis {a}");
        }
    }
}

/// The cost is Σ_o ρ(‖r_o‖² / (σ_px σ_o)²) + Σ_k ρ_label(e_kᵀΛe_k) + e_Xᵀ Λ_X e_X, summed here
/// term by term from the definitions: a coarse keypoint (σ_o > 1) counts for 1/σ_o² as much.
#[test]
fn the_cost_weighs_each_observation_by_its_keypoint_sigma() {
    let mut rng = SplitMix64::new(4);
    let (camera, cams, landmarks, observations) = scene(&mut rng, 4, 40, 1.5);
    let observations = with_keypoint_sigmas(&mut rng, &observations);
    let offset = SE3::exp(&rng.twist(0.05, 0.05));
    let labels: Vec<SE3> = cams.iter().map(|c| *c * offset.inverse() * SE3::exp(&rng.twist(0.01, 0.01))).collect();
    let state = State { labels: cams.iter().map(|c| *c * offset.inverse()).collect(), offset, points: landmarks };
    let options = AdjustmentOptions { pixel_sigma_px: 0.8, ..AdjustmentOptions::default() };
    let sigma = LabelSigma { translation_m: 0.02, rotation_rad: 0.01 };
    let inliers = vec![true; observations.len()];
    let problem = Problem::new(&camera, &labels, &observations, &inliers, &options, sigma);
    let huber = |s: f64| if s <= 4.0 { s } else { 4.0 * s.sqrt() - 4.0 };
    let cauchy = |s: f64| 9.0 * (1.0 + s / 9.0).ln();
    let mut views = vec![0usize; state.points.len()];
    for o in &observations {
        views[o.point] += 1;
    }
    let mut expected = 0.0;
    // (a point one keyframe sees constrains nothing: the problem leaves it out)
    for o in observations.iter().filter(|o| views[o.point] >= 2) {
        let x = state.labels[o.keyframe] * state.offset;
        let u = crate::camera::project(&camera, &x, &state.points[o.point]).uv;
        expected += huber(((u - o.pixel) / (0.8 * o.sigma)).norm_squared());
    }
    for (l, b) in labels.iter().zip(&state.labels) {
        let e = (l.inverse() * *b).log();
        let s = (e.fixed_rows::<3>(0).norm_squared() / 0.02_f64.powi(2))
            + e.fixed_rows::<3>(3).norm_squared() / 0.01_f64.powi(2);
        expected += cauchy(s);
    }
    let ex = state.offset.log();
    expected += ex.fixed_rows::<3>(0).norm_squared() / 0.04 + ex.fixed_rows::<3>(3).norm_squared() / 0.04;
    let cost = problem.cost(&state);
    assert!((cost - expected).abs() < 1e-9 * expected, "{cost} against {expected}");
    assert!(observations.iter().any(|o| o.sigma > 3.0) && observations.iter().any(|o| o.sigma < 1.1));
}

/// The dense normal matrix of the whole problem (keyframes, offset, points) at `state`.
fn dense_normal_matrix(problem: &Problem<'_>, state: &State, n_points: usize) -> DMatrix<f64> {
    let n = problem.labels.len();
    let dim = 6 * (n + 1) + 3 * n_points;
    let mut h = DMatrix::<f64>::zeros(dim, dim);
    // a point nothing observes gets δ = 0: an identity block keeps H regular
    for (j, obs) in problem.by_point.iter().enumerate() {
        if obs.is_empty() {
            let mut v = h.view_mut((6 * (n + 1) + 3 * j, 6 * (n + 1) + 3 * j), (3, 3));
            v += Matrix3::identity();
        }
    }
    for j in problem.by_point.len()..n_points {
        let mut v = h.view_mut((6 * (n + 1) + 3 * j, 6 * (n + 1) + 3 * j), (3, 3));
        v += Matrix3::identity();
    }
    for obs in &problem.by_point {
        for &i in obs {
            let o = &problem.observations[i];
            let l = problem.linearize(state, o).expect("in front");
            let mut j = DMatrix::<f64>::zeros(2, dim);
            j.view_mut((0, 6 * o.keyframe), (2, 6)).copy_from(&l.j_label);
            j.view_mut((0, 6 * n), (2, 6)).copy_from(&l.j_offset);
            j.view_mut((0, 6 * (n + 1) + 3 * o.point), (2, 3)).copy_from(&l.j_point);
            h += j.transpose() * &j * l.weight;
        }
    }
    for k in 0..n {
        let (_, hk, _) = problem.label_prior(state, k);
        let mut v = h.view_mut((6 * k, 6 * k), (6, 6));
        v += hk;
    }
    let (_, hx, _) = problem.offset_prior(state);
    let mut v = h.view_mut((6 * n, 6 * n), (6, 6));
    v += hx;
    h
}

/// A [`scene`] of `keyframes` cameras and `landmarks` points (seed `seed`, 0.5 px noise), its
/// labels on an offset sensor with 1 cm / 0.3° of noise, and at the truth: the labels, the
/// number of points, the adjustment's covariances and the dense inverse of its full normal
/// matrix (keyframes, offset, points).
fn covariances_and_dense_inverse(
    seed: u64,
    keyframes: usize,
    landmarks: usize,
) -> (Vec<SE3>, usize, Covariances, DMatrix<f64>) {
    let mut rng = SplitMix64::new(seed);
    let (camera, cams, landmarks, observations) = scene(&mut rng, keyframes, landmarks, 0.5);
    let offset = SE3::exp(&rng.twist(0.05, 0.05));
    let labels: Vec<SE3> =
        cams.iter().map(|c| *c * offset.inverse() * SE3::exp(&rng.pose_noise(0.01, 0.005))).collect();
    let options = AdjustmentOptions { pixel_loss: RobustLoss::None, ..AdjustmentOptions::default() };
    let inliers = vec![true; observations.len()];
    let sigma = LabelSigma { translation_m: 0.01, rotation_rad: 0.005 };
    let problem = Problem::new(&camera, &labels, &observations, &inliers, &options, sigma);
    let state = State { labels: labels.clone(), offset, points: landmarks.clone() };
    let covariances = problem.covariances(&state).expect("regular");
    let dense =
        dense_normal_matrix(&problem.for_covariances(), &state, landmarks.len()).try_inverse().expect("invertible");
    (labels, landmarks.len(), covariances, dense)
}

/// The marginal covariances (selected inverse through the Schur complement) equal the blocks
/// of the dense inverse of the full normal matrix.
#[test]
fn marginal_covariances_equal_the_dense_inverse() {
    let (labels, points, covariances, dense) = covariances_and_dense_inverse(2, 6, 40);
    let n = labels.len();
    let scale = dense.amax();
    for k in 0..n {
        let want = dense.fixed_view::<6, 6>(6 * k, 6 * k).into_owned();
        assert!((covariances.label_poses[k] - want).amax() < 1e-9 * scale, "keyframe {k}");
        let want = dense.fixed_view::<6, 6>(6 * k, 6 * n).into_owned();
        assert!((covariances.label_offset[k] - want).amax() < 1e-9 * scale, "keyframe {k} × offset");
    }
    let want = dense.fixed_view::<6, 6>(6 * n, 6 * n).into_owned();
    assert!((covariances.offset - want).amax() < 1e-9 * scale);
    for j in (0..points).step_by(3) {
        let want = dense.fixed_view::<3, 3>(6 * (n + 1) + 3 * j, 6 * (n + 1) + 3 * j).into_owned();
        assert!((covariances.points[j] - want).amax() < 1e-9 * scale, "point {j}");
    }
}

/// The neighbourhood covariances equal the brute-force sum over the dense inverse's blocks,
/// each keyframe's perturbation carried into k's frame by the finite-difference Jacobian of
/// ε ↦ log(D exp(ε) D⁻¹), D = B_k⁻¹ B_a; on a path longer than a neighbourhood, the ends
/// take the part of the window that exists.
#[test]
fn neighbourhood_covariances_equal_the_dense_inverse() {
    let (labels, _, covariances, dense) = covariances_and_dense_inverse(4, 14, 60);
    let n = labels.len();
    let transport = |d: &SE3| {
        let h = 1e-6;
        let mut j = Matrix6::zeros();
        for i in 0..6 {
            let mut e = Vector6::zeros();
            e[i] = h;
            let plus = (*d * SE3::exp(&e) * d.inverse()).log();
            let minus = (*d * SE3::exp(&(-e)) * d.inverse()).log();
            j.set_column(i, &((plus - minus) / (2.0 * h)));
        }
        j
    };
    let scale = dense.amax();
    for k in 0..n {
        let (lo, hi) = (k.saturating_sub(NEIGHBOURHOOD_KEYFRAMES), (k + NEIGHBOURHOOD_KEYFRAMES).min(n - 1));
        let m = (hi - lo + 1) as f64;
        let mut want = Matrix6::zeros();
        for a in lo..=hi {
            for b in lo..=hi {
                let ja = transport(&(labels[k].inverse() * labels[a]));
                let jb = transport(&(labels[k].inverse() * labels[b]));
                want += ja * dense.fixed_view::<6, 6>(6 * a, 6 * b) * jb.transpose();
            }
        }
        want /= m * m;
        let got = covariances.label_neighbourhoods[k];
        assert!((got - want).amax() < 1e-6 * scale, "keyframe {k}: {got} against {want}");
        // the mean of the neighbourhood is known better than one keyframe
        assert!(got.trace() < covariances.label_poses[k].trace(), "keyframe {k}");
    }
}

/// One GN step of the reduced system equals the dense solve of the full normal equations.
#[test]
fn the_reduced_step_equals_the_dense_step() {
    let mut rng = SplitMix64::new(4);
    let (camera, cams, landmarks, observations) = scene(&mut rng, 5, 30, 0.5);
    let labels: Vec<SE3> = cams.iter().map(|c| *c * SE3::exp(&rng.pose_noise(0.02, 0.01))).collect();
    let options = AdjustmentOptions::default();
    let inliers = vec![true; observations.len()];
    let problem = Problem::new(&camera, &labels, &observations, &inliers, &options, WIDE_LABEL_SIGMA);
    let points: Vec<Vector3<f64>> = landmarks.iter().map(|p| p + rng.unit_vector() * 0.02).collect();
    let state = State { labels: labels.clone(), offset: SE3::exp(&rng.twist(0.02, 0.02)), points };
    let reduced = problem.reduce(&state, 0.0);
    let delta = reduced.s.cholesky().expect("SPD").solve(&reduced.rhs);
    let stepped = problem.retract(&state, &delta, &reduced);
    // dense: H δ = −g
    let n = labels.len();
    let h = dense_normal_matrix(&problem, &state, landmarks.len());
    let mut g = DVector::<f64>::zeros(h.nrows());
    for obs in &problem.by_point {
        for &i in obs {
            let o = &observations[i];
            let l = problem.linearize(&state, o).expect("in front");
            let w = l.weight;
            let mut gk = g.fixed_rows_mut::<6>(6 * o.keyframe);
            gk += l.j_label.transpose() * l.r * w;
            let mut gx = g.fixed_rows_mut::<6>(6 * n);
            gx += l.j_offset.transpose() * l.r * w;
            let mut gp = g.fixed_rows_mut::<3>(6 * (n + 1) + 3 * o.point);
            gp += l.j_point.transpose() * l.r * w;
        }
    }
    for k in 0..n {
        let (_, _, gk) = problem.label_prior(&state, k);
        let mut v = g.fixed_rows_mut::<6>(6 * k);
        v += gk;
    }
    let (_, _, gx) = problem.offset_prior(&state);
    let mut v = g.fixed_rows_mut::<6>(6 * n);
    v += gx;
    let dense = h.cholesky().expect("SPD").solve(&(-g));
    for k in 0..=n {
        let want = dense.fixed_rows::<6>(6 * k).into_owned();
        let got = Vector6::from_column_slice(&delta[6 * k..6 * k + 6]);
        assert!((got - want).norm() < 1e-8 * want.norm().max(1e-6), "block {k}: {got} vs {want}");
    }
    for j in 0..landmarks.len() {
        let want = state.points[j] + dense.fixed_rows::<3>(6 * (n + 1) + 3 * j);
        assert!((stepped.points[j] - want).norm() < 1e-8, "point {j}");
    }
}

/// Labels on a sensor 5 cm and 3° from the camera, 2 mm / 0.05° noise, and one run of 8
/// keyframes displaced by 20 cm / 5°, in eight random scenes: the adjustment recovers the
/// camera poses and the offset within their covariances (and within 5 cm / 0.3°, a quarter of
/// the displacement: the labels' noise and the path's ±25° of turn leave the offset's
/// translation known to a few centimetres), corrects the run by ≈ the displacement,
/// significantly, leaves the other labels within 1 cm, and estimates the σ of the consistent
/// labels (mm), not the run's. One scene's thresholds fitted to its seed failed at half of
/// the others (camera and offset errors up to 4 cm inside their covariances, σ 5.6 mm).
#[test]
fn recovers_a_displaced_run_and_the_sensor_offset() {
    for seed in 1..=8 {
        let mut rng = SplitMix64::new(seed);
        let n = 40;
        let (camera, cams, landmarks, observations) = scene(&mut rng, n, 500, 0.5);
        let axis = Vector3::new(0.3, -1.0, 0.5).normalize();
        let offset_true = SE3::new(SO3::exp(&(axis * 3f64.to_radians())), Vector3::new(0.04, -0.02, 0.02));
        let run = 20..28;
        let bump = SE3::exp(&crate::lie::se3::twist(&Vector3::new(0.12, 0.1, -0.12), &(axis * 5f64.to_radians())));
        let labels: Vec<SE3> = cams
            .iter()
            .enumerate()
            .map(|(k, c)| {
                let l = *c * offset_true.inverse() * SE3::exp(&rng.pose_noise(0.002, 0.001));
                if run.contains(&k) { bump * l } else { l }
            })
            .collect();
        let points: Vec<Vector3<f64>> = landmarks.iter().map(|p| p + rng.unit_vector() * 0.05).collect();
        let adjusted =
            bundle_adjust(&camera, &labels, &points, &observations, &AdjustmentOptions::default()).expect("adjusts");
        let nees = |estimate: &SE3, covariance: &nalgebra::Matrix6<f64>, truth: &SE3| {
            let e = (estimate.inverse() * *truth).log();
            (e.transpose() * covariance.try_inverse().expect("SPD") * e)[0]
        };
        for (k, (a, c)) in adjusted.camera_poses().iter().zip(&cams).enumerate() {
            let (t, r) = pose_error(a, c);
            assert!(t < 0.05 && r < 0.3f64.to_radians(), "seed {seed} keyframe {k}: {t} m, {} deg", r.to_degrees());
            let m = nees(a, &adjusted.camera_pose_covariances[k], c);
            assert!(m < crate::stats::chi2::CHI2_6_999, "seed {seed} keyframe {k}: NEES {m}");
        }
        let (dt, dr) = pose_error(&adjusted.offset, &offset_true);
        assert!(dt < 0.05 && dr < 0.3f64.to_radians(), "seed {seed}: offset off by {dt} m, {} deg", dr.to_degrees());
        let m = nees(&adjusted.offset, &adjusted.offset_covariance, &offset_true);
        assert!(m < crate::stats::chi2::CHI2_6_999, "seed {seed}: offset NEES {m}");
        let corrections = adjusted.corrections(&labels);
        for (k, (e, m)) in corrections.iter().enumerate() {
            if run.contains(&k) {
                assert!(se3::phi(e).norm() > 4f64.to_radians() && *m > 100.0, "seed {seed} run keyframe {k}: {e}, {m}");
            } else {
                assert!(se3::rho(e).norm() < 0.01, "seed {seed}: keyframe {k} moved by {}", se3::rho(e).norm());
            }
        }
        assert!(adjusted.rms_px.1 < 0.8, "seed {seed}: {:?}", adjusted.rms_px);
        // the estimated σ is that of the consistent labels (mm), not the run's (20 cm)
        assert!(adjusted.label_sigma.translation_m < 0.01, "seed {seed}: {:?}", adjusted.label_sigma);
    }
}

/// Candidates join where the adjusted poses fit them. A run of 8 labels displaced by
/// 20 cm / 5° as in [`recovers_a_displaced_run_and_the_sensor_offset`], and the views a
/// triangulation from the labels would reject left out of the start: of the points both the
/// run and the rest see, nine in ten keep only the rest's views and give the run's as
/// candidates (the tenth keeps both — the few tracks that tie the run to the rest at the
/// start), and some of the other points have a mismatched candidate 30 px off. With the
/// candidates the run comes back to within 1 cm / 0.1° of the truth (0.3–0.4 cm), at least
/// 80 % of the true candidates are used and no mismatch; without them the run stays at least
/// twice as far off (1.1–1.5 cm).
#[test]
fn candidates_join_where_the_adjusted_poses_fit_them() {
    for seed in 1..=4 {
        let mut rng = SplitMix64::new(seed);
        let (camera, cams, landmarks, observations) = scene(&mut rng, 40, 500, 0.5);
        let run = 20..28;
        let axis = Vector3::new(0.3, -1.0, 0.5).normalize();
        let bump = SE3::exp(&se3::twist(&Vector3::new(0.12, 0.1, -0.12), &(axis * 5f64.to_radians())));
        let labels: Vec<SE3> = cams
            .iter()
            .enumerate()
            .map(|(k, c)| {
                let l = *c * SE3::exp(&rng.pose_noise(0.002, 0.001));
                if run.contains(&k) { bump * l } else { l }
            })
            .collect();
        let seen_by = |inside: bool| {
            let mut seen = vec![false; landmarks.len()];
            for o in observations.iter().filter(|o| run.contains(&o.keyframe) == inside) {
                seen[o.point] = true;
            }
            seen
        };
        let (by_run, by_rest) = (seen_by(true), seen_by(false));
        let (mut kept, mut candidates) = (Vec::new(), Vec::new());
        for o in &observations {
            let shared = by_run[o.point] && by_rest[o.point];
            if shared && o.point % 10 != 0 && run.contains(&o.keyframe) {
                candidates.push(*o);
            } else {
                kept.push(*o);
            }
        }
        let true_candidates = candidates.len();
        for o in kept.iter().filter(|o| o.point % 10 == 5).step_by(3) {
            candidates.push(Observation { pixel: o.pixel + Vector2::new(30.0, 0.0), ..*o });
        }
        let points: Vec<Vector3<f64>> = landmarks.iter().map(|p| p + rng.unit_vector() * 0.05).collect();
        let options = AdjustmentOptions { estimate_offset: false, ..AdjustmentOptions::default() };
        let start = (&labels[..], &SE3::identity());
        let without = bundle_adjust_from(&camera, &labels, start, &points, &kept, &options).expect("adjusts");
        let with = bundle_adjust_with_candidates(&camera, &labels, start, &points, &kept, &candidates, &options)
            .expect("adjusts");
        let worst = |a: &Adjustment| {
            run.clone()
                .map(|k| pose_error(&a.label_poses[k], &cams[k]))
                .fold((0.0f64, 0.0f64), |m, e| (m.0.max(e.0), m.1.max(e.1)))
        };
        let (t, r) = worst(&with);
        assert!(t < 0.01 && r < 0.1f64.to_radians(), "seed {seed}: run off by {t} m, {} deg", r.to_degrees());
        let (t0, _) = worst(&without);
        assert!(t0 > 2.0 * t, "seed {seed}: without the candidates {t0} m, with {t} m");
        let used = &with.inliers[kept.len()..];
        assert_eq!(used.len(), candidates.len());
        let joined = used[..true_candidates].iter().filter(|u| **u).count();
        assert!(joined as f64 >= 0.8 * true_candidates as f64, "seed {seed}: {joined} of {true_candidates}");
        assert!(used[true_candidates..].iter().all(|u| !u), "seed {seed}: a mismatch joined");
    }
}

/// The covariances cover the error: over 60 scenes (independent samples: one keyframe, the
/// middle one, and the offset per scene), NEES within the χ²₆ 95 % region for 88–99.5 %, by
/// least squares and with the default kernels (Cauchy on the label priors, Huber on the
/// pixels), whose covariances take the weights' information scale; and with the kernels the
/// median NEES is that of χ²₆ (5.35; 4.5–6.5 asked, the median of 120 draws has σ ≈ 0.4):
/// measured 6.1 (91 % inside; least squares 5.6, 92 %), and 4.4 (99 %) from the IRLS weights
/// alone, which count the label priors' information at their average weight 0.63.
#[test]
fn covariances_cover_the_error() {
    let least_squares = AdjustmentOptions {
        label_loss: RobustLoss::None,
        pixel_loss: RobustLoss::None,
        ..AdjustmentOptions::default()
    };
    let (share, nees) = coverage_of_the_error(&least_squares);
    assert!((0.88..=0.995).contains(&share), "least squares: {share}, median NEES {nees}");
    let (share, nees) = coverage_of_the_error(&AdjustmentOptions::default());
    assert!((0.88..=0.995).contains(&share) && (4.5..=6.5).contains(&nees), "kernels: {share}, median NEES {nees}");
}

/// [`covariances_cover_the_error`] with `options` (labels σ 1 cm / 0.005 rad given): the
/// share of the NEES inside the χ²₆ 95 % region and their median.
fn coverage_of_the_error(options: &AdjustmentOptions) -> (f64, f64) {
    let (mut inside, mut total) = (0usize, 0usize);
    let mut nees = Vec::new();
    for seed in 0..60 {
        let mut rng = SplitMix64::new(100 + seed);
        let (camera, cams, landmarks, observations) = scene(&mut rng, 12, 150, 1.0);
        let offset_true = SE3::exp(&rng.twist(0.05, 0.05));
        let labels: Vec<SE3> =
            cams.iter().map(|c| *c * offset_true.inverse() * SE3::exp(&rng.pose_noise(0.01, 0.005))).collect();
        let options = AdjustmentOptions {
            label_sigma: Some(LabelSigma { translation_m: 0.01, rotation_rad: 0.005 }),
            ..*options
        };
        let adjusted = bundle_adjust(&camera, &labels, &landmarks, &observations, &options).expect("adjusts");
        let k = cams.len() / 2;
        let samples = [
            (adjusted.camera_poses()[k], adjusted.camera_pose_covariances[k], cams[k]),
            (adjusted.offset, adjusted.offset_covariance, offset_true),
        ];
        for (estimate, covariance, truth) in samples {
            let e = (estimate.inverse() * truth).log();
            let m = (e.transpose() * covariance.try_inverse().expect("SPD") * e)[0];
            nees.push(m);
            inside += usize::from(m < crate::stats::chi2::CHI2_6_95);
            total += 1;
        }
    }
    (inside as f64 / total as f64, median(nees))
}

#[test]
fn same_bits_with_any_thread_count() {
    use std::num::NonZero;

    use crate::parallel::{Parallelism, with_parallelism};
    let mut rng = SplitMix64::new(5);
    let (camera, cams, landmarks, observations) = scene(&mut rng, 12, 200, 0.5);
    let labels: Vec<SE3> = cams.iter().map(|c| *c * SE3::exp(&rng.pose_noise(0.01, 0.005))).collect();
    let run = || bundle_adjust(&camera, &labels, &landmarks, &observations, &AdjustmentOptions::default()).expect("ok");
    let one = with_parallelism(&Parallelism::Threads(NonZero::new(1).expect("1")), run);
    let two = with_parallelism(&Parallelism::Threads(NonZero::new(2).expect("2")), run);
    let bits = |a: &Adjustment| {
        a.camera_poses()
            .iter()
            .flat_map(|p| p.matrix().iter().map(|v| v.to_bits()).collect::<Vec<_>>())
            .collect::<Vec<_>>()
    };
    assert_eq!(bits(&one), bits(&two));
    assert_eq!(one, two);
}

#[test]
fn bad_inputs_are_refused_by_name() {
    let camera = Camera::new(525.0, 525.0, 320.0, 240.0).expect("valid");
    let labels = vec![SE3::identity(); 2];
    let points = vec![Vector3::new(0.0, 0.0, 4.0)];
    let o = |keyframe, point| Observation { keyframe, point, pixel: Vector2::new(320.0, 240.0), sigma: 1.0 };
    let err = bundle_adjust(&camera, &labels, &points, &[o(2, 0)], &AdjustmentOptions::default()).expect_err("kf 2");
    assert!(err.to_string().contains("observations[0]"), "{err}");
    let start = (&labels[..], &SE3::identity());
    let options = AdjustmentOptions::default();
    let err =
        bundle_adjust_with_candidates(&camera, &labels, start, &points, &[o(1, 0)], &[o(0, 0), o(0, 1)], &options)
            .expect_err("point 1");
    assert!(err.to_string().contains("candidates[1]"), "{err}");
    let bad = AdjustmentOptions { readmit_px: f64::NAN, ..AdjustmentOptions::default() };
    assert!(bad.check().expect_err("nan").to_string().contains("readmit_px"));
    let err = bundle_adjust(&camera, &[], &points, &[], &AdjustmentOptions::default()).expect_err("empty");
    assert!(err.to_string().contains("labels"), "{err}");
    let bad = AdjustmentOptions { pixel_sigma_px: 0.0, ..AdjustmentOptions::default() };
    assert!(bad.check().expect_err("σ").to_string().contains("pixel_sigma_px"));
    let bad = AdjustmentOptions {
        label_sigma: Some(LabelSigma { translation_m: f64::NAN, rotation_rad: 1.0 }),
        ..AdjustmentOptions::default()
    };
    assert!(bad.check().expect_err("nan").to_string().contains("label_sigma"));
    // σ whose σ⁻² over- or underflows the normal equations (a denormal σ makes every cost infinite)
    let bad = AdjustmentOptions { pixel_sigma_px: 5e-324, ..AdjustmentOptions::default() };
    assert!(bad.check().expect_err("denormal").to_string().contains("pixel_sigma_px"));
    let bad = AdjustmentOptions {
        label_sigma: Some(LabelSigma { translation_m: 0.02, rotation_rad: 1e300 }),
        ..AdjustmentOptions::default()
    };
    assert!(bad.check().expect_err("huge").to_string().contains("label_sigma"));
    let tiny = Observation { sigma: 1e-12, ..o(0, 0) };
    let err =
        bundle_adjust(&camera, &labels, &points, &[o(1, 0), tiny], &AdjustmentOptions::default()).expect_err("σ_o");
    assert!(err.to_string().contains("observations[1]"), "{err}");
    // a pixel whose squared residual at the start overflows: named as that observation
    let far = Observation { pixel: Vector2::new(1e300, 240.0), ..o(0, 0) };
    let err =
        bundle_adjust(&camera, &labels, &points, &[o(1, 0), far], &AdjustmentOptions::default()).expect_err("far");
    assert!(err.to_string().contains("observations[1]"), "{err}");
}

/// n poses 10 cm apart along x, unrotated: a path for the label-σ and τ tests, whose
/// corrections do not depend on it.
fn poses_along_x(n: usize) -> Vec<SE3> {
    (0..n).map(|k| SE3::new(SO3::identity(), Vector3::new(0.1 * k as f64, 0.0, 0.0))).collect()
}

/// τ against the closed form of an AR(1) sequence, (1 + φ)/(1 − φ), and thinning: keyframes
/// closer than the spacing are not counted.
#[test]
fn correlation_length_of_an_ar1_sequence() {
    let mut rng = SplitMix64::new(21);
    let n = 4000;
    let adjusted = poses_along_x(n);
    for phi in [0.0f64, 0.5, 0.8] {
        let mut e = Vector6::zeros();
        let labels: Vec<SE3> = adjusted
            .iter()
            .map(|b| {
                let fresh = Vector6::from_fn(|_, _| rng.normal() * 0.01);
                e = e * phi + fresh * (1.0 - phi * phi).sqrt();
                *b * SE3::exp(&e).inverse()
            })
            .collect();
        let (tt, tr) = correlation_lengths(&labels, &adjusted);
        let want = (1.0 + phi) / (1.0 - phi);
        for got in [tt, tr] {
            assert!((got / want - 1.0).abs() < 0.2, "φ = {phi}: τ {got}, closed form {want}");
        }
    }
    // the same sequence with each keyframe repeated 4 times 1 cm apart gives the same τ
    let dense: Vec<SE3> = (0..4 * n / 4)
        .map(|k| SE3::new(SO3::identity(), Vector3::new(0.1 * (k / 4) as f64 + 0.01 * (k % 4) as f64, 0.0, 0.0)))
        .collect();
    let labels: Vec<SE3> =
        dense.iter().map(|b| *b * SE3::exp(&(Vector6::from_fn(|_, _| rng.normal()) * 0.01))).collect();
    let (tt, _) = correlation_lengths(&labels, &dense);
    assert!(tt < 1.3, "repeated keyframes counted: τ {tt}");
}

/// The labels' σ over the corrections a prior holds: independent label noise of σ 1 cm / 0.01
/// rad per axis with a fifth of 5000 labels displaced by 20 σ. Over all corrections the
/// median of ‖e‖² is the 0.5/0.8 quantile of the others' χ²₃ (closed form: σ × 1.117);
/// without the displaced ones it is the median (σ within the sampling error, ≈ 1.5 %).
#[test]
fn the_labels_sigma_is_not_moved_by_a_displaced_run() {
    use crate::stats::chi2::{CHI2_3_MEDIAN, quantile};
    let mut rng = SplitMix64::new(29);
    let n = 5000;
    let adjusted = poses_along_x(n);
    let sigma = 0.01;
    let labels: Vec<SE3> = adjusted
        .iter()
        .enumerate()
        .map(|(k, b)| {
            let noise = Vector6::from_fn(|_, _| rng.normal() * sigma);
            let run = if k % 5 == 0 { Vector6::repeat(20.0 * sigma) } else { Vector6::zeros() };
            *b * SE3::exp(&(noise + run)).inverse()
        })
        .collect();
    let all = estimate_label_sigma(&labels, &adjusted);
    let moved = (quantile(3, 0.5 / 0.8) / CHI2_3_MEDIAN).sqrt();
    for got in [all.translation_m, all.rotation_rad] {
        assert!((got / (sigma * moved) - 1.0).abs() < 0.03, "over all: {got}, closed form {}", sigma * moved);
    }
    let prior = LabelSigma { translation_m: 3.0 * sigma, rotation_rad: 3.0 * sigma };
    let held = estimate_label_sigma_within(&labels, &adjusted, Some(prior));
    for got in [held.translation_m, held.rotation_rad] {
        assert!((got / sigma - 1.0).abs() < 0.03, "held: {got}");
    }
    assert_eq!(estimate_label_sigma_within(&labels, &adjusted, None), all);
}

/// τ over the corrections a prior holds: independent label noise with a run of 40 of 1000
/// labels displaced together by 20 σ reads as a long correlation over all corrections and
/// as none without the run — which a prior of the scatter times √τ holds as outliers.
#[test]
fn a_displaced_run_is_not_counted_as_drift() {
    let mut rng = SplitMix64::new(23);
    let n = 1000;
    let adjusted = poses_along_x(n);
    let labels: Vec<SE3> = adjusted
        .iter()
        .enumerate()
        .map(|(k, b)| {
            let noise = Vector6::from_fn(|_, _| rng.normal() * 0.01);
            let run = if (500..540).contains(&k) { Vector6::repeat(0.2) } else { Vector6::zeros() };
            *b * SE3::exp(&(noise + run)).inverse()
        })
        .collect();
    let all = correlation_lengths(&labels, &adjusted);
    assert_eq!(all, correlation_lengths_within(&labels, &adjusted, None));
    assert!(all.0 > 10.0 && all.1 > 10.0, "τ over all corrections {all:?}");
    let scatter = 0.01;
    let prior = LabelSigma { translation_m: scatter * all.0.sqrt(), rotation_rad: scatter * all.1.sqrt() };
    let (tt, tr) = correlation_lengths_within(&labels, &adjusted, Some(prior));
    assert!(tt < 1.3 && tr < 1.3, "τ without the run ({tt}, {tr})");
}
