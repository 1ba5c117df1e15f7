"""The adversarial worker: a long-lived process that runs one case at a time for the parent
(:mod:`harness`) and answers with its outcome, so that a case that aborts, segfaults or hangs
the interpreter takes down only this process — the parent sees the dead pipe or the timeout,
names the case, and starts a fresh worker.

A *case* is plain data (picklable without this module): an expression tree of tuples

* ``("call", target, args, kwargs)`` — ``target`` is a dotted path (``"geoloc.lie.so3_exp"``)
  or another expression; arguments may themselves be expressions;
* ``("attr", expr, name)`` — an attribute (a method) of an evaluated expression;
* ``("cached", key)`` — a fixture built once per worker (a small map, a trained model);
* ``("file", data_bytes, suffix)`` — a fresh temporary file holding ``data_bytes``; its path;
* ``("path", kind)`` — a path that cannot be used: ``"missing"``, ``"dir"``, ``"unwritable"``;

plus ``check`` (the name of the invariant the result must satisfy) and ``names`` (the argument
names an :class:`geoloc.InvalidInputError` may name). Protocol: 4-byte big-endian length +
pickle, both ways, on a private copy of fd 1 (the case's own prints go to stderr).
"""

from __future__ import annotations

import atexit
import contextlib
import importlib
import io
import os
import pickle
import shutil
import struct
import sys
import tempfile
import traceback
from pathlib import Path
from typing import Any

import numpy as np

_CACHE: dict[str, Any] = {}
_TMP = Path(tempfile.mkdtemp(prefix="geoloc-adv-"))
atexit.register(shutil.rmtree, _TMP, True)


def _resolve(path: str) -> Any:
    parts = path.split(".")
    for i in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:i]))
        except ImportError:
            continue
        for p in parts[i:]:
            obj = getattr(obj, p)
        return obj
    raise ImportError(path)


def _fresh(suffix: str = "") -> Path:
    fd, name = tempfile.mkstemp(dir=_TMP, suffix=suffix)
    os.close(fd)
    return Path(name)


def _cached(key: str) -> Any:
    if key not in _CACHE:
        import fixtures

        _CACHE[key] = getattr(fixtures, key)(_TMP)
    return _CACHE[key]


def evaluate(expr: Any) -> Any:
    if isinstance(expr, tuple) and expr and isinstance(expr[0], str):
        tag = expr[0]
        if tag == "call":
            _, target, args, kwargs = expr
            fn = _resolve(target) if isinstance(target, str) else evaluate(target)
            return fn(*[evaluate(a) for a in args], **{k: evaluate(v) for k, v in kwargs.items()})
        if tag == "attr":
            return getattr(evaluate(expr[1]), expr[2])
        if tag == "cached":
            return _cached(expr[1])
        if tag == "file":
            p = _fresh(expr[2])
            p.write_bytes(expr[1])
            return str(p)
        if tag == "path":
            kind = expr[1]
            if kind == "missingdir":
                return str(_TMP / "no-such-dir")
            if kind == "missing":
                return str(_TMP / "no-such-dir" / "x.geoloc")
            if kind == "dir":
                return str(_TMP)
            if kind == "unwritable":
                return "/proc/geoloc-adv/x.out"
            if kind == "fresh":
                return str(_fresh(".png"))
            if kind == "newdir":
                return str(_TMP / f"out-{len(os.listdir(_TMP))}")
        if tag == "tuple":
            return tuple(evaluate(a) for a in expr[1])
        if tag == "list":
            return [evaluate(a) for a in expr[1]]
        if tag == "lit":
            return expr[1]
    return expr


def _names_argument(message: str, names: list[str]) -> bool:
    return not names or any(n in message for n in names)


def run_case(case: dict[str, Any]) -> dict[str, Any]:
    import geoloc
    import invariants

    try:
        if case.get("files") is not None:
            return _run_file_case(case)
        if case.get("cli") is not None:
            return invariants.run_cli(case, evaluate)
        result = evaluate(case["expr"])
    except geoloc.FileAccessError as e:
        # A path that cannot be read or written (missing, a folder): the documented OSError,
        # its message names the path — a clean rejection, like an InvalidInputError.
        return {"kind": "rejected", "detail": str(e)[:200]}
    except geoloc.InvalidInputError as e:
        msg = str(e)
        # A FileFormatError names the file and the failed check (documented), not an argument.
        if not isinstance(e, geoloc.FileFormatError) and not _names_argument(msg, case.get("names", [])):
            return {"kind": "wrong-name", "detail": f"{type(e).__name__}: {msg[:300]}"}
        return {"kind": "rejected", "detail": msg[:200]}
    except Exception as e:  # noqa: BLE001 — classifying is the point
        return {"kind": "wrong-type", "detail": f"{type(e).__name__}: {str(e)[:300]}",
                "tb": traceback.format_exc()[-1500:]}
    except BaseException as e:  # PanicException derives from BaseException
        if type(e).__name__ == "PanicException":
            return {"kind": "panic", "detail": str(e)[:300]}
        raise
    try:
        problem = invariants.check(case.get("check", "any"), result, case)
    except Exception as e:  # noqa: BLE001
        problem = f"invariant check raised {type(e).__name__}: {e}"
    if problem:
        return {"kind": "invariant", "detail": problem[:300]}
    return {"kind": "ok", "detail": ""}


def _classify(e: BaseException, case: dict[str, Any]) -> dict[str, Any]:
    import geoloc

    if isinstance(e, geoloc.FileAccessError):
        return {"kind": "rejected", "detail": str(e)[:200]}
    if isinstance(e, geoloc.InvalidInputError):
        if not isinstance(e, geoloc.FileFormatError) and not _names_argument(str(e), case.get("names", [])):
            return {"kind": "wrong-name", "detail": f"{type(e).__name__}: {str(e)[:300]}"}
        return {"kind": "rejected", "detail": str(e)[:200]}
    if isinstance(e, MemoryError) and case["files"]["kind"] == "limited":
        return {"kind": "rejected", "detail": "MemoryError under RLIMIT_AS"}
    return {"kind": "wrong-type", "detail": f"{type(e).__name__}: {str(e)[:300]}", "tb": traceback.format_exc()[-1500:]}


def _run_file_case(case: dict[str, Any]) -> dict[str, Any]:
    """A file case (``file_cases.py``): run by ``files_runner``, then the CLI it asks for,
    then the file invariants (no half-written or replaced input)."""
    import files_runner
    import invariants

    try:
        out = files_runner.run(case, _TMP, _cached)
    except Exception as e:  # noqa: BLE001 — classifying is the point
        return _classify(e, case)
    if out.get("problem"):
        return {"kind": "invariant", "detail": out["problem"][:300]}
    if "error" in out:
        return _classify(out["error"], case)
    if "cli" in out:
        result = invariants.run_cli({"cli": out["cli"], "names": case.get("names", [])}, evaluate)
        if "unchanged" in out:
            path, before = out["unchanged"]
            if Path(path).read_bytes() != before:
                return {"kind": "invariant", "detail": f"the input {path!r} was changed by the command"}
        if out.get("must_fail") and result["kind"] == "ok":
            return {"kind": "invariant", "detail": "an output aliasing an input was accepted"}
        return result
    if "result" in out:
        problem = invariants.check(case.get("check", "any"), out["result"], case)
        if problem:
            return {"kind": "invariant", "detail": problem[:300]}
    return {"kind": "ok", "detail": ""}


def main() -> None:
    sys.path.insert(0, str(Path(__file__).parent))
    os.chdir(_TMP)  # relative paths a case writes ("3", "1.0") land in the worker's own folder
    proto = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    sys.stdout = io.TextIOWrapper(os.fdopen(1, "wb", closefd=False), write_through=True)
    stdin = sys.stdin.buffer
    with contextlib.suppress(Exception):
        import geoloc  # noqa: F401 — pay the import once, before the first case
    proto.write(b"RDY!")
    proto.flush()
    while True:
        head = stdin.read(4)
        if len(head) < 4:
            return
        case = pickle.loads(stdin.read(struct.unpack(">I", head)[0]))
        try:
            out = run_case(case)
        except BaseException as e:  # noqa: BLE001
            out = {"kind": "wrong-type", "detail": f"{type(e).__name__}: {e}"[:300]}
        data = pickle.dumps(out)
        proto.write(struct.pack(">I", len(data)) + data)
        proto.flush()


if __name__ == "__main__":
    np.seterr(all="ignore")
    main()
