"""The scripts in benchmarks/ are not run by the test suite (they time things and take
minutes), but every one of them must at least compile, and those with options answer
``--help`` (importing what they use): a script broken
by a change of the API would otherwise only show when someone regenerates a report."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

BENCHMARKS = sorted((Path(__file__).resolve().parents[1] / "benchmarks").glob("*.py"))
SCRIPTS = [p for p in BENCHMARKS if not p.name.startswith("_")]
#: The scripts with a command line (the others run their one measurement when started).
WITH_OPTIONS = [p for p in SCRIPTS if "argparse" in p.read_text(encoding="utf-8")]


def test_there_are_benchmarks() -> None:
    assert len(SCRIPTS) >= 10, SCRIPTS


@pytest.mark.parametrize("path", BENCHMARKS, ids=[p.name for p in BENCHMARKS])
def test_every_benchmark_compiles(path: Path) -> None:
    compile(path.read_text(encoding="utf-8"), str(path), "exec")


@pytest.mark.slow
@pytest.mark.parametrize("path", WITH_OPTIONS, ids=[p.name for p in WITH_OPTIONS])
def test_every_benchmark_with_options_answers_help(path: Path) -> None:
    result = subprocess.run([sys.executable, str(path), "--help"], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    assert "usage:" in result.stdout
