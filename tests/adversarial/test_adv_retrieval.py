"""Adversarial cases for geoloc's `retrieval` entry points (see cases.py for what is generated)."""

from __future__ import annotations

from typing import Any

from hypothesis import given

from . import cases
from .conftest import HAS_TORCH, adversarial_settings, check_case
from .harness import Worker


@adversarial_settings()
@given(case=cases.module_cases("retrieval", with_onnx=HAS_TORCH))
def test_adversarial_retrieval(worker: Worker, case: dict[str, Any]) -> None:
    check_case(worker, "retrieval", case)
