"""``geoloc train``: train the descriptor network on posed images and export it to ONNX.

Registered by ``geoloc.cli`` with :func:`add_train_command`, in the style of the other
commands: the dataset options, ``--frames A:B:K`` and the argparse types of
:mod:`geoloc.commands._options`, the dataset read by :func:`geoloc.commands._common.load_dataset`,
a handler returning the exit status, user errors as :class:`geoloc.InvalidInputError`.
Importing this module needs no torch; the handler says ``pip install "geoloc[train]"`` in one
line when torch is missing.

    geoloc train --dataset P|synthetic [--format 7scenes|tum|folder|synthetic] [--intrinsics …]
                 [--trajectory FILE] [--synthetic-frames N] [--frames A:B[:K]] [--tiny] [--epochs N]
                 [--dim D] [--pairs N] [--batch-size N] [--lr X] [--seed S]
                 [--hard-negatives] [--checkpoint FILE [--resume]] [--init FILE]
                 [--validation F] [--eval-every N] [--weight-decay X]
                 [--device auto|cpu|cuda] [--threads N] [--no-progress] --out model.onnx

``--format`` defaults to ``7scenes`` (``synthetic`` when ``--dataset synthetic``). The
spelling of earlier releases, ``--train A:B [--stride K]``, still works for this release: it
means ``--frames A:B:K`` (and, on the synthetic room, ``--synthetic-frames B`` as before) and
prints a deprecation line on stderr.

Defaults are the paper's schedule (GoogLeNet, 500 epochs of 128 + 128 pairs, batch 128,
Adam 1e-3); ``--tiny`` switches to the small backbone and :data:`TINY_EPOCHS` epochs, a run
of a few minutes on 2 CPU cores.
"""

from __future__ import annotations

import argparse
import dataclasses
import re
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Iterator

from ..commands._common import SYNTHETIC_FRAMES, FrameRange, dataset_inputs, load_dataset, select
from ..commands._options import (
    MAX_SEED,
    bounded_float,
    bounded_int,
    dataset_options,
    existing_file,
    frame_range,
    output_file,
    positive_float,
)
from .._io import write_json_atomic
from ..exceptions import InvalidInputError
from . import INSTALL_HINT
from .evaluate import MEASUREMENTS, VALIDATION_FRACTION, VALIDATION_MARGIN

__all__ = ["TINY_EPOCHS", "add_train_command", "load_frames"]

#: Epochs of ``--tiny`` when ``--epochs`` is not given.
TINY_EPOCHS = 10
#: The paper's epochs (GoogLeNet) when ``--epochs`` is not given.
PAPER_EPOCHS = 500
MAX_EPOCHS = 100_000
MAX_PAIRS = 1_000_000
#: What the deprecated ``--train A:B`` / ``--stride K`` are now spelled as.
DEPRECATED = "geoloc train: --train A:B and --stride K are deprecated and will be removed in the next release; use --frames A:B:K"

Handler = Callable[[argparse.Namespace], int]


def device_name(text: str) -> str:
    """``auto``, ``cpu``, ``cuda`` or ``cuda:N``, checked while parsing, so a bad ``--device`` is
    an argparse error naming the option before anything is loaded or printed."""
    if not re.fullmatch(r"auto|cpu|cuda(:\d{1,3})?", text):
        raise argparse.ArgumentTypeError(f"expected auto, cpu, cuda or cuda:N, got {text!r}")
    return text


def _frame_option(args: argparse.Namespace) -> tuple[FrameRange | None, str, bool]:
    """The frame range to train on, the option that named it, and whether it was given in the
    deprecated spelling (``--train A:B`` / ``--stride K``)."""
    deprecated = args.train is not None or args.stride is not None
    if not deprecated:
        return args.frames, "--frames", False
    if args.frames is not None:
        given = "--train" if args.train is not None else "--stride"
        raise InvalidInputError(f"{given}: replaced by --frames A:B:K; give --frames only")
    old = args.train or FrameRange(None, None)
    if old.step != 1 and args.stride is not None:
        raise InvalidInputError("--stride: the range already has a step (A:B:K); give --frames A:B:K only")
    step = args.stride if args.stride is not None else old.step
    return FrameRange(old.start, old.stop, step), "--train" if args.train is not None else "--stride", True


def load_frames(args: argparse.Namespace) -> tuple[Any, Any]:
    """The dataset of ``--dataset``/``--format`` (as every command loads it) and the frames of
    ``--frames`` (or the deprecated ``--train``/``--stride``) to train on."""
    frames, option, deprecated = _frame_option(args)
    if args.format is None:
        args.format = "synthetic" if args.dataset == "synthetic" else "7scenes"
    if args.synthetic_frames is None:  # --train 0:B built a room of B frames; keep that for its last release
        old_stop = frames.stop if deprecated and frames is not None else None
        args.synthetic_frames = old_stop if args.format == "synthetic" and old_stop is not None else SYNTHETIC_FRAMES
    dataset = load_dataset(args)
    return dataset, select(dataset, frames, option)


def add_train_command(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> Handler:
    """Add ``geoloc train`` to ``commands`` (the subparsers of ``geoloc``); return its handler."""
    p = commands.add_parser(
        "train",
        help="train the CNN image descriptor (Siamese GoogLeNet) and export it to ONNX (needs geoloc[train])",
        description="Train the paper's image descriptor network on posed images — pairs labelled by pose "
        "thresholds (positive ≤ 0.3 m and ≤ 15°, negative ≥ 1 m or ≥ 45°), contrastive loss with margin 1 — "
        "and export it to ONNX, checked against torch, for --retrieval MODEL.onnx. Needs PyTorch: "
        f"{INSTALL_HINT}.",
        epilog="example: geoloc train --dataset synthetic --tiny --out model.onnx",
    )
    dataset_options(p, trajectory=True, required=False, format_default="7scenes, or synthetic with --dataset synthetic")
    p.set_defaults(synthetic_frames=None)  # 300, or B of the deprecated --train A:B (see load_frames)
    p.add_argument("--frames", type=frame_range, metavar="A:B", help="train on frame positions A..B-1 (A:B:K every K-th; default: all)")
    p.add_argument("--train", type=frame_range, metavar="A:B", help="deprecated: --frames A:B")
    p.add_argument("--stride", type=bounded_int(1, 1_000_000), metavar="K", help="deprecated: --frames A:B:K")
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
    p.add_argument("--init", type=existing_file, metavar="FILE", help="start from these weights: a geoloc checkpoint or state dict, or torchvision's GoogLeNet "
        "state dict (e.g. ImageNet or Places weights; mapped onto the network, first convolution summed to grayscale, "
        "classifier heads dropped); read without running code from the file")
    p.add_argument(
        "--validation", type=bounded_float(0.0, 0.5), default=VALIDATION_FRACTION, metavar="F",
        help=f"hold out the last fraction F of the frames ({VALIDATION_MARGIN} more before them left out) and keep the epoch "
        f"of the best recall@1 on them; 0: keep the last epoch (default: {VALIDATION_FRACTION})",
    )
    p.add_argument("--eval-every", type=bounded_int(1, MAX_EPOCHS), default=None, metavar="N",
                   help=f"epochs between two recall@1 measurements on the held-out frames (default: {MEASUREMENTS} over the run)")
    p.add_argument("--weight-decay", type=bounded_float(0.0, 1.0), default=0.0, metavar="X",
                   help="AdamW with this decoupled weight decay (default: 0, the paper's Adam)")
    p.add_argument("--device", type=device_name, default="auto", metavar="DEV", help="auto (CUDA when present), cpu, cuda, cuda:N (default: auto)")
    p.add_argument("--threads", type=bounded_int(1, 1024), metavar="N", help="torch CPU threads (default: torch's)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")

    def run(args: argparse.Namespace) -> int:
        from .._io import refuse_alias, refuse_shared_outputs, shown
        from . import require_torch

        if args.resume and not args.checkpoint:
            raise InvalidInputError("--resume: needs --checkpoint FILE")
        # the checkpoint is written during the run, the model and its curve at its end
        refuse_shared_outputs([("--out", args.out), ("--out (its .curve.json)", curve_path(args.out)), ("--checkpoint", args.checkpoint)])
        refuse_alias(args.out, "--out", [("--init", args.init), ("--checkpoint", args.checkpoint)])
        refuse_alias(args.checkpoint, "--checkpoint", [("--init", args.init)])
        require_torch()
        from .export import export_onnx
        from .network import build_network
        from .pretrained import init_weights, load_checkpoint
        from .train import TrainConfig, train

        init_state = None
        if args.init is not None:  # refuse a foreign --init before loading frames; say what it loads
            try:  # read once: the weights checked here are the ones trained from
                init_state = load_checkpoint(args.init)["model"]
                init = init_weights(build_network("tiny" if args.tiny else "googlenet", args.dim), args.init, init_state)
            except InvalidInputError as e:
                raise InvalidInputError(f"--init: {str(e).removeprefix('checkpoint: ').removeprefix('init_from: ')}") from None
            print(init.summary(), file=sys.stderr)
        dataset, frames = load_frames(args)
        refuse_alias(args.out, "--out", dataset_inputs(dataset, "--dataset"))
        refuse_alias(curve_path(args.out), "--out (its .curve.json)", dataset_inputs(dataset, "--dataset") + [("--init", args.init)])
        refuse_alias(args.checkpoint, "--checkpoint", dataset_inputs(dataset, "--dataset"))
        epochs = args.epochs or (TINY_EPOCHS if args.tiny else PAPER_EPOCHS)
        with options_named(TrainConfig):
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
                validation=args.validation,
                eval_every=args.eval_every,
                weight_decay=args.weight_decay,
                progress=not args.no_progress,
            )
        if args.train is not None or args.stride is not None:
            print(DEPRECATED, file=sys.stderr)
        print(f"geoloc train: {len(frames)} frames, {config.backbone}, D = {config.dim}, {epochs} epochs", file=sys.stderr)
        start = time.perf_counter()
        with options_named(TrainConfig, frames="--frames"):  # the loss diverging names the learning rate
            result = train(frames, config, init_state=init_state)
        elapsed = time.perf_counter() - start
        stats = result.pair_stats
        with options_named(TrainConfig, path="--out"):
            report = export_onnx(result.model, args.out)
        print(
            f"trained {len(result.epoch_seconds)} epochs in {elapsed:.1f} s "
            f"({elapsed / max(len(result.epoch_seconds), 1):.2f} s/epoch incl. reading), final loss {result.losses[-1]:.4f}; "
            f"{stats['anchors_with_positive']}/{stats['images']} images have a positive partner"
        )
        print(selection_summary(result.selection))
        print(f"wrote {shown(report.path)} ({report.size_bytes / 1e6:.1f} MB, D = {report.dim}, sha256 {report.sha256[:16]}…)")
        if result.selection.get("curve"):
            curve = curve_path(args.out)
            write_json_atomic(curve, {"config": config.as_dict(), **result.selection}, "--out")
            print(f"wrote {shown(curve)} (the validation curve)")
        return 0

    return run


def curve_path(out: Any) -> Path:
    """Where the validation curve of a model written to ``out`` goes: ``MODEL.curve.json``."""
    p = Path(out)
    return p.with_name(p.stem + ".curve.json")


def selection_summary(selection: dict[str, Any]) -> str:
    """The validation curve and the chosen epoch, or why there was none, in a few lines."""
    if not selection.get("curve"):
        return f"model selection: off ({selection.get('why', 'no validation block')}); the last epoch is kept"
    points = "  ".join(f"{e}: {100 * r:.1f} %" for e, r in selection["curve"])
    return (
        f"validation recall@1 ({selection['validation_frames']} held-out frames, {selection['training_frames']} trained on) "
        f"by epoch: {points}\nkept epoch {selection['best_epoch']}"
    )



#: TrainConfig fields whose command-line option is not ``--`` and the field's name with dashes.
FIELD_OPTIONS = {"n_pos": "--pairs", "n_neg": "--pairs", "init_from": "--init"}


@contextmanager
def options_named(config_type: Any, **arguments: str) -> Iterator[None]:
    """A refusal that names a field of ``config_type`` (``lr: …``) names the command-line
    option instead (``--lr: …``): the user typed the option, not the field; ``arguments``
    maps other argument names to their options (``frames="--frames"``)."""
    try:
        yield
    except InvalidInputError as e:
        field, sep, reason = str(e).partition(": ")
        if sep and field in arguments:
            raise InvalidInputError(f"{arguments[field]}: {reason}") from None
        if not sep or field not in {f.name for f in dataclasses.fields(config_type)}:
            raise
        option = FIELD_OPTIONS.get(field, "--" + field.replace("_", "-"))
        raise InvalidInputError(f"{option}: {reason}") from None
