"""Running the `geoloc` command in a subprocess, for the CLI tests."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import geoloc


def checkout_env() -> dict[str, str]:
    """This process's environment with this checkout's package first on ``PYTHONPATH``: what a
    child Python process needs to import the geoloc under test."""
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(Path(geoloc.__file__).parents[1]), os.environ.get("PYTHONPATH", "")]))


def run_geoloc(*args: str, cwd: Path | None = None, timeout: float | None = None) -> subprocess.CompletedProcess[str]:
    """`python -m geoloc ARGS` with this checkout's package first on the path (``timeout``:
    seconds before subprocess.TimeoutExpired, for runs that could block)."""
    env = checkout_env()
    return subprocess.run(
        [sys.executable, "-m", "geoloc", *args], capture_output=True, text=True, cwd=cwd, env=env, timeout=timeout,
        errors="surrogateescape",
    )


def one_line_error(result: subprocess.CompletedProcess[str], *names: str) -> str:
    """The run failed with exit 2 and one error line (no traceback) naming ``names``."""
    assert result.returncode == 2, result.stdout + result.stderr
    assert "Traceback" not in result.stderr, result.stderr
    errors = [line for line in result.stderr.splitlines() if "error" in line]
    assert len(errors) == 1, result.stderr
    for name in names:
        assert name in errors[0], result.stderr
    return errors[0]
