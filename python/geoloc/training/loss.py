"""The contrastive loss (Hadsell, Chopra & LeCun, CVPR 2006), the paper's Eq. (contrastive).

For descriptors a, b of a pair with label Y (0 = similar, 1 = dissimilar) and
D = ‖a − b‖₂:

    L(a, b, Y) = (1 − Y) · ½ D²  +  Y · ½ max(0, m − D)²,     m = 1 (the margin)

averaged over the pairs. The paper writes it as L(s₁, s₂) with s₁ the label and s₂ the
distance. Similar pairs are pulled together; dissimilar ones pushed apart until they are m
apart, and left alone beyond (with L2-normalized descriptors D ∈ [0, 2]).
"""

from __future__ import annotations

import torch

__all__ = ["DEFAULT_MARGIN", "contrastive_loss"]

DEFAULT_MARGIN = 1.0
#: Added under the square root of D so its gradient stays finite at D = 0.
DISTANCE_EPS = 1e-12


def contrastive_loss(a: torch.Tensor, b: torch.Tensor, label: torch.Tensor, margin: float = DEFAULT_MARGIN) -> torch.Tensor:
    """Mean contrastive loss of the pairs (a[k], b[k]) with label[k] ∈ {0 similar, 1 dissimilar}.

    ``a``, ``b``: (N, D); ``label``: (N,) integers or floats. Returns a scalar tensor.
    """
    if a.shape != b.shape or a.ndim != 2 or label.shape != (a.shape[0],):
        raise ValueError(f"expected a, b of shape (N, D) and label (N,), got {tuple(a.shape)}, {tuple(b.shape)}, {tuple(label.shape)}")
    if margin <= 0:
        raise ValueError(f"margin: expected > 0, got {margin!r}")
    y = label.to(a.dtype)
    d2 = (a - b).pow(2).sum(dim=1)
    d = torch.sqrt(d2 + DISTANCE_EPS)
    per_pair = (1.0 - y) * 0.5 * d2 + y * 0.5 * torch.clamp(margin - d, min=0.0).pow(2)
    return per_pair.mean()
