"""The per-frame localizer at the level of features (keypoints + descriptors).

:class:`FeatureMap` holds keyframes with known world_from_cam poses, their undistorted
keypoints and local descriptors (uint8 rows: binary/ORB; float rows: SIFT), optional global
descriptors and pose-label covariances, and builds the retrieval structure (bag of words by
default — no network needed — or the global descriptors). :class:`FeatureLocalizer` runs the
paper's pipeline frame after frame (retrieval → keyframe group → triangulation, cached →
PnP with calibrated covariance → constant-velocity motion → gated fusion) and keeps the
motion history. Image-level mapping (feature extraction, datasets) builds on these.
"""

from __future__ import annotations

import json
import os

from typing import Any, Literal, Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import _core
from ._core import Localization as LocalizationResult
from ._validation import as_batch, as_float64, choice, real_scalar
from .camera import Camera
from .exceptions import FileAccessError, InvalidInputError
from .retrieval import _f32_rows, _local_descriptors

#: The camera models ``FeatureMap(refine_intrinsics=True)`` can estimate (geoloc-core's
#: ``IntrinsicsModel``): focal lengths and principal point, + radial k1 k2, + tangential p1 p2.
INTRINSICS_MODELS = ("pinhole", "radial", "radial-tangential")

__all__ = ["FeatureLocalizer", "FeatureMap", "LocalizationResult"]

Array = NDArray[np.float64]


def _keypoints(x: ArrayLike, name: str, n: int | None = None) -> Array:
    k = as_float64(x, name)
    if k.ndim != 2 or k.shape[1] != 2 or (n is not None and k.shape[0] != n):
        want = f"({n}, 2)" if n is not None else "(N, 2)"
        raise InvalidInputError(f"{name}: expected shape {want}, got {k.shape}")
    return np.ascontiguousarray(k)


def _noise_source(cov: NDArray[np.float64], samples: int) -> str:
    """Where C_map came from, in words (the core picks; this only describes)."""
    if not np.any(cov):
        return "none (the map's noise was not estimated)"
    if samples < _core.MIN_NOISE_SAMPLES:
        sigma = np.sqrt(np.diag(cov))
        return (
            f"default: {samples} held-out keyframes < {_core.MIN_NOISE_SAMPLES} cannot estimate it "
            f"(σ {100 * sigma[0]:.0f} cm / {np.degrees(sigma[3]):.0f}° per axis)"
        )
    return f"estimated from {samples} held-out keyframes"


class FeatureMap:
    """Keyframes (poses + features) and their retrieval structure; see the module doc.

    Everything is checked here, at construction (counts, finiteness, float32 range, pose
    covariances symmetric positive semi-definite, ``retrieval`` in {"bow", "global"}, the
    vocabulary's limits ``branching`` ≤ 1024, ``depth`` ≤ 24, ``branching**depth`` ≤ 2**24),
    so a map that builds localizes.

    ``estimate_noise=True`` estimates the map's own noise once built (see :attr:`map_noise`):
    the map-frame covariance C_map by re-localizing every 10th keyframe against the others
    (its ±15 neighbours excluded), and with ``timestamps`` (one per keyframe, seconds) the
    motion model's acceleration process noise.

    ``model=True`` builds the map-level 3D model of the model locator (``locator="model"``)
    once, here, and stores it with the map (:attr:`model_points`); without it a model
    localizer builds it when it is created.

    ``refine_intrinsics=True`` first estimates the camera from the keyframes themselves —
    their tracks, with the poses known, fix the focal lengths, the principal point and (per
    ``intrinsics_model``) a radial and tangential distortion the nominal ``camera`` lacks —
    and corrects the keyframes' keypoints and, in the localizer, every query's keypoints with
    it; :attr:`self_calibration` reports what was found, and why not when the tracks do not
    determine the camera (too short or too straight a recording: the keypoints are then left
    as they are). With both, the keyframe pairs are matched once for the two: building the
    map with ``model=True`` is cheaper than building the model later."""

    def __init__(
        self,
        camera: Camera,
        poses: ArrayLike,
        keypoints: Sequence[ArrayLike],
        descriptors: Sequence[ArrayLike],
        global_descriptors: ArrayLike | None = None,
        pose_covariances: ArrayLike | None = None,
        retrieval: Literal["bow", "global"] = "bow",
        branching: int = 10,
        depth: int = 3,
        seed: int = 0,
        timestamps: ArrayLike | None = None,
        estimate_noise: bool = False,
        model: bool = False,
        refine_intrinsics: bool = False,
        intrinsics_model: Literal["pinhole", "radial", "radial-tangential"] = "radial-tangential",
        adjust_labels: bool = False,
    ) -> None:
        if not isinstance(camera, Camera):
            raise InvalidInputError(f"camera: expected a geoloc.Camera, got {type(camera).__name__}")
        flat, lead = as_batch(poses, "poses", (4, 4))
        if len(lead) != 1:
            raise InvalidInputError(f"poses: expected shape (K, 4, 4), got {np.shape(poses)}")
        n = flat.shape[0]
        for name, value in (("keypoints", keypoints), ("descriptors", descriptors)):
            if not isinstance(value, (list, tuple)) and not (isinstance(value, np.ndarray) and value.ndim >= 1):
                raise InvalidInputError(f"{name}: expected a list of one array per pose, got {type(value).__name__}")
        if len(keypoints) != n or len(descriptors) != n:
            raise InvalidInputError(f"keypoints, descriptors: expected one array per pose ({n})")
        descs = [_local_descriptors(d, f"descriptors[{i}]") for i, d in enumerate(descriptors)]
        kps = [_keypoints(k, f"keypoints[{i}]", len(descs[i])) for i, k in enumerate(keypoints)]
        g = None if global_descriptors is None else _f32_rows(global_descriptors, "global_descriptors")
        covs = None
        if pose_covariances is not None:
            c = as_float64(pose_covariances, "pose_covariances")
            if c.shape != (n, 6, 6):
                raise InvalidInputError(f"pose_covariances: expected shape ({n}, 6, 6), got {c.shape}")
            covs = np.ascontiguousarray(c.reshape(n, 36))
        ts = None
        if timestamps is not None:
            ts = np.ascontiguousarray(as_float64(timestamps, "timestamps"))
            if ts.shape != (n,):
                raise InvalidInputError(f"timestamps: expected shape ({n},), got {ts.shape}")
        self.camera = camera
        self.frontend: dict[str, Any] = {}
        self._map = _core.FeatureMap(
            camera.intrinsics, flat, kps, descs, global_descriptors=g, pose_covariances=covs,
            retrieval=retrieval, branching=branching, depth=depth, seed=seed,
            timestamps=ts, estimate_noise=bool(estimate_noise), model=bool(model),
            refine_intrinsics=bool(refine_intrinsics),
            intrinsics_model=choice(intrinsics_model, "intrinsics_model", INTRINSICS_MODELS),
            adjust_labels=bool(adjust_labels),
        )

    @property
    def self_calibration(self) -> dict[str, Any] | None:
        """The camera the map estimated from its keyframes (``refine_intrinsics=True``), or
        None when it was not tried: ``camera`` {fx, fy, cx, cy} and ``distortion`` (OpenCV's
        k1, k2, p1, p2, k3) when there is a correction — the keyframes' keypoints are then
        stored corrected and every query's keypoints are corrected the same way by the
        localizer — else absent; ``reason`` ("ok" or why not); the tracks' pixel residuals
        ``rms_before_px`` / ``rms_after_px`` and ``median_before_px`` / ``median_after_px``;
        ``observations`` and ``points`` used; ``correction_sigma_px``, the RMS 1σ of the
        correction over the tracks' pixels (applied only below 0.5 px)."""
        text = self._map.self_calibration_json
        return None if text is None else dict(json.loads(text))

    @property
    def labels(self) -> dict[str, Any] | None:
        """The labels' correction by bundle adjustment (``adjust_labels=True``), or None when
        the labels were not adjusted: ``label_sigma_m`` / ``label_sigma_deg`` (the labels' σ the
        adjustment estimated), the label-to-camera offset (``label_from_cam_translation_m``,
        ``label_from_cam_rotation_deg`` and their σ), the median correction, ``rms_px`` (the
        tracks' reprojection error with the labels and after), ``observations`` (used,
        rejected) and ``runs``: consecutive keyframes (≥ 3) whose corrections are significant
        (beyond the χ²₆ 99.9 % quantile of their covariance), with the largest correction."""
        text = self._map.labels_json
        return None if text is None else dict(json.loads(text))

    @property
    def label_poses(self) -> NDArray[np.float64] | None:
        """The pose labels as given (K, 4, 4), or None when they were not adjusted."""
        return self._map.label_poses

    @property
    def keyframe_poses(self) -> NDArray[np.float64]:
        """The keyframe poses (K, 4, 4) in the labels' convention: the adjusted ones when the
        labels were adjusted, else the labels."""
        return self._map.keyframe_poses

    @property
    def camera_poses(self) -> NDArray[np.float64]:
        """The keyframes' camera poses world_from_cam (K, 4, 4): the labels moved by the
        adjustment and the label-to-camera offset (the labels when not adjusted)."""
        return self._map.camera_poses

    @property
    def model_points(self) -> int | None:
        """Points of the stored map-level 3D model, or None when the map has none."""
        return self._map.model_points

    @property
    def map_noise(self) -> dict[str, Any]:
        """What was estimated about the map's noise at build time (all zero when not):
        ``pose_covariance`` C_map (6, 6, right perturbation, translation first; added to every
        returned covariance), ``acceleration_psd`` (6,) of the motion model's process noise,
        ``velocity_mean`` and ``velocity_variance`` (6,) of its velocity prior (per twist axis,
        from the keyframes' timestamps and poses; zero in maps saved before it: no prior),
        ``holdout_samples`` (held-out keyframes C_map comes from; with fewer than
        ``geoloc._core.MIN_NOISE_SAMPLES`` C_map is a conservative default, never zero),
        ``pose_covariance_source`` (which of the two, in words) and, for a map built in this
        process (not stored in the file), ``holdout``: the held-out re-localizations
        (``keyframe`` (n,), ``delta`` (n, 6) = log(T_label⁻¹T_est), ``covariance`` (n, 6, 6) C_G,
        ``used`` (n,) bool)."""
        cov, psd, velocity_mean, velocity_variance, samples = self._map.map_noise
        keyframes, deltas, covs, used = self._map.map_noise_holdout
        holdout = {
            "keyframe": np.asarray(keyframes, dtype=np.int64),
            "delta": deltas,
            "covariance": covs,
            "used": np.asarray(used, dtype=bool),
        }
        return {
            "pose_covariance": cov,
            "acceleration_psd": np.asarray(psd),
            "velocity_mean": np.asarray(velocity_mean),
            "velocity_variance": np.asarray(velocity_variance),
            "holdout_samples": samples,
            "pose_covariance_source": _noise_source(cov, samples),
            "holdout": holdout,
        }

    def __len__(self) -> int:
        return len(self._map)

    def save(self, path: str | os.PathLike[str], frontend: Mapping[str, Any] | None = None) -> None:
        """Write the map to one ``.geoloc`` file (safetensors), atomically: an interrupted save
        keeps the previous file. ``frontend`` (a JSON-able dict) records the caller's settings."""
        from ._io import check_output_path

        target = check_output_path(path, "path")
        text = json.dumps(dict(frontend or {}), sort_keys=True, allow_nan=False)
        self._map.save(os.fspath(target), text)

    @classmethod
    def load(cls, path: str | os.PathLike[str], camera: Camera | None = None) -> FeatureMap:
        """Read a map written by :meth:`save`, checking it whole first: a truncated, corrupt or
        other-version file raises :class:`geoloc.exceptions.FileFormatError`. ``camera`` gives
        the image size and distortion (the file stores the intrinsics); its intrinsics must
        match. The caller's settings are in ``.frontend``."""
        from ._io import as_path, shown, special_kind

        source = as_path(path, "path")
        kind = special_kind(source)
        if kind is not None:  # never opened: a FIFO would block the reader
            raise FileAccessError(f"{shown(source)}: cannot read the map: it is {kind}, not a regular file")
        core, text = _core.FeatureMap.load(os.fspath(source))
        intrinsics = core.intrinsics
        if camera is None:
            camera = Camera(*intrinsics)
        elif not isinstance(camera, Camera) or camera.intrinsics != intrinsics:
            raise InvalidInputError(f"camera: must be a geoloc.Camera with the map's intrinsics {intrinsics}")
        self = cls.__new__(cls)
        self.camera = camera
        self._map = core
        self.frontend = json.loads(text)
        return self


LocalizationResult.__doc__ = """One frame: ``pose`` (4, 4) world_from_cam and ``covariance`` (6, 6, right
perturbation, translation first), or None when lost; ``source`` is "geometric", "fused",
"motion" or "lost"; ``reason`` says why; ``keyframe`` the keyframe whose group gave the
geometric pose (the retrieved one, or the last frame's when the paper's locator tracked),
``inliers`` the PnP inliers; per-stage ``timings_ms``."""


class FeatureLocalizer:
    """Localizes frames (given as features) against a :class:`FeatureMap`, frame after frame.

    Options (checked in the core): ``pixel_sigma``, ``max_residual``, ``gate_sigma`` finite
    and > 0, ``history`` an integer ≥ 2 (numpy integers accepted). ``locator``: "paper" (one
    retrieved keyframe, its co-visible group triangulated on the fly) or "model" (top-``top_k``
    retrieval against the map-level 3D model, PnP, guided matching; builds the model here if
    the map has none)."""

    def __init__(
        self,
        map: FeatureMap,
        pixel_sigma: float = 1.0,
        max_residual: float = 5.0,
        gate_sigma: float = 3.0,
        history: int = 4,
        locator: Literal["paper", "model"] = "paper",
        top_k: int = 5,
    ) -> None:
        if not isinstance(map, FeatureMap):
            raise InvalidInputError(f"map: expected a geoloc.localizer.FeatureMap, got {type(map).__name__}")
        self._loc = _core.FeatureLocalizer(
            map._map, pixel_sigma=real_scalar(pixel_sigma, "pixel_sigma"), max_residual=real_scalar(max_residual, "max_residual"),
            gate_sigma=real_scalar(gate_sigma, "gate_sigma"), history=history, locator=str(locator), top_k=top_k,
        )

    def localize(
        self,
        timestamp: float,
        keypoints: ArrayLike,
        descriptors: ArrayLike,
        global_descriptor: ArrayLike | None = None,
        pixel_sigmas: ArrayLike | None = None,
    ) -> LocalizationResult:
        """Localize one frame taken at ``timestamp`` (seconds, increasing); ``global_descriptor``
        is one (D,) vector when the map retrieves by global descriptor. ``pixel_sigmas`` (N,):
        each keypoint's positional σ from its detector scale (:attr:`geoloc.features.Features.pixel_sigmas`,
        finite and > 0); keypoint i's pixel noise in PnP is then ``pixel_sigma`` × ``pixel_sigmas[i]``
        (None: ``pixel_sigma`` for all)."""
        d = _local_descriptors(descriptors, "descriptors")
        k = _keypoints(keypoints, "keypoints", len(d))
        g = None
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
        return self._loc.localize(real_scalar(timestamp, "timestamp"), k, d, g, s)

    def reset(self) -> None:
        """Forget the motion history (and the last frame's keyframe, which the paper's
        locator tracks)."""
        self._loc.reset()
