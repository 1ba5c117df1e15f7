"""``geoloc evaluate``: build a map from a train range, localize a test range, report.

The report is the paper's kind of table (median translation / rotation error, recall,
sources, NEES calibration, time per frame), one row per mode; on 7-Scenes it shows the
paper's own figures for the scene as a reference column. ``--json`` writes the result dict
(:func:`geoloc.evaluation.summarize`), ``--plots`` the four PNGs per mode.

``--reference FILE`` also scores the test frames against an independent reference trajectory
(:mod:`geoloc.reference`): a similarity S and a fixed camera-frame offset X are fitted on the
training frames, S·R_i·X ≈ the map's keyframe pose of frame i (:func:`map_keyframe_poses`), and
each test estimate is compared with S·R_j·X; the table then has a row against the labels and a
row against the reference per mode.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..exceptions import DatasetError, InvalidInputError
from ..features import DEFAULT_KIND, DEFAULT_N_FEATURES
from ._common import (
    FrameRange,
    MAP_DONE,
    MODES,
    Progress,
    command_localizer,
    dataset_inputs,
    describe_labels,
    describe_self_calibration,
    load_dataset,
    localize_sequence,
    model_input,
    open_retrieval,
    option_message,
    stage_table,
)

__all__ = ["PAPER_7SCENES", "evaluate_split", "load_reference_option", "map_keyframe_poses", "report", "run"]

#: The paper's Table III (7-Scenes), median (m, deg): "Our method (Single image)" and
#: "(Multiple model)", by scene name as it appears in the dataset's path.
PAPER_7SCENES: dict[str, dict[str, tuple[float, float]]] = {
    "chess": {"single": (0.12, 4.06), "sequential": (0.13, 3.87)},
    "fire": {"single": (0.08, 4.11), "sequential": (0.08, 4.04)},
    "heads": {"single": (0.08, 4.42), "sequential": (0.05, 4.50)},
    "office": {"single": (0.23, 9.64), "sequential": (0.14, 7.31)},
    "pumpkin": {"single": (0.25, 8.79), "sequential": (0.16, 6.30)},
    "redkitchen": {"single": (0.02, 1.10), "sequential": (0.02, 1.40)},
    "stairs": {"single": (0.11, 5.22), "sequential": (0.08, 5.40)},
}
#: When both modes run, the top-level keys of the JSON are this mode's (the full system).
PRIMARY_MODE = "sequential"


def _modes(mode: str) -> tuple[str, ...]:
    return MODES if mode == "both" else (mode,)


def default_split(n: int, fmt: str) -> tuple[FrameRange, FrameRange]:
    """Train/test when not given: the synthetic room's two laps (first half / second half);
    otherwise the paper's protocol, the last 100 frames are the test set (the last half of a
    sequence shorter than 200 frames) and everything before them the training set."""
    if fmt == "synthetic":
        cut = n // 2
    else:
        cut = n - min(100, n // 2)
    return FrameRange(0, cut), FrameRange(cut, n)


def _positions(r: slice) -> set[int]:
    return set(range(r.start, r.stop, r.step))


def load_reference_option(path: str, fmt: str | None) -> dict[str, Any]:
    """``--reference`` / ``--reference-format``: ``{"file", "format", "keys", "poses"}`` of
    :func:`geoloc.reference.load_reference`, its errors headed ``--reference:``."""
    from ..reference import load_reference

    try:
        keys, poses = load_reference(path, fmt or "auto")
    except DatasetError as e:
        raise InvalidInputError(option_message(str(e), "--reference")) from None
    kind = "7scenes-reference" if keys.dtype.kind in "iu" else "tum"
    return {"file": path, "format": kind, "keys": keys, "poses": poses}


def map_keyframe_poses(the_map: Any, labels: NDArray[np.float64]) -> NDArray[np.float64]:
    """The poses a reference is aligned to, one per training frame (``labels``, (N, 4, 4)):
    the map's own keyframe poses (``the_map.keyframe_poses``, the adjusted poses when the map
    adjusts its keyframes) where the map has them, else the training labels it was built from."""
    poses = getattr(the_map, "keyframe_poses", None)
    if poses is None or getattr(the_map, "labels", None) is None:
        # a map that did not adjust its labels holds the labels themselves
        return labels
    arr = np.asarray(poses, dtype=np.float64)
    if arr.shape != labels.shape:
        raise InvalidInputError(
            f"--reference: the map has {arr.shape[0] if arr.ndim == 3 else arr.shape} keyframe poses for "
            f"{len(labels)} training frames (the alignment needs one per training frame)"
        )
    return arr


def _reference_rows(reference: dict[str, Any], seq: Any, what: str) -> NDArray[np.int64]:
    """The reference row of each frame of ``seq`` (-1: none), matched by frame index or time."""
    from ..reference import match_reference

    rows = match_reference(reference["keys"], seq.indices, seq.timestamps)
    if what == "test" and (rows < 0).any():
        missing = seq.indices[rows < 0]
        listed = ", ".join(str(int(f)) for f in missing[:5]) + (" …" if len(missing) > 5 else "")
        raise InvalidInputError(
            f"--reference: {str(reference['file'])!r} has no pose for {len(missing)} of the {len(seq)} test frames ({listed})"
        )
    if what == "train" and (rows >= 0).sum() < 3:
        raise InvalidInputError(
            f"--reference: {str(reference['file'])!r} has poses for {(rows >= 0).sum()} of the {len(seq)} training frames; "
            "the alignment needs at least 3"
        )
    return rows


#: A reference whose aligned training poses lie a median of more than this many Huber scales
#: (2 cm / 1°) from the poses it is fitted to is refused: labels that drift (7-Scenes: 2–3 cm /
#: 1.5° from an SfM reference) stay well inside it; frame indices shifted by half the
#: sequence gave 20 cm / 7°.
MAX_MEDIAN_RESIDUAL_SCALES = 5.0


#: A reference whose frame-to-frame rotation angles match the training frames' clearly
#: better under frame numbers shifted by at least this many frames ...
MIN_NUMBERING_SHIFT = 2
#: ... (RMS difference below this fraction of the RMS under their own numbers) is refused as
#: wrongly numbered (:func:`geoloc.reference.numbering_shift`). On 7-Scenes frames 0–699
#: against the SfM reference, 152 windows of 30–600 training frames under their own numbers
#: came no closer than 0.85 at a shift of 2 or more (shifts of one frame fit better in
#: places: the labels are the depth camera's, whose frames are not the colour camera's);
#: numbers shifted by 5, −10, 20 and 40 frames are refused in 73 %, 87 %, 86 % and 65 % of
#: the windows — the rest are left to the residual check below; with every third frame of
#: those windows (84), none refused as numbered and 99 % of the shifted ones refused.
NUMBERING_SHIFT_RATIO = 2.0 / 3.0


def _check_numbering(reference: dict[str, Any], train_seq: Any) -> None:
    """InvalidInputError naming --reference when the reference describes the training frames
    clearly better under shifted frame numbers or times (:data:`MIN_NUMBERING_SHIFT`,
    :data:`NUMBERING_SHIFT_RATIO`): the similarity and offset fit absorbs a shift into an offset
    of metres and scores every test frame against another frame's pose."""
    from ..reference import numbering_shift

    found = numbering_shift(reference["keys"], reference["poses"], train_seq.poses, train_seq.indices, train_seq.timestamps)
    if found is None:
        return
    own, best = found.rms_deg[0], found.rms_deg[found.best]
    if abs(found.best) >= MIN_NUMBERING_SHIFT and best < NUMBERING_SHIFT_RATIO * own:
        unit = "frames" if reference["format"] == "7scenes-reference" else "frame intervals in time"
        raise InvalidInputError(
            f"--reference: {str(reference['file'])!r} matches the training frames' rotation from frame to frame best "
            f"shifted by {found.best:+d} {unit} (RMS {best:.3g}° against {own:.3g}° as numbered) — wrong frame numbers "
            "or timestamps?"
        )


def _checked_alignment_uncertainty(alignment: Any, test_reference: NDArray[np.float64], file: Any) -> tuple[float, float]:
    """The alignment's own uncertainty at the test frames' aligned reference poses (median
    position m, rotation deg); InvalidInputError naming --reference when it is beyond the
    first recall threshold a pose is scored at (5 cm / 5°): the training frames it shares with the dataset do not determine S
    and X, and a score against that reference means nothing. (Three frames 7 mm apart: ±18 m;
    60 frames of 7-Scenes for the next 30: ±3 cm / 0.7°, at 2 cm / 1° per frame.) Refused
    too when the training frames' residuals have a median beyond
    :data:`MAX_MEDIAN_RESIDUAL_SCALES` Huber scales: the reference does not describe those
    frames (wrong frame numbers or timestamps, another scene or unit), and the uncertainty,
    computed for residuals of the scales' size, would understate it."""
    from ..evaluation import RECALL_THRESHOLDS

    st = alignment.statistics()
    max_p = MAX_MEDIAN_RESIDUAL_SCALES * alignment.position_scale_m
    max_r = MAX_MEDIAN_RESIDUAL_SCALES * alignment.rotation_scale_deg
    if not (st["median_position_m"] <= max_p and st["median_rotation_deg"] <= max_r):
        raise InvalidInputError(
            f"--reference: {str(file)!r} does not fit the training frames: aligned by a similarity and one camera offset, "
            f"its poses lie a median {100 * st['median_position_m']:.3g} cm / {st['median_rotation_deg']:.3g}° from them "
            f"(at most {100 * max_p:g} cm / {max_r:g}° is accepted) — wrong frame numbers or timestamps, another scene, "
            "or another unit?"
        )
    sigma_p, sigma_r = alignment.uncertainty(test_reference)
    p, r = float(np.median(sigma_p)), float(np.median(sigma_r))
    max_m, max_deg = RECALL_THRESHOLDS[0]
    if not (p <= max_m and r <= max_deg):
        raise InvalidInputError(
            f"--reference: the training frames of {str(file)!r} do not determine its alignment: it alone leaves the test "
            f"frames' reference poses ±{100 * p:.3g} cm / ±{r:.3g}° (median), more than the {100 * max_m:g} cm / "
            f"{max_deg:g}° a pose is scored at; give reference poses for more, or more spread-out, training frames"
        )
    return p, r


def evaluate_split(
    sequence: Any,
    train: FrameRange,
    test: FrameRange,
    modes: tuple[str, ...],
    *,
    features: str = DEFAULT_KIND,
    n_features: int = DEFAULT_N_FEATURES,
    retrieval: str = "bow",
    options: tuple[str, str] = ("--train", "--test"),
    locator: str | None = None,
    refine_intrinsics: bool | None = None,
    adjust_labels: bool | None = None,
    reference: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Build the map from ``sequence[train]``, localize ``sequence[test]`` in each mode.

    Returns ``{"map": Map, "build_s": float, "test": Sequence, "summaries": {mode: dict}}``,
    each summary :func:`geoloc.evaluation.summarize_results` plus per-frame ``frame`` (the
    dataset's frame index) and ``reason``. ``locator`` is "paper" or "model";
    ``refine_intrinsics`` estimates the camera from the keyframes, ``adjust_labels`` corrects
    the training labels by bundle adjustment (:meth:`Map.build`; None: the core's default).
    With ``reference`` (:func:`load_reference_option`), also ``"reference"``: the file, the
    :class:`~geoloc.reference.ReferenceAlignment` fitted on the training frames that the
    reference has, and ``summaries`` ({mode: dict}) against the aligned reference.
    """
    from ..evaluation import score_against_reference, summarize_results
    from ..mapping import Map
    from ..reference import align_reference

    train_slice = train.resolve(len(sequence), options[0], sequence.name)
    test_slice = test.resolve(len(sequence), options[1], sequence.name)
    if sequence.poses is None:
        raise InvalidInputError(f"--dataset: {sequence.name!r} has no ground-truth poses (evaluate needs them)")
    overlap = _positions(train_slice) & _positions(test_slice)
    if overlap:
        print(
            f"geoloc: warning: {options[0]} {train} and {options[1]} {test} share {len(overlap)} frames "
            "(those test frames are in the map)",
            file=sys.stderr,
        )
    train_seq, test_seq = sequence[train_slice], sequence[test_slice]
    if reference is not None:  # checked before the map is built (the alignment on the labels)
        train_rows = _reference_rows(reference, train_seq, "train")
        _check_numbering(reference, train_seq)
        test_reference = reference["poses"][_reference_rows(reference, test_seq, "test")]
        on_labels = align_reference(reference["poses"][train_rows[train_rows >= 0]], train_seq.poses[train_rows >= 0])
        _checked_alignment_uncertainty(on_labels, test_reference, reference["file"])
    start = time.perf_counter()
    network = open_retrieval(retrieval)
    the_map = Map.build(
        train_seq,
        retrieval=network,
        features=features,
        n_features=n_features,
        refine_intrinsics=refine_intrinsics,
        adjust_labels=adjust_labels,
        model=False if locator == "paper" else None,
        progress=Progress("map", then=MAP_DONE),
    )
    build_s = time.perf_counter() - start
    against: dict[str, Any] | None = None
    if reference is not None:
        fitted = train_rows >= 0
        targets = map_keyframe_poses(the_map, train_seq.poses)
        alignment = align_reference(reference["poses"][train_rows[fitted]], targets[fitted])
        alignment_sigma = _checked_alignment_uncertainty(alignment, test_reference, reference["file"])
        against = {
            "file": reference["file"],
            "format": reference["format"],
            "fitted_to": "labels" if targets is train_seq.poses else "map keyframe poses",
            "alignment": alignment,
            "alignment_sigma": alignment_sigma,
            "summaries": {},
        }
    summaries: dict[str, Any] = {}
    for mode in modes:
        localizer = command_localizer(the_map, None if network == "bow" else network, locator)
        results = localize_sequence(localizer, test_seq, mode, Progress(f"{mode:>10}"))
        summary = summarize_results(results, test_seq.poses, test_seq.timestamps)
        scored = [(summaries, summary)]
        if against is not None:
            scored.append((against["summaries"], score_against_reference(results, against["alignment"], test_reference, test_seq.timestamps)))
        for into, s in scored:
            for entry, r, frame in zip(s["per_frame"], results, test_seq.indices):
                entry["frame"] = int(frame)
                entry["reason"] = r.reason
            s["mode"] = mode
            into[mode] = s
    out = {"map": the_map, "build_s": build_s, "test": test_seq, "summaries": summaries, "train_slice": train_slice, "test_slice": test_slice}
    if against is not None:
        out["reference"] = against
    return out


def reference_for(dataset: str | None, fmt: str) -> tuple[str, dict[str, tuple[float, float]]] | None:
    """The paper's 7-Scenes row for the scene named in the dataset's path, if any."""
    if fmt != "7scenes" or dataset is None:
        return None
    text = str(Path(dataset).resolve()).lower().replace("-", "").replace("_", "")
    for scene, row in PAPER_7SCENES.items():
        if scene in text:
            return scene, row
    return None


def report(
    sequence: Any,
    run: dict[str, Any],
    *,
    dataset: str | None,
    fmt: str,
    train: FrameRange,
    test: FrameRange,
    timings: bool,
    out: Any = None,
) -> dict[str, Any]:
    """Print the table (and per-stage times) to ``out``; return the JSON-ready result."""
    from ..evaluation import format_table

    out = out or sys.stdout
    summaries: dict[str, dict[str, Any]] = run["summaries"]
    against: dict[str, Any] | None = run.get("reference")
    suffix = "" if against is None else " vs labels"
    rows = {f"{sequence.name} ({mode}){suffix}": s for mode, s in summaries.items()}
    ref = reference_for(dataset, fmt)
    reference = None
    if ref is not None:
        reference = {f"{sequence.name} ({mode}){suffix}": ref[1][mode] for mode in summaries}
    table_rows = dict(rows)
    if against is not None:  # each mode's row against the labels, then against the reference
        table_rows = {}
        for mode, s in summaries.items():
            table_rows[f"{sequence.name} ({mode}) vs labels"] = s
            table_rows[f"{sequence.name} ({mode}) vs reference"] = against["summaries"][mode]
    cam = sequence.camera
    print(
        f"{sequence.name}: map of {len(run['map'])} keyframes (frames {train}) built in {run['build_s']:.1f} s; "
        f"{len(run['test'])} test frames ({test}); camera fx={cam.intrinsics[0]:g} fy={cam.intrinsics[1]:g} "
        f"cx={cam.intrinsics[2]:g} cy={cam.intrinsics[3]:g}",
        file=out,
    )
    print(describe_self_calibration(run["map"].self_calibration), file=out)
    print(describe_labels(run["map"].labels), file=out)
    print(format_table(table_rows, reference), file=out)
    if against is not None:
        print(describe_alignment(against), file=out)
    if ref is not None:
        single, multi = ref[1]["single"], ref[1]["sequential"]
        print(
            f"Reference: the paper's 7-Scenes {ref[0]} row (Table III): single image {single[0]:.2f} m, {single[1]:.2f}°; "
            f"multiple images {multi[0]:.2f} m, {multi[1]:.2f}°",
            file=out,
        )
    if timings:
        print(file=out)
        print(stage_table(rows), file=out)
    primary = summaries[PRIMARY_MODE] if PRIMARY_MODE in summaries else next(iter(summaries.values()))
    result: dict[str, Any] = dict(primary)
    result.update(
        {
            "dataset": sequence.name,
            "format": fmt,
            "camera": {"intrinsics": list(cam.intrinsics), "width": cam.width, "height": cam.height},
            "train": str(train),
            "test": str(test),
            "map": {"keyframes": len(run["map"]), "build_s": run["build_s"], "self_calibration": run["map"].self_calibration},
            "modes": summaries,
        }
    )
    if ref is not None:
        result["reference"] = {"paper_7scenes_scene": ref[0], **{m: list(v) for m, v in ref[1].items()}}
    if against is not None:
        result["against_reference"] = {
            "file": str(against["file"]),
            "format": against["format"],
            "fitted_to": against["fitted_to"],
            "alignment": against["alignment"].as_dict(),
            "alignment_sigma_at_test_frames": {"position_m": against["alignment_sigma"][0], "rotation_deg": against["alignment_sigma"][1]},
            "modes": against["summaries"],
        }
    return result


def describe_alignment(against: dict[str, Any]) -> str:
    """One line on the reference's alignment: S, X and its residuals on the training frames."""
    a = against["alignment"]
    st = a.statistics()
    d = a.as_dict()
    return (
        f"Aligned reference {str(against['file'])!r} ({against['format']}): S·R·X fitted on {st['frames']} training frames to the "
        f"{against['fitted_to']} (Huber {a.position_scale_m * 100:g} cm / {a.rotation_scale_deg:g}°): scale {a.scale:.4f}, "
        f"offset X {d['offset_rotation_deg']:.2f}° / {a.scale * d['offset_translation'] * 100:.1f} cm; training residuals median "
        f"{st['median_position_m'] * 100:.1f} cm / {st['median_rotation_deg']:.2f}°, 90 % {st['p90_position_m'] * 100:.1f} cm / "
        f"{st['p90_rotation_deg']:.2f}°; the alignment's own uncertainty at the test frames ±{100 * against['alignment_sigma'][0]:.2g} cm / "
        f"±{against['alignment_sigma'][1]:.2g}° (median)"
    )


def plot_files(directory: str | None, modes: tuple[str, ...]) -> list[Path]:
    """The files :func:`write_plots` writes into ``directory`` for ``modes`` (none without a directory)."""
    from ..plots import PLOT_FILES

    if directory is None:
        return []
    return [Path(directory) / mode / name for mode in modes for name in PLOT_FILES.values()]


def plot_folders(directory: str, modes: tuple[str, ...], option: str) -> list[Path]:
    """Makes ``directory`` and ``directory/<mode>/`` for every mode before any work is done
    (``directory``'s parent must exist): a folder that cannot be made — a file in the way,
    no permission — is an InvalidInputError naming ``option`` before anything is computed or
    written, not after the results are. Returns the folders it made (not those that were
    there), parents first; a failure removes the ones it had made."""
    root = Path(directory)
    made: list[Path] = []
    try:
        for folder in (root, *(root / mode for mode in modes)):
            if folder.exists() and not folder.is_dir():
                raise InvalidInputError(f"{option}: {str(folder)!r} is a file, where the plots' folder goes")
            if folder.is_dir():
                continue
            try:
                folder.mkdir()
            except OSError as e:
                raise InvalidInputError(f"{option}: cannot create {str(folder)!r} ({e.strerror})") from None
            made.append(folder)
    except BaseException:
        remove_empty(made)
        raise
    return made


def remove_empty(folders: list[Path]) -> None:
    """Removes ``folders`` (parents first in the list), children first, each only if empty."""
    for folder in reversed(folders):
        try:
            folder.rmdir()
        except OSError:
            pass  # not empty (something else wrote there) or gone: leave it


@contextmanager
def folders_for_the_run(directory: str | Path | None, modes: tuple[str, ...], option: str) -> Iterator[None]:
    """:func:`plot_folders` before the work in the ``with`` block (nothing without a
    directory); when that work fails, the folders made here are removed again if still
    empty — a failed command leaves no empty folders behind."""
    made = [] if directory is None else plot_folders(str(directory), modes, option)
    try:
        yield
    except BaseException:
        remove_empty(made)
        raise


def write_plots(directory: str, summaries: dict[str, dict[str, Any]]) -> list[Path]:
    """The four PNGs of each mode into ``directory/<mode>/`` (:func:`plot_folders` made the
    folders)."""
    from ..plots import write_all

    root = Path(directory)
    plot_folders(directory, tuple(summaries), "--plots")
    written: list[Path] = []
    for mode, summary in summaries.items():
        written.extend(write_all(summary, root / mode).values())
    return written


def run(args: argparse.Namespace) -> int:
    """The ``evaluate`` command."""
    from .._io import refuse_alias, shown, write_json_atomic

    reference_file = getattr(args, "reference", None)
    reference_format = getattr(args, "reference_format", None)
    if reference_format is not None and reference_file is None:
        raise InvalidInputError("--reference-format: only used with --reference FILE")
    reference = None if reference_file is None else load_reference_option(reference_file, reference_format)
    sequence = load_dataset(args)
    inputs = [*dataset_inputs(sequence, "--dataset"), ("--reference", reference_file), *model_input(args.retrieval)]
    refuse_alias(args.json, "--json", inputs)
    for plot in plot_files(args.plots, _modes(args.mode)):
        refuse_alias(plot, "--plots", inputs)
    default_train, default_test = default_split(len(sequence), args.format)
    train = args.train or default_train
    test = args.test or default_test
    with folders_for_the_run(args.plots, _modes(args.mode), "--plots"):
        result = evaluate_split(
            sequence, train, test, _modes(args.mode), features=args.features, n_features=args.n_features,
            retrieval=args.retrieval, locator=args.locator, refine_intrinsics=args.refine_intrinsics,
            adjust_labels=args.adjust_labels, reference=reference,
        )
        data = report(sequence, result, dataset=args.dataset, fmt=args.format, train=train, test=test, timings=args.timings)
        if args.json:
            write_json_atomic(args.json, data, "--json")
            print(f"wrote {shown(args.json)}")
        if args.plots:
            write_plots(args.plots, result["summaries"])
            print(f"wrote plots to {shown(Path(args.plots) / ('{' + ','.join(result['summaries']) + '}'))}/")
    return 0
