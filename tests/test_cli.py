"""The ``geoloc`` command line, run as a user runs it (a subprocess)."""

from __future__ import annotations

import subprocess
import sys

import geoloc


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "geoloc", *args], capture_output=True, text=True)


def test_version() -> None:
    result = _run("--version")
    assert result.returncode == 0
    assert result.stdout.strip() == f"geoloc {geoloc.__version__}"


def test_selfcheck_passes_and_reports_every_check() -> None:
    result = _run("selfcheck", "--samples", "10")
    assert result.returncode == 0, result.stdout + result.stderr
    assert "all checks passed" in result.stdout
    assert result.stdout.count(" ok") == 9
    assert "se3_exp on 200000 twists" in result.stdout


def test_selfcheck_fails_when_a_check_fails(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    from geoloc import selfcheck

    monkeypatch.setattr(selfcheck, "EXP_LOG_TOL", 0.0)  # no implementation is exact
    assert selfcheck.main(per_regime=5) == 1


def test_no_command_prints_help_and_fails() -> None:
    result = _run()
    assert result.returncode == 2
    assert "selfcheck" in result.stderr


def test_bad_option_values_are_refused() -> None:
    result = _run("selfcheck", "--samples", "0")
    assert result.returncode == 2
    assert "--samples must be at least 1" in result.stderr
