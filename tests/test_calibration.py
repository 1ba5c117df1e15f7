"""At the image level: the map records its estimated noise (and keeps it through
save/load), and the sequential mode is never worse than the geometric locator alone on the
synthetic room. The 7-Scenes cross-validation is ``benchmarks/calibration.py`` (minutes)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

import geoloc
from geoloc.evaluation import summarize_results
from geoloc.lie import se3_inverse, se3_log

pytest.importorskip("cv2")


@pytest.fixture(scope="module")
def room() -> tuple[Any, Any, geoloc.Map]:
    seq = geoloc.datasets.synthetic_room(n_frames=150, seed=0)
    train, test = seq[:100], seq[100:]
    return train, test, geoloc.Map.build(train)


def test_map_records_its_noise_and_keeps_it(room: tuple[Any, Any, geoloc.Map], tmp_path: Path) -> None:
    train, _, m = room
    noise = m.map_noise
    # every held-out keyframe it placed is one recorded sample; 100 keyframes place too few to
    # estimate the noise from them, so it is the documented default, never zero
    assert 0 < noise["holdout_samples"] == len(noise["holdout"]["keyframe"]) < geoloc._core.MIN_NOISE_SAMPLES
    assert noise["pose_covariance_source"].startswith("default:"), noise["pose_covariance_source"]
    c = noise["pose_covariance"]
    assert c.shape == (6, 6) and np.all(np.isfinite(c)) and np.all(np.linalg.eigvalsh(c) >= 0)
    assert noise["acceleration_psd"].shape == (6,) and np.all(noise["acceleration_psd"] > 0)
    # the velocity prior: the keyframes' (camera) body velocities, mean and variance
    dt = np.diff(train.timestamps)
    poses = m.camera_poses
    v = np.array([se3_log(se3_inverse(a) @ b) / d for a, b, d in zip(poses[:-1], poses[1:], dt)])
    np.testing.assert_allclose(noise["velocity_mean"], v.mean(0), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(noise["velocity_variance"], v.var(0), rtol=1e-9, atol=1e-12)
    assert np.all(np.diag(c) > 0), np.diag(c)
    m.save(tmp_path / "room.geoloc")
    back = geoloc.Map.load(tmp_path / "room.geoloc").map_noise
    np.testing.assert_array_equal(back["pose_covariance"], c)
    for key in ("acceleration_psd", "velocity_mean", "velocity_variance"):
        np.testing.assert_array_equal(back[key], noise[key])


@pytest.fixture(scope="module")
def exact() -> tuple[Any, geoloc.Map]:
    """A map large enough to estimate its noise (≥ 12 held-out keyframes), exact labels."""
    seq = geoloc.datasets.synthetic_room(n_frames=300, seed=0)
    return seq, geoloc.Map.build(seq[:300:2], n_features=500)


def test_noise_the_held_out_keyframes_cannot_resolve_is_floored_and_said(exact: tuple[Any, geoloc.Map], tmp_path: Path) -> None:
    # exact labels: the held-out errors are all measurement error — no axis has map noise
    # beyond chance (one standard error, the resolution rule, is exceeded by chance on about
    # one axis in six); C_map is floored on every unresolved axis, never zero, and says which
    _, exact_map = exact
    noise = exact_map.map_noise
    assert noise["holdout_samples"] >= geoloc._core.MIN_NOISE_SAMPLES
    h = noise["holdout"]
    second = h["delta"] ** 2
    excess = second.mean(0) - np.einsum("nii->ni", h["covariance"]).mean(0)
    standard_error = second.std(0, ddof=1) / np.sqrt(len(second))
    # resolved ⇔ the excess second moment exceeds one standard error, written out in numpy
    np.testing.assert_array_equal(noise["resolved"], excess > standard_error)
    assert np.all(excess < 3 * standard_error), excess / standard_error  # no map noise beyond chance
    unresolved = ~noise["resolved"]
    assert unresolved.sum() >= 4, noise["resolved"]
    c = np.diag(noise["pose_covariance"])
    n = len(second)
    floor = standard_error * n / (n - 7) * (1 - 1e-12)
    assert np.all(c > 0) and np.all(c[unresolved] >= floor[unresolved]), (c, standard_error)
    names = ", ".join(a for a, u in zip(("tx", "ty", "tz", "φx", "φy", "φz"), unresolved) if u)
    assert f"on {names} they do not resolve it" in noise["pose_covariance_source"], noise["pose_covariance_source"]
    support = noise["holdout_inliers"]
    assert support > 0 and (
        f"; a pose on n < {support:.0f} inliers (their median) gets C_map·{support:.0f}/n;" in noise["pose_covariance_source"]
    ), noise["pose_covariance_source"]
    assert noise["pose_covariance_source"].endswith(
        f"rising linearly to C_map at the held-out keyframes' least distance (ν ≥ {noise['near']['holdout_distance']:.2f})"
    ), noise["pose_covariance_source"]
    path = tmp_path / "exact.geoloc"
    exact_map.save(path)
    # the samples are build-time diagnostics, what they resolve is kept: a loaded map says the same
    loaded = geoloc.Map.load(path).map_noise
    assert loaded["holdout"] is None or len(loaded["holdout"]["keyframe"]) == 0
    np.testing.assert_array_equal(loaded["resolved"], noise["resolved"])
    assert loaded["pose_covariance_source"] == noise["pose_covariance_source"]


def test_a_pose_with_less_support_than_the_held_out_keyframes_gets_more_map_noise(
    exact: tuple[Any, geoloc.Map], tmp_path: Path
) -> None:
    """n̄ is the median inliers of the held-out samples C_map used; it is stored with the map;
    a pose on n inliers carries C_map·max(1, n̄/n) (written out in numpy here)."""
    seq, m = exact
    noise = m.map_noise
    h = noise["holdout"]
    assert h["used"].all() and len(h["inliers"]) == noise["holdout_samples"]
    n_bar = float(np.median(h["inliers"]))
    assert noise["holdout_inliers"] == n_bar > 0
    c = noise["pose_covariance"]
    for n in (1, int(n_bar) // 2, int(n_bar), 10 * int(n_bar)):
        np.testing.assert_allclose(m.map_noise_at(n), c * max(1.0, n_bar / n), rtol=1e-15)
    np.testing.assert_array_equal(m.map_noise_at(None), c)
    for bad in (-1, 1.5, True, "10"):
        with pytest.raises(ValueError, match="inliers"):
            m.map_noise_at(bad)  # type: ignore[arg-type]
    np.testing.assert_array_equal(m.map_noise_at(2**70), c)  # more support than any n̄: unscaled
    m.save(tmp_path / "support.geoloc")
    assert geoloc.Map.load(tmp_path / "support.geoloc").map_noise["holdout_inliers"] == n_bar
    # single images: each pose's factor from its own inliers and its distance from the keyframes
    results = geoloc.Localizer(m).localize_sequence(seq[1:300:10], "single")
    assert any(r.pose is not None for r in results)
    for r in results:
        want = 1.0 if r.pose is None else near_weight(noise, r.novelty) * max(1.0, n_bar / r.inliers)
        assert r.map_noise_scale == pytest.approx(want, rel=1e-15), (r.inliers, r.source)


def pose_distances(pose: Any, keyframes: Any) -> Any:
    """ν of ``pose`` from each keyframe, written out: √((‖Δt‖ / 0.1 m)² + (angle / 5°)²), the
    angle from the trace of R_kᵀR."""
    t = np.linalg.norm(keyframes[:, :3, 3] - pose[:3, 3], axis=1)
    trace = np.einsum("kji,ji->k", keyframes[:, :3, :3], pose[:3, :3])
    angle = np.degrees(np.arccos(np.clip((trace - 1) / 2, -1, 1)))
    return np.hypot(t / 0.1, angle / 5.0)


def near_weight(noise: dict[str, Any], novelty: float | None) -> float:
    """w = clamp((ν − ν₀)/(ν₁ − ν₀), 0, 1), 1 without a near regime."""
    near = noise["near"]
    if near is None or novelty is None:
        return 1.0
    return float(np.clip((novelty - near["spacing"]) / (near["holdout_distance"] - near["spacing"]), 0.0, 1.0))


def test_a_pose_beside_the_keyframes_carries_their_variance_not_c_map(
    exact: tuple[Any, geoloc.Map], tmp_path: Path
) -> None:
    """The near regime: C_near where the keyframes are as close as to each other, C_map from
    the held-out keyframes' least distance on, linear between; a result's novelty is its
    camera pose's distance from the nearest keyframe (checked in numpy); the regime survives
    the file. The labels here are exact, so the images agree with them and the map keeps
    them: C_near is the labels' σ the adjustment estimated."""
    seq, m = exact
    noise = m.map_noise
    near = noise["near"]
    assert near is not None and 0 < near["spacing"] < near["holdout_distance"]
    h = noise["holdout"]
    assert near["holdout_distance"] == h["novelty"][h["used"]].min()
    keyframes = m.camera_poses
    spacing = [np.sort(pose_distances(k, keyframes))[1] for k in keyframes]
    assert near["spacing"] == pytest.approx(np.median(spacing), rel=1e-9)
    labels = m.labels
    assert labels is not None
    sigma_m, sigma_deg = labels["label_sigma_m"], labels["label_sigma_deg"]
    want = np.minimum(np.r_[[sigma_m**2] * 3, [np.radians(sigma_deg) ** 2] * 3], np.diag(noise["pose_covariance"]))
    np.testing.assert_allclose(np.diag(near["covariance"]), want, rtol=1e-12)
    c, c_near, n_bar = noise["pose_covariance"], near["covariance"], noise["holdout_inliers"]
    for nu in (0.0, near["spacing"], (near["spacing"] + near["holdout_distance"]) / 2, near["holdout_distance"], 50.0):
        w = near_weight(noise, nu)
        np.testing.assert_allclose(m.map_noise_at(10, nu), (1 - w) * c_near + w * c * max(1.0, n_bar / 10), rtol=1e-12)
    assert near_weight(noise, near["spacing"]) == 0.0 and near_weight(noise, near["holdout_distance"]) == 1.0
    for bad in (-1.0, float("nan"), "1", True):
        with pytest.raises(ValueError, match="novelty"):
            m.map_noise_at(10, bad)  # type: ignore[arg-type]
    # queries between the keyframes: their novelty is that of their camera pose, most are near
    results = geoloc.Localizer(m).localize_sequence(seq[1:300:10], "single")
    answered = [r for r in results if r.pose is not None]
    assert answered and all(r.novelty is not None for r in answered)
    for r in answered:
        assert r.novelty == pytest.approx(pose_distances(r.camera_pose, keyframes).min(), rel=1e-6, abs=1e-9)
    assert np.median([r.novelty for r in answered]) < near["spacing"]
    assert all(r.novelty is None for r in results if r.pose is None)
    m.save(tmp_path / "near.geoloc")
    back = geoloc.Map.load(tmp_path / "near.geoloc").map_noise["near"]
    assert back is not None and back["spacing"] == near["spacing"] and back["holdout_distance"] == near["holdout_distance"]
    np.testing.assert_array_equal(back["covariance"], c_near)


def test_sequential_is_never_worse_than_single(room: tuple[Any, Any, geoloc.Map]) -> None:
    _, test, m = room
    summaries = {}
    for mode in ("single", "sequential"):
        results = geoloc.Localizer(m).localize_sequence(test, mode)
        summaries[mode] = summarize_results(results, test.poses)
    single, seq = summaries["single"], summaries["sequential"]
    # "no worse": within 15 % of the single mode's median — a fifth of a millimetre on this
    # scene, whose fast orbit (3 m/s) gives the motion model nothing to add: 1.08× without the
    # map's velocity prior, 1.12× with it (1.54 mm single, 2026-11-25), rotation better in both
    assert seq["median_translation_m"] <= 1.15 * single["median_translation_m"]
    assert seq["median_rotation_deg"] <= 1.15 * single["median_rotation_deg"]
    assert seq["median_translation_all_m"] <= 1.15 * single["median_translation_all_m"]
    assert seq["median_rotation_all_deg"] <= 1.15 * single["median_rotation_all_deg"]
    assert seq["recall"]["5cm_5deg"] >= single["recall"]["5cm_5deg"]
    assert seq["nees_coverage"] >= 0.85 and single["nees_coverage"] >= 0.85


def test_localize_sequence_modes(room: tuple[Any, Any, geoloc.Map]) -> None:
    """single resets before every frame (every source geometric or lost), sequential keeps the
    history; an unknown mode is refused by name."""
    _, test, m = room
    short = test[:6]
    single = geoloc.Localizer(m).localize_sequence(short, "single")
    assert len(single) == 6 and {r.source for r in single} <= {"geometric", "lost"}
    assert all("decode" in r.timings and r.timings["total"] >= r.timings["decode"] for r in single)
    sequential = geoloc.Localizer(m).localize_sequence(short, "sequential")
    assert any(r.source in ("fused", "motion") for r in sequential)
    with pytest.raises(geoloc.InvalidInputError, match="mode: expected one of single, sequential"):
        geoloc.Localizer(m).localize_sequence(short, "batch")
