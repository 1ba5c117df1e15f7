"""geoloc.adjustment.bundle_adjust: the labels' adjustment as a function, checked against
COLMAP's bundle adjuster (pycolmap + pyceres) on the same problem — the same cost at the
same values, the same minimum — and a map's problem against what its build adjusts."""

from __future__ import annotations

import re
import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from geoloc import InvalidInputError, Map, datasets
from geoloc.adjustment import AdjustmentProblem, bundle_adjust
from geoloc.lie import se3_exp, se3_inverse, se3_log

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
REDKITCHEN = DATA / "7scenes-redkitchen"
INTRINSICS = (525.0, 523.0, 319.5, 239.5)
SIGMA = (0.02, np.radians(1.0))


def _peer() -> Any:
    pytest.importorskip("pycolmap", reason="COLMAP's bundle adjuster is the reference (dev extra)")
    pytest.importorskip("pyceres", reason="COLMAP's cost functions need pyceres (dev extra)")
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import _colmap_adjustment

    return _colmap_adjustment


def _problem(seed: int = 0, n_keyframes: int = 8, n_points: int = 150) -> tuple[AdjustmentProblem, np.ndarray]:
    """Keyframes along 1 m looking at points 2.5–6 m away, 0.5 px noise; the labels sit on a
    sensor 3° and 5 cm from the camera and carry 1 cm / 0.5° of noise each; the points start
    1 cm off; only points two keyframes see. Returns the problem and the true camera poses."""
    rng = np.random.default_rng(seed)
    cams = np.array([se3_exp(np.r_[0.15 * k, 0.02 * np.sin(k), 0.0, 0.01 * k, 0.03 * np.cos(k), 0.0]) for k in range(n_keyframes)])
    points = np.c_[rng.uniform(-2.0, 3.0, n_points), rng.uniform(-1.5, 1.5, n_points), rng.uniform(2.5, 6.0, n_points)]
    offset = se3_exp(np.r_[0.03, -0.02, 0.03, np.radians([2.0, -1.5, 1.5])])  # label_from_cam
    labels = np.array([c @ se3_inverse(offset) @ se3_exp(np.r_[rng.normal(0, 0.01, 3), rng.normal(0, np.radians(0.5), 3)])
                       for c in cams])
    fx, fy, cx, cy = INTRINSICS
    kf, pt, px = [], [], []
    for k, c in enumerate(cams):
        local = (points - c[:3, 3]) @ c[:3, :3]
        uv = np.c_[fx * local[:, 0] / local[:, 2] + cx, fy * local[:, 1] / local[:, 2] + cy] + rng.normal(0, 0.5, (n_points, 2))
        seen = (local[:, 2] > 0.5) & (uv[:, 0] > 0) & (uv[:, 0] < 640) & (uv[:, 1] > 0) & (uv[:, 1] < 480)
        kf += [k] * int(seen.sum())
        pt += list(np.flatnonzero(seen))
        px += list(uv[seen])
    kf_arr, pt_arr, px_arr = np.array(kf), np.array(pt), np.array(px)
    tracked = np.flatnonzero(np.bincount(pt_arr, minlength=n_points) >= 2)  # a point needs two views
    keep = np.isin(pt_arr, tracked)
    renumbered = np.searchsorted(tracked, pt_arr[keep])
    start_points = points[tracked] + rng.normal(0, 0.01, (len(tracked), 3))
    problem = AdjustmentProblem(INTRINSICS, labels, start_points, kf_arr[keep], renumbered, px_arr[keep])
    return problem, cams


def _cost_at(problem: AdjustmentProblem, labels: np.ndarray, offset: np.ndarray, points: np.ndarray) -> float:
    """geoloc's cost function at a state (the start cost of a one-iteration round)."""
    at = AdjustmentProblem(problem.intrinsics, problem.labels, points, problem.obs_keyframes, problem.obs_points,
                           problem.obs_pixels)
    return float(bundle_adjust(at, label_sigma=SIGMA, start=labels, offset=offset, max_iterations=1, outlier_px=1e9).cost[0])


def test_the_cost_is_colmaps_where_the_priors_are_at_their_labels() -> None:
    """At the labels (every prior at zero, X = I) geoloc's cost and COLMAP's (its reprojection
    cost under Huber 2, doubled from Ceres' ½Σρ) agree to rounding: the same residuals, the
    same pinhole, the same kernel."""
    colmap = _peer()
    problem, _ = _problem()
    peer = colmap.colmap_adjustment(problem, SIGMA)
    ours = _cost_at(problem, problem.labels, np.eye(4), problem.points)
    assert ours == pytest.approx(peer.cost(), rel=1e-10)
    assert ours > 100.0  # the start is far from the minimum: the check is not of zeros


def test_away_from_the_labels_the_priors_agree_to_second_order() -> None:
    """COLMAP's prior residual (log(R_B⁻¹R_L), t(B⁻¹L)) is geoloc's −log(L⁻¹B)^∨ to first order:
    with every B moved by 1 cm / 0.5° and X by 2 cm / 1° the two costs differ by far less than
    the priors' share of the cost."""
    colmap = _peer()
    problem, _ = _problem(seed=1)
    rng = np.random.default_rng(7)
    moved = np.array([b @ se3_exp(np.r_[rng.normal(0, 0.01, 3), rng.normal(0, np.radians(0.5), 3)]) for b in problem.labels])
    offset = se3_exp(np.r_[0.02, 0.0, 0.0, np.radians([1.0, 0.0, 0.0])])
    peer = colmap.colmap_adjustment(problem, SIGMA)
    peer.set_state(moved, offset, problem.points)
    ours, theirs = _cost_at(problem, moved, offset, problem.points), peer.cost()
    priors = ours - _cost_at(problem, problem.labels, np.eye(4), problem.points)
    assert abs(ours - theirs) < 1e-3 * abs(priors)


def test_the_minimum_is_colmaps() -> None:
    """From the same start both solvers find the same minimum: camera poses B_k X within
    0.1 mm / 0.005°, the same offset X, costs within 10⁻⁶ (each under both cost functions);
    and that minimum has the true trajectory's shape to 1 cm (relative poses; the offset's
    rotation needs more turning than this path has — the Rust tests recover it). The
    rotation of the whole trajectory is held by the label priors alone, a flat direction: a
    change of its cost by 2·10⁻⁷ turns it by 0.07°, so both run to their own convergence."""
    colmap = _peer()
    problem, truth = _problem(seed=2)
    ours = bundle_adjust(problem, label_sigma=SIGMA, outlier_px=1e9, max_iterations=200)
    peer = colmap.colmap_adjustment(problem, SIGMA)
    summary = peer.solve(threads=1, max_iterations=1000)
    assert str(summary.termination_type).endswith("CONVERGENCE")
    labels, offset, points = peer.state()
    delta = se3_log(se3_inverse(ours.label_poses @ ours.offset) @ (labels @ offset))
    assert np.abs(delta[:, :3]).max() < 1e-4
    assert np.degrees(np.abs(delta[:, 3:]).max()) < 5e-3
    assert np.abs(se3_log((se3_inverse(ours.offset) @ offset)[None])).max() < 1e-4
    theirs = _cost_at(problem, labels, offset, points)
    assert ours.cost[1] == pytest.approx(theirs, rel=1e-6)
    assert ours.cost[1] == pytest.approx(2.0 * summary.final_cost, rel=1e-6)
    # the truth up to the gauge the priors leave: the camera poses' shape
    rel_true = se3_log(se3_inverse(truth[0]) @ truth[1:])
    rel_est = se3_log(se3_inverse(ours.camera_poses[0]) @ ours.camera_poses[1:])
    assert np.abs(rel_est - rel_true).max() < 0.01


def test_keypoint_sigmas_weigh_the_pixel_terms() -> None:
    """With ``obs_sigmas`` s_o the pixel terms are Huber₂(‖π(K, L_k⁻¹P_j) − u_o‖² / s_o²): the
    start cost (priors at zero, X = I) against the sum computed here with numpy; a coarse
    keypoint (s_o > 1) counts for less, so the cost falls."""
    problem, _ = _problem(seed=3)
    rng = np.random.default_rng(5)
    sigmas = 1.2 ** rng.integers(0, 8, len(problem.obs_pixels)).astype(float)
    weighted = AdjustmentProblem(problem.intrinsics, problem.labels, problem.points, problem.obs_keyframes,
                                 problem.obs_points, problem.obs_pixels, obs_sigmas=sigmas)
    fx, fy, cx, cy = problem.intrinsics
    poses = problem.labels[problem.obs_keyframes]
    local = np.einsum("nji,nj->ni", poses[:, :3, :3], problem.points[problem.obs_points] - poses[:, :3, 3])
    uv = np.c_[fx * local[:, 0] / local[:, 2] + cx, fy * local[:, 1] / local[:, 2] + cy]
    s = np.sum((uv - problem.obs_pixels) ** 2, axis=1) / sigmas**2
    expected = float(np.sum(np.where(s <= 4.0, s, 4.0 * np.sqrt(s) - 4.0)))
    cost = bundle_adjust(weighted, label_sigma=SIGMA, max_iterations=1, outlier_px=1e9).cost[0]
    assert cost == pytest.approx(expected, rel=1e-10)
    assert cost < bundle_adjust(problem, label_sigma=SIGMA, max_iterations=1, outlier_px=1e9).cost[0]
    bad = AdjustmentProblem(problem.intrinsics, problem.labels, problem.points, problem.obs_keyframes,
                            problem.obs_points, problem.obs_pixels, obs_sigmas=sigmas[:-1])
    with pytest.raises(InvalidInputError, match="obs_sigmas"):
        bundle_adjust(bad)
    zero = AdjustmentProblem(problem.intrinsics, problem.labels, problem.points, problem.obs_keyframes,
                             problem.obs_points, problem.obs_pixels, obs_sigmas=np.where(np.arange(len(sigmas)) == 3, 0.0, sigmas))
    with pytest.raises(InvalidInputError, match="obs_sigmas: entry 3"):
        bundle_adjust(zero)
    nan = AdjustmentProblem(problem.intrinsics, problem.labels, problem.points, problem.obs_keyframes,
                            problem.obs_points, problem.obs_pixels, obs_sigmas=np.full(len(sigmas), np.nan))
    with pytest.raises(InvalidInputError, match="obs_sigmas"):
        bundle_adjust(nan)


def _replaced(problem: AdjustmentProblem, **changes: Any) -> AdjustmentProblem:
    fields = {k: getattr(problem, k) for k in ("intrinsics", "labels", "points", "obs_keyframes", "obs_points", "obs_pixels")}
    fields.update(changes)
    return AdjustmentProblem(**fields)


@pytest.mark.parametrize(
    ("change", "name"),
    [
        ({"obs_points": np.array([0, 1])}, "obs_points"),
        ({"obs_keyframes": np.full(3, -1)}, "obs_keyframes"),
        ({"points": np.zeros((4, 2))}, "points"),
        ({"obs_pixels": np.zeros((3, 3))}, "obs_pixels"),
        ({"labels": np.eye(4)}, "labels"),
        ({"labels": np.stack([np.eye(4), 2 * np.eye(4)])}, "labels"),
        ({"intrinsics": (525.0, 525.0, 320.0)}, "intrinsics"),
        ({"intrinsics": 525.0}, "intrinsics"),
        ({"intrinsics": (525.0, 525.0, 320.0, "240")}, "intrinsics"),
        ({"intrinsics": (-525.0, 525.0, 320.0, 240.0)}, "f"),
        ({"obs_keyframes": np.array([0, 0, 5])}, "observations[2]"),
        ({"obs_points": np.array([0, 1, 9])}, "observations[2]"),
        ({"points": np.array([[0.0, 0.0, np.nan], [0, 0, 1], [0, 0, 1]])}, "points"),
    ],
)
def test_bad_input_names_the_argument(change: dict[str, Any], name: str) -> None:
    base = AdjustmentProblem(INTRINSICS, np.stack([np.eye(4), np.eye(4)]), np.array([[0.0, 0, 2], [0.1, 0, 2], [0, 0.1, 2]]),
                             np.array([0, 0, 1]), np.array([0, 1, 2]), np.array([[320.0, 240], [340, 240], [320, 250]]))
    with pytest.raises(InvalidInputError, match=re.escape(name)):
        bundle_adjust(_replaced(base, **change))


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"label_sigma": (0.01,)}, "label_sigma"),
        ({"label_sigma": 0.01}, "label_sigma"),
        ({"label_sigma": (0.01, None)}, "label_sigma"),
        ({"label_sigma": (0.0, 0.01)}, "label_sigma"),
        ({"max_iterations": 0}, "max_iterations"),
        ({"outlier_px": float("nan")}, "outlier_px"),
        ({"start": np.eye(4)}, "start"),
        ({"offset": np.zeros((4, 4))}, "offset"),
        ({"pixel_sigma": 0.0}, "pixel_sigma"),
        ({"max_iterations": True}, "max_iterations"),
    ],
)
def test_bad_options_name_the_option(kwargs: dict[str, Any], name: str) -> None:
    problem, _ = _problem(n_keyframes=3, n_points=30)
    with pytest.raises(InvalidInputError, match=name):
        bundle_adjust(problem, **kwargs)
    with pytest.raises(InvalidInputError, match="problem"):
        bundle_adjust({"labels": problem.labels})  # type: ignore[arg-type]


@pytest.mark.skipif(not REDKITCHEN.is_dir(), reason="needs ../shared/data/7scenes-redkitchen")
def test_a_maps_problem_is_the_one_its_build_adjusts() -> None:
    """The problem a map returns, adjusted by the function with σ estimated, gives the build's
    own correction of the labels at the skeleton keyframes (to rounding); an adjusted map has
    no such problem left (its poses are no longer the labels)."""
    seq = datasets.load_7scenes(REDKITCHEN)[0:60]
    options = {"refine_intrinsics": False, "estimate_noise": False, "model": False}
    kept = Map.build(seq, adjust_labels=False, **options)
    problem = kept.label_adjustment_problem()
    assert problem.keyframes is not None and len(problem.keyframes) == len(problem.labels) < len(kept)
    assert np.array_equal(problem.labels, kept.keyframe_poses[problem.keyframes])
    assert problem.obs_keyframes.max() < len(problem.labels) and problem.obs_points.max() < len(problem.points)
    adjusted = Map.build(seq, **options)
    assert adjusted.labels is not None and adjusted.labels["applied"]
    ours = bundle_adjust(problem)
    # (to rounding: the map carries each correction L_k⁻¹B_k to its keyframes as L_k·Δ_k)
    assert np.allclose(adjusted.camera_poses[problem.keyframes], ours.camera_poses, rtol=0, atol=1e-12)
    assert np.allclose(adjusted.keyframe_poses[problem.keyframes], ours.label_poses, rtol=0, atol=1e-12)
    with pytest.raises(InvalidInputError, match="labels"):
        adjusted.label_adjustment_problem()


def test_threads_at_once_give_the_bits_of_one_call() -> None:
    """Four threads adjusting the same problem at once (the core releases the GIL) each return
    exactly what one call alone returns: no state is shared between calls."""
    problem, _ = _problem(seed=3)
    alone = bundle_adjust(problem, label_sigma=SIGMA)
    barrier = threading.Barrier(4)

    def adjust(_: int) -> Any:
        barrier.wait()
        return bundle_adjust(problem, label_sigma=SIGMA)

    with ThreadPoolExecutor(4) as pool:
        results = list(pool.map(adjust, range(4)))
    for r in results:
        for name in ("label_poses", "camera_poses", "offset", "points", "label_pose_covariances", "point_covariances"):
            assert np.array_equal(getattr(r, name), getattr(alone, name)), name
        assert r.cost == alone.cost and r.iterations == alone.iterations
