"""Global image descriptors at run time: the CNN through onnxruntime, and a tiny-image baseline.

Everything here is torch-free: a descriptor network trained with ``geoloc.training`` (the
``train`` extra, PyTorch) is exported to ONNX and run by :class:`OnnxDescriptor` with
onnxruntime only. :func:`preprocess` is the **one** definition of the network's input, used
by training and inference alike, so the two can never drift apart:

    BGR uint8 (H, W, 3) ─► grayscale (OpenCV's BGR2GRAY) ─► 224×224 (INTER_AREA, aspect
    not kept, as the paper's "regularized to 224×224") ─► (g/255 − 0.5)/0.25, float32 (1, 224, 224)

Its version string :data:`PREPROCESS_ID` is written into every exported model and checked
when the model is loaded.

Images follow OpenCV's convention: uint8, (H, W, 3) BGR or (H, W) grayscale. "images" is one
such array, an (N, H, W, 3) array, or a sequence of arrays (sizes may differ).
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any, Mapping, Sequence, Union

import numpy as np
from numpy.typing import NDArray

from ._io import as_path, read_bytes
from .exceptions import GeolocError, InvalidInputError

__all__ = [
    "INPUT_SIZE",
    "PREPROCESS_ID",
    "OnnxDescriptor",
    "normalize",
    "preprocess",
    "tiny_image_descriptors",
    "to_gray",
]

#: Network input (height, width), pixels.
INPUT_SIZE: tuple[int, int] = (224, 224)
#: Intensity normalization of the network input: (gray / 255 − MEAN) / STD.
PIXEL_MEAN = 0.5
PIXEL_STD = 0.25
#: Names the preprocessing above; stored in exported models and checked on load.
PREPROCESS_ID = "gray224-area-mean0.5-std0.25-v1"
#: ONNX metadata keys written by ``geoloc.training.export`` and read here.
META_NAME = "geoloc.name"
META_PREPROCESS = "geoloc.preprocess"
#: The tiny-image baseline's default size (width, height): 768 numbers per image.
TINY_IMAGE_SIZE: tuple[int, int] = (32, 24)
#: The smallest image side accepted (smaller is not an image anyone means to localize).
MIN_IMAGE_SIDE = 8

Images = Union[NDArray[np.uint8], Sequence[NDArray[np.uint8]]]


def _cv2() -> Any:
    try:
        import cv2
    except ImportError:  # pragma: no cover - opencv is a dependency
        raise GeolocError('geoloc.descriptor needs OpenCV: pip install "opencv-python-headless"') from None
    return cv2


def _image_list(images: Any, name: str) -> list[NDArray[np.uint8]]:
    """``images`` as a list of 2-D (gray) or 3-D (H, W, 3) uint8 arrays, each validated."""
    if isinstance(images, np.ndarray):
        if images.ndim == 2 or (images.ndim == 3 and images.shape[2] in (1, 3)):
            items: list[Any] = [images]
        elif images.ndim == 4:
            items = list(images)
        else:
            raise InvalidInputError(
                f"{name}: expected an (H, W, 3) BGR or (H, W) gray uint8 image, an (N, H, W, 3) batch "
                f"or a list of images, got an array of shape {images.shape}"
            )
    elif isinstance(images, (list, tuple)):
        items = list(images)
    else:
        raise InvalidInputError(f"{name}: expected a uint8 image array or a list of them, got {type(images).__name__}")
    out = []
    for i, img in enumerate(items):
        arr = np.asarray(img)
        where = f"{name}[{i}]"
        if arr.dtype != np.uint8:
            raise InvalidInputError(f"{where}: expected dtype uint8 (OpenCV BGR or gray), got {arr.dtype}")
        if arr.ndim == 3 and arr.shape[2] == 1:
            arr = arr[:, :, 0]
        if not (arr.ndim == 2 or (arr.ndim == 3 and arr.shape[2] == 3)):
            raise InvalidInputError(f"{where}: expected shape (H, W, 3) or (H, W), got {arr.shape}")
        if min(arr.shape[:2]) < MIN_IMAGE_SIDE:
            raise InvalidInputError(f"{where}: image of {arr.shape[1]}×{arr.shape[0]} px is smaller than {MIN_IMAGE_SIDE} px")
        out.append(arr)
    return out


def _check_size(size: Any) -> tuple[int, int]:
    """``size`` as (height, width), two integers in [1, 4096]; else InvalidInputError naming it."""
    if (
        not isinstance(size, (tuple, list))
        or len(size) != 2
        or not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in size)
        or not all(1 <= int(v) <= 4096 for v in size)
    ):
        raise InvalidInputError(f"size: expected (height, width), two integers in [1, 4096], got {size!r}")
    return int(size[0]), int(size[1])


def to_gray(images: Images, size: tuple[int, int] = INPUT_SIZE) -> NDArray[np.uint8]:
    """Grayscale images resized to ``size`` = (height, width): (N, height, width) uint8.

    The first, integer half of :func:`preprocess` (training caches this: 50 kB an image)."""
    cv2 = _cv2()
    h, w = _check_size(size)
    frames = _image_list(images, "images")
    out = np.empty((len(frames), h, w), dtype=np.uint8)
    for i, img in enumerate(frames):
        gray = img if img.ndim == 2 else cv2.cvtColor(np.ascontiguousarray(img), cv2.COLOR_BGR2GRAY)
        out[i] = cv2.resize(gray, (w, h), interpolation=cv2.INTER_AREA)
    return out


def normalize(gray: NDArray[np.uint8]) -> NDArray[np.float32]:
    """(N, H, W) uint8 from :func:`to_gray` → (N, 1, H, W) float32 network input."""
    g = np.asarray(gray)
    if g.dtype != np.uint8 or g.ndim != 3:
        raise InvalidInputError(f"gray: expected an (N, H, W) uint8 array, got {g.dtype} {g.shape}")
    x = g.astype(np.float32)[:, None]
    x *= np.float32(1.0 / 255.0)
    x -= np.float32(PIXEL_MEAN)
    x *= np.float32(1.0 / PIXEL_STD)
    return x


def preprocess(images: Images) -> NDArray[np.float32]:
    """The network input of ``images``: (N, 1, 224, 224) float32 (see the module doc).

    >>> preprocess(np.zeros((480, 640, 3), np.uint8)).shape
    (1, 1, 224, 224)
    """
    return normalize(to_gray(images))


def tiny_image_descriptors(images: Images, size: tuple[int, int] = TINY_IMAGE_SIZE) -> NDArray[np.float32]:
    """The tiny-image retrieval baseline: each image in grayscale, downsampled to ``size`` =
    (width, height) by area averaging, made zero-mean and unit-norm: (N, width·height) float32.

    Nearest neighbours under L2 (:class:`geoloc.retrieval.DescriptorIndex`) then rank images
    by normalized cross-correlation. A constant image gives the zero vector.
    """
    h, w = _check_size(size)[::-1]  # size is (width, height) here
    small = to_gray(images, (int(h), int(w))).reshape(-1, int(w) * int(h)).astype(np.float32)
    small -= small.mean(axis=1, keepdims=True)
    norm = np.linalg.norm(small, axis=1, keepdims=True)
    np.divide(small, norm, out=small, where=norm > 0)
    return small


class _BadRow(InvalidInputError):
    """A descriptor row the network got wrong (row ``row`` of its batch)."""

    def __init__(self, name: str, row: int, what: str) -> None:
        super().__init__(f"{name}[{row}]: {what}")
        self.row, self.what = row, what


def _checked_l2_normalize(x: NDArray[np.float32], model: str, name: str) -> NDArray[np.float32]:
    """Rows scaled to unit length; a non-finite row or an all-zero row (which has no
    direction) is refused, naming the row of ``name`` and the model, rather than returned as
    NaN or zeros."""
    norm = np.linalg.norm(x.astype(np.float64), axis=1)
    bad = np.flatnonzero(~np.isfinite(norm) | ~np.isfinite(x).all(axis=1))
    if bad.size:
        raise _BadRow(name, int(bad[0]), f"the network {model!r} gave a non-finite descriptor (NaN or inf)")
    zero = np.flatnonzero(norm == 0)
    if zero.size:
        raise _BadRow(name, int(zero[0]), f"the network {model!r} gave an all-zero descriptor, which cannot be L2-normalised")
    norm32 = np.linalg.norm(x, axis=1, keepdims=True)
    if np.isfinite(norm32).all():  # float32 arithmetic, as the descriptors were always normalised
        out: NDArray[np.float32] = np.divide(x, np.maximum(norm32, np.float32(1e-12)), dtype=np.float32)
    else:  # rows so large that their float32 norm overflows
        out = (x / norm[:, None]).astype(np.float32)
    return out


#: Upper bounds of OnnxDescriptor's ``threads`` (4236 threads hung the session's creation) and
#: ``batch_size`` (onnxruntime takes a C int; a batch is held in memory at once).
MAX_THREADS = 256
MAX_BATCH = 4096


def _positive_int(value: Any, name: str, high: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not 1 <= value <= high:
        raise InvalidInputError(f"{name}: expected an integer in [1, {high}], got {value!r}")
    return int(value)


class OnnxDescriptor:
    """A global image descriptor network exported to ONNX, run with onnxruntime on the CPU.

    ``descriptor(images)`` gives (N, D) float32 L2-normalized rows (see the module doc for
    what "images" may be), computed ``batch_size`` images at a time with ``threads``
    intra-op threads. The model must take (N, 1, 224, 224) float32 and give (N, D); a model
    exported by ``geoloc train`` also records its name and preprocessing, which must be
    this module's :data:`PREPROCESS_ID`.

    :attr:`name`, :attr:`input_size`, :attr:`dim` and :attr:`sha256` (of the file) identify
    the model; :attr:`signature` gathers them so a map can record which model built it and
    :meth:`check_signature` refuses another one.
    """

    def __init__(self, path: str | Path, threads: int = 2, batch_size: int = 16) -> None:
        self.threads = _positive_int(threads, "threads", MAX_THREADS)
        self.batch_size = _positive_int(batch_size, "batch_size", MAX_BATCH)
        self.path = as_path(path, "path")
        try:
            data = read_bytes(self.path, "path")  # a FIFO or folder is refused, never opened
        except InvalidInputError as e:
            raise InvalidInputError(f"path: cannot read the model file ({str(e).removeprefix('path: ')})") from None
        self.sha256 = hashlib.sha256(data).hexdigest()
        try:
            import onnxruntime as ort  # type: ignore[import-untyped]
        except ImportError:  # pragma: no cover - a dependency
            raise GeolocError('OnnxDescriptor needs onnxruntime: pip install "onnxruntime>=1.18"') from None
        options = ort.SessionOptions()
        options.intra_op_num_threads = self.threads
        options.inter_op_num_threads = 1
        options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
        options.use_deterministic_compute = True
        options.log_severity_level = 3
        try:
            self._session = ort.InferenceSession(data, options, providers=["CPUExecutionProvider"])
        except Exception as e:  # onnxruntime raises its own exception types for bad files
            first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
            raise InvalidInputError(f"path: {str(self.path)!r} is not a readable ONNX model ({first[:200]})") from None
        inputs, outputs = self._session.get_inputs(), self._session.get_outputs()
        want = f"one input of shape (N, 1, {INPUT_SIZE[0]}, {INPUT_SIZE[1]}) float32 and an (N, D) output"
        if len(inputs) != 1 or len(outputs) < 1:
            raise InvalidInputError(f"path: {str(self.path)!r} is not a descriptor model (expected {want})")
        shape_in, shape_out = list(inputs[0].shape), list(outputs[0].shape)
        if (
            inputs[0].type != "tensor(float)"
            or len(shape_in) != 4
            or shape_in[1:] != [1, *INPUT_SIZE]
            or len(shape_out) != 2
            or not isinstance(shape_out[1], int)
        ):
            raise InvalidInputError(
                f"path: {str(self.path)!r} is not a descriptor model: input {inputs[0].type} {shape_in}, "
                f"output {shape_out} (expected {want})"
            )
        meta = dict(self._session.get_modelmeta().custom_metadata_map)
        recorded = meta.get(META_PREPROCESS)
        if recorded is not None and recorded != PREPROCESS_ID:
            raise InvalidInputError(
                f"path: {str(self.path)!r} was trained with preprocessing {recorded!r}, this geoloc uses {PREPROCESS_ID!r}"
            )
        # A model exported with a fixed batch size (often 1) is run that many images at a time.
        fixed = shape_in[0]
        if isinstance(fixed, int) and not 1 <= fixed <= MAX_BATCH:
            raise InvalidInputError(f"path: {str(self.path)!r} has a fixed batch size of {fixed}")
        self.fixed_batch: int | None = fixed if isinstance(fixed, int) else None
        self._input_name = inputs[0].name
        self._output_name = outputs[0].name
        self.name: str = meta.get(META_NAME) or self.path.stem
        self.input_size: tuple[int, int] = INPUT_SIZE
        self.dim: int = int(shape_out[1])
        self.metadata: dict[str, str] = meta

    def __repr__(self) -> str:
        return f"OnnxDescriptor({str(self.path)!r}, name={self.name!r}, dim={self.dim}, sha256={self.sha256[:12]}…)"

    @property
    def signature(self) -> dict[str, Any]:
        """What identifies this model: name, input_size (height, width), dim, sha256."""
        return {"name": self.name, "input_size": list(self.input_size), "dim": self.dim, "sha256": self.sha256}

    def check_signature(self, recorded: Mapping[str, Any], what: str = "the map") -> None:
        """Raise :class:`InvalidInputError` unless ``recorded`` (a :attr:`signature`) is this model's."""
        if recorded.get("sha256") != self.sha256:
            raise InvalidInputError(
                f"descriptor: {what} was built with model {recorded.get('name')!r} "
                f"(sha256 {str(recorded.get('sha256'))[:12]}…), not {self.name!r} (sha256 {self.sha256[:12]}…); "
                "use the same model file or rebuild"
            )

    def run_preprocessed(self, batch: NDArray[np.float32]) -> NDArray[np.float32]:
        """Descriptors of already preprocessed (N, 1, 224, 224) float32 input, N ≤ anything."""
        x = np.asarray(batch)
        if x.dtype != np.float32 or x.ndim != 4 or x.shape[1:] != (1, *INPUT_SIZE):
            raise InvalidInputError(f"batch: expected (N, 1, {INPUT_SIZE[0]}, {INPUT_SIZE[1]}) float32, got {x.dtype} {x.shape}")
        n = x.shape[0]
        if n == 0:
            return np.zeros((0, self.dim), dtype=np.float32)
        step = self.fixed_batch or n
        rows = []
        for start in range(0, n, step):
            chunk = np.ascontiguousarray(x[start : start + step])
            if len(chunk) < step:  # a fixed-size batch, padded with copies of its first image
                chunk = np.concatenate([chunk, np.repeat(chunk[:1], step - len(chunk), axis=0)])
            (out,) = self._session.run([self._output_name], {self._input_name: chunk})
            rows.append(np.asarray(out, dtype=np.float32).reshape(step, -1)[: min(step, n - start)])
        raw = np.concatenate(rows)
        if raw.shape != (n, self.dim):
            raise InvalidInputError(f"path: {str(self.path)!r} gave descriptors of shape {raw.shape} for {n} images, expected ({n}, {self.dim})")
        return _checked_l2_normalize(raw, self.name, "batch")

    def __call__(self, images: Images) -> NDArray[np.float32]:
        """(N, D) float32 L2-normalized descriptors of ``images``."""
        frames = _image_list(images, "images")
        out = np.empty((len(frames), self.dim), dtype=np.float32)
        for start in range(0, len(frames), self.batch_size):
            chunk = frames[start : start + self.batch_size]
            try:
                out[start : start + len(chunk)] = self.run_preprocessed(preprocess(chunk))
            except _BadRow as e:
                raise InvalidInputError(f"images[{start + e.row}]: {e.what}") from None
        return out
