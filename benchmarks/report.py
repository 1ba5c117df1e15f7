"""Render a benchmark's ``--json`` output as a markdown report with its provenance.

Two ways in:

    python benchmarks/report.py run --out docs/reports/latency-run.md -- \\
        python benchmarks/latency.py --passes 1
    python benchmarks/report.py render result.json --out docs/reports/x.md \\
        --command "python benchmarks/x.py --json result.json" [--measured "2026-11-25, 2 cores"]

``run`` runs the benchmark itself (appending ``--json FILE`` to its command line), so the
header it writes is what happened: the date and duration, the git commit (and the tracked
files that differed from it), the machine (CPU model, cores usable, memory, OS, Python and
library versions, ``GEOLOC_*`` settings, the load average) and the exact command. The page holds that
header, the benchmark's printed output (its own tables) and the JSON rendered as tables
(per-frame arrays are summarized by their length, not printed). ``render`` does the same for
a JSON file made earlier; as this script cannot know where that ran, the header says so
unless ``--measured`` tells it.

The benchmarks with ``--json``: calibration, geometry, honesty, label_adjustment,
label_consistency, latency, lie, localizer, novel_views, retrieval, retrieval_networks, robot
(label_runs reads calibration's), and ``geoloc montecarlo``. Not a test.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import platform
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
#: Lists longer than this are summarized by their length.
MAX_INLINE = 12
#: Rows of a table of records, at most.
MAX_ROWS = 60
#: Lines of the benchmark's printed output kept (the last ones).
MAX_OUTPUT_LINES = 300
#: Nesting depth rendered; deeper values are summarized.
MAX_DEPTH = 4


# ---------------------------------------------------------------- provenance


def _git(*args: str) -> str | None:
    try:
        out = subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, check=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.rstrip("\n")


def commit() -> str:
    """The checked-out commit, and the tracked files that differ from it, if any."""
    head = (_git("rev-parse", "HEAD") or "").strip() or None
    if head is None:
        return "unknown (not a git checkout)"
    dirty = [line[3:] for line in (_git("status", "--porcelain", "--untracked-files=no") or "").splitlines()]
    subject = _git("log", "-1", "--format=%cd %s", "--date=short") or ""
    text = f"`{head}` ({subject[:80]})"
    if dirty:
        shown = ", ".join(dirty[:8]) + (f" and {len(dirty) - 8} more" if len(dirty) > 8 else "")
        text += f" + uncommitted changes to {shown}"
    return text


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _memory() -> str:
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                return f"{int(line.split()[1]) / 2**20:.1f} GiB"
    except (OSError, ValueError, IndexError):
        pass
    return "unknown"


def _versions() -> str:
    parts = [f"Python {platform.python_version()}"]
    for name in ("numpy", "cv2", "geoloc"):
        try:
            module = __import__(name)
            parts.append(f"{name} {getattr(module, '__version__', '?')}")
        except Exception:  # a missing or broken package is reported, not fatal
            parts.append(f"{name} not importable")
    for name in ("poselib", "pycolmap", "onnxruntime", "torch"):  # peers and runtimes, when installed
        try:
            module = __import__(name)
        except Exception:
            continue
        parts.append(f"{name} {getattr(module, '__version__', '?')}")
    return ", ".join(parts)


def machine() -> dict[str, str]:
    """What the numbers were measured on."""
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    env = {k: v for k, v in os.environ.items() if k.startswith("GEOLOC_") or k == "PYTHONPATH"}
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg()) if hasattr(os, "getloadavg") else "unknown"
    return {
        "CPU": f"{_cpu_model()}, {usable} of {os.cpu_count()} cores usable",
        "memory": _memory(),
        "OS": platform.platform(),
        "software": _versions(),
        "settings": ", ".join(f"{k}={v}" for k, v in sorted(env.items())) or "no GEOLOC_* variables set",
        "load": f"{load} (1, 5, 15 min load average at the start: other work on the machine slows timings)",
    }


# ---------------------------------------------------------------- JSON → markdown


def _is_scalar(x: Any) -> bool:
    return x is None or isinstance(x, (str, int, float, bool))


def _fmt(x: Any) -> str:
    if x is None:
        return "—"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, float):
        if x != x:
            return "nan"
        if x == 0 or 1e-3 <= abs(x) < 1e6:
            return f"{x:.4g}"
        return f"{x:.3e}"
    if isinstance(x, list):
        if len(x) <= MAX_INLINE and all(_is_scalar(v) for v in x):
            return "[" + ", ".join(_fmt(v) for v in x) + "]"
        return f"({len(x)} values)"
    if isinstance(x, dict):
        return f"({len(x)} entries)"
    return str(x).replace("|", "\\|").replace("\n", " ")


def _cell(x: Any) -> str:
    return _fmt(x) if (_is_scalar(x) or isinstance(x, list)) else f"({len(x)} entries)"


def _table(header: list[str], rows: list[list[str]]) -> list[str]:
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(r) + " |" for r in rows]
    return out


def _inline_keys(d: dict[str, Any]) -> list[str]:
    """The keys of ``d`` whose values fit in a table cell."""
    return [k for k, v in d.items() if _is_scalar(v) or (isinstance(v, list) and len(v) <= MAX_INLINE and all(_is_scalar(x) for x in v))]


def render_json(value: Any, title: str = "", depth: int = 0) -> list[str]:
    """Markdown for one JSON value: scalars as a key/value table, a dict of like dicts as one
    table (a row per key), a list of records as a table of their scalar fields; deeper
    structure as subsections, summarized below ``MAX_DEPTH``."""
    heading = "#" * min(6, depth + 2) + " " + title if title else ""
    lines: list[str] = [heading, ""] if heading else []
    if _is_scalar(value) or (isinstance(value, list) and all(_is_scalar(v) for v in value)):
        return lines + [_fmt(value), ""]
    if isinstance(value, list):
        records = [v for v in value if isinstance(v, dict)]
        if len(records) == len(value):
            keys = list(dict.fromkeys(k for r in records for k in _inline_keys(r)))
            rows = [[_cell(r.get(k)) for k in keys] for r in records[:MAX_ROWS]]
            more = [f"({len(records) - MAX_ROWS} more rows not shown)", ""] if len(records) > MAX_ROWS else []
            return lines + _table(keys, rows) + [""] + more
        return lines + [f"({len(value)} values)", ""]
    assert isinstance(value, dict)
    if depth >= MAX_DEPTH:
        return lines + [f"({len(value)} entries, not rendered)", ""]
    simple = _inline_keys(value)
    if simple:
        lines += _table(["key", "value"], [[str(k), _cell(value[k])] for k in simple]) + [""]
    nested = {k: v for k, v in value.items() if k not in simple}
    dicts = {k: v for k, v in nested.items() if isinstance(v, dict)}
    columns = list(dict.fromkeys(c for v in dicts.values() for c in _inline_keys(v)))
    # a dict of dicts that share their scalar fields: one table, a row per entry
    common = set(columns).intersection(*(_inline_keys(v) for v in dicts.values())) if dicts else set()
    if len(dicts) >= 2 and columns and 2 * len(common) >= len(columns):
        lines += _table([""] + columns, [[str(k)] + [_cell(v.get(c)) for c in columns] for k, v in dicts.items()]) + [""]
        for k, v in dicts.items():
            inline = _inline_keys(v)
            rest = {c: x for c, x in v.items() if c not in inline}
            if rest:
                lines += render_json(rest, f"{title} / {k}" if title else str(k), depth + 1)
        nested = {k: v for k, v in nested.items() if k not in dicts}
    for k, v in nested.items():
        lines += render_json(v, f"{title} / {k}" if title else str(k), depth + 1)
    return lines


# ---------------------------------------------------------------- pages


def page(
    title: str, summary: str, provenance: list[tuple[str, str]], output: str | None, result: Any
) -> str:
    lines = [f"# {title}", ""]
    if summary:
        lines += [summary, ""]
    lines += _table(["", ""], [[k, v] for k, v in provenance]) + [""]
    if output:
        kept = output.rstrip("\n").splitlines()[-MAX_OUTPUT_LINES:]
        lines += ["## The benchmark's output", "", "```text", *kept, "```", ""]
    lines += ["## The `--json` result", ""]
    lines += render_json(result)
    while lines and not lines[-1]:
        lines.pop()
    return "\n".join(lines) + "\n"


def _docstring_summary(command: list[str]) -> str:
    """The first line of the benchmark script's docstring, when the command runs one."""
    for word in command:
        script = Path(word) if Path(word).is_absolute() else ROOT / word
        if word.endswith(".py") and script.is_file():
            import ast

            doc = ast.get_docstring(ast.parse(script.read_text()))
            if doc:
                return " ".join(doc.strip().split("\n\n")[0].split())
    return ""


def _title(command: list[str]) -> str:
    scripts = [Path(w).stem for w in command if w.endswith(".py")]
    return f"Report: {scripts[0].replace('_', ' ')}" if scripts else "Report"


def run(args: argparse.Namespace) -> int:
    command = list(args.command)
    if command and command[0] == "--":
        command = command[1:]
    if not command:
        raise SystemExit("report.py run: give the benchmark's command after --")
    if "--json" in command:
        raise SystemExit("report.py run: leave --json out; this script adds it")
    where = [("commit", commit()), *machine().items()]  # before the run: what it ran on
    with tempfile.TemporaryDirectory() as folder:
        result_path = Path(folder) / "result.json"
        started = dt.datetime.now(dt.timezone.utc)
        start = time.perf_counter()
        proc = subprocess.run([*command, "--json", str(result_path)], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        seconds = time.perf_counter() - start
        sys.stdout.write(proc.stdout)
        if proc.returncode != 0:
            print(f"report.py: the benchmark exited with status {proc.returncode}; no report written", file=sys.stderr)
            return proc.returncode
        if not result_path.is_file():
            print("report.py: the benchmark wrote no --json result (missing data?); no report written", file=sys.stderr)
            return 1
        result = json.loads(result_path.read_text())
    provenance = [
        ("date", f"{started:%Y-%m-%d %H:%M} UTC, {seconds:.0f} s"),
        *where,
        ("command", f"`{shlex.join(command)} --json FILE`"),
        ("page", f"`python benchmarks/report.py run --out {args.out} -- {shlex.join(command)}`"),
    ]
    text = page(args.title or _title(command), _docstring_summary(command), provenance, proc.stdout, result)
    _write(Path(args.out), text)
    return 0


def render(args: argparse.Namespace) -> int:
    result = json.loads(Path(args.json).read_text())
    measured = args.measured or "not recorded: rendered from a result file made earlier"
    provenance = [
        ("measured", measured),
        ("command", f"`{args.command}`"),
        ("rendered", f"{dt.datetime.now(dt.timezone.utc):%Y-%m-%d %H:%M} UTC at commit {commit()}"),
    ]
    words = shlex.split(args.command)
    text = page(args.title or _title(words), _docstring_summary(words), provenance, None, result)
    _write(Path(args.out), text)
    return 0


def _write(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(text)
    tmp.replace(path)
    print(f"wrote {path}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="how", required=True)
    r = sub.add_parser("run", help="run a benchmark with --json and write its report")
    r.add_argument("--out", required=True, help="the markdown page to write (e.g. docs/reports/latency-run.md)")
    r.add_argument("--title", help="the page's title (default: from the script's name)")
    r.add_argument("command", nargs=argparse.REMAINDER, help="-- then the benchmark's command line, without --json")
    g = sub.add_parser("render", help="render a --json file made earlier")
    g.add_argument("json", help="the benchmark's --json output")
    g.add_argument("--out", required=True, help="the markdown page to write")
    g.add_argument("--command", required=True, help="the exact command that made the file")
    g.add_argument("--measured", help="when and where it was measured (date, commit, machine), if known")
    g.add_argument("--title", help="the page's title (default: from the script's name)")
    args = ap.parse_args(argv)
    return run(args) if args.how == "run" else render(args)


if __name__ == "__main__":
    sys.exit(main())
