"""Bundle adjustment of keyframe poses given as labels: the map's label correction as a
function, for a problem of your own or a map's (:meth:`geoloc.Map.label_adjustment_problem`).

The model (geoloc-core's ``adjust``; docs/labels.md): unknowns are per keyframe k the
label-convention pose B_k (world_from_label), the points P_j and one label-to-camera offset
X = label_from_cam (the camera of keyframe k is T_k = B_k X); the minimized cost is

    Σ_o ρ_px(‖π(K, T_k⁻¹ P_j) − u_o‖² / (σ_px s_o)²) + Σ_k ρ_label(e_kᵀ Λ e_k) + e_Xᵀ Λ_X e_X,
    e_k = log(L_k⁻¹ B_k)^∨,   e_X = log(X)^∨,

s_o the observation's keypoint σ (``obs_sigmas``), ρ_px Huber (width 2), ρ_label Cauchy (width 3) with ρ(s) the squared-norm convention
(Huber: s inside, 2k√s − k² outside; Cauchy: k² ln(1 + s/k²)), Λ = diag(σ_t⁻² I₃, σ_r⁻² I₃)
(right perturbation, translation first) and Λ_X the offset's weak prior (0.2 m, 0.2 rad).
Pixels are undistorted, in the pinhole camera ``intrinsics`` (fx, fy, cx, cy).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import _core
from ._validation import as_float64, real_scalar
from .exceptions import InvalidInputError
from .geometry import _index_array, _matrix_stack, _pose_stack, _real_array

__all__ = ["Adjustment", "AdjustmentProblem", "bundle_adjust"]

Array = NDArray[np.float64]

#: ``max_iterations`` beyond this is this (a cap no adjustment reaches: each round stops when
#: the cost no longer decreases), so that any integer ≥ 1 is a valid cap.
_ITERATIONS_CAP = 2**32

#: The result of :func:`bundle_adjust` (a compiled class): ``label_poses`` (K, 4, 4) the
#: adjusted B_k, ``camera_poses`` (K, 4, 4) T_k = B_k X, ``offset`` (4, 4) X, ``points``
#: (N, 3), the marginal covariances ``label_pose_covariances`` (K, 6, 6), ``offset_covariance``
#: (6, 6) and ``point_covariances`` (N, 3, 3), ``inliers`` (M,) the observations the last round
#: used, ``label_sigma`` (σ_t m, σ_r rad) the priors used, ``cost`` (start, final) Σρ as above,
#: ``rms_px`` (start, final) and ``iterations``.
Adjustment = _core.Adjustment


@dataclass(frozen=True)
class AdjustmentProblem:
    """A labels' adjustment problem: ``labels`` (K, 4, 4) world_from_label, the priors and the
    start; ``points`` (N, 3) world, a start; observation ``i`` is point ``obs_points[i]`` seen
    by keyframe ``obs_keyframes[i]`` at pixel ``obs_pixels[i]`` (undistorted, px), a keypoint
    of σ ``obs_sigmas[i]`` times the nominal pixel σ (its detector scale, ORB 1.2^level; None:
    1 for every observation); ``intrinsics`` (fx, fy, cx, cy). From a map, ``keyframes`` (K,)
    are the map's keyframe indices of the problem's keyframes (the skeleton the map adjusts)."""

    intrinsics: tuple[float, float, float, float]
    labels: Array
    points: Array
    obs_keyframes: NDArray[np.int64]
    obs_points: NDArray[np.int64]
    obs_pixels: Array
    obs_sigmas: Array | None = None
    keyframes: NDArray[np.int64] | None = None


def bundle_adjust(
    problem: AdjustmentProblem,
    *,
    label_sigma: tuple[float, float] | None = None,
    start: ArrayLike | None = None,
    offset: ArrayLike | None = None,
    estimate_offset: bool = True,
    max_iterations: int = 40,
    outlier_px: float = 4.0,
    pixel_sigma: float = 1.0,
) -> Any:
    """Adjusts ``problem`` (see the module doc) and returns an :data:`Adjustment`.

    ``label_sigma`` (σ_t in m, σ_r in rad): the labels' σ; None estimates it from the data as
    a map build does (a wide first pass, then the robust scatter of the corrections times √τ).
    ``start`` (K, 4, 4) and ``offset`` (4, 4): where B and X start (default the labels and the
    identity). With σ given the adjustment is two Levenberg–Marquardt rounds of at most
    ``max_iterations``, observations beyond ``outlier_px`` dropped between them (a large
    ``outlier_px`` keeps them all). Bad input raises :class:`geoloc.InvalidInputError` naming
    the argument.
    """
    if not isinstance(problem, AdjustmentProblem):
        raise InvalidInputError(f"problem: expected an AdjustmentProblem, got {type(problem).__name__}")
    labels = _pose_stack(problem.labels, "labels")
    points = _real_array(problem.points, "points")
    if points.ndim != 2 or points.shape[1] != 3:
        raise InvalidInputError(f"points: expected shape (N, 3), got {points.shape}")
    pixels = _real_array(problem.obs_pixels, "obs_pixels")
    if pixels.ndim != 2 or pixels.shape[1] != 2:
        raise InvalidInputError(f"obs_pixels: expected shape (M, 2), got {pixels.shape}")
    m = len(pixels)
    keyframes = _index_array(problem.obs_keyframes, "obs_keyframes", m)
    point_ids = _index_array(problem.obs_points, "obs_points", m)
    pixel_sigma = _sigma(pixel_sigma, "pixel_sigma")
    sigmas = None
    if problem.obs_sigmas is not None:
        sigmas = np.ascontiguousarray(as_float64(problem.obs_sigmas, "obs_sigmas"))
        if sigmas.shape != (m,):
            raise InvalidInputError(f"obs_sigmas: expected shape ({m},) like obs_pixels, got {sigmas.shape}")
        low, high = _core.ADJUSTMENT_SIGMA_RANGE
        scaled = sigmas * pixel_sigma  # pixel_sigma > 0: within the range only when σ > 0
        bad = ~((scaled >= low) & (scaled <= high))
        if bad.any():
            i = int(np.argmax(bad))
            raise InvalidInputError(
                f"obs_sigmas: entry {i} is {sigmas[i]}: times pixel_sigma it must lie in [{low:g}, {high:g}] px")
    intrinsics = as_float64(problem.intrinsics, "intrinsics")
    if intrinsics.shape != (4,):
        raise InvalidInputError(f"intrinsics: expected (fx, fy, cx, cy), got shape {intrinsics.shape}")
    sigma = None
    if label_sigma is not None:
        pair = as_float64(label_sigma, "label_sigma")
        if pair.shape != (2,):
            raise InvalidInputError(f"label_sigma: expected (translation m, rotation rad), got shape {pair.shape}")
        sigma = (float(pair[0]), float(pair[1]))
    if isinstance(max_iterations, bool) or not isinstance(max_iterations, (int, np.integer)) or max_iterations < 1:
        raise InvalidInputError(f"max_iterations: expected an integer ≥ 1, got {max_iterations!r:.40}")
    start_flat = None if start is None else _pose_stack(start, "start")
    offset_arr = None if offset is None else np.ascontiguousarray(_matrix_stack(offset, "offset", (4, 4)))
    return _core.bundle_adjust(
        (float(intrinsics[0]), float(intrinsics[1]), float(intrinsics[2]), float(intrinsics[3])),
        labels,
        points,
        keyframes,
        point_ids,
        pixels,
        obs_sigmas=sigmas,
        start=start_flat,
        offset=offset_arr,
        label_sigma=sigma,
        estimate_offset=bool(estimate_offset),
        max_iterations=min(int(max_iterations), _ITERATIONS_CAP),
        outlier_px=real_scalar(outlier_px, "outlier_px"),
        pixel_sigma=pixel_sigma,
    )


def _sigma(value: Any, name: str) -> float:
    """A σ the adjustment can whiten by: a real number within the core's
    ``ADJUSTMENT_SIGMA_RANGE`` (the core names its own option otherwise)."""
    v = real_scalar(value, name)
    low, high = _core.ADJUSTMENT_SIGMA_RANGE
    if not low <= v <= high:
        raise InvalidInputError(f"{name}: must lie in [{low:g}, {high:g}], got {v}")
    return v
