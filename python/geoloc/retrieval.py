"""Exact nearest-neighbour retrieval over global image descriptors."""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import _core
from .exceptions import InvalidInputError

__all__ = ["DescriptorIndex"]


def _f32_rows(x: ArrayLike, name: str, dim: int | None = None) -> NDArray[np.float32]:
    arr = np.asarray(x)
    if arr.dtype.kind not in "iuf":
        raise InvalidInputError(f"{name}: expected real numbers, got an array of dtype {arr.dtype}")
    if arr.ndim == 1 and dim is not None:
        arr = arr.reshape(1, -1)
    if arr.ndim != 2 or (dim is not None and arr.shape[1] != dim):
        want = f"(N, {dim})" if dim is not None else "(N, D)"
        raise InvalidInputError(f"{name}: expected shape {want}, got {arr.shape}")
    out = np.ascontiguousarray(arr, dtype=np.float32)
    if not np.isfinite(out).all():
        row = int(np.argwhere(~np.isfinite(out))[0][0])
        raise InvalidInputError(f"{name}[{row}] is not finite (NaN or inf)")
    return out


class DescriptorIndex:
    """Exact k-nearest-neighbour search (Euclidean) over (N, D) descriptors.

    The same neighbours as a brute-force scan, ties broken by the lower index; a kiddo k-d
    tree for D ≤ 8 and a parallel flat scan above (``backend`` forces one). Queries run in
    Rust without the GIL, in parallel over queries. Many identical descriptors (a stopped
    camera) are fine.

    >>> idx = DescriptorIndex(np.eye(3, dtype=np.float32))
    >>> dist, ind = idx.query(np.array([[0.9, 0.1, 0.0]]), k=1)
    """

    def __init__(self, descriptors: ArrayLike, backend: Literal["kdtree", "flat"] | None = None) -> None:
        data = _f32_rows(descriptors, "descriptors")
        if data.shape[0] == 0 or data.shape[1] == 0:
            raise InvalidInputError(f"descriptors: expected a non-empty (N, D) array, got {data.shape}")
        if backend not in (None, "kdtree", "flat"):
            raise InvalidInputError(f"backend: expected 'kdtree', 'flat' or None, got {backend!r}")
        self._index = _core.DescriptorIndex(data, backend)

    def __len__(self) -> int:
        return len(self._index)

    @property
    def dim(self) -> int:
        """D."""
        return int(self._index.dim)

    @property
    def backend(self) -> str:
        """``"kdtree"`` or ``"flat"``."""
        return str(self._index.backend)

    def query(self, queries: ArrayLike, k: int = 1) -> tuple[NDArray[np.float32], NDArray[np.int64]]:
        """Distances and indices of the ``k`` nearest descriptors of each query row, each of
        shape (Q, k), nearest first (a single (D,) query gives (1, k))."""
        if not isinstance(k, (int, np.integer)) or k < 1 or k > len(self):
            raise InvalidInputError(f"k: expected an integer in 1..{len(self)}, got {k!r}")
        q = _f32_rows(queries, "queries", self.dim)
        dist, ind = self._index.query(q, int(k))
        return dist, ind
