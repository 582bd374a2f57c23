"""Conversions between numpy data and ROS 2 messages (as mcap_ros2 encodes/decodes them).

Encoders return plain dicts that ``mcap_ros2.writer.Writer.write_message`` serialises;
decoders take the objects ``mcap_ros2.decoder.DecoderFactory`` produces. Every decoding
error names the topic it came from.
"""

from __future__ import annotations

from typing import Any, Literal

import cv2
import numpy as np

from frontend.errors import FrontendInputError
from ssmvpr_common.poses import matrix_to_quaternion, pose_from_translation_quaternion

NANOSECONDS = 1_000_000_000

# sensor_msgs/PointField datatype constants -> numpy scalar type.
POINT_FIELD_DTYPES: dict[int, type[np.generic]] = {
    1: np.int8,
    2: np.uint8,
    3: np.int16,
    4: np.uint16,
    5: np.int32,
    6: np.uint32,
    7: np.float32,
    8: np.float64,
}
FLOAT32 = 7
TIME_FIELD_NAMES = ("t", "time", "timestamp")
IMAGE_CHANNELS = {"rgb8": 3, "bgr8": 3, "mono8": 1}
COMPRESSED_FORMATS = ("jpeg", "png")


# --------------------------------------------------------------------------- time


def seconds_to_nanoseconds(seconds: float) -> int:
    """Integer nanoseconds of a non-negative finite time (MCAP log times are uint64)."""
    if not np.isfinite(seconds) or seconds < 0:
        raise ValueError(f"timestamp {seconds} is not a finite non-negative time")
    return int(round(seconds * NANOSECONDS))


def stamp_dict(seconds: float) -> dict[str, int]:
    """builtin_interfaces/Time of a time in seconds."""
    sec, nanosec = divmod(seconds_to_nanoseconds(seconds), NANOSECONDS)
    return {"sec": sec, "nanosec": nanosec}


def stamp_seconds(stamp: Any) -> float:
    """Seconds of a decoded builtin_interfaces/Time."""
    return stamp.sec + stamp.nanosec / NANOSECONDS


def header_dict(seconds: float, frame_id: str) -> dict[str, Any]:
    return {"stamp": stamp_dict(seconds), "frame_id": frame_id}


# --------------------------------------------------------------------------- encoding


def image_message(image: np.ndarray, seconds: float, frame_id: str) -> dict[str, Any]:
    """sensor_msgs/Image, rgb8, from an HxWx3 uint8 RGB array."""
    image = np.ascontiguousarray(image, dtype=np.uint8)
    height, width = image.shape[:2]
    return {
        "header": header_dict(seconds, frame_id),
        "height": height,
        "width": width,
        "encoding": "rgb8",
        "is_bigendian": 0,
        "step": width * 3,
        "data": image.tobytes(),
    }


def compressed_image_message(
    image: np.ndarray, seconds: float, frame_id: str, fmt: str, params: list[int]
) -> dict[str, Any]:
    """sensor_msgs/CompressedImage (``jpeg`` or ``png``) from an RGB array."""
    ok, buffer = cv2.imencode(f".{fmt}", cv2.cvtColor(image, cv2.COLOR_RGB2BGR), params)
    if not ok:
        raise ValueError(f"cv2 could not encode a {image.shape} image as {fmt}")
    return encoded_image_message(buffer.tobytes(), seconds, frame_id, fmt)


def encoded_image_message(data: bytes, seconds: float, frame_id: str, fmt: str) -> dict[str, Any]:
    """sensor_msgs/CompressedImage around bytes already encoded as ``fmt``."""
    return {"header": header_dict(seconds, frame_id), "format": fmt, "data": data}


def camera_info_message(k: np.ndarray, width: int, height: int, seconds: float, frame_id: str) -> dict[str, Any]:
    """sensor_msgs/CameraInfo of a distortion-free pinhole K (plumb_bob with zero d, P = [K | 0])
    for images of width x height, unbinned and uncropped."""
    k = np.asarray(k, dtype=np.float64).reshape(3, 3)
    return {
        "header": header_dict(seconds, frame_id),
        "height": height,
        "width": width,
        "distortion_model": "plumb_bob",
        "d": [0.0] * 5,
        "k": [float(v) for v in k.ravel()],
        "r": [float(v) for v in np.eye(3).ravel()],
        "p": [float(v) for v in np.hstack([k, np.zeros((3, 1))]).ravel()],
        "binning_x": 0,
        "binning_y": 0,
        "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False},
    }


def point_cloud_message(points: np.ndarray, times: np.ndarray | None, seconds: float, frame_id: str) -> dict[str, Any]:
    """sensor_msgs/PointCloud2 with float32 x, y, z and, when given, float32 ``t``."""
    names = ["x", "y", "z"] + (["t"] if times is not None else [])
    cloud = np.empty(len(points), dtype=[(name, np.float32) for name in names])
    for axis, name in enumerate("xyz"):
        cloud[name] = points[:, axis]
    if times is not None:
        cloud["t"] = times
    point_step = cloud.dtype.itemsize
    itemsize = np.dtype(np.float32).itemsize
    return {
        "header": header_dict(seconds, frame_id),
        "height": 1,
        "width": len(points),
        "fields": [
            {"name": name, "offset": i * itemsize, "datatype": FLOAT32, "count": 1} for i, name in enumerate(names)
        ],
        "is_bigendian": False,
        "point_step": point_step,
        "row_step": point_step * len(points),
        "data": cloud.tobytes(),
        "is_dense": bool(np.all(np.isfinite(points))),
    }


def pose_dict(pose: np.ndarray) -> dict[str, Any]:
    """geometry_msgs/Pose of a 4x4 transform."""
    x, y, z = (float(v) for v in pose[:3, 3])
    qx, qy, qz, qw = (float(v) for v in matrix_to_quaternion(pose[:3, :3]))
    return {
        "position": {"x": x, "y": y, "z": z},
        "orientation": {"x": qx, "y": qy, "z": qz, "w": qw},
    }


def odometry_message(pose: np.ndarray, seconds: float, world_frame: str, body_frame: str) -> dict[str, Any]:
    """nav_msgs/Odometry carrying the pose (covariance and twist left at zero)."""
    zeros = [0.0] * 36
    return {
        "header": header_dict(seconds, world_frame),
        "child_frame_id": body_frame,
        "pose": {"pose": pose_dict(pose), "covariance": zeros},
        "twist": {"twist": {}, "covariance": list(zeros)},
    }


def pose_stamped_message(pose: np.ndarray, seconds: float, world_frame: str) -> dict[str, Any]:
    """geometry_msgs/PoseStamped of a 4x4 transform."""
    return {"header": header_dict(seconds, world_frame), "pose": pose_dict(pose)}


def path_message(poses: np.ndarray, stamps: np.ndarray, world_frame: str) -> dict[str, Any]:
    """nav_msgs/Path of (N, 4, 4) poses with their times; the header takes the last time."""
    last = float(stamps[-1]) if len(stamps) else 0.0
    return {
        "header": header_dict(last, world_frame),
        "poses": [pose_stamped_message(p, float(t), world_frame) for p, t in zip(poses, stamps)],
    }


LINE_LIST = 5  # visualization_msgs/Marker.LINE_LIST


def line_list_marker(
    segments: list[tuple[np.ndarray, np.ndarray]],
    seconds: float,
    world_frame: str,
    namespace: str,
    marker_id: int,
    rgba: tuple[float, float, float, float],
    width: float,
) -> dict[str, Any]:
    """visualization_msgs/Marker LINE_LIST: one line per (start, end) xyz pair."""
    points = [{"x": float(p[0]), "y": float(p[1]), "z": float(p[2])} for pair in segments for p in pair]
    r, g, b, a = (float(v) for v in rgba)
    return {
        "header": header_dict(seconds, world_frame),
        "ns": namespace,
        "id": marker_id,
        "type": LINE_LIST,
        "action": 0,
        "pose": pose_dict(np.eye(4)),
        "scale": {"x": width, "y": 0.0, "z": 0.0},
        "color": {"r": r, "g": g, "b": b, "a": a},
        "lifetime": {"sec": 0, "nanosec": 0},
        "frame_locked": False,
        "points": points,
        "colors": [],
        "texture_resource": "",
        "texture": {"header": header_dict(seconds, world_frame), "format": "", "data": b""},
        "uv_coordinates": [],
        "text": "",
        "mesh_resource": "",
        "mesh_file": {"filename": "", "data": b""},
        "mesh_use_embedded_materials": False,
    }


# --------------------------------------------------------------------------- decoding


def decode_image(msg: Any, topic: str) -> np.ndarray:
    """HxWx3 RGB uint8 from a sensor_msgs/Image in rgb8, bgr8 or mono8.

    Refused (FrontendInputError, which the reader counts as a skipped image): an image with no
    pixels, which every later stage (thumbnail, backbone, registration) would fail on, and one
    whose data is shorter than ``step * height`` bytes: such a message was cut or mis-described,
    and reading it anyway would give wrong pixels. Bytes beyond ``step * height`` (a driver's
    padding) are ignored, as before.
    """
    encoding = str(msg.encoding).lower()
    channels = IMAGE_CHANNELS.get(encoding)
    if channels is None:
        raise FrontendInputError(
            f"{topic}: image encoding '{msg.encoding}' is not supported (supported: {', '.join(IMAGE_CHANNELS)})"
        )
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    _check_image_layout(topic, encoding, width, height, step, channels, data.size)
    row_bytes = width * channels
    rows = data[: height * step].reshape(height, step)[:, :row_bytes]
    pixels = rows.reshape(height, width, channels)
    if encoding == "mono8":
        return np.repeat(pixels, 3, axis=2)
    if encoding == "bgr8":
        return np.ascontiguousarray(pixels[:, :, ::-1])
    return pixels.copy()


def _check_image_layout(
    topic: str, encoding: str, width: int, height: int, step: int, channels: int, size: int
) -> None:
    """Raise FrontendInputError unless the header describes pixels that the data holds."""
    if width <= 0 or height <= 0:
        raise FrontendInputError(f"{topic}: {encoding} image is empty ({width}x{height} pixels)")
    if step < width * channels:
        raise FrontendInputError(
            f"{topic}: {encoding} image {width}x{height} has step {step}, "
            f"fewer than the {width * channels} bytes a row needs"
        )
    if size < step * height:
        raise FrontendInputError(
            f"{topic}: {encoding} image {width}x{height} with step {step} has {size} data bytes, "
            f"fewer than the {step * height} it needs"
        )


def decode_compressed_image(msg: Any, topic: str) -> np.ndarray | None:
    """RGB uint8 from a jpeg/png sensor_msgs/CompressedImage; None when undecodable."""
    fmt = str(msg.format).lower()
    if not any(name in fmt for name in (*COMPRESSED_FORMATS, "jpg")):
        raise FrontendInputError(
            f"{topic}: compressed image format '{msg.format}' is not supported "
            f"(supported: {', '.join(COMPRESSED_FORMATS)})"
        )
    buffer = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    bgr = cv2.imdecode(buffer, cv2.IMREAD_COLOR) if buffer.size else None
    if bgr is None:
        return None
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def _field_dtype(field: Any, topic: str) -> np.dtype:
    scalar = POINT_FIELD_DTYPES.get(int(field.datatype))
    if scalar is None:
        raise FrontendInputError(f"{topic}: PointCloud2 field '{field.name}' has unknown datatype {field.datatype}")
    return np.dtype(scalar)


def decode_point_cloud(msg: Any, topic: str) -> tuple[np.ndarray, np.ndarray | None]:
    """(Nx3 float64 points, N per-point times in seconds or None) from a PointCloud2.

    Any layout is accepted: fields are located by name/offset/datatype, padding and
    ``row_step`` > ``width * point_step`` are skipped, big-endian data is byte-swapped.
    Integer time fields are taken as nanoseconds (Ouster's ``t``), float ones as seconds.
    """
    fields = {str(f.name): f for f in msg.fields}
    missing = [axis for axis in "xyz" if axis not in fields]
    if missing:
        raise FrontendInputError(f"{topic}: PointCloud2 lacks field(s) {missing}; fields are {sorted(fields)}")
    time_name = next((name for name in TIME_FIELD_NAMES if name in fields), None)
    wanted = ["x", "y", "z"] + ([time_name] if time_name else [])
    order: Literal[">", "<"] = ">" if msg.is_bigendian else "<"
    point_step, height, width = int(msg.point_step), int(msg.height), int(msg.width)
    formats = [_field_dtype(fields[n], topic).newbyteorder(order) for n in wanted]
    offsets = [int(fields[n].offset) for n in wanted]
    if any(o + f.itemsize > point_step for o, f in zip(offsets, formats)):
        raise FrontendInputError(f"{topic}: PointCloud2 field offsets exceed point_step {point_step}")
    dtype = np.dtype({"names": wanted, "formats": formats, "offsets": offsets, "itemsize": point_step})
    row_step = max(int(msg.row_step), width * point_step)
    data = bytes(msg.data)
    if height * width == 0:
        return np.zeros((0, 3)), (np.zeros(0) if time_name else None)
    if len(data) < row_step * (height - 1) + width * point_step:
        raise FrontendInputError(
            f"{topic}: PointCloud2 {width}x{height} (point_step {point_step}, row_step "
            f"{row_step}) has only {len(data)} data bytes"
        )
    # A strided view over the message bytes: row padding and unused fields are never copied.
    cloud = np.ndarray((height, width), dtype=dtype, buffer=data, strides=(row_step, point_step))
    points = np.stack([cloud[a].astype(np.float64).ravel() for a in "xyz"], axis=1)
    times = None
    if time_name is not None:
        raw = cloud[time_name].ravel()
        times = raw.astype(np.float64)
        if np.issubdtype(raw.dtype, np.integer):
            times /= NANOSECONDS
    return points, times


def decode_camera_info(msg: Any, topic: str) -> tuple[Any, int, int]:
    """(K, width, height) of a sensor_msgs/CameraInfo, ROS 2 (``k``) or ROS 1 (``K``): K as logged
    (9 row-major values, for the caller to check), a size of 0 where the driver left it unknown.
    Refused (FrontendInputError): a binned or cropped (ROI) camera, whose K describes the full
    sensor rather than the images logged."""
    values = getattr(msg, "k", None)
    if values is None:
        values = getattr(msg, "K", None)
    if values is None:
        raise FrontendInputError(f"{topic}: CameraInfo has no k (or K) field")
    width, height = int(getattr(msg, "width", 0)), int(getattr(msg, "height", 0))
    binning = (int(getattr(msg, "binning_x", 0)), int(getattr(msg, "binning_y", 0)))
    roi = getattr(msg, "roi", None)
    window = (0, 0, 0, 0) if roi is None else (int(roi.x_offset), int(roi.y_offset), int(roi.width), int(roi.height))
    cropped = window[:2] != (0, 0) or window[2:] not in ((0, 0), (width, height))
    if max(binning) > 1 or cropped:
        raise FrontendInputError(
            f"{topic}: CameraInfo with binning {binning} and ROI {window}: K is for the full sensor, "
            "not for the images logged (not supported)"
        )
    return values, width, height


def decode_pose(msg: Any, topic: str) -> np.ndarray:
    """4x4 pose of an Odometry / PoseStamped / PoseWithCovarianceStamped message."""
    pose = msg.pose
    if hasattr(pose, "pose"):  # Odometry and PoseWithCovarianceStamped nest one level more
        pose = pose.pose
    try:
        p, q = pose.position, pose.orientation
    except AttributeError:
        raise FrontendInputError(f"{topic}: message has no pose.position/orientation") from None
    quaternion = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
    if not np.all(np.isfinite(quaternion)) or np.linalg.norm(quaternion) == 0:
        return np.full((4, 4), np.nan)
    return pose_from_translation_quaternion(np.array([p.x, p.y, p.z]), quaternion)
