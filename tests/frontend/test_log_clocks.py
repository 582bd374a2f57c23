"""One clock per log: header stamps or log time for every topic, never mixed frame by frame,
and times no writer can hold refused before any work (hardening round two, clocks)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
from mcap_ros2.writer import Writer

from frontend.errors import FrontendInputError
from frontend.frame import Frame
from frontend.sources import McapSource, ros_convert, ros_msgdefs, write_frames


def _write(path: Path, events: list[tuple[float, float, str]]) -> None:
    """(log time, header stamp, topic) camera images and LiDAR scans, in the order given."""
    with open(path, "wb") as stream:
        writer = Writer(stream)
        schemas = {
            t: writer.register_msgdef(t, ros_msgdefs.MSGDEFS[t]) for t in (ros_msgdefs.IMAGE, ros_msgdefs.POINT_CLOUD2)
        }
        for k, (log_time, stamp, topic) in enumerate(events):
            if topic == "/cam":
                datatype, message = (
                    ros_msgdefs.IMAGE,
                    ros_convert.image_message(np.full((4, 4, 3), k % 250, np.uint8), stamp, "cam"),
                )
            else:
                points = np.random.default_rng(k).normal(size=(20, 3))
                datatype, message = (
                    ros_msgdefs.POINT_CLOUD2,
                    ros_convert.point_cloud_message(points, None, stamp, "lidar"),
                )
            ns = ros_convert.seconds_to_nanoseconds(log_time)
            writer.write_message(topic, schemas[datatype], message, log_time=ns, publish_time=ns)
        writer.finish()


def _pairs(start_log: float, stamps: list[float]) -> list[tuple[float, float, str]]:
    events = []
    for k, stamp in enumerate(stamps):
        events += [(start_log + 0.1 * k, stamp, "/cam"), (start_log + 0.1 * k + 0.01, stamp, "/points")]
    return events


def test_stamps_left_at_zero_time_the_whole_log_by_log_time(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """A recorder that never sets header stamps but logs wall-clock time: every frame is kept,
    timed by log time, and it is said once (before: 1 frame of 45, the rest 'clock went back')."""
    path = tmp_path / "unset.mcap"
    _write(path, _pairs(1.7e9, [0.0] * 45))
    source = McapSource(path)
    with caplog.at_level(logging.WARNING):
        frames = list(source)
    assert len(frames) == 45 and all(f.points is not None for f in frames)
    assert frames[0].timestamp == pytest.approx(1.7e9) and frames[-1].timestamp == pytest.approx(1.7e9 + 4.4)
    assert source.stats.notes["clock_log_time"] == 1 and not source.stats.skipped
    assert sum("timed by log time" in r.getMessage() for r in caplog.records) == 1


def test_a_first_stamp_of_zero_never_mixes_clocks(tmp_path: Path) -> None:
    """First stamp 0, later stamps set: log time for the whole log, not log time for frame 0
    and stamps after it (which read as the clock going back and lost every later frame)."""
    path = tmp_path / "first_zero.mcap"
    _write(path, _pairs(1.7e9, [0.0] + [5.0 + 0.1 * k for k in range(1, 20)]))
    source = McapSource(path)
    frames = list(source)
    assert len(frames) == 20 and not source.stats.skipped
    assert np.all(np.diff([f.timestamp for f in frames]) > 0)


def test_times_no_writer_can_hold_are_refused_before_any_frame(tmp_path: Path) -> None:
    path = tmp_path / "far.mcap"
    _write(path, _pairs(1.8e10, [0.0] + [1.0 + k for k in range(1, 6)]))
    with pytest.raises(FrontendInputError, match=r"far\.mcap: /\w+ log time: time 1\.8e\+10 s is outside .*2038"):
        McapSource(path)  # when the log is opened: before the backbone loads, before any frame


def test_a_zero_stamp_inside_a_stamped_log_is_a_counted_skip(tmp_path: Path) -> None:
    path = tmp_path / "one_zero.mcap"
    stamps = [100.0 + 0.1 * k for k in range(10)]
    events = _pairs(1.7e9, stamps)
    events[8] = (events[8][0], 0.0, "/cam")  # frame 4's image lost its stamp
    _write(path, events)
    source = McapSource(path)
    frames = list(source)
    assert source.stats.skipped["unset_stamp_camera"] == 1 and not source.stats.notes["clock_log_time"]
    assert len(frames) == 9 and frames[0].timestamp == pytest.approx(100.0)  # timed by header stamps


def test_our_own_logs_start_at_time_zero_on_both_clocks(tmp_path: Path) -> None:
    """A log written from time 0 (the simulator's) is header-stamped from its first frame."""
    path = tmp_path / "sim.mcap"
    rng = np.random.default_rng(0)
    frames = [
        Frame(
            index=k,
            timestamp=0.1 * k,
            image=rng.integers(0, 256, (8, 8, 3), dtype=np.uint8),
            points=rng.normal(size=(30, 3)),
        )
        for k in range(5)
    ]
    write_frames(frames, path)
    source = McapSource(path)
    got = list(source)
    assert [f.timestamp for f in got] == pytest.approx([0.1 * k for k in range(5)])
    assert not source.stats.notes and not source.stats.skipped


def test_run_refuses_such_a_log_in_one_line_and_writes_nothing(tmp_path: Path) -> None:
    """Before: every frame skipped as 'clock went back', then a struct.error writing trajectory.mcap."""
    from cli_helpers import assert_user_error, invoke

    path = tmp_path / "far.mcap"
    _write(path, _pairs(1.8e10, [0.0] + [1.0 + k for k in range(1, 6)]))
    assert_user_error(invoke("run", path, "--out", tmp_path / "out", "--odometry", "kiss-icp"), "far.mcap", "2038")
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())
