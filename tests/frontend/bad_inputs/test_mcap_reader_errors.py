"""MCAP reader: bad input is reported clearly, damaged logs yield what they can."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from mcap_ros2.writer import Writer

from frontend.config import McapSourceConfig, McapWriterConfig
from frontend.errors import FrontendInputError
from frontend.frame import Frame
from frontend.sources import McapSource, ros_convert, ros_msgdefs, write_frames


def _frame(i: float, t: float, rng: np.random.Generator) -> Frame:
    pose = np.eye(4)
    pose[0, 3] = i
    return Frame(
        index=int(i),
        timestamp=t,
        image=rng.integers(0, 256, (16, 16, 3), dtype=np.uint8),
        points=rng.normal(size=(200, 3)),
        logged_pose=pose,
        gt_pose=pose,
    )


class _RawLog:
    """Hand-written log: messages in any order, with any stamps."""

    def __init__(self, path: Path, chunk_size: int = 1024 * 1024) -> None:
        self._stream = open(path, "wb")
        self._writer = Writer(self._stream, chunk_size=chunk_size)
        self._schemas: dict[str, object] = {}

    def put(self, topic: str, datatype: str, message: dict, log_time: float) -> None:
        if datatype not in self._schemas:
            self._schemas[datatype] = self._writer.register_msgdef(datatype, ros_msgdefs.MSGDEFS[datatype])
        ns = ros_convert.seconds_to_nanoseconds(log_time)
        self._writer.write_message(topic, self._schemas[datatype], message, log_time=ns, publish_time=ns)

    def close(self) -> None:
        self._writer.finish()
        self._stream.close()


def _rgb(t: float) -> dict:
    return ros_convert.image_message(np.full((4, 4, 3), 7, np.uint8), t, "cam")


def test_missing_topic_lists_topics_present(tmp_path: Path) -> None:
    path = tmp_path / "log.mcap"
    write_frames([_frame(0, 1.0, np.random.default_rng(0))], path)
    with pytest.raises(FrontendInputError) as info:
        McapSource(path, McapSourceConfig(lidar_topic="/velodyne_points"))
    message = str(info.value)
    assert "/velodyne_points" in message and "\n" not in message
    for topic, kind in [
        ("/camera/image_raw", "sensor_msgs/msg/Image"),
        ("/odom", "nav_msgs/msg/Odometry"),
        ("/lidar/points", "sensor_msgs/msg/PointCloud2"),
    ]:
        assert f"{topic} ({kind})" in message


def test_topic_of_wrong_type(tmp_path: Path) -> None:
    path = tmp_path / "log.mcap"
    write_frames([_frame(0, 1.0, np.random.default_rng(0))], path)
    with pytest.raises(FrontendInputError, match=r"'/odom' has type nav_msgs/msg/Odometry"):
        McapSource(path, McapSourceConfig(camera_topic="/odom"))


def test_no_sensor_topic_and_not_mcap(tmp_path: Path) -> None:
    path = tmp_path / "poses_only.mcap"
    write_frames([Frame(0, 1.0, logged_pose=np.eye(4))], path)
    with pytest.raises(FrontendInputError, match=r"no camera .* or LiDAR .*/odom \(nav_msgs"):
        McapSource(path)
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"this is not an mcap file at all")
    with pytest.raises(FrontendInputError, match=r"junk\.mcap: not an MCAP file"):
        McapSource(junk)
    with pytest.raises(FrontendInputError, match="not found"):
        McapSource(tmp_path / "missing.mcap")


def test_unknown_image_encoding_is_a_counted_skip_naming_encoding_topic_and_time(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "enc.mcap"
    log = _RawLog(path)
    message = _rgb(1.0)
    message["encoding"] = "16UC1"
    log.put("/depth/image", ros_msgdefs.IMAGE, message, 1.0)
    log.put("/depth/image", ros_msgdefs.IMAGE, _rgb(2.0), 2.0)
    log.close()
    source = McapSource(path)
    with caplog.at_level(logging.WARNING):
        assert [f.timestamp for f in source] == [2.0]
    assert source.stats.skipped["undecodable_image"] == 1
    text = caplog.records[0].getMessage()
    assert "/depth/image at t=1.000000" in text and "encoding '16UC1' is not supported" in text
    with pytest.raises(FrontendInputError, match=r"encoding '16UC1' is not supported"):
        list(McapSource(path, McapSourceConfig(skip_undecodable_images=False)))


@pytest.mark.parametrize("damage", ["wrong_step", "bad_encoding", "corrupt_jpeg"])
def test_a_bad_image_keeps_the_scan_of_its_frame(tmp_path: Path, damage: str) -> None:
    """Camera drives the frames; one image is broken: its frame still carries the LiDAR scan
    (odometry needs every scan it can get) and the image is counted as skipped."""
    path = tmp_path / f"{damage}.mcap"
    log = _RawLog(path)
    rng = np.random.default_rng(4)
    compressed = damage == "corrupt_jpeg"
    for i in range(4):
        t = 1.0 + 0.1 * i
        pixels = np.full((8, 8, 3), 9, np.uint8)
        if compressed:
            image = ros_convert.compressed_image_message(pixels, t, "cam", "jpeg", [])
            if i == 2:
                image["data"] = b"\xff\xd8garbage"
            log.put("/cam/compressed", ros_msgdefs.COMPRESSED_IMAGE, image, t)
        else:
            image = ros_convert.image_message(pixels, t, "cam")
            if i == 2 and damage == "wrong_step":
                image["step"] = 4  # fewer bytes per row than 8 rgb8 pixels need
            if i == 2 and damage == "bad_encoding":
                image["encoding"] = "bayer_rggb8"
            log.put("/cam", ros_msgdefs.IMAGE, image, t)
        cloud = ros_convert.point_cloud_message(rng.normal(size=(50, 3)), None, t, "lidar")
        log.put("/lidar", ros_msgdefs.POINT_CLOUD2, cloud, t)
    log.close()
    source = McapSource(path)
    frames = list(source)
    assert [f.image is None for f in frames] == [False, False, True, False]
    assert all(f.points is not None and len(f.points) == 50 for f in frames)
    assert source.stats.skipped["undecodable_image"] == 1


def test_a_bad_rear_image_keeps_the_rest_of_its_frame(tmp_path: Path) -> None:
    """A corrupt rear image is a counted skip naming its topic; the frame keeps its forward
    image and scan, and the rear camera's other frames keep theirs."""
    path = tmp_path / "rear.mcap"
    log = _RawLog(path)
    rng = np.random.default_rng(5)
    for i in range(4):
        t = 1.0 + 0.1 * i
        pixels = np.full((8, 8, 3), 9, np.uint8)
        log.put("/camera/image_raw", ros_msgdefs.IMAGE, ros_convert.image_message(pixels, t, "cam"), t)
        rear = ros_convert.compressed_image_message(pixels, t, "cam_rear", "jpeg", [])
        if i == 1:
            rear["data"] = b"\xff\xd8garbage"
        log.put("/camera_rear/image_raw/compressed", ros_msgdefs.COMPRESSED_IMAGE, rear, t)
        cloud = ros_convert.point_cloud_message(rng.normal(size=(50, 3)), None, t, "lidar")
        log.put("/lidar", ros_msgdefs.POINT_CLOUD2, cloud, t)
    log.close()
    source = McapSource(path)
    assert source.topics["rear_camera"].startswith("/camera_rear/image_raw/compressed")
    frames = list(source)
    assert [f.rear_image is None for f in frames] == [False, True, False, False]
    assert all(f.image is not None and f.points is not None for f in frames)
    assert source.stats.skipped["undecodable_image"] == 1


def test_undecodable_compressed_image_is_counted(tmp_path: Path) -> None:
    path = tmp_path / "jpeg.mcap"
    write_frames(
        [Frame(i, 1.0 + i, image=np.zeros((8, 8, 3), np.uint8)) for i in range(3)],
        path,
        McapWriterConfig(image_format="jpeg"),
    )
    log = _RawLog(tmp_path / "broken.mcap")
    good = ros_convert.compressed_image_message(np.zeros((8, 8, 3), np.uint8), 1.0, "cam", "jpeg", [])
    log.put("/cam/compressed", ros_msgdefs.COMPRESSED_IMAGE, good, 1.0)
    broken = dict(good, header=ros_convert.header_dict(2.0, "cam"), data=b"\xff\xd8garbage")
    log.put("/cam/compressed", ros_msgdefs.COMPRESSED_IMAGE, broken, 2.0)
    log.close()
    source = McapSource(tmp_path / "broken.mcap")
    assert len(list(source)) == 1
    assert source.stats.skipped["undecodable_image"] == 1
    with pytest.raises(FrontendInputError, match="cannot be decoded"):
        list(McapSource(tmp_path / "broken.mcap", McapSourceConfig(skip_undecodable_images=False)))


def _truncated_log(tmp_path: Path, n: int = 12) -> tuple[Path, list[Frame]]:
    rng = np.random.default_rng(1)
    frames = [_frame(i, 10.0 + 0.1 * i, rng) for i in range(n)]
    path = tmp_path / "full.mcap"
    # Small chunks: one frame's messages per chunk, so a cut loses only the tail.
    write_frames(frames, path, McapWriterConfig(chunk_size=1024, compression="none"))
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    return cut, frames


def test_truncated_log_yields_frames_before_the_cut_then_raises(tmp_path: Path) -> None:
    cut, frames = _truncated_log(tmp_path)
    source = McapSource(cut)
    assert source.length is None  # no summary to count from
    got: list[Frame] = []
    with pytest.raises(FrontendInputError, match=r"cut\.mcap: log is truncated or corrupt after \d+ frames"):
        for frame in source:
            got.append(frame)
    assert 3 <= len(got) < len(frames)
    for want, have in zip(frames, got):
        assert have.timestamp == pytest.approx(want.timestamp)
        assert np.array_equal(have.image, want.image)
    # every frame but possibly the last is complete
    for have, want in zip(got[:-1], frames):
        np.testing.assert_allclose(have.points, want.points, atol=1e-5)
        np.testing.assert_allclose(have.gt_pose, want.gt_pose)


def test_a_log_cut_before_any_topic_is_called_truncated_not_topicless(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    path = tmp_path / "full.mcap"
    # one large chunk: a cut inside it leaves no channel record readable
    write_frames([_frame(i, 10.0 + 0.1 * i, rng) for i in range(6)], path, McapWriterConfig(compression="none"))
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[:2000])
    with pytest.raises(
        FrontendInputError, match=r"cut\.mcap: log is truncated or corrupt before any camera or LiDAR topic"
    ):
        McapSource(cut)


def test_truncated_log_non_strict_warns_once_and_stops(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    cut, _ = _truncated_log(tmp_path)
    source = McapSource(cut, McapSourceConfig(strict=False))
    with caplog.at_level(logging.WARNING):
        got = list(source)
    assert len(got) >= 3
    assert source.stats.skipped["truncated"] == 1
    assert sum("truncated" in r.getMessage() for r in caplog.records) == 1


def test_non_monotonic_timestamps_are_counted_and_skipped(tmp_path: Path) -> None:
    path = tmp_path / "jumps.mcap"
    log = _RawLog(path)
    for t in [1.0, 2.0, 1.5, 2.0, 3.0, 0.5, 4.0]:
        log.put("/cam", ros_msgdefs.IMAGE, _rgb(t), 10.0)  # one log time: file order kept
    log.close()
    source = McapSource(path)
    got = list(source)
    assert [f.timestamp for f in got] == [1.0, 2.0, 3.0, 4.0]
    assert [f.index for f in got] == [0, 1, 2, 3]
    assert source.stats.skipped["non_monotonic_camera"] == 3
    assert "non_monotonic_camera=3" in source.stats.summary()


@pytest.mark.parametrize("chunk_size", [1024, 1024 * 1024])  # jump across chunks / inside one
def test_backward_clock_jump_in_an_indexed_log_is_never_interleaved(tmp_path: Path, chunk_size: int) -> None:
    """The recorder's clock is set back 2 s after 3 s of driving: sorting the indexed log by
    log time would interleave the two parts (x going back and forth); the jump is seen instead."""
    times = [10.0 + 0.1 * i for i in range(30)] + [11.0 + 0.1 * i for i in range(40)]
    path = tmp_path / "jump.mcap"
    log = _RawLog(path, chunk_size)  # a recorder writes what arrives, stamped by its clock
    for i, t in enumerate(times):
        pose = np.eye(4)
        pose[0, 3] = i
        log.put("/cam", ros_msgdefs.IMAGE, _rgb(t), t)
        log.put("/gt", ros_msgdefs.POSE_STAMPED, ros_convert.pose_stamped_message(pose, t, "map"), t)
    log.close()
    source = McapSource(path)
    got = list(source)
    stamps = [f.timestamp for f in got]
    xs = [f.gt_pose[0, 3] for f in got]
    assert np.all(np.diff(stamps) > 0) and np.all(np.diff(xs) > 0)  # one pass along the route
    assert xs[:30] == list(range(30)) and xs[30] == 50  # the part before the jump, then after it
    assert source.stats.notes["clock_went_back"] == 1
    assert source.stats.skipped["non_monotonic_camera"] == 20


def test_forward_clock_leap_is_kept_and_warned(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    rng = np.random.default_rng(3)
    frames = [_frame(i, t, rng) for i, t in enumerate([1.0, 1.1, 1.2, 61.2, 61.3])]
    path = tmp_path / "leap.mcap"
    write_frames(frames, path)
    source = McapSource(path)
    with caplog.at_level(logging.WARNING):
        assert len(list(source)) == 5
    assert source.stats.notes["clock_jump_camera"] == 1
    assert any("leaps 60.000 s forward" in r.getMessage() for r in caplog.records)


def test_association_by_nearest_stamp_within_tolerance(tmp_path: Path) -> None:
    """Camera at 10 Hz; LiDAR stamped 20 ms later but logged 80 ms late; odom at 100 Hz;
    gt only every other frame. Association must pick the nearest stamp, not log order."""
    path = tmp_path / "sync.mcap"
    log = _RawLog(path)
    rng = np.random.default_rng(2)
    events = []
    for k in range(10):
        t = 1.0 + 0.1 * k
        events.append((t, "/cam", ros_msgdefs.IMAGE, _rgb(t)))
        cloud = ros_convert.point_cloud_message(rng.normal(size=(5, 3)) + k, None, t + 0.02, "lidar")
        events.append((t + 0.1, "/points", ros_msgdefs.POINT_CLOUD2, cloud))
        if k % 2 == 0:
            pose = np.eye(4)
            pose[0, 3] = k
            events.append((t, "/gt", ros_msgdefs.POSE_STAMPED, ros_convert.pose_stamped_message(pose, t, "map")))
    for j in range(100):
        t = 1.0 + 0.01 * j + 0.003
        pose = np.eye(4)
        pose[1, 3] = t
        events.append((t, "/odom", ros_msgdefs.ODOMETRY, ros_convert.odometry_message(pose, t, "map", "base")))
    for log_time, topic, datatype, message in sorted(events, key=lambda e: e[0]):
        log.put(topic, datatype, message, log_time)
    log.close()
    # Buffers far smaller than the log: 100 odom messages, 16 kept at most.
    config = McapSourceConfig(association_tolerance_s=0.03, max_buffered_messages=16, max_pending_frames=4)
    source = McapSource(path, config)
    frames = list(source)
    assert len(frames) == 10
    for k, frame in enumerate(frames):
        assert frame.points is not None and np.mean(frame.points) == pytest.approx(k, abs=1.5)
        assert frame.logged_pose[1, 3] == pytest.approx(frame.timestamp + 0.003, abs=1e-9)
        assert (frame.gt_pose is not None) == (k % 2 == 0)
    assert source.stats.notes["unmatched_gt_pose"] == 5
    assert source.stats.notes["association_forced"] == 0
    # a tolerance below the LiDAR offset leaves every frame without a scan
    tight = McapSource(path, McapSourceConfig(association_tolerance_s=0.01))
    assert all(f.points is None for f in tight)
    assert tight.stats.notes["unmatched_lidar"] == 10


def test_associator_memory_stays_bounded_on_long_streams() -> None:
    from frontend.sources.association import StreamAssociator
    from frontend.sources.base import SourceStats

    stats = SourceStats()
    assoc = StreamAssociator(["odom", "lidar"], 0.02, 0.3, max_pending=5, max_buffered=12, stats=stats)
    decided = []
    for k in range(20000):  # 200 Hz odom, 10 Hz camera, LiDAR 10 Hz logged 50 ms late
        t = 0.005 * k
        decided += assoc.add_aux("odom", t, t)
        if k % 20 == 0:
            decided += assoc.add_driver(t, t)
        if k % 20 == 10:
            decided += assoc.add_aux("lidar", t - 0.05, t - 0.05)
        assert len(assoc._pending) <= 5 and all(len(b) <= 12 for b in assoc._buffers.values())
    decided += assoc.flush()
    assert len(decided) == 1000
    assert all(d.matches["odom"] == pytest.approx(d.time) for d in decided)
    assert all(d.matches["lidar"] == pytest.approx(d.time) for d in decided[:-1])
