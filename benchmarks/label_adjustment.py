"""How far the map's keyframe poses lie from an image-consistent reference, labels kept and
labels corrected by bundle adjustment (``Map.build(adjust_labels=...)``).

On the shared 7-Scenes redkitchen frames (``../shared/data``): builds the map of ``--frames``
both ways, aligns the SfM reference to each map's keyframe poses as the evaluation does (a
similarity and a fixed camera-frame offset, Huber 2 cm / 1°, ``geoloc.reference``) and prints
the median and 95th-percentile translation / rotation differences overall and per 100-frame
block, each block's offset (the norm of the mean of δ = log(T_ref⁻¹T)^∨ over its keyframes:
the part of the difference the whole block shares — a systematic disagreement between the
map and the reference, not scatter), the build times and the labels' report.

    PYTHONPATH=python python benchmarks/label_adjustment.py [--frames 0:600:1] [--json out.json]
        [--write-poses FILE]

``--write-poses`` writes the corrected map's keyframe poses in the reference's own format
(``index`` and the row-major top 3×4, one line per frame): a second image-consistent
reference to score against (``benchmarks/calibration.py --reference FILE``). It is this
project's adjustment, not an independent one: where it and the SfM reference disagree, the
difference shows how far a block-level number rests on the reference chosen.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

import geoloc
from geoloc.lie import se3_inverse, se3_log
from geoloc.reference import align_reference, load_reference

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
SEQUENCE = DATA / "7scenes-redkitchen"
REFERENCE = DATA / "7scenes-redkitchen-reference" / "sfm-poses.txt"


def differences(poses: np.ndarray, aligned: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per frame: ‖t − t_ref‖ (m) and the rotation angle of R_refᵀR (deg)."""
    dt = np.linalg.norm(poses[:, :3, 3] - aligned[:, :3, 3], axis=1)
    rel = np.einsum("nji,njk->nik", aligned[:, :3, :3], poses[:, :3, :3])
    angle = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    return dt, angle


def write_reference(path: Path, frames: np.ndarray, poses: np.ndarray) -> None:
    """``poses`` (N, 4, 4) of dataset frames ``frames`` in the 7scenes-reference format that
    :func:`geoloc.reference.load_reference` reads (exact: ``repr`` of each float)."""
    if len(frames) != len(poses):
        raise ValueError(f"{len(poses)} keyframe poses for {len(frames)} frames: the map did not keep every frame")
    lines = [" ".join([str(int(i)), *(repr(float(x)) for x in p[:3, :4].ravel())]) for i, p in zip(frames, poses)]
    path.write_text("\n".join(lines) + "\n")


def span_disagreement(labels: np.ndarray, other: np.ndarray, start: int, last: int) -> np.ndarray:
    """log((L_s⁻¹ L_e)⁻¹ (P_s⁻¹ P_e))^∨ for s = ``start``, e = ``last``: how far the labels'
    motion from keyframe s to e is from that of the poses ``other`` (translation first)."""
    motion = lambda p: se3_inverse(p[start]) @ p[last]  # noqa: E731
    return np.asarray(se3_log(se3_inverse(motion(labels)) @ motion(other)))


def steps_against_reference(labels: np.ndarray, adjusted: np.ndarray, aligned: np.ndarray,
                            steps: list[dict[str, Any]], largest: int = 5) -> dict[str, Any]:
    """The map's steps in the labels' motion (``Map.labels["steps"]``) checked against the
    reference: per step the labels' disagreement across it with the adjusted poses (the
    map's finding) and with the reference, and that one's rank among the reference's
    disagreements over every span of the step's length (0.5: a typical span; a step the
    reference confirms ranks near 1); and the reference's own ``largest`` jumps of the
    labels (over spans of 5 keyframes, greedily without overlap) and whether a step of the
    map covers each."""
    size = lambda d: [float(np.linalg.norm(d[:3])), float(np.degrees(np.linalg.norm(d[3:])))]  # noqa: E731
    spans: dict[int, np.ndarray] = {}
    found = []
    for s in steps:
        n = s["end"] - 1 - s["start"]
        if n not in spans:
            spans[n] = np.array([size(span_disagreement(labels, aligned, a, a + n))[0] for a in range(len(labels) - n)])
        reference = size(span_disagreement(labels, aligned, s["start"], s["end"] - 1))
        found.append({"start": s["start"], "end": s["end"],
                      "map": size(span_disagreement(labels, adjusted, s["start"], s["end"] - 1)),
                      "reference": reference, "rank": float(np.mean(spans[n] < reference[0]))})
    window = 5
    jumps = np.array([size(span_disagreement(labels, aligned, a, a + window))[0] for a in range(len(labels) - window)])
    taken: list[dict[str, Any]] = []
    for a in np.argsort(-jumps, kind="stable"):
        if len(taken) == largest:
            break
        if all(abs(int(a) - t["start"]) > window for t in taken):
            covered = any(s["start"] <= a + window and a <= s["end"] - 1 for s in steps)
            taken.append({"start": int(a), "end": int(a) + window + 1, "reference_m": float(jumps[a]),
                          "covered": bool(covered)})
    return {"steps": found, "reference_jumps": taken}


def measure(seq: Any, frames: np.ndarray, reference: np.ndarray, adjust: bool, write_poses: Path | None = None
            ) -> dict[str, Any]:
    start = time.perf_counter()
    m = geoloc.Map.build(seq, adjust_labels=adjust, estimate_noise=False)
    build_s = time.perf_counter() - start
    poses = m.keyframe_poses
    if write_poses is not None:
        write_reference(write_poses, frames, poses)
    aligned = align_reference(reference[frames], poses).apply(reference[frames])
    dt, angle = differences(poses, aligned)
    delta = se3_log(se3_inverse(aligned) @ poses)
    blocks, offsets = {}, {}
    for b in range(int(frames.min()) // 100 * 100, int(frames.max()) + 1, 100):
        sel = (frames >= b) & (frames < b + 100)
        if sel.any():
            blocks[f"{b}-{b + 99}"] = [float(np.median(dt[sel])), float(np.median(angle[sel]))]
            mean = delta[sel].mean(axis=0)
            offsets[f"{b}-{b + 99}"] = [float(np.linalg.norm(mean[:3])), float(np.degrees(np.linalg.norm(mean[3:])))]
    labels = m.labels
    steps = None
    if labels is not None and m.label_poses is not None:
        steps = steps_against_reference(m.label_poses, poses, aligned, labels["steps"])
    return {
        "steps": steps,
        "build_s": build_s,
        "median": [float(np.median(dt)), float(np.median(angle))],
        "p95": [float(np.percentile(dt, 95)), float(np.percentile(angle, 95))],
        "blocks": blocks,
        "block_offsets": offsets,
        "labels": m.labels,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", default="0:600:1", help="A:B:K, the map's frames (default 0:600:1)")
    ap.add_argument("--json", help="write the results here")
    ap.add_argument("--write-poses", type=Path, help="write the corrected map's keyframe poses here (reference format)")
    args = ap.parse_args()
    if not (SEQUENCE.is_dir() and REFERENCE.is_file()):
        print(f"no shared data at {SEQUENCE} / {REFERENCE}")
        return 0
    a, b, k = (int(x) for x in args.frames.split(":"))
    frames = np.arange(a, b, k)
    keys, poses = load_reference(REFERENCE)
    reference = np.full((int(keys.max()) + 1, 4, 4), np.nan)
    reference[keys] = poses
    seq = geoloc.datasets.load_7scenes(SEQUENCE)[a:b:k]
    report = {"frames": args.frames}
    for name, adjust in (("labels kept", False), ("labels corrected", True)):
        r = measure(seq, frames, reference, adjust, args.write_poses if adjust else None)
        report[name] = r
        (mt, mr), (pt, pr) = r["median"], r["p95"]
        print(f"{name:<17} median {100 * mt:.2f} cm / {mr:.2f}°   p95 {100 * pt:.2f} cm / {pr:.2f}°   build {r['build_s']:.1f} s")
        print("                  " + "  ".join(f"{n}: {100 * t:.1f} cm / {d:.2f}°" for n, (t, d) in r["blocks"].items()))
        print("  block offsets   " + "  ".join(f"{n}: {100 * t:.1f} cm / {d:.2f}°" for n, (t, d) in r["block_offsets"].items()))
        if r["labels"]:
            lab = r["labels"]
            print(f"                  σ {1e3 * lab['label_sigma_m']:.1f} mm / {lab['label_sigma_deg']:.2f}°, τ "
                  f"{np.round(lab['correlation_keyframes'], 1).tolist()}, offset {lab['label_from_cam_rotation_deg']:.2f}°, "
                  f"runs {[(x['start'] * k + a, x['end'] * k + a) for x in lab['runs']]}")
        if r["steps"]:
            st, lab = r["steps"], r["labels"]
            frame = lambda i: int(frames[i])  # noqa: E731
            print(f"  steps           {len(st['steps'])} in the labels' motion (σ per keyframe pair "
                  f"{1e3 * lab['step_sigma_m']:.1f} mm / {lab['step_sigma_deg']:.2f}°), frames: map / reference "
                  "disagreement of the labels across each:")
            print("                  " + "  ".join(
                f"{frame(x['start'])}-{frame(x['end'] - 1)}: {100 * x['map'][0]:.1f} / {100 * x['reference'][0]:.1f} cm"
                for x in st["steps"]))
            ranks = [x["rank"] for x in st["steps"]]
            print(f"                  the reference's disagreement across a step ranks among the spans of its length "
                  f"at a median {np.median(ranks):.2f} (0.5: a typical span), above 0.9 for {sum(r > 0.9 for r in ranks)} "
                  f"of {len(ranks)} steps, above 0.5 for {sum(r > 0.5 for r in ranks)}")
            print("                  the reference's largest jumps of the labels (over 5 keyframes): " + "  ".join(
                f"{frame(j['start'])}-{frame(j['end'] - 1)} {100 * j['reference_m']:.1f} cm "
                f"({'a step' if j['covered'] else 'no step'})" for j in st["reference_jumps"]))
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
