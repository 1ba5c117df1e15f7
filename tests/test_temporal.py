"""Keyframes, the motion model and fusion through the Python API."""

from __future__ import annotations

import numpy as np
import pytest

import geoloc
from geoloc import geometry, lie
from geoloc.montecarlo import CHI2_6DOF_95


def _track(n: int, step: float = 0.02) -> np.ndarray:
    return lie.se3_exp(np.c_[np.arange(n) * step, np.zeros((n, 5))])


def test_keyframe_score_known_values_and_broadcast() -> None:
    T = _track(3, 0.1)
    assert geometry.keyframe_score(T[0], T[1]) == pytest.approx(1.0)
    assert geometry.keyframe_score(T[0], T[0]) == pytest.approx(np.exp(-0.25))
    rot6 = np.eye(4)
    rot6[:3, :3] = lie.so3_exp([0, np.radians(6), 0])
    rot6[0, 3] = 0.1
    assert geometry.keyframe_score(np.eye(4), rot6) == pytest.approx(0.5, rel=1e-9)
    assert geometry.keyframe_score(np.eye(4), T).shape == (3,)


def test_select_keyframes_matches_the_paper_layout() -> None:
    poses = _track(200)
    np.testing.assert_array_equal(geometry.select_keyframes(poses, 100), [85, 90, 95, 100, 105, 110, 115])
    assert geometry.select_keyframes(poses, 0).tolist()[0] == 0
    with pytest.raises(geoloc.InvalidInputError, match="k: 200 is out of range"):
        geometry.select_keyframes(poses, 200)
    with pytest.raises(geoloc.InvalidInputError, match="k: expected a non-negative integer"):
        geometry.select_keyframes(poses, -1)


def test_motion_prediction_is_exact_for_constant_velocity_and_calibrated() -> None:
    rng = np.random.default_rng(0)
    times = np.array([0.0, 1 / 30, 2 / 30, 4 / 30])  # a dropped frame
    sig = 0.01
    cov = np.eye(6) * sig**2
    inside, trials = 0, 1000
    for _ in range(trials):
        start = lie.se3_exp(rng.normal(size=6))
        v = rng.normal(size=6) * 0.5
        truth = lie.se3_compose(start, lie.se3_exp(np.outer(times, v)))
        noisy = lie.se3_compose(truth, lie.se3_exp(rng.normal(size=(4, 6)) * sig))
        p = geoloc.motion_predict(noisy, times, 5 / 30, covariances=np.stack([cov] * 4))
        e = lie.se3_log(lie.se3_inverse(start @ lie.se3_exp(v * 5 / 30)) @ p.pose)
        inside += e @ np.linalg.solve(p.covariance, e) <= CHI2_6DOF_95
    assert 0.92 <= inside / trials <= 0.98
    exact = geoloc.motion_predict(truth, times, 0.2, covariances=np.stack([cov] * 4))
    np.testing.assert_allclose(exact.pose, start @ lie.se3_exp(v * 0.2), atol=1e-9)
    np.testing.assert_allclose(exact.velocity, v, atol=1e-8)


def test_motion_process_noise_adds_the_closed_form() -> None:
    """acceleration_psd q adds Q(τ) = diag(q)(τ³/3 + τ²T_w/3) to the covariance, nothing to the pose."""
    times = np.array([0.0, 1 / 30, 2 / 30, 4 / 30])
    poses = lie.se3_exp(np.outer(times, [0.3, 0.0, 0.1, 0.0, 0.2, 0.0]))
    cov = np.stack([np.eye(6) * 1e-4] * 4)
    q = np.array([0.5, 0.4, 0.3, 0.02, 0.03, 0.04])
    plain = geoloc.motion_predict(poses, times, 0.25, covariances=cov)
    noisy = geoloc.motion_predict(poses, times, 0.25, covariances=cov, acceleration_psd=q)
    tau, window = 0.25 - 4 / 30, 4 / 30
    np.testing.assert_allclose(noisy.covariance - plain.covariance, np.diag(q * (tau**3 / 3 + tau**2 * window / 3)), atol=1e-15)
    np.testing.assert_array_equal(noisy.pose, plain.pose)
    with pytest.raises(geoloc.InvalidInputError, match="acceleration_psd"):
        geoloc.motion_predict(poses, times, 0.25, covariances=cov, acceleration_psd=-q)
    with pytest.raises(geoloc.InvalidInputError, match="acceleration_psd"):
        geoloc.motion_predict(poses, times, 0.25, covariances=cov, acceleration_psd=q[:5])


def test_motion_velocity_prior_is_the_bayesian_linear_fit() -> None:
    """Translation-only poses along x make the fit linear: (p_r, v) minimize
    ‖y − A(p_r, v)‖²/σ² + (v − μ)²/s, solved here by numpy's lstsq on the stacked, whitened
    rows (an independent solve of the same problem); the prediction at t_q is p_r + (t_q − t_r)v."""
    times = np.array([0.0, 1 / 30, 2 / 30, 3 / 30])
    x = np.array([0.0, 0.02, 0.01, 0.05])  # noisy positions, m
    poses = np.stack([np.eye(4)] * 4)
    poses[:, 0, 3] = x
    sigma, mu, s = 0.01, np.array([0.3, 0, 0, 0, 0, 0]), np.full(6, 0.01)
    cov = np.stack([np.eye(6) * sigma**2] * 4)
    p = geoloc.motion_predict(poses, times, 4 / 30, covariances=cov, velocity_mean=mu, velocity_variance=s)
    a = np.vstack([np.column_stack([np.ones(4), times - times[-1]]) / sigma, [0.0, 1 / np.sqrt(s[0])]])
    y = np.concatenate([x / sigma, [mu[0] / np.sqrt(s[0])]])
    (pr, v), *_ = np.linalg.lstsq(a, y, rcond=None)
    np.testing.assert_allclose(p.pose[0, 3], pr + v / 30, atol=1e-10)
    np.testing.assert_allclose(p.velocity[0], v, atol=1e-8)
    g = np.array([1.0, 1 / 30])
    np.testing.assert_allclose(p.covariance[0, 0], g @ np.linalg.inv(a.T @ a) @ g, rtol=1e-8)
    without = geoloc.motion_predict(poses, times, 4 / 30, covariances=cov)
    assert abs(without.velocity[0] - v) > 0.05  # the prior matters here
    for kwargs, name in (({"velocity_variance": -s}, "velocity_variance"), ({"velocity_mean": mu[:5]}, "velocity_mean"),
                         ({"velocity_mean": np.full(6, np.inf), "velocity_variance": s}, "velocity_mean")):
        with pytest.raises(geoloc.InvalidInputError, match=name):
            geoloc.motion_predict(poses, times, 0.2, covariances=cov, **kwargs)


def test_motion_bad_input() -> None:
    poses = _track(3)
    with pytest.raises(geoloc.InvalidInputError, match=r"timestamps: expected shape \(3,\)"):
        geoloc.motion_predict(poses, [0.0, 0.1], 0.3)
    with pytest.raises(geoloc.InvalidInputError, match="timestamps: must be distinct"):
        geoloc.motion_predict(poses, [0.0, 0.1, 0.1], 0.3)
    with pytest.raises(geoloc.InvalidInputError, match="need at least 3 poses"):
        geoloc.motion_predict(poses[:2], [0.0, 0.1], 0.3)
    with pytest.raises(geoloc.InvalidInputError, match="covariances"):
        geoloc.motion_predict(poses, [0.0, 0.1, 0.2], 0.3, covariances=np.zeros((3, 6, 6)))
    with pytest.raises(geoloc.InvalidInputError, match="t_query"):
        geoloc.motion_predict(poses, [0.0, 0.1, 0.2], [0.3, 0.4])


def test_fusion_gates_a_ten_sigma_outlier_and_fuses_otherwise() -> None:
    cov = np.eye(6) * 1e-4
    far = lie.se3_exp([0.1, 0, 0, 0, 0, 0])
    for gate in ("isometric", "chi2"):
        r = geoloc.fuse(np.eye(4), cov, far, cov, gate=gate)
        assert r.source == "motion"
        np.testing.assert_array_equal(r.pose, np.eye(4))
    near = lie.se3_exp([0.01, 0, 0, 0, 0, 0])
    r = geoloc.fuse(np.eye(4), cov, near, cov)
    assert r.source == "fused"
    assert r.pose[0, 3] == pytest.approx(0.005, abs=1e-9)
    np.testing.assert_allclose(r.covariance, cov / 2, atol=1e-9)  # J_r⁻¹ at ±5 mm: 1e-5 relative
    with pytest.raises(geoloc.InvalidInputError, match="cov_g: is not positive definite"):
        geoloc.fuse(np.eye(4), cov, near, np.zeros((6, 6)))
    with pytest.raises(geoloc.InvalidInputError, match="gate: expected"):
        geoloc.fuse(np.eye(4), cov, near, cov, gate="max")  # type: ignore[arg-type]
    with pytest.raises(geoloc.InvalidInputError, match=r"pose_m: expected shape \(4, 4\)"):
        geoloc.fuse(np.stack([np.eye(4)] * 2), cov, near, cov)


# --- bad inputs ---------------------------------------------------------------------


def test_motion_predict_refuses_an_overflowing_query_time() -> None:
    with pytest.raises(geoloc.InvalidInputError, match="t_query: is 1e300 s from the latest"):
        geoloc.motion_predict(_track(4), [0.0, 0.1, 0.2, 0.3], 1e300)


def test_negative_pose_covariances_are_refused() -> None:
    covs = np.tile(np.eye(6) * 1e-4, (4, 1, 1))
    covs[1] = -covs[1]
    with pytest.raises(geoloc.InvalidInputError, match=r"covariances\[1\]: is not positive semi-definite"):
        geoloc.motion_predict(_track(4), [0.0, 0.1, 0.2, 0.3], 0.4, covs)
    T = _track(2)
    with pytest.raises(geoloc.InvalidInputError, match="cov_g: is not positive semi-definite"):
        geoloc.fuse(T[0], np.eye(6) * 1e-4, T[1], -np.eye(6) * 1e-4)


def test_results_report_their_solve() -> None:
    T = _track(4)
    pred = geoloc.motion_predict(T, [0.0, 0.1, 0.2, 0.3], 0.4, np.tile(np.eye(6) * 1e-4, (4, 1, 1)))
    assert pred.termination == "step_converged" and pred.iterations >= 1
    fused = geoloc.fuse(pred.pose, pred.covariance, pred.pose, pred.covariance)
    assert fused.source == "fused" and fused.termination == "step_converged"
    gated = geoloc.fuse(T[0], np.eye(6) * 1e-6, T[3], np.eye(6) * 1e-6)
    assert gated.source == "motion" and gated.iterations == 0 and gated.termination is None


def test_select_keyframes_counts_are_checked() -> None:
    with pytest.raises(geoloc.InvalidInputError, match="n: "):
        geometry.select_keyframes(_track(5), 2, n=2**70)
    expected = geometry.select_keyframes(_track(5), 2, n=3).tolist()
    assert geometry.select_keyframes(_track(5), np.int64(2), n=np.int64(3)).tolist() == expected
