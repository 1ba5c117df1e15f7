"""The documentation builds (``mkdocs build --strict``, no network), its links lead somewhere,
and the command-line reference names every option the parser has."""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
#: The pages whose relative links are checked.
PAGES = [ROOT / "README.md", ROOT / "CHANGELOG.md", *sorted(DOCS.rglob("*.md"))]
#: The modules the Python reference must document.
API_MODULES = ("geoloc", "geoloc.lie", "geoloc.geometry", "geoloc.datasets", "geoloc.evaluation",
               "geoloc.features", "geoloc.retrieval", "geoloc.matching")
#: Inline markdown links and images: [text](target) / ![alt](target), target without spaces.
LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")


def _without_code(text: str) -> str:
    """``text`` with fenced code blocks and inline code removed (links there are examples)."""
    text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    return re.sub(r"`[^`\n]*`", "", text)


def _relative_links(page: Path) -> list[str]:
    targets = LINK.findall(_without_code(page.read_text()))
    return [t for t in targets if not re.match(r"^[a-z][a-z0-9+.-]*:", t, re.I) and not t.startswith("#")]


def test_pages_have_links_to_check() -> None:
    assert _relative_links(ROOT / "README.md"), "the README links to no docs page"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_point_to_files(page: Path) -> None:
    missing = []
    for target in _relative_links(page):
        path = target.split("#", 1)[0].split("?", 1)[0]
        if path and not (page.parent / path).exists():
            missing.append(target)
    assert not missing, f"{page.relative_to(ROOT)} links to missing files: {missing}"


def test_docs_pages_stay_inside_docs() -> None:
    """mkdocs serves docs/ only: a link from a docs page out of it is dead on the site."""
    outside = []
    for page in DOCS.rglob("*.md"):
        for target in _relative_links(page):
            path = target.split("#", 1)[0]
            if path and DOCS.resolve() not in (page.parent / path).resolve().parents:
                outside.append(f"{page.relative_to(ROOT)} → {target}")
    assert not outside, outside


def _mkdocs_config() -> dict:
    import yaml

    config: dict = yaml.safe_load((ROOT / "mkdocs.yml").read_text())
    return config


def _nav_pages(entries: object) -> set[str]:
    """Every page path named in a mkdocs nav (nested lists of paths and {title: entry})."""
    if isinstance(entries, str):
        return {entries}
    if isinstance(entries, list):
        return set().union(*(_nav_pages(e) for e in entries))
    if isinstance(entries, dict):
        return set().union(*(_nav_pages(e) for e in entries.values()))
    return set()


def test_every_page_is_in_the_navigation() -> None:
    pages = {p.relative_to(DOCS).as_posix() for p in DOCS.glob("**/*.md")}
    nav = _nav_pages(_mkdocs_config()["nav"])
    assert pages <= nav, f"mkdocs.yml's nav lacks {sorted(pages - nav)}"
    assert nav <= pages, f"mkdocs.yml's nav names missing pages {sorted(nav - pages)}"


def test_the_strict_build_fails_on_broken_links_and_omitted_pages() -> None:
    """--strict turns warnings into failures: dead links and anchors, and pages left out of
    the nav, must be warnings (one `validation` block: a second one would replace the first)."""
    validation = _mkdocs_config()["validation"]
    assert validation["links"]["not_found"] == "warn"
    assert validation["links"]["anchors"] == "warn"
    assert validation["links"]["unrecognized_links"] == "warn"
    assert validation["nav"]["omitted_files"] == "warn"


def test_the_reference_documents_the_public_modules() -> None:
    text = (DOCS / "python-api.md").read_text()
    directives = set(re.findall(r"^::: ([\w.]+)\s*$", text, flags=re.M))
    assert set(API_MODULES) <= directives, sorted(set(API_MODULES) - directives)


def test_cli_reference_names_every_command_and_option() -> None:
    from geoloc.cli import build_parser

    parser, handlers = build_parser()
    text = (DOCS / "cli.md").read_text()
    sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    missing = []
    for name, command in sub.choices.items():  # type: ignore[attr-defined]
        if f"## geoloc {name}" not in text:
            missing.append(f"section for {name}")
        for action in command._actions:
            for option in action.option_strings:
                if option.startswith("--") and option != "--help" and option not in text:
                    missing.append(f"{name} {option}")
    assert set(sub.choices) == set(handlers)  # type: ignore[attr-defined]
    assert not missing, f"docs/cli.md lacks: {missing}"


def test_site_builds_strict(tmp_path: Path) -> None:
    for module in ("mkdocs", "mkdocstrings", "mkdocstrings_handlers.python"):
        if importlib.util.find_spec(module.split(".")[0]) is None or importlib.util.find_spec(module) is None:
            pytest.skip(f"{module} is not installed (python -m pip install -e '.[dev]' installs the doc tools)")
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=ROOT, capture_output=True, text=True, timeout=600,
    )
    assert proc.returncode == 0, f"mkdocs build --strict failed:\n{proc.stdout}\n{proc.stderr}"
    html = (tmp_path / "site" / "python-api.html").read_text()
    for name in ("geoloc.Map", "geoloc.Localizer", "geoloc.lie.se3_exp", "geoloc.geometry.solve_pnp"):
        assert f'id="{name}"' in html, f"the API reference has no entry for {name}"
