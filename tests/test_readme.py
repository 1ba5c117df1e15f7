"""The README stays true and short: its Python quick start runs, .ci/run runs its test command,
and it (with the docs pages) carries no issue numbers, commit hashes or private design notes."""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = (ROOT / "README.md").read_text()
#: The README is the front door, not the results log.
MAX_README_LINES = 200


def _blocks(lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", README, flags=re.S)


def test_python_example_runs(tmp_path: Path) -> None:
    blocks = _blocks("python")
    assert blocks, "README has no python example"
    cwd = os.getcwd()
    os.chdir(tmp_path)  # whatever an example writes lands here
    try:
        for code in blocks:
            exec(compile(code, "README.md", "exec"), {"__name__": "__readme__"})
    finally:
        os.chdir(cwd)


def test_quick_start_builds_a_map_and_localizes() -> None:
    code = "\n".join(_blocks("python"))
    for call in ("geoloc.datasets.synthetic_room(", "geoloc.Map.build(", "geoloc.Localizer(", ".localize("):
        assert call in code, f"the README's quick start no longer calls {call}"


def test_ci_runs_the_readme_test_command() -> None:
    commands = [b.strip() for b in _blocks("bash")]
    test_command = next(c for c in commands if "pytest" in c)
    ci = (ROOT / ".ci" / "run").read_text().strip().splitlines()
    assert ci[-1] == test_command


def test_install_command_runs_the_main_job() -> None:
    commands = [b.strip() for b in _blocks("bash")]
    assert commands[0] == "python -m pip install . && geoloc demo"


def test_readme_is_short() -> None:
    n = len(README.splitlines())
    assert n <= MAX_README_LINES, f"README.md has {n} lines (at most {MAX_README_LINES}): measured results go to docs/reports/"


#: What a reader of the README or the docs cannot follow: a tracker's issue number, a commit
#: hash, a design note that is not in the repository. The changelog and the recorded
#: reports (docs/reports/) keep their history and are not checked.
FORBIDDEN = {
    "an issue number": re.compile(r"\bissues? \d+|(?<![\w&])#\d+\b", re.I),
    "a commit hash": re.compile(r"(?<![\w./-])(?=[0-9a-f]*[a-f])(?=[0-9a-f]*\d)[0-9a-f]{7,40}(?![\w-])"),
    "DESIGN.md": re.compile(r"DESIGN\.md"),
}


def _user_pages() -> list[Path]:
    docs = ROOT / "docs"
    pages = [ROOT / "README.md"] + sorted(p for p in docs.rglob("*.md") if docs / "reports" not in p.parents)
    return pages


@pytest.mark.parametrize("page", _user_pages(), ids=lambda p: str(p.relative_to(ROOT)))
def test_pages_speak_to_users(page: Path) -> None:
    text = page.read_text()
    found = [
        f"{what} at line {text.count(chr(10), 0, m.start()) + 1}: {m.group(0)!r}"
        for what, pattern in FORBIDDEN.items()
        for m in pattern.finditer(text)
    ]
    assert not found, f"{page.relative_to(ROOT)} has " + "; ".join(found)


def test_the_checks_catch_what_they_should() -> None:
    def caught(text: str) -> bool:
        return any(p.search(text) for p in FORBIDDEN.values())

    for bad in ("see issue 13", "Issues 8 and 13", "fixed in #24", "main at 076ef05", "commit a199063^", "DESIGN.md §1"):
        assert caught(bad), bad
    for fine in ("7-Scenes", "0–99", "1e-6", "fnv1a64:<16 hex>", "#define", "| 1000000 |", "se3_exp", "a7b", "sha256"):
        assert not caught(fine), fine
