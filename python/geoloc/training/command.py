"""``geoloc train``: train the descriptor network on posed images and export it to ONNX.

Registered by ``geoloc.cli`` with :func:`add_train_command` (the style of the other
commands: argparse types that name the option, a handler returning the exit status, user
errors as :class:`geoloc.InvalidInputError`). Importing this module needs no torch; the
handler says ``pip install "geoloc[train]"`` in one line when torch is missing.

    geoloc train --dataset P|synthetic [--format 7scenes|tum|folder] [--tiny] [--epochs N]
                 [--train A:B] [--stride K] [--dim D] [--pairs N] [--batch-size N] [--lr X] [--seed S]
                 [--hard-negatives] [--checkpoint FILE [--resume]] [--init FILE]
                 [--device auto|cpu|cuda] [--threads N] [--no-progress] --out model.onnx

Defaults are the paper's schedule (GoogLeNet, 500 epochs of 128 + 128 pairs, batch 128,
Adam 1e-3); ``--tiny`` switches to the small backbone and :data:`TINY_EPOCHS` epochs, a run
of a few minutes on 2 CPU cores.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time
from pathlib import Path
from typing import Any, Callable

from ..exceptions import GeolocError, InvalidInputError
from . import INSTALL_HINT

__all__ = ["TINY_EPOCHS", "add_train_command", "load_frames"]

#: Epochs of ``--tiny`` when ``--epochs`` is not given.
TINY_EPOCHS = 10
#: The paper's epochs (GoogLeNet) when ``--epochs`` is not given.
PAPER_EPOCHS = 500
#: Frames of ``--dataset synthetic``.
SYNTHETIC_FRAMES = 300
MAX_EPOCHS = 100_000
MAX_PAIRS = 1_000_000

Handler = Callable[[argparse.Namespace], int]


def frame_range(text: str) -> tuple[int, int | None]:
    """An argparse ``type`` for ``A:B`` (frames A ≤ i < B; either side may be empty)."""
    parts = text.split(":")
    try:
        if len(parts) != 2:
            raise ValueError
        a = int(parts[0]) if parts[0] else 0
        b = int(parts[1]) if parts[1] else None
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected A:B (frame indices, e.g. 0:600), got {text!r}") from None
    if a < 0 or (b is not None and b <= a):
        raise argparse.ArgumentTypeError(f"expected 0 ≤ A < B, got {text!r}")
    return a, b


def positive_float(text: str) -> float:
    """An argparse ``type`` for a finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (value > 0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return value


def input_file(text: str) -> str:
    """An argparse ``type`` for a file to read: an existing regular file (a FIFO or a folder
    is named as such and never opened)."""
    from .._io import check_input_file

    try:
        check_input_file(text, "path")
    except InvalidInputError as e:
        raise argparse.ArgumentTypeError(str(e).removeprefix("path: ")) from None
    return text


def _dataset_files(frames: Any) -> list[tuple[str, Any]]:
    """``("--dataset", file)`` for the files the training frames are read from."""
    seq = getattr(frames, "frames", frames)
    return [("--dataset", f) for f in getattr(seq, "files", ())]


class _Subset:
    """frames[a:b:stride] of any posed-frame sequence (only ``len`` and ``[i]`` are used)."""

    def __init__(self, frames: Any, indices: range) -> None:
        self.frames, self.indices = frames, indices

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, i: int) -> Any:
        return self.frames[self.indices[i]]


def load_frames(
    dataset: str,
    fmt: str = "7scenes",
    frames: tuple[int, int | None] = (0, None),
    seed: int = 0,
    trajectory: str | None = None,
    stride: int = 1,
) -> Any:
    """The posed frames of ``--dataset`` (a path, or ``synthetic``): frames A ≤ i < B, every
    ``stride``-th.

    Uses ``geoloc.datasets``; where it is not installed, 7-Scenes folders are read by
    :class:`geoloc.training.frames.SevenScenesFrames`.
    """
    datasets: Any
    try:
        datasets = importlib.import_module("geoloc.datasets")
    except ModuleNotFoundError as e:
        if e.name != "geoloc.datasets":
            raise
        datasets = None
    if dataset == "synthetic":
        if datasets is None:
            raise GeolocError("--dataset synthetic needs geoloc.datasets, which this installation lacks")
        n = SYNTHETIC_FRAMES if frames[1] is None else frames[1]
        seq: Any = datasets.synthetic_room(n_frames=n, seed=seed)
    else:
        path = Path(dataset)
        if not path.exists():
            raise InvalidInputError(f"--dataset: no such file or folder: {dataset!r}")
        if fmt == "7scenes":
            if datasets is not None:
                seq = _load(datasets, fmt, path, trajectory)
            else:
                from .frames import SevenScenesFrames

                seq = SevenScenesFrames(path)
        elif datasets is None:
            raise GeolocError(f"--format {fmt} needs geoloc.datasets, which this installation lacks")
        else:
            seq = _load(datasets, fmt, path, trajectory)
    start, stop = frames
    stop = len(seq) if stop is None else stop
    if start >= len(seq) or stop > len(seq):
        raise InvalidInputError(f"--train: frames {start}:{stop} are outside the dataset's {len(seq)} frames")
    return seq if (start, stop, stride) == (0, len(seq), 1) else _Subset(seq, range(start, stop, stride))


def device_name(text: str) -> str:
    """``auto``, ``cpu``, ``cuda`` or ``cuda:N``, checked while parsing, so a bad ``--device`` is
    an argparse error naming the option before anything is loaded or printed."""
    import re

    if not re.fullmatch(r"auto|cpu|cuda(:\d{1,3})?", text):
        raise argparse.ArgumentTypeError(f"expected auto, cpu, cuda or cuda:N, got {text!r}")
    return text


def _load(datasets: Any, fmt: str, path: Path, trajectory: str | None) -> Any:
    """The dataset loader's DatasetError (``"path: …"``) re-headed with the option that set
    the argument (``--dataset``, ``--trajectory``), as the other commands do."""
    from ..commands._common import option_message
    from ..exceptions import DatasetError

    try:
        if fmt == "7scenes":
            return datasets.load_7scenes(path)
        if fmt == "tum":
            return datasets.load_tum(path)
        return datasets.load_folder(path, trajectory=trajectory or "traj.txt")
    except DatasetError as e:
        raise InvalidInputError(option_message(str(e), "--dataset")) from None


def add_train_command(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> Handler:
    """Add ``geoloc train`` to ``commands`` (the subparsers of ``geoloc``); return its handler."""
    from ..cli import MAX_SEED, bounded_int, output_file

    p = commands.add_parser(
        "train",
        help="train the CNN image descriptor (Siamese GoogLeNet) and export it to ONNX (needs geoloc[train])",
        description="Train the paper's image descriptor network on posed images — pairs labelled by pose "
        "thresholds (positive ≤ 0.3 m and ≤ 15°, negative ≥ 1 m or ≥ 45°), contrastive loss with margin 1 — "
        "and export it to ONNX, checked against torch, for --retrieval MODEL.onnx. Needs PyTorch: "
        f"{INSTALL_HINT}.",
        epilog="example: geoloc train --dataset synthetic --tiny --out model.onnx",
    )
    p.add_argument("--dataset", required=True, metavar="P", help="dataset folder, or 'synthetic' for the built-in room")
    p.add_argument("--format", choices=("7scenes", "tum", "folder"), default="7scenes", help="layout of --dataset (default: 7scenes)")
    p.add_argument("--trajectory", metavar="FILE", help="trajectory file of a --format folder dataset (default: traj.txt)")
    p.add_argument("--train", type=frame_range, default=(0, None), metavar="A:B", help="train on frames A ≤ i < B (default: all)")
    p.add_argument("--stride", type=bounded_int(1, 1_000_000), default=1, metavar="K", help="use every K-th frame of the range (default: 1)")
    p.add_argument("--out", required=True, type=output_file, metavar="MODEL.onnx", help="the ONNX model to write")
    p.add_argument("--tiny", action="store_true", help=f"the small CPU backbone instead of GoogLeNet ({TINY_EPOCHS} epochs by default)")
    p.add_argument("--epochs", type=bounded_int(1, MAX_EPOCHS), metavar="N", help=f"epochs (default: {PAPER_EPOCHS}, or {TINY_EPOCHS} with --tiny)")
    p.add_argument("--dim", type=bounded_int(1, 4096), default=128, metavar="D", help="descriptor dimension (default: 128)")
    p.add_argument("--pairs", type=bounded_int(1, MAX_PAIRS), default=128, metavar="N", help="positive and negative pairs each per epoch (default: 128)")
    p.add_argument("--batch-size", type=bounded_int(1, MAX_PAIRS), default=128, metavar="N", help="pairs per Adam step (default: 128)")
    p.add_argument("--lr", type=positive_float, default=1e-3, metavar="X", help="Adam learning rate (default: 1e-3)")
    p.add_argument("--seed", type=bounded_int(0, MAX_SEED), default=0, metavar="S", help="random seed (default: 0)")
    p.add_argument("--hard-negatives", action="store_true", help="mine each negative among 32 candidates with the current network")
    p.add_argument("--checkpoint", type=output_file, metavar="FILE", help="save a checkpoint every 10 epochs and at the end")
    p.add_argument("--resume", action="store_true", help="continue from --checkpoint")
    p.add_argument("--init", type=input_file, metavar="FILE", help="start from the weights of a local checkpoint")
    p.add_argument("--device", type=device_name, default="auto", metavar="DEV", help="auto (CUDA when present), cpu, cuda, cuda:N (default: auto)")
    p.add_argument("--threads", type=bounded_int(1, 1024), metavar="N", help="torch CPU threads (default: torch's)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")

    def run(args: argparse.Namespace) -> int:
        from . import require_torch

        from .._io import refuse_alias, shown

        if args.resume and not args.checkpoint:
            raise InvalidInputError("--resume: needs --checkpoint FILE")
        refuse_alias(args.out, "--out", [("--init", args.init), ("--checkpoint", args.checkpoint)])
        refuse_alias(args.checkpoint, "--checkpoint", [("--init", args.init)])
        require_torch()
        from .export import export_onnx
        from .train import TrainConfig, load_checkpoint, train

        if args.init is not None:  # refuse a foreign --init before loading frames or printing anything
            try:
                load_checkpoint(args.init)
            except InvalidInputError as e:
                raise InvalidInputError(f"--init: {str(e).removeprefix('checkpoint: ')}") from None
        frames = load_frames(args.dataset, args.format, args.train, args.seed, args.trajectory, args.stride)
        refuse_alias(args.out, "--out", _dataset_files(frames))
        refuse_alias(args.checkpoint, "--checkpoint", _dataset_files(frames))
        epochs = args.epochs or (TINY_EPOCHS if args.tiny else PAPER_EPOCHS)
        config = TrainConfig(
            backbone="tiny" if args.tiny else "googlenet",
            dim=args.dim,
            epochs=epochs,
            batch_size=args.batch_size,
            n_pos=args.pairs,
            n_neg=args.pairs,
            lr=args.lr,
            hard_negatives=args.hard_negatives,
            seed=args.seed,
            device=args.device,
            threads=args.threads,
            checkpoint=args.checkpoint,
            resume=args.resume,
            init_from=args.init,
            progress=not args.no_progress,
        )
        print(f"geoloc train: {len(frames)} frames, {config.backbone}, D = {config.dim}, {epochs} epochs", file=sys.stderr)
        start = time.perf_counter()
        result = train(frames, config)
        elapsed = time.perf_counter() - start
        stats = result.pair_stats
        report = export_onnx(result.model, args.out)
        print(
            f"trained {len(result.epoch_seconds)} epochs in {elapsed:.1f} s "
            f"({elapsed / max(len(result.epoch_seconds), 1):.2f} s/epoch incl. reading), final loss {result.losses[-1]:.4f}; "
            f"{stats['anchors_with_positive']}/{stats['images']} images have a positive partner"
        )
        print(f"wrote {shown(report.path)} ({report.size_bytes / 1e6:.1f} MB, D = {report.dim}, sha256 {report.sha256[:16]}…)")
        return 0

    return run
