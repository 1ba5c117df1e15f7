"""geoloc.lie against vectorized numpy, scipy's Rotation and pypose, on identical twists.

    python benchmarks/lie.py [--n 200000] [--json out.json]

Prints, per operation, the best and median wall time of each implementation and its ratio
to geoloc. The numpy implementation is the straightforward vectorized Rodrigues/Barfoot
code an engineer would write; its results are checked against geoloc before timing.
Not part of the test suite.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np
from numpy.typing import NDArray

sys.path.insert(0, os.path.dirname(__file__))

from _timing import Timing, measure, print_table  # noqa: E402

from geoloc import lie  # noqa: E402
from geoloc.testing import random_twists  # noqa: E402

Array = NDArray[np.float64]


def numpy_hat(v: Array) -> Array:
    out = np.zeros((*v.shape[:-1], 3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def numpy_se3_exp(xi: Array) -> Array:
    """Vectorized SE(3) exp: R by Rodrigues, t = J_l(φ) ρ, with a small-angle guard."""
    rho, phi = xi[:, :3], xi[:, 3:]
    theta = np.linalg.norm(phi, axis=1)
    small = theta < 1e-8
    t_safe = np.where(small, 1.0, theta)
    a = np.where(small, 1.0, np.sin(t_safe) / t_safe)
    b = np.where(small, 0.5, (1.0 - np.cos(t_safe)) / t_safe**2)
    c = np.where(small, 1.0 / 6.0, (t_safe - np.sin(t_safe)) / t_safe**3)
    K = numpy_hat(phi)
    K2 = K @ K
    eye = np.eye(3)
    R = eye + a[:, None, None] * K + b[:, None, None] * K2
    V = eye + b[:, None, None] * K + c[:, None, None] * K2
    T = np.zeros((len(xi), 4, 4))
    T[:, :3, :3] = R
    T[:, :3, 3] = np.einsum("nij,nj->ni", V, rho)
    T[:, 3, 3] = 1.0
    return T


def numpy_so3_log(R: Array) -> Array:
    """Vectorized SO(3) log by the textbook θ/(2 sin θ)(R − Rᵀ)^∨ (inaccurate near π)."""
    cos = np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(cos)
    w = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    small = theta < 1e-8
    scale = np.where(small, 0.5, theta / (2.0 * np.sin(np.where(small, 1.0, theta))))
    return scale[:, None] * w


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n", type=int, default=200_000)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--json", default=None, help="also write the rows here")
    args = parser.parse_args()
    report: dict[str, object] = {}
    n = args.n
    xi = random_twists(np.random.default_rng(0), n, 1.0, 10.0)
    xi[:, 3:] *= np.random.default_rng(1).uniform(0, np.pi - 0.01, size=(n, 1))  # angles 0…π
    T = lie.se3_exp(xi)
    R = T[:, :3, :3].copy()
    phi = xi[:, 3:].copy()

    # correctness of the peers on these inputs before any timing
    np.testing.assert_allclose(numpy_se3_exp(xi), T, atol=1e-9)
    np.testing.assert_allclose(numpy_so3_log(R), phi, atol=1e-6)

    print(f"geoloc.lie benchmark: {n} twists, angles uniform in [0, π), |ρ| ≤ 10 m, "
          f"{os.cpu_count()} CPUs")

    rows: list[Timing] = [
        measure("geoloc.lie.se3_exp", lambda: lie.se3_exp(xi), args.repeats),
        measure("numpy vectorized se3_exp", lambda: numpy_se3_exp(xi), args.repeats),
    ]
    pp = _pypose()
    if pp is not None:
        import torch

        xi_pp = torch.from_numpy(np.hstack([xi[:, :3], xi[:, 3:]]))  # pypose se3: (ρ, φ)
        rows.append(measure("pypose se3_Exp().matrix()", lambda: pp.se3(xi_pp).Exp().matrix(), args.repeats))
    report["se3_exp"] = print_table("se3_exp", n, rows, "geoloc.lie.se3_exp")

    rows = [
        measure("geoloc.lie.so3_exp", lambda: lie.so3_exp(phi), args.repeats),
        measure("numpy vectorized so3_exp", lambda: numpy_se3_exp(np.hstack([np.zeros_like(phi), phi]))[:, :3, :3], args.repeats),
    ]
    rotation = _scipy_rotation()
    if rotation is not None:
        rows.append(measure("scipy Rotation.from_rotvec().as_matrix()", lambda: rotation.from_rotvec(phi).as_matrix(), args.repeats))
    report["so3_exp"] = print_table("so3_exp", n, rows, "geoloc.lie.so3_exp")

    rows = [
        measure("geoloc.lie.so3_log", lambda: lie.so3_log(R), args.repeats),
        measure("numpy vectorized so3_log", lambda: numpy_so3_log(R), args.repeats),
    ]
    if rotation is not None:
        rows.append(measure("scipy Rotation.from_matrix().as_rotvec()", lambda: rotation.from_matrix(R).as_rotvec(), args.repeats))
    report["so3_log"] = print_table("so3_log", n, rows, "geoloc.lie.so3_log")

    near_pi = random_twists(np.random.default_rng(2), 1000, np.pi - 1e-6, 0.0)[:, 3:]
    R_pi = lie.so3_exp(near_pi)
    print("  accuracy at θ = π − 1e-6 (max |φ̂ − φ| over 1000 rotations):")
    errors = {
        "geoloc": float(np.abs(lie.so3_log(R_pi) - near_pi).max()),
        "numpy textbook": float(np.abs(numpy_so3_log(R_pi) - near_pi).max()),
        **({"scipy": float(np.abs(rotation.from_matrix(R_pi).as_rotvec() - near_pi).max())} if rotation else {}),
    }
    print("    " + ", ".join(f"{name} {error:.1e}" for name, error in errors.items()))
    report["so3_log error at π − 1e-6 (rad)"] = errors

    rows = [
        measure("geoloc.lie.se3_log", lambda: lie.se3_log(T), args.repeats),
        measure("geoloc.lie.se3_right_jacobian", lambda: lie.se3_right_jacobian(xi), args.repeats),
        measure("geoloc.lie.se3_adjoint", lambda: lie.se3_adjoint(T), args.repeats),
    ]
    report["other geoloc.lie calls"] = print_table("other geoloc.lie calls", n, rows, "geoloc.lie.se3_log")
    if args.json:
        import json

        with open(args.json, "w") as f:
            json.dump(report, f, indent=1)


def _scipy_rotation():  # type: ignore[no-untyped-def]
    try:
        from scipy.spatial.transform import Rotation
    except ImportError:
        print("(scipy not installed: skipping scipy.spatial.transform.Rotation)")
        return None
    return Rotation


def _pypose():  # type: ignore[no-untyped-def]
    try:
        import pypose
    except ImportError:
        print("(pypose not installed: skipping it)")
        return None
    return pypose


if __name__ == "__main__":
    main()
