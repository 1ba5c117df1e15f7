"""Worker-side: the documented invariants of each kind of result, and the in-process CLI
runner. Each check returns ``None`` when the result is acceptable, else what is wrong."""

from __future__ import annotations

import contextlib
import io
import os
from pathlib import Path
from typing import Any, Callable

import numpy as np

TOL = 1e-6


def _finite(x: Any, what: str) -> str | None:
    a = np.asarray(x)
    if a.dtype.kind in "fc" and not np.all(np.isfinite(a)):
        return f"{what} is not finite"
    return None


def _rotations(r: Any, what: str = "rotation") -> str | None:
    r = np.asarray(r, dtype=float)
    if r.shape[-2:] != (3, 3):
        return f"{what} has shape {r.shape}"
    if (p := _finite(r, what)) is not None:
        return p
    eye = np.einsum("...ji,...jk->...ik", r, r)
    if r.size and np.abs(eye - np.eye(3)).max() > 1e-6:
        return f"{what} is not orthonormal (max |RᵀR − I| = {np.abs(eye - np.eye(3)).max():.3g})"
    if r.size and np.abs(np.linalg.det(r) - 1).max() > 1e-6:
        return f"{what} has det ≠ 1"
    return None


def _poses(t: Any, what: str = "pose") -> str | None:
    t = np.asarray(t, dtype=float)
    if t.shape[-2:] != (4, 4):
        return f"{what} has shape {t.shape}"
    if (p := _finite(t, what)) is not None:
        return p
    if t.size and np.abs(t[..., 3, :] - [0, 0, 0, 1]).max() > 0:
        return f"{what} last row is not [0 0 0 1]"
    return _rotations(t[..., :3, :3], what + " rotation")


def _psd(c: Any, n: int, what: str = "covariance") -> str | None:
    c = np.asarray(c, dtype=float)
    if c.shape[-2:] != (n, n):
        return f"{what} has shape {c.shape}"
    if (p := _finite(c, what)) is not None:
        return p
    if not c.size:
        return None
    sym = np.abs(c - np.swapaxes(c, -1, -2)).max()
    scale = max(np.abs(c).max(), 1e-300)
    if sym > 1e-9 * scale:
        return f"{what} not symmetric ({sym:.3g})"
    w = np.linalg.eigvalsh(0.5 * (c + np.swapaxes(c, -1, -2)))
    if w.min() < -1e-9 * scale:
        return f"{what} not PSD (min eigenvalue {w.min():.3g})"
    return None


def _first(*problems: str | None) -> str | None:
    return next((p for p in problems if p is not None), None)


def _angle(a: Any) -> str | None:
    a = np.asarray(a, dtype=float)
    if (p := _finite(a, "angle")) is not None:
        return p
    if a.size and (a.min() < 0 or a.max() > np.pi + 1e-12):
        return "angle outside [0, π]"
    return None


def _knn(res: Any, case: dict[str, Any]) -> str | None:
    dist, ind = res
    dist, ind = np.asarray(dist), np.asarray(ind)
    if dist.shape != ind.shape or dist.ndim != 2:
        return f"shapes {dist.shape} vs {ind.shape}"
    if (p := _finite(dist, "distances")) is not None:
        return p
    if dist.size and dist.min() < 0:
        return "negative distance"
    if dist.shape[1] > 1 and np.any(np.diff(dist, axis=1) < -1e-6):
        return "distances not sorted"
    if ind.size and ind.min() < 0:
        return "negative index"
    n = case.get("n_database")
    if n is not None and ind.size and ind.max() >= n:
        return f"index {ind.max()} ≥ database size {n}"
    if case.get("exact") is not None and dist.size:
        if not np.array_equal(ind[:, 0], np.asarray(case["exact"])[: ind.shape[0]]):
            return "1-NN differs from the brute-force answer"
    return None


def _bow(res: Any, case: dict[str, Any]) -> str | None:
    scores, ind = np.asarray(res[0]), np.asarray(res[1])
    if scores.shape != ind.shape:
        return "shapes differ"
    if (p := _finite(scores, "scores")) is not None:
        return p
    if scores.size and (scores.min() < 0 or scores.max() > 1):
        return f"score outside [0, 1]: {scores.min()}..{scores.max()}"
    return None


def _pnp(r: Any, case: dict[str, Any]) -> str | None:
    if not r.success:
        return None if r.reason else "success=False without a reason"
    return _first(_poses(r.pose), _psd(r.covariance, 6), _finite([r.rms, r.sigma_p, r.sigma_r], "sigmas"))


def _tri(r: Any, case: dict[str, Any]) -> str | None:
    n = len(r.track_ids)
    if r.points.shape != (n, 3) or r.status.shape != (n,):
        return "inconsistent shapes"
    ok = r.status == 0
    return _first(_finite(r.points[ok], "valid points"), _psd(r.covariances[ok], 3, "point covariance"))


def _motion(r: Any, case: dict[str, Any]) -> str | None:
    return _first(_poses(r.pose), _psd(r.covariance, 6))


def _fusion(r: Any, case: dict[str, Any]) -> str | None:
    if r.source not in ("fused", "motion", "geometric"):
        return f"source {r.source!r}"
    return _first(_poses(r.pose), _psd(r.covariance, 6))


def _localization(r: Any, case: dict[str, Any]) -> str | None:
    if r.pose is None:
        return None if r.reason else "lost without a reason"
    return _first(_poses(r.pose), _psd(r.covariance, 6) if r.covariance is not None else None)


def _score(a: Any, case: dict[str, Any]) -> str | None:
    a = np.asarray(a, dtype=float)
    if (p := _finite(a, "score")) is not None:
        return p
    if a.size and (a.min() < 0 or a.max() > 1):
        return "score outside [0, 1]"
    return None


def _indices(a: Any, case: dict[str, Any]) -> str | None:
    a = np.asarray(a)
    if a.dtype.kind not in "iu":
        return f"dtype {a.dtype}"
    if a.size and a.min() < 0:
        return "negative index"
    return None


def _match(res: Any, case: dict[str, Any]) -> str | None:
    pairs, dist = np.asarray(res[0]), np.asarray(res[1])
    if pairs.ndim != 2 or pairs.shape[1] != 2 or dist.shape != (pairs.shape[0],):
        return f"shapes {pairs.shape} {dist.shape}"
    if (p := _finite(dist, "match distances")) is not None:
        return p
    if case.get("min_matches") is not None and len(pairs) < case["min_matches"]:
        return f"only {len(pairs)} self-matches"
    return None


def _descriptors(a: Any, case: dict[str, Any]) -> str | None:
    a = np.asarray(a)
    if a.ndim != 2 or a.dtype != np.float32:
        return f"descriptors {a.shape} {a.dtype}"
    return _finite(a, "descriptors")


def _sigmas(res: Any, case: dict[str, Any]) -> str | None:
    return _first(*[_finite(x, "sigma") for x in res])


CHECKS: dict[str, Callable[[Any, dict[str, Any]], str | None]] = {
    "any": lambda r, c: None,
    "finite": lambda r, c: _finite(r, "result"),
    "rot": lambda r, c: _rotations(r),
    "pose": lambda r, c: _poses(r),
    "angle": lambda r, c: _angle(r),
    "psd6": lambda r, c: _psd(r, 6),
    "quat": lambda r, c: _first(
        _finite(r, "quaternion"),
        None if not np.size(r) or np.allclose(np.linalg.norm(r, axis=-1), 1, atol=1e-9) else "not unit",
    ),
    "knn": _knn,
    "bow": _bow,
    "pnp": _pnp,
    "tri": _tri,
    "motion": _motion,
    "fusion": _fusion,
    "localization": _localization,
    "score": _score,
    "indices": _indices,
    "match": _match,
    "descriptors": _descriptors,
    "sigmas": _sigmas,
    "mask": lambda r, c: None if np.asarray(r).dtype == bool else f"dtype {np.asarray(r).dtype}",
    "str": lambda r, c: None if isinstance(r, str) and "nan" not in r.lower() else f"{r!r}",
}


def check(name: str, result: Any, case: dict[str, Any]) -> str | None:
    return CHECKS[name](result, case)


def run_cli(case: dict[str, Any], evaluate: Callable[[Any], Any]) -> dict[str, Any]:
    """Run ``geoloc.cli.main(argv)`` in this process; the CLI contract: exit 0, or a non-zero
    exit with exactly one line on stderr that names the option, no traceback, and no folder
    created that the user did not ask for."""
    from geoloc import cli

    argv = [str(evaluate(a)) for a in case["cli"]]
    watch = [Path(evaluate(p)) for p in case.get("watch", [])]
    err, out = io.StringIO(), io.StringIO()
    cwd = os.getcwd()
    os.chdir(evaluate(("path", "dir")))
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
            try:
                code = cli.main(argv)
            except SystemExit as e:
                code = e.code if isinstance(e.code, int) else (0 if e.code is None else 2)
            except BaseException as e:  # noqa: BLE001
                return {"kind": "wrong-type", "detail": f"{type(e).__name__} escaped main: {e}"[:300]}
    finally:
        os.chdir(cwd)
    text = err.getvalue()
    lines = [line for line in text.splitlines() if line.strip()]
    created = [str(p) for p in watch if p.exists()]
    if created:
        return {"kind": "invariant", "detail": f"created {created}"}
    if "Traceback" in text:
        return {"kind": "invariant", "detail": "traceback on stderr: " + text[-300:]}
    if code == 0:
        return {"kind": "ok", "detail": ""}
    usage = [line for line in lines if not line.startswith("usage:") and not line.startswith(" ")]
    if len(usage) != 1:
        return {"kind": "invariant", "detail": f"exit {code} with {len(usage)} error lines: {text[-300:]!r}"}
    names = case.get("names", [])
    if names and not any(n in usage[0] for n in names):
        return {"kind": "wrong-name", "detail": usage[0][:300]}
    return {"kind": "rejected", "detail": usage[0][:200]}
