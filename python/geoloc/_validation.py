"""Argument checks shared by the public wrappers: every failure names the argument."""

from __future__ import annotations

from math import prod
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .exceptions import InvalidInputError, NotARotationError

__all__ = ["as_batch", "broadcast_batches", "check_rigid", "describe_shape", "rigid_poses"]

_REAL_KINDS = "iuf"


def describe_shape(item_shape: tuple[int, ...]) -> str:
    """'(3,) or (..., 3)' style description of an accepted shape."""
    inner = ", ".join(str(d) for d in item_shape)
    single = f"({inner},)" if len(item_shape) == 1 else f"({inner})"
    return f"{single} or (N, {inner})"


def as_float64(x: Any, name: str) -> NDArray[np.float64]:
    """``x`` as a float64 array, refusing non-real dtypes and non-finite values."""
    try:
        arr = np.asarray(x)
    except (ValueError, TypeError) as exc:  # ragged nested sequences
        raise InvalidInputError(f"{name}: cannot be read as an array ({exc})") from None
    if arr.dtype.kind not in _REAL_KINDS:
        raise InvalidInputError(
            f"{name}: expected real numbers (float64), got an array of dtype {arr.dtype}"
        )
    arr = arr.astype(np.float64, copy=False)
    if not np.isfinite(arr).all():
        bad = np.argwhere(~np.isfinite(arr))[0]
        where = "" if arr.ndim == 0 else "[" + ", ".join(str(i) for i in bad) + "]"
        raise InvalidInputError(f"{name}{where} is not finite (NaN or inf)")
    return arr


def as_batch(
    x: Any, name: str, item_shape: tuple[int, ...]
) -> tuple[NDArray[np.float64], tuple[int, ...]]:
    """Validate ``x`` as one item of ``item_shape`` or a batch of them.

    Returns the items as a C-contiguous ``(N, prod(item_shape))`` float64 array and the
    leading batch shape (``()`` for a single item), so results can be reshaped back.
    """
    arr = as_float64(x, name)
    k = len(item_shape)
    if arr.ndim < k or arr.shape[arr.ndim - k :] != item_shape:
        raise InvalidInputError(
            f"{name}: expected shape {describe_shape(item_shape)}, got {arr.shape}"
        )
    lead = arr.shape[: arr.ndim - k]
    flat = np.ascontiguousarray(arr).reshape(-1, prod(item_shape))
    return flat, lead


def broadcast_batches(
    items: list[tuple[NDArray[np.float64], tuple[int, ...], str]],
) -> tuple[list[NDArray[np.float64]], tuple[int, ...]]:
    """Broadcast several ``(flat, lead, name)`` batches against each other (numpy rules).

    Returns contiguous flat arrays with a common number of rows and the common lead shape.
    """
    try:
        lead = np.broadcast_shapes(*(it[1] for it in items))
    except ValueError:
        shapes = ", ".join(f"{name} batch {lead}" for _, lead, name in items)
        raise InvalidInputError(f"batch shapes do not broadcast: {shapes}") from None
    out = []
    for flat, item_lead, _ in items:
        width = flat.shape[1]
        full = np.broadcast_to(flat.reshape(*item_lead, width), (*lead, width))
        out.append(np.ascontiguousarray(full).reshape(-1, width))
    return out, lead


def real_scalar(value: Any, name: str) -> float:
    """A real number (Python or numpy int/float; bool is refused) as float, for the core to
    range-check; anything else — None, a string, a complex, an array — is an InvalidInputError
    naming ``name`` (the bindings would raise a bare TypeError). Integers too large for a
    float (2**1100) are refused as well."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InvalidInputError(f"{name}: expected a real number, got {type(value).__name__} {value!r:.40}")
    try:
        return float(value)
    except OverflowError:
        raise InvalidInputError(f"{name}: an integer of {len(str(abs(int(value))))} digits does not fit a float64") from None


def check_progress(progress: Any) -> None:
    """InvalidInputError naming ``progress`` unless it is None or callable (checked before
    any work, not when it is first called)."""
    if progress is not None and not callable(progress):
        raise InvalidInputError(f"progress: expected a callable or None, got {type(progress).__name__}")


def choice(value: Any, name: str, choices: tuple[str, ...]) -> str:
    """``value`` when it is one of ``choices``; else an InvalidInputError naming ``name``."""
    if not isinstance(value, str) or value not in choices:
        raise InvalidInputError(f"{name}: expected one of {', '.join(map(repr, choices))}, got {value!r:.40}")
    return value


def keypoint_rows(x: Any, name: str, n: int | None = None) -> NDArray[np.float64]:
    """``x`` as C-contiguous (N, 2) float64 pixel rows (N = ``n`` when given)."""
    k = as_float64(x, name)
    if k.ndim != 2 or k.shape[1] != 2 or (n is not None and k.shape[0] != n):
        want = f"({n}, 2)" if n is not None else "(N, 2)"
        raise InvalidInputError(f"{name}: expected shape {want}, got {k.shape}")
    return np.ascontiguousarray(k)


def given_options(**values: Any) -> dict[str, Any]:
    """The options the caller set (not None), for the core, which applies its own default
    to every other one."""
    return {k: v for k, v in values.items() if v is not None}


def rigid_poses(x: Any, name: str) -> NDArray[np.float64]:
    """``x`` as (N, 4, 4) float64 rigid transforms (a single (4, 4) becomes N = 1);
    InvalidInputError for another shape, NotARotationError naming ``name[i]`` (see
    :func:`check_rigid`)."""
    arr = as_float64(x, name)
    if arr.shape == (4, 4):
        arr = arr[None]
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise InvalidInputError(f"{name}: expected shape (4, 4) or (N, 4, 4), got {arr.shape}")
    check_rigid(arr, name)
    return arr


def check_rigid(arr: NDArray[np.float64], name: str) -> None:
    """NotARotationError naming ``name[i]`` for the first pose that is not rigid (last row
    (0, 0, 0, 1), |RᵀR − I| ≤ 1e-6, det R > 0) — checked here so that the error names this
    function's argument, not the argument of the geoloc.lie call inside."""
    if not len(arr):
        return
    rot = arr[:, :3, :3]
    with np.errstate(all="ignore"):
        ortho = np.abs(np.einsum("nji,njk->nik", rot, rot) - np.eye(3)).max(axis=(1, 2))
        det = np.linalg.det(rot)
    bad = (np.abs(arr[:, 3] - [0.0, 0.0, 0.0, 1.0]).max(axis=1) > 0) | ~(ortho <= 1e-6) | ~(det > 0)
    if bad.any():
        i = int(np.argmax(bad))
        raise NotARotationError(
            f"{name}[{i}] is not a rigid transform (last row {arr[i, 3].tolist()}, max |RᵀR − I| = {ortho[i]:.3g}); "
            "project near-rotations first (geoloc.lie.se3_project)"
        )


def check_network(network: Any, name: str) -> None:
    """InvalidInputError naming ``name`` unless ``network`` is callable (a list of (H, W) grey
    images → (N, D) descriptors)."""
    if not callable(network):
        raise InvalidInputError(
            f"{name}: expected a network, a callable from a list of (H, W) grey images to (N, D) descriptors, "
            f"got {type(network).__name__}"
        )


def network_rows(network: Any, images: list[Any], name: str) -> NDArray[np.float32]:
    """``network(images)`` as (len(images), D) float32 rows, D ≥ 1; InvalidInputError naming
    ``name`` (the argument that gave the network) when it is not callable
    (:func:`check_network`) or returns anything else — text, another row count, no rows, more
    dimensions — instead of numpy's or the core's error about an argument the caller never
    passed."""
    check_network(network, name)
    out = network(images)
    try:
        rows = np.asarray(out, dtype=np.float32)
    except (TypeError, ValueError):
        raise InvalidInputError(f"{name}: the network returned values that are not numbers ({type(out).__name__})") from None
    if rows.ndim != 2 or rows.shape[0] != len(images) or rows.shape[1] == 0:
        raise InvalidInputError(
            f"{name}: the network returned shape {rows.shape} for {len(images)} images; expected ({len(images)}, D), D ≥ 1"
        )
    return rows
