"""geoloc.training: loss, pair sampling, networks, export parity, determinism, resume, the
``geoloc train`` command, and a tiny training run that must beat the tiny-image baseline.

The torch tests need the ``train`` extra (CI installs it); they skip only where torch is not
installed.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import geoloc
from geoloc import lie
from geoloc.descriptor import OnnxDescriptor, preprocess, tiny_image_descriptors
from geoloc.training.evaluate import correct_matrix, rank_by_descriptors, recall_at_k
from geoloc.training.frames import PosedImage, gray_images, poses_of
from geoloc.training.pairs import DISSIMILAR, SIMILAR, PairSampler, PairThresholds

from posed_images import SEVEN_SCENES, seven_scenes, standin

torch = pytest.importorskip("torch", reason="the train extra (PyTorch) is not installed")

from geoloc.training.command import add_train_command  # noqa: E402
from geoloc.training.export import PARITY_ATOL, export_onnx  # noqa: E402
from geoloc.training.loss import contrastive_loss  # noqa: E402
from geoloc.training.network import build_network  # noqa: E402
from geoloc.training.train import TrainConfig, embed, load_network, train  # noqa: E402

#: The recall@1 margin the tiny CNN must beat the tiny-image baseline by: 10 points on
#: 7-Scenes (measured: +24 with seed 0, +12 with seed 2); 5 on the rendered stand-in (+6.6).
RECALL_MARGIN = {"7scenes": 0.10, "standin": 0.05}
#: Epochs of the tiny run (recall@1 on 7-Scenes peaks around 8–11 epochs of 128 + 128 pairs).
TINY_EPOCHS = 10


def _random_poses(n: int, seed: int, spread_m: float = 1.0, spread_rad: float = 0.6) -> np.ndarray:
    rng = np.random.default_rng(seed)
    xi = np.concatenate([rng.uniform(-spread_m, spread_m, (n, 3)), rng.uniform(-spread_rad, spread_rad, (n, 3))], axis=1)
    return lie.se3_exp(xi)


# --- loss -------------------------------------------------------------------------------------


def test_contrastive_loss_matches_a_hand_computed_value() -> None:
    a = torch.tensor([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    b = torch.tensor([[0.6, 0.8], [0.6, 0.8], [0.0, -1.0]])
    label = torch.tensor([SIMILAR, DISSIMILAR, DISSIMILAR])
    # D² = 0.16 + 0.64 = 0.8 for the first two pairs, D = 2 for the third (beyond the margin)
    # similar: ½·0.8 = 0.4; dissimilar at D = √0.8: ½·(1 − √0.8)² = 0.0055728…; third: 0
    want = (0.4 + 0.5 * (1 - np.sqrt(0.8)) ** 2 + 0.0) / 3
    assert float(contrastive_loss(a, b, label, margin=1.0)) == pytest.approx(want, rel=1e-6)
    # margin 3: the third pair now costs ½·(3 − 2)² = 0.5
    want3 = (0.4 + 0.5 * (3 - np.sqrt(0.8)) ** 2 + 0.5) / 3
    assert float(contrastive_loss(a, b, label, margin=3.0)) == pytest.approx(want3, rel=1e-6)


def test_contrastive_loss_gradient_is_finite_for_identical_descriptors() -> None:
    a = torch.ones(2, 4, requires_grad=True)
    loss = contrastive_loss(a, torch.ones(2, 4), torch.tensor([0, 1]))
    loss.backward()
    assert torch.isfinite(a.grad).all()
    with pytest.raises(ValueError, match="expected a, b of shape"):
        contrastive_loss(torch.ones(2, 4), torch.ones(3, 4), torch.tensor([0, 1]))


# --- pairs ------------------------------------------------------------------------------------


def _motion(poses: np.ndarray, i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Independent reference: distance and geoloc.lie.rotation_angle of R_iᵀR_j (degrees)."""
    dist = np.linalg.norm(poses[i, :3, 3] - poses[j, :3, 3], axis=1)
    rel = np.einsum("nba,nbc->nac", poses[i, :3, :3], poses[j, :3, :3])
    return dist, np.degrees(lie.rotation_angle(rel))


@pytest.mark.parametrize("hard", [False, True])
def test_pairs_respect_the_thresholds(hard: bool) -> None:
    poses = _random_poses(300, seed=3)
    t = PairThresholds(pos_max_m=0.5, pos_max_deg=30.0, neg_min_m=1.2, neg_min_deg=50.0)
    sampler = PairSampler(poses, t, seed=1)
    descriptors = np.random.default_rng(0).normal(size=(300, 8)).astype(np.float32) if hard else None
    pairs = sampler.sample(epoch=4, n_pos=200, n_neg=300, descriptors=descriptors, candidates=8)
    assert len(pairs) == 500 and (pairs.label[:200] == SIMILAR).all() and (pairs.label[200:] == DISSIMILAR).all()
    dist, angle = _motion(poses, pairs.first, pairs.second)
    pos, neg = pairs.label == SIMILAR, pairs.label == DISSIMILAR
    assert (pairs.first[pos] != pairs.second[pos]).all()
    assert (dist[pos] <= 0.5).all() and (angle[pos] <= 30.0 + 1e-9).all()
    assert ((dist[neg] >= 1.2) | (angle[neg] >= 50.0 - 1e-9)).all()
    # the same epoch gives the same pairs; another epoch other pairs
    again = sampler.sample(epoch=4, n_pos=200, n_neg=300, descriptors=descriptors, candidates=8)
    assert (again.second == pairs.second).all()
    assert not (sampler.sample(epoch=5, n_pos=200, n_neg=300, descriptors=descriptors, candidates=8).second == pairs.second).all()


def test_hard_negatives_are_closer_in_descriptor_space() -> None:
    poses = _random_poses(200, seed=4)
    sampler = PairSampler(poses, seed=0)
    d = np.random.default_rng(1).normal(size=(200, 16)).astype(np.float32)
    uniform = sampler.sample(epoch=0, n_pos=0, n_neg=400)
    hard = sampler.sample(epoch=0, n_pos=0, n_neg=400, descriptors=d, candidates=16)
    gap = lambda p: np.linalg.norm(d[p.first] - d[p.second], axis=1).mean()  # noqa: E731
    assert gap(hard) < 0.8 * gap(uniform)


def test_pair_thresholds_are_checked() -> None:
    with pytest.raises(geoloc.InvalidInputError, match="a negative must be further than a positive"):
        PairThresholds(pos_max_m=2.0, neg_min_m=1.0)
    with pytest.raises(geoloc.InvalidInputError, match="no image has a positive partner"):
        PairSampler(np.stack([np.eye(4), lie.se3_exp([5.0, 0, 0, 0, 0, 0])])).sample(0)
    with pytest.raises(geoloc.InvalidInputError, match="poses"):
        PairSampler(np.eye(4)[None])


def test_poses_are_projected_and_checked() -> None:
    pose = np.eye(4)
    pose[:3, :3] *= 1.0002  # 7-Scenes-like non-orthonormal rotation
    out = poses_of([PosedImage(np.zeros((8, 8, 3), np.uint8), pose)])
    assert np.allclose(out[0, :3, :3] @ out[0, :3, :3].T, np.eye(3), atol=1e-12)
    with pytest.raises(geoloc.InvalidInputError, match=r"frames\[0\].pose"):
        poses_of([PosedImage(np.zeros((8, 8, 3), np.uint8), None)])  # type: ignore[arg-type]


# --- networks and export ----------------------------------------------------------------------


@pytest.mark.parametrize("backbone, dim", [("tiny", 32), ("googlenet", 128)])
def test_network_gives_unit_descriptors(backbone: str, dim: int) -> None:
    torch.manual_seed(0)
    net = build_network(backbone, dim).eval()  # type: ignore[arg-type]
    with torch.no_grad():
        z = net(torch.randn(2, 1, 224, 224))
    assert z.shape == (2, dim)
    assert torch.allclose(z.norm(dim=1), torch.ones(2), atol=1e-6)


def test_googlenet_has_the_inception_v1_layout() -> None:
    net = build_network("googlenet")
    blocks = [m for m in net.backbone.blocks if m.__class__.__name__ == "Inception"]
    assert len(blocks) == 9
    assert [b.out_channels for b in blocks] == [256, 480, 512, 512, 512, 528, 832, 832, 1024]
    assert net.backbone.out_features == 1024


@pytest.mark.parametrize("backbone", ["tiny", "googlenet"])
def test_export_matches_torch(backbone: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    torch.manual_seed(1)
    net = build_network(backbone, 64)  # type: ignore[arg-type]
    report = export_onnx(net, tmp_path / "m.onnx", name="test-net")
    assert report.max_abs_diff < PARITY_ATOL and "max |diff|" in capsys.readouterr().err
    desc = OnnxDescriptor(report.path, threads=2)
    assert (desc.name, desc.dim, desc.sha256, desc.input_size) == ("test-net", 64, report.sha256, (224, 224))
    # the whole runtime path (uint8 images → preprocess → onnxruntime) against torch
    images = [np.random.default_rng(i).integers(0, 256, (120, 160, 3), dtype=np.uint8) for i in range(3)]
    with torch.no_grad():
        want = net.eval()(torch.from_numpy(preprocess(images))).numpy()
    assert np.abs(desc(images) - want).max() < PARITY_ATOL


# --- training ---------------------------------------------------------------------------------


def _toy_frames(n: int = 40) -> tuple[list[PosedImage], np.ndarray]:
    rng = np.random.default_rng(0)
    poses = np.stack([lie.se3_exp([0.05 * i, 0, 0, 0, 0.02 * i, 0]) for i in range(n)])
    frames = [PosedImage(rng.integers(0, 256, (60, 80, 3), dtype=np.uint8), p) for p in poses]
    return frames, gray_images(frames)


TINY_FAST = dict(backbone="tiny", dim=16, n_pos=8, n_neg=8, batch_size=8, progress=False, threads=1)


def test_training_is_deterministic_and_resumes_exactly(tmp_path: Path) -> None:
    frames, gray = _toy_frames()
    straight = train(frames, gray=gray, epochs=4, **TINY_FAST)
    again = train(frames, gray=gray, epochs=4, **TINY_FAST)
    ckpt = tmp_path / "ckpt.pt"
    train(frames, gray=gray, epochs=2, checkpoint=str(ckpt), **TINY_FAST)
    resumed = train(frames, gray=gray, epochs=4, checkpoint=str(ckpt), resume=True, **TINY_FAST)
    for name, w in straight.model.state_dict().items():
        assert torch.equal(w, again.model.state_dict()[name]), name
        assert torch.equal(w, resumed.model.state_dict()[name]), name
    assert resumed.losses == straight.losses and len(resumed.epoch_seconds) == 2
    # the checkpoint holds the finished run and loads as a network
    assert torch.equal(embed_tensor(load_network(ckpt), gray), embed_tensor(resumed.model, gray))


def embed_tensor(net: torch.nn.Module, gray: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(embed(net, gray))  # type: ignore[arg-type]


def test_init_from_a_local_checkpoint(tmp_path: Path) -> None:
    frames, gray = _toy_frames()
    first = train(frames, gray=gray, epochs=1, checkpoint=str(tmp_path / "a.pt"), **TINY_FAST)
    torch.save(first.model.state_dict(), tmp_path / "state.pt")
    for source in ("a.pt", "state.pt"):
        start = train(frames, gray=gray, epochs=1, init_from=str(tmp_path / source), lr=1e-12, **TINY_FAST)
        for name, w in first.model.state_dict().items():
            if w.dtype.is_floating_point and "running" not in name:
                assert torch.allclose(w, start.model.state_dict()[name], atol=1e-6), name
    with pytest.raises(geoloc.InvalidInputError, match="do not fit a tiny network with dim 8"):
        train(frames, gray=gray, epochs=1, init_from=str(tmp_path / "a.pt"), **{**TINY_FAST, "dim": 8})
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(geoloc.InvalidInputError, match="not a readable torch checkpoint"):
        train(frames, gray=gray, epochs=1, init_from=str(tmp_path / "junk.pt"), **TINY_FAST)


def test_config_is_checked() -> None:
    with pytest.raises(geoloc.InvalidInputError, match="backbone"):
        TrainConfig(backbone="resnet")
    with pytest.raises(geoloc.InvalidInputError, match="epochs"):
        TrainConfig(epochs=0)
    with pytest.raises(geoloc.InvalidInputError, match="resume: needs a checkpoint"):
        TrainConfig(resume=True)
    for kwargs, name in [({"lr": "0.1"}, "lr"), ({"lr": None}, "lr"), ({"validation": "0.1"}, "validation"),
                         ({"weight_decay": "0"}, "weight_decay"), ({"threads": True}, "threads"), ({"seed": 2**70}, "seed")]:
        # a string gave numpy's TypeError; threads=True and a 70-bit seed failed only when training started
        with pytest.raises(geoloc.InvalidInputError, match=f"^{name}: "):
            TrainConfig(**kwargs)  # type: ignore[arg-type]
    defaults = TrainConfig()
    assert (defaults.lr, defaults.batch_size, defaults.n_pos, defaults.n_neg, defaults.epochs, defaults.margin) == (
        1e-3, 128, 128, 128, 500, 1.0
    )


def test_export_arguments_are_checked_by_name(tmp_path: Path) -> None:
    net = build_network("tiny", 32)
    cases = [
        ({"model": None}, "model: expected a geoloc DescriptorNet"),
        ({"path": tmp_path / "nodir" / "x.onnx"}, "path: "),  # it said "out:", a name export_onnx has not
        ({"atol": float("nan")}, "atol: expected a finite number > 0"),  # the parity check compared against nan
        ({"name": 5}, "name: expected a string"),
    ]
    for change, message in cases:
        kwargs = {"model": net, "path": tmp_path / "m.onnx", "quiet": True, **change}
        with pytest.raises(geoloc.InvalidInputError, match=f"^{message}"):
            export_onnx(**kwargs)  # type: ignore[arg-type]
    assert not (tmp_path / "m.onnx").exists()


def test_a_missing_init_file_names_init_from(tmp_path: Path) -> None:
    from geoloc.training.pretrained import init_weights

    with pytest.raises(geoloc.InvalidInputError, match="^init_from: no file"):  # it said "checkpoint:"
        init_weights(build_network("tiny", 32), tmp_path / "nope.pt")


# --- the command ------------------------------------------------------------------------------


def _run_command(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="geoloc")
    handler = add_train_command(parser.add_subparsers(dest="command"))
    return handler(parser.parse_args(["train", *argv]))


@pytest.mark.skipif(not SEVEN_SCENES.is_dir(), reason=f"shared 7-Scenes frames not found at {SEVEN_SCENES}")
def test_train_command_writes_a_model(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "m.onnx"
    argv = ["--dataset", str(SEVEN_SCENES), "--tiny", "--epochs", "1", "--pairs", "8", "--train", "0:600", "--stride", "10",
            "--dim", "32", "--no-progress", "--out", str(out)]
    assert _run_command(argv) == 0
    assert "wrote" in capsys.readouterr().out
    desc = OnnxDescriptor(out)
    assert desc.dim == 32 and desc.name == "m"


def test_train_command_errors(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(geoloc.InvalidInputError, match="--dataset: no such file or folder"):
        _run_command(["--dataset", str(tmp_path / "nope"), "--out", str(tmp_path / "m.onnx")])
    with pytest.raises(SystemExit):
        _run_command(["--dataset", "x", "--train", "5:2", "--out", str(tmp_path / "m.onnx")])
    monkeypatch.setitem(sys.modules, "torch", None)  # as if the train extra were missing
    with pytest.raises(geoloc.GeolocError, match=r'pip install "geoloc\[train\]"'):
        _run_command(["--dataset", str(tmp_path), "--out", str(tmp_path / "m.onnx")])


@pytest.mark.skipif(not SEVEN_SCENES.is_dir(), reason=f"shared 7-Scenes frames not found at {SEVEN_SCENES}")
def test_too_few_frames_names_the_frames_option(tmp_path: Path) -> None:
    """It said "frames: training needs at least 2 …", the Python argument's name."""
    with pytest.raises(geoloc.InvalidInputError, match="^--frames: training needs at least 2"):
        _run_command(["--dataset", str(SEVEN_SCENES), "--tiny", "--frames", "0:1", "--no-progress",
                      "--out", str(tmp_path / "m.onnx")])
    assert not (tmp_path / "m.onnx").exists()


def test_an_absurd_learning_rate_is_refused_before_any_work(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`--lr` above the largest rate Adam can use is refused with one line naming the option (exit 2),
    before the frames are read, and nothing is written."""
    from geoloc.cli import main

    out = tmp_path / "m.onnx"
    argv = ["train", "--dataset", "synthetic", "--tiny", "--epochs", "1", "--pairs", "2", "--batch-size", "2",
            "--dim", "8", "--no-progress", "--out", str(out), "--lr", "1e21"]
    assert main(argv) == 2
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1 and "--lr: expected at most 1" in lines[0], lines  # the option, as typed
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("checkpoint", ["m.onnx", "m.curve.json", "sub/../m.onnx"])
def test_a_checkpoint_that_another_output_would_replace_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], checkpoint: str
) -> None:
    """`--checkpoint m.curve.json --out m.onnx` trained, then the curve replaced the checkpoint
    and `--resume` failed; `--checkpoint m.onnx --out m.onnx` (a new file) likewise. Refused
    before any work, naming both, nothing written."""
    from geoloc.cli import main

    (tmp_path / "sub").mkdir()  # "sub/../m.onnx": another spelling of the model's path
    argv = ["train", "--dataset", "synthetic", "--tiny", "--epochs", "1", "--pairs", "2", "--batch-size", "2",
            "--dim", "8", "--no-progress", "--out", str(tmp_path / "m.onnx"), "--checkpoint", str(tmp_path / checkpoint)]
    assert main(argv) == 2
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(lines) == 1 and "--checkpoint" in lines[0] and "is the same file as --out" in lines[0], lines
    assert sorted(p.name for p in tmp_path.iterdir()) == ["sub"]


def test_a_diverging_loss_names_the_learning_rate(monkeypatch: pytest.MonkeyPatch) -> None:
    """A loss that becomes NaN stops training with an error naming `lr` (the user's to lower),
    not an internal error."""
    from geoloc.training import train as train_module

    monkeypatch.setattr(train_module, "contrastive_loss", lambda a, b, y, m: (a.sum() + b.sum()) * float("nan"))
    def pose(x: float) -> np.ndarray:
        T = np.eye(4)
        T[0, 3] = x
        return T

    # frames 0.2 m apart along a line: neighbours are similar pairs, frames 1 m apart dissimilar
    posed = [PosedImage(np.zeros((24, 32, 3), np.uint8), pose(0.2 * i)) for i in range(8)]
    cfg = TrainConfig(backbone="tiny", dim=8, epochs=1, n_pos=2, n_neg=2, batch_size=2, validation=0.0, progress=False)
    with pytest.raises(geoloc.InvalidInputError, match=r"lr: the loss became nan at epoch 1 with lr = 0.001; lower it"):
        train(posed, cfg)


# --- a tiny training run beats the tiny-image baseline ----------------------------------------


def _split() -> tuple[str, list[PosedImage], list[PosedImage]]:
    if SEVEN_SCENES.is_dir():
        return "7scenes", seven_scenes(range(0, 600)), seven_scenes(range(600, 700))
    return "standin", *standin()


@pytest.mark.slow
def test_tiny_network_beats_the_tiny_image_baseline(capsys: pytest.CaptureFixture[str]) -> None:
    what, train_frames, test_frames = _split()
    train_gray, test_gray = gray_images(train_frames), gray_images(test_frames)
    start = time.perf_counter()
    # A regression check of the training code on the configuration its margin was measured
    # with — every training frame, the last epoch (validation=0) — not a claim about held-out
    # retrieval: with the default validation block (frames ~510-599 held out) the same run
    # retrieves 600-699 at 30 % recall@1, below the baseline's 43 % and an untrained
    # network's 33 % (docs/training.md).
    result = train(
        train_frames, gray=train_gray, backbone="tiny", epochs=TINY_EPOCHS, threads=2, progress=False, seed=0, validation=0.0
    )
    seconds = time.perf_counter() - start
    correct = correct_matrix(poses_of(train_frames), poses_of(test_frames))
    cnn = recall_at_k(correct, rank_by_descriptors(embed(result.model, train_gray), embed(result.model, test_gray)))
    tiny = tiny_image_descriptors([f.image for f in train_frames]), tiny_image_descriptors([f.image for f in test_frames])
    base = recall_at_k(correct, rank_by_descriptors(*tiny))
    with capsys.disabled():
        print(f"\n{what} (train / held-out queries): tiny CNN ({TINY_EPOCHS} epochs, {seconds:.1f} s): {cnn}\n  tiny-image baseline: {base}")
    assert cnn.recall_at_1 >= base.recall_at_1 + RECALL_MARGIN[what]
