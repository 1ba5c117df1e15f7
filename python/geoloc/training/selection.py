"""Model selection on held-out training frames: which epoch's network to keep.

The training loss says how well the network separates the pairs it trains on, not how well it
retrieves images it has not seen — on 7-Scenes the paper's GoogLeNet reaches a loss of 0.003
while its recall@1 on new frames stays at 21–25 % and falls late in training. So a part of the
*training* frames is held out (never the test frames, which the caller keeps apart):

* the **validation block** is the last ``fraction`` of the frames in the order given — one
  contiguous block, as a robot's later visit to a place would be — and the ``margin`` frames
  before it are dropped from training too (they see what the block sees from a step away;
  the project's folds use 15 frames on either side);
* every ``every`` epochs (and after the last) the network describes the training frames
  (the database) and the block (the queries); recall@1 is the fraction of queries whose
  nearest training descriptor is a correct retrieval (within 0.3 m / 15° of the query's pose,
  :func:`.evaluate.correct_matrix`);
* the network of the best recall@1 (the earliest on a tie) is the result.

A block of fewer than :data:`MIN_VALIDATION_FRAMES` frames, or a split that leaves fewer than 2
training frames, measures nothing: selection is then off and the last epoch is kept (the
:class:`ValidationSplit` says why).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from numpy.typing import NDArray

from .evaluate import correct_matrix, rank_by_descriptors, recall_at_k

#: Fewest frames in a validation block worth measuring.
MIN_VALIDATION_FRAMES = 10


@dataclass(frozen=True)
class ValidationSplit:
    """Positions (into the frames given) of the training frames and of the validation block;
    ``validation`` empty and ``why`` set when selection is off."""

    train: NDArray[np.int64]
    validation: NDArray[np.int64]
    why: str = ""

    @property
    def active(self) -> bool:
        return len(self.validation) > 0


def split_validation(n: int, fraction: float, margin: int) -> ValidationSplit:
    """The last ``ceil(fraction · n)`` of ``n`` frames as the validation block, the ``margin``
    frames before it dropped, the rest for training (see the module doc)."""
    everything = np.arange(n, dtype=np.int64)
    none = np.zeros(0, dtype=np.int64)
    if fraction <= 0:
        return ValidationSplit(everything, none, "no validation block asked for")
    size = int(np.ceil(fraction * n))
    start = n - size
    train = everything[: max(start - margin, 0)]
    if size < MIN_VALIDATION_FRAMES or len(train) < 2:
        why = f"{size} validation frames and {len(train)} training frames are too few to select on (at least {MIN_VALIDATION_FRAMES} and 2)"
        return ValidationSplit(everything, none, why)
    return ValidationSplit(train, everything[start:])


@dataclass
class Selector:
    """Recall@1 of a network on the validation block, and the best network so far.

    ``poses`` and ``gray`` are all the frames' (the split's positions index them)."""

    split: ValidationSplit
    poses: NDArray[np.float64]
    gray: NDArray[np.uint8]
    curve: list[tuple[int, float]] = field(default_factory=list)
    best_epoch: int | None = None
    best_state: dict[str, torch.Tensor] | None = None

    def __post_init__(self) -> None:
        self._correct = correct_matrix(self.poses[self.split.train], self.poses[self.split.validation])

    def recall_at_1(self, descriptors: NDArray[np.float32]) -> float:
        """recall@1 of the validation block given every frame's descriptor (N, D)."""
        ranked = rank_by_descriptors(descriptors[self.split.train], descriptors[self.split.validation], k=1)
        return recall_at_k(self._correct, ranked, k=1).recall_at_1

    def record(self, epoch: int, recall: float, model: torch.nn.Module) -> None:
        """Adds (epoch, recall@1) to the curve; keeps the model's weights if it is the best."""
        self.curve.append((epoch, recall))
        if self.best_epoch is None or recall > max(r for e, r in self.curve[:-1]):
            self.best_epoch = epoch
            self.best_state = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}

    def as_dict(self) -> dict[str, object]:
        """The curve and the choice, for a checkpoint or a report (no weights)."""
        return {
            "validation_frames": int(len(self.split.validation)),
            "training_frames": int(len(self.split.train)),
            "curve": [[e, r] for e, r in self.curve],
            "best_epoch": self.best_epoch,
        }

    def restore(self, saved: dict[str, object], best_state: dict[str, torch.Tensor] | None) -> None:
        """Continues a curve saved by :meth:`as_dict` (a resumed run)."""
        curve = saved.get("curve", [])
        assert isinstance(curve, list)
        self.curve = [(int(e), float(r)) for e, r in curve]
        best = saved.get("best_epoch")
        self.best_epoch = None if best is None else int(best)  # type: ignore[call-overload]
        self.best_state = best_state
