"""The `geoloc` command line with odd file names, FIFOs, outputs that alias inputs, damaged
map headers, fixed-batch networks, bad output names and numbered images: one error line
naming the option (exit 2), no traceback, no crash, no hang, every input byte-identical."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

import geoloc
from cli_runner import checkout_env, one_line_error, run_geoloc
from geoloc import datasets
from geoloc._images import write_image

ODD = os.fsdecode(b"\xff")
SMALL = ["--n-features", "200"]
#: A run that takes longer than this has blocked on a FIFO.
FIFO_TIMEOUT_S = 120


@pytest.fixture(scope="module")
def room_map(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("map") / "room.geoloc"
    room = datasets.synthetic_room(n_frames=40)
    geoloc.Map.build(room[:20]).save(path)
    return path


def _images(folder: Path, names: list[str], frames: list[int]) -> Path:
    room = datasets.synthetic_room(n_frames=40)
    folder.mkdir()
    for name, i in zip(names, frames):
        write_image(folder / name, room[i].image)
    return folder


def test_localize_a_folder_with_a_non_utf8_file_name(room_map: Path, tmp_path: Path) -> None:
    images = _images(tmp_path / "images", [f"{ODD}\udcfe1.png"], [10])
    result = run_geoloc("localize", "--map", str(room_map), "--images", str(images), "--out", str(tmp_path / "p.txt"))
    assert result.returncode in (0, 2), result.stderr  # localized, or every frame lost: never a crash (-11)
    assert "Traceback" not in result.stderr


def test_build_map_from_a_folder_with_a_non_utf8_name(tmp_path: Path) -> None:
    folder = tmp_path / f"data{ODD}"
    datasets.synthetic_room(n_frames=20).write_tum(folder)
    out = tmp_path / f"map{ODD}.geoloc"
    result = run_geoloc("build-map", "--dataset", str(folder), "--format", "tum", *SMALL, "--frames", "0:8", "--out", str(out))
    assert result.returncode == 0, result.stderr
    assert len(geoloc.Map.load(out)) == 8
    assert "map\\xff.geoloc" in result.stdout


@pytest.mark.parametrize("alias", ["same", "dot", "symlink", "hardlink"])
def test_localize_refuses_an_out_that_is_the_map(room_map: Path, tmp_path: Path, alias: str) -> None:
    the_map = tmp_path / "m.geoloc"
    the_map.write_bytes(room_map.read_bytes())
    before = the_map.read_bytes()
    out = {"same": str(the_map), "dot": "./m.geoloc", "symlink": "link.geoloc", "hardlink": "hard.geoloc"}[alias]
    if alias == "symlink":
        os.symlink(the_map, tmp_path / out)
    if alias == "hardlink":
        os.link(the_map, tmp_path / out)
    result = run_geoloc(
        "localize", "--map", str(the_map), "--format", "synthetic", "--synthetic-frames", "40", "--frames", "20:22",
        "--out", out, cwd=tmp_path,
    )
    one_line_error(result, "--out", "--map", "same file")
    assert the_map.read_bytes() == before


def test_build_map_refuses_an_out_that_is_the_trajectory(tmp_path: Path) -> None:
    folder = _images(tmp_path / "data", ["0.png", "1.png", "2.png"], [0, 1, 2])
    room = datasets.synthetic_room(n_frames=40)
    geoloc.evaluation.write_tum_trajectory(folder / "traj.txt", [0.0, 1.0, 2.0], room.poses[:3])
    before = (folder / "traj.txt").read_bytes()
    result = run_geoloc(
        "build-map", "--dataset", str(folder), "--format", "folder", "--intrinsics", "525,525,319.5,239.5", *SMALL,
        "--out", str(folder / "traj.txt"),
    )
    one_line_error(result, "--out", "--dataset", "same file")
    assert (folder / "traj.txt").read_bytes() == before


def test_evaluate_refuses_a_json_that_is_the_reference(tmp_path: Path) -> None:
    reference = tmp_path / "ref.txt"
    reference.write_text("0 0 0 0 0 0 0 1\n")
    result = run_geoloc(
        "evaluate", "--format", "synthetic", "--synthetic-frames", "20", "--reference", str(reference), "--json", str(reference)
    )
    one_line_error(result, "--json", "--reference", "same file")
    assert reference.read_text() == "0 0 0 0 0 0 0 1\n"


def test_a_fifo_as_the_map_is_named_as_a_fifo(tmp_path: Path) -> None:
    os.mkfifo(tmp_path / "m.geoloc")
    result = run_geoloc(
        "localize", "--map", str(tmp_path / "m.geoloc"), "--format", "synthetic", "--out", str(tmp_path / "p.txt"), timeout=FIFO_TIMEOUT_S
    )
    assert result.returncode == 2 and "--map" in result.stderr and "is a FIFO, not a regular file" in result.stderr


def test_a_fifo_as_a_pose_file_is_named_and_does_not_block(tmp_path: Path) -> None:
    folder = _images(tmp_path / "data", ["0.png", "1.png"], [0, 1])
    os.mkfifo(folder / "traj.txt")
    try:
        result = run_geoloc(
            "build-map", "--dataset", str(folder), "--format", "folder", "--intrinsics", "525,525,319.5,239.5", *SMALL,
            "--out", str(tmp_path / "m.geoloc"), timeout=FIFO_TIMEOUT_S,
        )
    except subprocess.TimeoutExpired:  # the regression itself
        pytest.fail("build-map blocked on the FIFO")
    one_line_error(result, "traj.txt", "is a FIFO, not a regular file")


def test_a_map_whose_header_lacks_the_features_record_is_refused(room_map: Path, tmp_path: Path) -> None:
    the_map = geoloc.Map.load(room_map)
    frontend = the_map.settings
    del frontend["features"]
    damaged = tmp_path / "damaged.geoloc"
    the_map._core.save(str(damaged), json.dumps(frontend))
    result = run_geoloc("localize", "--map", str(damaged), "--format", "synthetic", "--out", str(tmp_path / "p.txt"))
    one_line_error(result, "--map", "features")


def test_a_network_with_a_fixed_batch_of_one_builds_and_localizes(tmp_path: Path) -> None:
    pytest.importorskip("onnx")
    from onnx_models import linear_model

    model = linear_model(tmp_path / "fixed.onnx", batch=1)
    out = tmp_path / "m.geoloc"
    syn = ["--format", "synthetic", "--synthetic-frames", "40"]
    result = run_geoloc("build-map", *syn, "--frames", "0:10", *SMALL, "--retrieval", str(model), "--out", str(out))
    assert result.returncode == 0, result.stderr
    assert "bag-of-words fused with the network" in result.stdout, result.stdout
    result = run_geoloc("localize", "--map", str(out), *syn, "--frames", "2:4", "--retrieval", str(model), "--out", str(tmp_path / "p.txt"))
    assert result.returncode in (0, 2) and "internal error" not in result.stderr and "Traceback" not in result.stderr, result.stderr


@pytest.mark.parametrize("name", ["a" * 300 + ".geoloc", "missing/", "x/"])
def test_a_bad_output_name_is_one_error_line(tmp_path: Path, name: str) -> None:
    (tmp_path / "x").mkdir()
    result = run_geoloc("build-map", "--format", "synthetic", "--synthetic-frames", "20", "--out", name, cwd=tmp_path)
    one_line_error(result, "--out")
    assert sorted(os.listdir(tmp_path)) == ["x"]
    assert os.listdir(tmp_path / "x") == []


def test_numbered_images_are_localized_in_number_order(room_map: Path, tmp_path: Path) -> None:
    images = _images(tmp_path / "images", ["9.png", "10.png", "11.png"], [5, 6, 7])
    out = tmp_path / "p.txt"
    result = run_geoloc("localize", "--map", str(room_map), "--images", str(images), "--mode", "single", "--out", str(out))
    assert result.returncode == 0, result.stderr
    times = [float(line.split()[0]) for line in out.read_text().splitlines() if not line.startswith("#")]
    assert times == sorted(times) and set(times) <= {9.0, 10.0, 11.0}
    assert "9.png before 10.png" in " ".join(run_geoloc("localize", "--help").stdout.split())
    room = datasets.synthetic_room(n_frames=40)
    poses = {float(line.split()[0]): np.array(line.split()[1:4], float) for line in out.read_text().splitlines() if not line.startswith("#")}
    for t, frame in zip((9.0, 10.0, 11.0), (5, 6, 7)):
        if t in poses:
            assert np.linalg.norm(poses[t] - room.poses[frame, :3, 3]) < 0.5


@pytest.mark.skipif(not hasattr(__import__("signal"), "SIGHUP"), reason="POSIX signals")
@pytest.mark.parametrize("name", ["SIGTERM", "SIGHUP"])
def test_a_stop_signal_ends_a_command_as_ctrl_c_does(tmp_path: Path, name: str) -> None:
    """SIGTERM / SIGHUP (a service stopped, ssh dropped) killed the Python CLI outright, a
    partial map left in a hidden temp file for good; now they end it as Ctrl-C does: one line,
    exit 128 + the signal, the previous output kept, no temp file."""
    import signal
    import sys
    import time

    out = tmp_path / "m.geoloc"
    out.write_bytes(b"the previous map")
    env = checkout_env()
    proc = subprocess.Popen(
        [sys.executable, "-m", "geoloc", "build-map", "--format", "synthetic", "--synthetic-frames", "3000", "--out", str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
    )
    time.sleep(4.0)  # importing, then extracting features: a long way from writing
    proc.send_signal(getattr(signal, name))
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + getattr(signal, name), err
    assert "geoloc build-map: interrupted" in err and "Traceback" not in err
    assert out.read_bytes() == b"the previous map"
    assert sorted(os.listdir(tmp_path)) == ["m.geoloc"]
