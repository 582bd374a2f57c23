"""Which odometry a log gets and building it in this process: what `make_odometry` and the
odometry's own process (`own_process`) both build from, so neither imports the other."""

from __future__ import annotations

from frontend.config import OdometryConfig, PoseFileConfig
from frontend.errors import FrontendInputError
from frontend.odometry.base import Odometry
from frontend.odometry.kiss_icp import KissIcpOdometry
from frontend.odometry.logged import LoggedPoseOdometry


def choose_odometry(config: OdometryConfig, topics: dict[str, str], log: str) -> OdometryConfig:
    """The odometry config for a log with these streams (a Source's ``topics``): ``auto`` becomes
    kiss-icp when there are scans and the logged poses otherwise. An odometry the log cannot
    feed is refused here, naming the log, instead of running with a pose that never moves."""
    streams = ", ".join(sorted(topics)) or "none"
    pose_role = "gt_pose" if config.logged.pose_source == "gt" else "logged_pose"
    # poses read as ground truth only (an image folder's poses file by default): say how to drive with them
    hint = (
        "; its poses are read as ground truth: to take odometry from them set "
        "frontend.odometry.logged.pose_source: gt (an image folder: `run --pose-role logged`, or both to "
        "evaluate against them too)"
        if pose_role == "logged_pose" and "gt_pose" in topics
        else ""
    )
    kind = config.kind
    if kind == "auto":
        if "lidar" in topics:
            kind = "kiss_icp"
        elif pose_role in topics:
            kind = "logged"
        else:
            raise FrontendInputError(
                f"{log}: no LiDAR scans and no logged poses to take odometry from (streams: {streams}){hint}"
            )
    if kind == "kiss_icp" and "lidar" not in topics:
        raise FrontendInputError(
            f"{log}: kiss-icp odometry needs LiDAR scans and the log has none (streams: {streams}); "
            "try --odometry logged"
        )
    if kind == "logged" and pose_role not in topics:
        raise FrontendInputError(f"{log}: logged odometry needs a {pose_role} stream (streams: {streams}){hint}")
    return config.model_copy(update={"kind": kind})


def make_in_process(
    config: OdometryConfig, pose_config: PoseFileConfig | None = None, kept_voxel: float | None = None
) -> Odometry:
    """The odometry ``config.kind`` names (``auto`` resolved first), built in this process
    (kept_voxel: see `KissIcpOdometry`)."""
    if config.kind == "auto":
        raise FrontendInputError("odometry kind 'auto' depends on the log: resolve it with choose_odometry first")
    if config.kind == "kiss_icp":
        return KissIcpOdometry(config.kiss_icp, kept_voxel)
    return LoggedPoseOdometry(config.logged, pose_config)
