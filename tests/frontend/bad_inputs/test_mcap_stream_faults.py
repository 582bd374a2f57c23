"""Faults inside an MCAP stream that are finite and well-formed on the wire but unusable:
zero-size images, image data that does not match its header, pose glitches far beyond what a
vehicle can move. Each is a counted skip naming topic and time; the frame keeps its other sensors."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import pytest
from mcap_ros2.writer import Writer

from frontend.config import McapSourceConfig
from frontend.errors import FrontendInputError
from frontend.sources import McapSource, ros_convert, ros_msgdefs
from frontend.sources.pose_jumps import MAX_SPEED_M_S, RELOCATION_MESSAGES, RELOCATION_SECONDS, PoseJumpCheck


def _write(path: Path, messages: list[tuple[str, str, dict, float]]) -> Path:
    """A log of (topic, type, message, time) in the order given."""
    with open(path, "wb") as stream:
        writer = Writer(stream)
        schemas: dict[str, object] = {}
        for topic, datatype, message, t in messages:
            if datatype not in schemas:
                schemas[datatype] = writer.register_msgdef(datatype, ros_msgdefs.MSGDEFS[datatype])
            ns = ros_convert.seconds_to_nanoseconds(t)
            writer.write_message(topic, schemas[datatype], message, log_time=ns, publish_time=ns)
        writer.finish()
    return path


def _pose(x: float) -> np.ndarray:
    pose = np.eye(4)
    pose[0, 3] = x
    return pose


def _image_damage(message: dict, damage: str) -> dict:
    if damage == "zero_size":
        return dict(message, height=0, width=0, step=0, data=b"")
    if damage == "zero_width":
        return dict(message, width=0, step=0)  # the data is still there: the header says no pixels
    if damage == "zero_height":
        return dict(message, height=0)
    assert damage == "short_data"
    return dict(message, data=message["data"][:-1])


DAMAGE = {
    "zero_size": "image is empty (0x0 pixels)",
    "zero_width": "image is empty (0x6 pixels)",
    "zero_height": "image is empty (8x0 pixels)",
    "short_data": "image 8x6 with step 24 has 143 data bytes, fewer than the 144 it needs",
}


def test_bytes_beyond_the_image_are_ignored(tmp_path: Path) -> None:
    """A driver that pads each image's data: the pixels are read, the padding ignored (refusing
    it would have dropped every camera frame of such a log)."""
    image = np.arange(6 * 8 * 3, dtype=np.uint8).reshape(6, 8, 3)
    message = ros_convert.image_message(image, 1.0, "cam")
    padded = dict(message, data=message["data"] + b"\0" * 7)
    path = _write(tmp_path / "padded.mcap", [("/cam", ros_msgdefs.IMAGE, padded, 1.0)])
    source = McapSource(path)
    frames = list(source)
    assert len(frames) == 1 and not source.stats.skipped
    np.testing.assert_array_equal(frames[0].image, image)


@pytest.mark.parametrize("damage", sorted(DAMAGE))
def test_a_zero_size_or_mismatched_image_is_a_counted_skip_keeping_the_frame(
    tmp_path: Path, damage: str, caplog: pytest.LogCaptureFixture
) -> None:
    """Before: a 0x0 image came out as an empty array and a later stage (the keyframe's
    thumbnail, cv2.cvtColor) ended the run with a traceback."""
    messages = []
    for i in range(4):
        t = 1.0 + 0.1 * i
        image = ros_convert.image_message(np.full((6, 8, 3), 9, np.uint8), t, "cam")
        messages.append(("/cam", ros_msgdefs.IMAGE, _image_damage(image, damage) if i == 2 else image, t))
        messages.append(("/odom", ros_msgdefs.ODOMETRY, ros_convert.odometry_message(_pose(i), t, "map", "base"), t))
    path = _write(tmp_path / f"{damage}.mcap", messages)
    source = McapSource(path)
    with caplog.at_level(logging.WARNING):
        frames = list(source)
    assert [f.image is None for f in frames] == [False, False, True, False]
    assert all(f.logged_pose is not None for f in frames)  # the frame keeps its other sensors
    assert source.stats.skipped == {"undecodable_image": 1}
    assert f"/cam at t=1.200000: rgb8 {DAMAGE[damage]}" in caplog.text
    with pytest.raises(FrontendInputError, match="image"):
        list(McapSource(path, McapSourceConfig(skip_undecodable_images=False)))


def _odometry_log(path: Path, xs: list[float], dt: float = 0.1) -> Path:
    messages = []
    for i, x in enumerate(xs):
        t = 1.0 + dt * i
        messages.append(
            ("/cam", ros_msgdefs.IMAGE, ros_convert.image_message(np.zeros((4, 4, 3), np.uint8), t, "c"), t)
        )
        messages.append(("/odom", ros_msgdefs.ODOMETRY, ros_convert.odometry_message(_pose(x), t, "map", "base"), t))
    return _write(path, messages)


@pytest.mark.parametrize("jump", [1e4, 1e5, 1e300])
def test_an_odometry_glitch_is_a_counted_skip(tmp_path: Path, jump: float, caplog: pytest.LogCaptureFixture) -> None:
    """Two messages far away and back: before, 1e4 m went into the trajectory unremarked and
    1e5 m broke the pose graph; now both are skipped (the odometry holds its pose over them)."""
    xs = [0.0, 1.0, 2.0, jump, jump, 5.0, 6.0]
    source = McapSource(_odometry_log(tmp_path / "glitch.mcap", xs))
    with caplog.at_level(logging.WARNING):
        frames = list(source)
    assert [f.logged_pose is None for f in frames] == [False, False, False, True, True, False, False]
    assert all(f.image is not None for f in frames)
    assert source.stats.skipped == {"implausible_logged_pose": 2}
    assert "/odom at t=1.300000: pose jumped" in caplog.text and "pose skipped" in caplog.text


def test_fast_but_possible_motion_and_long_gaps_pass(tmp_path: Path) -> None:
    xs = [0.0, 30.0, 60.0, 90.0]  # 300 m/s: an aircraft, not a glitch
    source = McapSource(_odometry_log(tmp_path / "fast.mcap", xs))
    assert all(f.logged_pose is not None for f in source) and not source.stats.skipped
    slow = McapSource(_odometry_log(tmp_path / "gap.mcap", [0.0, 5e4], dt=60.0))  # a minute without odometry
    assert all(f.logged_pose is not None for f in slow) and not slow.stats.skipped


def _refused_before_relocation(dt: float) -> int:
    """Messages refused before a moved stream is followed: RELOCATION_MESSAGES agreeing ones,
    spanning RELOCATION_SECONDS (the last of them is taken)."""
    return max(RELOCATION_MESSAGES, math.ceil(round(RELOCATION_SECONDS / dt, 9)) + 1) - 1


def test_a_stream_that_moved_for_good_is_followed_after_a_few_messages(tmp_path: Path) -> None:
    """An odometry reset is no glitch: once enough poses over a second agree, they are used."""
    refused = _refused_before_relocation(0.1)
    xs = [0.0, 1.0] + [1e5 + i for i in range(refused + 3)]
    source = McapSource(_odometry_log(tmp_path / "reset.mcap", xs, dt=0.1))
    kept = [f.logged_pose is not None for f in source]
    assert kept == [True, True] + [False] * refused + [True, True, True]
    assert source.stats.skipped["implausible_logged_pose"] == refused
    assert source.stats.notes["relocated_logged_pose"] == 1


def test_jump_check_of_a_first_pose_that_was_the_glitch() -> None:
    """The first pose is the reference; when it was the glitch, the real track takes over after
    a second of agreeing poses instead of being refused until the speed limit catches up."""
    check = PoseJumpCheck()
    assert check.check(0.0, _pose(1e6)).refused is None
    refused = _refused_before_relocation(0.1)
    verdicts = [check.check(0.1 * k, _pose(float(k))) for k in range(1, refused + 3)]
    assert [v.refused is not None for v in verdicts] == [True] * refused + [False, False]
    assert verdicts[refused].relocated is not None and verdicts[-1].relocated is None


def test_a_fast_stream_glitch_is_not_taken_for_a_relocation() -> None:
    """At 100 Hz five agreeing messages last 40 ms: a glitch, and the jump back is no relocation."""
    check = PoseJumpCheck()
    check.check(0.0, _pose(0.0))
    glitch = [check.check(0.01 * k, _pose(1e5)) for k in range(1, 2 * RELOCATION_MESSAGES)]
    assert all(v.refused is not None and v.relocated is None for v in glitch)
    back = check.check(0.01 * 2 * RELOCATION_MESSAGES, _pose(0.5))
    assert back.refused is None and back.relocated is None


def test_jump_check_scattered_glitches_never_relocate() -> None:
    check = PoseJumpCheck()
    check.check(0.0, _pose(0.0))
    for k in range(1, 4 * RELOCATION_MESSAGES):
        far = 1e5 * (1 if k % 2 else -1)  # glitches that disagree with each other
        assert check.check(0.1 * k, _pose(far)).refused is not None
    assert check.check(4 * RELOCATION_MESSAGES * 0.1, _pose(1.0)).refused is None
    assert MAX_SPEED_M_S >= 300.0  # no aircraft-speed log is refused
