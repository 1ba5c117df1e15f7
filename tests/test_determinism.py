"""Same input, same bytes: the feature-level map (its camera estimated from the keyframes,
its labels adjusted, its 3D model and the paper locator's pair matches built) and localizer
on a seeded synthetic scene — with a stopped camera, i.e. a run of identical keyframes and
of identical query frames, where BoW scores tie exactly — give a byte-identical saved map
and byte-identical poses, covariances and sources in separate processes, with
GEOLOC_NUM_THREADS=1 and 2, and with parallelism off. (BoW near-ties are the sharp case: a
sum in a hash map's iteration order flips them between processes.)
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

import pytest
from posed_images import SEVEN_SCENES

ROOT = Path(__file__).resolve().parents[1]

SCRIPT = r"""
import hashlib, sys
import numpy as np
from geoloc import Localizer, Map

from test_localizer import CAM as cam, _observe, _walk

rng = np.random.default_rng(0)
pts = rng.uniform([-8, -1.5, 3], [8, 1.5, 6], (1500, 3))
desc = rng.integers(0, 256, (1500, 32), dtype=np.uint8)

def walk(t, offset):
    return _walk(min(t, 1.2), offset)  # the camera stops at t = 1.2 s

def observe(rng, pose):
    return _observe(rng, pose, pts, desc)

poses, kps, descs = [], [], []
for i in range(30):
    pose = walk(0.1 * i, 0.0)
    if i > 14 and poses:
        k, d = kps[-1], descs[-1]  # the stopped camera: identical keyframes
    else:
        k, d = observe(rng, pose)
    poses.append(pose); kps.append(k); descs.append(d)
m = Map.from_features(cam, np.stack(poses), kps, descs, branching=8, depth=3, seed=1, refine_intrinsics=True,
               adjust_labels=True, model=True, estimate_noise=False)
loc = Localizer(m)
h = hashlib.sha256()
h.update(repr(sorted(m.self_calibration.items())).encode())  # the camera estimate too
import os, tempfile
with tempfile.TemporaryDirectory() as tmp:  # the saved map's bytes: adjusted labels, model, pair matches
    m.save(os.path.join(tmp, "m.geoloc"))
    with open(os.path.join(tmp, "m.geoloc"), "rb") as f:
        h.update(f.read())
frame = None
for f in range(40):
    t = 0.3 + f / 30
    if t < 1.2 or frame is None:
        frame = observe(rng, walk(t, 0.1))  # after 1.2 s: identical query frames
    r = loc.localize_features(t, *frame)
    h.update(r.source.encode() + r.reason.encode() + np.int64(r.keyframe).tobytes())
    if r.pose is not None:
        h.update(np.ascontiguousarray(r.pose).tobytes() + np.ascontiguousarray(r.covariance).tobytes())
print(h.hexdigest())
"""


def _digest(env_extra: dict[str, str]) -> str:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("GEOLOC_", "RAYON_"))}
    env.update(env_extra)
    paths = [str(ROOT / "python"), str(ROOT / "tests"), env.get("PYTHONPATH", "")]
    env["PYTHONPATH"] = os.pathsep.join(filter(None, paths))
    env.setdefault("PYTHONHASHSEED", "random")
    out = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


@pytest.fixture(scope="module")
def reference() -> str:
    return _digest({})


def test_two_processes_give_the_same_bytes(reference: str) -> None:
    assert len(reference) == len(hashlib.sha256().hexdigest())
    assert _digest({}) == reference


@pytest.mark.parametrize(
    "env",
    [{"GEOLOC_NUM_THREADS": "1"}, {"GEOLOC_NUM_THREADS": "2"}, {"GEOLOC_PARALLELISM": "false"}, {"RAYON_NUM_THREADS": "2"}],
    ids=["1-thread", "2-threads", "parallelism-off", "rayon-2"],
)
def test_thread_settings_give_the_same_bytes(reference: str, env: dict[str, str]) -> None:
    assert _digest(env) == reference


KITCHEN_SCRIPT = r"""
import hashlib, sys
import numpy as np
import geoloc

seq = geoloc.datasets.load_7scenes(sys.argv[1])
loc = geoloc.Localizer(geoloc.Map.load(sys.argv[2]))
h = hashlib.sha256()
for r in loc.localize_sequence(seq[100:140], "single"):
    h.update(r.source.encode() + np.int64(r.keyframe if r.keyframe is not None else -1).tobytes())
    if r.pose is not None:
        h.update(np.ascontiguousarray(r.pose).tobytes() + np.ascontiguousarray(r.covariance).tobytes())
print(h.hexdigest())
"""


@pytest.fixture(scope="module")
def kitchen_map(tmp_path_factory: pytest.TempPathFactory) -> Path:
    if not SEVEN_SCENES.is_dir():
        pytest.skip(f"the shared 7-Scenes frames are absent ({SEVEN_SCENES})")
    import geoloc

    path = tmp_path_factory.mktemp("kitchen") / "map.geoloc"
    geoloc.Map.build(geoloc.datasets.load_7scenes(SEVEN_SCENES)[0:100], "bow").save(path)
    return path


def _kitchen_digest(map_path: Path, env_extra: dict[str, str]) -> str:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("GEOLOC_", "RAYON_"))}
    env.update(env_extra)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT / "python"), env.get("PYTHONPATH", "")]))
    args = [sys.executable, "-c", KITCHEN_SCRIPT, str(SEVEN_SCENES), str(map_path)]
    out = subprocess.run(args, env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


def test_real_frames_give_the_same_answers_with_any_thread_count(kitchen_map: Path) -> None:
    """Frames 100–139 against a map of frames 0–99: several are refused by the first two
    hypotheses and answered from a lower-ranked keyframe (model locator step 7), where a
    batch as wide as the threads would let the thread count into the answer (frame 111)."""
    one = _kitchen_digest(kitchen_map, {"GEOLOC_NUM_THREADS": "1"})
    assert len(one) == len(hashlib.sha256().hexdigest())
    for env in ({"GEOLOC_NUM_THREADS": "2"}, {"GEOLOC_NUM_THREADS": "3"}, {"GEOLOC_PARALLELISM": "false"}):
        assert _kitchen_digest(kitchen_map, env) == one, env
