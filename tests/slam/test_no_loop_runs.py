"""A run whose route never comes back says so in words (summary, plots) instead of showing n/a
and empty axes; the top view keeps the odometry visible under the optimised path; `demo` keeps
its simulated log in the user cache, outside the results, and reuses it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from cli_helpers import clean_ssmvpr_environment, invoke  # noqa: F401

from ssmvpr_slam.app.simulated_logs import simulated_log_path
from ssmvpr_slam.backend.se3 import make_pose, rot_z
from ssmvpr_slam.config.slam import load_config
from ssmvpr_slam.evaluation import plots
from ssmvpr_slam.evaluation.config import LoopMetricsConfig
from ssmvpr_slam.evaluation.loop_metrics import evaluate_loops


def _straight(n: int = 40) -> np.ndarray:
    return np.array([make_pose(rot_z(0.0), [2.0 * i, 0.0, 0.0]) for i in range(n)])


@pytest.fixture
def figures(monkeypatch: pytest.MonkeyPatch) -> list[Any]:
    drawn: list[Any] = []
    monkeypatch.setattr(plots, "save_figure", lambda fig, path, config=None: drawn.append(fig) or Path(path))
    return drawn


def _texts(fig: Any) -> str:
    return " ".join(t.get_text() for ax in fig.axes for t in ax.texts)


def test_plots_say_no_revisit_and_no_loops(figures: list[Any], tmp_path: Path) -> None:
    gt = _straight()
    evaluation = evaluate_loops(gt, [], LoopMetricsConfig(revisit_radius=5.0, correct_radius=10.0, min_frame_gap=10))
    assert evaluation.n_revisits == 0
    plots.plot_loop_summary(tmp_path / "loops.png", evaluation)
    plots.plot_trajectories(tmp_path / "top.png", gt, gt, gt)
    assert "no revisits in the ground truth" in _texts(figures[0])
    assert "no loops" in _texts(figures[1])
    odometry, optimised = (line for line in figures[1].axes[0].lines if line.get_label() in ("odometry", "optimised"))
    # the same path twice: the odometry is drawn wider and dashed, so it shows beside the optimised line
    assert odometry.get_linewidth() > optimised.get_linewidth() and odometry.get_linestyle() != "-"


def test_a_loop_plot_with_loops_has_no_such_note(figures: list[Any], tmp_path: Path) -> None:
    ang = np.linspace(0, 4 * np.pi, 80)
    gt = np.array([make_pose(rot_z(a), [10 * np.cos(a), 10 * np.sin(a), 0]) for a in ang])
    plots.plot_trajectories(tmp_path / "top.png", gt, gt, gt, loops=[(60, 20)])
    assert "no loops" not in _texts(figures[0])


def test_the_simulated_log_is_named_by_its_settings(tmp_path: Path) -> None:
    quick, default = load_config("quick"), load_config()
    assert simulated_log_path(quick, tmp_path) == simulated_log_path(load_config("quick"), tmp_path)
    assert simulated_log_path(quick, tmp_path) != simulated_log_path(default, tmp_path)
    assert simulated_log_path(quick, tmp_path).parent == tmp_path / "simulated"


def test_demo_keeps_its_log_in_the_cache_and_reuses_it(tmp_path: Path, weights_path: Path) -> None:
    cache, out = tmp_path / "cache", tmp_path / "results"
    args = ["demo", "-c", "quick", "--frames", 3, "--odometry", "logged", "--weights", weights_path,
            "--device", "cpu", "--out", out]  # fmt: skip
    first = invoke(*args, env={"SSMVPR_CACHE": str(cache)})
    assert first.exit_code == 0, first.output
    logs = list((cache / "simulated").glob("*.mcap"))
    assert len(logs) == 1 and "already rendered" not in first.output
    second = invoke(*args, env={"SSMVPR_CACHE": str(cache)})
    assert second.exit_code == 0 and "already rendered" in second.output, second.output
    assert list((cache / "simulated").glob("*.mcap")) == logs  # the same file, not a new one
    assert not list(out.rglob("*.mcap")) or all(p.name == "trajectory.mcap" for p in out.rglob("*.mcap"))
    assert (out / "latest-demo" / "metrics.json").is_file()
