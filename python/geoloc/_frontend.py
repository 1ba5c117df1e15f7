"""The map file's frontend header: what the Python side records about how a map was built
(features, camera size and distortion, retrieval, source frames) and reads back on load."""

from __future__ import annotations

from typing import Any

from ._io import shown
from .camera import Camera
from .exceptions import FileFormatError, InvalidInputError
from .features import FeatureExtractor

#: The frontend header's schema version inside the map file.
FRONTEND_VERSION = 1


def descriptor_record(descriptor: Any) -> dict[str, Any]:
    """What a map records of a global-descriptor network: its kind, name, sha256, input size
    and dimension (whichever it has)."""
    record: dict[str, Any] = {"kind": type(descriptor).__name__}
    for key in ("name", "sha256", "input_size", "dim"):
        value = getattr(descriptor, key, None)
        if isinstance(value, (str, int, float)) or (isinstance(value, tuple) and all(isinstance(v, int) for v in value)):
            # names from file names may hold bytes that are not UTF-8: recorded as \xNN text
            record[key] = list(value) if isinstance(value, tuple) else shown(value) if isinstance(value, str) else value
    return record


def camera_record(camera: Camera) -> dict[str, Any]:
    """The camera's image size and distortion (the file stores the intrinsics itself)."""
    return {"width": camera.width, "height": camera.height, "dist": list(camera.dist or ())}


def _record(frontend: dict[str, Any], key: str, fields: dict[str, type | tuple[type, ...]], source: str) -> dict[str, Any]:
    """``frontend[key]``, a dict holding ``fields`` of the given types; else FileFormatError
    naming the file and the field."""
    record = frontend.get(key)
    if not isinstance(record, dict):
        raise FileFormatError(f"{source}: the map's frontend header has no {key!r} record (got {type(record).__name__})")
    for name, kind in fields.items():
        value = record.get(name)
        if not isinstance(value, kind) or (isinstance(value, bool) and kind is int):
            raise FileFormatError(f"{source}: the map's frontend field {key}.{name} is missing or malformed ({value!r:.40})")
    return record


def frontend_parts(
    frontend: dict[str, Any], intrinsics: tuple[float, float, float, float], source: str
) -> tuple[FeatureExtractor | None, Camera]:
    """The feature extractor (None for a map built from features) and the camera a map
    file's frontend header records, checked field by field: a hand-made or damaged header
    is a FileFormatError naming the field after ``source`` (the file or argument it came from,
    as the message names it: ``path: 'room.geoloc'``, ``data``)."""
    cam = _record(frontend, "camera", {"width": int, "height": int, "dist": list}, source)
    retrieval = frontend.get("retrieval")
    if retrieval not in ("bow", "global", "fused") and not isinstance(retrieval, dict):
        raise FileFormatError(f"{source}: the map's frontend field retrieval is missing or malformed ({retrieval!r:.40})")
    if "features" not in frontend:
        raise FileFormatError(f"{source}: the map's frontend header has no 'features' record")
    extractor = None
    if frontend["features"] is not None:  # None: a map built from features
        f = _record(frontend, "features", {"kind": str, "n_features": int, "root_sift": bool}, source)
        try:
            extractor = FeatureExtractor(f["kind"], f["n_features"], root_sift=f["root_sift"])
        except InvalidInputError as e:
            raise FileFormatError(f"{source}: the map's frontend field features is not valid ({e})") from None
    try:
        fx, fy, cx, cy = intrinsics
        camera = Camera(fx, fy, cx, cy, width=cam["width"], height=cam["height"], dist=cam["dist"] or None)
    except (InvalidInputError, TypeError) as e:
        raise FileFormatError(f"{source}: the map's frontend field camera is not valid ({e})") from None
    return extractor, camera
