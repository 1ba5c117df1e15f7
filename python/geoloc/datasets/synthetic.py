"""A built-in synthetic indoor scene with exact poses: the room of ``geoloc demo``.

The room (world frame: metres, **z up**, origin at the floor's centre) is
``ROOM_SIZE_M`` = 6 × 5 × 2.6 m: four walls, floor, ceiling and four furniture boxes
standing near the walls. Every surface has its own procedural texture (seeded, distinct per
surface, never tiled): a smooth colour wash under hundreds of random high-contrast polygons,
triangles and letters of many sizes (2–25 cm), so ORB finds many corners on every view and
matches are unambiguous. Surfaces are shaded by their orientation.

The camera (640×480, fx = fy = 525, cx = 319.5, cy = 239.5, no distortion) goes **twice
around an ellipse** in the middle of the room (semi-axes 1.4 × 1.0 m), looking outwards at
the walls and furniture and slightly down at the floor. The two laps revisit the same places
at different heights (1.2 → 1.5 m and back) and headings (±12° yaw offset), so frames of one
lap localize against the other. Timestamps are frame / 30 s; poses are world_from_cam
(camera x right, y down, z forward), exact.

Rendering: :mod:`geoloc.datasets.render` (planar homographies + per-pixel depth test).
Options perturb the images only, never the poses: Gaussian pixel ``noise`` (σ in grey
levels), Gaussian ``blur`` (σ in pixels) and ``lighting = (gain, offset)`` applied as
``gain·I + offset``. Same arguments → identical bytes (noise is seeded per frame by
``(seed, frame index)``, so the order of access does not matter).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from .._opencv import import_cv2
from ..camera import Camera
from ..exceptions import InvalidInputError
from .render import TexturedRect, render_view
from .sequence import Sequence

__all__ = ["SYNTHETIC_CAMERA", "SyntheticRoom", "room_trajectory", "synthetic_room"]

SYNTHETIC_CAMERA = Camera(525.0, 525.0, 319.5, 239.5, 640, 480)
FRAME_RATE_HZ = 30.0
ROOM_SIZE_M = (6.0, 5.0, 2.6)
TEXELS_PER_M = 256.0
SHAPES_PER_M2 = 140.0
SHAPE_SIZE_RANGE_M = (0.02, 0.25)
# Furniture boxes: (centre x, centre y, size x, size y, height), metres.
FURNITURE = (
    (2.25, 1.55, 1.0, 0.7, 0.8),
    (-2.45, -0.9, 0.6, 1.3, 1.7),
    (0.7, -2.05, 1.4, 0.5, 1.0),
    (-1.1, 2.0, 0.9, 0.6, 0.55),
)
ELLIPSE_SEMI_AXES_M = (1.4, 1.0)
MEAN_HEIGHT_M = 1.35
HEIGHT_SWING_M = 0.15
YAW_SWING_RAD = math.radians(12.0)
PITCH_RAD = math.radians(-18.0)
PITCH_SWING_RAD = math.radians(5.0)
ROLL_SWING_RAD = math.radians(3.0)
_LIGHT_DIRECTION = np.array([0.3, -0.5, 0.81]) / np.linalg.norm([0.3, -0.5, 0.81])


# ---------------------------------------------------------------------------- textures


def _texture(rng: np.random.Generator, width_m: float, height_m: float, shade: float) -> NDArray[np.uint8]:
    """A corner-rich, non-repeating texture of ``width_m × height_m`` at TEXELS_PER_M."""
    cv2 = import_cv2("the synthetic scene")
    w = max(int(round(width_m * TEXELS_PER_M)), 8)
    h = max(int(round(height_m * TEXELS_PER_M)), 8)
    coarse = rng.uniform(40, 215, size=(max(h // 96, 2), max(w // 96, 2), 3)).astype(np.float32)
    img = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
    img = np.clip(img, 0, 255).astype(np.uint8)
    n = int(SHAPES_PER_M2 * width_m * height_m)
    lo, hi = (s * TEXELS_PER_M for s in SHAPE_SIZE_RANGE_M)
    sizes = np.exp(rng.uniform(math.log(lo), math.log(hi), n))
    centres = rng.uniform([0, 0], [w, h], (n, 2))
    kinds = rng.integers(0, 4, n)
    colours = rng.integers(0, 256, (n, 3))
    angles = rng.uniform(0, 2 * math.pi, (n, 5))
    radii = rng.uniform(0.35, 1.0, (n, 5))
    letters = rng.integers(0, 36, (n, 2))
    alphabet = "ABCDEFGHKMNPRTVWXYZ2345789#%&@$EFHKL"
    for k in range(n):
        colour = tuple(int(c) for c in colours[k])
        r = sizes[k] / 2
        if kinds[k] == 3:
            text = alphabet[letters[k, 0]] + alphabet[letters[k, 1]]
            scale = sizes[k] / 40.0
            org = (int(centres[k, 0] - r), int(centres[k, 1] + r / 2))
            cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, colour, max(int(scale * 2.5), 1), cv2.LINE_AA)
            continue
        corners = 3 if kinds[k] == 0 else (4 if kinds[k] == 1 else 5)
        a = np.sort(angles[k, :corners])
        pts = centres[k] + r * radii[k, :corners, None] * np.column_stack([np.cos(a), np.sin(a)])
        cv2.fillPoly(img, [np.round(pts * 16).astype(np.int32)], colour, cv2.LINE_AA, shift=4)
    # Mirrored left-right: a rectangle's (u, v) is a left-handed pair seen from its visible
    # side (u × v points at the viewer), so this makes letters read the right way round.
    shaded: NDArray[np.uint8] = np.clip(np.asarray(img[:, ::-1], dtype=np.float32) * shade, 0, 255).astype(np.uint8)
    shaded.setflags(write=False)
    return shaded


def _rect(rng: np.random.Generator, origin: Iterable[float], u: Iterable[float], v: Iterable[float], a: float, b: float) -> TexturedRect:
    u_arr, v_arr = np.array(u, dtype=np.float64), np.array(v, dtype=np.float64)
    normal = np.cross(u_arr, v_arr)
    shade = 0.72 + 0.28 * abs(float(normal @ _LIGHT_DIRECTION))
    return TexturedRect(np.array(origin, dtype=np.float64), u_arr, v_arr, _texture(rng, a, b, shade), TEXELS_PER_M)


class SyntheticRoom:
    """The room's textured rectangles (built once per seed) and a renderer for any pose."""

    def __init__(self, seed: int = 0) -> None:
        sx, sy, sz = ROOM_SIZE_M
        x0, x1, y0, y1 = -sx / 2, sx / 2, -sy / 2, sy / 2
        # One child generator per surface: distinct, reproducible textures.
        streams = iter(np.random.SeedSequence([seed, 0x600D]).spawn(64))

        def rect(origin: Iterable[float], u: Iterable[float], v: Iterable[float], a: float, b: float) -> TexturedRect:
            return _rect(np.random.default_rng(next(streams)), origin, u, v, a, b)

        # Normals u × v point into the room (the visible side). v = down on walls keeps the
        # texture upright.
        rects = [
            rect((x0, y0, sz), (1, 0, 0), (0, 0, -1), sx, sz),  # wall y = y0, normal +y
            rect((x1, y1, sz), (-1, 0, 0), (0, 0, -1), sx, sz),  # wall y = y1, normal -y
            rect((x1, y0, sz), (0, 1, 0), (0, 0, -1), sy, sz),  # wall x = x1, normal -x
            rect((x0, y1, sz), (0, -1, 0), (0, 0, -1), sy, sz),  # wall x = x0, normal +x
            rect((x0, y0, 0), (1, 0, 0), (0, 1, 0), sx, sy),  # floor, normal +z
            rect((x0, y0, sz), (0, 1, 0), (1, 0, 0), sy, sx),  # ceiling, normal -z
        ]
        for cx, cy, wx, wy, h in FURNITURE:
            bx0, bx1, by0, by1 = cx - wx / 2, cx + wx / 2, cy - wy / 2, cy + wy / 2
            rects += [  # box faces: normals point out of the box
                rect((bx1, by0, h), (-1, 0, 0), (0, 0, -1), wx, h),  # normal -y
                rect((bx0, by1, h), (1, 0, 0), (0, 0, -1), wx, h),  # normal +y
                rect((bx1, by1, h), (0, -1, 0), (0, 0, -1), wy, h),  # normal +x
                rect((bx0, by0, h), (0, 1, 0), (0, 0, -1), wy, h),  # normal -x
                rect((bx0, by0, h), (1, 0, 0), (0, 1, 0), wx, wy),  # top, normal +z
            ]
        self.rects = rects
        self.camera = SYNTHETIC_CAMERA

    def render(self, world_from_cam: NDArray[np.float64]) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
        """BGR image (480, 640, 3) uint8 and inverse depth (480, 640) float32 (1/m)."""
        return render_view(self.rects, self.camera, world_from_cam)


@lru_cache(maxsize=4)
def _room(seed: int) -> SyntheticRoom:
    """Rooms are immutable (read-only textures): build each seed's textures once."""
    return SyntheticRoom(seed)


# ---------------------------------------------------------------------------- trajectory


def _world_from_cam(position: NDArray[np.float64], yaw: float, pitch: float, roll: float) -> NDArray[np.float64]:
    forward = np.array([math.cos(yaw) * math.cos(pitch), math.sin(yaw) * math.cos(pitch), math.sin(pitch)])
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c, s = math.cos(roll), math.sin(roll)
    x_cam, y_cam = c * right + s * down, -s * right + c * down
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x_cam, y_cam, forward])
    T[:3, 3] = position
    return T


#: Largest ``n_frames`` of :func:`synthetic_room` (its trajectory takes ~0.1 ms per frame).
MAX_FRAMES = 20_000


def room_trajectory(n_frames: int) -> NDArray[np.float64]:
    """(n_frames, 4, 4) world_from_cam poses: two laps around the room (see the module doc)."""
    poses = np.empty((n_frames, 4, 4))
    a, b = ELLIPSE_SEMI_AXES_M
    for i in range(n_frames):
        s = i / n_frames  # fraction of the whole trajectory (two laps)
        theta = 4.0 * math.pi * s
        position = np.array([a * math.cos(theta), b * math.sin(theta), MEAN_HEIGHT_M - HEIGHT_SWING_M * math.cos(2 * math.pi * s)])
        outward = math.atan2(math.sin(theta) / b, math.cos(theta) / a)  # normal of the ellipse
        yaw = outward + YAW_SWING_RAD * math.sin(2 * math.pi * s)
        pitch = PITCH_RAD + PITCH_SWING_RAD * math.sin(3 * theta)
        roll = ROLL_SWING_RAD * math.sin(5 * theta)
        poses[i] = _world_from_cam(position, yaw, pitch, roll)
    return poses


# ---------------------------------------------------------------------------- the dataset


def synthetic_room(
    n_frames: int = 300,
    seed: int = 0,
    noise: float = 0.0,
    blur: float = 0.0,
    lighting: tuple[float, float] = (1.0, 0.0),
) -> Sequence:
    """The synthetic room as a :class:`Sequence` of ``n_frames`` rendered frames (lazily).

    ``noise``: σ of additive Gaussian pixel noise in grey levels (0–255 scale); ``blur``:
    σ of a Gaussian blur in pixels; ``lighting``: (gain, offset), image → gain·image + offset.
    ``seed`` picks the textures and the noise. See the module doc for the scene and path.
    """
    if not isinstance(n_frames, (int, np.integer)) or isinstance(n_frames, bool) or n_frames < 1:
        raise InvalidInputError(f"n_frames: expected a positive integer, got {n_frames!r}")
    if n_frames > MAX_FRAMES:  # the trajectory is built frame by frame: 344 532 frames took > 30 s
        raise InvalidInputError(f"n_frames: must be at most {MAX_FRAMES}, got {n_frames}")
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
        raise InvalidInputError(f"seed: expected an integer ≥ 0, got {seed!r}")
    for name, value in (("noise", noise), ("blur", blur)):
        if not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
            raise InvalidInputError(f"{name}: expected a finite number ≥ 0, got {value!r}")
    try:
        gain, offset = (float(x) for x in lighting)
    except (TypeError, ValueError):
        raise InvalidInputError(f"lighting: expected (gain, offset), got {lighting!r}") from None
    if not (math.isfinite(gain) and gain > 0 and math.isfinite(offset)):
        raise InvalidInputError(f"lighting: expected a gain > 0 and a finite offset, got {lighting!r}")
    room = _room(int(seed))
    poses = room_trajectory(int(n_frames))
    cv2 = import_cv2("the synthetic scene")

    def load(i: int, gray: bool) -> NDArray[np.uint8]:
        image, _ = room.render(poses[i])
        if not (gain == 1.0 and offset == 0.0 and blur == 0.0 and noise == 0.0):
            out = image.astype(np.float32) * gain + offset
            if blur > 0:
                out = cv2.GaussianBlur(out, (0, 0), float(blur))
            if noise > 0:
                rng = np.random.default_rng([int(seed), i, 0x9015E])
                out = out + rng.normal(0.0, float(noise), out.shape).astype(np.float32)
            image = np.clip(np.round(out), 0, 255).astype(np.uint8)
        if gray:
            return np.asarray(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY), dtype=np.uint8)
        return image

    times = np.arange(n_frames, dtype=np.float64) / FRAME_RATE_HZ
    name = f"synthetic-room-seed{seed}"
    return Sequence(name, room.camera, times, poses, load)
