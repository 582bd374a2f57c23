"""A run takes its camera's calibration from the log for two-view registration: a simulated log
carries the renderer's K beside each image, and `run` puts it into the two-view settings unless
the config gives its own (`ssmvpr_slam.app.runner.use_calibration`)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from frontend.simulation.simulator import TraverseSimulator
from frontend.sources import open_source, write_frames
from ssmvpr_slam.app.runner import use_calibration
from ssmvpr_slam.config.slam import load_config


def _simulated_log(path: Path) -> tuple[Path, np.ndarray]:
    config = load_config("quick", {"simulation": {"max_frames": 3}})
    simulator = TraverseSimulator(config.simulation)
    write_frames(simulator.frames(), path, config.frontend.writer, simulator.intrinsics)
    return path, simulator.intrinsics["camera"].k


def test_a_run_uses_the_logs_calibration_unless_the_config_has_one(tmp_path: Path) -> None:
    path, k = _simulated_log(tmp_path / "sim.mcap")
    config = load_config()
    source = open_source(path, config.frontend.source, config.frontend.pose_files)
    assert config.backend.registration.two_view.fx is None  # the default: none
    use_calibration(config, source)
    two_view = config.backend.registration.two_view
    assert (two_view.fx, two_view.fy, two_view.cx, two_view.cy) == (k[0, 0], k[1, 1], k[0, 2], k[1, 2])
    hfov = math.degrees(2 * math.atan((2 * two_view.cx + 1) / (2 * two_view.fx)))
    assert hfov == pytest.approx(config.simulation.camera.hfov_deg)  # the renderer's own field of view
    given = load_config(None, {"backend": {"registration": {"two_view": {"fx": 123.0}}}})
    use_calibration(given, source)
    assert given.backend.registration.two_view.fx == 123.0 and given.backend.registration.two_view.cx is None


def test_a_log_without_calibration_leaves_the_field_of_view_guess(tmp_path: Path) -> None:
    config = load_config("quick", {"simulation": {"max_frames": 3}})
    path = tmp_path / "plain.mcap"
    write_frames(TraverseSimulator(config.simulation).frames(), path, config.frontend.writer)
    source = open_source(path, config.frontend.source, config.frontend.pose_files)
    use_calibration(config, source)
    assert config.backend.registration.two_view.fx is None
