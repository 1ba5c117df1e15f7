"""The adversarial suite's fixtures: one crash-isolated worker process per session, the number
of examples per module (from the hypothesis profile of tests/conftest.py: ``ci`` when ``CI``
is set), and the defects that are known and recorded (each has a strict-xfail reproducer in
``test_adv_known.py``) so the fuzz tests fail only on new ones."""

from __future__ import annotations

import importlib.util
import re
from collections.abc import Iterator
from typing import Any

import pytest
from hypothesis import HealthCheck, settings

from .harness import GOOD, Worker, describe

#: Cases per module: ~1/8 of the profile's max_examples (ci: 300 → 37), at least 12.
EXAMPLES = max(12, settings.default.max_examples // 8)
HAS_TORCH = importlib.util.find_spec("torch") is not None and importlib.util.find_spec("onnxruntime") is not None

#: Known defects in files other sessions own: (module, kind, regex on the failure detail).
KNOWN: list[tuple[str, str, str]] = [
    ("fusion", "wrong-type", r"TypeError: '.*' object is not an instance of 'str'"),
    ("localizer", "wrong-type", r"TypeError: (float\(\) argument|object of type|'.*' object is not)"),
    ("localizer", "wrong-type", r"TypeError: int\(\) argument"),
    ("mapping", "wrong-type", r"TypeError: expected str, bytes or os.PathLike object"),
    ("motion", "wrong-type", r"TypeError: '.*' object is not an instance of"),
]


def is_known(module: str, out: dict[str, Any]) -> bool:
    return any(m == module and k == out["kind"] and re.search(rx, out["detail"]) for m, k, rx in KNOWN)


@pytest.fixture(scope="session")
def worker() -> Iterator[Worker]:
    w = Worker()
    yield w
    w.close()


def adversarial_settings() -> settings:
    return settings(max_examples=EXAMPLES, deadline=None, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture,
                                           HealthCheck.data_too_large])


def check_case(worker: Worker, module: str, case: dict[str, Any]) -> None:
    out = worker.run(case)
    if out["kind"] in GOOD or is_known(module, out):
        return
    pytest.fail(f"{out['kind']}: {describe(case)}\n  -> {out['detail']}", pytrace=False)
