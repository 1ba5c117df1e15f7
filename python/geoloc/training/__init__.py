"""Training the paper's image descriptor network (needs the ``train`` extra: PyTorch).

A Siamese Inception v1 (GoogLeNet, written in plain torch) on grayscale 224×224 images,
contrastive loss with margin 1 on pairs labelled by their poses, exported to ONNX for
:class:`geoloc.descriptor.OnnxDescriptor`.

Modules: :mod:`.frames` (the input protocol, torch-free), :mod:`.pairs` (pose-threshold pair
sampling, numpy only), :mod:`.network`, :mod:`.loss`, :mod:`.train`, :mod:`.export` (torch)
and :mod:`.command` (``geoloc train``). This ``__init__`` imports no torch, so the runtime
package and the CLI can import ``geoloc.training.command`` without it; nothing in
``geoloc`` outside this subpackage imports it.
"""

from __future__ import annotations

#: What to install when torch is missing (one line, shown by ``geoloc train``).
INSTALL_HINT = 'pip install "geoloc[train]"'


def require_torch() -> None:
    """Raise :class:`geoloc.GeolocError` with the install command when torch is missing."""
    try:
        import torch  # noqa: F401
    except ImportError:
        from ..exceptions import GeolocError

        raise GeolocError(f"training needs PyTorch, which is not installed: {INSTALL_HINT}") from None
