"""Per-stage latency of the image pipeline on real 640×480 frames, and the cost of Map.build.

    PYTHONPATH=python python benchmarks/pipeline.py [--dataset ../shared/data/7scenes-redkitchen]

A map is built from frames 0–599 of the 7-Scenes sample (ORB, 1000 features, BoW), then
frames 600–699 are localized in single mode (history forgotten before every frame) and in
sequential mode (motion model + fusion). For each stage — decode (JPEG → grey), features
(ORB + undistortion), retrieval (BoW), keyframes + triangulation (keyframe group, cached
map points), matching, PnP (RANSAC + LM + covariance), motion/fusion — and for the whole
frame, the median and 90th percentile in milliseconds are printed, plus the wall time of
Map.build on the 600 frames and of its feature extraction alone. The load average is
printed with the table: timings on a shared machine are only comparable at equal load.
Not part of the test suite.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "python"))

from geoloc import datasets  # noqa: E402
from geoloc.features import FeatureExtractor  # noqa: E402
from geoloc import Localizer, Map  # noqa: E402

DEFAULT_DATASET = ROOT.parent / "shared" / "data" / "7scenes-redkitchen"
#: Printed rows: (label, the localizer's stage names summed per frame).
STAGES = (
    ("decode", ("decode",)),
    ("features", ("features",)),
    ("retrieval", ("retrieval",)),
    ("keyframes + triangulation", ("keyframes", "map_points")),
    ("matching", ("matching",)),
    ("PnP", ("pnp",)),
    ("motion + fusion", ("motion_fusion",)),
    ("total (end to end)", ("total",)),
)


def stage_stats(results: list[object]) -> dict[str, tuple[float, float]]:
    """(median, p90) ms per printed stage."""
    out = {}
    for label, keys in STAGES:
        values = np.array([sum(r.timings.get(k, 0.0) for k in keys) for r in results])  # type: ignore[attr-defined]
        out[label] = (float(np.median(values)), float(np.percentile(values, 90)))
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset", default=str(DEFAULT_DATASET), help="7-Scenes folder (default: the shared sample)")
    parser.add_argument("--intrinsics", default="525,525,320,240", help="fx,fy,cx,cy (default: 525,525,320,240)")
    parser.add_argument("--train", type=int, nargs=2, default=(0, 600), metavar=("A", "B"), help="map frames (default 0 600)")
    parser.add_argument("--test", type=int, nargs=2, default=(600, 700), metavar=("C", "D"), help="query frames (default 600 700)")
    args = parser.parse_args()
    if not Path(args.dataset).is_dir():
        print(f"pipeline benchmark: dataset {args.dataset!r} not found (see ../shared/data/README.md)", file=sys.stderr)
        return 2
    fx, fy, cx, cy = (float(v) for v in args.intrinsics.split(","))
    seq = datasets.load_7scenes(args.dataset, intrinsics=(fx, fy, cx, cy))
    train, test = seq[args.train[0] : args.train[1]], seq[args.test[0] : args.test[1]]
    load_before = os.getloadavg()

    extract = FeatureExtractor()
    start = time.perf_counter()
    for i in range(len(train)):
        extract(train.gray(i), train.camera)
    features_s = time.perf_counter() - start
    start = time.perf_counter()
    the_map = Map.build(train)
    build_s = time.perf_counter() - start

    stats = {}
    walls = {}
    for mode in ("single", "sequential"):
        start = time.perf_counter()
        results = Localizer(the_map).localize_sequence(test, mode)
        walls[mode] = (time.perf_counter() - start) / len(test)
        stats[mode] = stage_stats(results)
        lost = sum(r.pose is None for r in results)
        stats[mode]["lost frames"] = (float(lost), float(lost))
    load_after = os.getloadavg()

    print(f"geoloc pipeline benchmark: {seq.name}, {seq.camera.width}×{seq.camera.height}, ORB 1000 + BoW; "
          f"map frames {args.train[0]}–{args.train[1] - 1}, queries {args.test[0]}–{args.test[1] - 1}")
    print(f"machine: {os.cpu_count()} cores, load average {load_before[0]:.1f} before, {load_after[0]:.1f} after")
    print(f"\nMap.build on {len(train)} frames: {build_s:.1f} s "
          f"({1e3 * build_s / len(train):.1f} ms/frame; decode + ORB alone {features_s:.1f} s)")
    print(f"\n{'stage (ms per frame)':<28}{'single median':>15}{'single p90':>12}{'seq. median':>13}{'seq. p90':>10}")
    for label in [s[0] for s in STAGES] + ["lost frames"]:
        (m1, p1), (m2, p2) = stats["single"][label], stats["sequential"][label]
        fmt = ".0f" if label == "lost frames" else ".2f"
        print(f"{label:<28}{m1:>15{fmt}}{p1:>12{fmt}}{m2:>13{fmt}}{p2:>10{fmt}}")
    print(f"{'wall time per frame (mean)':<28}{1e3 * walls['single']:>15.2f}{'':>12}{1e3 * walls['sequential']:>13.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
