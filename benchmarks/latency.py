"""Per-frame latency of the core (features given): median / p90 / p99 / max on the paper's split.

The map is built from the shared 7-Scenes frames 0–599 (every frame, with its 3D model); the
test frames 600–699 are described once (ORB 1000, as the map), then localized by the core
alone — ``Localizer.localize_features`` with the keypoints and descriptors given, so decoding
and feature extraction are not in the times — with both locators, single (``reset()``
before every frame) and sequential. Each of ``--passes`` passes uses a fresh localizer (as on
a robot that just started), so a tail that comes from work done on first use shows in every
pass; the time to create it (``start``: work done before the first frame) and the memory it
holds (``MB``: resident memory added by creating the localizer and running a pass, the
largest over the passes; Linux only) are printed beside. A robot at 30 Hz needs p99 ≤ 2× the
median and ≤ 20 ms.

    GEOLOC_NUM_THREADS=2 PYTHONPATH=python python benchmarks/latency.py [--passes 3] [--json out.json]

Not a test: timings belong here, not in the test suite.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
KITCHEN = ROOT.parent / "shared" / "data" / "7scenes-redkitchen"


def resident_mb() -> float:
    """This process's resident memory (MB) from /proc/self/status; NaN where there is none."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


def percentiles(ms: list[float]) -> dict[str, float]:
    a = np.asarray(ms)
    return {
        "median": float(np.median(a)),
        "p90": float(np.percentile(a, 90)),
        "p99": float(np.percentile(a, 99)),
        "max": float(a.max()),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--passes", type=int, default=3)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    import geoloc
    from geoloc.datasets import load_7scenes
    from geoloc import Localizer

    seq = load_7scenes(KITCHEN)
    start = time.perf_counter()
    the_map = geoloc.Map.build(seq[0:600], model=True)
    print(f"map: 600 keyframes in {time.perf_counter() - start:.0f} s", flush=True)
    test = seq[600:700]
    features = [the_map.features(test.gray(i), the_map.camera) for i in range(len(test))]
    report: dict[str, Any] = {}
    print(f"{'locator':<7} {'mode':<11} {'median':>8} {'p90':>8} {'p99':>8} {'max':>8}  p99/median  start    MB  "
          f"(ms, {args.passes} passes × 100 frames; start: creating the localizer, median over the passes; "
          "MB: resident memory it added, largest pass)")
    for locator in ("paper", "model"):
        for mode in ("single", "sequential"):
            ms: list[float] = []
            start_ms: list[float] = []
            held_mb: list[float] = []
            for _ in range(args.passes):
                before = resident_mb()
                t0 = time.perf_counter()
                loc = Localizer(the_map, locator=locator)  # a fresh localizer, as a robot that just started
                start_ms.append(1e3 * (time.perf_counter() - t0))
                for k, f in enumerate(features):
                    if mode == "single":
                        loc.reset()
                    t0 = time.perf_counter()
                    loc.localize_features(float(test.timestamps[k]), f.keypoints, f.descriptors, None, pixel_sigmas=f.pixel_sigmas)
                    ms.append(1e3 * (time.perf_counter() - t0))
                held_mb.append(resident_mb() - before)
                del loc
            p = percentiles(ms)
            p["start"] = float(np.median(start_ms))
            p["memory_mb"] = float(max(held_mb))
            report[f"{locator}/{mode}"] = p
            print(
                f"{locator:<7} {mode:<11} {p['median']:8.2f} {p['p90']:8.2f} {p['p99']:8.2f} {p['max']:8.2f}  "
                f"{p['p99'] / p['median']:10.2f} {p['start']:6.0f} {p['memory_mb']:5.0f}",
                flush=True,
            )
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
