"""Any folder of images with a TUM trajectory: the dataset format of last resort.

Images are all files with an image extension (png, jpg, jpeg, bmp, tif, tiff), sorted by
number when every name is a decimal number (``9.png`` before ``10.png``: the order of their
timestamps; digits, one point, an exponent — ``20230101_120000`` is not a number), else by
name. The trajectory (``traj.txt`` by default, TUM format ``timestamp tx ty tz qx qy qz
qw``) is matched to them in one of two ways (``match=``):

* ``"timestamp"``: every image name (without extension) is its timestamp in seconds
  (``1305031102.175304.png``, as TUM and :meth:`Sequence.write_tum` name them); each image
  takes the pose nearest in time (≤ ``max_time_difference``), images without one are dropped;
* ``"row"``: the k-th image (by name) has the k-th pose and its timestamp; the counts must
  be equal;
* ``"auto"`` (default): ``"timestamp"`` when every image name is a number, else ``"row"``.
  A trajectory file may also say so itself in a comment line ``# match: row`` (or
  ``# match: timestamp``), which ``"auto"`` obeys.

``trajectory=None`` (or a missing default ``traj.txt``) gives a sequence without poses,
timestamped by name when names are numbers, else by index / 30 s.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Literal

import numpy as np

from .._validation import real_scalar
from ..camera import Camera
from ..exceptions import DatasetError, InvalidInputError
from .._io import read_bytes
from ._files import decimal_number, existing_folder, file_loader, refuse_repeated_times
from .sequence import Sequence
from .tum import associate, read_tum_trajectory, resolve_camera

__all__ = ["IMAGE_EXTENSIONS", "load_folder"]

IMAGE_EXTENSIONS = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"})
DEFAULT_TRAJECTORY = "traj.txt"
FALLBACK_FRAME_RATE_HZ = 30.0


def load_folder(
    path: str | os.PathLike[str],
    trajectory: str | os.PathLike[str] | None = DEFAULT_TRAJECTORY,
    intrinsics: tuple[float, float, float, float] | Camera | None = None,
    match: Literal["auto", "timestamp", "row"] = "auto",
    max_time_difference: float = 0.02,
) -> Sequence:
    """Images of ``path`` (in number order when all names are numbers, else by name) + an optional TUM ``trajectory`` (relative to
    ``path`` unless absolute) as a :class:`Sequence`; see the module doc for ``match``.
    The camera size is the first image's; every image must have it."""
    from .._images import read_image

    root = existing_folder(path)
    if match not in ("auto", "timestamp", "row"):
        raise InvalidInputError(f"match: expected 'auto', 'timestamp' or 'row', got {match!r}")
    files = _in_order([p for p in root.iterdir() if p.suffix.lower() in IMAGE_EXTENSIONS and p.is_file()])
    if not files:
        raise DatasetError(f"path: {str(root)!r} has no images ({', '.join(sorted(IMAGE_EXTENSIONS))})")
    if intrinsics is None:
        raise DatasetError(f"intrinsics: a plain image folder has no calibration; pass intrinsics=(fx, fy, cx, cy) for {str(root)!r}")
    first = read_image(files[0], "image file", gray=True, error=DatasetError)
    camera = resolve_camera(intrinsics, root, (first.shape[1], first.shape[0]))
    name_times = _name_timestamps(files)
    if name_times is not None:
        refuse_repeated_times(name_times, f"path: the image names in {str(root)!r}", [repr(f.name) for f in files])

    if trajectory is not None and not isinstance(trajectory, (str, os.PathLike)):
        raise InvalidInputError(f"trajectory: expected a file name or None, got {type(trajectory).__name__}")
    if not math.isfinite(real_scalar(max_time_difference, "max_time_difference")) or max_time_difference < 0:
        raise InvalidInputError(f"max_time_difference: expected seconds ≥ 0, got {max_time_difference!r}")
    traj_file = None if trajectory is None else (root / trajectory)
    if traj_file is None or (not traj_file.exists() and str(trajectory) == DEFAULT_TRAJECTORY):
        times = name_times if name_times is not None else np.arange(len(files)) / FALLBACK_FRAME_RATE_HZ
        return Sequence(root.name, camera, times, None, file_loader(files, camera), files=files)
    if not traj_file.exists():
        raise DatasetError(f"trajectory: file {str(traj_file)!r} does not exist")
    traj_times, poses = read_tum_trajectory(traj_file)
    mode = match if match != "auto" else _declared_match(traj_file) or ("timestamp" if name_times is not None else "row")
    if mode == "row":
        if len(poses) != len(files):
            raise DatasetError(
                f"trajectory: {str(traj_file)!r} has {len(poses)} poses for {len(files)} images in {str(root)!r} "
                "(row-for-row matching needs equal counts)"
            )
        return Sequence(root.name, camera, traj_times, poses, file_loader(files, camera), files=[*files, traj_file])
    if name_times is None:
        raise DatasetError(f"match: timestamp matching needs image names that are timestamps in {str(root)!r}")
    pick = associate(name_times, traj_times, max_time_difference)
    keep = pick >= 0
    if not keep.any():
        raise DatasetError(f"trajectory: no image of {str(root)!r} has a pose within {max_time_difference} s in {str(traj_file)!r}")
    kept = np.flatnonzero(keep).tolist()
    return Sequence(
        root.name, camera, name_times[keep], poses[pick[keep]], file_loader([files[k] for k in kept], camera, kept), kept,
        files=[*files, traj_file],
    )


def _in_order(files: list[Path]) -> list[Path]:
    """The images in time order: by the number when every name is a number (``9.png`` before
    ``10.png``, as their timestamps say), else by name."""
    numbers = [decimal_number(p.stem) for p in files]
    if files and all(n is not None for n in numbers):
        return [p for _, p in sorted(zip(numbers, files), key=lambda pair: (pair[0], pair[1].name))]
    return sorted(files)


def _name_timestamps(files: list[Path]) -> np.ndarray | None:
    numbers = [decimal_number(f.stem) for f in files]
    if any(n is None for n in numbers):
        return None
    return np.array(numbers, dtype=np.float64)


def _declared_match(path: Path) -> Literal["timestamp", "row"] | None:
    for line in read_bytes(path, "trajectory", DatasetError).decode("utf-8", errors="replace").splitlines():
        text = line.strip().lstrip("#").strip().lower().replace(" ", "")
        if line.lstrip().startswith("#") and text in ("match:row", "match:timestamp"):
            return "row" if text.endswith("row") else "timestamp"
    return None
