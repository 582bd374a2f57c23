"""Odometry in a process of its own: the same poses, scans and counters as in this process, the
same errors, and a child that dies becomes an error naming the frame rather than a hang."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from frontend.config import KissIcpConfig, OdometryConfig
from frontend.errors import FrontendInputError
from frontend.frame import Frame
from frontend.odometry import OdometryProcess, OdometryProcessError, make_odometry
from frontend.odometry.own_process import _POLL_S, submitted_ahead

ROOT = Path(__file__).resolve().parents[2]
CONFIG = OdometryConfig(kind="kiss_icp", kiss_icp=KissIcpConfig(max_num_threads=1))


@pytest.fixture(scope="module")
def kitti_frames(shared_dir: Path) -> list[Frame]:
    """Two consecutive real KITTI 00 Velodyne scans (x, y, z, reflectance as float32)."""
    image = np.zeros((4, 4, 3), np.uint8)  # what the pipeline needs of a keyframe; the child never gets it
    velodyne = shared_dir / "data" / "kitti00_scans" / "velodyne"
    return [
        Frame(k, 0.1 * k, image=image, points=np.fromfile(velodyne / name, np.float32).reshape(-1, 4)[:, :3])
        for k, name in enumerate(["000094.bin", "000095.bin"])
    ]


def test_real_scans_give_the_same_poses_scans_and_counts_as_in_process(kitti_frames: list[Frame]) -> None:
    frames = [*kitti_frames, Frame(2, 0.2, points=None)]  # a frame without a scan: counted, pose predicted
    here = make_odometry(CONFIG)
    with make_odometry(CONFIG, own_process=True) as there:
        assert isinstance(there, OdometryProcess)
        poses = []
        for frame in frames:
            start = time.perf_counter()
            poses.append(there.update(frame))  # kiss-icp's sums are not bit-reproducible: to 1e-9
            waited = time.perf_counter() - start
            # the child's own time in update, part of the wait here (the rest: the way there and back)
            assert there.last_update_s is not None and 0.0 < there.last_update_s < waited
            np.testing.assert_allclose(poses[-1], here.update(frame), rtol=0, atol=1e-9)
            expected = getattr(here, "last_scan", None)
            if expected is None:
                assert there.last_scan is None
            else:
                np.testing.assert_allclose(there.last_scan, expected, rtol=0, atol=1e-9)
        assert np.linalg.norm(poses[1][:3, 3]) > 0.3  # the car moved between the two scans (0.47 m)
        assert there.stats.updates == len(frames) and there.stats.skipped == {"no_points": 1}


def test_a_warning_in_the_child_is_logged_here(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING), OdometryProcess(CONFIG) as odometry:
        odometry.update(Frame(0, 0.0, points=np.zeros((0, 3))))
    assert odometry.stats.skipped == {"empty_scan": 1}
    assert any("frame 0" in r.getMessage() and r.name == "frontend.odometry" for r in caplog.records)


def test_bad_input_raises_the_same_error_naming_the_frame() -> None:
    with OdometryProcess(CONFIG) as odometry, pytest.raises(FrontendInputError, match=r"frame 7 .*shape \(5, 2\)"):
        odometry.update(Frame(7, 0.7, points=np.zeros((5, 2))))


def test_a_bad_config_fails_at_start_with_the_childs_error() -> None:
    with pytest.raises(FrontendInputError, match="choose_odometry"):  # raised by make_odometry in the child
        OdometryProcess(OdometryConfig(kind="auto"))


def test_a_dead_child_is_an_error_naming_the_frame_not_a_hang(kitti_frames: list[Frame]) -> None:
    odometry = OdometryProcess(CONFIG)
    odometry._process.kill()
    frame = kitti_frames[0]
    result: list[BaseException | None] = []

    def call() -> None:
        try:
            odometry.update(frame)
            result.append(None)
        except BaseException as exc:
            result.append(exc)

    worker = threading.Thread(target=call, daemon=True)
    started = time.monotonic()
    worker.start()
    worker.join(timeout=30.0)
    assert result, "update() hung on a dead child"
    assert time.monotonic() - started < 10 * _POLL_S + 5.0
    assert isinstance(result[0], OdometryProcessError)
    assert "frame 0" in str(result[0]) and "exit code -9" in str(result[0])
    with pytest.raises(OdometryProcessError, match="closed"):
        odometry.update(frame)


def test_an_update_interrupted_mid_wait_closes_it_rather_than_leave_a_reply_for_the_next(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    odometry = OdometryProcess(CONFIG)

    def interrupted(*args: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(odometry, "_receive", interrupted)
    with pytest.raises(KeyboardInterrupt):
        odometry.update(Frame(0, 0.0, points=np.zeros((0, 3))))
    monkeypatch.undo()
    with pytest.raises(OdometryProcessError, match="frame 1 .*closed"):
        odometry.update(Frame(1, 0.1, points=np.zeros((0, 3))))


def test_close_ends_the_child_and_is_idempotent() -> None:
    odometry = OdometryProcess(CONFIG)
    # a terminal's Ctrl-C goes to a process group: the child is not in ours, so it never sees one
    assert os.getpgid(odometry._process.pid) != os.getpgid(0)
    odometry.close()
    odometry.close()
    assert odometry._process.poll() == 0
    with pytest.raises(OdometryProcessError, match="frame 3 .*closed"):
        odometry.update(Frame(3, 0.3, points=np.zeros((0, 3))))


def test_a_script_without_a_main_guard_can_use_it(tmp_path: Path) -> None:
    """multiprocessing's spawn would run such a script again in the child; a fresh python does not."""
    script = textwrap.dedent(
        """
        import numpy as np
        from frontend.config import OdometryConfig
        from frontend.frame import Frame
        from frontend.odometry import make_odometry
        print("script ran")
        odometry = make_odometry(OdometryConfig(kind="kiss_icp"), own_process=True)
        print(odometry.update(Frame(0, 0.0, points=np.zeros((0, 3))))[0, 0])
        odometry.close()
        """
    )
    path = tmp_path / "no_guard.py"
    path.write_text(script)
    done = subprocess.run([sys.executable, str(path)], capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["script", "ran", "1.0"]


# ------------------------------------------------------------------ frames handed over ahead


def test_frames_handed_over_ahead_give_the_poses_of_one_at_a_time(kitti_frames: list[Frame]) -> None:
    frames = [*kitti_frames, Frame(2, 0.2, points=None), Frame(3, 0.3, points=kitti_frames[1].points)]
    with make_odometry(CONFIG, own_process=True) as one, make_odometry(CONFIG, own_process=True) as ahead:
        assert isinstance(ahead, OdometryProcess)
        expected = [one.update(frame) for frame in frames]
        got = []
        for frame in submitted_ahead(iter(frames), ahead, 2):
            assert len(ahead._pending) == min(3, len(frames) - frame.index)  # this frame and two more in flight
            got.append(ahead.update(frame))
        np.testing.assert_allclose(np.array(got), np.array(expected), rtol=0, atol=1e-9)
        assert ahead.stats.updates == len(frames) and ahead.stats.skipped == {"no_points": 1}


def test_poses_are_taken_in_the_order_the_frames_went(kitti_frames: list[Frame]) -> None:
    with OdometryProcess(CONFIG) as odometry:
        odometry.submit(kitti_frames[0])
        odometry.submit(kitti_frames[1])
        with pytest.raises(RuntimeError, match="frame 1 .*taken before frame 0"):
            odometry.update(kitti_frames[1])
        odometry.update(kitti_frames[0])
        odometry.update(kitti_frames[1])


def test_a_bad_frame_handed_ahead_fails_at_its_own_turn_and_the_next_still_registers(
    kitti_frames: list[Frame],
) -> None:
    bad = Frame(1, 0.1, points=np.zeros((5, 2)))
    good = Frame(2, 0.2, points=kitti_frames[1].points)
    with OdometryProcess(CONFIG) as odometry:
        frames = submitted_ahead(iter([kitti_frames[0], bad, good]), odometry, 2)
        assert np.allclose(odometry.update(next(frames)), np.eye(4))  # the first scan is the origin
        with pytest.raises(FrontendInputError, match=r"frame 1 .*shape \(5, 2\)"):
            odometry.update(next(frames))
        assert np.linalg.norm(odometry.update(next(frames))[:3, 3]) > 0.3
        assert odometry.stats.updates == 3


def test_closing_with_frames_in_flight_ends_the_child_cleanly(kitti_frames: list[Frame]) -> None:
    odometry = OdometryProcess(CONFIG)
    for k in range(4):
        odometry.submit(Frame(k, 0.1 * k, points=kitti_frames[k % 2].points))
    started = time.monotonic()
    odometry.close()
    assert odometry._process.poll() == 0 and time.monotonic() - started < 10.0
    with pytest.raises(OdometryProcessError, match="closed"):
        odometry.update(kitti_frames[0])


def test_a_frame_that_cannot_be_sent_fails_at_its_turn_not_the_frame_before(kitti_frames: list[Frame]) -> None:
    unsendable = Frame(1, 0.1, points=np.array([lambda: None], dtype=object))  # a lambda does not pickle
    with OdometryProcess(CONFIG) as odometry:
        odometry.submit(kitti_frames[0])
        odometry.submit(unsendable)
        assert np.allclose(odometry.update(kitti_frames[0]), np.eye(4))  # sent before the failure: its pose comes
        with pytest.raises(OdometryProcessError, match="frame 1 .*could not be sent"):
            odometry.update(unsendable)


class _Submitted:
    """What `submitted_ahead` hands over, in order."""

    def __init__(self) -> None:
        self.indices: list[int] = []

    def submit(self, frame: Frame) -> None:
        self.indices.append(frame.index)


def test_submitted_ahead_keeps_depth_frames_in_flight_and_a_fault_after_the_frames_before_it() -> None:
    def source():
        yield from (Frame(k, 0.1 * k) for k in range(5))
        raise FrontendInputError("cut.mcap: truncated after 5 frames")

    odometry = _Submitted()
    frames = submitted_ahead(source(), odometry, 2)  # type: ignore[arg-type]
    taken = []
    with pytest.raises(FrontendInputError, match="truncated after 5 frames"):
        for frame in frames:
            assert odometry.indices[-1] == min(frame.index + 2, 4)  # handed over two frames early
            taken.append(frame.index)
    assert taken == [0, 1, 2, 3, 4] and odometry.indices == taken
