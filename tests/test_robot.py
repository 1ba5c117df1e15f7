"""The robot binary ``geoloc-rs`` against the Python localizer: a map built and frames
exported from Python, localized by ``geoloc-rs localize`` — the same poses, covariances and
sources as :class:`geoloc.Localizer` on the same frames, bit for bit; bad input refused
with the frame named and the lines already written kept.

The binary is built once per session (``cargo build --release -p geoloc-cli``; a no-op
when it is up to date); the tests skip when neither it nor cargo is available.
"""

from __future__ import annotations

import math
import os
import resource
import shutil
import struct
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import geoloc
from geoloc import datasets, lie
from geoloc._core import FrameWriter

pytestmark = pytest.mark.slow  # builds geoloc-rs (cargo build --release) and runs it

ROOT = Path(__file__).resolve().parents[1]
BINARY = ROOT / "target" / "release" / "geoloc-rs"
REDKITCHEN = ROOT.parent / "shared" / "data" / "7scenes-redkitchen"
#: The synthetic room: two laps; lap 1 (frames 0–29) is the map, lap 2 the queries.
ROOM_FRAMES = 60
MAP_FRAMES = slice(0, 30)
QUERY_FRAMES = slice(30, 60)
#: Columns of a pose line: TUM (8), source, 21 covariance entries.
COLUMNS = 30
UPPER = np.triu_indices(6)


@pytest.fixture(scope="session")
def geoloc_rs() -> Path:
    cargo = shutil.which("cargo")
    if cargo is not None:
        build = subprocess.run(
            [cargo, "build", "--release", "-p", "geoloc-cli"], cwd=ROOT, capture_output=True, text=True
        )
        assert build.returncode == 0, build.stderr[-3000:]
    if not BINARY.is_file():
        pytest.skip(f"geoloc-rs not built at {BINARY} and no cargo to build it")
    return BINARY


def _run(binary: Path, *args: str, stdin: bytes | None = None) -> subprocess.CompletedProcess[str]:
    env = {"GEOLOC_NUM_THREADS": "1", "PATH": "/usr/bin:/bin"}
    return subprocess.run(
        [str(binary), *args], input=None if stdin is None else stdin.decode("latin-1"), capture_output=True,
        text=True, timeout=600, env=env, encoding="latin-1",
    )


@pytest.fixture(scope="module")
def room() -> datasets.Sequence:
    return datasets.synthetic_room(n_frames=ROOM_FRAMES)


@pytest.fixture(scope="module")
def room_map(room: datasets.Sequence, tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("robot") / "room.geoloc"
    geoloc.Map.build(room[MAP_FRAMES]).save(path)
    return path


def _python_lines(map_path: Path, frames: datasets.Sequence) -> list[tuple[list[float], str]]:
    """What geoloc.Localizer says, frame after frame: (30 numbers but the source, source)."""
    loc = geoloc.Localizer(geoloc.Map.load(map_path))
    out = []
    for i in range(len(frames)):
        t = float(frames.timestamps[i])
        r = loc.localize(frames.gray(i), t)
        if r.pose is None:
            values = [t] + [math.nan] * (7 + 21)
        else:
            tum = [float(v) for v in geoloc.format_tum_line(t, r.pose).split()]
            values = tum + [float(v) for v in np.asarray(r.covariance)[UPPER]]
        out.append((values, r.source))
    return out


def _parse(stdout: str) -> list[tuple[list[float], str]]:
    lines = stdout.splitlines()
    assert lines[0].startswith("# timestamp tx ty tz qx qy qz qw source cov_upper_21")
    out = []
    for line in lines[1:]:
        cols = line.split(" ")
        assert len(cols) == COLUMNS, line
        out.append(([float(c) for c in cols[:8] + cols[9:]], cols[8]))
    return out


def _assert_bit_identical(got: list[tuple[list[float], str]], want: list[tuple[list[float], str]]) -> None:
    assert len(got) == len(want)
    for i, ((g, gs), (w, ws)) in enumerate(zip(got, want)):
        assert gs == ws, f"frame {i}: source {gs} != {ws}"
        g_bits = np.array(g, dtype=np.float64).view(np.uint64)
        w_bits = np.array(w, dtype=np.float64).view(np.uint64)
        both_nan = np.isnan(g) & np.isnan(w)
        assert np.array_equal(g_bits[~both_nan], w_bits[~both_nan]), f"frame {i}: {g} != {w}"


def _localize(binary: Path, map_path: Path, frames: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    return _run(binary, "localize", "--map", str(map_path), "--input", str(frames), *extra)


# ------------------------------------------------------------------ same bits as Python


@pytest.mark.parametrize("fmt", ["binary", "jsonl"])
def test_geoloc_rs_gives_the_python_localizers_bits(
    geoloc_rs: Path, room: datasets.Sequence, room_map: Path, tmp_path: Path, fmt: str
) -> None:
    queries = room[QUERY_FRAMES]
    frames = tmp_path / f"frames.{fmt}"
    m = geoloc.Map.load(room_map)
    assert geoloc.export_frames(m, queries, frames, format=fmt) == len(queries)  # type: ignore[arg-type]
    result = _localize(geoloc_rs, room_map, frames, "--format", fmt, "--threads", "1")
    assert result.returncode == 0, result.stderr
    got = _parse(result.stdout)
    want = _python_lines(room_map, queries)
    _assert_bit_identical(got, want)
    sources = {s for _, s in got}
    assert sources & {"fused", "geometric"}, sources


class TinyImageNetwork:
    """A deterministic stand-in for a descriptor network: the tiny-image descriptor, with the
    name and sha256 a map records."""

    name, sha256, dim = "tiny-image", "0" * 64, 32 * 24

    def __call__(self, images: list[np.ndarray]) -> np.ndarray:
        return geoloc.descriptor.tiny_image_descriptors(images)


def test_geoloc_rs_localizes_a_fused_map_as_python_does(geoloc_rs: Path, room: datasets.Sequence, tmp_path: Path) -> None:
    """A map built with a network fuses it with BoW; geoloc-rs reads it, needs each frame's
    global descriptor, and gives Python's bits."""
    net = TinyImageNetwork()
    path = tmp_path / "fused.geoloc"
    geoloc.Map.build(room[MAP_FRAMES], retrieval=net).save(path)
    m = geoloc.Map.load(path)
    assert m.settings["retrieval"]["name"] == "tiny-image" and m._core.retrieval == "fused"
    info = _run(geoloc_rs, "info", str(path))
    assert "bag of words (" in info.stdout and "768-value global descriptor" in info.stdout, info.stdout
    queries = room[QUERY_FRAMES]
    frames = tmp_path / "frames.bin"
    geoloc.export_frames(m, queries, frames, global_descriptor=net)
    result = _localize(geoloc_rs, path, frames, "--threads", "1")
    assert result.returncode == 0, result.stderr
    loc = geoloc.Localizer(m, global_descriptor=net)
    want = []
    for i in range(len(queries)):
        t = float(queries.timestamps[i])
        r = loc.localize(queries.gray(i), t)
        values = [t] + [math.nan] * 28 if r.pose is None else (
            [float(v) for v in geoloc.format_tum_line(t, r.pose).split()] + [float(v) for v in np.asarray(r.covariance)[UPPER]])
        want.append((values, r.source))
    got = _parse(result.stdout)
    _assert_bit_identical(got, want)
    assert {s for _, s in got} & {"fused", "geometric"}
    # frames without the global descriptor are refused, naming the frame
    plain = tmp_path / "plain.bin"
    geoloc.export_frames(geoloc.Map.build(room[MAP_FRAMES]), queries[:2], plain)
    refused = _localize(geoloc_rs, path, plain)
    assert refused.returncode != 0 and "frame 0: the map retrieves by a 768-value global descriptor" in refused.stderr, refused.stderr


def test_stdin_threads_output_file_and_stats(geoloc_rs: Path, room: datasets.Sequence, room_map: Path, tmp_path: Path) -> None:
    queries = room[30:38]
    frames = tmp_path / "frames.bin"
    geoloc.export_frames(geoloc.Map.load(room_map), queries, frames)
    first = _localize(geoloc_rs, room_map, frames, "--threads", "1")
    out = tmp_path / "poses.txt"
    piped = _run(geoloc_rs, "localize", "--map", str(room_map), "--input", "-", "--output", str(out), "--threads", "2",
                 "--stats", stdin=frames.read_bytes())
    assert piped.returncode == 0, piped.stderr
    assert out.read_text() == first.stdout  # same bytes whatever the thread count
    assert "8 frames" in piped.stderr and "frames/s" in piped.stderr and "peak RSS" in piped.stderr
    # benchmarks/robot.py --json reads the summary's numbers
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    try:
        import robot as robot_benchmark
    finally:
        sys.path.pop(0)
    stats = robot_benchmark.parse_stats(piped.stderr)
    assert stats["frames"] == 8 and float(stats["frames_per_s"]) > 0  # type: ignore[arg-type]
    assert sum(stats["sources"].values()) == 8, stats  # type: ignore[attr-defined]
    assert {"retrieval", "total"} <= set(stats["median_ms"]), stats  # type: ignore[arg-type]
    assert float(stats["peak_rss_mib"]) > 0  # type: ignore[arg-type]
    # the first eight columns read as a TUM trajectory
    tum = np.loadtxt(out, usecols=range(8))
    assert tum.shape == (8, 8) and np.all(np.diff(tum[:, 0]) > 0)


def test_info_describes_the_map(geoloc_rs: Path, room_map: Path) -> None:
    result = _run(geoloc_rs, "info", str(room_map))
    assert result.returncode == 0, result.stderr
    for want in ("geoloc-map version 1", "keyframes         30", "binary (32 bytes, Hamming)", "orb, 1000 per image",
                 "bag of words", "pose covariances  ", "pose labels       ", "camera estimate   ", f"{room_map.stat().st_size} bytes",
                 "map noise         C_map "):  # the output is read as latin-1: ASCII only here
        assert want in result.stdout, (want, result.stdout)


@pytest.mark.skipif(not REDKITCHEN.is_dir(), reason=f"7-Scenes sample data not found at {REDKITCHEN} (see ../shared/data/README.md)")
def test_geoloc_rs_gives_the_python_localizers_bits_on_7scenes(geoloc_rs: Path, tmp_path: Path) -> None:
    seq = datasets.load_7scenes(REDKITCHEN)
    map_path = tmp_path / "kitchen.geoloc"
    geoloc.Map.build(seq[0:600:3]).save(map_path)
    queries = seq[600:700:5]
    frames = tmp_path / "frames.bin"
    geoloc.export_frames(geoloc.Map.load(map_path), queries, frames)
    result = _localize(geoloc_rs, map_path, frames, "--threads", "1", "--stats")
    assert result.returncode == 0, result.stderr
    print("\n" + result.stderr)
    _assert_bit_identical(_parse(result.stdout), _python_lines(map_path, queries))
    # --camera-pose: the camera's own pose (Python's camera_pose, bit for bit), and the
    # covariance C_cam = Ad_{X⁻¹} C_label Ad_{X⁻¹}ᵀ + Σ_X, X = T_label⁻¹ T_cam (the map's offset),
    # Σ_X one matrix for every frame, its σ those the label report gives for the offset
    camera_out = _localize(geoloc_rs, map_path, frames, "--threads", "1", "--camera-pose").stdout
    # the header says which pose the file holds
    assert camera_out.splitlines()[0].endswith("; pose: world_from_cam: the camera's own pose")
    assert result.stdout.splitlines()[0].endswith("; pose: world_from_cam in the convention of the map's pose labels")
    camera = _parse(camera_out)
    loaded = geoloc.Map.load(map_path)
    loc = geoloc.Localizer(loaded)
    apart, offsets = [], []
    for i, ((values, source), (label_values, _)) in enumerate(zip(camera, _parse(result.stdout))):
        r = loc.localize(queries.gray(i), float(queries.timestamps[i]))
        assert source == r.source
        if r.pose is None:
            continue
        want = [float(v) for v in geoloc.format_tum_line(float(queries.timestamps[i]), r.camera_pose).split()]
        assert np.array_equal(np.array(values[:8]).view(np.uint64), np.array(want).view(np.uint64)), (i, values[:8], want)
        x = lie.se3_compose(lie.se3_inverse(r.pose), r.camera_pose)
        c_cam = np.zeros((6, 6))
        c_cam[UPPER] = values[8:]
        c_cam = c_cam + np.triu(c_cam, 1).T
        assert r.camera_covariance is not None
        assert np.array_equal(np.array(values[8:]).view(np.uint64), r.camera_covariance[UPPER].view(np.uint64)), i
        # both covariances exactly symmetric: a file keeps one triangle, a Cholesky reads the other
        assert np.array_equal(r.covariance, r.covariance.T) and np.array_equal(r.camera_covariance, r.camera_covariance.T)
        ad_inv = lie.se3_adjoint(lie.se3_inverse(x))
        offsets.append(c_cam - ad_inv @ r.covariance @ ad_inv.T)
        apart.append(np.linalg.norm(x[:3, 3]))
    assert apart and min(apart) > 0.05, apart  # the labels track the depth camera, ≈ 17 cm away
    labels = loaded.labels
    assert labels is not None
    # the offset in full: Map.labels and geoloc-rs info give the X every answer applies, exactly
    offset = np.array(labels["label_from_cam"])
    np.testing.assert_allclose(offset, x, atol=1e-12)
    line = next(s for s in _run(geoloc_rs, "info", str(map_path)).stdout.splitlines() if s.startswith("label_from_cam"))
    rows = line[line.index("[") + 1:line.index("]")].split(";")
    assert np.array_equal(np.array([[float(v) for v in row.split()] for row in rows]), offset[:3]), (line, offset)
    sigma = np.r_[labels["label_from_cam_translation_sigma_m"], np.radians(labels["label_from_cam_rotation_sigma_deg"])]
    offset_covariance = np.array(labels["label_from_cam_covariance"])
    for sigma_x in offsets:
        np.testing.assert_allclose(sigma_x, offsets[0], rtol=1e-6, atol=1e-12)
        np.testing.assert_allclose(np.sqrt(np.diag(sigma_x)), sigma, rtol=1e-6)
        np.testing.assert_allclose(sigma_x, offset_covariance, rtol=1e-6, atol=1e-9 * float(np.abs(offset_covariance).max()))


# ------------------------------------------------------------------ bad input


def _fnv1a(data: bytes) -> int:
    h = 0xCBF29CE484222325
    for b in data:
        h = ((h ^ b) * 0x100000001B3) & 0xFFFFFFFFFFFFFFFF
    return h


def _raw_record(t: float, keypoints: np.ndarray, sigmas: np.ndarray, descriptors: np.ndarray) -> bytes:
    """One binary record written from the documented layout (so invalid values can be sent)."""
    n, width = descriptors.shape
    payload = struct.pack("<dIB3xII", t, n, 0, width, 0)
    payload += np.ascontiguousarray(keypoints, "<f8").tobytes() + np.ascontiguousarray(sigmas, "<f8").tobytes()
    payload += np.ascontiguousarray(descriptors, np.uint8).tobytes()
    payload += struct.pack("<Q", _fnv1a(payload))
    return struct.pack("<I", len(payload)) + payload


@pytest.fixture(scope="module")
def valid_stream(room: datasets.Sequence, room_map: Path, tmp_path_factory: pytest.TempPathFactory) -> bytes:
    path = tmp_path_factory.mktemp("stream") / "frames.bin"
    geoloc.export_frames(geoloc.Map.load(room_map), room[30:34], path)
    return path.read_bytes()


def _records(stream: bytes) -> list[bytes]:
    out, at = [], 16
    while at < len(stream):
        n = struct.unpack_from("<I", stream, at)[0]
        out.append(stream[at : at + 4 + n])
        at += 4 + n
    return out


def _refused(binary: Path, map_path: Path, stream: bytes, tmp_path: Path, message: str, good: int) -> None:
    out = tmp_path / "poses.txt"
    result = _run(binary, "localize", "--map", str(map_path), "--input", "-", "--output", str(out), stdin=stream)
    assert result.returncode == 1, result.stderr
    assert len(result.stderr.strip().splitlines()) == 1 and message in result.stderr, result.stderr
    assert result.stderr.startswith("geoloc-rs: error: ")
    written = out.read_text().splitlines()
    assert len(written) == 1 + good and all(len(line.split(" ")) == COLUMNS for line in written[1:])


def test_a_truncated_stream_names_the_frame_and_keeps_the_lines_before(
    geoloc_rs: Path, room_map: Path, valid_stream: bytes, tmp_path: Path
) -> None:
    _refused(geoloc_rs, room_map, valid_stream[:-50], tmp_path, "frame 3: truncated record", 3)


def test_a_nan_keypoint_names_the_frame(geoloc_rs: Path, room_map: Path, valid_stream: bytes, tmp_path: Path) -> None:
    kps = np.array([[10.0, 20.0], [np.nan, 5.0]])
    bad = _raw_record(100.0, kps, np.ones(2), np.zeros((2, 32), np.uint8))
    _refused(geoloc_rs, room_map, valid_stream + bad, tmp_path, "frame 4: keypoints[1] is not finite", 4)


def test_a_backwards_timestamp_names_the_frame(geoloc_rs: Path, room_map: Path, valid_stream: bytes, tmp_path: Path) -> None:
    recs = _records(valid_stream)
    swapped = valid_stream[:16] + recs[0] + recs[2] + recs[1] + recs[3]
    _refused(geoloc_rs, room_map, swapped, tmp_path, "frame 2: timestamp", 2)


def test_a_wrong_descriptor_width_or_kind_names_the_frame(
    geoloc_rs: Path, room_map: Path, valid_stream: bytes, tmp_path: Path
) -> None:
    for descriptors, what in ((np.zeros((3, 16), np.uint8), "binary descriptors of width 16"),
                              (np.zeros((3, 32), np.float32), "float descriptors of width 32")):
        path = tmp_path / "odd.bin"
        w = FrameWriter(str(path))
        w.write(1e6, np.zeros((3, 2)), np.ones(3), descriptors)
        w.close()
        _refused(geoloc_rs, room_map, valid_stream + path.read_bytes()[16:], tmp_path, f"frame 4: {what}", 4)


def test_a_corrupt_or_other_version_map_is_refused(geoloc_rs: Path, room_map: Path, valid_stream: bytes, tmp_path: Path) -> None:
    data = bytearray(room_map.read_bytes())
    data[len(data) // 2] ^= 0x40
    bad = tmp_path / "bad.geoloc"
    bad.write_bytes(bytes(data))
    for args in (("info", str(bad)), ("localize", "--map", str(bad), "--input", "-")):
        result = _run(geoloc_rs, *args, stdin=valid_stream)
        assert result.returncode == 1 and result.stdout == ""
        assert result.stderr.startswith("geoloc-rs: error: ") and "bad.geoloc" in result.stderr, result.stderr
    other = room_map.read_bytes().replace(b'\\"version\\":1,', b'\\"version\\":7,', 1)
    bad.write_bytes(other)
    result = _run(geoloc_rs, "info", str(bad))
    assert result.returncode == 1 and "version 7 is not supported" in result.stderr, result.stderr


# ------------------------------------------------------------------ export_frames


def test_export_frames_writes_atomically_and_checks_its_arguments(room: datasets.Sequence, room_map: Path, tmp_path: Path) -> None:
    m = geoloc.Map.load(room_map)
    path = tmp_path / "frames.bin"
    path.write_bytes(b"previous")

    def boom(done: int) -> None:
        if done == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        geoloc.export_frames(m, room[30:34], path, progress=boom)
    assert path.read_bytes() == b"previous" and list(tmp_path.iterdir()) == [path]
    pairs: list[tuple[float, Any]] = [(float(room.timestamps[i]), room.gray(i)) for i in (30, 31)]
    assert geoloc.export_frames(m, pairs, path) == 2
    assert path.read_bytes()[:8] == b"GLFRAMES"
    with pytest.raises(geoloc.InvalidInputError, match="format"):
        geoloc.export_frames(m, pairs, path, format="xml")  # type: ignore[arg-type]
    with pytest.raises(geoloc.InvalidInputError, match="frames"):
        geoloc.export_frames(m, "frames", path)
    with pytest.raises(geoloc.InvalidInputError, match="map"):
        geoloc.export_frames("room.geoloc", pairs, path)  # type: ignore[arg-type]
    with pytest.raises(geoloc.InvalidInputError, match="path"):
        geoloc.export_frames(m, pairs, tmp_path / "missing" / "f.bin")
    w = FrameWriter(str(tmp_path / "w.bin"))
    w.close()
    with pytest.raises(ValueError, match="closed"):
        w.write(0.0, np.zeros((0, 2)), np.zeros(0), np.zeros((0, 32), np.uint8))
    with pytest.raises(ValueError, match="format"):
        FrameWriter(str(tmp_path / "x.bin"), format="xml")


# ------------------------------------------------------------------ files a robot meets


def test_an_output_that_is_an_input_is_refused_and_the_inputs_kept(
    geoloc_rs: Path, room_map: Path, valid_stream: bytes, tmp_path: Path
) -> None:
    frames = tmp_path / "frames.bin"
    frames.write_bytes(valid_stream)
    (tmp_path / "link.bin").symlink_to(frames)
    (tmp_path / "hard.bin").hardlink_to(frames)
    map_bytes = room_map.read_bytes()
    for output, aliased in ((frames, "--input"), (tmp_path / "." / "frames.bin", "--input"),
                            (tmp_path / "link.bin", "--input"), (tmp_path / "hard.bin", "--input"),
                            (room_map, "--map")):
        result = _localize(geoloc_rs, room_map, frames, "--output", str(output))
        assert result.returncode == 1, result.stderr
        assert f"--output {output}: is the same file as {aliased}" in result.stderr, result.stderr
        assert frames.read_bytes() == valid_stream and room_map.read_bytes() == map_bytes, output
    out = tmp_path / "poses.txt"
    result = _localize(geoloc_rs, room_map, tmp_path / "link.bin", "--output", str(out))
    assert result.returncode == 0, result.stderr
    assert len(out.read_text().splitlines()) == 1 + len(_records(valid_stream))
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_a_fifo_in_place_of_a_file_is_refused_without_hanging(
    geoloc_rs: Path, room_map: Path, valid_stream: bytes, tmp_path: Path
) -> None:
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    frames = tmp_path / "frames.bin"
    frames.write_bytes(valid_stream)
    for args in (("info", str(fifo)), ("localize", "--map", str(fifo), "--input", str(frames)),
                 ("localize", "--map", str(room_map), "--input", str(fifo))):
        result = subprocess.run([str(geoloc_rs), *args], capture_output=True, text=True, timeout=30)
        assert result.returncode == 1, (args, result.stderr)
        assert f"{fifo}: not a regular file (a FIFO)" in result.stderr, (args, result.stderr)
    # the Python loader goes through the same core reader (a subprocess: a hang fails, not stalls)
    load = subprocess.run([sys.executable, "-c", f"import geoloc; geoloc.Map.load({str(fifo)!r})"],
                          capture_output=True, text=True, timeout=60)
    assert load.returncode != 0 and "not a regular file" in load.stderr, load.stderr[-2000:]


def _huge_claim() -> tuple[bytes, int]:
    """The adversarial probe's 44-byte stream: a record whose sizes agree with its length
    field, ~4.12 GB of float descriptors, and nothing after the fixed fields."""
    width = 4096
    n = (4_120_000_000 - 32) // (16 + 8 + 4 * width)
    length = 32 + n * (16 + 8 + 4 * width)
    data = b"GLFRAMES" + struct.pack("<II", 1, 0) + struct.pack("<I", length)
    data += struct.pack("<dIB3xII", 1.0, n, 1, width, 0)
    assert len(data) == 44
    return data, length


def _two_gb_address_space() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (2_000_000_000, 2_000_000_000))


def test_a_huge_record_claim_is_a_clean_error_under_a_memory_limit(
    geoloc_rs: Path, room_map: Path, tmp_path: Path
) -> None:
    data, length = _huge_claim()
    frames = tmp_path / "claim.bin"
    frames.write_bytes(data)
    for input_arg, stdin, want in (
        (str(frames), None, f"frame 0: payload length field claims {length} bytes, but only 24 are left"),
        ("-", data, f"frame 0: truncated record (24 of {length} payload bytes)"),
    ):
        result = subprocess.run(
            [str(geoloc_rs), "localize", "--map", str(room_map), "--input", input_arg], input=stdin,
            capture_output=True, timeout=120, env={"GEOLOC_NUM_THREADS": "1"}, preexec_fn=_two_gb_address_space,
        )
        stderr = result.stderr.decode("latin-1")
        assert result.returncode == 1, (result.returncode, stderr)  # not 134 (abort) or 139
        assert want in stderr, stderr
