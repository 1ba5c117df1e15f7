"""The constant-velocity motion model (see geoloc-core ``motion``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import _core
from ._validation import as_batch, as_float64
from .exceptions import InvalidInputError

__all__ = ["MotionPrediction", "motion_predict"]

Array = NDArray[np.float64]


@dataclass(frozen=True)
class MotionPrediction:
    """A one-step prediction: pose (4, 4) world_from_cam, covariance (6, 6, right
    perturbation, translation first), the fitted body velocity (v, ω) per second and the RMS
    of the fit residuals."""

    pose: Array
    covariance: Array
    velocity: Array
    rms_residual: float


def motion_predict(
    poses: ArrayLike, timestamps: ArrayLike, t_query: float, covariances: ArrayLike | None = None
) -> MotionPrediction:
    """Fit T(t) = T_r exp((t − t_r) ξ^) to the last poses (world_from_cam, (m, 4, 4)) at
    ``timestamps`` (seconds; irregular spacing and dropped frames are fine) and predict the
    pose at ``t_query``.

    With ``covariances`` (m, 6, 6) of the poses the fit is weighted and the predicted
    covariance is calibrated when the motion is constant; without them (the paper's way) the
    per-axis noise is estimated from the fit residuals, which needs m ≥ 3.
    """
    flat, lead = as_batch(poses, "poses", (4, 4))
    if len(lead) != 1:
        raise InvalidInputError(f"poses: expected shape (m, 4, 4), got {np.shape(poses)}")
    t = as_float64(timestamps, "timestamps")
    if t.shape != (flat.shape[0],):
        raise InvalidInputError(f"timestamps: expected shape ({flat.shape[0]},) like poses, got {t.shape}")
    tq = as_float64(t_query, "t_query")
    if tq.shape != ():
        raise InvalidInputError(f"t_query: expected a number, got shape {tq.shape}")
    covs = None
    if covariances is not None:
        c = as_float64(covariances, "covariances")
        if c.shape != (flat.shape[0], 6, 6):
            raise InvalidInputError(f"covariances: expected shape ({flat.shape[0]}, 6, 6), got {c.shape}")
        covs = np.ascontiguousarray(c.reshape(-1, 36))
    raw: dict[str, Any] = _core.motion_predict(flat, np.ascontiguousarray(t), float(tq), covs)
    return MotionPrediction(
        pose=raw["pose"].reshape(4, 4),
        covariance=raw["covariance"].reshape(6, 6),
        velocity=np.asarray(raw["velocity"]),
        rms_residual=float(raw["rms_residual"]),
    )
