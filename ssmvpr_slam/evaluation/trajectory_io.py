"""TUM and KITTI trajectory files, as evo reads and writes them.

TUM: one pose per line, ``t x y z qx qy qz qw`` (Hamilton quaternion, scalar last).
KITTI: one pose per line, the 12 row-major values of the top 3x4 of the 4x4 matrix.
``#`` comments and blank lines are skipped on read. Poses are 4x4 body-to-world.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ssmvpr_slam.backend.se3 import as_pose, as_pose_array, make_pose
from ssmvpr_slam.evaluation.atomic import atomic_write_text

TUM_FIELDS = 8
KITTI_FIELDS = 12
QUATERNION_NORM_TOL = 1e-3
"""A stored quaternion whose norm is off by more than this is treated as corrupt."""
KITTI_ROTATION_TOL = 1e-4
"""KITTI files round to ~6 significant digits; rotations within this are re-orthonormalised."""
NUMBER_FORMAT = "{:.9f}"
KITTI_NUMBER_FORMAT = "{:.9e}"


def _data_lines(path: Path) -> list[tuple[int, list[str]]]:
    if not path.is_file():
        raise FileNotFoundError(f"{path}: trajectory file not found")
    rows = []
    with path.open("r", encoding="utf-8") as handle:
        for lineno, line in enumerate(handle, start=1):
            stripped = line.strip()
            if not stripped or stripped.startswith("#"):
                continue
            rows.append((lineno, stripped.split()))
    return rows


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
    for lineno, fields in _data_lines(path):
        values = _numbers(path, lineno, fields, TUM_FIELDS, "t x y z qx qy qz qw")
        quat = values[4:8]
        norm = float(np.linalg.norm(quat))
        if abs(norm - 1.0) > QUATERNION_NORM_TOL:
            raise ValueError(f"{path}:{lineno}: quaternion norm is {norm:.6g}, expected 1")
        rot = Rotation.from_quat(quat / norm).as_matrix()  # scipy: (x, y, z, w)
        stamps.append(values[0])
        poses.append(make_pose(rot, values[1:4]))
    return np.asarray(stamps, dtype=np.float64), _stack(poses)


def write_tum(path: str | os.PathLike[str], timestamps: np.ndarray, poses: np.ndarray) -> Path:
    """Write a TUM file atomically; quaternions are stored with qw >= 0."""
    stamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    mats = as_pose_array("poses", poses)
    if len(stamps) != len(mats):
        raise ValueError(f"timestamps: {len(stamps)} stamps for {len(mats)} poses")
    if not np.all(np.isfinite(stamps)):
        raise ValueError("timestamps: contains NaN or inf")
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    for stamp, pose in zip(stamps, mats):
        quat = Rotation.from_matrix(pose[:3, :3]).as_quat()
        if quat[3] < 0:
            quat = -quat
        values = [stamp, *pose[:3, 3], *quat]
        lines.append(" ".join(NUMBER_FORMAT.format(v) for v in values))
    return atomic_write_text(path, "\n".join(lines) + "\n")


def read_kitti(path: str | os.PathLike[str]) -> np.ndarray:
    """Return poses (N, 4, 4) from a KITTI file."""
    path = Path(path)
    poses = []
    for lineno, fields in _data_lines(path):
        values = _numbers(path, lineno, fields, KITTI_FIELDS, "3x4 row-major")
        pose = np.eye(4)
        pose[:3, :4] = values.reshape(3, 4)
        poses.append(as_pose(f"{path}:{lineno}", pose, KITTI_ROTATION_TOL))
    return _stack(poses)


def write_kitti(path: str | os.PathLike[str], poses: np.ndarray) -> Path:
    """Write a KITTI file atomically."""
    mats = as_pose_array("poses", poses)
    lines = [
        " ".join(KITTI_NUMBER_FORMAT.format(v) for v in pose[:3, :4].reshape(-1)) for pose in mats
    ]
    return atomic_write_text(path, "\n".join(lines) + ("\n" if lines else ""))


def _stack(poses: list[np.ndarray]) -> np.ndarray:
    return np.stack(poses) if poses else np.zeros((0, 4, 4))
