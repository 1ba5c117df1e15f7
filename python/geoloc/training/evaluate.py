"""Retrieval recall@k from poses (torch-free): is the retrieved training image near the query?

A retrieval is correct when the retrieved training image lies within ``max_m`` metres and
``max_deg`` degrees of the query's true pose (defaults 0.3 m / 15°, the positive thresholds
of :class:`.pairs.PairThresholds`). recall@k: the fraction of queries with a correct image
among the first k. The *ceiling* — the fraction of queries that have any correct training
image at all — bounds every method (on the 7-Scenes split many test frames have none).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from ..exceptions import InvalidInputError
from ..retrieval import DescriptorIndex
from .pairs import relative_motion

__all__ = ["RecallReport", "correct_matrix", "rank_by_descriptors", "recall_at_k"]

DEFAULT_MAX_M = 0.3
DEFAULT_MAX_DEG = 15.0
#: Model selection (:mod:`.selection`): the last fraction of the training frames held out ...
VALIDATION_FRACTION = 0.15
#: ... with this many frames before the block left out of training too (the folds' margin) ...
VALIDATION_MARGIN = 15
#: ... and recall@1 on it measured this many times over a run (every epochs // 10 epochs).
MEASUREMENTS = 10


def correct_matrix(
    train_poses: NDArray[np.float64], query_poses: NDArray[np.float64], max_m: float = DEFAULT_MAX_M, max_deg: float = DEFAULT_MAX_DEG
) -> NDArray[np.bool_]:
    """(Q, N) boolean: training image j is a correct retrieval for query q."""
    both = np.concatenate([np.asarray(train_poses, np.float64), np.asarray(query_poses, np.float64)])
    n = len(train_poses)
    out = np.zeros((len(query_poses), n), dtype=bool)
    for q in range(len(query_poses)):
        dist, angle = relative_motion(both, n + q)
        out[q] = (dist[:n] <= max_m) & (angle[:n] <= max_deg)
    return out


def rank_by_descriptors(train: NDArray[np.float32], queries: NDArray[np.float32], k: int = 5) -> NDArray[np.int64]:
    """(Q, k) indices of the k nearest training descriptors (exact L2, DescriptorIndex)."""
    _, ind = DescriptorIndex(train).query(queries, k=min(k, len(train)))
    return ind


@dataclass(frozen=True)
class RecallReport:
    """recall@1, recall@k and the ceiling (fractions of the queries)."""

    recall_at_1: float
    recall_at_k: float
    k: int
    ceiling: float
    queries: int

    def __str__(self) -> str:
        return (
            f"recall@1 {100 * self.recall_at_1:.1f} %  recall@{self.k} {100 * self.recall_at_k:.1f} %  "
            f"(ceiling {100 * self.ceiling:.1f} %, {self.queries} queries)"
        )


def recall_at_k(correct: NDArray[np.bool_], ranked: NDArray[np.int64], k: int = 5) -> RecallReport:
    """recall@1 and recall@k of ``ranked`` ((Q, ≥k) indices, best first) under ``correct``."""
    ranked = np.asarray(ranked)
    if ranked.ndim != 2 or ranked.shape[0] != correct.shape[0] or ranked.shape[1] < 1:
        raise InvalidInputError(f"ranked: expected ({correct.shape[0]}, k) indices, got {ranked.shape}")
    hits = np.take_along_axis(correct, ranked, axis=1)
    return RecallReport(
        recall_at_1=float(hits[:, 0].mean()),
        recall_at_k=float(hits[:, :k].any(axis=1).mean()),
        k=int(min(k, ranked.shape[1])),
        ceiling=float(correct.any(axis=1).mean()),
        queries=int(correct.shape[0]),
    )
