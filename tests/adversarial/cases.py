"""Hypothesis strategies of adversarial cases, one per public module (see ``worker.py`` for
the case format). Each public callable is described once by a :class:`Spec` — a valid call
plus the kind of each argument — and a case mutates zero to two arguments with values drawn
from the adversarial pool of that kind: wrong shapes (0, 1, wrong rank, huge), dtypes (int,
bool, object, float32, complex, strings), non-contiguous / Fortran / read-only layouts,
NaN/±inf, extreme magnitudes (1e±300, 1e20, denormals), degenerate values, and out-of-range
options (negative, zero, 2**70, numpy integers, bool, None, wrong strings)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from hypothesis import strategies as st

CAMERA_PY = (525.0, 525.0, 320.0, 240.0)


def call(target: Any, *args: Any, **kwargs: Any) -> tuple[Any, ...]:
    return ("call", target, tuple(args), kwargs)


def attr(expr: Any, name: str) -> tuple[Any, ...]:
    return ("attr", expr, name)


CAM = call("geoloc.Camera", *CAMERA_PY)
SPECIALS = [np.nan, np.inf, -np.inf, 1e300, -1e300, 1e20, 5e-324, 1e-310, 0.0, -0.0, 3e38, 1e200]

# ------------------------------------------------------------------------- pools of values


def floats_pool() -> st.SearchStrategy[Any]:
    return st.one_of(
        st.sampled_from([0.0, -1.0, -1e-12, np.nan, np.inf, -np.inf, 1e300, -1e300, 5e-324, 1e20,
                         2**70, np.int64(3), np.float32(2.5), True, False, None, "1.0", 1 + 2j, [1.0]]),
        st.floats(allow_nan=True, allow_infinity=True),
    )


def ints_pool() -> st.SearchStrategy[Any]:
    return st.one_of(
        st.sampled_from([0, -1, 1, 2, 2**31, 2**62, 2**63, 2**64, 2**70, -(2**70), 10**9, np.int64(5),
                         np.uint16(3), np.int8(-1), True, False, None, 3.5, "3", np.nan, np.float64(4.0)]),
        st.integers(min_value=-(2**80), max_value=2**80),
    )


def bools_pool() -> st.SearchStrategy[Any]:
    return st.sampled_from([True, False, None, 0, 1, 2, "yes", np.bool_(True), np.int64(1), 0.5])


def strings_pool(choices: list[str]) -> st.SearchStrategy[Any]:
    wrong = ["", "x", "HUBER", " huber", None, 1, b"huber", True, "\x00", "é" * 3]
    return st.sampled_from(choices + wrong)


@st.composite
def array_pool(draw: st.DrawFn, base: np.ndarray, huge: int) -> Any:
    with np.errstate(all="ignore"):
        return _array_variant(draw, np.array(base), huge)


def _array_variant(draw: st.DrawFn, b: np.ndarray, huge: int) -> Any:
    how = draw(st.sampled_from(
        ["special", "scale", "empty", "one", "rank+", "rank-", "lastdim", "huge", "dtype", "layout",
         "python", "scalar", "duplicate"]))
    if how == "special" and b.size and b.dtype.kind == "f":
        out = b.astype(float).copy()
        idx = draw(st.lists(st.integers(0, out.size - 1), min_size=1, max_size=3))
        out.flat[idx] = draw(st.sampled_from(SPECIALS))
        return out
    if how == "scale" and b.dtype.kind in "fiu":
        return b.astype(float) * draw(st.sampled_from([1e300, 1e20, 1e-300, 1e-320, 0.0, -1.0, 1e8]))
    if how == "empty":
        return b[:0] if b.ndim else np.zeros((0,))
    if how == "one":
        return b[:1] if b.ndim else b.reshape(1)
    if how == "rank+":
        return b[None]
    if how == "rank-":
        return b.reshape(-1) if b.ndim > 1 else b.reshape(-1)[:1].reshape(()) if b.size else b
    if how == "lastdim" and b.ndim:
        k = draw(st.sampled_from([0, 1, -1]))
        return b[..., :-1] if k == -1 or b.shape[-1] < 2 else np.concatenate([b, b[..., :1]], axis=-1)
    if how == "huge" and b.ndim and len(b):
        n = draw(st.sampled_from([huge, huge // 10 + 1]))
        return np.resize(b, (n,) + b.shape[1:])
    if how == "dtype":
        kind = draw(st.sampled_from(["int64", "bool", "object", "float32", "complex", "str", "float16",
                                     "uint8", "int32"]))
        if kind == "str":
            return b.astype(str)
        if kind == "complex":
            return b.astype(complex) + 1j
        with np.errstate(all="ignore"):
            return b.astype(kind)
    if how == "layout":
        kind = draw(st.sampled_from(["noncontig", "fortran", "readonly", "negstride"]))
        if kind == "noncontig":
            return np.stack([b, b], axis=-1)[..., 0]
        if kind == "fortran":
            return np.asfortranarray(b)
        if kind == "readonly":
            c = b.copy()
            c.setflags(write=False)
            return c
        return b[::-1] if b.ndim else b
    if how == "python":
        return b.tolist()
    if how == "scalar":
        return draw(st.sampled_from([None, 0.0, "abc", 7, np.float64(1.0), [[]], object]))
    if how == "duplicate" and b.ndim and len(b):
        return np.repeat(b[:1], len(b), axis=0)
    return b


# ------------------------------------------------------------------------- specs


@dataclass
class Spec:
    """One public callable: ``target`` (a dotted path or an expression), its valid arguments
    ``args`` (name → (kind, value)), which of them are positional, the result's invariant and,
    per argument, the names an error about it may use (aliases)."""

    module: str
    target: Any
    args: dict[str, tuple[str, Any]]
    positional: tuple[str, ...] = ()
    check: str = "any"
    aliases: dict[str, list[str]] = field(default_factory=dict)
    huge: int = 20000
    timeout: float | None = None
    extra: dict[str, Any] = field(default_factory=dict)
    frozen: tuple[str, ...] = ()

    def __repr__(self) -> str:
        target = self.target if isinstance(self.target, str) else "<expression>"
        return f"Spec({target}, {list(self.args)})"

    def _repr_pretty_(self, p: Any, cycle: bool) -> None:  # hypothesis' pretty printer
        p.text(repr(self))


def _value(draw: st.DrawFn, kind: str, value: Any, huge: int) -> Any:
    if kind == "array":
        return draw(array_pool(value, huge))
    if kind == "float":
        return draw(floats_pool())
    if kind == "int":
        return draw(ints_pool())
    if kind == "bool":
        return draw(bools_pool())
    if kind.startswith("str:"):
        return draw(strings_pool(kind[4:].split("|")))
    if kind == "camera":
        bad = draw(st.sampled_from([None, "cam", 1.0, CAMERA_PY]))
        fx = draw(floats_pool())
        return draw(st.sampled_from([bad, call("geoloc.Camera", fx, 525.0, 320.0, 240.0)]))
    if kind == "any":
        return draw(st.one_of(floats_pool(), ints_pool(), st.just(np.zeros((2, 2)))))
    return value


@st.composite
def cases(draw: st.DrawFn, spec: Spec) -> dict[str, Any]:
    mutable = [n for n in spec.args if n not in spec.frozen]
    chosen = draw(st.lists(st.sampled_from(mutable), max_size=2, unique=True)) if mutable else []
    values = {}
    for name, (kind, value) in spec.args.items():
        values[name] = _value(draw, kind, value, spec.huge) if name in chosen else value
    args = [values[n] for n in spec.positional]
    kwargs = {n: v for n, v in values.items() if n not in spec.positional}
    target = spec.target
    names = sorted({a for n in chosen for a in [n, *spec.aliases.get(n, [])]} | set(spec.extra.get("names", [])))
    case: dict[str, Any] = {
        "module": spec.module,
        "expr": call(target, *args, **kwargs),
        "check": spec.check if not chosen else spec.extra.get("mutated_check", spec.check),
        "names": names or ["<no argument was mutated: a valid call must not be refused>"],
        "timeout": spec.timeout,
    }
    case.update({k: v for k, v in spec.extra.items() if k not in ("mutated_check", "names") and not chosen})
    return case


def _rng() -> np.random.Generator:
    return np.random.default_rng(12345)


def _rotations(n: int) -> np.ndarray:
    rng = _rng()
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], 1)


def _poses(n: int, step: float = 0.05) -> np.ndarray:
    t = np.repeat(np.eye(4)[None], n, axis=0)
    t[:, :3, :3] = _rotations(n) if n > 1 else np.eye(3)
    t[:, :3, 3] = _rng().normal(size=(n, 3))
    return t


def _track(n: int) -> np.ndarray:
    t = np.repeat(np.eye(4)[None], n, axis=0)
    t[:, 0, 3] = 0.05 * np.arange(n)
    return t


def _scene(n: int = 60, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    pts = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), rng.uniform(3, 6, n)])
    fx, fy, cx, cy = CAMERA_PY
    px = np.column_stack([fx * pts[:, 0] / pts[:, 2] + cx, fy * pts[:, 1] / pts[:, 2] + cy])
    return pts, px


# --- lie
R3 = _rotations(3)
T3 = _poses(3)
PHI = np.random.default_rng(1).normal(size=(3, 3))
XI = np.random.default_rng(2).normal(size=(3, 6))


def lie_specs() -> list[Spec]:
    a = lambda v: ("array", v)  # noqa: E731
    m = "lie"
    s = [
        Spec(m, "geoloc.lie.so3_exp", {"phi": a(PHI)}, ("phi",), "rot"),
        Spec(m, "geoloc.lie.so3_log", {"R": a(R3)}, ("R",), "finite"),
        Spec(m, "geoloc.lie.so3_hat", {"phi": a(PHI)}, ("phi",), "finite"),
        Spec(m, "geoloc.lie.so3_vee", {"M": a(np.array([np.cross(np.eye(3), v) for v in PHI]))}, ("M",), "finite"),
        Spec(m, "geoloc.lie.so3_project", {"R": a(R3 + 0.01)}, ("R",), "rot"),
        Spec(m, "geoloc.lie.so3_to_quaternion_wxyz", {"R": a(R3)}, ("R",), "quat"),
        Spec(m, "geoloc.lie.so3_from_quaternion_wxyz", {"q": a(np.array([[1.0, 0, 0, 0], [0.5, 0.5, 0.5, 0.5]]))}, ("q",), "rot"),
        Spec(m, "geoloc.lie.rotation_angle", {"R": a(R3)}, ("R",), "angle"),
        Spec(m, "geoloc.lie.se3_exp", {"xi": a(XI)}, ("xi",), "pose"),
        Spec(m, "geoloc.lie.se3_log", {"T": a(T3)}, ("T",), "finite"),
        Spec(m, "geoloc.lie.se3_hat", {"xi": a(XI)}, ("xi",), "finite"),
        Spec(m, "geoloc.lie.se3_curly_hat", {"xi": a(XI)}, ("xi",), "finite"),
        Spec(m, "geoloc.lie.se3_vee", {"M": a(np.zeros((3, 4, 4)))}, ("M",), "finite"),
        Spec(m, "geoloc.lie.se3_adjoint", {"T": a(T3)}, ("T",), "finite"),
        Spec(m, "geoloc.lie.se3_inverse", {"T": a(T3)}, ("T",), "pose"),
        Spec(m, "geoloc.lie.se3_project", {"T": a(T3)}, ("T",), "pose"),
        Spec(m, "geoloc.lie.se3_compose", {"T1": a(T3), "T2": a(T3[::-1].copy())}, ("T1", "T2"), "pose"),
        Spec(m, "geoloc.lie.se3_distance", {"T1": a(T3), "T2": a(T3[::-1].copy())}, ("T1", "T2"), "finite"),
        Spec(m, "geoloc.lie.se3_interpolate", {"T1": a(T3), "T2": a(T3[::-1].copy()), "alpha": ("float", 0.3)},
             ("T1", "T2", "alpha"), "pose"),
        Spec(m, "geoloc.lie.se3_transform_points", {"T": a(T3[0]), "points": a(PHI)}, ("T", "points"), "finite"),
    ]
    for side in ("left", "right"):
        for inv in ("", "_inv"):
            s.append(Spec(m, f"geoloc.lie.so3_{side}_jacobian{inv}", {"phi": a(PHI)}, ("phi",), "finite"))
            s.append(Spec(m, f"geoloc.lie.se3_{side}_jacobian{inv}", {"xi": a(XI)}, ("xi",), "finite"))
    return s


# --- geometry
PTS, PX = _scene()
TRI_POSES = _track(3) * 1.0
TRI_POSES[:, 0, 3] = [0.0, 0.3, 0.6]


def _tri_obs() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    pts, _ = _scene(20, 3)
    cam_ids, track_ids, pix = [], [], []
    fx, fy, cx, cy = CAMERA_PY
    for c, T in enumerate(TRI_POSES):
        p = pts - T[:3, 3]
        pix.append(np.column_stack([fx * p[:, 0] / p[:, 2] + cx, fy * p[:, 1] / p[:, 2] + cy]))
        cam_ids += [c] * len(pts)
        track_ids += list(range(len(pts)))
    return np.array(cam_ids), np.array(track_ids), np.vstack(pix)


CAM_IDS, TRACK_IDS, TRI_PX = _tri_obs()


def geometry_specs() -> list[Spec]:
    a = lambda v: ("array", v)  # noqa: E731
    m = "geometry"
    pnp_args = {
        "points3d": a(PTS), "pixels": a(PX), "cam": ("camera", CAM), "init_pose": a(np.eye(4)),
        "ransac": ("bool", True), "huber": ("float", 1.0), "max_residual": ("float", 5.0),
        "loss": ("str:huber|cauchy|none", "huber"), "pixel_sigma": ("float", 1.0),
        "covariance": ("str:propagated|paper", "propagated"),
        "point_covariances": a(np.repeat(1e-4 * np.eye(3)[None], len(PTS), axis=0)),
        "min_iterations": ("int", 10), "max_iterations": ("int", 200), "confidence": ("float", 0.99),
        "seed": ("int", 0),
    }
    return [
        Spec(m, "geoloc.geometry.solve_pnp", pnp_args, ("points3d", "pixels", "cam"), "pnp",
             aliases={"cam": ["fx", "camera", "cam"], "points3d": ["pixels", "point_covariances"],
                      "pixels": ["points3d", "point_covariances"], "point_covariances": ["points3d"]}, huge=3000),
        Spec(m, "geoloc.geometry.triangulate",
             {"poses": a(TRI_POSES), "cam": ("camera", CAM), "cam_ids": a(CAM_IDS), "track_ids": a(TRACK_IDS),
              "pixels": a(TRI_PX), "huber": ("float", 1.0), "loss": ("str:huber|cauchy|none", "huber"),
              "max_residual": ("float", 5.0), "pixel_sigma": ("float", 1.0), "min_angle": ("float", 0.01),
              "pose_covariances": a(np.repeat(1e-6 * np.eye(6)[None], 3, axis=0))},
             ("poses", "cam", "cam_ids", "track_ids", "pixels"), "tri",
             aliases={"cam": ["fx", "camera"], "cam_ids": ["pixels", "track_ids"], "track_ids": ["pixels", "cam_ids"],
                      "pixels": ["cam_ids", "track_ids"], "poses": ["cam_ids", "pose_covariances"],
                      "pose_covariances": ["poses"]}, huge=5000),
        Spec(m, "geoloc.geometry.keyframe_score",
             {"T1": a(T3), "T2": a(T3[::-1].copy()), "d_m": ("float", 0.1), "ell": ("float", 0.2),
              "alpha_m": ("float", 0.05)}, ("T1", "T2"), "score", aliases={"T1": ["T2"], "T2": ["T1"]}),
        Spec(m, "geoloc.geometry.select_keyframes",
             {"poses": a(_track(30)), "k": ("int", 10), "n": ("int", 5), "window": ("int", 10), "d_m": ("float", 0.1),
              "ell": ("float", 0.2), "alpha_m": ("float", 0.05), "min_score": ("float", 1e-3)},
             ("poses", "k"), "indices", aliases={"poses": ["k"]}),
    ]


# --- matching / retrieval
DESC_U8 = np.random.default_rng(4).integers(0, 256, size=(50, 32), dtype=np.uint8)
DESC_F32 = np.random.default_rng(5).normal(size=(60, 16)).astype(np.float32)


def matching_specs() -> list[Spec]:
    a = lambda v: ("array", v)  # noqa: E731
    m = "matching"
    pairs = np.column_stack([np.arange(20), np.arange(20)])
    return [
        Spec(m, "geoloc.matching.match_descriptors",
             {"descriptors_a": a(DESC_U8), "descriptors_b": a(DESC_U8[::-1].copy()), "ratio": ("float", 0.8),
              "mutual": ("bool", True), "max_distance": ("float", None)},
             ("descriptors_a", "descriptors_b"), "match",
             aliases={"descriptors_a": ["descriptors_b"], "descriptors_b": ["descriptors_a"]}),
        Spec(m, "geoloc.matching.match_descriptors",
             {"descriptors_a": a(DESC_F32), "descriptors_b": a(DESC_F32[:40].copy()), "ratio": ("float", None),
              "mutual": ("bool", False), "max_distance": ("float", 10.0)},
             ("descriptors_a", "descriptors_b"), "match",
             aliases={"descriptors_a": ["descriptors_b"], "descriptors_b": ["descriptors_a"]}),
        Spec(m, "geoloc.matching.epipolar_filter",
             {"cam": ("camera", CAM), "pose_a": a(TRI_POSES[0]), "pose_b": a(TRI_POSES[1]),
              "keypoints_a": a(TRI_PX[:20]), "keypoints_b": a(TRI_PX[20:40]), "pairs": a(pairs), "max_px": ("float", 2.0)},
             ("cam", "pose_a", "pose_b", "keypoints_a", "keypoints_b", "pairs"), "mask",
             aliases={"cam": ["fx", "camera"], "keypoints_a": ["pairs"], "keypoints_b": ["pairs"],
                      "pose_a": ["pose_b"], "pose_b": ["pose_a"]}),
    ]


@st.composite
def scaled_index_case(draw: st.DrawFn) -> dict[str, Any]:
    """Exact 1-NN for every finite float32 input (values near 1e20, 1e-25, …)."""
    scale = draw(st.sampled_from([1e20, 1e19, 1e-25, 1e-40, 3e38, 1.0]))
    backend = draw(st.sampled_from([None, "flat", "kdtree"]))
    seed = draw(st.integers(0, 2**16))
    dim = draw(st.sampled_from([3, 8, 64]))
    x = np.clip(np.random.default_rng(seed).normal(size=(60, dim)) * scale, -3e38, 3e38).astype(np.float32)
    if not np.all(np.isfinite(x)):
        x = np.clip(x, -3e38, 3e38).astype(np.float32)
    q = x[[7, 42]]
    idx = call("geoloc.retrieval.DescriptorIndex", x, backend=backend)
    return {"module": "retrieval", "expr": call(attr(idx, "query"), q, k=3), "check": "knn",
            "names": ["descriptors", "queries", "backend"], "n_database": 60, "exact": [7, 42]}


@st.composite
def self_match_case(draw: st.DrawFn) -> dict[str, Any]:
    scale = draw(st.sampled_from([1e20, 1e-25, 3e38, 1.0]))
    x = np.clip(np.random.default_rng(draw(st.integers(0, 999))).normal(size=(50, 16)) * scale, -3e38, 3e38)
    x = x.astype(np.float32)
    return {"module": "matching", "expr": call("geoloc.matching.match_descriptors", x, x.copy()), "check": "match",
            "names": ["descriptors_a", "descriptors_b"], "min_matches": 50}


def retrieval_specs() -> list[Spec]:
    a = lambda v: ("array", v)  # noqa: E731
    m = "retrieval"
    idx = call("geoloc.retrieval.DescriptorIndex", DESC_F32)
    voc = call("geoloc.retrieval.Vocabulary.train", np.vstack([DESC_U8] * 2), 3, 2)
    db = call("geoloc.retrieval.BowDatabase", voc, [DESC_U8[:20], DESC_U8[20:40], DESC_U8[30:]])
    return [
        Spec(m, "geoloc.retrieval.DescriptorIndex", {"descriptors": a(DESC_F32), "backend": ("str:kdtree|flat", None)},
             ("descriptors",), "any"),
        Spec(m, attr(idx, "query"), {"queries": a(DESC_F32[:5]), "k": ("int", 3)}, ("queries",), "knn",
             extra={"n_database": 60}),
        Spec(m, "geoloc.retrieval.Vocabulary.train",
             {"descriptors": a(DESC_U8), "branching": ("int", 3), "depth": ("int", 2), "seed": ("int", 0)},
             ("descriptors",), "any", huge=3000,
             # "descriptors: 50 descriptors cannot make 97 clusters" states the conflict
             aliases={"branching": ["descriptors"], "depth": ["descriptors"]}),
        Spec(m, attr(voc, "words"), {"descriptors": a(DESC_U8[:10])}, ("descriptors",), "indices"),
        Spec(m, "geoloc.retrieval.BowDatabase", {"vocabulary": ("any", voc), "images": ("array", np.stack([DESC_U8[:10]] * 3))},
             ("vocabulary", "images"), "any"),
        Spec(m, attr(db, "query"), {"descriptors": a(DESC_U8[:15]), "k": ("int", 2)}, ("descriptors",), "bow"),
    ]


# --- motion / fusion
COV6 = np.diag([1e-4] * 3 + [1e-5] * 3)


def temporal_specs() -> list[Spec]:
    a = lambda v: ("array", v)  # noqa: E731
    pm = np.eye(4)
    pg = np.eye(4)
    pg[0, 3] = 0.005
    return [
        Spec("motion", "geoloc.motion_predict",
             {"poses": a(_track(4)), "timestamps": a(np.array([0.0, 0.1, 0.2, 0.3])), "t_query": ("float", 0.4),
              "covariances": a(np.repeat(COV6[None], 4, axis=0)), "acceleration_psd": a(np.full(6, 0.1)),
              "velocity_mean": a(np.array([0.1, 0.0, -0.1, 0.0, 0.2, 0.0])), "velocity_variance": a(np.full(6, 0.05))},
             ("poses", "timestamps", "t_query"), "motion",
             aliases={"poses": ["timestamps", "covariances"], "timestamps": ["poses", "t_query"],
                      "t_query": ["timestamps"], "covariances": ["poses"]}),
        Spec("fusion", "geoloc.fuse",
             {"pose_m": a(pm), "cov_m": a(COV6), "pose_g": a(pg), "cov_g": a(COV6 * 2), "gate_sigma": ("float", 3.0),
              "gate": ("str:isometric|chi2", "isometric")},
             ("pose_m", "cov_m", "pose_g", "cov_g"), "fusion"),
    ]


# --- camera / features / descriptor
IMG = (np.random.default_rng(6).uniform(0, 255, size=(120, 160, 3))).astype(np.uint8)


def camera_specs() -> list[Spec]:
    a = lambda v: ("array", v)  # noqa: E731
    return [
        Spec("camera", "geoloc.Camera",
             {"fx": ("float", 525.0), "fy": ("float", 525.0), "cx": ("float", 320.0), "cy": ("float", 240.0),
              "width": ("int", 640), "height": ("int", 480), "dist": a(np.array([0.1, -0.05, 0.0, 0.0]))},
             ("fx", "fy", "cx", "cy"), "any"),
        Spec("camera", attr(call("geoloc.Camera", *CAMERA_PY, dist=(0.1, -0.05, 0.001, 0.0)), "undistort_points"),
             {"pixels": a(PX)}, ("pixels",), "finite"),
    ]


def features_specs() -> list[Spec]:
    a = lambda v: ("array", v)  # noqa: E731
    ex = call("geoloc.features.FeatureExtractor", "orb", 200)
    return [
        Spec("features", "geoloc.features.FeatureExtractor",
             {"kind": ("str:orb|sift", "orb"), "n_features": ("int", 200), "root_sift": ("bool", False)}, (), "any"),
        Spec("features", ex, {"image": a(IMG), "camera": ("camera", call("geoloc.Camera", *CAMERA_PY, width=160, height=120))},
             ("image", "camera"), "any", huge=400, aliases={"image": ["images"], "camera": ["fx", "camera"]}),
        Spec("features", "geoloc.features.decode_sift_octave", {"packed": a(np.array([0, 256, 65791, 16777215]))},
             ("packed",), "any"),
    ]


def descriptor_specs(with_onnx: bool) -> list[Spec]:
    a = lambda v: ("array", v)  # noqa: E731
    imgs = np.stack([IMG, IMG[::-1].copy()])
    s = [
        Spec("descriptor", "geoloc.descriptor.to_gray", {"images": a(imgs), "size": ("any", (64, 48))}, ("images",), "any", huge=50),
        Spec("descriptor", "geoloc.descriptor.normalize", {"gray": a(imgs[:, :, :, 0])}, ("gray",), "finite", huge=50),
        Spec("descriptor", "geoloc.descriptor.preprocess", {"images": a(imgs)}, ("images",), "finite", huge=50),
        Spec("descriptor", "geoloc.descriptor.tiny_image_descriptors", {"images": a(imgs), "size": ("any", (32, 24))},
             ("images",), "descriptors", huge=50),
    ]
    if with_onnx:
        d = ("cached", "onnx_descriptor")
        s += [
            Spec("descriptor", d, {"images": a(imgs)}, ("images",), "descriptors", huge=40, timeout=30),
            Spec("descriptor", "geoloc.OnnxDescriptor",
                 {"path": ("any", ("cached", "onnx_model")), "threads": ("int", 1), "batch_size": ("int", 4)},
                 ("path",), "any", timeout=30),
        ]
    return s


# --- evaluation / plots
EST = _track(5)
GT = _track(5) + 0.0
GT[:, 1, 3] += 0.01
COVS = np.repeat(COV6[None], 5, axis=0)


def evaluation_specs() -> list[Spec]:
    a = lambda v: ("array", v)  # noqa: E731
    m = "evaluation"
    al = {"est": ["gt", "cov"], "gt": ["est"], "cov": ["est"]}
    return [
        Spec(m, "geoloc.evaluation.pose_errors", {"est": a(EST), "gt": a(GT)}, ("est", "gt"), "sigmas", aliases=al),
        Spec(m, "geoloc.evaluation.tangent_errors", {"est": a(EST), "gt": a(GT)}, ("est", "gt"), "finite", aliases=al),
        Spec(m, "geoloc.evaluation.nees", {"est": a(EST), "cov": a(COVS), "gt": a(GT)}, ("est", "cov", "gt"), "finite", aliases=al),
        Spec(m, "geoloc.evaluation.axis_coverage", {"est": a(EST), "cov": a(COVS), "gt": a(GT), "z": ("float", 1.96)},
             ("est", "cov", "gt"), "finite", aliases=al),
        Spec(m, "geoloc.evaluation.isometric_sigmas", {"cov": a(COVS)}, ("cov",), "sigmas"),
        Spec(m, "geoloc.evaluation.chi2_6_cdf", {"x": a(np.array([0.0, 1.0, 12.59]))}, ("x",), "score"),
        Spec(m, "geoloc.evaluation.chi2_6_quantile", {"p": a(np.array([0.1, 0.5, 0.95]))}, ("p",), "finite"),
        Spec(m, "geoloc.evaluation.format_tum_line", {"timestamp": ("float", 1.5), "pose": a(EST[1])},
             ("timestamp", "pose"), "str"),
        Spec(m, "geoloc.evaluation.tum_trajectory_text", {"timestamps": a(np.arange(5.0)), "poses": a(EST)},
             ("timestamps", "poses"), "str", aliases={"timestamps": ["poses"], "poses": ["timestamps"]}),
        Spec(m, "geoloc.evaluation.write_tum_trajectory",
             {"path": ("any", ("path", "fresh")), "timestamps": a(np.arange(5.0)), "poses": a(EST)},
             ("path", "timestamps", "poses"), "any", aliases={"timestamps": ["poses"], "poses": ["timestamps"]}),
        Spec(m, "geoloc.evaluation.summarize",
             {"estimates": a(EST), "ground_truth": a(GT), "covariances": a(COVS), "timestamps": a(np.arange(5.0))},
             ("estimates", "ground_truth"), "any",
             aliases={"estimates": ["ground_truth"], "ground_truth": ["estimates", "covariances", "timestamps"], "covariances": ["estimates"],
                      "timestamps": ["estimates"]}),
    ]


def _results() -> Any:
    return call("geoloc.evaluation.summarize", list(EST), GT, covariances=list(COVS), timestamps=np.arange(5.0))


def plots_specs() -> list[Spec]:
    a = lambda v: ("array", v)  # noqa: E731
    return [
        Spec("plots", "geoloc.plots.plot_trajectory", {"results": ("any", _results()), "path": ("any", ("path", "fresh"))},
             ("results", "path"), "any", timeout=40),
    ] + [Spec("plots", f"geoloc.plots.{f}", {"results": ("any", _results()), "path": ("any", ("path", "fresh"))},
              ("results", "path"), "any", timeout=40) for f in ("plot_error_cdf", "plot_calibration")]


# --- datasets
def datasets_specs() -> list[Spec]:
    return [
        Spec("datasets", "geoloc.datasets.synthetic_room",
             {"n_frames": ("int", 3), "seed": ("int", 0), "noise": ("float", 0.0), "blur": ("float", 0.0)},
             (), "any", timeout=30, aliases={"n_frames": ["n_frames"]}),
        Spec("datasets", "geoloc.datasets.load_tum",
             {"path": ("any", ("cached", "small_dataset_dir")), "intrinsics": ("any", CAMERA_PY),
              "max_time_difference": ("float", 0.02)}, ("path",), "any", timeout=30),
        Spec("datasets", "geoloc.datasets.load_folder",
             {"path": ("any", ("path", "missing")), "trajectory": ("any", "traj.txt"),
              "intrinsics": ("any", CAMERA_PY), "match": ("str:auto|timestamp|row", "auto"),
              "max_time_difference": ("float", 0.02)}, ("path",), "any", extra={"names": ["path"]}),
        Spec("datasets", "geoloc.datasets.load_7scenes", {"path": ("any", ("path", "dir")), "intrinsics": ("any", CAMERA_PY)},
             ("path",), "any", extra={"names": ["path"]}),
    ]


# --- map / localizer
def map_specs() -> list[Spec]:
    a = lambda v: ("array", v)  # noqa: E731
    m = ("cached", "small_map")
    loc = call("geoloc.Localizer", m)
    room_cam = attr(("cached", "small_room"), "camera")
    room_img = attr(call(attr(("cached", "small_room"), "__getitem__"), 11), "image")
    garbage = [b"", b"\x00" * 64, b"GEOLOC" + b"\xff" * 100, b'{"__metadata__": {}}', b"\x10\x00\x00\x00\x00\x00\x00\x00{}" + b"x" * 8]
    return [
        Spec("mapping", "geoloc.Localizer",
             {"map": ("any", m), "camera": ("camera", room_cam), "pixel_sigma": ("float", 1.0), "max_residual": ("float", 5.0),
              "gate_sigma": ("float", 3.0), "history": ("int", 4), "locator": ("str:paper|model", "paper"),
              "top_k": ("int", 5)}, ("map",), "any", timeout=60,
             aliases={"camera": ["fx", "camera"], "map": ["map"]}),
        Spec("mapping", attr(loc, "localize"), {"image": a(np.resize(IMG, (480, 640, 3))), "timestamp": ("float", 1.0)},
             ("image", "timestamp"), "localization", timeout=60, huge=300),
        Spec("mapping", attr(loc, "localize"), {"image": ("any", room_img), "timestamp": ("float", 1.0)},
             ("image", "timestamp"), "localization", timeout=60, frozen=("image",)),
        Spec("mapping", "geoloc.Map.load", {"path": ("any", ("cached", "small_map_file"))}, ("path",), "any",
             timeout=60),
        Spec("mapping", "geoloc.Map.from_bytes", {"data": ("any", call(attr(m, "to_bytes")))}, ("data",), "any",
             timeout=60),
    ] + [Spec("mapping", "geoloc.Map.load", {"path": ("any", ("file", g, ".geoloc"))}, ("path",), "any", frozen=("path",),
              extra={"names": ["path", ".geoloc"]}) for g in garbage] + [
        Spec("mapping", "geoloc.Map.from_bytes", {"data": ("any", g)}, ("data",), "any", frozen=("data",),
             extra={"names": ["data"]}) for g in garbage]


def feature_localizer_specs() -> list[Spec]:
    a = lambda v: ("array", v)  # noqa: E731
    fm = ("cached", "feature_map")
    rng = np.random.default_rng(0)
    kps = [rng.uniform(0, 480, size=(40, 2)) for _ in range(3)]
    return [
        Spec("localizer", "geoloc.Map.from_features",
             {"camera": ("camera", CAM), "poses": a(_track(3)), "keypoints": ("any", kps), "descriptors": a(np.stack([DESC_U8[:40]] * 3)),
              "pose_covariances": a(np.repeat(COV6[None], 3, axis=0)), "branching": ("int", 3), "depth": ("int", 2),
              "seed": ("int", 0), "refine_intrinsics": ("bool", True), "estimate_noise": ("bool", False),
              "adjust_labels": ("bool", False),
              "intrinsics_model": ("str:pinhole|radial|radial-tangential", "radial-tangential")},
             ("camera", "poses", "keypoints", "descriptors"), "any",
             aliases={"camera": ["fx", "camera"], "poses": ["keypoints", "descriptors", "pose_covariances"],
                      "descriptors": ["keypoints"], "keypoints": ["descriptors"], "pose_covariances": ["poses"],
                      "branching": ["descriptors"], "depth": ["descriptors"]}),
        Spec("localizer", attr(call("geoloc.Localizer", fm), "localize_features"),
             {"timestamp": ("float", 0.5), "keypoints": a(kps[0]), "descriptors": a(DESC_U8[:40])},
             ("timestamp", "keypoints", "descriptors"), "localization",
             aliases={"keypoints": ["descriptors"], "descriptors": ["keypoints"]}),
        Spec("localizer", "geoloc.Localizer",
             {"map": ("any", fm), "pixel_sigma": ("float", 1.0), "max_residual": ("float", 5.0), "gate_sigma": ("float", 3.0),
              "history": ("int", 4), "locator": ("str:paper|model", "paper"), "top_k": ("int", 5)}, ("map",), "any"),
    ]


def _adjustment_problem() -> dict[str, np.ndarray]:
    """Four keyframes 10 cm apart looking at 30 points 3–5 m away, every point seen by every
    keyframe (exact pixels), the labels the camera poses."""
    rng = np.random.default_rng(7)
    labels = _track(4)
    labels[:, 0, 3] = 0.1 * np.arange(4)
    depth = rng.uniform(3.0, 5.0, 30)
    points = np.c_[rng.uniform(-0.4, 0.4, 30) * depth, rng.uniform(-0.3, 0.3, 30) * depth, depth]
    fx, fy, cx, cy = CAMERA_PY
    local = points[None] - labels[:, None, :3, 3]
    pixels = np.stack([fx * local[..., 0] / local[..., 2] + cx, fy * local[..., 1] / local[..., 2] + cy], -1)
    return {"labels": labels, "points": points, "obs_keyframes": np.repeat(np.arange(4), 30),
            "obs_points": np.tile(np.arange(30), 4), "obs_pixels": pixels.reshape(-1, 2), "obs_sigmas": np.ones(120)}


ADJ = _adjustment_problem()


def adjustment_specs() -> list[Spec]:
    a = lambda v: ("array", v)  # noqa: E731
    m = "adjustment"
    problem = call("geoloc.adjustment.AdjustmentProblem", CAMERA_PY, *(ADJ[k] for k in
                   ("labels", "points", "obs_keyframes", "obs_points", "obs_pixels")))
    obs = ["obs_keyframes", "obs_points", "obs_pixels", "obs_sigmas"]
    return [
        # the problem's fields: fixtures.adjust builds the problem from them and adjusts it
        Spec(m, "fixtures.adjust", {"intrinsics": ("any", CAMERA_PY), **{k: a(v) for k, v in ADJ.items()}},
             (), "any", timeout=60,
             # the core names an observation it refuses: observations[i]
             aliases={"labels": ["obs_keyframes", "observations"], "points": ["obs_points", "observations"],
                      **{k: [*(o for o in obs if o != k), "observations"] for k in obs}}),
        Spec(m, "geoloc.adjustment.bundle_adjust",
             {"problem": ("any", problem), "label_sigma": ("any", (0.02, 0.02)), "start": a(ADJ["labels"]),
              "offset": a(np.eye(4)), "estimate_offset": ("bool", True), "max_iterations": ("int", 10),
              "outlier_px": ("float", 4.0), "pixel_sigma": ("float", 1.0)}, ("problem",), "any", timeout=60,
             aliases={"start": ["labels"]}),
        Spec(m, attr(("cached", "small_map_labels_kept"), "label_adjustment_problem"), {}, (), "any", timeout=60),
    ]


def all_specs(with_onnx: bool = False) -> dict[str, list[Spec]]:
    groups: dict[str, list[Spec]] = {}
    for fn in (lie_specs, geometry_specs, matching_specs, retrieval_specs, temporal_specs, camera_specs, features_specs,
               evaluation_specs, plots_specs, datasets_specs, map_specs, feature_localizer_specs, adjustment_specs):
        for s in fn():
            groups.setdefault(s.module, []).append(s)
    for s in descriptor_specs(with_onnx):
        groups.setdefault(s.module, []).append(s)
    return groups


def module_cases(module: str, with_onnx: bool = False) -> st.SearchStrategy[dict[str, Any]]:
    if module == "cli":
        return st.one_of([cli_cases(c) for c in CLI if with_onnx or c != "train"])
    if module == "files":
        try:
            from . import file_cases
        except ImportError:  # imported as a top-level module (benchmarks/adversarial.py)
            import file_cases  # type: ignore[no-redef]
        return file_cases.file_cases()
    if module.startswith("cli:"):
        return cli_cases(module[4:])
    specs = all_specs(with_onnx)[module]
    strategies = [cases(s) for s in specs]
    if module == "retrieval":
        strategies.append(scaled_index_case())
    if module == "matching":
        strategies.append(self_match_case())
    return st.one_of(strategies)


# --- the CLI: one option at a time set to a bad value, the others valid and cheap
MISSING = ("path", "missing")  # <tmp>/no-such-dir/x.geoloc: its folder must never be created
BAD_VALUES = ["", "-1", "0", "abc", "1180591620717411303424", "nan", "inf", "-inf", "1e999", "1:0", "::", "a:b",
              "3.5", "-0", "0x10", " 7", "1,2,3", "1,2,3,4,5", "nan,1,1,1", "é", "--", "/nonexistent/dir/x.out",
              "1000000000"]
BAD_FILES = [MISSING, ("path", "dir"), ("path", "unwritable"), ("file", b"", ".geoloc"),
             ("file", b"\x00" * 40, ".geoloc"), ("file", b"PK\x03\x04garbage", ".onnx"),
             ("file", b"\x08\x00\x00\x00\x00\x00\x00\x00{\"a\":1}", ".geoloc")]
SYN = ["--format", "synthetic", "--synthetic-frames", "20"]

#: command → (base argv, {option: "value"|"file"|"out"|"flag"})
CLI: dict[str, tuple[list[Any], dict[str, str]]] = {
    "demo": (["--out", ("path", "newdir"), "--frames", "20", "--no-plots"], {"--out": "out", "--frames": "value"}),
    "build-map": ([*SYN, "--frames", "0:3", "--n-features", "100", "--out", ("path", "fresh")],
                  {"--dataset": "file", "--format": "value", "--intrinsics": "value", "--trajectory": "file",
                   "--synthetic-frames": "value", "--frames": "value", "--step": "value", "--features": "value",
                   "--n-features": "value", "--retrieval": "file", "--out": "out"}),
    "localize": (["--map", ("cached", "small_map_file"), *SYN, "--frames", "0:2", "--out", ("path", "fresh")],
                 {"--map": "file", "--images": "file", "--frames": "value", "--mode": "value", "--retrieval": "file",
                  "--out": "out", "--synthetic-frames": "value", "--intrinsics": "value"}),
    # three frames of the room triangulate no model: the paper's locator is the one that runs
    "evaluate": ([*SYN, "--train", "0:3", "--test", "3:5", "--n-features", "100", "--locator", "paper"],
                 {"--json": "out", "--locator": "value", "--plots": "out", "--train": "value", "--test": "value", "--mode": "value",
                  "--n-features": "value", "--retrieval": "file", "--dataset": "file", "--format": "value",
                  "--synthetic-frames": "value", "--features": "value"}),
    "selfcheck": (["--samples", "2"], {"--samples": "value"}),
    "montecarlo": (["--trials", "2", "--no-progress"],
                   {"--trials": "value", "--seed": "value", "--json": "out", "--covariance": "value", "--scene": "value"}),
    "train": (["--dataset", "synthetic", "--tiny", "--epochs", "1", "--pairs", "2", "--batch-size", "2", "--dim", "8",
               "--no-progress", "--out", ("path", "fresh")],
              {"--dataset": "file", "--format": "value", "--train": "value", "--stride": "value", "--epochs": "value",
               "--dim": "value", "--pairs": "value", "--batch-size": "value", "--lr": "value", "--seed": "value",
               "--checkpoint": "out", "--init": "file", "--device": "value", "--threads": "value", "--out": "out"}),
}


@st.composite
def cli_cases(draw: st.DrawFn, command: str) -> dict[str, Any]:
    base, options = CLI[command]
    option = draw(st.sampled_from(sorted(options)))
    kind = options[option]
    if kind == "value":
        value: Any = draw(st.sampled_from(BAD_VALUES))
    elif kind == "file":
        value = draw(st.sampled_from(BAD_FILES))
    else:
        value = draw(st.sampled_from([MISSING, ("path", "dir"), ("path", "unwritable"), "/nonexistent/dir/x.json"]))
    argv = list(base)
    if option in argv:
        i = argv.index(option)
        argv[i + 1] = value
    else:
        argv += [option, value]
    if draw(st.booleans()):  # the same option twice, or a stray positional / unknown option
        argv += draw(st.sampled_from([[], ["--no-such-option"], ["stray"]]))
    names = [option, "--no-such-option", "stray", "unrecognized"]
    return {"module": "cli", "cli": [command, *argv], "names": names, "timeout": 90,
            "watch": [("path", "missingdir"), "/nonexistent"]}
