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
    assert 0 < out["input_checks_ms_per_frame"] < out["ms_per_frame"]["mean"]  # part of every update
    # fast's map voxel (0.75 m) is not the kept size (0.5 m): the deskewed scan is filtered again
    assert out["kept_scan_reused"] is False and out["keep_scan_ms_per_frame"] > 0


@pytest.mark.slow
def test_the_default_keeps_kiss_icp_s_own_voxelised_scan_unless_told_not_to() -> None:
    reused, filtered = _run("--frames", "4"), _run("--frames", "4", "--no-kept-reuse")
    assert reused.returncode == 0 and filtered.returncode == 0, reused.stderr[-2000:] + filtered.stderr[-2000:]
    assert json.loads(reused.stdout)["kept_scan_reused"] is True
    assert json.loads(filtered.stdout)["kept_scan_reused"] is False


@pytest.mark.slow
def test_kiss_icp_in_its_own_process_a_frame_ahead_gives_the_same_trajectory() -> None:
    here, there = _run("--frames", "6"), _run("--frames", "6", "--own-process", "--ahead", "1")
    assert here.returncode == 0 and there.returncode == 0, here.stderr[-2000:] + there.stderr[-2000:]
    a, b = json.loads(here.stdout), json.loads(there.stdout)
    assert (a["own_process"], b["own_process"], b["ahead"]) == (False, True, 1)
    assert b["ate_rmse_m"] == pytest.approx(a["ate_rmse_m"], abs=1e-6)
    assert b["front_end_ms_per_frame"] > 0 and b["cpu_ms_per_frame"] > 0  # the child's CPU time counted


def test_an_unknown_preset_is_one_line_naming_the_option() -> None:
    proc = _run("--frames", "4", "--slam-config", "nosuch")
    assert proc.returncode == 2
    assert proc.stderr.strip().splitlines()[-1].startswith("bench_odometry.py: error: --slam-config:")
