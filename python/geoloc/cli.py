"""The ``geoloc`` command line.

Every command validates its options where they are parsed (argparse types that name the
option), and every error a user can cause — bad input, a missing or unwritable file — ends in
**one line on stderr** naming what is wrong (a malformed command line prints the command's
usage above it, as argparse does) and a non-zero exit status (2 for a usage or
input error, 1 for a failed run). A traceback is printed only with ``--debug``. Output files
are written atomically and missing folders are never created.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
import traceback
from typing import Callable, Sequence

from .commands._options import (
    EXIT_FAILURE,
    EXIT_USAGE,
    MAX_SEED,
    MAX_SYNTHETIC_FRAMES,
    bounded_int,
    dataset_options,
    existing_file,
    frame_range,
    new_folder,
    output_file,
    output_file_or_stdout,
    retrieval,
)
from . import _core
from .exceptions import GeolocError, InvalidInputError
from .montecarlo import MAX_TRIALS as MONTECARLO_MAX_TRIALS
from .reference import REFERENCE_FORMATS

#: The largest trial / sample counts the commands accept (bounded run time and memory);
#: the trials are the Monte-Carlo function's own bound.
MAX_TRIALS = MONTECARLO_MAX_TRIALS
MAX_SELFCHECK_SAMPLES = 100_000
#: The largest feature count the commands accept.
MAX_FEATURES = 100_000

Handler = Callable[[argparse.Namespace], int]


class _HelpFormatter(argparse.HelpFormatter):
    """Wraps descriptions as usual but prints an ``example:`` epilog verbatim, so the
    example's command lines can be copied as they are."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        if text.startswith("example"):
            return text
        return super()._fill_text(text, width, indent)


def _example(*lines: str) -> str:
    """An epilog: ``example:`` then the command, continuation lines ending in a backslash."""
    return "example:\n  " + " \\\n      ".join(lines)


def _feature_options(parser: argparse.ArgumentParser) -> None:
    from .features import DEFAULT_KIND, DEFAULT_N_FEATURES

    parser.add_argument(
        "--features", choices=("orb", "sift"), default=DEFAULT_KIND, help=f"local features (default: {DEFAULT_KIND})"
    )
    parser.add_argument(
        "--n-features", type=bounded_int(50, MAX_FEATURES), default=DEFAULT_N_FEATURES, metavar="N",
        help=f"features per image (default: {DEFAULT_N_FEATURES})",
    )
    parser.add_argument(
        "--retrieval", type=retrieval, default="bow", metavar="bow|MODEL.onnx",
        help="image retrieval: bow, a bag of words trained on the map's features, or a descriptor "
        "network exported by 'geoloc train' (default: bow)",
    )


def _calibration_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--nominal-intrinsics", dest="refine_intrinsics", action="store_const", const=False, default=None,
        help="use --intrinsics as they are; by default the map estimates the real camera (focal lengths, "
        "principal point, lens distortion) from its own keyframes and corrects every keypoint with it",
    )
    parser.add_argument(
        "--keep-labels", dest="adjust_labels", action="store_const", const=False, default=None,
        help="use the sequence's pose labels as the keyframes' truth; by default the map corrects them by "
        "bundle adjustment (keyframe poses, points and one label-to-camera offset, the labels as robust "
        "priors) so that it agrees with its images",
    )


def _add_demo(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> Handler:
    demo = commands.add_parser(
        "demo",
        formatter_class=_HelpFormatter,
        help="the synthetic room end to end; writes ./geoloc-demo/results.json + plots",
        description="Render the built-in synthetic room (two laps around it), build a map from the "
        "first lap, localize frames of the second lap in single mode (history forgotten before each "
        "frame) and sequential mode (motion model + fusion), print the paper-style table and the "
        "per-stage times, and write results.json and the plots. About half a minute on 2 cores.",
        epilog=_example("geoloc demo --out geoloc-demo"),
    )
    demo.add_argument(
        "--out", type=new_folder, default="geoloc-demo", metavar="DIR",
        help="output folder, created if missing (its parent must exist; default: ./geoloc-demo)",
    )
    demo.add_argument(
        "--frames", type=bounded_int(20, MAX_SYNTHETIC_FRAMES), default=300, metavar="N",
        help="frames of the room, two laps: the map from lap 1, the test from lap 2 (default: 300)",
    )
    demo.add_argument("--no-plots", action="store_true", help="write results.json only")

    def run(args: argparse.Namespace) -> int:
        from .commands import demo

        return demo.run(args)

    return run


def _add_build_map(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> Handler:
    build = commands.add_parser(
        "build-map",
        formatter_class=_HelpFormatter,
        help="build a map file from a dataset with poses",
        description="Extract local features of the dataset's frames, train the retrieval vocabulary "
        "and write everything to one .geoloc map file (safetensors; written atomically). "
        "A progress bar goes to stderr when it is a terminal.",
        epilog=_example(
            "geoloc build-map --dataset ../shared/data/7scenes-redkitchen --format 7scenes",
            "--intrinsics 525,525,320,240 --frames 0:600 --out redkitchen.geoloc",
        ),
    )
    dataset_options(build, trajectory=True)
    build.add_argument("--frames", type=frame_range, metavar="A:B", help="frame positions A..B-1 (A:B:K every K-th; default: all)")
    build.add_argument(
        "--step", type=bounded_int(1, 10_000), default=1, metavar="K", help="every K-th selected frame becomes a keyframe (default: 1)"
    )
    _feature_options(build)
    _calibration_option(build)
    build.add_argument(
        "--model", action=argparse.BooleanOptionalAction, default=None,
        help="store the map-level 3D model of the model locator (default: the core's, geoloc.Map.default_options(); "
        "--no-model: a model localizer builds it when it starts, the paper's locator does not need it)",
    )
    build.add_argument("--out", type=output_file, required=True, metavar="scene.geoloc", help="map file to write (its folder must exist)")

    def run(args: argparse.Namespace) -> int:
        from .commands import build_map

        return build_map.run(args)

    return run


def _add_localize(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> Handler:
    loc = commands.add_parser(
        "localize",
        formatter_class=_HelpFormatter,
        help="localize images against a map; writes a TUM trajectory",
        description="Localize every image of a folder (numeric names in number order, their number "
        "the timestamp; other names sorted by name, timestamps index/30 s) or of a dataset against a map built by build-map, and write the "
        "poses as a TUM trajectory (timestamp tx ty tz qx qy qz qw), atomically: in the convention of the map's pose labels "
        "(what the map was built from), or with --camera-pose the camera's own. "
        "Lost frames are left out of the file and counted in the summary line on stderr.",
        epilog=_example(
            "geoloc localize --map redkitchen.geoloc --dataset ../shared/data/7scenes-redkitchen",
            "--format 7scenes --frames 600:700 --mode sequential --out poses.txt",
        ),
    )
    loc.add_argument("--map", type=existing_file, required=True, metavar="scene.geoloc", help="map file (from build-map)")
    loc.add_argument(
        "--images", metavar="DIR",
        help="a folder of images of the map camera's size, localized in order: by number when every name is a number "
        "(9.png before 10.png; the number is the timestamp in seconds), else by name (timestamps index/30 s)",
    )
    dataset_options(loc, required=False, intrinsics_default="the map's camera")
    loc.add_argument("--frames", type=frame_range, metavar="A:B", help="frame positions A..B-1 (A:B:K every K-th; default: all)")
    loc.add_argument(
        "--mode", choices=("single", "sequential"), default="sequential",
        help="single: every frame on its own; sequential: motion model + fusion (default: sequential)",
    )
    loc.add_argument(
        "--retrieval", type=retrieval, default=None, metavar="MODEL.onnx",
        help="the descriptor network the map was built with (maps that retrieve by a network only)",
    )
    loc.add_argument(
        "--locator", choices=("paper", "model"), default=None,
        help="paper: one retrieved keyframe and its group; model: top-k retrieval against the map's 3D model "
        "(default: the core's, geoloc.Localizer.default_options())",
    )
    loc.add_argument(
        "--out", type=output_file_or_stdout, required=True, metavar="poses.txt",
        help="TUM trajectory to write (its folder must exist); - writes it to standard output",
    )
    loc.add_argument(
        "--camera-pose", action="store_true",
        help="write the camera's own pose (world_from_cam); by default the pose in the convention of the map's "
        "pose labels, comparable with them (the two differ by the label-to-camera offset the map estimated)",
    )

    def run(args: argparse.Namespace) -> int:
        from .commands import localize

        if (args.images is None) == (args.dataset is None and args.format != "synthetic"):
            raise InvalidInputError("--images/--dataset: give exactly one (a folder of images, or a dataset with --format)")
        return localize.run(args)

    return run


def _add_evaluate(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> Handler:
    ev = commands.add_parser(
        "evaluate",
        formatter_class=_HelpFormatter,
        help="build a map from a train range, localize a test range, print errors and calibration",
        description="Build a map from the --train frames, localize the --test frames in single "
        "and/or sequential mode, and print the paper-style table: median translation/rotation "
        "error, recall (5 cm/5°, 25 cm/2°, 10 cm/1°), sources, NEES calibration and time per "
        "frame, with the paper's figures as a reference on 7-Scenes. Default split: the "
        "synthetic room's two laps; otherwise the last 100 frames are the test set.",
        epilog=_example(
            "geoloc evaluate --dataset ../shared/data/7scenes-redkitchen --format 7scenes",
            "--intrinsics 525,525,320,240 --train 0:600 --test 600:700 --json r.json --timings --plots out/",
        ),
    )
    dataset_options(ev, trajectory=True)
    ev.add_argument("--train", type=frame_range, metavar="A:B", help="map frames (A:B:K every K-th)")
    ev.add_argument("--test", type=frame_range, metavar="C:D", help="test frames (C:D:K every K-th)")
    ev.add_argument(
        "--mode", choices=("single", "sequential", "both"), default="both",
        help="single: history forgotten before every frame; sequential: motion model + fusion (default: both)",
    )
    _feature_options(ev)
    _calibration_option(ev)
    ev.add_argument(
        "--locator", choices=("paper", "model"), default=None,
        help="paper: one retrieved keyframe and its group; model: top-k retrieval against the map's 3D model "
        "(default: the core's, geoloc.Localizer.default_options())",
    )
    ev.add_argument(
        "--reference", type=existing_file, metavar="FILE",
        help="also score the test frames against this independent reference trajectory (e.g. a structure-from-motion "
        "reconstruction of the same images): a similarity and one fixed camera-frame offset are fitted (Huber, 2 cm / 1°) "
        "on the training frames to the map's keyframe poses, and the table gets a row against the labels and a row "
        "against the aligned reference per mode",
    )
    ev.add_argument(
        "--reference-format", choices=REFERENCE_FORMATS, metavar="auto|7scenes-reference|tum",
        help="--reference's format: 7scenes-reference (frame index then the row-major top 3x4 camera-to-world pose per "
        "line), tum (t tx ty tz qx qy qz qw, matched to frames by time); default auto, by the values per line",
    )
    ev.add_argument("--json", type=output_file, metavar="FILE", help="write the result dict as JSON")
    ev.add_argument("--timings", action="store_true", help="print the median time of every stage")
    ev.add_argument(
        "--plots", type=new_folder, metavar="DIR",
        help="write DIR/<mode>/{trajectory,errors,error_cdf,calibration}.png (DIR is created if its parent exists)",
    )

    def run(args: argparse.Namespace) -> int:
        from .commands import evaluate

        return evaluate.run(args)

    return run


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
    mc.add_argument(
        "--scene", choices=("paper", "short", "ahead", "random"), default="paper",
        help="fixed paper-like scene, fixed short-baseline scene (keyframes over 0.35 m, points 2.5–6 m), the short-baseline "
        "scene with the target 0.25 m ahead of the keyframes and turned 6°, or a random one per trial",
    )
    mc.add_argument("--seed", type=bounded_int(0, MAX_SEED), default=0, metavar="S", help="random seed (default: 0)")
    mc.add_argument("--json", metavar="FILE", type=output_file, help="also write the columns as JSON")
    mc.add_argument("--no-progress", action="store_true", help="no progress bar")

    def run(args: argparse.Namespace) -> int:
        from . import montecarlo

        models = ("paper", "propagated") if args.covariance == "both" else (args.covariance,)
        return montecarlo.main(args.trials, models, args.scene, args.seed, args.json, not args.no_progress)

    return run


def _add_train(commands: argparse._SubParsersAction[argparse.ArgumentParser]) -> Handler:
    # The parser and handler live with the training code; importing them needs no torch.
    from .training.command import add_train_command

    return add_train_command(commands)


#: The commands, in the order ``--help`` lists them.
COMMANDS: tuple[Callable[[argparse._SubParsersAction[argparse.ArgumentParser]], Handler], ...] = (
    _add_demo,
    _add_build_map,
    _add_localize,
    _add_evaluate,
    _add_selfcheck,
    _add_montecarlo,
    _add_train,
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


#: The number of SIGPIPE (the signal a writer to a pipe nobody reads gets), also where the
#: signal module lacks it.
SIGPIPE = int(getattr(signal, "SIGPIPE", 13))


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``geoloc`` with ``argv`` (default: ``sys.argv[1:]``); return the exit status."""
    from ._io import shown

    parser, handlers = build_parser()
    args, unknown = parser.parse_known_args(argv)
    if args.command is None:
        if unknown:
            parser.error(f"unrecognized arguments: {' '.join(unknown)}")
        parser.print_help(sys.stderr)
        return EXIT_USAGE
    if unknown:  # the command's usage and "geoloc COMMAND: error: …", not the top level's
        _command_parser(parser, args.command).error(f"unrecognized arguments: {' '.join(unknown)}")
    # a robot capping its CPU use with a typo must learn that the cap did not apply
    threads_warning = _core.num_threads_warning(os.environ.get("GEOLOC_NUM_THREADS"))
    if threads_warning:
        print(f"geoloc {args.command}: warning: {threads_warning}", file=sys.stderr)
    restore = _stop_on_termination()
    try:
        return handlers[args.command](args)
    except KeyboardInterrupt as e:
        signum = e.args[0] if e.args and isinstance(e.args[0], int) else signal.SIGINT
        print(f"geoloc {args.command}: interrupted", file=sys.stderr)
        return 128 + int(signum)
    except BrokenPipeError:
        # the reader of standard output went away (`| head`): stop quietly with the status of a
        # tool the SIGPIPE ended, standard output pointed at /dev/null so that the interpreter's
        # last flush does not fail again
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
        return 128 + SIGPIPE
    except (GeolocError, ValueError, OSError) as e:
        if args.debug:
            traceback.print_exc()
        status = EXIT_USAGE if isinstance(e, (GeolocError, ValueError)) else EXIT_FAILURE
        message = shown(" ".join(str(e).split()) or type(e).__name__)
        print(f"geoloc {args.command}: error: {message}", file=sys.stderr)
        return status
    except Exception as e:  # a bug, not the user's fault: still one line unless --debug
        if args.debug:
            traceback.print_exc()
        print(
            f"geoloc {args.command}: internal error: {type(e).__name__}: {shown(str(e))} (rerun with --debug for the traceback)",
            file=sys.stderr,
        )
        return EXIT_FAILURE
    finally:
        restore()


def _command_parser(parser: argparse.ArgumentParser, command: str) -> argparse.ArgumentParser:
    """The sub-parser of ``command`` in ``parser`` (built by :func:`build_parser`)."""
    (commands,) = (a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    sub: argparse.ArgumentParser = commands.choices[command]
    return sub


def _stop_on_termination() -> Callable[[], None]:
    """SIGTERM and SIGHUP (a service stopped, an ssh session dropped) end a command as Ctrl-C
    does — a KeyboardInterrupt carrying the signal's number, so that writers remove their
    temp files and keep the previous output — instead of killing the process with a temp
    file left behind. A native call (the core writing a map) finishes first. Returns the
    function that puts the previous handlers back (main thread only; elsewhere nothing)."""
    if threading.current_thread() is not threading.main_thread():
        return lambda: None

    def stop(signum: int, frame: object) -> None:
        raise KeyboardInterrupt(signum)

    watched = [signal.SIGTERM, *([signal.SIGHUP] if hasattr(signal, "SIGHUP") else [])]
    previous = {s: signal.signal(s, stop) for s in watched}

    def restore() -> None:
        for s, handler in previous.items():
            signal.signal(s, handler)

    return restore
