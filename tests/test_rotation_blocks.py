"""Pose files are checked as what they are: a rotation block more than 1e-2 from orthonormal
(‖RᵀR − I‖_F) is refused with the file and frame named, not projected into a rotation; the
7-Scenes release's near-rotations (det 0.9995–0.9999) still load."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from geoloc import lie
from geoloc.datasets.sevenscenes import read_7scenes_pose
from geoloc.datasets.tum import read_tum_trajectory
from geoloc.exceptions import DatasetError, NotARotationError
from geoloc.reference import load_reference


def _pose_file(path: Path, block: np.ndarray) -> Path:
    pose = np.eye(4)
    pose[:3, :3] = block
    np.savetxt(path, pose)
    return path


@pytest.mark.parametrize(
    "block",
    [
        np.array([[1, 0.9, 0], [0, 1, 0], [0, 0, 1]], dtype=float),  # a shear: once a 24° rotation
        np.diag([100.0, 1.0, 0.01]),  # a scale: once the identity
        np.diag([1.02, 1.0, 1.0]),  # 4 % stretch
    ],
)
def test_garbage_rotation_blocks_are_refused_with_the_file_named(tmp_path, block):
    path = _pose_file(tmp_path / "frame-000007.pose.txt", block)
    with pytest.raises(DatasetError, match=r"frame-000007\.pose\.txt.*not a rotation"):
        read_7scenes_pose(path)
    with pytest.raises(NotARotationError, match="R"):
        lie.so3_project_near(block)


def test_near_rotations_still_load_and_project(tmp_path):
    rng = np.random.default_rng(0)
    rot = lie.so3_exp(rng.normal(size=3))
    near = rot * 0.9997  # det ≈ 0.9991: like the 7-Scenes release
    got = read_7scenes_pose(_pose_file(tmp_path / "p.txt", near))
    np.testing.assert_allclose(got[:3, :3], rot, atol=1e-12)
    # the bound is ‖RᵀR − I‖_F, compared with a hand-made stretch on either side of 1e-2
    for scale, ok in [(1 + 0.0099 / 2 / np.sqrt(3), True), (1 + 0.0101 / 2 / np.sqrt(3), False)]:
        m = rot * scale
        assert (lie.orthonormality_error(m) <= lie.MAX_ORTHONORMALITY_ERROR) == ok
        if ok:
            lie.so3_project_near(m)
        else:
            with pytest.raises(NotARotationError):
                lie.so3_project_near(m)


def test_batch_names_the_block_and_refuses_reflections():
    blocks = np.stack([np.eye(3), np.diag([1.0, 1.0, -1.0])])
    with pytest.raises(NotARotationError, match=r"poses\[1\]"):
        lie.so3_project_near(blocks, "poses")


def test_reference_and_tum_files_use_the_same_bound(tmp_path):
    ref = tmp_path / "ref.txt"
    ref.write_text("0 1 0 0 0 0 1 0 0 0 0 1 0\n1 1 0.9 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(DatasetError, match="line 2.*not a rotation"):
        load_reference(ref)
    tum = tmp_path / "traj.txt"
    tum.write_text("0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 0.99\n")
    with pytest.raises(DatasetError, match="pose 2 has no unit quaternion"):
        read_tum_trajectory(tum)
    tum.write_text("0 0 0 0 0 0 0 1\n1 0 0 0 0.7071 0 0 0.7071\n")  # 4 decimals, as TUM files print
    assert read_tum_trajectory(tum)[1].shape == (2, 4, 4)
