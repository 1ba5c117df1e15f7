"""geoloc.plots: the four evaluation PNGs are written, valid and non-empty."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

import geoloc
from geoloc import evaluation, lie

pytest.importorskip("matplotlib")
plots = pytest.importorskip("geoloc.plots")
cv2 = pytest.importorskip("cv2")

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
MIN_PNG_BYTES = 5_000
N_FRAMES = 60
SIGMA_P_M = 0.02
SIGMA_R_RAD = 0.01


def _results() -> dict[str, object]:
    """A calibrated fake run: a circle, errors drawn from the reported covariance, lost frames."""
    rng = np.random.default_rng(0)
    angle = np.linspace(0, 2 * np.pi, N_FRAMES)
    gt = np.tile(np.eye(4), (N_FRAMES, 1, 1))
    gt[:, 0, 3], gt[:, 1, 3], gt[:, 2, 3] = 2 * np.cos(angle), 1.5 * np.sin(angle), 1.2
    gt[:, :3, :3] = lie.so3_exp(np.column_stack([np.zeros(N_FRAMES), np.zeros(N_FRAMES), angle]))
    cov = np.diag([SIGMA_P_M**2] * 3 + [SIGMA_R_RAD**2] * 3)
    delta = rng.multivariate_normal(np.zeros(6), cov, N_FRAMES)
    est = np.einsum("nij,njk->nik", gt, lie.se3_exp(-delta))
    lost = {7, 30}
    sources = ["lost" if k in lost else ("geometric" if k % 3 == 0 else "fused") for k in range(N_FRAMES)]
    return evaluation.summarize(
        [None if k in lost else est[k] for k in range(N_FRAMES)],
        gt,
        covariances=[None if k in lost else cov for k in range(N_FRAMES)],
        sources=sources,
        timestamps=np.arange(N_FRAMES) / 30,
    )


def test_write_all_gives_valid_pngs(tmp_path: Path) -> None:
    written = plots.write_all(_results(), tmp_path / "plots")
    assert set(written) == {"trajectory", "errors", "error_cdf", "calibration"}
    for path in written.values():
        data = path.read_bytes()
        assert data.startswith(PNG_SIGNATURE) and len(data) > MIN_PNG_BYTES, path
        image = cv2.imread(str(path))
        assert image is not None and image.shape[0] > 100 and image.shape[1] > 100
        assert image.std() > 1.0  # something is drawn


def test_bad_input(tmp_path: Path) -> None:
    with pytest.raises(geoloc.InvalidInputError, match="results"):
        plots.plot_trajectory({}, tmp_path / "t.png")
    with pytest.raises(geoloc.InvalidInputError, match="does not exist"):
        plots.plot_error_cdf(_results(), tmp_path / "missing" / "cdf.png")
    with pytest.raises(geoloc.InvalidInputError, match="parent folder"):
        plots.write_all(_results(), tmp_path / "a" / "b")


@pytest.mark.parametrize("suffix", ["svg", "pdf", "eps"])
def test_vector_plots_are_the_same_bytes_in_every_run(tmp_path: Path, suffix: str) -> None:
    """They carried the creation time and (SVG) random clip-path ids."""
    results = _results()
    first = plots.plot_trajectory(results, tmp_path / f"a.{suffix}").read_bytes()
    second = plots.plot_trajectory(results, tmp_path / f"b.{suffix}").read_bytes()
    assert first == second
    assert b"CreationDate" not in first and b"<dc:date>" not in first
    assert first.startswith({"svg": b"<?xml", "pdf": b"%PDF", "eps": b"%!PS"}[suffix])


def test_a_run_with_every_frame_lost_plots_without_warnings(tmp_path: Path) -> None:
    """The calibration plot's legend had no labelled artist and matplotlib warned on stderr."""
    results = dict(_results())
    results["per_frame"] = [{**f, "nees": None} for f in results["per_frame"]]  # type: ignore[attr-defined]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        plots.plot_calibration(results, tmp_path / "calibration.png")


@pytest.mark.parametrize("per_frame", [[{"a": 1}], "abc", [1, 2], [{"position_gt": [0, 0, 0]}]])
def test_malformed_results_are_refused_naming_results(tmp_path: Path, per_frame: object) -> None:
    """A KeyError 'position_gt', a TypeError or an AttributeError came out of the plot functions."""
    for plot in (plots.plot_trajectory, plots.plot_errors_over_time, plots.plot_error_cdf, plots.plot_calibration):
        with pytest.raises(geoloc.InvalidInputError, match="^results: "):
            plot({"per_frame": per_frame}, tmp_path / "p.png")
    bad = dict(_results())
    bad["per_frame"] = [{**f, "nees": "x"} for f in bad["per_frame"]]  # type: ignore[attr-defined]
    with pytest.raises(geoloc.InvalidInputError, match="^results: per_frame entries' 'nees' must be numbers"):
        plots.plot_calibration(bad, tmp_path / "p.png")
