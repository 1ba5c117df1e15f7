"""The map: keyframes with known poses, their features and the retrieval structure.

A :class:`Map` is built either from images — :meth:`Map.build` takes a
:class:`geoloc.datasets.Sequence` with world_from_cam poses, extracts OpenCV features (ORB by
default, SIFT as an option) and trains a bag-of-words vocabulary (no network needed; the
default) or runs a global-descriptor network (any callable ``images -> (N, D) float32``, e.g.
:class:`geoloc.descriptor.OnnxDescriptor`) — or from features a caller computed
(:meth:`Map.from_features`). Both paths take the same build options with the same defaults,
the core's (:meth:`Map.default_options`): the labels corrected by bundle adjustment, the
camera estimated from the keyframes, the map's own noise estimated. The map is saved to one
``.geoloc`` file (safetensors, written atomically by geoloc-core) that Python and the robot
binary ``geoloc-rs`` both read. :class:`geoloc.Localizer` localizes against it.
"""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path
from typing import Any, Callable, Literal, Protocol, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import _core
from ._frontend import FRONTEND_VERSION, camera_record, descriptor_record, frontend_parts
from ._io import shown
from .adjustment import AdjustmentProblem
from ._validation import as_batch, as_float64, check_progress, choice, given_options, keypoint_rows, network_rows, real_scalar
from .camera import Camera
from .exceptions import FileAccessError, FileFormatError, InvalidInputError
from .features import DEFAULT_KIND, DEFAULT_N_FEATURES, FeatureExtractor
from .retrieval import _f32_rows, _local_descriptors

__all__ = ["GlobalDescriptor", "INTRINSICS_MODELS", "Map"]

#: The camera models the map can estimate (geoloc-core's ``IntrinsicsModel``): focal lengths
#: and principal point, + radial k1 k2, + tangential p1 p2.
INTRINSICS_MODELS = ("pinhole", "radial", "radial-tangential")


class GlobalDescriptor(Protocol):
    """What a network retrieval needs: images → (N, D) float32, and a name to record."""

    def __call__(self, images: list[NDArray[np.uint8]]) -> NDArray[np.float32]: ...


ProgressCallback = Callable[[int, int], None]


def _as_int(value: Any, name: str, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or int(value) < low:
        raise InvalidInputError(f"{name}: expected an integer ≥ {low}, got {value!r}")
    return int(value)


def _flag(value: bool | None, name: str) -> bool | None:
    if value is not None and not isinstance(value, (bool, np.bool_)):
        raise InvalidInputError(f"{name}: expected True or False, got {value!r:.40}")
    return None if value is None else bool(value)


def _increasing(timestamps: NDArray[np.float64]) -> NDArray[np.float64] | None:
    """The keyframes' timestamps for the process-noise estimate, or None when they do not
    strictly increase (then the motion model gets no process noise from the map)."""
    return timestamps if len(timestamps) >= 3 and bool(np.all(np.diff(timestamps) > 0)) else None


#: The six axes of a pose perturbation, translation first (right perturbation).
def _build_options(
    branching: int | None,
    depth: int | None,
    seed: int | None,
    estimate_noise: bool | None,
    model: bool | None,
    refine_intrinsics: bool | None,
    intrinsics_model: str | None,
    adjust_labels: bool | None,
) -> dict[str, Any]:
    """The build options the caller set, checked by type here and by value in the core."""
    return given_options(
        branching=branching,
        depth=depth,
        seed=seed,
        estimate_noise=_flag(estimate_noise, "estimate_noise"),
        model=_flag(model, "model"),
        refine_intrinsics=_flag(refine_intrinsics, "refine_intrinsics"),
        intrinsics_model=None if intrinsics_model is None else choice(intrinsics_model, "intrinsics_model", INTRINSICS_MODELS),
        adjust_labels=_flag(adjust_labels, "adjust_labels"),
    )


def _core_map(
    camera: Camera,
    poses: ArrayLike,
    keypoints: Sequence[ArrayLike],
    descriptors: Sequence[ArrayLike],
    global_descriptors: ArrayLike | None,
    pose_covariances: ArrayLike | None,
    timestamps: ArrayLike | None,
    options: dict[str, Any],
) -> Any:
    """The core map from checked keyframe arrays (counts, shapes, finiteness, float32 range,
    covariance shape; the core checks symmetry and positive semi-definiteness)."""
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
    kps = [keypoint_rows(k, f"keypoints[{i}]", len(descs[i])) for i, k in enumerate(keypoints)]
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
    return _core.FeatureMap(
        camera.intrinsics, flat, kps, descs, global_descriptors=g, pose_covariances=covs, timestamps=ts, options=options
    )


class Map:
    """Keyframes with known poses, their features and the retrieval structure; see the
    module doc. Create one with :meth:`build` (images) or :meth:`from_features`, or
    :meth:`load` a saved one."""

    def __init__(
        self,
        core: Any,
        camera: Camera,
        extractor: FeatureExtractor | None,
        frontend: dict[str, Any],
        inputs: tuple[tuple[str, Path], ...] = (),
    ) -> None:
        self._core = core
        self._camera = camera
        self._extractor = extractor
        self._frontend = frontend
        # (argument, file) for every file the map was built from: :meth:`save` never replaces one
        self._inputs = inputs
        # the file :meth:`load` read it from (None otherwise): a writer of something else
        # (``export_frames``) must not replace it; saving the map back to it may
        self._loaded_from: Path | None = None

    @staticmethod
    def default_options() -> dict[str, Any]:
        """The core's default build options (what every ``None`` argument of :meth:`build`
        and :meth:`from_features` means)."""
        return dict(_core.build_defaults())

    @classmethod
    def build(
        cls,
        sequence: Any,
        retrieval: str | GlobalDescriptor = "bow",
        features: str = DEFAULT_KIND,
        *,
        n_features: int = DEFAULT_N_FEATURES,
        root_sift: bool = False,
        keyframe_step: int = 1,
        branching: int | None = None,
        depth: int | None = None,
        seed: int | None = None,
        estimate_noise: bool | None = None,
        model: bool | None = None,
        refine_intrinsics: bool | None = None,
        intrinsics_model: Literal["pinhole", "radial", "radial-tangential"] | None = None,
        adjust_labels: bool | None = None,
        progress: ProgressCallback | None = None,
    ) -> Map:
        """Build a map from ``sequence`` (every ``keyframe_step``-th frame becomes a keyframe).

        ``retrieval`` is ``"bow"`` (a ``branching``^``depth``-word vocabulary trained on the
        keyframes' descriptors, seeded by ``seed``) or a global-descriptor network, which the
        map combines with that vocabulary (``"fused"``: BoW and the network each propose
        keyframes and two-view verification of the query's matches orders them, so the
        network adds candidates and never removes BoW's; see ``docs/design.md``);
        ``features`` is ``"orb"`` or ``"sift"`` with ``n_features`` per image.
        ``progress(done, total)`` is called after each keyframe.

        Every option left ``None`` takes the core's default (:meth:`default_options`):

        - ``estimate_noise`` (default on): the map's own noise — the map-frame covariance
          C_map from re-localizing held-out keyframes, and the motion model's process noise
          from the frames' timestamps (:attr:`map_noise`); stored in the map file.
        - ``adjust_labels`` (default on): the pose labels corrected by bundle adjustment —
          keyframe poses, points and one label-to-camera offset, the labels as robust priors
          whose σ is estimated — so that the map agrees with its images (:attr:`labels`,
          :attr:`keyframe_poses`, :attr:`label_poses`); results stay in the labels' convention.
        - ``refine_intrinsics`` (default on): the real camera estimated from the keyframes'
          own tracks — focal lengths, principal point and lens distortion per
          ``intrinsics_model`` — and the keyframes' and every query's keypoints corrected
          with it (:attr:`self_calibration` says what was found, or why not).
        - ``model`` (default on): the map-level 3D model of the default, model locator
          built and stored too (off: a localizer with ``locator="model"`` builds it when it
          starts; the paper's locator needs none).

        The keyframe pairs are matched once for all of these steps.
        """
        from .datasets import Sequence

        if not isinstance(sequence, Sequence):
            raise InvalidInputError(f"sequence: expected a geoloc.datasets.Sequence, got {type(sequence).__name__}")
        if sequence.poses is None:
            raise InvalidInputError(f"sequence: {sequence.name!r} has no poses; a map needs world_from_cam poses")
        # a step past the sequence keeps its first frame alone, as a step of its length does
        step = min(_as_int(keyframe_step, "keyframe_step", 1), max(1, len(sequence)))
        if isinstance(retrieval, str) and retrieval != "bow":
            raise InvalidInputError(f"retrieval: expected 'bow' or a global-descriptor network, got {retrieval!r}")
        if not isinstance(retrieval, str) and not callable(retrieval):
            raise InvalidInputError(f"retrieval: expected 'bow' or a callable network, got {type(retrieval).__name__}")
        options = _build_options(branching, depth, seed, estimate_noise, model, refine_intrinsics, intrinsics_model, adjust_labels)
        kind = choice(features, "features", ("orb", "sift"))
        root = bool(_flag(root_sift, "root_sift"))
        check_progress(progress)
        extractor = FeatureExtractor(kind, _as_int(n_features, "n_features", 1), root_sift=root)  # type: ignore[arg-type]
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
        global_descriptors = None if isinstance(retrieval, str) else network_rows(retrieval, images, "retrieval")
        options["retrieval"] = "bow" if isinstance(retrieval, str) else "fused"
        try:
            core = _core_map(
                camera, sequence.poses[indices], keypoints, descriptors, global_descriptors, None,
                _increasing(sequence.timestamps[indices]), options,
            )
        except InvalidInputError as e:
            if not str(e).startswith("descriptors:"):
                raise
            # the features were extracted here: say from what, not only what the core got
            total = sum(len(d) for d in descriptors)
            raise InvalidInputError(
                f"sequence: its {len(indices)} keyframes' images gave {total} {extractor.kind} features in all "
                f"(n_features={extractor.n_features}), too few for a map — images without texture, or n_features too "
                f"small? ({e})"
            ) from None
        frontend = {
            "version": FRONTEND_VERSION,
            "features": {"kind": extractor.kind, "n_features": extractor.n_features, "root_sift": extractor.root_sift},
            "camera": camera_record(camera),
            "retrieval": "bow" if isinstance(retrieval, str) else descriptor_record(retrieval),
            # the dataset's frame numbers (Frame.index), not positions in the sequence as sliced
            "source": {"sequence": shown(sequence.name), "frames": [int(i) for i in sequence.indices[indices]]},
        }
        inputs = [("sequence", f) for f in sequence.files]
        network_file = getattr(retrieval, "path", None)
        if isinstance(network_file, Path):
            inputs.append(("retrieval", network_file))
        return cls(core, camera, extractor, frontend, tuple(inputs))

    @classmethod
    def from_features(
        cls,
        camera: Camera,
        poses: ArrayLike,
        keypoints: Sequence[ArrayLike],
        descriptors: Sequence[ArrayLike],
        *,
        global_descriptors: ArrayLike | None = None,
        pose_covariances: ArrayLike | None = None,
        timestamps: ArrayLike | None = None,
        retrieval: Literal["bow", "global", "fused"] | None = None,
        branching: int | None = None,
        depth: int | None = None,
        seed: int | None = None,
        estimate_noise: bool | None = None,
        model: bool | None = None,
        refine_intrinsics: bool | None = None,
        intrinsics_model: Literal["pinhole", "radial", "radial-tangential"] | None = None,
        adjust_labels: bool | None = None,
    ) -> Map:
        """Build a map from features you computed: ``poses`` (K, 4, 4) world_from_cam, per
        keyframe ``keypoints`` (N, 2) undistorted pixels and local ``descriptors`` (N, W)
        (uint8 rows: binary/ORB; float rows: SIFT), optional ``global_descriptors`` (K, D)
        (``retrieval="global"`` retrieves by them alone, ``"fused"`` — the default when they
        are given — combines them with bag of words as :meth:`build` does with a network;
        without them the default is bag of words),
        ``pose_covariances`` (K, 6, 6) of the labels and ``timestamps`` (K,) in seconds. The
        pose covariances are the keyframes' while the labels are kept (``adjust_labels=False``,
        or labels the images agree with); a labels' adjustment that is applied replaces them
        by the adjusted poses' marginal covariances (:attr:`labels` says which happened).

        The build options and their defaults are those of :meth:`build`. Everything is
        checked here (counts, finiteness, float32 range, covariances symmetric positive
        semi-definite, the vocabulary's limits ``branching`` ≤ 1024, ``depth`` ≤ 24,
        ``branching**depth`` ≤ 2**24), so a map that builds localizes. Such a map localizes
        features (:meth:`geoloc.Localizer.localize_features`), not images."""
        if retrieval is not None:
            choice(retrieval, "retrieval", ("bow", "global", "fused"))
        if global_descriptors is not None and retrieval == "bow":
            raise InvalidInputError(
                "global_descriptors: given with retrieval='bow', which does not use them "
                "(retrieval='fused' combines them with bag of words, 'global' retrieves by them alone)"
            )
        if global_descriptors is None and retrieval in ("global", "fused"):
            raise InvalidInputError(
                f"global_descriptors: retrieval={retrieval!r} retrieves by them, and none were given "
                "(retrieval='bow' needs none)"
            )
        if global_descriptors is not None and retrieval is None:
            retrieval = "fused"  # as Map.build with a network: they were silently dropped
        options = _build_options(branching, depth, seed, estimate_noise, model, refine_intrinsics, intrinsics_model, adjust_labels)
        options.update(given_options(retrieval=retrieval))
        core = _core_map(camera, poses, keypoints, descriptors, global_descriptors, pose_covariances, timestamps, options)
        frontend = {
            "version": FRONTEND_VERSION,
            "features": None,
            "camera": camera_record(camera),
            "retrieval": core.retrieval,
            "source": {"keyframes": len(core)},
        }
        return cls(core, camera, None, frontend)

    @property
    def camera(self) -> Camera:
        """The camera the map was built with (queries must use the same intrinsics)."""
        return self._camera

    @property
    def features(self) -> FeatureExtractor | None:
        """The feature extractor queries are described with (None for a map built from features)."""
        return self._extractor

    @property
    def settings(self) -> dict[str, Any]:
        """What the map records about how it was built: features, camera, retrieval, and its
        ``source`` — a built map's sequence name and ``frames``, the dataset's frame numbers of
        its keyframes (``Frame.index``)."""
        copy: dict[str, Any] = json.loads(json.dumps(self._frontend))
        return copy

    @property
    def self_calibration(self) -> dict[str, Any] | None:
        """The camera the map estimated from its keyframes (``refine_intrinsics``), or None
        when it was not tried: ``camera`` {fx, fy, cx, cy} and ``distortion`` (OpenCV's k1,
        k2, p1, p2, k3) when there is a correction — the keyframes' keypoints are then
        stored corrected and every query's keypoints are corrected the same way by the
        localizer — else absent; ``reason`` ("ok" or why not); the tracks' pixel residuals
        ``rms_before_px`` / ``rms_after_px`` and ``median_before_px`` / ``median_after_px``;
        ``observations`` and ``points`` used; ``correction_sigma_px``, the RMS 1σ of the
        correction over the tracks' pixels (applied only below 0.5 px)."""
        text = self._core.self_calibration_json
        return None if text is None else dict(json.loads(text))

    @property
    def labels(self) -> dict[str, Any] | None:
        """The labels' correction by bundle adjustment (``adjust_labels``), or None when the
        labels were not adjusted: ``applied`` (whether the map uses the adjusted poses),
        ``state`` (that in words: "adjusted", "kept (the images agree with them)", or "kept
        (not checked: …)" when no track linked the keyframes), ``summary`` (the report in one
        line, as ``geoloc build-map`` and ``geoloc-rs info`` print it), ``label_sigma_m`` /
        ``label_sigma_deg`` (the labels' σ the
        adjustment estimated), the label-to-camera offset (``label_from_cam``, the 4×4 X with
        T_cam = T_label·X, as nested lists; ``label_from_cam_translation_m``,
        ``label_from_cam_rotation_deg`` and their σ; ``label_from_cam_covariance``, its full 6×6
        covariance Σ_X as nested lists, right perturbation, translation first), the median correction, ``rms_px`` (the
        tracks' reprojection error with the labels and after), ``observations`` (used,
        rejected), ``runs``: consecutive keyframes (≥ 3) whose corrections are significant
        (beyond the χ²₆ 99.9 % quantile of their covariance), with the largest correction,
        ``steps``: where the labels' motion jumps away from the images' — consecutive keyframe
        pairs k, k + 1 whose d_k = log((L_k⁻¹L_{k+1})⁻¹(B_k⁻¹B_{k+1}))^∨ is beyond the χ²₆
        99.9 % quantile of the pairs' robust scatter (``step_sigma_m``, ``step_sigma_deg``),
        each with ``start``, ``end`` (one past), the disagreement across it
        (``translation_m``, ``rotation_deg``) and ``significance`` (its largest pair's),
        ``breaks``: jumps in the labels the images show before the adjustment — consecutive
        keyframes ``at`` − 1, ``at`` whose descriptor matches an essential matrix explains
        (``image_inliers``) while the labels' epipolar geometry keeps fewer than a third as
        many (``label_inliers``, of ``matches``), ``repaired`` when a re-placed part begins or
        ends there —, ``replaced``: the keyframes ``start`` …
        ``end`` − 1 those jumps cut off that the images re-placed before the adjustment
        (``correction``, log(C) with L' = C·L in the world frame, translation first;
        ``correction_m``, ``correction_deg``; ``localized`` of them located by PnP, ``agreeing``
        on it) — a break no segment's correction reconciles is a jump the map could not
        repair: the keyframes beyond it keep their labels' error —, ``loops``: revisits whose
        labels disagree with the images — keyframes ``a`` < ``b`` the map's retrieval paired
        whose matches an essential matrix explains (``image_inliers``) while the labels keep
        fewer than a third (``label_inliers``, of ``matches``), with ``disagreement`` (b
        located by PnP against a's neighbourhood: log((L_a⁻¹L_b)⁻¹ Z_ab), b's frame,
        translation first; ``disagreement_m``, ``disagreement_deg``; None when not located)
        and ``closed`` (the pose graph that moved the adjustment's start kept it) —, and
        per keyframe, as lists, ``corrections`` (K × 6) e_k = log(L_k⁻¹ B_k)^∨ — label L_k to
        adjusted pose B_k, right perturbation, translation (m) first, rotation (rad) — and
        ``significance`` (K) e_kᵀ Σ_k⁻¹ e_k, Σ_k the adjusted pose's covariance."""
        text = self._core.labels_json
        if text is None:
            return None
        report = dict(json.loads(text))
        corrections, significance = self._core.label_corrections, self._core.label_significance
        report["corrections"] = None if corrections is None else corrections.tolist()
        report["significance"] = None if significance is None else significance.tolist()
        return report

    @property
    def label_poses(self) -> NDArray[np.float64] | None:
        """The pose labels as given (K, 4, 4), or None when they were not adjusted."""
        poses: NDArray[np.float64] | None = self._core.label_poses
        return poses

    @property
    def keyframe_poses(self) -> NDArray[np.float64]:
        """The keyframe poses (K, 4, 4) in the labels' convention: the adjusted ones when the
        labels were adjusted, else the labels."""
        poses: NDArray[np.float64] = self._core.keyframe_poses
        return poses

    @property
    def camera_poses(self) -> NDArray[np.float64]:
        """The keyframes' camera poses world_from_cam (K, 4, 4): the labels moved by the
        adjustment and the label-to-camera offset (the labels when not adjusted). The
        localizer, the motion model and the map's noise work in this frame."""
        poses: NDArray[np.float64] = self._core.camera_poses
        return poses

    def label_adjustment_problem(self) -> AdjustmentProblem:
        """The problem :meth:`build` solves to correct the labels (``adjust_labels``), for
        :func:`geoloc.adjustment.bundle_adjust` or a peer's adjuster: the skeleton keyframes
        (``keyframes``, the map's indices), their labels, the points triangulated from them
        and the tracks' observations, in this map's camera and keypoints (corrected when the
        map estimated its camera). The views the triangulation rejected, which the map's own
        adjustment tries again once its poses fit them (its candidates), are not part of it.
        Only for a map built with ``adjust_labels=False``: an adjusted map's problem is that of
        other start poses (InvalidInputError naming ``labels``)."""
        keyframes, labels, points, obs_kf, obs_pt, obs_px = self._core.label_adjustment_problem()
        return AdjustmentProblem(self._camera.intrinsics, labels, points, obs_kf, obs_pt, obs_px, keyframes=keyframes)

    @property
    def model_points(self) -> int | None:
        """How many points the stored map-level 3D model holds, or None when the map has none."""
        points: int | None = self._core.model_points
        return points

    @property
    def map_noise(self) -> dict[str, Any]:
        """What was estimated about the map's noise at build time (all zero when not):
        ``pose_covariance`` C_map (6, 6, right perturbation, translation first; added to every
        returned covariance), ``acceleration_psd`` (6,) of the motion model's process noise,
        ``velocity_mean`` and ``velocity_variance`` (6,) of its velocity prior (per twist axis,
        from the keyframes' timestamps and poses; zero in maps saved before it: no prior),
        ``holdout_samples`` (held-out keyframes C_map comes from; with fewer than
        ``geoloc._core.MIN_NOISE_SAMPLES`` C_map is a conservative default, never zero),
        ``holdout_inliers`` n̄ (their median PnP inliers: a pose resting on n < n̄ inliers gets
        C_map·n̄/n, see :meth:`map_noise_at`; 0: C_map applies unscaled), ``near`` (None, or
        the near regime: ``covariance`` C_near (6, 6), the keyframe poses' own variance that a
        pose as close to a keyframe as the keyframes are to each other — distance ν ≤
        ``spacing`` — carries instead of C_map, rising linearly to C_map at ν ≥
        ``holdout_distance``, the held-out keyframes' least distance; ν in
        :attr:`Localization.novelty`'s units, 10 cm or 5° = 1),
        ``pose_covariance_source`` (which of the two and the support rule, in words) and, for a map built in this
        process (not stored in the file: empty in a loaded map), ``holdout``: the held-out re-localizations
        (``keyframe`` (n,), ``delta`` (n, 6) = log(T_label⁻¹T_est), ``covariance`` (n, 6, 6) C_G,
        ``inliers`` (n,), ``used`` (n,) bool, ``novelty`` (n,) each one's distance from the
        keyframes its re-localization kept); ``resolved`` (6,) bool: per axis, whether those samples resolve
        C_map (an axis they do not is floored, never zero; stored in the map file, so a loaded
        map says the same; None with too few samples or for a file saved before it was stored)."""
        cov, psd, velocity_mean, velocity_variance, samples, support = self._core.map_noise
        keyframes, deltas, covs, inliers, used, novelty = self._core.map_noise_holdout
        resolved = self._core.map_noise_resolved
        near = self._core.map_noise_near
        holdout = {
            "keyframe": np.asarray(keyframes, dtype=np.int64),
            "delta": deltas,
            "covariance": covs,
            "inliers": np.asarray(inliers, dtype=np.int64),
            "used": np.asarray(used, dtype=bool),
            "novelty": np.asarray(novelty, dtype=np.float64),
        }
        return {
            "pose_covariance": cov,
            "acceleration_psd": np.asarray(psd),
            "velocity_mean": np.asarray(velocity_mean),
            "velocity_variance": np.asarray(velocity_variance),
            "holdout_samples": samples,
            "holdout_inliers": support,
            "pose_covariance_source": self._core.map_noise_description,
            "holdout": holdout,
            "resolved": None if resolved is None else np.asarray(resolved, dtype=bool),
            "near": None if near is None else {"covariance": near[0], "spacing": near[1], "holdout_distance": near[2]},
        }

    def map_noise_at(self, inliers: int | None, novelty: float | None = None) -> NDArray[np.float64]:
        """The map noise (6, 6, as ``map_noise["pose_covariance"]``) of a pose resting on
        ``inliers`` PnP inliers at distance ``novelty`` from its nearest keyframe
        (:attr:`Localization.novelty`): (1 − w)·C_near + w·C_map·max(1, n̄/inliers), n̄ =
        ``map_noise["holdout_inliers"]`` (unscaled for None, 0 inliers or n̄ = 0), w = 1 without
        a near regime (``map_noise["near"]``) or a ``novelty``, else clamp((ν − ν₀)/(ν₁ − ν₀), 0,
        1) — what the localizer adds to the camera pose's covariance.
        When the map adjusted its labels, a result's ``covariance`` is in the labels'
        convention, and what it holds of this is Ad_X C Ad_Xᵀ (X the label-to-camera offset,
        right perturbation: T_label = T_cam X⁻¹)."""
        # any support at or above n̄ leaves C_map unscaled: a count past the core's integer range is that
        count = None if inliers is None else min(_as_int(inliers, "inliers", 0), int(np.iinfo(np.uint32).max))
        nu = None if novelty is None else real_scalar(novelty, "novelty")
        out: NDArray[np.float64] = self._core.map_noise_at(count, nu)
        return out

    def retrieve_features(
        self,
        keypoints: ArrayLike,
        descriptors: ArrayLike,
        global_descriptor: ArrayLike | None = None,
        k: int = 5,
    ) -> list[int]:
        """The ``k`` keyframes most similar to a query, best first — the localizer's retrieval
        (bag of words, the network's global descriptor, or both verified, as the map was
        built): ``keypoints`` (N, 2) undistorted pixels, ``descriptors`` (N, W) as the
        keyframes', ``global_descriptor`` (D,) for a map built with a network."""
        descs = _local_descriptors(descriptors, "descriptors")
        kps = keypoint_rows(keypoints, "keypoints", len(descs))
        g = None if global_descriptor is None else _f32_rows(np.asarray(global_descriptor)[None], "global_descriptor")[0]
        # more than every keyframe is every keyframe (a count past the core's integer range too)
        count = min(_as_int(k, "k", 1), max(1, len(self)))
        return [int(i) for i in self._core.retrieve(kps, descs, g, count)]

    def __len__(self) -> int:
        return len(self._core)

    def __repr__(self) -> str:
        return f"Map({len(self)} keyframes, features={self._extractor!r}, retrieval={self._frontend['retrieval']!r})"

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the map to one ``.geoloc`` file, atomically (an interrupted save keeps the
        old file; a path that is one of the files the map was built from — the sequence's
        images, pose and list files, the retrieval network's model file — is refused, also
        through a symlink or a hard link)."""
        from ._io import check_output_path, refuse_alias

        target = check_output_path(path, "path")
        refuse_alias(target, "path", self._inputs)
        text = json.dumps(self._frontend, sort_keys=True, allow_nan=False)
        self._core.save(os.fspath(target), text)

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> Map:
        """Read a map written by :meth:`save`, checking it whole first: a truncated, corrupt or
        other-version file raises :class:`geoloc.exceptions.FileFormatError`. A map saved by
        the deprecated ``geoloc.localizer.FeatureMap`` loads as a map built from features."""
        from ._io import as_path, special_kind

        source = as_path(path, "path")
        kind = special_kind(source)
        if kind is not None:  # never opened: a FIFO would block the reader
            raise FileAccessError(f"{shown(source)}: cannot read the map: it is {kind}, not a regular file")
        core, text = _core.FeatureMap.load(os.fspath(source))
        loaded = cls._from_core(core, text, f"path: {shown(source)!r}")
        loaded._loaded_from = Path(source)
        return loaded

    def to_bytes(self) -> bytes:
        """The bytes :meth:`save` writes, in memory — a map sent to another process or kept in
        a database; :meth:`from_bytes` reads them back. A map pickles as these bytes."""
        text = json.dumps(self._frontend, sort_keys=True, allow_nan=False)
        data: bytes = self._core.to_bytes(text)
        return data

    @classmethod
    def from_bytes(cls, data: bytes | bytearray | memoryview) -> Map:
        """A map from :meth:`to_bytes`'s bytes (or a map file's, read whole), checked whole as
        :meth:`load` checks a file: truncated, corrupt or other-version bytes raise
        :class:`geoloc.exceptions.FileFormatError`."""
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise InvalidInputError(f"data: expected the bytes of a saved map, got {type(data).__name__}")
        try:
            core, text = _core.FeatureMap.from_bytes(bytes(data))
        except FileFormatError as exc:
            raise FileFormatError(f"data: {exc}") from None
        return cls._from_core(core, text, "data")

    def __reduce__(self) -> tuple[Any, ...]:
        # pickled as the file's bytes, with the files it was built from (a save over one of
        # them stays refused in the process that unpickles it)
        return (_unpickled_map, (self.to_bytes(), self._inputs))

    @classmethod
    def _from_core(cls, core: Any, text: str, source: str) -> Map:
        """The map of a core map and its frontend record ``text``, which must be of this version
        or absent (a FeatureMap file); ``source`` names where they were read from in messages
        (``path: 'room.geoloc'``, ``data``)."""
        frontend = json.loads(text)
        if not isinstance(frontend, dict) or frontend.get("version", FRONTEND_VERSION) != FRONTEND_VERSION:
            found = frontend.get("version") if isinstance(frontend, dict) else frontend
            raise FileFormatError(
                f"{source}: its frontend record (version {found!r}) was not written by this version of "
                f"geoloc's Python package, which reads version {FRONTEND_VERSION}"
            )
        if "version" not in frontend:  # a FeatureMap file: the caller's own settings, no frontend record
            warnings.warn(
                f"{source}: a map saved by the deprecated geoloc.localizer.FeatureMap; "
                "it loads as a map built from features (save it again to upgrade it)",
                DeprecationWarning,
                stacklevel=3,
            )
            frontend = {
                "version": FRONTEND_VERSION,
                "features": None,
                "camera": camera_record(Camera(*core.intrinsics)),
                "retrieval": core.retrieval,
                "source": {"keyframes": len(core)},
            }
        extractor, camera = frontend_parts(frontend, core.intrinsics, source)
        return cls(core, camera, extractor, frontend)


def _unpickled_map(data: bytes, inputs: tuple[tuple[str, Path], ...]) -> Map:
    """The map :meth:`Map.__reduce__` pickled."""
    unpickled = Map.from_bytes(data)
    unpickled._inputs = inputs
    return unpickled


def __getattr__(name: str) -> Any:
    """The deprecated names ``geoloc.mapping.Localizer`` and ``geoloc.mapping.MapLocalization``
    (now ``geoloc.Localizer`` and ``geoloc.Localization``), for one release. Resolved on use,
    so this module does not import the localizer."""
    if name in ("Localizer", "MapLocalization"):
        import importlib

        new = "Localizer" if name == "Localizer" else "Localization"
        warnings.warn(f"geoloc.mapping.{name} is deprecated; use geoloc.{new}", DeprecationWarning, stacklevel=2)
        return getattr(importlib.import_module(f"{__package__}.localizer"), new)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
