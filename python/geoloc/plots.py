"""PNG plots of an evaluation (matplotlib, Agg canvas, no display, no pyplot state).

Each function takes the result dictionary of :func:`geoloc.evaluation.summarize` (its
``per_frame`` entries) and writes one PNG; :func:`write_all` writes all four:

* ``trajectory.png`` — top view of the estimated and ground-truth positions, with the 95 %
  position ellipse of each estimate. The covariance's translation block lives in the
  estimate's right-perturbation tangent (camera axes), so it is rotated into world axes
  first (Σ_world = R C_ρρ Rᵀ, which ``summarize`` stores as ``position_covariance``), then
  restricted to the plotted pair of axes: the ellipse is {x : xᵀ Σ₂⁻¹ x ≤ χ²₂(0.95)}.
  The two world axes plotted are the two along which the ground truth spreads most.
* ``errors.png`` — translation and rotation error over time, points coloured by source.
* ``error_cdf.png`` — empirical CDFs of the translation and rotation errors (lost frames
  never reach the curve's top: the CDF is over all frames).
* ``calibration.png`` — sorted NEES against the χ²₆ quantiles (a calibrated covariance
  lies on the diagonal; above it is over-confident).
"""

from __future__ import annotations

import io
import math
import os
import re
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ._io import as_path, check_output_path, write_bytes_atomic
from ._opencv import import_figure
from .evaluation import CHI2_6_95, chi2_6_quantile
from .exceptions import InvalidInputError

__all__ = ["plot_calibration", "plot_error_cdf", "plot_errors_over_time", "plot_trajectory", "write_all"]

CHI2_2_95 = -2.0 * math.log(0.05)
"""χ²₂(0.95) = −2 ln 0.05: the 95 % ellipse of a 2-D Gaussian."""
ELLIPSE_POINTS = 48
SOURCE_COLOURS = {"geometric": "tab:blue", "fused": "tab:green", "motion": "tab:orange", "lost": "tab:red"}
FIGURE_DPI = 110
#: The files :func:`write_all` writes, by plot.
PLOT_FILES = {"trajectory": "trajectory.png", "errors": "errors.png", "error_cdf": "error_cdf.png", "calibration": "calibration.png"}
CALIBRATION_Y_RANGE = 4.0
"""The calibration plot shows NEES up to this multiple of its x range; larger ones are
marked at the top edge (over-confident frames would otherwise squash the plot)."""
AXIS_NAMES = ("x", "y", "z")

Results = Mapping[str, Any]


def _frames(results: Results, keys: tuple[str, ...]) -> list[Mapping[str, Any]]:
    """``results["per_frame"]``, each entry a mapping holding ``keys`` (what the plot reads);
    InvalidInputError naming ``results`` and the first entry and key missing otherwise."""
    frames = results.get("per_frame") if isinstance(results, Mapping) else None
    if not frames or not isinstance(frames, (list, tuple)):
        raise InvalidInputError("results: expected the dictionary of geoloc.evaluation.summarize with per_frame entries")
    for i, f in enumerate(frames):
        missing = [k for k in keys if k not in f] if isinstance(f, Mapping) else list(keys)
        if missing:
            raise InvalidInputError(
                f"results: per_frame[{i}] has no {missing[0]!r} (expected the entries of geoloc.evaluation.summarize)"
            )
    return list(frames)


def _save(fig: Any, path: str | os.PathLike[str]) -> Path:
    """Render ``fig`` in memory in the format of ``path``'s suffix (PNG without one), then
    write it atomically (never a half-written file; matplotlib never gets the path). The same
    figure gives the same bytes in every run: the vector formats' creation dates are left out
    and SVG ids are hashed with a fixed salt."""
    import matplotlib

    target = check_output_path(path, "path")
    buffer = io.BytesIO()
    fmt = target.suffix.lstrip(".").lower() or "png"
    undated = {"pdf": {"CreationDate": None}, "svg": {"Date": None}}.get(fmt)
    try:
        with matplotlib.rc_context({"svg.hashsalt": "geoloc"}):
            fig.savefig(buffer, format=fmt, dpi=FIGURE_DPI, metadata=undated)
    except ValueError as e:  # a format matplotlib does not write
        raise InvalidInputError(f"path: cannot write a plot as {fmt!r} ({e})") from None
    data = buffer.getvalue()
    if fmt in ("ps", "eps"):  # PostScript takes no metadata to drop the date: its comment line goes
        data = re.sub(rb"^%%CreationDate: [^\n]*\n", b"", data, count=1, flags=re.MULTILINE)
    write_bytes_atomic(target, data, "path")
    return target


def _errors(frames: list[Mapping[str, Any]], key: str) -> np.ndarray:
    """The frames' ``key`` as floats, NaN where it is None (a lost frame)."""
    try:
        return np.array([np.nan if f[key] is None else f[key] for f in frames], dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidInputError(f"results: per_frame entries' {key!r} must be numbers or None") from None


def plot_trajectory(results: Results, path: str | os.PathLike[str]) -> Path:
    """Top view: estimate vs ground truth with 95 % position ellipses (see the module doc)."""
    frames = _frames(results, ("position_gt", "position", "position_covariance"))
    gt = np.array([f["position_gt"] for f in frames], dtype=np.float64)
    spread = gt.max(axis=0) - gt.min(axis=0)
    a, b = sorted(np.argsort(spread)[::-1][:2].tolist())
    Figure = import_figure()
    fig = Figure(figsize=(6.4, 5.6))
    ax = fig.add_subplot()
    ax.plot(gt[:, a], gt[:, b], "-", color="0.3", lw=1.2, label="ground truth")
    est = [(k, f) for k, f in enumerate(frames) if f["position"] is not None]
    if est:
        pos = np.array([f["position"] for _, f in est])
        ax.plot(pos[:, a], pos[:, b], ".", color="tab:blue", ms=3, label="estimate")
        angle = np.linspace(0, 2 * math.pi, ELLIPSE_POINTS)
        circle = np.stack([np.cos(angle), np.sin(angle)])
        labelled = False
        for _, f in est:
            if f["position_covariance"] is None:
                continue
            cov = np.array(f["position_covariance"])[np.ix_([a, b], [a, b])]
            vals, vecs = np.linalg.eigh(cov)
            outline = vecs @ (np.sqrt(np.maximum(vals, 0.0) * CHI2_2_95)[:, None] * circle)
            ax.plot(
                f["position"][a] + outline[0],
                f["position"][b] + outline[1],
                "-",
                color="tab:purple",
                lw=0.6,
                alpha=0.7,
                label=None if labelled else "95 % ellipse",
            )
            labelled = True
    ax.set_xlabel(f"{AXIS_NAMES[a]} [m]")
    ax.set_ylabel(f"{AXIS_NAMES[b]} [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title("Trajectory (top view)")
    ax.legend(loc="best", fontsize=8)
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    return _save(fig, path)


def plot_errors_over_time(results: Results, path: str | os.PathLike[str]) -> Path:
    """Translation (cm) and rotation (deg) error per frame over time, coloured by source;
    lost frames are marked along the bottom."""
    frames = _frames(results, ("timestamp", "translation_error_m", "rotation_error_deg", "source"))
    t = np.array([f["timestamp"] for f in frames], dtype=np.float64)
    trans, rot = _errors(frames, "translation_error_m") * 100, _errors(frames, "rotation_error_deg")
    sources = np.array([f["source"] for f in frames])
    Figure = import_figure()
    fig = Figure(figsize=(7.5, 5.0))
    axes = fig.subplots(2, 1, sharex=True)
    for ax, values, label in ((axes[0], trans, "translation error [cm]"), (axes[1], rot, "rotation error [°]")):
        ax.plot(t, values, "-", color="0.75", lw=0.8)
        for source in sorted(set(sources.tolist())):
            pick = sources == source
            if source == "lost" or np.isnan(values[pick]).all():
                ax.plot(t[pick], np.zeros(int(pick.sum())), "x", color=SOURCE_COLOURS["lost"], ms=5, label="lost")
            else:
                ax.plot(t[pick], values[pick], "o", ms=3, color=SOURCE_COLOURS.get(source, "tab:gray"), label=source)
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8)
    axes[1].set_xlabel("time [s]")
    axes[0].set_title("Error over time")
    fig.tight_layout()
    return _save(fig, path)


def plot_error_cdf(results: Results, path: str | os.PathLike[str]) -> Path:
    """Empirical CDFs of translation (cm) and rotation (deg) error over all frames."""
    frames = _frames(results, ("translation_error_m", "rotation_error_deg"))
    n = len(frames)
    Figure = import_figure()
    fig = Figure(figsize=(8.0, 3.6))
    axes = fig.subplots(1, 2)
    for ax, values, label in (
        (axes[0], _errors(frames, "translation_error_m") * 100, "translation error [cm]"),
        (axes[1], _errors(frames, "rotation_error_deg"), "rotation error [°]"),
    ):
        ok = np.sort(values[np.isfinite(values)])
        if len(ok):
            ax.step(ok, np.arange(1, len(ok) + 1) / n, where="post", color="tab:blue")
        ax.set_xlabel(label)
        ax.set_ylabel("fraction of frames")
        ax.set_ylim(0, 1.02)
        ax.grid(True, alpha=0.3)
    fig.suptitle("Error CDF")
    fig.tight_layout()
    return _save(fig, path)


def plot_calibration(results: Results, path: str | os.PathLike[str]) -> Path:
    """Q–Q plot: sorted NEES against χ²₆ quantiles, with the diagonal and the 95 % line;
    NEES beyond CALIBRATION_Y_RANGE × the x range are marked at the top edge."""
    frames = _frames(results, ("nees",))
    values = np.sort(_errors(frames, "nees"))
    values = values[np.isfinite(values)]
    Figure = import_figure()
    fig = Figure(figsize=(5.0, 5.0))
    ax = fig.add_subplot()
    if len(values):
        expected = chi2_6_quantile((np.arange(1, len(values) + 1) - 0.5) / len(values))
        top = float(max(expected.max(), CHI2_6_95) * 1.1)
        ceiling = CALIBRATION_Y_RANGE * top
        inside_plot = values <= ceiling
        ax.plot(expected[inside_plot], values[inside_plot], "o", ms=3, color="tab:blue", label=f"{len(values)} frames")
        if not inside_plot.all():
            clipped = int((~inside_plot).sum())
            ax.plot(expected[~inside_plot], np.full(clipped, ceiling), "^", ms=5, color="tab:red", label=f"{clipped} beyond the axis")
        ax.plot([0, top], [0, top], "--", color="0.4", lw=1, label="calibrated")
        ax.axhline(CHI2_6_95, color="tab:red", lw=0.8, label="χ²₆(0.95)")
        ax.set_xlim(0, top)
        ax.set_ylim(0, max(top, min(float(values.max()), ceiling)) * 1.05)
        inside = float(np.mean(values <= CHI2_6_95))
        ax.set_title(f"NEES calibration: {inside:.1%} ≤ χ²₆(0.95)")
        ax.legend(loc="upper left", fontsize=8)
    else:
        ax.set_title("NEES calibration: no covariances")
    ax.set_xlabel("χ²₆ quantile")
    ax.set_ylabel("NEES (sorted)")
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    return _save(fig, path)


def write_all(results: Results, directory: str | os.PathLike[str]) -> dict[str, Path]:
    """Write the four plots into ``directory`` (created if missing; its parent must exist);
    returns {name: path}."""
    folder = as_path(directory, "directory")
    if not folder.parent.is_dir():
        raise InvalidInputError(f"directory: parent folder {str(folder.parent)!r} does not exist")
    try:
        folder.mkdir(exist_ok=True)
    except OSError as exc:
        raise InvalidInputError(f"directory: cannot create {str(folder)!r} ({exc.strerror})") from None
    draw = {"trajectory": plot_trajectory, "errors": plot_errors_over_time, "error_cdf": plot_error_cdf, "calibration": plot_calibration}
    return {key: draw[key](results, folder / name) for key, name in PLOT_FILES.items()}
