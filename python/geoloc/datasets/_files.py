"""File helpers shared by the dataset loaders; every failure names the file."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from ..camera import Camera
from ..exceptions import DatasetError
from .sequence import ImageLoader, load_image

__all__ = ["data_rows", "existing_folder", "file_loader", "floats"]


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


def data_rows(path: Path) -> list[list[str]]:
    """Whitespace/comma-separated fields of the non-comment lines of a text file."""
    from .._io import read_bytes

    data = read_bytes(path, "path", DatasetError)  # a FIFO or folder in its place is refused, never opened
    try:
        text = data.decode("utf-8", errors="strict")
    except UnicodeDecodeError as exc:
        raise DatasetError(f"file {str(path)!r} cannot be read as text ({exc})") from None
    rows = []
    for line in text.splitlines():
        line = line.strip()
        if line and not line.startswith("#"):
            rows.append(line.replace(",", " ").split())
    return rows


def floats(fields: list[str], path: Path, line: int) -> list[float]:
    try:
        values = [float(f) for f in fields]
    except ValueError:
        raise DatasetError(f"file {str(path)!r}: entry {line} is not numbers: {' '.join(fields)!r}") from None
    if not all(np.isfinite(values)):
        raise DatasetError(f"file {str(path)!r}: entry {line} has a non-finite number")
    return values
