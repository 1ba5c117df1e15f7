"""``geoloc selfcheck``: verify the installed Lie-group core against independent references.

Every row compares geoloc with a reference that shares no formula with it (a Taylor-series
matrix exponential, central differences) over angles from 0 to π − 1e-6 and translations up
to 30 m, then times a 200k-twist batch. Exit status 1 if any check fails.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
from numpy.typing import NDArray

from . import lie
from .testing import ANGLE_REGIMES_RAD, numerical_jacobian, random_twists, reference_expm

Array = NDArray[np.float64]

#: Tolerances of the checks (relative to max(1, |reference|)).
EXP_LOG_TOL = 1e-8
JACOBIAN_TOL = 1e-5


@dataclass
class CheckResult:
    """One line of the self-check table."""

    name: str
    max_error: float
    tolerance: float

    @property
    def passed(self) -> bool:
        return bool(self.max_error <= self.tolerance)


def _relative(a: Array, b: Array) -> float:
    scale = np.maximum(1.0, np.abs(b).reshape(len(b), -1).max(axis=1))
    return float((np.abs(a - b).reshape(len(b), -1).max(axis=1) / scale).max())


def _sample(rng: np.random.Generator, per_regime: int) -> Array:
    return np.vstack(
        [random_twists(rng, per_regime, angle, t) for angle in ANGLE_REGIMES_RAD for t in (0.0, 1.0, 30.0)]
    )


def run_checks(per_regime: int = 200, seed: int = 0) -> list[CheckResult]:
    """Run every check and return its result rows."""
    rng = np.random.default_rng(seed)
    xi = _sample(rng, per_regime)
    phi = xi[:, 3:]
    eye6 = np.broadcast_to(np.eye(6), (len(xi), 6, 6))
    h = 1e-7  # keeps perturbed angles below π for the π − 1e-6 regime

    def right_jac_fd(x: Array) -> Array:
        base_inv = lie.se3_inverse(lie.se3_exp(x))
        return numerical_jacobian(lambda y: lie.se3_log(lie.se3_compose(base_inv, lie.se3_exp(y))), x, h)

    def log_fd(x: Array) -> Array:
        base = lie.se3_exp(x)
        zero = np.zeros_like(x)
        return numerical_jacobian(
            lambda d: lie.se3_log(lie.se3_compose(base, lie.se3_exp(d))), zero, h
        )

    away_from_pi = np.linalg.norm(phi, axis=1) < np.pi - 1e-3
    checks: list[tuple[str, Callable[[], float], float]] = [
        ("se3_exp = expm(ξ^)", lambda: _relative(lie.se3_exp(xi), reference_expm(lie.se3_hat(xi))), EXP_LOG_TOL),
        ("so3_exp = expm(φ^)", lambda: _relative(lie.so3_exp(phi), reference_expm(lie.so3_hat(phi))), EXP_LOG_TOL),
        ("se3_log(se3_exp(ξ)) = ξ", lambda: _relative(lie.se3_log(lie.se3_exp(xi)), xi), EXP_LOG_TOL),
        ("so3_log(so3_exp(φ)) = φ", lambda: _relative(lie.so3_log(lie.so3_exp(phi)), phi), EXP_LOG_TOL),
        (
            "Ad(exp ξ) = expm(ad ξ)",
            lambda: _relative(lie.se3_adjoint(lie.se3_exp(xi)), reference_expm(lie.se3_curly_hat(xi))),
            EXP_LOG_TOL,
        ),
        ("𝒥_r(ξ) vs central differences", lambda: _relative(lie.se3_right_jacobian(xi), right_jac_fd(xi)), JACOBIAN_TOL),
        (
            "𝒥_r⁻¹(ξ) vs d log(T exp δ)/dδ",
            lambda: _relative(lie.se3_right_jacobian_inv(xi[away_from_pi]), log_fd(xi[away_from_pi])),
            JACOBIAN_TOL,
        ),
        (
            "𝒥_l(ξ) = Ad(exp ξ) 𝒥_r(ξ)",
            lambda: _relative(lie.se3_left_jacobian(xi), lie.se3_adjoint(lie.se3_exp(xi)) @ lie.se3_right_jacobian(xi)),
            EXP_LOG_TOL,
        ),
        (
            "𝒥_r(ξ) 𝒥_r⁻¹(ξ) = I",
            lambda: _relative(lie.se3_right_jacobian(xi) @ lie.se3_right_jacobian_inv(xi), eye6),
            EXP_LOG_TOL,
        ),
    ]
    return [CheckResult(name, fn(), tol) for name, fn, tol in checks]


def time_se3_exp(n: int = 200_000, repeats: int = 5, seed: int = 1) -> float:
    """Best-of-``repeats`` seconds for one ``lie.se3_exp`` call on ``n`` random twists."""
    xi = random_twists(np.random.default_rng(seed), n, 1.0, 10.0)
    best = np.inf
    for _ in range(repeats):
        start = time.perf_counter()
        lie.se3_exp(xi)
        best = min(best, time.perf_counter() - start)
    return float(best)


def main(per_regime: int = 200) -> int:
    """Print the self-check table; return 0 if every check passed, 1 otherwise."""
    from . import __version__

    results = run_checks(per_regime)
    n = per_regime * len(ANGLE_REGIMES_RAD) * 3
    print(f"geoloc {__version__} self-check: {n} twists, angles 0 … π−1e-6 rad, |ρ| ≤ 30 m")
    width = max(len(r.name) for r in results)
    print(f"  {'check':<{width}}  {'max rel. error':>14}  {'tolerance':>9}")
    for r in results:
        mark = "ok" if r.passed else "FAIL"
        print(f"  {r.name:<{width}}  {r.max_error:>14.2e}  {r.tolerance:>9.0e}  {mark}")
    seconds = time_se3_exp()
    print(f"  se3_exp on 200000 twists: {seconds * 1e3:.1f} ms ({200_000 / seconds / 1e6:.1f} M twists/s)")
    failed = [r.name for r in results if not r.passed]
    print("all checks passed" if not failed else f"FAILED: {', '.join(failed)}")
    return 1 if failed else 0
