"""Adversarial file cases (see file_cases.py): odd paths, special files, concurrent writers,
outputs aliasing inputs, memory limits and crafted-but-checksummed map files."""

from __future__ import annotations

from typing import Any

import pytest
from hypothesis import given

from . import file_cases
from .conftest import adversarial_settings, check_case
from .harness import Worker

KINDS = {
    "odd": file_cases.odd_path_cases,
    "special": file_cases.special_cases,
    "concurrent": file_cases.concurrent_cases,
    "alias": file_cases.alias_cases,
    "limited": file_cases.limited_cases,
    "crafted": file_cases.crafted_cases,
}


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_adversarial_files(worker: Worker, kind: str) -> None:
    @adversarial_settings()
    @given(case=KINDS[kind]())
    def run(case: dict[str, Any]) -> None:
        check_case(worker, "files", case)

    run()
