"""Odometry: kiss-icp on LiDAR scans, or poses logged with the traverse (with drift)."""

from __future__ import annotations

from frontend.config import OdometryConfig, PoseFileConfig
from frontend.odometry.base import Odometry, OdometryStats
from frontend.odometry.factory import choose_odometry, make_in_process
from frontend.odometry.kiss_icp import KissIcpOdometry
from frontend.odometry.logged import DriftModel, LoggedPoseOdometry
from frontend.odometry.own_process import OdometryProcess, OdometryProcessError


def make_odometry(
    config: OdometryConfig | None = None,
    pose_config: PoseFileConfig | None = None,
    own_process: bool = False,
    kept_voxel: float | None = None,
) -> Odometry:
    """The odometry ``config.kind`` names (``auto`` must first be resolved by `choose_odometry`).

    own_process: run it in a process of its own (`OdometryProcess`), so that threads beside it
    are not held up by kiss-icp, which keeps the GIL while it registers a scan. kept_voxel: the
    voxel size the caller keeps scans at (`KissIcpOdometry`)."""
    config = config or OdometryConfig(kind="kiss_icp")
    if own_process and config.kind != "auto":
        return OdometryProcess(config, pose_config, kept_voxel)
    return make_in_process(config, pose_config, kept_voxel)


__all__ = [
    "DriftModel",
    "KissIcpOdometry",
    "LoggedPoseOdometry",
    "Odometry",
    "OdometryProcess",
    "OdometryProcessError",
    "OdometryStats",
    "choose_odometry",
    "make_odometry",
]
