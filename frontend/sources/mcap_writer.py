"""Write Frames as a standard ROS 2 MCAP log (opens in Foxglove, reads back with McapSource).

Schemas are ros2msg text, messages CDR. The log is written to a temp file beside the
target and renamed into place on a clean close, so an interrupted run never leaves a
truncated log under the final name.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterable, Mapping
from pathlib import Path
from types import TracebackType
from typing import Any

import cv2
import numpy as np
from mcap.records import Schema
from mcap.writer import CompressionType
from mcap_ros2.writer import Writer

from frontend.config import McapWriterConfig
from frontend.errors import FrontendInputError
from frontend.frame import Frame
from frontend.sources import ros_convert, ros_msgdefs
from frontend.sources.intrinsics import CameraIntrinsics
from ssmvpr_common.atomic import default_file_mode
from ssmvpr_common.disk_full import writing
from ssmvpr_common.poses import pose_problem

_COMPRESSION = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
}


class McapFrameWriter:
    """Context manager: ``with McapFrameWriter(path) as w: w.write(frame)``.

    Camera -> ``camera_topic`` (Image rgb8) or ``compressed_camera_topic`` (CompressedImage
    jpeg/png), points -> ``lidar_topic`` (PointCloud2, float32 x y z [t]), logged pose ->
    ``odom_topic`` (Odometry), gt pose -> ``gt_topic`` (PoseStamped). Absent Frame fields
    are not written. Frame timestamps become both header stamps and log times.

    ``intrinsics`` (camera role ``camera`` / ``rear_camera`` -> its calibration, e.g. a Source's
    :attr:`~frontend.sources.base.Source.intrinsics`) adds a CameraInfo on ``camera_info_topic`` /
    ``rear_camera_info_topic`` beside each image of that camera, as a ROS driver publishes it.
    """

    def __init__(
        self,
        path: str | Path,
        config: McapWriterConfig | None = None,
        intrinsics: Mapping[str, CameraIntrinsics] | None = None,
    ) -> None:
        self.path = Path(path)
        self.config = config or McapWriterConfig()
        self.intrinsics = dict(intrinsics or {})
        unknown = set(self.intrinsics) - {"camera", "rear_camera"}
        if unknown:
            raise ValueError(f"intrinsics for unknown camera role(s) {sorted(unknown)}; roles: camera, rear_camera")
        self.frames_written = 0
        self._last_time: float | None = None
        self._tmp_path: Path | None = None
        self._file: Any = None
        self._writer: Writer | None = None
        self._schemas: dict[str, Schema] = {}

    # ---------------------------------------------------------------- lifecycle

    def open(self) -> McapFrameWriter:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=self.path.parent, prefix=f".{self.path.name}.", suffix=".tmp")
        self._tmp_path = Path(tmp)
        self._file = os.fdopen(fd, "wb")
        self._writer = Writer(
            self._file,
            chunk_size=self.config.chunk_size,
            compression=_COMPRESSION[self.config.compression],
        )
        return self

    def close(self) -> None:
        """Finish the log and move it to its final name."""
        if self._writer is None or self._tmp_path is None:
            return
        try:
            with writing(self.path):  # a full disk: one error naming the log
                self._writer.finish()
                self._file.flush()
                os.fsync(self._file.fileno())
                self._file.close()
            os.chmod(self._tmp_path, default_file_mode())
            os.replace(self._tmp_path, self.path)
        except BaseException:  # e.g. the target is a folder: no temp file is left behind
            self.abort()
            raise
        self._writer = None

    def abort(self) -> None:
        """Drop the partial log (nothing appears under the final name)."""
        if self._file is not None and not self._file.closed:
            self._file.close()
        if self._tmp_path is not None:
            self._tmp_path.unlink(missing_ok=True)
        self._writer = None

    def __enter__(self) -> McapFrameWriter:
        return self.open()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

    # ---------------------------------------------------------------- writing

    def _schema(self, datatype: str) -> Schema:
        assert self._writer is not None, "write() checks that the log is open"
        if datatype not in self._schemas:
            self._schemas[datatype] = self._writer.register_msgdef(datatype, ros_msgdefs.MSGDEFS[datatype])
        return self._schemas[datatype]

    def _put(self, topic: str, datatype: str, message: dict[str, Any], nanoseconds: int) -> None:
        assert self._writer is not None, "write() checks that the log is open"
        with writing(self.path):  # a chunk is written out as it fills: a full disk names the log
            self._writer.write_message(
                topic, self._schema(datatype), message, log_time=nanoseconds, publish_time=nanoseconds
            )

    def _fail(self, frame: Frame, why: str) -> FrontendInputError:
        return FrontendInputError(f"{self.path}: frame {frame.index} not written: {why}")

    def write_message(self, topic: str, datatype: str, message: dict[str, Any], seconds: float) -> None:
        """Append one message of a type `ros_msgdefs.MSGDEFS` defines (results, not frames)."""
        if self._writer is None:
            raise RuntimeError("McapFrameWriter.write_message called outside 'with' (or after close)")
        self._put(topic, datatype, message, ros_convert.seconds_to_nanoseconds(seconds))

    def write(self, frame: Frame) -> None:
        """Append one frame; timestamps must be non-negative and increasing."""
        if self._writer is None:
            raise RuntimeError("McapFrameWriter.write called outside 'with' (or after close)")
        cfg = self.config
        t = float(frame.timestamp)
        try:
            ns = ros_convert.seconds_to_nanoseconds(t)
        except ValueError as error:
            raise self._fail(frame, str(error)) from None
        if self._last_time is not None and t <= self._last_time:
            raise self._fail(frame, f"timestamp {t} is not after the previous {self._last_time}")
        self._last_time = t

        if frame.image is not None:
            self._write_image(frame, frame.image, t, ns, rear=False)
        if frame.rear_image is not None:
            self._write_image(frame, frame.rear_image, t, ns, rear=True)
        if frame.points is not None:
            points = np.asarray(frame.points, dtype=np.float64)
            if points.ndim != 2 or points.shape[1] != 3:
                raise self._fail(frame, f"points have shape {points.shape}, expected (N, 3)")
            times = frame.point_times
            if times is not None and len(times) != len(points):
                raise self._fail(frame, f"{len(times)} point_times for {len(points)} points")
            msg = ros_convert.point_cloud_message(points, times, t, cfg.lidar_frame_id)
            self._put(cfg.lidar_topic, ros_msgdefs.POINT_CLOUD2, msg, ns)
        if frame.logged_pose is not None:
            self._check_pose(frame, frame.logged_pose, "logged_pose")
            msg = ros_convert.odometry_message(frame.logged_pose, t, cfg.world_frame_id, cfg.body_frame_id)
            self._put(cfg.odom_topic, ros_msgdefs.ODOMETRY, msg, ns)
        if frame.gt_pose is not None:
            self._check_pose(frame, frame.gt_pose, "gt_pose")
            msg = ros_convert.pose_stamped_message(frame.gt_pose, t, cfg.world_frame_id)
            self._put(cfg.gt_topic, ros_msgdefs.POSE_STAMPED, msg, ns)
        self.frames_written += 1

    def _check_pose(self, frame: Frame, pose: np.ndarray, name: str) -> None:
        problem = pose_problem(pose, self.config.rotation_tolerance)
        if problem is not None:
            raise self._fail(frame, f"{name}: {problem}")

    def _write_image(self, frame: Frame, image: np.ndarray, t: float, ns: int, rear: bool) -> None:
        cfg = self.config
        image = np.asarray(image)
        name = "rear_image" if rear else "image"
        if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
            raise self._fail(frame, f"{name} is {image.dtype} {image.shape}, expected HxWx3 uint8")
        frame_id = cfg.rear_camera_frame_id if rear else cfg.camera_frame_id
        calibration = self.intrinsics.get("rear_camera" if rear else "camera")
        if calibration is not None:
            height, width = image.shape[:2]
            if (calibration.width or width, calibration.height or height) != (width, height):
                raise self._fail(
                    frame,
                    f"{name} is {width}x{height} but its intrinsics are for "
                    f"{calibration.width}x{calibration.height} images",
                )
            msg = ros_convert.camera_info_message(calibration.k, width, height, t, frame_id)
            self._put(cfg.rear_camera_info_topic if rear else cfg.camera_info_topic, ros_msgdefs.CAMERA_INFO, msg, ns)
        if cfg.image_format == "raw":
            msg = ros_convert.image_message(image, t, frame_id)
            self._put(cfg.rear_camera_topic if rear else cfg.camera_topic, ros_msgdefs.IMAGE, msg, ns)
            return
        params = (
            [cv2.IMWRITE_JPEG_QUALITY, cfg.jpeg_quality]
            if cfg.image_format == "jpeg"
            else [cv2.IMWRITE_PNG_COMPRESSION, cfg.png_compression]
        )
        msg = ros_convert.compressed_image_message(image, t, frame_id, cfg.image_format, params)
        topic = cfg.compressed_rear_camera_topic if rear else cfg.compressed_camera_topic
        self._put(topic, ros_msgdefs.COMPRESSED_IMAGE, msg, ns)


def write_frames(
    frames: Iterable[Frame],
    path: str | Path,
    config: McapWriterConfig | None = None,
    intrinsics: Mapping[str, CameraIntrinsics] | None = None,
) -> int:
    """Write every frame of an iterable (e.g. a Source) to one MCAP log, with each camera's
    calibration when given (`McapFrameWriter`); returns the count."""
    with McapFrameWriter(path, config, intrinsics) as writer:
        for frame in frames:
            writer.write(frame)
    return writer.frames_written
