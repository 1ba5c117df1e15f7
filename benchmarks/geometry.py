"""Side-by-side: geoloc's PnP and triangulation against OpenCV, PoseLib and pycolmap.

    python benchmarks/geometry.py [--trials 200] [--json out.json]

All peers run in this process on identical data (K = (525, 525, 320, 240), 1 px noise):

1. PnP refinement (LM) from a perturbed pose (2 cm, 1°), N = 50 / 200 / 1000 points:
   geoloc with its 6×6 covariance — default Huber kernel (robust rounds + a final
   least-squares solve) and without a kernel (plain least squares, as the peers) —,
   cv2.solvePnPRefineLM, poselib.refine_absolute_pose, pycolmap.refine_absolute_pose
   (with covariance).
2. RANSAC PnP at 0 / 30 / 50 % outliers, N = 50 / 200 / 1000, no initial pose, 5 px
   threshold, ≥100 iterations, confidence 0.9999: geoloc, poselib.estimate_absolute_pose,
   cv2.solvePnPRansac (SQPnP refinement), pycolmap.estimate_absolute_pose.
3. Triangulation of 4000 tracks seen in 2–7 of 7 views, 10 % outlier observations:
   geoloc.geometry.triangulate (all tracks, one call), a vectorized numpy DLT, pycolmap's
   LO-RANSAC estimate_triangulation (one call per track) and cv2.triangulatePoints (first
   two views of each track).

Prints time per call, accuracy and success rate, and each peer's time relative to geoloc
(``--json``: the same rows, for ``benchmarks/report.py``). Peers that are not installed are
skipped (``pip install -e ".[bench]"`` installs them). Not part of the test suite.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from typing import Any, Callable

import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, os.path.dirname(__file__))

import geoloc  # noqa: E402
from geoloc import geometry, lie  # noqa: E402
from geoloc.montecarlo import look_at  # noqa: E402

Array = NDArray[np.float64]
CAM = geoloc.Camera(525.0, 525.0, 320.0, 240.0)
K = CAM.K


def optional(name: str) -> Any:
    try:
        return __import__(name)
    except ImportError:
        print(f"({name} not installed: skipped)")
        return None


cv2 = optional("cv2")
poselib = optional("poselib")
pycolmap = optional("pycolmap")


def project(T: Array, pts: Array) -> Array:
    p = lie.se3_transform_points(lie.se3_inverse(T), pts)
    return p[:, :2] / p[:, 2:] * 525.0 + [320.0, 240.0]


def random_view(rng: np.random.Generator, n: int) -> tuple[Array, Array]:
    T = lie.se3_exp(np.r_[rng.uniform(-5, 5, 3), rng.normal(size=3)])
    uv = rng.uniform([0, 0], [640, 480], (n, 2))
    z = rng.uniform(2, 8, (n, 1))
    return T, lie.se3_transform_points(T, np.hstack([(uv - [320, 240]) / 525.0, np.ones((n, 1))]) * z)


def pose_error(est: Array, truth: Array) -> tuple[float, float]:
    d = lie.se3_inverse(truth) @ est
    return float(np.linalg.norm(est[:3, 3] - truth[:3, 3])), float(np.degrees(lie.rotation_angle(d[:3, :3])))


def cam_from_world(T: Array) -> Array:
    return lie.se3_inverse(T)


def from_cam_from_world(R: Array, t: Array) -> Array:
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, np.ravel(t)
    return lie.se3_inverse(M)


# ------------------------------------------------------------------------------- solvers
def geoloc_refine(pts: Array, px: Array, init: Array) -> Array:
    return geometry.solve_pnp(pts, px, CAM, init_pose=init, ransac=False).pose


def geoloc_refine_plain(pts: Array, px: Array, init: Array) -> Array:
    return geometry.solve_pnp(pts, px, CAM, init_pose=init, ransac=False, loss="none").pose


def cv2_refine(pts: Array, px: Array, init: Array) -> Array:
    cw = cam_from_world(init)
    rvec, _ = cv2.Rodrigues(cw[:3, :3])
    tvec = cw[:3, 3].reshape(3, 1).copy()
    rvec, tvec = cv2.solvePnPRefineLM(pts, px, K, None, rvec, tvec)
    return from_cam_from_world(cv2.Rodrigues(rvec)[0], tvec)


def poselib_camera() -> Any:
    return poselib.Camera("PINHOLE", [525.0, 525.0, 320.0, 240.0], 640, 480)


def poselib_refine(pts: Array, px: Array, init: Array) -> Array:
    cw = cam_from_world(init)
    pose = poselib.CameraPose()
    pose.R, pose.t = cw[:3, :3], cw[:3, 3]
    out, _ = poselib.refine_absolute_pose(px, pts, pose, poselib_camera(), {})
    return from_cam_from_world(out.R, out.t)


def colmap_camera() -> Any:
    return pycolmap.Camera(model="PINHOLE", width=640, height=480, params=[525.0, 525.0, 320.0, 240.0])


def colmap_refine(pts: Array, px: Array, init: Array) -> Array:
    cw = cam_from_world(init)
    out = pycolmap.refine_absolute_pose(
        pycolmap.Rigid3d(cw[:3, :]), px, pts, np.ones(len(pts), dtype=bool), colmap_camera(),
        return_covariance=True,
    )
    m = out["cam_from_world"].matrix()
    return from_cam_from_world(m[:, :3], m[:, 3])


def geoloc_ransac(pts: Array, px: Array) -> Array | None:
    r = geometry.solve_pnp(pts, px, CAM, min_iterations=100, confidence=0.9999, max_residual=5.0)
    return r.pose if r.success else None


def poselib_ransac(pts: Array, px: Array) -> Array | None:
    pose, info = poselib.estimate_absolute_pose(
        px, pts, poselib_camera(),
        {"max_reproj_error": 5.0, "min_iterations": 100, "max_iterations": 10000, "success_prob": 0.9999}, {},
    )
    return from_cam_from_world(pose.R, pose.t)


def cv2_ransac(pts: Array, px: Array) -> Array | None:
    ok, rvec, tvec, _ = cv2.solvePnPRansac(
        pts, px, K, None, iterationsCount=10000, reprojectionError=5.0, confidence=0.9999, flags=cv2.SOLVEPNP_SQPNP
    )
    return from_cam_from_world(cv2.Rodrigues(rvec)[0], tvec) if ok else None


def colmap_ransac(pts: Array, px: Array) -> Array | None:
    opts = pycolmap.AbsolutePoseEstimationOptions()
    opts.ransac.max_error = 5.0
    opts.ransac.min_num_trials = 100
    opts.ransac.confidence = 0.9999
    out = pycolmap.estimate_absolute_pose(px, pts, colmap_camera(), opts)
    if out is None:
        return None
    m = out["cam_from_world"].matrix()
    return from_cam_from_world(m[:, :3], m[:, 3])


# ----------------------------------------------------------------------------- harness
def run_pnp(
    title: str,
    solvers: dict[str, Callable[..., Array | None]],
    make: Callable[[np.random.Generator], tuple[Array, Array, Array, Array]],
    trials: int,
    uses_init: bool,
) -> dict[str, dict[str, float]]:
    rng = np.random.default_rng(0)
    cases = [make(rng) for _ in range(trials)]
    rows = []
    for name, fn in solvers.items():
        errors, ok = [], 0
        fn(*(cases[0][1:] if uses_init else cases[0][1:3]))  # warm-up
        start = time.perf_counter()
        outs = [fn(*(c[1:] if uses_init else c[1:3])) for c in cases]
        elapsed = (time.perf_counter() - start) / trials
        for (truth, *_), est in zip(cases, outs):
            if est is None:
                continue
            cm, deg = pose_error(est, truth)
            errors.append((100 * cm, deg))
            ok += cm <= 0.05 and deg <= 1.0
        med = np.median(np.array(errors), axis=0) if errors else (np.nan, np.nan)
        rows.append((name, elapsed, med, ok / trials))
    base = rows[0][1]
    print(f"\n{title} ({trials} trials)")
    print(f"  {'implementation':<36} {'µs/call':>9} {'× geoloc':>9} {'median cm':>10} {'median °':>9} {'ok 5cm/1°':>10}")
    for name, t, med, ok in rows:
        print(f"  {name:<36} {t * 1e6:>9.1f} {t / base:>8.2f}x {med[0]:>10.3f} {med[1]:>9.4f} {100 * ok:>9.1f}%")
    return {
        name: {"us_per_call": t * 1e6, "x_geoloc": t / base, "median_cm": float(med[0]), "median_deg": float(med[1]),
               "ok_5cm_1deg": ok}
        for name, t, med, ok in rows
    }


def refine_case(n: int) -> Callable[[np.random.Generator], tuple[Array, Array, Array, Array]]:
    def make(rng: np.random.Generator) -> tuple[Array, Array, Array, Array]:
        T, pts = random_view(rng, n)
        px = project(T, pts) + rng.normal(size=(n, 2))
        d = np.r_[rng.normal(size=3) * 0.02 / np.sqrt(3), rng.normal(size=3) * np.radians(1) / np.sqrt(3)]
        return T, pts, px, T @ lie.se3_exp(d)
    return make


def ransac_case(n: int, outliers: float) -> Callable[[np.random.Generator], tuple[Array, Array, Array, Array]]:
    def make(rng: np.random.Generator) -> tuple[Array, Array, Array, Array]:
        T, pts = random_view(rng, n)
        px = project(T, pts) + rng.normal(size=(n, 2))
        bad = rng.permutation(n)[: int(round(outliers * n))]
        px[bad] = rng.uniform([0, 0], [640, 480], (len(bad), 2))
        return T, pts, px, np.eye(4)
    return make


# ------------------------------------------------------------------------ triangulation
def triangulation_scene(rng: np.random.Generator, n_tracks: int = 2000) -> dict[str, Any]:
    focus = np.array([0.0, 0.0, 5.0])
    poses = np.stack([look_at(np.array([x, 0.1 * np.sin(3 * x), 0.0]), focus) for x in np.linspace(-1.0, 1.0, 7)])
    points = focus + rng.uniform([-2, -1.5, -1.5], [2, 1.5, 1.5], (n_tracks, 3))
    cam_ids, track_ids, pixels, outlier = [], [], [], []
    for t in range(n_tracks):
        views = rng.choice(7, size=rng.integers(2, 8), replace=False)
        for c in views:
            uv = project(poses[c], points[t][None])[0] + rng.normal(size=2)
            bad = rng.uniform() < 0.1
            if bad:
                uv = rng.uniform([0, 0], [640, 480])
            cam_ids.append(c)
            track_ids.append(t)
            pixels.append(uv)
            outlier.append(bad)
    return {
        "poses": poses, "points": points, "cam_ids": np.array(cam_ids), "track_ids": np.array(track_ids),
        "pixels": np.array(pixels), "outlier": np.array(outlier),
    }


def numpy_dlt(poses: Array, cam_ids: NDArray[np.int64], track_ids: NDArray[np.int64], pixels: Array, n: int) -> Array:
    """Vectorized N-view DLT: tracks grouped by view count, one batched SVD per group."""
    cw = lie.se3_inverse(poses)[:, :3, :]
    P = K @ cw  # (C, 3, 4)
    rows = np.stack([pixels[:, :1] * P[cam_ids, 2] - P[cam_ids, 0], pixels[:, 1:] * P[cam_ids, 2] - P[cam_ids, 1]], axis=1)
    order = np.argsort(track_ids, kind="stable")
    counts = np.bincount(track_ids, minlength=n)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    out = np.full((n, 3), np.nan)
    for v in np.unique(counts[counts >= 2]):
        tracks = np.flatnonzero(counts == v)
        idx = order[starts[tracks][:, None] + np.arange(v)]  # (T, v)
        A = rows[idx].reshape(len(tracks), 2 * v, 4)
        _, _, vt = np.linalg.svd(A)
        h = vt[:, -1]
        out[tracks] = h[:, :3] / h[:, 3:]
    return out


def colmap_triangulate(scene: dict[str, Any]) -> Array:
    cams = [colmap_camera()]
    rigs = [pycolmap.Rigid3d(lie.se3_inverse(T)[:3, :]) for T in scene["poses"]]
    opts = pycolmap.EstimateTriangulationOptions()
    opts.ransac.max_error = 5.0 / 525.0  # angular error (rad) ≈ 5 px
    n = len(scene["points"])
    out = np.full((n, 3), np.nan)
    order = np.argsort(scene["track_ids"], kind="stable")
    bounds = np.searchsorted(scene["track_ids"][order], np.arange(n + 1))
    for t in range(n):
        obs = order[bounds[t] : bounds[t + 1]]
        res = pycolmap.estimate_triangulation(
            scene["pixels"][obs], [rigs[c] for c in scene["cam_ids"][obs]], cams * len(obs), opts
        )
        if res is not None:
            out[t] = np.ravel(res["xyz"])
    return out


def cv2_triangulate(scene: dict[str, Any]) -> Array:
    """cv2.triangulatePoints on the first two views of each track, batched per camera pair."""
    P = K @ lie.se3_inverse(scene["poses"])[:, :3, :]
    n = len(scene["points"])
    order = np.argsort(scene["track_ids"], kind="stable")
    first = order[np.searchsorted(scene["track_ids"][order], np.arange(n))]
    second = order[np.searchsorted(scene["track_ids"][order], np.arange(n)) + 1]
    out = np.full((n, 3), np.nan)
    ca, cb = scene["cam_ids"][first], scene["cam_ids"][second]
    for a in range(7):
        for b in range(7):
            sel = np.flatnonzero((ca == a) & (cb == b))
            if len(sel):
                h = cv2.triangulatePoints(P[a], P[b], scene["pixels"][first[sel]].T, scene["pixels"][second[sel]].T)
                out[sel] = (h[:3] / h[3]).T
    return out


def run_triangulation() -> dict[str, dict[str, float]]:
    scene = triangulation_scene(np.random.default_rng(1), 4000)
    n = len(scene["points"])
    impls: dict[str, Callable[[], Array]] = {
        "geoloc.geometry.triangulate": lambda: _geoloc_points(scene),
        "numpy vectorized DLT": lambda: numpy_dlt(scene["poses"], scene["cam_ids"], scene["track_ids"], scene["pixels"], n),
    }
    if pycolmap is not None:
        impls["pycolmap estimate_triangulation"] = lambda: colmap_triangulate(scene)
    if cv2 is not None:
        impls["cv2.triangulatePoints (2 views)"] = lambda: cv2_triangulate(scene)
    rows = []
    for name, fn in impls.items():
        fn()
        times = []
        for _ in range(3 if "pycolmap" in name else 7):
            start = time.perf_counter()
            pts = fn()
            times.append(time.perf_counter() - start)
        err = np.linalg.norm(pts - scene["points"], axis=1)
        valid = np.isfinite(err)
        rows.append((
            name, min(times), valid.mean(), np.median(err[valid]), np.sqrt(np.mean(err[valid] ** 2)),
            np.mean(err[valid] > 0.1), int(np.sum(err[valid] > 1.0)),
        ))
    base = rows[0][1]
    print(f"\nTriangulation: {n} tracks, 2–7 of 7 views, 10 % outlier observations, 1 px noise "
          f"({len(scene['pixels'])} observations; errors over the points each method returns)")
    print(f"  {'implementation':<36} {'ms':>8} {'× geoloc':>9} {'returned':>9} {'median cm':>10} {'RMS cm':>8} {'>10 cm':>7} {'>1 m':>5}")
    for name, t, v, med, rms, gross, huge in rows:
        print(f"  {name:<36} {t * 1e3:>8.2f} {t / base:>8.2f}x {100 * v:>8.1f}% {100 * med:>10.2f} {100 * rms:>8.1f} {100 * gross:>6.1f}% {huge:>5}")
    return {
        name: {"ms": t * 1e3, "x_geoloc": t / base, "returned": float(v), "median_cm": 100 * float(med),
               "rms_cm": 100 * float(rms), "over_10cm": float(gross), "over_1m": huge}
        for name, t, v, med, rms, gross, huge in rows
    }


def _geoloc_points(scene: dict[str, Any]) -> Array:
    tri = geometry.triangulate(scene["poses"], CAM, scene["cam_ids"], scene["track_ids"], scene["pixels"])
    return np.where(tri.valid[:, None], tri.points, np.nan)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--trials", type=int, default=200)
    parser.add_argument("--sizes", type=int, nargs="+", default=[50, 200, 1000])
    parser.add_argument("--json", default=None, help="also write the rows here")
    args = parser.parse_args()
    print(f"geoloc {geoloc.__version__} geometry benchmark; {os.cpu_count()} CPUs")
    report: dict[str, Any] = {}
    for n in args.sizes:
        solvers: dict[str, Callable[..., Array | None]] = {
            "geoloc solve_pnp (Huber LM + cov)": geoloc_refine,
            "geoloc solve_pnp (plain LM + cov)": geoloc_refine_plain,
        }
        if cv2 is not None:
            solvers["cv2.solvePnPRefineLM"] = cv2_refine
        if poselib is not None:
            solvers["poselib.refine_absolute_pose"] = poselib_refine
        if pycolmap is not None:
            solvers["pycolmap.refine_absolute_pose (+cov)"] = colmap_refine
        title = f"PnP refinement from a 2 cm / 1° perturbed pose, N = {n}"
        report[title] = run_pnp(title, solvers, refine_case(n), args.trials, True)
    for n in args.sizes:
        for outliers in (0.0, 0.3, 0.5):
            solvers = {"geoloc solve_pnp (P3P RANSAC)": geoloc_ransac}
            if poselib is not None:
                solvers["poselib.estimate_absolute_pose"] = poselib_ransac
            if cv2 is not None:
                solvers["cv2.solvePnPRansac (SQPnP)"] = cv2_ransac
            if pycolmap is not None:
                solvers["pycolmap.estimate_absolute_pose"] = colmap_ransac
            title = f"RANSAC PnP, N = {n}, {int(100 * outliers)} % outliers"
            report[title] = run_pnp(title, solvers, ransac_case(n, outliers), args.trials, False)
    report["Triangulation, 4000 tracks"] = run_triangulation()
    if args.json:
        import json

        with open(args.json, "w") as f:
            json.dump(report, f, indent=1)


if __name__ == "__main__":
    main()
