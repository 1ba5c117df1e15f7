"""geoloc.datasets: the 7-Scenes (both layouts), TUM and folder loaders, Sequence slicing, errors."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

import geoloc
from geoloc import datasets
from geoloc.datasets.tum import TUM_CAMERAS

cv2 = pytest.importorskip("cv2")

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
PLAIN = DATA / "7scenes-redkitchen"
ORIGINAL = DATA / "7scenes-redkitchen-original-format"
ORTHONORMAL_TOL = 1e-12
SAME_POSE_TOL = 1e-7  # the plain copies were re-printed with %.18e from 8-digit originals
JPEG_MEAN_ABS_DIFF = 6.0  # grey levels: the plain layout is the JPEG (PSNR 33–36 dB) of the PNGs
ORIGINAL_FRAMES = range(150, 160)
GRAY_MEAN_ABS_DIFF = 2.0  # grey levels: libjpeg's luma vs cvtColor of the decoded colour
TIME_TOL = 1e-9
SHIFT_S = 0.015  # < default max_time_difference 0.02 s


def _need(path: Path) -> None:
    if not path.is_dir():
        pytest.skip(f"shared sample data not found at {path} (see ../shared/data/README.md)")


# ---------------------------------------------------------------------------- 7-Scenes


def test_7scenes_plain_layout() -> None:
    _need(PLAIN)
    seq = datasets.load_7scenes(PLAIN)
    assert len(seq) == 700 and seq.name == PLAIN.name
    assert seq.camera.intrinsics == (525.0, 525.0, 320.0, 240.0)
    assert seq.poses is not None and seq.poses.shape == (700, 4, 4)
    R = seq.poses[:, :3, :3]
    assert np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max() < ORTHONORMAL_TOL
    assert np.allclose(np.linalg.det(R), 1.0, atol=ORTHONORMAL_TOL)
    assert np.allclose(seq.timestamps, np.arange(700) / 30)
    frame = seq[150]
    assert frame.image.shape == (480, 640, 3) and frame.image.dtype == np.uint8
    assert frame.index == 150 and frame.timestamp == pytest.approx(5.0)


def test_7scenes_original_format_agrees_with_the_plain_layout() -> None:
    _need(PLAIN)
    _need(ORIGINAL)
    original = datasets.load_7scenes(ORIGINAL)
    plain = datasets.load_7scenes(PLAIN)[ORIGINAL_FRAMES.start : ORIGINAL_FRAMES.stop]
    assert len(original) == len(ORIGINAL_FRAMES)
    assert list(original.indices) == list(ORIGINAL_FRAMES) == list(plain.indices)
    assert np.allclose(original.timestamps, plain.timestamps, atol=TIME_TOL)
    assert original.poses is not None and plain.poses is not None
    assert np.abs(original.poses - plain.poses).max() < SAME_POSE_TOL
    png, jpg = original[0].image.astype(float), plain[0].image.astype(float)
    assert np.abs(png - jpg).mean() < JPEG_MEAN_ABS_DIFF  # same frame, same channel order
    gray = plain.gray(0)  # decoded as grey: the JPEG's luma, close to converting the colour
    assert gray.shape == (480, 640) and gray.dtype == np.uint8
    assert np.abs(gray.astype(float) - cv2.cvtColor(plain[0].image, cv2.COLOR_BGR2GRAY)).mean() < GRAY_MEAN_ABS_DIFF
    depth_camera = datasets.load_7scenes(ORIGINAL, intrinsics="file").camera
    assert depth_camera.intrinsics == (585.0, 585.0, 320.0, 240.0)


def test_any_sequence_writes_a_tum_folder(tmp_path: Path) -> None:
    _need(ORIGINAL)
    seq = datasets.load_7scenes(ORIGINAL)[2:5]
    loaded = datasets.load_tum(seq.write_tum(tmp_path / "kitchen"))
    assert loaded.camera == seq.camera and loaded.poses is not None and seq.poses is not None
    assert np.allclose(loaded.poses, seq.poses, atol=1e-12)
    assert np.array_equal(loaded[1].image, seq[1].image)
    with pytest.raises(geoloc.DatasetError, match="parent folder"):
        seq.write_tum(tmp_path / "missing" / "kitchen")


def _copy_frames(tmp_path: Path, numbers: range) -> Path:
    _need(ORIGINAL)
    folder = tmp_path / "seq-01"
    folder.mkdir()
    for n in numbers:
        for suffix in ("color.png", "pose.txt"):
            shutil.copy(ORIGINAL / f"frame-{n:06d}.{suffix}", folder)
    return folder


def test_7scenes_bad_input(tmp_path: Path) -> None:
    with pytest.raises(geoloc.DatasetError, match="does not exist"):
        datasets.load_7scenes(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(geoloc.DatasetError, match="no 7-Scenes colour frames"):
        datasets.load_7scenes(tmp_path / "empty")
    folder = _copy_frames(tmp_path, range(150, 153))
    (folder / "frame-000151.pose.txt").write_text("1 2 3\nnot numbers\n")
    with pytest.raises(geoloc.DatasetError, match="frame-000151.pose.txt"):
        datasets.load_7scenes(folder)
    (folder / "frame-000151.pose.txt").write_text("1 0 0 0\n0 1 0 0\n0 0 1 0\n")
    with pytest.raises(geoloc.DatasetError, match="expected 16 numbers"):
        datasets.load_7scenes(folder)
    (folder / "frame-000151.pose.txt").unlink()
    with pytest.raises(geoloc.DatasetError, match=r"frame-000151.pose.txt' is missing"):
        datasets.load_7scenes(folder)
    with pytest.raises(geoloc.DatasetError, match="camera-intrinsics.txt"):
        datasets.load_7scenes(folder, intrinsics="file")
    # one frame under two names: both named (it guessed "png and jpg?" and named neither)
    shutil.copy(folder / "frame-000150.color.png", folder / "frame-0000150.color.png")
    with pytest.raises(geoloc.DatasetError, match=r"has frame 150 twice: 'frame-0000150.color.png' and 'frame-000150.color.png'"):
        datasets.load_7scenes(folder)


def test_images_of_another_size_or_unreadable_are_named(tmp_path: Path) -> None:
    folder = _copy_frames(tmp_path, range(150, 152))
    small = cv2.imread(str(folder / "frame-000150.color.png"))[::2, ::2]
    cv2.imwrite(str(folder / "frame-000150.color.png"), small)
    (folder / "frame-000151.color.png").write_bytes(b"\x89PNG but not really")
    seq = datasets.load_7scenes(folder)  # images are read lazily ...
    with pytest.raises(geoloc.DatasetError, match=r"frame-000150.color.png'.*320×240, the camera is 640×480"):
        seq[0]  # ... and checked when read
    with pytest.raises(geoloc.DatasetError, match=r"frame-000151.color.png' cannot be read"):
        seq[1]


# ---------------------------------------------------------------------------- Sequence


def test_sequence_slicing_and_iteration() -> None:
    seq = datasets.synthetic_room(n_frames=20)
    part = seq[5:15]
    assert len(part) == 10 and part[0].index == 5 and part.camera == seq.camera
    assert np.array_equal(part.timestamps, seq.timestamps[5:15])
    assert seq.poses is not None and part.poses is not None
    assert np.array_equal(part.poses, seq.poses[5:15])
    stepped = seq[::4]
    assert list(stepped.indices) == [0, 4, 8, 12, 16]
    assert list(seq[[3, 1, 19]].indices) == [3, 1, 19]
    assert list(seq[np.arange(20) % 7 == 0].indices) == [0, 7, 14]
    assert list(seq[10:][::5].indices) == [10, 15]
    assert seq[-1].index == 19
    assert np.array_equal(stepped[1].image, seq[4].image)
    assert [f.index for f in seq[2:5]] == [2, 3, 4]
    assert np.array_equal(stepped.gray(1), cv2.cvtColor(seq[4].image, cv2.COLOR_BGR2GRAY))
    with pytest.raises(geoloc.InvalidInputError, match="selects no frames"):
        seq[30:40]
    with pytest.raises(geoloc.InvalidInputError, match="selects no frames"):
        seq[np.zeros(20, dtype=bool)]
    with pytest.raises(geoloc.InvalidInputError, match="selects no frames"):
        seq[[]]
    with pytest.raises(IndexError):
        seq[20]
    with pytest.raises(geoloc.InvalidInputError, match="mask"):
        seq[np.ones(3, dtype=bool)]
    assert seq.poses.flags.writeable is False  # ground truth cannot be edited by accident


# ---------------------------------------------------------------------------- TUM


@pytest.fixture(scope="module")
def tum_folder(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, datasets.Sequence]:
    seq = datasets.synthetic_room(n_frames=30)[::3]
    root = seq.write_tum(tmp_path_factory.mktemp("tum") / "room")
    return root, seq


def test_tum_round_trip(tum_folder: tuple[Path, datasets.Sequence]) -> None:
    root, seq = tum_folder
    assert {p.name for p in root.iterdir()} == {"rgb", "rgb.txt", "groundtruth.txt", "camera.txt"}
    loaded = datasets.load_tum(root)
    assert len(loaded) == len(seq) and loaded.camera == seq.camera
    assert loaded.poses is not None and seq.poses is not None
    assert np.allclose(loaded.poses, seq.poses, atol=1e-12)
    assert np.allclose(loaded.timestamps, seq.timestamps, atol=1e-6)
    assert np.array_equal(loaded[2].image, seq[2].image)  # PNG is lossless


def test_tum_association_and_intrinsics(tum_folder: tuple[Path, datasets.Sequence], tmp_path: Path) -> None:
    root, seq = tum_folder
    copy = tmp_path / "rgbd_dataset_freiburg1_room"
    shutil.copytree(root, copy)
    (copy / "camera.txt").unlink()
    assert datasets.load_tum(copy).camera == TUM_CAMERAS["freiburg1"]
    assert datasets.load_tum(copy).camera.dist is not None
    assert datasets.load_tum(copy, intrinsics=(500, 500, 320, 240)).camera.intrinsics == (500, 500, 320, 240)
    # Ground truth at shifted times; one pose missing: its image is dropped.
    gt = [line for line in (copy / "groundtruth.txt").read_text().splitlines() if not line.startswith("#")]
    shifted = [" ".join([repr(float(line.split()[0]) + SHIFT_S), *line.split()[1:]]) for line in gt]
    (copy / "groundtruth.txt").write_text("# shifted\n" + "\n".join(shifted[:4] + shifted[5:]) + "\n")
    loaded = datasets.load_tum(copy)
    assert len(loaded) == len(seq) - 1 and 4 not in loaded.indices.tolist()
    assert loaded.poses is not None and seq.poses is not None
    assert np.allclose(loaded.poses[:4], seq.poses[:4], atol=1e-12)
    with pytest.raises(geoloc.DatasetError, match="within 0.01 s"):
        datasets.load_tum(copy, max_time_difference=0.01)
    # No camera file and no TUM camera in the name: ask for intrinsics.
    anonymous = tmp_path / "recording"
    copy.rename(anonymous)
    with pytest.raises(geoloc.DatasetError, match="pass intrinsics"):
        datasets.load_tum(anonymous)


def test_tum_bad_input(tum_folder: tuple[Path, datasets.Sequence], tmp_path: Path) -> None:
    root, _ = tum_folder
    with pytest.raises(geoloc.DatasetError, match="does not exist"):
        datasets.load_tum(tmp_path / "missing")
    copy = tmp_path / "room"
    shutil.copytree(root, copy)
    (copy / "groundtruth.txt").write_text("0.0 1 2 3 0 0 0\n")
    with pytest.raises(geoloc.DatasetError, match="has 7 values, expected 8"):
        datasets.load_tum(copy)
    (copy / "groundtruth.txt").write_text("0.0 1 2 3 0 0 0 0\n")
    with pytest.raises(geoloc.DatasetError, match="no unit quaternion"):
        datasets.load_tum(copy)
    # decimal numbers only: float() read "1_0" as 10, and 1e999 overflows to inf
    (copy / "groundtruth.txt").write_text("0.0 1_0 2 3 0 0 0 1\n")
    with pytest.raises(geoloc.DatasetError, match="entry 1 is not numbers: '0.0 1_0"):
        datasets.load_tum(copy)
    (copy / "groundtruth.txt").write_text("0.0 1e999 2 3 0 0 0 1\n")
    with pytest.raises(geoloc.DatasetError, match="entry 1 has a non-finite number"):
        datasets.load_tum(copy)
    (copy / "groundtruth.txt").unlink()
    assert datasets.load_tum(copy).poses is None  # no ground truth: every image, no poses
    (copy / "rgb.txt").write_text("# nothing\n")
    with pytest.raises(geoloc.DatasetError, match="lists no images"):
        datasets.load_tum(copy)
    (copy / "rgb.txt").unlink()
    with pytest.raises(geoloc.DatasetError, match="rgb.txt' does not exist"):
        datasets.load_tum(copy)


def test_repeated_timestamps_are_refused_naming_both_entries(tum_folder: tuple[Path, datasets.Sequence],
                                                              tmp_path: Path) -> None:
    """A second ground-truth row at a frame's time, 5 m off, silently became that frame's label
    (the later row won), in ``load_tum``, ``build-map`` and ``evaluate --reference``."""
    from geoloc.reference import load_reference

    root, _ = tum_folder
    copy = tmp_path / "room"
    shutil.copytree(root, copy)
    gt = [line for line in (copy / "groundtruth.txt").read_text().splitlines() if not line.startswith("#")]
    t, *pose = gt[8].split()
    (copy / "groundtruth.txt").write_text("\n".join([*gt, " ".join([t, str(float(pose[0]) + 5), *pose[1:]])]) + "\n")
    with pytest.raises(geoloc.DatasetError, match=rf"groundtruth.txt'.*pose 11 has the timestamp {t} of pose 9"):
        datasets.load_tum(copy)
    with pytest.raises(geoloc.DatasetError, match="pose 11 has the timestamp"):
        load_reference(copy / "groundtruth.txt", fmt="tum")
    shutil.copy(root / "groundtruth.txt", copy / "groundtruth.txt")
    rgb = [line for line in (copy / "rgb.txt").read_text().splitlines() if not line.startswith("#")]
    (copy / "rgb.txt").write_text("\n".join([*rgb, f"{rgb[2].split()[0]} {rgb[3].split()[1]}"]) + "\n")
    with pytest.raises(geoloc.DatasetError, match="rgb.txt'.*entry 11 has the timestamp .* of entry 3"):
        datasets.load_tum(copy)


def test_two_image_names_of_one_timestamp_are_refused_naming_both(tmp_path: Path) -> None:
    """``63.png`` and ``063.png`` reached the localizer as one time twice ("timestamp: must
    increase, got 63", naming no file)."""
    for name in ("63.png", "063.png", "64.png"):
        cv2.imwrite(str(tmp_path / name), np.zeros((48, 64, 3), np.uint8))
    with pytest.raises(geoloc.DatasetError, match=r"image names in .*: '63.png' has the timestamp 63.0 of '063.png'"):
        datasets.load_folder(tmp_path, intrinsics=(50, 50, 32, 24))


def test_associate_gives_a_tie_to_the_earlier_reference() -> None:
    from geoloc.datasets.tum import associate

    reference = np.array([0.9, 1.0, 1.0, 1.1])
    assert associate(np.array([1.0000001, 0.95, 1.05, 2.0]), reference, 0.5).tolist() == [1, 0, 1, -1]


# ---------------------------------------------------------------------------- folder


def test_images_listed_out_of_time_order_are_refused(tum_folder: tuple[Path, datasets.Sequence], tmp_path: Path) -> None:
    """A reversed rgb.txt loaded as a sequence whose time ran backwards, without a word."""
    root, _ = tum_folder
    copy = tmp_path / "room"
    shutil.copytree(root, copy)
    lines = (copy / "rgb.txt").read_text().splitlines()
    header, rows = [x for x in lines if x.startswith("#")], [x for x in lines if not x.startswith("#")]
    (copy / "rgb.txt").write_text("\n".join([*header, *rows[::-1]]) + "\n")
    with pytest.raises(geoloc.DatasetError, match=r"rgb.txt'.*entry 2 has the timestamp .*, before entry 1's .* time order"):
        datasets.load_tum(copy)


def test_folder_by_timestamp_and_row(tum_folder: tuple[Path, datasets.Sequence], tmp_path: Path) -> None:
    root, seq = tum_folder
    intrinsics = seq.camera.intrinsics
    by_time = datasets.load_folder(root / "rgb", trajectory=root / "groundtruth.txt", intrinsics=intrinsics)
    assert len(by_time) == len(seq) and by_time.poses is not None and seq.poses is not None
    assert np.allclose(by_time.poses, seq.poses, atol=1e-12)

    named = tmp_path / "images"
    named.mkdir()
    for k, image in enumerate(sorted((root / "rgb").iterdir())):
        shutil.copy(image, named / f"img_{k:03d}.png")
    shutil.copy(root / "groundtruth.txt", named / "traj.txt")
    by_row = datasets.load_folder(named, intrinsics=intrinsics)
    assert by_row.poses is not None and np.allclose(by_row.poses, seq.poses, atol=1e-12)
    assert np.array_equal(by_row[3].image, seq[3].image)

    lines = (named / "traj.txt").read_text().splitlines()
    (named / "traj.txt").write_text("\n".join(lines[:-1]) + "\n")
    with pytest.raises(geoloc.DatasetError, match="poses for 10 images"):
        datasets.load_folder(named, intrinsics=intrinsics)
    (named / "traj.txt").unlink()
    no_poses = datasets.load_folder(named, intrinsics=intrinsics)
    assert no_poses.poses is None and len(no_poses) == len(seq)


def test_folder_bad_input(tmp_path: Path) -> None:
    with pytest.raises(geoloc.DatasetError, match="does not exist"):
        datasets.load_folder(tmp_path / "missing", intrinsics=(500, 500, 320, 240))
    with pytest.raises(geoloc.DatasetError, match="has no images"):
        datasets.load_folder(tmp_path, intrinsics=(500, 500, 320, 240))
    cv2.imwrite(str(tmp_path / "a.png"), np.zeros((48, 64, 3), np.uint8))
    with pytest.raises(geoloc.DatasetError, match="intrinsics"):
        datasets.load_folder(tmp_path)
    with pytest.raises(geoloc.DatasetError, match="poses.txt' does not exist"):
        datasets.load_folder(tmp_path, trajectory="poses.txt", intrinsics=(50, 50, 32, 24))
    with pytest.raises(geoloc.InvalidInputError, match="expected 4 values"):
        datasets.load_folder(tmp_path, intrinsics=(50, 50, 32))  # type: ignore[arg-type]
    assert datasets.load_folder(tmp_path, intrinsics=(50, 50, 32, 24)).camera.width == 64


def test_import_geoloc_needs_numpy_only() -> None:
    import subprocess
    import sys

    code = "import sys, geoloc, geoloc.datasets, geoloc.evaluation, geoloc.features, geoloc.plots; print(sorted({'cv2', 'matplotlib'} & set(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == "[]"


def test_write_tum_refuses_to_write_over_the_folder_it_was_read_from(tum_folder: tuple[Path, datasets.Sequence],
                                                                     tmp_path: Path) -> None:
    """``seq[0:3].write_tum(its own folder)`` replaced rgb.txt, groundtruth.txt and images."""
    root, seq = tum_folder
    copy = tmp_path / "room"
    shutil.copytree(root, copy)
    before = {p: p.read_bytes() for p in copy.rglob("*") if p.is_file()}
    loaded = datasets.load_tum(copy)
    with pytest.raises(geoloc.InvalidInputError, match=r"^path: .*rgb.* is the same file as the input sequence"):
        loaded[0:3].write_tum(copy)
    assert {p: p.read_bytes() for p in copy.rglob("*") if p.is_file()} == before
    assert len(datasets.load_tum(copy)) == len(seq)
    assert len(datasets.load_tum(loaded[0:3].write_tum(tmp_path / "other"))) == 3  # another folder is written


def test_write_tum_keeps_frames_a_tenth_of_a_microsecond_apart(tmp_path: Path) -> None:
    """Names of six decimals gave both frames one image file and load_tum refused the folder."""
    room = datasets.synthetic_room(n_frames=2, seed=0)
    folder = tmp_path / "close"
    folder.mkdir()
    for i, name in enumerate(("1.0000001", "1.0000002")):
        cv2.imwrite(str(folder / f"{name}.png"), room[i].image)
    seq = datasets.load_folder(folder, trajectory=None, intrinsics=room.camera)
    loaded = datasets.load_tum(seq.write_tum(tmp_path / "tum"))
    assert loaded.timestamps.tolist() == [1.0000001, 1.0000002]  # exact: shortest round-trip repr
    assert np.array_equal(loaded[0].image, room[0].image) and np.array_equal(loaded[1].image, room[1].image)


def test_tum_file_names_keep_their_commas_and_spaces(tum_folder: tuple[Path, datasets.Sequence], tmp_path: Path) -> None:
    """rgb.txt's 'rgb/a,b.png' was read as 'rgb/a b.png', and 'c  d.png' as 'c d.png'."""
    root, seq = tum_folder
    copy = tmp_path / "room"
    shutil.copytree(root, copy)
    (copy / "groundtruth.txt").unlink()
    names = ["rgb/a,b.png", "rgb/c  d.png", "rgb/e.png"]
    lines = []
    for i, name in enumerate(names):
        cv2.imwrite(str(copy / name), seq[i].image)
        lines.append(f"{i}.5{',' if i == 2 else ' '}{name}")  # the TUM tools also take a comma as separator
    (copy / "rgb.txt").write_text("\n".join(lines) + "\n")
    loaded = datasets.load_tum(copy)
    assert [p.name for p in loaded.files[1:4]] == ["a,b.png", "c  d.png", "e.png"]
    assert all(np.array_equal(loaded[i].image, seq[i].image) for i in range(3))


@pytest.mark.parametrize("stems", [("20230101_120000", "20230101_120001"), ("nan", "1"), ("١", "٢"), ("1e1", "1_5")])
def test_folder_image_names_are_timestamps_only_when_they_are_decimal_numbers(tmp_path: Path,
                                                                              stems: tuple[str, str]) -> None:
    """float() read '20230101_120000' (a camera's date_time name) as 20230101120000 s."""
    room = datasets.synthetic_room(n_frames=2, seed=0)
    for i, stem in enumerate(stems):
        cv2.imwrite(str(tmp_path / f"{stem}.png"), room[i].image)
    seq = datasets.load_folder(tmp_path, trajectory=None, intrinsics=room.camera)
    assert seq.timestamps[0] == 0.0 and seq.timestamps[1] > 0  # not numbers: frames by name at the fallback rate
    assert [p.stem for p in seq.files] == sorted(stems)
