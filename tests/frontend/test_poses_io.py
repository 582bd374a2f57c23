"""A pose file as the front end reads it (frontend.poses_io): round trips through the common
writer, the format detected, the tolerance from PoseFileConfig."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from frontend.config import PoseFileConfig
from frontend.odometry.logged import so3_exp
from frontend.poses_io import read_poses
from ssmvpr_common.poses import matrix_to_quaternion, quaternion_to_matrix
from ssmvpr_common.trajectory_io import TrajectoryFileError, write_kitti, write_tum


def _random_poses(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    for pose in poses:
        pose[:3, :3] = so3_exp(rng.normal(size=3))
        pose[:3, 3] = rng.normal(size=3) * 100
    return poses


@given(st.lists(st.floats(-1, 1, allow_nan=False), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1))
@settings(max_examples=60, deadline=None)
def test_quaternion_matrix_round_trip(q: list[float]) -> None:
    q = np.array(q) / np.linalg.norm(q)
    r = quaternion_to_matrix(q)
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
    back = matrix_to_quaternion(r)
    assert back[3] >= 0
    assert min(np.abs(back - q).max(), np.abs(back + q).max()) < 1e-9  # q and -q: same rotation


def test_tum_round_trip(tmp_path: Path) -> None:
    poses = _random_poses(20, 0)
    stamps = 1_305_031_102.175304 + np.arange(20) * 0.033
    path = tmp_path / "traj_tum.txt"
    write_tum(path, stamps, poses)
    loaded = read_poses(path)
    assert loaded.format == "tum"
    np.testing.assert_allclose(loaded.timestamps, stamps, atol=1e-9)
    np.testing.assert_allclose(loaded.poses, poses, atol=1e-6)
    assert not [p for p in tmp_path.iterdir() if p.name != "traj_tum.txt"]  # no temp files left


def test_kitti_round_trip(tmp_path: Path) -> None:
    poses = _random_poses(15, 1)
    path = tmp_path / "00.txt"
    write_kitti(path, poses)
    assert len(path.read_text().splitlines()[0].split()) == 12
    loaded = read_poses(path)
    assert loaded.format == "kitti" and loaded.timestamps is None
    np.testing.assert_allclose(loaded.poses, poses, atol=1e-6)


def test_comments_blank_lines_and_commas_are_read(tmp_path: Path) -> None:
    path = tmp_path / "tum.txt"
    path.write_text("# timestamp tx ty tz qx qy qz qw\n\n0.0 1 2 3 0 0 0 1\n1.0,1,2,3,0,0,0,1\n")
    assert len(read_poses(path).poses) == 2


def test_the_front_ends_tolerance_decides(tmp_path: Path) -> None:
    path = tmp_path / "loose.txt"
    path.write_text("0 1 2 3 0 0 0 1.002\n")  # |q| - 1 = 0.002: over the default 1e-3
    with pytest.raises(TrajectoryFileError, match=r"loose\.txt:1: quaternion norm"):
        read_poses(path)
    assert len(read_poses(path, config=PoseFileConfig(rotation_tolerance=0.01)).poses) == 1
