"""Camera calibration from logs (`Source.intrinsics`): CameraInfo written beside the images and
read back from MCAP logs and ROS bags, paired with its camera by topic; KITTI's calib.txt; a
calibration that cannot be right is a counted warning, never a K."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest
from tool_module import load_tool

from frontend.config import KittiSourceConfig, McapSourceConfig, McapWriterConfig
from frontend.errors import FrontendInputError
from frontend.frame import Frame
from frontend.simulation.config import SimulationConfig
from frontend.simulation.simulator import TraverseSimulator
from frontend.sources import KittiSource, McapFrameWriter, McapSource, RosbagSource, open_source, write_frames
from frontend.sources.intrinsics import CameraIntrinsics, k_problem, pinhole
from frontend.sources.ros_convert import camera_info_message
from frontend.sources.ros_msgdefs import CAMERA_INFO
from frontend.sources.ros_stream import camera_info_candidates

mcap_to_rosbag = load_tool("mcap_to_rosbag").mcap_to_rosbag

FRONT = pinhole(100.0, 101.0, 15.5, 11.5, 32, 24)
REAR = pinhole(50.0, 50.0, 16.0, 12.0)


def _frames(n: int = 3, rear: bool = True) -> list[Frame]:
    rng = np.random.default_rng(0)
    return [
        Frame(
            index=i,
            timestamp=10.0 + 0.1 * i,
            image=rng.integers(0, 256, (24, 32, 3), dtype=np.uint8),
            rear_image=rng.integers(0, 256, (24, 32, 3), dtype=np.uint8) if rear else None,
        )
        for i in range(n)
    ]


def _same(got: CameraIntrinsics, want: CameraIntrinsics, size: tuple[int, int] = (32, 24)) -> None:
    assert got.k.dtype == np.float64 and np.array_equal(got.k, want.k)
    assert (got.width, got.height) == size


def _log_with_info(path: Path, k: list[float], **fields: int) -> Path:
    """A camera log whose /camera/camera_info carries a hand-made K (and CameraInfo fields)."""
    with McapFrameWriter(path) as writer:
        for frame in _frames(2, rear=False):
            message = camera_info_message(np.eye(3), 32, 24, frame.timestamp, "camera")
            message.update(k=k, **fields)
            writer.write_message("/camera/camera_info", CAMERA_INFO, message, frame.timestamp)
            writer.write(frame)
    return path


@pytest.mark.parametrize("image_format", ["raw", "jpeg"])
def test_written_calibration_reads_back_exactly(tmp_path: Path, image_format: str) -> None:
    path = tmp_path / "log.mcap"
    frames = _frames()
    write_frames(frames, path, McapWriterConfig(image_format=image_format), {"camera": FRONT, "rear_camera": REAR})
    source = McapSource(path)
    intrinsics = source.intrinsics
    assert set(intrinsics) == {"camera", "rear_camera"}
    _same(intrinsics["camera"], FRONT)
    _same(intrinsics["rear_camera"], REAR)  # the size is the images' it was written with
    assert set(source.topics) == {"camera", "rear_camera"}  # calibration is no frame stream
    out = list(source)
    assert len(out) == 3 and (image_format == "jpeg" or np.array_equal(out[2].rear_image, frames[2].rear_image))
    assert not source.stats.notes and not source.stats.skipped


def test_a_log_without_calibration_has_none(tmp_path: Path) -> None:
    path = tmp_path / "plain.mcap"
    write_frames(_frames(), path)
    source = McapSource(path)
    assert source.intrinsics == {} and not source.stats.notes


def test_calibration_pairs_with_the_camera_beside_it() -> None:
    assert camera_info_candidates("/camera/image_raw", "sensor_msgs/msg/Image") == ["/camera/camera_info"]
    assert camera_info_candidates("/cam/image_raw/compressed", "sensor_msgs/msg/CompressedImage") == [
        "/cam/image_raw/camera_info",
        "/cam/camera_info",
    ]
    assert camera_info_candidates("/image_raw", "sensor_msgs/msg/Image") == ["/camera_info"]


def test_automatic_named_and_switched_off_pairing(tmp_path: Path) -> None:
    """Another camera's namespace pairs by itself; an info topic elsewhere only when named."""
    beside = McapWriterConfig(camera_topic="/front/image_raw", camera_info_topic="/front/camera_info")
    path = tmp_path / "front.mcap"
    write_frames(_frames(rear=False), path, beside, {"camera": FRONT})
    _same(McapSource(path).intrinsics["camera"], FRONT)
    assert McapSource(path, McapSourceConfig(camera_info_topic="")).intrinsics == {}

    elsewhere = tmp_path / "elsewhere.mcap"
    write_frames(_frames(rear=False), elsewhere, McapWriterConfig(camera_info_topic="/calib/front"), {"camera": FRONT})
    assert McapSource(elsewhere).intrinsics == {}
    _same(McapSource(elsewhere, McapSourceConfig(camera_info_topic="/calib/front")).intrinsics["camera"], FRONT)
    with pytest.raises(FrontendInputError, match=r"camera info topic '/calib/back' not found"):
        McapSource(elsewhere, McapSourceConfig(camera_info_topic="/calib/back"))
    with pytest.raises(FrontendInputError, match=r"camera info topic '/camera/image_raw' has type .*Image"):
        McapSource(elsewhere, McapSourceConfig(camera_info_topic="/camera/image_raw"))


def test_one_info_topic_beside_both_cameras_is_used_for_neither(tmp_path: Path) -> None:
    path = tmp_path / "shared.mcap"
    config = McapWriterConfig(rear_camera_topic="/camera/image_rear", rear_camera_info_topic="/camera/camera_info")
    write_frames(_frames(), path, config, {"camera": FRONT})
    source = McapSource(path, McapSourceConfig(rear_camera_topic="/camera/image_rear"))
    assert source.intrinsics == {} and source.stats.notes["ambiguous_calibration"] == 2


def test_an_uncalibrated_camera_is_a_counted_warning(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """ROS drivers publish K all zeros for a camera nobody calibrated: no K, one warning, counted
    in every reading's stats."""
    source = McapSource(_log_with_info(tmp_path / "zeros.mcap", [0.0] * 9))
    with caplog.at_level(logging.WARNING):
        assert source.intrinsics == {} and source.intrinsics == {}  # read once
    assert source.stats.notes["invalid_calibration"] == 1
    assert any("/camera/camera_info: K is all zeros" in r.getMessage() for r in caplog.records)
    assert len(list(source)) == 2 and source.stats.notes["invalid_calibration"] == 1


@pytest.mark.parametrize(
    ("k", "fields", "reason"),
    [
        ([np.nan, 0, 16, 0, 100, 12, 0, 0, 1], {}, "invalid_calibration"),
        ([-100, 0, 16, 0, 100, 12, 0, 0, 1], {}, "invalid_calibration"),
        ([100, 0, 16, 0, 100, 12, 0, 0, 0], {}, "invalid_calibration"),
        ([100, 0, 16, 0, 100, 12, 0, 0, 1], {"binning_x": 2}, "unreadable_calibration"),
    ],
)
def test_a_calibration_that_cannot_be_right_is_ignored(tmp_path: Path, k: list, fields: dict, reason: str) -> None:
    source = McapSource(_log_with_info(tmp_path / "bad.mcap", [float(v) for v in k], **fields))
    assert source.intrinsics == {} and source.stats.notes == {reason: 1}


def test_k_problems_and_the_checked_type() -> None:
    assert k_problem(FRONT.k) is None and k_problem(FRONT.k.ravel().tolist()) is None
    assert "8 values" in str(k_problem([1.0] * 8))
    with pytest.raises(ValueError, match="all zeros"):
        CameraIntrinsics(np.zeros((3, 3)))
    with pytest.raises(ValueError):
        FRONT.k[0, 0] = 1.0  # read-only: a cached K cannot be changed by its user


def test_the_writer_refuses_a_calibration_for_other_images(tmp_path: Path) -> None:
    with pytest.raises(FrontendInputError, match=r"image is 32x24 but its intrinsics are for 64x48 images"):
        write_frames(_frames(), tmp_path / "x.mcap", intrinsics={"camera": pinhole(1, 1, 0, 0, 64, 48)})
    with pytest.raises(ValueError, match="unknown camera role"):
        McapFrameWriter(tmp_path / "x.mcap", intrinsics={"left": FRONT})


def test_bags_carry_the_calibration(tmp_path: Path) -> None:
    log = tmp_path / "log.mcap"
    write_frames(_frames(), log, McapWriterConfig(image_format="png"), {"camera": FRONT, "rear_camera": REAR})
    for fmt, name in (("ros1", "log.bag"), ("ros2-sqlite3", "log_db3")):
        source = open_source(mcap_to_rosbag(log, tmp_path / name, fmt))
        assert isinstance(source, RosbagSource)
        _same(source.intrinsics["camera"], FRONT)  # ROS 1's K, ROS 2's k
        _same(source.intrinsics["rear_camera"], REAR)
        assert len(list(source)) == 3 and not source.stats.notes


def test_the_simulator_k_is_its_renderer_rays(tmp_path: Path) -> None:
    """K^-1 (u, v, 1) of every pixel is the ray the renderer casts (x right, y down; the renderer
    takes y left, z up), and a simulated log carries it."""
    simulator = TraverseSimulator(SimulationConfig(max_frames=2, lidar={"enabled": False}))
    intrinsics = simulator.intrinsics
    assert set(intrinsics) == {"camera", "rear_camera"}
    k = intrinsics["camera"]
    assert simulator.camera is not None and (k.width, k.height) == (320, 240)
    u, v = np.arange(k.width), np.arange(k.height)
    rays_x = (u - k.k[0, 2]) / k.k[0, 0]
    rays_y = (v - k.k[1, 2]) / k.k[1, 1]
    np.testing.assert_allclose(-simulator.camera.lateral, rays_x, atol=1e-6)
    np.testing.assert_allclose(-simulator.camera.slope, rays_y, atol=1e-6)
    assert k.k[0, 0] == pytest.approx(160.0)  # 90 degrees across 320 pixels
    log = tmp_path / "sim.mcap"
    write_frames(simulator.frames(), log, intrinsics=intrinsics)
    _same(McapSource(log).intrinsics["rear_camera"], k, (320, 240))


def _kitti(root: Path, calib: str | None) -> Path:
    seq = root / "sequences" / "00"
    for folder in ("image_0", "image_2"):
        (seq / folder).mkdir(parents=True)
        for i in range(2):
            cv2.imwrite(str(seq / folder / f"{i:06d}.png"), np.zeros((10, 12, 3), np.uint8))
    (seq / "times.txt").write_text("0.0\n0.1\n")
    if calib is not None:
        (seq / "calib.txt").write_text(calib)
    return seq


def _p(f: float, cx: float, cy: float, tx: float = 0.0) -> str:
    return " ".join(f"{v:.12e}" for v in [f, 0, cx, tx, 0, f, cy, 0, 0, 0, 1, 0])


def test_kitti_k_is_the_read_camera_projection(tmp_path: Path) -> None:
    calib = f"P0: {_p(718.856, 607.1928, 185.2157)}\nP1: {_p(1, 1, 1)}\nP2: {_p(707.0, 601.9, 183.1, 46.0)}\n"
    seq = _kitti(tmp_path, calib)
    colour = open_source(seq)
    assert isinstance(colour, KittiSource)
    _same(colour.intrinsics["camera"], pinhole(707.0, 707.0, 601.9, 183.1), (12, 10))
    grey = KittiSource(seq, KittiSourceConfig(camera="image_0"))
    _same(grey.intrinsics["camera"], pinhole(718.856, 718.856, 607.1928, 185.2157), (12, 10))


@pytest.mark.parametrize(
    ("calib", "notes"),
    [
        (None, {}),
        (f"P0: {_p(718.856, 607.1928, 185.2157)}\n", {}),  # another camera's
        ("P2: " + " ".join(["0"] * 12) + "\n", {"invalid_calibration": 1}),
        ("P2: 1 2 3\n", {"invalid_calibration": 1}),
    ],
)
def test_kitti_without_a_usable_projection_has_no_k(tmp_path: Path, calib: str | None, notes: dict) -> None:
    source = KittiSource(_kitti(tmp_path, calib), KittiSourceConfig(camera="image_2"))
    assert source.intrinsics == {} and source.stats.notes == notes
