"""TUM / KITTI pose files: round trips, format detection and line-precise errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from frontend.errors import FrontendInputError
from frontend.odometry.logged import so3_exp
from frontend.poses_io import read_kitti, read_poses, read_tum, write_kitti, write_tum
from ssmvpr_common.poses import matrix_to_quaternion, quaternion_to_matrix


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


def test_comments_and_blank_lines_are_ignored(tmp_path: Path) -> None:
    path = tmp_path / "tum.txt"
    path.write_text("# timestamp tx ty tz qx qy qz qw\n\n0.0 1 2 3 0 0 0 1\n1.0,1,2,3,0,0,0,1\n")
    assert len(read_tum(path).poses) == 2


@pytest.mark.parametrize(
    ("content", "reader", "pattern"),
    [
        ("0 1 2 3 0 0 0 1\n1 1 2 3 0 0 1\n", read_tum, r"bad\.txt:2: expected 8 values"),
        ("0 1 2 3 0 0 0 1\n1 nan 2 3 0 0 0 1\n", read_tum, r"bad\.txt:2: NaN or inf"),
        ("0 1 2 3 0 0 0 1\n1 1 2 3 0 0 0 2\n", read_tum, r"bad\.txt:2: quaternion norm 2"),
        ("0 1 2 3 0 0 0 1\n1 1 x 3 0 0 0 1\n", read_tum, r"bad\.txt:2: non-numeric"),
        ("1 0 0 0 0 1 0 0 0 0 1 inf\n", read_kitti, r"bad\.txt:1: NaN or inf"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n2 0 0 0 0 1 0 0 0 0 1 0\n", read_kitti, r"bad\.txt:2: rotation is not orthonormal"),
        ("-1 0 0 0 0 1 0 0 0 0 1 0\n", read_kitti, r"bad\.txt:1: .*determinant"),
        ("1 0 0 0 0 1 0 0 0 0 1\n", read_kitti, r"bad\.txt:1: expected 12 values"),
    ],
)
def test_bad_lines_name_file_and_line(tmp_path: Path, content: str, reader, pattern: str) -> None:
    path = tmp_path / "bad.txt"
    path.write_text(content)
    with pytest.raises(FrontendInputError, match=pattern) as info:
        reader(path)
    assert "\n" not in str(info.value)


def test_format_detection_errors(tmp_path: Path) -> None:
    empty = tmp_path / "empty.txt"
    empty.write_text("# nothing\n")
    with pytest.raises(FrontendInputError, match="no data lines"):
        read_poses(empty)
    odd = tmp_path / "odd.txt"
    odd.write_text("1 2 3\n")
    with pytest.raises(FrontendInputError, match=r"odd\.txt:1: 3 values; expected 8 \(TUM\) or 12"):
        read_poses(odd)
    with pytest.raises(FrontendInputError, match="cannot read"):
        read_poses(tmp_path / "missing.txt", format="tum")


def test_writing_invalid_poses_leaves_no_file(tmp_path: Path) -> None:
    poses = _random_poses(3, 2)
    poses[1, 0, 0] = np.nan
    with pytest.raises(FrontendInputError, match=r"out\.txt: pose 1 not written"):
        write_kitti(tmp_path / "out.txt", poses)
    with pytest.raises(FrontendInputError, match="timestamps"):
        write_tum(tmp_path / "out.txt", np.arange(2.0), _random_poses(3, 3))
    assert list(tmp_path.iterdir()) == []
