"""Gated, covariance-weighted fusion of the geometric pose with the motion prediction."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import _core
from ._validation import as_batch, as_float64
from .exceptions import InvalidInputError

__all__ = ["FusionResult", "fuse"]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class FusionResult:
    """The fused pose (4, 4), its covariance (6, 6) and where it came from: ``"fused"`` or
    ``"motion"`` (the geometric pose failed the gate)."""

    pose: Array
    covariance: Array
    source: str
    iterations: int


def _one_pose(x: ArrayLike, name: str) -> Array:
    flat, lead = as_batch(x, name, (4, 4))
    if lead != ():
        raise InvalidInputError(f"{name}: expected shape (4, 4), got {np.shape(x)}")
    return flat


def _one_cov(x: ArrayLike, name: str) -> Array:
    c = as_float64(x, name)
    if c.shape != (6, 6):
        raise InvalidInputError(f"{name}: expected shape (6, 6), got {c.shape}")
    return np.ascontiguousarray(c.reshape(1, 36))


def fuse(
    pose_m: ArrayLike,
    cov_m: ArrayLike,
    pose_g: ArrayLike,
    cov_g: ArrayLike,
    gate_sigma: float = 3.0,
    gate: Literal["isometric", "chi2"] = "isometric",
) -> FusionResult:
    """Fuse the motion prediction (T_M, C_M) with the geometric pose (T_G, C_G).

    The geometric pose is first gated: ``"isometric"`` (the paper's) rejects it when its
    position or rotation lies beyond ``gate_sigma`` isometric σ of T_M; ``"chi2"`` when the
    6-DoF Mahalanobis distance of log(T_M⁻¹T_G) under C_M + C_G exceeds the χ²₆ quantile of
    the same probability. A rejected T_G gives T_M, C_M (source ``"motion"``); otherwise
    Gauss–Newton minimizes ‖log(T_M⁻¹T)‖²_{C_M⁻¹} + ‖log(T_G⁻¹T)‖²_{C_G⁻¹} and C_F = H⁻¹.
    Covariances: right perturbation, translation first.
    """
    if gate not in ("isometric", "chi2"):
        raise InvalidInputError(f"gate: expected 'isometric' or 'chi2', got {gate!r}")
    raw: dict[str, Any] = _core.fuse(
        _one_pose(pose_m, "pose_m"), _one_cov(cov_m, "cov_m"), _one_pose(pose_g, "pose_g"), _one_cov(cov_g, "cov_g"),
        float(gate_sigma), gate,
    )
    return FusionResult(
        pose=raw["pose"].reshape(4, 4),
        covariance=raw["covariance"].reshape(6, 6),
        source=str(raw["source"]),
        iterations=int(raw["iterations"]),
    )
