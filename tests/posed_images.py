"""Posed images for the descriptor tests: the shared 7-Scenes frames when present, else a
small rendered stand-in (a camera looping twice around a box room with textured walls)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from geoloc.training.frames import PosedImage

#: ../shared/data beside the repository (tests skip or fall back when it is absent).
SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
SEVEN_SCENES = SHARED_DATA / "7scenes-redkitchen"

ROOM_HALF = np.array([3.0, 1.2, 3.0])  # box room [-x, x] × [-y, y] × [-z, z], metres
TEXTURE = 256
WIDTH, HEIGHT, FOCAL = 160, 120, 130.0


def _textures(rng: np.random.Generator) -> list[np.ndarray]:
    out = []
    for _ in range(6):
        tex = np.full((TEXTURE, TEXTURE, 3), rng.integers(40, 200, 3), dtype=np.uint8)
        for _ in range(25):
            colour = tuple(int(c) for c in rng.integers(0, 256, 3))
            if rng.random() < 0.5:
                c = rng.integers(0, TEXTURE, 2)
                cv2.circle(tex, (int(c[0]), int(c[1])), int(rng.integers(6, 40)), colour, -1)
            else:
                a, b = rng.integers(0, TEXTURE, 2), rng.integers(0, TEXTURE, 2)
                cv2.rectangle(tex, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), colour, -1)
        out.append(tex)
    return out


def _pose(t: float, radius: float) -> np.ndarray:
    """world_from_cam on a circle, looking outward-ish (x right, y down, z forward)."""
    c = np.array([radius * np.cos(t), 0.1 * np.sin(3 * t), radius * np.sin(t)])
    yaw = t + 0.6
    forward = np.array([np.cos(yaw), 0.0, np.sin(yaw)])
    down = np.array([0.0, 1.0, 0.0])
    right = np.cross(down, forward)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, down, forward], axis=1)
    pose[:3, 3] = c
    return pose


def render(pose: np.ndarray, textures: list[np.ndarray]) -> np.ndarray:
    """BGR image of the box room seen from ``pose`` (nearest-texel lookup)."""
    u, v = np.meshgrid(np.arange(WIDTH) - WIDTH / 2 + 0.5, np.arange(HEIGHT) - HEIGHT / 2 + 0.5)
    rays = np.stack([u / FOCAL, v / FOCAL, np.ones_like(u)], axis=-1) @ pose[:3, :3].T
    origin = pose[:3, 3]
    best_t = np.full(u.shape, np.inf)
    image = np.zeros((HEIGHT, WIDTH, 3), dtype=np.uint8)
    for axis in range(3):
        for side, sign in enumerate((-1.0, 1.0)):
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (sign * ROOM_HALF[axis] - origin[axis]) / rays[..., axis]
            hit = origin + t[..., None] * rays
            others = [a for a in range(3) if a != axis]
            s = (hit[..., others[0]] / ROOM_HALF[others[0]] + 1) / 2
            r = (hit[..., others[1]] / ROOM_HALF[others[1]] + 1) / 2
            ok = (t > 0) & (t < best_t) & (s >= 0) & (s <= 1) & (r >= 0) & (r <= 1)
            tex = textures[2 * axis + side]
            ix = np.clip((s * (TEXTURE - 1)).astype(int), 0, TEXTURE - 1)
            iy = np.clip((r * (TEXTURE - 1)).astype(int), 0, TEXTURE - 1)
            image[ok] = tex[iy[ok], ix[ok]]
            best_t = np.where(ok, t, best_t)
    return image


def _lighting(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A random linear illumination ramp (up to ±70 %) across the image: breaks global
    correlation, keeps local structure."""
    h, w = image.shape[:2]
    angle = rng.uniform(0, 2 * np.pi)
    yy, xx = np.mgrid[0:h, 0:w]
    ramp = ((xx / w - 0.5) * np.cos(angle) + (yy / h - 0.5) * np.sin(angle)) * rng.uniform(0.6, 1.4)
    return np.clip(image * (1.0 + ramp)[..., None], 0, 255).astype(np.uint8)


def _yawed(pose: np.ndarray, yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    out = pose.copy()
    out[:3, :3] = pose[:3, :3] @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return out


def standin(n_train: int = 240, n_test: int = 60, seed: int = 0) -> tuple[list[PosedImage], list[PosedImage]]:
    """Training frames: a loop at radius 1.2 m; test frames: a later loop at radius 1.35 m,
    turned ±10° off the training headings; every frame under a random illumination ramp."""
    rng = np.random.default_rng(seed)
    textures = _textures(rng)
    train = [_pose(2 * np.pi * i / n_train, 1.2) for i in range(n_train)]
    test = [_yawed(_pose(2 * np.pi * (i + 0.5) / n_test, 1.35), np.radians(10.0) * (-1) ** i) for i in range(n_test)]
    make = lambda p: PosedImage(_lighting(render(p, textures), rng), p)  # noqa: E731
    return [make(p) for p in train], [make(p) for p in test]


def seven_scenes(indices: range | list[int]) -> list[PosedImage]:
    """The chosen shared 7-Scenes frames (call only when SEVEN_SCENES exists)."""
    from geoloc.training.frames import SevenScenesFrames

    return SevenScenesFrames(SEVEN_SCENES).subset(list(indices))
