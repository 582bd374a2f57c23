"""Plots render headless to PNG files, atomically, and reject mismatched inputs."""

from __future__ import annotations

import numpy as np
import pytest

from ssmvpr_slam.backend.se3 import make_pose, rot_z
from ssmvpr_slam.evaluation.config import LoopMetricsConfig, PlotConfig
from ssmvpr_slam.evaluation.loop_metrics import evaluate_loops
from ssmvpr_slam.evaluation.metrics import ate
from ssmvpr_slam.evaluation.plots import (
    plot_loop_summary,
    plot_trajectories,
    plot_translation_error,
)

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
SMALL = PlotConfig(dpi=40, width_in=4, height_in=3)


@pytest.fixture(scope="module")
def run():
    ang = np.linspace(0, 4 * np.pi, 80)
    gt = np.array([make_pose(rot_z(a), [10 * np.cos(a), 10 * np.sin(a), 0]) for a in ang])
    odom = gt.copy()
    odom[:, :3, 3] += np.linspace(0, 3, 80)[:, None] * [1, 0.5, 0]
    opt = gt.copy()
    opt[:, :3, 3] += 0.05
    loops = [(60, 20), (70, 30), (75, 5)]
    return gt, odom, opt, loops


def is_png(path) -> bool:
    return path.read_bytes()[:8] == PNG_MAGIC


def test_all_plots_render(tmp_path, run):
    gt, odom, opt, loops = run
    evaluation = evaluate_loops(gt, loops, LoopMetricsConfig(revisit_radius=1.0, correct_radius=2.0, min_frame_gap=10))
    assert evaluation.loop_correct == [True, True, False]
    odom_ate, opt_ate = ate(gt, odom), ate(gt, opt)
    paths = [
        plot_trajectories(
            tmp_path / "top.png",
            gt,
            odom_ate.aligned_poses,
            opt_ate.aligned_poses,
            loops,
            evaluation.loop_correct,
            config=SMALL,
        ),
        plot_translation_error(tmp_path / "err.png", odom_ate.errors, opt_ate.errors, config=SMALL),
        plot_loop_summary(tmp_path / "loops.png", evaluation, config=SMALL),
    ]
    assert all(is_png(p) for p in paths)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["err.png", "loops.png", "top.png"]


def test_undefined_ratios_still_plot(tmp_path, run):
    gt, *_ = run
    evaluation = evaluate_loops(gt, [], LoopMetricsConfig(min_frame_gap=1000))
    assert is_png(plot_loop_summary(tmp_path / "loops.png", evaluation, config=SMALL))


def test_plot_input_errors(tmp_path, run):
    gt, odom, opt, loops = run
    with pytest.raises(ValueError, match="loop_correct"):
        plot_trajectories(tmp_path / "a.png", gt, loops=loops, loop_correct=[True], config=SMALL)
    with pytest.raises(ValueError, match="at least one"):
        plot_trajectories(tmp_path / "a.png", config=SMALL)
    with pytest.raises(ValueError, match=r"loops\[0\]"):
        plot_trajectories(tmp_path / "a.png", gt, loops=[(500, 1)], config=SMALL)
    with pytest.raises(ValueError, match="distance_m"):
        plot_translation_error(tmp_path / "b.png", np.ones(5), None, distance_m=np.ones(3), config=SMALL)
    assert not list(tmp_path.iterdir())
