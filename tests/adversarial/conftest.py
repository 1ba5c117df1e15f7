"""The adversarial suite's fixtures: one crash-isolated worker process per session, the number
of examples per module (from the hypothesis profile of tests/conftest.py: ``ci`` when ``CI``
is set), and the defects that are known and recorded (each has a strict-xfail reproducer in
``test_adv_known.py``) so the fuzz tests fail only on new ones."""

from __future__ import annotations

import contextlib
import importlib.util
import re
import warnings
from collections.abc import Iterator
from typing import Any

import pytest
from hypothesis import HealthCheck, settings

from .harness import GOOD, Worker, describe

# Hypothesis imports hypothesis.extra._patching (→ libcst → mypy_extensions, which warns a
# DeprecationWarning) only when it reports a failure; under filterwarnings=error that turned
# every failing example into a pytest INTERNALERROR that hid the failure. Import it once here.
with warnings.catch_warnings():
    warnings.simplefilter("ignore", DeprecationWarning)
    with contextlib.suppress(ImportError):
        import hypothesis.extra._patching  # noqa: F401

#: Cases per module: 1/4 of the profile's max_examples (ci: 300 → 75, fast: 50 → 12), at least 12.
EXAMPLES = max(12, settings.default.max_examples // 4)
HAS_TORCH = importlib.util.find_spec("torch") is not None and importlib.util.find_spec("onnxruntime") is not None

#: Known defects in files other sessions own: (module, kind, regex on the failure detail).
KNOWN: list[tuple[str, str, str]] = []  # defects tolerated by the fuzz tests: none left


def is_known(module: str, out: dict[str, Any]) -> bool:
    return any(m == module and k == out["kind"] and re.search(rx, out["detail"]) for m, k, rx in KNOWN)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    # The strategies carry the valid numpy arguments; hypothesis warns when their repr is long.
    for item in items:
        if "adversarial" in str(item.path):
            item.add_marker(pytest.mark.filterwarnings("ignore:Generating overly large repr"))


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
