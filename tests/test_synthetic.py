"""The synthetic room: exact geometry, determinism, image options, feature richness, and a
quick end-to-end localization with ORB and the feature-level localizer."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

import geoloc
from geoloc import datasets, lie
from geoloc.datasets.synthetic import SyntheticRoom, room_trajectory
from geoloc.features import FeatureExtractor
from geoloc import Localizer, Map

cv2 = pytest.importorskip("cv2")

N_RAYS = 400
INV_DEPTH_RTOL = 1e-4  # float32 inverse depth
EDGE_PIXEL_FRACTION = 0.02  # pixels on a surface boundary may pick either surface
MIN_ORB_PER_FRAME = 900  # of 1000 requested
MIN_ORB_PER_QUADRANT = 50  # 5 % of the features: corners everywhere, not in one corner
MAX_STEP_M = 0.1
MAX_STEP_DEG = 5.0
REVISIT_DISTANCE_M = 0.35
LOCALIZATION_MEDIAN_M = 0.01
LOCALIZATION_MEDIAN_DEG = 0.3


def _ray_cast_inverse_depth(room: SyntheticRoom, pose: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Reference: intersect each pixel's ray with every rectangle, keep the nearest hit."""
    cam = room.camera
    rays_cam = np.column_stack([(pixels[:, 0] - cam.cx) / cam.fx, (pixels[:, 1] - cam.cy) / cam.fy, np.ones(len(pixels))])
    rays = rays_cam @ pose[:3, :3].T  # world directions, z_cam = 1
    centre = pose[:3, 3]
    best = np.full(len(pixels), np.inf)
    for rect in room.rects:
        n = rect.normal
        denom = rays @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = ((rect.origin - centre) @ n) / denom
        hit = centre + depth[:, None] * rays
        h, w = rect.texture.shape[:2]
        a = (hit - rect.origin) @ rect.u * rect.texels_per_m
        b = (hit - rect.origin) @ rect.v * rect.texels_per_m
        inside = (depth > 0) & (a >= 0) & (a <= w) & (b >= 0) & (b <= h)
        best = np.where(inside & (depth < best), depth, best)
    return 1.0 / best


def test_render_matches_ray_casting() -> None:
    room = SyntheticRoom(0)
    rng = np.random.default_rng(0)
    for pose in room_trajectory(300)[::37]:
        _, inv_depth = room.render(pose)
        pixels = rng.integers([0, 0], [640, 480], (N_RAYS, 2))
        reference = _ray_cast_inverse_depth(room, pose, pixels.astype(np.float64))
        rendered = inv_depth[pixels[:, 1], pixels[:, 0]]
        mismatched = ~np.isclose(rendered, reference, rtol=INV_DEPTH_RTOL)
        assert mismatched.mean() <= EDGE_PIXEL_FRACTION


def test_deterministic_options_and_timing() -> None:
    a = datasets.synthetic_room(n_frames=50, seed=0)
    b = datasets.synthetic_room(n_frames=50, seed=0)
    assert a[7].image.tobytes() == b[7].image.tobytes()
    assert a[7].image.tobytes() != datasets.synthetic_room(n_frames=50, seed=1)[7].image.tobytes()
    noisy = datasets.synthetic_room(n_frames=50, noise=4.0, blur=1.0, lighting=(0.7, 20.0))
    assert noisy[7].image.tobytes() == datasets.synthetic_room(n_frames=50, noise=4.0, blur=1.0, lighting=(0.7, 20.0))[7].image.tobytes()
    clean, dim = a[7].image.astype(float), noisy[7].image.astype(float)
    assert abs(dim.mean() - (0.7 * clean.mean() + 20.0)) < 2.0  # gain/offset, noise is zero-mean
    assert np.array_equal(noisy.poses, a.poses)  # options change pixels only
    times = []
    for k in range(0, 50, 5):
        start = time.perf_counter()
        a[k]
        times.append(time.perf_counter() - start)
    print(f"\nsynthetic room: {1000 * np.median(times):.1f} ms per 640×480 frame (median of {len(times)})")


def test_trajectory_is_smooth_and_revisits() -> None:
    poses = room_trajectory(300)
    step = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    turn = np.degrees(lie.rotation_angle(np.einsum("nji,njk->nik", poses[:-1, :3, :3], poses[1:, :3, :3])))
    assert step.max() < MAX_STEP_M and turn.max() < MAX_STEP_DEG
    first, second = poses[:150, :3, 3], poses[150:, :3, 3]
    nearest = np.linalg.norm(second[:, None] - first[None], axis=2).min(axis=1)
    assert nearest.max() < REVISIT_DISTANCE_M
    assert np.abs(second[:, 2] - first[:, 2]).max() > 0.1  # ... but from another height


def test_every_view_is_rich_in_orb_corners() -> None:
    seq = datasets.synthetic_room(n_frames=300)
    extract = FeatureExtractor()
    counts = []
    for frame in seq[::20]:
        f = extract(frame.image, seq.camera)
        counts.append(len(f))
        assert len(f) >= MIN_ORB_PER_FRAME, frame.index
        quadrant = (f.keypoints[:, 0] >= 320).astype(int) + 2 * (f.keypoints[:, 1] >= 240).astype(int)
        assert np.bincount(quadrant, minlength=4).min() >= MIN_ORB_PER_QUADRANT, frame.index
    print(f"\nORB per synthetic frame: median {np.median(counts):.0f}, min {min(counts)}")


def test_bad_arguments() -> None:
    for kwargs, name in (
        ({"n_frames": 0}, "n_frames"),
        ({"seed": -1}, "seed"),
        ({"noise": -1.0}, "noise"),
        ({"blur": float("nan")}, "blur"),
        ({"lighting": (0.0, 0.0)}, "lighting"),
        ({"lighting": 2.0}, "lighting"),
    ):
        with pytest.raises(geoloc.InvalidInputError, match=name):
            datasets.synthetic_room(**kwargs)  # type: ignore[arg-type]


def test_held_out_frames_localize_to_a_centimetre() -> None:
    """Map from lap 1 (every 2nd frame), localize lap-2 frames, history reset before each
    (the geometric path alone). ~6 s: the one end-to-end check of the image pipeline."""
    seq = datasets.synthetic_room(n_frames=300)
    extract = FeatureExtractor()
    train = seq[0:150:2]
    feats = [extract(f.image, seq.camera) for f in train]
    assert train.poses is not None
    feature_map = Map.from_features(seq.camera, train.poses, [f.keypoints for f in feats], [f.descriptors for f in feats], estimate_noise=False, refine_intrinsics=False, adjust_labels=False)
    localizer = Localizer(feature_map)
    trans, rot = [], []
    for frame in seq[155:300:15]:
        f = extract(frame.image, seq.camera)
        localizer.reset()
        r = localizer.localize_features(frame.timestamp, f.keypoints, f.descriptors)
        assert r.pose is not None and frame.pose is not None, (frame.index, r.reason)
        t_err, r_err = geoloc.evaluation.pose_errors(r.pose, frame.pose)
        trans.append(t_err[0])
        rot.append(r_err[0])
    print(f"\nsynthetic held-out frames: median {1000 * np.median(trans):.1f} mm / {np.median(rot):.3f}°, max {1000 * max(trans):.1f} mm")
    assert np.median(trans) <= LOCALIZATION_MEDIAN_M and np.median(rot) <= LOCALIZATION_MEDIAN_DEG
    assert math.isfinite(max(trans))
