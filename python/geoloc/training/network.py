"""The descriptor network: Inception v1 (GoogLeNet) or a tiny CNN, then FC → L2-normalized D.

GoogLeNet follows Szegedy et al., *Going deeper with convolutions* (CVPR 2015), Table 1: the
stem (7×7/2 conv 64, max pool, 1×1 conv 64, 3×3 conv 192, max pool), inception blocks
3a 3b, max pool, 4a–4e, max pool, 5a 5b (1024 channels), global average pooling, dropout
40 %; written in plain torch (torchvision is not a dependency). Two changes, both common in
re-implementations: every convolution is followed by batch normalization (instead of the
two local response normalizations), because it trains from scratch on a few hundred images
with Adam at 1e-3; the auxiliary classifiers are left out (they served ImageNet training).
The 5×5 branch is a real 5×5 convolution as in the paper. The input is one grayscale
channel (the paper's Siamese network uses 224×224 grayscale images).

The head is a fully connected layer to D (default :data:`DEFAULT_DIM` = 128: the paper does
not state its descriptor size) followed by L2 normalization, so descriptors live on the unit
sphere, distances are in [0, 2] and the contrastive margin m = 1 is meaningful. Both twins of
the Siamese network are this one module (shared weights): a pair is two forward passes.

``backbone="tiny"`` is a 3-conv CNN on a 56×56 average-pooled input (≈ 0.4 M parameters,
≈ 9 M multiply-adds) for CPUs and tests; it keeps the 7×7 spatial grid before the FC so the
descriptor knows where things are in the image, which matters for telling apart places in
one scene.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import nn
from torch.nn import functional as F

__all__ = ["BACKBONES", "DEFAULT_DIM", "DescriptorNet", "GoogLeNet", "Inception", "TinyBackbone", "build_network"]

DEFAULT_DIM = 128
Backbone = Literal["googlenet", "tiny"]
BACKBONES: tuple[str, ...] = ("googlenet", "tiny")
#: Dropout before the FC of GoogLeNet (the paper's 40 %).
GOOGLENET_DROPOUT = 0.4
#: BatchNorm epsilon (as the BN-Inception re-implementations).
BN_EPS = 1e-3


class ConvBN(nn.Sequential):
    """Convolution (no bias) → batch norm → ReLU."""

    def __init__(self, c_in: int, c_out: int, kernel: int, stride: int = 1, padding: int = 0) -> None:
        super().__init__(
            nn.Conv2d(c_in, c_out, kernel, stride=stride, padding=padding, bias=False),
            nn.BatchNorm2d(c_out, eps=BN_EPS),
            nn.ReLU(inplace=True),
        )


class Inception(nn.Module):
    """One inception block: 1×1 | 1×1→3×3 | 1×1→5×5 | 3×3 max pool→1×1, concatenated."""

    def __init__(self, c_in: int, c1: int, c3r: int, c3: int, c5r: int, c5: int, pool: int) -> None:
        super().__init__()
        self.branch1 = ConvBN(c_in, c1, 1)
        self.branch3 = nn.Sequential(ConvBN(c_in, c3r, 1), ConvBN(c3r, c3, 3, padding=1))
        self.branch5 = nn.Sequential(ConvBN(c_in, c5r, 1), ConvBN(c5r, c5, 5, padding=2))
        self.branch_pool = nn.Sequential(nn.MaxPool2d(3, stride=1, padding=1), ConvBN(c_in, pool, 1))
        self.out_channels = c1 + c3 + c5 + pool

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.cat([self.branch1(x), self.branch3(x), self.branch5(x), self.branch_pool(x)], dim=1)


#: (name, #1×1, #3×3 reduce, #3×3, #5×5 reduce, #5×5, pool proj) — Szegedy et al. 2015, Table 1.
INCEPTION_LAYOUT: tuple[tuple[str, int, int, int, int, int, int], ...] = (
    ("3a", 64, 96, 128, 16, 32, 32),
    ("3b", 128, 128, 192, 32, 96, 64),
    ("4a", 192, 96, 208, 16, 48, 64),
    ("4b", 160, 112, 224, 24, 64, 64),
    ("4c", 128, 128, 256, 24, 64, 64),
    ("4d", 112, 144, 288, 32, 64, 64),
    ("4e", 256, 160, 320, 32, 128, 128),
    ("5a", 256, 160, 320, 32, 128, 128),
    ("5b", 384, 192, 384, 48, 128, 128),
)
#: A 3×3/2 max pool comes after these blocks (28→14 after 3b, 14→7 after 4e).
POOL_AFTER = ("3b", "4e")


class GoogLeNet(nn.Module):
    """Inception v1 feature extractor: (N, 1, 224, 224) → (N, 1024) (global average pool)."""

    def __init__(self, in_channels: int = 1) -> None:
        super().__init__()
        self.stem = nn.Sequential(
            ConvBN(in_channels, 64, 7, stride=2, padding=3),  # 112
            nn.MaxPool2d(3, stride=2, ceil_mode=True),  # 56
            ConvBN(64, 64, 1),
            ConvBN(64, 192, 3, padding=1),
            nn.MaxPool2d(3, stride=2, ceil_mode=True),  # 28
        )
        blocks: list[nn.Module] = []
        c = 192
        for name, *widths in INCEPTION_LAYOUT:
            block = Inception(c, *widths)
            blocks.append(block)
            c = block.out_channels
            if name in POOL_AFTER:
                blocks.append(nn.MaxPool2d(3, stride=2, ceil_mode=True))
        self.blocks = nn.Sequential(*blocks)
        self.out_features = c  # 1024

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.blocks(self.stem(x))
        return torch.flatten(F.adaptive_avg_pool2d(x, 1), 1)


class TinyBackbone(nn.Module):
    """A small CNN: a 4×4 average pool on the input (224 → 56), then three conv blocks with
    2×2 max pools (56 → 28 → 14 → 7), flattened: (N, 4·width·7·7) — the 7×7 grid is kept."""

    def __init__(self, in_channels: int = 1, width: int = 16) -> None:
        super().__init__()
        self.features = nn.Sequential(
            nn.AvgPool2d(4),  # 56×56: the input resolution a tiny network can use
            ConvBN(in_channels, width, 5, padding=2),
            nn.MaxPool2d(2),  # 28
            ConvBN(width, 2 * width, 3, padding=1),
            nn.MaxPool2d(2),  # 14
            ConvBN(2 * width, 4 * width, 3, padding=1),
            nn.MaxPool2d(2),  # 7
        )
        self.out_features = 4 * width * 7 * 7

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.flatten(self.features(x), 1)


class DescriptorNet(nn.Module):
    """Backbone → (dropout) → FC → L2 normalization: (N, 1, 224, 224) → (N, dim) unit rows."""

    def __init__(self, backbone: Backbone = "googlenet", dim: int = DEFAULT_DIM, dropout: float | None = None) -> None:
        super().__init__()
        if backbone not in BACKBONES:
            raise ValueError(f"backbone: expected one of {BACKBONES}, got {backbone!r}")
        if not isinstance(dim, int) or dim < 1:
            raise ValueError(f"dim: expected a positive integer, got {dim!r}")
        self.backbone_name = backbone
        self.dim = dim
        self.backbone: nn.Module = GoogLeNet() if backbone == "googlenet" else TinyBackbone()
        p = (GOOGLENET_DROPOUT if backbone == "googlenet" else 0.0) if dropout is None else dropout
        self.dropout = nn.Dropout(p)
        self.fc = nn.Linear(int(self.backbone.out_features), dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        z = self.fc(self.dropout(self.backbone(x)))
        # x / max(‖x‖, ε), spelled out so the ONNX graph is plain ReduceL2/Max/Div
        out: torch.Tensor = z / torch.clamp(torch.linalg.vector_norm(z, dim=1, keepdim=True), min=1e-12)
        return out


def build_network(backbone: Backbone = "googlenet", dim: int = DEFAULT_DIM) -> DescriptorNet:
    """A freshly initialized :class:`DescriptorNet` (Kaiming-normal convolutions, the torch
    default elsewhere); seed torch first for reproducible weights."""
    net = DescriptorNet(backbone, dim)
    for m in net.modules():
        if isinstance(m, nn.Conv2d):
            nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
    return net
