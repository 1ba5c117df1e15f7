# Stub of the compiled module geoloc._core (crates/geoloc-py); checked against the built
# module by mypy.stubtest in tests/test_stubs.py. Every function maps rows: (N, in) float64,
# C-contiguous, finite → (N, out) float64; matrices are flattened row-major.
import os
from typing import Any, final

import numpy as np
from numpy.typing import NDArray

__version__: str
PARALLEL_MIN_ITEMS: int

def so3_hat(phi: NDArray[np.float64]) -> NDArray[np.float64]: ...
def so3_vee(m: NDArray[np.float64]) -> NDArray[np.float64]: ...
def so3_exp(phi: NDArray[np.float64]) -> NDArray[np.float64]: ...
def so3_log(rotation: NDArray[np.float64]) -> NDArray[np.float64]: ...
def so3_project(m: NDArray[np.float64]) -> NDArray[np.float64]: ...
def rotation_angle(rotation: NDArray[np.float64]) -> NDArray[np.float64]: ...
def so3_to_quaternion_wxyz(rotation: NDArray[np.float64]) -> NDArray[np.float64]: ...
def so3_from_quaternion_wxyz(q: NDArray[np.float64]) -> NDArray[np.float64]: ...
def so3_left_jacobian(phi: NDArray[np.float64]) -> NDArray[np.float64]: ...
def so3_right_jacobian(phi: NDArray[np.float64]) -> NDArray[np.float64]: ...
def so3_left_jacobian_inv(phi: NDArray[np.float64]) -> NDArray[np.float64]: ...
def so3_right_jacobian_inv(phi: NDArray[np.float64]) -> NDArray[np.float64]: ...
def se3_hat(xi: NDArray[np.float64]) -> NDArray[np.float64]: ...
def se3_vee(m: NDArray[np.float64]) -> NDArray[np.float64]: ...
def se3_curly_hat(xi: NDArray[np.float64]) -> NDArray[np.float64]: ...
def se3_exp(xi: NDArray[np.float64]) -> NDArray[np.float64]: ...
def se3_log(pose: NDArray[np.float64]) -> NDArray[np.float64]: ...
def se3_inverse(pose: NDArray[np.float64]) -> NDArray[np.float64]: ...
def se3_adjoint(pose: NDArray[np.float64]) -> NDArray[np.float64]: ...
def se3_project(pose: NDArray[np.float64]) -> NDArray[np.float64]: ...
def se3_left_jacobian(xi: NDArray[np.float64]) -> NDArray[np.float64]: ...
def se3_right_jacobian(xi: NDArray[np.float64]) -> NDArray[np.float64]: ...
def se3_left_jacobian_inv(xi: NDArray[np.float64]) -> NDArray[np.float64]: ...
def se3_right_jacobian_inv(xi: NDArray[np.float64]) -> NDArray[np.float64]: ...
def se3_compose(pose1: NDArray[np.float64], pose2: NDArray[np.float64]) -> NDArray[np.float64]: ...
def se3_distance(pose1: NDArray[np.float64], pose2: NDArray[np.float64]) -> NDArray[np.float64]: ...
def se3_interpolate(
    pose1: NDArray[np.float64], pose2: NDArray[np.float64], alpha: NDArray[np.float64]
) -> NDArray[np.float64]: ...
def se3_transform_points(
    pose: NDArray[np.float64], points: NDArray[np.float64]
) -> NDArray[np.float64]: ...
def triangulate(
    poses_wc: NDArray[np.float64],
    intrinsics: tuple[float, float, float, float],
    cam_ids: NDArray[np.int64],
    track_ids: NDArray[np.int64],
    pixels: NDArray[np.float64],
    pose_covariances: NDArray[np.float64] | None,
    loss: str,
    loss_width: float,
    pixel_sigma: float,
    max_residual: float,
    min_angle: float,
) -> dict[str, Any]: ...
def solve_pnp(
    points3d: NDArray[np.float64],
    pixels: NDArray[np.float64],
    intrinsics: tuple[float, float, float, float],
    init_pose: NDArray[np.float64] | None,
    point_covariances: NDArray[np.float64] | None,
    point_pose_jacobians: NDArray[np.float64] | None,
    pose_covariances: NDArray[np.float64] | None,
    loss: str,
    loss_width: float,
    pixel_sigma: float,
    max_residual: float,
    covariance: str,
    min_iterations: int,
    max_iterations: int,
    confidence: float,
    seed: int,
) -> dict[str, Any]: ...
def keyframe_score(
    pose1: NDArray[np.float64], pose2: NDArray[np.float64], d_m: float, ell: float, alpha_m: float
) -> NDArray[np.float64]: ...
def select_keyframes(
    poses_wc: NDArray[np.float64],
    k: int,
    n: int,
    window: int,
    d_m: float,
    ell: float,
    alpha_m: float,
    min_score: float,
) -> NDArray[np.uint64]: ...
def motion_predict(
    poses_wc: NDArray[np.float64],
    timestamps: NDArray[np.float64],
    t_query: float,
    covariances: NDArray[np.float64] | None,
) -> dict[str, Any]: ...
def fuse(
    pose_m: NDArray[np.float64],
    cov_m: NDArray[np.float64],
    pose_g: NDArray[np.float64],
    cov_g: NDArray[np.float64],
    gate_sigma: float,
    gate: str,
) -> dict[str, Any]: ...
def match_descriptors(
    descriptors_a: NDArray[Any],
    descriptors_b: NDArray[Any],
    *,
    ratio: float | None = ...,
    mutual: bool = True,
    max_distance: float | None = None,
) -> tuple[NDArray[np.int64], NDArray[np.float32]]: ...
def epipolar_filter(
    intrinsics: tuple[float, float, float, float],
    pose_a: NDArray[np.float64],
    pose_b: NDArray[np.float64],
    keypoints_a: NDArray[np.float64],
    keypoints_b: NDArray[np.float64],
    pairs: NDArray[np.int64],
    *,
    max_px: float = 2.0,
) -> NDArray[np.bool_]: ...

# --- retrieval, bow, matching, localizer (geoloc_core::{retrieval, bow, matching, map, localizer}) ---

@final
class DescriptorIndex:
    def __new__(cls, descriptors: NDArray[np.float32], *, backend: str | None = None) -> DescriptorIndex: ...
    def query(self, queries: NDArray[np.float32], k: int | np.integer[Any] | None = None) -> tuple[NDArray[np.float32], NDArray[np.int64]]: ...
    def __len__(self) -> int: ...
    @property
    def dim(self) -> int: ...
    @property
    def backend(self) -> str: ...

@final
class Vocabulary:
    @staticmethod
    def train(
        descriptors: NDArray[Any],
        *,
        branching: int | np.integer[Any] | None = None,
        depth: int | np.integer[Any] | None = None,
        seed: int | np.integer[Any] | None = None,
    ) -> Vocabulary: ...
    def words(self, descriptors: NDArray[Any]) -> NDArray[np.uint32]: ...
    def __len__(self) -> int: ...

@final
class BowDatabase:
    def __new__(cls, vocabulary: Vocabulary, images: list[NDArray[Any]]) -> BowDatabase: ...
    def query(self, descriptors: NDArray[Any], k: int | np.integer[Any] | None = None) -> tuple[NDArray[np.float32], NDArray[np.int64]]: ...
    @property
    def vocabulary(self) -> Vocabulary: ...
    def __len__(self) -> int: ...

@final
class FeatureMap:
    def __new__(
        cls,
        intrinsics: tuple[float, float, float, float],
        poses_wc: NDArray[np.float64],
        keypoints_list: list[NDArray[np.float64]],
        descriptors_list: list[NDArray[Any]],
        *,
        global_descriptors: NDArray[np.float32] | None = None,
        pose_covariances: NDArray[np.float64] | None = None,
        retrieval: str = "bow",
        branching: int | np.integer[Any] | None = None,
        depth: int | np.integer[Any] | None = None,
        seed: int | np.integer[Any] | None = None,
    ) -> FeatureMap: ...
    def __len__(self) -> int: ...
    @property
    def intrinsics(self) -> tuple[float, float, float, float]: ...
    def save(self, path: str | os.PathLike[str], frontend: str) -> None: ...
    @staticmethod
    def load(path: str | os.PathLike[str]) -> tuple[FeatureMap, str]: ...

@final
class Localization:
    @property
    def pose(self) -> NDArray[np.float64] | None: ...
    @property
    def covariance(self) -> NDArray[np.float64] | None: ...
    @property
    def source(self) -> str: ...
    @property
    def reason(self) -> str: ...
    @property
    def keyframe(self) -> int: ...
    @property
    def inliers(self) -> int: ...
    @property
    def timings_ms(self) -> dict[str, float]: ...

@final
class FeatureLocalizer:
    def __new__(
        cls,
        map: FeatureMap,
        *,
        pixel_sigma: float = 1.0,
        max_residual: float = 5.0,
        gate_sigma: float = 3.0,
        history: int | np.integer[Any] | None = None,
    ) -> FeatureLocalizer: ...
    def localize(
        self,
        timestamp: float,
        keypoints: NDArray[np.float64],
        descriptors: NDArray[Any],
        global_descriptor: NDArray[np.float32] | None = None,
    ) -> Localization: ...
    def reset(self) -> None: ...
