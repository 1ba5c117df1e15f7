"""The ``geoloc`` command line.

Every command validates its options where they are parsed (argparse types that name the
option), and every error a user can cause — bad input, a missing or unwritable file — ends as
**one line on stderr** naming what is wrong and a non-zero exit status (2 for a usage or
input error, 1 for a failed run). A traceback is printed only with ``--debug``. Output files
are written atomically and missing folders are never created.
"""

from __future__ import annotations

import argparse
import sys
import traceback
from typing import Callable, Sequence

from .exceptions import GeolocError

#: Exit status of a usage or input error (argparse uses 2 too).
EXIT_USAGE = 2
#: Exit status of a run that failed for another reason (a check failed, I/O failed).
EXIT_FAILURE = 1

#: The largest trial / sample counts the commands accept (bounded run time and memory).
MAX_TRIALS = 1_000_000
MAX_SELFCHECK_SAMPLES = 100_000
#: Seeds are stored in 64-bit unsigned integers by the core.
MAX_SEED = 2**63 - 1

Handler = Callable[[argparse.Namespace], int]


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


def output_file(text: str) -> str:
    """An argparse ``type`` for a file to write: its folder must exist and be writable."""
    from ._io import check_output_path

    try:
        check_output_path(text, "path")
    except GeolocError as e:
        raise argparse.ArgumentTypeError(str(e).removeprefix("path: ")) from None
    return text


def _add_selfcheck(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> Handler:
    check = commands.add_parser(
        "selfcheck",
        help="verify the installed Lie-group core against independent references",
        description="Compare geoloc's SO(3)/SE(3) maps and Jacobians with a Taylor-series "
        "matrix exponential and central differences, and time a 200k batch.",
        epilog="example: geoloc selfcheck --samples 50",
    )
    check.add_argument(
        "--samples", type=bounded_int(1, MAX_SELFCHECK_SAMPLES), default=200, metavar="N",
        help="twists per (angle, translation) regime (default: 200)",
    )

    def run(args: argparse.Namespace) -> int:
        from . import selfcheck

        return selfcheck.main(args.samples)

    return run


def _add_montecarlo(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> Handler:
    mc = commands.add_parser(
        "montecarlo",
        help="the paper's Monte-Carlo test of the pose covariance (coverage tables)",
        description="Triangulate 119 points from 4 noisy training cameras, solve the target's "
        "PnP, and check the returned 6x6 covariance against the true error: per-axis 1.96σ "
        "coverage, 6-DoF NEES coverage and the paper's scalar figure, for σ_p ∈ {1, 2} px and "
        "three levels of pose-label noise.",
        epilog="example: geoloc montecarlo --trials 1000 --covariance propagated --json mc.json",
    )
    mc.add_argument(
        "--trials", type=bounded_int(1, MAX_TRIALS), default=1000, metavar="N",
        help="trials per column (default: 1000)",
    )
    mc.add_argument(
        "--covariance", choices=("paper", "propagated", "both"), default="both",
        help="covariance model(s) to test (default: both)",
    )
    mc.add_argument("--scene", choices=("paper", "random"), default="paper", help="fixed paper-like scene or a random one per trial")
    mc.add_argument("--seed", type=bounded_int(0, MAX_SEED), default=0, metavar="S", help="random seed (default: 0)")
    mc.add_argument("--json", metavar="FILE", type=output_file, help="also write the columns as JSON")
    mc.add_argument("--no-progress", action="store_true", help="no progress bar")

    def run(args: argparse.Namespace) -> int:
        from . import montecarlo

        models = ("paper", "propagated") if args.covariance == "both" else (args.covariance,)
        return montecarlo.main(args.trials, models, args.scene, args.seed, args.json, not args.no_progress)

    return run


#: The commands, in the order ``--help`` lists them.
COMMANDS: tuple[Callable[[argparse._SubParsersAction[argparse.ArgumentParser]], Handler], ...] = (
    _add_selfcheck,
    _add_montecarlo,
)


def build_parser() -> tuple[argparse.ArgumentParser, dict[str, Handler]]:
    """The argument parser of ``geoloc`` and the handler of each command."""
    from . import __version__

    parser = argparse.ArgumentParser(
        prog="geoloc",
        description="Image-based 6-DoF camera localization with a calibrated covariance.",
    )
    parser.add_argument("--version", action="version", version=f"geoloc {__version__}")
    parser.add_argument("--debug", action="store_true", help="print a traceback when a command fails")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")
    handlers: dict[str, Handler] = {}
    for add in COMMANDS:
        before = set(commands.choices)
        handler = add(commands)
        (name,) = set(commands.choices) - before
        handlers[name] = handler
    return parser, handlers


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``geoloc`` with ``argv`` (default: ``sys.argv[1:]``); return the exit status."""
    parser, handlers = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help(sys.stderr)
        return EXIT_USAGE
    try:
        return handlers[args.command](args)
    except KeyboardInterrupt:
        print(f"geoloc {args.command}: interrupted", file=sys.stderr)
        return 130
    except (GeolocError, ValueError, OSError) as e:
        if args.debug:
            traceback.print_exc()
        status = EXIT_USAGE if isinstance(e, (GeolocError, ValueError)) else EXIT_FAILURE
        message = " ".join(str(e).split()) or type(e).__name__
        print(f"geoloc {args.command}: error: {message}", file=sys.stderr)
        return status
    except Exception as e:  # a bug, not the user's fault: still one line unless --debug
        if args.debug:
            traceback.print_exc()
        print(
            f"geoloc {args.command}: internal error: {type(e).__name__}: {e} (rerun with --debug for the traceback)",
            file=sys.stderr,
        )
        return EXIT_FAILURE
