"""Odometry: kiss-icp on LiDAR scans, or poses logged with the traverse (with drift)."""

from __future__ import annotations

from frontend.config import OdometryConfig, PoseFileConfig
from frontend.odometry.base import Odometry, OdometryStats
from frontend.odometry.kiss_icp import KissIcpOdometry
from frontend.odometry.logged import DriftModel, LoggedPoseOdometry


def make_odometry(
    config: OdometryConfig | None = None, pose_config: PoseFileConfig | None = None
) -> Odometry:
    """The odometry ``config.kind`` names."""
    config = config or OdometryConfig()
    if config.kind == "kiss_icp":
        return KissIcpOdometry(config.kiss_icp)
    return LoggedPoseOdometry(config.logged, pose_config)


__all__ = [
    "DriftModel",
    "KissIcpOdometry",
    "LoggedPoseOdometry",
    "Odometry",
    "OdometryStats",
    "make_odometry",
]
