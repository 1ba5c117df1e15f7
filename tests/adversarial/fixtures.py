"""Worker-side fixtures, built once per worker process and cached (``("cached", name)``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np


def small_room(tmp: Path) -> Any:
    import geoloc

    return geoloc.datasets.synthetic_room(n_frames=12, seed=0)


def _small_room_map(**options: Any) -> Any:
    """A map of the first 10 frames of a 12-frame synthetic room, built with ``options``."""
    import geoloc

    seq = geoloc.datasets.synthetic_room(n_frames=12, seed=0)
    return geoloc.Map.build(seq[:10], n_features=300, branching=4, depth=2, **options)


def small_map(tmp: Path) -> Any:
    return _small_room_map()


def small_map_labels_kept(tmp: Path) -> Any:
    """The small map built without adjusting its labels: it has a label adjustment problem to give."""
    return _small_room_map(adjust_labels=False)


def small_map_file(tmp: Path) -> str:
    m = small_map(tmp)
    path = tmp / "small.geoloc"
    m.save(path)
    return str(path)


def small_dataset_dir(tmp: Path) -> str:
    """A small TUM RGB-D folder (written by Sequence.write_tum)."""
    import geoloc

    seq = geoloc.datasets.synthetic_room(n_frames=4, seed=1)
    return str(seq.write_tum(tmp / "tum-ds"))


def feature_map(tmp: Path) -> Any:
    """Three keyframes 15 cm apart seeing the same 40 landmarks 3–5 m away (each landmark keeps
    its descriptor): a map whose 3D model has points, so the default (model) locator serves it."""
    from geoloc import Camera, Map

    rng = np.random.default_rng(0)
    camera = Camera(525, 525, 320, 240)
    poses = np.repeat(np.eye(4)[None], 3, axis=0)
    poses[:, 0, 3] = [0.0, 0.15, 0.3]
    depth = rng.uniform(3.0, 5.0, 40)
    landmarks = np.stack([rng.uniform(-0.4, 0.4, 40) * depth, rng.uniform(-0.3, 0.3, 40) * depth, depth], axis=1)
    descs = rng.integers(0, 256, size=(40, 32), dtype=np.uint8)
    kps = []
    for pose in poses:
        cam = landmarks - pose[:3, 3]  # the keyframes look along +z, unrotated
        kps.append(np.stack([525 * cam[:, 0] / cam[:, 2] + 320, 525 * cam[:, 1] / cam[:, 2] + 240], axis=1))
    return Map.from_features(camera, poses, kps, [descs] * 3, branching=3, depth=2, estimate_noise=False, refine_intrinsics=False, adjust_labels=False)


def onnx_model(tmp: Path) -> str:
    """A tiny ONNX descriptor exported with geoloc.training (the parent skips these cases
    when torch is missing)."""
    import torch

    from geoloc.training.export import export_onnx
    from geoloc.training.network import build_network

    torch.manual_seed(0)
    path = tmp / "tiny.onnx"
    export_onnx(build_network("tiny", 32), path, quiet=True)
    return str(path)


def onnx_descriptor(tmp: Path) -> Any:
    from geoloc import OnnxDescriptor

    return OnnxDescriptor(onnx_model(tmp))


def adjust(intrinsics: Any, labels: Any, points: Any, obs_keyframes: Any, obs_points: Any, obs_pixels: Any,
           obs_sigmas: Any) -> Any:
    """geoloc.adjustment.bundle_adjust of the problem these fields make (σ given: one round
    pair, no estimate), so that a case can mutate a field of the problem."""
    from geoloc.adjustment import AdjustmentProblem, bundle_adjust

    problem = AdjustmentProblem(intrinsics, labels, points, obs_keyframes, obs_points, obs_pixels, obs_sigmas)
    return bundle_adjust(problem, label_sigma=(0.02, 0.02), max_iterations=10)
