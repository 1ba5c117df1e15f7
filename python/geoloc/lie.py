"""SO(3) and SE(3) Lie-group operations, vectorized over leading batch axes.

Conventions (the same everywhere in geoloc):

* A pose ``T`` is **world_from_cam** (camera-to-world): ``p_world = R @ p_cam + t``.
* A twist is ``xi = (rho, phi)`` — **translation first** — and ``T = exp(xi^)``.
* Perturbations are on the **right**: ``T ⊞ δ = T @ exp(δ^)``; pose covariances live in that
  tangent space, translation first.
* Jacobians follow Barfoot, *State Estimation for Robotics* (2017):
  ``exp(xi + d) ≈ exp(xi) @ exp(J_r(xi) d) ≈ exp(J_l(xi) d) @ exp(xi)``, ``J_r(xi) = J_l(-xi)``.
* Angles in radians, translations in metres, everything float64.

Each function takes one item (e.g. ``phi`` of shape ``(3,)``) or a batch with any leading
axes (``(N, 3)``, ``(A, B, 3)``) and returns the same leading axes. A batch is one call into
Rust (geoloc-core), run without the GIL and in parallel for large batches. Bad input raises
:class:`geoloc.InvalidInputError` (a ``ValueError``) naming the argument; matrices that must
be rotations are checked to 1e-6 (:class:`geoloc.NotARotationError`) — project
near-rotations from real datasets with :func:`so3_project` / :func:`se3_project`.
"""

from __future__ import annotations

from typing import Any, Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import _core
from ._validation import as_batch, broadcast_batches
from .exceptions import InvalidInputError, NotARotationError

__all__ = [
    "MAX_ORTHONORMALITY_ERROR",
    "orthonormality_error",
    "rotation_angle",
    "se3_adjoint",
    "se3_compose",
    "se3_curly_hat",
    "se3_distance",
    "se3_exp",
    "se3_hat",
    "se3_interpolate",
    "se3_inverse",
    "se3_left_jacobian",
    "se3_left_jacobian_inv",
    "se3_log",
    "se3_project",
    "se3_right_jacobian",
    "se3_right_jacobian_inv",
    "se3_transform_points",
    "se3_vee",
    "so3_exp",
    "so3_from_quaternion_wxyz",
    "so3_hat",
    "so3_left_jacobian",
    "so3_left_jacobian_inv",
    "so3_log",
    "so3_project",
    "so3_project_near",
    "so3_right_jacobian",
    "so3_right_jacobian_inv",
    "so3_to_quaternion_wxyz",
    "so3_vee",
]

Array = NDArray[np.float64]
_CoreFn = Callable[..., Array]


def _call(
    core_fn: _CoreFn,
    args: list[tuple[Any, str, tuple[int, ...]]],
    out_shape: tuple[int, ...],
) -> Array:
    """Validate, broadcast, call ``core_fn`` on flat rows, and restore the batch shape."""
    batches = [(*as_batch(x, name, shape), name) for x, name, shape in args]
    if len(batches) == 1:
        flats, lead = [batches[0][0]], batches[0][1]
    else:
        flats, lead = broadcast_batches(batches)
    # a single item (no batch axis): the core names the argument without an index
    out = core_fn(*flats, single=lead == ())
    return out.reshape(lead + out_shape)


# ----------------------------------------------------------------------------- SO(3)


def so3_hat(phi: ArrayLike) -> Array:
    """``phi^``: the skew matrix with ``phi^ @ v = cross(phi, v)``. (…, 3) → (…, 3, 3)."""
    return _call(_core.so3_hat, [(phi, "phi", (3,))], (3, 3))


def so3_vee(M: ArrayLike) -> Array:
    """The inverse of :func:`so3_hat`, of the skew part ``(M - Mᵀ)/2``. (…, 3, 3) → (…, 3)."""
    return _call(_core.so3_vee, [(M, "M", (3, 3))], (3,))


def so3_exp(phi: ArrayLike) -> Array:
    """Rotation matrices ``exp(phi^)`` (Rodrigues). (…, 3) → (…, 3, 3)."""
    return _call(_core.so3_exp, [(phi, "phi", (3,))], (3, 3))


def so3_log(R: ArrayLike) -> Array:
    """Rotation vectors ``log(R)^∨`` with norm in [0, π]. (…, 3, 3) → (…, 3).

    Accurate at tiny angles and next to π (computed through the unit quaternion).
    """
    return _call(_core.so3_log, [(R, "R", (3, 3))], (3,))


def so3_project(R: ArrayLike) -> Array:
    """The nearest rotation (Frobenius norm) to each near-rotation matrix. (…, 3, 3).

    Use on real data whose rotations are slightly non-orthonormal (7-Scenes ships
    det ≈ 0.9995). Reflections and rank-deficient matrices raise NotARotationError.
    """
    return _call(_core.so3_project, [(R, "R", (3, 3))], (3, 3))


#: Largest ‖RᵀR − I‖_F of a rotation block read from a file that is projected onto SO(3): the
#: 7-Scenes release's blocks (det 0.9995–0.9999) are within 2e-3; a block further off is not a
#: rotation with rounding error but a wrong matrix (a shear, a scale), and is refused.
MAX_ORTHONORMALITY_ERROR = 1e-2


def orthonormality_error(R: ArrayLike) -> Array:
    """‖RᵀR − I‖_F of each 3×3 block. (…, 3, 3) → (…)."""
    r = np.asarray(R, dtype=np.float64)
    if r.shape[-2:] != (3, 3):
        raise InvalidInputError(f"R: expected (..., 3, 3), got {r.shape}")
    gram = np.swapaxes(r, -1, -2) @ r
    return np.asarray(np.linalg.norm(gram - np.eye(3), axis=(-2, -1)))


def so3_project_near(R: ArrayLike, name: str = "R") -> Array:
    """:func:`so3_project` for near-rotations only: every block must have
    ‖RᵀR − I‖_F ≤ :data:`MAX_ORTHONORMALITY_ERROR` and det > 0, else
    :class:`~geoloc.exceptions.NotARotationError` naming ``name`` (and the block's index in a
    batch) with its error. (…, 3, 3) → (…, 3, 3)."""
    r = np.asarray(R, dtype=np.float64)
    error = orthonormality_error(r)
    det = np.linalg.det(r) if np.isfinite(r).all() else np.full(error.shape, np.nan)
    bad = ~((error <= MAX_ORTHONORMALITY_ERROR) & (det > 0))
    if bad.any():
        where = "" if r.ndim == 2 else str([int(i) for i in np.argwhere(bad)[0]])
        e, d = float(np.asarray(error)[bad][0]), float(np.asarray(det)[bad][0])
        raise NotARotationError(
            f"{name}{where}: not a rotation (‖RᵀR − I‖_F = {e:.3g}, det {d:.4g}; "
            f"at most {MAX_ORTHONORMALITY_ERROR:g} and det > 0 are projected onto SO(3))"
        )
    return so3_project(r)


def rotation_angle(R: ArrayLike) -> Array:
    """Θ(R) = atan2(‖(R − Rᵀ)^∨‖/2, (tr R − 1)/2) ∈ [0, π]; never NaN. (…, 3, 3) → (…)."""
    return _call(_core.rotation_angle, [(R, "R", (3, 3))], ())


def so3_to_quaternion_wxyz(R: ArrayLike) -> Array:
    """Unit quaternions (w, x, y, z) of rotations (Shepperd's method). (…, 3, 3) → (…, 4)."""
    return _call(_core.so3_to_quaternion_wxyz, [(R, "R", (3, 3))], (4,))


def so3_from_quaternion_wxyz(q: ArrayLike) -> Array:
    """Rotations of quaternions (w, x, y, z), normalized first. (…, 4) → (…, 3, 3)."""
    return _call(_core.so3_from_quaternion_wxyz, [(q, "q", (4,))], (3, 3))


def so3_left_jacobian(phi: ArrayLike) -> Array:
    """J_l(φ) = I + (1 − cos θ)/θ² φ^ + (θ − sin θ)/θ³ φ^². (…, 3) → (…, 3, 3)."""
    return _call(_core.so3_left_jacobian, [(phi, "phi", (3,))], (3, 3))


def so3_right_jacobian(phi: ArrayLike) -> Array:
    """J_r(φ) = J_l(−φ): exp(φ + δ) ≈ exp(φ) exp(J_r(φ) δ). (…, 3) → (…, 3, 3)."""
    return _call(_core.so3_right_jacobian, [(phi, "phi", (3,))], (3, 3))


def so3_left_jacobian_inv(phi: ArrayLike) -> Array:
    """J_l⁻¹(φ) in closed form. (…, 3) → (…, 3, 3). ``phi`` at a nonzero multiple of 2π
    (to working precision: J_l's smallest singular value 2|sin(‖φ‖/2)|/‖φ‖ below 1e-9), where
    J_l is singular, raises InvalidInputError."""
    return _call(_core.so3_left_jacobian_inv, [(phi, "phi", (3,))], (3, 3))


def so3_right_jacobian_inv(phi: ArrayLike) -> Array:
    """J_r⁻¹(φ) = J_l⁻¹(−φ), the derivative of log(R exp(δ)) at δ = 0. (…, 3) → (…, 3, 3);
    refused where J_l is singular, as :func:`so3_left_jacobian_inv`."""
    return _call(_core.so3_right_jacobian_inv, [(phi, "phi", (3,))], (3, 3))


# ----------------------------------------------------------------------------- SE(3)


def se3_hat(xi: ArrayLike) -> Array:
    """``xi^ = [[phi^, rho], [0, 0]]`` for twists (rho, phi). (…, 6) → (…, 4, 4)."""
    return _call(_core.se3_hat, [(xi, "xi", (6,))], (4, 4))


def se3_vee(M: ArrayLike) -> Array:
    """The inverse of :func:`se3_hat`. (…, 4, 4) → (…, 6)."""
    return _call(_core.se3_vee, [(M, "M", (4, 4))], (6,))


def se3_curly_hat(xi: ArrayLike) -> Array:
    """ad(ξ) = [[φ^, ρ^], [0, φ^]], with Ad(exp ξ) = expm(ad ξ). (…, 6) → (…, 6, 6)."""
    return _call(_core.se3_curly_hat, [(xi, "xi", (6,))], (6, 6))


def se3_exp(xi: ArrayLike) -> Array:
    """Rigid transforms ``exp(xi^) = [[exp(phi^), J_l(phi) rho], [0, 1]]``. (…, 6) → (…, 4, 4)."""
    return _call(_core.se3_exp, [(xi, "xi", (6,))], (4, 4))


def se3_log(T: ArrayLike) -> Array:
    """Twists (rho, phi) = log(T)^∨, ‖phi‖ ∈ [0, π]. (…, 4, 4) → (…, 6)."""
    return _call(_core.se3_log, [(T, "T", (4, 4))], (6,))


def se3_inverse(T: ArrayLike) -> Array:
    """``T⁻¹ = [[Rᵀ, −Rᵀ t], [0, 1]]``. (…, 4, 4) → (…, 4, 4)."""
    return _call(_core.se3_inverse, [(T, "T", (4, 4))], (4, 4))


def se3_adjoint(T: ArrayLike) -> Array:
    """Ad(T) = [[R, t^ R], [0, R]] (translation-first twists). (…, 4, 4) → (…, 6, 6)."""
    return _call(_core.se3_adjoint, [(T, "T", (4, 4))], (6, 6))


def se3_project(T: ArrayLike) -> Array:
    """Rigid transforms with the rotation block projected onto SO(3). (…, 4, 4)."""
    return _call(_core.se3_project, [(T, "T", (4, 4))], (4, 4))


def se3_left_jacobian(xi: ArrayLike) -> Array:
    """𝒥_l(ξ) = [[J_l(φ), Q(ξ)], [0, J_l(φ)]] (Barfoot eq. 7.85). (…, 6) → (…, 6, 6)."""
    return _call(_core.se3_left_jacobian, [(xi, "xi", (6,))], (6, 6))


def se3_right_jacobian(xi: ArrayLike) -> Array:
    """𝒥_r(ξ) = 𝒥_l(−ξ): exp(ξ + δ) ≈ exp(ξ) exp(𝒥_r(ξ) δ). (…, 6) → (…, 6, 6)."""
    return _call(_core.se3_right_jacobian, [(xi, "xi", (6,))], (6, 6))


def se3_left_jacobian_inv(xi: ArrayLike) -> Array:
    """𝒥_l⁻¹(ξ) = [[J_l⁻¹, −J_l⁻¹ Q J_l⁻¹], [0, J_l⁻¹]] (closed form). (…, 6) → (…, 6, 6).
    Refused like :func:`so3_left_jacobian_inv` where its rotation part makes J_l singular."""
    return _call(_core.se3_left_jacobian_inv, [(xi, "xi", (6,))], (6, 6))


def se3_right_jacobian_inv(xi: ArrayLike) -> Array:
    """𝒥_r⁻¹(ξ), the derivative of log(T exp(δ)) at δ = 0 for T = exp(ξ). (…, 6) → (…, 6, 6);
    refused where J_l is singular, as :func:`se3_left_jacobian_inv`."""
    return _call(_core.se3_right_jacobian_inv, [(xi, "xi", (6,))], (6, 6))


def se3_compose(T1: ArrayLike, T2: ArrayLike) -> Array:
    """``T1 @ T2`` for rigid transforms, batch axes broadcast. → (…, 4, 4)."""
    return _call(_core.se3_compose, [(T1, "T1", (4, 4)), (T2, "T2", (4, 4))], (4, 4))


def se3_distance(T1: ArrayLike, T2: ArrayLike) -> Array:
    """d(T1, T2) = ‖log(T1⁻¹ T2)^∨‖₂ (metres and radians mixed, as in the paper). → (…).
    Poses whose distance overflows a float (translations near 1e308) raise InvalidInputError."""
    out = _call(_core.se3_distance, [(T1, "T1", (4, 4)), (T2, "T2", (4, 4))], ())
    if not np.isfinite(out).all():
        raise InvalidInputError("T1, T2: the distance overflows a float (translations too large)")
    return out


def se3_interpolate(T1: ArrayLike, T2: ArrayLike, alpha: ArrayLike) -> Array:
    """The geodesic ``T1 exp(alpha log(T1⁻¹ T2))``: T1 at alpha = 0, T2 at 1. → (…, 4, 4)."""
    return _call(
        _core.se3_interpolate,
        [(T1, "T1", (4, 4)), (T2, "T2", (4, 4)), (alpha, "alpha", ())],
        (4, 4),
    )


def se3_transform_points(T: ArrayLike, points: ArrayLike) -> Array:
    """``R @ p + t`` for each point, batch axes broadcast (e.g. one T, (N, 3) points)."""
    return _call(_core.se3_transform_points, [(T, "T", (4, 4)), (points, "points", (3,))], (3,))
