"""geoloc.descriptor: preprocessing, the tiny-image baseline, OnnxDescriptor, and a full
localization with an ONNX model that never imports torch."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import geoloc
from geoloc.descriptor import (
    INPUT_SIZE,
    PIXEL_MEAN,
    PIXEL_STD,
    OnnxDescriptor,
    preprocess,
    tiny_image_descriptors,
    to_gray,
)

TESTS = Path(__file__).resolve().parent
#: onnxruntime batching vs one image at a time: the same kernels, at most rounding apart.
BATCH_ATOL = 1e-5


def _images(n: int, seed: int = 0, shape: tuple[int, int] = (120, 160)) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (*shape, 3), dtype=np.uint8) for _ in range(n)]


@pytest.fixture(scope="module")
def model_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small (untrained, seeded) descriptor network exported by geoloc.training."""
    torch = pytest.importorskip("torch", reason="the train extra (PyTorch) is needed to export a test model")
    from geoloc.training.export import export_onnx
    from geoloc.training.network import build_network

    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("model") / "tiny.onnx"
    export_onnx(build_network("tiny", 32), path, quiet=True)
    return path


# --- preprocessing ----------------------------------------------------------------------------


def test_preprocess_shape_and_values() -> None:
    x = preprocess(np.full((480, 640, 3), 128, np.uint8))
    assert x.shape == (1, 1, *INPUT_SIZE) and x.dtype == np.float32
    assert np.allclose(x, (128 / 255 - PIXEL_MEAN) / PIXEL_STD, rtol=0, atol=1e-6)
    # one (H, W, 3) image, an (N, H, W, 3) batch, a list of mixed sizes, gray images
    imgs = _images(3)
    batch = preprocess(np.stack(imgs))
    assert batch.shape == (3, 1, 224, 224)
    assert np.array_equal(batch[1], preprocess(imgs[1])[0])
    mixed = preprocess([imgs[0], _images(1, 1, (480, 640))[0], to_gray(imgs[2], (50, 70))[0]])
    assert mixed.shape == (3, 1, 224, 224) and np.array_equal(mixed[0], batch[0])
    gray = np.full((100, 100), 7, np.uint8)
    assert np.array_equal(preprocess(gray), preprocess(np.repeat(gray[:, :, None], 3, axis=2)))
    assert preprocess([]).shape == (0, 1, 224, 224)


@pytest.mark.parametrize(
    "bad, match",
    [
        (np.zeros((50, 50, 3), np.float32), r"images\[0\]: expected dtype uint8"),
        ([np.zeros((50, 50, 3), np.uint8), np.zeros((50, 50, 4), np.uint8)], r"images\[1\]: expected shape"),
        (np.zeros((4, 50, 50, 3, 1), np.uint8), "expected an"),
        (np.zeros((4, 50, 3), np.uint8), r"images\[0\]: image of 50×4 px is smaller"),
        ("image.png", "expected a uint8 image array"),
    ],
)
def test_preprocess_refuses_bad_images(bad: object, match: str) -> None:
    with pytest.raises(geoloc.InvalidInputError, match=match):
        preprocess(bad)  # type: ignore[arg-type]


def test_tiny_image_descriptors() -> None:
    imgs = _images(4)
    d = tiny_image_descriptors(imgs)
    assert d.shape == (4, 32 * 24) and d.dtype == np.float32
    assert np.allclose(d.mean(axis=1), 0, atol=1e-6) and np.allclose(np.linalg.norm(d, axis=1), 1, atol=1e-5)
    # invariant to gain and offset (within uint8 rounding); a constant image gives zeros
    brighter = [np.clip(0.5 * i.astype(np.float64) + 60, 0, 255).astype(np.uint8) for i in imgs]
    assert np.abs(tiny_image_descriptors(brighter) - d).max() < 0.02
    assert not tiny_image_descriptors(np.full((40, 40), 9, np.uint8)).any()
    assert tiny_image_descriptors(imgs, size=(8, 6)).shape == (4, 48)
    with pytest.raises(geoloc.InvalidInputError, match="size"):
        tiny_image_descriptors(imgs, size=(0, 6))


# --- OnnxDescriptor ---------------------------------------------------------------------------


def test_onnx_descriptor_identity(model_path: Path) -> None:
    desc = OnnxDescriptor(model_path, threads=2)
    assert desc.name == "tiny" and desc.dim == 32 and desc.input_size == (224, 224)
    assert desc.sha256 == hashlib.sha256(model_path.read_bytes()).hexdigest()
    assert desc.signature == {"name": "tiny", "input_size": [224, 224], "dim": 32, "sha256": desc.sha256}
    desc.check_signature(desc.signature)
    with pytest.raises(geoloc.InvalidInputError, match="was built with model 'other'"):
        desc.check_signature({**desc.signature, "name": "other", "sha256": "0" * 64})


def test_onnx_descriptor_batching_equals_one_by_one(model_path: Path) -> None:
    imgs = _images(21, seed=5)
    batched = OnnxDescriptor(model_path, batch_size=16)(imgs)  # a full batch of 16 and one of 5
    single = np.concatenate([OnnxDescriptor(model_path, batch_size=1)([im]) for im in imgs])
    assert batched.shape == (21, 32) and batched.dtype == np.float32
    assert np.allclose(np.linalg.norm(batched, axis=1), 1, atol=1e-6)
    assert np.abs(batched - single).max() < BATCH_ATOL
    assert np.array_equal(OnnxDescriptor(model_path, threads=1)(imgs), OnnxDescriptor(model_path, threads=1)(imgs))
    assert OnnxDescriptor(model_path)([]).shape == (0, 32)


def test_onnx_descriptor_refuses_bad_files_and_arguments(model_path: Path, tmp_path: Path) -> None:
    with pytest.raises(geoloc.InvalidInputError, match="cannot read the model file"):
        OnnxDescriptor(tmp_path / "missing.onnx")
    truncated = tmp_path / "truncated.onnx"
    truncated.write_bytes(model_path.read_bytes()[:5000])
    with pytest.raises(geoloc.InvalidInputError, match="is not a readable ONNX model"):
        OnnxDescriptor(truncated)
    (tmp_path / "text.onnx").write_text("hello")
    with pytest.raises(geoloc.InvalidInputError, match="is not a readable ONNX model"):
        OnnxDescriptor(tmp_path / "text.onnx")
    for kwargs, match in (({"threads": 0}, "threads"), ({"batch_size": 1.5}, "batch_size")):
        with pytest.raises(geoloc.InvalidInputError, match=match):
            OnnxDescriptor(model_path, **kwargs)  # type: ignore[arg-type]
    with pytest.raises(geoloc.InvalidInputError, match=r"images\[0\]: expected dtype uint8"):
        OnnxDescriptor(model_path)(np.zeros((60, 80, 3), np.float64))


def test_onnx_descriptor_refuses_other_models(model_path: Path, tmp_path: Path) -> None:
    onnx = pytest.importorskip("onnx", reason="the train extra (onnx) is needed to edit a test model")
    proto = onnx.load(str(model_path))
    for entry in proto.metadata_props:
        if entry.key == "geoloc.preprocess":
            entry.value = "rgb256-v0"
    onnx.save(proto, str(tmp_path / "other_preprocess.onnx"))
    with pytest.raises(geoloc.InvalidInputError, match="trained with preprocessing 'rgb256-v0'"):
        OnnxDescriptor(tmp_path / "other_preprocess.onnx")
    torch = pytest.importorskip("torch")
    rgb = torch.nn.Sequential(torch.nn.Conv2d(3, 4, 3), torch.nn.Flatten())
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(rgb, (torch.zeros(1, 3, 32, 32),), str(tmp_path / "rgb.onnx"), dynamo=False)
    with pytest.raises(geoloc.InvalidInputError, match="is not a descriptor model"):
        OnnxDescriptor(tmp_path / "rgb.onnx")


# --- no torch at run time ---------------------------------------------------------------------

LOCALIZE_WITHOUT_TORCH = textwrap.dedent(
    """
    import sys
    import numpy as np
    import geoloc, geoloc.descriptor, geoloc.localizer, geoloc.retrieval
    import geoloc.training, geoloc.training.command, geoloc.training.frames, geoloc.training.pairs
    from geoloc import lie
    from geoloc.descriptor import OnnxDescriptor, tiny_image_descriptors
    from geoloc import Localizer, Map
    from geoloc.montecarlo import look_at
    from posed_images import render, _textures
    assert "torch" not in sys.modules, "importing geoloc imported torch"

    cam = geoloc.Camera(525, 525, 320, 240)
    rng = np.random.default_rng(0)
    textures = _textures(rng)
    pts = rng.uniform([-4, -1.5, 3], [4, 1.5, 7], (800, 3))
    desc = rng.integers(0, 256, (800, 32), dtype=np.uint8)

    def walk(t, offset):
        c = np.array([-1.5 + 0.6 * t, offset, 0.0])
        return look_at(c, c + np.array([0.1 * np.sin(1.3 * t), 0.0, 5.0]))

    def observe(pose):
        p = lie.se3_transform_points(lie.se3_inverse(pose), pts)
        uv = p[:, :2] / p[:, 2:] * 525 + [320, 240]
        ok = (p[:, 2] > 0.5) & (uv[:, 0] >= 0) & (uv[:, 0] < 640) & (uv[:, 1] >= 0) & (uv[:, 1] < 480)
        return uv[ok] + 0.3 * rng.normal(size=(ok.sum(), 2)), desc[ok]

    net = OnnxDescriptor(sys.argv[1], threads=2)
    poses = np.stack([walk(0.1 * i, 0.0) for i in range(40)])
    obs = [observe(p) for p in poses]
    g = net([render(p, textures) for p in poses])
    m = Map.from_features(cam, poses, [o[0] for o in obs], [o[1] for o in obs], global_descriptors=g, retrieval="global", estimate_noise=False, refine_intrinsics=False, adjust_labels=False)
    loc = Localizer(m)
    located = 0
    for f in range(10):
        t = 0.5 + f / 10
        truth = walk(t, 0.1)
        kp, d = observe(truth)
        r = loc.localize_features(t, kp, d, global_descriptor=net([render(truth, textures)])[0])
        located += r.pose is not None and np.linalg.norm(r.pose[:3, 3] - truth[:3, 3]) < 0.05
    tiny_image_descriptors([render(poses[0], textures)])
    assert located >= 8, located
    assert "torch" not in sys.modules, "the runtime imported torch"
    print("ok", located, sorted(k for k in sys.modules if k.split(".")[0] in ("onnxruntime", "torch"))[:3])
    """
)


def test_localization_with_an_onnx_model_never_imports_torch(model_path: Path) -> None:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), *sys.path])}
    proc = subprocess.run(
        [sys.executable, "-c", LOCALIZE_WITHOUT_TORCH, str(model_path)], capture_output=True, text=True, env=env, timeout=300
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert proc.stdout.startswith("ok")
    assert "onnxruntime" in proc.stdout
