"""What several commands share: datasets from options, frame ranges, progress, localization runs.

Errors a user can cause are raised as :class:`geoloc.InvalidInputError` whose message starts
with the option's name (``--test: …``); :func:`geoloc.cli.main` prints it as one line.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from ..exceptions import DatasetError, InvalidInputError
from ..localizer import SEQUENCE_MODES

__all__ = [
    "FORMATS",
    "MODES",
    "FrameRange",
    "Progress",
    "dataset_inputs",
    "load_dataset",
    "localize_sequence",
    "select",
]

#: The dataset formats ``--format`` accepts.
FORMATS = ("7scenes", "tum", "folder", "synthetic")
#: Localization modes: ``single`` forgets the motion history before every frame (the
#: paper's single-image row); ``sequential`` keeps it (motion model + fusion).
MODES = SEQUENCE_MODES
#: What the map's progress bar says once every keyframe's features are extracted.
MAP_DONE = "features done; training the vocabulary and indexing the keyframes"
#: Frames of the built-in room when ``--format synthetic`` (two laps).
SYNTHETIC_FRAMES = 300


@dataclass(frozen=True)
class FrameRange:
    """``A:B`` or ``A:B:K`` (half-open, 0-based positions in the sequence as loaded, every
    K-th frame); ``A`` or ``B`` may be left out (``600:`` = from 600 to the end)."""

    start: int | None
    stop: int | None
    step: int = 1

    @classmethod
    def parse(cls, text: str) -> FrameRange:
        parts = text.split(":")
        if len(parts) not in (2, 3):
            raise ValueError(f"expected A:B or A:B:K (frame positions), got {text!r}")
        try:
            values = [None if p.strip() == "" else int(p, 10) for p in parts]
        except ValueError:
            raise ValueError(f"expected integers in A:B or A:B:K, got {text!r}") from None
        start, stop = values[0], values[1]
        step = values[2] if len(values) == 3 and values[2] is not None else 1
        if (start is not None and start < 0) or (stop is not None and stop < 0):
            raise ValueError(f"frame positions must be ≥ 0, got {text!r}")
        if step < 1:
            raise ValueError(f"the step K must be ≥ 1, got {text!r}")
        if start is not None and stop is not None and stop <= start:
            raise ValueError(f"expected A < B, got {text!r}")
        return cls(start, stop, step)

    def __str__(self) -> str:
        a = "" if self.start is None else str(self.start)
        b = "" if self.stop is None else str(self.stop)
        return f"{a}:{b}" + (f":{self.step}" if self.step != 1 else "")

    def resolve(self, n: int, option: str, name: str) -> slice:
        """The slice into a sequence of ``n`` frames; InvalidInputError naming ``option`` when
        the range is not inside it."""
        start = 0 if self.start is None else self.start
        stop = n if self.stop is None else self.stop
        if start >= n or stop > n or stop <= start:
            raise InvalidInputError(
                f"{option}: {self} is outside the sequence {name!r}, which has {n} frames (positions 0:{n})"
            )
        return slice(start, stop, self.step)


def select(sequence: Any, frames: FrameRange | None, option: str) -> Any:
    """``sequence[frames]`` checked against its length (the whole sequence when None)."""
    if frames is None:
        return sequence
    return sequence[frames.resolve(len(sequence), option, sequence.name)]


def load_dataset(args: argparse.Namespace, camera: Any = None, poses: bool = True) -> Any:
    """The :class:`~geoloc.datasets.Sequence` named by ``--dataset``/``--format`` (and
    ``--intrinsics``, ``--trajectory``, ``--synthetic-frames`` where the command has them).

    ``camera`` (a :class:`geoloc.Camera`) is used when ``--intrinsics`` is not given and the
    format needs intrinsics (a map's camera, for ``localize``). ``poses=False`` (images to
    localize): a ``tum`` or ``folder`` dataset's every image, its trajectory not read — an
    image without a pose is not dropped.
    """
    from .. import datasets

    fmt = args.format
    intrinsics = getattr(args, "intrinsics", None)
    if fmt == "synthetic":
        if args.dataset not in (None, "synthetic"):
            raise InvalidInputError(
                f"--dataset: not used with --format synthetic (the room is built in), got {args.dataset!r}"
            )
        if intrinsics is not None:
            raise InvalidInputError("--intrinsics: the synthetic room has its own camera (525, 525, 319.5, 239.5)")
        return datasets.synthetic_room(n_frames=getattr(args, "synthetic_frames", SYNTHETIC_FRAMES))
    if args.dataset is None:
        raise InvalidInputError(f"--dataset: required with --format {fmt} (a dataset folder)")
    root = Path(args.dataset)
    if not root.is_dir():
        if root.exists():
            raise InvalidInputError(f"--dataset: folder {str(root)!r} is a file, expected a folder")
        raise InvalidInputError(f"--dataset: no such file or folder: {str(root)!r} does not exist")
    try:
        return _load_files(args, fmt, root, intrinsics if intrinsics is not None else camera, poses)
    except DatasetError as e:
        raise InvalidInputError(option_message(str(e), "--dataset")) from None


#: Loader argument names → the command-line options that set them.
_OPTION_OF = {"path": None, "intrinsics": "--intrinsics", "trajectory": "--trajectory", "match": "--trajectory"}


def option_message(message: str, option: str) -> str:
    """A loader's message (``"path: …"``, ``"intrinsics: …"``) re-headed with the option
    that set that argument (``option`` for the dataset path itself, and by default)."""
    head, sep, rest = message.partition(": ")
    if sep and head in _OPTION_OF:
        return f"{_OPTION_OF[head] or option}: {rest}"
    return f"{option}: {message}"


def _load_files(args: argparse.Namespace, fmt: str, root: Path, given: Any, poses: bool = True) -> Any:
    from .. import datasets

    trajectory = getattr(args, "trajectory", None)
    if trajectory is not None and fmt != "folder":
        raise InvalidInputError(f"--trajectory: only used with --format folder (a {fmt} dataset has its own poses)")
    if fmt == "7scenes":
        return datasets.load_7scenes(root, intrinsics=given if given is not None else (525.0, 525.0, 320.0, 240.0))
    if fmt == "tum":
        return datasets.load_tum(root, intrinsics=given, ground_truth=poses)
    if given is None:
        raise InvalidInputError("--intrinsics: a plain image folder has no calibration; pass --intrinsics fx,fy,cx,cy")
    if not poses:
        return _every_image(root, given)
    if trajectory is not None and not str(trajectory).strip():
        raise InvalidInputError(f"--trajectory: expected a file name in {str(root)!r}, got {trajectory!r}")
    if trajectory is not None and (root / trajectory).is_dir():
        raise InvalidInputError(f"--trajectory: {str(root / trajectory)!r} is a folder, not a trajectory file")
    if trajectory is not None and not (root / trajectory).is_file():
        raise InvalidInputError(f"--trajectory: file {str(root / trajectory)!r} does not exist")
    return datasets.load_folder(root, trajectory=trajectory if trajectory is not None else "traj.txt", intrinsics=given)


def _every_image(root: Path, intrinsics: Any) -> Any:
    """Every image of a ``folder`` dataset, to localize: timed by its trajectory ``traj.txt``
    when that gives every image a pose (a folder of unnumbered images has no other clock),
    else by the images' names (or index / 30 s), with a warning on stderr that the
    trajectory does not cover them — never an image left out for want of a pose."""
    from .. import datasets

    every = datasets.load_folder(root, trajectory=None, intrinsics=intrinsics)
    if not (root / "traj.txt").is_file():
        return every
    try:
        timed = datasets.load_folder(root, trajectory="traj.txt", intrinsics=intrinsics)
    except DatasetError as e:
        why = str(e).partition(": ")[2] or str(e)
    else:
        if len(timed) == len(every):
            return timed
        why = f"it gives {len(timed)} of the {len(every)} images a pose"
    print(f"geoloc: warning: --dataset: traj.txt does not time every image ({why}); localizing all {len(every)} "
          "images, timed by their names", file=sys.stderr)
    return every


def dataset_inputs(sequence: Any, option: str) -> list[tuple[str, Any]]:
    """``(option, file)`` for every file ``sequence`` was read from (for
    :func:`geoloc._io.refuse_alias`: no output may replace one of them)."""
    return [(option, f) for f in getattr(sequence, "files", ())]


def model_input(retrieval: str | None) -> list[tuple[str, Any]]:
    """``--retrieval``'s model file as an input (none for ``bow``)."""
    return [] if retrieval in (None, "bow") else [("--retrieval", retrieval)]


class Progress:
    """A one-line progress bar on stderr (only when stderr is a terminal), redrawn at each
    percent; ``then`` is a line printed when the bar is full (what comes next, unbarred)."""

    WIDTH = 30

    def __init__(self, label: str, enabled: bool | None = None, then: str | None = None) -> None:
        self.label = label
        self.then = then
        self.enabled = sys.stderr.isatty() if enabled is None else enabled
        self._start = time.perf_counter()

    def __call__(self, done: int, total: int) -> None:
        if not self.enabled or total <= 0 or (done != total and done % max(1, total // 100)):
            return
        filled = int(self.WIDTH * done / total)
        elapsed = time.perf_counter() - self._start
        sys.stderr.write(f"\r{self.label} [{'#' * filled}{'.' * (self.WIDTH - filled)}] {done}/{total} {elapsed:.0f}s")
        if done == total:
            sys.stderr.write("\n" if self.then is None else f"\n{self.label}: {self.then}\n")
        sys.stderr.flush()


def localize_sequence(
    localizer: Any, sequence: Any, mode: str, progress: Callable[[int, int], None] | None = None
) -> list[Any]:
    """:meth:`geoloc.Localizer.localize_sequence` with the error named as the option ``--mode``."""
    if mode not in MODES:
        raise InvalidInputError(f"--mode: expected one of {', '.join(MODES)}, got {mode!r}")
    results: list[Any] = localizer.localize_sequence(sequence, mode, progress)
    return results


def stage_table(summaries: dict[str, dict[str, Any]]) -> str:
    """Per-stage median milliseconds, one column per row of ``summaries``."""
    names = list(summaries)
    stages: list[str] = []
    for s in summaries.values():
        for key in s.get("timing_ms", {}):
            stage = key.removeprefix("median_")
            if stage not in stages:
                stages.append(stage)
    order = ["decode", "features", "retrieval", "keyframes", "map_points", "matching", "pnp", "motion_fusion"]
    stages = [s for s in order if s in stages] + sorted(s for s in stages if s not in order and s != "total")
    stages.append("total")
    rows = [["stage (median ms)", *names]]
    for stage in stages:
        cells = []
        for name in names:
            v = summaries[name].get("timing_ms", {}).get(f"median_{stage}")
            cells.append("—" if v is None else f"{v:.2f}")
        rows.append([stage, *cells])
    widths = [max(len(r[i]) for r in rows) for i in range(len(rows[0]))]
    lines = ["  ".join(c.rjust(w) if i else c.ljust(w) for i, (c, w) in enumerate(zip(r, widths))) for r in rows]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)



def open_retrieval(text: str) -> Any:
    """``--retrieval``: ``"bow"``, or the :class:`geoloc.descriptor.OnnxDescriptor` of MODEL.onnx."""
    if text == "bow":
        return text
    from ..descriptor import OnnxDescriptor

    try:
        return OnnxDescriptor(text)
    except InvalidInputError as e:
        raise InvalidInputError(option_message(str(e), "--retrieval")) from None


def describe_self_calibration(found: dict[str, Any] | None) -> str:
    """One line on the camera a map estimated from its keyframes (``Map.self_calibration``); the
    track residuals' median first (what the robust fit lowers), then their RMS (a few large
    residuals dominate it, and it may rise as the many fall)."""
    if found is None:
        return "camera: the given intrinsics, as they are (--nominal-intrinsics)"
    cam = found.get("camera")
    if cam is None:
        return f"camera: the given intrinsics (not refined: {found['reason']})"
    k1, k2, p1, p2, _ = found["distortion"]
    return (
        f"camera estimated from the keyframes: fx {cam['fx']:.1f} fy {cam['fy']:.1f} cx {cam['cx']:.1f} cy {cam['cy']:.1f}, "
        f"k1 {k1:+.4f} k2 {k2:+.4f} p1 {p1:+.5f} p2 {p2:+.5f}; track residuals median {found['median_before_px']:.2f} -> "
        f"{found['median_after_px']:.2f} px, rms {found['rms_before_px']:.2f} -> {found['rms_after_px']:.2f} px "
        f"over {found['observations']} observations (correction 1σ "
        f"{found['correction_sigma_px']:.2f} px)"
    )


def describe_labels(found: dict[str, Any] | None) -> str:
    """One line on what the map's bundle adjustment found about its pose labels: the core's
    summary in ``Map.labels`` (what ``geoloc-rs info`` prints too)."""
    if found is None:
        return "labels: kept as the keyframes' truth (--keep-labels)"
    return f"labels {found['summary']}"


def describe_model(the_map: Any) -> str:
    """One line on the map's 3D model (``Map.model_points``): its size and, when the model
    locator could place no frame with it (the core refuses such a localizer), why."""
    from ..localizer import Localizer

    points = the_map.model_points
    if points is None:
        return "3D model: none stored (the model locator builds it when it starts)"
    try:
        Localizer(the_map, locator="model")
    except InvalidInputError as e:
        return f"3D model: {points} points; {str(e).removeprefix('locator: ')}"
    return f"3D model: {points} points"


def command_localizer(the_map: Any, network: Any, locator: str | None) -> Any:
    """``Localizer(the_map, global_descriptor=network, locator=locator)`` for a command: the
    core's refusal of the locator names the command's option (``--locator``), not the
    Python argument."""
    from ..localizer import Localizer

    try:
        return Localizer(the_map, global_descriptor=network, locator=locator)  # type: ignore[arg-type]
    except InvalidInputError as e:
        text = str(e)
        if not text.startswith("locator: "):
            raise
        hint = text.removeprefix("locator: ").replace("use the paper's locator", "use --locator paper")
        raise InvalidInputError(f"--locator: {hint}") from None


def describe_map_noise(noise: dict[str, Any]) -> str:
    """One line on the map's noise C_map (``Map.map_noise``): where it came from and the
    support it was measured at (the core's wording)."""
    return f"map noise C_map: {noise['pose_covariance_source']}"
