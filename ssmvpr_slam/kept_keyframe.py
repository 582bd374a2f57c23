"""What a run keeps of a keyframe once its full images have been encoded.

Full camera images are megabytes a keyframe; a run keeps what its later stages need instead:
the poses, the voxelised scan where there is one (ICP registers loops between scans), grey
copies of the images within a pixel budget where there is none (two-view registration needs
them), and a JPEG thumbnail when trajectory.mcap is written."""

from __future__ import annotations

import numpy as np

from frontend.frame import Frame
from frontend.odometry.base import Odometry
from ssmvpr_slam.backend.kept_scan import keep_scan
from ssmvpr_slam.backend.two_view import reduce_image
from ssmvpr_slam.config.slam import SlamConfig
from ssmvpr_slam.run_result import Keyframe
from ssmvpr_slam.thumbnail import thumbnail_jpeg


def keep_keyframe(frame: Frame, pose: np.ndarray, keyframe_id: int, config: SlamConfig, odometry: Odometry) -> Keyframe:
    """The keyframe as the run keeps it (see the module docstring); `frame` must have an image."""
    assert frame.image is not None
    pipeline = config.pipeline
    scan = None
    if (voxel := kept_voxel(config)) is not None:
        scan = keep_scan(scan_of(frame, odometry), voxel, voxelised=getattr(odometry, "last_scan_voxel", None) == voxel)
    image = rear = None
    if scan is None:
        image = reduce_image(frame.image, pipeline.keyframe_image_pixels, f"keyframe {keyframe_id} image")
        if frame.rear_image is not None:
            rear = reduce_image(frame.rear_image, pipeline.keyframe_image_pixels, f"keyframe {keyframe_id} rear image")
    thumbnail = None
    if config.results.mcap:
        name = f"keyframe {keyframe_id} (frame {frame.index})"
        thumbnail = thumbnail_jpeg(frame.image, config.results.mcap_thumbnail_width, name)
    return Keyframe(
        id=keyframe_id,
        frame_index=frame.index,
        timestamp=frame.timestamp,
        odom_pose=np.array(pose, dtype=np.float64),
        gt_pose=None if frame.gt_pose is None else np.array(frame.gt_pose, dtype=np.float64),
        scan=scan,
        image=image,
        rear_image=rear,
        thumbnail=thumbnail,
    )


def kept_voxel(config: SlamConfig) -> float | None:
    """The voxel size (m) a keyframe's scan is kept at for loop registration (None: no scans kept)."""
    if not config.pipeline.use_lidar_for_loops:
        return None
    lidar = config.backend.registration.lidar
    return lidar.voxel_size * lidar.map_downsample_factor


def scan_of(frame: Frame, odometry: Odometry) -> np.ndarray | None:
    """The odometry's motion-compensated scan when it has one (kiss-icp), else the raw one."""
    deskewed = getattr(odometry, "last_scan", None)
    return deskewed if deskewed is not None else frame.points
