"""Writing files atomically: a temp file in the same folder, fsync, then rename.

An interrupted write never leaves a half-written file and never destroys the previous one.
Missing parent folders are **not** created: a path in a folder that does not exist is a
mistake the user should hear about, not a directory tree silently made for them.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any, Callable, TextIO

from .exceptions import InvalidInputError

__all__ = ["check_output_path", "write_json_atomic", "write_text_atomic"]


def as_path(path: Any, name: str = "path") -> Path:
    """``path`` (a str or os.PathLike) as a Path; anything else (a number, an array, None, a
    string with a NUL byte) is an InvalidInputError naming ``name`` rather than a TypeError."""
    if not isinstance(path, (str, os.PathLike)) or "\x00" in os.fspath(path):
        raise InvalidInputError(f"{name}: expected a file path (str or os.PathLike), got {type(path).__name__}")
    return Path(path)


def check_output_path(path: str | os.PathLike[str], name: str = "path") -> Path:
    """``path`` as a Path whose parent folder exists and is writable; else InvalidInputError naming ``name``."""
    target = as_path(path, name)
    parent = target.parent
    if target.is_dir():
        raise InvalidInputError(f"{name}: {str(target)!r} is a folder, expected a file path")
    if not parent.is_dir():
        raise InvalidInputError(f"{name}: folder {str(parent)!r} does not exist (create it first)")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InvalidInputError(f"{name}: folder {str(parent)!r} is not writable")
    return target


def _write_atomic(path: str | os.PathLike[str], name: str, write: Callable[[TextIO], object]) -> None:
    target = check_output_path(path, name)
    try:
        fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.", suffix=".tmp")
    except OSError as e:
        raise InvalidInputError(f"{name}: cannot write to {str(target.parent)!r}: {e.strerror}") from None
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="\n") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, target)
    except OSError as e:
        Path(tmp).unlink(missing_ok=True)
        raise InvalidInputError(f"{name}: cannot write {str(target)!r} ({e.strerror or e})") from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_text_atomic(path: str | os.PathLike[str], text: str, name: str = "path") -> None:
    """Write ``text`` (UTF-8, '\\n' line ends) to ``path`` atomically."""
    _write_atomic(path, name, lambda f: f.write(text))


def write_json_atomic(path: str | os.PathLike[str], data: Any, name: str = "path") -> None:
    """Write ``data`` as indented JSON to ``path`` atomically (non-finite floats refused)."""
    text = json.dumps(data, indent=2, allow_nan=False) + "\n"
    write_text_atomic(path, text, name)
