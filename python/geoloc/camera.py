"""The pinhole camera."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ._validation import as_float64
from .exceptions import InvalidInputError

__all__ = ["Camera"]


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics K = (fx, fy, cx, cy) in pixels, with the image size and optional
    OpenCV distortion coefficients.

    Projection follows the paper, ``x = K T⁻¹ X`` for a world_from_cam pose T. The core
    works on *undistorted* pixels: when ``dist`` is given, :meth:`undistort_points` removes
    the distortion (needs OpenCV, ``pip install opencv-python``).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int = 640
    height: int = 480
    dist: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.floating, np.integer)) or not math.isfinite(value):
                raise InvalidInputError(f"{name}: expected a finite number, got {value!r}")
            object.__setattr__(self, name, float(value))
        for name in ("fx", "fy"):
            if getattr(self, name) <= 0:
                raise InvalidInputError(f"{name}: focal length must be > 0, got {getattr(self, name)}")
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value <= 0:
                raise InvalidInputError(f"{name}: expected a positive integer, got {value!r}")
        if self.dist is not None:
            raw = np.asarray(self.dist) if not isinstance(self.dist, (str, bytes)) else np.asarray([])
            if raw.dtype.kind not in "iuf":
                raise InvalidInputError(f"dist: expected OpenCV coefficients (real numbers), got {self.dist!r:.60}")
            dist = tuple(float(v) for v in raw.astype(np.float64).ravel())
            if len(dist) not in (4, 5, 8, 12, 14) or not all(math.isfinite(v) for v in dist):
                raise InvalidInputError(
                    f"dist: expected 4, 5, 8, 12 or 14 finite OpenCV coefficients, got {self.dist!r}"
                )
            object.__setattr__(self, "dist", dist if any(dist) else None)

    @property
    def intrinsics(self) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy)."""
        return (self.fx, self.fy, self.cx, self.cy)

    @property
    def K(self) -> NDArray[np.float64]:
        """The 3×3 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def undistort_points(self, pixels: ArrayLike) -> NDArray[np.float64]:
        """Distorted pixels (N, 2) → undistorted pixels of the same K (identity without ``dist``)."""
        pts = as_float64(pixels, "pixels")
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise InvalidInputError(f"pixels: expected shape (N, 2), got {pts.shape}")
        if self.dist is None or len(pts) == 0:
            return pts.copy()
        if np.abs(pts).max() > _MAX_PIXEL:
            raise InvalidInputError(f"pixels: |value| {np.abs(pts).max():.3g} exceeds {_MAX_PIXEL:.0e} px")
        cv2 = _import_cv2()
        # iterated to convergence: OpenCV's default stops after 5 fixed-point iterations,
        # which left corner pixels of a strongly distorted lens (k1 = −0.28) 0.57 px off
        criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, UNDISTORT_ITERATIONS, UNDISTORT_EPS)
        out = cv2.undistortPoints(pts.reshape(-1, 1, 2), self.K, np.asarray(self.dist), None, None, self.K, criteria)
        return np.asarray(out, dtype=np.float64).reshape(-1, 2)


#: Fixed-point iterations of :meth:`Camera.undistort_points` at most, and the distortion
#: residual (normalized image units) at which it stops.
UNDISTORT_ITERATIONS, UNDISTORT_EPS = 100, 1e-12

#: Largest |pixel| undistort_points accepts: OpenCV's iterative undistortion overflows to NaN
#: far below float64's range (1e302 px returned NaN), and no image is a billion pixels wide.
_MAX_PIXEL = 1e9


def _import_cv2() -> Any:
    try:
        import cv2  # type: ignore[import-not-found,unused-ignore]
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(
            "undistorting points needs OpenCV: pip install opencv-python"
        ) from exc
    return cv2
