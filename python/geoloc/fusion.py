"""Gated, covariance-weighted fusion of the geometric pose with the motion prediction."""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import _core
from ._validation import as_float64, choice, real_scalar
from .exceptions import InvalidInputError

__all__ = ["FusionResult", "fuse"]

Array = NDArray[np.float64]


#: The fused pose (a compiled class): ``pose`` (4, 4), ``covariance`` (6, 6), ``source`` —
#: ``"fused"`` or ``"motion"`` (the geometric pose failed the gate) — and the Gauss–Newton
#: ``iterations`` and ``termination`` (0 and None when gated).
FusionResult = _core.FusionResult


def _one(x: ArrayLike, name: str, shape: tuple[int, int]) -> Array:
    c = as_float64(x, name)
    if c.shape != shape:
        raise InvalidInputError(f"{name}: expected shape {shape}, got {c.shape}")
    return np.ascontiguousarray(c)


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
    return _core.fuse(
        _one(pose_m, "pose_m", (4, 4)), _one(cov_m, "cov_m", (6, 6)), _one(pose_g, "pose_g", (4, 4)),
        _one(cov_g, "cov_g", (6, 6)), gate_sigma=real_scalar(gate_sigma, "gate_sigma"),
        gate=choice(gate, "gate", ("isometric", "chi2")),
    )
