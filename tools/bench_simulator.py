"""Benchmark the city simulator at default settings; prints JSON.

Usage: python tools/bench_simulator.py [--frames N] [--repeats R] [--full]
       python tools/bench_simulator.py --stream-mcap [--sim-config YAML] [--route FILE] [--laps N]
  --full also generates the whole default demo traverse and reports its wall time and stats.
  --stream-mcap writes a whole traverse to an MCAP log (in a temporary folder, deleted after)
  and reports the resident memory at every tenth of the frames: a long route must stream at
  bounded memory, so RSS may grow with the city (built once, along the route) but not with the
  frames written.
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

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _memory import peak_rss_mb, rss_mb  # noqa: E402
from _sim_options import add_simulation_options, simulation_config  # noqa: E402


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


def stream_mcap(args: argparse.Namespace, parser: argparse.ArgumentParser) -> dict:
    """Simulate a whole traverse into an MCAP log; RSS along the way."""
    import tempfile

    from frontend.sources import write_frames

    overrides = {"route": {"laps": args.laps}} if args.laps else {}
    config = simulation_config(parser, args, **overrides)
    rss_start = rss_mb()
    t0 = time.perf_counter()
    sim = TraverseSimulator(config)
    setup_s = time.perf_counter() - t0
    rss_after_setup = rss_mb()
    n = len(sim)
    marks = {max(1, round(n * i / 10)) for i in range(1, 11)}
    samples: list[dict[str, float]] = []

    def frames():  # noqa: ANN202
        for k, frame in enumerate(sim.frames(), start=1):
            yield frame
            if k in marks:
                samples.append({"frames": k, "rss_mb": round(rss_mb(), 1)})

    with tempfile.TemporaryDirectory() as tmp:
        log = Path(tmp) / "traverse.mcap"
        t1 = time.perf_counter()
        written = write_frames(frames(), log)
        seconds = time.perf_counter() - t1
        size_mb = log.stat().st_size / 1e6
    stats = sim.stats()
    rss = [s["rss_mb"] for s in samples]
    return {
        "route": config.route.preset,
        "frames": written,
        "path_m": round(float(stats["length_m"]), 1) if "length_m" in stats else None,
        "setup_s": round(setup_s, 1),
        "frames_per_second": round(written / seconds, 2),
        "mcap_mb": round(size_mb, 1),
        "rss_mb": {"start": round(rss_start, 1), "after_setup": round(rss_after_setup, 1), "by_frames": samples},
        "rss_growth_second_half_mb": round(rss[-1] - rss[len(rss) // 2 - 1], 1) if len(rss) >= 2 else None,
        "peak_rss_mb": round(peak_rss_mb(), 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeats", type=int, default=3, help="best of this many timing runs")
    ap.add_argument("--full", action="store_true", help="also time the whole demo traverse")
    ap.add_argument("--stream-mcap", action="store_true", help="write a whole traverse to MCAP; RSS along the way")
    ap.add_argument("--laps", type=int, default=None, help="--stream-mcap: laps of a preset route")
    add_simulation_options(ap, ("--sim-config",))
    args = ap.parse_args()
    if args.stream_mcap:
        print(json.dumps(stream_mcap(args, ap), indent=2))
        return
    args.frames = args.frames or 40

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
