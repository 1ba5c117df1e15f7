"""geoloc's labels' adjustment against pycolmap's bundle adjustment on the same problem.

The problem is the one ``Map.build`` solves first when it corrects the labels of the shared
7-Scenes redkitchen frames ``--frames`` (default 0–599; the map built with
``adjust_labels=False, refine_intrinsics=False``, so that :meth:`geoloc.Map.label_adjustment_problem`
is the adjustment on the nominal camera): the skeleton keyframes, their labels, the points
triangulated from them and the tracks' observations. The labels' σ is fixed at geoloc's
estimate (``bundle_adjust`` with σ estimated, run once), and no observation is dropped
between rounds (``outlier_px`` 10⁹ px), so both solvers minimize the same cost from the
same values:

    Σ_o Huber₂(‖π(K, T_k⁻¹ P_j) − u_o‖²) + Σ_k Cauchy₃(e_kᵀ Λ e_k) + e_Xᵀ Λ_X e_X

— geoloc's ``bundle_adjust`` (Levenberg–Marquardt, points eliminated, block-envelope
Cholesky, then the marginal covariances of every pose and point), and COLMAP's Ceres bundle
adjuster on a pycolmap reconstruction of the problem with the priors added as COLMAP's
``AbsolutePosePriorCost`` (``benchmarks/_colmap_adjustment.py``), with the solver options
COLMAP picks for it, once with COLMAP's iteration cap (100) and once run to convergence
(cap 1000). Both run in this process on ``GEOLOC_NUM_THREADS`` threads (default 2).

Printed: the start cost under both cost functions (they must agree), each solution's final
cost under both, iterations, wall time (best and median of ``--repeats``; COLMAP's problem
construction timed apart from its solve), the two solutions' difference, and each solution's
keyframe poses against the SfM reference (aligned as the evaluation aligns it): which of the
minima the images prefer.

    PYTHONPATH=python python benchmarks/adjustment.py [--frames 0:600:1] [--repeats 3] [--json out.json]

Needs pycolmap and pyceres (``pip install -e ".[bench]"``). Result: ``docs/reports/adjustment-run.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

import geoloc
from geoloc.adjustment import bundle_adjust
from geoloc.lie import se3_inverse, se3_log
from geoloc.reference import align_reference, load_reference

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"
SEQUENCE = DATA / "7scenes-redkitchen"
REFERENCE = DATA / "7scenes-redkitchen-reference" / "sfm-poses.txt"
#: COLMAP's iteration cap (``BundleAdjustmentOptions().ceres.solver_options.max_num_iterations``)
#: and the cap of the run to convergence.
COLMAP_CAP = 100
CONVERGED_CAP = 1000
#: An outlier threshold no reprojection error reaches: every observation stays.
KEEP_ALL_PX = 1e9


def timed(fn: Callable[[], Any], repeats: int) -> tuple[Any, list[float]]:
    """``fn()`` run ``repeats`` times: the last result and the sorted wall times (s)."""
    times, out = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - start)
    return out, sorted(times)


def against_reference(frames: np.ndarray, poses: np.ndarray, reference: np.ndarray) -> list[float]:
    """Median distance (m) and rotation (°) of ``poses`` from the reference poses of
    ``frames``, aligned on them as documented (``geoloc.reference``)."""
    aligned = align_reference(reference[frames], poses).apply(reference[frames])
    delta = se3_log(se3_inverse(aligned) @ poses)
    return [float(np.median(np.linalg.norm(delta[:, :3], axis=1))), float(np.degrees(np.median(np.linalg.norm(delta[:, 3:], axis=1))))]


def difference(a: np.ndarray, b: np.ndarray) -> list[float]:
    """Median and largest distance (m) and rotation (°) between two stacks of poses."""
    delta = se3_log(se3_inverse(a) @ b)
    t, r = np.linalg.norm(delta[:, :3], axis=1), np.degrees(np.linalg.norm(delta[:, 3:], axis=1))
    return [float(np.median(t)), float(t.max()), float(np.median(r)), float(r.max())]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", default="0:600:1", help="A:B:K, the map's frames (default 0:600:1)")
    ap.add_argument("--repeats", type=int, default=3, help="timed runs of each solver (default 3)")
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args()
    try:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from _colmap_adjustment import colmap_adjustment
    except ImportError as exc:
        print(f"needs pycolmap and pyceres (pip install -e \".[bench]\"): {exc}")
        return 0
    if not (SEQUENCE.is_dir() and REFERENCE.is_file()):
        print(f"no shared data at {SEQUENCE} / {REFERENCE}")
        return 0
    threads = int(os.environ.get("GEOLOC_NUM_THREADS", "2"))
    a, b, k = (int(x) for x in args.frames.split(":"))
    seq = geoloc.datasets.load_7scenes(SEQUENCE)[a:b:k]
    m = geoloc.Map.build(seq, adjust_labels=False, refine_intrinsics=False, estimate_noise=False, model=False)
    problem = m.label_adjustment_problem()
    frames = np.asarray(m.settings["source"]["frames"])[problem.keyframes]
    keys, ref_poses = load_reference(REFERENCE)
    reference = np.full((int(keys.max()) + 1, 4, 4), np.nan)
    reference[keys] = ref_poses
    sigma = bundle_adjust(problem).label_sigma
    print(f"problem: frames {args.frames}, {len(problem.labels)} skeleton keyframes, {len(problem.points)} points, "
          f"{len(problem.obs_pixels)} observations; label σ {1e3 * sigma[0]:.1f} mm / {np.degrees(sigma[1]):.2f}° "
          f"(geoloc's estimate, fixed for both); {threads} threads")

    ours, our_times = timed(lambda: bundle_adjust(problem, label_sigma=sigma, outlier_px=KEEP_ALL_PX), args.repeats)
    built, build_times = timed(lambda: colmap_adjustment(problem, sigma), args.repeats)
    start_colmap = built.cost()

    def colmap_run(cap: int) -> tuple[Any, Any, list[float]]:
        peers = [colmap_adjustment(problem, sigma) for _ in range(args.repeats)]
        times, summary = [], None
        for peer in peers:
            t0 = time.perf_counter()
            summary = peer.solve(threads, cap)
            times.append(time.perf_counter() - t0)
        return peers[-1], summary, sorted(times)

    def geoloc_cost_at(labels: np.ndarray, offset: np.ndarray, points: np.ndarray) -> float:
        """geoloc's cost function at a state (one round's start cost)."""
        at = type(problem)(problem.intrinsics, problem.labels, points, problem.obs_keyframes, problem.obs_points,
                           problem.obs_pixels)
        return float(bundle_adjust(at, label_sigma=sigma, outlier_px=KEEP_ALL_PX, start=labels, offset=offset,
                                   max_iterations=1).cost[0])

    rows: dict[str, Any] = {}
    check = colmap_adjustment(problem, sigma)
    check.set_state(ours.label_poses, ours.offset, ours.points)
    rows["geoloc"] = {
        "iterations": ours.iterations, "cost_geoloc": ours.cost[1], "cost_colmap": check.cost(),
        "solve_s": our_times, "build_s": None, "poses": ours.label_poses, "offset": ours.offset,
    }
    for name, cap in ((f"pycolmap (cap {COLMAP_CAP})", COLMAP_CAP), (f"pycolmap (cap {CONVERGED_CAP})", CONVERGED_CAP)):
        peer, summary, times = colmap_run(cap)
        labels, offset, points = peer.state()
        rows[name] = {
            "iterations": int(summary.num_successful_steps + summary.num_unsuccessful_steps),
            "termination": str(summary.termination_type).split(".")[-1],
            "cost_geoloc": geoloc_cost_at(labels, offset, points), "cost_colmap": 2.0 * float(summary.final_cost),
            "solve_s": times, "build_s": build_times, "poses": labels, "offset": offset,
        }

    print(f"start cost: geoloc {ours.cost[0]:.6f}, COLMAP's {start_colmap:.6f} (Σρ; relative difference "
          f"{abs(ours.cost[0] - start_colmap) / ours.cost[0]:.1e})")
    base = rows["geoloc"]["solve_s"][0]
    print(f"{'solver':<22} {'iterations':>10} {'final cost (geoloc / COLMAP function)':>40} {'best s':>8} {'median s':>9} "
          f"{'ratio':>6} {'+ build s':>9}  vs reference (median)")
    for name, r in rows.items():
        r["reference"] = against_reference(frames, r["poses"], reference)
        build = "—" if r["build_s"] is None else f"{r['build_s'][0]:.2f}"
        term = f" {r['termination']}" if "termination" in r else ""
        print(f"{name:<22} {r['iterations']:>10} {r['cost_geoloc']:>19.2f} / {r['cost_colmap']:<18.2f} {r['solve_s'][0]:>8.2f} "
              f"{r['solve_s'][len(r['solve_s']) // 2]:>9.2f} {r['solve_s'][0] / base:>5.1f}x {build:>9}  "
              f"{100 * r['reference'][0]:.2f} cm / {r['reference'][1]:.2f}°{term}")
    print("geoloc's time includes the marginal covariances of every pose and point; COLMAP's solve does not compute them")
    for name, r in rows.items():
        x = se3_log(r["offset"][None])[0]
        r["offset_m_deg"] = [float(np.linalg.norm(x[:3])), float(np.degrees(np.linalg.norm(x[3:])))]
        print(f"{name}: label-to-camera offset X {100 * r['offset_m_deg'][0]:.2f} cm / {r['offset_m_deg'][1]:.3f}°")
    mine = rows["geoloc"]
    for name, r in rows.items():
        if name != "geoloc":
            d = difference(mine["poses"] @ mine["offset"], r["poses"] @ r["offset"])
            print(f"geoloc vs {name}: camera poses B_k X differ by a median {1e3 * d[0]:.2f} mm (largest "
                  f"{1e3 * d[1]:.2f}) and {d[2]:.4f}° (largest {d[3]:.4f}°)")
    if args.json:
        out = {n: {k: v for k, v in r.items() if k not in ("poses", "offset")} for n, r in rows.items()}
        out["problem"] = {"frames": args.frames, "keyframes": len(problem.labels), "points": len(problem.points),
                          "observations": len(problem.obs_pixels), "label_sigma": list(sigma),
                          "start_cost": [ours.cost[0], start_colmap], "threads": threads}
        Path(args.json).write_text(json.dumps(out, indent=1, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
