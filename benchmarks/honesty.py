"""Honesty as a rate: does a `geometric`/`fused` answer lie about where the camera is?

Maps of 30, 100 and 600 keyframes of the shared 7-Scenes redkitchen frames (0:60:2, 0:300:3,
0:600), and two maps of 100 consecutive frames elsewhere in the sequence (300:400 and 500:600,
named 100@300 and 100@500: the kitchen seen from other places, so that the out-of-map
queries are not all of one region); queries each map covers and queries it does not:

* ``in-range`` — frames inside the map's span that are not keyframes (0:60:2, 0:300:3: the
  frames between keyframes, every 4th / 7th), for the 600-keyframe map the paper's test
  frames 600–699 (every 2nd), none for the 100@ maps (every frame of their span is a keyframe);
* ``outside`` — frames of 0–699 more than 30 frames from the map's span, every 10th (the
  kitchen loops: some of these see what the map saw, from elsewhere);
* ``other-scene`` — 40 frames of the synthetic room (another place entirely);
* ``noise`` — 20 images of uniform noise and 20 of blurred noise.

Every query is localized with both locators, ``single`` (``reset()`` before each frame) and
``sequential`` (each query set in capture order through the motion model). Errors are
measured against the SfM reference (``../shared/data/7scenes-redkitchen-reference``),
aligned to each map's keyframe poses on the map's own frames as ``geoloc evaluate
--reference`` does; a pose for an other-scene or noise query is a gross error by definition.

Among frames reported ``geometric``/``fused`` it prints the fraction outside the 99.9 % χ²₆
region of the returned covariance (NEES > 22.46) and the fraction more than 0.5 m or 10° off
— the acceptance targets are ≤ 1 % and ≤ 0.5 % — and, per map, the recall of the in-range
queries (reported and within 0.5 m / 10°), with the worst offenders.

    PYTHONPATH=python python benchmarks/honesty.py [--maps 30,100,100@300,100@500,600] [--locators paper,model]
        [--modes single,sequential] [--keep-labels] [--json out.json]

Not a test: the 600-keyframe map alone takes about a minute to build on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from geoloc.evaluation import CHI2_6_999

ROOT = Path(__file__).resolve().parent.parent
DATA = ROOT.parent / "shared" / "data"
KITCHEN = DATA / "7scenes-redkitchen"
REFERENCE = DATA / "7scenes-redkitchen-reference" / "sfm-poses.txt"

#: map name → (first, stop, step) of its keyframes.
MAPS = {"30": (0, 60, 2), "100": (0, 300, 3), "100@300": (300, 400, 1), "100@500": (500, 600, 1), "600": (0, 600, 1)}
#: map name → (first, stop, step) of the frames after its span that are its ``in-range``
#: queries rather than ``outside`` ones: the paper's test frames for the 600-keyframe map.
TEST_SPANS = {"600": (600, 700, 2)}
#: Query frames this many frames from the map's span or more are ``outside`` it.
OUTSIDE_MARGIN = 30
GROSS_M, GROSS_DEG = 0.5, 10.0


def query_sets(name: str, n_frames: int) -> dict[str, list[int]]:
    a, b, s = MAPS[name]
    # between the keyframes of a subsampled map (a map of every frame has none)
    in_range = [i for i in range(a, b) if i % s][:: max(1, (b - a) // (s * 15))] if s > 1 else []
    outside = [i for i in range(0, n_frames, 10) if i < a - OUTSIDE_MARGIN or i >= b + OUTSIDE_MARGIN]
    if name in TEST_SPANS:
        lo, hi, step = TEST_SPANS[name]
        in_range += list(range(lo, min(hi, n_frames), step))
        outside = [i for i in outside if not lo <= i < hi]
    return {"in-range": in_range, "outside": outside}


def noise_images(shape: tuple[int, int], seed: int = 0) -> list[np.ndarray]:
    import cv2

    rng = np.random.default_rng(seed)
    plain = [rng.integers(0, 256, shape, dtype=np.uint8) for _ in range(20)]
    blurred = [cv2.GaussianBlur(rng.integers(0, 256, shape, dtype=np.uint8), (0, 0), 2.0) for _ in range(20)]
    return plain + blurred


def run_queries(localizer: Any, images: list[Any], mode: str) -> list[Any]:
    localizer.reset()
    out = []
    for t, image in enumerate(images):
        if mode == "single":
            localizer.reset()
        out.append(localizer.localize(image, 1.0 + t / 30.0))
    return out


def score(results: list[Any], truth: np.ndarray | None) -> list[dict[str, Any]]:
    from geoloc import evaluation

    rows = []
    for k, r in enumerate(results):
        row: dict[str, Any] = {"source": r.source, "inliers": int(r.inliers), "reason": r.reason}
        if r.source in ("geometric", "fused"):
            if truth is None:
                row.update(position_m=float("inf"), rotation_deg=float("inf"), nees=float("inf"))
            else:
                p, a = evaluation.pose_errors(r.pose[None], truth[k][None])
                row.update(
                    position_m=float(p[0]),
                    rotation_deg=float(a[0]),
                    nees=float(evaluation.nees(r.pose[None], r.covariance[None], truth[k][None])[0]),
                )
        rows.append(row)
    return rows


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    reported = [r for r in rows if r["source"] in ("geometric", "fused")]
    gross = [r for r in reported if r["position_m"] > GROSS_M or r["rotation_deg"] > GROSS_DEG]
    outside = [r for r in reported if not r["nees"] <= CHI2_6_999]
    return {
        "frames": len(rows),
        "reported": len(reported),
        "gross": len(gross),
        "outside_999": len(outside),
        "correct": len(reported) - len(gross),
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--maps", default="30,100,100@300,100@500,600")
    ap.add_argument("--locators", default="paper,model")
    ap.add_argument("--modes", default="single,sequential")
    ap.add_argument("--json", default=None)
    ap.add_argument("--keep-labels", dest="adjust_labels", action="store_false",
                    help="build the maps with the labels as given (adjust_labels=False, the CLI's --keep-labels)")
    args = ap.parse_args()
    if not KITCHEN.is_dir() or not REFERENCE.is_file():
        print(f"honesty: needs {KITCHEN} and {REFERENCE}", file=sys.stderr)
        return 2
    import geoloc
    from geoloc.datasets import load_7scenes, synthetic_room
    from geoloc.reference import align_reference, load_reference, match_reference

    kitchen = load_7scenes(KITCHEN)
    keys, ref_poses = load_reference(REFERENCE)
    room = synthetic_room(40, seed=3)
    room_images = [room.gray(i) for i in range(len(room))]
    noise = noise_images(kitchen.gray(0).shape)
    report: dict[str, Any] = {"maps": {}}
    totals: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for name in args.maps.split(","):
        a, b, s = MAPS[name]
        train = kitchen[list(range(a, b, s))]
        start = time.perf_counter()
        the_map = geoloc.Map.build(train, model=True, adjust_labels=args.adjust_labels)
        build_s = time.perf_counter() - start
        rows_train = match_reference(keys, train.indices)
        alignment = align_reference(ref_poses[rows_train], the_map.keyframe_poses)
        sets = query_sets(name, len(kitchen))
        noise_note = "C_map " + str(the_map.map_noise.get("pose_covariance_source", "(not described)"))
        print(f"map {name}: {len(train)} keyframes, built in {build_s:.0f} s {noise_note}", flush=True)
        map_report: dict[str, Any] = {"build_s": build_s, "sets": {}}
        for locator in args.locators.split(","):
            localizer = geoloc.Localizer(the_map, locator=locator)  # type: ignore[arg-type]
            for mode in args.modes.split(","):
                for set_name in ("in-range", "outside", "other-scene", "noise"):
                    if set_name in sets:
                        frames = sets[set_name]
                        images: list[Any] = [kitchen.gray(i) for i in frames]
                        truth = alignment.apply(ref_poses[match_reference(keys, np.array(frames))])
                    else:
                        images = room_images if set_name == "other-scene" else noise
                        truth = None
                    rows = score(run_queries(localizer, images, mode), truth)
                    for row, frame in zip(rows, sets.get(set_name, range(len(rows)))):
                        row["frame"] = int(frame)
                    totals.setdefault((locator, mode), []).extend(rows)
                    sm = summary(rows)
                    map_report["sets"][f"{locator}/{mode}/{set_name}"] = {"summary": sm, "rows": rows}
                    worst = sorted(
                        (r for r in rows if r["source"] in ("geometric", "fused") and not r["nees"] <= CHI2_6_999),
                        key=lambda r: -r["nees"],
                    )[:3]
                    note = "  ".join(
                        f"#{r['frame']} {r['position_m']:.2f} m/{r['rotation_deg']:.1f}° NEES {r['nees']:.0f}"
                        for r in worst
                    )
                    print(
                        f"  {locator:<6} {mode:<10} {set_name:<12} {sm['frames']:>4} frames  reported {sm['reported']:>4}"
                        f"  correct {sm['correct']:>4}  gross {sm['gross']:>3}  outside 99.9% {sm['outside_999']:>3}  {note}",
                        flush=True,
                    )
        report["maps"][name] = map_report
    print("\nall maps and query sets (rates among reported frames; targets ≤ 1 % outside, ≤ 0.5 % gross):")
    for (locator, mode), rows in totals.items():
        sm = summary(rows)
        n = max(sm["reported"], 1)
        print(
            f"  {locator:<6} {mode:<10} reported {sm['reported']:>5} of {sm['frames']:>5}   outside 99.9 % "
            f"{100 * sm['outside_999'] / n:5.2f} %   gross {100 * sm['gross'] / n:5.2f} %"
        )
        report.setdefault("totals", {})[f"{locator}/{mode}"] = sm
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1, default=float) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
