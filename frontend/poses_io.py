"""A pose file beside a log's images or route, read with the front end's settings.

The formats, the checks and the one error type (`TrajectoryFileError`, naming file:line) are
`ssmvpr_common.trajectory_io`'s; this adds what the front end asks of a pose file: the format
detected when not given, and the tolerance from `frontend.pose_files` (`PoseFileConfig`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from frontend.config import PoseFileConfig
from ssmvpr_common.trajectory_io import TrajectoryFormat, detect_format, read_kitti, read_tum


@dataclass
class PoseFile:
    """What a pose file held: timestamps exist for TUM only."""

    poses: np.ndarray  # (N, 4, 4)
    timestamps: np.ndarray | None  # (N,) seconds
    format: TrajectoryFormat


def read_poses(
    path: str | Path, format: TrajectoryFormat | None = None, config: PoseFileConfig | None = None
) -> PoseFile:
    """Read a TUM or KITTI file; the format is detected when not given."""
    tolerance = (config or PoseFileConfig()).rotation_tolerance
    format = format or detect_format(path)
    if format == "tum":
        stamps, poses = read_tum(path, tolerance)
        return PoseFile(poses, stamps, "tum")
    return PoseFile(read_kitti(path, tolerance), None, "kitti")
