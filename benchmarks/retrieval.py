"""geoloc.retrieval.DescriptorIndex against scipy's cKDTree and a numpy brute force.

    python benchmarks/retrieval.py [--queries 2000] [--json FILE]

N ∈ {1k, 10k, 20k, 100k} × D ∈ {3, 16, 32, 128} L2-normalized random descriptors; build and
query (k = 1) times in one process, results checked equal to brute force. Not a test.
``--json``: the same rows (best of 3 query ms, build ms, agreement), for ``benchmarks/report.py``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(__file__))

from geoloc.retrieval import DescriptorIndex  # noqa: E402


def best_of(fn, repeats=3):  # type: ignore[no-untyped-def]
    best = np.inf
    out = None
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - start)
    return best, out


def numpy_brute(data: np.ndarray, q: np.ndarray) -> np.ndarray:
    # ‖q − x‖² = ‖q‖² + ‖x‖² − 2 q·x, in blocks of 256 queries
    out = np.empty(len(q), dtype=np.int64)
    dn = (data * data).sum(1)
    for s in range(0, len(q), 256):
        block = q[s : s + 256]
        d2 = dn[None] - 2.0 * block @ data.T
        out[s : s + 256] = np.argmin(d2, axis=1)
    return out


def finite(x: float) -> float | None:
    """``x``, or None for NaN (a peer that was skipped): JSON has no NaN."""
    return None if np.isnan(x) else float(x)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--queries", type=int, default=2000)
    parser.add_argument("--json", default=None, help="also write the rows here")
    args = parser.parse_args()
    rows: dict[str, dict[str, float | None]] = {}
    try:
        from scipy.spatial import cKDTree
    except ImportError:
        cKDTree = None  # noqa: N806
        print("(scipy not installed: cKDTree skipped)")
    rng = np.random.default_rng(0)
    print(f"retrieval benchmark: {args.queries} queries, k = 1, {os.cpu_count()} CPUs; query ms (build ms)")
    print(f"  {'N × D':<12} {'geoloc':>18} {'cKDTree':>18} {'numpy brute':>12} {'cKDTree/geoloc':>15}")
    for n in (1000, 10_000, 20_000, 100_000):
        for dim in (3, 16, 32, 128):
            data = rng.normal(size=(n, dim)).astype(np.float32)
            data /= np.linalg.norm(data, axis=1, keepdims=True)
            q = rng.normal(size=(args.queries, dim)).astype(np.float32)
            q /= np.linalg.norm(q, axis=1, keepdims=True)
            build_g, idx = best_of(lambda: DescriptorIndex(data), 1)
            t_g, (_, ind) = best_of(lambda: idx.query(q, 1))
            row = f"  {f'{n} × {dim}':<12} {t_g * 1e3:>9.1f} ({build_g * 1e3:>6.1f})"
            if cKDTree is not None and (n * dim <= 2_000_000):
                build_s, tree = best_of(lambda: cKDTree(data), 1)
                t_s, (_, ind_s) = best_of(lambda: tree.query(q, k=1), 1)
                agree = np.mean(ind[:, 0] == ind_s)
                row += f" {t_s * 1e3:>9.1f} ({build_s * 1e3:>6.1f})"
            else:
                t_s, agree = np.nan, np.nan
                row += f" {'—':>18}"
            t_b, ind_b = best_of(lambda: numpy_brute(data, q), 1)
            row += f" {t_b * 1e3:>12.1f} {t_s / t_g:>14.1f}x"
            assert np.mean(ind[:, 0] == ind_b) > 0.999, "geoloc must equal brute force"
            print(row + ("" if np.isnan(agree) else f"   (agree {100 * agree:.1f} %)"))
            rows[f"{n} x {dim}"] = {
                "geoloc_query_ms": t_g * 1e3, "geoloc_build_ms": build_g * 1e3, "ckdtree_query_ms": finite(t_s * 1e3),
                "numpy_brute_ms": t_b * 1e3, "ckdtree_over_geoloc": finite(t_s / t_g), "ckdtree_agreement": finite(agree),
            }
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"queries": args.queries, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
