"""Exact nearest-neighbour retrieval over global image descriptors."""

from __future__ import annotations

from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import _core
from .exceptions import InvalidInputError

__all__ = ["BowDatabase", "DescriptorIndex", "Vocabulary"]


def _f32_rows(x: ArrayLike, name: str, dim: int | None = None) -> NDArray[np.float32]:
    arr = np.asarray(x)
    if arr.dtype.kind not in "iuf":
        raise InvalidInputError(f"{name}: expected real numbers, got an array of dtype {arr.dtype}")
    if arr.ndim == 1 and dim is not None:
        arr = arr.reshape(1, -1)
    if arr.ndim != 2 or (dim is not None and arr.shape[1] != dim):
        want = f"(N, {dim})" if dim is not None else "(N, D)"
        raise InvalidInputError(f"{name}: expected shape {want}, got {arr.shape}")
    if arr.dtype.kind == "f" and arr.dtype.itemsize > 4:
        too_big = np.isfinite(arr) & (np.abs(arr) > np.finfo(np.float32).max)
        if too_big.any():
            row = int(np.argwhere(too_big)[0][0])
            raise InvalidInputError(f"{name}[{row}] overflows float32 (|x| > {np.finfo(np.float32).max:.3g})")
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
        if backend is not None and backend not in ("kdtree", "flat"):
            raise InvalidInputError(f"backend: expected 'kdtree', 'flat' or None, got {backend!r:.40}")
        self._index = _core.DescriptorIndex(_f32_rows(descriptors, "descriptors"), backend=backend)

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
        shape (Q, k), nearest first (a single (D,) query gives (1, k)). Exact for every
        finite input (an f64 scan takes over at magnitudes where f32 squares overflow)."""
        if not isinstance(k, (int, np.integer)) or isinstance(k, bool) or k < 1 or k > len(self):
            raise InvalidInputError(f"k: expected an integer in 1..{len(self)}, got {k!r}")
        return self._index.query(_f32_rows(queries, "queries", self.dim), k)


def _local_descriptors(x: ArrayLike, name: str) -> NDArray[np.uint8] | NDArray[np.float32]:
    """(N, W) uint8 rows as they are (binary), floating rows as C-contiguous float32 rows;
    other integer or boolean rows are refused: binary descriptors are bytes, and read as
    floats they would be compared as another kind."""
    arr = np.asarray(x)
    if arr.ndim != 2 or arr.shape[1] == 0:
        raise InvalidInputError(f"{name}: expected shape (N, W), got {arr.shape}")
    if arr.dtype == np.uint8:
        return np.ascontiguousarray(arr)
    if arr.dtype.kind in "biu":
        raise InvalidInputError(
            f"{name}: expected uint8 rows (binary descriptors, e.g. ORB) or floating rows (e.g. SIFT), got {arr.dtype}"
        )
    return _f32_rows(arr, name)


class Vocabulary:
    """A hierarchical visual vocabulary of up to ``branching``**``depth`` words, clustered
    from local descriptors: k-means (k-means++ seeding, D² weights) for float descriptors
    (SIFT), k-majority with Hamming distance for binary uint8 ones (ORB). Needs no training
    framework. Limits: ``branching`` ≤ 1024, ``depth`` ≤ 24, ``branching**depth`` ≤ 2**24."""

    def __init__(self, core: _core.Vocabulary) -> None:
        self._vocabulary = core

    @classmethod
    def train(cls, descriptors: ArrayLike, branching: int = 10, depth: int = 3, seed: int = 0) -> Vocabulary:
        """Cluster ``descriptors`` (N, W) into a vocabulary tree (seeded, reproducible)."""
        d = _local_descriptors(descriptors, "descriptors")
        return cls(_core.Vocabulary.train(d, branching=branching, depth=depth, seed=seed))

    def __len__(self) -> int:
        return len(self._vocabulary)

    def words(self, descriptors: ArrayLike) -> NDArray[np.uint32]:
        """The word of each descriptor (N,)."""
        return self._vocabulary.words(_local_descriptors(descriptors, "descriptors"))


class BowDatabase:
    """TF-IDF bag-of-words image database (L1 scoring, DBoW2's), built from the local
    descriptors of each image; :meth:`query` ranks the images for a query image. Scores are
    in [0, 1] and reproducible bit for bit; equal scores rank by image index.

    Term frequency per descriptor kind (as in :meth:`geoloc.Map.from_features`): the word's
    count for binary descriptors (ORB, DBoW2's), its presence (0/1) for float ones (SIFT,
    RootSIFT) — SIFT fires dozens of times on one repetitive texture (a striped carpet),
    and with counts those bursts made a few keyframes every query's best match."""

    def __init__(self, vocabulary: Vocabulary, images: list[ArrayLike]) -> None:
        if not isinstance(vocabulary, Vocabulary):
            raise InvalidInputError(f"vocabulary: expected a geoloc.retrieval.Vocabulary, got {type(vocabulary).__name__}")
        self.vocabulary = vocabulary
        if isinstance(images, (str, bytes, np.ndarray)) and np.ndim(images) < 3 or not hasattr(images, "__iter__"):
            raise InvalidInputError(f"images: expected a list of (N, W) descriptor arrays, got {type(images).__name__}")
        descs = [_local_descriptors(d, f"images[{i}]") for i, d in enumerate(images)]
        try:
            self._database = _core.BowDatabase(vocabulary._vocabulary, descs)
        except InvalidInputError as exc:  # the core names its own argument, `descriptors`
            raise type(exc)(f"images: {exc}") from None

    def __len__(self) -> int:
        return len(self._database)

    def query(self, descriptors: ArrayLike, k: int = 1) -> tuple[NDArray[np.float32], NDArray[np.int64]]:
        """Scores (k,) in [0, 1] and image indices (k,) of the best images, best first."""
        return self._database.query(_local_descriptors(descriptors, "descriptors"), k)
