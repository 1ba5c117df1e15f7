"""Image sequences with ground truth: 7-Scenes, TUM RGB-D, plain folders and a synthetic room.

Every loader returns a :class:`Sequence` of :class:`Frame` (image (H, W, 3) uint8 **BGR**,
timestamp s, pose (4, 4) **world_from_cam** float64 or None). Bad input raises
:class:`geoloc.exceptions.DatasetError` (an InvalidInputError) naming the file or folder.
Reading images needs OpenCV (``pip install opencv-python-headless``).
"""

from __future__ import annotations

from .folder import load_folder
from .sequence import Frame, Sequence
from .sevenscenes import load_7scenes
from .synthetic import synthetic_room
from .tum import load_tum

__all__ = ["Frame", "Sequence", "load_7scenes", "load_folder", "load_tum", "synthetic_room"]
