"""Model selection on held-out training frames (geoloc.training.selection): the split, the
bookkeeping, and that the returned network is the epoch of the best held-out recall@1 —
checked by retraining to that epoch and by recomputing the recall with numpy."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import geoloc
from geoloc import lie
from geoloc.training.frames import PosedImage, gray_images

torch = pytest.importorskip("torch", reason="the train extra (PyTorch) is not installed")

from geoloc.training.selection import MIN_VALIDATION_FRAMES, split_validation  # noqa: E402
from geoloc.training.train import embed, load_network, train  # noqa: E402

TINY = dict(backbone="tiny", dim=16, n_pos=8, n_neg=8, batch_size=8, progress=False, threads=1)


def frames(n: int = 120) -> tuple[object, np.ndarray]:
    """Random images at poses along a walk (no retrieval to learn) — enough for bookkeeping."""
    rng = np.random.default_rng(1)
    poses = np.stack([lie.se3_exp([0.04 * i, 0, 0, 0, 0.01 * i, 0]) for i in range(n)])
    images = [PosedImage(rng.integers(0, 256, (60, 80, 3), dtype=np.uint8), p) for p in poses]
    return images, gray_images(images)


def room(n: int = 120) -> tuple[object, np.ndarray]:
    """The synthetic room's rendered frames: a lap whose end revisits its start, so the
    held-out block has correct training images and the recall moves with training."""
    seq = geoloc.datasets.synthetic_room(n_frames=n, seed=0)
    return seq, gray_images(seq)


def test_the_validation_block_is_the_last_fraction_after_a_margin() -> None:
    s = split_validation(100, 0.15, 15)
    np.testing.assert_array_equal(s.validation, np.arange(85, 100))
    np.testing.assert_array_equal(s.train, np.arange(0, 70))
    assert s.active and s.why == ""
    off = split_validation(100, 0.0, 15)
    assert not off.active and len(off.train) == 100 and "no validation" in off.why
    small = split_validation(MIN_VALIDATION_FRAMES * 4, 0.2, 15)  # 8 frames
    assert not small.active and len(small.train) == MIN_VALIDATION_FRAMES * 4 and "too few" in small.why
    assert not split_validation(12, 0.5, 15).active  # nothing left to train on


def recall_at_1_numpy(model: torch.nn.Module, gray: np.ndarray, poses: np.ndarray, train_idx: np.ndarray, val_idx: np.ndarray) -> float:
    """recall@1 written out: nearest training descriptor by squared distance, correct within 0.3 m / 15°."""
    d = embed(model, gray)  # type: ignore[arg-type]
    hits = 0
    for q in val_idx:
        j = train_idx[np.argmin(((d[train_idx] - d[q]) ** 2).sum(1))]
        rel = np.linalg.inv(poses[j]) @ poses[q]
        angle = np.degrees(np.arccos(np.clip((np.trace(rel[:3, :3]) - 1) / 2, -1, 1)))
        hits += int(np.linalg.norm(rel[:3, 3]) <= 0.3 and angle <= 15.0)
    return hits / len(val_idx)


def test_the_best_held_out_epoch_is_returned(tmp_path: Path) -> None:
    images, gray = room()
    poses = np.asarray(images.poses)  # type: ignore[attr-defined]
    result = train(images, gray=gray, epochs=8, eval_every=2, checkpoint=str(tmp_path / "c.pt"), **TINY)
    sel = result.selection
    assert [e for e, _ in sel["curve"]] == [2, 4, 6, 8]
    assert len({r for _, r in sel["curve"]}) > 1, sel  # the recall moves: there is something to select
    assert (sel["validation_frames"], sel["training_frames"]) == (18, 87)
    best = sel["best_epoch"]
    recalls = dict(sel["curve"])
    assert recalls[best] == max(recalls.values()) and best == min(e for e, r in recalls.items() if r == recalls[best])
    split = split_validation(len(images), 0.15, 15)
    # the recall is what numpy computes for the returned network
    assert recall_at_1_numpy(result.model, gray, poses, split.train, split.validation) == pytest.approx(recalls[best])
    # the returned network is the run stopped at that epoch (training is deterministic)
    stopped = train(images, gray=gray, epochs=best, eval_every=2, **TINY)
    for name, w in stopped.model.state_dict().items():
        assert torch.equal(w, result.model.state_dict()[name]), name
    # the checkpoint's result is the selected network, and a resumed run selects the same
    assert torch.equal(torch.from_numpy(embed(load_network(tmp_path / "c.pt"), gray)), torch.from_numpy(embed(result.model, gray)))
    train(images, gray=gray, epochs=4, eval_every=2, checkpoint=str(tmp_path / "r.pt"), **TINY)
    resumed = train(images, gray=gray, epochs=8, eval_every=2, checkpoint=str(tmp_path / "r.pt"), resume=True, **TINY)
    assert resumed.selection == sel
    for name, w in resumed.model.state_dict().items():
        assert torch.equal(w, result.model.state_dict()[name]), name


def test_without_a_block_the_last_epoch_is_kept() -> None:
    images, gray = frames(40)
    off = train(images, gray=gray, epochs=2, **TINY)
    assert "too few" in off.selection["why"] and "curve" not in off.selection
    explicit = train(images, gray=gray, epochs=2, validation=0.0, **TINY)
    for name, w in explicit.model.state_dict().items():
        assert torch.equal(w, off.model.state_dict()[name]), name


def test_weight_decay_uses_adamw_and_changes_the_weights() -> None:
    images, gray = frames(40)
    plain = train(images, gray=gray, epochs=2, **TINY)
    decayed = train(images, gray=gray, epochs=2, weight_decay=0.5, **TINY)
    assert not torch.equal(plain.model.fc.weight, decayed.model.fc.weight)
    with pytest.raises(Exception, match="weight_decay"):
        train(images, gray=gray, epochs=1, weight_decay=-1.0, **TINY)
    with pytest.raises(Exception, match="validation"):
        train(images, gray=gray, epochs=1, validation=0.9, **TINY)


def test_the_command_prints_and_saves_the_curve(tmp_path: Path) -> None:
    out = tmp_path / "m.onnx"
    done = subprocess.run(
        [sys.executable, "-m", "geoloc", "train", "--dataset", "synthetic", "--synthetic-frames", "120", "--tiny",
         "--epochs", "2", "--eval-every", "1", "--pairs", "8", "--batch-size", "8", "--dim", "8", "--no-progress",
         "--threads", "1", "--out", str(out)],
        capture_output=True, text=True,
    )
    assert done.returncode == 0, done.stderr
    assert "validation recall@1 (18 held-out frames, 87 trained on) by epoch: 1: " in done.stdout, done.stdout
    saved = json.loads((tmp_path / "m.curve.json").read_text())
    assert [e for e, _ in saved["curve"]] == [1, 2] and saved["best_epoch"] in (1, 2)
    assert saved["config"]["validation"] == 0.15
    bad = subprocess.run([sys.executable, "-m", "geoloc", "train", "--dataset", "synthetic", "--validation", "0.9", "--out", str(out)],
                         capture_output=True, text=True)
    assert bad.returncode != 0 and "--validation" in bad.stderr


@pytest.mark.parametrize("bad", [0, -2, 1.5, True, "3"])
def test_a_bad_eval_every_is_refused_by_name(bad: object) -> None:
    images, gray = frames(40)
    with pytest.raises(geoloc.InvalidInputError, match=r"^eval_every: expected a positive integer or None"):
        train(images, gray=gray, epochs=1, eval_every=bad, **TINY)


def test_an_out_whose_curve_would_overwrite_the_init_weights_is_refused(tmp_path: Path) -> None:
    """``--out m.onnx`` writes ``m.curve.json`` beside it: when that is the ``--init`` file the
    command refuses before training, and the weights file is left as it was."""
    from geoloc.training.network import build_network

    init = tmp_path / "m.curve.json"
    torch.save(build_network("tiny", 8).state_dict(), init)
    before = init.read_bytes()
    done = subprocess.run(
        [sys.executable, "-m", "geoloc", "train", "--dataset", "synthetic", "--synthetic-frames", "60", "--tiny",
         "--dim", "8", "--epochs", "1", "--no-progress", "--init", str(init), "--out", str(tmp_path / "m.onnx")],
        capture_output=True, text=True,
    )
    assert done.returncode != 0 and "--out (its .curve.json)" in done.stderr and "--init" in done.stderr, done.stderr
    assert init.read_bytes() == before and not (tmp_path / "m.onnx").exists()
