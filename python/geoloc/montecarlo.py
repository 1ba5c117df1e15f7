"""``geoloc montecarlo``: the paper's Monte-Carlo test of the locator's uncertainty.

The paper's experiment (§Monte-Carlo synthetic experiment): 119 points seen partially by 4
training cameras and the target camera; i.i.d. Gaussian pixel noise σ_p ∈ {1, 2} px on all
2D tracks; pose-label noise ∈ {0, (1 cm, 0.5°), (3 cm, 1°)} on the training cameras; 1000
trials per column. Each trial triangulates the points from the (noisy) labels and solves
the target's PnP, then checks the returned covariance against the true error:

* **per-axis**: |eᵢ| ≤ 1.96 √Cᵢᵢ for each of the 6 axes of e = log(T_true⁻¹ T_est)^∨
  (right perturbation, translation first) — 95 % for a calibrated covariance;
* **NEES**: eᵀC⁻¹e ≤ χ²₆(0.95) = 12.59 — 95 % for a calibrated covariance;
* **the paper's scalar figure**: ‖t_est − t_true‖ ≤ 1.96 σ_p and Θ(R_estᵀR_true) ≤ 1.96 σ_r
  with the isometric σ_p, σ_r of the paper; a calibrated covariance scores ≈72 % (position,
  a χ²₃ ≤ 3.84 event) and ≈99 % (rotation) on it, so it is printed only for comparison.

Two covariance models are compared: ``paper`` (σ̂²(ΣJᵀJ)⁻¹, σ̂² = ‖r‖²/(2p − 1), points
taken as exact) and ``propagated`` (geoloc's default: pixel noise, point uncertainty and —
when label noise is present — the label covariance propagated).
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import asdict, dataclass, field
from typing import Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from . import geometry, lie
from .camera import Camera
from ._validation import real_scalar
from .exceptions import InvalidInputError

__all__ = ["CHI2_6DOF_95", "MAX_TRIALS", "PAPER_TABLE", "SCENES", "MonteCarloColumn", "montecarlo", "format_report"]

Array = NDArray[np.float64]

#: χ²₆ quantile at 95 %.
CHI2_6DOF_95 = 12.591587243743977
#: The paper's Table (Monte-Carlo): (angular %, positional %) per column.
PAPER_TABLE = {
    (1.0, 0.0, 0.0): (95.2, 96.0),
    (2.0, 0.0, 0.0): (94.6, 94.2),
    (1.0, 0.01, 0.5): (84.6, 92.8),
    (2.0, 0.01, 0.5): (79.8, 91.0),
    (1.0, 0.03, 1.0): (49.8, 74.4),
    (2.0, 0.03, 1.0): (62.4, 80.6),
}
DEFAULT_LABEL_NOISE = ((0.0, 0.0), (0.01, 0.5), (0.03, 1.0))
#: The scene kinds: the paper's fixed scene, a fixed short-baseline one, the short-baseline one
#: with the query ahead of the keyframes, a random one per trial.
SCENES = ("paper", "short", "ahead", "random")
N_POINTS = 119


@dataclass
class MonteCarloColumn:
    """Coverage rates (fractions) of one column for one covariance model."""

    model: str
    sigma_px: float
    label_noise_m: float
    label_noise_deg: float
    trials: int
    failures: int
    nees: float
    per_axis: list[float] = field(default_factory=list)
    paper_position: float = 0.0
    paper_rotation: float = 0.0
    median_error_m: float = 0.0
    median_error_deg: float = 0.0


def look_at(centre: Array, target: Array) -> Array:
    """world_from_cam of a camera at ``centre`` looking at ``target`` (z forward, y down)."""
    z = (target - centre) / np.linalg.norm(target - centre)
    up = np.array([1.0, 0.0, 0.0]) if abs(z[1]) > 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = centre
    return T


def paper_scene() -> tuple[Array, Array, Array]:
    """The fixed scene: 4 training cameras on a 1.2 m arc, the target between them and a
    little behind, all looking at 119 points in a 4 × 3 × 2 m box about 5 m away.
    Returns (training poses (4, 4, 4), target pose (4, 4), points (119, 3))."""
    rng = np.random.default_rng(2022)
    focus = np.array([0.0, 0.0, 5.0])
    centres = [np.array([x, 0.05 * i, 0.0]) for i, x in enumerate((-0.6, -0.2, 0.2, 0.6))]
    train = np.stack([look_at(c, focus) for c in centres])
    target = look_at(np.array([0.1, -0.1, -0.3]), focus + np.array([0.2, 0.1, 0.0]))
    points = focus + rng.uniform([-2.0, -1.5, -1.0], [2.0, 1.5, 1.0], size=(N_POINTS, 3))
    return train, target, points


def short_baseline_scene() -> tuple[Array, Array, Array]:
    """The short-baseline scene: 4 training cameras spread over 0.35 m, the target
    among them and a little behind, 119 points 2.5–6 m away — triangulation angles of a few
    degrees, so the points' depth is poorly known and strongly correlated with the labels.
    Returns (training poses (4, 4, 4), target pose (4, 4), points (119, 3))."""
    rng = np.random.default_rng(2035)
    focus = np.array([0.0, 0.0, 4.25])
    centres = [np.array([x, 0.02 * i, 0.0]) for i, x in enumerate((-0.175, -0.058, 0.058, 0.175))]
    train = np.stack([look_at(c, focus) for c in centres])
    target = look_at(np.array([0.03, -0.04, -0.15]), focus + np.array([0.1, 0.05, 0.0]))
    points = rng.uniform([-1.4, -1.0, 2.5], [1.4, 1.0, 6.0], size=(N_POINTS, 3))
    points[:, :2] *= points[:, 2:] / focus[2]  # inside the view frustum at every depth
    return train, target, points


def short_baseline_ahead_scene() -> tuple[Array, Array, Array]:
    """The short-baseline scene's keyframes and points with the target 0.25 m in front of the
    keyframes (towards the points) and turned 6° about its vertical axis: it sees the
    poorly-triangulated depths from a place no keyframe saw them from, where a linearised
    point covariance that is too small shows first.
    Returns (training poses (4, 4, 4), target pose (4, 4), points (119, 3))."""
    train, _, points = short_baseline_scene()
    focus = np.array([0.0, 0.0, 4.25])
    target = look_at(np.array([0.03, -0.04, 0.25]), focus + np.array([0.1, 0.05, 0.0]))
    target[:3, :3] = target[:3, :3] @ lie.so3_exp(np.array([0.0, np.radians(6.0), 0.0]))
    return train, target, points


def random_scene(rng: np.random.Generator) -> tuple[Array, Array, Array]:
    """A random scene of the same kind: 5 cameras in a 3 × 1 × 0.6 m box looking at a random
    focus 4–7 m away, 119 random points around it; one camera is the target."""
    focus = rng.uniform([-1.0, -1.0, 4.0], [1.0, 1.0, 7.0])
    centres = rng.uniform([-1.5, -0.5, -0.3], [1.5, 0.5, 0.3], size=(5, 3))
    poses = np.stack([look_at(c, focus) for c in centres])
    points = focus + rng.uniform([-2.0, -1.5, -1.0], [2.0, 1.5, 1.0], size=(N_POINTS, 3))
    return poses[:4], poses[4], points


def _project(cam: Camera, world_from_cam: Array, points: Array) -> tuple[Array, NDArray[np.bool_]]:
    p = lie.se3_transform_points(lie.se3_inverse(world_from_cam), points)
    uv = p[:, :2] / p[:, 2:] * [cam.fx, cam.fy] + [cam.cx, cam.cy]
    inside = (p[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    return uv, inside


def _trial(
    rng: np.random.Generator,
    cam: Camera,
    scene: tuple[Array, Array, Array],
    sigma: float,
    label: tuple[float, float],
    models: Sequence[str],
) -> dict[str, tuple[Array, Array, geometry.PnPResult] | None]:
    train, target, points = scene
    st, sr = label[0], np.radians(label[1])
    label_cov = None
    labels = train
    if st > 0 or sr > 0:
        noise = np.hstack([rng.normal(0, st, (len(train), 3)), rng.normal(0, sr, (len(train), 3))])
        labels = lie.se3_compose(train, lie.se3_exp(noise))
        label_cov = np.broadcast_to(np.diag([st**2] * 3 + [sr**2] * 3), (len(train), 6, 6)).copy()
    cam_ids, track_ids, pixels = [], [], []
    for k, pose in enumerate(train):
        uv, inside = _project(cam, pose, points)
        uv = uv + rng.normal(0, sigma, uv.shape)
        idx = np.flatnonzero(inside)
        cam_ids.append(np.full(len(idx), k))
        track_ids.append(idx)
        pixels.append(uv[idx])
    tri = geometry.triangulate(
        labels, cam, np.concatenate(cam_ids), np.concatenate(track_ids), np.vstack(pixels),
        pixel_sigma=sigma, pose_covariances=label_cov,
    )
    uv, inside = _project(cam, target, points)
    uv = uv + rng.normal(0, sigma, uv.shape)
    valid = np.zeros(len(points), dtype=bool)
    valid[tri.track_ids] = tri.valid  # one row per observed track; unobserved tracks gave no point
    use = np.flatnonzero(inside & valid)
    rows = tri.rows(use)
    out: dict[str, tuple[Array, Array, geometry.PnPResult] | None] = {}
    for model in models:
        if model == "paper":
            res = geometry.solve_pnp(tri.points[rows], uv[use], cam, covariance="paper", pixel_sigma=sigma)
        else:
            res = geometry.solve_pnp(
                tri.points[rows], uv[use], cam, pixel_sigma=sigma, uncertainty=tri.uncertainty(rows)
            )
        out[model] = (target, res.pose, res) if res.success else None
    return out


def _score(column: MonteCarloColumn, outcomes: list[tuple[Array, Array, geometry.PnPResult] | None]) -> None:
    good = [o for o in outcomes if o is not None]
    column.failures = len(outcomes) - len(good)
    column.trials = len(good)
    if not good:
        return
    truth = np.stack([o[0] for o in good])
    est = np.stack([o[1] for o in good])
    cov = np.stack([o[2].covariance for o in good])
    e = lie.se3_log(lie.se3_compose(lie.se3_inverse(truth), est))
    nees = np.einsum("ni,nij,nj->n", e, np.linalg.inv(cov), e)
    sd = np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
    column.nees = float(np.mean(nees <= CHI2_6DOF_95))
    column.per_axis = [float(v) for v in np.mean(np.abs(e) <= 1.96 * sd, axis=0)]
    pos_err = np.linalg.norm(est[:, :3, 3] - truth[:, :3, 3], axis=1)
    rot_err = lie.rotation_angle(np.swapaxes(est[:, :3, :3], 1, 2) @ truth[:, :3, :3])
    sigma_p = np.array([o[2].sigma_p for o in good])
    sigma_r = np.array([o[2].sigma_r for o in good])
    column.paper_position = float(np.mean(pos_err <= 1.96 * sigma_p))
    column.paper_rotation = float(np.mean(rot_err <= 1.96 * sigma_r))
    column.median_error_m = float(np.median(pos_err))
    column.median_error_deg = float(np.degrees(np.median(rot_err)))


#: Largest ``trials`` :func:`montecarlo` runs (each trial is a few milliseconds per column).
MAX_TRIALS = 100_000


def montecarlo(
    trials: int = 1000,
    sigmas: Sequence[float] = (1.0, 2.0),
    label_noise: Sequence[tuple[float, float]] = DEFAULT_LABEL_NOISE,
    models: Sequence[str] = ("paper", "propagated"),
    scene: str = "paper",
    seed: int = 0,
    progress: Callable[[int, int], None] | None = None,
) -> list[MonteCarloColumn]:
    """Run the experiment; one :class:`MonteCarloColumn` per (label noise, σ, model).

    ``label_noise`` entries are (metres, degrees) standard deviations per axis; ``scene`` is
    ``"paper"`` (one fixed scene), ``"short"`` (one fixed short-baseline scene: keyframes over
    0.35 m, points 2.5–6 m away), ``"ahead"`` (the short-baseline scene with the target 0.25 m
    in front of the keyframes, turned 6°) or ``"random"`` (a new random scene every trial).
    ``trials`` is at most :data:`MAX_TRIALS`; ``seed`` a non-negative integer below 2⁶⁴.
    Invalid arguments raise :class:`geoloc.InvalidInputError` (a ``ValueError``).
    """
    if not isinstance(trials, (int, np.integer)) or not 1 <= trials <= MAX_TRIALS:
        raise InvalidInputError(f"trials: expected an integer in [1, {MAX_TRIALS}], got {trials!r}")
    if not isinstance(seed, (int, np.integer)) or not 0 <= seed < 2**64:
        raise InvalidInputError(f"seed: expected a non-negative integer below 2**64, got {seed!r}")
    if scene not in SCENES:
        raise InvalidInputError(f"scene: expected one of {', '.join(map(repr, SCENES))}, got {scene!r}")
    for m in models:
        if m not in ("paper", "propagated"):
            raise InvalidInputError(f"models: expected 'paper' or 'propagated', got {m!r}")
    sigmas = _nonnegative_list(sigmas, "sigmas", "pixel σ")
    label_noise = [
        tuple(_nonnegative_list(pair, f"label_noise[{i}]", "(metres, degrees)", length=2))  # type: ignore[misc]
        for i, pair in enumerate(_sequence(label_noise, "label_noise"))
    ]
    cam = Camera(525.0, 525.0, 320.0, 240.0)
    rng = np.random.default_rng(seed)
    fixed = {"short": short_baseline_scene, "ahead": short_baseline_ahead_scene}.get(scene, paper_scene)()
    columns: list[MonteCarloColumn] = []
    total = trials * len(sigmas) * len(label_noise)
    done = 0
    for label in label_noise:
        for sigma in sigmas:
            outcomes: dict[str, list[tuple[Array, Array, geometry.PnPResult] | None]] = {m: [] for m in models}
            for _ in range(trials):
                s = random_scene(rng) if scene == "random" else fixed
                for m, o in _trial(rng, cam, s, sigma, label, models).items():
                    outcomes[m].append(o)
                done += 1
                if progress is not None:
                    progress(done, total)
            for m in models:
                col = MonteCarloColumn(m, sigma, label[0], label[1], 0, 0, 0.0)
                _score(col, outcomes[m])
                columns.append(col)
    return columns


def _sequence(values: object, name: str) -> list[object]:
    """``values`` as a non-empty list; InvalidInputError naming ``name`` for a scalar or string."""
    if isinstance(values, (str, bytes)) or not isinstance(values, (list, tuple, np.ndarray)):
        raise InvalidInputError(f"{name}: expected a sequence, got {type(values).__name__} {values!r:.40}")
    if len(values) == 0:
        raise InvalidInputError(f"{name}: expected at least one entry")
    return list(values)


def _nonnegative_list(values: object, name: str, what: str, length: int | None = None) -> list[float]:
    """``values`` as finite numbers ≥ 0 (``length`` of them when given), or InvalidInputError
    naming ``name`` (a noise level is a standard deviation)."""
    items = _sequence(values, name)
    if length is not None and len(items) != length:
        raise InvalidInputError(f"{name}: expected {what}, {length} numbers, got {len(items)}")
    out = [real_scalar(v, name) for v in items]
    if not all(math.isfinite(v) and v >= 0.0 for v in out):
        raise InvalidInputError(f"{name}: expected finite standard deviations ≥ 0, got {out}")
    return out


def format_report(columns: list[MonteCarloColumn], trials: int, scene: str, seconds: float) -> str:
    """The table the command prints: coverage (%) per column and model, the paper's beside."""
    keys = sorted({(c.label_noise_m, c.label_noise_deg, c.sigma_px) for c in columns})
    head = "  ".join(f"{_label(m, d):>12}" for m, d, _ in keys)
    sig = "  ".join(f"{'σ=' + format(s, 'g') + ' px':>12}" for _, _, s in keys)
    lines = [
        f"Monte-Carlo: {trials} trials per column, {scene} scene, {N_POINTS} points, 4 training cameras + target ({seconds:.1f} s)",
        f"{'label noise':<34}{head}",
        f"{'pixel noise':<34}{sig}",
        f"{'paper, as published: angular':<34}" + "  ".join(f"{_paper(s, m, d, 0):>12}" for m, d, s in keys),
        f"{'paper, as published: positional':<34}" + "  ".join(f"{_paper(s, m, d, 1):>12}" for m, d, s in keys),
    ]
    for model in dict.fromkeys(c.model for c in columns):
        by_key = {(c.label_noise_m, c.label_noise_deg, c.sigma_px): c for c in columns if c.model == model}
        cols = [by_key[k] for k in keys]
        lines.append(f"covariance={model}")
        rows: list[tuple[str, Callable[[MonteCarloColumn], str]]] = [
            ("  paper's scalar, position", lambda c: f"{100 * c.paper_position:.1f}"),
            ("  paper's scalar, rotation", lambda c: f"{100 * c.paper_rotation:.1f}"),
            ("  per-axis 1.96σ, min–max", lambda c: f"{100 * min(c.per_axis):.1f}–{100 * max(c.per_axis):.1f}" if c.per_axis else "n/a"),
            ("  NEES χ²₆ ≤ 12.59", lambda c: f"{100 * c.nees:.1f}"),
            ("  median error (cm / °)", lambda c: f"{100 * c.median_error_m:.2f}/{c.median_error_deg:.2f}"),
            ("  failed trials", lambda c: f"{c.failures}"),
        ]
        for name, fmt in rows:
            lines.append(f"{name:<34}" + "  ".join(f"{fmt(c):>12}" for c in cols))
    lines.append("target for a calibrated covariance: per-axis and NEES 95 %; scalar ≈72 % / ≈99 %")
    return "\n".join(lines)


def _label(m: float, d: float) -> str:
    return "none" if m == 0 and d == 0 else f"{100 * m:g} cm, {d:g}°"


def _paper(sigma: float, m: float, d: float, which: int) -> str:
    v = PAPER_TABLE.get((sigma, m, d))
    return "—" if v is None else f"{v[which]:.1f}"


def text_progress(done: int, total: int) -> None:
    """A one-line progress bar on stderr, redrawn at each percent."""
    if done != total and done % max(1, total // 100):
        return
    width = 30
    filled = int(width * done / total)
    sys.stderr.write(f"\r[{'#' * filled}{'.' * (width - filled)}] {done}/{total} trials")
    if done == total:
        sys.stderr.write("\n")
    sys.stderr.flush()


def main(trials: int, models: Sequence[str], scene: str, seed: int, json_path: str | None, show_progress: bool) -> int:
    """Run and print; write the columns as JSON to ``json_path`` when given."""
    start = time.perf_counter()
    show = show_progress and sys.stderr.isatty()
    columns = montecarlo(trials, models=models, scene=scene, seed=seed, progress=text_progress if show else None)
    print(format_report(columns, trials, scene, time.perf_counter() - start))
    if json_path:
        from ._io import write_json_atomic

        write_json_atomic(json_path, {"trials": trials, "scene": scene, "seed": seed, "columns": [asdict(c) for c in columns]})
    return 0
