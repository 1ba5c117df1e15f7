"""Microsoft 7-Scenes (Shotton et al., CVPR 2013): colour frames with camera-to-world poses.

Two layouts are read, file by file, in the same folder:

* the **plain layout** of ``../shared/data/7scenes-redkitchen``: ``frame-XXXXXX.color.jpg``
  (or ``.png``) + ``frame-XXXXXX.pose.txt`` written by numpy (space-separated, LF);
* the **original release** (a ``seq-XX`` folder, e.g. ``7scenes-redkitchen-original-format``):
  lossless ``.color.png``, pose files tab-separated with CRLF line ends and 3-digit
  exponents (``7.0352107e-001``), and a ``camera-intrinsics.txt``.

Poses are 4×4 world_from_cam (camera x right, y down, z forward). Their rotation blocks are
slightly non-orthonormal in the release (det 0.9995–0.9999), so they are projected onto
SO(3) (:func:`geoloc.lie.so3_project`); otherwise angles come out ~1.5° wrong.
Timestamps are the frame number / 30 s (the Kinect ran at 30 Hz; the release has no times),
so frame 150 is at 5.0 s in either layout.

Intrinsics: 7-Scenes calibrates only the *depth* camera, and ``camera-intrinsics.txt`` holds
exactly that K (fx = fy = 585, cx = 320, cy = 240). The colour images are usually used with
fx = fy = 525, cx = 320, cy = 240 (the default here). ``intrinsics="file"`` takes the file's
K instead, for whoever prefers it; no distortion model is given in either case.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Literal

import numpy as np

from .. import lie
from ..camera import Camera
from ..exceptions import DatasetError, NotARotationError
from ._files import data_rows, existing_folder, file_loader, floats
from .sequence import Sequence
from .tum import resolve_camera

__all__ = ["FRAME_RATE_HZ", "load_7scenes", "read_7scenes_intrinsics", "read_7scenes_pose"]

FRAME_RATE_HZ = 30.0
IMAGE_SIZE = (640, 480)
INTRINSICS_FILE = "camera-intrinsics.txt"
_FRAME = re.compile(r"^frame-(\d+)\.color\.(png|jpg|jpeg)$", re.IGNORECASE)
_MAX_BOTTOM_ROW_ERROR = 1e-6


def _read_matrix(path: Path, n: int, what: str) -> np.ndarray:
    """The n×n matrix a text file holds (n rows of n numbers, any whitespace/line ends)."""
    values = [v for k, r in enumerate(data_rows(path)) for v in floats(r, path, k + 1)]
    if len(values) != n * n:
        raise DatasetError(f"{what} {str(path)!r}: expected {n * n} numbers (a {n}×{n} matrix), got {len(values)}")
    return np.array(values).reshape(n, n)


def read_7scenes_pose(path: str | os.PathLike[str]) -> np.ndarray:
    """One pose file (4 rows of 4 numbers, any whitespace/line ends) → (4, 4) world_from_cam,
    rotation projected onto SO(3)."""
    p = Path(path)
    pose = _read_matrix(p, 4, "pose file")
    if np.abs(pose[3] - [0, 0, 0, 1]).max() > _MAX_BOTTOM_ROW_ERROR:
        raise DatasetError(f"pose file {str(p)!r}: last row is {pose[3].tolist()}, expected [0, 0, 0, 1]")
    try:
        pose[:3, :3] = lie.so3_project_near(pose[:3, :3], "rotation block")
    except NotARotationError as e:
        raise DatasetError(f"pose file {str(p)!r}: {e}") from None
    pose[3] = [0.0, 0.0, 0.0, 1.0]
    return pose


def read_7scenes_intrinsics(path: str | os.PathLike[str]) -> Camera:
    """``camera-intrinsics.txt`` (a 3×3 K) as a 640×480 Camera without distortion."""
    K = _read_matrix(Path(path), 3, "intrinsics file")
    return Camera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], *IMAGE_SIZE)


def load_7scenes(
    path: str | os.PathLike[str],
    intrinsics: tuple[float, float, float, float] | Camera | Literal["file"] = (525.0, 525.0, 320.0, 240.0),
) -> Sequence:
    """A 7-Scenes sequence folder (either layout, see the module doc) as a :class:`Sequence`,
    frames in frame-number order, every frame with its pose."""
    root = existing_folder(path)
    frames: list[tuple[int, Path]] = []
    for entry in root.iterdir():
        m = _FRAME.match(entry.name)
        if m:
            frames.append((int(m.group(1)), entry))
    if not frames:
        raise DatasetError(f"path: {str(root)!r} has no 7-Scenes colour frames (frame-XXXXXX.color.png/jpg)")
    frames.sort()
    numbers = [n for n, _ in frames]
    if len(set(numbers)) != len(numbers):
        dup = next(n for n in numbers if numbers.count(n) > 1)
        names = " and ".join(repr(p.name) for n, p in frames if n == dup)
        raise DatasetError(f"path: {str(root)!r} has frame {dup} twice: {names}")
    if intrinsics == "file":
        camera = read_7scenes_intrinsics(root / INTRINSICS_FILE)
    else:
        camera = resolve_camera(intrinsics, root, IMAGE_SIZE)
    poses = []
    for n, _ in frames:
        pose_file = root / f"frame-{n:06d}.pose.txt"
        if not pose_file.exists():
            raise DatasetError(f"pose file {str(pose_file)!r} is missing (frame {n} has an image)")
        poses.append(read_7scenes_pose(pose_file))
    times = np.array(numbers, dtype=np.float64) / FRAME_RATE_HZ
    images = [f for _, f in frames]
    read = [*images, *(root / f"frame-{n:06d}.pose.txt" for n in numbers)]
    if intrinsics == "file":
        read.append(root / INTRINSICS_FILE)
    return Sequence(root.name, camera, times, np.stack(poses), file_loader(images, camera, numbers), numbers, files=read)
