"""The demo's simulated log and settings (`ssmvpr_slam.app.simulated_logs`): the log is simulated into
the cache once and streamed from there next time; the log's own odometry makes the demo camera
only. The `demo` command end to end: test_no_loop_runs.py."""

from __future__ import annotations

import io
from pathlib import Path

import pytest
from cli_helpers import clean_ssmvpr_environment  # noqa: F401
from pydantic import ValidationError
from rich.console import Console

from ssmvpr_slam.app.simulated_logs import demo_log, simulated_log_path, with_demo_odometry
from ssmvpr_slam.config.slam import SlamConfig, load_config
from ssmvpr_slam.results.run_folder import OutputError


def _console() -> tuple[Console, io.StringIO]:
    text = io.StringIO()
    return Console(file=text, width=200), text


def _tiny() -> SlamConfig:
    config = load_config("quick")
    config.simulation = config.simulation.model_copy(update={"max_frames": 2})
    return config


def test_the_demo_log_is_simulated_into_the_cache_once_then_reused(tmp_path: Path) -> None:
    config = _tiny()
    console, text = _console()
    log = demo_log(config, console, tmp_path)
    assert log == simulated_log_path(config, tmp_path) and log.is_file() and log.stat().st_size > 0
    assert "already rendered" not in text.getvalue()
    written = log.stat().st_mtime_ns
    again = demo_log(config, console, tmp_path)
    assert again == log and log.stat().st_mtime_ns == written  # streamed from the cache, not rendered again
    assert f"simulated log (already rendered): {log}" in text.getvalue()
    assert [p.name for p in (tmp_path / "simulated").iterdir()] == [log.name]


def test_a_cache_that_cannot_hold_the_log_is_named(tmp_path: Path) -> None:
    (tmp_path / "simulated").write_text("a file where the cache folder goes")
    with pytest.raises(OutputError, match=r"the simulated log's cache folder \(\$SSMVPR_CACHE\)"):
        demo_log(_tiny(), _console()[0], tmp_path)


def test_logged_odometry_makes_the_demo_camera_only() -> None:
    config = load_config("quick")
    assert config.pipeline.use_lidar_for_loops
    logged = with_demo_odometry(config, "logged")
    assert logged.frontend.odometry.kind == "logged" and not logged.pipeline.use_lidar_for_loops
    lidar = with_demo_odometry(config, "kiss_icp")
    assert lidar.frontend.odometry.kind == "kiss_icp" and lidar.pipeline.use_lidar_for_loops
    assert config.pipeline.use_lidar_for_loops and config.frontend.odometry == load_config("quick").frontend.odometry
    with pytest.raises(ValidationError):
        with_demo_odometry(config, "wheels")
