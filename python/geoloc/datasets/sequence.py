"""A recorded image sequence: frames with timestamps and (optionally) ground-truth poses.

Conventions: images are (H, W, 3) uint8 in **BGR** channel order (OpenCV's, as
OpenCV decodes them); timestamps are seconds; poses are 4×4 float64
**world_from_cam** (camera-to-world, camera axes x right, y down, z forward).

A :class:`Sequence` loads its images lazily, one at a time, from an *image source* (files
on disk, or a renderer for the synthetic scene), so slicing a 10 000-frame dataset costs
nothing until a frame is read.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, overload

import numpy as np
from numpy.typing import ArrayLike, NDArray

from ..camera import Camera
from ..exceptions import DatasetError, InvalidInputError
from ._files import ImageLoader, load_image

__all__ = ["Frame", "Sequence", "load_image"]

@dataclass(frozen=True, eq=False)
class Frame:
    """One frame of a :class:`Sequence`.

    ``image`` is (H, W, 3) uint8 in **BGR** order (OpenCV's); ``timestamp`` in seconds;
    ``pose`` the (4, 4) float64 world_from_cam ground truth, or None when the dataset has
    none; ``index`` the frame's index in the dataset as loaded (slicing keeps it, so
    ``seq[100:200][0].index == 100``).
    """

    image: NDArray[np.uint8]
    timestamp: float
    pose: NDArray[np.float64] | None
    index: int


class Sequence:
    """Frames of one recording: ``len(seq)``, ``seq[i] -> Frame``, ``seq[a:b] -> Sequence``.

    Also indexable by a step slice (``seq[::5]``) or an integer array / list
    (``seq[[0, 3, 7]]``, ``seq[mask]`` with a boolean mask), iterable, with
    ``seq.timestamps`` (N,) seconds, ``seq.poses`` (N, 4, 4) world_from_cam or None,
    ``seq.camera`` and ``seq.name``. Images are read only when a frame is accessed.
    """

    def __init__(
        self,
        name: str,
        camera: Camera,
        timestamps: ArrayLike,
        poses: ArrayLike | None,
        load: ImageLoader,
        source_indices: ArrayLike | None = None,
        *,
        files: Iterable[str | os.PathLike[str]] = (),
    ) -> None:
        if not isinstance(camera, Camera):
            raise InvalidInputError(f"camera: expected a geoloc.Camera, got {type(camera).__name__}")
        ts = np.array(timestamps, dtype=np.float64).reshape(-1)
        if not np.isfinite(ts).all():
            raise InvalidInputError("timestamps: expected finite seconds")
        n = len(ts)
        if n == 0:
            raise InvalidInputError(f"sequence {name!r}: no frames")
        pose_array = None
        if poses is not None:
            pose_array = np.array(poses, dtype=np.float64)
            if pose_array.shape != (n, 4, 4):
                raise InvalidInputError(f"poses: expected shape ({n}, 4, 4), got {pose_array.shape}")
            pose_array.setflags(write=False)
        idx = np.arange(n) if source_indices is None else np.array(source_indices, dtype=np.int64).reshape(-1)
        if len(idx) != n:
            raise InvalidInputError(f"source_indices: expected {n} entries, got {len(idx)}")
        ts.setflags(write=False)
        idx.setflags(write=False)
        self.name = name
        self.camera = camera
        self._timestamps = ts
        self._poses = pose_array
        self._load = load
        self._source_indices = idx
        self._files = tuple(Path(f) for f in files)

    # ------------------------------------------------------------------ properties

    @property
    def timestamps(self) -> NDArray[np.float64]:
        """(N,) seconds, read-only."""
        return self._timestamps

    @property
    def poses(self) -> NDArray[np.float64] | None:
        """(N, 4, 4) world_from_cam ground truth (read-only), or None."""
        return self._poses

    @property
    def indices(self) -> NDArray[np.int64]:
        """(N,) index of each frame in the dataset as loaded (``Frame.index``)."""
        return self._source_indices

    @property
    def files(self) -> tuple[Path, ...]:
        """The files the dataset was read from (images, pose and list files), kept whole by
        slicing; empty for a rendered sequence. A command refuses to write over any of them."""
        return self._files

    def __len__(self) -> int:
        return len(self._timestamps)

    def __repr__(self) -> str:
        gt = "with poses" if self._poses is not None else "no poses"
        return f"Sequence({self.name!r}, {len(self)} frames, {self.camera.width}×{self.camera.height}, {gt})"

    # ------------------------------------------------------------------ access

    @overload
    def __getitem__(self, key: int | np.integer[Any]) -> Frame: ...

    @overload
    def __getitem__(self, key: slice | list[int] | list[bool] | NDArray[Any]) -> Sequence: ...

    def __getitem__(self, key: Any) -> Frame | Sequence:
        n = len(self)
        if isinstance(key, (int, np.integer)) and not isinstance(key, bool):
            i = int(key)
            if not -n <= i < n:
                raise IndexError(f"frame index {i} out of range for a sequence of {n} frames")
            i %= n
            source = int(self._source_indices[i])
            return Frame(
                image=self._load(source, False),
                timestamp=float(self._timestamps[i]),
                pose=None if self._poses is None else self._poses[i].copy(),
                index=source,
            )
        if isinstance(key, slice):
            picked = np.arange(n)[key]
            what = f"slice {key.start}:{key.stop}:{key.step}".replace("None", "")
        else:
            arr = np.asarray(key)
            if arr.size == 0:
                arr = arr.astype(np.int64)
            if arr.dtype == bool:
                if arr.shape != (n,):
                    raise InvalidInputError(f"mask: expected shape ({n},), got {arr.shape}")
                picked = np.flatnonzero(arr)
            elif arr.dtype.kind in "iu" and arr.ndim == 1:
                if len(arr) and (arr.min() < -n or arr.max() >= n):
                    raise IndexError(f"frame indices out of range for a sequence of {n} frames")
                picked = arr % n if len(arr) else arr.astype(np.int64)
            else:
                raise InvalidInputError(
                    f"index: expected an int, a slice, an integer array or a boolean mask, got {type(key).__name__}"
                )
            what = "index array"
        if len(picked) == 0:
            raise InvalidInputError(f"{what} selects no frames of {self.name!r} ({n} frames)")
        return Sequence(
            self.name,
            self.camera,
            self._timestamps[picked],
            None if self._poses is None else self._poses[picked],
            self._load,
            self._source_indices[picked],
            files=self._files,
        )

    def gray(self, i: int) -> NDArray[np.uint8]:
        """Frame i's image as (H, W) uint8 grey, what feature extraction needs.

        Files are decoded directly as grey (cheaper than colour; for JPEG this is the
        encoded luma). On the 7-Scenes JPEGs this is what the core's reference figures were
        measured with; converting the BGR image instead moves ORB keypoints slightly.
        """
        n = len(self)
        if not isinstance(i, (int, np.integer)) or not -n <= int(i) < n:
            raise IndexError(f"frame index {i!r} out of range for a sequence of {n} frames")
        return self._load(int(self._source_indices[int(i) % n]), True)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    # ------------------------------------------------------------------ export

    def write_tum(self, path: str | os.PathLike[str]) -> Path:
        """Write the sequence as a TUM RGB-D folder that :func:`geoloc.datasets.load_tum` reads.

        Creates the folder ``path`` (its parent must exist) holding ``rgb/<timestamp>.png``
        (lossless), ``rgb.txt``, ``groundtruth.txt`` (when the sequence has poses; TUM
        order ``timestamp tx ty tz qx qy qz qw``) and ``camera.txt`` (see
        :func:`geoloc.datasets.tum.write_camera_file`). Timestamps are written exactly
        (shortest round-trip repr), so frames 0.1 µs apart keep their own images. A file
        the sequence was read from (:attr:`files`) is never written over: such a ``path`` is
        refused before anything is written. Returns the folder.
        """
        from .._images import write_image
        from .._io import refuse_alias, write_text_atomic
        from ..evaluation import write_tum_trajectory
        from ._files import write_camera_file

        root = Path(path)
        if not root.parent.is_dir():
            raise DatasetError(f"path: parent folder {str(root.parent)!r} does not exist")
        stamps = [repr(float(t)) for t in self._timestamps]
        if len(set(stamps)) != len(stamps):
            raise DatasetError("path: the sequence has two frames with one timestamp; their images would share one file")
        names = [f"rgb/{t}.png" for t in stamps]
        outputs = [root / n for n in names] + [root / "rgb.txt", root / "groundtruth.txt", root / "camera.txt"]
        inputs = [("sequence", f) for f in self._files]
        for out in outputs:
            refuse_alias(out, "path", inputs)
        try:
            (root / "rgb").mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise DatasetError(f"path: cannot create {str(root)!r} ({exc.strerror})") from None
        lines = ["# color images", "# written by geoloc", "# timestamp filename"]
        for frame, stamp, name in zip(self, stamps, names):
            write_image(root / name, frame.image, "path")
            lines.append(f"{stamp} {name}")
        write_text_atomic(root / "rgb.txt", "\n".join(lines) + "\n", "path")
        if self._poses is not None:
            write_tum_trajectory(root / "groundtruth.txt", self._timestamps, self._poses)
        write_camera_file(root / "camera.txt", self.camera)
        return root
