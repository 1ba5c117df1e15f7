"""The hand-written stub python/geoloc/_core.pyi matches the compiled module."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # mypy and stubtest over the whole package

ROOT = Path(__file__).resolve().parents[1]


def test_stub_matches_compiled_module() -> None:
    pytest.importorskip("mypy")
    result = subprocess.run(
        [sys.executable, "-m", "mypy.stubtest", "geoloc._core", "--ignore-missing-stub"],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert result.returncode == 0, result.stdout + result.stderr


def test_package_type_checks_strictly() -> None:
    pytest.importorskip("mypy")
    result = subprocess.run(
        [sys.executable, "-m", "mypy", "--strict", str(ROOT / "python" / "geoloc")],
        capture_output=True,
        text=True,
        cwd=ROOT,
    )
    assert result.returncode == 0, result.stdout + result.stderr


def test_every_core_function_is_in_the_stub() -> None:
    import geoloc._core as core

    stub = (ROOT / "python" / "geoloc" / "_core.pyi").read_text()
    public = [n for n in dir(core) if not n.startswith("_") and callable(getattr(core, n))]
    missing = [n for n in public if f"def {n}(" not in stub and f"class {n}:" not in stub]
    assert not missing, missing
