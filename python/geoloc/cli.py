"""The ``geoloc`` command line."""

from __future__ import annotations

import argparse
import sys
from typing import Sequence


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``geoloc``."""
    from . import __version__

    parser = argparse.ArgumentParser(
        prog="geoloc",
        description="Image-based 6-DoF camera localization with a calibrated covariance.",
    )
    parser.add_argument("--version", action="version", version=f"geoloc {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")
    check = commands.add_parser(
        "selfcheck",
        help="verify the installed Lie-group core against independent references",
        description="Compare geoloc's SO(3)/SE(3) maps and Jacobians with a Taylor-series "
        "matrix exponential and central differences, and time a 200k batch.",
    )
    check.add_argument(
        "--samples", type=int, default=200, metavar="N",
        help="twists per (angle, translation) regime (default: 200)",
    )
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``geoloc`` with ``argv`` (default: ``sys.argv[1:]``); return the exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command == "selfcheck":
        if args.samples < 1:
            parser.error("--samples must be at least 1")
        from . import selfcheck

        return selfcheck.main(args.samples)
    parser.print_help(sys.stderr)
    return 2
