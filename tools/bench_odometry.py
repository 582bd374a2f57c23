#!/usr/bin/env python3
"""kiss-icp odometry on a simulated traverse (the demo's by default): accuracy and speed; prints JSON.

Frames are rendered first, so the timing covers odometry alone (validation, deskew,
registration, map update). Accuracy against the simulator's ground truth: ATE after SE(3)
alignment, also of the first 25 / 50 / 75 % of the frames (each aligned on its own, to see
whether ATE grows with route length), drift per 100 m, and the KITTI devkit's relative error
(% and deg / 100 m over 100..800 m segments, comparable with the KITTI leaderboard).

    python tools/bench_odometry.py [--frames N] [--config SIM_YAML] [--route POSES_FILE]
                                   [--poses-frame auto|camera|body] [--slam-config fast|FILE]
                                   [--no-kept-reuse] [--own-process [--ahead N]]

`--slam-config` takes kiss-icp's settings from a SLAM config or preset
(`frontend.odometry.kiss_icp`; e.g. `fast`); without it, the default preset's as `run` uses them
(SSMVPR_ variables apply, e.g. SSMVPR_FRONTEND__ODOMETRY__KISS_ICP__MAX_NUM_THREADS=8).
`input_checks_ms_per_frame` is the checks every scan passes before kiss-icp (non-finite,
placeholder and out-of-range points dropped), part of the odometry's update.
`keep_scan_ms_per_frame` is what keeping each scan for loop registration costs after it, as a
run keeps it: kiss-icp's own voxelised scan where its size is the kept one, or with
`--no-kept-reuse` the deskewed scan filtered again.

`--own-process` runs kiss-icp in a process of its own, as an overlapped `run` does, and hands it
each frame `--ahead` frames before its pose is taken (`pipeline.odometry_ahead_frames`; 0: one at
a time). `front_end_ms_per_frame` is then the pace of the loop that takes the poses and keeps the
scans: what the front end's thread sees, against `ms_per_frame`, the odometry's own update.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from frontend.config import OdometryConfig  # noqa: E402
from frontend.odometry import KissIcpOdometry, OdometryProcess  # noqa: E402
from frontend.odometry.own_process import submitted_ahead  # noqa: E402
from frontend.simulation import TraverseSimulator  # noqa: E402
from ssmvpr_slam.backend.kept_scan import keep_scan  # noqa: E402
from ssmvpr_slam.config.slam import ConfigError, load_config  # noqa: E402
from ssmvpr_slam.evaluation.metrics import ate, drift_per_100m, kitti_relative_error, path_lengths  # noqa: E402
from ssmvpr_slam.kept_keyframe import kept_voxel  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _cpu import cpu_seconds  # noqa: E402
from _sim_options import add_simulation_options, simulation_config  # noqa: E402

PREFIXES = (0.25, 0.5, 0.75, 1.0)
"""Fractions of the frames whose ATE is reported, each SE(3)-aligned on its own."""


def ate_by_prefix(gt: np.ndarray, est: np.ndarray) -> list[dict[str, float | int]]:
    """ATE RMSE of growing prefixes: a global alignment hides where along the route error builds up."""
    lengths = path_lengths(gt)
    out = []
    for fraction in PREFIXES:
        n = min(len(gt), max(3, round(fraction * len(gt))))
        out.append({"fraction": fraction, "frames": n, "path_m": round(float(lengths[n - 1]), 1),
                    "ate_rmse_m": ate(gt[:n], est[:n]).stats.rmse})  # fmt: skip
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_simulation_options(parser, ("--config", "--sim-config"))
    parser.add_argument(
        "--slam-config", default=None, help="SLAM preset or YAML whose frontend.odometry.kiss_icp to use"
    )
    parser.add_argument(
        "--no-kept-reuse", action="store_true", help="filter the deskewed scan again to keep it (as before reuse)"
    )
    parser.add_argument("--own-process", action="store_true", help="kiss-icp in a process of its own")
    parser.add_argument("--ahead", type=int, default=1, help="with --own-process: frames handed over ahead")
    args = parser.parse_args(argv)
    if args.ahead < 0:
        parser.error("--ahead must be 0 or more")
    try:
        slam_config = load_config(args.slam_config)
    except ConfigError as exc:
        parser.error(f"--slam-config: {exc}")
    kiss_icp, voxel = slam_config.frontend.odometry.kiss_icp, kept_voxel(slam_config)
    if args.frames is not None and args.frames < 3:
        parser.error("--frames must be at least 3")
    simulator = TraverseSimulator(simulation_config(parser, args, camera={"enabled": False}))
    frames = list(simulator.frames())
    kept = None if args.no_kept_reuse else voxel
    if args.own_process:
        odometry: KissIcpOdometry | OdometryProcess = OdometryProcess(OdometryConfig(kind="kiss_icp", kiss_icp=kiss_icp),
                                                                      kept_voxel=kept)  # fmt: skip
        stream = submitted_ahead(iter(frames), odometry, args.ahead)
    else:
        odometry, stream = KissIcpOdometry(kiss_icp, kept), iter(frames)
    estimates, seconds, keeping = [], [], []
    cpu_start = cpu_seconds()
    loop_start = time.perf_counter()
    for frame in stream:
        start = time.perf_counter()
        estimates.append(odometry.update(frame))
        waited = time.perf_counter() - start
        seconds.append(odometry.last_update_s if args.own_process else waited)  # the odometry's own time
        if voxel is not None:
            start = time.perf_counter()
            keep_scan(odometry.last_scan, voxel, voxelised=odometry.last_scan_voxel == voxel)
            keeping.append(time.perf_counter() - start)
    front_end = (time.perf_counter() - loop_start) / len(frames)
    if args.own_process:
        odometry.close()  # its CPU time counts once it is reaped
    cpu_seconds_used = sum(cpu_seconds()) - sum(cpu_start)
    checker, checks = KissIcpOdometry(kiss_icp), []  # the input checks before kiss-icp, part of every update
    for frame in frames:
        start = time.perf_counter()
        checker.clean(frame)
        checks.append(time.perf_counter() - start)
    gt = np.array([f.gt_pose for f in frames])
    est = np.array(estimates)
    result = {
        "machine": {"cpus": os.cpu_count(), "load_average": os.getloadavg()},
        "frames": len(frames),
        "points_per_scan": int(np.median([len(f.points) for f in frames])),
        "frames_per_second": len(frames) / sum(seconds),
        "kiss_icp": kiss_icp.model_dump(),
        "ms_per_frame": {
            "median": 1000 * float(np.median(seconds)),
            "p90": 1000 * float(np.percentile(seconds, 90)),
            "mean": 1000 * float(np.mean(seconds)),
        },
        # all threads (kiss-icp's TBB workers too): what a frame costs a CPU shared with the backbone
        "cpu_ms_per_frame": 1000 * cpu_seconds_used / len(frames),
        "keep_scan_ms_per_frame": 1000 * float(np.median(keeping)) if keeping else None,
        "input_checks_ms_per_frame": 1000 * float(np.median(checks)),
        "own_process": args.own_process,
        "ahead": args.ahead if args.own_process else None,
        "front_end_ms_per_frame": 1000 * front_end,
        "kept_scan_reused": odometry.last_scan_voxel is not None,
        "path_m": float(path_lengths(gt)[-1]),
        "ate_rmse_m": ate(gt, est).stats.rmse,
        "ate_by_prefix": ate_by_prefix(gt, est),
        "drift_per_100m": drift_per_100m(gt, est).to_dict(),
        "kitti_rel_error": kitti_relative_error(gt, est).to_dict(),
        "skipped": odometry.stats.skipped if hasattr(odometry.stats, "skipped") else None,
        "target": {"frames_per_second": 10.0},
    }
    result["target"]["pass"] = result["frames_per_second"] >= 10.0
    json.dump(result, sys.stdout, indent=2, default=str)
    print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
