"""geoloc.geometry through the bindings: exact recovery, robustness, calibration on random
scenes (a smaller Monte-Carlo than the Rust suite), and bad inputs."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

import geoloc
from geoloc import geometry, lie
from geoloc.montecarlo import CHI2_6DOF_95, look_at

CAM = geoloc.Camera(525.0, 525.0, 320.0, 240.0)
Array = NDArray[np.float64]


def _project(T: Array, pts: Array) -> Array:
    p = lie.se3_transform_points(lie.se3_inverse(T), pts)
    return p[:, :2] / p[:, 2:] * 525.0 + [320.0, 240.0]


def _random_view(rng: np.random.Generator, n: int) -> tuple[Array, Array]:
    T = lie.se3_exp(np.r_[rng.uniform(-5, 5, 3), rng.normal(size=3)])
    uv = rng.uniform([0, 0], [640, 480], (n, 2))
    z = rng.uniform(2, 8, (n, 1))
    p_cam = np.hstack([(uv - [320, 240]) / 525.0, np.ones((n, 1))]) * z
    return T, lie.se3_transform_points(T, p_cam)


def test_solve_pnp_exact_and_from_init() -> None:
    rng = np.random.default_rng(0)
    T, pts = _random_view(rng, 40)
    px = _project(T, pts)
    res = geometry.solve_pnp(pts, px, CAM)
    assert res.success and res.reason == "ok"
    np.testing.assert_allclose(res.pose, T, atol=1e-8)
    assert res.inliers.all() and res.rms < 1e-6
    init = T @ lie.se3_exp([0.05, -0.02, 0.03, 0.02, 0.01, -0.02])
    res2 = geometry.solve_pnp(pts, px, CAM, init_pose=init, ransac=False)
    np.testing.assert_allclose(res2.pose, T, atol=1e-8)
    assert res2.ransac_iterations == 0


def test_solve_pnp_pixel_sigmas_weight_each_correspondence() -> None:
    """Half the pixels 4× noisier: with their σ the pose is more accurate and its covariance
    calibrated (small Monte-Carlo; the Rust suite has the closed form and 1000 trials)."""
    rng = np.random.default_rng(7)
    sq = {True: [], False: []}
    inside = 0
    for _ in range(150):
        T, pts = _random_view(rng, 60)
        sig = np.where(np.arange(60) % 2 == 0, 1.0, 4.0)
        px = _project(T, pts) + rng.normal(size=(60, 2)) * sig[:, None]
        for weighted in (True, False):
            res = geometry.solve_pnp(pts, px, CAM, pixel_sigmas=sig if weighted else None)
            assert res.success
            sq[weighted].append(np.sum((res.pose[:3, 3] - T[:3, 3]) ** 2))
            if weighted:
                e = lie.se3_log(lie.se3_inverse(T) @ res.pose)
                inside += float(e @ np.linalg.solve(res.covariance, e)) <= CHI2_6DOF_95
    assert np.sqrt(np.mean(sq[True])) < 0.8 * np.sqrt(np.mean(sq[False]))
    assert 0.90 <= inside / 150 <= 0.99


def test_solve_pnp_forty_percent_outliers() -> None:
    rng = np.random.default_rng(1)
    ok = 0
    for trial in range(100):
        T, pts = _random_view(rng, 100)
        px = _project(T, pts) + rng.normal(size=(100, 2))
        bad = rng.uniform(size=100) < 0.4
        px[bad] = rng.uniform([0, 0], [640, 480], (bad.sum(), 2))
        res = geometry.solve_pnp(pts, px, CAM, seed=trial)
        err = lie.se3_inverse(T) @ res.pose
        ok += res.success and np.linalg.norm(err[:3, 3]) < 0.05 and lie.rotation_angle(err[:3, :3]) < np.radians(1)
    assert ok >= 98


def test_triangulate_then_locate_is_calibrated_on_random_scenes() -> None:
    """NEES coverage of the propagated covariance over 300 random scenes (σ = 1 px)."""
    rng = np.random.default_rng(7)
    inside = 0
    trials = 300
    for _ in range(trials):
        focus = rng.uniform([-1, -1, 4], [1, 1, 7])
        poses = np.stack([look_at(c, focus) for c in rng.uniform([-1.5, -0.5, -0.3], [1.5, 0.5, 0.3], (5, 3))])
        pts = focus + rng.uniform([-2, -1.5, -1], [2, 1.5, 1], (119, 3))
        cam_ids = np.repeat(np.arange(4), 119)
        track_ids = np.tile(np.arange(119), 4)
        px = np.vstack([_project(poses[k], pts) for k in range(4)]) + rng.normal(size=(476, 2))
        tri = geometry.triangulate(poses[:4], CAM, cam_ids, track_ids, px)
        use = np.flatnonzero(tri.valid)
        q = _project(poses[4], pts[use]) + rng.normal(size=(len(use), 2))
        res = geometry.solve_pnp(tri.points[use], q, CAM, uncertainty=tri.uncertainty(use))
        assert res.success, res.reason
        e = lie.se3_log(lie.se3_inverse(poses[4]) @ res.pose)
        inside += e @ np.linalg.solve(res.covariance, e) <= CHI2_6DOF_95
    assert 0.91 <= inside / trials <= 0.99, inside / trials


def test_paper_covariance_is_selectable_and_different() -> None:
    rng = np.random.default_rng(3)
    T, pts = _random_view(rng, 60)
    px = _project(T, pts) + rng.normal(size=(60, 2))
    a = geometry.solve_pnp(pts, px, CAM, covariance="paper")
    b = geometry.solve_pnp(pts, px, CAM, covariance="propagated")
    assert a.success and b.success
    assert not np.allclose(a.covariance, b.covariance)
    for r in (a, b):
        assert np.allclose(r.covariance, r.covariance.T)
        assert np.all(np.linalg.eigvalsh(r.covariance) > 0)
        assert r.sigma_p > 0 and r.sigma_r > 0


def test_degenerate_geometry_fails_with_a_reason() -> None:
    pts = np.c_[np.linspace(-1, 1, 20), np.zeros(20), np.full(20, 5.0)]
    px = _project(np.eye(4), pts)
    res = geometry.solve_pnp(pts, px, CAM)
    assert not res.success and res.reason
    res = geometry.solve_pnp(pts[:3], px[:3], CAM)
    assert not res.success and "too few" in res.reason
    assert not res.inliers.any() and np.isnan(res.rms)


def test_triangulate_reasons_and_outputs() -> None:
    poses = np.stack([look_at(np.array([x, 0.0, 0.0]), np.array([0.0, 0.0, 5.0])) for x in (-0.5, 0.0, 0.5)])
    pts = np.array([[0.0, 0.0, 5.0], [0.3, 0.2, 4.0], [0.0, 0.0, 5000.0]])
    cam_ids = np.array([0, 1, 2, 0, 0, 2])
    track_ids = np.array([0, 0, 0, 1, 2, 2])
    px = np.vstack([_project(poses[c], pts[t][None]) for c, t in zip(cam_ids, track_ids)])
    tri = geometry.triangulate(poses, CAM, cam_ids, track_ids, px)
    assert tri.points.shape == (3, 3) and tri.covariances.shape == (3, 3, 3)
    assert tri.pose_jacobians is None
    with_covs = geometry.triangulate(poses, CAM, cam_ids, track_ids, px, pose_covariances=np.tile(np.eye(6) * 1e-6, (3, 1, 1)))
    assert with_covs.pose_jacobians is not None and with_covs.pose_jacobians.shape == (3, 3, 3, 6)
    assert np.abs(with_covs.pose_jacobians[0]).max() > 0 and not with_covs.pose_jacobians[1].any()
    assert with_covs.uncertainty([0]).pose_jacobians is not None
    np.testing.assert_allclose(tri.points[0], pts[0], atol=1e-9)
    assert tri.reasons() == ["ok", "fewer than two inlier views", "triangulation angle below min_angle"]
    assert list(tri.valid) == [True, False, False]
    assert tri.observation_inliers.tolist() == [True, True, True, False, False, False]
    unc = tri.uncertainty([0])
    assert unc.covariances.shape == (1, 3, 3) and unc.pose_jacobians is None


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"points3d": np.zeros((5, 2))}, r"points3d: expected shape \(N, 3\)"),
        ({"pixels": np.zeros((4, 2))}, r"pixels: expected shape \(5, 2\)"),
        ({"pixels": np.full((5, 2), np.nan)}, r"pixels\[0\] holds a non-finite value"),
        ({"points3d": np.full((5, 3), np.inf)}, r"points3d\[0\] holds a non-finite value"),
        ({"pixels": np.array([["a", "b"]] * 5)}, "pixels: expected real numbers"),
        ({"covariance": "exact"}, "covariance: expected"),
        ({"ransac": False}, "init_pose: required"),
        ({"init_pose": np.eye(3)}, r"init_pose: expected shape"),
        ({"init_pose": np.diag([2.0, 1, 1, 1])}, "init_pose is not a rigid transform"),
        ({"huber": 0.0}, "huber: expected a finite number > 0"),
        ({"pixel_sigma": -1.0}, "pixel_sigma"),
        ({"point_covariances": np.zeros((4, 3, 3))}, r"point_covariances: expected shape \(5, 3, 3\)"),
        ({"point_covariances": np.tile(np.array([[1.0, 2, 0], [0, 1, 0], [0, 0, 1]]), (5, 1, 1))}, "symmetric"),
        ({"loss": "tukey"}, "loss: expected one of"),
        ({"seed": -1}, "seed: expected a non-negative integer"),
        ({"confidence": 1.0}, "confidence: must be in"),
        ({"cam": (525, 525, 320, 240)}, "cam: expected a geoloc.Camera"),
        ({"pixel_sigmas": np.ones(4)}, r"pixel_sigmas: expected shape \(5,\)"),
        ({"pixel_sigmas": np.array([1.0, 1, 1, 1, 0])}, "pixel_sigmas: entry 4 must be finite and > 0"),
        ({"pixel_sigmas": np.array([1.0, 1, np.nan, 1, 1])}, "pixel_sigmas: entry 2 must be finite and > 0"),
        ({"pixel_sigmas": np.array(["a"] * 5)}, "pixel_sigmas: expected real numbers"),
    ],
)
def test_solve_pnp_bad_input(kwargs: dict[str, object], match: str) -> None:
    args: dict[str, object] = {"points3d": np.ones((5, 3)) + np.arange(5)[:, None], "pixels": np.ones((5, 2)), "cam": CAM}
    args.update(kwargs)
    with pytest.raises(geoloc.InvalidInputError, match=match):
        geometry.solve_pnp(**args)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"cam_ids": np.array([0, 5])}, r"cam_ids\[1\] = 5 but there are 2 poses"),
        ({"cam_ids": np.array([0, -1])}, r"cam_ids\[1\] = -1 is negative"),
        ({"cam_ids": np.array([0.0, 1.0])}, "cam_ids: expected integer indices"),
        ({"track_ids": np.array([0])}, r"track_ids: expected shape \(2,\)"),
        ({"poses": np.eye(4)}, r"poses: expected shape \(C, 4, 4\)"),
        ({"pose_covariances": np.zeros((3, 6, 6))}, r"pose_covariances: expected shape \(2, 6, 6\)"),
        ({"max_residual": np.inf}, "max_residual"),
    ],
)
def test_triangulate_bad_input(kwargs: dict[str, object], match: str) -> None:
    args: dict[str, object] = {
        "poses": np.stack([np.eye(4), lie.se3_exp([1.0, 0, 0, 0, 0, 0])]),
        "cam": CAM,
        "cam_ids": np.array([0, 1]),
        "track_ids": np.array([0, 0]),
        "pixels": np.array([[320.0, 240.0], [300.0, 240.0]]),
    }
    args.update(kwargs)
    with pytest.raises(geoloc.InvalidInputError, match=match):
        geometry.triangulate(**args)  # type: ignore[arg-type]


def test_camera_validation_and_undistort_without_distortion() -> None:
    with pytest.raises(geoloc.InvalidInputError, match="fx: focal length must be > 0"):
        geoloc.Camera(0, 1, 0, 0)
    with pytest.raises(geoloc.InvalidInputError, match="cy: expected a finite number"):
        geoloc.Camera(1, 1, 0, float("nan"))
    with pytest.raises(geoloc.InvalidInputError, match="dist: expected"):
        geoloc.Camera(1, 1, 0, 0, dist=(0.1, 0.2, 0.3))
    cam = geoloc.Camera(500, 500, 320, 240, dist=(0.0, 0.0, 0.0, 0.0))
    assert cam.dist is None
    pts = np.array([[10.0, 20.0]])
    np.testing.assert_array_equal(cam.undistort_points(pts), pts)
    np.testing.assert_array_equal(cam.K, [[500, 0, 320], [0, 500, 240], [0, 0, 1]])


@pytest.mark.parametrize(
    "dist",
    [
        (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0),  # EuRoC cam0: strong barrel
        (0.2624, -0.9531, -0.0054, 0.0026, 1.1633),  # TUM fr1
        (-0.3, 0.1, 0.001, -0.001, 0.0, 0.05, 0.02, 0.01),  # rational (8 coefficients)
    ],
    ids=["euroc", "tum-fr1", "rational"],
)
def test_undistort_points_inverts_the_forward_distortion_over_the_image(dist: tuple[float, ...]) -> None:
    """Against OpenCV's forward model (projectPoints): undistorted pixels on a grid over the
    image, distorted, come back to 1e-5 px. OpenCV's default undistortion (5 fixed-point
    iterations) left EuRoC's corners 0.57 px off."""
    import cv2

    cam = geoloc.Camera(458.654, 457.296, 367.215, 248.375, 752, 480, dist)
    u, v = np.meshgrid(np.linspace(40, 712, 25), np.linspace(30, 450, 15))
    undistorted = np.column_stack([u.ravel(), v.ravel()])
    rays = np.column_stack([(undistorted - [cam.cx, cam.cy]) / [cam.fx, cam.fy], np.ones(len(undistorted))])
    distorted, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), cam.K, np.asarray(dist))
    back = cam.undistort_points(distorted.reshape(-1, 2))
    assert np.abs(back - undistorted).max() < 1e-5


# --- bad inputs, one test each -------------------------------------------------------


def _two_view_tracks(ids: list[int]) -> tuple[Array, NDArray[np.int64], NDArray[np.int64], Array]:
    poses = np.stack([look_at(np.array([x, 0.0, 0.0]), np.array([0.0, 0.0, 5.0])) for x in (-0.5, 0.5)])
    pts = np.array([[0.0, 0.0, 5.0], [0.3, 0.2, 4.0]])
    cam_ids = np.array([0, 1, 0, 1])
    track_ids = np.array([ids[0], ids[0], ids[1], ids[1]], dtype=np.int64)
    px = np.vstack([_project(poses[c], pts[i // 2][None]) for i, c in enumerate(cam_ids)])
    return poses, cam_ids, track_ids, px


@pytest.mark.parametrize("big", [10**9, 2**62])
def test_triangulate_huge_track_ids_cost_no_memory(big: int) -> None:
    poses, cam_ids, track_ids, px = _two_view_tracks([0, big])
    tri = geometry.triangulate(poses, CAM, cam_ids, track_ids, px)
    assert tri.track_ids.tolist() == [0, big] and tri.points.shape == (2, 3)
    dense = geometry.triangulate(poses, CAM, cam_ids, np.array([0, 0, 1, 1]), px)
    np.testing.assert_array_equal(tri.points, dense.points)
    assert tri.rows([big]).tolist() == [1]


def test_solve_pnp_iteration_counts_are_capped() -> None:
    rng = np.random.default_rng(0)
    _, pts = _random_view(rng, 20)
    px = rng.uniform([0, 0], [640, 480], (20, 2))
    with pytest.raises(geoloc.InvalidInputError, match="min_iterations: must be at most 1000000"):
        geometry.solve_pnp(pts, px, CAM, min_iterations=10**9, max_iterations=10**9)
    with pytest.raises(geoloc.InvalidInputError, match="max_iterations: must be at most"):
        geometry.solve_pnp(pts, px, CAM, max_iterations=10**9)


def test_solve_pnp_random_pixels_are_not_a_pose() -> None:
    for seed in range(20):
        rng = np.random.default_rng(seed)
        _, pts = _random_view(rng, 200)
        px = rng.uniform([0, 0], [640, 480], (200, 2))
        res = geometry.solve_pnp(pts, px, CAM, seed=seed)
        assert not res.success, (seed, int(res.inliers.sum()))
        assert "chance" in res.reason or "RANSAC" in res.reason, res.reason


def test_solve_pnp_refuses_negative_covariances() -> None:
    rng = np.random.default_rng(1)
    T, pts = _random_view(rng, 12)
    px = _project(T, pts)
    covs = np.tile(np.eye(3) * 1e-4, (12, 1, 1))
    covs[3] *= -1
    with pytest.raises(geoloc.InvalidInputError, match=r"point_covariances\[3\]: is not positive semi-definite"):
        geometry.solve_pnp(pts, px, CAM, point_covariances=covs)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"seed": 2**70}, "seed: .* is too large"),
        ({"seed": -1}, "seed: expected a non-negative integer"),
        ({"min_iterations": -1}, "min_iterations: expected a non-negative integer"),
        ({"max_iterations": 2**70}, "max_iterations: .* is too large"),
        ({"seed": 1.5}, "seed: expected a non-negative integer"),
    ],
)
def test_solve_pnp_counts_are_checked_not_overflowed(kwargs: dict[str, object], match: str) -> None:
    rng = np.random.default_rng(2)
    T, pts = _random_view(rng, 12)
    with pytest.raises(geoloc.InvalidInputError, match=match):
        geometry.solve_pnp(pts, _project(T, pts), CAM, **kwargs)  # type: ignore[arg-type]


def test_solve_pnp_accepts_numpy_integers() -> None:
    rng = np.random.default_rng(3)
    T, pts = _random_view(rng, 30)
    res = geometry.solve_pnp(pts, _project(T, pts), CAM, seed=np.int64(5), min_iterations=np.uint16(10))
    assert res.success and res.pose.shape == (4, 4) and res.covariance.shape == (6, 6)


def test_solve_pnp_ransac_flag_with_an_initial_pose() -> None:
    """ransac=True with init_pose also runs RANSAC and keeps the better start; the default
    (None) trusts the initial pose; ransac=False needs one."""
    rng = np.random.default_rng(4)
    T, pts = _random_view(rng, 60)
    px = _project(T, pts) + rng.normal(size=(60, 2))
    wrong = T @ lie.se3_exp([0.0, 0.0, 0.0, 0.0, np.pi, 0.0])
    both = geometry.solve_pnp(pts, px, CAM, init_pose=wrong, ransac=True)
    assert both.success and both.ransac_iterations > 0
    assert np.linalg.norm(both.pose[:3, 3] - T[:3, 3]) < 0.05
    trusted = geometry.solve_pnp(pts, px, CAM, init_pose=wrong)
    assert trusted.ransac_iterations == 0
    assert not trusted.success or np.linalg.norm(trusted.pose[:3, 3] - T[:3, 3]) > 0.05
    good = geometry.solve_pnp(pts, px, CAM, init_pose=T, ransac=True)
    plain = geometry.solve_pnp(pts, px, CAM, init_pose=T)
    np.testing.assert_allclose(good.pose, plain.pose, atol=1e-5)  # same optimum from either start


def test_track_status_texts_come_from_core() -> None:
    assert geometry.TRACK_STATUS[0] == "ok"
    assert geometry.TRACK_STATUS[6] == "only two of three or more views agree"
    assert sorted(geometry.TRACK_STATUS) == list(range(7))
