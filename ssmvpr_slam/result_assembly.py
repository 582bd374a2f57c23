"""A `RunResult` from the core's parts: the keyframes and loops so far, the optimised poses, the
graph as g2o data, the database. Apart from `SlamSystem` so that the core reads as the method's
flow; the same assembly serves the final result and a checkpoint's partial one."""

from __future__ import annotations

from collections import Counter
from dataclasses import replace
from typing import Any

import numpy as np

from frontend.odometry.base import Odometry
from loopclosure.detector import LoopDetector
from ssmvpr_slam.backend.g2o_io import from_pose_graph
from ssmvpr_slam.backend.pose_graph import PoseGraph
from ssmvpr_slam.prior_map import PriorMap
from ssmvpr_slam.run_result import RunResult, StreamEnd, frozen_array, keyframe_poses
from ssmvpr_slam.run_state import RunState


def assemble_result(
    state: RunState,
    detector: LoopDetector,
    graph: PoseGraph,
    prior_map: PriorMap | None,
    by_id: dict[int, np.ndarray],
    final: set[int],
    ending: StreamEnd,
    odometry_stats: dict[str, Any],
    recoveries: tuple[str, ...],
) -> RunResult:
    """The result with the poses `by_id` (keyframe id -> pose); a loop whose factor is not among
    `final` (handles still in the graph) is marked dropped."""
    kfs = tuple(state.keyframes)
    stamps, odom = keyframe_poses(kfs)
    optimised, pose_graph = odom, None
    in_map: np.ndarray | None = odom
    if kfs:
        optimised = frozen_array([by_id[k.id] for k in kfs])
        in_map = in_map_frame(prior_map, graph, optimised)
        pose_graph = from_pose_graph(graph, optimised)
    loops = tuple(
        replace(r, dropped=True) if r.factor_handle is not None and r.factor_handle not in final else r
        for r in state.loops
    )
    return RunResult(
        keyframes=kfs,
        loops=loops,
        stamps=stamps,
        odometry=odom,
        optimised=optimised,
        in_map_frame=in_map,
        anchored=graph.anchor() is not None if kfs else False,
        frames_seen=state.frames_seen,
        frames_skipped=dict(state.frames_skipped),
        rear_keyframes=state.rear_keyframes,
        timings=tuple(dict(r) for r in state.times.rows),
        odometry_stats=odometry_stats,
        ending=ending,
        pose_graph=pose_graph,
        database=detector.database,
        rear_database=detector.rear_database,
        session_places=session_places(detector),
        prior_map=prior_map,
        graph_recoveries=recoveries,
        keyframes_judged=detector.keyframes_judged,
        too_short_to_decide=detector.too_short_to_decide(),
    )


def in_map_frame(prior_map: PriorMap | None, graph: PoseGraph, optimised: np.ndarray) -> np.ndarray | None:
    """Poses in the map frame: the session's own without a prior map, the prior map's once
    a map loop anchored the session, None if it never was."""
    if prior_map is None:
        return optimised
    anchor = graph.anchor()
    return None if anchor is None else frozen_array(np.linalg.inv(anchor) @ optimised)


def session_places(detector: LoopDetector) -> dict[int, int]:
    """Keyframe id -> database place index of this session's places."""
    database = detector.database
    if database is None:
        return {}
    first = detector.prior_places
    return {database.places[i].frame_id: i for i in range(first, len(database))}


def odometry_stats_of(odometry: Odometry) -> dict[str, Any]:
    """The odometry's counters (copies: the result must not change when the odometry goes on)."""
    stats = getattr(odometry, "stats", None)
    if stats is None:
        return {}
    return {
        k: (Counter(v) if isinstance(v, Counter) else set(v) if isinstance(v, set) else v)
        for k, v in vars(stats).items()
    }
