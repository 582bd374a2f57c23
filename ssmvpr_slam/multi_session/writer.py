"""The merged map's files, written into the map's staging folder (published as one unit):

- `map.json`: the manifest `map --add` and `run --map` read: sessions (name, log, results
  folder, component), components, each session's frame in its component's frame;
- `database/`: the main map's places (every session joined into it), each with its pose in the
  map frame, its ground truth and its scan (or kept images): a prior map for `run --map`;
- `trajectories/<session>.tum|.kitti`: each session's keyframes in its map's frame;
- `map.g2o`: the main map's pose graph with the solved poses;
- `cross_session_loops.csv`: every accepted cross-session proposal and what became of it;
- `map_top_view.png`: the map from above, one colour per session, cross-session loops drawn;
- `metrics.json`, `config.yaml`.
"""

from __future__ import annotations

import csv
import io
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from loopclosure.database import PlaceDatabase
from loopclosure.detector import PLACE_LINKS_KEY, RUNNER_UPS_KEY
from ssmvpr_common.atomic import atomic_write_text
from ssmvpr_common.trajectory_io import write_kitti, write_tum
from ssmvpr_slam.backend.g2o_io import write_g2o
from ssmvpr_slam.config.slam import SlamConfig, dump_config
from ssmvpr_slam.multi_session.cross_loops import CrossLoop, merged_place_links
from ssmvpr_slam.multi_session.merged_graph import MapGraph
from ssmvpr_slam.multi_session.session_map import SessionMap
from ssmvpr_slam.prior_map import MAP_MANIFEST, KeptImages, save_map
from ssmvpr_slam.results.run_folder import write_json

MAP_VERSION = 1
CROSS_LOOP_COLUMNS = [
    "query_session", "query_kf", "match_session", "match_kf", "camera", "direction", "decision_score",
    "registration", "registration_accepted", "registration_reason", "inlier_ratio", "rmse", "linked", "in_graph",
    "gt_distance_m",
]  # fmt: skip


def write_manifest(folder: Path, manifest: dict[str, Any]) -> None:
    write_json(folder / MAP_MANIFEST, {"version": MAP_VERSION, **manifest})


def write_map_database(
    folder: Path,
    sessions: list[SessionMap],
    members: list[int],
    poses: dict[int, np.ndarray],
    loops: list[CrossLoop],
    in_graph: dict[int, bool],
    config: SlamConfig,
) -> None:
    """The main map's places: every member session's, in order, posed in the map frame."""
    parts = [sessions[s].places.database for s in members]
    database, starts = PlaceDatabase.merged(parts, config.vpr.database)
    start_of = dict(zip(members, starts))
    database.places = [
        replace(
            info, frame_id=start_of[s] + k, extra={**info.extra, "session": sessions[s].name, "session_keyframe": k}
        )
        for s in members
        for k, info in enumerate(sessions[s].places.database.places)
    ]
    largest = max(members, key=lambda s: len(sessions[s]))  # the longest stream's wrong-match model
    database.extra[RUNNER_UPS_KEY] = sessions[largest].places.database.extra.get(RUNNER_UPS_KEY)
    links = merged_place_links([sessions[s] for s in members], starts)
    links += [
        [start_of[loops[k].query] + loops[k].query_kf, start_of[loops[k].match] + loops[k].match_kf]
        for k, kept in in_graph.items()
        if kept and loops[k].query in start_of and loops[k].match in start_of
    ]  # a place two sessions share is one place to the next session
    database.extra[PLACE_LINKS_KEY] = links
    map_poses, scans, gt = {}, {}, {}
    images = KeptImages()  # what `run --map` verifies its loops to a camera-only map with
    for s in members:
        places = sessions[s].places
        images.update(places.images.moved(start_of[s]))
        for k in range(len(sessions[s])):
            index = start_of[s] + k
            map_poses[index] = poses[s][k]
            if k in places.scans:
                scans[index] = places.scans[k]
            if k in places.gt_poses:
                gt[index] = places.gt_poses[k]
    save_map(folder, database, config.vpr, map_poses, scans, gt, images)


def write_trajectories(folder: Path, sessions: list[SessionMap], poses: dict[int, np.ndarray]) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for s, session_poses in poses.items():
        stamps = np.array([info.timestamp for info in sessions[s].places.database.places])
        write_tum(folder / f"{sessions[s].name}.tum", stamps, session_poses)
        write_kitti(folder / f"{sessions[s].name}.kitti", session_poses)


def write_map_graph(path: Path, graph: MapGraph, poses: np.ndarray) -> None:
    write_g2o(path, graph.graph, poses)


def write_cross_loops(
    path: Path,
    sessions: list[SessionMap],
    loops: list[CrossLoop],
    linked: set[int],
    in_graph: dict[int, bool],
    distances: list[float | None],
) -> None:
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(CROSS_LOOP_COLUMNS)
    for k, loop in enumerate(loops):
        p, reg = loop.proposal, loop.registration
        writer.writerow([
            sessions[loop.query].name, loop.query_kf, sessions[loop.match].name, loop.match_kf, p.camera,
            p.direction or "", "" if p.decision_score is None else f"{p.decision_score:.3f}", reg.method,
            int(reg.accepted), reg.reason, f"{reg.inlier_ratio:.3f}", f"{reg.rmse:.3f}", int(k in linked),
            int(in_graph.get(k, False)), "" if distances[k] is None else f"{distances[k]:.2f}",
        ])  # fmt: skip
    atomic_write_text(path, buffer.getvalue())


def write_config(folder: Path, config: SlamConfig) -> None:
    atomic_write_text(folder / "config.yaml", dump_config(config))


def plot_map(
    path: Path,
    sessions: list[SessionMap],
    poses: dict[int, np.ndarray],
    loops: list[CrossLoop],
    in_graph: dict[int, bool],
    config: SlamConfig,
) -> None:
    """Top view of the map: each session's keyframes in its own colour, cross-session loops in black."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ssmvpr_common.atomic import atomic_write_bytes

    plot = config.evaluation.plots
    fig, ax = plt.subplots(figsize=(plot.width_in, plot.height_in))
    for s, session_poses in poses.items():
        xy = session_poses[:, :2, 3]
        ax.plot(xy[:, 0], xy[:, 1], lw=1.2, label=sessions[s].name)
    for k, kept in in_graph.items():
        loop = loops[k]
        if kept and loop.query in poses and loop.match in poses:
            a = poses[loop.query][loop.query_kf, :2, 3]
            b = poses[loop.match][loop.match_kf, :2, 3]
            ax.plot([a[0], b[0]], [a[1], b[1]], color="black", lw=0.6, alpha=0.6)
    ax.set_aspect("equal")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title("Merged map (top view): sessions and cross-session loops")
    ax.legend(fontsize="small", loc="best")
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=plot.dpi, bbox_inches="tight")
    plt.close(fig)
    atomic_write_bytes(path, buffer.getvalue())
