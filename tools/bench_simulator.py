"""Benchmark the city simulator at default settings; prints JSON.

Usage: python tools/bench_simulator.py [--frames N] [--repeats R] [--full]
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


def _rate(fn, ks, repeats: int) -> tuple[float, float]:
    """(frames per wall-clock second, CPU milliseconds per frame), best of ``repeats`` runs
    (as timeit does: other processes sharing the machine only ever slow a run down)."""
    fn(ks[0])  # warm-up
    best_wall = best_cpu = float("inf")
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        for k in ks:
            fn(k)
        best_wall = min(best_wall, time.perf_counter() - t0)
        best_cpu = min(best_cpu, time.process_time() - c0)
    return len(ks) / best_wall, best_cpu / len(ks) * 1000


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, default=40, help="frames timed per measurement")
    ap.add_argument("--repeats", type=int, default=3, help="best of this many timing runs")
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
    }
    for name, fn in (("camera", sim.render_image), ("lidar", sim.render_scan), ("frame", sim.frame)):
        fps, cpu_ms = _rate(fn, ks, args.repeats)
        out[f"{name}_fps"] = round(fps, 1)
        out[f"{name}_ms"] = round(1000 / fps, 1)
        out[f"{name}_cpu_ms"] = round(cpu_ms, 1)
    if args.full:
        t0, c0 = time.perf_counter(), time.process_time()
        n_points = 0
        for f in TraverseSimulator(default_demo_config()).frames():
            n_points += len(f.points)
        out["demo_generation_s"] = round(time.perf_counter() - t0, 2)
        out["demo_generation_cpu_s"] = round(time.process_time() - c0, 2)
        out["demo"] = sim.stats()
        out["demo"]["mean_points_per_scan"] = round(n_points / len(sim))
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
