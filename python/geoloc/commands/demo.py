"""``geoloc demo``: the synthetic room end to end, no data to download.

Two laps around the built-in room: a map from the first lap, the second lap's frames
localized against it (single and sequential mode), the paper-style table on stdout,
``results.json`` and the plots in the output folder.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from ..exceptions import InvalidInputError
from ._common import MODES, FrameRange
from .evaluate import evaluate_split, folders_for_the_run, remove_empty, report, write_plots

__all__ = ["DEFAULT_FRAMES", "run", "split"]

#: Frames of the demo's room (two laps); 300 runs in well under a minute on 2 cores.
DEFAULT_FRAMES = 300
#: The demo's map has about this many keyframes per lap, and about this many test frames.
KEYFRAMES_PER_LAP = 75
TEST_FRAMES = 50


def split(n_frames: int) -> tuple[FrameRange, FrameRange]:
    """Lap 1 (every step-th frame) for the map, lap 2 (every step-th frame) for the test."""
    half = n_frames // 2
    return (
        FrameRange(0, half, max(1, half // KEYFRAMES_PER_LAP)),
        FrameRange(half, n_frames, max(1, (n_frames - half) // TEST_FRAMES)),
    )


def run(args: argparse.Namespace) -> int:
    """The ``demo`` command."""
    from .._io import write_json_atomic
    from ..datasets import synthetic_room

    start = time.perf_counter()
    out = Path(args.out)
    made: list[Path] = []
    if not out.exists():
        if not out.parent.is_dir():
            raise InvalidInputError(f"--out: folder {str(out.parent)!r} does not exist (create it first)")
        try:
            out.mkdir()
        except OSError as e:
            raise InvalidInputError(f"--out: cannot create {str(out)!r} ({e.strerror})") from None
        made.append(out)
    elif not out.is_dir():
        raise InvalidInputError(f"--out: {str(out)!r} is a file, expected a folder")
    try:
        with folders_for_the_run(None if args.no_plots else out, MODES, "--out"):
            sequence = synthetic_room(n_frames=args.frames)
            train, test = split(args.frames)
            result = evaluate_split(sequence, train, test, MODES)
            data = report(sequence, result, dataset=None, fmt="synthetic", train=train, test=test, timings=True)
            data["demo"] = {"frames": args.frames}
            write_json_atomic(out / "results.json", data, "--out")
            written = f"wrote {out / 'results.json'}"
            if not args.no_plots:
                write_plots(str(out), result["summaries"])
                written += f" and plots in {out}/{{{','.join(result['summaries'])}}}/"
    except BaseException:
        remove_empty(made)  # the folder this run made, unless it holds something
        raise
    print(f"{written} ({time.perf_counter() - start:.0f} s in all)")
    return 0
