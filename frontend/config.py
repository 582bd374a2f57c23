"""Every tunable of the front end, as pydantic models (kiss-icp's config style).

The application nests :class:`FrontendConfig` in its own settings; each sub-model can also
be used on its own (``McapSourceConfig()``, ``KissIcpConfig(voxel_size=0.5)``). Unknown
keys are rejected so that a typo in a YAML preset fails loudly instead of being ignored.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from ssmvpr_common.settings_model import SettingsModel

# Topic value meaning "do not read / write this stream at all".
TOPIC_OFF = ""


# --------------------------------------------------------------------------- sources


class McapWriterConfig(SettingsModel):
    """How :class:`~frontend.sources.mcap_writer.McapFrameWriter` lays out a log."""

    camera_topic: str = Field("/camera/image_raw", description="forward camera images when image_format is raw (Image)")
    compressed_camera_topic: str = Field(
        "/camera/image_raw/compressed", description="forward camera images when jpeg or png (CompressedImage)"
    )
    rear_camera_topic: str = Field("/camera_rear/image_raw", description="rear camera images when raw (Image)")
    compressed_rear_camera_topic: str = Field(
        "/camera_rear/image_raw/compressed", description="rear camera images when jpeg or png (CompressedImage)"
    )
    camera_info_topic: str = Field(
        "/camera/camera_info", description="forward camera calibration (CameraInfo), when the writer is given one"
    )
    rear_camera_info_topic: str = Field(
        "/camera_rear/camera_info", description="rear camera calibration (CameraInfo), when the writer is given one"
    )
    lidar_topic: str = Field("/lidar/points", description="LiDAR scans (PointCloud2)")
    odom_topic: str = Field("/odom", description="logged poses (Odometry)")
    gt_topic: str = Field("/ground_truth", description="ground-truth poses (PoseStamped)")
    image_format: Literal["raw", "jpeg", "png"] = Field(
        "raw", description="camera images as raw rgb8 Image, or JPEG / PNG CompressedImage"
    )
    jpeg_quality: int = Field(90, ge=1, le=100, description="OpenCV JPEG quality of jpeg images")
    png_compression: int = Field(3, ge=0, le=9, description="OpenCV PNG compression level of png images")
    world_frame_id: str = Field("map", description="frame_id of the pose messages (the fixed world frame)")
    body_frame_id: str = Field("base_link", description="child_frame_id of the odometry messages")
    camera_frame_id: str = Field("camera", description="frame_id of the forward camera's images")
    rear_camera_frame_id: str = Field("camera_rear", description="frame_id of the rear camera's images")
    lidar_frame_id: str = Field("lidar", description="frame_id of the point clouds")
    chunk_size: int = Field(1024 * 1024, gt=0, description="bytes per MCAP chunk")
    compression: Literal["zstd", "lz4", "none"] = Field("zstd", description="compression of the MCAP chunks")
    rotation_tolerance: float = Field(1e-3, gt=0.0, description="a pose whose |R^T R - I| exceeds this is refused")


class McapSourceConfig(SettingsModel):
    """How an MCAP log is read and its streams associated into frames.

    A topic left ``None`` is found by message type; ``""`` switches the stream off.
    """

    camera_topic: str | None = Field(None, description="forward camera (Image or CompressedImage)")
    rear_camera_topic: str | None = Field(
        None, description="backward-looking camera; None = the writer's rear topic names only (never by type)"
    )
    camera_info_topic: str | None = Field(
        None,
        description="forward camera calibration (CameraInfo); None = the one beside the camera topic "
        "(/camera/image_raw or /camera/image_raw/compressed -> /camera/camera_info)",
    )
    rear_camera_info_topic: str | None = Field(
        None, description="rear camera calibration (CameraInfo); None = the one beside the rear camera topic"
    )
    lidar_topic: str | None = Field(None, description="LiDAR scans (PointCloud2)")
    odom_topic: str | None = Field(None, description="logged poses (found by type: Odometry)")
    gt_topic: str | None = Field(None, description="ground-truth poses (found by type: PoseStamped)")
    drive: Literal["auto", "camera", "lidar"] = Field(
        "auto", description="stream whose messages become frames; auto = camera if present"
    )
    association_tolerance_s: float = Field(
        0.05, ge=0.0, description="max |dt| between a frame and an associated message"
    )
    max_latency_s: float = Field(
        0.5,
        ge=0.0,
        description="how far (in stamp time) other streams may lag the driving stream",
    )
    max_pending_frames: int = Field(64, ge=1, description="frames held while waiting")
    max_buffered_messages: int = Field(64, ge=2, description="per-stream look-back buffer")
    use_header_stamp: bool = Field(
        True, description="time messages by header.stamp; log time for the whole log when a topic's first stamp is 0"
    )
    strict: bool = Field(True, description="truncated/corrupt log: raise (True) or warn once and stop (False)")
    skip_undecodable_images: bool = Field(
        True, description="bad image: count it, keep the frame's other sensors (False: stop)"
    )
    max_time_gap_s: float = Field(5.0, gt=0.0, description="a stream's time leaping further forward is warned about")


class KittiSourceConfig(SettingsModel):
    """A KITTI odometry sequence folder (``sequences/XX``)."""

    camera: Literal["auto", "image_2", "image_0", "none"] = Field(
        "auto", description="image folder to read; auto = image_2 (colour) if present, else image_0"
    )
    load_points: bool = Field(True, description="read the velodyne/ scans (False: camera only)")
    poses_file: str | None = Field(None, description="explicit ground-truth poses file")
    gt_frame: Literal["auto", "lidar", "camera"] = Field(
        "auto", description="body frame of gt_pose; auto = lidar when velodyne/ exists"
    )
    max_time_gap_s: float = Field(5.0, gt=0.0, description="a time leaping further forward is warned about")


class FolderSourceConfig(SettingsModel):
    """A folder of images with an optional TUM or KITTI poses file."""

    image_dir: str | None = Field(None, description="sub-folder with the images (auto)")
    poses_file: str | None = Field(None, description="poses file (auto: poses.txt, ...)")
    times_file: str | None = Field(None, description="one timestamp per image (auto)")
    pose_role: Literal["gt", "logged", "both"] = Field(
        "gt", description="the poses file gives the ground truth, the logged odometry, or both"
    )
    association_tolerance_s: float = Field(
        0.02, ge=0.0, description="image time vs TUM pose time, when both are timestamps"
    )
    max_time_gap_s: float = Field(5.0, gt=0.0, description="a time leaping further forward is warned about")
    frame_period_s: float = Field(0.1, gt=0.0, description="timestamp step when no times are known")


class SourceConfig(SettingsModel):
    """Which data source :func:`~frontend.sources.open_source` builds, and its settings."""

    kind: Literal["auto", "mcap", "rosbag", "kitti", "folder"] = Field(
        "auto", description="source type; auto = detected from the path's suffix and contents"
    )
    mcap: McapSourceConfig = Field(
        default_factory=McapSourceConfig, description="MCAP logs and ROS 1 / ROS 2 bags: topics, association, clock"
    )
    kitti: KittiSourceConfig = Field(default_factory=KittiSourceConfig)
    folder: FolderSourceConfig = Field(default_factory=FolderSourceConfig)


# --------------------------------------------------------------------------- odometry


class KissIcpConfig(SettingsModel):
    """kiss-icp's ``KISSConfig`` fields, flattened, plus our input guards."""

    max_range: float = Field(100.0, gt=0.0, description="m; farther returns are dropped")
    min_range: float = Field(0.5, ge=0.0, description="nearer returns are the vehicle itself or a driver's placeholder")
    deskew: bool = Field(True, description="used only when a scan has real per-point times")
    voxel_size: float | None = Field(None, gt=0.0, description="None: max_range / 100")
    max_points_per_voxel: int = Field(
        10,
        ge=1,
        description="points kept per voxel of the local map; kiss-icp's own default is 20. 10, with the 1e-3 "
        "convergence below, halves kiss-icp's CPU a scan on the simulated demo and KITTI 06 routes at the same or "
        "better odometry ATE, and registers the real KITTI pairs as closely (docs/slam_demo.md)",
    )
    max_num_iterations: int = Field(500, ge=1, description="ICP iterations per scan at most")
    convergence_criterion: float = Field(
        1e-3, gt=0.0, description="ICP stops once a pose update's norm is below this; kiss-icp's own default is 1e-4"
    )
    max_num_threads: int = Field(
        8,
        ge=0,
        description="Threads of its registration, at most the cores (0 = all cores). On a 16-core GPU machine one "
        "demo scan took 82 / 55 / 39 ms on 4 / 8 / 16 threads (kiss-icp's own 20 points and 1e-4), and a whole "
        "run went from 6.3 to 8.1 keyframes/s at 8 (docs/streaming.md). kiss-icp fixes one cap per process at its "
        "first registration "
        "(frontend/odometry/kiss_threads.py): where the odometry runs in the main process (pipeline.overlap "
        "off), the first built of this and backend.registration.lidar.max_num_threads counts for both",
    )
    fixed_threshold: float | None = Field(
        None, gt=0.0, description="m; constant correspondence threshold sigma; None: kiss-icp's adaptive one"
    )
    initial_threshold: float = Field(
        2.0, gt=0.0, description="m; adaptive threshold sigma until motions above min_motion_th are seen"
    )
    min_motion_th: float = Field(
        0.1, ge=0.0, description="m; smaller model deviations do not update the adaptive threshold"
    )
    min_points: int = Field(20, ge=1, description="fewer valid in-range points: skip the scan, predict the pose")
    predict_on_skip: bool = Field(True, description="skipped scan: constant-velocity prediction (else hold the pose)")

    @model_validator(mode="after")
    def _check_ranges(self) -> KissIcpConfig:
        if self.min_range >= self.max_range:
            raise ValueError(f"min_range {self.min_range} must be < max_range {self.max_range}")
        return self


class DriftConfig(SettingsModel):
    """Seeded drift injected into logged poses, so loop closures have something to fix.

    Per step of length d metres: translation scaled by (1 + translation_scale_error),
    yaw rotated by yaw_bias_per_m * d, and Gaussian random walks whose standard deviations
    grow with sqrt(d).
    """

    enabled: bool = Field(False, description="inject this drift into the poses used as odometry")
    seed: int = Field(0, ge=0, le=2**32 - 1, description="of numpy's generator (0 .. 2**32 - 1)")
    translation_scale_error: float = Field(0.0, gt=-1.0, description="relative error of each step's length")
    yaw_bias_per_m: float = Field(0.0, description="rad per metre travelled")
    yaw_axis: Literal["x", "y", "z"] = Field(
        "z", description="body axis of yaw: z for z-up robots, y for KITTI's camera frame"
    )
    translation_noise_per_sqrt_m: float = Field(0.0, ge=0.0, description="m / sqrt(m)")
    rotation_noise_per_sqrt_m: float = Field(0.0, ge=0.0, description="rad / sqrt(m)")


class LoggedOdometryConfig(SettingsModel):
    """Odometry read from the log's poses (optionally degraded by :class:`DriftConfig`)."""

    pose_source: Literal["logged", "gt"] = Field(
        "logged", description="frame poses used as odometry: the logged ones or the ground truth"
    )
    drift: DriftConfig = Field(default_factory=DriftConfig)


class OdometryConfig(SettingsModel):
    """Which odometry :func:`~frontend.odometry.make_odometry` builds."""

    kind: Literal["auto", "kiss_icp", "logged"] = Field(
        "auto", description="auto: kiss-icp when the log has LiDAR scans, else the logged poses"
    )
    kiss_icp: KissIcpConfig = Field(default_factory=KissIcpConfig)
    logged: LoggedOdometryConfig = Field(default_factory=LoggedOdometryConfig)


# --------------------------------------------------------------------------- pose files


class PoseFileConfig(SettingsModel):
    """Reading and writing TUM / KITTI trajectory files (:mod:`frontend.poses_io`, :mod:`ssmvpr_common.trajectory_io`)."""

    rotation_tolerance: float = Field(
        1e-3, gt=0.0, description="max |R^T R - I| (or |q| - 1) before a line is rejected"
    )


# --------------------------------------------------------------------------- keyframes


class KeyframeConfig(SettingsModel):
    """A frame becomes a keyframe when any enabled threshold is reached (None = off)."""

    min_distance_m: float | None = Field(1.0, gt=0.0, description="m moved since the last keyframe")
    min_angle_deg: float | None = Field(10.0, gt=0.0, description="deg turned (rotation angle) since the last keyframe")
    max_interval_s: float | None = Field(None, gt=0.0, description="s elapsed since the last keyframe")


class FrontendConfig(SettingsModel):
    """Everything the front end needs; nested into the application's settings."""

    source: SourceConfig = Field(default_factory=SourceConfig)
    writer: McapWriterConfig = Field(
        default_factory=lambda: McapWriterConfig(image_format="jpeg"),
        description="how `simulate` and `demo` write logs: camera images as JPEG (CompressedImage), "
        "a third smaller with the same loops and ATE",
    )
    odometry: OdometryConfig = Field(default_factory=OdometryConfig)
    keyframes: KeyframeConfig = Field(default_factory=KeyframeConfig)
    pose_files: PoseFileConfig = Field(default_factory=PoseFileConfig)
