"""Novel viewpoints: the paper's locator vs the map-level 3D model locator.

Cross-validation on the shared 7-Scenes redkitchen frames 0–699: a test block of 100 frames,
the map trained on the rest minus 15 frames on either side; single-image mode (``reset()``
before every frame), fx = fy = 525, BoW retrieval, 1000 features. Per fold × locator
(paper, model) × features (ORB, SIFT): median translation / rotation error, recall within
5 cm / 5°, median PnP inliers, median per-frame core time (``timings["total"]``), and the
map build time (features are extracted once, outside the timings): BoW vocabulary and
database, the camera estimate (``--refine-intrinsics``) and the 3D model, one ``Map.from_features(...,
model=True, estimate_noise=False, refine_intrinsics=False, adjust_labels=False)`` (with the estimate, the keyframe pairs are matched once for both).

    PYTHONPATH=python python benchmarks/novel_views.py [--folds 6,0] [--features orb,sift] [--json out.json]
        [--uniform-sigma] [--refine-intrinsics] [--adjust-labels] [--reference FILE]

Errors are against the labels and, on a second row per locator (``vs ref``), against the SfM
reference (``--reference``, default the shared one when present) aligned on the fold's training
frames to the map's keyframe poses (``geoloc.reference.align_reference``, as ``geoloc evaluate
--reference`` does). The maps keep their labels unless ``--adjust-labels`` (``Map.build``'s
default) has them corrected by bundle adjustment.

Each query keypoint is weighted by its detector-scale σ (``Features.pixel_sigmas``), as
``geoloc.Localizer`` does; ``--uniform-sigma`` weights them all alike (1 px).

Not a test: each fold builds a map of ~570 frames and its model per feature kind. ``GEOLOC_NUM_THREADS``
defaults to 2 here (the issue's "2 cores").
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "7scenes-redkitchen"
REFERENCE = DATA.parent / "7scenes-redkitchen-reference" / "sfm-poses.txt"
BLOCK = 100
MARGIN = 15
FRAMES = 700


def extract(seq: Any, kind: str) -> tuple[list[Any], list[Any], list[Any]]:
    """Keypoints, descriptors and pixel σ of every frame (the extractor of ``geoloc.Map.build``)."""
    from geoloc.features import FeatureExtractor

    ex = FeatureExtractor(kind, 1000)  # type: ignore[arg-type]
    kps, descs, sigmas = [], [], []
    for i in range(len(seq)):
        f = ex(seq.gray(i), seq.camera)
        kps.append(f.keypoints)
        descs.append(f.descriptors)
        sigmas.append(f.pixel_sigmas)
    return kps, descs, sigmas


def errors(pose: Any, truth: Any) -> tuple[float, float]:
    """Translation (m) and rotation (°) error of ``pose`` against ``truth`` (∞ when lost)."""
    if pose is None:
        return float("inf"), float("inf")
    d = np.linalg.inv(truth) @ pose
    angle = np.degrees(np.arccos(np.clip((np.trace(d[:3, :3]) - 1) / 2, -1, 1)))
    return float(np.linalg.norm(d[:3, 3])), float(angle)


def bias(poses: list[Any], truth: Any) -> tuple[Any, float]:
    """The median camera-frame error δ = log(T_label⁻¹ T_est) (translation cm, rotation °) over
    the frames within 0.5 m, and the median translation error left once it is removed (cm):
    a small remainder means the locator is consistent and the error is a bias between the
    labels of the map's and the test block's parts of the trajectory."""
    from geoloc import lie

    ds = []
    for p, t in zip(poses, truth):
        if p is not None:
            d = np.linalg.inv(t) @ np.asarray(p)
            if np.linalg.norm(d[:3, 3]) < 0.5:
                ds.append(np.r_[d[:3, 3], lie.so3_log(lie.so3_project(d[:3, :3]))])
    if not ds:
        return None, float("nan")
    a = np.array(ds)
    med = np.median(a, axis=0)
    rest = float(np.median(np.linalg.norm(a[:, :3] - med[:3], axis=1)) * 100)
    return np.r_[med[:3] * 100, np.degrees(med[3:])], rest


def scores(poses: list[Any], truth: Any) -> dict[str, float]:
    """Median translation (cm) / rotation (°) error and recall within 5 cm / 5° of ``poses``
    (None: lost, an infinite error) against ``truth``."""
    et, er = np.array([errors(None if p is None else np.asarray(p), t) for p, t in zip(poses, truth)]).T
    return {
        "median_cm": float(np.median(et) * 100),
        "median_deg": float(np.median(er)),
        "recall_5cm_5deg": float(np.mean((et < 0.05) & (er < 5.0))),
    }


def run_fold(
    seq: Any, feats: tuple[list[Any], list[Any], list[Any]], b: int, uniform: bool = False, refine: bool = False,
    adjust: bool = False, reference: Any = None,
) -> dict[str, Any]:
    from geoloc import Localizer, Map
    from geoloc.reference import align_reference

    lo, hi = b * BLOCK, min((b + 1) * BLOCK, FRAMES)
    train = [i for i in range(FRAMES) if i < lo - MARGIN or i >= hi + MARGIN]
    kps, descs, sigmas = feats
    poses = seq.poses[:FRAMES]
    t0 = time.perf_counter()
    the_map = Map.from_features(
        seq.camera, poses[train], [kps[i] for i in train], [descs[i] for i in train],
        refine_intrinsics=refine, model=True, estimate_noise=False, adjust_labels=adjust,
    )
    map_build_s = time.perf_counter() - t0
    truth_reference = None
    if reference is not None:
        truth_reference = align_reference(reference[train], the_map.keyframe_poses).apply(reference[lo:hi])
    localizers = {locator: Localizer(the_map, locator=locator) for locator in ("paper", "model")}
    out: dict[str, Any] = {
        "train": len(train),
        "map_build_s": map_build_s,
        "self_calibration": the_map.self_calibration,
    }
    for locator in ("paper", "model"):
        loc = localizers[locator]
        inl, ms, raw = [], [], []
        for i in range(lo, hi):
            loc.reset()
            r = loc.localize_features(float(i) / 30.0, kps[i], descs[i], pixel_sigmas=None if uniform else sigmas[i])
            inl.append(r.inliers)
            ms.append(r.timings["total"])
            raw.append(None if r.pose is None else np.asarray(r.pose).tolist())
        out[locator] = {
            **scores(raw, poses[lo:hi]),
            "median_inliers": float(np.median(inl)),
            "median_ms": float(np.median(ms)),
            "p90_ms": float(np.percentile(ms, 90)),
            "poses": raw,
        }
        b_vec, rest = bias(raw, poses[lo:hi])
        out[locator]["bias_cm_deg"] = None if b_vec is None else b_vec.tolist()
        out[locator]["median_cm_without_bias"] = rest
        if truth_reference is not None:
            out[locator]["vs_reference"] = scores(raw, truth_reference)
    return out


def main() -> int:
    import geoloc
    from geoloc.commands._common import describe_self_calibration

    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--folds", default="6,0", help="comma-separated test blocks of 100 frames (0–6)")
    ap.add_argument("--features", default="orb,sift", help="comma-separated: orb, sift")
    ap.add_argument("--json", help="write the results (with every pose) here")
    ap.add_argument("--uniform-sigma", action="store_true", help="no per-keypoint pixel σ (every keypoint 1 px)")
    ap.add_argument("--refine-intrinsics", action="store_true",
                    help="maps estimate their camera from their own tracks (Map.build's default)")
    ap.add_argument("--adjust-labels", action="store_true",
                    help="maps correct their labels by bundle adjustment (Map.build's default)")
    ap.add_argument("--reference", type=Path, default=REFERENCE if REFERENCE.is_file() else None,
                    help="SfM reference poses to score against as well (default: the shared one, when present)")
    args = ap.parse_args()
    if not DATA.is_dir():
        print(f"no shared data at {DATA}: nothing to measure")
        return 0
    reference = None
    if args.reference is not None:
        from geoloc.reference import load_reference

        keys, ref_poses = load_reference(args.reference)
        reference = np.full((max(int(keys.max()) + 1, FRAMES), 4, 4), np.nan)
        reference[keys] = ref_poses
    seq = geoloc.datasets.load_7scenes(DATA, intrinsics=(525.0, 525.0, 320.0, 240.0))[:FRAMES]
    report: dict[str, Any] = {}
    print(f"{'fold':<8} {'feat':<5} {'locator':<7} {'median':>16} {'5cm/5°':>7} {'inliers':>8} {'ms/frame':>9}  map build", flush=True)
    for kind in args.features.split(","):
        t0 = time.perf_counter()
        feats = extract(seq, kind)
        print(f"({kind}: features of {FRAMES} frames in {time.perf_counter() - t0:.0f} s)", flush=True)
        for b in (int(x) for x in args.folds.split(",")):
            r = run_fold(seq, feats, b, uniform=args.uniform_sigma, refine=args.refine_intrinsics,
                         adjust=args.adjust_labels, reference=reference)
            name = f"{b * BLOCK}-{min((b + 1) * BLOCK, FRAMES) - 1}"
            report[f"{name} {kind}"] = r
            if r["self_calibration"] is not None:
                print(f"{name:<8} {kind:<5} {describe_self_calibration(r['self_calibration'])}", flush=True)
            for locator in ("paper", "model"):
                s = r[locator]
                build = f"{r['map_build_s']:.1f} s with the model ({r['train']} kf)" if locator == "paper" else ""
                print(
                    f"{name:<8} {kind:<5} {locator:<7} {s['median_cm']:>7.1f} cm {s['median_deg']:>5.2f}° "
                    f"{s['recall_5cm_5deg']:>7.0%} {s['median_inliers']:>8.0f} {s['median_ms']:>9.1f}  {build}",
                    flush=True,
                )
                if "vs_reference" in s:
                    v = s["vs_reference"]
                    print(f"{name:<8} {kind:<5} {'vs ref':<7} {v['median_cm']:>7.1f} cm {v['median_deg']:>5.2f}° "
                          f"{v['recall_5cm_5deg']:>7.0%}", flush=True)
                if s["bias_cm_deg"] is not None:
                    print(
                        f"{'':<22}camera-frame median error (x y z cm, φx φy φz °) {np.round(s['bias_cm_deg'], 1).tolist()}; "
                        f"without it the median is {s['median_cm_without_bias']:.1f} cm",
                        flush=True,
                    )
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    os.environ.setdefault("GEOLOC_NUM_THREADS", "2")
    sys.exit(main())
