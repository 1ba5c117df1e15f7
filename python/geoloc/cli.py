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
    mc = commands.add_parser(
        "montecarlo",
        help="the paper's Monte-Carlo test of the pose covariance (coverage tables)",
        description="Triangulate 119 points from 4 noisy training cameras, solve the target's "
        "PnP, and check the returned 6x6 covariance against the true error: per-axis 1.96σ "
        "coverage, 6-DoF NEES coverage and the paper's scalar figure, for σ_p ∈ {1, 2} px and "
        "three levels of pose-label noise.",
    )
    mc.add_argument("--trials", type=int, default=1000, help="trials per column (default: 1000)")
    mc.add_argument(
        "--covariance", choices=("paper", "propagated", "both"), default="both",
        help="covariance model(s) to test (default: both)",
    )
    mc.add_argument("--scene", choices=("paper", "random"), default="paper", help="fixed paper-like scene or a random one per trial")
    mc.add_argument("--seed", type=int, default=0)
    mc.add_argument("--json", metavar="FILE", help="also write the columns as JSON")
    mc.add_argument("--no-progress", action="store_true", help="no progress bar")
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
    if args.command == "montecarlo":
        if args.trials < 1:
            parser.error("--trials must be at least 1")
        from . import montecarlo

        models = ("paper", "propagated") if args.covariance == "both" else (args.covariance,)
        return montecarlo.main(args.trials, models, args.scene, args.seed, args.json, not args.no_progress)
    parser.print_help(sys.stderr)
    return 2
