"""geoloc.evaluation: errors, NEES and coverage against independent references; TUM files."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

import geoloc
from geoloc import evaluation, lie

EXACT = 1e-12
TIGHT = 1e-9
N_MONTE_CARLO = 4000
COVERAGE_TARGET = 0.95
# Binomial 4σ of a 95 % fraction over N_MONTE_CARLO draws.
COVERAGE_TOLERANCE = 4 * math.sqrt(COVERAGE_TARGET * (1 - COVERAGE_TARGET) / N_MONTE_CARLO)


def _random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    return lie.se3_exp(np.concatenate([rng.normal(0, 2, (n, 3)), rng.normal(0, 1, (n, 3))], axis=1))


def _random_spd(rng: np.random.Generator) -> np.ndarray:
    scale = np.array([0.02, 0.01, 0.03, 0.004, 0.01, 0.006])
    a = rng.normal(size=(6, 6)) * scale[:, None]
    return a @ a.T + np.diag(scale**2)


def test_pose_errors_known_values() -> None:
    gt = np.eye(4)
    est = np.eye(4)
    est[:3, 3] = [0.03, 0.04, 0.0]
    est[:3, :3] = lie.so3_exp([0.0, 0.0, math.radians(10.0)])
    trans, rot = evaluation.pose_errors(est, gt)
    assert trans.shape == rot.shape == (1,)
    assert abs(trans[0] - 0.05) < EXACT
    assert abs(rot[0] - 10.0) < TIGHT


def test_pose_errors_batch_equals_loop() -> None:
    rng = np.random.default_rng(0)
    est, gt = _random_poses(rng, 20), _random_poses(rng, 20)
    trans, rot = evaluation.pose_errors(est, gt)
    for k in range(20):
        t1, r1 = evaluation.pose_errors(est[k], gt[k])
        assert trans[k] == t1[0] and abs(rot[k] - r1[0]) < TIGHT
        reference = math.degrees(math.acos(np.clip((np.trace(est[k, :3, :3].T @ gt[k, :3, :3]) - 1) / 2, -1, 1)))
        assert abs(rot[k] - reference) < 1e-6


def test_tangent_error_is_the_right_perturbation_translation_first() -> None:
    rng = np.random.default_rng(1)
    est = _random_poses(rng, 10)
    delta = rng.normal(0, 0.05, (10, 6))
    gt = np.einsum("nij,njk->nik", est, lie.se3_exp(delta))  # T_gt = T_est · exp(δ^)
    assert np.allclose(evaluation.tangent_errors(est, gt), delta, atol=TIGHT)


def test_nees_matches_a_hand_computed_quadratic_form() -> None:
    rng = np.random.default_rng(2)
    est = _random_poses(rng, 5)
    covs = np.stack([_random_spd(rng) for _ in range(5)])
    delta = np.stack([rng.multivariate_normal(np.zeros(6), c) for c in covs])
    gt = np.einsum("nij,njk->nik", est, lie.se3_exp(delta))
    reference = np.array([d @ np.linalg.inv(c) @ d for d, c in zip(delta, covs)])
    assert np.allclose(evaluation.nees(est, covs, gt), reference, rtol=1e-8)


def test_calibrated_errors_cover_95_percent() -> None:
    rng = np.random.default_rng(3)
    cov = _random_spd(rng)
    est = np.repeat(_random_poses(rng, 1), N_MONTE_CARLO, axis=0)
    delta = rng.multivariate_normal(np.zeros(6), cov, N_MONTE_CARLO)
    gt = np.einsum("nij,njk->nik", est, lie.se3_exp(delta))
    covs = np.repeat(cov[None], N_MONTE_CARLO, axis=0)
    nees = evaluation.nees(est, covs, gt)
    assert abs(np.mean(nees <= evaluation.CHI2_6_95) - COVERAGE_TARGET) < COVERAGE_TOLERANCE
    assert np.all(np.abs(evaluation.axis_coverage(est, covs, gt) - COVERAGE_TARGET) < COVERAGE_TOLERANCE)
    # An over-confident covariance (σ halved) is caught.
    assert np.mean(evaluation.nees(est, covs / 4, gt) <= evaluation.CHI2_6_95) < COVERAGE_TARGET - 10 * COVERAGE_TOLERANCE


def test_chi2_6_against_scipy() -> None:
    stats = pytest.importorskip("scipy.stats")
    x = np.linspace(0, 40, 81)
    assert np.allclose(evaluation.chi2_6_cdf(x), stats.chi2.cdf(x, 6), atol=1e-12)
    p = np.linspace(0.001, 0.999, 50)
    assert np.allclose(evaluation.chi2_6_quantile(p), stats.chi2.ppf(p, 6), rtol=1e-9)
    assert abs(evaluation.CHI2_6_95 - stats.chi2.ppf(0.95, 6)) < 1e-9


def test_isometric_sigmas() -> None:
    cov = np.diag([0.01**2, 0.02**2, 0.03**2, 0.0, 0.0, math.radians(2.0) ** 2])
    sigma_p, sigma_r = evaluation.isometric_sigmas(cov)
    assert abs(sigma_p[0] - 0.02) < EXACT
    assert abs(sigma_r[0] - math.radians(2.0)) < TIGHT


def test_nees_refuses_a_singular_covariance() -> None:
    with pytest.raises(geoloc.InvalidInputError, match=r"cov\[0\]: not positive definite"):
        evaluation.nees(np.eye(4), np.zeros((6, 6)), np.eye(4))
    with pytest.raises(geoloc.InvalidInputError, match="est, gt"):
        evaluation.pose_errors(np.stack([np.eye(4)] * 2), np.eye(4))


def test_an_overflowing_nees_names_the_frame_and_all_its_inputs() -> None:
    """δᵀC⁻¹δ beyond any float — poses 1e300 m apart, or a covariance at the edge of
    underflow — is refused naming the frame's pose and covariance alike (either may be the
    cause), not returned as ∞ or NaN."""
    far = np.eye(4)
    far[2, 3] = 1e300
    shifted = np.eye(4)
    shifted[0, 3] = 1e10
    cases = {
        "poses 1e300 m apart": (np.stack([np.eye(4)] * 2), np.stack([np.eye(6)] * 2), np.stack([np.eye(4), far])),
        "covariance near underflow": (
            np.stack([np.eye(4), shifted]), np.stack([np.eye(6), np.eye(6) * 1e-300]), np.stack([np.eye(4)] * 2)
        ),
    }
    for why, (est, cov, gt) in cases.items():
        with pytest.raises(geoloc.InvalidInputError, match=r"cov\[1\], est\[1\], gt\[1\]: the NEES overflows"):
            evaluation.nees(est, cov, gt)
        assert np.isfinite(evaluation.nees(est[:1], cov[:1], gt[:1])).all(), why


def _summary_inputs() -> tuple[list[np.ndarray | None], np.ndarray, list[np.ndarray | None], list[str]]:
    gt = np.stack([np.eye(4)] * 4)
    offsets = [0.01, 0.2, None, 0.04]  # metres along x; None = lost
    est: list[np.ndarray | None] = []
    for d in offsets:
        if d is None:
            est.append(None)
            continue
        T = np.eye(4)
        T[0, 3] = d
        est.append(T)
    cov = np.eye(6) * 0.02**2
    covs: list[np.ndarray | None] = [None if e is None else cov for e in est]
    return est, gt, covs, ["geometric", "fused", "lost", "fused"]


def test_summarize_keys_lost_frames_and_json() -> None:
    est, gt, covs, sources = _summary_inputs()
    timings = [{"total": 10.0, "pnp": 2.0}, {"total": 12.0, "pnp": 3.0}, {"total": 5.0}, {"total": 11.0, "pnp": 4.0}]
    s = evaluation.summarize(est, gt, covs, sources, timings, timestamps=[0.0, 0.1, 0.2, 0.3])
    design_keys = {"median_translation_m", "median_rotation_deg", "frames", "sources", "recall", "timing_ms", "nees_coverage", "per_frame"}
    assert design_keys <= set(s)
    assert s["frames"] == 4 and s["localized"] == 3
    assert s["median_translation_m"] == pytest.approx(0.04)  # median of the localized 0.01, 0.2, 0.04
    # over all four frames, the lost one as ∞: median of 0.01, 0.04, 0.2, ∞ = (0.04 + 0.2) / 2
    assert s["median_translation_all_m"] == pytest.approx(0.12) and s["median_rotation_all_deg"] == 0.0
    half_lost = evaluation.summarize([est[0], None, None, est[3]], gt)
    assert half_lost["median_translation_all_m"] is None and half_lost["median_translation_m"] == pytest.approx(0.025)
    assert s["recall"] == {"5cm_5deg": 0.5, "25cm_2deg": 0.75, "10cm_1deg": 0.5}  # the lost frame fails
    assert s["sources"] == {"fused": 2, "geometric": 1, "lost": 1}
    assert s["timing_ms"] == {"median_pnp": 3.0, "median_total": 10.5}
    # NEES per frame = (d/0.02)^2: 0.25, 100, 4 → two of three inside χ²₆(0.95).
    assert s["nees_coverage"] == pytest.approx(2 / 3)
    lost = s["per_frame"][2]
    assert lost["source"] == "lost" and lost["translation_error_m"] is None and lost["nees"] is None
    assert s["per_frame"][0]["sigma_p"] == pytest.approx(0.02)
    json.dumps(s, allow_nan=False)


def test_summarize_results_and_table() -> None:
    from geoloc import Localization

    est, gt, covs, sources = _summary_inputs()
    results = [Localization(e, c, s, "", 0, 0, {"total": 1.0}) for e, c, s in zip(est, covs, sources)]
    s = evaluation.summarize_results(results, gt)
    assert s["sources"]["lost"] == 1 and s["timing_ms"]["median_total"] == 1.0
    table = evaluation.format_table({"room": s}, reference={"room": (0.02, 1.10)})
    lines = table.splitlines()
    assert lines[0].split()[:2] == ["Sequence", "Frames"] and "Reference" in lines[0]
    assert "0.040m, 0.00°" in lines[2] and "0.02m, 1.10°" in lines[2]
    assert "Median, lost=∞" in lines[0] and "0.120m, 0.00°" in lines[2]  # 0.01, 0.04, 0.2, ∞
    with pytest.raises(geoloc.InvalidInputError, match="estimates: expected 4"):
        evaluation.summarize(est[:3], gt)


def test_malformed_inputs_of_the_summaries_are_refused_by_name() -> None:
    """Each raised a bare ValueError, TypeError, AttributeError or IndexError."""
    est, gt, covs, sources = _summary_inputs()
    n = len(gt)
    cases = [
        (lambda: evaluation.summarize(est, gt, timings_ms=[{"total": "x"}] * n), r"^timings_ms\[0\]\['total'\]: expected a real"),
        (lambda: evaluation.summarize(est, gt, timings_ms=[5] * n), r"^timings_ms\[0\]: expected a mapping"),
        (lambda: evaluation.summarize_results(None, gt), "^results: expected a sequence"),  # type: ignore[arg-type]
        (lambda: evaluation.summarize_results([1, 2, 3, 4], gt), r"^results\[0\]: expected a localizer result"),
        (lambda: evaluation.format_table({"a": 5}), "^summaries: expected a mapping"),  # type: ignore[dict-item]
        (lambda: evaluation.format_table({"a": {}}, reference={"a": (1,)}), r"^reference: expected a mapping of row name to \(metres"),
    ]
    for call, message in cases:
        with pytest.raises(geoloc.InvalidInputError, match=message):
            call()


def test_format_tum_line() -> None:
    T = np.eye(4)
    T[:3, :3] = lie.so3_exp([0.0, 0.0, math.pi / 2])
    T[:3, 3] = [1.0, -2.0, 0.5]
    fields = geoloc.format_tum_line(12.5, T).split()
    assert len(fields) == 8
    values = [float(f) for f in fields]
    half = math.sqrt(0.5)
    assert values[:4] == [12.5, 1.0, -2.0, 0.5]
    assert np.allclose(values[4:], [0.0, 0.0, half, half], atol=EXACT)  # qx qy qz qw
    with pytest.raises(geoloc.InvalidInputError, match="timestamp"):
        geoloc.format_tum_line(float("nan"), T)


def test_tum_trajectory_is_read_back_by_evo(tmp_path: Path) -> None:
    file_interface = pytest.importorskip("evo.tools.file_interface")
    rng = np.random.default_rng(4)
    poses = _random_poses(rng, 12)
    times = 1305031102.175304 + np.arange(12) / 30
    path = tmp_path / "traj.txt"
    evaluation.write_tum_trajectory(path, times, poses)
    traj = file_interface.read_tum_trajectory_file(str(path))
    assert np.array_equal(traj.timestamps, times)
    assert np.allclose(traj.positions_xyz, poses[:, :3, 3], atol=EXACT)
    rotations = lie.so3_from_quaternion_wxyz(traj.orientations_quat_wxyz)
    assert np.allclose(rotations, poses[:, :3, :3], atol=TIGHT)
    assert [p.name for p in tmp_path.iterdir()] == ["traj.txt"]  # no temp file left


def test_trajectory_writes_are_atomic_and_never_create_folders(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    missing = tmp_path / "no" / "such" / "traj.txt"
    with pytest.raises(geoloc.InvalidInputError, match="does not exist") as info:
        evaluation.write_tum_trajectory(missing, [0.0], np.eye(4)[None])
    assert str(missing.parent) in str(info.value) and not (tmp_path / "no").exists()
    with pytest.raises(geoloc.InvalidInputError, match="is a folder"):
        evaluation.write_tum_trajectory(tmp_path, [0.0], np.eye(4)[None])

    path = tmp_path / "traj.txt"
    path.write_text("old\n")

    def broken_fsync(fd: int) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("geoloc._io.os.fsync", broken_fsync)
    with pytest.raises(geoloc.InvalidInputError, match="No space left"):
        evaluation.write_tum_trajectory(path, [0.0], np.eye(4)[None])
    assert path.read_text() == "old\n"
    assert [p.name for p in tmp_path.iterdir()] == ["traj.txt"]
    with pytest.raises(geoloc.InvalidInputError, match="same count"):
        evaluation.write_tum_trajectory(path, [0.0, 1.0], np.eye(4)[None])
