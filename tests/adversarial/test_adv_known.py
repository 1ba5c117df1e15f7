"""Regression tests for the defects the adversarial suite found in fusion.py, motion.rs,
localizer.py and mapping.py while other work was under way there (each was a strict xfail
until it was fixed)."""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
import pytest

import geoloc
from geoloc import Localizer, Map

TRACK = np.repeat(np.eye(4)[None], 4, axis=0)
TRACK[:, 0, 3] = 0.05 * np.arange(4)
COV = np.repeat(np.diag([1e-4] * 3 + [1e-5] * 3)[None], 4, axis=0)
P_G = np.eye(4)
P_G[0, 3] = 0.005
CAM = geoloc.Camera(525, 525, 320, 240)
_rng = np.random.default_rng(0)
KPS = [_rng.uniform(0, 480, size=(40, 2)) for _ in range(3)]
DESCS = [_rng.integers(0, 256, size=(40, 32), dtype=np.uint8) for _ in range(3)]


def _rejects(call: Callable[[], Any], name: str) -> None:
    with pytest.raises(geoloc.InvalidInputError, match=name):
        call()


def _finite_prediction(call: Callable[[], Any]) -> None:
    try:
        r = call()
    except geoloc.InvalidInputError:
        return
    assert np.isfinite(r.pose).all() and np.isfinite(r.covariance).all()



@pytest.mark.parametrize("gate", [1, None, b"isometric", True])
def test_fuse_gate_not_a_string(gate: Any) -> None:
    _rejects(lambda: geoloc.fuse(np.eye(4), COV[0], P_G, COV[0], gate=gate), "gate")


@pytest.mark.parametrize("gate_sigma", [None, [1.0]])
def test_fuse_gate_sigma_not_a_number(gate_sigma: Any) -> None:
    _rejects(lambda: geoloc.fuse(np.eye(4), COV[0], P_G, COV[0], gate_sigma=gate_sigma), "gate_sigma")


def test_motion_denormal_timestamps() -> None:
    _finite_prediction(lambda: geoloc.motion_predict(TRACK, [0.0, 1e-321, 2e-321, 3e-321], 0.4))


@pytest.mark.parametrize("scale", [1e-310, "one entry 1e-320"])
def test_motion_denormal_covariances(scale: Any) -> None:
    covs = COV.copy()
    if scale == "one entry 1e-320":
        covs[0, 0, 0] = 1e-320
    else:
        covs = covs * scale
    _finite_prediction(lambda: geoloc.motion_predict(TRACK, [0.0, 0.1, 0.2, 0.3], 0.4, covariances=covs))


def test_feature_map_keypoints_not_a_sequence() -> None:
    _rejects(lambda: Map.from_features(CAM, TRACK[:3], 0, DESCS, estimate_noise=False, refine_intrinsics=False, adjust_labels=False), "keypoints")


def test_feature_localizer_max_residual_none() -> None:
    fm = Map.from_features(CAM, TRACK[:3], KPS, DESCS, branching=3, depth=2, estimate_noise=False, refine_intrinsics=False, adjust_labels=False)
    _rejects(lambda: Localizer(fm, max_residual="5"), "max_residual")  # type: ignore[arg-type]


@pytest.mark.parametrize("path", [924, None])
def test_map_load_not_a_path(path: Any) -> None:
    _rejects(lambda: geoloc.Map.load(path), "path")


def test_map_localizer_timestamp_none() -> None:
    seq = geoloc.datasets.synthetic_room(n_frames=12, seed=0)
    m = geoloc.Map.build(seq[:10], n_features=300, branching=4, depth=2)
    _rejects(lambda: geoloc.Localizer(m).localize(seq[11].image, None), "timestamp")  # type: ignore[arg-type]


def test_fuse_denormal_covariance_names_cov_m() -> None:
    _rejects(lambda: geoloc.fuse(np.eye(4), COV[0] * 1e-310, P_G, COV[0] * 2), "cov_m")


def test_summarize_names_covariances_when_their_sigma_overflows():
    """Found by the long profile: covariances of 1e296 were blamed on an argument "cov"."""
    poses = np.repeat(np.eye(4)[None], 5, axis=0)
    covs = np.repeat((np.eye(6) * 1e296)[None], 5, axis=0)
    with pytest.raises(geoloc.InvalidInputError, match=r"^covariances"):
        geoloc.evaluation.summarize(poses, poses, covariances=covs, timestamps=[0.0, 1.0, 2.0, 3.0, 4.0])


def test_se3_distance_that_overflows_is_refused_not_infinite():
    """Found by the long profile: finite poses 2e308 apart gave an infinite distance."""
    a, b = np.eye(4), np.eye(4)
    a[0, 3], b[0, 3] = 1e308, -1e308
    _rejects(lambda: geoloc.lie.se3_distance(a, b), "T1, T2")
    assert geoloc.lie.se3_distance(np.eye(4), np.eye(4)) == 0.0


def test_nees_of_a_covariance_at_underflow_is_refused_not_infinite():
    """Found by the long profile: a positive definite but subnormal covariance gave NEES = inf."""
    truth = np.eye(4)
    truth[0, 3] = 1e-3
    _rejects(lambda: geoloc.evaluation.nees(np.eye(4)[None], (np.eye(6) * 1e-320)[None], truth[None]), r"cov\[0\]")
