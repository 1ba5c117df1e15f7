"""The per-frame localizer at the level of features (keypoints + descriptors).

:class:`FeatureMap` holds keyframes with known world_from_cam poses, their undistorted
keypoints and local descriptors (uint8 rows: binary/ORB; float rows: SIFT), optional global
descriptors and pose-label covariances, and builds the retrieval structure (bag of words by
default — no network needed — or the global descriptors). :class:`FeatureLocalizer` runs the
paper's pipeline frame after frame (retrieval → keyframe group → triangulation, cached →
PnP with calibrated covariance → constant-velocity motion → gated fusion) and keeps the
motion history. Image-level mapping (feature extraction, datasets) builds on these.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import _core
from ._validation import as_batch, as_float64
from .camera import Camera
from .exceptions import InvalidInputError

__all__ = ["FeatureLocalizer", "FeatureMap", "LocalizationResult"]

Array = NDArray[np.float64]


def _descriptors(x: ArrayLike, name: str) -> NDArray[Any]:
    arr = np.asarray(x)
    if arr.ndim != 2:
        raise InvalidInputError(f"{name}: expected shape (N, W), got {arr.shape}")
    if arr.dtype == np.uint8:
        return np.ascontiguousarray(arr)
    return np.ascontiguousarray(as_float64(arr, name), dtype=np.float32)


def _keypoints(x: ArrayLike, name: str, n: int | None = None) -> Array:
    k = as_float64(x, name)
    if k.ndim != 2 or k.shape[1] != 2 or (n is not None and k.shape[0] != n):
        want = f"({n}, 2)" if n is not None else "(N, 2)"
        raise InvalidInputError(f"{name}: expected shape {want}, got {k.shape}")
    return np.ascontiguousarray(k)


class FeatureMap:
    """Keyframes (poses + features) and their retrieval structure; see the module doc."""

    def __init__(
        self,
        camera: Camera,
        poses: ArrayLike,
        keypoints: Sequence[ArrayLike],
        descriptors: Sequence[ArrayLike],
        global_descriptors: ArrayLike | None = None,
        pose_covariances: ArrayLike | None = None,
        retrieval: Literal["bow", "global"] = "bow",
        branching: int = 10,
        depth: int = 3,
        seed: int = 0,
    ) -> None:
        if not isinstance(camera, Camera):
            raise InvalidInputError(f"camera: expected a geoloc.Camera, got {type(camera).__name__}")
        flat, lead = as_batch(poses, "poses", (4, 4))
        if len(lead) != 1:
            raise InvalidInputError(f"poses: expected shape (K, 4, 4), got {np.shape(poses)}")
        n = flat.shape[0]
        if len(keypoints) != n or len(descriptors) != n:
            raise InvalidInputError(f"keypoints, descriptors: expected one array per pose ({n})")
        descs = [_descriptors(d, f"descriptors[{i}]") for i, d in enumerate(descriptors)]
        kps = [_keypoints(k, f"keypoints[{i}]", len(descs[i])) for i, k in enumerate(keypoints)]
        g = None
        if global_descriptors is not None:
            g = np.ascontiguousarray(as_float64(global_descriptors, "global_descriptors"), dtype=np.float32)
            if g.ndim != 2 or g.shape[0] != n:
                raise InvalidInputError(f"global_descriptors: expected shape ({n}, D), got {g.shape}")
        covs = None
        if pose_covariances is not None:
            c = as_float64(pose_covariances, "pose_covariances")
            if c.shape != (n, 6, 6):
                raise InvalidInputError(f"pose_covariances: expected shape ({n}, 6, 6), got {c.shape}")
            covs = np.ascontiguousarray(c.reshape(n, 36))
        if retrieval not in ("bow", "global"):
            raise InvalidInputError(f"retrieval: expected 'bow' or 'global', got {retrieval!r}")
        self.camera = camera
        self._map = _core.FeatureMap(camera.intrinsics, flat, kps, descs, g, covs, retrieval, int(branching), int(depth), int(seed))

    def __len__(self) -> int:
        return len(self._map)


@dataclass(frozen=True)
class LocalizationResult:
    """One frame: pose (4, 4) world_from_cam and covariance (6, 6, right perturbation,
    translation first), or None when lost; ``source`` is "geometric", "fused", "motion" or
    "lost"; ``reason`` says why; per-stage ``timings_ms``."""

    pose: Array | None
    covariance: Array | None
    source: str
    reason: str
    keyframe: int
    inliers: int
    timings_ms: dict[str, float] = field(default_factory=dict)


class FeatureLocalizer:
    """Localizes frames (given as features) against a :class:`FeatureMap`, frame after frame."""

    def __init__(
        self, map: FeatureMap, pixel_sigma: float = 1.0, max_residual: float = 5.0, gate_sigma: float = 3.0, history: int = 4
    ) -> None:
        if not isinstance(map, FeatureMap):
            raise InvalidInputError(f"map: expected a geoloc.localizer.FeatureMap, got {type(map).__name__}")
        for name, v in (("pixel_sigma", pixel_sigma), ("max_residual", max_residual), ("gate_sigma", gate_sigma)):
            if not np.isfinite(v) or v <= 0:
                raise InvalidInputError(f"{name}: expected a finite number > 0, got {v!r}")
        if not isinstance(history, int) or history < 2:
            raise InvalidInputError(f"history: expected an integer ≥ 2, got {history!r}")
        self._loc = _core.FeatureLocalizer(map._map, float(pixel_sigma), float(max_residual), float(gate_sigma), history)

    def localize(
        self, timestamp: float, keypoints: ArrayLike, descriptors: ArrayLike, global_descriptor: ArrayLike | None = None
    ) -> LocalizationResult:
        """Localize one frame taken at ``timestamp`` (seconds, increasing)."""
        d = _descriptors(descriptors, "descriptors")
        k = _keypoints(keypoints, "keypoints", len(d))
        g = None if global_descriptor is None else np.ascontiguousarray(as_float64(global_descriptor, "global_descriptor").ravel(), dtype=np.float32)
        raw: dict[str, Any] = self._loc.localize(float(timestamp), k, d, g)
        return LocalizationResult(
            pose=None if raw["pose"] is None else raw["pose"].reshape(4, 4),
            covariance=None if raw["covariance"] is None else raw["covariance"].reshape(6, 6),
            source=str(raw["source"]),
            reason=str(raw["reason"]),
            keyframe=int(raw["keyframe"]),
            inliers=int(raw["inliers"]),
            timings_ms=dict(raw["timings_ms"]),
        )

    def reset(self) -> None:
        """Forget the motion history."""
        self._loc.reset()
