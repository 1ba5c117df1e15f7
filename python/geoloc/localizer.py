"""The per-frame localizer: :class:`Localizer` against a :class:`geoloc.Map`, and its
result :class:`Localization`.

Frame after frame: features (from the image, or given) → retrieval → keyframe group →
triangulation (cached) → PnP with a calibrated covariance → constant-velocity motion model →
gated fusion; the motion history is kept between frames. Every option left ``None`` takes
the core's default (:meth:`Localizer.default_options`), the same in Python, in the CLI and
in ``geoloc-rs``.

``FeatureMap``, ``FeatureLocalizer`` and ``LocalizationResult`` are the deprecated names of
the feature-level path (now :meth:`geoloc.Map.from_features`,
:meth:`Localizer.localize_features` and :class:`Localization`); they keep working for one
release with a ``DeprecationWarning``.
"""

from __future__ import annotations

import os
import time
import warnings
from dataclasses import dataclass, field
from typing import Any, Literal, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import _core
from ._validation import as_float64, check_network, check_progress, given_options, keypoint_rows, network_rows, real_scalar
from .camera import Camera
from .exceptions import InvalidInputError
from .features import FeatureExtractor
from .mapping import GlobalDescriptor, Map, ProgressCallback
from .retrieval import _f32_rows, _local_descriptors

__all__ = ["FeatureLocalizer", "FeatureMap", "Localization", "Localizer", "SEQUENCE_MODES"]

#: The modes of :meth:`Localizer.localize_sequence`.
SEQUENCE_MODES = ("single", "sequential")


@dataclass(frozen=True)
class Localization:
    """One localized frame: ``pose`` (4, 4) world_from_cam and ``covariance`` (6, 6, right
    perturbation, translation first) or None when lost; ``source`` "geometric" / "fused" /
    "motion" / "lost"; ``reason`` says why; ``keyframe`` the keyframe whose group gave the
    geometric pose (the retrieved one, or the last frame's when the paper's locator
    tracked; 0 when no geometric pose was found — a ``lost`` frame, or a ``motion`` answer
    whose measurement failed — so read it with ``source`` and ``inliers``); PnP ``inliers`` of the frame's geometric pose (for a ``motion`` answer, those of
    the refused or failed measurement, not support for the answered pose); ``timings`` in ms per stage (the core's ``retrieval``,
    ``keyframes``, ``map_points``, ``matching``, ``pnp``, ``motion_fusion``; from an image
    also ``decode`` and ``features``; ``total``). When the map adjusted its labels, ``pose`` is
    in the labels' convention (world_from_label, what the sequence's poses were) and
    ``camera_pose`` is the camera's own world_from_cam, with ``camera_covariance`` its 6×6
    covariance: Ad_{X⁻¹} C Ad_{X⁻¹}ᵀ + Σ_X for the offset X = pose⁻¹ · camera_pose and its
    covariance Σ_X (``Map.labels["label_from_cam_covariance"]``, a full 6×6); otherwise the two poses and the two
    covariances are equal.
    ``map_noise_scale`` is the factor on the map's C_map inside ``covariance``: w·max(1, n̄/n)
    for a pose resting on n inliers when the map's held-out keyframes had a median n̄
    (``Map.map_noise["holdout_inliers"]``; a motion-only frame takes the last measurement's
    n), 1 when lost; w ∈ [0, 1] is C_map's weight at the pose's ``novelty`` ν, its distance from
    the nearest keyframe (√((Δt / 10 cm)² + (Δθ / 5°)²); None when lost): a pose as near a
    keyframe as the keyframes are to each other carries the keyframe poses' own variance
    instead of C_map (``Map.map_noise["near"]``, :meth:`Map.map_noise_at`)."""

    pose: NDArray[np.float64] | None
    covariance: NDArray[np.float64] | None
    source: str
    reason: str
    keyframe: int
    inliers: int
    timings: dict[str, float] = field(default_factory=dict)
    camera_pose: NDArray[np.float64] | None = None
    map_noise_scale: float = 1.0
    novelty: float | None = None
    camera_covariance: NDArray[np.float64] | None = None

    @property
    def timings_ms(self) -> dict[str, float]:
        """Deprecated alias of :attr:`timings` (milliseconds)."""
        warnings.warn("Localization.timings_ms is deprecated; use .timings (milliseconds)", DeprecationWarning, stacklevel=2)
        return self.timings


def _from_core(r: Any, timings: dict[str, float] | None = None) -> Localization:
    stages = dict(timings or {})
    stages.update(r.timings_ms)
    return Localization(r.pose, r.covariance, r.source, r.reason, r.keyframe, r.inliers, stages, r.camera_pose,
                        r.map_noise_scale, r.novelty, r.camera_covariance)


def check_map_camera(camera: Camera, map: Map, name: str) -> None:
    """InvalidInputError naming ``name`` unless ``camera`` is the map's — intrinsics, image
    size and distortion alike: the queries' keypoints are corrected with the map's camera, so
    frames of another camera would be localized as if taken with it."""
    if camera == map.camera:
        return
    differ = [
        f"{what} {mine} where the map has {theirs}"
        for what, mine, theirs in (
            ("intrinsics", camera.intrinsics, map.camera.intrinsics),
            ("image size", (camera.width, camera.height), (map.camera.width, map.camera.height)),
            ("distortion", camera.dist, map.camera.dist),
        )
        if mine != theirs
    ]
    raise InvalidInputError(
        f"{name}: not the map's camera — {'; '.join(differ)}; queries must be described with the map's camera"
    )


def check_map_network(global_descriptor: GlobalDescriptor | None, map: Map) -> None:
    """InvalidInputError naming ``global_descriptor`` unless it is what the map retrieves
    with: None for a bag-of-words map, the network (same sha256) it was built with otherwise."""
    recorded = map.settings["retrieval"]
    if recorded == "bow" and global_descriptor is not None:
        raise InvalidInputError(
            "global_descriptor: this map retrieves by bag of words alone and would not use a network "
            "(it ran on every query for nothing); build the map with the network to use one"
        )
    if isinstance(recorded, dict) and global_descriptor is None:
        raise InvalidInputError("global_descriptor: this map retrieves by a network; pass the same network here")
    if isinstance(recorded, dict) and "sha256" in recorded:
        if getattr(global_descriptor, "sha256", None) != recorded["sha256"]:
            raise InvalidInputError(
                f"global_descriptor: the map was built with network {recorded.get('name', '?')!r} "
                f"(sha256 {str(recorded['sha256'])[:12]}…); this is another model"
            )
    if global_descriptor is not None:
        check_network(global_descriptor, "global_descriptor")


def query_gray(image: Any, extractor: FeatureExtractor, camera: Camera) -> NDArray[np.uint8]:
    """A query's grey image, as Map.build described its keyframes: a path decoded straight to
    grey, a BGR image converted (``extractor.gray``); the features and a global-descriptor
    network both see it (``Localizer.localize`` and ``export_frames``)."""
    if isinstance(image, (str, os.PathLike)):
        from ._images import read_image

        return extractor.gray(read_image(image, "image", gray=True), camera)
    if isinstance(image, (bytes, bytearray)):  # numpy would make it a one-string array
        raise InvalidInputError(f"image: expected a path (str or os.PathLike) or an image array, got {type(image).__name__}")
    return extractor.gray(np.asarray(image), camera)


class Localizer:
    """Localizes frames against a :class:`geoloc.Map`, frame after frame, keeping the motion
    history.

    ``locator``: "paper" (the paper's: one retrieved keyframe and its co-visible group,
    triangulated on the fly) or "model" (top-``top_k`` retrieval against the map-level 3D
    model, PnP, guided matching, and the next ``top_k`` of the ranking when those give no
    accepted pose; built here when the map has none; refused, naming
    ``locator``, when the model has fewer points than a pose needs — keyframes too close
    together to triangulate from — since it could place no frame). In sequence the paper's
    locator also tracks: when the retrieved keyframe's group gives fewer than half the
    inliers of the last frame, the last frame's group is tried too and the pose with more
    inliers kept (the result's ``reason`` says so). Each keypoint's pixel noise in PnP and
    triangulation is ``pixel_sigma`` × its own σ from the detector scale
    (:attr:`geoloc.features.Features.pixel_sigmas`: 1.2^level for ORB); residuals beyond
    ``max_residual`` px are outliers; a geometric pose farther than ``gate_sigma`` σ from the
    motion prediction (fitted to the last ``history`` poses) is not fused. ``None`` = the
    core's default (:meth:`default_options`); the core checks every value.

    ``camera`` (optional) must be the map's camera — intrinsics, image size and distortion;
    ``global_descriptor`` is the
    network a map that retrieves by global descriptors was built with (for :meth:`localize`)."""

    def __init__(
        self,
        map: Map,
        camera: Camera | None = None,
        *,
        pixel_sigma: float | None = None,
        max_residual: float | None = None,
        gate_sigma: float | None = None,
        history: int | None = None,
        global_descriptor: GlobalDescriptor | None = None,
        locator: Literal["paper", "model"] | None = None,
        top_k: int | None = None,
    ) -> None:
        if not isinstance(map, Map):
            raise InvalidInputError(f"map: expected a geoloc.Map, got {type(map).__name__}")
        if isinstance(camera, str) and camera in ("paper", "model"):
            raise InvalidInputError(
                f"camera: expected a geoloc.Camera, got the string {camera!r}; the locator is a keyword: locator={camera!r}"
            )
        if camera is not None and not isinstance(camera, Camera):
            raise InvalidInputError(f"camera: expected a geoloc.Camera, got {type(camera).__name__}")
        if camera is not None:
            check_map_camera(camera, map, "camera")
        check_map_network(global_descriptor, map)
        recorded = map.settings["retrieval"]
        if locator is not None and not isinstance(locator, str):
            raise InvalidInputError(f"locator: expected 'paper' or 'model', got {locator!r:.40}")
        options = given_options(
            pixel_sigma=None if pixel_sigma is None else real_scalar(pixel_sigma, "pixel_sigma"),
            max_residual=None if max_residual is None else real_scalar(max_residual, "max_residual"),
            gate_sigma=None if gate_sigma is None else real_scalar(gate_sigma, "gate_sigma"),
            history=history,
            locator=locator,
            top_k=top_k,
        )
        self.map = map
        self.camera = camera or map.camera
        self._global = global_descriptor
        self._bow_only = recorded == "bow"
        self._core = _core.FeatureLocalizer(map._core, options=options)

    @staticmethod
    def default_options() -> dict[str, Any]:
        """The core's default localizer options (what every ``None`` argument means)."""
        return dict(_core.localizer_defaults())

    @property
    def options(self) -> dict[str, Any]:
        """The options this localizer runs with (the keys of :meth:`default_options`)."""
        return dict(self._core.options)

    def localize(self, image: Any, timestamp: float) -> Localization:
        """Localize one image (a path, (H, W) gray or (H, W, 3) BGR uint8 of the map's size)
        taken at ``timestamp`` (seconds, increasing), described with the map's features.

        A BGR image is converted to grey first (OpenCV's BGR → grey), and the features and
        the global-descriptor network, when the map has one, see that grey image, as they
        saw the keyframes' at build. A path is decoded straight to grey (for a JPEG its
        luma), as ``localize_sequence``, ``export_frames`` and the CLI read a dataset's
        files; the two greys of one JPEG differ by a few levels, and so do the answers."""
        extractor = self.map.features
        if extractor is None:
            raise InvalidInputError(
                "image: this map was built from features (Map.from_features); localize it with localize_features"
            )
        start = time.perf_counter()
        gray = query_gray(image, extractor, self.camera)
        decoded = time.perf_counter()
        f = extractor(gray, self.camera)
        described = time.perf_counter()
        g = None
        if self._global is not None:
            g = network_rows(self._global, [gray], "global_descriptor")[0]
        r = self._core.localize(
            real_scalar(timestamp, "timestamp"), f.keypoints, f.descriptors, g, pixel_sigmas=f.pixel_sigmas
        )
        end = time.perf_counter()
        result = _from_core(r, {"decode": 1e3 * (decoded - start), "features": 1e3 * (described - decoded)})
        result.timings["total"] = 1e3 * (end - start)
        return result

    def localize_features(
        self,
        timestamp: float,
        keypoints: ArrayLike,
        descriptors: ArrayLike,
        global_descriptor: ArrayLike | None = None,
        pixel_sigmas: ArrayLike | None = None,
    ) -> Localization:
        """Localize one frame given as features, taken at ``timestamp`` (seconds,
        increasing): ``keypoints`` (N, 2) undistorted pixels, ``descriptors`` (N, W) of the
        map's kind, ``global_descriptor`` one (D,) vector when the map retrieves by global
        descriptors, ``pixel_sigmas`` (N,) each keypoint's positional σ from its detector
        scale (:attr:`geoloc.features.Features.pixel_sigmas`, finite and > 0; keypoint i's
        pixel noise is then ``pixel_sigma`` × ``pixel_sigmas[i]``; None: ``pixel_sigma``)."""
        d = _local_descriptors(descriptors, "descriptors")
        k = keypoint_rows(keypoints, "keypoints", len(d))
        g = None
        if global_descriptor is not None and self._bow_only:
            raise InvalidInputError(
                "global_descriptor: this map retrieves by bag of words alone and would not use it; "
                "build the map with a network to retrieve by one"
            )
        if global_descriptor is not None:
            g = np.asarray(global_descriptor)
            if g.ndim != 1:
                raise InvalidInputError(f"global_descriptor: expected shape (D,), got {g.shape}")
            g = _f32_rows(g[None], "global_descriptor")[0]
        s = None
        if pixel_sigmas is not None:
            s = as_float64(pixel_sigmas, "pixel_sigmas")
            if s.shape != (len(k),):
                raise InvalidInputError(f"pixel_sigmas: expected shape ({len(k)},), got {s.shape}")
            s = np.ascontiguousarray(s)
        return _from_core(self._core.localize(real_scalar(timestamp, "timestamp"), k, d, g, s))

    def reset(self) -> None:
        """Forget the motion history and the last frame's keyframe (the next frame is
        localized by geometry alone)."""
        self._core.reset()

    def __reduce__(self) -> tuple[Any, ...]:
        raise TypeError(
            "a Localizer cannot be pickled: it holds one stream's motion history; pickle its map "
            "(a geoloc.Map pickles as its file's bytes) and make a Localizer in each process"
        )

    def localize_sequence(
        self, sequence: Any, mode: str = "sequential", progress: ProgressCallback | None = None
    ) -> list[Localization]:
        """Localize every frame of ``sequence`` (a :class:`geoloc.datasets.Sequence`, whose
        camera must be the map's) in order, from an empty motion history. ``mode``
        ``"sequential"`` keeps the history from frame to frame (motion model + gated fusion);
        ``"single"`` resets it before every frame (the geometric locator alone). Each result's ``timings`` gets ``decode`` (reading the image
        as grey — rendering it, for the synthetic room) and its ``total`` includes it.
        ``progress(done, total)`` is called after every frame."""
        # a Sequence, or anything with its frames' interface (len, gray(i), timestamps)
        if not all(hasattr(sequence, a) for a in ("__len__", "gray", "timestamps")):
            raise InvalidInputError(f"sequence: expected a geoloc.datasets.Sequence, got {type(sequence).__name__}")
        if mode not in SEQUENCE_MODES:
            raise InvalidInputError(f"mode: expected one of {', '.join(SEQUENCE_MODES)}, got {mode!r}")
        camera = getattr(sequence, "camera", None)
        if camera is not None:
            check_map_camera(camera, self.map, "sequence")
        check_progress(progress)
        self.reset()
        results = []
        n = len(sequence)
        for i in range(n):
            if mode == "single":
                self.reset()
            start = time.perf_counter()
            gray = sequence.gray(i)
            decode_ms = 1e3 * (time.perf_counter() - start)
            try:
                r = self.localize(gray, float(sequence.timestamps[i]))
            except InvalidInputError as e:  # which frame: the core knows only this one's values
                raise type(e)(f"{e} (frame {int(sequence.indices[i])} of {sequence.name!r}, position {i})") from None
            r.timings["total"] = r.timings.get("total", 0.0) - r.timings.get("decode", 0.0) + decode_ms
            r.timings["decode"] = decode_ms
            results.append(r)
            if progress is not None:
                progress(i + 1, n)
        return results


def _deprecated(old: str, new: str) -> None:
    warnings.warn(f"{old} is deprecated and will be removed in the next release; use {new}", DeprecationWarning, stacklevel=3)


class FeatureMap(Map):
    """Deprecated: :meth:`geoloc.Map.from_features`. Kept for one release with its former
    defaults (the map's noise, camera and labels not estimated), so that old code gives the
    results it gave."""

    def __init__(
        self,
        camera: Camera,
        poses: ArrayLike,
        keypoints: Sequence[ArrayLike],
        descriptors: Sequence[ArrayLike],
        global_descriptors: ArrayLike | None = None,
        pose_covariances: ArrayLike | None = None,
        retrieval: Literal["bow", "global"] = "bow",
        branching: int | None = None,
        depth: int | None = None,
        seed: int | None = None,
        timestamps: ArrayLike | None = None,
        estimate_noise: bool = False,
        model: bool = False,
        refine_intrinsics: bool = False,
        intrinsics_model: Literal["pinhole", "radial", "radial-tangential"] | None = None,
        adjust_labels: bool = False,
    ) -> None:
        _deprecated("geoloc.localizer.FeatureMap", "geoloc.Map.from_features")
        built = Map.from_features(
            camera, poses, keypoints, descriptors, global_descriptors=global_descriptors,
            pose_covariances=pose_covariances, timestamps=timestamps, retrieval=retrieval, branching=branching,
            depth=depth, seed=seed, estimate_noise=estimate_noise, model=model, refine_intrinsics=refine_intrinsics,
            intrinsics_model=intrinsics_model, adjust_labels=adjust_labels,
        )
        super().__init__(built._core, built.camera, None, built._frontend)

    @property
    def frontend(self) -> dict[str, Any]:
        """The caller's settings given to :meth:`save` (empty when none)."""
        caller: dict[str, Any] = self.settings.get("caller", {})
        return caller

    def save(self, path: str | os.PathLike[str], frontend: dict[str, Any] | None = None) -> None:
        """:meth:`geoloc.Map.save`; ``frontend`` (a JSON-able dict) is kept as the caller's settings."""
        if frontend:
            self._frontend = {**self._frontend, "caller": dict(frontend)}
        super().save(path)

    @classmethod
    def load(cls, path: str | os.PathLike[str], camera: Camera | None = None) -> Map:
        """:meth:`geoloc.Map.load` (``camera``, when given, must have the map's intrinsics)."""
        _deprecated("geoloc.localizer.FeatureMap.load", "geoloc.Map.load")
        loaded = Map.load(path)
        if camera is not None and (not isinstance(camera, Camera) or camera.intrinsics != loaded.camera.intrinsics):
            raise InvalidInputError(f"camera: must be a geoloc.Camera with the map's intrinsics {loaded.camera.intrinsics}")
        return loaded


class FeatureLocalizer:
    """Deprecated: :class:`Localizer` and :meth:`Localizer.localize_features`."""

    def __init__(
        self,
        map: Map,
        pixel_sigma: float | None = None,
        max_residual: float | None = None,
        gate_sigma: float | None = None,
        history: int | None = None,
        locator: Literal["paper", "model"] | None = None,
        top_k: int | None = None,
    ) -> None:
        _deprecated("geoloc.localizer.FeatureLocalizer", "geoloc.Localizer(...).localize_features")
        self._localizer = Localizer(
            map, pixel_sigma=pixel_sigma, max_residual=max_residual, gate_sigma=gate_sigma, history=history,
            locator=locator, top_k=top_k,
        )

    def localize(
        self,
        timestamp: float,
        keypoints: ArrayLike,
        descriptors: ArrayLike,
        global_descriptor: ArrayLike | None = None,
        pixel_sigmas: ArrayLike | None = None,
    ) -> Localization:
        """:meth:`Localizer.localize_features`."""
        return self._localizer.localize_features(timestamp, keypoints, descriptors, global_descriptor, pixel_sigmas)

    def reset(self) -> None:
        """:meth:`Localizer.reset`."""
        self._localizer.reset()


def __getattr__(name: str) -> Any:
    if name == "LocalizationResult":
        _deprecated("geoloc.localizer.LocalizationResult", "geoloc.Localization")
        return Localization
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
