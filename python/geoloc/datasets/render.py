"""Rendering textured planar rectangles with a depth test: the synthetic room's camera.

Each :class:`TexturedRect` is the set ``X(s, t) = origin + (s / ppm)·u + (t / ppm)·v`` for
texel coordinates 0 ≤ s ≤ width_texels, 0 ≤ t ≤ height_texels (texel (i, j) of the image
covers [i, i+1) × [j, j+1), its centre at s = i + ½) (``u``, ``v`` orthonormal,
``ppm`` texels per metre), seen from the side its normal ``u × v`` points to.

For a camera with intrinsics K and pose world_from_cam T = (R, c), a texel maps to a pixel by
the homography ``H = K [Rᵀu/ppm, Rᵀv/ppm, Rᵀ(origin − c)]``: ``H (s, t, 1)ᵀ = z (x, y, 1)ᵀ``
with z the depth. Its inverse therefore gives, for every pixel (x, y), the texel
(s, t) = (h₁·p, h₂·p) / (h₃·p), p = (x, y, 1), and the **inverse depth** 1/z = h₃·p — affine
in the pixel coordinates, so the depth test costs three affine maps per rectangle. A pixel
shows the rectangle when its texel lies inside the rectangle, 1/z is within (0, 1/near]
(in front of the near plane), and 1/z beats the z-buffer. Texture sampling is bilinear
(``cv2.remap`` on the per-pixel texel coordinates, which is what
``cv2.warpPerspective`` does with H⁻¹). Pixel (x, y) is the
centre of the pixel, as in OpenCV and :class:`geoloc.Camera`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from .._opencv import import_cv2
from ..camera import Camera

__all__ = ["NEAR_PLANE_M", "TexturedRect", "render_view"]

NEAR_PLANE_M = 0.05
BACKGROUND_GRAY = 128


@dataclass(frozen=True, eq=False)
class TexturedRect:
    """A planar textured rectangle; see the module doc. ``texture`` is (H, W, 3) uint8 BGR."""

    origin: NDArray[np.float64]
    u: NDArray[np.float64]
    v: NDArray[np.float64]
    texture: NDArray[np.uint8]
    texels_per_m: float

    @property
    def normal(self) -> NDArray[np.float64]:
        """Unit normal u × v, pointing to the visible side."""
        return np.cross(self.u, self.v)

    @property
    def corners(self) -> NDArray[np.float64]:
        """(4, 3) world corners in order origin, +u, +u+v, +v."""
        h, w = self.texture.shape[:2]
        su = self.u * (w / self.texels_per_m)
        sv = self.v * (h / self.texels_per_m)
        return np.stack([self.origin, self.origin + su, self.origin + su + sv, self.origin + sv])


def _clip_near(points_cam: NDArray[np.float64], near: float) -> NDArray[np.float64]:
    """Sutherland–Hodgman clip of a polygon (K, 3) in camera coordinates to z ≥ near."""
    out = []
    k = len(points_cam)
    for i in range(k):
        a, b = points_cam[i], points_cam[(i + 1) % k]
        a_in, b_in = a[2] >= near, b[2] >= near
        if a_in:
            out.append(a)
        if a_in != b_in:
            alpha = (near - a[2]) / (b[2] - a[2])
            out.append(a + alpha * (b - a))
    return np.array(out).reshape(-1, 3)


def render_view(
    rects: list[TexturedRect], camera: Camera, world_from_cam: NDArray[np.float64], near: float = NEAR_PLANE_M
) -> tuple[NDArray[np.uint8], NDArray[np.float32]]:
    """Render the rectangles seen from ``world_from_cam``: BGR image (H, W, 3) uint8 and the
    inverse depth (H, W) float32 in 1/m (0 where nothing is seen)."""
    cv2 = import_cv2("rendering the synthetic scene")
    W, H = camera.width, camera.height
    image = np.full((H, W, 3), BACKGROUND_GRAY, dtype=np.uint8)
    inv_depth = np.zeros((H, W), dtype=np.float32)
    R = world_from_cam[:3, :3]
    c = world_from_cam[:3, 3]
    K = camera.K
    xs = np.arange(W, dtype=np.float32)
    ys = np.arange(H, dtype=np.float32)
    for rect in rects:
        if float(rect.normal @ (c - rect.origin)) <= 0.0:
            continue  # seen from behind
        corners_cam = (rect.corners - c) @ R
        poly = _clip_near(corners_cam, near)
        if len(poly) < 3:
            continue
        px = poly[:, :2] / poly[:, 2:] * [camera.fx, camera.fy] + [camera.cx, camera.cy]
        x0 = max(int(np.floor(px[:, 0].min())), 0)
        x1 = min(int(np.ceil(px[:, 0].max())) + 1, W)
        y0 = max(int(np.floor(px[:, 1].min())), 0)
        y1 = min(int(np.ceil(px[:, 1].max())) + 1, H)
        if x0 >= x1 or y0 >= y1:
            continue
        img_from_tex = K @ np.column_stack([R.T @ rect.u / rect.texels_per_m, R.T @ rect.v / rect.texels_per_m, R.T @ (rect.origin - c)])
        tex_from_img = np.linalg.inv(img_from_tex)
        # Rows of tex_from_img applied to p = (x, y, 1): affine maps over the box (float32:
        # texel coordinates stay within 1e-3 texel, the depth test within 1e-6 relative).
        m = tex_from_img.astype(np.float32)
        gx, gy = xs[None, x0:x1], ys[y0:y1, None]
        inv_z = m[2, 0] * gx + (m[2, 1] * gy + m[2, 2])
        box_inv_depth = inv_depth[y0:y1, x0:x1]
        visible = inv_z > box_inv_depth  # also "in front": the z-buffer holds values ≥ 0
        visible &= inv_z <= np.float32(1.0 / near)
        if not visible.any():
            continue
        z = 1.0 / np.maximum(inv_z, np.float32(1e-12))
        s = m[0, 0] * gx + (m[0, 1] * gy + m[0, 2])
        s *= z
        t = m[1, 0] * gx + (m[1, 1] * gy + m[1, 2])
        t *= z
        th, tw = rect.texture.shape[:2]
        visible &= s >= 0
        visible &= s <= tw
        visible &= t >= 0
        visible &= t <= th
        if not visible.any():
            continue
        # Texel centres; clipped so that hidden pixels (behind the camera: huge s, t) stay
        # cheap for remap's border handling.
        np.clip(s - 0.5, -1.0, tw, out=s)
        np.clip(t - 0.5, -1.0, th, out=t)
        sampled = cv2.remap(rect.texture, s, t, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        np.copyto(image[y0:y1, x0:x1], sampled, where=visible[:, :, None])
        np.copyto(box_inv_depth, inv_z, where=visible)
    return image, inv_depth
