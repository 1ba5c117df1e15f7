"""Runs of consistent gross errors in a calibration run: label disagreement, located in time.

Reads the ``--json`` of ``benchmarks/calibration.py`` (every frame's error δ = log(T_label⁻¹
T_est) in the camera frame, its retrieved keyframe, and each map's held-out keyframes with
their errors) and prints, per cross-validation fold,

* the *runs* of test frames (at least ``--min-run`` consecutive, single-image mode) whose
  error exceeds ``--gross`` m, with the median error vector of the run and the frame numbers
  of the keyframes they were localized against, and the error of the fold's other frames;
* the held-out keyframes of the fold's map with an error above ``--gross`` (frame numbers).

A locator failure (RANSAC on the wrong place, a wrong minimum) gives errors that change from
one frame to the next with the retrieved keyframes and the inliers; a disagreement between
the labels of two parts of the trajectory gives the *same* error vector over a whole run of
frames whatever keyframes they are matched to, and the same part of the trajectory shows up
in the held-out keyframes of the other folds' maps. Which one it is decides whether a
covariance estimated from the map can cover it: the map cannot know that the labels of a
part it does not contain disagree with its own.

    PYTHONPATH=python python benchmarks/calibration.py --json cal.json
    PYTHONPATH=python python benchmarks/label_runs.py cal.json

Measured 2026-11-25 on ``calibration.py`` (paper locator, ORB, per-keypoint σ, the nominal
camera fx = fy = 525), runs of ≥ 5 frames with errors above 15 cm:

    fold 300-399  run 329-373: 33 of 45 frames, median (+19, -20, -16) cm (-5.2, -4.5, -0.5)°,
                  localized against frames 420-473 (and 280, 284); the fold's other 55
                  frames: median 3.1 cm
    fold 400-499  run 431-450: 11 of 20 frames, median (-28, +18, +1) cm (+4.0, +5.4, +0.9)°,
                  localized against frames 349-368; the other 65 frames: median 3.6 cm
    held out      5-6 keyframes of 340-375 and 440-475 are 16-48 cm off in each of the five
                  maps that hold both visits (folds 0-99, 100-199, 200-299, 500-599, 600-699)

With each map's camera estimated from its own keyframes (``Map.build``'s default, 2026-11-25)
the same runs remain: 340-373, 28 of 34 frames, (+27, -18, -12) cm (-4.8, -6.0, -0.8)°
against 422-466; 433-461, 16 of 29 frames, (-15, +20, 0) cm (+4.3, +3.1, -0.7)° against
352-372 — the camera model is not what makes them.

The two runs are the same disagreement seen from either side — queries of ≈ 330-370
against a map of ≈ 420-470 and queries of ≈ 430-450 against a map of ≈ 350-370 — with
opposite signs: the labels of these two visits of one part of the kitchen disagree by
20-30 cm and 5-7°, which no locator can be within less of both. A 100-frame test block that
holds one visit cannot be covered by a noise estimate made from a map that lacks it (fold
300-399: 67 % NEES coverage), and a map that holds both inflates every other fold's estimate
(200-299, 500-599: 99-100 %).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

BLOCK = 100
MARGIN = 15
FRAMES = 700


def training_frames(lo: int, n: int = FRAMES) -> np.ndarray:
    """The frame numbers of a fold's map keyframes (calibration.py's split)."""
    return np.array([i for i in range(n) if i < lo - MARGIN or i >= lo + BLOCK + MARGIN])


def runs(mask: np.ndarray, min_run: int, max_gap: int = 3) -> list[tuple[int, int]]:
    """[start, end) of the runs of True in ``mask`` at least ``min_run`` long, bridging gaps
    of at most ``max_gap`` False entries."""
    out: list[tuple[int, int]] = []
    idx = np.flatnonzero(mask)
    if len(idx) == 0:
        return out
    start = prev = int(idx[0])
    for i in idx[1:]:
        if i - prev > max_gap + 1:
            if prev + 1 - start >= min_run:
                out.append((start, prev + 1))
            start = int(i)
        prev = int(i)
    if prev + 1 - start >= min_run:
        out.append((start, prev + 1))
    return out


def describe(name: str, fold: dict[str, Any], gross: float, min_run: int) -> list[str]:
    lo = int(name.split("-")[0])
    kf_frames = training_frames(lo)
    frames = fold["frames"]["single"]
    err = np.array([np.inf if f["delta"] is None else np.linalg.norm(f["delta"][:3]) for f in frames])
    lines = []
    gross_mask = np.isfinite(err) & (err > gross)
    found = runs(gross_mask, min_run)
    inside = np.zeros(len(frames), dtype=bool)
    for a, b in found:
        inside[a:b] = True
        deltas = np.array([frames[j]["delta"] for j in range(a, b) if gross_mask[j]])
        med = np.median(deltas, axis=0)
        kfs = sorted({int(kf_frames[frames[j]["keyframe"]]) for j in range(a, b) if gross_mask[j]})
        lines.append(
            f"  run {lo + a}-{lo + b - 1}: {int(np.sum(gross_mask[a:b]))} of {b - a} frames > {100 * gross:.0f} cm, "
            f"median error ({', '.join(f'{100 * v:+.0f}' for v in med[:3])}) cm "
            f"({', '.join(f'{np.degrees(v):+.1f}' for v in med[3:])})°, keyframes (frame numbers) {kfs}"
        )
    rest = err[~inside & np.isfinite(err)]
    if found and len(rest):
        lines.append(f"  the other {len(rest)} localized frames: median {100 * np.median(rest):.1f} cm")
    held = fold["map_noise"]["holdout"]
    big = [
        (int(kf_frames[k]), float(np.linalg.norm(np.array(d)[:3])))
        for k, d in zip(held["keyframe"], held["delta"])
        if np.linalg.norm(np.array(d)[:3]) > gross
    ]
    if big:
        lines.append("  held-out keyframes of this map > "
                     f"{100 * gross:.0f} cm: " + ", ".join(f"frame {f} {100 * e:.0f} cm" for f, e in big))
    return lines


def main() -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("json", help="the --json output of benchmarks/calibration.py")
    ap.add_argument("--gross", type=float, default=0.15, help="an error above this is gross (m, default 0.15)")
    ap.add_argument("--min-run", type=int, default=5, help="shortest run of gross frames (default 5)")
    args = ap.parse_args()
    report = json.loads(Path(args.json).read_text())
    for name, fold in report.items():
        if name == "synthetic" or "frames" not in fold:
            continue
        print(f"fold {name}:")
        lines = describe(name, fold, args.gross, args.min_run)
        print("\n".join(lines) if lines else "  no run of gross errors")
    return 0


if __name__ == "__main__":
    sys.exit(main())
