#!/usr/bin/env python3
"""kiss-icp odometry on the simulated demo traverse: accuracy and speed; prints JSON.

Frames are rendered first, so the timing covers odometry alone (validation, deskew,
registration, map update). Accuracy: ATE after SE(3) alignment and drift per 100 m against
the simulator's ground truth.

    python tools/bench_odometry.py [--frames N]
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

from frontend.config import KissIcpConfig  # noqa: E402
from frontend.odometry import KissIcpOdometry  # noqa: E402
from frontend.simulation import TraverseSimulator, default_demo_config  # noqa: E402
from ssmvpr_slam.evaluation.metrics import ate, drift_per_100m  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=None, help="default: the whole demo traverse")
    args = parser.parse_args(argv)
    simulator = TraverseSimulator(default_demo_config(camera={"enabled": False}, max_frames=args.frames))
    frames = list(simulator.frames())
    odometry = KissIcpOdometry(KissIcpConfig())
    estimates, seconds = [], []
    for frame in frames:
        start = time.perf_counter()
        estimates.append(odometry.update(frame))
        seconds.append(time.perf_counter() - start)
    gt = np.array([f.gt_pose for f in frames])
    est = np.array(estimates)
    result = {
        "machine": {"cpus": os.cpu_count(), "load_average": os.getloadavg()},
        "frames": len(frames),
        "points_per_scan": int(np.median([len(f.points) for f in frames])),
        "frames_per_second": len(frames) / sum(seconds),
        "ms_per_frame": {"median": 1000 * float(np.median(seconds)), "p90": 1000 * float(np.percentile(seconds, 90))},
        "ate_rmse_m": ate(gt, est).stats.rmse,
        "drift_per_100m": drift_per_100m(gt, est).to_dict(),
        "skipped": odometry.stats.skipped if hasattr(odometry.stats, "skipped") else None,
        "target": {"frames_per_second": 10.0},
    }
    result["target"]["pass"] = result["frames_per_second"] >= 10.0
    json.dump(result, sys.stdout, indent=2, default=str)
    print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
