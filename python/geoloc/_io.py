"""Reading input files safely and writing output files atomically.

Inputs: :func:`check_input_file` / :func:`read_bytes` accept only a regular file (a FIFO, a
socket, a device or a folder is named as such and never opened, so a FIFO cannot block a
run) and name the argument and the path (its ``repr``, so odd bytes show). Paths go to C
libraries only as bytes read by Python: OpenCV gets :func:`read_bytes`' data, never a path.

Outputs: a temp file in the same folder (a unique ``mkstemp`` name), fsync, then rename, so an
interrupted write never leaves a half-written file and never destroys the previous one. The
new file keeps the permissions of the one it replaces; a new file gets those of a plain
``open(path, "w")`` (0666 less the umask), as the core's writer gives them. An output that is
a symlink is written through (the file it points to is replaced, the link kept); a dangling
one is refused.
Missing parent folders are **not** created: a path in a folder that does not exist is a
mistake the user should hear about, not a directory tree silently made for them. A path
ending in a separator means a folder and is refused as a file to write. :func:`refuse_alias`
refuses an output that is the same file as one of the inputs (same path, ``./`` alias,
symlink or hard link).
"""

from __future__ import annotations

import errno
import json
import os
import stat
import tempfile
from collections.abc import Iterable
from pathlib import Path
from typing import Any, Callable, TextIO

from .exceptions import FileAccessError, InvalidInputError

__all__ = [
    "check_input_file",
    "check_output_path",
    "file_identity",
    "read_bytes",
    "refuse_alias",
    "refuse_shared_outputs",
    "shown",
    "special_kind",
    "write_bytes_atomic",
    "write_json_atomic",
    "write_text_atomic",
]

#: The longest temp-name stem taken from the target's name (the temp name must fit NAME_MAX too).
_TEMP_STEM = 64
_KINDS = (
    (stat.S_ISDIR, "a folder"),
    (stat.S_ISFIFO, "a FIFO"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
)


def as_path(path: Any, name: str = "path") -> Path:
    """``path`` (a str or os.PathLike) as a Path; anything else (a number, an array, None, a
    string with a NUL byte) is an InvalidInputError naming ``name`` rather than a TypeError."""
    if not isinstance(path, (str, os.PathLike)) or not isinstance(os.fspath(path), str):
        raise InvalidInputError(f"{name}: expected a file path (str or os.PathLike), got {type(path).__name__}")
    if "\x00" in os.fspath(path):
        raise InvalidInputError(f"{name}: {os.fspath(path)!r} contains a NUL byte, which no file name can hold")
    return Path(path)


def shown(path: Any) -> str:
    """``path`` as printable text: bytes that are not UTF-8 (surrogate escapes) as ``\\xNN``,
    so printing a path never raises UnicodeEncodeError."""
    text = os.fspath(path) if isinstance(path, (str, os.PathLike)) else str(path)
    if isinstance(text, bytes):
        text = os.fsdecode(text)
    return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


def _kind(mode: int) -> str:
    return next((what for test, what in _KINDS if test(mode)), "not a regular file")


def _not_a_folder_above(folder: Path) -> tuple[Path, str] | None:
    """The nearest existing path among ``folder`` and its parents, with what it is, when it
    is not a folder (a file in the way of a path to write); None otherwise."""
    for p in (folder, *folder.parents):
        try:
            mode = os.stat(p).st_mode
        except OSError:
            continue
        return None if stat.S_ISDIR(mode) else (p, "a regular file" if stat.S_ISREG(mode) else _kind(mode))
    return None


def _reason(e: OSError) -> str:
    if e.errno == errno.ENAMETOOLONG:
        return "its name is too long for the file system"
    return e.strerror or str(e)


def special_kind(path: Any) -> str | None:
    """What ``path`` is when it exists and is not a regular file ("a FIFO", "a folder" …);
    None for a regular file or a path that cannot be examined (the reader then says why)."""
    try:
        mode = os.stat(path).st_mode
    except (OSError, ValueError):
        return None
    return None if stat.S_ISREG(mode) else _kind(mode)


def check_input_file(path: Any, name: str = "path", error: type[InvalidInputError] = FileAccessError) -> Path:
    """``path`` as a Path when it is an existing regular file (symlinks followed); else
    ``error`` naming ``name``, the path, and what it is (missing, a folder, a FIFO …)."""
    target = as_path(path, name)
    try:
        mode = os.stat(target).st_mode
    except FileNotFoundError:
        raise error(f"{name}: file {str(target)!r} does not exist") from None
    except OSError as e:
        raise error(f"{name}: cannot read {str(target)!r} ({_reason(e)})") from None
    if not stat.S_ISREG(mode):
        raise error(f"{name}: {str(target)!r} is {_kind(mode)}, not a regular file")
    return target


def read_bytes(path: Any, name: str = "path", error: type[InvalidInputError] = FileAccessError) -> bytes:
    """The contents of the regular file ``path`` (see :func:`check_input_file`). Opened
    non-blocking and checked again on the open descriptor, so a FIFO swapped in after the
    check cannot block the read."""
    target = check_input_file(path, name, error)
    try:
        fd = os.open(target, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except OSError as e:
        raise error(f"{name}: cannot read {str(target)!r} ({_reason(e)})") from None
    with os.fdopen(fd, "rb") as f:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            raise error(f"{name}: {str(target)!r} is {_kind(mode)}, not a regular file")
        try:
            return f.read()
        except OSError as e:
            raise error(f"{name}: cannot read {str(target)!r} ({_reason(e)})") from None


def check_output_path(path: Any, name: str = "path") -> Path:
    """``path`` as a Path to a file whose parent folder exists and is writable; else
    FileAccessError naming ``name``. A path ending in a separator names a folder and is
    refused; so is a name longer than the file system allows, and a symlink to nothing."""
    target = as_path(path, name)
    text = os.fspath(path)
    if text.endswith(os.sep) or (os.altsep is not None and text.endswith(os.altsep)):
        raise FileAccessError(f"{name}: {text!r} ends in {text[-1]!r}, which names a folder; expected a file path")
    parent = target.parent
    try:
        name_max = os.pathconf(parent, "PC_NAME_MAX")
    except (OSError, ValueError):
        name_max = 255
    size = len(os.fsencode(target.name))
    if size > name_max:
        raise FileAccessError(f"{name}: the file name {target.name[:40]!r}… is {size} bytes; the folder allows {name_max}")
    if os.path.islink(target) and not os.path.exists(target):
        raise FileAccessError(
            f"{name}: {str(target)!r} is a symlink to a file that does not exist (not written through a dangling link)"
        )
    try:
        mode = os.stat(target).st_mode
    except FileNotFoundError:
        mode = None
    except OSError as e:
        if e.errno != errno.ENOTDIR:
            raise FileAccessError(f"{name}: cannot write {str(target)!r} ({_reason(e)})") from None
        mode = None
    if mode is not None and stat.S_ISDIR(mode):
        raise FileAccessError(f"{name}: {str(target)!r} is a folder, expected a file path")
    if mode is not None and not stat.S_ISREG(mode):
        raise FileAccessError(f"{name}: {str(target)!r} is {_kind(mode)}, not a regular file to replace")
    if not parent.is_dir():
        blocking = _not_a_folder_above(parent)
        if blocking is not None:
            where, what = blocking
            raise FileAccessError(f"{name}: {str(where)!r} is {what}, not a folder: cannot write {str(target)!r}")
        raise FileAccessError(f"{name}: folder {str(parent)!r} does not exist (create it first)")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise FileAccessError(f"{name}: folder {str(parent)!r} is not writable")
    return target


def file_identity(path: Any) -> tuple[int, int] | None:
    """(device, inode) of the file at ``path`` (symlinks followed), None when there is none:
    two paths of one file share it, and a replaced file gets another."""
    try:
        st = os.stat(path)
    except (OSError, ValueError):
        return None
    return (st.st_dev, st.st_ino)


def refuse_alias(output: Any, output_name: str, inputs: Iterable[tuple[str, Any]]) -> None:
    """InvalidInputError naming ``output_name`` and the input when the file ``output`` would
    be written to is one of ``inputs`` (``(name, path)`` pairs; None paths are skipped): the
    same resolved path, or the same device and inode (a symlink or a hard link). An output
    that does not exist yet is never the same file as an input."""
    if output is None:
        return
    out = file_identity(output)
    if out is None:
        return
    real = os.path.realpath(output)
    for name, path in inputs:
        if path is None:
            continue
        if file_identity(path) == out or os.path.realpath(path) == real:
            alias = "" if os.fspath(path) == os.fspath(output) else f" ({str(path)!r})"
            raise InvalidInputError(
                f"{output_name}: {str(output)!r} is the same file as the input {name}{alias}; writing it would "
                "replace that input (choose another output)"
            )


def refuse_shared_outputs(outputs: Iterable[tuple[str, Any]]) -> None:
    """InvalidInputError naming both when two of ``outputs`` (``(name, path)`` pairs; None
    paths are skipped) are one file — the same resolved path, existing or not yet, or the
    same device and inode: the later write would replace the earlier one's output."""
    seen: list[tuple[str, str, Any]] = []
    for name, path in outputs:
        if path is None:
            continue
        real, identity = os.path.realpath(path), file_identity(path)
        for other, other_real, other_identity in seen:
            if real == other_real or (identity is not None and identity == other_identity):
                raise InvalidInputError(
                    f"{name}: {str(path)!r} is the same file as {other}; one output would replace the other (choose another)"
                )
        seen.append((name, real, identity))


def _umask() -> int:
    """The process's umask, read without changing it where Linux shows it (``os.umask``
    sets it to read it, which races with other threads creating files)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _mode_for(target: Path) -> int:
    """The permission bits the file written to ``target`` gets: the replaced file's, or
    0666 less the umask for a new one."""
    try:
        return stat.S_IMODE(os.stat(target).st_mode)
    except OSError:
        return 0o666 & ~_umask()


def _written_through(target: Path, name: str) -> Path:
    """The file a write to the checked output ``target`` replaces: ``target``, or the file
    a symlink there points to (checked as an output in turn)."""
    return check_output_path(os.path.realpath(target), name) if os.path.islink(target) else target


def _temp(target: Path, name: str, text: bool) -> tuple[int, str]:
    try:
        return tempfile.mkstemp(dir=target.parent, prefix=f".{target.name[:_TEMP_STEM]}.", suffix=".tmp", text=text)
    except OSError as e:
        raise InvalidInputError(f"{name}: cannot write to {str(target.parent)!r}: {_reason(e)}") from None


def _write_atomic(path: Any, name: str, write: Callable[[Any], object], binary: bool = False) -> None:
    target = _written_through(check_output_path(path, name), name)
    mode = _mode_for(target)
    fd, tmp = _temp(target, name, not binary)
    try:
        if hasattr(os, "fchmod"):
            os.fchmod(fd, mode)
        f: Any = os.fdopen(fd, "wb") if binary else os.fdopen(fd, "w", encoding="utf-8", newline="\n")
        with f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, target)
    except OSError as e:
        Path(tmp).unlink(missing_ok=True)
        raise InvalidInputError(f"{name}: cannot write {str(target)!r} ({_reason(e)})") from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_bytes_atomic(path: Any, data: bytes, name: str = "path") -> None:
    """Write ``data`` to ``path`` atomically."""
    _write_atomic(path, name, lambda f: f.write(data), binary=True)


def write_text_atomic(path: Any, text: str, name: str = "path") -> None:
    """Write ``text`` (UTF-8, '\\n' line ends) to ``path`` atomically."""

    def write(f: TextIO) -> None:
        f.write(text)

    _write_atomic(path, name, write)


def write_json_atomic(path: Any, data: Any, name: str = "path") -> None:
    """Write ``data`` as indented JSON to ``path`` atomically (non-finite floats refused)."""
    text = json.dumps(data, indent=2, allow_nan=False) + "\n"
    write_text_atomic(path, text, name)
