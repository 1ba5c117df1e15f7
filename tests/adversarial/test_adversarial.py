"""The adversarial suite: one test, parametrized over every target — each public module's entry
points (see cases.py for what is generated), every command line of ``geoloc`` (cases.CLI: one
option at a time set to a bad value) and every kind of file case (file_cases.py: odd paths,
special files, concurrent writers, outputs aliasing inputs, memory limits, crafted map files).

Each case runs in the crash-isolated worker. A module's case passes with a valid result or an
InvalidInputError naming the argument; a command line passes when it exits 0, or non-zero with
exactly one stderr line naming the option, no traceback and no folder created (run in-process
in the worker: ``geoloc.cli.main``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from . import cases, file_cases
from .conftest import EXAMPLES, HAS_TORCH, adversarial_settings, check_case
from .harness import Worker

pytestmark = pytest.mark.slow

#: The modules with entry points to attack (the keys of cases.all_specs).
MODULES = sorted(cases.all_specs(with_onnx=HAS_TORCH))
#: The commands of ``geoloc`` (``train`` needs torch).
COMMANDS = [c for c in cases.CLI if HAS_TORCH or c != "train"]
#: The kinds of file cases.
FILE_KINDS: dict[str, Callable[[], st.SearchStrategy[dict[str, Any]]]] = {
    "odd": file_cases.odd_path_cases,
    "special": file_cases.special_cases,
    "concurrent": file_cases.concurrent_cases,
    "alias": file_cases.alias_cases,
    "limited": file_cases.limited_cases,
    "crafted": file_cases.crafted_cases,
}
#: Every target: ``module``, ``cli:command`` or ``files:kind``.
TARGETS = [*MODULES, *(f"cli:{c}" for c in COMMANDS), *(f"files:{k}" for k in sorted(FILE_KINDS))]


def strategy(target: str) -> st.SearchStrategy[dict[str, Any]]:
    """The cases of one target."""
    if target.startswith("files:"):
        return FILE_KINDS[target.removeprefix("files:")]()
    return cases.module_cases(target, with_onnx=HAS_TORCH)


def examples(target: str) -> int:
    """Cases per target: EXAMPLES (conftest.py, from the hypothesis profile), a quarter of it
    (at least 6) per command line, whose cases run whole commands."""
    return max(6, EXAMPLES // 4) if target.startswith("cli:") else EXAMPLES


@pytest.mark.parametrize("target", TARGETS)
def test_adversarial(worker: Worker, target: str) -> None:
    module = target.split(":")[0]  # what check_case reports and matches known defects against

    @settings(adversarial_settings(), max_examples=examples(target))
    @given(case=strategy(target))
    def run(case: dict[str, Any]) -> None:
        check_case(worker, module, case)

    run()



@pytest.mark.parametrize("command", COMMANDS)
def test_the_base_command_lines_succeed(worker: Worker, command: str) -> None:
    """Every command line the CLI cases start from exits 0 as it is: a base that fails on its
    own turns every case that reaches the failure into a false "wrong-name" report."""
    base, _ = cases.CLI[command]
    out = worker.run({"module": "cli", "cli": [command, *base], "names": [], "timeout": 90, "watch": []})
    assert out["kind"] == "ok", f"{command} {base}: {out}"
