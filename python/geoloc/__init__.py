"""geoloc: where is the camera? 6-DoF pose and a calibrated 6×6 covariance from images.

Poses are world_from_cam (camera-to-world) 4×4 float64 matrices; twists are (rho, phi),
translation first; perturbations and covariances are on the right (``T @ exp(δ^)``).
"""

from __future__ import annotations

from . import descriptor, geometry, lie, localizer, matching, retrieval
from ._core import __version__
from .camera import Camera
from .descriptor import OnnxDescriptor
from .exceptions import GeolocError, InvalidInputError, NotARotationError
from .fusion import FusionResult, fuse
from .motion import MotionPrediction, motion_predict

__all__ = [
    "Camera",
    "FusionResult",
    "GeolocError",
    "InvalidInputError",
    "MotionPrediction",
    "NotARotationError",
    "OnnxDescriptor",
    "__version__",
    "descriptor",
    "fuse",
    "geometry",
    "lie",
    "localizer",
    "matching",
    "motion_predict",
    "retrieval",
]
