"""The ``geoloc`` command line, run as a user runs it (a subprocess)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

import geoloc
from geoloc.datasets.synthetic import MAX_FRAMES as SYNTHETIC_MAX_FRAMES
from geoloc.montecarlo import MAX_TRIALS


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


@pytest.mark.parametrize(
    ("value", "warned"),
    [("abc", "is not a thread count"), ("0", "is not a thread count"), ("100000", "is above 256"), ("2", None), ("", None)],
)
def test_a_thread_count_the_core_ignores_or_caps_is_named(value: str, warned: str | None) -> None:
    """GEOLOC_NUM_THREADS that is not a count ≥ 1 (ignored) or above the cap (capped): one
    warning line naming it, and the command still runs; a good or empty one: no warning."""
    env = {**os.environ, "GEOLOC_NUM_THREADS": value}
    result = subprocess.run([sys.executable, "-m", "geoloc", "selfcheck", "--samples", "2"],
                            capture_output=True, text=True, env=env)
    assert result.returncode == 0, result.stderr
    lines = result.stderr.splitlines()
    if warned is None:
        assert lines == []
    else:
        assert len(lines) == 1 and lines[0].startswith("geoloc selfcheck: warning: GEOLOC_NUM_THREADS="), lines
        assert warned in lines[0]


def test_no_command_prints_help_and_fails() -> None:
    result = _run()
    assert result.returncode == 2
    assert "selfcheck" in result.stderr


def test_bad_option_values_are_refused() -> None:
    result = _run("selfcheck", "--samples", "0")
    assert result.returncode == 2
    assert "argument --samples: must be between 1 and" in result.stderr


@pytest.mark.parametrize(
    ("args", "names"),
    [
        (("montecarlo", "--trials", "1000000000"), "--trials"),
        (("montecarlo", "--trials", "ten"), "--trials"),
        (("montecarlo", "--seed", "-1"), "--seed"),
        (("montecarlo", "--seed", str(2**70)), "--seed"),
        (("selfcheck", "--samples", "1000000000"), "--samples"),
        (("montecarlo", "--covariance", "magic"), "--covariance"),
        (("montecarlo", "--json", "-"), "--json"),  # it wrote a file named '-' where localize writes to stdout
        # one past the function's own bound: refused by the option, not later by the argument
        (("montecarlo", "--trials", str(MAX_TRIALS + 1)), "--trials"),
        (("demo", "--frames", str(SYNTHETIC_MAX_FRAMES + 1)), "--frames"),
        (("evaluate", "--format", "synthetic", "--synthetic-frames", str(SYNTHETIC_MAX_FRAMES + 1)),
         "--synthetic-frames"),
    ],
)
def test_out_of_range_options_are_one_line_naming_the_option(args: tuple[str, ...], names: str) -> None:
    result = _run(*args)
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    error_lines = [line for line in result.stderr.splitlines() if "error" in line]
    assert len(error_lines) == 1 and names in error_lines[0], result.stderr


def test_an_unknown_option_of_a_command_is_refused_with_that_commands_usage() -> None:
    """It printed the top level's usage and "geoloc: error: unrecognized arguments"."""
    result = _run("evaluate", "--format", "synthetic", "--dim", "3")
    assert result.returncode == 2
    assert "usage: geoloc evaluate" in result.stderr
    assert result.stderr.splitlines()[-1] == "geoloc evaluate: error: unrecognized arguments: --dim 3"
    top = _run("--dim", "3")
    assert top.returncode == 2 and "usage: geoloc [-h]" in top.stderr


def test_output_in_a_missing_folder_is_refused_and_not_created(tmp_path: Path) -> None:
    missing = tmp_path / "no" / "such" / "dir"
    result = _run("montecarlo", "--trials", "1", "--json", str(missing / "x.json"))
    assert result.returncode == 2
    assert "Traceback" not in result.stderr and "--json" in result.stderr and "does not exist" in result.stderr
    assert not (tmp_path / "no").exists()
    folder = _run("montecarlo", "--trials", "1", "--json", str(tmp_path))
    assert folder.returncode == 2 and "is a folder" in folder.stderr


def _failing_handler(error: Exception):  # type: ignore[no-untyped-def]
    def handler(args):  # type: ignore[no-untyped-def]
        raise error

    return handler


@pytest.mark.parametrize(
    ("error", "status", "text"),
    [
        (geoloc.InvalidInputError("dataset: folder 'x' does not exist"), 2, "error: dataset: folder 'x' does not exist"),
        (OSError(28, "No space left on device"), 1, "No space left on device"),
        (RuntimeError("boom"), 1, "internal error: RuntimeError: boom"),
    ],
)
def test_failures_are_one_line_unless_debug(monkeypatch, capsys, error, status, text) -> None:  # type: ignore[no-untyped-def]
    from geoloc import cli

    original = cli.build_parser

    def patched():  # type: ignore[no-untyped-def]
        parser, handlers = original()
        handlers["selfcheck"] = _failing_handler(error)
        return parser, handlers

    monkeypatch.setattr(cli, "build_parser", patched)
    assert cli.main(["selfcheck"]) == status
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and text in err and "Traceback" not in err
    assert cli.main(["--debug", "selfcheck"]) == status
    assert "Traceback" in capsys.readouterr().err
