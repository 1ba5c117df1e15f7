"""Hand-made ONNX descriptor models for the tests (needs the ``onnx`` package): a linear map of
the flattened (N, 1, 224, 224) input to (N, D), with a fixed or free batch dimension and chosen
weights (zero weights and an ``inf`` bias give inf rows; zero weights and bias give zero rows)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

PIXELS = 224 * 224


def linear_model(path: Path, batch: int | None = None, dim: int = 8, weight_scale: float = 1e-3, bias: float = 0.0) -> Path:
    """Write the model to ``path``; ``batch`` None is a free batch dimension."""
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    n: int | str = "N" if batch is None else batch
    weights = (np.random.default_rng(0).normal(size=(PIXELS, dim)) * weight_scale).astype(np.float32)
    graph = helper.make_graph(
        [
            helper.make_node("Flatten", ["image"], ["flat"], axis=1),
            helper.make_node("MatMul", ["flat", "w"], ["lin"]),
            helper.make_node("Add", ["lin", "b"], ["descriptor"]),
        ],
        "linear",
        [helper.make_tensor_value_info("image", TensorProto.FLOAT, [n, 1, 224, 224])],
        [helper.make_tensor_value_info("descriptor", TensorProto.FLOAT, [n, dim])],
        [numpy_helper.from_array(weights, "w"), numpy_helper.from_array(np.full(dim, bias, np.float32), "b")],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)])
    model.ir_version = 8
    onnx.save(model, str(path))
    return path
