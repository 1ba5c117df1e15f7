"""Accuracy and calibration of estimated poses against ground truth; TUM trajectory files.

Conventions: poses are 4×4 world_from_cam; a pose covariance is 6×6 in the **right-
perturbation tangent space of the estimate, translation first**: the truth is modelled as
T_gt = T_est · exp(δ^), δ = (ρ, φ) ~ N(0, C). So the error vector is
``δ = log(T_est⁻¹ T_gt)^∨`` and the normalized estimation error squared is
``NEES = δᵀ C⁻¹ δ``, χ²₆-distributed for a calibrated estimator (Bar-Shalom et al. 2001,
§5.4): 95 % of frames should have NEES ≤ χ²₆(0.95) = 12.59, and each tangent axis k should
have |δ_k| ≤ 1.96 √C_kk on 95 % of frames.

Reported errors (as in the paper): translation ‖t_est − t_gt‖ in metres and rotation
Θ(R_estᵀ R_gt) in degrees. In :func:`summarize`, frames without an estimate ("lost") count
as **failures in recall** (its denominator is every frame) and are **excluded from medians
and means**, which are over localized frames only; NEES statistics are over the frames that
have a covariance.

Against an independent reference instead of the labels (:mod:`geoloc.reference`, re-exported
here): :func:`load_reference` reads it, :func:`align_reference` fits the similarity S and the
camera-frame offset X with S·R_i·X ≈ M_i on the map's frames, and
:func:`score_against_reference` is :func:`summarize_results` against S·R_j·X.
"""

from __future__ import annotations

import math
import os
from collections import Counter
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import _core, lie
from ._io import write_text_atomic
from ._validation import as_float64, real_scalar, rigid_poses as _poses
from .exceptions import InvalidInputError
from .reference import ReferenceAlignment, align_reference, load_reference, match_reference

__all__ = [
    "CHI2_6_95",
    "CHI2_6_999",
    "RECALL_THRESHOLDS",
    "ReferenceAlignment",
    "align_reference",
    "axis_coverage",
    "chi2_6_cdf",
    "chi2_6_quantile",
    "format_table",
    "format_tum_line",
    "isometric_sigmas",
    "load_reference",
    "match_reference",
    "nees",
    "pose_errors",
    "score_against_reference",
    "summarize",
    "summarize_results",
    "tangent_errors",
    "tum_trajectory_text",
    "write_tum_trajectory",
]

Array = NDArray[np.float64]

CHI2_6_95: float = _core.CHI2_6_95
"""χ²₆(0.95): the 95 % quantile of the chi-square distribution with 6 degrees of freedom (the core's)."""
CHI2_6_999: float = _core.CHI2_6_999
"""χ²₆(0.999): beyond it an error lies outside its covariance's 99.9 % region (the core's)."""
COVERAGE_Z = 1.959963984540054
"""Two-sided 95 % quantile of the standard normal: per-axis coverage uses |δ_k| ≤ z·σ_k."""
RECALL_THRESHOLDS: tuple[tuple[float, float], ...] = ((0.05, 5.0), (0.25, 2.0), (0.10, 1.0))
"""(translation m, rotation deg) pairs for recall: 5 cm/5°, 25 cm/2°, 10 cm/1°."""
TANGENT_AXES = ("tx", "ty", "tz", "rx", "ry", "rz")
"""Names of the right-perturbation tangent axes (ρ then φ, in the estimate's camera axes)."""


# ---------------------------------------------------------------------------- χ²₆


def _real_values(x: ArrayLike, name: str) -> Array:
    """``x`` as float64 (±inf and NaN kept); non-real input is an InvalidInputError."""
    try:
        raw = np.asarray(x)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{name}: cannot be read as an array ({exc})") from None
    if raw.dtype.kind not in "biuf":
        raise InvalidInputError(f"{name}: expected real numbers, got an array of dtype {raw.dtype}")
    return raw.astype(np.float64)


def chi2_6_cdf(x: ArrayLike) -> Array:
    """CDF of χ²₆ (closed form for even degrees of freedom): 1 − e^(−x/2)(1 + x/2 + x²/8).

    ``x`` may be +inf (CDF 1); NaN and non-real values are an InvalidInputError naming ``x``."""
    arr = _real_values(x, "x")
    if np.isnan(arr).any():
        raise InvalidInputError("x: is NaN")
    h = np.maximum(arr, 0.0) / 2.0
    # Beyond h = 400 the tail e^(−h)·(…) is below 1e-170; computing it would overflow h² to inf.
    hs = np.minimum(h, 400.0)
    return np.asarray(np.where(h >= 400.0, 1.0, 1.0 - np.exp(-hs) * (1.0 + hs + hs * hs / 2.0)))


def chi2_6_quantile(p: ArrayLike) -> Array:
    """Inverse of :func:`chi2_6_cdf` for p in [0, 1): the core's χ² quantile (bisection to the last bit)."""
    q = _real_values(p, "p")
    if ((q < 0) | (q >= 1)).any() or not np.isfinite(q).all():
        raise InvalidInputError("p: expected probabilities in [0, 1)")
    flat = np.ascontiguousarray(q, dtype=np.float64).reshape(-1)
    return np.asarray(_core.chi2_quantile(flat, 6)).reshape(q.shape)


# ---------------------------------------------------------------------------- errors


def _pair(est: ArrayLike, gt: ArrayLike) -> tuple[Array, Array]:
    e, g = _poses(est, "est"), _poses(gt, "gt")
    if len(e) != len(g):
        raise InvalidInputError(f"est, gt: expected the same number of poses, got {len(e)} and {len(g)}")
    return e, g


def pose_errors(est: ArrayLike, gt: ArrayLike) -> tuple[Array, Array]:
    """Translation error ‖t_est − t_gt‖ (m) and rotation error Θ(R_estᵀ R_gt) (degrees),
    each (N,), for (N, 4, 4) (or single (4, 4)) world_from_cam poses."""
    e, g = _pair(est, gt)
    diff = e[:, :3, 3] - g[:, :3, 3]
    # ‖d‖ scaled by its largest component: the plain norm overflows to inf at 1e200 m
    big = np.abs(diff).max(axis=1, initial=0.0)
    trans = big * np.linalg.norm(diff / np.where(big > 0, big, 1.0)[:, None], axis=1)
    rel = np.einsum("nji,njk->nik", e[:, :3, :3], g[:, :3, :3])
    rot = np.degrees(lie.rotation_angle(rel))
    return trans, np.asarray(rot, dtype=np.float64).reshape(-1)


def tangent_errors(est: ArrayLike, gt: ArrayLike) -> Array:
    """δ = log(T_est⁻¹ T_gt)^∨ (N, 6), translation first: the truth in the estimate's
    right-perturbation tangent space."""
    e, g = _pair(est, gt)
    return np.asarray(lie.se3_log(lie.se3_compose(lie.se3_inverse(e), g))).reshape(-1, 6)


def _covariances(cov: ArrayLike, n: int, name: str = "cov") -> Array:
    c = as_float64(cov, name)
    if c.shape == (6, 6):
        c = c[None]
    if c.shape != (n, 6, 6):
        raise InvalidInputError(f"{name}: expected shape ({n}, 6, 6), got {c.shape}")
    return c


def nees(est: ArrayLike, cov: ArrayLike, gt: ArrayLike) -> Array:
    """NEES = δᵀ C⁻¹ δ per frame (N,), δ = log(T_est⁻¹ T_gt)^∨, C the estimate's covariance
    (right perturbation, translation first). Raises naming the frame if C is not positive
    definite."""
    delta = tangent_errors(est, gt)
    c = _covariances(cov, len(delta))
    out = np.empty(len(delta))
    for k in range(len(delta)):
        try:
            chol = np.linalg.cholesky(c[k])
        except np.linalg.LinAlgError:
            raise InvalidInputError(f"cov[{k}]: not positive definite") from None
        with np.errstate(all="ignore"):
            w = np.linalg.solve(chol, delta[k])
            out[k] = float(w @ w)
        if not np.isfinite(out[k]):
            # δᵀC⁻¹δ overflows: a covariance at the edge of underflow, or an error beyond any
            # covariance (translations of 1e300) — the frame's three inputs share the blame
            raise InvalidInputError(
                f"cov[{k}], est[{k}], gt[{k}]: the NEES overflows (error up to {np.abs(delta[k]).max():.1e} "
                "against this covariance): the covariance is too close to singular or the poses too far apart"
            )
    return out


def axis_coverage(est: ArrayLike, cov: ArrayLike, gt: ArrayLike, z: float = COVERAGE_Z) -> Array:
    """Per tangent axis (6,): fraction of frames with |δ_k| ≤ z·√C_kk (0.95 when calibrated)."""
    delta = tangent_errors(est, gt)
    c = _covariances(cov, len(delta))
    sigma = np.sqrt(np.maximum(np.diagonal(c, axis1=1, axis2=2), 0.0))
    z = real_scalar(z, "z")
    return np.asarray((np.abs(delta) <= z * sigma).mean(axis=0), dtype=np.float64)


def isometric_sigmas(cov: ArrayLike, name: str = "cov") -> tuple[Array, Array]:
    """The paper's isometric σ per covariance: σ_p = mean √diag(C_ρρ) (m) and
    σ_r = Θ(exp(√diag(C_φφ)^)) (radians). (6, 6) or (N, 6, 6) → (N,), (N,). Errors name
    ``name``."""
    c = as_float64(cov, name)
    if c.shape[-2:] != (6, 6) or c.ndim not in (2, 3):
        raise InvalidInputError(f"{name}: expected shape (6, 6) or (N, 6, 6), got {c.shape}")
    c = c.reshape(-1, 6, 6)
    sd = np.sqrt(np.maximum(np.diagonal(c, axis1=1, axis2=2), 0.0))
    sigma_p = sd[:, :3].mean(axis=1)
    try:
        sigma_r = np.asarray(lie.rotation_angle(lie.so3_exp(sd[:, 3:]))).reshape(-1)
    except InvalidInputError as exc:  # √diag(C_φφ) beyond so3_exp's range
        raise InvalidInputError(f"{name}: rotation standard deviations out of range ({exc})") from None
    return sigma_p, sigma_r


# ---------------------------------------------------------------------------- summary


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def summarize(
    estimates: Sequence[ArrayLike | None],
    ground_truth: ArrayLike,
    covariances: Sequence[ArrayLike | None] | None = None,
    sources: Sequence[str] | None = None,
    timings_ms: Sequence[Mapping[str, float]] | None = None,
    timestamps: ArrayLike | None = None,
) -> dict[str, Any]:
    """The result dictionary (JSON-ready) for N frames.

    ``estimates[k]`` is frame k's (4, 4) world_from_cam pose or None when lost;
    ``covariances[k]`` its (6, 6) right-perturbation covariance (translation first) or None;
    ``sources[k]`` "geometric" / "fused" / "motion" / "lost" (default: "geometric" or "lost");
    ``timings_ms[k]`` per-stage milliseconds (with "total"); ``timestamps`` (N,) seconds, the
    ``timestamp`` of each ``per_frame`` entry (default: k, the frame's position — its
    ``index`` is always k, a position in these N frames, not a dataset frame number).

    Keys: ``frames``, ``localized``, ``median_translation_m``, ``median_rotation_deg``,
    ``mean_translation_m``, ``mean_rotation_deg`` (over localized frames; None if none),
    ``median_translation_all_m``, ``median_rotation_all_deg`` (over **all** frames, a lost
    frame counting as an infinite error — the convention of ``recall``, so that two modes
    that lose different frames are compared on the same frames; None when half or more are
    lost),
    ``recall`` ({"5cm_5deg", "25cm_2deg", "10cm_1deg"}: fraction of **all** frames, lost =
    failure), ``sources`` (counts), ``timing_ms`` ({"median_total", "median_<stage>"}),
    ``nees_coverage`` (fraction of frames with a covariance whose NEES ≤ χ²₆(0.95)),
    ``median_nees``, ``axis_coverage`` ({"tx" … "rz"}: 1.96σ coverage per tangent axis),
    ``calibrated_frames``, ``units`` and ``per_frame`` (index, timestamp, source,
    translation_error_m, rotation_error_deg, sigma_p (m), sigma_r (deg), nees, position,
    position_gt, position_covariance: the 3×3 position covariance rotated into world axes,
    R C_ρρ Rᵀ). Unavailable values are None.
    """
    gt = _poses(ground_truth, "ground_truth")
    n = len(gt)
    for name, seq in (("estimates", estimates), ("covariances", covariances), ("sources", sources), ("timings_ms", timings_ms)):
        if (seq is not None or name == "estimates") and (isinstance(seq, (str, bytes)) or not hasattr(seq, "__len__") or (isinstance(seq, np.ndarray) and seq.ndim == 0)):
            raise InvalidInputError(f"{name}: expected a sequence of {n} entries, got {type(seq).__name__}")
    if len(estimates) != n:
        raise InvalidInputError(f"estimates: expected {n} entries (one per ground-truth pose), got {len(estimates)}")
    for name, seq in (("covariances", covariances), ("sources", sources), ("timings_ms", timings_ms)):
        if seq is not None and len(seq) != n:
            raise InvalidInputError(f"{name}: expected {n} entries, got {len(seq)}")
    times = np.arange(n, dtype=np.float64) if timestamps is None else as_float64(timestamps, "timestamps").reshape(-1)
    if len(times) != n:
        raise InvalidInputError(f"timestamps: expected {n} entries, got {len(times)}")
    localized = np.array([e is not None for e in estimates], dtype=bool)
    src = list(sources) if sources is not None else ["geometric" if ok else "lost" for ok in localized]

    trans = np.full(n, np.nan)
    rot = np.full(n, np.nan)
    est = np.full((n, 4, 4), np.nan)
    if localized.any():
        est[localized] = _poses(np.stack([as_float64(e, f"estimates[{k}]") for k, e in enumerate(estimates) if e is not None]), "estimates")
        trans[localized], rot[localized] = pose_errors(est[localized], gt[localized])
    nees_values = np.full(n, np.nan)
    sigma_p = np.full(n, np.nan)
    sigma_r = np.full(n, np.nan)
    cov_world: list[list[list[float]] | None] = [None] * n
    has_cov = np.zeros(n, dtype=bool)
    cov_stack = np.zeros((n, 6, 6))
    if covariances is not None:
        for k, c in enumerate(covariances):
            if c is not None and localized[k]:
                cov_stack[k] = _covariances(c, 1, f"covariances[{k}]")[0]
                has_cov[k] = True
        if has_cov.any():
            try:
                nees_values[has_cov] = nees(est[has_cov], cov_stack[has_cov], gt[has_cov])
            except InvalidInputError as exc:
                raise InvalidInputError(f"covariances: {exc}") from None
            sigma_p[has_cov], sr = isometric_sigmas(cov_stack[has_cov], "covariances")
            sigma_r[has_cov] = np.degrees(sr)
            for j in np.flatnonzero(has_cov).tolist():
                R = est[j, :3, :3]
                cov_world[j] = (R @ cov_stack[j, :3, :3] @ R.T).tolist()

    ok_t, ok_r = trans[localized], rot[localized]
    recall = {
        f"{round(t * 100)}cm_{round(r)}deg": float(np.mean(localized & (np.nan_to_num(trans, nan=np.inf) <= t) & (np.nan_to_num(rot, nan=np.inf) <= r)))
        for t, r in RECALL_THRESHOLDS
    }
    timing: dict[str, float] = {}
    if timings_ms is not None and n:
        for k, t in enumerate(timings_ms):
            if not isinstance(t, Mapping):
                raise InvalidInputError(f"timings_ms[{k}]: expected a mapping of stage to milliseconds, got {type(t).__name__}")
        stages = sorted({k for t in timings_ms for k in t})
        for stage in stages:
            values = [real_scalar(t[stage], f"timings_ms[{k}][{stage!r}]") for k, t in enumerate(timings_ms) if stage in t]
            timing[f"median_{stage}"] = float(np.median(values))
    nees_ok = nees_values[has_cov]
    summary: dict[str, Any] = {
        "frames": n,
        "localized": int(localized.sum()),
        "median_translation_m": _finite(float(np.median(ok_t))) if len(ok_t) else None,
        "median_rotation_deg": _finite(float(np.median(ok_r))) if len(ok_r) else None,
        "median_translation_all_m": _finite(float(np.median(np.where(localized, trans, np.inf)))) if n else None,
        "median_rotation_all_deg": _finite(float(np.median(np.where(localized, rot, np.inf)))) if n else None,
        "mean_translation_m": _finite(float(np.mean(ok_t))) if len(ok_t) else None,
        "mean_rotation_deg": _finite(float(np.mean(ok_r))) if len(ok_r) else None,
        "recall": recall,
        "sources": dict(sorted(Counter(src).items())),
        "timing_ms": timing,
        "nees_coverage": float(np.mean(nees_ok <= CHI2_6_95)) if len(nees_ok) else None,
        "median_nees": float(np.median(nees_ok)) if len(nees_ok) else None,
        "axis_coverage": (
            dict(zip(TANGENT_AXES, axis_coverage(est[has_cov], cov_stack[has_cov], gt[has_cov]).tolist()))
            if has_cov.any()
            else None
        ),
        "calibrated_frames": int(has_cov.sum()),
        "units": {"translation": "m", "rotation": "deg", "sigma_p": "m", "sigma_r": "deg", "timing": "ms"},
        "per_frame": [
            {
                "index": k,
                "timestamp": float(times[k]),
                "source": src[k],
                "translation_error_m": _finite(trans[k]),
                "rotation_error_deg": _finite(rot[k]),
                "sigma_p": _finite(sigma_p[k]),
                "sigma_r": _finite(sigma_r[k]),
                "nees": _finite(nees_values[k]),
                "position": est[k, :3, 3].tolist() if localized[k] else None,
                "position_gt": gt[k, :3, 3].tolist(),
                "position_covariance": cov_world[k],
            }
            for k in range(n)
        ],
    }
    return summary


def summarize_results(results: Sequence[Any], ground_truth: ArrayLike, timestamps: ArrayLike | None = None) -> dict[str, Any]:
    """:func:`summarize` of localizer results: objects with ``.pose``, ``.covariance``,
    ``.source`` and ``.timings`` (ms per stage), e.g. :class:`geoloc.Localization`."""
    if isinstance(results, (str, bytes)) or not isinstance(results, Sequence):
        raise InvalidInputError(f"results: expected a sequence of localizer results, got {type(results).__name__}")
    for k, r in enumerate(results):
        if not all(hasattr(r, a) for a in ("pose", "covariance", "source")):
            raise InvalidInputError(f"results[{k}]: expected a localizer result (.pose, .covariance, .source), got {type(r).__name__}")
    timings = [dict(getattr(r, "timings", None) or {}) for r in results]
    return summarize(
        [r.pose for r in results],
        ground_truth,
        covariances=[r.covariance for r in results],
        sources=[str(r.source) for r in results],
        timings_ms=timings,
        timestamps=timestamps,
    )


def score_against_reference(
    results: Sequence[Any], alignment: ReferenceAlignment, reference_poses: ArrayLike, timestamps: ArrayLike | None = None
) -> dict[str, Any]:
    """:func:`summarize_results` with the aligned reference as the truth: frame k's estimate
    is compared with S · R_k · X (``alignment.apply(reference_poses)[k]``), where
    ``reference_poses[k]`` is the reference's (4, 4) world_from_cam pose of result k's frame.
    For raw estimates, call :func:`summarize` with ``alignment.apply(reference_poses)``."""
    return summarize_results(results, alignment.apply(reference_poses), timestamps)


def _cell(value: float | None, fmt: str) -> str:
    return "—" if value is None else format(value, fmt)


def format_table(summaries: Mapping[str, Mapping[str, Any]], reference: Mapping[str, tuple[float, float]] | None = None) -> str:
    """A plain-text table laid out like the paper's: one row per sequence, median error as
    "0.02m, 1.10°" (over the localized frames, then over all frames with a lost one as an
    infinite error), then recall, sources and calibration. ``reference`` adds the paper's
    (or any other method's) median (m, deg) per row name."""
    if not isinstance(summaries, Mapping) or not all(isinstance(v, Mapping) for v in summaries.values()):
        raise InvalidInputError("summaries: expected a mapping of row name to a summary (geoloc.evaluation.summarize)")
    if reference is not None and (
        not isinstance(reference, Mapping)
        or not all(isinstance(v, (tuple, list)) and len(v) == 2 for v in reference.values())
    ):
        raise InvalidInputError("reference: expected a mapping of row name to (metres, degrees)")
    header = ["Sequence", "Frames", "Median", "Median, lost=∞", "Mean", "5cm,5°", "25cm,2°", "10cm,1°", "NEES≤χ²₆", "Sources", "ms"]
    if reference is not None:
        header.insert(3, "Reference")
    rows = [header]
    for name, s in summaries.items():
        med = (
            "lost"
            if s.get("median_translation_m") is None
            else f"{s['median_translation_m']:.3f}m, {s['median_rotation_deg']:.2f}°"
        )
        med_all = (
            "—"
            if s.get("median_translation_all_m") is None or s.get("median_rotation_all_deg") is None
            else f"{s['median_translation_all_m']:.3f}m, {s['median_rotation_all_deg']:.2f}°"
        )
        mean = "—" if s.get("mean_translation_m") is None else f"{s['mean_translation_m']:.3f}m, {s['mean_rotation_deg']:.2f}°"
        recall = s.get("recall", {})
        row = [
            name,
            str(s.get("frames", "")),
            med,
            med_all,
            mean,
            _cell(recall.get("5cm_5deg"), ".1%"),
            _cell(recall.get("25cm_2deg"), ".1%"),
            _cell(recall.get("10cm_1deg"), ".1%"),
            _cell(s.get("nees_coverage"), ".1%"),
            " ".join(f"{k}:{v}" for k, v in s.get("sources", {}).items()),
            _cell(s.get("timing_ms", {}).get("median_total"), ".1f"),
        ]
        if reference is not None:
            ref = reference.get(name)
            row.insert(3, "—" if ref is None else f"{ref[0]:.2f}m, {ref[1]:.2f}°")
        rows.append(row)
    widths = [max(len(r[i]) for r in rows) for i in range(len(header))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)).rstrip() for r in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


# ---------------------------------------------------------------------------- TUM files


def format_tum_line(timestamp: float, pose: ArrayLike) -> str:
    """``"t tx ty tz qx qy qz qw"`` for one world_from_cam pose (TUM order: quaternion
    x, y, z, w, with w ≥ 0), every number written exactly (shortest round-trip repr)."""
    t = real_scalar(timestamp, "timestamp")
    if not math.isfinite(t):
        raise InvalidInputError(f"timestamp: expected a finite number, got {timestamp!r}")
    T = _poses(pose, "pose")
    if len(T) != 1:
        raise InvalidInputError(f"pose: expected one (4, 4) pose, got {len(T)}")
    q_wxyz = np.asarray(lie.so3_to_quaternion_wxyz(T[0, :3, :3])).reshape(4)
    if q_wxyz[0] < 0:
        q_wxyz = -q_wxyz
    values = [*T[0, :3, 3], q_wxyz[1], q_wxyz[2], q_wxyz[3], q_wxyz[0]]
    return " ".join(repr(float(v)) for v in [t, *values])


def tum_trajectory_text(timestamps: ArrayLike, poses: ArrayLike, convention: str = "world_from_cam") -> str:
    """``timestamps`` (N,) s and ``poses`` (N, 4, 4) as the text of a TUM trajectory: a
    comment line naming the poses' ``convention``, then one :func:`format_tum_line` per pose."""
    ts = as_float64(timestamps, "timestamps").reshape(-1)
    T = _poses(poses, "poses")
    if len(ts) != len(T):
        raise InvalidInputError(f"timestamps, poses: expected the same count, got {len(ts)} and {len(T)}")
    if not isinstance(convention, str) or "\n" in convention:
        raise InvalidInputError(f"convention: expected one line of text, got {convention!r:.60}")
    lines = [f"# timestamp tx ty tz qx qy qz qw ({convention}; written by geoloc)"]
    lines += [format_tum_line(t, p) for t, p in zip(ts, T)]
    return "\n".join(lines) + "\n"


def write_tum_trajectory(
    path: str | os.PathLike[str], timestamps: ArrayLike, poses: ArrayLike, convention: str = "world_from_cam"
) -> None:
    """Write :func:`tum_trajectory_text` to ``path`` atomically: a temp file in the same
    folder, fsync, rename. Missing parent folders are not created; an unwritable path raises
    InvalidInputError naming it."""
    write_text_atomic(path, tum_trajectory_text(timestamps, poses, convention))
