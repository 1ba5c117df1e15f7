"""The argparse option types and option groups the commands share.

Every type names what is wrong in its message (argparse prefixes the option), so a bad value
is one line on stderr before anything is loaded. :mod:`geoloc.cli` builds the parsers with
these, and so does ``geoloc train`` (:mod:`geoloc.training.command`, which the cli registers
and which imports nothing from it).
"""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path
from typing import Callable

from ..exceptions import GeolocError
from ..datasets.synthetic import MAX_FRAMES as SYNTHETIC_MAX_FRAMES
from ._common import FORMATS, FrameRange

__all__ = [
    "EXIT_FAILURE",
    "EXIT_USAGE",
    "MAX_SEED",
    "MAX_SYNTHETIC_FRAMES",
    "bounded_int",
    "dataset_options",
    "existing_file",
    "frame_range",
    "intrinsics",
    "new_folder",
    "STDOUT",
    "output_file",
    "output_file_or_stdout",
    "positive_float",
    "retrieval",
]

#: Seeds are stored in 64-bit unsigned integers by the core.
MAX_SEED = 2**63 - 1
#: The largest synthetic room (frames) the commands accept: the generator's own bound.
MAX_SYNTHETIC_FRAMES = SYNTHETIC_MAX_FRAMES


def bounded_int(low: int, high: int) -> Callable[[str], int]:
    """An argparse ``type`` accepting integers in [low, high]; the message says the range."""

    def parse(text: str) -> int:
        try:
            value = int(text, 10)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"must be between {low} and {high}, got {value}")
        return value

    parse.__name__ = "integer"
    return parse


def positive_float(text: str) -> float:
    """An argparse ``type`` for a finite number > 0."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (value > 0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return value


def bounded_float(lo: float, hi: float) -> Callable[[str], float]:
    """An argparse ``type`` for a finite number within [lo, hi]."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not (lo <= value <= hi):
            raise argparse.ArgumentTypeError(f"must be a number within [{lo:g}, {hi:g}], got {text}")
        return value

    parse.__name__ = "number"
    return parse


def output_file(text: str) -> str:
    """An argparse ``type`` for a file to write: its folder must exist and be writable. ``-``
    is refused: it means standard output where an option can write there
    (:func:`output_file_or_stdout`), and a file named ``-`` is spelled ``./-``."""
    from .._io import check_output_path

    if text == STDOUT:
        raise argparse.ArgumentTypeError("'-' (standard output) is not an output of this option; give a file name (./- for a file named '-')")
    try:
        check_output_path(text, "path")
    except GeolocError as e:
        raise argparse.ArgumentTypeError(str(e).removeprefix("path: ")) from None
    return text


#: Exit status of a usage or input error (argparse uses 2 too).
EXIT_USAGE = 2
#: Exit status of a run that failed for another reason (a check failed, I/O failed, every
#: frame lost).
EXIT_FAILURE = 1

#: The output name that means standard output.
STDOUT = "-"


def output_file_or_stdout(text: str) -> str:
    """:func:`output_file`, or ``-`` for standard output."""
    return text if text == STDOUT else output_file(text)


def frame_range(text: str) -> FrameRange:
    """An argparse ``type`` for ``A:B`` or ``A:B:K`` (checked against the sequence later)."""
    try:
        return FrameRange.parse(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None


frame_range.__name__ = "frame range"


def intrinsics(text: str) -> tuple[float, float, float, float]:
    """An argparse ``type`` for ``fx,fy,cx,cy``: four finite numbers, fx and fy > 0."""
    parts = text.replace(" ", "").split(",")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected fx,fy,cx,cy (four numbers), got {text!r}") from None
    if len(values) != 4 or not all(math.isfinite(v) for v in values) or values[0] <= 0 or values[1] <= 0:
        raise argparse.ArgumentTypeError(f"expected fx,fy,cx,cy: four finite numbers with fx, fy > 0, got {text!r}")
    return values


intrinsics.__name__ = "intrinsics"


def existing_file(text: str) -> str:
    """An argparse ``type`` for a file to read: an existing regular file (a folder, a FIFO or
    a device is named as such and never opened)."""
    from .._io import check_input_file

    try:
        check_input_file(text, "path")
    except GeolocError as e:
        raise argparse.ArgumentTypeError(str(e).removeprefix("path: ")) from None
    return text


def new_folder(text: str) -> str:
    """An argparse ``type`` for a folder to write into: an existing folder, or a new one
    whose parent exists (it is created then; nothing above it ever is)."""
    path = Path(text)
    try:
        exists = os.path.lexists(path)
        if exists and not path.is_dir():
            raise argparse.ArgumentTypeError(f"{text!r} exists and is not a folder")
        if not exists and not path.parent.is_dir():
            raise argparse.ArgumentTypeError(f"folder {str(path.parent)!r} does not exist (create it first)")
    except OSError as e:  # a name too long for the file system, a loop of symlinks
        raise argparse.ArgumentTypeError(f"cannot use {text!r} as a folder ({e.strerror or e})") from None
    return text


def retrieval(text: str) -> str:
    """An argparse ``type`` for ``--retrieval``: ``bow`` or an existing ``MODEL.onnx`` file
    (a descriptor network exported by ``geoloc train``)."""
    if text == "bow":
        return text
    if text.endswith(".onnx"):
        from .._io import check_input_file

        try:
            check_input_file(text, "path")
        except GeolocError as e:
            raise argparse.ArgumentTypeError("model " + str(e).removeprefix("path: ")) from None
        return text
    raise argparse.ArgumentTypeError(f"expected bow or a MODEL.onnx file, got {text!r}")


def dataset_options(
    parser: argparse.ArgumentParser,
    trajectory: bool = False,
    required: bool = True,
    intrinsics_default: str | None = None,
    format_default: str | None = None,
) -> None:
    """``--dataset``, ``--format``, ``--intrinsics``, ``--synthetic-frames`` and, with
    ``trajectory``, ``--trajectory``: what :func:`geoloc.commands._common.load_dataset` reads.
    ``format_default`` is said in ``--format``'s help where the command has one."""
    parser.add_argument(
        "--dataset", metavar="P",
        help="dataset folder (not needed with --format synthetic, the built-in room)",
    )
    parser.add_argument(
        "--format", choices=FORMATS, required=required,
        help="7scenes (frame-XXXXXX.color.{jpg,png} + .pose.txt), tum (rgb.txt + groundtruth.txt), "
        "folder (images + a TUM trajectory), synthetic (the built-in room)"
        + (f" (default: {format_default})" if format_default else ""),
    )
    parser.add_argument(
        "--intrinsics", type=intrinsics, metavar="fx,fy,cx,cy",
        help="pinhole intrinsics in pixels (default: "
        + (intrinsics_default or "7scenes 525,525,320,240; tum from the folder name or camera.txt; folder: required")
        + ")",
    )
    if trajectory:
        parser.add_argument(
            "--trajectory", metavar="FILE",
            help="--format folder: the TUM trajectory, relative to the dataset folder (default: traj.txt)",
        )
    parser.add_argument(
        "--synthetic-frames", type=bounded_int(20, MAX_SYNTHETIC_FRAMES), default=300, metavar="N",
        help="--format synthetic: frames of the room, two laps (default: 300)",
    )
