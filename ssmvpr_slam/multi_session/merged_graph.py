"""One pose graph per map: every session's odometry chain and in-session loops, plus the
cross-session loops that joined them, solved as `optimize` solves a graph (robust kernel,
GNC, the leave-one-out check of the loops it keeps).

Vertex ids: session s's keyframe k is `base[s] + k`, the bases one id apart from the previous
session's last keyframe, so no id of one session follows another's (consecutive ids are
odometry to the solver). The initial estimate is each session's own optimised trajectory
moved into the map frame by the link offsets.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ssmvpr_slam.backend.g2o_io import GraphEdge, PoseGraphData
from ssmvpr_slam.backend.graph_optimizer import OptimizationResult, OptimizerSettings, optimize_graph
from ssmvpr_slam.multi_session.cross_loops import CrossLoop
from ssmvpr_slam.multi_session.session_map import SessionMap


@dataclass(frozen=True)
class CrossEdge:
    """A loop factor between two sessions: T_mq places keyframe `query_kf` of session `query`
    in the frame of keyframe `match_kf` of session `match`."""

    query: int
    query_kf: int
    match: int
    match_kf: int
    T_mq: np.ndarray
    information: np.ndarray

    @classmethod
    def of(cls, loop: CrossLoop) -> CrossEdge:
        return cls(loop.query, loop.query_kf, loop.match, loop.match_kf, loop.registration.T_mq, loop.information)


@dataclass
class MapGraph:
    """A component's graph, where each session's keyframes sit in it, and which of its loop
    edges are cross-session loops (edge index -> index into the cross-loop list)."""

    sessions: list[int]
    base: dict[int, int]
    graph: PoseGraphData
    cross_edges: dict[int, int]

    def vertex(self, session: int, kf: int) -> int:
        return self.base[session] + kf

    def session_poses(self, poses: np.ndarray, session: int, count: int) -> np.ndarray:
        """(count, 4, 4) of `session` out of poses in the graph's id order."""
        start = self.graph.index_of(self.vertex(session, 0))
        return poses[start : start + count]


def build_map_graph(
    component: list[int],
    sessions: list[SessionMap],
    frames: dict[int, np.ndarray],
    cross: list[CrossEdge],
) -> MapGraph:
    """The component's graph from its sessions' own graphs and the cross-session edges between
    its sessions (`cross_edges` maps their graph edge index to their index in `cross`)."""
    base: dict[int, int] = {}
    next_id = 0
    ids: list[int] = []
    poses: list[np.ndarray] = []
    edges: list[GraphEdge] = []
    for s in component:
        session = sessions[s]
        base[s] = next_id
        ids.extend(next_id + k for k in range(len(session)))
        poses.extend(frames[s] @ p for p in session.poses)
        edges.extend(
            GraphEdge(
                next_id + session.graph.index_of(e.i), next_id + session.graph.index_of(e.j), e.measured, e.information
            )  # fmt: skip
            for e in session.graph.edges
        )
        next_id += len(session) + 1  # a gap: the next session's first id does not follow this one's last
    cross_edges = {}
    members = set(component)
    for index, loop in enumerate(cross):
        if loop.query in members and loop.match in members:
            cross_edges[len(edges)] = index
            edges.append(
                GraphEdge(
                    base[loop.match] + loop.match_kf, base[loop.query] + loop.query_kf, loop.T_mq, loop.information
                )  # fmt: skip
            )
    graph = PoseGraphData(3, tuple(ids), np.array(poses), tuple(edges), source="<map>")
    return MapGraph(list(component), base, graph, cross_edges)


def solve_map_graph(map_graph: MapGraph, settings: OptimizerSettings | None = None) -> OptimizationResult:
    """The robust solve `optimize` runs (GNC with the leave-one-out check)."""
    return optimize_graph(map_graph.graph, settings or OptimizerSettings())


def cross_edge_inliers(map_graph: MapGraph, result: OptimizationResult) -> dict[int, bool]:
    """Index into the cross edges -> whether the solve kept it."""
    inlier = dict(zip(result.loop_indices.tolist(), result.loop_inlier.tolist()))
    return {loop: bool(inlier.get(edge, False)) for edge, loop in map_graph.cross_edges.items()}
