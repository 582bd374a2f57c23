"""TUM / KITTI trajectory files (ssmvpr_common.trajectory_io, the one reader and writer): round
trips, atomic writes, one error type naming file and line."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ssmvpr_common.errors import SsmvprError
from ssmvpr_common.trajectory_io import (
    TrajectoryFileError,
    detect_format,
    read_kitti,
    read_tum,
    write_kitti,
    write_tum,
)


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix()
    poses[:, :3, 3] = rng.normal(0, 50, (n, 3))
    return poses


def test_tum_round_trip(tmp_path):
    poses = random_poses(25)
    stamps = 1.7e9 + np.arange(25) * 0.1
    path = write_tum(tmp_path / "sub" / "traj.tum", stamps, poses)
    t, back = read_tum(path)
    np.testing.assert_allclose(t, stamps, atol=1e-6)
    np.testing.assert_allclose(back, poses, atol=1e-8)
    assert not list(path.parent.glob(".*.tmp"))


def test_tum_quaternion_order_is_xyzw_scalar_last(tmp_path):
    yaw = np.pi / 2
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_euler("z", yaw).as_matrix()
    write_tum(tmp_path / "t.txt", [0.0], pose[None])
    line = (tmp_path / "t.txt").read_text().splitlines()[1].split()
    qx, qy, qz, qw = map(float, line[4:])
    expected = [0, 0, np.sin(yaw / 2), np.cos(yaw / 2)]
    np.testing.assert_allclose([qx, qy, qz, qw], expected, atol=1e-9)


def test_kitti_round_trip(tmp_path):
    poses = random_poses(12, seed=3)
    path = write_kitti(tmp_path / "traj.txt", poses)
    assert all(len(line.split()) == 12 for line in path.read_text().splitlines())
    np.testing.assert_allclose(read_kitti(path), poses, atol=1e-8)


def test_comments_and_blank_lines_are_skipped(tmp_path):
    path = tmp_path / "t.tum"
    path.write_text("# header\n\n0 1 2 3 0 0 0 1\n   \n1 1 2 3 0 0 0 1\n")
    stamps, poses = read_tum(path)
    assert stamps.tolist() == [0.0, 1.0]
    np.testing.assert_allclose(poses[1, :3, 3], [1, 2, 3])


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("0 1 2 3 0 0 0 1\n0 1 2 3 0 0 1\n", r"t\.tum:2: expected 8 numbers"),
        ("0 1 2 3 0 0 0 1\n\n0 1 x 3 0 0 0 1\n", r"t\.tum:3: not a number"),
        ("0 1 2 nan 0 0 0 1\n", r"t\.tum:1: NaN or inf"),
        ("0 1 2 3 0 0 0 2\n", r"t\.tum:1: quaternion norm"),
        ("0 1 2 3 0 0 0 1\n1 1 2 3 0 0 0 1.01\n", r"t\.tum:2: quaternion norm 1.01"),
    ],
)
def test_bad_tum_lines_name_file_and_line(tmp_path, text, match):
    path = tmp_path / "t.tum"
    path.write_text(text)
    with pytest.raises(TrajectoryFileError, match=match) as caught:
        read_tum(path)
    assert "\n" not in str(caught.value)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("1 0 0 0 0 1 0 0 0 0 1\n", r"k\.txt:1: expected 12 numbers"),
        ("1 0 0 0 0 1 0 0 0 0 1 0\n2 0 0 0 0 1 0 0 0 0 1 0\n", r"k\.txt:2: rotation"),
        ("1 0 0 0 0 1 0 0 0 0 1 inf\n", r"k\.txt:1: NaN or inf"),
        ("-1 0 0 0 0 1 0 0 0 0 1 0\n", r"k\.txt:1: .*determinant"),
    ],
)
def test_bad_kitti_lines_name_file_and_line(tmp_path, text, match):
    path = tmp_path / "k.txt"
    path.write_text(text)
    with pytest.raises(TrajectoryFileError, match=match):
        read_kitti(path)


def test_missing_file_and_bad_inputs(tmp_path):
    with pytest.raises(TrajectoryFileError, match="nope.txt: trajectory file not found"):
        read_kitti(tmp_path / "nope.txt")
    with pytest.raises(TrajectoryFileError, match="timestamps"):
        write_tum(tmp_path / "t.tum", [0.0, 1.0], random_poses(3))
    bad = random_poses(2)
    bad[1, 0, 0] = np.nan
    with pytest.raises(TrajectoryFileError, match=r"k\.txt: pose 1 not written: pose contains NaN"):
        write_kitti(tmp_path / "k.txt", bad)
    assert not (tmp_path / "k.txt").exists()


def test_one_error_type_a_user_can_catch_as_the_projects_or_as_a_value_error(tmp_path):
    (tmp_path / "empty.txt").write_text("# nothing\n")
    (tmp_path / "odd.txt").write_text("1 2 3\n")
    (tmp_path / "binary.txt").write_bytes(b"\x00\xff\x10")
    for path, match in [("empty.txt", "no data lines"), ("odd.txt", r"odd\.txt:1: 3 values; expected 8 \(TUM\) or 12"),
                        ("binary.txt", "not UTF-8 text"), ("missing.txt", "not found")]:  # fmt: skip
        with pytest.raises(TrajectoryFileError, match=match) as caught:
            detect_format(tmp_path / path)
        assert isinstance(caught.value, SsmvprError) and isinstance(caught.value, ValueError)


def test_the_format_is_told_by_the_first_data_line(tmp_path):
    write_tum(tmp_path / "a.txt", [0.0], random_poses(1))
    write_kitti(tmp_path / "b.txt", random_poses(1))
    assert (detect_format(tmp_path / "a.txt"), detect_format(tmp_path / "b.txt")) == ("tum", "kitti")


def test_failed_write_keeps_previous_file(tmp_path):
    path = write_kitti(tmp_path / "k.txt", random_poses(2))
    before = path.read_text()
    with pytest.raises(TrajectoryFileError):
        write_kitti(path, np.zeros((2, 4, 4)))
    assert path.read_text() == before
