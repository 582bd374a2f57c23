"""TUM and KITTI trajectory files, as evo reads and writes them.

TUM: one pose per line, ``t x y z qx qy qz qw`` (Hamilton quaternion, scalar last).
KITTI: one pose per line, the 12 row-major values of the top 3x4 of the 4x4 matrix.
``#`` comments and blank lines are skipped on read. Poses are 4x4 body-to-world.

Line scanning, quaternion and matrix conversions and line formatting are
:mod:`ssmvpr_common.poses`'s; on top of them this module keeps the evaluation's contract:
`FileNotFoundError` for a missing file, plain `ValueError` wording, the back end's pose
checks (`as_pose`, tighter rotation tolerance, rotations re-orthonormalised), a header line
and fixed 9-decimal numbers in TUM files, 10 significant digits in KITTI files.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from ssmvpr_common import poses as pose_format
from ssmvpr_common.atomic import atomic_write_text
from ssmvpr_common.text_files import read_text
from ssmvpr_slam.backend.se3 import as_pose, as_pose_array

TUM_FIELDS = pose_format.TUM_COLUMNS
KITTI_FIELDS = pose_format.KITTI_COLUMNS
QUATERNION_NORM_TOL = 1e-3
"""A stored quaternion whose norm is off by more than this is treated as corrupt."""
KITTI_ROTATION_TOL = 1e-4
"""KITTI files round to ~6 significant digits; rotations within this are re-orthonormalised."""
NUMBER_FORMAT = "{:.9f}"
KITTI_NUMBER_FORMAT = "{:.9e}"
TUM_HEADER = "# timestamp tx ty tz qx qy qz qw"


def _rows(path: Path, expected: int, fmt: str) -> Iterator[tuple[int, np.ndarray]]:
    """(line number, values) of each data line, each checked to hold `expected` numbers."""
    if not path.is_file():
        raise FileNotFoundError(f"{path}: trajectory file not found")
    for lineno, fields in pose_format.data_lines(read_text(path, ValueError)):
        yield lineno, _numbers(path, lineno, fields, expected, fmt)


def _numbers(path: Path, lineno: int, fields: list[str], expected: int, fmt: str) -> np.ndarray:
    if len(fields) != expected:
        raise ValueError(f"{path}:{lineno}: expected {expected} numbers ({fmt}), got {len(fields)}")
    try:
        values = np.array([float(f) for f in fields])
    except ValueError:
        raise ValueError(f"{path}:{lineno}: not a number in {' '.join(fields)!r}") from None
    if not np.all(np.isfinite(values)):
        raise ValueError(f"{path}:{lineno}: NaN or inf in {' '.join(fields)!r}")
    return values


def read_tum(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Return (timestamps (N,), poses (N, 4, 4)) from a TUM file."""
    path = Path(path)
    stamps, poses = [], []
    for lineno, values in _rows(path, TUM_FIELDS, "t x y z qx qy qz qw"):
        problem = pose_format.quaternion_problem(values[4:8], QUATERNION_NORM_TOL)
        if problem is not None:
            raise ValueError(f"{path}:{lineno}: {problem}")
        stamps.append(values[0])
        poses.append(pose_format.pose_from_translation_quaternion(values[1:4], values[4:8]))
    return np.asarray(stamps, dtype=np.float64), pose_format.stack_poses(poses)


def write_tum(path: str | os.PathLike[str], timestamps: np.ndarray, poses: np.ndarray) -> Path:
    """Write a TUM file atomically; quaternions are stored with qw >= 0."""
    stamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    mats = as_pose_array("poses", poses)
    if len(stamps) != len(mats):
        raise ValueError(f"timestamps: {len(stamps)} stamps for {len(mats)} poses")
    if not np.all(np.isfinite(stamps)):
        raise ValueError("timestamps: contains NaN or inf")
    lines = [TUM_HEADER, *pose_format.tum_lines(stamps, mats, NUMBER_FORMAT, NUMBER_FORMAT)]
    return atomic_write_text(path, "".join(line + "\n" for line in lines))


def read_kitti(path: str | os.PathLike[str]) -> np.ndarray:
    """Return poses (N, 4, 4) from a KITTI file."""
    path = Path(path)
    poses = [
        as_pose(f"{path}:{lineno}", pose_format.pose_from_kitti_row(values), KITTI_ROTATION_TOL)
        for lineno, values in _rows(path, KITTI_FIELDS, "3x4 row-major")
    ]
    return pose_format.stack_poses(poses)


def write_kitti(path: str | os.PathLike[str], poses: np.ndarray) -> Path:
    """Write a KITTI file atomically."""
    lines = pose_format.kitti_lines(as_pose_array("poses", poses), KITTI_NUMBER_FORMAT)
    return atomic_write_text(path, "".join(line + "\n" for line in lines))
