"""geoloc.lie against independent oracles (scipy's expm/logm, a Taylor-series expm,
central differences), plus shapes, batching and bad inputs."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
from numpy.typing import NDArray

import geoloc
from geoloc import lie
from geoloc.testing import ANGLE_REGIMES_RAD, numerical_jacobian, random_twists, reference_expm

EXP_LOG_RTOL = 1e-8  # ≤1e-8 relative on exp/log
JACOBIAN_RTOL = 1e-5  # ≤1e-5 on Jacobians
TRANSLATIONS_M = (0.0, 1.0, 30.0)
Array = NDArray[np.float64]


def _rel(a: Array, b: Array) -> float:
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-300))


def _vee_se3(m: Array) -> Array:
    return np.array([m[0, 3], m[1, 3], m[2, 3], m[2, 1], m[0, 2], m[1, 0]])


@pytest.fixture(scope="module")
def regime_twists() -> list[tuple[float, float, Array]]:
    rng = np.random.default_rng(2)
    return [
        (angle, t, random_twists(rng, 20, angle, t))
        for angle in ANGLE_REGIMES_RAD
        for t in TRANSLATIONS_M
    ]


def test_se3_exp_matches_scipy_expm(regime_twists: list[tuple[float, float, Array]]) -> None:
    for angle, t, xis in regime_twists:
        for xi in xis:
            ref = scipy.linalg.expm(lie.se3_hat(xi))
            assert _rel(lie.se3_exp(xi), ref) <= EXP_LOG_RTOL, (angle, t, xi)
            # the rotation part alone, relative to its own (unit) scale
            assert _rel(lie.so3_exp(xi[3:]), ref[:3, :3]) <= EXP_LOG_RTOL


@pytest.mark.slow
def test_log_matches_scipy_logm_and_the_generating_twist(regime_twists: list[tuple[float, float, Array]]) -> None:
    for angle, t, xis in regime_twists:
        for xi in xis:
            T = scipy.linalg.expm(lie.se3_hat(xi))  # independent of geoloc's exp
            got = lie.se3_log(T)
            # logm itself is only ~1e-7 relative at 1e-9 rad and ~1e-9 next to π, so it is
            # held to max(1, |ref|); the generating twist below is the tight reference
            ref = _vee_se3(np.real(scipy.linalg.logm(T)))
            assert np.linalg.norm(got - ref) <= EXP_LOG_RTOL * max(np.linalg.norm(ref), 1.0)
            # φ and ρ each keep their own relative precision, also at 1e-9 rad
            for part in (slice(0, 3), slice(3, 6)):
                truth = xi[part]
                err = np.linalg.norm(got[part] - truth)
                assert err <= EXP_LOG_RTOL * np.linalg.norm(truth) + 1e-15, (angle, t, part, err)
            phi_got = lie.so3_log(T[:3, :3])
            assert np.linalg.norm(phi_got - xi[3:]) <= EXP_LOG_RTOL * np.linalg.norm(xi[3:]) + 1e-300


def test_adjoint_of_exp_is_expm_of_curly_hat(regime_twists: list[tuple[float, float, Array]]) -> None:
    for _, _, xis in regime_twists:
        got = lie.se3_adjoint(lie.se3_exp(xis))
        ref = np.stack([scipy.linalg.expm(m) for m in lie.se3_curly_hat(xis)])
        assert _rel(got, ref) <= EXP_LOG_RTOL


def test_reference_expm_agrees_with_scipy() -> None:
    rng = np.random.default_rng(0)
    a = rng.normal(size=(20, 6, 6)) * 3
    ref = np.stack([scipy.linalg.expm(m) for m in a])
    assert _rel(reference_expm(a), ref) < 1e-12


@pytest.mark.parametrize("side", ["right", "left"])
def test_se3_jacobians_match_central_differences(side: str, regime_twists: list[tuple[float, float, Array]]) -> None:
    h = 1e-7
    for _, _, xis in regime_twists:
        T = lie.se3_exp(xis)
        T_inv = lie.se3_inverse(T)
        if side == "right":
            fd = numerical_jacobian(lambda y: lie.se3_log(lie.se3_compose(T_inv, lie.se3_exp(y))), xis, h)
            analytic = lie.se3_right_jacobian(xis)
        else:
            fd = numerical_jacobian(lambda y: lie.se3_log(lie.se3_compose(lie.se3_exp(y), T_inv)), xis, h)
            analytic = lie.se3_left_jacobian(xis)
        scale = np.maximum(1.0, np.abs(fd).max(axis=(1, 2)))
        err = (np.abs(analytic - fd).max(axis=(1, 2)) / scale).max()
        assert err <= JACOBIAN_RTOL


@pytest.mark.parametrize("side", ["right", "left"])
def test_so3_jacobians_and_inverses_match_central_differences(side: str) -> None:
    rng = np.random.default_rng(5)
    for angle in ANGLE_REGIMES_RAD:
        phi = random_twists(rng, 20, angle, 0.0)[:, 3:]
        R = lie.so3_exp(phi)
        Rt = np.swapaxes(R, -1, -2)
        zero = np.zeros_like(phi)
        if side == "right":
            jac_fd = numerical_jacobian(lambda y: lie.so3_log(Rt @ lie.so3_exp(y)), phi, 1e-7)
            inv_fd = numerical_jacobian(lambda d: lie.so3_log(R @ lie.so3_exp(d)), zero, 1e-7)
            jac, inv = lie.so3_right_jacobian(phi), lie.so3_right_jacobian_inv(phi)
        else:
            jac_fd = numerical_jacobian(lambda y: lie.so3_log(lie.so3_exp(y) @ Rt), phi, 1e-7)
            inv_fd = numerical_jacobian(lambda d: lie.so3_log(lie.so3_exp(d) @ R), zero, 1e-7)
            jac, inv = lie.so3_left_jacobian(phi), lie.so3_left_jacobian_inv(phi)
        assert np.abs(jac - jac_fd).max() <= JACOBIAN_RTOL
        if angle < np.pi - 1e-3:  # the log jumps across π; its derivative is checked below it
            assert np.abs(inv - inv_fd).max() <= JACOBIAN_RTOL


def test_inverse_jacobians_are_matrix_inverses() -> None:
    xi = random_twists(np.random.default_rng(9), 200, 2.0, 30.0)
    for jac, inv in [
        (lie.se3_left_jacobian, lie.se3_left_jacobian_inv),
        (lie.se3_right_jacobian, lie.se3_right_jacobian_inv),
    ]:
        assert _rel(inv(xi), np.linalg.inv(jac(xi))) < 1e-10
    phi = xi[:, 3:]
    assert _rel(lie.so3_right_jacobian_inv(phi), np.linalg.inv(lie.so3_right_jacobian(phi))) < 1e-12


def test_rotation_angle_known_values_and_no_nan() -> None:
    assert lie.rotation_angle(np.eye(3)) == 0.0
    assert lie.rotation_angle(lie.so3_exp([0.0, 0.0, np.pi / 2])) == pytest.approx(np.pi / 2, abs=1e-15)
    assert lie.rotation_angle(np.diag([1.0, -1.0, -1.0])) == pytest.approx(np.pi, abs=1e-15)
    # trace a hair outside [-1, 3] (accumulated round-off): acos would give NaN
    assert lie.rotation_angle(np.eye(3) * (1 + 1e-12)) == 0.0
    assert lie.rotation_angle(np.diag([1.0, -1.0 - 1e-12, -1.0 - 1e-12])) == pytest.approx(np.pi)
    tiny = lie.rotation_angle(lie.so3_exp([1e-9, 0.0, 0.0]))
    assert tiny == pytest.approx(1e-9, rel=1e-12)


def test_se3_exp_known_value() -> None:
    # a quarter turn about z with translation along x: t = J_l(φ) ρ, closed form
    T = lie.se3_exp([1.0, 0.0, 0.0, 0.0, 0.0, np.pi / 2])
    c = 2 / np.pi  # sin θ/θ ; (1 − cos θ)/θ = 2/π
    expected_t = np.array([c, c, 0.0])
    np.testing.assert_allclose(T[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)
    np.testing.assert_allclose(T[:3, 3], expected_t, atol=1e-15)
    np.testing.assert_array_equal(T[3], [0, 0, 0, 1])


def test_quaternions_round_trip_and_match_scipy() -> None:
    from scipy.spatial.transform import Rotation

    R = lie.so3_exp(random_twists(np.random.default_rng(1), 100, 2.5, 0)[:, 3:])
    q = lie.so3_to_quaternion_wxyz(R)
    ref_xyzw = Rotation.from_matrix(R).as_quat()
    ref = np.hstack([ref_xyzw[:, 3:], ref_xyzw[:, :3]])
    ref *= np.sign(ref[:, :1]) * np.sign(q[:, :1])  # q and −q are the same rotation
    np.testing.assert_allclose(q, ref, atol=1e-14)
    np.testing.assert_allclose(lie.so3_from_quaternion_wxyz(q), R, atol=1e-14)


def test_projection_fixes_real_dataset_rotations() -> None:
    R = lie.so3_exp([0.3, -0.2, 1.1])
    M = R * 0.9997  # like 7-Scenes: det ≈ 0.9991
    with pytest.raises(geoloc.NotARotationError, match="so3_project"):
        lie.so3_log(M)
    P = lie.so3_project(M)
    np.testing.assert_allclose(P, R, atol=1e-14)
    T = np.eye(4)
    T[:3, :3] = M
    T[:3, 3] = [1, 2, 3]
    np.testing.assert_allclose(lie.se3_project(T)[:3, :3], R, atol=1e-14)


def test_distance_interpolation_compose_transform() -> None:
    rng = np.random.default_rng(4)
    a = lie.se3_exp(random_twists(rng, 50, 1.0, 10.0))
    xi = random_twists(rng, 50, 0.7, 2.0)
    b = lie.se3_compose(a, lie.se3_exp(xi))
    np.testing.assert_allclose(lie.se3_distance(a, b), np.linalg.norm(xi, axis=1), rtol=1e-12)
    np.testing.assert_allclose(lie.se3_compose(a, lie.se3_exp(xi)), a @ lie.se3_exp(xi), atol=1e-12)
    mid = lie.se3_interpolate(a, b, 0.25)
    np.testing.assert_allclose(lie.se3_distance(a, mid), 0.25 * np.linalg.norm(xi, axis=1), rtol=1e-10)
    np.testing.assert_allclose(lie.se3_interpolate(a, b, 1.0), b, atol=1e-12)
    # one pose broadcast over many points equals homogeneous multiplication
    pts = rng.normal(size=(30, 3))
    ref = (a[0] @ np.hstack([pts, np.ones((30, 1))]).T).T[:, :3]
    np.testing.assert_allclose(lie.se3_transform_points(a[0], pts), ref, atol=1e-12)
    np.testing.assert_allclose(lie.se3_inverse(a), np.linalg.inv(a), atol=1e-12)


def test_hat_vee_round_trip() -> None:
    xi = random_twists(np.random.default_rng(3), 10, 1.0, 1.0)
    np.testing.assert_array_equal(lie.se3_vee(lie.se3_hat(xi)), xi)
    np.testing.assert_array_equal(lie.so3_vee(lie.so3_hat(xi[:, 3:])), xi[:, 3:])
    v = np.array([0.3, -1.0, 2.0])
    np.testing.assert_allclose(lie.so3_hat(xi[0, 3:]) @ v, np.cross(xi[0, 3:], v), atol=1e-15)


# ------------------------------------------------------------------- shapes and batching


def test_batch_shapes() -> None:
    xi = np.zeros((2, 5, 6))
    assert lie.se3_exp(xi).shape == (2, 5, 4, 4)
    assert lie.se3_exp(xi[0, 0]).shape == (4, 4)
    assert lie.se3_log(lie.se3_exp(xi)).shape == (2, 5, 6)
    assert lie.se3_distance(np.eye(4), lie.se3_exp(xi)).shape == (2, 5)
    assert lie.rotation_angle(np.eye(3)).shape == ()
    assert lie.se3_exp(np.zeros((0, 6))).shape == (0, 4, 4)
    assert lie.so3_log(np.zeros((0, 3, 3))).shape == (0, 3)


def test_accepts_lists_ints_float32_and_non_contiguous() -> None:
    ref = lie.se3_exp(np.array([1.0, 2.0, 3.0, 0.0, 0.0, 0.0]))
    np.testing.assert_array_equal(lie.se3_exp([1, 2, 3, 0, 0, 0]), ref)
    np.testing.assert_array_equal(lie.se3_exp(np.array([1, 2, 3, 0, 0, 0], dtype=np.float32)), ref)
    big = random_twists(np.random.default_rng(0), 40, 1.0, 5.0)
    strided = big[::2]
    np.testing.assert_array_equal(lie.se3_exp(strided), lie.se3_exp(np.ascontiguousarray(strided)))
    fortran = np.asfortranarray(big)
    np.testing.assert_array_equal(lie.se3_exp(fortran), lie.se3_exp(big))


def test_large_parallel_batch_equals_sequential_chunks() -> None:
    n = 5 * geoloc._core.PARALLEL_MIN_ITEMS + 17
    xi = random_twists(np.random.default_rng(8), n, 2.0, 30.0)
    whole = lie.se3_exp(xi)
    pieces = np.concatenate([lie.se3_exp(xi[i : i + 1000]) for i in range(0, n, 1000)])
    np.testing.assert_array_equal(whole, pieces)


# ------------------------------------------------------------------------- bad inputs


@pytest.mark.parametrize(
    ("fn", "arg", "match"),
    [
        (lie.se3_exp, np.zeros(5), r"xi: expected shape \(6,\) or \(N, 6\), got \(5,\)"),
        (lie.se3_exp, np.zeros((3, 7)), r"xi: expected shape"),
        (lie.so3_exp, np.zeros((3, 4)), r"phi: expected shape \(3,\) or \(N, 3\), got \(3, 4\)"),
        (lie.so3_log, np.zeros(3), r"R: expected shape \(3, 3\) or \(N, 3, 3\)"),
        (lie.se3_log, np.eye(3), r"T: expected shape \(4, 4\)"),
        (lie.se3_exp, np.array(["a"] * 6), r"xi: expected real numbers.*dtype <U1"),
        (lie.se3_exp, np.zeros(6, dtype=complex), r"xi: expected real numbers.*complex128"),
        (lie.se3_exp, np.zeros(6, dtype=bool), r"xi: expected real numbers.*bool"),
        (lie.se3_exp, [[0.0] * 6, [0.0] * 5], r"xi: cannot be read as an array"),
        (lie.se3_exp, np.array([0, 0, np.nan, 0, 0, 0]), r"xi\[2\] is not finite"),
        (lie.so3_exp, np.array([[0, 0, 0], [0, np.inf, 0]]), r"phi\[1, 1\] is not finite"),
        (lie.se3_exp, 3.0, r"xi: expected shape"),
    ],
)
def test_bad_input_raises_value_error_naming_the_argument(fn, arg, match) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(geoloc.InvalidInputError, match=match) as info:
        fn(arg)
    assert isinstance(info.value, ValueError)


def test_non_rotations_are_refused_with_their_index() -> None:
    R = lie.so3_exp(np.zeros((5, 3)))
    R[3, 0, 0] = 2.0
    with pytest.raises(geoloc.NotARotationError, match=r"R\[3\] is not a rotation"):
        lie.so3_log(R)
    with pytest.raises(geoloc.NotARotationError, match=r"R is not a rotation"):
        lie.so3_log(R[3])
    with pytest.raises(geoloc.NotARotationError, match="reflection|det"):
        lie.so3_project(np.diag([1.0, 1.0, -1.0]))
    T = np.eye(4)
    T[3, 0] = 0.5
    with pytest.raises(geoloc.NotARotationError, match=r"T is not a rigid transform.*last row"):
        lie.se3_log(T)
    with pytest.raises(geoloc.NotARotationError, match=r"T2\[1\]"):
        lie.se3_distance(np.eye(4), np.stack([np.eye(4), T]))


def test_first_bad_item_of_a_parallel_batch_is_reported() -> None:
    n = 3 * geoloc._core.PARALLEL_MIN_ITEMS
    T = lie.se3_exp(np.zeros((n, 6)))
    T[n - 5, 0, 0] = 3.0
    T[n - 1, 0, 0] = 3.0
    with pytest.raises(geoloc.NotARotationError, match=rf"T\[{n - 5}\]"):
        lie.se3_log(T)


def test_mismatched_batches_are_refused() -> None:
    with pytest.raises(geoloc.InvalidInputError, match="do not broadcast"):
        lie.se3_compose(np.stack([np.eye(4)] * 2), np.stack([np.eye(4)] * 3))


def test_core_refuses_bad_layouts_without_panicking() -> None:
    core = geoloc._core
    with pytest.raises(ValueError, match=r"phi: expected shape \(N, 3\)"):
        core.so3_exp(np.zeros((2, 4)))
    with pytest.raises(ValueError, match="C-contiguous"):
        core.so3_exp(np.zeros((4, 3))[::2])
    with pytest.raises(ValueError, match=r"phi\[1\] holds a non-finite"):
        core.so3_exp(np.array([[0.0, 0, 0], [0, np.nan, 0]]))
    with pytest.raises(ValueError, match="has 3 items but T1 has 2"):
        core.se3_compose(np.zeros((2, 16)), np.zeros((3, 16)))
    with pytest.raises(TypeError):
        core.so3_exp(np.zeros((2, 3), dtype=np.float32))


# --- bad inputs ---------------------------------------------------------------------


def test_exp_refuses_overflowing_magnitudes() -> None:
    with pytest.raises(geoloc.InvalidInputError, match=r"phi: ‖φ‖ ≥ 1e300 rad exceeds 1e12"):
        lie.so3_exp([1e300, 0.0, 0.0])
    with pytest.raises(geoloc.InvalidInputError, match=r"xi\[1\]"):
        lie.se3_exp([[0.0] * 6, [1e200, 0, 0, 0, 0, 0.1]])
    with pytest.raises(geoloc.InvalidInputError, match=r"phi: "):
        lie.so3_right_jacobian([0.0, 1e300, 0.0])
    assert np.isfinite(lie.so3_exp([1e6, 0.0, 0.0])).all()


def test_so3_project_is_immune_to_scale() -> None:
    R = lie.so3_exp([0.3, -0.2, 0.1])
    for scale in (1e200, 1e-200):
        np.testing.assert_allclose(lie.so3_project(scale * R), R, atol=1e-14)
    np.testing.assert_allclose(lie.so3_project(1e200 * np.eye(3)), np.eye(3), atol=1e-15)


def test_rotation_angle_refuses_non_rotations() -> None:
    with pytest.raises(geoloc.NotARotationError, match=r"R is not a near-rotation"):
        lie.rotation_angle(np.ones((3, 3)))
    # a real dataset's near-rotation (det ≈ 0.9995) still has its angle
    assert lie.rotation_angle(0.9998 * lie.so3_exp([0.0, 0.0, 0.5])) == pytest.approx(0.5, abs=1e-3)


def test_jacobian_inverses_refuse_a_rotation_vector_where_the_jacobian_is_singular() -> None:
    """At ‖φ‖ = 2π the closed form gave 2.6e16 entries (J·J⁻¹ − I = 1) instead of an error."""
    phi = np.array([0.0, 2 * np.pi, 0.0])
    for fn, arg in [(lie.so3_left_jacobian_inv, phi), (lie.so3_right_jacobian_inv, phi),
                    (lie.se3_left_jacobian_inv, np.r_[1.0, 0, 0, phi]), (lie.se3_right_jacobian_inv, np.r_[1.0, 0, 0, phi])]:
        name = "phi" if arg.shape == (3,) else "xi"
        with pytest.raises(geoloc.InvalidInputError, match=rf"^{name}: ‖φ‖ = 6.28\S* rad is 1·2π"):
            fn(arg)
    with pytest.raises(geoloc.InvalidInputError, match=r"^phi\[1\]: "):
        lie.so3_left_jacobian_inv(np.stack([phi / 2, 2 * phi]))
    beside = np.array([0.0, 2 * np.pi - 1e-6, 0.0])  # nearly singular, still invertible
    np.testing.assert_allclose(lie.so3_left_jacobian(beside) @ lie.so3_left_jacobian_inv(beside), np.eye(3), atol=1e-6)
