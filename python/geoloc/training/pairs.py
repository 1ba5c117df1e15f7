"""Positive and negative image pairs from pose thresholds (numpy only, no torch).

The paper labels pairs with "arbitrary thresholds of the pose". Ours, in
:class:`PairThresholds` (defaults):

* **positive** (label 0, "similar"): ‖p_i − p_j‖ ≤ 0.3 m **and** Θ(R_iᵀR_j) ≤ 15° — the
  same 0.3 m / 15° that makes a retrieval correct in the recall@k evaluation;
* **negative** (label 1, "dissimilar"): ‖p_i − p_j‖ ≥ 1.0 m **or** Θ(R_iᵀR_j) ≥ 45°;
* pairs in between are never sampled (neither label is right for them).

Each epoch draws ``n_pos`` positives and ``n_neg`` negatives with a generator seeded by
(seed, epoch), so an epoch's pairs do not depend on how training got there (resume gives the
same pairs). Hard-negative mining (optional) replaces uniform negatives: for each anchor,
``candidates`` random negatives are scored with the current descriptors and the closest one
(the most confusable) is kept.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from ..exceptions import InvalidInputError

__all__ = ["PairSampler", "PairThresholds", "Pairs", "relative_motion"]

#: Label of a similar pair (the contrastive loss pulls it together) and of a dissimilar one.
SIMILAR, DISSIMILAR = 0, 1


@dataclass(frozen=True)
class PairThresholds:
    """Pose thresholds that label a pair; see the module doc. Metres and degrees."""

    pos_max_m: float = 0.3
    pos_max_deg: float = 15.0
    neg_min_m: float = 1.0
    neg_min_deg: float = 45.0

    def __post_init__(self) -> None:
        for name, v in asdict(self).items():
            if not np.isfinite(v) or v < 0:
                raise InvalidInputError(f"{name}: expected a finite number ≥ 0, got {v!r}")
        if self.neg_min_m < self.pos_max_m or self.neg_min_deg < self.pos_max_deg:
            raise InvalidInputError(
                "thresholds: a negative must be further than a positive "
                f"(neg_min_m {self.neg_min_m} ≥ pos_max_m {self.pos_max_m}, "
                f"neg_min_deg {self.neg_min_deg} ≥ pos_max_deg {self.pos_max_deg})"
            )

    def as_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in asdict(self).items()}


def relative_motion(poses: NDArray[np.float64], i: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Distance (m) and rotation angle (deg) from pose ``i`` to every pose: two (N,) arrays.

    Θ = atan2(‖vee(R − Rᵀ)‖/2, (tr R − 1)/2) with R = R_iᵀR_j: stable near 0 and π, never
    NaN for slightly non-orthonormal input.
    """
    dist = np.linalg.norm(poses[:, :3, 3] - poses[i, :3, 3], axis=1)
    rel = np.einsum("ba,nbc->nac", poses[i, :3, :3], poses[:, :3, :3])  # R_iᵀ R_j
    cos = (np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0
    skew = np.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]], axis=1)
    sin = np.linalg.norm(skew, axis=1) / 2.0
    return dist, np.degrees(np.arctan2(sin, cos))


@dataclass(frozen=True)
class Pairs:
    """Index pairs (first[k], second[k]) and their labels (0 similar, 1 dissimilar)."""

    first: NDArray[np.int64]
    second: NDArray[np.int64]
    label: NDArray[np.int64]

    def __len__(self) -> int:
        return len(self.label)


class PairSampler:
    """Samples labelled pairs among N posed images; see the module doc.

    ``poses`` (N, 4, 4) world_from_cam. Anchors without any positive (or negative) partner
    are never drawn for that kind of pair; if no image has one, sampling raises.
    """

    def __init__(self, poses: NDArray[np.float64], thresholds: PairThresholds | None = None, seed: int = 0) -> None:
        p = np.asarray(poses, dtype=np.float64)
        if p.ndim != 3 or p.shape[1:] != (4, 4) or len(p) < 2:
            raise InvalidInputError(f"poses: expected (N, 4, 4) with N ≥ 2, got {p.shape}")
        if not np.isfinite(p).all():
            raise InvalidInputError("poses: not finite (NaN or inf)")
        self.poses = p
        self.thresholds = thresholds or PairThresholds()
        self.seed = int(seed)
        # Positives are few and kept; negatives are most pairs, so only their count is kept
        # (O(N) memory) and an anchor's list is recomputed when it is drawn.
        self._positives: list[NDArray[np.int64]] = []
        n_negatives = np.zeros(len(p), dtype=np.int64)
        for i in range(len(p)):
            pos, neg = self._partners(i)
            self._positives.append(np.flatnonzero(pos))
            n_negatives[i] = int(neg.sum())
        self._n_negatives = n_negatives
        self._pos_anchors = np.array([i for i, a in enumerate(self._positives) if len(a)], dtype=np.int64)
        self._neg_anchors = np.flatnonzero(n_negatives > 0).astype(np.int64)

    def _partners(self, i: int) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
        t = self.thresholds
        dist, angle = relative_motion(self.poses, i)
        pos = (dist <= t.pos_max_m) & (angle <= t.pos_max_deg)
        pos[i] = False
        neg = (dist >= t.neg_min_m) | (angle >= t.neg_min_deg)
        return pos, neg

    def __len__(self) -> int:
        return len(self.poses)

    def positives(self, i: int) -> NDArray[np.int64]:
        """Indices of i's positive partners."""
        return self._positives[i]

    def negatives(self, i: int) -> NDArray[np.int64]:
        """Indices of i's negative partners."""
        return np.flatnonzero(self._partners(i)[1])

    def stats(self) -> dict[str, Any]:
        """How many anchors have a positive / negative partner, and the mean counts."""
        return {
            "images": len(self),
            "anchors_with_positive": int(len(self._pos_anchors)),
            "anchors_with_negative": int(len(self._neg_anchors)),
            "mean_positives": float(np.mean([len(a) for a in self._positives])),
            "mean_negatives": float(self._n_negatives.mean()),
        }

    def rng(self, epoch: int) -> np.random.Generator:
        """The generator of ``epoch`` (seeded by (seed, epoch))."""
        return np.random.default_rng([self.seed, int(epoch)])

    def sample(
        self,
        epoch: int,
        n_pos: int = 128,
        n_neg: int = 128,
        descriptors: NDArray[np.float32] | None = None,
        candidates: int = 32,
    ) -> Pairs:
        """``n_pos`` positives then ``n_neg`` negatives for ``epoch``; with ``descriptors``
        ((N, D), the current network's) each negative is the closest of ``candidates``."""
        rng = self.rng(epoch)
        if n_pos and not len(self._pos_anchors):
            raise InvalidInputError(
                f"no image has a positive partner within {self.thresholds.pos_max_m} m / {self.thresholds.pos_max_deg}°: "
                "the images are too far apart for these thresholds"
            )
        if n_neg and not len(self._neg_anchors):
            raise InvalidInputError(
                f"no pair of images is {self.thresholds.neg_min_m} m or {self.thresholds.neg_min_deg}° apart: "
                "need a larger scene (or smaller negative thresholds)"
            )
        first, second = [], []
        for a in rng.choice(self._pos_anchors, size=n_pos) if n_pos else []:
            first.append(a)
            second.append(rng.choice(self._positives[a]))
        for a in rng.choice(self._neg_anchors, size=n_neg) if n_neg else []:
            partners = self.negatives(int(a))
            if descriptors is None:
                b = rng.choice(partners)
            else:
                cand = rng.choice(partners, size=min(candidates, len(partners)), replace=False)
                d2 = ((descriptors[cand] - descriptors[a]) ** 2).sum(axis=1)
                b = cand[int(np.argmin(d2))]
            first.append(a)
            second.append(b)
        label = np.array([SIMILAR] * n_pos + [DISSIMILAR] * n_neg, dtype=np.int64)
        return Pairs(np.array(first, dtype=np.int64), np.array(second, dtype=np.int64), label)
