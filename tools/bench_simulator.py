"""Benchmark the city simulator at default settings; prints JSON.

Usage: python tools/bench_simulator.py [--frames N] [--full]
  --full also generates the whole default demo traverse and reports its wall time and stats.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from frontend.simulation import TraverseSimulator, default_demo_config  # noqa: E402


def _rate(fn, ks) -> float:
    fn(ks[0])  # warm-up
    t0 = time.perf_counter()
    for k in ks:
        fn(k)
    return len(ks) / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, default=40, help="frames timed per measurement")
    ap.add_argument("--full", action="store_true", help="also time the whole demo traverse")
    args = ap.parse_args()

    t0 = time.perf_counter()
    sim = TraverseSimulator(default_demo_config())
    setup_s = time.perf_counter() - t0
    step = max(1, len(sim) // args.frames)
    ks = list(range(0, len(sim), step))[: args.frames]
    cfg = sim.config
    out = {
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
        "camera": f"{cfg.camera.width}x{cfg.camera.height} hfov {cfg.camera.hfov_deg}",
        "lidar": f"{cfg.lidar.beams}x{cfg.lidar.azimuths}",
        "segments": sim.city.n_segments,
        "setup_s": round(setup_s, 3),
        "camera_fps": round(_rate(sim.render_image, ks), 1),
        "lidar_fps": round(_rate(sim.render_scan, ks), 1),
        "frame_fps": round(_rate(sim.frame, ks), 1),
    }
    out["camera_ms"] = round(1000 / out["camera_fps"], 1)
    out["lidar_ms"] = round(1000 / out["lidar_fps"], 1)
    out["frame_ms"] = round(1000 / out["frame_fps"], 1)
    if args.full:
        t0 = time.perf_counter()
        n_points = 0
        for f in TraverseSimulator(default_demo_config()).frames():
            n_points += len(f.points)
        out["demo_generation_s"] = round(time.perf_counter() - t0, 2)
        out["demo"] = sim.stats()
        out["demo"]["mean_points_per_scan"] = round(n_points / len(sim))
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
