"""tools/bench_slam.py runs end to end on a short simulated traverse, stages overlapped (the
odometry in its own process), then one stage after another (`--serial`), and prints one JSON
object with the pace per keyframe, the CPU time it cost, and the two schedules compared."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

SCRIPT = Path(__file__).resolve().parents[2] / "tools" / "bench_slam.py"


@pytest.mark.slow
def test_bench_slam_reports_stages_and_the_pace_per_keyframe(weights_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, str(SCRIPT), "--frames", "24", "--overlap", "--serial", "--weights", str(weights_path)],
        capture_output=True, text=True, timeout=600, check=False,
        # a warm-up short enough (3 keyframes, 48 stage-I vectors) for the short run to query stage I
        # and the encoder's thread on, as `auto` puts it on 4 cores or more
        env={**os.environ, "SSMVPR_DETECTOR__PCA_WARMUP_KEYFRAMES": "3", "SSMVPR_VPR__FILTERING__PCA__DIM": "32",
             "SSMVPR_PIPELINE__ENCODE_AHEAD": "true"},
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout)  # stdout is exactly one JSON object
    assert out["frames"] == 24 and out["settings"]["overlap"] is True and out["error"] is None
    # stage I searched exactly: torch on a GPU, faiss without one (exact_backend auto)
    assert out["settings"]["stage1_index"] == "exact"
    expected_device = "cuda" if torch.cuda.is_available() else None
    assert out["settings"]["stage1_torch_device"] == expected_device
    n = out["keyframes"]
    assert 6 <= n <= 24
    stages = out["latency_per_keyframe_s"]
    assert stages["backbone"]["median_s"] > 0 and stages["front_end"]["median_s"] > 0
    # the front end by part: kiss-icp in its process (handed a frame ahead), the wait for it, keeping
    assert out["settings"]["odometry_ahead_frames"] == 1
    assert stages["odometry"]["median_s"] > 0 and stages["keyframe_keeping"]["median_s"] > 0
    assert stages["odometry_wait"]["mean_s"] >= 0
    pace = out["keyframe_interval_s"]
    assert 0 < pace["median_s"] <= pace["p90_s"] and pace["mean_s"] > 0
    assert pace["mean_s"] * (n - 1) <= out["wall_s"]  # the intervals lie within the run
    assert out["target"]["pass"] == (pace["median_s"] <= out["target"]["median_keyframe_interval_s"])
    # the CPU time the run used, the odometry child's included (overlap puts kiss-icp there)
    cpu = out["cpu"]
    assert cpu["child_processes_s"] > 0 and cpu["process_s"] > 0
    assert cpu["core_s_per_keyframe"] == pytest.approx((cpu["process_s"] + cpu["child_processes_s"]) / n, rel=0.01)
    assert cpu["floor_per_keyframe_s"] == pytest.approx(cpu["core_s_per_keyframe"] / out["machine"]["cpus"])
    assert 0 < cpu["utilisation_of_all_cores"] <= 1.05  # no more CPU than the cores had
    assert cpu["floor_per_keyframe_s"] * n <= out["wall_s"] * 1.05
    # the serial schedule in the same process: the same loops, its own figures, their ratio
    serial = out["serial"]
    assert serial["settings"]["overlap"] is False and serial["settings"]["registration_worker"] is False
    assert serial["settings"]["encode_ahead"] is False
    assert serial["keyframes"] == n and serial["error"] is None
    serial_stages = serial["latency_per_keyframe_s"]  # kiss-icp in this process: the wait is its update
    assert serial_stages["odometry_wait"]["mean_s"] == pytest.approx(serial_stages["odometry"]["mean_s"])
    assert out["same_loops"] is True and out["loops_accepted"] == serial["loops_accepted"]
    assert out["speedup"] == pytest.approx(out["keyframes_per_second"] / serial["keyframes_per_second"])
    assert out["keyframe_interval_p99_s"] >= pace["median_s"]
    assert out["stages_sum_per_keyframe_s"]["median_s"] > 0
    # the critical path: each thread's time a keyframe, the slowest named, and the pace it allows
    for run in (out, serial):
        threads, critical = run["threads_per_keyframe_s"], run["critical_path"]
        assert critical["mean_s"] == max(threads.values()) == threads[critical["thread"]] > 0
        assert critical["keyframes_per_second_bound"] == pytest.approx(1 / critical["mean_s"])
    assert out["settings"]["encode_ahead"] is True
    threads = out["threads_per_keyframe_s"]
    assert set(threads) >= {"back_end", "front_end", "odometry_process", "encoder"}
    assert threads["encoder"] > 0 and stages["backbone_ahead"]["mean_s"] > 0  # keyframes after the warm-up
    assert stages["back_end_wait"]["median_s"] >= 0
    assert set(serial["threads_per_keyframe_s"]) == {"front_and_back_end"}  # one thread: the stages add up
