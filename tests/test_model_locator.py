"""The model locator through the Python API: the synthetic room, the stored model,
the option checks. The core tests cover the model against true points, the no-leak rule and
thread determinism; 7-Scenes numbers are in benchmarks/novel_views.py."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

import geoloc
from geoloc.evaluation import summarize_results
from geoloc.exceptions import InvalidInputError
from geoloc import Localizer, Map

pytest.importorskip("cv2")
pytestmark = pytest.mark.slow  # builds the room's 3D model


@pytest.fixture(scope="module")
def room() -> tuple[Any, geoloc.Map]:
    seq = geoloc.datasets.synthetic_room(n_frames=120, seed=0)
    return seq[80:], geoloc.Map.build(seq[:80], estimate_noise=False, model=True)


def single(m: geoloc.Map, test: Any, locator: str) -> tuple[dict[str, Any], list[int]]:
    loc = geoloc.Localizer(m, locator=locator)  # type: ignore[arg-type]
    results = []
    for i in range(len(test)):
        loc.reset()
        results.append(loc.localize(test.gray(i), float(test.timestamps[i])))
    return summarize_results(results, test.poses), [r.inliers for r in results]


def test_model_locator_matches_or_beats_the_paper_on_the_room(room: tuple[Any, geoloc.Map]) -> None:
    test, m = room
    assert m.model_points is not None and m.model_points > 100
    paper, paper_inliers = single(m, test, "paper")
    model, model_inliers = single(m, test, "model")
    assert model["recall"]["5cm_5deg"] >= paper["recall"]["5cm_5deg"]
    assert model["median_translation_m"] <= max(paper["median_translation_m"], 0.005)
    assert np.median(model_inliers) >= np.median(paper_inliers)


def test_the_model_is_saved_and_old_maps_build_it_on_demand(room: tuple[Any, geoloc.Map], tmp_path: Path) -> None:
    test, m = room
    m.save(tmp_path / "room.geoloc")
    back = geoloc.Map.load(tmp_path / "room.geoloc")
    assert back.model_points == m.model_points
    a, _ = single(m, test, "model")
    b, _ = single(back, test, "model")
    assert a["median_translation_m"] == b["median_translation_m"]
    # a map without a model (model=False, or written before it existed): the localizer builds the same one
    seq = geoloc.datasets.synthetic_room(n_frames=120, seed=0)[:80]
    ex = geoloc.features.FeatureExtractor("orb", 1000)
    feats = [ex(seq.gray(i), seq.camera) for i in range(len(seq))]
    args = (seq.camera, seq.poses, [f.keypoints for f in feats], [f.descriptors for f in feats])
    plain = Map.from_features(*args, model=False, estimate_noise=False, refine_intrinsics=False, adjust_labels=False)
    assert plain.model_points is None
    f = ex(test.gray(0), test.camera)
    got = Localizer(plain, locator="model").localize_features(0.0, f.keypoints, f.descriptors)
    want = Localizer(Map.from_features(*args, model=True, estimate_noise=False, refine_intrinsics=False, adjust_labels=False), locator="model").localize_features(0.0, f.keypoints, f.descriptors)
    assert got.pose is not None and want.pose is not None
    np.testing.assert_array_equal(got.pose, want.pose)


def test_bad_locator_options_are_refused_by_name(room: tuple[Any, geoloc.Map]) -> None:
    _, m = room
    with pytest.raises(InvalidInputError, match="locator"):
        geoloc.Localizer(m, locator="hloc")  # type: ignore[arg-type]
    with pytest.raises(InvalidInputError, match="top_k"):
        geoloc.Localizer(m, locator="model", top_k=0)


def test_cli_build_map_with_model_then_localize_with_the_model_locator(tmp_path: Path) -> None:
    import os
    import subprocess
    import sys

    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(Path(geoloc.__file__).parents[1]), env.get("PYTHONPATH", "")])

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "geoloc", *args], capture_output=True, text=True, env=env)

    path, out = tmp_path / "room.geoloc", tmp_path / "poses.txt"
    room = ("--format", "synthetic", "--synthetic-frames", "60")
    built = run("build-map", *room, "--frames", "0:30", "--out", str(path))
    assert built.returncode == 0, built.stdout + built.stderr
    assert geoloc.Map.load(path).model_points  # stored by default
    bare = tmp_path / "bare.geoloc"
    built = run("build-map", *room, "--frames", "0:30", "--no-model", "--out", str(bare))
    assert built.returncode == 0, built.stdout + built.stderr
    assert not geoloc.Map.load(bare).model_points
    done = run("localize", "--map", str(path), *room, "--frames", "30:60:3", "--mode", "single", "--locator", "model", "--out", str(out))
    assert done.returncode == 0, done.stdout + done.stderr
    rows = [line.split() for line in out.read_text().splitlines() if not line.startswith("#")]
    truth = geoloc.datasets.synthetic_room(n_frames=60).poses[30:60:3, :3, 3]
    assert len(rows) == 10
    assert np.median(np.linalg.norm(np.array([[float(v) for v in r[1:4]] for r in rows]) - truth, axis=1)) < 0.01
    bad = run("localize", "--map", str(path), *room, "--locator", "hloc", "--out", str(out))
    assert bad.returncode == 2 and "--locator" in bad.stderr
