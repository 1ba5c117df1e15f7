"""Per-frame features for the robot binary ``geoloc-rs``: :func:`export_frames`.

A robot without Python localizes with ``geoloc-rs localize --map MAP --input FRAMES``. This
module writes FRAMES: for each image, what :meth:`geoloc.Localizer.localize` computes before
it calls the core — the keypoints (undistorted pixels) with their positional σ and local
descriptors from ``map.features`` with the map's camera, and the global descriptor when the
map retrieves by a network — as the versioned, length-prefixed, checksummed binary stream of
``geoloc_core::frames`` (or its JSON-lines variant, for debugging). The stream is written by
the same Rust code ``geoloc-rs`` reads it with (:class:`geoloc._core.FrameWriter`), to a temp
file renamed onto ``path`` at the end, so an interrupted export leaves no half-written file.

Fed the same frames, ``geoloc-rs localize`` and :class:`geoloc.Localizer` give bit-identical
poses and covariances (tests/test_robot.py checks it).
"""

from __future__ import annotations

import math
import os
from typing import Any, Callable, Iterable, Literal

import numpy as np
from numpy.typing import NDArray

from ._core import FrameWriter
from ._validation import check_progress, real_scalar
from .exceptions import InvalidInputError
from .localizer import check_map_camera, check_map_network, query_gray
from .mapping import GlobalDescriptor, Map

__all__ = ["export_frames"]


def _frames(frames: Any, map: Map, target: Any) -> Iterable[tuple[float, Any]]:
    """(timestamp, image) pairs: a Sequence's grey frames (``Sequence.gray``, as the CLI's
    localize uses; its camera must be the map's), or the caller's own pairs, each checked —
    a pair, a finite real timestamp, increasing as the localizer needs them, an image path
    that is not the output ``target`` — before it is written, naming ``frames`` and the
    position."""
    from .datasets import Sequence

    if isinstance(frames, Sequence):
        check_map_camera(frames.camera, map, "frames")
        stamps = np.asarray(frames.timestamps, dtype=np.float64)
        backwards = np.flatnonzero(np.diff(stamps) <= 0)
        if len(backwards):
            i = int(backwards[0]) + 1
            raise InvalidInputError(
                f"frames: timestamps[{i}] = {float(stamps[i])!r} does not increase (the frame before is at {float(stamps[i - 1])!r}); "
                "geoloc-rs localizes frames in time order"
            )
        return ((float(stamps[i]), frames.gray(i)) for i in range(len(frames)))
    if isinstance(frames, (str, bytes, os.PathLike)) or not isinstance(frames, Iterable):
        raise InvalidInputError(
            f"frames: expected a geoloc.datasets.Sequence or an iterable of (timestamp, image), got {type(frames).__name__}"
        )
    return _checked_pairs(frames, target)


def _checked_pairs(frames: Iterable[Any], target: Any) -> Iterable[tuple[float, Any]]:
    from ._io import refuse_alias

    last = -math.inf
    for i, pair in enumerate(frames):
        if not (isinstance(pair, tuple) and len(pair) == 2):
            raise InvalidInputError(f"frames[{i}]: expected a (timestamp, image) pair, got {type(pair).__name__}")
        t = real_scalar(pair[0], f"frames[{i}] timestamp")
        if not math.isfinite(t):
            raise InvalidInputError(f"frames[{i}] timestamp: {t} is not finite")
        if t <= last:
            raise InvalidInputError(f"frames[{i}] timestamp: {t!r} does not increase (the frame before is at {last!r})")
        last = t
        if isinstance(pair[1], (str, os.PathLike)):
            # the output replaces its target only at the end, after this image was read
            refuse_alias(target, "path", [(f"frames[{i}] image", pair[1])])
        yield t, pair[1]


def export_frames(
    map: Map,
    frames: Any,
    path: str | os.PathLike[str],
    *,
    format: Literal["binary", "jsonl"] = "binary",
    global_descriptor: GlobalDescriptor | None = None,
    progress: Callable[[int], None] | None = None,
) -> int:
    """Write the features of ``frames`` for ``geoloc-rs localize`` to ``path``; returns the
    number of frames written.

    ``frames`` is a :class:`geoloc.datasets.Sequence` or an iterable of ``(timestamp, image)``
    with images as :meth:`geoloc.Localizer.localize` takes them (a path, (H, W) grey or
    (H, W, 3) BGR uint8). ``global_descriptor`` is the map's network, needed (and checked, by
    its sha256) exactly when :class:`geoloc.Localizer` needs it. ``format`` is ``"binary"``
    (the robot's) or ``"jsonl"`` (one JSON object per line). ``progress(done)`` is called
    after each frame. The file appears at ``path`` only once complete; a ``path`` that is the
    map's own file (:meth:`geoloc.Map.load`) or one of the images is refused.
    """
    if not isinstance(map, Map):
        raise InvalidInputError(f"map: expected a geoloc.Map, got {type(map).__name__}")
    extractor = map.features
    if extractor is None:
        raise InvalidInputError("map: built from features (Map.from_features); it has no feature extractor to describe images")
    if format not in ("binary", "jsonl"):
        raise InvalidInputError(f"format: expected 'binary' or 'jsonl', got {format!r}")
    from ._io import check_output_path, refuse_alias
    from ._validation import network_rows

    target = check_output_path(path, "path")
    refuse_alias(target, "path", [("map", map._loaded_from), *(("frames", f) for f in getattr(frames, "files", ()))])
    # the network is checked against the map, and images decoded, as the Localizer does
    check_map_network(global_descriptor, map)
    check_progress(progress)
    pairs = _frames(frames, map, target)
    writer = FrameWriter(os.fspath(target), format=format)
    try:
        for done, (timestamp, image) in enumerate(pairs, start=1):
            try:
                gray = query_gray(image, extractor, map.camera)
            except InvalidInputError as e:  # which frame's image
                raise InvalidInputError(f"frames[{done - 1}] {e}") from None
            f = extractor(gray, map.camera)
            g: NDArray[np.float32] | None = None
            if global_descriptor is not None:
                g = np.ascontiguousarray(network_rows(global_descriptor, [gray], "global_descriptor")[0])
            writer.write(timestamp, f.keypoints, f.pixel_sigmas, f.descriptors, g)
            if progress is not None:
                progress(done)
        return writer.close()
    except BaseException:
        writer.abort()
        raise
