"""The long profile of the adversarial suite (tests/adversarial): ≥ 20 000 generated cases
over every public module and the file cases (odd paths, FIFOs, concurrent writers, aliased
outputs, memory limits, crafted checksummed maps), each run in the crash-isolated worker, printing per module the
number of cases, how many passed (a valid result, or an InvalidInputError naming the
argument) and the failures by kind (wrong-type, wrong-name, panic, crash, hang, invariant),
with up to five reproducers of each.

    PYTHONPATH=$PWD/python python benchmarks/adversarial.py            # 20 000+ cases
    PYTHONPATH=$PWD/python python benchmarks/adversarial.py --per-module 50 --modules lie,geometry

Exit status 1 when any case failed.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tests" / "adversarial"))

from hypothesis import HealthCheck, given, settings  # noqa: E402

import cases  # noqa: E402  (tests/adversarial on sys.path)
from harness import GOOD, Tally, Worker  # noqa: E402

#: Share of the cases per module (the heavy modules, which build maps or plots, get fewer).
WEIGHTS = {"files": 0.3, "cli": 0.3, "mapping": 0.25, "plots": 0.1, "datasets": 0.3, "descriptor": 0.5, "features": 0.6, "localizer": 0.6}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--per-module", type=int, default=2000, help="cases for a module of weight 1 (default 2000: ≥ 20 000 in all)")
    ap.add_argument("--modules", default="", help="comma-separated subset")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    with_onnx = importlib.util.find_spec("torch") is not None
    modules = [*cases.all_specs(with_onnx), "cli", "files"]
    if args.modules:
        modules = [m for m in modules if m in args.modules.split(",")]
    tally = Tally()
    worker = Worker()
    t0 = time.perf_counter()
    try:
        for module in modules:
            n = max(20, int(args.per_module * WEIGHTS.get(module, 1.0)))
            t_mod = time.perf_counter()

            @settings(max_examples=n, deadline=None, database=None, derandomize=False,
                      suppress_health_check=list(HealthCheck))
            @given(case=cases.module_cases(module, with_onnx))
            def run(case: dict) -> None:
                tally.add(module, case, worker.run(case))

            run()
            c = tally.counts[module]
            print(f"{module:<12} {c['cases']:>6} cases {c['passed']:>6} passed "
                  f"({time.perf_counter() - t_mod:.0f} s)", flush=True)
    finally:
        worker.close()
    print(f"\n{'module':<12} {'cases':>7} {'passed':>7} {'ok':>7} {'rejected':>8}  failures by kind")
    total = 0
    bad = 0
    for module, c in tally.counts.items():
        fails = {k[5:]: v for k, v in c.items() if k.startswith("fail:")}
        total += c["cases"]
        bad += sum(fails.values())
        print(f"{module:<12} {c['cases']:>7} {c['passed']:>7} {c['ok']:>7} {c['rejected']:>8}  {fails or '-'}")
    print(f"{'total':<12} {total:>7} {total - bad:>7}   in {time.perf_counter() - t0:.0f} s, "
          f"{worker.restarts} worker restarts")
    for (module, kind), examples in sorted(tally.examples.items()):
        print(f"\n[{module}] {kind}:")
        for e in examples:
            print("   ", e)
    return 1 if bad else 0


if __name__ == "__main__":
    assert GOOD
    sys.exit(main())
