#!/usr/bin/env python3
"""Per-keyframe latency of the SLAM pipeline by stage, and its memory per keyframe; prints JSON.

Stages (metrics.json's `latency_per_keyframe`): backbone (CNN + cubes + PCA; with
`pipeline.encode_ahead` about 0, the codes coming with the keyframe, and backbone_ahead the
encoder thread's time for them, waits for the precision lock stage I and II take included), database_query
(stage I), spatial_matching (stage II), sequence_matching, gate, registration (the back end's
wait for loop registrations due at the keyframe: their whole computation when inline, only what
the worker had not finished otherwise), registration_work (the computation of the registrations
applied at the keyframe, in the worker or inline), isam2_update, total (the back end's time per
keyframe), and front_end (source, odometry and keyframe selection since the previous keyframe;
with `pipeline.overlap` it runs beside the back end). `stages_sum_per_keyframe_s` adds every
stage's seconds of a keyframe: the time one after another would take, against which the
interval shows what running them in flight together gains. `keyframe_interval_s` is the time from one
keyframe leaving the back end to the next, everything included: the end-to-end time per
keyframe a user sees, which the target (median <= 100 ms) is about. `wall_per_keyframe_s` also
spreads the start (first inference, PCA fit) over the keyframes. `cpu` is the CPU time the run
used (this process and an odometry child, all threads) per keyframe, and that divided by the
cores: the floor under which no schedule of the same work can bring `keyframe_interval_s`.
`threads_per_keyframe_s` gives each thread's (or process's) seconds a keyframe, means after the
PCA warm-up: the back end (`total`), the front end, and where they run apart the encoder
(`backbone_ahead`), the odometry's process (`odometry`) and the registration worker
(`registration_work`); `critical_path` names the slowest, whose time bounds the pace from below
on any number of cores. `back_end_wait` is the back end's wait for its next keyframe (its idle time).

    python tools/bench_slam.py [--frames 200] [--odometry kiss_icp|logged] [--log demo.mcap] [--serial]
        [--overlap | --no-overlap] [--precision fp32|bf16|int8|auto] [--omp-wait-policy PASSIVE|ACTIVE|inherit]
        [--sim-config long.yaml] [--laps N] [--no-lidar-loops] [--rss-every 100] [--weights PATH] [--device auto]

Frames come from the simulator (rendered on the fly, in the source's place) or from a log
written beforehand (`--log`, e.g. by `ssmvpr-slam simulate`: decoding then costs what it costs
in a `run`). `--rss-every N` samples the resident memory every N keyframes and fits its slope
per keyframe over the second half of the run; the place database's own bytes per place are
reported beside it, so the growth besides the database is the difference.

`--serial` runs the same frames a second time in this process one stage after another (no
overlap, no encoding ahead, loop registrations inline; the same registration lag, so the same loops and
trajectory): its figures under `serial`, `speedup` (keyframes per second over the serial ones)
and `same_loops` (both accepted the same loops).

OMP_WAIT_POLICY must be set before torch loads its OpenMP runtime, so the option is applied
before torch is imported ('inherit' leaves the environment as it is). Every result records the
load average before and after: the machine is shared.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _cpu import cpu_seconds  # noqa: E402
from _memory import peak_rss_mb, rss_mb  # noqa: E402


def _parser() -> argparse.ArgumentParser:
    from _sim_options import add_simulation_options

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_simulation_options(parser, ("--sim-config",))
    parser.add_argument("--log", type=Path, default=None, help="read frames from this log instead of simulating")
    parser.add_argument("--laps", type=int, default=None, help="laps of the simulated route (route.laps)")
    parser.add_argument("--odometry", choices=["kiss_icp", "logged"], default="kiss_icp")
    parser.add_argument("--no-lidar-loops", action="store_true", help="pipeline.use_lidar_for_loops: false")
    parser.add_argument("--overlap", action=argparse.BooleanOptionalAction, default=None,
                        help="pipeline.overlap (default: as configured)")  # fmt: skip
    parser.add_argument("--precision", default=None, help="vpr.backbone.precision")
    parser.add_argument("--omp-wait-policy", default="inherit", help="PASSIVE | ACTIVE | inherit (the environment's)")
    parser.add_argument("--rss-every", type=int, default=0, help="sample RSS every N keyframes (0: off)")
    parser.add_argument(
        "--release-heap-every", type=int, default=None, help="pipeline.release_heap_every_keyframes (0: never)"
    )
    parser.add_argument("--weights", default=None, help="VGG16 weights (default: resolve as configured)")
    parser.add_argument("--device", default=None, help="auto | cpu | cuda")
    parser.add_argument("--config", default=None)
    parser.add_argument("--serial", action="store_true",
                        help="also run the traverse one stage after another (no overlap, loops registered inline) "
                             "in this process, and report both, their ratio (speedup) and whether they accepted the "
                             "same loops (same_loops)")  # fmt: skip
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    if args.omp_wait_policy != "inherit":  # before torch (imported below) loads OpenMP
        os.environ["OMP_WAIT_POLICY"] = args.omp_wait_policy
    if args.frames is None and args.log is None and args.sim_config is None and args.laps is None:
        args.frames = 200

    from loopclosure.backbone import load_backbone
    from ssmvpr_slam.config.slam import load_config

    config = load_config(args.config)
    if args.weights:
        config.vpr.backbone.weights = args.weights
    if args.device:
        config.vpr.backbone.device = args.device
    if args.precision:
        config.vpr.backbone.precision = args.precision
    if args.overlap is not None:
        config.pipeline.overlap = args.overlap
    if args.no_lidar_loops:
        config.pipeline.use_lidar_for_loops = False
    if args.release_heap_every is not None:
        config.pipeline.release_heap_every_keyframes = args.release_heap_every
    config.frontend.odometry.kind = args.odometry
    frames, traverse = _frames(parser, args, config)
    backbone = load_backbone(config.vpr.backbone)
    result, run = _run(config, frames(), backbone, args)
    result["traverse"] = traverse
    if args.serial:  # the one-after-another schedule, same process, same frames: what the stages in flight gain
        serial_config = config.model_copy(deep=True)
        serial_config.pipeline.overlap = False
        serial_config.pipeline.registration_worker = False
        serial_config.pipeline.encode_ahead = False
        serial, serial_run = _run(serial_config, frames(), backbone, args)
        result["serial"] = serial
        result["speedup"] = (
            result["keyframes_per_second"] / serial["keyframes_per_second"] if serial["keyframes_per_second"] else None
        )
        result["same_loops"] = _accepted(run) == _accepted(serial_run)
    json.dump(result, sys.stdout, indent=2)
    print()
    failure = result["error"] or (result.get("serial") or {}).get("error")
    if failure is not None:  # the numbers above cover the frames before it
        print(f"bench_slam: the run failed: {failure}", file=sys.stderr)
        return 1
    return 0


def _frames(parser: argparse.ArgumentParser, args: argparse.Namespace, config: Any) -> tuple[Any, dict[str, Any]]:
    """A function giving the traverse's frames afresh (each schedule reads them anew), and what it is."""
    from _sim_options import simulation_config

    from frontend.simulation.simulator import TraverseSimulator
    from frontend.sources import open_source

    if args.log is not None:

        def from_log() -> Any:
            frames = iter(open_source(args.log, config.frontend.source, config.frontend.pose_files))
            return frames if args.frames is None else (f for k, f in zip(range(args.frames), frames))

        return from_log, {"log": str(args.log)}
    sim = simulation_config(parser, args, **({"route": {"laps": args.laps}} if args.laps else {}))
    if not config.pipeline.use_lidar_for_loops and args.odometry == "logged":
        sim = sim.model_copy(update={"lidar": sim.lidar.model_copy(update={"enabled": False})})  # nothing reads it
    traverse = {"simulated": sim.route.preset, "laps": sim.route.laps, "max_frames": sim.max_frames,
                "lidar": sim.lidar.enabled}  # fmt: skip
    return (lambda: TraverseSimulator(sim).frames()), traverse


def _accepted(run: Any) -> list[tuple[int, int, str]]:
    """The loops the detector accepted: (query keyframe, matched keyframe, camera)."""
    return [(r.proposal.query_id, r.proposal.match_id, r.proposal.camera) for r in run.loops if r.proposal.accepted]


def _run(config: Any, frames: Any, backbone: Any, args: argparse.Namespace) -> tuple[dict[str, Any], Any]:
    """One run of the traverse: its figures, and its result."""
    import numpy as np
    import torch

    from frontend.odometry import OdometryProcess
    from loopclosure.torch_projection import uses_torch_projection
    from ssmvpr_slam.app.pipeline import SlamPipeline
    from ssmvpr_slam.app.runner import build_odometry
    from ssmvpr_slam.evaluation.metrics import ate
    from ssmvpr_slam.run_result import latency_summary
    from ssmvpr_slam.run_state import RunState

    pipeline = SlamPipeline.build(config, build_odometry(config), backbone)
    samples: list[dict[str, float]] = []
    load_before = os.getloadavg()
    finished_at: list[float] = []  # when each keyframe left the back end: the pace the user sees
    cpu_at: list[float] = []  # this process's CPU seconds (all its threads) at the same moments

    def sample(state: RunState) -> None:
        n = len(state.keyframes)
        if n > len(finished_at):
            finished_at.append(time.perf_counter())
            cpu_at.append(time.process_time())
        if args.rss_every and n and n % args.rss_every == 0 and (not samples or samples[-1]["keyframes"] != n):
            database = pipeline.detector.database
            samples.append({
                "keyframes": n, "frames": state.frames_seen, "rss_mb": round(rss_mb(), 2),
                "database_places": 0 if database is None else len(database),
                "kept_mb": round(sum(k.nbytes for k in state.keyframes) / 1e6, 3),
                "load_1min": round(os.getloadavg()[0], 2), "seconds": round(time.perf_counter() - start, 1),
            })  # fmt: skip
            print(json.dumps(samples[-1]), file=sys.stderr, flush=True)  # a run cut short keeps its samples

    start, cpu_start = time.perf_counter(), cpu_seconds()
    state = pipeline.run(frames, sample)
    wall = time.perf_counter() - start
    summary = state.times.summary()
    n_kf = len(state.keyframes)
    intervals = np.diff(finished_at)  # from keyframe to keyframe: front end, back end and waits alike
    interval = latency_summary([{"keyframe": float(t)} for t in intervals]).get("keyframe")
    pace = None if interval is None else interval["median_s"]
    run = pipeline.finish()  # ends an odometry process too (its CPU time counts once it is reaped)
    cpu = _cpu_use(cpu_start, cpu_seconds(), wall, n_kf, np.diff(cpu_at), latency_summary)
    error = pipeline.step_error
    failure = f"{type(error).__name__}: {error}" if error is not None else pipeline.ending.source_error
    stages = ("front_end", "backbone", "backbone_ahead", "database_query", "spatial_matching", "sequence_matching",
              "gate", "registration_work", "isam2_update")  # fmt: skip
    work = [sum(row.get(k, 0.0) for k in stages) for row in state.times.rows]
    gt = [k.gt_pose for k in run.keyframes]
    result: dict[str, Any] = {
        "machine": {
            "cpus": os.cpu_count(),
            "torch": torch.__version__,
            "torch_threads": torch.get_num_threads(),
            "device": str(backbone.device),
            "cuda_device": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
            "load_average_before": load_before,
            "load_average_after": os.getloadavg(),
            "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
        },
        "settings": {
            "odometry": args.odometry,
            "overlap": config.pipeline.overlapped,
            "registration_worker": config.pipeline.registers_in_worker,
            "encode_ahead": config.pipeline.encodes_ahead,
            "registration_lag_keyframes": config.pipeline.registration_lag_keyframes,
            "precision": config.vpr.backbone.precision,
            "lidar_loops": config.pipeline.use_lidar_for_loops,
            "keyframe_image_pixels": config.pipeline.keyframe_image_pixels,
            "release_heap_every_keyframes": config.pipeline.release_heap_every_keyframes,
            "read_ahead_frames": config.pipeline.read_ahead_frames if config.pipeline.overlapped else 0,
            "odometry_ahead_frames": config.pipeline.odometry_ahead_frames
            if isinstance(pipeline.odometry, OdometryProcess)
            else 0,
            "kiss_icp_max_num_threads": config.frontend.odometry.kiss_icp.max_num_threads,
            "codes_projected_by": "torch" if uses_torch_projection(config.vpr, backbone.device) else "numpy",
            **_stage1_search(pipeline.detector.database),
        },
        "heap_trims": {"calls": pipeline.heap.calls, "seconds": round(pipeline.heap.seconds, 3)},
        "frames": state.frames_seen,
        "keyframes": n_kf,
        "rear_keyframes": state.rear_keyframes,
        "loops_proposed": len(state.loops),
        "loops_accepted": len(_accepted(run)),
        "loops_in_graph": sum(r.in_graph for r in run.loops),
        "ate_optimised_m": ate(np.array(gt), run.optimised).stats.rmse
        if n_kf and all(g is not None for g in gt)
        else None,
        "wall_s": wall,
        "frames_per_second": state.frames_seen / wall,
        "keyframes_per_second": n_kf / wall,
        "wall_per_keyframe_s": wall / n_kf if n_kf else None,
        "latency_per_keyframe_s": summary,
        "keyframe_interval_s": interval,
        "keyframe_interval_p99_s": float(np.percentile(intervals, 99)) if len(intervals) else None,
        # the pace against the work: every stage's seconds of a keyframe added up (the worker's
        # registrations and the front end included), the time one after another would take
        "stages_sum_per_keyframe_s": {"median_s": float(np.median(work)), "mean_s": float(np.mean(work))}
        if work
        else None,
        "cpu": cpu,
        **_critical_path(state.times.rows, config, isinstance(pipeline.odometry, OdometryProcess)),
        "error": failure,
        "target": {"median_keyframe_interval_s": 0.1, "pass": bool(pace is not None and pace <= 0.1)},
    }
    if args.rss_every:
        result["memory"] = _memory(samples, pipeline, state, np)
    return result, run


def _stage1_search(database: Any) -> dict[str, str | None]:
    """What stage I ran on (`exact_backend: auto` picks torch where torch sees a GPU); None
    before the database had a place."""
    out: dict[str, str | None] = {"stage1_index": None, "stage1_torch_device": None, "stage1_torch_storage": None}
    if database is None or not len(database):
        return out
    if database.filtering.index == "numpy":
        return {**out, "stage1_index": "numpy"}
    index = database.search_index()  # the index the run searched, already up to date
    return {"stage1_index": index.kind, "stage1_torch_device": index.search_device,
            "stage1_torch_storage": index.search_storage}  # fmt: skip


def _critical_path(rows: list[dict[str, float]], config: Any, odometry_process: bool) -> dict[str, Any]:
    """Each thread's (or process's) seconds a keyframe, means over the keyframes after the PCA
    warm-up (the steady stream): with the stages in flight the slowest of them bounds the pace
    whatever the others do (the critical path); one after another, the stages of the one thread
    add up. Which one it is says where a gain must come from. The source's reader thread is not
    among them (its time is not recorded by keyframe; `bench_odometry.py` times it by frame)."""
    steady = rows[config.detector.pca_warmup_keyframes :] or rows

    def mean(stage: str) -> float:
        return sum(row.get(stage, 0.0) for row in steady) / len(steady) if steady else 0.0

    settings = config.pipeline
    if settings.overlapped:
        threads = {"back_end": mean("total"), "front_end": mean("front_end")}
        if settings.encodes_ahead:
            threads["encoder"] = mean("backbone_ahead")
        if odometry_process:
            threads["odometry_process"] = mean("odometry")
    else:
        threads = {"front_and_back_end": mean("total") + mean("front_end")}
    if settings.registers_in_worker:
        threads["registration_worker"] = mean("registration_work")
    slowest = max(threads, key=lambda name: threads[name])
    seconds = threads[slowest]
    return {
        "threads_per_keyframe_s": threads,
        "critical_path": {
            "thread": slowest,
            "mean_s": seconds,
            "keyframes_per_second_bound": 1.0 / seconds if seconds > 0 else None,
        },  # fmt: skip
    }


def _cpu_use(start: tuple[float, float], end: tuple[float, float], wall: float, n_kf: int, intervals: Any,
             latency_summary: Any) -> dict[str, Any]:  # fmt: skip
    """The work a keyframe needs in core-seconds, measured rather than assumed: divided by the
    cores it is the floor no schedule of that work can beat on this machine."""
    own, children = end[0] - start[0], end[1] - start[1]
    cores = os.cpu_count() or 1
    per_kf = (own + children) / n_kf if n_kf else None
    steady = latency_summary([{"cpu": float(t)} for t in intervals]).get("cpu")  # this process, keyframe to keyframe
    return {
        "process_s": round(own, 2),
        "child_processes_s": round(children, 2),
        "utilisation_of_all_cores": round((own + children) / (wall * cores), 3) if wall else None,
        "core_s_per_keyframe": per_kf,
        "floor_per_keyframe_s": None if per_kf is None else per_kf / cores,
        "process_core_s_keyframe_to_keyframe": steady,
    }


def _memory(samples: list[dict[str, float]], pipeline: Any, state: Any, np: Any) -> dict[str, Any]:
    """RSS samples and the slope per keyframe over the second half (the first holds the warm-up,
    the city and the allocators settling); the database's own bytes per place beside it."""
    database = pipeline.detector.database
    per_place = database.bytes_per_place if database is not None else 0
    late = samples[len(samples) // 2 :]
    slope = None
    if len(late) >= 2:
        k = np.array([s["keyframes"] for s in late], float)
        rss = np.array([s["rss_mb"] for s in late], float) * 1024 * 1024
        slope = float(np.polyfit(k, rss, 1)[0])
    kept = [k.nbytes for k in state.keyframes]
    return {
        "samples": samples,
        "rss_slope_kb_per_keyframe": None if slope is None else round(slope / 1024, 1),
        "fitted_over_keyframes": [late[0]["keyframes"], late[-1]["keyframes"]] if len(late) >= 2 else None,
        "database_codes_kb_per_place": round(per_place / 1024, 1),
        "rss_slope_besides_database_kb": None if slope is None else round((slope - per_place) / 1024, 1),
        "kept_per_keyframe_kb": {
            "mean": round(float(np.mean(kept)) / 1024, 1) if kept else None,
            "max": round(float(np.max(kept)) / 1024, 1) if kept else None,
        },
        "peak_rss_mb": round(peak_rss_mb(), 1),
        "target_besides_database_kb": 150,
    }


if __name__ == "__main__":
    raise SystemExit(main())
