"""Route files in their own conventions: KITTI camera poses, KITTI-style and TUM body poses.

A route file gives where a vehicle drove. Its frame convention decides which plane is the
ground: KITTI odometry ground truth describes camera 0 (x right, y down, z forward; the ground
is x-z), while TUM files and KITTI-format files written by LiDAR odometry (kiss-icp, this
project) describe a body frame (x forward, y left, z up; the ground is x-y). Reading a camera
file as a body file turns a city loop into a line, so the convention is detected from the
poses themselves: the direction of travel, seen in each pose's own frame, is +z for a camera
and +x for a body. A file that fits neither (or a degenerate path) is refused with one line
naming the file.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from frontend.errors import FrontendInputError
from frontend.poses_io import read_poses

PosesFrame = Literal["auto", "camera", "body"]

# Camera (x right, y down, z forward) -> body (x forward, y left, z up).
CAMERA_TO_BODY = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
# Share of the travelled distance that must lie along the detected forward axis.
_FORWARD_SHARE = 0.8
_MIN_LENGTH_M = 20.0


@dataclass(frozen=True)
class RouteFile:
    """Positions of a route file in a z-up world (x-y ground), and what was detected."""

    positions: np.ndarray  # (N, 3) metres, z up
    timestamps: np.ndarray | None
    frame: Literal["camera", "body"]
    file_format: Literal["tum", "kitti"]

    @property
    def length(self) -> float:
        return float(np.linalg.norm(np.diff(self.positions, axis=0), axis=1).sum())


def detect_frame(rotations: np.ndarray, positions: np.ndarray) -> Literal["camera", "body"] | None:
    """Which local axis the vehicle travels along: +z (camera), +x (body), or None (neither)."""
    step = np.diff(positions, axis=0)
    dist = np.linalg.norm(step, axis=1)
    moving = dist > 1e-3
    if not moving.any():
        return None
    local = np.einsum("nji,nj->ni", rotations[:-1][moving], step[moving])  # R^T d
    total = dist[moving].sum()
    if local[:, 2].sum() >= _FORWARD_SHARE * total:
        return "camera"
    if local[:, 0].sum() >= _FORWARD_SHARE * total:
        return "body"
    return None


def read_route_file(path: str | Path, fmt: str = "auto", frame: PosesFrame = "auto") -> RouteFile:
    """Read a TUM (``t x y z qx qy qz qw``) or KITTI (3x4 row-major) poses file as a route.

    ``frame`` says which convention the poses use; ``auto`` detects it from the direction of
    travel. Raises TrajectoryFileError naming file:line on a line that is no pose, and
    FrontendInputError naming the file on a route that cannot be driven.
    """
    path = Path(path)
    if fmt not in ("auto", "tum", "kitti"):
        raise FrontendInputError(f"poses file {path}: unknown format {fmt!r} (tum | kitti | auto)")
    read = read_poses(path, None if fmt == "auto" else fmt)  # type: ignore[arg-type]
    if not len(read.poses):
        raise FrontendInputError(f"poses file {path}: no poses")
    stamps, pos, rot = read.timestamps, read.poses[:, :3, 3], read.poses[:, :3, :3]
    fmt = read.format
    if len(pos) < 2 or np.ptp(pos, axis=0).max() < 1e-6:
        raise FrontendInputError(f"poses file {path}: every pose is the same; the path does not move")
    detected = detect_frame(rot, pos)
    if frame == "auto":
        if detected is None:
            raise FrontendInputError(
                f"poses file {path}: fits neither a camera convention (travel along +z, KITTI ground truth) "
                "nor a body convention (travel along +x, TUM / LiDAR odometry); set route.poses_frame"
            )
        frame = detected
    if frame == "camera":
        pos = pos @ CAMERA_TO_BODY.T
    elif frame != "body":
        raise FrontendInputError(f"poses file {path}: unknown poses frame {frame!r} (camera | body | auto)")
    pos = pos - pos[0] * np.array([0.0, 0.0, 1.0])  # heights relative to the start
    route = RouteFile(positions=pos, timestamps=stamps, frame=frame, file_format=fmt)  # type: ignore[arg-type]
    if route.length < _MIN_LENGTH_M:
        raise FrontendInputError(
            f"poses file {path}: the path is {route.length:.1f} m long; a route needs at least {_MIN_LENGTH_M:.0f} m"
        )
    return route
