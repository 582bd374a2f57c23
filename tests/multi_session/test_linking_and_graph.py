"""Joining sessions (`linking`) and solving their map (`merged_graph`) on sessions made here:
two drives along one street, each in its own frame, with loops measured from the ground truth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from loopclosure.detector import LoopProposal
from ssmvpr_slam.backend.g2o_io import GraphEdge, PoseGraphData
from ssmvpr_slam.backend.loop_registration import LoopRegistration
from ssmvpr_slam.backend.noise import sigmas6
from ssmvpr_slam.backend.se3 import invert, make_pose, rot_z
from ssmvpr_slam.config.map import MapConfig
from ssmvpr_slam.evaluation.metrics import ate
from ssmvpr_slam.multi_session.cross_loops import CrossLoop
from ssmvpr_slam.multi_session.linking import graph_loops, link_sessions
from ssmvpr_slam.multi_session.merged_graph import CrossEdge, build_map_graph, cross_edge_inliers, solve_map_graph
from ssmvpr_slam.multi_session.session_map import SessionMap

STEP_M = 2.0
ODOMETRY_INFO = np.diag(1.0 / np.square(sigmas6(1e-3, 0.05)))


def _world_poses(start_x: float, n: int, lateral: float = 0.0) -> np.ndarray:
    """A drive east along y = lateral, gently curving so that yaw drift shows."""
    poses = []
    for k in range(n):
        x = start_x + STEP_M * k
        poses.append(make_pose(rot_z(0.002 * x), np.array([x, lateral + 0.001 * x**2, 0.0])))
    return np.array(poses)


def _session(name: str, world: np.ndarray, yaw_drift_per_step: float = 0.0) -> SessionMap:
    """A session whose frame is its first pose, its odometry drifting in yaw."""
    own = [invert(world[0]) @ p for p in world]
    steps = [invert(a) @ b for a, b in zip(own, own[1:])]
    drifted = [np.eye(4)]
    for step in steps:
        drifted.append(drifted[-1] @ make_pose(rot_z(yaw_drift_per_step), np.zeros(3)) @ step)
    edges = tuple(GraphEdge(k, k + 1, step, ODOMETRY_INFO) for k, step in enumerate(steps))
    graph = PoseGraphData(3, tuple(range(len(world))), np.array(drifted), edges)
    return SessionMap(name, f"{name}.mcap", None, None, graph)  # type: ignore[arg-type]  # places: not read here


def _loop(query: int, query_kf: int, match: int, match_kf: int, T_mq: np.ndarray) -> CrossLoop:
    proposal = LoopProposal(query_kf, match_kf, match_kf, 0.5, 0.5, 0, 0.0, True, "test")
    registration = LoopRegistration(T_mq, True, "test", 0.9, 0.05, sigmas6(0.02, 0.1))
    return CrossLoop(query, query_kf, match, match_kf, proposal, registration)


def _true_loops(worlds: list[np.ndarray], pairs: list[tuple[int, int, int, int]]) -> list[CrossLoop]:
    return [_loop(q, qk, m, mk, invert(worlds[m][mk]) @ worlds[q][qk]) for q, qk, m, mk in pairs]


@pytest.fixture
def street() -> tuple[list[np.ndarray], list[SessionMap]]:
    """Session 0 drives x = 0..98 m; session 1 starts at x = 40 m, 1.5 m to the side, and drives on."""
    worlds = [_world_poses(0.0, 50), _world_poses(40.0, 40, lateral=1.5)]
    return worlds, [_session("a", worlds[0]), _session("b", worlds[1])]


def test_agreeing_loops_join_two_sessions_where_the_ground_truth_puts_them(street):
    worlds, sessions = street
    loops = _true_loops(worlds, [(1, k, 0, 20 + k) for k in range(0, 20, 4)])
    wrong = _loop(1, 2, 0, 5, make_pose(rot_z(0.3), np.array([4.0, 0.0, 0.0])))  # a look-alike corner ICP aligned
    links = link_sessions([*loops, wrong], sessions, MapConfig())
    assert len(links.links) == 1 and links.components == [[0, 1]]
    link = links.links[0]
    assert (link.a, link.b) == (0, 1) and link.loops == (0, 1, 2, 3, 4) and link.disagreeing == (5,)
    expected = invert(worlds[0][0]) @ worlds[1][0]  # session 1's frame in session 0's
    np.testing.assert_allclose(link.T_ab, expected, atol=1e-9)
    np.testing.assert_allclose(links.frames[1], expected, atol=1e-9)
    assert links.kept == {0, 1, 2, 3, 4}


def test_too_few_agreeing_loops_leave_the_sessions_apart(street):
    """Two loops are not enough (min_agreeing_loops 3), and neither are three that disagree:
    the sessions stay two maps, never forced together."""
    worlds, sessions = street
    two = _true_loops(worlds, [(1, 0, 0, 20), (1, 8, 0, 28)])
    links = link_sessions(two, sessions, MapConfig())
    assert links.links == [] and links.components == [[0], [1]] and links.unjoined_pairs == {(0, 1): 2}
    scattered = [_loop(1, k, 0, 20 + k, make_pose(rot_z(0.2 * k), np.array([3.0 * k, 0.0, 0.0]))) for k in range(3)]
    assert link_sessions(scattered, sessions, MapConfig()).components == [[0], [1]]
    # the larger session's map comes first
    assert link_sessions([], [sessions[1], sessions[0]], MapConfig()).components == [[1], [0]]


def test_a_loop_that_is_not_verified_never_joins_anything(street):
    worlds, sessions = street
    loops = _true_loops(worlds, [(1, k, 0, 20 + k) for k in range(0, 20, 4)])
    unverified = [
        CrossLoop(
            lp.query,
            lp.query_kf,
            lp.match,
            lp.match_kf,
            lp.proposal,
            LoopRegistration(lp.registration.T_mq, False, "poor alignment", 0.1, 1.0),
        )  # fmt: skip
        for lp in loops
    ]
    assert link_sessions(unverified, sessions, MapConfig()).components == [[0], [1]]


def test_the_map_graph_corrects_both_sessions_drift_through_the_cross_session_loops():
    """With drifting odometry in both sessions, loops between them (each measured from the
    ground truth) pull the map onto the world; a wrong loop added among them is rejected by
    the robust solve, as `optimize` rejects one."""
    worlds = [_world_poses(0.0, 60), _world_poses(0.0, 60, lateral=1.0)]
    sessions = [_session("a", worlds[0], 2e-3), _session("b", worlds[1], -2e-3)]
    pairs = [(1, k, 0, k) for k in range(0, 60, 3)]
    loops = _true_loops(worlds, pairs)
    links = link_sessions(loops, sessions, MapConfig(agree_translation_m=10.0, agree_yaw_deg=20.0))
    assert links.components == [[0, 1]]
    edges = [CrossEdge.of(loops[k]) for k in sorted(links.kept)]
    wrong = CrossEdge(1, 30, 0, 55, make_pose(rot_z(0.4), np.array([2.0, 1.0, 0.0])), edges[0].information)
    graph = build_map_graph([0, 1], sessions, links.frames, [*edges, wrong])
    result = solve_map_graph(graph)
    inliers = cross_edge_inliers(graph, result)
    assert inliers[len(edges)] is False and all(inliers[k] for k in range(len(edges)))
    truth = np.concatenate([invert(worlds[0][0]) @ p for w in worlds for p in w]).reshape(-1, 4, 4)
    merged = np.concatenate([graph.session_poses(result.poses, s, 60) for s in (0, 1)])
    drifted = np.concatenate([sessions[0].poses, links.frames[1] @ sessions[1].poses])
    before, after = ate(truth, drifted, "se3").stats.rmse, ate(truth, merged, "se3").stats.rmse
    assert after < 0.5 * before, (before, after)
    assert math.isfinite(after) and after < 0.3


def test_vertex_ids_of_two_sessions_are_never_consecutive(street):
    """Consecutive ids are odometry to the solver: a session's first keyframe must not follow
    the previous session's last."""
    _, sessions = street
    graph = build_map_graph([0, 1], sessions, {0: np.eye(4), 1: np.eye(4)}, [])
    assert graph.vertex(1, 0) - graph.vertex(0, len(sessions[0]) - 1) == 2
    assert len(graph.graph.odometry) == len(sessions[0]) + len(sessions[1]) - 2


def test_every_verified_loop_within_a_map_goes_to_its_graph_and_none_across_maps(street):
    """The agreement joins the sessions; the graph then takes every verified loop between them,
    the disagreeing ones too (the robust solve judges them), and none to a session left apart."""
    worlds, sessions = street
    third = _session("c", _world_poses(500.0, 10))
    loops = _true_loops(worlds, [(1, k, 0, 20 + k) for k in range(0, 20, 4)])
    shifted = _loop(1, 2, 0, 22, make_pose(rot_z(0.0), np.array([0.0, 5.0, 0.0])))  # verified, disagreeing
    lone = _loop(2, 0, 0, 3, np.eye(4))  # one verified loop to a third session: not enough to join it
    every = [*loops, shifted, lone]
    links = link_sessions(every, [*sessions, third], MapConfig())
    assert links.components == [[0, 1], [2]] and links.kept == {0, 1, 2, 3, 4}
    assert graph_loops(every, links) == [0, 1, 2, 3, 4, 5]
