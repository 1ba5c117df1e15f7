"""Test helpers shipped with the library: independent numerical references and hypothesis
strategies for geoloc's inputs (hypothesis is imported only when a strategy is requested).

The references use no Lie closed forms, so they can check geoloc's:

* :func:`reference_expm` — matrix exponential by scaling and squaring of the Taylor series;
* :func:`numerical_jacobian` — central differences of any batched map.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:  # pragma: no cover
    from hypothesis.strategies import SearchStrategy

__all__ = [
    "ANGLE_REGIMES_RAD",
    "numerical_jacobian",
    "random_twists",
    "reference_expm",
    "twists",
]

Array = NDArray[np.float64]

#: Angles every identity is checked at: identity, tiny, around geoloc's Taylor threshold
#: (0.2 rad), ordinary, and just short of π.
ANGLE_REGIMES_RAD = (0.0, 1e-9, 1e-8, 0.19, 0.21, 1.3, np.pi - 1e-6)

_TAYLOR_TERMS = 20


def reference_expm(a: Array) -> Array:
    """exp(A) for a batch (…, k, k): scaling and squaring with a 20-term Taylor series.

    Independent of any Lie-group formula; accurate to ~1e-15 relative for the small
    matrices (norm ≲ 100) of se(3).
    """
    a = np.asarray(a, dtype=np.float64)
    norm = np.abs(a).sum(axis=-1).max(axis=-1)
    squarings = np.maximum(0, np.ceil(np.log2(np.maximum(norm, 1e-300) / 0.5))).astype(int)
    scaled = a / (2.0 ** squarings)[..., None, None]
    eye = np.broadcast_to(np.eye(a.shape[-1]), a.shape)
    term = eye.copy()
    total = eye.copy()
    for k in range(1, _TAYLOR_TERMS + 1):
        term = term @ scaled / k
        total = total + term
    for s in range(int(squarings.max(initial=0))):
        mask = squarings > s
        total[mask] = total[mask] @ total[mask]
    return total


def numerical_jacobian(f: Callable[[Array], Array], x: Array, h: float = 1e-6) -> Array:
    """Central-difference Jacobian of a batched map ``f: (N, n) → (N, m)`` at ``x`` (N, n).

    Returns (N, m, n): column i is (f(x + h eᵢ) − f(x − h eᵢ)) / 2h.
    """
    x = np.asarray(x, dtype=np.float64)
    n = x.shape[-1]
    cols = []
    for i in range(n):
        step = np.zeros(n)
        step[i] = h
        cols.append((f(x + step) - f(x - step)) / (2.0 * h))
    return np.stack(cols, axis=-1)


def random_twists(
    rng: np.random.Generator, n: int, angle_rad: float, max_translation_m: float
) -> Array:
    """``n`` twists (rho, phi) with ‖phi‖ = ``angle_rad`` (uniform axis) and rho uniform in
    a ball of radius ``max_translation_m``."""
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    direction = rng.normal(size=(n, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    radius = max_translation_m * rng.uniform(size=(n, 1)) ** (1.0 / 3.0)
    return np.hstack([direction * radius, axis * angle_rad])


def twists(max_translation_m: float = 30.0, max_angle_rad: float = np.pi - 1e-6) -> SearchStrategy[Any]:
    """Hypothesis strategy of twists (rho, phi) covering every angle regime, including
    identity, 1e-9 rad and π − 1e-6, with translations up to ``max_translation_m``."""
    try:
        from hypothesis import strategies as st
    except ImportError as exc:  # pragma: no cover
        raise ImportError("geoloc.testing.twists needs hypothesis: pip install hypothesis") from exc

    angle = st.one_of(
        st.sampled_from([a for a in ANGLE_REGIMES_RAD if a <= max_angle_rad]),
        st.floats(0.0, max_angle_rad),
        st.floats(1e-12, 1e-6),
    )
    unit = st.tuples(*[st.floats(-1.0, 1.0)] * 3).filter(lambda v: float(np.dot(v, v)) > 1e-4)
    coord = st.floats(-max_translation_m, max_translation_m)
    rho = st.tuples(coord, coord, coord)

    def build(args: tuple[float, tuple[float, ...], tuple[float, ...]]) -> Array:
        a, axis, r = args
        axis_arr = np.asarray(axis) / np.linalg.norm(axis)
        return np.concatenate([np.asarray(r), a * axis_arr])

    return st.tuples(angle, unit, rho).map(build)
