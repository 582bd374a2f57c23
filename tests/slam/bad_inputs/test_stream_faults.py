"""`run` on small logs with one fault inside the stream: the run goes on (a counted warning, no
traceback) and writes its results, or, where it cannot go on, ends with one `error:` line and
the results of the frames before the fault.

Before: a 0x0 camera image ended the run in cv2.cvtColor (the keyframe thumbnail); an odometry
step of 1e5 m made iSAM2 fail, its retry fail with "key already exists", and no results were
written at all."""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace

import gtsam
import numpy as np
import pytest
from cli_helpers import assert_user_error, clean_ssmvpr_environment, invoke  # noqa: F401

from frontend.config import McapWriterConfig
from frontend.frame import Frame
from frontend.odometry.logged import LoggedPoseOdometry
from frontend.simulation import SimulationConfig, TraverseSimulator
from frontend.sources import McapFrameWriter, ros_convert, ros_msgdefs
from ssmvpr_slam import thumbnail
from ssmvpr_slam.backend.pose_graph import PoseGraph
from ssmvpr_slam.config.slam import load_config
from ssmvpr_slam.system import SlamSystem

FRAMES = 14
GLITCH = (3, 4)  # two odometry messages 1e5 m away, then back: refused by the reader
MOVED_FROM = 8  # the odometry is 1e5 m away for good: followed after a second (6 messages), iSAM2 needs QR


def _bad_image(frame: Frame) -> dict | None:
    """The damaged sensor_msgs/Image of frames 5-7 (None: the frame's own image is written)."""
    message = ros_convert.image_message(frame.image, frame.timestamp, "camera")
    if frame.index == 5:
        return dict(message, height=0, width=0, step=0, data=b"")
    if frame.index == 6:
        return dict(message, width=0, step=0)
    if frame.index == 7:
        return dict(message, data=message["data"][:-3])
    return None


def _moved(frame: Frame) -> Frame:
    if frame.index not in GLITCH and frame.index < MOVED_FROM:
        return frame
    pose = frame.logged_pose.copy()
    pose[0, 3] += 1e5
    return dataclasses.replace(frame, logged_pose=pose)


def _write_log(path: Path, change: Callable[[Frame], Frame], bad_image: Callable[[Frame], dict | None]) -> Path:
    config = McapWriterConfig(chunk_size=64 * 1024)
    sim = TraverseSimulator(SimulationConfig(max_frames=FRAMES, lidar={"enabled": False}))
    with McapFrameWriter(path, config) as writer:
        for frame in sim.frames():
            frame = change(frame)
            image = bad_image(frame)
            if image is not None:
                writer.write_message(config.camera_topic, ros_msgdefs.IMAGE, image, frame.timestamp)
                frame = dataclasses.replace(frame, image=None)
            writer.write(frame)
    return path


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> SimpleNamespace:
    base = tmp_path_factory.mktemp("stream_faults")
    return SimpleNamespace(
        images=_write_log(base / "images.mcap", lambda f: f, _bad_image),
        odometry=_write_log(base / "odometry.mcap", _moved, lambda f: None),
    )


def _run(log: Path, out: Path, weights_path: Path):  # noqa: ANN202
    return invoke("run", log, "--odometry", "logged", "--weights", weights_path, "--device", "cpu", "--out", out)


def _run_through(log: Path, out: Path, weights_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """`run` on a faulty log, its warnings captured: it must end as a clean run does."""
    with caplog.at_level("WARNING"):
        result = _run(log, out, weights_path)
    assert result.exit_code == 0, (result.output, result.exception)
    assert "Traceback" not in result.output


def _metrics(out: Path) -> dict:
    return json.loads((out / "latest" / "metrics.json").read_text())


def test_zero_size_and_mismatched_images_are_skipped(
    logs: SimpleNamespace, weights_path: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    _run_through(logs.images, tmp_path / "out", weights_path, caplog)
    assert "/camera/image_raw at t=1.000000: rgb8 image is empty (0x0 pixels); message skipped" in caplog.text
    metrics = _metrics(tmp_path / "out")
    assert metrics["source_stats"]["skipped"] == {"undecodable_image": 3}
    assert metrics["frames"] == FRAMES and metrics["frames_skipped"] == {"no camera image": 3}
    assert metrics["error"] is None and (tmp_path / "out" / "latest" / "trajectory.mcap").is_file()
    assert metrics["pose_graph_recoveries"] == []


def test_odometry_glitch_is_skipped_and_a_lasting_jump_is_solved(
    logs: SimpleNamespace, weights_path: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    _run_through(logs.odometry, tmp_path / "out", weights_path, caplog)
    assert "/odom at t=0.600000: pose jumped 1e+05 m in 0.2 s" in caplog.text
    assert "poses agree: followed from here" in caplog.text
    recovery = [r.getMessage() for r in caplog.records if "re-solved with QR" in r.getMessage()]
    assert len(recovery) == 1 and recovery[0].startswith("frame 13 (keyframe "), caplog.text
    assert "odometry step of 1.0e+05 m" in recovery[0]
    metrics = _metrics(tmp_path / "out")
    assert metrics["pose_graph_recoveries"] == recovery  # recorded beside the warning
    assert metrics["source_stats"]["skipped"] == {"implausible_logged_pose": len(GLITCH) + 5}
    assert metrics["source_stats"]["notes"]["relocated_logged_pose"] == 1
    optimised = np.loadtxt(tmp_path / "out" / "latest" / "optimised.tum")
    assert len(optimised) == metrics["keyframes"] and optimised[:, 1].max() > 9e4  # the track it was told
    assert np.all(np.isfinite(optimised))


class _RefusesKeyframe2:
    """An iSAM2 that fails on every step holding keyframe 2's value: no fallback can help."""

    def __init__(self, isam: gtsam.ISAM2) -> None:
        self._isam = isam

    def update(self, *args: object):  # noqa: ANN202
        if len(args) > 1 and args[1].exists(gtsam.symbol("x", 2)):  # type: ignore[attr-defined]
            raise RuntimeError("Indeterminate linear system detected (Symbol: x2).")
        return self._isam.update(*args)

    def calculateEstimate(self) -> gtsam.Values:  # noqa: N802
        return self._isam.calculateEstimate()


def test_a_pose_graph_that_cannot_go_on_ends_the_run_with_its_results(
    logs: SimpleNamespace, weights_path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The last fallback failing too (forced here) ends the run: one error line naming the
    frame, no traceback, and the results of the frames before it written."""
    new_isam = PoseGraph._new_isam
    monkeypatch.setattr(PoseGraph, "_new_isam", lambda graph: _RefusesKeyframe2(new_isam(graph)))
    out = tmp_path / "out"
    line = assert_user_error(
        _run(logs.images, out, weights_path), "(keyframe 2): iSAM2 cannot solve the pose graph with keyframe(s) 2"
    )
    assert line.startswith("error: frame ")
    metrics = _metrics(out)
    assert metrics["keyframes"] == 3 and "PoseGraphError" in metrics["error"]


def test_an_empty_image_from_any_source_is_a_counted_skip_of_the_frame() -> None:
    """Defence behind the readers: a source that lets a 0xN image through does not end the run."""
    config = load_config()
    system = SlamSystem(config, LoggedPoseOdometry(), backbone=None)  # type: ignore[arg-type]  # front needs none
    for index, shape in enumerate([(0, 0, 3), (0, 64, 3), (48, 0, 3)]):
        assert system.front(Frame(index, float(index), image=np.zeros(shape, np.uint8), logged_pose=np.eye(4))) is None
    system.sync_front_counts()
    assert system.state.frames_skipped == {"empty camera image": 3}
    rear = Frame(3, 3.0, image=np.zeros((48, 64, 3), np.uint8), rear_image=np.zeros((0, 0, 3), np.uint8),
                 logged_pose=np.eye(4))  # fmt: skip
    item = system.front(rear)
    assert item is not None and item.rear_image is None  # the forward image still makes the keyframe


@pytest.mark.parametrize("shape", [(0, 0, 3), (10, 0, 3), (5,), (4, 4, 2)])
def test_a_thumbnail_never_ends_a_run(shape: tuple[int, ...], caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level("WARNING"):
        assert thumbnail.thumbnail_jpeg(np.zeros(shape, np.uint8), 80, "keyframe 3 (frame 9)") is None
    assert "keyframe 3 (frame 9): no thumbnail in trajectory.mcap" in caplog.text
    assert thumbnail.thumbnail_jpeg(np.zeros((240, 1, 3), np.uint8), 80)  # thin, but a picture
