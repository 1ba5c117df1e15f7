"""geoloc: where is the camera? 6-DoF pose and a calibrated 6×6 covariance from images.

Poses are world_from_cam (camera-to-world) 4×4 float64 matrices; twists are (rho, phi),
translation first; perturbations and covariances are on the right (``T @ exp(δ^)``).
"""

from __future__ import annotations

from . import adjustment, datasets, descriptor, evaluation, features, geometry, lie, localizer, mapping, matching, plots, retrieval
from ._core import __version__
from .camera import Camera
from .descriptor import OnnxDescriptor
from .evaluation import format_tum_line
from .export import export_frames
from .exceptions import DatasetError, FileAccessError, FileFormatError, GeolocError, InvalidInputError, NotARotationError
from .fusion import FusionResult, fuse
from .localizer import Localization, Localizer
from .mapping import Map
from .motion import MotionPrediction, motion_predict

__all__ = [
    "Camera",
    "DatasetError",
    "FileAccessError",
    "FileFormatError",
    "FusionResult",
    "GeolocError",
    "InvalidInputError",
    "Localization",
    "Localizer",
    "Map",
    "MotionPrediction",
    "NotARotationError",
    "OnnxDescriptor",
    "__version__",
    "adjustment",
    "datasets",
    "descriptor",
    "evaluation",
    "export_frames",
    "features",
    "format_tum_line",
    "fuse",
    "geometry",
    "lie",
    "localizer",
    "mapping",
    "matching",
    "motion_predict",
    "plots",
    "retrieval",
]
