"""Scoring against an independent reference trajectory instead of the dataset's labels.

A reference (e.g. a structure-from-motion reconstruction of the same images) lives in its own
world frame, scale and camera convention. Before comparing, it is expressed in the map's frame
by a **similarity** S acting on the world and one fixed **camera-frame offset** X acting on the
camera, fitted on frames whose map poses are known (the training frames):

    S · R_i · X ≈ M_i,

with R_i the reference's and M_i the map's world_from_cam pose of frame i. Precisely, for
S = (s > 0, R_S ∈ SO(3), t_S ∈ ℝ³), X = (R_X ∈ SO(3), t_X ∈ ℝ³) and R_i = (R_i, t_i):

    rotation  R_S · R_i · R_X
    position  s · R_S · (t_i + R_i · t_X) + t_S

i.e. the 4×4 product [[s R_S, t_S], [0, 1]] · R_i · X with the scale divided out of the
rotation block. X is applied first, so its translation t_X is in **reference units** (before
the scale); the residuals are in map units.

Fit: Huber on the per-frame position residual ‖p_i − m_i‖ (scale ``position_scale_m``, 2 cm)
and rotation residual Θ_i = ‖log(M_iᵀ A_i)‖ (scale ``rotation_scale_deg``, 1°), minimising

    Σ_i ρ(‖p_i − m_i‖ / δ_p) + ρ(Θ_i / δ_r),   ρ(u) = u²/2 (u ≤ 1), u − 1/2 (u > 1),

by iteratively reweighted Gauss–Newton (Levenberg–Marquardt safeguarded) on the 13 parameters
(log s, a left rotation increment of R_S, t_S, a right rotation increment of R_X, t_X), from a
closed-form start: Umeyama's similarity on the camera centres (Huber-reweighted) and the
chordal mean rotation for R_X, t_X = 0.

How well the fitted frames determine S and X: at the solution, the parameters' covariance
Σ = H⁻¹, H the Gauss–Newton Hessian of the cost with each frame's residual of the Huber scales'
size (δ_p, δ_r: what agreement means), propagated to an aligned pose A_j = S · R_j · X to first
order, σ_p,j = √tr(J_p,j Σ J_p,jᵀ), σ_r,j = √tr(J_r,j Σ J_r,jᵀ)
(:meth:`ReferenceAlignment.uncertainty`). Three frames 7 mm apart leave the aligned poses of
frames half a metre away uncertain by metres: no score against them means anything, and
``geoloc evaluate --reference`` refuses such an alignment.

Reference files (:func:`load_reference`): ``7scenes-reference`` — per line ``index`` then the
12 numbers of the top 3×4 of the camera-to-world pose, row-major (rotation blocks must be near
orthonormal, ‖RᵀR − I‖_F ≤ 1e-2, and are projected onto SO(3)) — and ``tum`` —
``t tx ty tz qx qy qz qw``. ``#`` starts a comment line; commas also separate values.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from . import lie
from ._io import as_path, read_bytes
from ._validation import as_float64, choice, real_scalar, rigid_poses as _poses
from .exceptions import DatasetError, InvalidInputError, NotARotationError

__all__ = [
    "REFERENCE_FORMATS",
    "NumberingShift",
    "ReferenceAlignment",
    "align_reference",
    "load_reference",
    "match_reference",
    "numbering_shift",
]

Array = NDArray[np.float64]
ReferenceFormat = Literal["auto", "7scenes-reference", "tum"]

#: The formats :func:`load_reference` reads ("auto" tells them apart by the values per line).
REFERENCE_FORMATS: tuple[str, ...] = ("auto", "7scenes-reference", "tum")
_VALUES = {"7scenes-reference": 13, "tum": 8}
_MIN_FRAMES = 3


# ---------------------------------------------------------------------------- reading


def _numbered_rows(path: Path) -> list[tuple[int, list[str]]]:
    """(line number, fields) of the data lines of a UTF-8 text file; DatasetError naming the
    file (and the line of a non-UTF-8 byte) when it cannot be read."""
    if not os.path.lexists(path):
        raise DatasetError(f"reference file {str(path)!r} does not exist")
    try:  # a FIFO or a folder is refused, never opened
        data = read_bytes(path, "reference file")
    except InvalidInputError as e:
        raise DatasetError(f"reference file {str(path)!r} cannot be read ({str(e).removeprefix('reference file: ')})") from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        bad_line = data.count(b"\n", 0, exc.start) + 1
        raise DatasetError(
            f"reference file {str(path)!r}, line {bad_line}: not UTF-8 text (byte 0x{data[exc.start]:02x})"
        ) from None
    rows = []
    for number, line in enumerate(text.split("\n"), start=1):
        stripped = line.strip()
        if stripped and not stripped.startswith("#"):
            rows.append((number, stripped.replace(",", " ").split()))
    return rows


def _detect_format(path: Path, rows: list[tuple[int, list[str]]]) -> str:
    number, fields = rows[0]
    for fmt, count in _VALUES.items():
        if len(fields) == count:
            return fmt
    raise DatasetError(
        f"reference file {str(path)!r}, line {number}: cannot tell the format from {len(fields)} values "
        "(7scenes-reference lines have 13: index and the 3×4 pose; tum lines have 8: t tx ty tz qx qy qz qw); "
        "name the format"
    )


#: The largest frame index a reference file may give (int64, the keys' type).
MAX_FRAME_INDEX = int(np.iinfo(np.int64).max)


def _read_7scenes_reference(path: Path, rows: list[tuple[int, list[str]]]) -> tuple[NDArray[np.int64], Array]:
    where = f"reference file {str(path)!r}"
    indices = np.empty(len(rows), dtype=np.int64)
    poses = np.tile(np.eye(4), (len(rows), 1, 1))
    first_line: dict[int, int] = {}
    for k, (number, fields) in enumerate(rows):
        if len(fields) != 13:
            raise DatasetError(
                f"{where}, line {number}: {len(fields)} values, expected 13 (index and the 12 numbers of the 3×4 pose)"
            )
        if fields[0].startswith("\ufeff"):
            raise DatasetError(f"{where}, line {number}: starts with a byte-order mark (U+FEFF); save the file as "
                               "UTF-8 without one")
        if not (fields[0].isascii() and fields[0].isdigit()):
            raise DatasetError(f"{where}, line {number}: the frame index {fields[0]!r} is not an integer ≥ 0")
        index = int(fields[0])
        if index > MAX_FRAME_INDEX:
            raise DatasetError(f"{where}, line {number}: the frame index has {len(fields[0])} digits; "
                               f"a frame index is at most {MAX_FRAME_INDEX}")
        if index in first_line:
            raise DatasetError(f"{where}, line {number}: frame {index} again (first on line {first_line[index]})")
        first_line[index] = number
        try:
            values = np.array([float(f) for f in fields[1:]])
        except ValueError:
            raise DatasetError(f"{where}, line {number}: not numbers: {' '.join(fields[1:])!r}") from None
        if not np.isfinite(values).all():
            raise DatasetError(f"{where}, line {number}: a number is not finite")
        top = values.reshape(3, 4)
        try:
            poses[k, :3, :3] = lie.so3_project_near(top[:, :3], "the 3×3 block")
        except NotARotationError as e:
            raise DatasetError(f"{where}, line {number}: {e}") from None
        indices[k] = index
        poses[k, :3, 3] = top[:, 3]
    return indices, poses


def load_reference(
    path: str | os.PathLike[str], fmt: ReferenceFormat | str = "auto"
) -> tuple[NDArray[np.int64] | Array, Array]:
    """The keys (N,) and world_from_cam poses (N, 4, 4) float64 of a reference trajectory file.

    ``fmt`` "7scenes-reference": keys are the frame indices (int64), one line per frame,
    ``index`` then the row-major top 3×4 of the camera-to-world pose; rotation blocks with
    ‖RᵀR − I‖_F ≤ 1e-2 and det > 0 are projected onto SO(3) (SVD), others refused.
    ``fmt`` "tum": keys are timestamps (float64 s), read by
    :func:`geoloc.datasets.tum.read_tum_trajectory`. ``fmt`` "auto" (default) tells them
    apart by the number of values on the first data line (13 or 8).

    Raises :class:`~geoloc.exceptions.DatasetError` (an InvalidInputError) naming the file and
    the line for a missing, empty or non-UTF-8 file, a wrong number of values, a non-number,
    a repeated frame index or a block that is not a rotation.
    """
    p = as_path(path, "path")
    fmt = choice(fmt, "fmt", REFERENCE_FORMATS)
    if fmt == "tum":
        from .datasets._files import read_tum_trajectory

        return read_tum_trajectory(p)
    rows = _numbered_rows(p)
    if not rows:
        raise DatasetError(f"reference file {str(p)!r} has no poses")
    if fmt == "auto":
        fmt = _detect_format(p, rows)
        if fmt == "tum":
            return load_reference(p, "tum")
    return _read_7scenes_reference(p, rows)


def match_reference(
    keys: ArrayLike,
    frame_indices: ArrayLike | None = None,
    timestamps: ArrayLike | None = None,
    max_time_difference: float = 0.02,
) -> NDArray[np.int64]:
    """For each frame, the row of the reference holding its pose, or -1 when it has none.

    Integer ``keys`` (a 7scenes-reference file) are matched to ``frame_indices`` exactly;
    float ``keys`` (timestamps of a TUM file) to ``timestamps`` by the nearest time at most
    ``max_time_difference`` s away (as the TUM benchmark associates)."""
    k = np.asarray(keys)
    if k.ndim != 1 or k.dtype.kind not in "iuf":
        raise InvalidInputError(f"keys: expected (N,) frame indices or timestamps, got {k.dtype} {k.shape}")
    if k.dtype.kind in "iu":
        if frame_indices is None:
            raise InvalidInputError("frame_indices: needed to match a reference keyed by frame index")
        frames = np.asarray(frame_indices).reshape(-1)
        row_of = {int(key): row for row, key in enumerate(k.tolist())}
        return np.array([row_of.get(int(f), -1) for f in frames.tolist()], dtype=np.int64)
    if timestamps is None:
        raise InvalidInputError("timestamps: needed to match a reference keyed by time")
    limit = real_scalar(max_time_difference, "max_time_difference")
    if not limit >= 0:
        raise InvalidInputError(f"max_time_difference: expected seconds ≥ 0, got {max_time_difference!r}")
    from .datasets._files import associate

    times = as_float64(timestamps, "timestamps").reshape(-1)
    if not len(k):
        return np.full(len(times), -1, dtype=np.int64)
    return associate(times, as_float64(k, "keys"), limit)


# ---------------------------------------------------------------------------- alignment


@dataclass(frozen=True, eq=False)
class ReferenceAlignment:
    """A fitted S (``scale`` s, ``rotation`` R_S, ``translation`` t_S) and X (``offset``, a
    4×4 rigid transform whose translation is in reference units): ``apply(R) = S · R · X``
    (see the module doc). ``position_residuals_m`` (map units) and
    ``rotation_residuals_deg`` are the per-frame residuals on the frames it was fitted to;
    ``position_scale_m`` / ``rotation_scale_deg`` the Huber scales of the fit."""

    scale: float
    rotation: Array
    translation: Array
    offset: Array
    position_residuals_m: Array
    rotation_residuals_deg: Array
    position_scale_m: float
    rotation_scale_deg: float
    iterations: int
    converged: bool
    #: Covariance (13×13) of the parameters (log s, R_S's left increment, t_S, R_X's right
    #: increment, t_X) with residuals of the Huber scales' size (see the module doc); ∞ on
    #: the diagonal where the fitted frames do not determine them.
    covariance: Array

    def uncertainty(self, reference_poses: ArrayLike) -> tuple[Array, Array]:
        """The alignment's own uncertainty at the aligned poses S · R_j · X of
        ``reference_poses`` (N, 4, 4): σ_p (N,) in map units (√ of the position covariance's
        trace) and σ_r (N,) in degrees (likewise), propagated from :attr:`covariance`."""
        ref = _poses(reference_poses, "reference_poses")
        jp, jr = _aligned_jacobians(self.scale, self.rotation, self.offset[:3, :3], self.offset[:3, 3], ref)
        if not np.isfinite(self.covariance).all():
            inf = np.full(len(ref), np.inf)
            return inf, inf
        var_p = np.einsum("nki,ij,nkj->n", jp, self.covariance, jp)
        var_r = np.einsum("nki,ij,nkj->n", jr, self.covariance, jr)
        return np.sqrt(np.maximum(var_p, 0.0)), np.degrees(np.sqrt(np.maximum(var_r, 0.0)))

    @property
    def similarity(self) -> Array:
        """S as a 4×4 matrix [[s R_S, t_S], [0, 1]] (acting on world points)."""
        out = np.eye(4)
        out[:3, :3] = self.scale * self.rotation
        out[:3, 3] = self.translation
        return out

    def apply(self, reference_poses: ArrayLike, offset: bool = True) -> Array:
        """The reference poses in the map's frame, S · R_j · X: rotation R_S R_j R_X, position
        s R_S (t_j + R_j t_X) + t_S. (4, 4) or (N, 4, 4) → (N, 4, 4). ``offset=False`` leaves
        X out (S · R_j), to see what the camera-frame offset accounts for."""
        ref = _poses(reference_poses, "reference_poses")
        x = self.offset if offset else np.eye(4)
        return _transform(self.scale, self.rotation, self.translation, x[:3, :3], x[:3, 3], ref)

    def statistics(self) -> dict[str, float | int]:
        """Residuals on the fitting frames: ``frames``, median / 90th percentile / max of
        position (m) and rotation (deg), ``inlier_fraction`` (both within the Huber scales)."""
        p, r = self.position_residuals_m, self.rotation_residuals_deg
        return {
            "frames": len(p),
            "median_position_m": float(np.median(p)),
            "p90_position_m": float(np.percentile(p, 90)),
            "max_position_m": float(p.max()),
            "median_rotation_deg": float(np.median(r)),
            "p90_rotation_deg": float(np.percentile(r, 90)),
            "max_rotation_deg": float(r.max()),
            "inlier_fraction": float(np.mean((p <= self.position_scale_m) & (r <= self.rotation_scale_deg))),
        }

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready: S, X, the Huber scales, the fit's iterations and :meth:`statistics`.
        ``offset_translation`` is ‖t_X‖ in the reference's units (X acts before the scale);
        ``scale`` times it is the offset in the map's units."""
        return {
            "convention": "aligned = S · R · X; rotation R_S R R_X, position s R_S (t + R t_X) + t_S",
            "scale": self.scale,
            "rotation": self.rotation.tolist(),
            "translation": self.translation.tolist(),
            "offset": self.offset.tolist(),
            "offset_rotation_deg": float(np.degrees(lie.rotation_angle(self.offset[:3, :3]))),
            "offset_translation": float(np.linalg.norm(self.offset[:3, 3])),
            "position_scale_m": self.position_scale_m,
            "rotation_scale_deg": self.rotation_scale_deg,
            "iterations": self.iterations,
            "converged": self.converged,
            "training": self.statistics(),
        }


def _transform(s: float, rs: Array, ts: Array, rx: Array, tx: Array, ref: Array) -> Array:
    out = np.tile(np.eye(4), (len(ref), 1, 1))
    out[:, :3, :3] = rs @ ref[:, :3, :3] @ rx
    out[:, :3, 3] = s * (ref[:, :3, 3] + ref[:, :3, :3] @ tx) @ rs.T + ts
    return out


def _huber(u: Array) -> Array:
    return np.where(u <= 1.0, 0.5 * u * u, u - 0.5)


def _umeyama(x: Array, y: Array, w: Array) -> tuple[float, Array, Array]:
    """The weighted least-squares similarity y ≈ s R x + t (Umeyama 1991)."""
    w = w / w.sum()
    mx, my = w @ x, w @ y
    dx, dy = x - mx, y - my
    var = float(w @ (dx * dx).sum(axis=1))
    if not var > 0:
        raise InvalidInputError("reference_poses: the camera centres coincide; a similarity is not determined")
    u, d, vt = np.linalg.svd((dy * w[:, None]).T @ dx)
    sign = np.diag([1.0, 1.0, 1.0 if np.linalg.det(u) * np.linalg.det(vt) > 0 else -1.0])
    rot = u @ sign @ vt
    s = float(np.trace(np.diag(d) @ sign)) / var
    return s, rot, my - s * rot @ mx


def _mean_rotation(rotations: Array, w: Array) -> Array:
    """The chordal L2 mean: the rotation nearest (Frobenius) to Σ w_i R_i."""
    u, _, vt = np.linalg.svd(np.einsum("n,nij->ij", w, rotations))
    mean: Array = u @ np.diag([1.0, 1.0, 1.0 if np.linalg.det(u @ vt) > 0 else -1.0]) @ vt
    return mean


@dataclass(frozen=True)
class _State:
    log_s: float
    rs: Array
    ts: Array
    rx: Array
    tx: Array

    def step(self, d: Array) -> _State:
        return _State(
            self.log_s + float(d[0]),
            lie.so3_exp(d[1:4]) @ self.rs,
            self.ts + d[4:7],
            self.rx @ lie.so3_exp(d[7:10]),
            self.tx + d[10:13],
        )


def _aligned_jacobians(s: float, rs: Array, rx: Array, tx: Array, ref: Array) -> tuple[Array, Array]:
    """∂ of the aligned poses' positions (N, 3, 13) and rotations (N, 3, 13; right
    perturbation of A_j) with respect to the 13 parameters (the state's increments)."""
    r_rot, r_pos = ref[:, :3, :3], ref[:, :3, 3]
    uq = (r_pos + np.einsum("nij,j->ni", r_rot, tx)) @ rs.T  # R_S (t_j + R_j t_X)
    jp = np.zeros((len(ref), 3, 13))
    jp[:, :, 0] = s * uq
    jp[:, :, 1:4] = -s * lie.so3_hat(uq)
    jp[:, :, 4:7] = np.eye(3)
    jp[:, :, 10:13] = s * np.einsum("ij,njk->nik", rs, r_rot)
    jr = np.zeros((len(ref), 3, 13))
    jr[:, :, 1:4] = np.einsum("ij,njk,kl->nli", rs, r_rot, rx)  # A_jᵀ (R_S's left increment)
    jr[:, :, 7:10] = np.eye(3)
    return jp, jr


@dataclass(frozen=True)
class NumberingShift:
    """How well a reference's frame numbering (or timing) matches poses it should describe
    (:func:`numbering_shift`): ``rms_deg`` {shift: RMS difference of the frame-to-frame
    rotation angles}, and ``best``, the shift with the least."""

    rms_deg: dict[int, float]
    best: int


def _rotation_steps(poses: Array) -> Array:
    """|log(R_iᵀ R_{i+1})| (radians) of consecutive poses (N − 1,)."""
    relative = np.einsum("nji,njk->nik", poses[:-1, :3, :3], poses[1:, :3, :3])
    return np.asarray(lie.rotation_angle(relative), dtype=np.float64).reshape(-1)


def numbering_shift(
    keys: ArrayLike,
    reference_poses: ArrayLike,
    poses: ArrayLike,
    frame_indices: ArrayLike,
    timestamps: ArrayLike,
    max_shift: int | None = None,
) -> NumberingShift | None:
    """Whether the reference (``keys``, ``reference_poses`` as :func:`load_reference` returns
    them) describes the frames ``poses`` (N, 4, 4; with their ``frame_indices`` and
    ``timestamps``) under their own numbers or under shifted ones.

    The angle of the rotation from one frame of ``poses`` to the next (whatever the gap in
    frame numbers between them), θ_i = |log(R_iᵀ R_{i+1})|, does not depend on the world
    frame, the scale or a fixed camera offset (θ of S·R·X is θ of R), so the two trajectories'
    θ sequences agree at the right numbering whatever the alignment. Shifted by k frames, the
    reference is compared at frames i + k (a time-keyed one at t_i + k·Δt, Δt the median frame
    interval), for |k| ≤ ``max_shift`` (default: N, at least 30 and at most 200 — wider searches
    on short trajectories find chance matches), over the pairs both have: at least 10 and half
    as many as under the own numbering, else that shift is skipped. None when fewer than 10
    pairs are compared under the own numbering."""
    if max_shift is not None and (isinstance(max_shift, bool) or not isinstance(max_shift, int) or max_shift < 0):
        raise InvalidInputError(f"max_shift: expected an integer ≥ 0, got {max_shift!r}")
    ref = _poses(reference_poses, "reference_poses")
    own = _poses(poses, "poses")
    indices = np.asarray(frame_indices).reshape(-1)
    times = as_float64(timestamps, "timestamps").reshape(-1)
    if not (len(indices) == len(times) == len(own)):
        raise InvalidInputError(
            f"poses, frame_indices, timestamps: expected one per frame, got {len(own)}, {len(indices)}, {len(times)}"
        )
    if len(own) < 2:
        return None
    step = float(np.median(np.diff(times)))
    if not step > 0:
        return None
    keyed_by_time = np.asarray(keys).dtype.kind == "f"
    steps = _rotation_steps(own)
    if max_shift is None:
        max_shift = min(200, max(30, len(own)))
    rms: dict[int, float] = {}
    needed = 10
    for k in sorted(range(-max_shift, max_shift + 1), key=abs):  # 0 first: it sets how many pairs count
        rows = match_reference(keys, indices + k, times + k * step) if keyed_by_time else match_reference(keys, indices + k)
        paired = (rows[:-1] >= 0) & (rows[1:] >= 0)
        if paired.sum() < needed:
            if k == 0:
                return None
            continue
        if k == 0:
            needed = max(10, int(paired.sum()) // 2)
        theirs = _rotation_steps(ref[np.where(rows >= 0, rows, 0)])
        rms[k] = float(np.degrees(np.sqrt(np.mean((theirs - steps)[paired] ** 2))))
    return NumberingShift(rms, min(rms, key=lambda k: (rms[k], abs(k))))


def align_reference(
    reference_poses: ArrayLike,
    map_poses: ArrayLike,
    *,
    position_scale_m: float = 0.02,
    rotation_scale_deg: float = 1.0,
    max_iterations: int = 100,
) -> ReferenceAlignment:
    """Fit S and X with S · R_i · X ≈ M_i (see the module doc for the equation and the
    robust cost) for ``reference_poses`` R_i and ``map_poses`` M_i, each (N, 4, 4)
    world_from_cam of the same N ≥ 3 frames. ``position_scale_m`` and
    ``rotation_scale_deg`` are the Huber scales (residuals beyond them count linearly)."""
    ref = _poses(reference_poses, "reference_poses")
    target = _poses(map_poses, "map_poses")
    if len(ref) != len(target):
        raise InvalidInputError(f"reference_poses, map_poses: expected the same number of poses, got {len(ref)} and {len(target)}")
    if len(ref) < _MIN_FRAMES:
        raise InvalidInputError(f"reference_poses: expected at least {_MIN_FRAMES} frames to fit a similarity, got {len(ref)}")
    dp = real_scalar(position_scale_m, "position_scale_m")
    dr_deg = real_scalar(rotation_scale_deg, "rotation_scale_deg")
    for name, v in (("position_scale_m", dp), ("rotation_scale_deg", dr_deg)):
        if not (v > 0 and math.isfinite(v)):
            raise InvalidInputError(f"{name}: expected a positive number, got {v!r}")
    dr = math.radians(dr_deg)
    if isinstance(max_iterations, bool) or not isinstance(max_iterations, int) or max_iterations < 1:
        raise InvalidInputError(f"max_iterations: expected an integer ≥ 1, got {max_iterations!r}")

    r_rot, r_pos = ref[:, :3, :3], ref[:, :3, 3]
    m_rot, m_pos = target[:, :3, :3], target[:, :3, 3]

    def residuals(st: _State) -> tuple[Array, Array]:
        aligned = _transform(math.exp(st.log_s), st.rs, st.ts, st.rx, st.tx, ref)
        rot_res = np.asarray(lie.so3_log(np.einsum("nji,njk->nik", m_rot, aligned[:, :3, :3]))).reshape(-1, 3)
        return aligned[:, :3, 3] - m_pos, rot_res

    def cost(st: _State) -> float:
        rp, rr = residuals(st)
        return float(_huber(np.linalg.norm(rp, axis=1) / dp).sum() + _huber(np.linalg.norm(rr, axis=1) / dr).sum())

    # Closed-form start: Huber-reweighted Umeyama on the centres, then the mean offset rotation.
    w = np.ones(len(ref))
    for _ in range(5):
        s0, rs0, ts0 = _umeyama(r_pos, m_pos, w)
        u = np.linalg.norm(s0 * r_pos @ rs0.T + ts0 - m_pos, axis=1) / dp
        w = np.where(u <= 1.0, 1.0, 1.0 / np.maximum(u, 1.0))
    offsets = np.einsum("ji,njk,nkl->nil", rs0, r_rot, m_rot)  # (R_S R_i)ᵀ M_i
    w = np.ones(len(ref))
    for _ in range(5):
        rx0 = _mean_rotation(offsets, w)
        u = np.asarray(lie.rotation_angle(np.einsum("ji,njk->nik", rx0, offsets))).reshape(-1) / dr
        w = np.where(u <= 1.0, 1.0, 1.0 / np.maximum(u, 1.0))
    state = _State(math.log(s0), rs0, ts0, rx0, np.zeros(3))

    current = cost(state)
    damping = 1e-6
    converged = False
    iterations = 0
    for iterations in range(1, max_iterations + 1):
        rp, rr = residuals(state)
        jp, ja = _aligned_jacobians(math.exp(state.log_s), state.rs, state.rx, state.tx, ref)
        jr = np.einsum("nij,njk->nik", np.asarray(lie.so3_right_jacobian_inv(rr)).reshape(-1, 3, 3), ja)
        up = np.linalg.norm(rp, axis=1) / dp
        ur = np.linalg.norm(rr, axis=1) / dr
        wp = np.where(up <= 1.0, 1.0, 1.0 / np.maximum(up, 1.0)) / dp**2
        wr = np.where(ur <= 1.0, 1.0, 1.0 / np.maximum(ur, 1.0)) / dr**2
        hess = np.einsum("n,nki,nkj->ij", wp, jp, jp) + np.einsum("n,nki,nkj->ij", wr, jr, jr)
        grad = np.einsum("n,nki,nk->i", wp, jp, rp) + np.einsum("n,nki,nk->i", wr, jr, rr)
        accepted = False
        for _ in range(30):
            lhs = hess + damping * np.diag(np.diag(hess) + 1e-12)
            delta = -np.linalg.solve(lhs, grad)
            trial = state.step(delta)
            trial_cost = cost(trial)
            if trial_cost <= current:
                accepted = True
                break
            damping *= 10.0
        if not accepted:
            converged = True  # no step lowers the cost: a minimum to working precision
            break
        decrease = current - trial_cost
        state, current = trial, trial_cost
        if decrease <= 1e-15 * current:
            # the step, however damped, lowers the cost by rounding only: a minimum to
            # working precision (else equal-cost damped steps would be accepted forever)
            converged = True
            break
        damping = max(damping / 10.0, 1e-12)
        if damping < 1e-3 and float(np.abs(delta).max()) < 1e-10:
            converged = True
            break

    rp, rr = residuals(state)
    x = np.eye(4)
    x[:3, :3], x[:3, 3] = state.rx, state.tx
    # Σ = H⁻¹ with every frame's residual of the Huber scales' size (full weights 1/δ²)
    jp, jr = _aligned_jacobians(math.exp(state.log_s), state.rs, state.rx, state.tx, ref)
    jr = np.einsum("nij,njk->nik", np.asarray(lie.so3_right_jacobian_inv(rr)).reshape(-1, 3, 3), jr)
    information = np.einsum("nki,nkj->ij", jp, jp) / dp**2 + np.einsum("nki,nkj->ij", jr, jr) / dr**2
    e = np.linalg.eigvalsh(information)
    determined = e[0] > 1e-12 * e[-1] and e[-1] > 0
    covariance = np.linalg.inv(information) if determined else np.full((13, 13), np.inf)
    return ReferenceAlignment(
        scale=math.exp(state.log_s),
        rotation=state.rs,
        translation=state.ts,
        offset=x,
        position_residuals_m=np.linalg.norm(rp, axis=1),
        rotation_residuals_deg=np.degrees(np.linalg.norm(rr, axis=1)),
        position_scale_m=dp,
        rotation_scale_deg=dr_deg,
        iterations=iterations,
        converged=converged,
        covariance=covariance,
    )
