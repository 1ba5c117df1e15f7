"""Train one descriptor network per fold of the shared 7-Scenes frames and keep every frame's descriptor.

    python benchmarks/train_folds.py pack FRAMES.npz [--data ../shared/data/7scenes-redkitchen]
    python benchmarks/train_folds.py train --frames FRAMES.npz --out DIR [--backbone tiny|googlenet]
                                     [--fold LO ...] [--epochs N] [--device auto] [train options]

``pack`` writes the frames' network input (``to_gray``: (N, 224, 224) uint8) and poses to one
file, so that training can run where the JPEGs are not (a GPU machine).

``train``: for each fold — frames LO … LO+99 of 0–699 are the queries, the training frames the
rest less 15 frames on either side (the project's protocol) — trains a network on the fold's
training frames with ``geoloc.training.train`` (its defaults unless an option says otherwise:
the paper's schedule, the epoch selected on the last 15 % of the training frames) and writes
``DIR/<backbone>-<tag>-fold<LO>.npz``: the selected network's descriptor of *every* frame
(N, D), the fold's training and query frames, the selection curve, the training seconds and the
configuration. The network is not kept: ``benchmarks/retrieval_networks.py --folds
--descriptors DIR`` scores the descriptors (and BoW, and their combination) per fold.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "7scenes-redkitchen"
FOLD = 100
MARGIN = 15


def fold_indices(n: int, lo: int) -> tuple[np.ndarray, np.ndarray]:
    """(training frames, query frames) of the fold whose queries start at ``lo``."""
    hi = min(lo + FOLD, n)
    train = np.array([i for i in range(n) if i < lo - MARGIN or i >= hi + MARGIN], dtype=np.int64)
    return train, np.arange(lo, hi, dtype=np.int64)


def pack(args: argparse.Namespace) -> None:
    from geoloc.training.frames import SevenScenesFrames, gray_images, poses_of

    frames = SevenScenesFrames(args.data)
    n = min(len(frames), 700)
    sub = frames.subset(range(n))
    np.savez_compressed(args.file, gray=gray_images(sub), poses=poses_of(sub))
    print(f"packed {n} frames into {args.file}")


def train_folds(args: argparse.Namespace) -> None:
    from geoloc.training.frames import PosedImage
    from geoloc.training.train import TrainConfig, embed, train

    data = np.load(args.frames)
    gray, poses = data["gray"], data["poses"]
    n = len(gray)
    config = replace(
        TrainConfig(), backbone=args.backbone, device=args.device, threads=args.threads, progress=False,
        **{k: v for k, v in (("epochs", args.epochs), ("lr", args.lr), ("weight_decay", args.weight_decay),
                             ("augment", args.augment or None), ("seed", args.seed)) if v is not None},
    )
    args.out.mkdir(parents=True, exist_ok=True)
    for lo in args.fold or range(0, n, FOLD):
        train_idx, query_idx = fold_indices(n, lo)
        posed = [PosedImage(np.zeros((8, 8, 3), np.uint8), poses[i]) for i in train_idx]  # images come as gray
        start = time.perf_counter()
        result = train(posed, config, gray=gray[train_idx])
        seconds = time.perf_counter() - start
        descriptors = embed(result.model, gray)
        out = args.out / f"{args.backbone}-{args.tag}-fold{lo}.npz"
        np.savez_compressed(
            out, descriptors=descriptors, train=train_idx, queries=query_idx,
            meta=json.dumps({"seconds": seconds, "selection": result.selection, "config": config.as_dict(),
                             "final_loss": result.losses[-1], "device": args.device}),
        )
        print(f"fold {lo}: {config.epochs} epochs in {seconds:.1f} s, selected epoch "
              f"{result.selection.get('best_epoch')} -> {out}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("pack")
    p.add_argument("file", type=Path)
    p.add_argument("--data", type=Path, default=DATA)
    t = sub.add_parser("train")
    t.add_argument("--frames", type=Path, required=True)
    t.add_argument("--out", type=Path, required=True)
    t.add_argument("--backbone", default="tiny")
    t.add_argument("--tag", default="defaults", help="names the recipe in the output files")
    t.add_argument("--fold", type=int, action="append", help="the first query frame of a fold (repeatable; default all)")
    t.add_argument("--epochs", type=int)
    t.add_argument("--lr", type=float)
    t.add_argument("--weight-decay", type=float)
    t.add_argument("--augment", action="store_true")
    t.add_argument("--seed", type=int)
    t.add_argument("--device", default="auto")
    t.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    if args.command == "pack":
        if not args.data.is_dir():
            sys.exit(f"no 7-Scenes frames at {args.data}")
        pack(args)
    else:
        train_folds(args)


if __name__ == "__main__":
    main()
