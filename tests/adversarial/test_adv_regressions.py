"""Regression tests for the defects the adversarial suite found and that were fixed in this
branch (each names the argument in the InvalidInputError, or returns a valid result)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

import geoloc
from geoloc import datasets, descriptor, evaluation, features, geometry, matching, plots, retrieval
from geoloc.cli import main as cli_main

T = np.repeat(np.eye(4)[None], 3, axis=0)
T[:, 0, 3] = [0.0, 0.1, 0.2]
COV = np.repeat(np.diag([1e-4] * 3 + [1e-5] * 3)[None], 3, axis=0)


def test_undistort_points_empty_and_huge() -> None:
    """A numpy reshape error from Camera.undistort_points on an empty (0, 2) array;
    pixels of 1e302 came back NaN from OpenCV."""
    cam = geoloc.Camera(525, 525, 320, 240, dist=(0.1, -0.05, 0.001, 0.0))
    assert cam.undistort_points(np.zeros((0, 2))).shape == (0, 2)
    with pytest.raises(geoloc.InvalidInputError, match="^pixels: "):
        cam.undistort_points(np.full((3, 2), 3.5e302))


def test_map_load_of_a_missing_file_names_the_path(tmp_path: Path) -> None:
    """The suite's Map.load('3'): a string that names no file is a FileAccessError (an
    OSError) naming that path, not a crash or a wrong type."""
    missing = tmp_path / "3"
    with pytest.raises(geoloc.FileAccessError, match=f"^{missing}: cannot read the map"):
        geoloc.Map.load(str(missing))


def test_motion_predict_refuses_a_fit_swamped_by_rounding() -> None:
    """The suite's motion_predict with one pose 3e38 m away: the covariance came back
    indefinite (smallest eigenvalue −1.7e90); now an InvalidInputError naming the poses."""
    poses = np.repeat(np.eye(4)[None], 4, axis=0)
    poses[:, 0, 3] = [3e38, 0.1, 0.2, 0.3]
    covs = np.repeat(np.diag([1e-4] * 3 + [1e-5] * 3)[None], 4, axis=0)
    with pytest.raises(geoloc.InvalidInputError, match="^poses: "):
        geoloc.motion_predict(poses, np.array([0.0, 0.1, 0.2, 0.3]), 0.4, covariances=covs, acceleration_psd=np.full(6, 0.1))


def test_motion_predict_names_an_absurd_velocity_prior() -> None:
    """The suite's motion_predict with velocity_mean 1e300: the fit overflowed and the error
    named the poses; now the prior itself is refused by name (|mean| ≤ 1e6 per axis, a
    variance whose inverse is finite)."""
    poses = np.repeat(np.eye(4)[None], 4, axis=0)
    poses[:, 0, 3] = [0.0, 0.1, 0.2, 0.3]
    covs = np.repeat(np.diag([1e-4] * 3 + [1e-5] * 3)[None], 4, axis=0)
    t = np.array([0.0, 0.1, 0.2, 0.3])
    with pytest.raises(geoloc.InvalidInputError, match="^velocity_mean: "):
        geoloc.motion_predict(poses, t, 0.4, covariances=covs, velocity_mean=[1e300, 0, 0, 0, 0, 0], velocity_variance=np.full(6, 0.05))
    with pytest.raises(geoloc.InvalidInputError, match="^velocity_variance: "):
        geoloc.motion_predict(poses, t, 0.4, covariances=covs, velocity_mean=np.zeros(6), velocity_variance=np.full(6, 1e-320))


@pytest.mark.parametrize(
    "call, name",
    [
        (lambda: datasets.load_tum(924), "path"),  # type: ignore[arg-type]
        (lambda: datasets.load_7scenes(None), "path"),  # type: ignore[arg-type]
        (lambda: datasets.load_folder(np.zeros(2)), "path"),  # type: ignore[arg-type]
        (lambda: plots.plot_trajectory(evaluation.summarize(list(T), T), 3.0), "path"),  # type: ignore[arg-type]
        (lambda: evaluation.write_tum_trajectory(None, [0.0], np.eye(4)[None]), "path"),  # type: ignore[arg-type]
        (lambda: descriptor.OnnxDescriptor(146250536), "path"),  # type: ignore[arg-type]
    ],
)
def test_paths_that_are_not_paths(call: Any, name: str) -> None:
    with pytest.raises(geoloc.InvalidInputError, match=f"^{name}: expected a file path"):
        call()


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"loss": b"huber"}, "loss"),
        ({"loss": None}, "loss"),
        ({"covariance": 1}, "covariance"),
        ({"huber": None}, "huber"),
        ({"pixel_sigma": "1.0"}, "pixel_sigma"),
        ({"confidence": 1 + 2j}, "confidence"),
        ({"ransac": "yes"}, "ransac"),
        ({"max_residual": [5.0]}, "max_residual"),
    ],
)
def test_solve_pnp_option_types(kwargs: dict[str, Any], name: str) -> None:
    """Non-string options and non-number scalars raised TypeError from the bindings."""
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-1, 1, 20), rng.uniform(-1, 1, 20), rng.uniform(3, 6, 20)])
    px = 525 * pts[:, :2] / pts[:, 2:] + [320, 240]
    with pytest.raises(geoloc.InvalidInputError, match=f"^{name}: "):
        geometry.solve_pnp(pts, px, geoloc.Camera(525, 525, 320, 240), **kwargs)


def test_triangulate_and_keyframe_option_types() -> None:
    cam = geoloc.Camera(525, 525, 320, 240)
    with pytest.raises(geoloc.InvalidInputError, match="^loss: "):
        geometry.triangulate(T, cam, [0, 1], [0, 0], np.full((2, 2), 300.0), loss=b"huber")  # type: ignore[arg-type]
    with pytest.raises(geoloc.InvalidInputError, match="^pixel_sigma: "):
        geometry.triangulate(T, cam, [0, 1], [0, 0], np.full((2, 2), 300.0), pixel_sigma=None)  # type: ignore[arg-type]
    with pytest.raises(geoloc.InvalidInputError, match="^ell: "):
        geometry.keyframe_score(T[0], T[1], ell=2**70 * 2**1100)
    with pytest.raises(geoloc.InvalidInputError, match="^min_score: "):
        geometry.select_keyframes(T, 1, min_score=1 + 2j)  # type: ignore[arg-type]


def test_matching_and_retrieval_option_types() -> None:
    x = np.random.default_rng(1).normal(size=(10, 8)).astype(np.float32)
    with pytest.raises(geoloc.InvalidInputError, match="^ratio: "):
        matching.match_descriptors(x, x, ratio="1.0")  # type: ignore[arg-type]
    with pytest.raises(geoloc.InvalidInputError, match="^max_distance: "):
        matching.match_descriptors(x, x, max_distance=[1.0])  # type: ignore[arg-type]
    with pytest.raises(geoloc.InvalidInputError, match="^backend: "):
        retrieval.DescriptorIndex(x, backend=True)  # type: ignore[arg-type]
    u8 = np.random.default_rng(2).integers(0, 256, size=(60, 32), dtype=np.uint8)
    voc = retrieval.Vocabulary.train(u8, 3, 2)
    with pytest.raises(geoloc.InvalidInputError, match="^images: "):
        retrieval.BowDatabase(voc, None)  # type: ignore[arg-type]
    with pytest.raises(geoloc.InvalidInputError, match="^images: "):
        retrieval.BowDatabase(voc, [x])


def test_bow_scene_whose_words_discriminate() -> None:
    """A scene where every word is in every image has idf 0 and cannot tell images
    apart. Here each image has its own descriptors: each is retrieved by its own, score > 0."""
    rng = np.random.default_rng(3)
    images = [rng.integers(0, 256, size=(40, 32), dtype=np.uint8) for _ in range(4)]
    voc = retrieval.Vocabulary.train(np.vstack(images), 4, 3)
    db = retrieval.BowDatabase(voc, images)
    for i, d in enumerate(images):
        scores, ind = db.query(d, k=2)
        assert ind[0] == i and 0 < scores[0] <= 1 and scores[1] < scores[0]


def test_evaluation_names_its_own_arguments() -> None:
    bad = T.copy()
    bad[1, 3, 1] = 1e20
    with pytest.raises(geoloc.NotARotationError, match=r"^est\[1\] is not a rigid transform"):
        evaluation.tangent_errors(bad, T)
    with pytest.raises(geoloc.InvalidInputError, match="^cov: expected shape"):
        evaluation.isometric_sigmas(np.zeros((5, 6, 7)))
    with pytest.raises(geoloc.InvalidInputError, match="^cov: rotation standard deviations"):
        evaluation.isometric_sigmas(np.eye(6) * 1e296)
    with pytest.raises(geoloc.InvalidInputError, match="^covariances: expected a sequence"):
        evaluation.summarize(list(T), T, covariances=7)  # type: ignore[arg-type]
    with pytest.raises(geoloc.InvalidInputError, match="^timestamp: "):
        evaluation.format_tum_line(None, T[0])  # type: ignore[arg-type]
    with pytest.raises(geoloc.InvalidInputError, match="^x: "):
        evaluation.chi2_6_cdf("abc")
    with pytest.raises(geoloc.InvalidInputError, match="^p: "):
        evaluation.chi2_6_quantile("abc")
    assert evaluation.chi2_6_cdf([np.inf, 1e300, 0.0]).tolist() == [1.0, 1.0, 0.0]


def test_features_and_descriptor_bounds() -> None:
    with pytest.raises(geoloc.InvalidInputError, match="^n_features: must be at most"):
        features.FeatureExtractor("orb", 2**63)
    ex = features.FeatureExtractor("orb", 100)
    with pytest.raises(geoloc.InvalidInputError, match="^image: is empty"):
        ex(np.zeros((0, 160, 3), np.uint8), geoloc.Camera(525, 525, 80, 60, width=160, height=120))
    with pytest.raises(geoloc.InvalidInputError, match="^packed: "):
        features.decode_sift_octave(np.array(["abc"]))
    imgs = np.zeros((1, 40, 30, 3), np.uint8)
    for size in (7, 3.5, (0, 4), (10**9, 4), (True, 4)):
        with pytest.raises(geoloc.InvalidInputError, match="^size: "):
            descriptor.to_gray(imgs, size)  # type: ignore[arg-type]
        with pytest.raises(geoloc.InvalidInputError, match="^size: "):
            descriptor.tiny_image_descriptors(imgs, size)  # type: ignore[arg-type]


@pytest.mark.parametrize("kwargs, name", [({"threads": 4236}, "threads"), ({"batch_size": 2**31}, "batch_size")])
def test_onnx_descriptor_counts_are_bounded(tmp_path: Path, kwargs: dict[str, int], name: str) -> None:
    """threads=4236 hung creating the onnxruntime session; 2**31 raised a pybind TypeError."""
    model = tmp_path / "m.onnx"
    model.write_bytes(b"not read: the counts are checked first")
    with pytest.raises(geoloc.InvalidInputError, match=f"^{name}: expected an integer in"):
        descriptor.OnnxDescriptor(model, **kwargs)  # type: ignore[arg-type]


def test_datasets_bounds() -> None:
    with pytest.raises(geoloc.InvalidInputError, match="^n_frames: must be at most"):
        datasets.synthetic_room(n_frames=344532)


def test_dataset_option_types(tmp_path: Path) -> None:
    folder = datasets.synthetic_room(n_frames=2).write_tum(tmp_path / "tum")
    with pytest.raises(geoloc.InvalidInputError, match="^max_time_difference: "):
        datasets.load_tum(folder, max_time_difference=1 + 2j)  # type: ignore[arg-type]
    with pytest.raises(geoloc.InvalidInputError, match="^max_time_difference: "):
        datasets.load_folder(folder / "rgb", max_time_difference=None, intrinsics=(1, 1, 1, 1))  # type: ignore[arg-type]
    with pytest.raises(geoloc.InvalidInputError, match="^trajectory: "):
        datasets.load_folder(folder / "rgb", trajectory=-1481, intrinsics=(1, 1, 1, 1))  # type: ignore[arg-type]


def test_train_names_dataset_and_device_options(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`geoloc train` printed `path: …` for a bad --dataset and an info line then `device: …`."""
    bad = tmp_path / "x.onnx"
    bad.write_bytes(b"PK")
    assert cli_main(["train", "--dataset", str(bad), "--format", "tum", "--out", str(tmp_path / "m.onnx")]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("geoloc train: error: --dataset: "), err
    with pytest.raises(SystemExit) as exit_info:
        cli_main(["train", "--dataset", "synthetic", "--device", "nan,1,1,1", "--out", str(tmp_path / "m.onnx")])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("geoloc train: error: argument --device: ")
    assert not any(e.startswith("geoloc train: ") and " frames, " in e for e in err)  # no info line before it


def test_long_profile_findings() -> None:
    """Found by the long profile (benchmarks/adversarial.py)."""
    for dist in (object, "abc", [1 + 2j] * 4):
        with pytest.raises(geoloc.InvalidInputError, match="^dist: "):
            geoloc.Camera(525, 525, 320, 240, dist=dist)  # type: ignore[arg-type]
    # 2**70 is a valid (huge) integer option: a score, not a TypeError from np.isfinite
    assert np.isfinite(geometry.keyframe_score(T[0], T[1], d_m=2**70, ell=2**70, alpha_m=2**70))
    with pytest.raises(geoloc.InvalidInputError, match="^z: "):
        evaluation.axis_coverage(T, COV, T, z=None)  # type: ignore[arg-type]
    far = T.copy()
    far[:, 0, 3] = 1e300
    trans, _ = evaluation.pose_errors(T, far)
    assert np.all(np.isfinite(trans)) and np.allclose(trans, 1e300)


def test_so3_project_of_denormal_matrices() -> None:
    """2^1063 (the scale for entries near 6e-321) overflowed: so3_project returned NaN."""
    r = geoloc.lie.so3_exp([0.3, -0.2, 0.1])
    for scale in (1e-310, 1e-320):
        p = geoloc.lie.so3_project(r * scale)
        assert np.isfinite(p).all() and np.allclose(p.T @ p, np.eye(3), atol=1e-12)
        assert np.abs(p - r).max() < 0.05


def test_dataset_max_time_difference_huge_integer(tmp_path: Path) -> None:
    folder = datasets.synthetic_room(n_frames=2).write_tum(tmp_path / "tum")
    assert len(datasets.load_tum(folder, max_time_difference=2**70)) == 2
    with pytest.raises(geoloc.InvalidInputError, match="^max_time_difference: ") as raised:
        datasets.load_tum(folder, max_time_difference=2**1100)
    message = str(raised.value)
    assert "an integer of 332 digits does not fit a float64" in message and len(message) < 100, message


def test_train_refuses_a_foreign_init_before_printing(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("torch")
    bad = tmp_path / "init.pt"
    bad.write_bytes(b"\x00" * 24)
    code = cli_main(["train", "--dataset", "synthetic", "--tiny", "--init", str(bad), "--out", str(tmp_path / "m.onnx")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code != 0 and len(err) == 1 and err[0].startswith("geoloc train: error: --init: "), err


@pytest.mark.parametrize("alpha", [1e300, -1e200])
def test_se3_interpolate_refuses_an_overflowing_alpha(alpha: float) -> None:
    """se3_interpolate(T1, T2, 1e300) returned a NaN pose."""
    with pytest.raises(geoloc.InvalidInputError, match="^alpha"):
        geoloc.lie.se3_interpolate(T[0], T[1], alpha)
    assert np.isfinite(geoloc.lie.se3_interpolate(T[0], T[1], 1e6)).all()


def test_se3_interpolate_names_the_poses_when_their_relative_twist_overflows() -> None:
    far = T[0].copy()
    far[0, 3] = 1e300
    with pytest.raises(geoloc.InvalidInputError, match="^T1, T2: "):
        geoloc.lie.se3_interpolate(far, T[1], 0.3)


def test_triangulate_with_no_poses() -> None:
    """(0, 4, 4) poses with (0, 6, 6) pose covariances: a numpy reshape error, now named."""
    with pytest.raises(geoloc.InvalidInputError, match="cam_ids|poses"):
        geometry.triangulate(np.zeros((0, 4, 4)), geoloc.Camera(525, 525, 320, 240), [0, 1], [0, 0],
                             np.full((2, 2), 300.0), pose_covariances=np.zeros((0, 6, 6)))


@pytest.fixture(scope="module")
def small_map() -> tuple[datasets.Sequence, geoloc.Map]:
    room = datasets.synthetic_room(n_frames=20, seed=0)
    return room, geoloc.Map.build(room[:12:2])


def test_front_door_arguments_are_checked_before_any_work(small_map: tuple[datasets.Sequence, geoloc.Map]) -> None:
    """Each was a raw numpy/Python error, a late TypeError or silently accepted: a huge
    keyframe step, a root_sift that is not a bool (any truthy value turned RootSIFT on), a
    progress that is not callable, a localize_sequence argument that is not a Sequence, a
    huge retrieval count."""
    room, m = small_map
    assert len(geoloc.Map.build(room[:5], keyframe_step=2**70)) == 1, "a step past the sequence keeps its first frame"
    for bad, name in ((dict(root_sift="no"), "root_sift"), (dict(root_sift=np.nan), "root_sift"), (dict(progress=5), "progress")):
        calls: list[tuple[int, int]] = []
        with pytest.raises(geoloc.InvalidInputError, match=f"^{name}: "):
            geoloc.Map.build(room[:5], features="sift", **bad, **({} if "progress" in bad else {"progress": lambda d, n: calls.append((d, n))}))
        assert not calls, "refused before any keyframe was described"
    with pytest.raises(geoloc.InvalidInputError, match="^root_sift: "):
        features.FeatureExtractor("sift", root_sift="no")  # type: ignore[arg-type]
    loc = geoloc.Localizer(m)
    for bad in ([room[0]], None):
        with pytest.raises(geoloc.InvalidInputError, match="^sequence: expected a geoloc.datasets.Sequence"):
            loc.localize_sequence(bad)
    with pytest.raises(geoloc.InvalidInputError, match="^progress: "):
        loc.localize_sequence(room[12:14], progress=3)  # type: ignore[arg-type]
    f = m.features(room.gray(13), room.camera)
    assert sorted(m.retrieve_features(f.keypoints, f.descriptors, k=2**70)) == list(range(len(m)))
    # a path given as bytes was read as a one-string array: "expected uint8 pixels, got dtype |S6"
    with pytest.raises(geoloc.InvalidInputError, match=r"^image: expected a path \(str or os.PathLike\) or an image array, got bytes"):
        loc.localize(b"/x.png", 0.0)


def test_a_sequence_of_another_camera_is_refused_not_localized_as_the_maps(
    small_map: tuple[datasets.Sequence, geoloc.Map], tmp_path: Path
) -> None:
    """localize_sequence and export_frames ran a sequence of another camera with the map's
    (Localizer(camera=...) refused it); both refuse it now, naming the argument, and nothing
    is written."""
    room, m = small_map
    other = geoloc.Camera(600.0, 600.0, room.camera.cx, room.camera.cy, room.camera.width, room.camera.height)
    foreign = datasets.Sequence("foreign", other, room.timestamps[12:14], room.poses[12:14], lambda i, gray: room.gray(12 + i))
    with pytest.raises(geoloc.InvalidInputError, match=r"^sequence: not the map's camera — intrinsics \(600.0"):
        geoloc.Localizer(m).localize_sequence(foreign)
    out = tmp_path / "frames.bin"
    with pytest.raises(geoloc.InvalidInputError, match=r"^frames: not the map's camera"):
        geoloc.export_frames(m, foreign, out)
    assert not out.exists()


def test_export_frames_checks_each_pair_and_needs_no_model(small_map: tuple[datasets.Sequence, geoloc.Map], tmp_path: Path) -> None:
    """Pairs that are not (finite, increasing timestamp, image) are refused by position before
    anything is written (a decreasing pair used to be written and stop geoloc-rs at it); a map
    only the paper's locator can use (one keyframe: no 3D model) is exported as any other."""
    room, m = small_map
    g = room.gray(13)
    out = tmp_path / "frames.bin"
    for frames, needle in (
        ([("abc", g)], r"^frames\[0\] timestamp: expected a real number"),
        ([g], r"^frames\[0\]: expected a \(timestamp, image\) pair"),
        ([(1.0, g), (0.5, g)], r"^frames\[1\] timestamp: 0.5 does not increase"),
        ([(float("nan"), g)], r"^frames\[0\] timestamp: nan is not finite"),
    ):
        with pytest.raises(geoloc.InvalidInputError, match=needle):
            geoloc.export_frames(m, frames, out)
        assert not out.exists()
    with pytest.raises(geoloc.InvalidInputError, match="^progress: "):
        geoloc.export_frames(m, room[12:14], out, progress="yes")  # type: ignore[arg-type]
    one = geoloc.Map.build(room[:1])
    assert geoloc.export_frames(one, room[1:3], out) == 2


def test_a_path_that_cannot_be_read_or_written_is_an_oserror_and_names_the_argument(
    small_map: tuple[datasets.Sequence, geoloc.Map], tmp_path: Path
) -> None:
    """The documented FileAccessError (an OSError) for a missing file, a folder or a missing
    folder — it was InvalidInputError alone, which ``except OSError`` does not catch; it is
    still an InvalidInputError (a ValueError) naming the argument."""
    room, m = small_map
    cases = (
        (lambda: m.save(tmp_path / "nope" / "x.geoloc"), "^path: folder .* does not exist"),
        (lambda: m.save(tmp_path), "^path: .* is a folder"),
        (lambda: geoloc.Localizer(m).localize(tmp_path / "missing.png", 0.0), "^image: file .* does not exist"),
        (lambda: geoloc.export_frames(m, room[12:14], tmp_path / "nope" / "f.bin"), "^path: folder .* does not exist"),
        (lambda: geoloc.Map.load(tmp_path / "missing.geoloc"), "missing.geoloc"),
    )
    for call, needle in cases:
        with pytest.raises(OSError, match=needle) as raised:
            call()
        assert isinstance(raised.value, geoloc.FileAccessError) and isinstance(raised.value, geoloc.InvalidInputError)
