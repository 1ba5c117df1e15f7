"""Reading and writing image files without handing OpenCV a path.

OpenCV's ``imread`` / ``imwrite`` take a ``std::string``: a file name that is not UTF-8 (a
surrogate-escaped ``str``) crashed the interpreter, and they read FIFOs and devices as they
come. Here Python reads the bytes (:func:`geoloc._io.read_bytes`: regular files only) and
``cv2.imdecode`` decodes them; writing encodes with ``cv2.imencode`` and writes the bytes
atomically (:func:`geoloc._io.write_bytes_atomic`).
"""

from __future__ import annotations

import os
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ._io import read_bytes, write_bytes_atomic
from ._opencv import import_cv2
from .exceptions import FileAccessError, InvalidInputError

__all__ = ["read_image", "write_image"]


def read_image(
    path: Any, name: str = "image", gray: bool = False, error: type[InvalidInputError] = InvalidInputError
) -> NDArray[np.uint8]:
    """The image file ``path`` as (H, W, 3) uint8 BGR, or with ``gray`` decoded directly as
    (H, W) grey; ``error`` naming ``name`` and the path when it is missing, not a regular
    file, or not an image OpenCV can decode."""
    cv2 = import_cv2("reading images")
    # a file that cannot be read is an access error unless the caller names its own (a dataset's)
    data = read_bytes(path, name, FileAccessError if error is InvalidInputError else error)
    flag = cv2.IMREAD_GRAYSCALE if gray else cv2.IMREAD_COLOR
    image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), flag) if data else None
    if image is None:
        raise error(f"{name}: {os.fspath(path)!r} cannot be read as an image (OpenCV cannot decode it)")
    return np.ascontiguousarray(image, dtype=np.uint8)


def write_image(path: Any, image: NDArray[np.uint8], name: str = "path") -> None:
    """Write ``image`` to ``path`` atomically, in the format its extension names (``.png``, ``.jpg`` …)."""
    cv2 = import_cv2("writing images")
    ext = os.path.splitext(os.fspath(path))[1]
    try:
        ok, encoded = cv2.imencode(ext or ".png", np.ascontiguousarray(image))
    except cv2.error:
        ok = False
    if not ok:
        raise InvalidInputError(f"{name}: cannot encode an image of shape {np.shape(image)} as {ext or '(no extension)'!r}")
    write_bytes_atomic(path, encoded.tobytes(), name)
