"""What training reads: any sequence of posed images (torch-free).

The protocol is tiny on purpose — ``len(frames)`` and ``frames[i]`` giving an object with
``.image`` ((H, W, 3) uint8 BGR) and ``.pose`` ((4, 4) world_from_cam) — so
``geoloc.datasets.Sequence`` satisfies it, and so does a list of :class:`PosedImage`.

:class:`SevenScenesFrames` reads a 7-Scenes folder (``frame-XXXXXX.color.{png,jpg}`` +
``frame-XXXXXX.pose.txt``) lazily, poses as written in the files (benchmarks/retrieval_networks.py
reads its frames with it); ``geoloc train`` reads its dataset with :mod:`geoloc.datasets`, as
every command does.
"""

from __future__ import annotations

import io
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol, Sequence

import numpy as np
from numpy.typing import NDArray

from .. import lie
from .._io import read_bytes
from ..exceptions import InvalidInputError

__all__ = ["PosedFrame", "PosedFrames", "PosedImage", "SevenScenesFrames", "gray_images", "poses_of"]


class PosedFrame(Protocol):
    """One training image and its pose."""

    @property
    def image(self) -> NDArray[np.uint8]: ...  # (H, W, 3) uint8 BGR

    @property
    def pose(self) -> NDArray[np.float64] | None: ...  # (4, 4) world_from_cam


class PosedFrames(Protocol):
    """A sequence of posed images (``geoloc.datasets.Sequence`` is one)."""

    def __len__(self) -> int: ...

    def __getitem__(self, index: int, /) -> Any: ...  # -> PosedFrame


@dataclass(frozen=True)
class PosedImage:
    """A plain :class:`PosedFrame`."""

    image: NDArray[np.uint8]
    pose: NDArray[np.float64]



def poses_of(frames: PosedFrames) -> NDArray[np.float64]:
    """The (N, 4, 4) world_from_cam poses of ``frames``, rotations projected onto SO(3)
    (datasets such as 7-Scenes ship slightly non-orthonormal ones); every frame needs one."""
    n = len(frames)
    out = np.empty((n, 4, 4))
    for i in range(n):
        pose = frames[i].pose
        if pose is None:
            raise InvalidInputError(f"frames[{i}].pose: training needs a pose for every frame, got None")
        p = np.asarray(pose, dtype=np.float64)
        if p.shape != (4, 4) or not np.isfinite(p).all():
            raise InvalidInputError(f"frames[{i}].pose: expected a finite (4, 4) world_from_cam matrix, got {p.shape}")
        out[i] = p
        out[i, :3, :3] = lie.so3_project_near(p[:3, :3], f"frames[{i}].pose")
    out[:, 3] = (0.0, 0.0, 0.0, 1.0)
    return out


def gray_images(frames: PosedFrames, indices: Sequence[int] | None = None) -> NDArray[np.uint8]:
    """``to_gray`` (the integer half of the network's preprocessing) of the chosen frames:
    (N, 224, 224) uint8, read one frame at a time."""
    from ..descriptor import INPUT_SIZE, to_gray

    idx = range(len(frames)) if indices is None else indices
    out = np.empty((len(idx), *INPUT_SIZE), dtype=np.uint8)
    for k, i in enumerate(idx):
        out[k] = to_gray(np.asarray(frames[int(i)].image))[0]
    return out


_FRAME = re.compile(r"^frame-(\d+)\.color\.(png|jpg)$")


class SevenScenesFrames:
    """Frames of one 7-Scenes sequence folder, images read on access (OpenCV, BGR)."""

    def __init__(self, folder: str | Path) -> None:
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise InvalidInputError(f"dataset: {str(self.folder)!r} is not a folder")
        found = sorted((int(m.group(1)), p) for p in self.folder.iterdir() if (m := _FRAME.match(p.name)))
        if not found:
            raise InvalidInputError(f"dataset: no frame-XXXXXX.color.png/jpg in {str(self.folder)!r}")
        self._images = [p for _, p in found]
        self._poses = []
        for _, p in found:
            pose_file = p.with_name(p.name.split(".")[0] + ".pose.txt")
            try:  # read by Python first: a FIFO or a folder in its place is refused, not opened
                text = read_bytes(pose_file, "dataset").decode("utf-8")
                self._poses.append(np.loadtxt(io.StringIO(text)).reshape(4, 4))
            except (OSError, ValueError) as e:
                raise InvalidInputError(f"dataset: cannot read the pose {str(pose_file)!r} ({e})") from None

    def __len__(self) -> int:
        return len(self._images)

    def __getitem__(self, i: int) -> PosedImage:
        from .._images import read_image

        if not -len(self) <= i < len(self):
            raise IndexError(i)
        return PosedImage(image=read_image(self._images[i], "dataset"), pose=self._poses[i])

    def subset(self, indices: Sequence[int]) -> list[PosedImage]:
        """The chosen frames, loaded."""
        return [self[int(i)] for i in indices]
