"""Writing files atomically: a temp file in the same folder, then rename."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any


def write_json_atomic(path: str | os.PathLike[str], data: Any) -> None:
    """Write ``data`` as JSON to ``path``; an interrupted write leaves the old file intact."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(data, f, indent=2)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, target)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_text_atomic(path: str | os.PathLike[str], text: str, name: str = "path") -> None:
    """Write ``text`` to ``path`` atomically (temp file in the same folder, fsync, rename).

    Never creates missing parent folders: a missing or unwritable folder raises
    :class:`InvalidInputError` naming ``name`` and the path, and leaves no file behind.
    """
    from .exceptions import InvalidInputError

    target = Path(path)
    parent = target.parent
    if not parent.is_dir():
        raise InvalidInputError(f"{name}: folder {str(parent)!r} does not exist (cannot write {str(target)!r})")
    if target.is_dir():
        raise InvalidInputError(f"{name}: {str(target)!r} is a folder, expected a file path")
    try:
        fd, tmp = tempfile.mkstemp(dir=parent, prefix=f".{target.name}.", suffix=".tmp")
    except OSError as exc:
        raise InvalidInputError(f"{name}: cannot write to {str(parent)!r} ({exc.strerror})") from None
    try:
        with os.fdopen(fd, "w", encoding="utf-8", newline="\n") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, target)
    except OSError as exc:
        Path(tmp).unlink(missing_ok=True)
        raise InvalidInputError(f"{name}: cannot write {str(target)!r} ({exc.strerror})") from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
