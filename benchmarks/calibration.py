"""Calibration report: is the returned 6×6 covariance right on real images?

Cross-validation on the shared 7-Scenes redkitchen frames 0–699: every contiguous test block
of 100 frames, the map trained on the rest minus 15 frames on either side (the dev
protocol), ORB 1000, BoW retrieval, fx = fy = 525, t = i/30 s; both modes — ``single``
(the geometric locator alone, ``reset()`` before every frame) and ``sequential`` (motion
model + gated fusion) — and the synthetic room. Per fold × mode: median error, recall at
5 cm/5°, NEES coverage (χ²₆ 95 %), per-axis 1.96σ coverage (min over the six axes), median
NEES, sources; and the map's estimated noise (√diag C_map, acceleration PSD).

    PYTHONPATH=python python benchmarks/calibration.py [--folds 0,6] [--synthetic] [--json out.json]
        [--keep-labels] [--reference FILE] [--network DIR/NAME] [--seed S] [--paper-split] [--near-path]

``--near-path`` adds queries beside the mapped path, as a robot or a phone meets them in a
mapped room: every 10th frame of 0–699 (5, 15, …, 695) against a map of the other 630
(``near path``; not pooled with the folds). The folds' queries lie 1.35–6.3 from their
nearest training keyframe in ``Localization.novelty``'s units (10 cm or 5° = 1), these
0.01–0.27: they carry the map's near-regime noise, the folds' mostly C_map
(``Map.map_noise["near"]``; the "near regime" line of each evaluation).

``--keep-labels`` builds every map on the labels as they are (by default ``Map.build``
corrects them by bundle adjustment); with the
SfM reference (``--reference``, default the shared one when present) every fold × mode is
scored a second time, against the reference aligned on the fold's training frames to the
map's keyframe poses (``vs ref`` rows), beside the labels (``vs labels``).

``--network DIR/NAME`` builds every fold's map with a descriptor network too (``Map.build``
then fuses it with BoW): the network trained on that fold's training frames, given as the
descriptors of every frame that ``benchmarks/train_folds.py`` wrote (``DIR/NAME-fold<LO>.npz``),
looked up by image.

Not a test: a full run takes several minutes (7 map builds of ~600 frames). ``--json`` also
records the held-out samples of each map and every frame's error, covariance and source, so
C_map models can be compared offline on one run.

Results: ``docs/reports/calibration-run.md`` (default locator) and
``docs/reports/calibration-paper-run.md`` (``--locator paper``), generated with
``benchmarks/report.py run``. NEES = fraction inside χ²₆ 95 %; axis min = the lowest per-axis
1.96σ coverage; "median, lost=∞" is over all 100 frames, a lost frame an infinite error, as
the recall counts it — "median" is over the localized frames only, so two modes that lose
different frames are not compared on the same frames there. The second line per fold
breaks the single mode's NEES coverage down by PnP inlier count: where the covariance is too
small or too large. The third compares the modes on the frames both localized (against the
reference when given): the modes' own medians run over different frames, and the sequential
mode answers frames the single one loses. The fourth gives, per mode, the factor s on the
map's C_map at which the fold's NEES coverage, and its lowest per-axis coverage, would be
95 % (0: the measurement covariance alone covers it): C_map is one matrix per map, so it can be right on every fold only if the
folds need about the same s. The fifth and sixth give each mode's coverage with C_map scaled
by 0.1, 0.25, 0.5, 1 (as answered) and 2, and a last line per mode the same over the
frames of all folds run, pooled: how the coverage of each fold, and of all, moves with one
factor on every map's noise.

The "block structure" line asks what coverage a block *could* have: a block's errors are
largely one offset shared by its frames, plus a rest correlated over several frames, and a
block of such errors is covered either almost all or much less, whatever the covariance. Per
mode it gives, per axis of the whitened errors, φ (the shared fraction of their second
moment) and τ (the rest's integrated autocorrelation time, frames), and from a seeded
simulation of errors with that structure under a covariance that is exactly right: the
chance p that such a block is covered within 88–99 % (in NEES, and in NEES and every axis),
and how often it would be covered in NEES at least as well as the answers' covariance
covered it. The folds' last lines multiply these over the folds (independent blocks): the
chance that a right covariance puts every block in the band, the number of blocks it would
put there on average, and the chance that it covers every block at least as well as the
answers did.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

import geoloc
from geoloc.evaluation import CHI2_6_95, CHI2_6_999, COVERAGE_Z, summarize_results
from geoloc.lie import se3_adjoint, se3_inverse, se3_log

DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "7scenes-redkitchen"
REFERENCE = DATA.parent / "7scenes-redkitchen-reference" / "sfm-poses.txt"
BLOCK = 100
MARGIN = 15


def _digest(image: Any) -> bytes:
    import hashlib

    return hashlib.sha256(np.ascontiguousarray(image).tobytes()).digest()


def frame_rows(seq: Any) -> dict[bytes, int]:
    """Each frame of ``seq`` by its gray image's bytes (what ``Map.build`` and the localizer
    hand a network). Frames with identical images (the 7-Scenes sample repeats 68 frames
    verbatim) share one entry; a network gives them one descriptor anyway."""
    return {_digest(seq.gray(i)): i for i in range(len(seq))}


class FrameDescriptors:
    """A "network" that answers the descriptors saved for each frame (rows of
    ``descriptors``), recognizing a frame by its gray image's bytes (``rows``: ``frame_rows``)."""

    def __init__(self, rows: dict[bytes, int], descriptors: Any, name: str) -> None:
        import hashlib

        self._rows = rows
        self._d = np.asarray(descriptors, dtype=np.float32)
        self.name, self.dim = name, self._d.shape[1]
        self.sha256 = hashlib.sha256(self._d.tobytes()).hexdigest()

    def __call__(self, images: list[Any]) -> Any:
        return self._d[[self._rows[_digest(img)] for img in images]]


def evaluate(
    train: Any, test: Any, locator: str | None = None, adjust_labels: bool = True, reference: Any = None,
    network: Any = None, seed: int | None = None,
) -> dict[str, Any]:
    """Build the map on ``train``, localize ``test`` in both modes; the summaries, the map noise
    and (under ``"frames"``) the per-frame errors δ = log(T_gt⁻¹T_est), covariances and sources;
    with ``reference`` ((N, 4, 4) poses of every frame of the dataset) also the summaries against
    it (``"<mode> vs reference"``), aligned on the training frames to the map's keyframe poses."""
    t0 = time.perf_counter()
    # the paper's locator needs no 3D model; None: the core's default (the model locator)
    m = geoloc.Map.build(train, network or "bow", model=False if locator == "paper" else None, adjust_labels=adjust_labels,
                         seed=seed)
    build_s = time.perf_counter() - t0
    noise = m.map_noise
    h = noise["holdout"]
    out: dict[str, Any] = {
        "build_s": build_s,
        "map_noise": {
            "sqrt_diag": np.sqrt(np.diag(noise["pose_covariance"])).tolist(),
            "pose_covariance": noise["pose_covariance"].tolist(),
            "acceleration_psd": noise["acceleration_psd"].tolist(),
            "holdout_samples": noise["holdout_samples"],
            "holdout_inliers": noise["holdout_inliers"],
            "near": None if noise["near"] is None else {
                "sqrt_diag": np.sqrt(np.diag(noise["near"]["covariance"])).tolist(),
                "spacing": noise["near"]["spacing"],
                "holdout_distance": noise["near"]["holdout_distance"],
            },
            "holdout": {
                "keyframe": h["keyframe"].tolist(),
                "position": [train.poses[k][:3, 3].tolist() for k in h["keyframe"]],
                "delta": h["delta"].tolist(),
                "covariance": h["covariance"].tolist(),
                "inliers": h["inliers"].tolist(),
                "used": h["used"].tolist(),
                "novelty": h["novelty"].tolist(),
            },
        },
        "frames": {},
    }
    gt = test.poses
    alignment = None
    gt_reference = None
    if reference is not None:
        from geoloc.reference import align_reference

        alignment = align_reference(reference[train.indices], m.keyframe_poses)
        out["alignment"] = alignment.statistics()
        gt_reference = alignment.apply(reference[test.indices])
    # C_map in the results' convention (the labels'): Ad(X) C_map Ad(X)ᵀ, X = label_from_cam
    label_from_cam = se3_inverse(m.keyframe_poses[0]) @ m.camera_poses[0]
    adjoint = se3_adjoint(label_from_cam)
    out["map_noise"]["pose_covariance_labels"] = (adjoint @ noise["pose_covariance"] @ adjoint.T).tolist()
    out["label_from_cam"] = label_from_cam.tolist()
    for mode in ("single", "sequential"):
        results = geoloc.Localizer(m, locator=locator, global_descriptor=network).localize_sequence(test, mode)  # type: ignore[arg-type]
        if gt_reference is not None:
            ref = summarize_results(results, gt_reference)
            ref.pop("per_frame", None)
            out[f"{mode} vs reference"] = ref
        s = summarize_results(results, gt)
        s.pop("per_frame", None)
        sig = [isometric_sigmas(r.covariance)[0] for r in results if r.covariance is not None]
        s["median_sigma_p_m"] = float(np.median(sig)) if sig else None
        out[mode] = s
        out["frames"][mode] = [
            {
                "source": str(r.source),
                "reason": r.reason,
                "delta": None if r.pose is None else se3_log(se3_inverse(gt[i]) @ r.pose).tolist(),
                "delta_reference": None if r.pose is None or gt_reference is None
                else se3_log(se3_inverse(gt_reference[i]) @ r.pose).tolist(),
                "covariance": None if r.covariance is None else np.asarray(r.covariance).tolist(),
                "position": gt[i][:3, 3].tolist(),
                "inliers": int(r.inliers),
                "map_noise_scale": float(r.map_noise_scale),
                "novelty": None if r.novelty is None else float(r.novelty),
                "keyframe": int(r.keyframe),
            }
            for i, r in enumerate(results)
        ]
    return out


def isometric_sigmas(c: Any) -> tuple[float, float]:
    """The paper's isometric σ: mean √diag of the translation block (m), and of the rotation one."""
    d = np.sqrt(np.clip(np.diag(np.asarray(c)), 0.0, None))
    return float(d[:3].mean()), float(d[3:].mean())


#: ``--near-path``: every this-th frame (from the middle of each run of them) is a query.
NEAR_PATH_STEP = 10


def near_path(seq: Any) -> tuple[Any, Any]:
    """(train, test): frames 5, 15, …, the queries; the map of all the others."""
    test = np.arange(NEAR_PATH_STEP // 2, len(seq), NEAR_PATH_STEP)
    return seq[np.setdiff1d(np.arange(len(seq)), test)], seq[test]


def fold(seq: Any, b: int) -> tuple[Any, Any]:
    n = len(seq)
    lo, hi = b * BLOCK, min((b + 1) * BLOCK, n)
    keep = np.array([i for i in range(n) if i < lo - MARGIN or i >= hi + MARGIN])
    return seq[keep], seq[lo:hi]


#: PnP inlier-count bins of the coverage breakdown: [lo, hi).
INLIER_BINS = ((0, 20), (20, 40), (40, 80), (80, None))


def coverage_by_inliers(frames: list[dict[str, Any]]) -> str:
    """NEES coverage (χ²₆ 95 %) of the frames with a covariance, by their PnP inlier count:
    "<20: 82 % (28)  20-39: ..." — where a covariance is too small or too large."""
    cells = []
    for lo, hi in INLIER_BINS:
        nees = frame_nees([f for f in frames if lo <= f["inliers"] and (hi is None or f["inliers"] < hi)], "delta")
        label = f"<{hi}" if lo == 0 else (f"≥{lo}" if hi is None else f"{lo}-{hi - 1}")
        cells.append(f"{label}: " + ("—" if not len(nees) else f"{np.mean(nees <= CHI2_6_95):.0%} ({len(nees)})"))
    return "  ".join(cells)


def common_frame_medians(frames: dict[str, list[dict[str, Any]]], key: str) -> str:
    """Median translation error of each mode over the frames *both* localized (δ under ``key``):
    the modes' own medians run over different frames when one answers frames the other loses."""
    both = [i for i, (a, b) in enumerate(zip(frames["single"], frames["sequential"])) if a[key] is not None and b[key] is not None]
    if not both:
        return "no frame localized in both modes"
    errors = {mode: [float(np.linalg.norm(frames[mode][i][key][:3])) for i in both] for mode in frames}
    med = {mode: 100 * float(np.median(e)) for mode, e in errors.items()}
    farther = sum(q > s for s, q in zip(errors["single"], errors["sequential"]))
    closer = sum(q < s for s, q in zip(errors["single"], errors["sequential"]))
    return (f"{len(both)} frames: single {med['single']:.2f} cm, sequential {med['sequential']:.2f} cm "
            f"(sequential farther on {farther}, closer on {closer}: sign test p = {sign_test(farther, closer):.2f})")


def sign_test(k: int, m: int) -> float:
    """Two-sided exact sign test: the probability, were each of k + m paired differences
    equally likely either sign, of a split at least as uneven as k : m,
    min(1, 2·Σ_{i ≤ min(k, m)} C(n, i) / 2ⁿ) with n = k + m (1 for n = 0). A median gap between
    the modes with p well above 0.05 is one the frames do not tell from chance."""
    n = k + m
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, i) for i in range(min(k, m) + 1))
    return min(1.0, float(2 * tail / 2**n))


#: The coverage band asked of a 95 % region on every 100-frame block.
COVERAGE_BAND = (0.88, 0.99)


def integrated_autocorrelation_time(x: Any) -> float:
    """τ = 1 + 2 Σ_{k=1..M} ρ_k of the series ``x`` (ρ_k its lag-k autocorrelation about its
    mean), summed up to the first M ≥ 5τ (Sokal's window; at most n/2): the number of
    consecutive frames that carry about one sample's information. At least 1."""
    x = np.asarray(x, dtype=float) - np.mean(x)
    n, variance = len(x), float(x @ x) / len(x)
    if n < 4 or variance <= 0.0:
        return 1.0
    tau = 1.0
    for m in range(1, n // 2):
        tau += 2.0 * float(x[:-m] @ x[m:]) / (n - m) / variance
        if m >= 5.0 * tau:
            break
    return max(1.0, tau)


def block_structure(frames: list[dict[str, Any]], key: str) -> tuple[Any, Any] | None:
    """(φ, τ) per axis of a block's errors in capture order (δ under ``key``, whitened by the
    frame's own σ, z = δ_a/√C_aa): φ the fraction of their second moment that is one offset
    shared by the whole block, (z̄²/mean z² − τ/n)/(1 − τ/n) clipped to [0, 1] (the sample
    mean of n correlated frames carries τ/n of the variance by itself), and τ the integrated
    autocorrelation time of the rest. None for fewer than 10 answered frames."""
    z = np.array([np.asarray(f[key]) / np.sqrt(np.diag(np.asarray(f["covariance"])))
                  for f in frames if f[key] is not None and f["covariance"] is not None])
    if len(z) < 10:
        return None
    n = len(z)
    tau = np.array([integrated_autocorrelation_time(z[:, a]) for a in range(6)])
    raw = z.mean(axis=0) ** 2 / np.mean(z**2, axis=0)
    phi = np.clip((raw - tau / n) / np.maximum(1.0 - tau / n, 1e-9), 0.0, 1.0)
    return phi, tau


def simulated_block_coverage(phi: Any, tau: Any, n: int = BLOCK, trials: int = 4000, seed: int = 0) -> tuple[Any, Any]:
    """(NEES coverage, lowest per-axis coverage) of ``trials`` simulated blocks of ``n``
    frames whose covariance is *exactly right*, their errors with the structure of
    :func:`block_structure`. Seeded, so the same every run. Per axis a (independent),
    z_t = b + √(1 − φ_a)·e_t with b ~ N(0, φ_a) drawn once per block and e an AR(1) series of
    unit variance and integrated autocorrelation time τ_a (ρ = (τ − 1)/(τ + 1)); the
    covariance is I, NEES coverage the fraction of frames with ‖z‖² inside χ²₆ 95 %, axis
    coverage the fraction with |z_a| ≤ 1.96."""
    phi, tau = np.asarray(phi, dtype=float), np.asarray(tau, dtype=float)
    rho = (tau - 1.0) / (tau + 1.0)
    rng = np.random.default_rng(seed)
    shared = rng.standard_normal((trials, 1, 6)) * np.sqrt(phi)
    e = np.empty((trials, n, 6))
    e[:, 0] = rng.standard_normal((trials, 6))
    for t in range(1, n):
        e[:, t] = rho * e[:, t - 1] + np.sqrt(1.0 - rho**2) * rng.standard_normal((trials, 6))
    z = shared + np.sqrt(1.0 - phi) * e
    nees = np.mean(np.sum(z**2, axis=-1) <= CHI2_6_95, axis=1)
    axis = np.min(np.mean(np.abs(z) <= COVERAGE_Z, axis=1), axis=-1)
    return nees, axis


def calibrated_band_probability(phi: Any, tau: Any, n: int = BLOCK, band: tuple[float, float] = COVERAGE_BAND,
                                trials: int = 4000, seed: int = 0) -> tuple[float, float]:
    """(p_NEES, p_both): how often a block whose covariance is exactly right
    (:func:`simulated_block_coverage`) has its NEES coverage — and that and its lowest
    per-axis coverage — inside ``band``. With independent frames (φ = 0, τ = 1) p_NEES is
    the binomial P(88 ≤ Bin(100, 0.95) ≤ 99) = 0.99; a block that is one shared offset
    (φ = 1) is covered 0 or 100 %, never in between."""
    nees, axis = simulated_block_coverage(phi, tau, n, trials, seed)
    lo, hi = band
    in_nees = (nees >= lo) & (nees <= hi)
    return float(np.mean(in_nees)), float(np.mean(in_nees & (axis >= lo) & (axis <= hi)))


def frame_nees(frames: list[dict[str, Any]], key: str) -> Any:
    """NEES δᵀC⁻¹δ of every answered frame (δ under ``key``, with a covariance)."""
    return np.array([np.asarray(f[key]) @ np.linalg.solve(np.asarray(f["covariance"]), np.asarray(f[key]))
                     for f in frames if f[key] is not None and f["covariance"] is not None])


def nees_coverage(frames: list[dict[str, Any]], key: str) -> float | None:
    """The fraction of answered frames (δ under ``key``) inside their χ²₆ 95 % region."""
    nees = frame_nees(frames, key)
    return float(np.mean(nees <= CHI2_6_95)) if len(nees) else None


def block_chances(frames: list[dict[str, Any]], key: str) -> dict[str, Any] | None:
    """Of one block's answers (δ under ``key``): their structure φ, τ (:func:`block_structure`),
    the chances p_nees, p_both that a covariance exactly right for them puts the block in the
    coverage band (:func:`calibrated_band_probability`), their NEES coverage and
    p_at_least, how often that right covariance covers the block at least as well in NEES (a
    one-sided p of over-coverage). None when there are too few answers."""
    structure, observed = block_structure(frames, key), nees_coverage(frames, key)
    if structure is None or observed is None:
        return None
    phi, tau = structure
    nees, _ = simulated_block_coverage(phi, tau, len([f for f in frames if f[key] is not None]))
    p_nees, p_both = calibrated_band_probability(phi, tau)
    return {"phi": phi, "tau": tau, "p_nees": p_nees, "p_both": p_both, "observed": observed,
            "p_at_least": float(np.mean(nees >= observed - 1e-9))}


def block_structure_line(frames: dict[str, list[dict[str, Any]]], key: str) -> str:
    """Per mode: the errors' block structure and the chances of :func:`block_chances`."""
    cells = []
    for mode, fr in frames.items():
        c = block_chances(fr, key)
        if c is None:
            cells.append(f"{mode} —")
            continue
        cells.append(f"{mode} φ {np.round(c['phi'], 2).tolist()} τ {np.round(c['tau'], 1).tolist()}: "
                     f"p {c['p_nees']:.2f} / {c['p_both']:.2f}, "
                     f"NEES coverage ≥ {percent(c['observed'])} % with p {c['p_at_least']:.2f}")
    return "; ".join(cells)


#: Factors s on C_map at which ``calibration.py`` prints each fold's coverage (and the folds' pooled one).
MAP_NOISE_SCALES = (0.1, 0.25, 0.5, 1.0, 2.0)


def measurement_and_map_noise(frames: list[dict[str, Any]], key: str, c_map: Any) -> list[tuple[Any, Any, Any]]:
    """Per answered frame (δ under ``key``, C − C_i, C_i): its covariance split into the
    measurement part and C_i = f_i·C_map, the C_map it holds (f_i its ``map_noise_scale``,
    1 when absent; ``c_map`` in the results' convention; a near-regime frame's C_near part
    stays with the measurement)."""
    c_map = np.asarray(c_map)
    framed = [(np.asarray(f[key]), np.asarray(f["covariance"]), f.get("map_noise_scale", 1.0) * c_map)
              for f in frames if f[key] is not None and f["covariance"] is not None]
    return [(d, c - m, m) for d, c, m in framed]


def coverage_at(pairs: list[tuple[Any, Any, Any]], s: float, per_axis: bool = False) -> float:
    """Coverage of ``pairs`` (:func:`measurement_and_map_noise`) with the map noise scaled by
    s, C(s) = C − C_i + s·C_i: NEES coverage (χ²₆ 95 %), or with ``per_axis`` the lowest
    per-axis 1.96σ coverage."""
    if per_axis:
        inside = [np.abs(d) <= COVERAGE_Z * np.sqrt(np.diag(c + s * m)) for d, c, m in pairs]
        return float(np.min(np.mean(inside, axis=0)))
    return float(np.mean([d @ np.linalg.solve(c + s * m, d) <= CHI2_6_95 for d, c, m in pairs]))


def outside_region(frames: list[dict[str, Any]], key: str) -> tuple[int, int]:
    """(k, n): of the n answered frames with an error under ``key``, the k outside their
    99.9 % region (NEES δᵀC⁻¹δ above the χ²₆ 99.9 % quantile) — the answers the covariance
    does not hold at all."""
    nees = frame_nees(frames, key)
    return int(np.sum(nees > CHI2_6_999)), len(nees)


def percent(fraction: float) -> str:
    """``fraction`` in per cent, whole (one decimal where rounding would show a miss as 100)."""
    value = 100 * fraction
    return f"{value:.1f}" if 99.5 <= value < 100 else f"{value:.0f}"


def scored_against(against_reference: bool) -> tuple[str, str]:
    """The per-frame error key and its name in the printout: the reference's or the labels'."""
    return ("delta_reference", "reference") if against_reference else ("delta", "labels")


def coverage_by_map_noise_scale(pairs: list[tuple[Any, Any, Any]]) -> str:
    """``0.1: 46/58, …``: NEES / lowest-axis coverage (%, :func:`percent`) at each of
    :data:`MAP_NOISE_SCALES`."""
    if not pairs:
        return "—"
    return ", ".join(f"{s:g}: {percent(coverage_at(pairs, s))}/{percent(coverage_at(pairs, s, True))}"
                     for s in MAP_NOISE_SCALES)


def coverage_sweep_line(against: str, mode: str, pairs: list[tuple[Any, Any, Any]]) -> str:
    """The printed coverage of one mode against ``against`` with C_map × s (see the module doc)."""
    return (f"coverage against the {against} with C_map × s, {mode} (s: NEES / lowest axis %): "
            f"{coverage_by_map_noise_scale(pairs)}")


def map_noise_scale_for_coverage(frames: list[dict[str, Any]], key: str, c_map: Any, per_axis: bool = False,
                                 target: float = 0.95) -> float | None:
    """The factor s on the map noise (results' convention) at which the frames' coverage would
    be ``target`` (:func:`coverage_at`), s bisected on [0, 1000]
    (coverage grows with s). 0 when the measurement part alone covers ``target``; None without
    frames or when even s = 1000 does not. 1 means the map noise is right for the fold; the
    map's C_map is right on every fold only if every fold needs about the same s."""
    pairs = measurement_and_map_noise(frames, key, c_map)
    if not pairs:
        return None

    def coverage(s: float) -> float:
        return coverage_at(pairs, s, per_axis)

    if coverage(0.0) >= target:
        return 0.0
    lo, hi = 0.0, 1000.0
    if coverage(hi) < target:
        return None
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if coverage(mid) >= target else (mid, hi)
    return hi


#: Lower edges of the bins of a held-out keyframe's support n/n̄ (n its PnP inliers, n̄ its
#: map's median: ``Map.map_noise["holdout_inliers"]``); the last bin is open.
SUPPORT_BINS = (0.0, 0.25, 0.5, 0.75, 1.0)


def excess_by_support(noises: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Pooled over maps' held-out keyframes (each of ``noises`` a ``map_noise`` entry of
    :func:`evaluate`: ``holdout`` and ``holdout_inliers``), per bin of n/n̄
    (:data:`SUPPORT_BINS`): ``count``, ``support`` (the mean n/n̄), ``rule`` (the mean factor
    max(1, n̄/n) the localizer puts on C_map at that support), ``translation_m2`` and
    ``rotation_rad2``: the mean excess second moment δ² − C_G summed over the three axes of
    each. Empty bins are left out. C_map·max(1, n̄/n) holds if the excess grows as ``rule``."""
    rows = []
    for noise in noises:
        h = noise["holdout"]
        n_bar = noise["holdout_inliers"]
        if n_bar <= 0:
            continue
        delta, cov = np.asarray(h["delta"], dtype=float), np.asarray(h["covariance"], dtype=float)
        excess = delta**2 - np.einsum("nii->ni", cov)
        for e, n in zip(excess, h["inliers"]):
            rows.append((n / n_bar, max(1.0, n_bar / n) if n > 0 else 1.0, e[:3].sum(), e[3:].sum()))
    out = []
    edges = (*SUPPORT_BINS, np.inf)
    for lo, hi in zip(edges[:-1], edges[1:]):
        inside = [r for r in rows if lo <= r[0] < hi]
        if inside:
            support, rule, t, r = np.mean(inside, axis=0)
            out.append({"bin": [lo, None if np.isinf(hi) else hi], "count": len(inside), "support": float(support),
                        "rule": float(rule), "translation_m2": float(t), "rotation_rad2": float(r)})
    return out


def excess_by_support_line(bins: list[dict[str, Any]]) -> str:
    """``[0, 0.25): 19, 54.37 cm² / 1126 mrad² (×43.1 / ×41.5 of n ≥ n̄, the rule ×8.4); …``: per bin of
    :func:`excess_by_support`, the count, the excess and its ratio to the open top bin's (n ≥ n̄),
    beside the support rule's mean factor."""
    top = next((b for b in bins if b["bin"][1] is None), None)
    parts = []
    for b in bins:
        lo, hi = b["bin"]
        name = f"[{lo:g}, {hi:g})" if hi is not None else f"≥ {lo:g}"
        text = f"{name}: {b['count']}, {1e4 * b['translation_m2']:.2f} cm² / {1e6 * b['rotation_rad2']:.0f} mrad²"
        if top is not None and b is not top and top["translation_m2"] > 0 and top["rotation_rad2"] > 0:
            text += (f" (×{b['translation_m2'] / top['translation_m2']:.1f} / ×{b['rotation_rad2'] / top['rotation_rad2']:.1f}"
                     f" of n ≥ n̄, the rule ×{b['rule']:.1f})")
        parts.append(text)
    return "; ".join(parts) if parts else "—"


def row(name: str, mode: str, s: dict[str, Any]) -> str:
    med = "lost" if s["median_translation_m"] is None else f"{100 * s['median_translation_m']:.1f} cm / {s['median_rotation_deg']:.2f}°"
    all_t, all_r = s.get("median_translation_all_m"), s.get("median_rotation_all_deg")
    med_all = "lost" if all_t is None or all_r is None else f"{100 * all_t:.1f} cm / {all_r:.2f}°"
    axis = s.get("axis_coverage") or {}
    axis_vals = [v for v in (axis.values() if isinstance(axis, dict) else axis) if v is not None]
    axis_min = f"{min(axis_vals):.0%}" if axis_vals else "—"
    cov = "—" if s["nees_coverage"] is None else f"{s['nees_coverage']:.0%}"
    nees = "—" if s["median_nees"] is None else f"{s['median_nees']:.1f}"
    sig = "—" if s.get("median_sigma_p_m") is None else f"{100 * s['median_sigma_p_m']:.1f} cm"
    src = " ".join(f"{k[:3]}{v}" for k, v in s["sources"].items())
    return (
        f"{name:<10} {mode:<10} {med:>18} {med_all:>18} {s['recall'].get('5cm_5deg', 0):>7.0%} {cov:>6} {axis_min:>8} {nees:>8} {sig:>8}  {src}"
    )


#: The paper's split of the frames 0–699: train on 0–599, test on 600–699 (no margin).
PAPER_TRAIN = 600


def print_evaluation(name: str, r: dict[str, Any], against_reference: bool) -> None:
    """The rows of one evaluation (both modes, against the labels and the reference) and the
    lines on its coverage, its modes' common frames, its C_map factors and its map noise."""
    for mode in ("single", "sequential"):
        print(row(name, mode, r[mode]), flush=True)
        if f"{mode} vs reference" in r:
            print(row("", f"{mode[:3]} vs ref", r[f"{mode} vs reference"]), flush=True)
    print(f"{'':<10} NEES coverage by PnP inliers, single: {coverage_by_inliers(r['frames']['single'])}", flush=True)
    key, against = scored_against(against_reference)
    print(f"{'':<10} against the {against} on the {common_frame_medians(r['frames'], key)}", flush=True)
    c_map = r["map_noise"]["pose_covariance_labels"]
    scale = {
        (mode, per_axis): map_noise_scale_for_coverage(r["frames"][mode], key, c_map, per_axis)
        for mode in r["frames"] for per_axis in (False, True)
    }
    print(f"{'':<10} C_map × s for 95 % coverage against the {against} (NEES / lowest axis): "
          + ", ".join(f"{mode} " + " / ".join("—" if scale[mode, a] is None else f"{scale[mode, a]:.2f}" for a in (False, True))
                      for mode in r["frames"]), flush=True)
    for mode in r["frames"]:
        pairs = measurement_and_map_noise(r["frames"][mode], key, c_map)
        print(f"{'':<10} {coverage_sweep_line(against, mode, pairs)}", flush=True)
    print(f"{'':<10} outside the 99.9 % region against the {against}: "
          + ", ".join("{} {} of {}".format(mode, *outside_region(r["frames"][mode], key)) for mode in r["frames"]), flush=True)
    lo, hi = COVERAGE_BAND
    print(f"{'':<10} block structure against the {against} (φ shared fraction, τ frames per axis) and the chance p that a "
          f"covariance exactly right for such errors covers this block at {lo:.0%}–{hi:.0%} (NEES / NEES and every axis): "
          f"{block_structure_line(r['frames'], key)}", flush=True)
    n = r["map_noise"]
    novelty = [f["novelty"] for f in r["frames"]["single"] if f.get("novelty") is not None]
    if n.get("near") is not None and novelty:
        near = n["near"]
        print(f"{'':<10} near regime √diag C_near {np.round(near['sqrt_diag'], 4).tolist()} at ν ≤ {near['spacing']:.2f}, "
              f"C_map at ν ≥ {near['holdout_distance']:.2f}; the queries' ν (single) median {np.median(novelty):.2f}, "
              f"range {min(novelty):.2f}–{max(novelty):.2f}", flush=True)
    print(f"{'':<10} map noise √diag C_map {np.round(n['sqrt_diag'], 4).tolist()} "
          f"(n={n['holdout_samples']}, median inliers {n['holdout_inliers']:.0f}), "
          f"q {np.round(n['acceleration_psd'], 3).tolist()}, build {r['build_s']:.0f} s",
          flush=True)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--folds", default="0,1,2,3,4,5,6", help="comma-separated test blocks of 100 frames")
    ap.add_argument("--synthetic", action="store_true", help="also the synthetic room")
    ap.add_argument("--json", help="write the summaries here")
    ap.add_argument("--locator", choices=("paper", "model"), default=None,
                    help="the geometric locator (default: the core's; paper: the map is built without the 3D model, "
                    "C_map measured with the paper's locator)")
    ap.add_argument("--keep-labels", dest="adjust_labels", action="store_false",
                    help="maps keep their labels as the truth (default: corrected by bundle adjustment)")
    ap.add_argument("--reference", type=Path, default=REFERENCE if REFERENCE.is_file() else None,
                    help="SfM reference poses to score against as well (default: the shared one, when present)")
    ap.add_argument("--seed", type=int, default=None,
                    help="seed of every map's vocabulary (default: the core's); another seed shows how much a fold's "
                    "numbers move with a nuisance parameter")
    ap.add_argument("--network", type=Path, metavar="DIR/NAME",
                    help="fuse each fold's map with the network whose descriptors DIR/NAME-fold<LO>.npz holds")
    ap.add_argument("--near-path", action="store_true",
                    help=f"also queries beside the mapped path: every {NEAR_PATH_STEP}th frame of 0-699 against a map "
                    "of the rest")
    ap.add_argument("--paper-split", action="store_true",
                    help=f"also the paper's split: train on frames 0-{PAPER_TRAIN - 1}, test on {PAPER_TRAIN}-699")
    args = ap.parse_args()
    if args.paper_split and args.network is not None:
        ap.error("--paper-split: the saved network descriptors are per fold; there are none for the paper's split")
    reference = None
    if args.reference is not None:
        from geoloc.reference import load_reference

        keys, poses = load_reference(args.reference)
        reference = np.full((int(keys.max()) + 1, 4, 4), np.nan)
        reference[keys] = poses
    report: dict[str, Any] = {}
    header = f"{'fold':<10} {'mode':<10} {'median':>18} {'median, lost=∞':>18} {'5cm/5°':>7} {'NEES':>6} {'axis min':>8} {'med NEES':>8} {'σ_p med':>8}  sources"
    print(header, flush=True)
    if DATA.is_dir() and (args.folds or args.paper_split or args.near_path):
        seq = geoloc.datasets.load_7scenes(DATA)[:700]
        rows = frame_rows(seq) if args.network is not None else {}
        for b in (int(x) for x in args.folds.split(",") if x):
            train, test = fold(seq, b)
            network = None
            if args.network is not None:
                saved = args.network.parent / f"{args.network.name}-fold{b * BLOCK}.npz"
                network = FrameDescriptors(rows, np.load(saved)["descriptors"], args.network.name)
            r = evaluate(train, test, args.locator, args.adjust_labels, reference, network, args.seed)
            name = f"{b * BLOCK}-{b * BLOCK + len(test) - 1}"
            report[name] = r
            print_evaluation(name, r, reference is not None)
        if args.paper_split:
            r = evaluate(seq[:PAPER_TRAIN], seq[PAPER_TRAIN:], args.locator, args.adjust_labels, reference, None, args.seed)
            report["paper split"] = r
            print_evaluation(f"{PAPER_TRAIN}-{len(seq) - 1}", r, reference is not None)
        if args.near_path:
            train, test = near_path(seq)
            r = evaluate(train, test, args.locator, args.adjust_labels, reference, None, args.seed)
            report["near path"] = r
            print_evaluation("near path", r, reference is not None)
    elif args.folds or args.paper_split or args.near_path:
        print(f"(no shared data at {DATA}: 7-Scenes folds skipped)")
    folds = [name for name in report if name not in ("paper split", "near path")]
    if len(folds) > 1:
        key, against = scored_against(reference is not None)
        for mode in ("single", "sequential"):
            pairs = [p for name in folds for p in measurement_and_map_noise(
                report[name]["frames"][mode], key, report[name]["map_noise"]["pose_covariance_labels"])]
            print(f"folds {','.join(folds)} pooled ({len(pairs)} frames), {coverage_sweep_line(against, mode, pairs)}",
                  flush=True)
        for mode in ("single", "sequential"):
            chances = [c for name in folds if (c := block_chances(report[name]["frames"][mode], key)) is not None]
            p_nees, p_both = [c["p_nees"] for c in chances], [c["p_both"] for c in chances]
            print(f"folds {','.join(folds)}, {mode}: a covariance exactly right for each fold's errors would put all "
                  f"{len(chances)} blocks in the band with p {np.prod(p_nees):.3f} (NEES) / "
                  f"{np.prod(p_both):.3f} (NEES and every axis), expected blocks in it "
                  f"{sum(p_nees):.1f} / {sum(p_both):.1f}; and cover every block at least as "
                  f"well as the answers did (NEES) with p {np.prod([c['p_at_least'] for c in chances]):.1e}", flush=True)
        bins = excess_by_support([report[name]["map_noise"] for name in folds])
        report["held-out excess by support"] = bins
        print(f"folds {','.join(folds)}, the maps' held-out keyframes' excess second moment δ² − C_G (translation / "
              f"rotation, summed over the axes) by support n/n̄: {excess_by_support_line(bins)}", flush=True)
        print(f"folds {','.join(folds)} pooled, outside the 99.9 % region against the {against}: " + ", ".join(
            "{} {} of {}".format(mode, *np.sum([outside_region(report[name]["frames"][mode], key) for name in folds], axis=0))
            for mode in ("single", "sequential")), flush=True)
    if args.synthetic:
        seq = geoloc.datasets.synthetic_room(n_frames=300, seed=0)
        r = evaluate(seq[:200], seq[200:], args.locator)
        report["synthetic"] = r
        for mode in ("single", "sequential"):
            print(row("synthetic", mode, r[mode]), flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1, default=float))
    return 0


if __name__ == "__main__":
    os.environ.setdefault("GEOLOC_NUM_THREADS", "1")
    sys.exit(main())
