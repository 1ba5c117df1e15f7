"""geoloc.mapping: Map.build / save / load and the image-level Localizer, on a small room."""

from __future__ import annotations

import pickle
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import geoloc
from cli_runner import checkout_env
from geoloc import datasets, evaluation
from geoloc import Localizer, Map

#: Two laps of 40 frames (9° apart): lap 1 is the map, lap 2 the queries.
ROOM_FRAMES = 40
MAP_FRAMES = slice(0, ROOM_FRAMES // 2)
QUERIES = (21, 27, 33)
#: Lap-2 frames localize against a lap-1 map to a few mm (≤ 1 cm / 0.3° median).
MEDIAN_M = 0.01
MEDIAN_DEG = 0.3


@pytest.fixture(scope="module")
def room() -> datasets.Sequence:
    return datasets.synthetic_room(n_frames=ROOM_FRAMES)


@pytest.fixture(scope="module")
def room_map(room: datasets.Sequence) -> Map:
    return Map.build(room[MAP_FRAMES])


def _localize_queries(m: Map, room: datasets.Sequence) -> list[object]:
    loc = Localizer(m)
    out = []
    for i in QUERIES:
        loc.reset()
        out.append(loc.localize(room.gray(i), float(room.timestamps[i])))
    return out


def _poses_in_a_new_process(the_map: str, *args: str, stdin: bytes | None = None) -> list[str]:
    """The poses (hex of their bytes) of the :data:`QUERIES`, each localized afresh, in a new
    Python process against the map the expression ``the_map`` gives there (``args`` its
    ``sys.argv[1:]``, ``stdin`` its standard input)."""
    script = (
        "import pickle, sys; import geoloc; from geoloc import datasets\n"
        f"room = datasets.synthetic_room(n_frames={ROOM_FRAMES}); loc = geoloc.Localizer({the_map})\n"
        f"for i in {QUERIES!r}:\n"
        "    loc.reset(); print(loc.localize(room.gray(i), float(room.timestamps[i])).pose.tobytes().hex())\n"
    )
    out = subprocess.run([sys.executable, "-c", script, *args], input=stdin, capture_output=True, env=checkout_env(), check=True)
    return out.stdout.decode().split()


# ---------------------------------------------------------------------------- build


def test_build_records_what_it_was_built_from(room_map: Map) -> None:
    assert len(room_map) == ROOM_FRAMES // 2
    s = room_map.settings
    assert s["features"] == {"kind": "orb", "n_features": 1000, "root_sift": False}
    assert s["retrieval"] == "bow"
    assert s["source"]["frames"] == list(range(ROOM_FRAMES // 2))
    assert room_map.camera.intrinsics == datasets.synthetic.SYNTHETIC_CAMERA.intrinsics
    assert "20 keyframes" in repr(room_map)


def test_build_reports_progress_and_keyframe_step(room: datasets.Sequence) -> None:
    calls: list[tuple[int, int]] = []
    m = Map.build(room[0:10], keyframe_step=3, progress=lambda done, total: calls.append((done, total)))
    assert len(m) == 4 and calls == [(1, 4), (2, 4), (3, 4), (4, 4)]


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [({"retrieval": "vlad"}, "retrieval"), ({"retrieval": 3}, "retrieval"), ({"features": "akaze"}, "features"), ({"features": "ORB"}, "features"),
     ({"keyframe_step": 0}, "keyframe_step"), ({"n_features": 0}, "n_features")],
)
def test_build_refuses_bad_options(room: datasets.Sequence, kwargs: dict[str, object], name: str) -> None:
    with pytest.raises(geoloc.InvalidInputError, match=f"^{name}:"):
        Map.build(room[0:4], **kwargs)  # type: ignore[arg-type]


def test_build_needs_a_sequence_with_poses(room: datasets.Sequence) -> None:
    with pytest.raises(geoloc.InvalidInputError, match="sequence"):
        Map.build([room[0]])  # type: ignore[arg-type]
    blind = datasets.Sequence("blind", room.camera, room.timestamps[:3], None, lambda i, gray: room.gray(i) if gray else room[i].image)
    with pytest.raises(geoloc.InvalidInputError, match="no poses"):
        Map.build(blind)


# ---------------------------------------------------------------------------- localize


def test_held_out_frames_localize_to_a_centimetre(room_map: Map, room: datasets.Sequence) -> None:
    results = _localize_queries(room_map, room)
    assert all(r.source == "geometric" and r.pose is not None for r in results)  # type: ignore[attr-defined]
    trans, rot = evaluation.pose_errors(np.stack([r.pose for r in results]), room.poses[list(QUERIES)])  # type: ignore[attr-defined, index]
    assert np.median(trans) <= MEDIAN_M and np.median(rot) <= MEDIAN_DEG
    r = results[0]
    assert r.covariance.shape == (6, 6)  # type: ignore[attr-defined]
    assert {"decode", "features", "retrieval", "pnp", "total"} <= set(r.timings)  # type: ignore[attr-defined]


def test_grey_bgr_and_path_inputs_agree_bit_for_bit(room_map: Map, room: datasets.Sequence, tmp_path: Path) -> None:
    """BGR is converted as cv2.cvtColor does; a path is decoded as grey by cv2.imread, whose
    luma rounding differs (by one level) from cvtColor's, so each pair is compared with its own."""
    import cv2

    i = QUERIES[0]
    bgr = room[i].image
    path = tmp_path / "q.png"
    cv2.imwrite(str(path), bgr)

    def pose(image: object) -> bytes:
        return Localizer(room_map).localize(image, float(room.timestamps[i])).pose.tobytes()  # type: ignore[union-attr]

    assert pose(bgr) == pose(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))
    assert pose(str(path)) == pose(cv2.imread(str(path), cv2.IMREAD_GRAYSCALE))


def test_a_network_callable_sees_grey_images_at_build_and_at_query(room: datasets.Sequence, tmp_path: Path) -> None:
    """A retrieval callable (images → (N, D)) gets (H, W) grey images from Map.build, and the
    same kind of image from Localizer.localize — given BGR, grey or a path — and from
    export_frames given BGR (what geoloc-rs then localizes must be what localize computes)."""
    import cv2

    from geoloc import export_frames
    from geoloc.descriptor import tiny_image_descriptors

    seen: list[tuple[int, ...]] = []

    def network(images: list[np.ndarray]) -> np.ndarray:
        seen.extend(np.asarray(image).shape for image in images)
        return tiny_image_descriptors(images)

    m = Map.build(room[MAP_FRAMES], network)
    assert seen and set(seen) == {(room.camera.height, room.camera.width)}
    i = QUERIES[0]
    bgr = room[i].image
    seen.clear()
    path = tmp_path / "q.png"
    cv2.imwrite(str(path), bgr)
    results = [Localizer(m, global_descriptor=network).localize(image, float(room.timestamps[i]))
               for image in (bgr, cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), str(path))]
    assert seen == [(room.camera.height, room.camera.width)] * 3
    assert results[0].pose is not None and results[0].pose.tobytes() == results[1].pose.tobytes()
    seen.clear()
    export_frames(m, [(float(room.timestamps[i]), bgr)], tmp_path / "q.frames", global_descriptor=network)
    assert seen == [(room.camera.height, room.camera.width)]


def test_reset_forgets_the_history(room_map: Map, room: datasets.Sequence) -> None:
    loc = Localizer(room_map)
    for i in (21, 22, 23):
        last = loc.localize(room.gray(i), float(room.timestamps[i]))
    assert last.source != "geometric" or "no motion history" not in last.reason
    loc.reset()
    again = loc.localize(room.gray(24), float(room.timestamps[24]))
    assert again.source == "geometric" and "no motion history" in again.reason


def test_localizer_refuses_bad_inputs(room_map: Map, tmp_path: Path) -> None:
    with pytest.raises(geoloc.InvalidInputError, match="map"):
        Localizer("scene.geoloc")  # type: ignore[arg-type]
    with pytest.raises(geoloc.InvalidInputError, match="camera"):
        Localizer(room_map, geoloc.Camera(500.0, 500.0, 320.0, 240.0, 640, 480))
    with pytest.raises(geoloc.InvalidInputError, match=r"^camera: .*locator='paper'"):
        Localizer(room_map, "paper")  # type: ignore[arg-type]
    loc = Localizer(room_map)
    with pytest.raises(geoloc.InvalidInputError, match="image.*320×240"):
        loc.localize(np.zeros((240, 320), np.uint8), 0.0)
    with pytest.raises(geoloc.InvalidInputError, match="image"):
        loc.localize(str(tmp_path / "missing.png"), 0.0)
    with pytest.raises(geoloc.InvalidInputError, match="dtype"):
        loc.localize(np.zeros((480, 640), np.float32), 0.0)


# ---------------------------------------------------------------------------- files


def test_a_saved_map_gives_bit_identical_results_in_a_new_process(room_map: Map, room: datasets.Sequence, tmp_path: Path) -> None:
    path = tmp_path / "room.geoloc"
    room_map.save(path)
    expected = [r.pose.tobytes().hex() for r in _localize_queries(room_map, room)]  # type: ignore[attr-defined]
    assert _poses_in_a_new_process("geoloc.Map.load(sys.argv[1])", str(path)) == expected
    loaded = Map.load(path)
    assert loaded.settings == room_map.settings and len(loaded) == len(room_map)
    assert loaded.camera.intrinsics == room_map.camera.intrinsics


def test_damaged_map_files_are_refused(room_map: Map, tmp_path: Path) -> None:
    path = tmp_path / "room.geoloc"
    room_map.save(path)
    data = path.read_bytes()
    bad = tmp_path / "bad.geoloc"
    cuts = sorted({0, 1, 7, 8, 9, 64, len(data) // 2, len(data) - 1})
    for cut in cuts:
        bad.write_bytes(data[:cut])
        with pytest.raises(geoloc.GeolocError):
            Map.load(bad)
    header_len = int.from_bytes(data[:8], "little") if len(data) > 8 else 0
    for offset in sorted({8, 8 + header_len // 2, 8 + max(header_len - 1, 0)}):
        flipped = bytearray(data)
        flipped[offset] ^= 0x01
        bad.write_bytes(bytes(flipped))
        with pytest.raises(geoloc.GeolocError):
            Map.load(bad)
    with pytest.raises(geoloc.GeolocError):
        Map.load(tmp_path / "missing.geoloc")


def test_a_map_travels_as_its_file_bytes_and_pickles_into_another_process(
    room_map: Map, room: datasets.Sequence, tmp_path: Path
) -> None:
    """``to_bytes`` is the saved file byte for byte; ``from_bytes`` and a pickle (sent to a new
    process, as a process pool sends it) give the same map: the same settings and bit-identical
    answers."""
    path = tmp_path / "room.geoloc"
    room_map.save(path)
    data = room_map.to_bytes()
    assert data == path.read_bytes()
    expected = [r.pose.tobytes().hex() for r in _localize_queries(room_map, room)]  # type: ignore[attr-defined]
    for copy in (Map.from_bytes(data), Map.from_bytes(bytearray(data)), pickle.loads(pickle.dumps(room_map))):
        assert copy.settings == room_map.settings and copy.camera.intrinsics == room_map.camera.intrinsics
        assert [r.pose.tobytes().hex() for r in _localize_queries(copy, room)] == expected  # type: ignore[attr-defined]
        assert copy.to_bytes() == data
    assert _poses_in_a_new_process("pickle.loads(sys.stdin.buffer.read())", stdin=pickle.dumps(room_map)) == expected


def test_bad_map_bytes_are_refused_naming_the_argument(room_map: Map) -> None:
    data = room_map.to_bytes()
    for cut in sorted({0, 1, 8, 64, len(data) // 2, len(data) - 1}):
        with pytest.raises(geoloc.FileFormatError, match="^data: "):
            Map.from_bytes(data[:cut])
    flipped = bytearray(data)
    flipped[-1] ^= 1
    with pytest.raises(geoloc.FileFormatError, match="^data: .*checksum mismatch"):
        Map.from_bytes(flipped)
    for wrong in (None, "room.geoloc", Path("room.geoloc"), [1, 2]):
        with pytest.raises(geoloc.InvalidInputError, match="^data: expected the bytes of a saved map"):
            Map.from_bytes(wrong)  # type: ignore[arg-type]
    other = Map(room_map._core, room_map._camera, room_map._extractor, {**room_map._frontend, "version": 2})
    with pytest.raises(geoloc.FileFormatError, match=r"^data: its frontend record \(version 2\)"):
        Map.from_bytes(other.to_bytes())


def test_an_unpickled_map_still_refuses_to_save_over_its_inputs(room_map: Map, tmp_path: Path) -> None:
    image = tmp_path / "frame-000000.color.png"
    image.write_bytes(b"an input image")
    built = Map(room_map._core, room_map._camera, room_map._extractor, room_map._frontend, (("sequence", image),))
    with pytest.raises(geoloc.InvalidInputError, match="same file as the input sequence"):
        pickle.loads(pickle.dumps(built)).save(image)
    assert image.read_bytes() == b"an input image"


def test_a_localizer_is_not_pickled_and_says_what_to_pickle(room_map: Map) -> None:
    with pytest.raises(TypeError, match="pickle its map"):
        pickle.dumps(Localizer(room_map))


def test_a_map_of_another_frontend_version_is_a_file_format_error(room_map: Map, tmp_path: Path) -> None:
    """A file whose checksum holds but whose frontend record is of another version (a newer
    package wrote it) is refused as a file-format error naming the file, like any other file
    this package cannot read."""
    for version in (2, None, [1]):
        other = Map(room_map._core, room_map._camera, room_map._extractor, {**room_map._frontend, "version": version})
        path = tmp_path / f"v{version}.geoloc"
        other.save(path)
        with pytest.raises(geoloc.FileFormatError, match=re.escape(f"v{version}.geoloc") + ".*" + re.escape(f"version {version!r}")):
            Map.load(path)


def test_save_refuses_a_missing_folder_and_keeps_the_old_file(room_map: Map, tmp_path: Path) -> None:
    with pytest.raises(geoloc.InvalidInputError, match="does not exist"):
        room_map.save(tmp_path / "no" / "room.geoloc")
    assert not (tmp_path / "no").exists()
    path = tmp_path / "room.geoloc"
    room_map.save(path)
    before = path.read_bytes()
    room_map.save(path)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["room.geoloc"]  # no temp files left
