"""Matching against OpenCV's brute-force matcher, and the per-frame cost of the localizer.

    python benchmarks/localizer.py [--json FILE]

1. 2000 × 2000 binary (ORB-like, 32-byte) descriptors with ratio test 0.8 and mutual check:
   geoloc.matching vs cv2.BFMatcher(NORM_HAMMING).knnMatch(k=2) + ratio + cross check;
   1000 × 1000 float (128-D) descriptors vs cv2 NORM_L2. Same matches required.
2. One localizer step on a simulated sequence (1500 landmarks, ~1000 features per frame,
   BoW retrieval): per-stage median milliseconds over 60 frames.
Not part of the test suite. ``--json``: the same numbers, for ``benchmarks/report.py``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from typing import Any

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "tests"))

import geoloc  # noqa: E402
from geoloc import matching  # noqa: E402
from geoloc import Localizer, Map  # noqa: E402


def best_of(fn, repeats=5):  # type: ignore[no-untyped-def]
    times = []
    out = None
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - start)
    return min(times), out


def cv2_matches(a: np.ndarray, b: np.ndarray, norm: int) -> set[tuple[int, int]]:
    import cv2

    bf = cv2.BFMatcher(norm)
    fwd = bf.knnMatch(a, b, k=2)
    back = {m.queryIdx: m.trainIdx for m in bf.match(b, a)}
    return {(m.queryIdx, m.trainIdx) for m, n in fwd if m.distance < 0.8 * n.distance and back.get(m.trainIdx) == m.queryIdx}


def bench_matching() -> dict[str, Any]:
    rows: dict[str, Any] = {}
    rng = np.random.default_rng(0)
    try:
        import cv2
    except ImportError:
        cv2 = None
        print("(cv2 not installed: peers skipped)")
    for kind, n in (("binary 32 B", 2000), ("float 128-D", 1000)):
        if kind.startswith("binary"):
            a = rng.integers(0, 256, (n, 32), dtype=np.uint8)
            b = a[rng.permutation(n)].copy()
            b[:, 0] ^= rng.integers(0, 8, n, dtype=np.uint8)
            norm = None if cv2 is None else cv2.NORM_HAMMING
        else:
            a = rng.normal(size=(n, 128)).astype(np.float32)
            b = (a[rng.permutation(n)] + 0.05 * rng.normal(size=(n, 128))).astype(np.float32)
            norm = None if cv2 is None else cv2.NORM_L2
        t_g, (pairs, _) = best_of(lambda: matching.match_descriptors(a, b))
        line = f"  {kind:<12} {n} × {n}: geoloc {t_g * 1e3:7.1f} ms ({len(pairs)} matches)"
        row: dict[str, Any] = {"n": n, "geoloc_ms": t_g * 1e3, "matches": len(pairs)}
        if cv2 is not None:
            t_c, ref = best_of(lambda: cv2_matches(a, b, norm), 3)
            same = ref == {tuple(p) for p in pairs.tolist()}
            line += f", cv2 BFMatcher {t_c * 1e3:7.1f} ms ({len(ref)} matches) → {t_c / t_g:.1f}× ; same matches: {same}"
            row.update(cv2_ms=t_c * 1e3, cv2_over_geoloc=t_c / t_g, same_matches=same)
        print(line)
        rows[kind] = row
    return rows


def bench_localizer() -> dict[str, float]:
    from test_localizer import CAM, _observe, _walk

    rng = np.random.default_rng(0)
    pts = rng.uniform([-4, -1.5, 3], [4, 1.5, 7], (1500, 3))
    desc = rng.integers(0, 256, (1500, 32), dtype=np.uint8)
    poses = np.stack([_walk(0.1 * i, 0.0) for i in range(60)])
    obs = [_observe(rng, p, pts, desc) for p in poses]
    start = time.perf_counter()
    m = Map.from_features(CAM, poses, [o[0] for o in obs], [o[1] for o in obs], branching=10, depth=3, estimate_noise=False, refine_intrinsics=False, adjust_labels=False)
    print(f"  map of 60 keyframes ({np.mean([len(o[0]) for o in obs]):.0f} features each): built in {time.perf_counter() - start:.2f} s")
    loc = Localizer(m)
    stages: dict[str, list[float]] = {}
    for f in range(60):
        t = 0.3 + f / 30
        kp, d = _observe(rng, _walk(t, 0.15), pts, desc)
        r = loc.localize_features(t, kp, d)
        for k, v in r.timings.items():
            stages.setdefault(k, []).append(v)
    print("  per-frame median ms: " + ", ".join(f"{k} {np.median(v):.2f}" for k, v in stages.items()))
    print(f"  (map_points is non-zero only when the keyframe group changes: mean {np.mean(stages['map_points']):.1f} ms)")
    return {k: float(np.median(v)) for k, v in stages.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", default=None, help="also write the numbers here")
    args = parser.parse_args()
    print(f"geoloc {geoloc.__version__}, {os.cpu_count()} CPUs")
    print("matching (ratio 0.8 + mutual check):")
    matched = bench_matching()
    print("localizer step:")
    step = bench_localizer()
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"matching": matched, "localizer_step_median_ms": step}, f, indent=1)


if __name__ == "__main__":
    main()
