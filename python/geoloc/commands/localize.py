"""``geoloc localize``: images (a folder or a dataset) + a map → a TUM trajectory, in the
convention of the map's pose labels (``Localization.pose``) or, with ``--camera-pose``, the
camera's own (``Localization.camera_pose``).

Frames the localizer loses are left out of the trajectory file (TUM has no "unknown pose")
and counted in the one-line summary on stderr.
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from ..exceptions import DatasetError, InvalidInputError
from ._options import EXIT_FAILURE, STDOUT
from ._common import (
    Progress,
    command_localizer,
    dataset_inputs,
    load_dataset,
    localize_sequence,
    model_input,
    open_retrieval,
    option_message,
    select,
)

__all__ = ["run"]


def _load_map(path: str) -> Any:
    from ..mapping import Map

    try:
        return Map.load(path)
    except (ValueError, OSError) as e:  # the core names the problem (truncated, checksum, version)
        message = " ".join(str(e).split())
        raise InvalidInputError(f"--map: {message}") from None


def _images(args: argparse.Namespace, camera: Any) -> Any:
    from ..datasets import load_folder

    root = Path(args.images)
    if not root.is_dir():
        what = "is a file, expected a folder" if root.exists() else "does not exist"
        raise InvalidInputError(f"--images: folder {str(root)!r} {what}")
    # The folder's own size first (from its first image), so a size mismatch is one clear error.
    try:
        sequence = load_folder(root, trajectory=None, intrinsics=camera.intrinsics)
    except DatasetError as e:
        raise InvalidInputError(option_message(str(e), "--images")) from None
    size = (sequence.camera.width, sequence.camera.height)
    if size != (camera.width, camera.height):
        raise InvalidInputError(
            f"--images: the images in {str(root)!r} are {size[0]}×{size[1]}, the map's camera is {camera.width}×{camera.height}"
        )
    return load_folder(root, trajectory=None, intrinsics=camera)  # the map's camera, distortion included


def run(args: argparse.Namespace) -> int:
    """The ``localize`` command."""
    from .._io import refuse_alias, shown
    from ..evaluation import tum_trajectory_text, write_tum_trajectory

    to_stdout = args.out == STDOUT
    out = None if to_stdout else args.out
    refuse_alias(out, "--out", [("--map", args.map), *model_input(args.retrieval)])
    the_map = _load_map(args.map)
    network = None
    if the_map.settings["retrieval"] != "bow":
        if args.retrieval in (None, "bow"):
            raise InvalidInputError(f"--retrieval: {args.map!r} retrieves with a network; give its MODEL.onnx")
        network = open_retrieval(args.retrieval)
    camera = the_map.camera
    if args.images is not None:
        if args.format is not None or args.intrinsics is not None:
            raise InvalidInputError("--images: a folder of images takes the map's camera (no --format / --intrinsics)")
        sequence = _images(args, camera)
    else:
        if args.format is None:
            raise InvalidInputError("--format: required with --dataset (7scenes, tum, folder or synthetic)")
        sequence = load_dataset(args, camera=camera, poses=False)  # every image: localizing needs no pose
        if (sequence.camera.width, sequence.camera.height) != (camera.width, camera.height):
            raise InvalidInputError(
                f"--dataset: its images are {sequence.camera.width}×{sequence.camera.height}, "
                f"the map's camera is {camera.width}×{camera.height}"
            )
        if sequence.camera.intrinsics != camera.intrinsics:
            # the frames' camera comes from --intrinsics when given, else from the dataset (the
            # synthetic room has its own)
            source = "--intrinsics" if args.intrinsics is not None else f"--format {args.format}"
            raise InvalidInputError(
                f"{source}: the frames' intrinsics {sequence.camera.intrinsics} differ from the map's {camera.intrinsics} "
                "(queries must use the map's camera)"
            )
    option = "--images" if args.images is not None else "--dataset"
    # a folder's trajectory too, read or not (a TUM sequence lists its groundtruth.txt itself):
    # an output never replaces one; the built-in room has no folder
    folder = args.images if args.images is not None else args.dataset
    unread = [] if folder is None else [(option, p) for p in (Path(folder) / "traj.txt",) if p.is_file()]
    refuse_alias(out, "--out", dataset_inputs(sequence, option) + unread)
    sequence = select(sequence, args.frames, "--frames")
    localizer = command_localizer(the_map, network, args.locator)
    try:
        results = localize_sequence(localizer, sequence, args.mode, Progress("localize"))
    except DatasetError as e:  # a frame's file, read as it is localized: the option that named it
        raise InvalidInputError(option_message(str(e), option)) from None
    kept = [k for k, r in enumerate(results) if r.pose is not None]
    shown_out = "standard output" if to_stdout else shown(args.out)
    if not kept:
        # the run failed, the input was fine: exit 1, not the 2 of a usage or input error
        print(f"geoloc localize: error: every one of the {len(results)} frames was lost; nothing written to {shown_out}",
              file=sys.stderr)
        return EXIT_FAILURE
    timestamps = sequence.timestamps[kept]
    if args.camera_pose:
        poses = np.stack([results[k].camera_pose for k in kept])
        convention = "world_from_cam: the camera's own pose"
    else:
        poses = np.stack([results[k].pose for k in kept])
        convention = "world_from_cam in the convention of the map's pose labels; --camera-pose: the camera's own"
    if to_stdout:
        sys.stdout.write(tum_trajectory_text(timestamps, poses, convention))
        sys.stdout.flush()
    else:
        write_tum_trajectory(args.out, timestamps, poses, convention)
    sources = Counter(r.source for r in results)
    lost = len(results) - len(kept)
    counts = ", ".join(f"{k} {v}" for k, v in sorted(sources.items()))
    total_ms = float(np.median([r.timings["total"] for r in results]))
    print(
        f"geoloc localize: {len(kept)}/{len(results)} frames localized, {lost} lost ({counts}; "
        f"{args.mode} mode, median {total_ms:.1f} ms/frame) -> {shown_out}",
        file=sys.stderr,
    )
    return 0
