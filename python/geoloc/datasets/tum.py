"""The TUM RGB-D benchmark format (Sturm et al., IROS 2012), read and written.

A TUM folder holds ``rgb.txt`` (``timestamp filename`` per line) and, for recordings with
ground truth, ``groundtruth.txt`` (``timestamp tx ty tz qx qy qz qw``: the world_from_cam
translation and its rotation as a unit quaternion in **x, y, z, w** order). ``#`` starts
a comment line. Images and poses come at different rates; each image takes the pose with
the nearest timestamp, and images without one within ``max_time_difference`` are dropped
(as the benchmark's own ``associate.py`` does).

Intrinsics, in this order of precedence:
1. ``intrinsics=`` given to :func:`load_tum` — ``(fx, fy, cx, cy)``, or a :class:`Camera`
   (which may carry distortion);
2. a ``camera.txt`` in the folder, as :meth:`Sequence.write_tum` writes it
   (:func:`write_camera_file`);
3. the published Kinect calibration of the benchmark, chosen from the folder name
   (``freiburg1`` / ``freiburg2`` / ``freiburg3``, e.g. ``rgbd_dataset_freiburg1_xyz``),
   distortion included: fr1 and fr2 images are distorted; fr3 images were undistorted by
   the sensor, so their coefficients are zero.
Otherwise loading fails and asks for intrinsics.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

import numpy as np

from .._validation import real_scalar
from ..camera import Camera
from ..exceptions import DatasetError, InvalidInputError
from ._files import (  # the TUM trajectory and camera file formats: defined in ._files (no Sequence there), public here
    CAMERA_FILE_HEADER,
    associate,
    data_lines,
    existing_folder,
    file_loader,
    floats,
    read_camera_file,
    read_tum_trajectory,
    refuse_repeated_times,
    write_camera_file,
)
from .sequence import Sequence

__all__ = [
    "CAMERA_FILE_HEADER",
    "TUM_CAMERAS",
    "associate",
    "load_tum",
    "read_camera_file",
    "read_tum_trajectory",
    "resolve_camera",
    "write_camera_file",
]

TUM_IMAGE_SIZE = (640, 480)

TUM_CAMERAS: dict[str, Camera] = {
    # https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats ("Intrinsic Camera
    # Calibration of the Kinect"): fx fy cx cy, then OpenCV's k1 k2 p1 p2 k3.
    "freiburg1": Camera(517.3, 516.5, 318.6, 255.3, 640, 480, (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    "freiburg2": Camera(520.9, 521.0, 325.1, 249.7, 640, 480, (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    "freiburg3": Camera(535.4, 539.2, 320.1, 247.6, 640, 480, None),
}

Intrinsics = tuple[float, float, float, float] | Camera


def resolve_camera(intrinsics: Intrinsics | None, root: Path, size: tuple[int, int], name: str = "intrinsics") -> Camera:
    """A Camera from ``(fx, fy, cx, cy)`` (image ``size``) or a Camera given as is."""
    if isinstance(intrinsics, Camera):
        return intrinsics
    if intrinsics is None:
        raise DatasetError(f"{name}: no intrinsics for {str(root)!r}; pass intrinsics=(fx, fy, cx, cy)")
    try:
        values = [float(v) for v in intrinsics]
    except (TypeError, ValueError):
        raise InvalidInputError(f"{name}: expected (fx, fy, cx, cy) or a geoloc.Camera, got {intrinsics!r}") from None
    if len(values) != 4:
        raise InvalidInputError(f"{name}: expected 4 values (fx, fy, cx, cy), got {len(values)}")
    return Camera(values[0], values[1], values[2], values[3], size[0], size[1])


def load_tum(
    path: str | os.PathLike[str],
    intrinsics: Intrinsics | None = None,
    max_time_difference: float = 0.02,
    ground_truth: bool = True,
) -> Sequence:
    """A TUM RGB-D folder (``rgb.txt`` + optional ``groundtruth.txt``) as a :class:`Sequence`.

    Images are associated with ground-truth poses by nearest timestamp (at most
    ``max_time_difference`` s apart; others are dropped); without ``groundtruth.txt``, or
    with ``ground_truth=False`` (images to localize, which need no pose), every image is kept
    and ``seq.poses`` is None. ``Frame.index`` is the image's entry number in ``rgb.txt``
    (dropped images leave gaps). Intrinsics: see the module doc.
    """
    root = existing_folder(path)
    if not math.isfinite(real_scalar(max_time_difference, "max_time_difference")) or max_time_difference < 0:
        raise InvalidInputError(f"max_time_difference: expected seconds ≥ 0, got {max_time_difference!r}")
    rgb = root / "rgb.txt"
    # 'timestamp filename': the name is the rest of the line, spaces and commas included
    rows = [re.split(r"[\s,]+", line, maxsplit=1) for line in data_lines(rgb)]
    if not rows:
        raise DatasetError(f"{str(rgb)!r} lists no images")
    for k, row in enumerate(rows):
        if len(row) < 2:
            raise DatasetError(f"{str(rgb)!r}: entry {k + 1} has no file name (expected 'timestamp filename')")
    times = np.array([floats(r[:1], rgb, k + 1)[0] for k, r in enumerate(rows)])
    refuse_repeated_times(times, repr(str(rgb)), [f"entry {k + 1}" for k in range(len(rows))])
    back = np.flatnonzero(np.diff(times) < 0)
    if back.size:  # a sequence is in capture order: frame i + 1 after frame i
        k = int(back[0]) + 1
        raise DatasetError(
            f"{str(rgb)!r}: entry {k + 1} has the timestamp {float(times[k])!r}, before entry {k}'s "
            f"{float(times[k - 1])!r} (the entries must be in time order)"
        )
    files = [root / r[1] for r in rows]
    camera = _tum_camera(intrinsics, root)
    gt_file = root / "groundtruth.txt"
    read = [rgb, *files, *(p for p in (gt_file, root / "camera.txt") if p.exists())]
    if ground_truth and gt_file.exists():
        gt_times, gt_poses = read_tum_trajectory(gt_file)
        match = associate(times, gt_times, max_time_difference)
        keep = match >= 0
        if not keep.any():
            raise DatasetError(
                f"no image of {str(rgb)!r} has a pose in {str(gt_file)!r} within {max_time_difference} s "
                "(raise max_time_difference?)"
            )
        kept = np.flatnonzero(keep).tolist()
        return Sequence(
            root.name, camera, times[keep], gt_poses[match[keep]], file_loader([files[k] for k in kept], camera, kept), kept,
            files=read,
        )
    return Sequence(root.name, camera, times, None, file_loader(files, camera), files=read)


# ---------------------------------------------------------------------------- helpers


def _tum_camera(intrinsics: Intrinsics | None, root: Path) -> Camera:
    if intrinsics is not None:
        return resolve_camera(intrinsics, root, TUM_IMAGE_SIZE)
    if (root / "camera.txt").exists():
        return read_camera_file(root / "camera.txt")
    found = re.search(r"freiburg([123])", root.resolve().name)
    if found:
        return TUM_CAMERAS["freiburg" + found.group(1)]
    raise DatasetError(
        f"intrinsics: {str(root)!r} has no camera.txt and its name names no TUM camera "
        "(freiburg1/2/3); pass intrinsics=(fx, fy, cx, cy)"
    )
