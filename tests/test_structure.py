"""The shape of the package and of the suite: no import cycle in ``python/geoloc``, one way to
name a dataset and its frames on every command line (``geoloc train`` included), and the
``slow`` marker that splits off the fast subset (``python -m pytest -m "not slow"``)."""

from __future__ import annotations

import argparse
import ast
from pathlib import Path

import pytest

from geoloc.exceptions import InvalidInputError

PACKAGE = Path(__file__).resolve().parents[1] / "python" / "geoloc"


# --- the import graph ---------------------------------------------------------------------------


def _modules(root: Path) -> dict[str, tuple[Path, bool]]:
    """Every module of the package: dotted name → (file, is a package ``__init__``). A compiled
    extension counts through its stub (``_core.pyi``)."""
    found: dict[str, tuple[Path, bool]] = {}
    for f in sorted(root.rglob("*.py*")):
        if f.suffix not in (".py", ".pyi") or (f.suffix == ".pyi" and f.with_suffix(".py").exists()):
            continue
        parts = list(f.relative_to(root.parent).with_suffix("").parts)
        is_package = parts[-1] == "__init__"
        found[".".join(parts[:-1] if is_package else parts)] = (f, is_package)
    return found


def import_graph(root: Path = PACKAGE) -> dict[str, set[str]]:
    """Module → the package's modules it imports.

    Every import statement counts wherever it is — at module level, inside a function (a lazy
    import defers the cycle to run time but is a dependency all the same) and under
    ``if TYPE_CHECKING:``. ``from X import name`` is an edge to ``X.name`` where that is a
    module, else to ``X``; importing a submodule is not counted as importing its parent
    package (Python runs the parent's ``__init__`` first for every module alike)."""
    modules = _modules(root)
    top = root.name
    graph: dict[str, set[str]] = {}
    for name, (path, is_package) in modules.items():
        here = name.split(".") if is_package else name.split(".")[:-1]
        targets: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            if isinstance(node, ast.Import):
                targets.update(a.name for a in node.names if a.name.split(".")[0] == top)
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = here[: len(here) - (node.level - 1)]
                    source = ".".join(base + ([node.module] if node.module else []))
                else:
                    source = node.module or ""
                if source.split(".")[0] != top:
                    continue
                for alias in node.names:
                    sub = f"{source}.{alias.name}"
                    targets.add(sub if sub in modules else source)
        graph[name] = {t for t in targets if t in modules and t != name}
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as [a, b, …, a], or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state and (cycle := visit(nxt)) is not None:
                return cycle
        path.pop()
        state[node] = 2
        return None

    for start in sorted(graph):
        if start not in state and (cycle := visit(start)) is not None:
            return cycle
    return None


def test_the_package_has_no_import_cycle() -> None:
    graph = import_graph()
    assert {"geoloc", "geoloc.cli", "geoloc.datasets.sequence", "geoloc.training.command"} <= set(graph)
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle or [])


def test_the_cycle_finder_sees_lazy_and_relative_imports(tmp_path: Path) -> None:
    pkg = tmp_path / "geoloc"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("from . import a\n")
    (pkg / "a.py").write_text("from .sub import b\n")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "sub" / "b.py").write_text("def f():\n    from ..a import g\n")
    graph = import_graph(pkg)
    assert graph["geoloc"] == {"geoloc.a"} and graph["geoloc.a"] == {"geoloc.sub.b"}
    assert find_cycle(graph) == ["geoloc.a", "geoloc.sub.b", "geoloc.a"]
    (pkg / "sub" / "b.py").write_text("import numpy\nfrom geoloc.sub import __doc__\n")
    assert find_cycle(import_graph(pkg)) is None


# --- one way to name a dataset and its frames ----------------------------------------------------


def _train_args(*argv: str) -> argparse.Namespace:
    from geoloc.cli import build_parser

    parser, _ = build_parser()
    return parser.parse_args(["train", *argv, "--out", "m.onnx"])


def test_train_reads_frames_like_every_command() -> None:
    from geoloc.commands._common import FrameRange
    from geoloc.training.command import load_frames

    args = _train_args("--format", "synthetic", "--synthetic-frames", "40", "--frames", "10:40:3")
    assert args.frames == FrameRange(10, 40, 3)
    dataset, frames = load_frames(args)
    assert len(dataset) == 40 and frames.indices.tolist() == list(range(10, 40, 3))
    with pytest.raises(InvalidInputError, match="^--frames: 10:400 is outside"):
        load_frames(_train_args("--format", "synthetic", "--synthetic-frames", "40", "--frames", "10:400"))


def test_train_keeps_the_old_spelling_for_one_release() -> None:
    """``--dataset synthetic --train A:B --stride K`` is ``--frames A:B:K`` of a room of B frames,
    as it was; a deprecation line is printed when the run starts."""
    from geoloc.training.command import load_frames

    dataset, frames = load_frames(_train_args("--dataset", "synthetic", "--train", "0:30", "--stride", "5"))
    assert len(dataset) == 30 and frames.indices.tolist() == [0, 5, 10, 15, 20, 25]
    with pytest.raises(InvalidInputError, match="^--train: replaced by --frames"):
        load_frames(_train_args("--dataset", "synthetic", "--train", "0:30", "--frames", "0:30"))


# --- the test tiers ------------------------------------------------------------------------------


def test_the_slow_marker_is_registered(pytestconfig: pytest.Config) -> None:
    """``-m "not slow"`` selects the fast subset only while ``slow`` is a registered marker
    (with --strict-markers an unregistered one fails collection)."""
    names = [line.split(":")[0].strip() for line in pytestconfig.getini("markers")]
    assert "slow" in names
