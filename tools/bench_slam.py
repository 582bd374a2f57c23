#!/usr/bin/env python3
"""Per-keyframe latency of the SLAM pipeline by stage, on a simulated traverse; prints JSON.

Stages: backbone (CNN + cubes + PCA), database_query (stage I), spatial_matching (stage II),
gate, registration (ICP / two-view, only on gate-accepted proposals), isam2_update, total.
Target: median total <= 0.5 s per keyframe on a 2-core CPU.

    python tools/bench_slam.py [--frames 200] [--odometry kiss_icp|logged] [--weights PATH] [--device auto]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import torch


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--odometry", choices=["kiss_icp", "logged"], default="kiss_icp")
    parser.add_argument("--weights", default=None, help="VGG16 weights (default: resolve as configured)")
    parser.add_argument("--device", default=None, help="auto | cpu | cuda")
    parser.add_argument("--config", default=None)
    args = parser.parse_args(argv)

    from frontend.odometry import make_odometry
    from frontend.simulation.simulator import TraverseSimulator, default_demo_config
    from loopclosure.backbone import load_backbone
    from ssmvpr_slam.config import load_config
    from ssmvpr_slam.pipeline import SlamPipeline

    config = load_config(args.config)
    if args.weights:
        config.vpr.backbone.weights = args.weights
    if args.device:
        config.vpr.backbone.device = args.device
    config.frontend.odometry.kind = args.odometry
    simulator = TraverseSimulator(default_demo_config(max_frames=args.frames))
    backbone = load_backbone(config.vpr.backbone)
    pipeline = SlamPipeline(config, make_odometry(config.frontend.odometry, config.frontend.pose_files), backbone)
    start = time.perf_counter()
    state = pipeline.run(simulator.frames())
    wall = time.perf_counter() - start
    summary = state.times.summary()
    total = summary.get("total", {}).get("median_s")
    result = {
        "machine": {
            "cpus": os.cpu_count(),
            "torch": torch.__version__,
            "torch_threads": torch.get_num_threads(),
            "device": str(backbone.device),
            "cuda_device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
            "load_average": os.getloadavg(),
        },
        "frames": state.frames_seen,
        "keyframes": len(state.keyframes),
        "loops_proposed": len(state.loops),
        "loops_in_graph": sum(r.in_graph for r in state.loops),
        "wall_s": wall,
        "frames_per_second": state.frames_seen / wall,
        "keyframes_per_second": len(state.keyframes) / wall,
        "latency_per_keyframe_s": summary,
        "target": {"median_total_s": 0.5, "pass": bool(total is not None and total <= 0.5)},
    }
    json.dump(result, sys.stdout, indent=2)
    print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
