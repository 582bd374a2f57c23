"""`run --frames N`: a log processed up to its N-th frame, as a complete result."""

from __future__ import annotations

import json
from pathlib import Path

from cli_helpers import assert_user_error, clean_ssmvpr_environment, invoke  # noqa: F401 - autouse fixture

from frontend.config import McapWriterConfig
from frontend.simulation import SimulationConfig, TraverseSimulator
from frontend.sources import write_frames


def test_run_stops_after_the_given_frames(tmp_path: Path, weights_path: Path) -> None:
    log = tmp_path / "log.mcap"
    write_frames(TraverseSimulator(SimulationConfig(max_frames=9, lidar={"enabled": False})).frames(), log,
                 McapWriterConfig(chunk_size=64 * 1024))  # fmt: skip
    out = tmp_path / "out"
    result = invoke("run", log, "--frames", 5, "--odometry", "logged", "--weights", weights_path, "--device", "cpu",
                    "--out", out)  # fmt: skip
    assert result.exit_code == 0, (result.output, result.exception)
    folder = out / "latest"
    metrics = json.loads((folder / "metrics.json").read_text())
    assert metrics["frames"] == 5 and not metrics.get("interrupted")
    assert "max_frames: 5" in (folder / "config.yaml").read_text()  # a resume keeps the limit
    rows = [line for line in (folder / "odometry.tum").read_text().splitlines() if not line.startswith("#")]
    assert 1 <= len(rows) <= 5


def test_frames_must_be_positive_and_are_not_for_a_resume(tmp_path: Path) -> None:
    log = tmp_path / "missing.mcap"
    assert_user_error(invoke("run", log, "--frames", 0), "max_frames")
    assert_user_error(invoke("run", log, "--resume", tmp_path, "--frames", 3), "--frames cannot be combined")
