"""The single-image geometric locator: forward intersection (triangulation), backward
intersection (PnP) and the keyframe helpers, with calibrated uncertainty.

Conventions: poses are **world_from_cam** 4×4 float64; pixels are *undistorted*;
covariances of poses are 6×6 in the **right**-perturbation tangent space ``T @ exp(δ^)``,
translation first; point covariances are 3×3 in world coordinates (m²).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import _core
from ._validation import as_batch, as_float64, broadcast_batches, choice, real_scalar
from .camera import Camera
from .exceptions import InvalidInputError

__all__ = [
    "PnPResult",
    "PointUncertainty",
    "TRACK_STATUS",
    "TriangulationResult",
    "keyframe_score",
    "select_keyframes",
    "solve_pnp",
    "triangulate",
]

Array = NDArray[np.float64]

#: Meaning of :attr:`TriangulationResult.status` codes (the texts come from geoloc-core).
TRACK_STATUS: dict[int, str] = {code: reason for code, _name, reason in _core.track_statuses()}

#: The result of :func:`solve_pnp` (a compiled class): ``success``, ``reason``, ``pose`` (4, 4)
#: world_from_cam (identity when nothing was found), ``covariance`` (6, 6) right-perturbation
#: covariance, translation first (zeros on failure), ``inliers`` (N,) bool, ``rms`` (px),
#: ``sigma_p`` (m) and ``sigma_r`` (rad) — the paper's isometric σ — ``ransac_iterations``,
#: ``lm_iterations``, ``lm_converged`` and ``lm_termination``.
PnPResult = _core.PnPResult


@dataclass(frozen=True)
class PointUncertainty:
    """What a PnP needs to know about the errors of its 3D points.

    ``covariances`` (N, 3, 3): the part of each point's covariance independent between
    points (pixel noise of the keyframes). ``pose_jacobians`` (N, K, 3, 6) and
    ``pose_covariances`` (K, 6, 6), optional: keyframe-pose errors, shared by all points
    (D_jk = ∂X_j/∂δ_k for the right perturbation of keyframe k's world_from_cam).
    """

    covariances: Array
    pose_jacobians: Array | None = None
    pose_covariances: Array | None = None


@dataclass(frozen=True)
class TriangulationResult:
    """Per track: the point, whether it is valid and why, and its uncertainty.

    One row per distinct track id, in increasing order of id (``track_ids``): for tracks
    numbered 0..P−1 (all present) row i is track i. Ids are labels — ``10**9`` costs no
    memory."""

    track_ids: NDArray[np.int64]
    """(P,) the distinct track ids, increasing; row i is track ``track_ids[i]``."""
    points: Array
    """(P, 3) world coordinates (meaningful where ``valid``)."""
    status: NDArray[np.uint8]
    """(P,) 0 = ok, else a code of :data:`TRACK_STATUS`."""
    mean_residual: Array
    """(P,) mean reprojection residual of the inlier observations (px)."""
    max_angle: Array
    """(P,) largest angle between two inlier rays (rad)."""
    covariances: Array
    """(P, 3, 3) marginal covariance of each point: pixel noise plus keyframe-pose noise."""
    pixel_covariances: Array
    """(P, 3, 3) the part due to pixel noise only (independent between points)."""
    pose_jacobians: Array | None
    """(P, C, 3, 6) D = ∂X/∂δ for each pose (zeros where the pose does not see the point);
    computed only when ``pose_covariances`` were given, else None."""
    observation_inliers: NDArray[np.bool_]
    """(O,) per input observation: used by its (valid) track."""
    pose_covariances: Array | None
    """(C, 6, 6) the keyframe-pose covariances that were given, if any."""

    @property
    def valid(self) -> NDArray[np.bool_]:
        """(P,) the tracks that gave a point."""
        return np.asarray(self.status == 0)

    def reasons(self) -> list[str]:
        """A human-readable status per track (geoloc-core's texts)."""
        return [TRACK_STATUS[int(s)] for s in self.status]

    def rows(self, track_ids: ArrayLike) -> NDArray[np.int64]:
        """The rows of the tracks ``track_ids`` (each must be one of :attr:`track_ids`)."""
        ids = np.asarray(track_ids, dtype=np.int64)
        rows = np.searchsorted(self.track_ids, ids)
        if np.any(rows >= len(self.track_ids)) or np.any(self.track_ids[np.minimum(rows, len(self.track_ids) - 1)] != ids):
            raise InvalidInputError("track_ids: not all of them are tracks of this triangulation")
        return rows.astype(np.int64)

    def uncertainty(self, indices: ArrayLike | None = None) -> PointUncertainty:
        """The :class:`PointUncertainty` of the points ``indices`` (default: all), for
        :func:`solve_pnp`."""
        idx = slice(None) if indices is None else np.asarray(indices)
        if self.pose_covariances is None or self.pose_jacobians is None:
            return PointUncertainty(self.pixel_covariances[idx])
        return PointUncertainty(
            self.pixel_covariances[idx], self.pose_jacobians[idx], self.pose_covariances
        )


def _real_array(x: ArrayLike, name: str) -> Array:
    """``x`` as a C-contiguous float64 array of real numbers (no finiteness check)."""
    arr = np.asarray(x)
    if arr.dtype.kind not in "iuf":
        raise InvalidInputError(f"{name}: expected real numbers (float64), got an array of dtype {arr.dtype}")
    return np.ascontiguousarray(arr, dtype=np.float64)


_LOSSES = ("huber", "cauchy", "none")


def _flag(value: Any, name: str) -> bool | None:
    """None, or a bool (numpy bools too); anything else is an InvalidInputError naming ``name``."""
    if value is None or isinstance(value, (bool, np.bool_)):
        return None if value is None else bool(value)
    raise InvalidInputError(f"{name}: expected True, False or None, got {value!r:.40}")


def _index_array(x: ArrayLike, name: str, n: int) -> NDArray[np.int64]:
    arr = np.asarray(x)
    if arr.dtype.kind not in "iu" and not (arr.dtype.kind == "f" and arr.size == 0):
        raise InvalidInputError(f"{name}: expected integer indices, got dtype {arr.dtype}")
    if arr.dtype.kind == "u" and arr.size and arr.max() > np.iinfo(np.int64).max:
        raise InvalidInputError(f"{name}: ids above {np.iinfo(np.int64).max} are not supported")
    arr = arr.astype(np.int64, copy=False)
    if arr.shape != (n,):
        raise InvalidInputError(f"{name}: expected shape ({n},) like pixels, got {arr.shape}")
    return np.ascontiguousarray(arr)


def _pose_stack(poses: ArrayLike, name: str) -> Array:
    flat, lead = as_batch(poses, name, (4, 4))
    if len(lead) != 1:
        raise InvalidInputError(f"{name}: expected shape (C, 4, 4), got {np.shape(poses)}")
    return flat


def _matrix_stack(m: ArrayLike, name: str, shape: tuple[int, ...]) -> Array:
    """``m`` of shape ``shape`` as C-contiguous rows (value checks are geoloc-core's)."""
    arr = _real_array(m, name)
    if arr.shape != shape:
        raise InvalidInputError(f"{name}: expected shape {shape}, got {arr.shape}")
    return np.ascontiguousarray(arr.reshape(shape[0], int(np.prod(shape[1:]))))  # -1 fails for 0 rows


def triangulate(
    poses: ArrayLike,
    cam: Camera,
    cam_ids: ArrayLike,
    track_ids: ArrayLike,
    pixels: ArrayLike,
    *,
    huber: float = 1.0,
    loss: Literal["huber", "cauchy", "none"] = "huber",
    max_residual: float = 5.0,
    pixel_sigma: float = 1.0,
    min_angle: float = np.radians(1.0),
    pose_covariances: ArrayLike | None = None,
) -> TriangulationResult:
    """Forward intersection: triangulate tracks seen by cameras of known pose.

    Observation ``o`` says: track ``track_ids[o]`` is seen by camera ``cam_ids[o]`` (an index
    into ``poses``, world_from_cam (C, 4, 4)) at undistorted pixel ``pixels[o]``. Tracks are
    numbered 0..max(track_ids). Per track: N-view DLT, LM with a robust kernel (``loss``,
    width ``huber`` in units of ``pixel_sigma``), outlier views beyond ``max_residual`` px
    dropped (the paper's ε_r; widened to 4.29σ for large σ), and rejection by residual,
    cheirality and ``min_angle`` (rad). Runs in parallel without the GIL.

    ``pose_covariances`` (C, 6, 6): covariances of the poses (right perturbation,
    translation first); when given, they weight the views and are propagated into each
    point's covariance and into the shared sensitivities used by :func:`solve_pnp`.
    """
    if not isinstance(cam, Camera):
        raise InvalidInputError(f"cam: expected a geoloc.Camera, got {type(cam).__name__}")
    poses_flat = _pose_stack(poses, "poses")
    px = as_float64(pixels, "pixels")
    if px.ndim != 2 or px.shape[1] != 2:
        raise InvalidInputError(f"pixels: expected shape (O, 2), got {px.shape}")
    n_obs, n_cams = px.shape[0], poses_flat.shape[0]
    covs = None if pose_covariances is None else _matrix_stack(pose_covariances, "pose_covariances", (n_cams, 6, 6))
    raw = _core.triangulate(
        poses_flat, cam.intrinsics, _index_array(cam_ids, "cam_ids", n_obs), _index_array(track_ids, "track_ids", n_obs),
        np.ascontiguousarray(px), pose_covariances=covs, loss=choice(loss, "loss", _LOSSES),
        huber=real_scalar(huber, "huber"), pixel_sigma=real_scalar(pixel_sigma, "pixel_sigma"),
        max_residual=real_scalar(max_residual, "max_residual"), min_angle=real_scalar(min_angle, "min_angle"),
    )
    jacobians = raw.pose_jacobians
    p = len(raw.track_ids)
    return TriangulationResult(
        track_ids=raw.track_ids.astype(np.int64),
        points=raw.points,
        status=raw.status,
        mean_residual=raw.mean_residual,
        max_angle=raw.max_angle,
        covariances=raw.covariances,
        pixel_covariances=raw.pixel_covariances,
        pose_jacobians=None if jacobians is None else jacobians.reshape(p, n_cams, 3, 6),
        observation_inliers=raw.observation_inliers,
        pose_covariances=None if covs is None else covs.reshape(n_cams, 6, 6),
    )


def solve_pnp(
    points3d: ArrayLike,
    pixels: ArrayLike,
    cam: Camera,
    init_pose: ArrayLike | None = None,
    ransac: bool | None = None,
    huber: float = 1.0,
    max_residual: float = 5.0,
    *,
    loss: Literal["huber", "cauchy", "none"] = "huber",
    pixel_sigma: float = 1.0,
    covariance: Literal["propagated", "paper"] = "propagated",
    uncertainty: PointUncertainty | None = None,
    point_covariances: ArrayLike | None = None,
    pixel_sigmas: ArrayLike | None = None,
    min_iterations: int = 100,
    max_iterations: int = 10_000,
    confidence: float = 0.9999,
    seed: int = 0,
) -> PnPResult:
    """Backward intersection: the world_from_cam pose of a camera seeing ``points3d`` (N, 3)
    at undistorted ``pixels`` (N, 2), with a 6×6 covariance.

    The start: ``init_pose`` (4, 4) if given, else P3P RANSAC (MSAC scoring, adaptive
    iterations to ``confidence``, between ``min_iterations`` and ``max_iterations`` ≤ 10⁶,
    local optimization, seeded by ``seed``). ``ransac``: None (default) runs RANSAC exactly
    when there is no ``init_pose``; True with an ``init_pose`` runs RANSAC too and starts from
    whichever of the two has the lower MSAC score; False requires ``init_pose``. Then LM on
    SE(3) with a robust kernel (Huber of width ``huber`` σ by default), dropping
    correspondences beyond ``max_residual`` px (the paper's η_r) and re-solving.
    ``covariance="propagated"`` (default) propagates the query's ``pixel_sigma`` and the
    points' uncertainty (``uncertainty`` from :meth:`TriangulationResult.uncertainty`, or
    independent ``point_covariances`` (N, 3, 3), symmetric positive semi-definite);
    ``"paper"`` is the paper's σ̂²(ΣJᵀJ)⁻¹ with σ̂² = ‖r‖²/(2p − 1), for comparison.
    ``pixel_sigmas`` (N,), finite and > 0: a pixel noise per correspondence,
    σⱼ = ``pixel_sigma`` × ``pixel_sigmas[j]`` (e.g. a keypoint's σ from its detector scale,
    :attr:`geoloc.features.Features.pixel_sigmas`), in the weights, the η_r gate (widened to
    4.29σⱼ), the covariance and the variance factor.

    Geometry that cannot give a pose returns ``success=False`` with a ``reason``: too few
    points, no consensus, collinear points, or an inlier set that chance explains (fewer than
    9 inliers, or as many as random pixels would give — see geoloc-core ``pnp``). Invalid
    arguments raise :class:`geoloc.InvalidInputError` naming the argument.
    """
    if not isinstance(cam, Camera):
        raise InvalidInputError(f"cam: expected a geoloc.Camera, got {type(cam).__name__}")
    pts = _real_array(points3d, "points3d")
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InvalidInputError(f"points3d: expected shape (N, 3), got {pts.shape}")
    n = pts.shape[0]
    px = _real_array(pixels, "pixels")
    if px.shape != (n, 2):
        raise InvalidInputError(f"pixels: expected shape ({n}, 2) like points3d, got {px.shape}")
    init = None if init_pose is None else _real_array(init_pose, "init_pose")
    if init is not None and init.ndim != 2:
        raise InvalidInputError(f"init_pose: expected shape (4, 4), got {init.shape}")
    if uncertainty is not None and point_covariances is not None:
        raise InvalidInputError("point_covariances: give either uncertainty or point_covariances, not both")
    if point_covariances is not None:
        uncertainty = PointUncertainty(np.asarray(point_covariances))
    covs = jacs = pose_covs = None
    if uncertainty is not None:
        covs = _matrix_stack(uncertainty.covariances, "point_covariances", (n, 3, 3))
        if uncertainty.pose_jacobians is not None and uncertainty.pose_covariances is not None:
            k = np.shape(uncertainty.pose_covariances)[0]
            pose_covs = _matrix_stack(uncertainty.pose_covariances, "pose_covariances", (k, 6, 6))
            jacs = _matrix_stack(uncertainty.pose_jacobians, "pose_jacobians", (n, k, 3, 6)).reshape(n * k, 18)
        elif (uncertainty.pose_jacobians is None) != (uncertainty.pose_covariances is None):
            raise InvalidInputError("uncertainty: pose_jacobians and pose_covariances go together")
    sig = None
    if pixel_sigmas is not None:
        sig = np.ascontiguousarray(_real_array(pixel_sigmas, "pixel_sigmas"))
        if sig.shape != (n,):
            raise InvalidInputError(f"pixel_sigmas: expected shape ({n},) like points3d, got {sig.shape}")
    return _core.solve_pnp(
        pts, px, cam.intrinsics, init_pose=init, point_covariances=covs, point_pose_jacobians=jacs,
        pose_covariances=pose_covs, pixel_sigmas=sig, loss=choice(loss, "loss", _LOSSES), huber=real_scalar(huber, "huber"),
        pixel_sigma=real_scalar(pixel_sigma, "pixel_sigma"), max_residual=real_scalar(max_residual, "max_residual"),
        covariance=choice(covariance, "covariance", ("propagated", "paper")), ransac=_flag(ransac, "ransac"),
        min_iterations=min_iterations, max_iterations=max_iterations,
        confidence=real_scalar(confidence, "confidence"), seed=seed,
    )


def keyframe_score(
    T1: ArrayLike, T2: ArrayLike, d_m: float = 0.1, ell: float = 0.2, alpha_m: float = np.radians(3.0)
) -> Array:
    """s(T1, T2) = exp(−(‖p1 − p2‖ − d_m)²/ℓ²) · min(α_m/Θ(R1ᵀR2), 1) for world_from_cam poses
    (Θ = 0 scores 1); batch axes broadcast. Returns a float array of the batch shape."""
    a, lead_a = as_batch(T1, "T1", (4, 4))
    b, lead_b = as_batch(T2, "T2", (4, 4))
    (a, b), lead = broadcast_batches([(a, lead_a, "T1"), (b, lead_b, "T2")])
    out = _core.keyframe_score(
        a, b, d_m=real_scalar(d_m, "d_m"), ell=real_scalar(ell, "ell"), alpha_m=real_scalar(alpha_m, "alpha_m")
    )
    return np.asarray(out).reshape(lead)


def select_keyframes(
    poses: ArrayLike,
    k: int,
    n: int = 7,
    window: int = 100,
    d_m: float = 0.1,
    ell: float = 0.2,
    alpha_m: float = np.radians(3.0),
    min_score: float = 1e-3,
) -> NDArray[np.int64]:
    """The co-visible keyframe group around frame ``k`` (sorted indices into ``poses``).

    Alternately backward in [k_b − window, k_b) and forward in (k_f, k_f + window], the pose
    scoring best (:func:`keyframe_score`) against the current end of the group joins it and
    becomes the new end, until there are ``n`` members or no candidate scores ``min_score``;
    near the ends of a sequence the group is smaller or one-sided.
    """
    flat = _pose_stack(poses, "poses")
    reals = {name: real_scalar(v, name) for name, v in (("d_m", d_m), ("ell", ell), ("alpha_m", alpha_m), ("min_score", min_score))}
    out = _core.select_keyframes(flat, k, n=n, window=window, **reals)
    return np.asarray(out, dtype=np.int64)
