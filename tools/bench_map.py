#!/usr/bin/env python3
"""Many sessions, one map: simulate N sessions of one city, run `map` on them, print JSON.

    python tools/bench_map.py --sessions 4 [--frames-per-session F] [--workers W] [--config PRESET]
                              [--weights FILE] [--out DIR] [--ray-address ADDR] [--then-add] [--camera-only]

Each session drives its own loop of the city's street grid (`frontend.simulation.sessions`),
from its own start, by day or at dusk, with its own traffic and odometry drift; the ground truth
of all of them is in one world frame. The logs are simulated once into the user cache (as `demo`
keeps its log) and streamed again on later calls. Printed (these names are read by other checks):
sessions, sessions_merged, cross_session_precision, cross_session_recall, ate_merged_m (one SE(3)
alignment for the whole map), ate_oracle_m (the same sessions joined by perfect cross-session
loops: `ssmvpr_slam.multi_session.evaluation.oracle_ate`), wall_s (the `map` call, simulation
excluded), plus keyframes, keyframes_per_second_per_worker, the per-session ATE in the map and
of each session's own run, and the loop counts. --then-add: one more session of the city is run
in the merged map (`run --map`: its prior-map loops) and then added to it (`map --add`).
--camera-only: the sessions run without LiDAR loops over their logged (wheel) odometry, so
every loop, within a session and between sessions, is verified by two views (the oracle's loops
then carry the two-view place prior's sigmas).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from rich.console import Console  # noqa: E402

from frontend.simulation.sessions import city_sessions  # noqa: E402
from ssmvpr_slam.app.runner import run_log, simulate_to_mcap  # noqa: E402
from ssmvpr_slam.app.simulated_logs import simulated_log_path  # noqa: E402
from ssmvpr_slam.config.slam import SlamConfig, load_config  # noqa: E402
from ssmvpr_slam.multi_session.evaluation import oracle_ate  # noqa: E402
from ssmvpr_slam.multi_session.runner import map_logs  # noqa: E402
from ssmvpr_slam.multi_session.session_map import SessionMap  # noqa: E402


def localise_and_add(log: Path, folder: Path, config: SlamConfig, console: Console) -> dict[str, object]:
    """One more session: `run --map` in the merged map, then `map --map ... --add`."""
    start = time.perf_counter()
    _, run_metrics = run_log(log, config, folder, console, name="run")
    localised = {"seconds": time.perf_counter() - start, "prior_map_loops": run_metrics.get("prior_map_loops"),
                 "ate_optimised_m": run_metrics.get("ate_optimised", {}).get("rmse")}  # fmt: skip
    start = time.perf_counter()
    _, metrics = map_logs([log], config, console, add_to=folder)
    merged = {key: metrics.get(key) for key in ("sessions", "sessions_merged", "cross_session_precision",
                                                "cross_session_recall", "ate_merged_m", "maps")}  # fmt: skip
    return {"run_map": localised, "map_add": {**merged, "wall_s": time.perf_counter() - start}}


def loop_sigmas(config: SlamConfig, camera_only: bool) -> tuple[float, float]:
    """(rotation, translation) sigmas of the map's loops: ICP's, or the two-view place prior's."""
    if camera_only:
        two_view = config.backend.registration.two_view
        return two_view.rot_sigma, two_view.translation_sigma
    lidar = config.backend.registration.lidar
    return lidar.rot_sigma, lidar.trans_sigma


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sessions", type=int, default=4)
    parser.add_argument("--frames-per-session", type=int, default=None, help="default: each session's whole loop")
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--config", default="quick", help="preset or YAML (default quick: 3 Hz, 30 m blocks)")
    parser.add_argument("--block-size", type=float, default=60.0, help="m; the city's blocks (sessions ~600 m at 60)")
    parser.add_argument("--weights", default=None)
    parser.add_argument("--out", type=Path, default=None, help="where the map goes (default: a temporary folder)")
    parser.add_argument("--ray-address", default=None)
    parser.add_argument("--then-add", action="store_true",
                        help="then one more session of the city: localised in the map (run --map), then merged (--add)")  # fmt: skip
    parser.add_argument("--camera-only", action="store_true",
                        help="no LiDAR loops, the logs' wheel odometry: loops verified by two views")  # fmt: skip
    args = parser.parse_args()
    if args.sessions < 1 or args.workers < 1:
        parser.error("--sessions and --workers must be >= 1")
    overrides = {
        "simulation": {"camera": {"rear": True}, "city": {"block_size_m": args.block_size},
                       "max_frames": args.frames_per_session},
        "map": {"workers": args.workers},
    }  # fmt: skip
    if args.weights:
        overrides["vpr"] = {"backbone": {"weights": args.weights}}
    if args.camera_only:
        overrides["pipeline"] = {"use_lidar_for_loops": False}
        overrides["frontend"] = {"odometry": {"kind": "logged"}}
    config = load_config(args.config, overrides)
    if args.camera_only:  # the renderer's field of view where a cached log carries no calibration
        config.backend.registration.two_view.hfov_deg = config.simulation.camera.hfov_deg
    console = Console(stderr=True)
    logs = []
    for simulation in city_sessions(config.simulation, args.sessions + int(args.then_add)):
        session = config.model_copy(update={"simulation": simulation})
        path = simulated_log_path(session)
        if not path.exists():
            path.parent.mkdir(parents=True, exist_ok=True)
            simulate_to_mcap(session, path, console)
        logs.append(path)
    later = logs.pop() if args.then_add else None
    with tempfile.TemporaryDirectory(prefix="bench_map_") as scratch:
        named = []  # each session named by its number (`map` names a session after its log)
        for k, path in enumerate([*logs, *([later] if later else [])]):
            link = Path(scratch) / f"session{k}.mcap"
            link.symlink_to(path)
            named.append(link)
        logs, later = named[: len(logs)], (named[-1] if later else None)
        config.results.out_dir = str(args.out or Path(scratch) / "out")
        start = time.perf_counter()
        folder, metrics = map_logs(logs, config, console, ray_address=args.ray_address)
        wall = time.perf_counter() - start
        records = [r for r in metrics["session_results"] if r["error"] is None]
        sessions = [SessionMap.load(r["name"], r["log"], folder / r["folder"], config.vpr) for r in records]
        oracle = oracle_ate(sessions, config.evaluation.loops.revisit_radius, *loop_sigmas(config, args.camera_only))
        added = None if later is None else localise_and_add(later, folder, config, console)
    keyframes = sum(len(s) for s in sessions)
    session_seconds = sum(r["seconds"] for r in records)
    out = {
        "sessions": metrics["sessions"],
        "sessions_merged": metrics["sessions_merged"],
        "cross_session_precision": metrics["cross_session_precision"],
        "cross_session_recall": metrics["cross_session_recall"],
        "ate_merged_m": metrics.get("ate_merged_m"),
        "ate_oracle_m": oracle,
        "wall_s": wall,
        "workers": args.workers,
        "camera_only": args.camera_only,
        "keyframes": keyframes,
        "keyframes_per_second_per_worker": keyframes / session_seconds if session_seconds else None,
        "session_seconds": {r["name"]: r["seconds"] for r in records},
        "ate_per_session_m": metrics.get("ate_per_session_m"),
        "ate_own_run_m": metrics.get("ate_own_run_m"),
        "cross_session_loops": metrics["cross_session_loops"],
        "cross_session_revisit_keyframes": metrics["cross_session_revisit_keyframes"],
        "maps": metrics["maps"],
        "links": metrics["links"],
        "failed": [r["name"] for r in metrics["session_results"] if r["error"] is not None],
    }
    if added is not None:
        out["next_session"] = added
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
