"""tools/trace_keyframe_calls.py: the counting, and one keyframe of a short simulated log traced."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from tool_module import load_tool

TOOL = Path(__file__).resolve().parents[2] / "tools" / "trace_keyframe_calls.py"


@pytest.fixture(scope="module")
def tool():  # noqa: ANN201
    return load_tool("trace_keyframe_calls")


def test_visits_collapse_runs_and_returns_count_modules_entered_again(tool) -> None:  # noqa: ANN001
    events = ["a", "a", "b", "b", "a", "c", "a", "b"]
    summary = tool.summarise(events)
    assert summary["order"] == ["a", "b", "a", "c", "a", "b"]
    assert (summary["visits"], summary["modules"], summary["returns"]) == (6, 3, 3)
    assert tool.summarise([])["visits"] == 0


def test_one_keyframe_of_a_simulated_log_is_traced_through_the_core(tmp_path: Path) -> None:
    log = tmp_path / "short.mcap"
    cli = [sys.executable, "-c", "from ssmvpr_slam.cli import app; app()"]
    subprocess.run([*cli, "simulate", "-c", "quick", "--frames", "12", "--out", str(log)], check=True,
                   capture_output=True)  # fmt: skip
    done = subprocess.run([sys.executable, str(TOOL), "--log", str(log), "--config", "quick", "--weights", "random",
                           "--keyframe", "2"], capture_output=True, text=True, check=True)  # fmt: skip
    trace = json.loads(done.stdout)
    assert trace["keyframe"] == 2 and trace["visits"] >= trace["modules"] > 3
    assert {"ssmvpr_slam.system", "loopclosure.detector", "frontend.keyframes"} <= set(trace["order"])
    assert trace["returns"] == trace["visits"] - trace["modules"]
