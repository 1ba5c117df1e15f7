"""ONNX export of a trained descriptor network, checked against torch as part of the export.

The file takes ``image`` (N, 1, 224, 224) float32 — ``geoloc.descriptor.preprocess`` — and
gives ``descriptor`` (N, D) float32 L2-normalized rows, N dynamic. Its metadata records the
model's name, backbone, dimension and preprocessing id, which
:class:`geoloc.descriptor.OnnxDescriptor` reads and checks.

The TorchScript-based exporter (``dynamo=False``) is used on purpose: it writes one
self-contained file (the torch.export-based one splits large weights into a side file and
needs onnxscript) and these networks are plain convolutions. Its deprecation notice is
silenced here; torch is pinned by the ``train`` extra.

Before the file is moved into place, onnxruntime runs it on seeded random inputs (batch 1
and 3) and the largest absolute difference from torch is printed and must stay below
``atol`` (default :data:`PARITY_ATOL` = 1e-4), or the export fails and nothing is written.
"""

from __future__ import annotations

import hashlib
import math
import os
import sys
import tempfile
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np
import torch

from .._io import check_output_path, write_bytes_atomic
from .._validation import real_scalar
from ..descriptor import INPUT_SIZE, META_NAME, META_PREPROCESS, PREPROCESS_ID
from ..exceptions import GeolocError, InvalidInputError
from .network import DescriptorNet

__all__ = ["ExportReport", "PARITY_ATOL", "export_onnx"]

#: Largest |onnxruntime − torch| accepted on the parity inputs.
PARITY_ATOL = 1e-4
OPSET = 17
#: Batch sizes of the parity check (1 and a batch other than the traced one).
PARITY_BATCHES = (1, 3)


@dataclass(frozen=True)
class ExportReport:
    """Where the model went, its size and hash, and the parity check's max |difference|."""

    path: Path
    size_bytes: int
    sha256: str
    max_abs_diff: float
    dim: int


def _onnx_bytes(model: DescriptorNet) -> bytes:
    dummy = torch.zeros(2, 1, *INPUT_SIZE)
    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        file = Path(tmp) / "model.onnx"
        warnings.filterwarnings("ignore", category=DeprecationWarning)
        warnings.filterwarnings("ignore", category=FutureWarning)
        torch.onnx.export(
            model,
            (dummy,),
            file,
            input_names=["image"],
            output_names=["descriptor"],
            dynamic_axes={"image": {0: "batch"}, "descriptor": {0: "batch"}},
            opset_version=OPSET,
            do_constant_folding=True,
            dynamo=False,
        )
        return file.read_bytes()


def _with_metadata(data: bytes, meta: dict[str, str]) -> bytes:
    import onnx

    proto = onnx.load_from_string(data)
    del proto.metadata_props[:]
    for key, value in meta.items():
        entry = proto.metadata_props.add()
        entry.key, entry.value = key, value
    proto.producer_name = "geoloc"
    onnx.checker.check_model(proto)
    return bytes(proto.SerializeToString())


def _parity(data: bytes, model: DescriptorNet, seed: int) -> float:
    import onnxruntime as ort  # type: ignore[import-untyped]

    session = ort.InferenceSession(data, providers=["CPUExecutionProvider"])
    gen = torch.Generator().manual_seed(seed)
    worst = 0.0
    for batch in PARITY_BATCHES:
        x = torch.randn(batch, 1, *INPUT_SIZE, generator=gen)
        with torch.no_grad():
            want = model(x).numpy()
        (got,) = session.run(["descriptor"], {"image": x.numpy()})
        if got.shape != want.shape:
            raise GeolocError(f"export: onnxruntime gave shape {got.shape}, torch {want.shape}")
        worst = max(worst, float(np.abs(got - want).max()))
    return worst


def export_onnx(
    model: DescriptorNet,
    path: str | os.PathLike[str],
    name: str | None = None,
    atol: float = PARITY_ATOL,
    seed: int = 0,
    log: TextIO | None = None,
    quiet: bool = False,
) -> ExportReport:
    """Write ``model`` to ``path`` as ONNX (atomically) after checking it against torch.

    ``name`` (default: the file's stem) is stored in the metadata and becomes
    ``OnnxDescriptor.name``. Raises :class:`geoloc.GeolocError` when onnxruntime and torch
    differ by more than ``atol``; the check's result is printed to ``log`` (default: stderr)
    unless ``quiet``.
    """
    if not isinstance(model, DescriptorNet):
        raise InvalidInputError(f"model: expected a geoloc DescriptorNet, got {type(model).__name__}")
    if name is not None and not isinstance(name, str):
        raise InvalidInputError(f"name: expected a string or None, got {type(name).__name__}")
    bound = real_scalar(atol, "atol")
    if not (math.isfinite(bound) and bound > 0):
        raise InvalidInputError(f"atol: expected a finite number > 0, got {atol!r}")
    try:
        out = check_output_path(path, "path")
    except InvalidInputError as e:
        raise InvalidInputError(str(e).replace("path: folder", "path: the folder", 1)) from None
    model = model.eval().cpu()
    meta = {
        META_NAME: name or out.stem,
        META_PREPROCESS: PREPROCESS_ID,
        "geoloc.backbone": model.backbone_name,
        "geoloc.dim": str(model.dim),
    }
    data = _with_metadata(_onnx_bytes(model), meta)
    diff = _parity(data, model, seed)
    if not quiet:
        print(f"export: onnxruntime vs torch on random inputs (batches {PARITY_BATCHES}): max |diff| = {diff:.2e} (bound {atol:.0e})", file=log or sys.stderr)
    if not diff <= atol:
        raise GeolocError(f"export: onnxruntime and torch differ by {diff:.2e} > {atol:.0e}; the file was not written")
    write_bytes_atomic(out, data, "path")
    return ExportReport(out, len(data), hashlib.sha256(data).hexdigest(), diff, model.dim)
