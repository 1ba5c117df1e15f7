"""``geoloc train --init``: torchvision GoogLeNet weights mapped onto geoloc's network, checked
against the convolutions they came from; untrusted files never run code.

The torchvision layout is written out here from torchvision's ``googlenet`` source (no
torchvision needed): ``BasicConv2d`` = ``conv`` (no bias) + ``bn`` (eps 1e-3); the Inception
branches ``branch1``, ``branch2.{0,1}``, ``branch3.{0,1}`` (3×3, torchvision's known deviation
from the paper's 5×5), ``branch4.1``; the heads ``aux1``, ``aux2``, ``fc``.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

import geoloc

torch = pytest.importorskip("torch", reason="the train extra (PyTorch) is not installed")
F = torch.nn.functional

from geoloc.training.network import INCEPTION_LAYOUT, build_network  # noqa: E402
from geoloc.training.pretrained import init_weights  # noqa: E402

BN = ("weight", "bias", "running_mean", "running_var", "num_batches_tracked")


def basic_conv(prefix: str, c_in: int, c_out: int, k: int, g: torch.Generator) -> dict[str, torch.Tensor]:
    out = {f"{prefix}.conv.weight": torch.randn(c_out, c_in, k, k, generator=g)}
    for t in BN:
        if t == "num_batches_tracked":
            out[f"{prefix}.bn.{t}"] = torch.tensor(7)
        elif t == "running_var":
            out[f"{prefix}.bn.{t}"] = torch.rand(c_out, generator=g) + 0.5
        else:
            out[f"{prefix}.bn.{t}"] = torch.randn(c_out, generator=g)
    return out


def torchvision_googlenet_state(seed: int = 0) -> dict[str, torch.Tensor]:
    """A state dict with the layout and shapes of ``torchvision.models.googlenet(aux_logits=True)``."""
    g = torch.Generator().manual_seed(seed)
    s: dict[str, torch.Tensor] = {}
    s |= basic_conv("conv1", 3, 64, 7, g)
    s |= basic_conv("conv2", 64, 64, 1, g)
    s |= basic_conv("conv3", 64, 192, 3, g)
    c = 192
    for name, c1, c3r, c3, c5r, c5, pool in INCEPTION_LAYOUT:
        p = f"inception{name}"
        s |= basic_conv(f"{p}.branch1", c, c1, 1, g)
        s |= basic_conv(f"{p}.branch2.0", c, c3r, 1, g)
        s |= basic_conv(f"{p}.branch2.1", c3r, c3, 3, g)
        s |= basic_conv(f"{p}.branch3.0", c, c5r, 1, g)
        s |= basic_conv(f"{p}.branch3.1", c5r, c5, 3, g)
        s |= basic_conv(f"{p}.branch4.1", c, pool, 1, g)
        c = c1 + c3 + c5 + pool
    for aux, c_in in (("aux1", 512), ("aux2", 528)):
        s |= basic_conv(f"{aux}.conv", c_in, 128, 1, g)
        s[f"{aux}.fc1.weight"], s[f"{aux}.fc1.bias"] = torch.randn(1024, 2048, generator=g), torch.randn(1024, generator=g)
        s[f"{aux}.fc2.weight"], s[f"{aux}.fc2.bias"] = torch.randn(1000, 1024, generator=g), torch.randn(1000, generator=g)
    s["fc.weight"], s["fc.bias"] = torch.randn(1000, 1024, generator=g), torch.randn(1000, generator=g)
    return s


@pytest.fixture(scope="module")
def tv_file(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, torch.Tensor]]:
    state = torchvision_googlenet_state()
    path = tmp_path_factory.mktemp("tv") / "googlenet.pth"
    torch.save(state, path)
    return path, state


def test_torchvision_googlenet_maps_onto_the_network(tv_file: tuple[Path, dict[str, torch.Tensor]]) -> None:
    path, tv = tv_file
    torch.manual_seed(0)
    net = build_network("googlenet", 64)
    fc_before = net.fc.weight.detach().clone()
    report = init_weights(net, path)
    own = net.state_dict()
    # every backbone tensor loaded; geoloc's descriptor head left as initialized
    assert set(report.loaded) == {k for k in own if k.startswith("backbone.")}
    assert report.not_loaded == ("fc.weight", "fc.bias")
    assert torch.equal(net.fc.weight, fc_before)
    assert set(report.dropped) == {k for k in tv if k.startswith(("aux1.", "aux2.", "fc."))}
    # the first convolution summed to gray, and the nine 3×3 "5×5" branches padded
    adapted = dict(report.adapted)
    assert adapted.pop("backbone.stem.0.0.weight").startswith("RGB filters summed")
    assert len(adapted) == len(INCEPTION_LAYOUT) and all("zero-padded" in how for how in adapted.values())
    # batch-norm statistics and the unadapted kernels are the file's, by name
    assert torch.equal(own["backbone.stem.0.1.running_var"], tv["conv1.bn.running_var"])
    assert torch.equal(own["backbone.stem.3.0.weight"], tv["conv3.conv.weight"])
    assert torch.equal(own["backbone.blocks.3.branch_pool.1.1.bias"], tv["inception4a.branch4.1.bn.bias"])
    assert torch.equal(own["backbone.blocks.10.branch3.1.0.weight"], tv["inception5b.branch2.1.conv.weight"])
    assert report.summary().startswith("--init: torchvision GoogLeNet weights, ")


def test_adapted_convolutions_compute_what_the_originals_did(tv_file: tuple[Path, dict[str, torch.Tensor]]) -> None:
    path, tv = tv_file
    net = build_network("googlenet", 32)
    init_weights(net, path)
    g = torch.Generator().manual_seed(3)
    # gray image through the summed first convolution == its RGB replica through the original
    gray = torch.rand(2, 1, 64, 64, generator=g)
    got = net.backbone.stem[0][0](gray)
    want = F.conv2d(gray.expand(-1, 3, -1, -1), tv["conv1.conv.weight"], stride=2, padding=3)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-4)
    # the padded 5×5 kernel (padding 2) == torchvision's 3×3 (padding 1), block 4c
    x = torch.randn(1, 24, 14, 14, generator=g)
    got = net.backbone.blocks[5].branch5[1][0](x)
    want = F.conv2d(x, tv["inception4c.branch3.1.conv.weight"], padding=1)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-4)


def test_dataparallel_prefixes_are_stripped(tmp_path: Path, tv_file: tuple[Path, dict[str, torch.Tensor]]) -> None:
    _, tv = tv_file
    torch.save({f"module.{k}": v for k, v in tv.items()}, tmp_path / "dp.pth")
    report = init_weights(build_network("googlenet", 16), tmp_path / "dp.pth")
    assert len(report.loaded) == len([k for k in build_network("googlenet", 16).state_dict() if k.startswith("backbone.")])


def test_wrong_or_incomplete_weights_are_refused_by_name(tmp_path: Path, tv_file: tuple[Path, dict[str, torch.Tensor]]) -> None:
    path, tv = tv_file
    with pytest.raises(geoloc.InvalidInputError, match="googlenet backbone"):
        init_weights(build_network("tiny", 16), path)
    torch.save({k: v for k, v in tv.items() if k != "inception4b.branch2.1.conv.weight"}, tmp_path / "part.pth")
    with pytest.raises(geoloc.InvalidInputError, match=r"incomplete torchvision GoogLeNet.*blocks\.4\.branch3\.1\.0\.weight"):
        init_weights(build_network("googlenet", 16), tmp_path / "part.pth")
    torch.save({**tv, "conv3.conv.weight": torch.zeros(192, 64, 2, 2)}, tmp_path / "shape.pth")
    with pytest.raises(geoloc.InvalidInputError, match=r"'conv3.conv.weight' has shape \(192, 64, 2, 2\)"):
        init_weights(build_network("googlenet", 16), tmp_path / "shape.pth")


class _RunsCode:
    """Unpickling this calls ``os.makedirs(marker)``: what a plain pickle load would run."""

    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[object, tuple[str]]:
        return (os.makedirs, (self.marker,))


def test_a_file_that_would_run_code_is_refused_not_run(tmp_path: Path) -> None:
    marker = tmp_path / "ran"
    torch.save({"model": {"w": _RunsCode(str(marker))}}, tmp_path / "evil.pt")
    with pytest.raises(geoloc.InvalidInputError, match="not a readable torch checkpoint"):
        init_weights(build_network("tiny", 8), tmp_path / "evil.pt")
    assert not marker.exists()
    # the command refuses it before loading any frames, and says so under --init
    done = subprocess.run(
        [sys.executable, "-m", "geoloc", "train", "--dataset", str(tmp_path / "no-such"), "--tiny",
         "--init", str(tmp_path / "evil.pt"), "--out", str(tmp_path / "m.onnx")],
        capture_output=True, text=True,
    )
    assert done.returncode != 0 and "--init" in done.stderr and "Traceback" not in done.stderr, done.stderr
    assert not marker.exists() and not (tmp_path / "m.onnx").exists()


def test_the_command_reports_what_it_loaded(tmp_path: Path, tv_file: tuple[Path, dict[str, torch.Tensor]]) -> None:
    path, _ = tv_file
    done = subprocess.run(
        [sys.executable, "-m", "geoloc", "train", "--dataset", str(tmp_path / "no-such"),
         "--init", str(path), "--out", str(tmp_path / "m.onnx")],
        capture_output=True, text=True,
    )
    # the weights are checked and reported before the (missing) dataset is read
    assert "--init: torchvision GoogLeNet weights" in done.stderr, done.stderr
    assert "left as initialized (2): fc.weight, fc.bias" in done.stderr
    assert done.returncode != 0 and "dataset" in done.stderr


def test_the_command_reads_the_init_file_once_and_trains_from_what_it_checked(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The weights reported before the frames are read are the ones training starts from: the
    file is read once (a file replaced in between cannot slip in), and the trained network
    equals one trained by the API from those weights."""
    from geoloc.cli import main
    from geoloc.training import pretrained
    from geoloc.training.network import build_network
    from geoloc.training.train import load_network, train

    init = tmp_path / "start.pt"
    torch.manual_seed(3)
    torch.save(build_network("tiny", 8).state_dict(), init)
    reads: list[str] = []
    original = pretrained.load_checkpoint
    monkeypatch.setattr(pretrained, "load_checkpoint", lambda p, *name: reads.append(str(p)) or original(p, *name))
    ckpt = tmp_path / "run.ckpt"
    args = ["train", "--dataset", "synthetic", "--synthetic-frames", "60", "--tiny", "--dim", "8", "--epochs", "1",
            "--pairs", "8", "--batch-size", "8", "--threads", "1", "--no-progress", "--validation", "0",
            "--init", str(init), "--checkpoint", str(ckpt), "--out", str(tmp_path / "m.onnx")]
    assert main(args) == 0
    assert reads == [str(init)]
    seq = geoloc.datasets.synthetic_room(n_frames=60)
    want = train(seq, backbone="tiny", dim=8, epochs=1, n_pos=8, n_neg=8, batch_size=8, threads=1, progress=False,
                 validation=0.0, init_from=str(init))
    got = load_network(ckpt)
    for (name, a), b in zip(got.state_dict().items(), want.model.state_dict().values()):
        assert torch.equal(a, b), name
