"""The scripts in benchmarks/ are not run by the test suite (they time things and take
minutes), but every one of them must at least compile, and those with options answer
``--help`` (importing what they use): a script broken
by a change of the API would otherwise only show when someone regenerates a report."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

BENCHMARKS = sorted((Path(__file__).resolve().parents[1] / "benchmarks").glob("*.py"))
SCRIPTS = [p for p in BENCHMARKS if not p.name.startswith("_")]
#: The scripts with a command line (the others run their one measurement when started).
WITH_OPTIONS = [p for p in SCRIPTS if "argparse" in p.read_text(encoding="utf-8")]


def test_there_are_benchmarks() -> None:
    assert len(SCRIPTS) >= 10, SCRIPTS


@pytest.mark.parametrize("path", BENCHMARKS, ids=[p.name for p in BENCHMARKS])
def test_every_benchmark_compiles(path: Path) -> None:
    compile(path.read_text(encoding="utf-8"), str(path), "exec")


@pytest.mark.slow
@pytest.mark.parametrize("path", WITH_OPTIONS, ids=[p.name for p in WITH_OPTIONS])
def test_every_benchmark_with_options_answers_help(path: Path) -> None:
    result = subprocess.run([sys.executable, str(path), "--help"], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "usage:" in result.stdout


def _calibration_module():
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import calibration

    return calibration


def test_the_map_noise_factor_for_95_percent_has_its_closed_form() -> None:
    """C = C_G + C_map with C_G = εI (ε = 1e-12) and C_map = I: a frame's NEES at factor s is
    ‖δ‖²/(s + ε), so
    19 of 20 frames with ‖δ‖² = 1, …, 20 lie inside χ²₆ 95 % exactly from s = 19/χ²₆(0.95);
    per axis (δ on one axis) |δ| ≤ 1.96·√s from s = 19/1.96². Lost frames are skipped;
    nothing to cover gives None; frames the measurement part already covers give 0."""
    from geoloc.evaluation import CHI2_6_95, COVERAGE_Z

    cal = _calibration_module()
    eye = np.eye(6)
    frames = [{"d": np.sqrt(k) * np.eye(6)[0], "covariance": (1 + 1e-12) * eye} for k in range(1, 21)]
    frames.append({"d": None, "covariance": None})
    nees_factor = cal.map_noise_scale_for_coverage(frames, "d", eye)
    assert nees_factor == pytest.approx(19 / CHI2_6_95, rel=1e-9)
    axis_factor = cal.map_noise_scale_for_coverage(frames, "d", eye, per_axis=True)
    assert axis_factor == pytest.approx(19 / COVERAGE_Z**2, rel=1e-9)
    assert cal.map_noise_scale_for_coverage([{"d": None, "covariance": None}], "d", eye) is None
    covered = [{"d": 0.1 * np.ones(6), "covariance": 2 * eye}]
    assert cal.map_noise_scale_for_coverage(covered, "d", eye) == 0.0
    # frames whose covariance holds the map noise scaled by 2 (C = εI + 2·C_map): NEES at s is
    # ‖δ‖²/(2s + ε), so the same 19 of 20 from s = 19/(2·χ²₆(0.95))
    scaled = [{"d": f["d"], "covariance": (2 + 1e-12) * eye, "map_noise_scale": 2.0} for f in frames[:-1]]
    assert cal.map_noise_scale_for_coverage(scaled, "d", eye) == pytest.approx(19 / (2 * CHI2_6_95), rel=1e-9)


def test_coverage_by_map_noise_factor_has_its_closed_form() -> None:
    """The same frames (C = εI + C_map, C_map = I, ‖δ‖² = k on one axis, k = 1…20): at factor s
    frame k is inside χ²₆ 95 % when k ≤ s·χ²₆(0.95) (12.59 s) and inside 1.96σ on its axis when
    k ≤ 1.96²·s (3.84 s), so at s = 0.1, 0.25, 0.5, 1, 2 the counts are 1, 3, 6, 12, 20 of 20
    (NEES) and 0, 0, 1, 3, 7 of 20 (axis)."""
    from geoloc.evaluation import CHI2_6_95, COVERAGE_Z

    cal = _calibration_module()
    eye = np.eye(6)
    frames = [{"d": np.sqrt(k) * np.eye(6)[0], "covariance": (1 + 1e-12) * eye} for k in range(1, 21)]
    frames.append({"d": None, "covariance": None})
    pairs = cal.measurement_and_map_noise(frames, "d", eye)
    assert len(pairs) == 20
    for s in cal.MAP_NOISE_SCALES:
        assert cal.coverage_at(pairs, s) == sum(k <= s * CHI2_6_95 for k in range(1, 21)) / 20
        assert cal.coverage_at(pairs, s, per_axis=True) == sum(k <= COVERAGE_Z**2 * s for k in range(1, 21)) / 20
    assert cal.coverage_by_map_noise_scale(pairs) == "0.1: 5/0, 0.25: 15/0, 0.5: 30/5, 1: 60/15, 2: 100/35"
    assert cal.coverage_by_map_noise_scale([]) == "—"
    # 1 frame of 200 far outside at every s: 99.5 %, not rounded up to a 100 that hides it
    far = [(np.zeros(6), 1e-12 * eye, eye)] * 199 + [(1e3 * np.ones(6), 1e-12 * eye, eye)]
    assert cal.coverage_by_map_noise_scale(far) == ", ".join(f"{s:g}: 99.5/99.5" for s in cal.MAP_NOISE_SCALES)


def test_the_modes_are_compared_on_the_frames_both_localized() -> None:
    cal = _calibration_module()
    frames = {
        "single": [{"d": [0.01, 0, 0]}, {"d": None}, {"d": [0.03, 0, 0]}, {"d": [0.05, 0, 0]}],
        "sequential": [{"d": [0.02, 0, 0]}, {"d": [0.9, 0, 0]}, {"d": None}, {"d": [0.04, 0, 0]}],
    }
    # frames 0 and 3: single 1 and 5 cm (median 3), sequential 2 and 4 cm (median 3)
    assert cal.common_frame_medians(frames, "d") == (
        "2 frames: single 3.00 cm, sequential 3.00 cm (sequential farther on 1, closer on 1: sign test p = 1.00)"
    )
    assert cal.common_frame_medians({"single": [{"d": None}], "sequential": [{"d": [1, 0, 0]}]}, "d") == (
        "no frame localized in both modes"
    )


def test_the_paper_split_is_refused_with_per_fold_network_descriptors(tmp_path: Path) -> None:
    script = Path(__file__).resolve().parents[1] / "benchmarks" / "calibration.py"
    result = subprocess.run([sys.executable, str(script), "--folds", "", "--paper-split", "--network", str(tmp_path / "net")],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 2 and "--paper-split: the saved network descriptors are per fold" in result.stderr, result.stderr


def test_outside_region_counts_answers_beyond_the_chi2_999_quantile() -> None:
    """Against scipy's χ²₆ quantile and a hand-built set: errors of NEES 22.4 and 22.5 fall
    either side of it; lost frames and frames without an error are not counted."""
    stats = pytest.importorskip("scipy.stats")
    cal = _calibration_module()
    assert cal.CHI2_6_999 == pytest.approx(stats.chi2.ppf(0.999, 6), rel=1e-12)
    cov = np.diag([4.0, 1.0, 1.0, 1.0, 1.0, 1.0])
    frame = lambda nees: {"d": [2.0 * np.sqrt(nees), 0, 0, 0, 0, 0], "covariance": cov.tolist()}  # noqa: E731
    frames = [frame(22.4), frame(22.5), frame(100.0), frame(0.0), {"d": None, "covariance": cov.tolist()},
              {"d": [1.0] * 6, "covariance": None}]
    assert cal.outside_region(frames, "d") == (2, 4)


@pytest.mark.parametrize(("k", "m"), [(0, 0), (0, 1), (3, 0), (52, 46), (55, 43), (58, 40), (10, 90), (50, 50)])
def test_the_sign_test_is_scipys_exact_binomial_test(k: int, m: int) -> None:
    stats = pytest.importorskip("scipy.stats")
    cal = _calibration_module()
    expected = 1.0 if k + m == 0 else stats.binomtest(k, k + m, 0.5).pvalue
    assert cal.sign_test(k, m) == pytest.approx(expected, rel=1e-12)


def test_the_written_keyframe_poses_read_back_as_a_reference(tmp_path: Path) -> None:
    """label_adjustment.py --write-poses: the file load_reference reads, with the frame
    indices as keys and the poses bit for bit (a second reference for calibration.py)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import label_adjustment

    from geoloc.lie import se3_exp
    from geoloc.reference import load_reference

    rng = np.random.default_rng(3)
    poses = np.stack([se3_exp(rng.normal(size=6)) for _ in range(5)])
    frames = np.array([4, 7, 9, 20, 21])
    path = tmp_path / "poses.txt"
    label_adjustment.write_reference(path, frames, poses)
    keys, read = load_reference(path, "7scenes-reference")
    assert keys.tolist() == frames.tolist()
    # the reader projects each rotation block onto SO(3): exact rotations come back within rounding
    np.testing.assert_allclose(read, poses, rtol=0, atol=1e-14)
    with pytest.raises(ValueError, match="did not keep every frame"):
        label_adjustment.write_reference(path, frames[:3], poses)


def test_a_step_checked_against_the_reference_is_the_jump_the_reference_shows() -> None:
    """label_adjustment.steps_against_reference on a walk whose labels jump by a known
    translation at keyframe 12 (and nowhere else): the step's disagreement with the truth
    (map and reference alike) is that translation's length, it ranks above every other
    span of its length, and the reference's largest jump lies on it; across a step where
    nothing jumped the labels agree with both."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    import label_adjustment

    from geoloc.lie import se3_exp

    rng = np.random.default_rng(5)
    truth = [np.eye(4)]
    for _ in range(39):
        truth.append(truth[-1] @ se3_exp(np.concatenate([rng.normal(0, 0.05, 3), rng.normal(0, 0.02, 3)])))
    truth_arr = np.stack(truth)
    jump = np.eye(4)
    jump[:3, 3] = [0.03, -0.04, 0.0]  # 5 cm, applied in the world frame from keyframe 12 on
    labels = truth_arr.copy()
    labels[12:] = jump @ labels[12:]
    steps = [{"start": 11, "end": 13}, {"start": 30, "end": 32}]
    got = label_adjustment.steps_against_reference(labels, truth_arr, truth_arr, steps, largest=1)
    first, quiet = got["steps"]
    assert first["map"][0] == pytest.approx(0.05, rel=1e-9) and first["reference"][0] == pytest.approx(0.05, rel=1e-9)
    assert first["rank"] > 0.9 and quiet["reference"][0] < 1e-9 and quiet["map"][0] < 1e-9
    assert got["reference_jumps"][0]["covered"] and got["reference_jumps"][0]["reference_m"] == pytest.approx(0.05)


def test_the_integrated_autocorrelation_time_of_an_ar1_series_is_its_closed_form() -> None:
    """AR(1) x_t = ρx_{t−1} + √(1 − ρ²)ε_t has ρ_k = ρ^k, so τ = 1 + 2Σρ^k = (1 + ρ)/(1 − ρ): 4 for
    ρ = 0.6, 1 for white noise (estimated on 20 000 samples, within 10 %)."""
    cal = _calibration_module()
    rng = np.random.default_rng(3)
    for rho, expected in ((0.6, 4.0), (0.0, 1.0)):
        x = np.empty(20_000)
        x[0] = rng.standard_normal()
        for t in range(1, len(x)):
            x[t] = rho * x[t - 1] + np.sqrt(1 - rho**2) * rng.standard_normal()
        assert cal.integrated_autocorrelation_time(x) == pytest.approx(expected, rel=0.1)
    assert cal.integrated_autocorrelation_time(np.ones(50)) == 1.0, "no variance: one sample per frame"


def test_a_block_that_is_one_offset_is_all_shared_and_white_noise_none() -> None:
    """block_structure: errors that are one offset plus a trace of noise have φ ≈ 1 on every
    axis; independent errors have φ ≈ 0 and τ ≈ 1; lost frames are skipped."""
    cal = _calibration_module()
    rng = np.random.default_rng(4)
    offset = np.array([0.02, -0.01, 0.015, 0.003, -0.002, 0.001])
    frames = [{"d": offset + 1e-5 * rng.standard_normal(6), "covariance": 1e-4 * np.eye(6)} for _ in range(100)]
    frames.append({"d": None, "covariance": None})
    phi, _ = cal.block_structure(frames, "d")
    assert np.all(phi > 0.99), phi
    white = [{"d": 0.01 * rng.standard_normal(6), "covariance": 1e-4 * np.eye(6)} for _ in range(2000)]
    phi, tau = cal.block_structure(white, "d")
    assert np.all(phi < 0.01) and np.all(np.abs(tau - 1) < 0.2), (phi, tau)
    assert cal.block_structure(frames[:5], "d") is None


def test_a_right_covariance_lands_independent_frames_in_the_band_as_the_binomial_says() -> None:
    """With independent frames (φ = 0, τ = 1) a right covariance covers each frame with
    probability 0.95, so a block of 100 is in 88–99 % with P(88 ≤ Bin(100, 0.95) ≤ 99), a
    closed form; a block that is one shared offset (φ = 1) is covered 0 or 100 %, never in
    the band; the same seed gives the same value."""
    import math

    cal = _calibration_module()
    binomial = sum(math.comb(100, k) * 0.95**k * 0.05 ** (100 - k) for k in range(88, 100))
    p_nees, p_both = cal.calibrated_band_probability(np.zeros(6), np.ones(6), trials=20_000)
    assert abs(p_nees - binomial) < 4 * math.sqrt(binomial * (1 - binomial) / 20_000), (p_nees, binomial)
    assert p_both <= p_nees
    assert cal.calibrated_band_probability(np.ones(6), np.ones(6), trials=500) == (0.0, 0.0)
    shared = cal.calibrated_band_probability(np.full(6, 0.5), np.full(6, 5.0), trials=500)
    assert shared == cal.calibrated_band_probability(np.full(6, 0.5), np.full(6, 5.0), trials=500)
    assert shared[0] < p_nees - 0.2, "a shared offset makes a block's coverage all or nothing"


def test_the_held_out_excess_is_binned_by_support_as_written_out() -> None:
    """Two maps (n̄ 100 and 200) whose held-out keyframes have δ = a on tx and b on φx and
    C_G = c·I (c = 1e-7): the excess is a² − 3c on translation and b² − 3c on rotation, binned by n/n̄.
    Written out: n/n̄ = 0.1 and 0.2 fall in [0, 0.25) (rule factors 10 and 5, mean 7.5), 0.6 in
    [0.5, 0.75), 1.0 and 2.5 in ≥ 1; [0.25, 0.5) and [0.75, 1) are empty and left out; a map
    without n̄ contributes nothing."""
    cal = _calibration_module()

    def noise(n_bar: float, samples: list[tuple[int, float, float]], c: float = 1e-7) -> dict:
        delta = [[a, 0, 0, b, 0, 0] for _, a, b in samples]
        return {"holdout_inliers": n_bar, "holdout": {"inliers": [n for n, _, _ in samples], "delta": delta,
                                                      "covariance": [(c * np.eye(6)).tolist()] * len(samples)}}

    bins = cal.excess_by_support([
        noise(100.0, [(10, 0.03, 0.002), (60, 0.01, 0.001), (250, 0.002, 0.0005)]),
        noise(200.0, [(40, 0.05, 0.004), (200, 0.004, 0.0015)]),
        noise(0.0, [(1, 9.0, 9.0)]),
    ])
    assert [b["bin"] for b in bins] == [[0.0, 0.25], [0.5, 0.75], [1.0, None]]
    assert [b["count"] for b in bins] == [2, 1, 2]
    low, mid, top = bins
    assert low["support"] == pytest.approx(0.15) and low["rule"] == pytest.approx(7.5)
    assert low["translation_m2"] == pytest.approx((0.03**2 + 0.05**2) / 2 - 3e-7, rel=1e-12)
    assert low["rotation_rad2"] == pytest.approx((0.002**2 + 0.004**2) / 2 - 3e-7, rel=1e-12)
    assert mid["rule"] == pytest.approx(100 / 60) and mid["translation_m2"] == pytest.approx(1e-4 - 3e-7, rel=1e-12)
    assert top["rule"] == 1.0 and top["support"] == pytest.approx(1.75)
    assert top["translation_m2"] == pytest.approx((0.002**2 + 0.004**2) / 2 - 3e-7, rel=1e-12)
    line = cal.excess_by_support_line(bins)
    # translation 0.0017 − 3e-7 m² (17.00 cm²) against the top bin's 1e-5 − 3e-7: ×175.2;
    # rotation 1e-5 − 3e-7 rad² (10 mrad²) against 1.25e-6 − 3e-7: ×10.2
    assert line == ("[0, 0.25): 2, 17.00 cm² / 10 mrad² (×175.2 / ×10.2 of n ≥ n̄, the rule ×7.5); "
                    "[0.5, 0.75): 1, 1.00 cm² / 1 mrad² (×10.3 / ×0.7 of n ≥ n̄, the rule ×1.7); "
                    "≥ 1: 2, 0.10 cm² / 1 mrad²"), line
    assert cal.excess_by_support_line([]) == "—"
