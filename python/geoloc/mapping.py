"""Image-level mapping and localization: :class:`Map` (build, save, load) and :class:`Localizer`.

A map is built from a :class:`geoloc.datasets.Sequence` with known world_from_cam poses:
every (selected) frame becomes a keyframe with its OpenCV features (ORB by default, SIFT as
an option) and, for retrieval, either a bag-of-words vocabulary trained on those features (no
network needed; the default) or the global descriptors of a network (any callable
``images -> (N, D) float32``, e.g. :class:`geoloc.descriptor.OnnxDescriptor`). The map is the
core's map plus the settings needed to describe a query the same way; it is saved to one
``.geoloc`` file (safetensors, written atomically by geoloc-core) that Python and the robot
binary ``geoloc-rs`` both read.

:class:`Localizer` runs the per-frame pipeline on images: decode → features →
retrieval → keyframe group → triangulation → PnP with covariance → motion model → gated fusion.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Literal, Protocol

import numpy as np
from numpy.typing import NDArray

from .camera import Camera
from ._io import shown
from ._validation import real_scalar
from .exceptions import FileFormatError, InvalidInputError
from .features import FeatureExtractor, Features
from .localizer import FeatureLocalizer, FeatureMap, LocalizationResult

__all__ = ["GlobalDescriptor", "Localizer", "Map", "MapLocalization"]

#: The modes of :meth:`Localizer.localize_sequence`.
SEQUENCE_MODES = ("single", "sequential")

#: The frontend settings' schema version inside the map file.
FRONTEND_VERSION = 1


class GlobalDescriptor(Protocol):
    """What a network retrieval needs: images → (N, D) float32, and a name to record."""

    def __call__(self, images: list[NDArray[np.uint8]]) -> NDArray[np.float32]: ...


ProgressCallback = Callable[[int, int], None]


def _as_int(value: Any, name: str, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or int(value) < low:
        raise InvalidInputError(f"{name}: expected an integer ≥ {low}, got {value!r}")
    return int(value)


def _descriptor_record(descriptor: Any) -> dict[str, Any]:
    record: dict[str, Any] = {"kind": type(descriptor).__name__}
    for key in ("name", "sha256", "input_size", "dim"):
        value = getattr(descriptor, key, None)
        if isinstance(value, (str, int, float)) or (isinstance(value, tuple) and all(isinstance(v, int) for v in value)):
            # names from file names may hold bytes that are not UTF-8: recorded as \xNN text
            record[key] = list(value) if isinstance(value, tuple) else shown(value) if isinstance(value, str) else value
    return record


def _increasing(timestamps: NDArray[np.float64]) -> NDArray[np.float64] | None:
    """The keyframes' timestamps for the process-noise estimate, or None when they do not
    strictly increase (then the motion model gets no process noise from the map)."""
    return timestamps if len(timestamps) >= 3 and bool(np.all(np.diff(timestamps) > 0)) else None


class Map:
    """Keyframes with known poses, their features and the retrieval structure; see the module doc."""

    def __init__(self, feature_map: FeatureMap, extractor: FeatureExtractor, frontend: dict[str, Any]) -> None:
        self._feature_map = feature_map
        self._extractor = extractor
        self._frontend = frontend

    @classmethod
    def build(
        cls,
        sequence: Any,
        retrieval: str | GlobalDescriptor = "bow",
        features: str = "orb",
        *,
        n_features: int = 1000,
        root_sift: bool = False,
        keyframe_step: int = 1,
        branching: int = 10,
        depth: int = 3,
        seed: int = 0,
        estimate_noise: bool = True,
        model: bool = False,
        refine_intrinsics: bool = True,
        adjust_labels: bool = True,
        progress: ProgressCallback | None = None,
    ) -> Map:
        """Build a map from ``sequence`` (every ``keyframe_step``-th frame becomes a keyframe).

        ``retrieval`` is ``"bow"`` (a ``branching``^``depth``-word vocabulary trained on the
        keyframes' descriptors, seeded by ``seed``) or a global-descriptor network;
        ``features`` is ``"orb"`` or ``"sift"`` with ``n_features`` per image.
        ``progress(done, total)`` is called after each keyframe. ``estimate_noise`` (default
        True) estimates the map's own noise after building it — the map-frame covariance
        from held-out keyframes and the motion model's process noise from the frames'
        timestamps (:attr:`map_noise`); it is stored in the map file. ``model`` (default False)
        builds the map-level 3D model of ``Localizer(..., locator="model")`` and stores it too
        (a map without one builds it when such a localizer starts). ``refine_intrinsics``
        (default True) first estimates the real camera from the keyframes' own tracks — focal
        lengths, principal point and lens distortion, with the poses known — and corrects the
        keyframes' and every query's keypoints with it (:attr:`self_calibration`; it says why
        not when the recording does not determine the camera, and the sequence's camera is
        then used as it is). ``adjust_labels`` (default True) corrects the sequence's pose
        labels by bundle adjustment — keyframe poses, points and one label-to-camera offset,
        the labels as robust priors whose σ is estimated — so that the map agrees with its
        images (:attr:`labels`, :attr:`keyframe_poses`, :attr:`label_poses`); localization
        results stay in the labels' convention. The keyframe pairs are matched once for all
        of these steps.
        """
        from .datasets import Sequence

        if not isinstance(sequence, Sequence):
            raise InvalidInputError(f"sequence: expected a geoloc.datasets.Sequence, got {type(sequence).__name__}")
        if sequence.poses is None:
            raise InvalidInputError(f"sequence: {sequence.name!r} has no poses; a map needs world_from_cam poses")
        step = _as_int(keyframe_step, "keyframe_step", 1)
        if isinstance(retrieval, str) and retrieval != "bow":
            raise InvalidInputError(f"retrieval: expected 'bow' or a global-descriptor network, got {retrieval!r}")
        if not isinstance(retrieval, str) and not callable(retrieval):
            raise InvalidInputError(f"retrieval: expected 'bow' or a callable network, got {type(retrieval).__name__}")
        extractor = FeatureExtractor(features, _as_int(n_features, "n_features", 1), root_sift=bool(root_sift))  # type: ignore[arg-type]
        indices = np.arange(0, len(sequence), step)
        camera = sequence.camera
        keypoints, descriptors, images = [], [], []
        for done, i in enumerate(indices, start=1):
            gray = sequence.gray(int(i))
            f = extractor(gray, camera)
            keypoints.append(f.keypoints)
            descriptors.append(f.descriptors)
            if not isinstance(retrieval, str):
                images.append(gray)
            if progress is not None:
                progress(done, len(indices))
        global_descriptors = None if isinstance(retrieval, str) else np.asarray(retrieval(images), dtype=np.float32)
        feature_map = FeatureMap(
            camera,
            sequence.poses[indices],
            keypoints,
            descriptors,
            global_descriptors=global_descriptors,
            retrieval="bow" if isinstance(retrieval, str) else "global",
            branching=branching,
            depth=depth,
            seed=seed,
            timestamps=_increasing(sequence.timestamps[indices]),
            estimate_noise=bool(estimate_noise),
            model=bool(model),
            refine_intrinsics=bool(refine_intrinsics),
            adjust_labels=bool(adjust_labels),
        )
        frontend = {
            "version": FRONTEND_VERSION,
            "features": {"kind": extractor.kind, "n_features": extractor.n_features, "root_sift": extractor.root_sift},
            "camera": {"width": camera.width, "height": camera.height, "dist": list(camera.dist or ())},
            "retrieval": "bow" if isinstance(retrieval, str) else _descriptor_record(retrieval),
            "source": {"sequence": shown(sequence.name), "frames": [int(i) for i in indices]},
        }
        return cls(feature_map, extractor, frontend)

    @property
    def camera(self) -> Camera:
        """The camera the map was built with (queries must use the same intrinsics)."""
        return self._feature_map.camera

    @property
    def labels(self) -> dict[str, Any] | None:
        """The labels' correction report; see :attr:`geoloc.localizer.FeatureMap.labels`."""
        return self._feature_map.labels

    @property
    def keyframe_poses(self) -> NDArray[np.float64]:
        """The keyframe poses in the labels' convention (adjusted when the labels were)."""
        return self._feature_map.keyframe_poses

    @property
    def label_poses(self) -> NDArray[np.float64] | None:
        """The pose labels as given, or None when they were not adjusted."""
        return self._feature_map.label_poses

    @property
    def camera_poses(self) -> NDArray[np.float64]:
        """The keyframes' camera poses world_from_cam (the frame the localizer, the motion
        model and the map's noise work in; the labels when they were not adjusted)."""
        return self._feature_map.camera_poses

    @property
    def map_noise(self) -> dict[str, Any]:
        """The noise estimated at build time; see :attr:`geoloc.localizer.FeatureMap.map_noise`."""
        return self._feature_map.map_noise

    @property
    def self_calibration(self) -> dict[str, Any] | None:
        """The camera estimated from the keyframes; see :attr:`geoloc.localizer.FeatureMap.self_calibration`."""
        return self._feature_map.self_calibration

    @property
    def features(self) -> FeatureExtractor:
        """The feature extractor queries are described with."""
        return self._extractor

    @property
    def settings(self) -> dict[str, Any]:
        """What the map records about how it was built (features, retrieval, source frames)."""
        copy: dict[str, Any] = json.loads(json.dumps(self._frontend))
        return copy

    def __len__(self) -> int:
        return len(self._feature_map)

    def __repr__(self) -> str:
        return f"Map({len(self)} keyframes, features={self._extractor!r}, retrieval={self._frontend['retrieval']!r})"

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the map to one ``.geoloc`` file, atomically (an interrupted save keeps the old file)."""
        from ._io import check_output_path

        target = check_output_path(path, "path")
        self._feature_map.save(target, self._frontend)

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> Map:
        """Read a map written by :meth:`save`; a truncated, corrupt or other-version file is refused."""
        from ._io import as_path

        feature_map = FeatureMap.load(as_path(path, "path"))
        frontend = feature_map.frontend
        if not isinstance(frontend, dict) or frontend.get("version") != FRONTEND_VERSION:
            raise InvalidInputError(f"path: {str(path)!r} was not written by this version of geoloc's Python package")
        extractor, camera = _frontend_parts(frontend, feature_map.camera.intrinsics, str(path))
        feature_map.camera = camera
        return cls(feature_map, extractor, frontend)


def _record(frontend: dict[str, Any], key: str, fields: dict[str, type | tuple[type, ...]], path: str) -> dict[str, Any]:
    """``frontend[key]``, a dict holding ``fields`` of the given types; else FileFormatError
    naming the file and the field."""
    record = frontend.get(key)
    if not isinstance(record, dict):
        raise FileFormatError(f"path: {path!r}: the map's frontend header has no {key!r} record (got {type(record).__name__})")
    for name, kind in fields.items():
        value = record.get(name)
        if not isinstance(value, kind) or (isinstance(value, bool) and kind is int):
            raise FileFormatError(f"path: {path!r}: the map's frontend field {key}.{name} is missing or malformed ({value!r:.40})")
    return record


def _frontend_parts(
    frontend: dict[str, Any], intrinsics: tuple[float, float, float, float], path: str
) -> tuple[FeatureExtractor, Camera]:
    """The feature extractor and camera a map file's frontend header records (checked field
    by field: a hand-made or damaged header is a FileFormatError naming the field)."""
    f = _record(frontend, "features", {"kind": str, "n_features": int, "root_sift": bool}, path)
    cam = _record(frontend, "camera", {"width": int, "height": int, "dist": list}, path)
    retrieval = frontend.get("retrieval")
    if retrieval != "bow" and not isinstance(retrieval, dict):
        raise FileFormatError(f"path: {path!r}: the map's frontend field retrieval is missing or malformed ({retrieval!r:.40})")
    try:
        extractor = FeatureExtractor(f["kind"], f["n_features"], root_sift=f["root_sift"])
    except InvalidInputError as e:
        raise FileFormatError(f"path: {path!r}: the map's frontend field features is not valid ({e})") from None
    try:
        fx, fy, cx, cy = intrinsics
        camera = Camera(fx, fy, cx, cy, width=cam["width"], height=cam["height"], dist=cam["dist"] or None)
    except (InvalidInputError, TypeError) as e:
        raise FileFormatError(f"path: {path!r}: the map's frontend field camera is not valid ({e})") from None
    return extractor, camera


@dataclass(frozen=True)
class MapLocalization:
    """One localized image: ``pose`` (4, 4) world_from_cam and ``covariance`` (6, 6, right
    perturbation, translation first) or None when lost; ``source`` "geometric" / "fused" /
    "motion" / "lost"; ``reason``; ``keyframe`` retrieved; PnP ``inliers``; ``timings`` in ms
    per stage (``decode``, ``features``, the core's stages, ``total``). When the map adjusted
    its labels, ``pose`` is in the labels' convention (world_from_label, what the sequence's
    poses were) and ``camera_pose`` is the camera's own world_from_cam; otherwise the two are
    equal."""

    pose: NDArray[np.float64] | None
    covariance: NDArray[np.float64] | None
    source: str
    reason: str
    keyframe: int
    inliers: int
    timings: dict[str, float] = field(default_factory=dict)
    camera_pose: NDArray[np.float64] | None = None

    @property
    def timings_ms(self) -> dict[str, float]:
        """Alias of :attr:`timings` (milliseconds)."""
        return self.timings


class Localizer:
    """Localizes images frame after frame against a :class:`Map`, keeping the motion history.

    ``locator``: "paper" (the paper's: one retrieved keyframe and its co-visible group) or
    "model" (top-``top_k`` retrieval against the map-level 3D model, PnP, guided matching).
    In sequence the paper's locator also tracks: when the retrieved keyframe's group gives
    fewer than half the inliers of the last frame, the last frame's group is tried too and
    the pose with more inliers kept (the result's ``reason`` says so).
    Each query keypoint's pixel noise in PnP is ``pixel_sigma`` × its own σ from the detector
    scale (:attr:`geoloc.features.Features.pixel_sigmas`: 1.2^level for ORB)."""

    def __init__(
        self,
        map: Map,
        camera: Camera | None = None,
        *,
        pixel_sigma: float = 1.0,
        max_residual: float = 5.0,
        gate_sigma: float = 3.0,
        history: int = 4,
        global_descriptor: GlobalDescriptor | None = None,
        locator: Literal["paper", "model"] = "paper",
        top_k: int = 5,
    ) -> None:
        if not isinstance(map, Map):
            raise InvalidInputError(f"map: expected a geoloc.Map, got {type(map).__name__}")
        if camera is not None and not isinstance(camera, Camera):
            raise InvalidInputError(f"camera: expected a geoloc.Camera, got {type(camera).__name__}")
        if camera is not None and camera.intrinsics != map.camera.intrinsics:
            raise InvalidInputError(
                f"camera: intrinsics {camera.intrinsics} differ from the map's {map.camera.intrinsics}; "
                "queries must be described with the map's camera"
            )
        recorded = map.settings["retrieval"]
        if recorded != "bow" and global_descriptor is None:
            raise InvalidInputError("global_descriptor: this map retrieves by a network; pass the same network here")
        if recorded != "bow" and isinstance(recorded, dict) and "sha256" in recorded:
            if getattr(global_descriptor, "sha256", None) != recorded["sha256"]:
                raise InvalidInputError(
                    f"global_descriptor: the map was built with network {recorded.get('name', '?')!r} "
                    f"(sha256 {str(recorded['sha256'])[:12]}…); this is another model"
                )
        self.map = map
        self.camera = camera or map.camera
        self._global = global_descriptor
        self._core = FeatureLocalizer(
            map._feature_map, pixel_sigma=pixel_sigma, max_residual=max_residual, gate_sigma=gate_sigma, history=history,
            locator=locator, top_k=top_k,
        )

    def _decode(self, image: Any) -> NDArray[np.uint8]:
        if isinstance(image, (str, os.PathLike)):
            from ._images import read_image

            return read_image(image, "image", gray=True)
        return np.asarray(image)

    def localize(self, image: Any, timestamp: float) -> MapLocalization:
        """Localize one image (a path, (H, W) gray or (H, W, 3) BGR uint8 of the map's size)
        taken at ``timestamp`` (seconds, increasing)."""
        start = time.perf_counter()
        pixels = self._decode(image)
        decoded = time.perf_counter()
        f: Features = self.map.features(pixels, self.camera)
        described = time.perf_counter()
        g = None
        if self._global is not None:
            g = np.asarray(self._global([pixels]), dtype=np.float32)[0]
        r: LocalizationResult = self._core.localize(
            real_scalar(timestamp, "timestamp"), f.keypoints, f.descriptors, g, pixel_sigmas=f.pixel_sigmas
        )
        end = time.perf_counter()
        timings = {"decode": 1e3 * (decoded - start), "features": 1e3 * (described - decoded)}
        timings.update(r.timings_ms)
        timings["total"] = 1e3 * (end - start)
        return MapLocalization(r.pose, r.covariance, r.source, r.reason, r.keyframe, r.inliers, timings, r.camera_pose)

    def reset(self) -> None:
        """Forget the motion history and the last frame's keyframe (the next frame is
        localized by geometry alone)."""
        self._core.reset()

    def localize_sequence(
        self, sequence: Any, mode: str = "sequential", progress: ProgressCallback | None = None
    ) -> list[MapLocalization]:
        """Localize every frame of ``sequence`` (a :class:`geoloc.datasets.Sequence`) in order,
        from an empty motion history. ``mode`` ``"sequential"`` keeps the history from frame to
        frame (motion model + gated fusion); ``"single"`` resets it before every frame (the
        geometric locator alone). Each result's ``timings`` gets ``decode`` (reading the image
        as grey — rendering it, for the synthetic room) and its ``total`` includes it.
        ``progress(done, total)`` is called after every frame."""
        if mode not in SEQUENCE_MODES:
            raise InvalidInputError(f"mode: expected one of {', '.join(SEQUENCE_MODES)}, got {mode!r}")
        self.reset()
        results = []
        n = len(sequence)
        for i in range(n):
            if mode == "single":
                self.reset()
            start = time.perf_counter()
            gray = sequence.gray(i)
            decode_ms = 1e3 * (time.perf_counter() - start)
            r = self.localize(gray, float(sequence.timestamps[i]))
            r.timings["total"] = r.timings.get("total", 0.0) - r.timings.get("decode", 0.0) + decode_ms
            r.timings["decode"] = decode_ms
            results.append(r)
            if progress is not None:
                progress(i + 1, n)
        return results
