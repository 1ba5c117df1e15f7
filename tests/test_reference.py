"""geoloc.reference: reading reference trajectories, the robust S·R·X alignment (against
scipy.optimize.least_squares as an independent solver), the 7-Scenes SfM reference against
the labels, and ``geoloc evaluate --reference``."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import geoloc
from cli_runner import one_line_error as _one_line_error
from cli_runner import run_geoloc as _run
from geoloc import datasets, evaluation, lie
from geoloc.exceptions import DatasetError, InvalidInputError
from geoloc.reference import ReferenceAlignment, align_reference, load_reference, match_reference, numbering_shift

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
REDKITCHEN = DATA / "7scenes-redkitchen"
SFM_POSES = DATA / "7scenes-redkitchen-reference" / "sfm-poses.txt"

N_FRAMES = 200
OUTLIERS = 10
POSITION_NOISE_M = 0.003
ROTATION_NOISE_RAD = math.radians(0.2)
#: Noise-limited recovery of S and X from N_FRAMES frames (largest over seeds 0–4: scale
#: 8e-5, rotations 0.026°, positions 0.8 mm).
RECOVERY_POSITION_M = 2e-3
RECOVERY_ROTATION_DEG = 0.05
RECOVERY_SCALE = 5e-4
#: Agreement with scipy's solver of the same robust cost (3e-9 measured; its finite-difference
#: Jacobian limits the precision of its minimum).
SOLVER_AGREEMENT = 1e-7
EXACT = 1e-9
#: The documented agreement of the SfM reference with the labels (../shared/data/README.md).
LABEL_MEDIAN_M = (0.01, 0.04)
LABEL_MEDIAN_DEG = 3.0
WITHOUT_OFFSET_DEG = (3.0, 5.0)


# ---------------------------------------------------------------------------- helpers


def _random_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    return lie.se3_exp(np.concatenate([rng.normal(0, 2, (n, 3)), rng.normal(0, 1, (n, 3))], axis=1))


def _true_s_and_x() -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """A known similarity (s, R_S, t_S) and camera-frame offset X (t_X in reference units)."""
    x = lie.se3_exp(np.array([0.04, -0.02, 0.03, 0.05, -0.03, 0.06]))
    return 1.7, lie.so3_exp(np.array([0.3, -0.5, 1.1])), np.array([2.0, -1.0, 0.5]), x


def _compose(s: float, rs: np.ndarray, ts: np.ndarray, x: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """S · R · X written out independently of geoloc: the 4×4 product with the scale divided
    out of the rotation block."""
    sim = np.eye(4)
    sim[:3, :3], sim[:3, 3] = s * rs, ts
    out = sim @ ref @ x
    out[:, :3, :3] /= s
    return out


def _noisy_map(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Reference poses, the map's poses S·R·X with noise and OUTLIERS gross errors, and the
    outliers' indices."""
    ref = _random_poses(rng, N_FRAMES)
    target = _compose(*_true_s_and_x(), ref)
    target[:, :3, 3] += rng.normal(0, POSITION_NOISE_M, (N_FRAMES, 3))
    target[:, :3, :3] = target[:, :3, :3] @ lie.so3_exp(rng.normal(0, ROTATION_NOISE_RAD, (N_FRAMES, 3)))
    bad = rng.choice(N_FRAMES, OUTLIERS, replace=False)
    target[bad, :3, 3] += rng.normal(0, 0.5, (OUTLIERS, 3))
    target[bad, :3, :3] = target[bad, :3, :3] @ lie.so3_exp(rng.normal(0, 0.4, (OUTLIERS, 3)))
    return ref, target, bad


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(lie.rotation_angle(a.T @ b)))


def _write(path: Path, text: str | bytes) -> Path:
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text, encoding="utf-8")
    return path


def _reference_lines(indices: list[int], poses: np.ndarray) -> str:
    return "".join(f"{i} " + " ".join(repr(float(v)) for v in T[:3].ravel()) + "\n" for i, T in zip(indices, poses))


# ---------------------------------------------------------------------------- alignment


def test_alignment_recovers_s_and_x_despite_outliers() -> None:
    rng = np.random.default_rng(0)
    ref, target, bad = _noisy_map(rng)
    s, rs, ts, x = _true_s_and_x()
    a = align_reference(ref, target)
    assert a.converged
    assert abs(a.scale / s - 1) < RECOVERY_SCALE
    assert _angle_deg(a.rotation, rs) < RECOVERY_ROTATION_DEG
    assert np.linalg.norm(a.translation - ts) < RECOVERY_POSITION_M
    assert _angle_deg(a.offset[:3, :3], x[:3, :3]) < RECOVERY_ROTATION_DEG
    assert np.linalg.norm(a.offset[:3, 3] - x[:3, 3]) * s < RECOVERY_POSITION_M
    # the outliers stand out in the residuals, the inliers are at the noise level
    inliers = np.setdiff1d(np.arange(N_FRAMES), bad)
    assert a.position_residuals_m[bad].min() > 10 * np.median(a.position_residuals_m[inliers])
    assert np.median(a.position_residuals_m[inliers]) < 3 * POSITION_NOISE_M
    stats = a.statistics()
    assert stats["frames"] == N_FRAMES and stats["inlier_fraction"] >= 0.9
    json.dumps(a.as_dict(), allow_nan=False)


def test_alignment_is_the_minimum_scipy_finds_for_the_same_robust_cost() -> None:
    """scipy.optimize.least_squares (loss='huber', residuals ‖Δp‖/δ_p and Θ/δ_r per frame:
    its cost ½Σρ(f²) is the module's Σρ(u)) from the true S and X reaches the same minimum."""
    optimize = pytest.importorskip("scipy.optimize")
    rotation = pytest.importorskip("scipy.spatial.transform").Rotation
    rng = np.random.default_rng(1)
    ref, target, _ = _noisy_map(rng)
    dp, dr = 0.02, math.radians(1.0)

    def unpack(v: np.ndarray) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        x = np.eye(4)
        x[:3, :3], x[:3, 3] = rotation.from_rotvec(v[7:10]).as_matrix(), v[10:13]
        return math.exp(v[0]), rotation.from_rotvec(v[1:4]).as_matrix(), v[4:7], x

    def residuals(v: np.ndarray) -> np.ndarray:
        aligned = _compose(*unpack(v), ref)
        rp = np.linalg.norm(aligned[:, :3, 3] - target[:, :3, 3], axis=1)
        rr = rotation.from_matrix(np.einsum("nji,njk->nik", target[:, :3, :3], aligned[:, :3, :3])).magnitude()
        return np.concatenate([rp / dp, rr / dr])

    s, rs, ts, x = _true_s_and_x()
    v0 = np.concatenate([[math.log(s)], rotation.from_matrix(rs).as_rotvec(), ts, rotation.from_matrix(x[:3, :3]).as_rotvec(), x[:3, 3]])
    fit = optimize.least_squares(residuals, v0, loss="huber", f_scale=1.0, jac="3-point", xtol=1e-15, ftol=1e-15, gtol=1e-15)
    s_ref, rs_ref, ts_ref, x_ref = unpack(fit.x)
    a = align_reference(ref, target, position_scale_m=0.02, rotation_scale_deg=1.0)
    assert abs(a.scale - s_ref) < SOLVER_AGREEMENT
    assert np.abs(a.rotation - rs_ref).max() < SOLVER_AGREEMENT
    assert np.abs(a.translation - ts_ref).max() < SOLVER_AGREEMENT
    assert np.abs(a.offset - x_ref).max() < SOLVER_AGREEMENT
    # and the same cost: the module's Σρ(u) equals scipy's ½Σρ(f²)
    ours = np.concatenate([a.position_residuals_m / dp, np.radians(a.rotation_residuals_deg) / dr])
    huber = np.where(ours <= 1, 0.5 * ours**2, ours - 0.5).sum()
    assert huber <= fit.cost * (1 + 1e-9)


def test_alignment_is_exact_without_noise_and_apply_is_s_r_x() -> None:
    rng = np.random.default_rng(2)
    ref = _random_poses(rng, 20)
    s, rs, ts, x = _true_s_and_x()
    a = align_reference(ref, _compose(s, rs, ts, x, ref))
    assert abs(a.scale - s) < EXACT and np.abs(a.rotation - rs).max() < EXACT
    assert np.abs(a.translation - ts).max() < EXACT and np.abs(a.offset - x).max() < EXACT
    assert a.position_residuals_m.max() < EXACT and a.rotation_residuals_deg.max() < EXACT
    others = _random_poses(rng, 5)
    np.testing.assert_allclose(a.apply(others), _compose(s, rs, ts, x, others), atol=EXACT)
    np.testing.assert_allclose(a.apply(others, offset=False), _compose(s, rs, ts, np.eye(4), others), atol=EXACT)
    np.testing.assert_allclose(a.apply(others[0]), a.apply(others[:1]), atol=0)
    sim = a.similarity
    np.testing.assert_allclose(sim[:3, :3], s * rs, atol=EXACT)


def test_alignment_uncertainty_is_the_spread_of_refits_to_fresh_noise() -> None:
    """Monte Carlo: 12 fitting frames, 300 fits to fresh Gaussian noise of per-axis σ
    (0.25 of the Huber scales, so every residual stays in the quadratic part); the empirical
    RMS spread of the aligned test poses matches :meth:`uncertainty` (which assumes residuals
    of the Huber scales' size) times 0.25, within the Monte-Carlo error."""
    rng = np.random.default_rng(3)
    ref = lie.se3_exp(np.concatenate([rng.normal(0, 0.3, (12, 3)), rng.normal(0, 0.3, (12, 3))], axis=1))
    test = lie.se3_exp(np.concatenate([rng.normal(0, 1.5, (5, 3)), rng.normal(0, 0.5, (5, 3))], axis=1))
    truth = _compose(*_true_s_and_x(), ref)
    aligned_truth = _compose(*_true_s_and_x(), test)
    fraction = 0.25
    sigma_p, sigma_r = fraction * 0.02, fraction * math.radians(1.0)
    dp, dr = [], []
    for _ in range(300):
        target = truth.copy()
        target[:, :3, 3] += rng.normal(0, sigma_p, (12, 3))
        target[:, :3, :3] = target[:, :3, :3] @ lie.so3_exp(rng.normal(0, sigma_r, (12, 3)))
        aligned = align_reference(ref, target).apply(test)
        dp.append(aligned[:, :3, 3] - aligned_truth[:, :3, 3])
        dr.append(np.stack([lie.so3_log(a.T @ b) for a, b in zip(aligned_truth[:, :3, :3], aligned[:, :3, :3])]))
    empirical_p = np.sqrt((np.stack(dp) ** 2).sum(axis=2).mean(axis=0))
    empirical_r = np.degrees(np.sqrt((np.stack(dr) ** 2).sum(axis=2).mean(axis=0)))
    predicted_p, predicted_r = align_reference(ref, truth).uncertainty(test)
    # 300 samples of a sum of three squares: the RMS is known to about ±7 %
    assert empirical_p == pytest.approx(fraction * predicted_p, rel=0.15)
    assert empirical_r == pytest.approx(fraction * predicted_r, rel=0.15)


def test_alignment_from_frames_that_cannot_determine_it_says_so() -> None:
    """Three frames 7 mm apart fit S and X to a few micrometres and leave a frame half a
    metre away uncertain by metres; the fitted frames themselves stay well determined."""
    rng = np.random.default_rng(4)
    ref = lie.se3_exp(np.concatenate([rng.normal(0, 0.004, (3, 3)), rng.normal(0, 0.002, (3, 3))], axis=1))
    target = _compose(*_true_s_and_x(), ref)
    far = lie.se3_exp(np.array([[0.5, 0.0, 0.0, 0.0, 0.3, 0.0]]))
    a = align_reference(ref, target)
    assert a.uncertainty(far)[0][0] > 1.0
    many = _random_poses(rng, 40)
    assert align_reference(many, _compose(*_true_s_and_x(), many)).uncertainty(far)[0][0] < 0.01


def test_huber_scales_matter_a_least_squares_fit_is_pulled_by_outliers() -> None:
    rng = np.random.default_rng(3)
    ref, target, _ = _noisy_map(rng)
    _, _, ts, _ = _true_s_and_x()
    robust = align_reference(ref, target)
    plain = align_reference(ref, target, position_scale_m=1e3, rotation_scale_deg=1e5)
    assert np.linalg.norm(plain.translation - ts) > 5 * np.linalg.norm(robust.translation - ts)


def test_score_against_reference_is_summarize_against_the_aligned_reference() -> None:
    rng = np.random.default_rng(4)
    ref = _random_poses(rng, 10)
    s, rs, ts, x = _true_s_and_x()
    a = align_reference(ref, _compose(s, rs, ts, x, ref))
    truth = _compose(s, rs, ts, x, ref)

    class Result:
        def __init__(self, pose: np.ndarray | None) -> None:
            self.pose, self.covariance, self.source, self.timings_ms = pose, None, "geometric" if pose is not None else "lost", {"total": 1.0}

    shifted = truth.copy()
    shifted[:, :3, 3] += [0.03, 0.0, 0.0]
    results = [Result(p) for p in shifted[:9]] + [Result(None)]
    summary = evaluation.score_against_reference(results, a, ref)
    assert summary["localized"] == 9
    assert abs(summary["median_translation_m"] - 0.03) < 1e-9
    assert summary["recall"]["5cm_5deg"] == pytest.approx(0.9)


@pytest.mark.parametrize(
    ("kwargs", "names"),
    [
        ({"reference_poses": np.tile(np.eye(4), (2, 1, 1)), "map_poses": np.tile(np.eye(4), (2, 1, 1))}, ("reference_poses", "at least 3")),
        ({"reference_poses": np.tile(np.eye(4), (4, 1, 1)), "map_poses": np.tile(np.eye(4), (3, 1, 1))}, ("map_poses", "same number")),
        ({"reference_poses": np.ones((4, 4, 4)), "map_poses": np.tile(np.eye(4), (4, 1, 1))}, ("reference_poses[0]", "rigid")),
        ({"reference_poses": np.tile(np.eye(4), (4, 1, 1)), "map_poses": np.tile(np.eye(4), (4, 1, 1))}, ("reference_poses", "coincide")),
    ],
)
def test_alignment_bad_inputs_name_the_argument(kwargs: dict[str, np.ndarray], names: tuple[str, ...]) -> None:
    with pytest.raises(InvalidInputError) as info:
        align_reference(kwargs["reference_poses"], kwargs["map_poses"])
    for name in names:
        assert name in str(info.value)


@pytest.mark.parametrize(("option", "value"), [("position_scale_m", 0.0), ("rotation_scale_deg", -1.0), ("position_scale_m", float("nan")), ("max_iterations", 0)])
def test_alignment_bad_options_name_the_option(option: str, value: float) -> None:
    ref = _random_poses(np.random.default_rng(5), 5)
    with pytest.raises(InvalidInputError, match=option):
        align_reference(ref, ref, **{option: value})  # type: ignore[arg-type]


# ---------------------------------------------------------------------------- files


def test_7scenes_reference_file_is_read_and_projected(tmp_path: Path) -> None:
    rng = np.random.default_rng(6)
    poses = _random_poses(rng, 4)
    skewed = poses.copy()
    skewed[:, :3, :3] *= 1.002  # ‖RᵀR − I‖_F ≈ 7e-3: accepted, then projected
    text = "# index then the 3×4 pose\n\n" + _reference_lines([3, 7, 5, 11], skewed).replace(" ", ", ", 1)
    keys, loaded = load_reference(_write(tmp_path / "ref.txt", text))
    assert keys.dtype == np.int64 and keys.tolist() == [3, 7, 5, 11]
    assert loaded.shape == (4, 4, 4) and loaded.dtype == np.float64
    np.testing.assert_allclose(loaded, poses, atol=1e-12)
    _, explicit = load_reference(tmp_path / "ref.txt", "7scenes-reference")
    np.testing.assert_array_equal(explicit, loaded)
    assert match_reference(keys, [5, 6, 11]).tolist() == [2, -1, 3]


def test_tum_reference_file_is_read_with_the_tum_reader(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    poses = _random_poses(rng, 5)
    times = np.array([0.0, 0.5, 1.0, 1.5, 2.0])
    evaluation.write_tum_trajectory(tmp_path / "traj.txt", times, poses)
    for fmt in ("auto", "tum"):
        keys, loaded = load_reference(tmp_path / "traj.txt", fmt)
        assert keys.dtype == np.float64
        np.testing.assert_array_equal(keys, times)
        np.testing.assert_allclose(loaded, poses, atol=1e-12)
    rows = match_reference(times, timestamps=[0.51, 1.0, 7.0])
    assert rows.tolist() == [1, 2, -1]


GOOD_LINE = "0 1 0 0 0.5 0 1 0 0.25 0 0 1 2\n"


@pytest.mark.parametrize(
    ("content", "fmt", "needles"),
    [
        (GOOD_LINE + GOOD_LINE.replace("0 1 0 0 0.5", "1 1 0 0", 1), "auto", ("line 2", "12 values", "expected 13")),
        ("# header\n" + GOOD_LINE + "\n" + GOOD_LINE.replace("0 1 0 0 0.5", "2 1.1 0 0 0.5", 1), "auto", ("line 4", "not a rotation")),
        (GOOD_LINE + GOOD_LINE.replace("0 1 0 0 0.5 0 1 0", "1 1 0 0 0.5 0 -1 0", 1), "7scenes-reference", ("line 2", "not a rotation", "det")),
        (GOOD_LINE + GOOD_LINE.replace("0.25", "abc", 1).replace("0 ", "1 ", 1), "auto", ("line 2", "not numbers")),
        (GOOD_LINE + GOOD_LINE.replace("0.25", "nan", 1).replace("0 ", "1 ", 1), "auto", ("line 2", "not finite")),
        (GOOD_LINE + GOOD_LINE, "auto", ("line 2", "frame 0 again", "line 1")),
        (GOOD_LINE.replace("0 ", "-1 ", 1), "auto", ("line 1", "not an integer")),
        (GOOD_LINE.replace("0 ", "99999999999999999999 ", 1), "auto", ("line 1", "20 digits", "at most 9223372036854775807")),
        (GOOD_LINE.replace("0 ", str(2**63) + " ", 1), "7scenes-reference", ("line 1", "19 digits")),
        ("\ufeff" + GOOD_LINE, "auto", ("line 1", "byte-order mark")),
        ("# only a comment\n\n", "auto", ("has no poses",)),
        ("", "7scenes-reference", ("has no poses",)),
        ("1 2 3 4 5\n", "auto", ("line 1", "cannot tell the format", "5 values")),
        (GOOD_LINE.encode() + b"1 \xff\xfe 0\n", "auto", ("line 2", "UTF-8")),
        ("0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0\n", "tum", ("pose 2", "7 values")),
        ("0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0\n", "auto", ("pose 2", "7 values")),
        ("", "tum", ("has no poses",)),
        (b"0 0 0 0 0 0 0 1\n\xff\n", "tum", ("cannot be read as text",)),
    ],
)
def test_bad_reference_files_name_the_file_and_line(tmp_path: Path, content: str | bytes, fmt: str, needles: tuple[str, ...]) -> None:
    path = _write(tmp_path / "bad-ref.txt", content)
    with pytest.raises(DatasetError) as info:
        load_reference(path, fmt)
    message = str(info.value)
    assert str(path) in message
    for needle in needles:
        assert needle in message, message
    assert isinstance(info.value, ValueError)


def test_missing_reference_file_and_bad_arguments(tmp_path: Path) -> None:
    missing = tmp_path / "nope.txt"
    for fmt in ("auto", "7scenes-reference", "tum"):
        with pytest.raises(DatasetError, match="does not exist") as info:
            load_reference(missing, fmt)
        assert str(missing) in str(info.value)
    with pytest.raises(DatasetError, match="cannot be read"):
        load_reference(tmp_path)  # a folder
    with pytest.raises(InvalidInputError, match="fmt"):
        load_reference(_write(tmp_path / "r.txt", GOOD_LINE), "kitti")
    with pytest.raises(InvalidInputError, match="path"):
        load_reference(3)  # type: ignore[arg-type]
    with pytest.raises(InvalidInputError, match="frame_indices"):
        match_reference(np.array([1, 2]))
    with pytest.raises(InvalidInputError, match="timestamps"):
        match_reference(np.array([1.0, 2.0]), frame_indices=[1])


# ---------------------------------------------------------------------------- the 7-Scenes reference


def _redkitchen() -> tuple[np.ndarray, np.ndarray]:
    """Labels and the SfM reference of frames 0–699 of the shared redkitchen sequence."""
    if not (REDKITCHEN.is_dir() and SFM_POSES.is_file()):
        pytest.skip(f"shared sample data not found at {REDKITCHEN} / {SFM_POSES} (see ../shared/data/README.md)")
    pytest.importorskip("cv2")
    seq = datasets.load_7scenes(REDKITCHEN)
    keys, ref = load_reference(SFM_POSES)
    rows = match_reference(keys, seq.indices)
    assert (rows >= 0).all()
    assert seq.poses is not None
    return seq.poses, ref[rows]


def _differences(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    dp = np.linalg.norm(a[:, :3, 3] - b[:, :3, 3], axis=1)
    dr = np.degrees(lie.rotation_angle(np.einsum("nji,njk->nik", a[:, :3, :3], b[:, :3, :3])))
    return dp, dr


def test_sfm_reference_agrees_with_the_labels_to_the_documented_level() -> None:
    """Fitted on the training frames 0–599: the aligned reference is within the documented
    1–4 cm / < 3° of the labels; without the camera-frame offset the orientations differ by
    a near-constant 3–4° (the labels are not the colour camera's orientation)."""
    labels, ref = _redkitchen()
    a = align_reference(ref[:600], labels[:600])
    assert a.converged
    assert 0.9 < a.scale < 1.1  # the reference was already brought to the labels' metric scale
    dp, dr = _differences(a.apply(ref[:600]), labels[:600])
    assert LABEL_MEDIAN_M[0] <= float(np.median(dp)) <= LABEL_MEDIAN_M[1]
    assert float(np.median(dr)) < LABEL_MEDIAN_DEG
    np.testing.assert_allclose(dp, a.position_residuals_m, atol=1e-9)
    _, dr0 = _differences(a.apply(ref[:600], offset=False), labels[:600])
    assert WITHOUT_OFFSET_DEG[0] <= float(np.median(dr0)) <= WITHOUT_OFFSET_DEG[1]
    # held-out frames 600–699, as evaluate scores them
    dp_test, dr_test = _differences(a.apply(ref[600:]), labels[600:])
    assert float(np.median(dp_test)) <= LABEL_MEDIAN_M[1] and float(np.median(dr_test)) < LABEL_MEDIAN_DEG


def _turning_trajectory(n: int) -> np.ndarray:
    """n poses whose rotation from frame to frame varies (0.2–2°, no period)."""
    rng = np.random.default_rng(5)
    steps = np.concatenate([rng.normal(0, 0.005, (n, 3)), rng.uniform(0.2, 2.0, (n, 1)) * math.pi / 180 * rng.normal(0, 1, (n, 3))], axis=1)
    poses = [np.eye(4)]
    for step in steps[1:]:
        poses.append(poses[-1] @ lie.se3_exp(step))
    return np.stack(poses)


@pytest.mark.parametrize("keyed_by", ["index", "time"])
@pytest.mark.parametrize("shift", [0, 7, -12])
def test_numbering_shift_finds_the_shift_whatever_the_similarity_and_offset(keyed_by: str, shift: int) -> None:
    """A reference that is S·R·X of the frames' own poses (another world frame, scale and
    camera), keyed k frames on: the rotation angles agree exactly at shift k and nowhere else."""
    n = 80
    own = _turning_trajectory(n)
    s, rs, ts, x = _true_s_and_x()
    inv_s = np.eye(4)
    inv_s[:3, :3], inv_s[:3, 3] = rs.T / s, -rs.T @ ts / s
    scaled = own.copy()
    scaled[:, :3, :3] *= s
    ref = inv_s @ scaled @ lie.se3_inverse(x)
    indices, times = np.arange(100, 100 + n), 10.0 + np.arange(n) / 30.0
    keys = indices + shift if keyed_by == "index" else times + shift / 30.0
    found = numbering_shift(keys, ref, own, indices, times)
    assert found is not None and found.best == shift
    assert found.rms_deg[shift] < 1e-6
    assert min(v for k, v in found.rms_deg.items() if k != shift) > 0.1


def test_numbering_shift_of_too_few_frames_is_none_and_bad_arguments_are_named() -> None:
    own = _turning_trajectory(8)
    indices = np.arange(8)
    assert numbering_shift(indices, own, own, indices, indices / 30.0) is None
    with pytest.raises(InvalidInputError, match="^poses, frame_indices, timestamps"):
        numbering_shift(indices, own, own, indices[:5], indices / 30.0)
    with pytest.raises(InvalidInputError, match="^max_shift"):
        numbering_shift(indices, own, own, indices, indices / 30.0, max_shift=-1)


def test_a_shifted_sfm_reference_is_refused_and_the_right_one_is_not() -> None:
    """7-Scenes frames 0–99 against the SfM reference: as numbered it passes; numbered 20
    frames on (as a shifted file would be), it is refused before any map is built."""
    from geoloc.commands.evaluate import _check_numbering

    if not (REDKITCHEN.is_dir() and SFM_POSES.is_file()):
        pytest.skip(f"shared sample data not found at {REDKITCHEN} / {SFM_POSES} (see ../shared/data/README.md)")
    train = datasets.load_7scenes(REDKITCHEN)[0:100]
    keys, poses = load_reference(SFM_POSES)
    reference = {"file": "sfm-poses.txt", "format": "7scenes-reference", "keys": keys, "poses": poses}
    _check_numbering(reference, train)
    with pytest.raises(InvalidInputError, match=r"^--reference: .* best shifted by \+20 frames"):
        _check_numbering({**reference, "keys": keys + 20}, train)


# ---------------------------------------------------------------------------- geoloc evaluate --reference


ROOM_FRAMES = 60


def _room_reference(tmp_path: Path, fmt: str, frames: slice = slice(None)) -> Path:
    """The synthetic room's labels M_i as a reference in another frame: R_i = S⁻¹ M_i X⁻¹ as
    4×4 products, with M_i's rotation block scaled by s (the inverse of :func:`_compose`)."""
    seq = datasets.synthetic_room(n_frames=ROOM_FRAMES)
    assert seq.poses is not None
    s, rs, ts, x = _true_s_and_x()
    inv_s = np.eye(4)
    inv_s[:3, :3], inv_s[:3, 3] = rs.T / s, -rs.T @ ts / s
    scaled = seq.poses.copy()
    scaled[:, :3, :3] *= s
    ref = inv_s @ scaled @ lie.se3_inverse(x)
    path = tmp_path / f"ref-{fmt}.txt"
    if fmt == "tum":
        evaluation.write_tum_trajectory(path, seq.timestamps[frames], ref[frames])
    else:
        path.write_text(_reference_lines(seq.indices[frames].tolist(), ref[frames]))
    return path


@pytest.mark.slow
@pytest.mark.parametrize("fmt", ["7scenes-reference", "tum"])
def test_evaluate_against_a_reference_prints_both_rows_and_writes_the_alignment(tmp_path: Path, fmt: str) -> None:
    """A reference that is the labels in another frame (known S, X): the scores against it
    are the scores against the labels, and the alignment is S and X."""
    path = _room_reference(tmp_path, fmt)
    result = _run(
        "evaluate", "--format", "synthetic", "--synthetic-frames", str(ROOM_FRAMES), "--test", "30:60:3", "--mode", "single",
        "--reference", str(path), "--reference-format", fmt, "--json", str(tmp_path / "r.json"),
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert "(single) vs labels" in result.stdout and "(single) vs reference" in result.stdout
    assert "training residuals median" in result.stdout
    data = json.loads((tmp_path / "r.json").read_text())
    against = data["against_reference"]
    assert against["format"] == fmt and against["fitted_to"] == "map keyframe poses"
    s, _, _, _ = _true_s_and_x()
    assert against["alignment"]["scale"] == pytest.approx(s, rel=1e-9)
    assert against["alignment"]["training"]["frames"] == ROOM_FRAMES // 2
    vs_ref = against["modes"]["single"]
    assert vs_ref["frames"] == data["frames"] == 10
    assert vs_ref["median_translation_m"] == pytest.approx(data["median_translation_m"], abs=1e-9)
    assert vs_ref["median_rotation_deg"] == pytest.approx(data["median_rotation_deg"], abs=1e-7)
    assert [f["frame"] for f in vs_ref["per_frame"]] == list(range(30, 60, 3))


@pytest.mark.slow
def test_evaluate_reference_errors_are_one_line(tmp_path: Path) -> None:
    room = ("evaluate", "--format", "synthetic", "--synthetic-frames", str(ROOM_FRAMES), "--test", "30:60:3", "--mode", "single")
    bad = _write(tmp_path / "bad.txt", "1 2 3 4 5\n")
    _one_line_error(_run(*room, "--reference", str(bad)), "--reference", "line 1", "cannot tell the format")
    _one_line_error(_run(*room, "--reference", str(tmp_path / "missing.txt")), "--reference", "does not exist")
    _one_line_error(_run(*room, "--reference-format", "tum"), "--reference-format", "--reference")
    partial = _room_reference(tmp_path, "7scenes-reference", slice(0, 40))
    _one_line_error(_run(*room, "--reference", str(partial)), "--reference", "no pose for 6 of the 10 test frames", "42")
    _one_line_error(_run(*room, "--reference", str(partial), "--reference-format", "kitti"), "--reference-format")
    # three training frames: a similarity fits them exactly, and determines nothing 30 frames on
    few = _room_reference(tmp_path, "7scenes-reference", np.r_[0:3, 30:60])  # type: ignore[arg-type]
    _one_line_error(_run(*room, "--reference", str(few)), "--reference", "do not determine its alignment")
    # the frame numbers shifted by a third of the room: the rotation from frame to frame
    # matches the training frames' 20 frames on
    lines = _room_reference(tmp_path, "7scenes-reference").read_text().splitlines()
    shifted = _write(tmp_path / "shifted.txt", "\n".join(
        f"{(int(line.split()[0]) + ROOM_FRAMES // 3) % ROOM_FRAMES} {line.split(maxsplit=1)[1]}" for line in lines
    ) + "\n")
    _one_line_error(_run(*room, "--reference", str(shifted)), "--reference", "best shifted by +20 frames")
    # another trajectory altogether: no numbering fits, and a similarity fits far from every
    # pose (it was accepted, with an "own uncertainty" of millimetres)
    other = _write(tmp_path / "other.txt", _reference_lines(list(range(ROOM_FRAMES)), _random_poses(np.random.default_rng(3), ROOM_FRAMES)))
    _one_line_error(_run(*room, "--reference", str(other)), "--reference", "does not fit the training frames")


def test_map_keyframe_poses_prefers_the_maps_own() -> None:
    from geoloc.commands.evaluate import map_keyframe_poses

    labels = _random_poses(np.random.default_rng(8), 4)
    moved = labels + 1.0

    class Adjusted:
        keyframe_poses = moved
        labels = {"label_sigma_m": 0.01}

    class NotAdjusted:
        keyframe_poses = moved
        labels = None

    assert map_keyframe_poses(object(), labels) is labels
    assert map_keyframe_poses(NotAdjusted(), labels) is labels
    np.testing.assert_array_equal(map_keyframe_poses(Adjusted(), labels), labels + 1.0)
    with pytest.raises(InvalidInputError, match="keyframe poses"):
        map_keyframe_poses(Adjusted(), labels[:3])


def test_reference_alignment_is_exported() -> None:
    assert evaluation.ReferenceAlignment is ReferenceAlignment
    for name in ("load_reference", "align_reference", "match_reference", "score_against_reference"):
        assert name in evaluation.__all__
