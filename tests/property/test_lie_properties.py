"""Hypothesis properties of geoloc.lie: every Lie identity over twists drawn
from all angle regimes (identity, 1e-9 rad, ordinary, π − 1e-6) and |ρ| ≤ 30 m."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from geoloc import lie
from geoloc.testing import numerical_jacobian, twists

Array = NDArray[np.float64]
EXP_LOG_RTOL = 1e-8
JACOBIAN_RTOL = 1e-5


def _close(a: Array, b: Array, rtol: float) -> bool:
    return bool(np.abs(a - b).max() <= rtol * max(1.0, float(np.abs(b).max())))


@given(twists())
def test_log_inverts_exp(xi: Array) -> None:
    back = lie.se3_log(lie.se3_exp(xi))
    for part in (slice(0, 3), slice(3, 6)):
        assert np.linalg.norm(back[part] - xi[part]) <= EXP_LOG_RTOL * np.linalg.norm(xi[part]) + 1e-14


@given(twists())
def test_exp_inverts_log(xi: Array) -> None:
    T = lie.se3_exp(xi)
    assert _close(lie.se3_exp(lie.se3_log(T)), T, 1e-12)


@given(st.lists(twists(), min_size=1, max_size=8))
def test_batch_equals_loop_of_singles(xis: list[Array]) -> None:
    batch = np.stack(xis)
    for fn in (lie.se3_exp, lie.se3_right_jacobian, lie.se3_left_jacobian_inv, lie.se3_curly_hat):
        expected = np.stack([fn(x) for x in xis])
        np.testing.assert_array_equal(fn(batch), expected)
    T = lie.se3_exp(batch)
    for fn in (lie.se3_log, lie.se3_adjoint, lie.se3_inverse):  # type: ignore[assignment]
        np.testing.assert_array_equal(fn(T), np.stack([fn(t) for t in T]))
    phi = batch[:, 3:]
    np.testing.assert_array_equal(lie.so3_exp(phi), np.stack([lie.so3_exp(p) for p in phi]))


@given(twists(), twists())
def test_adjoint_is_a_homomorphism(xi1: Array, xi2: Array) -> None:
    T1, T2 = lie.se3_exp(xi1), lie.se3_exp(xi2)
    assert _close(lie.se3_adjoint(T1 @ T2), lie.se3_adjoint(T1) @ lie.se3_adjoint(T2), 1e-11)


@given(twists(), twists(max_angle_rad=1.0))
def test_adjoint_moves_twists_across_poses(xi_pose: Array, xi: Array) -> None:
    T = lie.se3_exp(xi_pose)
    lhs = T @ lie.se3_exp(xi) @ lie.se3_inverse(T)
    assert _close(lhs, lie.se3_exp(lie.se3_adjoint(T) @ xi), 1e-10)


@given(twists())
def test_jacobians_times_inverses(xi: Array) -> None:
    scale = (1 + np.linalg.norm(xi)) ** 2
    for j, j_inv in [
        (lie.se3_left_jacobian, lie.se3_left_jacobian_inv),
        (lie.se3_right_jacobian, lie.se3_right_jacobian_inv),
    ]:
        assert np.abs(j(xi) @ j_inv(xi) - np.eye(6)).max() <= 1e-11 * scale
    phi = xi[3:]
    assert np.abs(lie.so3_left_jacobian(phi) @ lie.so3_left_jacobian_inv(phi) - np.eye(3)).max() < 1e-12


@given(twists())
def test_right_jacobian_is_left_of_negated_and_adjoint_related(xi: Array) -> None:
    np.testing.assert_array_equal(lie.se3_right_jacobian(xi), lie.se3_left_jacobian(-xi))
    via_adjoint = lie.se3_adjoint(lie.se3_exp(xi)) @ lie.se3_right_jacobian(xi)
    assert _close(lie.se3_left_jacobian(xi), via_adjoint, 1e-11)


@given(twists(max_angle_rad=np.pi - 1e-5))
def test_first_order_perturbation(xi: Array) -> None:
    """exp(ξ + δ) ≈ exp(ξ) exp(𝒥_r δ): the central-difference derivative of
    log(exp(ξ)⁻¹ exp(ξ + δ)) at δ = 0 is 𝒥_r(ξ) (and likewise on the left)."""
    T_inv = lie.se3_inverse(lie.se3_exp(xi))
    h = 1e-7
    fd_r = numerical_jacobian(lambda y: lie.se3_log(lie.se3_compose(T_inv, lie.se3_exp(y))), xi[None], h)[0]
    fd_l = numerical_jacobian(lambda y: lie.se3_log(lie.se3_compose(lie.se3_exp(y), T_inv)), xi[None], h)[0]
    assert _close(lie.se3_right_jacobian(xi), fd_r, JACOBIAN_RTOL)
    assert _close(lie.se3_left_jacobian(xi), fd_l, JACOBIAN_RTOL)


@given(twists(), twists())
def test_distance_is_a_symmetric_twist_norm(xi_a: Array, xi: Array) -> None:
    A = lie.se3_exp(xi_a)
    B = A @ lie.se3_exp(xi)
    d = lie.se3_distance(A, B)
    scale = 1 + np.linalg.norm(xi)
    assert abs(d - np.linalg.norm(xi)) <= 1e-8 * scale
    assert abs(d - lie.se3_distance(B, A)) <= 1e-8 * scale


@given(twists(), st.floats(0.0, 1.0))
def test_interpolation_splits_the_distance(xi: Array, alpha: float) -> None:
    A = lie.se3_exp(np.array([0.5, -1.0, 2.0, 0.1, 0.2, -0.3]))
    B = A @ lie.se3_exp(xi)
    M = lie.se3_interpolate(A, B, alpha)
    scale = 1 + np.linalg.norm(xi)
    assert abs(lie.se3_distance(A, M) - alpha * np.linalg.norm(xi)) <= 1e-8 * scale


@settings(max_examples=5)  # 10⁴ Python-level calls per example
@given(st.lists(twists(max_translation_m=1.0), min_size=50, max_size=50))
def test_compositions_stay_orthonormal(xis: list[Array]) -> None:
    T = np.eye(4)
    for _ in range(200):  # 10⁴ compositions in all
        for step in lie.se3_exp(np.stack(xis)):
            T = lie.se3_compose(T, step)
    R = T[:3, :3]
    assert np.abs(R.T @ R - np.eye(3)).max() < 1e4 * 4 * np.finfo(float).eps
    lie.so3_log(R)  # still accepted as a rotation
