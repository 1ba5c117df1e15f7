"""Adversarial command lines: every command with one option set to a bad value (garbage
numbers, ranges, choices, missing / folder / unwritable / garbage files, outputs in missing
folders) must exit non-zero with exactly one stderr line naming the option — or succeed —
with no traceback and no folder created (run in-process in the worker: ``geoloc.cli.main``)."""

from __future__ import annotations

from typing import Any

import pytest
from hypothesis import given, settings

from . import cases
from .conftest import HAS_TORCH, adversarial_settings, check_case
from .harness import Worker

COMMANDS = [c for c in cases.CLI if HAS_TORCH or c != "train"]


@pytest.mark.parametrize("command", COMMANDS)
def test_adversarial_cli(worker: Worker, command: str) -> None:
    @settings(adversarial_settings(), max_examples=max(6, adversarial_settings().max_examples // 4))
    @given(case=cases.cli_cases(command))
    def run(case: dict[str, Any]) -> None:
        check_case(worker, "cli", case)

    run()
