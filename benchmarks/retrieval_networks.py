"""Image retrieval on the shared 7-Scenes frames: the CNN descriptor against BoW and tiny images.

    python benchmarks/retrieval_networks.py --folds [--descriptors DIR] [--json out.json]
    python benchmarks/retrieval_networks.py [--model m.onnx ...] [--train-tiny EPOCHS] [--json out.json]
                                            [--data ../shared/data/7scenes-redkitchen]

``--folds``: every contiguous block of 100 frames of 0–699 is the query set in turn, the
training images the rest less 15 frames on either side (the project's protocol); per fold
recall@1 (correct within 0.3 m and 15°) of tiny images and of the maps geoloc builds — a map
of the fold's training frames from the default features (``Map.from_features``, the core's
bag of words) queried with ``Map.retrieve_features`` — and, for each network in
``--descriptors DIR`` (the per-fold descriptors ``benchmarks/train_folds.py`` writes, each
network trained on that fold's training frames), the network alone (exact L2 1-NN) and the
map fused with it (``retrieval="fused"``): its first keyframe for k = 1 and k = 5 (the
rankings the paper's and the model locator fall back on when BoW's keyframes give no accepted
pose), with the time per query.
Prints the table, the mean over the folds and each method's gain over BoW on its worst fold.
``--model`` files are not used with ``--folds``: a network trained on the queries would be
scored on its own training images.

Otherwise one split: training images: frames 0–599; queries: 600–699 (the paper's "last 100 frames"). A query is
answered correctly when the retrieved training image lies within 0.3 m and 15° of it;
recall@1 / recall@5 are fractions of all 100 queries, and the ceiling is the fraction that
has any correct training image at all. Methods:

* tiny image — grayscale 32×24, zero-mean, unit-norm, exact L2 1-NN
  (``geoloc.descriptor.tiny_image_descriptors`` + ``geoloc.retrieval.DescriptorIndex``);
* BoW — ORB (OpenCV, 1000 per image) into a 10³-word vocabulary with TF-IDF
  (``geoloc.retrieval.Vocabulary`` + ``BowDatabase``, the core's);
* CNN — each ``--model`` through ``geoloc.descriptor.OnnxDescriptor`` (2 threads), and with
  ``--train-tiny N`` a tiny network trained here for N epochs on frames 0–599 (needs torch).

Also prints the CNN's onnxruntime time per image at batch 1 and 16 (best of 3), with and
without preprocessing a 640×480 BGR frame, and the file size. Not a test.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from geoloc.descriptor import OnnxDescriptor, preprocess, tiny_image_descriptors
from geoloc.retrieval import BowDatabase, Vocabulary
from geoloc.training.evaluate import RecallReport, correct_matrix, rank_by_descriptors, recall_at_k
from geoloc.training.frames import SevenScenesFrames, gray_images, poses_of

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "7scenes-redkitchen"
TRAIN, TEST = range(0, 600), range(600, 700)
ORB_FEATURES = 1000


def bow_ranking(train_imgs: list[np.ndarray], test_imgs: list[np.ndarray], k: int) -> tuple[np.ndarray, float]:
    orb = cv2.ORB_create(nfeatures=ORB_FEATURES)

    def describe(img: np.ndarray) -> np.ndarray:
        _, d = orb.detectAndCompute(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY), None)
        return d if d is not None else np.zeros((0, 32), np.uint8)

    start = time.perf_counter()
    train_desc = [describe(i) for i in train_imgs]
    vocab = Vocabulary.train(np.concatenate(train_desc), branching=10, depth=3, seed=0)
    db = BowDatabase(vocab, train_desc)
    build_s = time.perf_counter() - start
    ranked = np.zeros((len(test_imgs), k), dtype=np.int64)
    for q, img in enumerate(test_imgs):
        _, ids = db.query(describe(img), k=k)
        ranked[q, : len(ids)] = ids
    return ranked, build_s


def time_per_image(net: OnnxDescriptor, x: np.ndarray, batch: int, repeats: int = 3) -> float:
    """Best-of-``repeats`` onnxruntime ms per image on preprocessed input, ``batch`` at a time."""
    best = np.inf
    net.run_preprocessed(x[:batch])  # warm-up
    for _ in range(repeats):
        start = time.perf_counter()
        for s in range(0, len(x), batch):
            net.run_preprocessed(x[s : s + batch])
        best = min(best, (time.perf_counter() - start) / len(x))
    return best * 1e3


def time_end_to_end(net: OnnxDescriptor, images: list[np.ndarray], batch: int, repeats: int = 3) -> float:
    """Best-of-``repeats`` ms per 640×480 BGR image, preprocessing included."""
    best = np.inf
    net.batch_size = batch
    net(images[:batch])
    for _ in range(repeats):
        start = time.perf_counter()
        net(images)
        best = min(best, (time.perf_counter() - start) / len(images))
    return best * 1e3


def train_tiny(frames: SevenScenesFrames, gray: np.ndarray, epochs: int, out: Path) -> Path:
    from geoloc.training.export import export_onnx
    from geoloc.training.frames import PosedImage
    from geoloc.training.train import train

    posed = [PosedImage(np.zeros((8, 8, 3), np.uint8), frames[i].pose) for i in TRAIN]  # images come as gray
    start = time.perf_counter()
    result = train(posed, gray=gray[list(TRAIN)], backbone="tiny", epochs=epochs, threads=2, progress=True)
    seconds = time.perf_counter() - start
    print(f"trained the tiny CNN: {epochs} epochs in {seconds:.1f} s ({seconds / epochs:.2f} s/epoch) on {len(posed)} frames")
    export_onnx(result.model, out, name=f"tiny-{epochs}ep")
    print(f"  (model kept at {out})")
    return out


def network_descriptors(folder: Path) -> dict[str, dict[int, Path]]:
    """``folder``'s ``<network>-fold<LO>.npz`` files (``benchmarks/train_folds.py``) by
    network and fold."""
    found: dict[str, dict[int, Path]] = {}
    for f in sorted(folder.glob("*-fold*.npz")):
        name, _, lo = f.stem.rpartition("-fold")
        if lo.isdigit():
            found.setdefault(name, {})[int(lo)] = f
    return found


def folds(args: argparse.Namespace) -> None:
    import geoloc
    from geoloc.features import FeatureExtractor

    seq = geoloc.datasets.load_7scenes(args.data)
    n = min(len(seq), 700)
    poses = np.stack([seq.poses[i] for i in range(n)])
    extractor = FeatureExtractor()
    features = [extractor(seq.gray(i), seq.camera) for i in range(n)]
    tiny = tiny_image_descriptors([seq[i].image for i in range(n)])
    networks = network_descriptors(args.descriptors) if args.descriptors else {}
    common = dict(estimate_noise=False, refine_intrinsics=False, adjust_labels=False, model=False)
    table: dict[str, dict[str, float]] = {}
    seconds: dict[str, list[float]] = {}
    methods = ["tiny image", "BoW"] + [f"{net} {m}" for net in networks for m in ("alone", "fused k=1", "fused k=5")]
    print("recall@1 (%) per fold; 'fused k=1': the fused ranking's first keyframe of BoW's best and the network's, "
          "verified (the paper locator's fallback); 'fused k=5': of BoW's 5 and the network's first 2, verified "
          "(the model locator's fallback)", flush=True)
    print(f"{'fold':<9} " + " ".join(f"{m:>{max(10, len(m))}}" for m in methods) + f" {'ceiling':>8}", flush=True)
    for lo in range(0, n, 100):
        hi = min(lo + 100, n)
        train_idx = np.array([i for i in range(n) if i < lo - 15 or i >= hi + 15])
        test_idx = np.arange(lo, hi)
        correct = correct_matrix(poses[train_idx], poses[test_idx])

        def recall(top: list[int]) -> float:
            return float(correct[np.arange(len(top)), top].mean())

        row = {"tiny image": recall_at_k(correct, rank_by_descriptors(tiny[train_idx], tiny[test_idx], 1), 1).recall_at_1}
        kps, descs = [features[i].keypoints for i in train_idx], [features[i].descriptors for i in train_idx]
        bow = geoloc.Map.from_features(seq.camera, poses[train_idx], kps, descs, **common)
        row["BoW"] = recall([bow.retrieve_features(features[q].keypoints, features[q].descriptors, k=1)[0] for q in test_idx])
        for net, files in networks.items():
            if lo not in files:
                continue
            d = np.load(files[lo])["descriptors"].astype(np.float32)
            row[f"{net} alone"] = recall_at_k(correct, rank_by_descriptors(d[train_idx], d[test_idx], 1), 1).recall_at_1
            fused = geoloc.Map.from_features(seq.camera, poses[train_idx], kps, descs, global_descriptors=d[train_idx], retrieval="fused", **common)
            for k in (1, 5):
                start = time.perf_counter()
                top = [fused.retrieve_features(features[q].keypoints, features[q].descriptors, d[q], k=k)[0] for q in test_idx]
                seconds.setdefault(f"fused k={k}", []).append((time.perf_counter() - start) / len(test_idx))
                row[f"{net} fused k={k}"] = recall(top)
        row["ceiling"] = float(correct.any(axis=1).mean())
        name = f"{lo}-{hi - 1}"
        table[name] = row
        cells = [f"{100 * row[m]:>{max(10, len(m)) - 1}.0f}%" if m in row else f"{'-':>{max(10, len(m))}}" for m in methods]
        print(f"{name:<9} " + " ".join(cells) + f" {100 * row['ceiling']:>7.0f}%", flush=True)
    mean = {m: float(np.mean([r[m] for r in table.values() if m in r])) for m in methods}
    print(f"{'mean':<9} " + " ".join(f"{100 * mean[m]:>{max(10, len(m)) - 1}.1f}%" for m in methods))
    worst = {m: float(min(r[m] - r["BoW"] for r in table.values() if m in r)) for m in methods if m != "BoW"}
    print("gain over BoW on the worst fold (recall@1 points): " + ", ".join(f"{m} {100 * g:+.0f}" for m, g in worst.items()))
    for k, v in seconds.items():
        print(f"{k}: {1e3 * float(np.median(v)):.1f} ms per query (median over folds; 2 threads)")
    if args.json:
        Path(args.json).write_text(json.dumps({"folds": table, "mean": mean, "worst_gain_over_bow": worst}, indent=1))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--model", type=Path, action="append", default=[], help="an ONNX descriptor model (repeatable)")
    parser.add_argument("--train-tiny", type=int, default=0, metavar="EPOCHS", help="also train a tiny CNN here (needs torch)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--k", type=int, default=5)
    parser.add_argument("--folds", action="store_true", help="every 100-frame block of 0-699 in turn (see above)")
    parser.add_argument("--descriptors", type=Path, help="--folds: a folder of benchmarks/train_folds.py outputs")
    parser.add_argument("--json", help="write the table here")
    args = parser.parse_args()
    if not args.data.is_dir():
        sys.exit(f"no 7-Scenes frames at {args.data}")
    if args.folds:
        folds(args)
        return

    frames = SevenScenesFrames(args.data)
    images = [frames[i].image for i in range(len(TRAIN) + len(TEST))]
    poses = poses_of(frames)
    train_imgs, test_imgs = images[: len(TRAIN)], images[len(TRAIN) :]
    correct = correct_matrix(poses[list(TRAIN)], poses[list(TEST)])
    rows: list[tuple[str, RecallReport, str]] = []

    tiny = tiny_image_descriptors(images)
    rows.append(("tiny image 32×24 (L2)", recall_at_k(correct, rank_by_descriptors(tiny[: len(TRAIN)], tiny[len(TRAIN) :], args.k), args.k), ""))
    ranked, build_s = bow_ranking(train_imgs, test_imgs, args.k)
    rows.append(("BoW (ORB 1000, 10^3 words, TF-IDF)", recall_at_k(correct, ranked, args.k), f"build {build_s:.1f} s"))

    models = list(args.model)
    if args.train_tiny:
        gray = gray_images(frames, range(len(TRAIN) + len(TEST)))
        models.append(train_tiny(frames, gray, args.train_tiny, Path(tempfile.mkdtemp()) / "tiny.onnx"))
    x = preprocess(test_imgs[:32])
    for path in models:
        net = OnnxDescriptor(path, threads=args.threads, batch_size=16)
        d = net(images)
        report = recall_at_k(correct, rank_by_descriptors(d[: len(TRAIN)], d[len(TRAIN) :], args.k), args.k)
        ms1, ms16 = time_per_image(net, x, 1), time_per_image(net, x, 16)
        e2e1, e2e16 = time_end_to_end(net, test_imgs[:32], 1), time_end_to_end(net, test_imgs[:32], 16)
        size = os.path.getsize(path) / 1e6
        rows.append((
            f"CNN {net.name} (D={net.dim})",
            report,
            f"{ms1:.2f} / {ms16:.2f} ms/img network, {e2e1:.2f} / {e2e16:.2f} with preprocessing "
            f"(batch 1 / 16, {args.threads} threads), {size:.1f} MB",
        ))

    print(f"\n7-Scenes redkitchen: train 0–599, queries 600–699; correct = within 0.3 m and 15°; "
          f"ceiling {100 * rows[0][1].ceiling:.0f} % (queries with any correct training image)")
    print(f"  {'method':<38} {'recall@1':>9} {'recall@' + str(args.k):>9}   notes")
    for name, r, note in rows:
        print(f"  {name:<38} {100 * r.recall_at_1:>8.0f}% {100 * r.recall_at_k:>8.0f}%   {note}")
    if args.json:
        table = {name: {"recall_at_1": r.recall_at_1, f"recall_at_{args.k}": r.recall_at_k, "notes": note} for name, r, note in rows}
        Path(args.json).write_text(json.dumps({"split": "train 0-599, queries 600-699", "ceiling": rows[0][1].ceiling,
                                               "methods": table}, indent=1))


if __name__ == "__main__":
    main()
