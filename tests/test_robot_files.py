"""A robot never crashes on a path, never loses a file, never gets a wrong error: the Python
API with odd file names (bytes that are not UTF-8), special files (FIFOs), outputs that alias
inputs, concurrent writers, damaged map headers and misbehaving descriptor networks."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

import geoloc
from cli_runner import checkout_env
from geoloc import datasets
from geoloc._images import write_image
from geoloc._io import check_output_path, refuse_alias, write_json_atomic

#: A FIFO test that takes longer than this has blocked on the FIFO.
FIFO_TIMEOUT_S = 60
#: A file name byte that is not UTF-8 (Python spells it as the surrogate U+DCFF).
ODD = os.fsdecode(b"\xff")
WRITERS = 8


@pytest.fixture(scope="module")
def small_map() -> geoloc.Map:
    room = datasets.synthetic_room(n_frames=12, seed=0)
    return geoloc.Map.build(room[:10], n_features=300, branching=4, depth=2)


def _python(code: str, *args: str, threads: str | None = "", timeout: float = FIFO_TIMEOUT_S
            ) -> subprocess.CompletedProcess[str]:
    """``code`` in a fresh interpreter with this checkout's package (so a crash or a blocked
    read is a failed assertion, not a dead or hung test run); ``threads`` sets
    GEOLOC_NUM_THREADS (None: unset; "" the default: as this process has it)."""
    env = dict(os.environ)
    if threads is None:
        env.pop("GEOLOC_NUM_THREADS", None)
    elif threads:
        env["GEOLOC_NUM_THREADS"] = threads
    env["PYTHONPATH"] = os.pathsep.join([str(Path(geoloc.__file__).parents[1]), env.get("PYTHONPATH", "")])
    return subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, env=env, timeout=timeout)


# ------------------------------------------------------------------ odd bytes in paths


def test_localize_a_missing_path_with_odd_bytes_names_it(small_map: geoloc.Map) -> None:
    """It segfaulted: cv2.imread got the surrogate-escaped name."""
    code = (
        "import geoloc, sys\n"
        "seq = geoloc.datasets.synthetic_room(n_frames=12, seed=0)\n"
        "loc = geoloc.Localizer(geoloc.Map.build(seq[:10], n_features=300, branching=4, depth=2))\n"
        "try:\n    loc.localize(sys.argv[1], 0.0)\n"
        "except geoloc.InvalidInputError as e:\n    print('refused:', e)\n"
    )
    result = _python(code, f"/tmp/no_such_{ODD}.jpg")
    assert result.returncode == 0, result.stderr
    assert "refused: image: file '/tmp/no_such_\\udcff.jpg' does not exist" in result.stdout, result.stdout


def test_images_with_odd_bytes_in_their_names_are_read(tmp_path: Path, small_map: geoloc.Map) -> None:
    room = datasets.synthetic_room(n_frames=12, seed=0)
    folder = tmp_path / f"images {ODD}\n-x"
    folder.mkdir()
    write_image(folder / f"{ODD}\udcfe1.png", room[5].image)  # a keyframe's view
    seq = datasets.load_folder(folder, trajectory=None, intrinsics=small_map.camera)
    assert seq.files == (folder / f"{ODD}\udcfe1.png",)
    np.testing.assert_array_equal(seq[0].image, room[5].image)
    by_path = geoloc.Localizer(small_map).localize(str(seq.files[0]), 0.0)
    by_pixels = geoloc.Localizer(small_map).localize(seq.gray(0), 0.0)
    assert (by_path.source, by_path.reason, by_path.inliers) == (by_pixels.source, by_pixels.reason, by_pixels.inliers)


def test_a_map_saves_and_loads_under_a_name_with_odd_bytes(tmp_path: Path, small_map: geoloc.Map) -> None:
    path = tmp_path / f"map {ODD}\n.geoloc"
    small_map.save(path)
    assert os.listdir(os.fsencode(tmp_path)) == [b"map \xff\n.geoloc"]
    assert len(geoloc.Map.load(path)) == len(small_map)


# ------------------------------------------------------------------ special files


@pytest.mark.parametrize(
    "call",
    [
        "geoloc.Map.load(path)",
        "geoloc.datasets.sequence.load_image(path, geoloc.Camera(525, 525, 320, 240))",
        "geoloc.OnnxDescriptor(path)",
        "geoloc.reference.load_reference(path)",
        "geoloc.datasets.sevenscenes.read_7scenes_pose(path)",
    ],
)
def test_a_fifo_is_named_and_never_opened(tmp_path: Path, call: str) -> None:
    fifo = tmp_path / "in.fifo"
    os.mkfifo(fifo)
    code = f"import sys, geoloc, geoloc.reference\npath = sys.argv[1]\ntry:\n    {call}\nexcept (geoloc.GeolocError) as e:\n    print('refused:', e)\n"
    result = _python(code, str(fifo))
    assert result.returncode == 0, result.stderr
    assert "refused:" in result.stdout and "is a FIFO, not a regular file" in result.stdout, result.stdout


def test_a_fifo_in_place_of_a_pose_file_is_named(tmp_path: Path) -> None:
    room = datasets.synthetic_room(n_frames=2, seed=0)
    for i in range(2):
        write_image(tmp_path / f"frame-{i:06d}.color.png", room[i].image)
    np.savetxt(tmp_path / "frame-000000.pose.txt", room.poses[0])
    os.mkfifo(tmp_path / "frame-000001.pose.txt")
    code = "import sys, geoloc\ntry:\n    geoloc.datasets.load_7scenes(sys.argv[1])\nexcept geoloc.DatasetError as e:\n    print('refused:', e)\n"
    result = _python(code, str(tmp_path))
    assert "frame-000001.pose.txt' is a FIFO, not a regular file" in result.stdout, result.stdout + result.stderr


def test_an_output_that_is_a_fifo_or_ends_in_a_separator_is_refused(tmp_path: Path) -> None:
    os.mkfifo(tmp_path / "out.fifo")
    with pytest.raises(geoloc.InvalidInputError, match="^out: .*is a FIFO"):
        check_output_path(tmp_path / "out.fifo", "out")
    with pytest.raises(geoloc.InvalidInputError, match="^out: .*names a folder"):
        check_output_path(str(tmp_path / "x") + "/", "out")
    with pytest.raises(geoloc.InvalidInputError, match="^out: the file name .* the folder allows"):
        check_output_path(tmp_path / ("a" * 300 + ".geoloc"), "out")
    # a file where a folder of the path should be: named as such, not as a missing folder
    (tmp_path / "afile").write_text("x")
    for path in (tmp_path / "afile" / "map.geoloc", tmp_path / "afile" / "sub" / "map.geoloc"):
        with pytest.raises(geoloc.InvalidInputError, match=r"^out: '.*afile' is a regular file, not a folder: cannot write"):
            check_output_path(path, "out")
    assert sorted(os.listdir(tmp_path)) == ["afile", "out.fifo"]


# ------------------------------------------------------------------ outputs that alias inputs


@pytest.mark.parametrize("alias", ["same", "dot", "symlink", "hardlink", "new"])
def test_refuse_alias_sees_through_every_spelling(tmp_path: Path, alias: str, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    data = tmp_path / "in.txt"
    data.write_text("input\n")
    out = {"same": str(data), "dot": "./in.txt", "symlink": "link.txt", "hardlink": "hard.txt", "new": "new.txt"}[alias]
    if alias == "symlink":
        os.symlink(data, out)
    if alias == "hardlink":
        os.link(data, out)
    if alias == "new":
        refuse_alias(out, "--out", [("--map", str(data))])  # a file that does not exist yet is never an input
        return
    with pytest.raises(geoloc.InvalidInputError, match="^--out: .* is the same file as the input --map"):
        refuse_alias(out, "--out", [("--map", str(data))])
    assert data.read_text() == "input\n"


def test_export_frames_refuses_to_overwrite_one_of_its_frames(tmp_path: Path, small_map: geoloc.Map) -> None:
    room = datasets.synthetic_room(n_frames=12, seed=0)
    write_image(tmp_path / "1.png", room[10].image)
    seq = datasets.load_folder(tmp_path, trajectory=None, intrinsics=small_map.camera)
    before = (tmp_path / "1.png").read_bytes()
    with pytest.raises(geoloc.InvalidInputError, match="^path: .* same file as the input frames"):
        geoloc.export_frames(small_map, seq, tmp_path / "1.png")
    assert (tmp_path / "1.png").read_bytes() == before


def test_export_frames_refuses_to_overwrite_an_image_of_its_pairs(tmp_path: Path, small_map: geoloc.Map) -> None:
    """It replaced the image: only a Sequence's files were checked, not (timestamp, path) pairs."""
    room = datasets.synthetic_room(n_frames=12, seed=0)
    for i in (0, 1):
        write_image(tmp_path / f"{i}.png", room[10 + i].image)
    before = (tmp_path / "1.png").read_bytes()
    pairs = [(0.0, tmp_path / "0.png"), (1.0, str(tmp_path / "1.png"))]
    with pytest.raises(geoloc.InvalidInputError, match=r"^path: .* same file as the input frames\[1\] image"):
        geoloc.export_frames(small_map, pairs, tmp_path / "1.png")
    assert (tmp_path / "1.png").read_bytes() == before
    assert geoloc.export_frames(small_map, pairs, tmp_path / "frames.bin") == 2


@pytest.mark.parametrize("alias", ["image", "symlink", "hardlink", "trajectory"])
def test_map_save_refuses_to_overwrite_a_file_the_map_was_built_from(tmp_path: Path, alias: str) -> None:
    """It replaced the image: ``Map.save`` checked only that the path was writable."""
    folder = datasets.synthetic_room(n_frames=12, seed=0)[:10].write_tum(tmp_path / "frames")
    seq = datasets.load_tum(folder)
    m = geoloc.Map.build(seq, n_features=300, branching=4, depth=2)
    trajectory = folder / "groundtruth.txt"
    input_file = trajectory if alias == "trajectory" else sorted((folder / "rgb").iterdir())[3]
    out = {"symlink": tmp_path / "link.geoloc", "hardlink": tmp_path / "hard.geoloc"}.get(alias, input_file)
    if alias == "symlink":
        os.symlink(input_file, out)
    if alias == "hardlink":
        os.link(input_file, out)
    before = input_file.read_bytes()
    with pytest.raises(geoloc.InvalidInputError, match="^path: .* is the same file as the input sequence"):
        m.save(out)
    assert input_file.read_bytes() == before
    m.save(tmp_path / "map.geoloc")  # any other path is written
    assert len(geoloc.Map.load(tmp_path / "map.geoloc")) == 10


def test_a_map_records_the_dataset_frame_numbers_of_its_keyframes() -> None:
    """It recorded positions in the sequence as sliced: seq[4:12][::2] gave [0, 2, 4, 6]."""
    room = datasets.synthetic_room(n_frames=12, seed=0)
    m = geoloc.Map.build(room[2:12][::2], n_features=300, branching=4, depth=2, keyframe_step=1)
    assert m.settings["source"]["frames"] == [2, 4, 6, 8, 10]
    m2 = geoloc.Map.build(room[2:12], n_features=300, branching=4, depth=2, keyframe_step=3)
    assert m2.settings["source"]["frames"] == [2, 5, 8, 11]


# ------------------------------------------------------------------ concurrent writers


def _concurrently(write: object, n: int = WRITERS) -> list[BaseException]:
    errors: list[BaseException] = []
    start = threading.Barrier(n)

    def run(k: int) -> None:
        start.wait()
        try:
            write(k)  # type: ignore[operator]
        except BaseException as e:  # noqa: BLE001 - collected and asserted on
            errors.append(e)

    threads = [threading.Thread(target=run, args=(k,)) for k in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return errors


def test_map_save_from_threads_to_one_path_leaves_one_complete_map(tmp_path: Path, small_map: geoloc.Map) -> None:
    """Eight threads save the map to one path at once: every save succeeds, the file loads and
    no temp file is left behind (each save needs its own temp name, not one per process)."""
    target = tmp_path / "shared.geoloc"
    errors = _concurrently(lambda k: small_map.save(target))
    assert not errors, [f"{type(e).__name__}: {e}" for e in errors]
    assert len(geoloc.Map.load(target)) == len(small_map)
    assert os.listdir(tmp_path) == ["shared.geoloc"]


def test_map_save_from_processes_to_one_path_leaves_one_complete_map(tmp_path: Path, small_map: geoloc.Map) -> None:
    source = tmp_path / "source.geoloc"
    small_map.save(source)
    target = tmp_path / "shared.geoloc"
    code = "import sys, geoloc\ngeoloc.Map.load(sys.argv[1]).save(sys.argv[2])\n"
    env = checkout_env()
    procs = [subprocess.Popen([sys.executable, "-c", code, str(source), str(target)], env=env) for _ in range(4)]
    assert [p.wait(timeout=120) for p in procs] == [0] * 4
    assert len(geoloc.Map.load(target)) == len(small_map)
    assert sorted(os.listdir(tmp_path)) == ["shared.geoloc", "source.geoloc"]


def test_json_writers_from_threads_leave_one_complete_version(tmp_path: Path) -> None:
    target = tmp_path / "r.json"
    versions = [{"writer": k, "values": list(range(1000 * k, 1000 * k + 500))} for k in range(WRITERS)]
    errors = _concurrently(lambda k: write_json_atomic(target, versions[k]))
    assert not errors
    assert json.loads(target.read_text()) in versions
    assert os.listdir(tmp_path) == ["r.json"]


# ------------------------------------------------------------------ what an output file is


def _plain_create_mode(folder: Path) -> int:
    """The permission bits a plain ``open(path, "w")`` gives a new file in ``folder``."""
    probe = folder / "plain-create-probe"
    probe.write_text("x")
    mode = stat.S_IMODE(probe.stat().st_mode)
    probe.unlink()
    return mode


@pytest.mark.skipif(not hasattr(os, "fchmod"), reason="POSIX permission bits")
def test_outputs_get_a_plain_creates_permissions_or_keep_the_replaced_files(tmp_path: Path,
                                                                            small_map: geoloc.Map) -> None:
    """Text outputs came out 0600 (mkstemp's mode): a viewer running as another user could
    not read the poses a robot wrote."""
    plain = _plain_create_mode(tmp_path)
    write_json_atomic(tmp_path / "new.json", {"a": 1})
    small_map.save(tmp_path / "new.geoloc")
    assert stat.S_IMODE((tmp_path / "new.json").stat().st_mode) == plain
    assert stat.S_IMODE((tmp_path / "new.geoloc").stat().st_mode) == plain
    for name, write in (("old.json", lambda p: write_json_atomic(p, {"b": 2})), ("old.geoloc", small_map.save)):
        target = tmp_path / name
        target.write_text("old")
        target.chmod(0o640)
        write(target)
        assert stat.S_IMODE(target.stat().st_mode) == 0o640, name


def test_outputs_are_written_through_a_symlink_and_refused_through_a_dangling_one(tmp_path: Path,
                                                                                  small_map: geoloc.Map) -> None:
    for name, write in (("r.json", lambda p: write_json_atomic(p, {"b": 2})), ("m.geoloc", small_map.save)):
        real, link = tmp_path / f"real-{name}", tmp_path / f"link-{name}"
        real.write_text("old")
        link.symlink_to(real.name)
        write(link)
        assert link.is_symlink() and real.read_bytes() != b"old", name
        dangling = tmp_path / f"dangling-{name}"
        dangling.symlink_to(f"nowhere-{name}")
        with pytest.raises(geoloc.InvalidInputError, match="dangling"):
            write(dangling)
        assert not (tmp_path / f"nowhere-{name}").exists()
    assert not [n for n in os.listdir(tmp_path) if n.endswith(".tmp")]


def test_a_map_of_featureless_images_says_so(tmp_path: Path) -> None:
    """Black images gave "descriptors: 0 descriptors cannot make 10 clusters", naming
    neither the images nor n_features."""
    root = datasets.synthetic_room(n_frames=6, seed=0)[:4].write_tum(tmp_path / "dark")
    for image in (root / "rgb").iterdir():
        write_image(image, np.zeros((480, 640, 3), np.uint8))
    with pytest.raises(geoloc.InvalidInputError, match=r"^sequence: its 4 keyframes' images gave 0 orb features in all \(n_features="):
        geoloc.Map.build(datasets.load_tum(root))


def test_a_path_with_a_nul_byte_is_named_for_it(tmp_path: Path, small_map: geoloc.Map) -> None:
    """It was "expected a file path (str or os.PathLike), got str" — for a str."""
    for call in (lambda: small_map.save(str(tmp_path / "x\x00y.geoloc")), lambda: geoloc.Map.load("x\x00y.geoloc")):
        with pytest.raises(geoloc.InvalidInputError, match="contains a NUL byte"):
            call()


def test_outputs_with_names_of_the_file_systems_full_length_are_written(tmp_path: Path, small_map: geoloc.Map) -> None:
    """The core's temp name repeated the whole target name and overflowed 255 bytes."""
    json_path, map_path = tmp_path / ("j" * 250 + ".json"), tmp_path / ("m" * 248 + ".geoloc")
    write_json_atomic(json_path, {"a": 1})
    small_map.save(map_path)
    assert json.loads(json_path.read_text()) == {"a": 1}
    assert len(geoloc.Map.load(map_path)) == len(small_map)
    assert sorted(os.listdir(tmp_path)) == sorted([json_path.name, map_path.name])


# ------------------------------------------------------------------ damaged map headers


@pytest.mark.parametrize("field", ["features", "camera", "retrieval", "features.n_features", "camera.width"])
def test_a_map_whose_frontend_lacks_a_field_is_a_format_error(tmp_path: Path, small_map: geoloc.Map, field: str) -> None:
    frontend = small_map.settings
    record, _, key = field.partition(".")
    if key:
        del frontend[record][key]
    else:
        del frontend[record]
    path = tmp_path / "m.geoloc"
    small_map._core.save(str(path), json.dumps(frontend))
    with pytest.raises(geoloc.FileFormatError, match=f"^path: .*m.geoloc'.*frontend.*{field}"):
        geoloc.Map.load(path)


# ------------------------------------------------------------------ descriptor networks


def test_a_model_with_a_fixed_batch_of_one_runs_image_by_image(tmp_path: Path) -> None:
    onnx_models = pytest.importorskip("onnx_models")
    pytest.importorskip("onnx")
    images = np.random.default_rng(1).integers(0, 255, size=(5, 60, 80, 3), dtype=np.uint8)
    free = geoloc.OnnxDescriptor(onnx_models.linear_model(tmp_path / "free.onnx"))
    for batch in (1, 3):
        fixed = geoloc.OnnxDescriptor(onnx_models.linear_model(tmp_path / f"fixed{batch}.onnx", batch=batch))
        assert fixed.fixed_batch == batch
        np.testing.assert_allclose(fixed(images), free(images), atol=1e-6)


@pytest.mark.parametrize(("bias", "what"), [(float("inf"), "non-finite descriptor"), (0.0, "all-zero descriptor")])
def test_a_model_that_gives_inf_or_zero_rows_is_refused(tmp_path: Path, bias: float, what: str) -> None:
    onnx_models = pytest.importorskip("onnx_models")
    pytest.importorskip("onnx")
    model = geoloc.OnnxDescriptor(onnx_models.linear_model(tmp_path / "bad.onnx", weight_scale=0.0, bias=bias))
    images = np.random.default_rng(1).integers(0, 255, size=(3, 60, 80, 3), dtype=np.uint8)
    with pytest.raises(geoloc.InvalidInputError, match=f"^images\\[0\\]: the network 'bad' gave an? {what}"):
        model(images)


# ------------------------------------------------------------------ image order


def test_numbered_images_are_in_number_order_and_their_times_agree(tmp_path: Path) -> None:
    room = datasets.synthetic_room(n_frames=3, seed=0)
    for k, number in enumerate((9, 10, 11)):
        write_image(tmp_path / f"{number}.png", room[k].image)
    seq = datasets.load_folder(tmp_path, trajectory=None, intrinsics=(525.0, 525.0, 320.0, 240.0))
    assert [p.name for p in seq.files] == ["9.png", "10.png", "11.png"]
    assert seq.timestamps.tolist() == [9.0, 10.0, 11.0]
    np.testing.assert_array_equal(seq[0].image, room[0].image)


def test_a_huge_file_that_is_not_a_map_is_refused_from_its_first_bytes(tmp_path: Path) -> None:
    """A mistaken --map (a 4 GiB file of zeros here, sparse) is refused from its header, not
    read whole into memory first: under a 1.5 GiB address-space limit the loader answers with a
    FileFormatError (it aborted on the 4 GiB allocation before)."""
    big = tmp_path / "big.geoloc"
    with open(big, "wb") as f:
        f.truncate(4 << 30)
    result = _python(
        "import resource, sys, geoloc\n"
        "resource.setrlimit(resource.RLIMIT_AS, (3 << 29, 3 << 29))\n"
        "try:\n"
        "    geoloc.Map.load(sys.argv[1])\n"
        "except geoloc.FileFormatError as e:\n"
        "    print('refused:', e)\n",
        str(big),
    )
    assert result.returncode == 0, result.stderr[-2000:]
    assert "refused:" in result.stdout and "header" in result.stdout, result.stdout


def test_a_map_with_bytes_appended_is_refused_naming_both_sizes(tmp_path: Path, small_map: geoloc.Map) -> None:
    path = tmp_path / "m.geoloc"
    small_map.save(path)
    size = path.stat().st_size
    with open(path, "ab") as f:
        f.write(b"\0" * 10)
    with pytest.raises(geoloc.FileFormatError, match=f"describes {size} bytes but the file holds {size + 10}"):
        geoloc.Map.load(path)


@pytest.mark.parametrize("threads", ["2", None])
def test_a_child_forked_after_the_pool_started_localizes(threads: str | None) -> None:
    """multiprocessing's fork start method copies the thread pool but not its threads: a child
    forked after the parent ran a parallel loop used to wait forever on it. It now runs its
    loops on its own thread and gets the parent's answer bit for bit."""
    code = (
        "import multiprocessing as mp, sys, geoloc\n"
        "room = geoloc.datasets.synthetic_room(n_frames=80, seed=0)\n"
        "m = geoloc.Map.build(room[:40], keyframe_step=2, n_features=500)\n"
        "fr = room[50]\n"
        "def pose():\n"
        "    r = geoloc.Localizer(m).localize(fr.image, fr.timestamp)\n"
        "    return None if r.pose is None else r.pose.tobytes()\n"
        "parent = pose()\n"
        "assert parent is not None\n"
        "def child(q):\n"
        "    q.put(pose())\n"
        "ctx = mp.get_context('fork'); q = ctx.Queue(); p = ctx.Process(target=child, args=(q,))\n"
        "p.start(); p.join(60)\n"
        "if p.is_alive():\n"
        "    p.kill(); print('child hung'); sys.exit(1)\n"
        "print('same' if q.get() == parent else 'different', p.exitcode)\n"
    )
    result = _python(code, threads=threads, timeout=240)
    assert result.returncode == 0, result.stdout + result.stderr[-2000:]
    assert result.stdout.strip() == "same 0"


def test_reset_waits_for_another_threads_frame_without_the_gil(small_map: geoloc.Map) -> None:
    """reset() while another thread is inside localize waits for that frame; it must wait as
    localize does, without the GIL — holding it stalled every Python thread of the process for
    the frame's length (a robot's watchdog and I/O threads among them). The main thread keeps
    running Python while a reset waits: it records times the whole test through."""
    import time

    room = datasets.synthetic_room(n_frames=12, seed=0)
    features = [small_map.features(room.gray(i), small_map.camera) for i in range(10, 12)]
    loc = geoloc.Localizer(small_map)
    done = threading.Event()
    waits: list[tuple[float, float]] = []

    def localizing() -> None:
        k = 0
        while not done.is_set():
            f = features[k % 2]
            loc.localize_features(float(k), f.keypoints, f.descriptors, pixel_sigmas=f.pixel_sigmas)
            k += 1

    def resetting() -> None:
        for _ in range(400):
            start = time.perf_counter()
            loc.reset()
            waits.append((start, time.perf_counter()))
            time.sleep(0.0005)
        done.set()

    threads = [threading.Thread(target=localizing), threading.Thread(target=resetting)]
    for t in threads:
        t.start()
    ticks = []
    while not done.is_set():
        ticks.append(time.perf_counter())
    for t in threads:
        t.join()
    ticks_array = np.array(ticks)
    # resets that waited for a frame (a reset alone takes microseconds)
    long_waits = [(a, b) for a, b in waits if b - a > 2e-3]
    assert len(long_waits) >= 5, f"the localizing thread held the lock in only {len(long_waits)} resets"
    # inside each such wait (less a margin for taking the GIL back), the main thread ran
    ran = [np.any((ticks_array > a) & (ticks_array < b - 1e-3)) for a, b in long_waits]
    assert np.mean(ran) > 0.5, f"the main thread ran during {sum(ran)} of {len(long_waits)} waiting resets"


def test_export_frames_refuses_to_overwrite_the_map_file_it_was_loaded_from(tmp_path: Path, small_map: geoloc.Map) -> None:
    """The map's own file is an input of the export as much as the images are (also through a
    symlink); saving the map back to it stays allowed."""
    small_map.save(tmp_path / "room.geoloc")
    (tmp_path / "link.geoloc").symlink_to(tmp_path / "room.geoloc")
    before = (tmp_path / "room.geoloc").read_bytes()
    loaded = geoloc.Map.load(tmp_path / "room.geoloc")
    room = datasets.synthetic_room(n_frames=12, seed=0)
    pairs = [(0.0, room[10].image)]
    for target in ("room.geoloc", "link.geoloc"):
        with pytest.raises(geoloc.InvalidInputError, match=r"^path: .* same file as the input map"):
            geoloc.export_frames(loaded, pairs, tmp_path / target)
    assert (tmp_path / "room.geoloc").read_bytes() == before
    loaded.save(tmp_path / "room.geoloc")
    assert (tmp_path / "room.geoloc").read_bytes() == before


def test_export_frames_refuses_a_sequence_whose_timestamps_go_back(tmp_path: Path, small_map: geoloc.Map) -> None:
    """geoloc-rs reads frames in time order: a reversed Sequence is refused before anything is written."""
    room = datasets.synthetic_room(n_frames=12, seed=0)
    for i in range(4):
        write_image(tmp_path / f"{i}.png", room[8 + i].image)
    seq = datasets.load_folder(tmp_path, trajectory=None, intrinsics=small_map.camera)
    with pytest.raises(geoloc.InvalidInputError, match=r"^frames: timestamps\[1\] = .* does not increase"):
        geoloc.export_frames(small_map, seq[::-1], tmp_path / "frames.bin")
    assert not (tmp_path / "frames.bin").exists()
    assert geoloc.export_frames(small_map, seq, tmp_path / "frames.bin") == 4


def test_export_frames_names_the_frame_whose_image_is_wrong(tmp_path: Path, small_map: geoloc.Map) -> None:
    room = datasets.synthetic_room(n_frames=12, seed=0)
    pairs = [(0.0, room[10].image), (1.0, np.zeros((5, 5), dtype=np.uint8))]
    with pytest.raises(geoloc.InvalidInputError, match=r"^frames\[1\] image: "):
        geoloc.export_frames(small_map, pairs, tmp_path / "frames.bin")
    assert not (tmp_path / "frames.bin").exists()
