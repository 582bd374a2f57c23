"""Reading and writing TUM and KITTI trajectory files for the front end.

The formats and pose conversions are :mod:`ssmvpr_common.poses`'s. Every reading error is a
:class:`~frontend.errors.FrontendInputError` naming the file and line, because a silently
skipped or mis-parsed pose corrupts every metric computed from the trajectory later. Writes
are atomic (temp file + ``os.replace``) so a crash never leaves half a trajectory behind.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from frontend.config import PoseFileConfig
from frontend.errors import FrontendInputError
from ssmvpr_common.atomic import atomic_write_text
from ssmvpr_common.poses import (
    KITTI_COLUMNS,
    TUM_COLUMNS,
    kitti_lines,
    nearest_rotation,
    pose_from_kitti_row,
    pose_from_translation_quaternion,
    pose_problem,
    quaternion_problem,
    stack_poses,
    tum_lines,
)
from ssmvpr_common.poses import data_lines as text_data_lines
from ssmvpr_common.text_files import read_text

PoseFormat = Literal["tum", "kitti"]


@dataclass
class PoseFile:
    """What a pose file held: timestamps exist for TUM only."""

    poses: np.ndarray  # (N, 4, 4)
    timestamps: np.ndarray | None  # (N,) seconds
    format: PoseFormat


def data_lines(path: Path) -> list[tuple[int, list[str]]]:
    """(line number, tokens) of each data line; an unreadable file is an input error naming it."""
    return text_data_lines(read_text(path, FrontendInputError))


def _floats(path: Path, lineno: int, tokens: list[str], expected: int, what: str) -> np.ndarray:
    if len(tokens) != expected:
        raise FrontendInputError(f"{path}:{lineno}: expected {expected} values ({what}), got {len(tokens)}")
    try:
        values = np.array([float(token) for token in tokens])
    except ValueError:
        raise FrontendInputError(f"{path}:{lineno}: non-numeric value in {what}") from None
    if not np.all(np.isfinite(values)):
        raise FrontendInputError(f"{path}:{lineno}: NaN or inf in {what}")
    return values


def read_tum(path: str | Path, config: PoseFileConfig | None = None) -> PoseFile:
    """Read a TUM trajectory; quaternions must be unit length within tolerance."""
    path, config = Path(path), config or PoseFileConfig()
    stamps, poses = [], []
    for lineno, tokens in data_lines(path):
        values = _floats(path, lineno, tokens, TUM_COLUMNS, "t x y z qx qy qz qw")
        problem = quaternion_problem(values[4:], config.rotation_tolerance)
        if problem is not None:
            raise FrontendInputError(f"{path}:{lineno}: {problem}")
        stamps.append(values[0])
        poses.append(pose_from_translation_quaternion(values[1:4], values[4:]))
    return PoseFile(stack_poses(poses), np.array(stamps, dtype=np.float64), "tum")


def read_kitti(path: str | Path, config: PoseFileConfig | None = None) -> PoseFile:
    """Read a KITTI trajectory; rotations must be orthonormal within tolerance."""
    path, config = Path(path), config or PoseFileConfig()
    poses = []
    for lineno, tokens in data_lines(path):
        values = _floats(path, lineno, tokens, KITTI_COLUMNS, "3x4 row-major pose")
        pose = pose_from_kitti_row(values)
        problem = pose_problem(pose, config.rotation_tolerance)
        if problem is not None:
            raise FrontendInputError(f"{path}:{lineno}: {problem}")
        pose[:3, :3] = nearest_rotation(pose[:3, :3])
        poses.append(pose)
    return PoseFile(stack_poses(poses), None, "kitti")


def detect_format(path: str | Path) -> PoseFormat:
    """TUM or KITTI, from the number of values on the first data line."""
    path = Path(path)
    rows = data_lines(path)
    if not rows:
        raise FrontendInputError(f"{path}: pose file has no data lines")
    lineno, tokens = rows[0]
    if len(tokens) == TUM_COLUMNS:
        return "tum"
    if len(tokens) == KITTI_COLUMNS:
        return "kitti"
    raise FrontendInputError(f"{path}:{lineno}: {len(tokens)} values; expected 8 (TUM) or 12 (KITTI)")


def read_poses(path: str | Path, format: PoseFormat | None = None, config: PoseFileConfig | None = None) -> PoseFile:
    """Read a TUM or KITTI file; the format is detected when not given."""
    format = format or detect_format(path)
    return read_tum(path, config) if format == "tum" else read_kitti(path, config)


def _checked_poses(path: Path, poses: np.ndarray, config: PoseFileConfig) -> np.ndarray:
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise FrontendInputError(f"{path}: poses to write have shape {poses.shape}, need (N,4,4)")
    for index, pose in enumerate(poses):
        problem = pose_problem(pose, config.rotation_tolerance)
        if problem is not None:
            raise FrontendInputError(f"{path}: pose {index} not written: {problem}")
    return poses


def write_tum(
    path: str | Path,
    timestamps: np.ndarray,
    poses: np.ndarray,
    config: PoseFileConfig | None = None,
) -> None:
    """Write a TUM trajectory (atomically)."""
    path, config = Path(path), config or PoseFileConfig()
    poses = _checked_poses(path, poses, config)
    timestamps = np.asarray(timestamps, dtype=np.float64).ravel()
    if len(timestamps) != len(poses) or not np.all(np.isfinite(timestamps)):
        raise FrontendInputError(f"{path}: need {len(poses)} finite timestamps, got {len(timestamps)}")
    stamp_format = f"{{:.{config.timestamp_decimals}f}}"
    lines = tum_lines(timestamps, poses, stamp_format, f"{{:.{config.value_digits}g}}")
    atomic_write_text(path, "".join(line + "\n" for line in lines))


def write_kitti(path: str | Path, poses: np.ndarray, config: PoseFileConfig | None = None) -> None:
    """Write a KITTI trajectory (atomically)."""
    path, config = Path(path), config or PoseFileConfig()
    poses = _checked_poses(path, poses, config)
    lines = kitti_lines(poses, f"{{:.{config.value_digits}g}}")
    atomic_write_text(path, "".join(line + "\n" for line in lines))
