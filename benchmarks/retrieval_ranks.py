"""BoW retrieval quality per descriptor kind: where does the map's
bag-of-words ranking put the keyframes that are actually near a query?

Same cross-validation as ``novel_views.py`` (7-Scenes redkitchen frames 0–699, a test block of
100 frames, the map trained on the rest minus 15 frames either side, 1000 features). For each
test frame, the keyframes "near" it are those within 0.3 m (camera centres) and 20° (relative
rotation) of its label pose; the table gives, per fold × descriptor kind, how many test
frames have a near keyframe at all, the fraction of those whose top-1 / top-k (k = the model
locator's default ``top_k`` = 5) retrieved keyframes hold one, and the median / 90th
percentile rank (1-based) of the first near keyframe in the full BoW ranking, and the "hub":
the keyframe retrieved first for the most test frames (over all of them) and their share —
a keyframe that is every query's best match is the failure this measures. The vocabulary
and database are built exactly as ``Map.from_features`` builds them (keyframe descriptors stacked in
keyframe order; the map's default ``branching`` = 10, ``depth`` = 3, seed 0; the term
weighting the vocabulary's descriptor kind gets, as in the map).

    PYTHONPATH=python python benchmarks/retrieval_ranks.py [--folds 0,6] [--features orb,sift,rootsift]
        [--cache /work/runs/feat-cache]

Not a test. ``--cache`` keeps the extracted features in .npz files (extraction dominates).

Measured 2026-11-24 (``near``: test frames with a keyframe within 0.3 m / 20° at all — on
0–99 only 33: frames 0–59 have none (the nearest is 0.35–0.45 m and 17–25° away), frames
60–99 are nearest to the fold's edge keyframe 115; ``hub``: share of the 100 test frames whose first
match is the one most-retrieved keyframe). Before, tf = count for every kind (84fa82e):

    fold     feat       near  top-1  top-5  med rank  p90 rank  words  hub
    0-99     orb          33    79%    85%       1.0      11.6   1000  18% kf 276
    0-99     sift         33    64%    97%       1.0       3.8   1000  31% kf 118
    0-99     rootsift     33    85%    97%       1.0       2.0   1000  34%
    600-699  orb          84    90%    98%       1.0       1.0   1000  10%
    600-699  sift         84    70%    92%       1.0       5.0   1000  30%
    600-699  rootsift     84    63%    90%       1.0       4.7   1000  20%

After, tf = presence for float descriptors (ORB unchanged, bit for bit):

    fold     feat       near  top-1  top-5  med rank  p90 rank  words  hub
    0-99     orb          33    79%    85%       1.0      11.6   1000  18% kf 276
    0-99     sift         33    73%    97%       1.0       3.0   1000  19% kf 116
    0-99     rootsift     33    70%    94%       1.0       3.0   1000  15% kf 116
    600-699  orb          84    90%    98%       1.0       1.0   1000  10% kf 182
    600-699  sift         84    64%    90%       1.0       5.0   1000  9% kf 171
    600-699  rootsift     84    73%    90%       1.0       4.0   1000  23% kf 160

The "near" columns barely move: where a near keyframe exists SIFT already found it. The
failure was the hub: with counts, SIFT's keyframes 116–133 (the striped carpet in view, one
word holding 41–57 of a keyframe's descriptors) were the first match of frames 0–59 too, for
which ORB retrieves keyframes 235–276 and the model locator gets 5–6 cm. The "before" hub shares of the
rows without a keyframe id come from the same scoring recomputed in numpy.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "7scenes-redkitchen"
BLOCK = 100
MARGIN = 15
FRAMES = 700
NEAR_M = 0.3
NEAR_DEG = 20.0
TOP_K = 5  # LocalizerOptions::default().top_k (the model locator's)
BRANCHING, DEPTH = 10, 3  # the core's defaults (geoloc.Map.default_options())


def features(seq: Any, kind: str, cache: Path | None) -> tuple[list[Any], list[Any]]:
    """Keypoints and descriptors of every frame (``rootsift`` = SIFT, ``root_sift=True``)."""
    from geoloc.features import FeatureExtractor

    path = cache / f"{kind}.npz" if cache else None
    if path is not None and path.exists():
        with np.load(path) as z:  # each z[...] reads the whole array again: once each
            n, all_kps, all_descs = z["counts"], z["kps"], z["descs"]
        offs = np.r_[0, np.cumsum(n)]
        return (
            [all_kps[offs[i] : offs[i + 1]] for i in range(len(n))],
            [all_descs[offs[i] : offs[i + 1]] for i in range(len(n))],
        )
    base = "orb" if kind == "orb" else "sift"
    ex = FeatureExtractor(base, 1000, root_sift=kind == "rootsift")  # type: ignore[arg-type]
    kps, descs = [], []
    for i in range(len(seq)):
        f = ex(seq.gray(i), seq.camera)
        kps.append(f.keypoints)
        descs.append(f.descriptors)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        np.savez(path, counts=np.array([len(k) for k in kps]), kps=np.concatenate(kps), descs=np.concatenate(descs))
    return kps, descs


def near(poses: Any, query: Any) -> Any:
    """Mask of the poses within NEAR_M / NEAR_DEG of ``query`` (camera-to-world 4×4)."""
    dt = np.linalg.norm(poses[:, :3, 3] - query[:3, 3], axis=1)
    rel = np.einsum("ij,nik->njk", query[:3, :3], poses[:, :3, :3])
    cos = np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)
    return (dt < NEAR_M) & (np.degrees(np.arccos(cos)) < NEAR_DEG)


def run_fold(seq: Any, feats: tuple[list[Any], list[Any]], b: int, kind: str) -> dict[str, Any]:
    from geoloc.retrieval import BowDatabase, Vocabulary

    lo, hi = b * BLOCK, min((b + 1) * BLOCK, FRAMES)
    train = [i for i in range(FRAMES) if i < lo - MARGIN or i >= hi + MARGIN]
    _, descs = feats
    poses = seq.poses[:FRAMES]
    branching, depth = BRANCHING, DEPTH
    vocab = Vocabulary.train(np.concatenate([descs[i] for i in train]), branching, depth, 0)
    db = BowDatabase(vocab, [descs[i] for i in train])
    ranks, has, firsts = [], 0, []
    for i in range(lo, hi):
        _, order = db.query(descs[i], len(train))
        firsts.append(train[int(order[0])])
        good = near(poses[train], poses[i])
        if not good.any():
            continue
        has += 1
        ranks.append(int(np.argmax(good[np.asarray(order)])) + 1)
    r = np.array(ranks)
    hub, hub_count = max(((k, firsts.count(k)) for k in sorted(set(firsts))), key=lambda x: x[1])
    return {
        "hub": f"{hub_count / len(firsts):.0%} kf {hub}",
        "near": has,
        "top1": float(np.mean(r <= 1)),
        "topk": float(np.mean(r <= TOP_K)),
        "median_rank": float(np.median(r)),
        "p90_rank": float(np.percentile(r, 90)),
        "words": len(vocab),
    }


def main() -> int:
    import geoloc

    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--folds", default="0,6")
    ap.add_argument("--features", default="orb,sift,rootsift")
    ap.add_argument("--cache", type=Path, default=None)
    args = ap.parse_args()
    if not DATA.is_dir():
        print(f"no shared data at {DATA}: nothing to measure")
        return 0
    seq = geoloc.datasets.load_7scenes(DATA, intrinsics=(525.0, 525.0, 320.0, 240.0))[:FRAMES]
    folds = [int(x) for x in args.folds.split(",")]
    rows = []
    for kind in args.features.split(","):
        t0 = time.perf_counter()
        feats = features(seq, kind, args.cache)
        print(f"({kind}: features in {time.perf_counter() - t0:.0f} s)", flush=True)
        for b in folds:
            rows.append((b, kind, run_fold(seq, feats, b, kind)))
    head = f"{'fold':<8} {'feat':<9} {'near':>5} {'top-1':>6} {'top-5':>6} {'med rank':>9} {'p90 rank':>9}"
    print(f"{head} {'words':>6}  hub")
    for b, kind, r in sorted(rows, key=lambda x: x[0]):
        name = f"{b * BLOCK}-{min((b + 1) * BLOCK, FRAMES) - 1}"
        print(
            f"{name:<8} {kind:<9} {r['near']:>5} {r['top1']:>6.0%} {r['topk']:>6.0%} "
            f"{r['median_rank']:>9.1f} {r['p90_rank']:>9.1f} {r['words']:>6}  {r['hub']}"
        )
    return 0


if __name__ == "__main__":
    os.environ.setdefault("GEOLOC_NUM_THREADS", "2")
    sys.exit(main())
