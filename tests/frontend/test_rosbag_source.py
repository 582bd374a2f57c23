"""ROS 1 bags and ROS 2 bag folders (SQLite and MCAP storage) stream the very frames of the MCAP
log they were converted from (written with `rosbags` itself); a cut or foreign bag is one error
line (the CLI side: tests/slam/test_rosbag_run.py)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from tool_module import load_tool

from frontend.config import McapSourceConfig
from frontend.errors import FrontendInputError
from frontend.simulation.config import SimulationConfig
from frontend.simulation.simulator import TraverseSimulator
from frontend.sources import RosbagSource, detect_kind, open_source, write_frames

mcap_to_rosbag = load_tool("mcap_to_rosbag").mcap_to_rosbag

FORMATS = {"ros1": "drive.bag", "ros2-sqlite3": "drive_db3", "ros2-mcap": "drive_mcap"}
FIELDS = ("image", "rear_image", "points", "point_times", "logged_pose", "gt_pose")


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("bags")
    log = folder / "drive.mcap"
    write_frames(TraverseSimulator(SimulationConfig(max_frames=8)).frames(), log)  # camera, rear, LiDAR, poses
    return {"mcap": log, **{fmt: mcap_to_rosbag(log, folder / name, fmt) for fmt, name in FORMATS.items()}}  # type: ignore[arg-type]


@pytest.mark.parametrize("fmt", sorted(FORMATS))
def test_a_bag_streams_the_frames_of_its_mcap(logs: dict[str, Path], fmt: str) -> None:
    assert detect_kind(logs[fmt]) == "rosbag"
    source = open_source(logs[fmt])
    assert isinstance(source, RosbagSource) and source.length == 8
    assert source.topics == open_source(logs["mcap"]).topics
    reference, frames = list(open_source(logs["mcap"])), list(source)
    assert len(frames) == len(reference) == 8
    for a, b in zip(reference, frames):
        assert a.timestamp == b.timestamp and a.index == b.index
        for field in FIELDS:
            x, y = getattr(a, field), getattr(b, field)
            assert (x is None) == (y is None), field
            assert x is None or np.array_equal(x, y), field
    assert a.points is not None and a.rear_image is not None and a.logged_pose is not None


def test_topics_are_named_and_checked_as_for_mcap(logs: dict[str, Path]) -> None:
    config = McapSourceConfig(camera_topic="/camera_rear/image_raw", rear_camera_topic="")
    frames = list(RosbagSource(logs["ros1"], config))
    reference = list(open_source(logs["mcap"]))
    assert np.array_equal(frames[3].image, reference[3].rear_image) and frames[3].rear_image is None
    with pytest.raises(
        FrontendInputError, match=r"camera topic '/front' not found; topics present: .*/camera/image_raw"
    ):
        RosbagSource(logs["ros2-sqlite3"], McapSourceConfig(camera_topic="/front"))


def cut_bag(path: Path, into: Path) -> Path:
    if path.is_file():
        into.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
        return into
    shutil.copytree(path, into)
    storage = next(p for p in into.iterdir() if p.suffix in (".db3", ".mcap"))
    storage.write_bytes(storage.read_bytes()[: storage.stat().st_size // 2])
    return into


@pytest.mark.parametrize("fmt", sorted(FORMATS))
def test_a_cut_bag_is_one_error_naming_it(logs: dict[str, Path], fmt: str, tmp_path: Path) -> None:
    cut = cut_bag(logs[fmt], tmp_path / f"cut_{FORMATS[fmt]}")
    with pytest.raises(FrontendInputError, match=rf"{cut}: cannot read this ROS [12] bag \(.+\)"):
        list(open_source(cut))


def test_a_file_that_is_no_bag(tmp_path: Path) -> None:
    fake = tmp_path / "notes.bag"
    fake.write_bytes(b"not a bag" * 100)
    with pytest.raises(FrontendInputError, match="cannot read this ROS 1 bag"):
        open_source(fake)
    with pytest.raises(FrontendInputError, match="already exists"):
        mcap_to_rosbag(tmp_path / "x.mcap", fake, "ros1")


@pytest.mark.parametrize("fmt", ["ros1", "ros2-sqlite3"])
def test_the_converter_turns_a_bag_back_into_the_same_frames(
    logs: dict[str, Path], fmt: str, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:

    tool = load_tool("rosbag_to_mcap")
    out = tmp_path / "back.mcap"
    assert tool.main([str(logs[fmt]), str(out), "--image-format", "png"]) == 0
    assert "wrote 8 frames" in capsys.readouterr().out
    for a, b in zip(open_source(logs["mcap"]), open_source(out), strict=True):
        assert a.timestamp == b.timestamp
        for field in FIELDS:  # pixels and points exactly; poses through a quaternion again, to 1e-12
            x, y = getattr(a, field), getattr(b, field)
            assert (x is None) == (y is None), field
            assert x is None or (np.allclose(x, y, rtol=0, atol=1e-12) if "pose" in field else np.array_equal(x, y))
    assert tool.main([str(logs[fmt]), str(tmp_path / "x.mcap"), "--camera-topic", "/front"]) == 2
    assert "camera topic '/front' not found" in capsys.readouterr().err
