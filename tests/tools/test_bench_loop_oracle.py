"""tools/bench_loop_oracle.py: perfect loops remove the wheel-odometry drift of the sim; JSON out."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[2] / "tools" / "bench_loop_oracle.py"


def test_ideal_loops_correct_wheel_drift_on_a_short_traverse() -> None:
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), "--odometry", "logged", "--frames", "360"],
        capture_output=True, text=True, timeout=300, check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout)["logged"]
    assert out["keyframes"] > 200
    assert out["odometry_ate_m"] > 1.0  # 360 frames of the drifting wheel odometry
    forward = out["forward"]
    assert forward["loops"] > 50  # lap 2 revisits lap 1
    assert forward["optimised_ate_m"] < 0.6 * out["odometry_ate_m"]
    assert out["forward_and_reverse"]["loops"] >= forward["loops"]
    # the KITTI devkit's relative error (over 100 m+ keyframe segments) drops with the loops too
    odom_kitti, opt_kitti = out["odometry_kitti_rel_error"], forward["optimised_kitti_rel_error"]
    assert odom_kitti["n_segments"] > 0 and opt_kitti["n_segments"] == odom_kitti["n_segments"]
    assert opt_kitti["rotation_deg_per_100m"] < odom_kitti["rotation_deg_per_100m"]


def test_too_few_frames_is_refused() -> None:
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), "--frames", "1"], capture_output=True, text=True, timeout=60, check=False
    )
    assert proc.returncode == 2
    assert "--frames must be at least 2" in proc.stderr


def test_bad_route_or_simulation_file_is_refused(tmp_path: Path) -> None:
    for option in (["--route", str(tmp_path / "missing.tum")], ["--sim-config", str(tmp_path / "missing.yaml")]):
        proc = subprocess.run(
            [sys.executable, str(SCRIPT), "--odometry", "logged", *option],
            capture_output=True, text=True, timeout=60, check=False,
        )  # fmt: skip
        assert proc.returncode == 2, proc.stderr[-2000:]
        assert "missing." in proc.stderr
