"""The file formats and file helpers the dataset loaders share — text rows, image files, the
camera file, TUM trajectories and timestamp association — every failure naming the file.

Nothing here builds a :class:`~geoloc.datasets.Sequence`, so every module of
:mod:`geoloc.datasets` (and :mod:`geoloc.reference`) can import it without a cycle; the
loaders (:mod:`.tum`, :mod:`.sevenscenes`, :mod:`.folder`) and :mod:`.sequence` build on it.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .. import lie
from ..camera import Camera
from ..exceptions import DatasetError, InvalidInputError

__all__ = [
    "CAMERA_FILE_HEADER",
    "ImageLoader",
    "associate",
    "check_image_size",
    "data_lines",
    "data_rows",
    "decimal_number",
    "existing_folder",
    "file_loader",
    "floats",
    "load_image",
    "read_camera_file",
    "read_tum_trajectory",
    "write_camera_file",
]

CAMERA_FILE_HEADER = "# geoloc camera: fx fy cx cy width height [OpenCV distortion k1 k2 p1 p2 [k3 ...]]"


ImageLoader = Callable[[int, bool], NDArray[np.uint8]]
"""``loader(source_index, gray)``: the frame's (H, W, 3) uint8 BGR image, or with
``gray=True`` its (H, W) uint8 grey image."""


def load_image(path: str | os.PathLike[str], camera: Camera, gray: bool = False) -> NDArray[np.uint8]:
    """Read one image as (H, W, 3) uint8 BGR — or, with ``gray``, decoded directly as
    (H, W) grey (for JPEG that is libjpeg's own luma, not a conversion of decoded colour) —
    and check its size against ``camera``.

    Raises :class:`DatasetError` naming the file when it is missing, cannot be decoded or
    is not ``camera.width × camera.height``.
    """
    from .._images import read_image

    image = read_image(path, "image file", gray, DatasetError)
    check_image_size(image, camera, f"image file {os.fspath(path)!r}")
    return np.ascontiguousarray(image, dtype=np.uint8)


def check_image_size(image: NDArray[Any], camera: Camera, what: str) -> None:
    """Raise DatasetError unless ``image`` is ``camera.height × camera.width``."""
    h, w = image.shape[:2]
    if (w, h) != (camera.width, camera.height):
        raise DatasetError(f"{what}: image is {w}×{h}, the camera is {camera.width}×{camera.height}")


def file_loader(files: list[Path], camera: Camera, numbers: list[int] | None = None) -> ImageLoader:
    """A loader reading ``files[i]`` (checked against ``camera``) for source index i, or,
    with ``numbers``, the file of frame number ``numbers[i]`` for source index numbers[i]."""
    by_key = dict(zip(range(len(files)) if numbers is None else numbers, files))

    def load(key: int, gray: bool) -> NDArray[np.uint8]:
        return load_image(by_key[key], camera, gray)

    return load


def existing_folder(path: str | os.PathLike[str]) -> Path:
    """``path`` as a Path, or DatasetError when it is not a folder."""
    from .._io import as_path

    root = as_path(path, "path")
    if not root.is_dir():
        raise DatasetError(f"path: dataset folder {str(root)!r} does not exist")
    return root


def data_lines(path: Path) -> list[str]:
    """The non-comment lines of a text file, stripped (blank lines and ``#`` lines left out)."""
    from .._io import read_bytes

    data = read_bytes(path, "path", DatasetError)  # a FIFO or folder in its place is refused, never opened
    try:
        text = data.decode("utf-8", errors="strict")
    except UnicodeDecodeError as exc:
        raise DatasetError(f"file {str(path)!r} cannot be read as text ({exc})") from None
    return [line for line in (raw.strip() for raw in text.splitlines()) if line and not line.startswith("#")]


def data_rows(path: Path) -> list[list[str]]:
    """Whitespace/comma-separated fields of the non-comment lines of a text file."""
    return [line.replace(",", " ").split() for line in data_lines(path)]


# a decimal number as data files and file names write it: digits, one point, an exponent;
# not Python's float() syntax, which also takes "1_000", "nan", "inf" and non-ASCII digits
_DECIMAL = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")


def decimal_number(text: str) -> float | None:
    """The finite number ``text`` spells (``_DECIMAL``), or None when it is not one."""
    if _DECIMAL.fullmatch(text) is None:
        return None
    value = float(text)
    return value if math.isfinite(value) else None


def floats(fields: list[str], path: Path, line: int) -> list[float]:
    """The numbers of one data line (``decimal_number``); DatasetError naming the file and
    the entry when a field is not a decimal number or is not finite (nan, inf, 1e999)."""
    values = []
    for f in fields:
        value = decimal_number(f)
        if value is None:
            if _DECIMAL.fullmatch(f) or f.lstrip("+-").lower() in ("nan", "inf", "infinity"):
                raise DatasetError(f"file {str(path)!r}: entry {line} has a non-finite number")
            raise DatasetError(f"file {str(path)!r}: entry {line} is not numbers: {' '.join(fields)!r}")
        values.append(value)
    return values


def read_camera_file(path: str | os.PathLike[str]) -> Camera:
    """The camera of a ``camera.txt``: one line ``fx fy cx cy width height [dist...]``."""
    p = Path(path)
    rows = data_rows(p)
    if len(rows) != 1 or len(rows[0]) < 6:
        raise DatasetError(f"camera file {str(p)!r}: expected one line 'fx fy cx cy width height [dist...]'")
    v = floats(rows[0], p, 1)
    dist = tuple(v[6:]) or None
    try:
        return Camera(v[0], v[1], v[2], v[3], int(v[4]), int(v[5]), dist)
    except InvalidInputError as exc:
        raise DatasetError(f"camera file {str(p)!r}: {exc}") from None


def write_camera_file(path: str | os.PathLike[str], camera: Camera) -> None:
    """Write ``camera`` as the one-line ``camera.txt`` that :func:`read_camera_file` reads."""
    from .._io import write_text_atomic

    values = [*camera.intrinsics, camera.width, camera.height, *(camera.dist or ())]
    write_text_atomic(path, CAMERA_FILE_HEADER + "\n" + " ".join(repr(v) for v in values) + "\n")


def read_tum_trajectory(path: str | os.PathLike[str]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Timestamps (N,) and world_from_cam poses (N, 4, 4) of a TUM trajectory file.

    Each line is ``timestamp tx ty tz qx qy qz qw`` (quaternion x, y, z, w; normalized
    here); ``#`` comments and blank lines are skipped; commas also separate values.
    """
    p = Path(path)
    rows = data_rows(p)
    if not rows:
        raise DatasetError(f"trajectory file {str(p)!r} has no poses")
    values = np.empty((len(rows), 8))
    for k, row in enumerate(rows):
        if len(row) != 8:
            raise DatasetError(
                f"trajectory file {str(p)!r}: pose {k + 1} has {len(row)} values, expected 8 "
                "(timestamp tx ty tz qx qy qz qw)"
            )
        values[k] = floats(row, p, k + 1)
    q_xyzw = values[:, 4:8]
    norms = np.linalg.norm(q_xyzw, axis=1)
    # the unnormalized quaternion's matrix is |q|² R, so ‖MᵀM − I‖_F = √3 · | |q|⁴ − 1 |: the
    # same near-rotation bound as a rotation block read from a file
    defect = np.sqrt(3.0) * np.abs(norms**4 - 1.0)
    if not (defect <= lie.MAX_ORTHONORMALITY_ERROR).all():
        bad = int(np.flatnonzero(~(defect <= lie.MAX_ORTHONORMALITY_ERROR))[0])
        raise DatasetError(
            f"trajectory file {str(p)!r}: pose {bad + 1} has no unit quaternion (norm {norms[bad]:.6g}; "
            f"√3·| |q|⁴ − 1 | at most {lie.MAX_ORTHONORMALITY_ERROR:g})"
        )
    q_wxyz = np.concatenate([q_xyzw[:, 3:], q_xyzw[:, :3]], axis=1) / norms[:, None]
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    poses[:, :3, :3] = lie.so3_from_quaternion_wxyz(q_wxyz)
    poses[:, :3, 3] = values[:, 1:4]
    refuse_repeated_times(values[:, 0], f"trajectory file {str(p)!r}")
    return values[:, 0].copy(), poses


def refuse_repeated_times(times: NDArray[np.float64], what: str, labels: list[str] | None = None) -> None:
    """DatasetError when two of ``times`` are equal: a timestamp names one moment, and of two
    entries at one moment a lookup by time would silently take one. ``what`` names the source
    (``"trajectory file 'x'"``), ``labels`` the entries (default ``pose k``, 1-based)."""
    t = np.asarray(times, dtype=np.float64)
    order = np.argsort(t, kind="stable")
    same = np.flatnonzero(np.diff(t[order]) == 0)
    if same.size:
        first, again = int(order[same[0]]), int(order[same[0] + 1])
        name = (lambda k: labels[k]) if labels is not None else (lambda k: f"pose {k + 1}")
        raise DatasetError(f"{what}: {name(again)} has the timestamp {float(t[again])!r} of {name(first)} (timestamps must differ)")


def associate(
    query_times: NDArray[np.float64], reference_times: NDArray[np.float64], max_time_difference: float
) -> NDArray[np.int64]:
    """For each query time, the index of the nearest reference time, or -1 when the nearest
    is more than ``max_time_difference`` seconds away. Ties go to the earlier reference."""
    ref = np.asarray(reference_times, dtype=np.float64)
    order = np.argsort(ref, kind="stable")
    sorted_ref = ref[order]
    q = np.asarray(query_times, dtype=np.float64)
    right = np.clip(np.searchsorted(sorted_ref, q), 0, len(ref) - 1)
    left = np.clip(right - 1, 0, len(ref) - 1)
    take_left = np.abs(q - sorted_ref[left]) <= np.abs(sorted_ref[right] - q)
    nearest = np.where(take_left, left, right)
    # of equal reference times the earliest (the stable sort keeps them in index order)
    nearest = np.searchsorted(sorted_ref, sorted_ref[nearest], side="left")
    out = order[nearest].astype(np.int64)
    out[np.abs(sorted_ref[nearest] - q) > max_time_difference] = -1
    return out
