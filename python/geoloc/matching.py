"""Local-descriptor matching: Hamming (binary, e.g. ORB) or Euclidean (float, e.g. SIFT),
Lowe's ratio test, a mutual check, and an epipolar check for images of known pose."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import _core
from ._validation import as_batch, as_float64, real_scalar
from .camera import Camera
from .exceptions import InvalidInputError
from .retrieval import _local_descriptors as _descriptors

__all__ = ["epipolar_filter", "match_descriptors"]


def match_descriptors(
    descriptors_a: ArrayLike,
    descriptors_b: ArrayLike,
    ratio: float | None = 0.8,
    mutual: bool = True,
    max_distance: float | None = None,
) -> tuple[NDArray[np.int64], NDArray[np.float32]]:
    """Match every row of ``descriptors_a`` (N, W) to its nearest row of ``descriptors_b``.

    uint8 descriptors are binary (W bytes, Hamming distance in bits); float ones use the
    Euclidean distance. A match survives Lowe's ``ratio`` test (best < ratio · second best),
    the ``mutual`` check (each is the other's best) and ``max_distance``. Returns the index
    pairs (M, 2) and their distances (M,), sorted by the first index. Parallel, GIL-free.
    """
    a = _descriptors(descriptors_a, "descriptors_a")
    b = _descriptors(descriptors_b, "descriptors_b")
    ratio = None if ratio is None else real_scalar(ratio, "ratio")
    max_distance = None if max_distance is None else real_scalar(max_distance, "max_distance")
    return _core.match_descriptors(a, b, ratio=ratio, mutual=bool(mutual), max_distance=max_distance)


def epipolar_filter(
    cam: Camera,
    pose_a: ArrayLike,
    pose_b: ArrayLike,
    keypoints_a: ArrayLike,
    keypoints_b: ArrayLike,
    pairs: ArrayLike,
    max_px: float = 2.0,
) -> NDArray[np.bool_]:
    """Mask of the ``pairs`` (M, 2) whose undistorted keypoints are within ``max_px``
    (Sampson distance) of the epipolar geometry of world_from_cam poses ``pose_a``,
    ``pose_b``: F = K⁻ᵀ t^R K⁻¹ with (R, t) = T_b⁻¹T_a."""
    if not isinstance(cam, Camera):
        raise InvalidInputError(f"cam: expected a geoloc.Camera, got {type(cam).__name__}")
    pa, lead_a = as_batch(pose_a, "pose_a", (4, 4))
    pb, lead_b = as_batch(pose_b, "pose_b", (4, 4))
    if lead_a != () or lead_b != ():
        raise InvalidInputError("pose_a, pose_b: expected one (4, 4) pose each")
    ka = as_float64(keypoints_a, "keypoints_a")
    kb = as_float64(keypoints_b, "keypoints_b")
    for name, k in (("keypoints_a", ka), ("keypoints_b", kb)):
        if k.ndim != 2 or k.shape[1] != 2:
            raise InvalidInputError(f"{name}: expected shape (N, 2), got {k.shape}")
    p = np.asarray(pairs)
    if p.ndim != 2 or p.shape[1] != 2 or p.dtype.kind not in "iu":
        raise InvalidInputError(f"pairs: expected integer pairs of shape (M, 2), got {p.shape} {p.dtype}")
    return _core.epipolar_filter(
        cam.intrinsics, pa, pb, np.ascontiguousarray(ka), np.ascontiguousarray(kb),
        np.ascontiguousarray(p, dtype=np.int64), max_px=real_scalar(max_px, "max_px"),
    )
