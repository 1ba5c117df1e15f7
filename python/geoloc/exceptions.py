"""The exceptions geoloc raises.

Every error derives from :class:`GeolocError`; errors about bad arguments also derive from
the builtin :class:`ValueError`, so ``except ValueError`` keeps working.
"""

from __future__ import annotations

__all__ = ["FileAccessError", "FileFormatError", "DatasetError", "GeolocError", "InvalidInputError", "NotARotationError"]


class GeolocError(Exception):
    """Base class of every error raised by geoloc."""


class InvalidInputError(GeolocError, ValueError):
    """An argument has the wrong shape, dtype or value; the message names the argument."""


class NotARotationError(InvalidInputError):
    """A matrix that must be a rotation (or rigid transform) is not one within tolerance.

    Real datasets often ship slightly non-orthonormal rotations; project them first with
    :func:`geoloc.lie.so3_project` / :func:`geoloc.lie.se3_project`.
    """


class DatasetError(InvalidInputError):
    """A dataset on disk cannot be read as asked: a missing folder or file, no images, an
    unreadable pose or trajectory file, mismatched counts, an image of another size. The
    message names the file or folder."""


class FileFormatError(InvalidInputError):
    """A file geoloc reads (a ``.geoloc`` map, a frame stream) is truncated, corrupt or of
    another format version; the message names the file and the check that failed. Nothing of
    such a file is loaded."""


class FileAccessError(InvalidInputError, OSError):
    """A file cannot be read or written (missing, a folder, a FIFO, not writable); the
    message names the argument and the path. Both an :class:`OSError` (``except OSError``
    catches it, as it catches the builtins' file errors) and an :class:`InvalidInputError`
    (the path is an argument like any other)."""
