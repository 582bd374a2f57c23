"""tools/bench_odometry.py runs on a few simulated frames, with kiss-icp's settings from a preset."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "tools" / "bench_odometry.py"


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=300, check=False
    )


@pytest.mark.slow
def test_kiss_icp_settings_come_from_the_slam_preset() -> None:
    proc = _run("--frames", "4", "--slam-config", "fast")
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout)
    kiss = out["kiss_icp"]
    assert (kiss["convergence_criterion"], kiss["voxel_size"], kiss["max_points_per_voxel"]) == (1e-3, 1.5, 5)
    assert out["frames"] == 4 and out["ms_per_frame"]["mean"] > 0 and out["cpu_ms_per_frame"] > 0


def test_an_unknown_preset_is_one_line_naming_the_option() -> None:
    proc = _run("--frames", "4", "--slam-config", "nosuch")
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines()[-1].startswith("bench_odometry.py: error: --slam-config:")
