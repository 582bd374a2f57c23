"""`map`: many logs into one map. Reads top to bottom as its steps:

1. start Ray (local, or the cluster at `--ray-address`) and the workers;
2. the shared PCA codebooks (given, the earlier map's with `--add`, or fitted on every log);
3. each log as a session, in parallel on the workers; a log that fails is reported by name;
4. each session's keyframes matched against the other sessions' places (Ray tasks);
5. sessions joined where enough verified loops agree (`linking`); one graph per map, solved
   robustly; sessions left apart are separate maps;
6. evaluation against the ground truth, when the sessions have it in one world frame;
7. the merged map written into a staging folder and published as one unit.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from ssmvpr_common.errors import SsmvprError
from ssmvpr_common.text_files import read_text
from ssmvpr_slam.backend.graph_optimizer import OptimizationResult
from ssmvpr_slam.config.slam import SlamConfig, resolve_weights_first
from ssmvpr_slam.errors import SlamError
from ssmvpr_slam.multi_session.cross_loops import CrossLoop
from ssmvpr_slam.multi_session.evaluation import evaluate_map, loop_distance
from ssmvpr_slam.multi_session.linking import SessionLinks, graph_loops, link_sessions
from ssmvpr_slam.multi_session.merged_graph import (
    CrossEdge,
    MapGraph,
    build_map_graph,
    cross_edge_inliers,
    solve_map_graph,
)
from ssmvpr_slam.multi_session.ray_cluster import ray_session
from ssmvpr_slam.multi_session.scheduling import all_cross_loops, fit_codebooks, run_sessions
from ssmvpr_slam.multi_session.session_map import SessionMap
from ssmvpr_slam.multi_session.staging import CODEBOOKS, FINISHED, PLAN, MapStaging, map_plan
from ssmvpr_slam.multi_session.stop import MapStop, MapStopped
from ssmvpr_slam.multi_session.workers import SessionOutcome
from ssmvpr_slam.multi_session.writer import (
    plot_map,
    write_config,
    write_cross_loops,
    write_manifest,
    write_map_database,
    write_map_graph,
    write_trajectories,
)
from ssmvpr_slam.prior_map import MAP_MANIFEST
from ssmvpr_slam.results.run_folder import interrupts_deferred, write_json


class MapError(SlamError, ValueError):
    """A map that cannot be made or extended (no session succeeded, a map folder that is not one)."""


def session_name(index: int, log: Path) -> str:
    """`s<index>_<log stem>`, in characters any file system takes."""
    stem = re.sub(r"[^A-Za-z0-9_.-]+", "_", log.stem if log.suffix else log.name).strip("._") or "log"
    return f"s{index}_{stem[:40]}"


def read_manifest(folder: Path) -> dict[str, Any]:
    """An earlier map's manifest (`map --add`); its session folders must still be there."""
    import json

    path = folder / MAP_MANIFEST
    if not path.is_file():
        raise MapError(f"{folder}: not a map folder (no {MAP_MANIFEST}); pass the folder `map` wrote")
    try:
        manifest = json.loads(read_text(path, MapError))
        sessions = manifest["sessions"]
        missing = [s["name"] for s in sessions if s["folder"] is not None and not (folder / s["folder"]).is_dir()]
    except (ValueError, KeyError, TypeError) as exc:
        raise MapError(f"{path}: not a map manifest ({type(exc).__name__}: {exc})") from None
    if missing:
        raise MapError(f"{folder}: the results of sessions {', '.join(missing)} are missing from sessions/")
    return manifest


@dataclass
class MainMap:
    """The main map's graph, its solved poses (graph id order) and the solve (None: one session)."""

    graph: MapGraph
    poses: np.ndarray
    result: OptimizationResult | None


def solve_maps(
    sessions: list[SessionMap], loops: list[CrossLoop], links: SessionLinks
) -> tuple[dict[int, np.ndarray], dict[int, bool], MainMap]:
    """Each component solved: poses by session (in its component's frame), whether each linked
    cross loop stayed in the graph, and the main map's graph and solution."""
    poses: dict[int, np.ndarray] = {}
    in_graph: dict[int, bool] = {}
    main: MainMap | None = None
    kept = graph_loops(loops, links)
    edges = [CrossEdge.of(loops[k]) for k in kept]
    for position, component in enumerate(links.components):
        if len(component) == 1:  # nothing joins it: its own run's solution, in its own frame
            poses[component[0]] = sessions[component[0]].poses
            if position == 0:
                graph = build_map_graph(component, sessions, links.frames, [])
                main = MainMap(graph, graph.graph.poses, None)
            continue
        graph = build_map_graph(component, sessions, links.frames, edges)
        result = solve_map_graph(graph)
        for s in component:
            poses[s] = graph.session_poses(result.poses, s, len(sessions[s]))
        in_graph.update({kept[e]: inlier for e, inlier in cross_edge_inliers(graph, result).items()})
        if position == 0:
            main = MainMap(graph, result.poses, result)
    assert main is not None  # there is always a first component
    return poses, in_graph, main


def map_logs(
    logs: list[Path],
    config: SlamConfig,
    console: Console | None = None,
    add_to: Path | None = None,
    ray_address: str | None = None,
    resume: Path | None = None,
) -> tuple[Path, dict[str, Any]]:
    """Make a map of `logs` (added to the map at `add_to`, if given); returns its folder and
    metrics. resume: a map left unfinished to go on with (by default the newest one of the same
    settings under the output folder is found and adopted)."""
    console = console or Console()
    started = time.perf_counter()
    previous = read_manifest(add_to) if add_to is not None else None
    earlier = previous["sessions"] if previous else []
    if not logs:
        raise MapError("no logs given: `map` needs at least one log (two to merge anything)")
    check_distinct(logs, earlier)
    config = config.model_copy(deep=True)
    resolve_weights_first(config)  # before Ray: a wrong path would fail every session, late
    jobs = [(len(earlier) + k, session_name(len(earlier) + k, log), str(log)) for k, log in enumerate(logs)]
    staging = MapStaging.open(Path(config.results.out_dir), map_plan(config, add_to), resume, console)
    stop = MapStop()
    try:
        records, sessions, loops, phases = _sessions_and_loops(staging, jobs, previous, add_to, config, console,
                                                               ray_address, stop, started)  # fmt: skip
    except KeyboardInterrupt:  # a second signal: quit at once, what finished stays
        raise MapStopped(stop.signum or signal.SIGINT, len(staging.finished()), len(jobs), staging.keep(),
                         abandoned=True) from None  # fmt: skip
    except BaseException:
        staging.keep() if staging.finished() else staging.staged.discard()
        raise
    try:
        with interrupts_deferred():
            metrics = _write_map(staging.path, records, sessions, loops, phases, config, started)
            final = staging.staged.publish()
    except BaseException:
        staging.keep()  # a second signal while writing: the sessions stay for the next call
        raise
    print_map_summary(console, metrics, final)
    return final, metrics


def check_distinct(logs: list[Path], earlier: list[dict[str, Any]]) -> None:
    """One log is one session: a log given twice, or already in the map it joins, is refused."""
    seen = {Path(s["log"]).resolve(): "is already a session of the map (--map)" for s in earlier}
    for log in logs:
        key = log.resolve()
        if key in seen:
            raise MapError(f"{log} {seen[key]}: each log is one session; give it once")
        seen[key] = "is given twice"


def _sessions_and_loops(
    staging: MapStaging,
    jobs: list[tuple[int, str, str]],
    previous: dict[str, Any] | None,
    add_to: Path | None,
    config: SlamConfig,
    console: Console,
    ray_address: str | None,
    stop: MapStop,
    started: float,
) -> tuple[list[dict[str, Any]], list[SessionMap], list[CrossLoop], dict[str, float]]:
    """Steps 1 to 4 on Ray: the codebooks, the sessions (those a stopped call finished reused),
    the cross-session loops. A stop request ends them with `MapStopped`."""
    folder = staging.path
    codebooks = folder / CODEBOOKS
    records = []
    for s in previous["sessions"] if previous else []:  # hard links: the earlier sessions' results are
        if s["folder"] is not None and not (folder / s["folder"]).exists():  # not copied, nor changed
            shutil.copytree(add_to / s["folder"], folder / s["folder"], copy_function=os.link, symlinks=True)  # type: ignore[operator]
        records.append(dict(s))  # (a session that failed stays on record, without results)
    if not codebooks.exists():
        if previous is not None and add_to is not None:
            shutil.copyfile(add_to / previous["codebooks"], codebooks)
        elif config.detector.codebooks is not None:
            shutil.copyfile(config.detector.codebooks, codebooks)
    reused = staging.reusable(jobs)
    if reused:
        console.print(f"reusing {len(reused)} session(s) a stopped `map` finished in {escape(str(folder))}: "
                      f"{escape(', '.join(reused))}")  # fmt: skip
    todo = [job for job in jobs if job[1] not in reused]
    _remove_leftovers(staging.sessions_dir, [r["folder"] for r in records] + [r["folder"] for r in reused.values()])

    def stopped() -> MapStopped:
        assert stop.signum is not None
        return MapStopped(stop.signum, len(staging.reusable(jobs)), len(jobs), staging.keep())

    def finished(outcome: SessionOutcome) -> None:
        if outcome.error is None and outcome.folder is not None:
            staging.record_finished(_record(outcome, folder), outcome.log)

    phases: dict[str, float] = {}
    with ray_session(config, ray_address), stop.installed():
        phases["start"], mark = time.perf_counter() - started, time.perf_counter()
        if not codebooks.exists():
            with console.status(f"fitting the shared PCA codebooks on {len(jobs)} logs"):
                if not fit_codebooks(config, [Path(j[2]) for j in jobs], codebooks, stop):
                    raise stopped()
        phases["codebooks"], mark = time.perf_counter() - mark, time.perf_counter()
        with console.status(f"running {len(todo)} session(s) on {min(config.map.workers, len(todo))} Ray worker(s)"):
            outcomes = (
                run_sessions(config, todo, codebooks, staging.sessions_dir, console, stop, finished) if todo else []
            )
        if stop.requested:
            _remove_leftovers(staging.sessions_dir, [r["folder"] for r in staging.finished().values()] +
                              [r["folder"] for r in records])  # fmt: skip
            raise stopped()
        by_index = {o.index: _record(o, folder) for o in outcomes}
        by_index.update({index: reused[name] for index, name, _ in jobs if name in reused})
        records += [{k: v for k, v in by_index[index].items() if k != "fingerprint"} for index, _, _ in jobs]
        _remove_leftovers(staging.sessions_dir, [r["folder"] for r in records])
        sessions = _load_sessions(records, folder, config, console)
        if not sessions:
            raise MapError("no session succeeded: nothing to map (see the errors above)")
        if previous is not None and all(by_index[index]["error"] is not None for index, _, _ in jobs):
            raise MapError(f"no added log succeeded ({len(jobs)} failed, see above): the map at {add_to} is unchanged")
        phases["sessions"], mark = time.perf_counter() - mark, time.perf_counter()
        with console.status(f"matching {len(sessions)} sessions against each other"):
            loops = all_cross_loops(sessions, config, stop) if len(sessions) > 1 else []
        if loops is None:
            raise stopped()
        phases["cross_session_matching"] = time.perf_counter() - mark
    return records, sessions, loops, phases


def _record(outcome: SessionOutcome, folder: Path) -> dict[str, Any]:
    relative = None if outcome.folder is None else str(Path(outcome.folder).relative_to(folder))
    return {"name": outcome.name, "log": outcome.log, "folder": relative, "error": outcome.error,
            "keyframes": outcome.keyframes, "seconds": outcome.seconds}  # fmt: skip


def _write_map(
    folder: Path,
    records: list[dict[str, Any]],
    sessions: list[SessionMap],
    loops: list[CrossLoop],
    phases: dict[str, float],
    config: SlamConfig,
    started: float,
) -> dict[str, Any]:
    """Steps 5 to 7: sessions joined and solved, evaluated, every output written into `folder`."""
    mark = time.perf_counter()
    links = link_sessions(loops, sessions, config.map)
    poses, in_graph, main = solve_maps(sessions, loops, links)
    phases["joining_and_solving"] = time.perf_counter() - mark
    members = links.components[0]
    metrics = evaluate_map(sessions, len(records), members, poses, loops, in_graph, config.evaluation.loops)
    metrics["wall_s"] = time.perf_counter() - started
    metrics["seconds"] = phases  # where the wall time went (writing the map is the rest)
    metrics["maps"] = [[sessions[s].name for s in c] for c in links.components]
    metrics["session_results"] = records
    metrics["links"] = [
        {"sessions": [sessions[link.a].name, sessions[link.b].name], "loops": len(link.loops),
         "disagreeing": len(link.disagreeing)}
        for link in links.links
    ]  # fmt: skip
    metrics["unjoined_pairs"] = [
        {"sessions": [sessions[a].name, sessions[b].name], "verified_loops": n}
        for (a, b), n in links.unjoined_pairs.items()
    ]
    result = main.result
    if result is not None:
        metrics["main_map_solve"] = {"loops": result.n_loops, "outliers": result.n_outliers,
                                     "seconds": result.seconds, "check_error": result.check_error}  # fmt: skip
    truth = [s.gt_poses() for s in sessions]
    distances = [loop_distance(loop, truth) for loop in loops]
    name_of = {s.name: k for k, s in enumerate(sessions)}
    component_of = {s: c for c, comp in enumerate(links.components) for s in comp}
    for record in records:
        k = name_of.get(record["name"])
        record["map"] = None if k is None else component_of[k]
        record["frame_in_map"] = None if k is None else links.frames[k].tolist()
    write_map_database(folder / "database", sessions, members, poses, loops, in_graph, config)
    write_trajectories(folder / "trajectories", sessions, poses)
    write_map_graph(folder / "map.g2o", main.graph, main.poses)
    write_cross_loops(folder / "cross_session_loops.csv", sessions, loops, links.kept, in_graph, distances)
    write_config(folder, config)
    if config.results.plots:
        plot_map(folder / "map_top_view.png", sessions, poses, loops, in_graph, config)
    write_json(folder / "metrics.json", metrics)
    for name in (PLAN, FINISHED):  # the staging's own bookkeeping is not part of the map
        (folder / name).unlink(missing_ok=True)
    write_manifest(folder, {"codebooks": CODEBOOKS, "sessions": records, "maps": metrics["maps"]})
    return metrics


def _remove_leftovers(sessions_dir: Path, folders: list[str | None]) -> None:
    """What a worker that died mid-session left in `sessions/` (a staging folder, half-written
    results): only the sessions' published results folders (and their `latest` links) stay."""
    keep = {Path(f).name for f in folders if f is not None}
    for entry in sessions_dir.iterdir():
        if entry.is_dir() and not entry.is_symlink() and entry.name not in keep:
            shutil.rmtree(entry, ignore_errors=True)


def _load_sessions(
    records: list[dict[str, Any]], folder: Path, config: SlamConfig, console: Console
) -> list[SessionMap]:
    """The sessions that produced a map; one whose results cannot be merged is reported and left out."""
    sessions = []
    for record in records:
        if record["error"] is not None:
            continue
        try:
            sessions.append(SessionMap.load(record["name"], record["log"], folder / record["folder"], config.vpr))
        except SsmvprError as exc:
            record["error"] = str(exc)
            console.print(f"[red]session {escape(record['name'])} left out:[/red] {escape(str(exc))}")
    return sessions


def print_map_summary(console: Console, metrics: dict[str, Any], folder: Path) -> None:
    table = Table(title="ssmvpr-slam map")
    table.add_column("metric")
    table.add_column("value", justify="right")
    failed = [r["name"] for r in metrics["session_results"] if r["error"] is not None]
    table.add_row("sessions / merged into the map", f"{metrics['sessions']} / {metrics['sessions_merged']}")
    if failed:
        table.add_row("sessions failed", ", ".join(failed))
    table.add_row("maps (sessions each)", " + ".join(str(len(m)) for m in metrics["maps"]))
    loops = metrics["cross_session_loops"]
    table.add_row("cross-session loops accepted / verified / in graph",
                  f"{loops['proposed_accepted']} / {loops['verified']} / {loops['in_graph']}")  # fmt: skip
    fmt = lambda v: "n/a" if v is None else f"{v:.3f}"  # noqa: E731
    if "cross_session_recall" in metrics:
        table.add_row("cross-session loop precision / recall",
                      f"{fmt(metrics['cross_session_precision'])} / {fmt(metrics['cross_session_recall'])}")  # fmt: skip
    if "ate_merged_m" in metrics:
        table.add_row("ATE RMSE of the map (one alignment)", f"{metrics['ate_merged_m']:.2f} m")
    table.add_row("wall time", f"{metrics['wall_s']:.0f} s")
    console.print(table)
    console.print(f"map in [bold]{escape(str(folder))}[/bold]")
