"""MCAP writer -> reader round trips, for every message type and layout we support."""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.writer import Writer

from frontend.config import McapSourceConfig, McapWriterConfig
from frontend.errors import FrontendInputError
from frontend.frame import Frame
from frontend.sources import McapFrameWriter, McapSource, open_source, ros_convert, ros_msgdefs, write_frames


def _pose(x: float, yaw: float = 0.0) -> np.ndarray:
    pose = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    pose[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    pose[:3, 3] = [x, 0.5 * x, -0.1 * x]
    return pose


def _umask() -> int:
    import os

    mask = os.umask(0)
    os.umask(mask)
    return mask


def _frames(n: int, rng: np.random.Generator, with_times: bool = True) -> list[Frame]:
    frames = []
    for i in range(n):
        points = rng.normal(size=(50 + i, 3)) * 10
        frames.append(
            Frame(
                index=i,
                timestamp=100.0 + 0.1 * i,
                image=rng.integers(0, 256, (24, 32, 3), dtype=np.uint8),
                points=points,
                point_times=np.linspace(0.0, 0.1, len(points)) if with_times else None,
                logged_pose=_pose(i, 0.1 * i),
                gt_pose=_pose(i + 0.5, -0.1 * i),
            )
        )
    return frames


def test_full_round_trip_raw_images(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    frames = _frames(6, rng)
    path = tmp_path / "log.mcap"
    assert write_frames(frames, path) == 6
    source = open_source(path)
    assert isinstance(source, McapSource)
    assert len(source) == 6
    assert set(source.topics) == {"camera", "lidar", "logged_pose", "gt_pose"}
    out = list(source)
    assert len(out) == 6
    assert source.stats.frames_yielded == 6 and not source.stats.skipped
    for want, got in zip(frames, out):
        assert got.index == want.index
        assert got.timestamp == pytest.approx(want.timestamp, abs=1e-9)
        assert got.image.dtype == np.uint8 and np.array_equal(got.image, want.image)
        np.testing.assert_allclose(got.points, want.points, rtol=1e-6, atol=1e-5)
        np.testing.assert_allclose(got.point_times, want.point_times, atol=1e-7)
        np.testing.assert_allclose(got.logged_pose, want.logged_pose, atol=1e-9)
        np.testing.assert_allclose(got.gt_pose, want.gt_pose, atol=1e-9)


def test_cloud_without_time_field_and_missing_streams(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    frames = _frames(3, rng, with_times=False)
    for frame in frames:
        frame.image = None  # LiDAR drives when there is no camera
        frame.gt_pose = None
    path = tmp_path / "lidar.mcap"
    write_frames(frames, path)
    source = McapSource(path)
    assert source.driver == "lidar"
    out = list(source)
    assert [f.index for f in out] == [0, 1, 2]
    assert all(f.point_times is None and f.image is None and f.gt_pose is None for f in out)
    np.testing.assert_allclose(out[2].points, frames[2].points, rtol=1e-6, atol=1e-5)


@pytest.mark.parametrize("fmt", ["jpeg", "png"])
def test_compressed_images(tmp_path: Path, fmt: str) -> None:
    yy, xx = np.mgrid[0:32, 0:48]
    image = np.stack([xx * 5, yy * 7, (xx + yy) * 2], axis=2).astype(np.uint8)
    path = tmp_path / f"{fmt}.mcap"
    config = McapWriterConfig(image_format=fmt, jpeg_quality=95)
    with McapFrameWriter(path, config) as writer:
        writer.write(Frame(0, 1.0, image=image))
        writer.write(Frame(1, 2.0, image=image[:, ::-1].copy()))
    source = McapSource(path)
    assert source.topics["camera"].startswith(config.compressed_camera_topic)
    out = list(source)
    assert len(out) == 2 and out[0].image.shape == image.shape
    error = np.abs(out[0].image.astype(int) - image.astype(int)).mean()
    assert error == 0 if fmt == "png" else error < 3  # colour order preserved, not swapped


def _write_raw(path: Path, topic: str, datatype: str, messages: list[tuple[float, dict]]) -> None:
    """Write hand-made ROS 2 messages (layouts our writer never produces)."""
    with open(path, "wb") as stream:
        writer = Writer(stream)
        schema = writer.register_msgdef(datatype, ros_msgdefs.MSGDEFS[datatype])
        for t, message in messages:
            ns = ros_convert.seconds_to_nanoseconds(t)
            writer.write_message(topic, schema, message, log_time=ns, publish_time=ns)
        writer.finish()


def _image(encoding: str, pixels: np.ndarray, t: float, pad: int = 0) -> dict:
    height, width = pixels.shape[:2]
    rows = pixels.reshape(height, -1)
    padded = np.concatenate([rows, np.zeros((height, pad), np.uint8)], axis=1)
    return {
        "header": ros_convert.header_dict(t, "cam"),
        "height": height,
        "width": width,
        "encoding": encoding,
        "is_bigendian": 0,
        "step": padded.shape[1],
        "data": padded.tobytes(),
    }


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "mono8"])
def test_image_encodings_become_rgb(tmp_path: Path, encoding: str) -> None:
    rgb = np.random.default_rng(2).integers(0, 256, (5, 7, 3), dtype=np.uint8)
    if encoding == "mono8":
        pixels, expected = rgb[:, :, 0].copy(), np.repeat(rgb[:, :, :1], 3, axis=2)
    elif encoding == "bgr8":
        pixels, expected = rgb[:, :, ::-1].copy(), rgb
    else:
        pixels, expected = rgb, rgb
    path = tmp_path / "enc.mcap"
    _write_raw(path, "/cam", ros_msgdefs.IMAGE, [(1.0, _image(encoding, pixels, 1.0, pad=3))])
    (frame,) = list(McapSource(path))
    assert frame.image.shape == (5, 7, 3) and frame.image.dtype == np.uint8
    assert np.array_equal(frame.image, expected)


def _cloud(
    fields: list[tuple[str, int, np.dtype]], values: np.ndarray, point_step: int, t: float, big_endian: bool = False
) -> dict:
    """PointCloud2 with arbitrary field offsets/types and padding."""
    order = ">" if big_endian else "<"
    dtype = np.dtype(
        {
            "names": [f[0] for f in fields],
            "formats": [np.dtype(f[2]).newbyteorder(order) for f in fields],
            "offsets": [f[1] for f in fields],
            "itemsize": point_step,
        }
    )
    cloud = np.zeros(len(values), dtype=dtype)
    for i, (name, _, _) in enumerate(fields):
        cloud[name] = values[:, i]
    codes = {np.dtype(v): k for k, v in ros_convert.POINT_FIELD_DTYPES.items()}
    return {
        "header": ros_convert.header_dict(t, "lidar"),
        "height": 1,
        "width": len(values),
        "fields": [{"name": n, "offset": o, "datatype": codes[np.dtype(d)], "count": 1} for n, o, d in fields],
        "is_bigendian": big_endian,
        "point_step": point_step,
        "row_step": point_step * len(values),
        "data": cloud.tobytes(),
        "is_dense": True,
    }


@pytest.mark.parametrize(
    ("time_name", "time_type", "scale", "big_endian"),
    [("t", np.uint32, 1e-9, False), ("time", np.float32, 1.0, True), ("timestamp", np.float64, 1.0, False)],
)
def test_point_cloud_layouts(tmp_path: Path, time_name: str, time_type, scale: float, big_endian: bool) -> None:
    rng = np.random.default_rng(3)
    xyz = rng.normal(size=(40, 3))
    raw_times = (np.arange(40) * 1000).astype(time_type) if scale != 1.0 else np.linspace(0, 0.1, 40)
    # float64 xyz, intensity in between, time at the end, 4 bytes of padding
    fields = [
        ("x", 0, np.float64),
        ("y", 8, np.float64),
        ("intensity", 16, np.float32),
        ("z", 20, np.float64),
        (time_name, 28, time_type),
    ]
    values = np.c_[xyz[:, :2], np.ones(40), xyz[:, 2], raw_times]
    message = _cloud(fields, values, point_step=40, t=5.0, big_endian=big_endian)
    path = tmp_path / "cloud.mcap"
    _write_raw(path, "/velodyne_points", ros_msgdefs.POINT_CLOUD2, [(5.0, message)])
    (frame,) = list(McapSource(path))
    np.testing.assert_allclose(frame.points, xyz)
    np.testing.assert_allclose(frame.point_times, raw_times.astype(np.float64) * scale, atol=1e-7)


def _skip_warnings(path: Path, caplog: pytest.LogCaptureFixture) -> tuple[list, McapSource, list[str]]:
    source = McapSource(path)
    with caplog.at_level(logging.WARNING):
        frames = list(source)
    return frames, source, [r.getMessage() for r in caplog.records]


def test_point_cloud_missing_xyz_is_a_named_skip(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    message = _cloud([("x", 0, np.float32), ("y", 4, np.float32)], np.zeros((3, 2)), 8, 1.0)
    path = tmp_path / "bad_cloud.mcap"
    _write_raw(path, "/points", ros_msgdefs.POINT_CLOUD2, [(1.0, message)])
    frames, source, warnings = _skip_warnings(path, caplog)
    assert frames == [] and source.stats.skipped["bad_lidar"] == 1
    assert any(re.search(r"/points at t=1\.000000.*lacks field", w) for w in warnings)


def test_schemas_are_standard_ros2(tmp_path: Path) -> None:
    """What Foxglove needs: ros2msg schemas with standard names, cdr messages, ros2 profile."""
    path = tmp_path / "log.mcap"
    write_frames(_frames(2, np.random.default_rng(4)), path)
    with open(path, "rb") as stream:
        reader = make_reader(stream)
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
    names = {s.name for s in summary.schemas.values()}
    assert path.stat().st_mode & 0o777 == 0o666 & ~_umask()  # not mkstemp's 0600
    assert names == {
        "sensor_msgs/msg/Image",
        "sensor_msgs/msg/PointCloud2",
        "nav_msgs/msg/Odometry",
        "geometry_msgs/msg/PoseStamped",
    }
    assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
    assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}


def test_writer_is_atomic(tmp_path: Path) -> None:
    path = tmp_path / "out.mcap"
    frames = _frames(3, np.random.default_rng(5))
    with pytest.raises(RuntimeError, match="boom"):
        with McapFrameWriter(path) as writer:
            writer.write(frames[0])
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []  # neither the final file nor a temp file
    with pytest.raises(FrontendInputError, match=r"out\.mcap.*not after"):
        with McapFrameWriter(path) as writer:
            writer.write(frames[1])
            writer.write(frames[0])
    assert list(tmp_path.iterdir()) == []


def test_writer_rejects_bad_frames(tmp_path: Path) -> None:
    bad_pose = np.eye(4)
    bad_pose[0, 0] = np.nan
    cases = [
        Frame(0, -1.0),
        Frame(0, 1.0, image=np.zeros((4, 4), np.uint8)),
        Frame(0, 1.0, points=np.zeros((4, 2))),
        Frame(0, 1.0, logged_pose=bad_pose),
    ]
    for frame in cases:
        with pytest.raises(FrontendInputError, match=r"bad\.mcap: frame 0"):
            with McapFrameWriter(tmp_path / "bad.mcap") as writer:
                writer.write(frame)
    assert not (tmp_path / "bad.mcap").exists()


def test_topics_overridable(tmp_path: Path) -> None:
    config = McapWriterConfig(camera_topic="/front/image", odom_topic="/vehicle/odom")
    path = tmp_path / "named.mcap"
    write_frames(_frames(2, np.random.default_rng(6)), path, config)
    source = McapSource(path, McapSourceConfig(camera_topic="/front/image", lidar_topic=""))
    assert source.topics["camera"].startswith("/front/image")
    assert source.topics["logged_pose"].startswith("/vehicle/odom")
    assert "lidar" not in source.topics
    assert all(f.points is None and f.logged_pose is not None for f in source)


def test_organised_cloud_with_row_padding(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    xyz = np.arange(2 * 3 * 3, dtype=np.float64).reshape(6, 3)
    fields = [("x", 0, np.float32), ("y", 4, np.float32), ("z", 8, np.float32)]
    message = _cloud(fields, xyz, point_step=16, t=2.0)
    rows = np.frombuffer(message["data"], np.uint8).reshape(2, 3 * 16)
    padded = np.concatenate([rows, np.full((2, 8), 255, np.uint8)], axis=1)  # 8 junk bytes per row
    message.update(height=2, width=3, row_step=3 * 16 + 8, data=padded.tobytes())
    path = tmp_path / "organised.mcap"
    _write_raw(path, "/os/points", ros_msgdefs.POINT_CLOUD2, [(2.0, message)])
    (frame,) = list(McapSource(path))
    np.testing.assert_array_equal(frame.points, xyz)
    assert frame.point_times is None
    short = dict(message, data=padded.tobytes()[:-20])
    _write_raw(path, "/os/points", ros_msgdefs.POINT_CLOUD2, [(2.0, short)])
    caplog.clear()
    frames, source, warnings = _skip_warnings(path, caplog)
    assert frames == [] and source.stats.skipped["bad_lidar"] == 1
    assert any(re.search(r"/os/points at t=2\.000000: PointCloud2 3x2 .* only", w) for w in warnings)


@pytest.mark.parametrize("image_format", ["raw", "png"])
def test_rear_camera_round_trip(tmp_path: Path, image_format: str) -> None:
    rng = np.random.default_rng(5)
    frames = _frames(4, rng)
    for frame in frames:
        frame.rear_image = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
    frames[2].rear_image = None  # a rear image that never arrived
    path = tmp_path / "rear.mcap"
    write_frames(frames, path, McapWriterConfig(image_format=image_format))
    source = McapSource(path)
    assert set(source.topics) == {"camera", "rear_camera", "lidar", "logged_pose", "gt_pose"}
    assert source.driver == "camera"
    out = list(source)
    assert len(out) == 4
    for want, got in zip(frames, out):
        assert np.array_equal(got.image, want.image)  # the forward camera is never mistaken for the rear one
        if want.rear_image is None:
            assert got.rear_image is None
        else:
            assert np.array_equal(got.rear_image, want.rear_image)


def test_a_second_camera_is_never_guessed_from_its_type(tmp_path: Path) -> None:
    """Only the writer's rear names (or a named topic) make a rear camera; an unknown second
    Image topic is not used as one, and a log whose only camera is a rear one has no front camera."""
    rng = np.random.default_rng(6)
    frames = _frames(3, rng)
    for frame in frames:
        frame.rear_image = rng.integers(0, 256, (24, 32, 3), dtype=np.uint8)
    other = tmp_path / "other_names.mcap"
    write_frames(frames, other, McapWriterConfig(rear_camera_topic="/left/image_raw"))
    source = McapSource(other)
    assert "rear_camera" not in source.topics and source.topics["camera"].startswith("/camera/image_raw")
    assert all(f.rear_image is None for f in source)

    named = McapSource(other, McapSourceConfig(rear_camera_topic="/left/image_raw"))
    out = list(named)
    assert all(np.array_equal(f.rear_image, w.rear_image) for f, w in zip(out, frames))

    for frame in frames:
        frame.image = None
    rear_only = tmp_path / "rear_only.mcap"
    write_frames(frames, rear_only)
    source = McapSource(rear_only)
    assert "camera" not in source.topics and source.topics["rear_camera"].startswith("/camera_rear/")
    assert source.driver == "lidar"
