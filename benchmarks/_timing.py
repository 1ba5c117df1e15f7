"""Timing helpers for the side-by-side benchmarks (not part of the test suite)."""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable


@dataclass
class Timing:
    """Best and median wall time of repeated runs of one implementation."""

    name: str
    best_s: float
    median_s: float


def measure(name: str, fn: Callable[[], object], repeats: int = 7, warmup: int = 1) -> Timing:
    """Run ``fn`` ``warmup`` + ``repeats`` times and keep the best and median wall times."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    times.sort()
    return Timing(name, times[0], times[len(times) // 2])


def print_table(title: str, n: int, timings: list[Timing], baseline: str) -> dict[str, dict[str, float]]:
    """Print times per call and per item, and each one's speed relative to ``baseline``;
    the same rows, by implementation, for a ``--json`` result."""
    base = next(t for t in timings if t.name == baseline)
    print(f"\n{title} ({n} items; ratio = other's time / {baseline}'s time)")
    print(f"  {'implementation':<42} {'best ms':>9} {'median ms':>10} {'ns/item':>9} {'ratio':>7}")
    for t in timings:
        ratio = t.best_s / base.best_s
        print(f"  {t.name:<42} {t.best_s * 1e3:>9.2f} {t.median_s * 1e3:>10.2f} "
              f"{t.best_s / n * 1e9:>9.1f} {ratio:>6.1f}x")
    return {
        t.name: {"best_ms": t.best_s * 1e3, "median_ms": t.median_s * 1e3, "ns_per_item": t.best_s / n * 1e9,
                 "ratio": t.best_s / base.best_s}
        for t in timings
    }
