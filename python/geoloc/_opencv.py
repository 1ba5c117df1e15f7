"""Optional heavy imports (OpenCV, matplotlib), imported on first use so that
``import geoloc`` needs numpy only; a missing package names what to install."""

from __future__ import annotations

from typing import Any

__all__ = ["import_cv2", "import_figure"]


def import_cv2(purpose: str) -> Any:
    """The ``cv2`` module, or an ImportError saying that ``purpose`` needs OpenCV."""
    try:
        import cv2  # type: ignore[import-not-found,unused-ignore]
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(f"{purpose} needs OpenCV: pip install opencv-python-headless") from exc
    return cv2


def import_figure() -> Any:
    """``matplotlib.figure.Figure``: figures drawn without pyplot (no global state, no
    display; ``Figure.savefig`` renders PNGs with the Agg canvas)."""
    try:
        from matplotlib.figure import Figure
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError("plots need matplotlib: pip install matplotlib") from exc
    return Figure
