"""``geoloc build-map``: a dataset with poses → one ``.geoloc`` map file."""

from __future__ import annotations

import argparse
import sys
import time

from ..exceptions import InvalidInputError
from ._common import (
    MAP_DONE,
    Progress,
    dataset_inputs,
    describe_labels,
    describe_map_noise,
    describe_model,
    describe_self_calibration,
    load_dataset,
    model_input,
    open_retrieval,
    select,
)

__all__ = ["run"]


def run(args: argparse.Namespace) -> int:
    """The ``build-map`` command."""
    from .._io import file_identity, refuse_alias, shown
    from ..mapping import Map

    dataset = load_dataset(args)
    refuse_alias(args.out, "--out", [*dataset_inputs(dataset, "--dataset"), *model_input(args.retrieval)])
    sequence = select(dataset, args.frames, "--frames")
    if sequence.poses is None:
        hint = " (give --trajectory FILE)" if args.format == "folder" else ""
        raise InvalidInputError(f"--dataset: {sequence.name!r} has no poses; a map needs world_from_cam poses{hint}")
    start = time.perf_counter()
    the_map = Map.build(
        sequence,
        retrieval=open_retrieval(args.retrieval),
        features=args.features,
        n_features=args.n_features,
        keyframe_step=args.step,
        model=getattr(args, "model", None),
        refine_intrinsics=getattr(args, "refine_intrinsics", None),
        adjust_labels=getattr(args, "adjust_labels", None),
        progress=Progress("map", then=MAP_DONE),
    )
    built = time.perf_counter() - start
    before = file_identity(args.out)
    try:
        the_map.save(args.out)
    except KeyboardInterrupt:
        # the core's write is not interrupted: a signal during it is handled when it returns,
        # with the new map in place — say so rather than only "interrupted"
        if file_identity(args.out) != before:
            print(f"geoloc build-map: the map was written to {shown(args.out)} before the interrupt", file=sys.stderr)
        raise
    cam = the_map.camera
    retrieval = "bag-of-words" if args.retrieval == "bow" else f"bag-of-words fused with the network {shown(args.retrieval)}"
    print(
        f"wrote {shown(args.out)}: {len(the_map)} keyframes of {sequence.name!r} ({args.features}, {args.n_features} features, "
        f"{retrieval} retrieval; camera {cam.width}×{cam.height}, fx={cam.intrinsics[0]:g}) in {built:.1f} s"
    )
    print(describe_self_calibration(the_map.self_calibration))
    print(describe_labels(the_map.labels))
    print(describe_model(the_map))
    print(describe_map_noise(the_map.map_noise))
    return 0
