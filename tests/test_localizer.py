"""The feature-level localizer on a small simulated sequence (a tiny version of the Rust test)."""

from __future__ import annotations

import numpy as np
import pytest

import geoloc
from geoloc import lie
from geoloc import Localization, Localizer, Map
from geoloc.montecarlo import look_at

CAM = geoloc.Camera(525, 525, 320, 240)


def _walk(t: float, offset: float) -> np.ndarray:
    c = np.array([-1.5 + 0.6 * t, offset + 0.05 * np.sin(2 * t), 0.0])
    return look_at(c, c + np.array([0.1 * np.sin(1.3 * t), 0.0, 5.0]))


def _observe(rng: np.random.Generator, pose: np.ndarray, pts: np.ndarray, desc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p = lie.se3_transform_points(lie.se3_inverse(pose), pts)
    uv = p[:, :2] / p[:, 2:] * 525 + [320, 240]
    ok = (p[:, 2] > 0.5) & (uv[:, 0] >= 0) & (uv[:, 0] < 640) & (uv[:, 1] >= 0) & (uv[:, 1] < 480)
    d = desc[ok].copy()
    flips = rng.integers(0, 256, size=(len(d), 3))
    for k in range(3):
        d[np.arange(len(d)), flips[:, k] // 8] ^= (1 << (flips[:, k] % 8)).astype(np.uint8)
    return uv[ok] + 0.5 * rng.normal(size=(ok.sum(), 2)), d


@pytest.fixture(scope="module")
def feature_map() -> tuple[Map, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    pts = rng.uniform([-4, -1.5, 3], [4, 1.5, 7], (800, 3))
    desc = rng.integers(0, 256, (800, 32), dtype=np.uint8)
    poses = np.stack([_walk(0.1 * i, 0.0) for i in range(40)])
    obs = [_observe(rng, p, pts, desc) for p in poses]
    m = Map.from_features(CAM, poses, [o[0] for o in obs], [o[1] for o in obs], branching=8, depth=2, estimate_noise=False, refine_intrinsics=False, adjust_labels=False)
    return m, pts, desc


def test_sequence_is_localized_with_fusion(feature_map: tuple[Map, np.ndarray, np.ndarray]) -> None:
    m, pts, desc = feature_map
    rng = np.random.default_rng(1)
    loc = Localizer(m)
    errors, sources = [], []
    for f in range(30):
        t = 0.3 + f / 30
        truth = _walk(t, 0.15)
        kp, d = _observe(rng, truth, pts, desc)
        r = loc.localize_features(t, kp, d)
        assert r.pose is not None and r.covariance is not None
        errors.append(np.linalg.norm(r.pose[:3, 3] - truth[:3, 3]))
        sources.append(r.source)
        assert set(r.timings) >= {"retrieval", "pnp", "total"}
    assert np.median(errors) < 0.01
    assert sources[0] == "geometric" and sources.count("fused") > 20


def test_bad_frames_and_maps(feature_map: tuple[Map, np.ndarray, np.ndarray]) -> None:
    m, _, _ = feature_map
    loc = Localizer(m)
    with pytest.raises(geoloc.InvalidInputError, match=r"keypoints: expected shape \(3, 2\)"):
        loc.localize_features(0.0, np.zeros((2, 2)), np.zeros((3, 32), dtype=np.uint8))
    with pytest.raises(geoloc.InvalidInputError, match="the vocabulary is for binary"):
        loc.localize_features(0.0, np.zeros((3, 2)), np.zeros((3, 32), dtype=np.float32))
    with pytest.raises(geoloc.InvalidInputError, match="retrieval"):
        Map.from_features(CAM, np.eye(4)[None], [np.zeros((1, 2))], [np.zeros((1, 32), dtype=np.uint8)], retrieval="ann", estimate_noise=False, refine_intrinsics=False, adjust_labels=False)  # type: ignore[arg-type]
    for kind in ("global", "fused"):
        with pytest.raises(geoloc.InvalidInputError, match=f"^global_descriptors: retrieval='{kind}' retrieves by them, and none were given"):
            Map.from_features(CAM, np.eye(4)[None], [np.zeros((1, 2))], [np.zeros((1, 32), dtype=np.uint8)], retrieval=kind, estimate_noise=False, refine_intrinsics=False, adjust_labels=False)  # type: ignore[arg-type]
    with pytest.raises(geoloc.InvalidInputError, match="history"):
        Localizer(m, history=1)


def test_pixel_sigmas_are_checked_by_name_and_used(feature_map: tuple[Map, np.ndarray, np.ndarray]) -> None:
    m, pts, desc = feature_map
    rng = np.random.default_rng(5)
    kp, d = _observe(rng, _walk(0.5, 0.1), pts, desc)
    loc = Localizer(m)
    n = len(kp)
    for bad, match in [
        (np.ones(n - 1), r"pixel_sigmas: expected shape"),
        (np.ones((n, 1)), r"pixel_sigmas: expected shape"),
        (np.r_[np.ones(n - 1), np.nan], r"pixel_sigmas\[\d+\] is not finite"),
        (np.r_[np.ones(n - 1), 0.0], r"pixel_sigmas: entry \d+ must be finite and > 0"),
        (np.r_[-np.ones(n - 1), 1.0], r"pixel_sigmas: entry 0 must be finite and > 0"),
        (np.array(["a"] * n), r"pixel_sigmas: expected real numbers"),
    ]:
        with pytest.raises(geoloc.InvalidInputError, match=match):
            loc.localize_features(0.5, kp, d, pixel_sigmas=bad)
    # ones are the uniform solve; 4 px on every query keypoint widens the covariance
    plain = Localizer(m).localize_features(0.5, kp, d)
    ones = Localizer(m).localize_features(0.5, kp, d, pixel_sigmas=np.ones(n))
    fours = Localizer(m).localize_features(0.5, kp, d, pixel_sigmas=np.full(n, 4.0))
    assert plain.covariance is not None and ones.covariance is not None and fours.covariance is not None
    assert ones.pose is not None and plain.pose is not None
    np.testing.assert_allclose(ones.pose, plain.pose, atol=1e-9)
    np.testing.assert_allclose(ones.covariance, plain.covariance, rtol=1e-6, atol=1e-14)
    assert np.all(np.diag(fours.covariance) > 1.5 * np.diag(plain.covariance))


def test_timestamps_must_increase(feature_map: tuple[Map, np.ndarray, np.ndarray]) -> None:
    m, pts, desc = feature_map
    rng = np.random.default_rng(2)
    loc = Localizer(m)
    kp, d = _observe(rng, _walk(0.5, 0.1), pts, desc)
    assert loc.localize_features(0.5, kp, d).source == "geometric"
    with pytest.raises(geoloc.InvalidInputError, match="timestamp: must be finite and increase"):
        loc.localize_features(0.5, kp, d)
    loc.reset()
    assert loc.localize_features(0.4, kp, d).source == "geometric"


def _tiny_map_inputs() -> tuple[np.ndarray, list[np.ndarray], list[np.ndarray]]:
    rng = np.random.default_rng(4)
    poses = np.stack([_walk(0.1 * i, 0.0) for i in range(3)])
    kps = [rng.uniform(0, 400, (20, 2)) for _ in range(3)]
    descs = [rng.integers(0, 256, (20, 32), dtype=np.uint8) for _ in range(3)]
    return poses, kps, descs


def test_map_refuses_bad_input_by_name() -> None:
    """Each raises InvalidInputError naming the argument."""
    poses, kps, descs = _tiny_map_inputs()
    with pytest.raises(geoloc.InvalidInputError, match=r"^depth: "):
        Map.from_features(CAM, poses, kps, descs, branching=2, depth=100000, estimate_noise=False, refine_intrinsics=False, adjust_labels=False)
    with pytest.raises(geoloc.InvalidInputError, match=r"^branching: "):
        Map.from_features(CAM, poses, kps, descs, branching=-1, estimate_noise=False, refine_intrinsics=False, adjust_labels=False)
    with pytest.raises(geoloc.InvalidInputError, match=r"^seed: "):
        Map.from_features(CAM, poses, kps, descs, seed=2**70, estimate_noise=False, refine_intrinsics=False, adjust_labels=False)
    covs = np.stack([np.eye(6) * 1e-4] * 3)
    covs[1, 2, 2] = -1e-4  # negative variance: used to turn every later frame into "lost"
    with pytest.raises(geoloc.InvalidInputError, match=r"^pose_covariances\[1\]: .*positive semi-definite"):
        Map.from_features(CAM, poses, kps, descs, pose_covariances=covs, estimate_noise=False, refine_intrinsics=False, adjust_labels=False)
    covs = np.stack([np.eye(6) * 1e-4] * 3)
    covs[2, 0, 1] = 1e-5
    with pytest.raises(geoloc.InvalidInputError, match=r"^pose_covariances\[2\]: .*symmetric"):
        Map.from_features(CAM, poses, kps, descs, pose_covariances=covs, estimate_noise=False, refine_intrinsics=False, adjust_labels=False)
    # a float64 descriptor beyond float32's range is refused at construction, not in localize
    fdescs = [np.ones((20, 8)) for _ in range(3)]
    fdescs[1][3, 0] = 1e39
    with pytest.raises(geoloc.InvalidInputError, match=r"^descriptors\[1\]\[3\] overflows float32"):
        Map.from_features(CAM, poses, kps, fdescs, estimate_noise=False, refine_intrinsics=False, adjust_labels=False)


def test_global_descriptor_shape_and_name() -> None:
    """A (2, D) global_descriptor was silently flattened, and a wrong length was
    reported as 'queries'."""
    poses, kps, descs = _tiny_map_inputs()
    g = np.random.default_rng(5).normal(size=(3, 4)).astype(np.float32)
    m = Map.from_features(CAM, poses, kps, descs, global_descriptors=g, retrieval="global", estimate_noise=False, refine_intrinsics=False, adjust_labels=False)
    loc = Localizer(m, locator="paper")  # random keypoints: no 3D model for the model locator
    with pytest.raises(geoloc.InvalidInputError, match=r"^global_descriptor: expected shape \(D,\)"):
        loc.localize_features(0.0, kps[0], descs[0], np.zeros((2, 2), np.float32))
    with pytest.raises(geoloc.InvalidInputError, match=r"^global_descriptor: expected 4 values, got 3"):
        loc.localize_features(0.0, kps[0], descs[0], np.zeros(3, np.float32))
    r = loc.localize_features(0.0, kps[0], descs[0], g[2])
    assert r.keyframe == 2


def test_a_map_refuses_descriptors_wider_than_a_frame_stream_carries() -> None:
    """5000-byte descriptors built a map that Python localized and geoloc-rs could not: every
    frame of its stream was refused ("descriptor width 5000 is not in 1..=4096")."""
    poses, kps, descs = _tiny_map_inputs()
    plain = {"estimate_noise": False, "refine_intrinsics": False, "adjust_labels": False, "branching": 2, "depth": 2}
    wide = [np.tile(d, (1, 4096 // 32 + 1))[:, :4097] for d in descs]
    with pytest.raises(geoloc.InvalidInputError, match=r"^descriptors: width 4097 is beyond the 4096 a frame stream carries"):
        Map.from_features(CAM, poses, kps, wide, **plain)
    Map.from_features(CAM, poses, kps, [w[:, :4096] for w in wide], **plain)  # the widest a stream carries
    long_global = np.ones((3, 2**16 + 1), np.float32)
    with pytest.raises(geoloc.InvalidInputError, match=r"^global_descriptors: length 65537 is beyond the 65536"):
        Map.from_features(CAM, poses, kps, descs, global_descriptors=long_global, retrieval="global", **plain)


def test_a_bool_is_no_number_for_an_option_or_an_intrinsic() -> None:
    """``Localizer(top_k=True)`` ran with top_k = 1 and ``Camera(True, …)`` with fx = 1."""
    poses, kps, descs = _tiny_map_inputs()
    m = Map.from_features(CAM, poses, kps, descs, branching=2, depth=2, estimate_noise=False, refine_intrinsics=False, adjust_labels=False)
    for name in ("top_k", "history", "pixel_sigma", "max_residual", "gate_sigma"):
        with pytest.raises(geoloc.InvalidInputError, match=rf"^{name}: expected .*bool"):
            Localizer(m, locator="paper", **{name: True})
    for name in ("fx", "fy", "cx", "cy", "width", "height"):
        values = {"fx": 500.0, "fy": 500.0, "cx": 320.0, "cy": 240.0, "width": 640, "height": 480, name: np.True_}
        with pytest.raises(geoloc.InvalidInputError, match=rf"^{name}: expected"):
            geoloc.Camera(**values)


def test_a_camera_other_than_the_maps_is_refused_whatever_differs() -> None:
    """Only fx, fy, cx, cy were compared: a camera with another distortion was accepted and
    corrected the queries with it (7.7 cm off instead of 0.4 cm), one of another image size
    refused every image of the map's size later."""
    poses, kps, descs = _tiny_map_inputs()
    m = Map.from_features(CAM, poses, kps, descs, branching=2, depth=2, estimate_noise=False, refine_intrinsics=False, adjust_labels=False)
    c = m.camera
    Localizer(m, geoloc.Camera(c.fx, c.fy, c.cx, c.cy, width=c.width, height=c.height), locator="paper")  # the same camera
    for other, what in [
        (geoloc.Camera(c.fx, c.fy, c.cx, c.cy, width=c.width, height=c.height, dist=(0.3, -0.2, 0, 0, 0)), "distortion"),
        (geoloc.Camera(c.fx, c.fy, c.cx, c.cy, width=2 * c.width, height=2 * c.height), "image size"),
        (geoloc.Camera(c.fx + 1, c.fy, c.cx, c.cy, width=c.width, height=c.height), "intrinsics"),
    ]:
        with pytest.raises(geoloc.InvalidInputError, match=rf"^camera: not the map's camera — {what} "):
            Localizer(m, other, locator="paper")


def test_global_descriptors_are_used_or_refused_never_ignored() -> None:
    """from_features(global_descriptors=G) without retrieval= built a bag-of-words map and
    dropped G; a network given to the localizer of a bag-of-words map ran on every query for
    nothing. G now makes the map fused (as Map.build with a network), retrieval='bow' with G,
    a network for a bag-of-words map and a frame's global descriptor for one are refused by name."""
    poses, kps, descs = _tiny_map_inputs()
    plain = {"branching": 2, "depth": 2, "estimate_noise": False, "refine_intrinsics": False, "adjust_labels": False}
    g = np.random.default_rng(5).normal(size=(3, 16)).astype(np.float32)
    assert Map.from_features(CAM, poses, kps, descs, global_descriptors=g, **plain).settings["retrieval"] == "fused"
    assert Map.from_features(CAM, poses, kps, descs, **plain).settings["retrieval"] == "bow"
    with pytest.raises(geoloc.InvalidInputError, match=r"^global_descriptors: given with retrieval='bow'"):
        Map.from_features(CAM, poses, kps, descs, global_descriptors=g, retrieval="bow", **plain)
    bow = Map.from_features(CAM, poses, kps, descs, **plain)
    with pytest.raises(geoloc.InvalidInputError, match=r"^global_descriptor: this map retrieves by bag of words alone"):
        Localizer(bow, global_descriptor=lambda images: np.zeros((len(images), 16), np.float32), locator="paper")
    # ... and so is a frame's global descriptor, which that map would drop
    loc = Localizer(bow, locator="paper")
    with pytest.raises(geoloc.InvalidInputError, match=r"^global_descriptor: this map retrieves by bag of words alone"):
        loc.localize_features(0.0, kps[0], descs[0], global_descriptor=g[0])
    assert isinstance(loc.localize_features(0.0, kps[0], descs[0]), geoloc.Localization)  # without it: accepted


def test_a_network_that_misbehaves_is_named_as_the_argument_that_gave_it() -> None:
    """Text from the network was a bare ValueError, a wrong row count named
    `global_descriptors` (never passed), an array instead of a network a TypeError at the
    first frame, no rows an IndexError."""
    room = geoloc.datasets.synthetic_room(n_frames=30)
    net = lambda images: np.stack([np.resize(i[::60, ::80].astype(np.float32).ravel(), 8) for i in images])  # noqa: E731
    bad = [
        (lambda images: np.array([["a"] * 8 for _ in images]), "values that are not numbers"),
        (lambda images: np.ones((len(images) - 1, 8)), r"shape \(9, 8\) for 10 images"),
        (lambda images: np.ones((len(images), 0)), r"shape \(10, 0\)"),
    ]
    for network, message in bad:
        with pytest.raises(geoloc.InvalidInputError, match=rf"^retrieval: the network returned {message}"):
            Map.build(room, retrieval=network, keyframe_step=3)
    m = Map.build(room, retrieval=net, keyframe_step=3)
    with pytest.raises(geoloc.InvalidInputError, match=r"^global_descriptor: expected a network, .* got ndarray"):
        Localizer(m, global_descriptor=np.ones(8))
    with pytest.raises(geoloc.InvalidInputError, match=r"^global_descriptor: the network returned shape \(0, 8\) for 1 images"):
        Localizer(m, global_descriptor=lambda images: np.zeros((0, 8))).localize(room.gray(4), 1.0)
    assert Localizer(m, global_descriptor=net).localize(room.gray(4), 1.0).source in ("geometric", "lost")


def test_integer_like_options() -> None:
    """Localizer(history=np.int64(5)) was refused."""
    poses, kps, descs = _tiny_map_inputs()
    m = Map.from_features(CAM, poses, kps, descs, branching=np.int64(2), depth=np.int32(2), seed=np.uint64(1), estimate_noise=False, refine_intrinsics=False, adjust_labels=False)
    Localizer(m, history=np.int64(5), locator="paper")  # random keypoints: no 3D model for the model locator
    with pytest.raises(geoloc.InvalidInputError, match=r"^history: "):
        Localizer(m, history=-3)
    with pytest.raises(geoloc.InvalidInputError, match=r"^history: "):
        Localizer(m, history=2**70)
    with pytest.raises(geoloc.InvalidInputError, match=r"^locator: the map's 3D model has 0 points"):
        Localizer(m)


def test_descriptors_of_an_integer_type_other_than_uint8_are_named_as_such(feature_map: tuple[Map, np.ndarray, np.ndarray]) -> None:
    """int64 descriptors (a plain list of ints) were read as float rows and refused as "the
    vocabulary is for binary descriptors of width 32": the width was right, the type was not."""
    m, pts, desc = feature_map
    kp, d = _observe(np.random.default_rng(3), _walk(0.5, 0.1), pts, desc)
    loc = Localizer(m)
    for wrong in (d.astype(np.int64), d.tolist(), d.astype(bool)):
        with pytest.raises(geoloc.InvalidInputError, match=r"^descriptors: expected uint8 rows .* got (int64|bool)"):
            loc.localize_features(0.5, kp, wrong)
    assert loc.localize_features(0.5, kp, d).source == "geometric"


def test_a_sequence_error_names_the_frame() -> None:
    """A timestamp that does not increase was "timestamp: must be finite and increase, got
    63", naming no frame of the sequence."""
    room = geoloc.datasets.synthetic_room(n_frames=12, seed=0)
    m = Map.build(room[:10], n_features=300, branching=4, depth=2)

    class Backwards:
        """Frames 10 and 11 of the room, their times swapped."""

        name, indices, timestamps = "room", np.array([10, 11]), room.timestamps[[11, 10]]

        def __len__(self) -> int:
            return 2

        def gray(self, i: int) -> np.ndarray:
            return room.gray(10 + i)

    with pytest.raises(geoloc.InvalidInputError, match=r"^timestamp: must be finite and increase.*\(frame 11 of 'room', position 1\)$"):
        Localizer(m).localize_sequence(Backwards(), "sequential")


def test_result_is_a_typed_class(feature_map: tuple[Map, np.ndarray, np.ndarray]) -> None:
    m, pts, desc = feature_map
    kp, d = _observe(np.random.default_rng(3), _walk(0.5, 0.1), pts, desc)
    r = Localizer(m).localize_features(0.5, kp, d)
    assert isinstance(r, Localization)
    assert r.pose is not None and r.pose.shape == (4, 4) and r.covariance is not None and r.covariance.shape == (6, 6)
    assert r.source == "geometric" and r.inliers > 0 and isinstance(r.keyframe, int)


# the camera that really took the pictures of test_refine_intrinsics: 1-3 % off the nominal CAM,
# with a lens distortion (OpenCV's k1, k2, p1, p2, k3)
_REAL_K = (516.0, 529.0, 314.0, 243.0)
_REAL_DIST = np.array([-0.06, 0.02, 0.004, -0.003, 0.0])


def _turning(t: float, offset: float) -> np.ndarray:
    """Walking along x while looking ±20° left and right (the turns make the focal length observable)."""
    c = np.array([-2.0 + 0.6 * t, offset, 0.0])
    yaw, pitch = 0.35 * np.sin(1.3 * t), 0.12 * np.cos(0.7 * t)
    return look_at(c, c + np.array([5 * np.tan(yaw), 5 * np.tan(pitch), 5.0]))


def _observe_real(rng: np.random.Generator, pose: np.ndarray, pts: np.ndarray, desc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What the real camera records (cv2.projectPoints with its distortion), 0.5 px noise."""
    import cv2

    p = lie.se3_transform_points(lie.se3_inverse(pose), pts)
    front = p[:, 2] > 0.5
    fx, fy, cx, cy = _REAL_K
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    uv = cv2.projectPoints(p[front], np.zeros(3), np.zeros(3), K, _REAL_DIST)[0].reshape(-1, 2)
    ok = (uv[:, 0] >= 0) & (uv[:, 0] < 640) & (uv[:, 1] >= 0) & (uv[:, 1] < 480)
    return uv[ok] + 0.5 * rng.normal(size=(ok.sum(), 2)), desc[front][ok].copy()


@pytest.mark.slow
def test_refine_intrinsics_finds_the_real_camera_and_localizes_better() -> None:
    rng = np.random.default_rng(3)
    pts = rng.uniform([-10, -1.5, 3], [10, 1.5, 6], (3000, 3))
    desc = rng.integers(0, 256, (3000, 32), dtype=np.uint8)
    poses = np.stack([_turning(0.1 * i, 0.0) for i in range(90)])
    obs = [_observe_real(rng, p, pts, desc) for p in poses]
    maps = {
        refine: Map.from_features(CAM, poses, [o[0] for o in obs], [o[1] for o in obs], branching=8, depth=3, refine_intrinsics=refine, estimate_noise=False, adjust_labels=False)
        for refine in (False, True)
    }
    assert maps[False].self_calibration is None
    sc = maps[True].self_calibration
    assert sc is not None and sc["reason"] == "ok", sc
    got = [sc["camera"][k] for k in ("fx", "fy", "cx", "cy")]
    np.testing.assert_allclose(got, _REAL_K, atol=2.0)
    assert sc["rms_after_px"] < 0.5 * sc["rms_before_px"] and sc["correction_sigma_px"] < 0.5
    errors = {}
    for refine, m in maps.items():
        loc = Localizer(m)
        e = []
        for i in range(30):
            truth = _turning(0.35 + 0.25 * i, 0.15)
            kp, d = _observe_real(rng, truth, pts, desc)
            loc.reset()
            r = loc.localize_features(float(i), kp, d)
            e.append(np.inf if r.pose is None else np.linalg.norm(r.pose[:3, 3] - truth[:3, 3]))
        errors[refine] = float(np.median(e))
    assert errors[True] < 0.5 * errors[False], errors


def test_refine_intrinsics_options_are_checked_and_a_weak_map_says_why(
    feature_map: tuple[Map, np.ndarray, np.ndarray], tmp_path: pytest.TempPathFactory
) -> None:
    rng = np.random.default_rng(4)
    pts = rng.uniform([-4, -1.5, 3], [4, 1.5, 7], (300, 3))
    desc = rng.integers(0, 256, (300, 32), dtype=np.uint8)
    poses = np.stack([_walk(0.1 * i, 0.0) for i in range(5)])
    obs = [_observe(rng, p, pts, desc) for p in poses]
    args = (CAM, poses, [o[0] for o in obs], [o[1] for o in obs])
    for bad in ("fisheye", 3):
        with pytest.raises(geoloc.InvalidInputError, match="intrinsics_model: expected one of"):
            Map.from_features(*args, branching=4, depth=2, refine_intrinsics=True, intrinsics_model=bad, estimate_noise=False, adjust_labels=False)  # type: ignore[arg-type]
    weak = Map.from_features(*args, branching=4, depth=2, refine_intrinsics=True, estimate_noise=False, adjust_labels=False)
    sc = weak.self_calibration
    assert sc is not None and "camera" not in sc and sc["reason"] != "ok", sc
    # what was found is stored in the map file
    path = tmp_path / "weak.geoloc"  # type: ignore[operator]
    weak.save(path)
    assert Map.load(path).self_calibration == sc


def test_fused_retrieval_keeps_bow_against_a_misleading_network_and_round_trips(tmp_path) -> None:
    """A map built with global descriptors and ``retrieval="fused"``: a network that points
    at a far keyframe cannot displace the keyframe BoW finds (two-view verification of the
    query's matches decides); an honest one agrees; the map saves and loads as fused; a query
    without its global descriptor, or with keypoints and descriptors that disagree, is
    refused by name."""
    rng = np.random.default_rng(0)
    pts = rng.uniform([-4, -1.5, 3], [4, 1.5, 7], (800, 3))
    desc = rng.integers(0, 256, (800, 32), dtype=np.uint8)
    poses = np.stack([_walk(0.25 * i, 0.0) for i in range(20)])
    obs = [_observe(rng, p, pts, desc) for p in poses]
    g = np.stack([[p[0, 3] / 10, 0.0] for p in poses]).astype(np.float32)  # a "network": position along the walk
    common = dict(branching=8, depth=3, estimate_noise=False, refine_intrinsics=False, adjust_labels=False, model=False)
    fused = Map.from_features(CAM, poses, [o[0] for o in obs], [o[1] for o in obs], global_descriptors=g, retrieval="fused", **common)
    bow = Map.from_features(CAM, poses, [o[0] for o in obs], [o[1] for o in obs], **common)
    net = Map.from_features(CAM, poses, [o[0] for o in obs], [o[1] for o in obs], global_descriptors=g, retrieval="global", **common)
    truth = _walk(2.4, 0.15)
    kp, d = _observe(rng, truth, pts, desc)
    distance = np.linalg.norm(poses[:, :3, 3] - truth[:3, 3], axis=1)
    far = g[int(np.argmax(distance))]
    assert net.retrieve_features(kp, d, far, k=1) == [int(np.argmax(distance))]
    found = bow.retrieve_features(kp, d, k=1)[0]
    assert distance[found] < 0.3
    assert fused.retrieve_features(kp, d, far, k=1) == [found]
    honest = np.array([truth[0, 3] / 10, 0.0], np.float32)
    assert distance[fused.retrieve_features(kp, d, honest, k=3)[0]] < 0.3
    assert fused.settings["retrieval"] == "fused"
    fused.save(tmp_path / "fused.geoloc")
    back = Map.load(tmp_path / "fused.geoloc")
    assert back.settings["retrieval"] == "fused"
    assert back.retrieve_features(kp, d, far, k=5) == fused.retrieve_features(kp, d, far, k=5)
    with pytest.raises(geoloc.InvalidInputError, match=r"^global_descriptor: this map retrieves by global descriptor"):
        fused.retrieve_features(kp, d)
    with pytest.raises(geoloc.InvalidInputError, match=r"^keypoints: expected shape"):
        fused.retrieve_features(kp[:-1], d, far)
    with pytest.raises(geoloc.InvalidInputError, match=r"^k: "):
        fused.retrieve_features(kp, d, far, k=0)
