"""`run` takes a ROS 1 or ROS 2 bag as it takes the MCAP log it was converted from (the same
keyframes, trajectory and loop decisions), and a cut bag is one error line."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from cli_helpers import assert_user_error, clean_ssmvpr_environment, invoke  # noqa: F401
from tool_module import load_tool

from frontend.simulation.config import SimulationConfig
from frontend.simulation.simulator import TraverseSimulator
from frontend.sources import write_frames

mcap_to_rosbag = load_tool("mcap_to_rosbag").mcap_to_rosbag


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("bags")
    log = folder / "drive.mcap"
    write_frames(TraverseSimulator(SimulationConfig(max_frames=8)).frames(), log)
    return {"mcap": log, "ros1": mcap_to_rosbag(log, folder / "drive.bag", "ros1"),
            "ros2": mcap_to_rosbag(log, folder / "drive_db3", "ros2-sqlite3")}  # fmt: skip


def test_run_gives_the_same_keyframes_and_trajectory_from_a_bag(
    logs: dict[str, Path], weights_path: Path, tmp_path: Path
) -> None:
    results = {}
    for kind in ("mcap", "ros1", "ros2"):
        out = tmp_path / kind
        result = invoke("run", logs[kind], "--odometry", "logged", "--weights", weights_path, "--device", "cpu",
                        "--out", out)  # fmt: skip
        assert result.exit_code == 0, result.output
        folder = out / "latest-run"
        metrics = json.loads((folder / "metrics.json").read_text())
        results[kind] = (metrics["frames"], metrics["keyframes"], (folder / "optimised.tum").read_text(),
                         (folder / "loop_closures.csv").read_text())  # fmt: skip
    assert results["ros1"] == results["mcap"] == results["ros2"] and results["mcap"][1] >= 2


def test_a_cut_bag_is_one_error_line(logs: dict[str, Path], tmp_path: Path) -> None:
    cut = tmp_path / "cut.bag"
    cut.write_bytes(logs["ros1"].read_bytes()[: logs["ros1"].stat().st_size // 2])
    assert_user_error(invoke("run", cut, "--out", tmp_path / "out"), str(cut), "cannot read this ROS 1 bag")
    folder = tmp_path / "cut_db3"
    shutil.copytree(logs["ros2"], folder)
    storage = next(folder.glob("*.db3"))
    storage.write_bytes(storage.read_bytes()[: storage.stat().st_size // 2])
    assert_user_error(invoke("run", folder, "--out", tmp_path / "out"), str(folder), "cannot read this ROS 2 bag")
    assert not (tmp_path / "out").exists()
