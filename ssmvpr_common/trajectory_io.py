"""TUM and KITTI trajectory files: the one reader and writer every package uses.

TUM: ``t x y z qx qy qz qw`` per line (Hamilton quaternion, scalar last), as evo writes it;
KITTI: the 12 row-major values of the top 3x4 block of a 4x4 pose. ``#`` and blank lines are
comments. Poses are 4x4 float64 body-to-world.

One error type and one tolerance policy, wherever a trajectory comes from (a pose file beside
images, a route, a ground truth for `optimize`, a run's own output): a line that is not a rigid
pose within `ROTATION_TOLERANCE` (|q| - 1, or |R^T R - I|) is a `TrajectoryFileError` naming
file:line, because a skipped or mis-parsed pose corrupts every metric computed from it later;
rotations within it are projected onto the nearest rotation (text files round). Writes are
atomic, so a crash never leaves half a trajectory behind."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal

import numpy as np

from ssmvpr_common import poses as pose_format
from ssmvpr_common.atomic import atomic_write_text
from ssmvpr_common.errors import SsmvprError
from ssmvpr_common.quoting import quoted
from ssmvpr_common.text_files import read_text

TrajectoryFormat = Literal["tum", "kitti"]
ROTATION_TOLERANCE = 1e-3  # KITTI's six significant digits and TUM's rounded quaternions stay inside it
TUM_HEADER = "# timestamp tx ty tz qx qy qz qw"


class TrajectoryFileError(SsmvprError, ValueError):
    """A TUM or KITTI file that cannot be read, or poses that cannot be written; the message
    names the file (and the line)."""


def _rows(path: Path, expected: int, what: str) -> list[tuple[int, np.ndarray]]:
    """(line number, values) of each data line, each holding `expected` finite numbers."""
    if not path.is_file():
        raise TrajectoryFileError(f"{path}: trajectory file not found")
    rows = []
    for lineno, tokens in pose_format.data_lines(read_text(path, TrajectoryFileError)):
        if len(tokens) != expected:
            raise TrajectoryFileError(f"{path}:{lineno}: expected {expected} numbers ({what}), got {len(tokens)}")
        try:
            values = np.array([float(token) for token in tokens])
        except ValueError:
            raise TrajectoryFileError(f"{path}:{lineno}: not a number in {quoted(' '.join(tokens))}") from None
        if not np.all(np.isfinite(values)):
            raise TrajectoryFileError(f"{path}:{lineno}: NaN or inf in {quoted(' '.join(tokens))}")
        rows.append((lineno, values))
    return rows


def read_tum(
    path: str | os.PathLike[str], rotation_tolerance: float = ROTATION_TOLERANCE
) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps (N,), poses (N, 4, 4)) of a TUM file."""
    path = Path(path)
    stamps, poses = [], []
    for lineno, values in _rows(path, pose_format.TUM_COLUMNS, "t x y z qx qy qz qw"):
        problem = pose_format.quaternion_problem(values[4:8], rotation_tolerance)
        if problem is not None:
            raise TrajectoryFileError(f"{path}:{lineno}: {problem}")
        stamps.append(values[0])
        poses.append(pose_format.pose_from_translation_quaternion(values[1:4], values[4:8]))
    return np.asarray(stamps, dtype=np.float64), pose_format.stack_poses(poses)


def read_kitti(path: str | os.PathLike[str], rotation_tolerance: float = ROTATION_TOLERANCE) -> np.ndarray:
    """Poses (N, 4, 4) of a KITTI file."""
    path = Path(path)
    poses = []
    for lineno, values in _rows(path, pose_format.KITTI_COLUMNS, "3x4 row-major pose"):
        pose = pose_format.pose_from_kitti_row(values)
        problem = pose_format.pose_problem(pose, rotation_tolerance)
        if problem is not None:
            raise TrajectoryFileError(f"{path}:{lineno}: {problem}")
        pose[:3, :3] = pose_format.nearest_rotation(pose[:3, :3])
        poses.append(pose)
    return pose_format.stack_poses(poses)


def detect_format(path: str | os.PathLike[str]) -> TrajectoryFormat:
    """TUM or KITTI, from the number of values on the first data line."""
    path = Path(path)
    if not path.is_file():
        raise TrajectoryFileError(f"{path}: trajectory file not found")
    rows = pose_format.data_lines(read_text(path, TrajectoryFileError))
    if not rows:
        raise TrajectoryFileError(f"{path}: pose file has no data lines")
    lineno, tokens = rows[0]
    if len(tokens) == pose_format.TUM_COLUMNS:
        return "tum"
    if len(tokens) == pose_format.KITTI_COLUMNS:
        return "kitti"
    raise TrajectoryFileError(f"{path}:{lineno}: {len(tokens)} values; expected 8 (TUM) or 12 (KITTI)")


def _checked_poses(path: Path, poses: np.ndarray, rotation_tolerance: float) -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise TrajectoryFileError(f"{path}: poses to write have shape {poses.shape}, need (N, 4, 4)")
    for index, pose in enumerate(poses):
        problem = pose_format.pose_problem(pose, rotation_tolerance)
        if problem is not None:
            raise TrajectoryFileError(f"{path}: pose {index} not written: {problem}")
    return poses


def write_tum(
    path: str | os.PathLike[str],
    timestamps: np.ndarray,
    poses: np.ndarray,
    *,
    timestamp_decimals: int = 9,
    value_digits: int = 10,
    rotation_tolerance: float = ROTATION_TOLERANCE,
) -> Path:
    """Write a TUM file atomically (a header comment, quaternions with qw >= 0)."""
    path = Path(path)
    poses = _checked_poses(path, poses, rotation_tolerance)
    stamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    if len(stamps) != len(poses) or not np.all(np.isfinite(stamps)):
        raise TrajectoryFileError(f"{path}: need {len(poses)} finite timestamps, got {len(stamps)}")
    lines = pose_format.tum_lines(stamps, poses, f"{{:.{timestamp_decimals}f}}", f"{{:.{value_digits}g}}")
    return atomic_write_text(path, "".join(line + "\n" for line in [TUM_HEADER, *lines]))


def write_kitti(
    path: str | os.PathLike[str],
    poses: np.ndarray,
    *,
    value_digits: int = 10,
    rotation_tolerance: float = ROTATION_TOLERANCE,
) -> Path:
    """Write a KITTI file atomically."""
    path = Path(path)
    lines = pose_format.kitti_lines(_checked_poses(path, poses, rotation_tolerance), f"{{:.{value_digits}g}}")
    return atomic_write_text(path, "".join(line + "\n" for line in lines))
