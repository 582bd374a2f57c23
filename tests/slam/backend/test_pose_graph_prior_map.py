"""Prior-map loops: an anchor variable places a new session in an earlier session's map frame,
and several map loops correct the new session's drift against the fixed map."""

from __future__ import annotations

import numpy as np
import pytest

from ssmvpr_slam.backend import PoseGraph, PoseGraphConfig
from ssmvpr_slam.evaluation.metrics import ate


def _pose(x: float, y: float, yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    out = np.eye(4)
    out[:2, :2] = [[c, -s], [s, c]]
    out[:2, 3] = (x, y)
    return out


def _square(n_side: int = 25, step: float = 2.0) -> list[np.ndarray]:
    """A 50 m square driven anticlockwise, a pose every `step` metres (map frame)."""
    poses, x, y, yaw = [], 0.0, 0.0, 0.0
    for _side in range(4):
        for _ in range(n_side):
            poses.append(_pose(x, y, yaw))
            x, y = x + step * np.cos(yaw), y + step * np.sin(yaw)
        yaw += np.pi / 2
    return poses


def _drifted(truth: list[np.ndarray], yaw_bias: float, start: np.ndarray) -> list[np.ndarray]:
    """Odometry of the same drive in another frame (starting at `start`), with a heading bias."""
    out = [start]
    for a, b in zip(truth[:-1], truth[1:]):
        delta = np.linalg.inv(a) @ b
        out.append(out[-1] @ delta @ _pose(0.0, 0.0, yaw_bias))
    return out


MAP = _square()
TRUTH = MAP  # the new session drives the mapped square again
ODOM = _drifted(TRUTH, yaw_bias=0.002, start=_pose(100.0, -40.0, 0.7))


def _session(map_places: list[int], wrong: dict[int, int] | None = None, config: PoseGraphConfig | None = None):
    graph = PoseGraph(config)
    handles = {}
    for k, pose in enumerate(ODOM):
        graph.add_keyframe(k, pose)
        if k in map_places:
            p = (wrong or {}).get(k, k)  # a wrong match: registered as if it were the right place
            handles[k] = graph.add_map_loop(
                p, MAP[p], k, np.linalg.inv(MAP[k]) @ TRUTH[k], sigmas=[0.02] * 3 + [0.1] * 3
            )
        graph.update()
    return graph, handles


def test_one_map_loop_places_the_session_in_the_map_frame() -> None:
    graph, _ = _session([0])
    anchor = graph.anchor()
    assert anchor is not None
    first = np.linalg.inv(anchor) @ graph.optimized_poses()[0]
    assert np.allclose(first, MAP[0], atol=1e-3)


def test_map_loops_correct_the_drift_against_the_map() -> None:
    graph, _ = _session(list(range(0, 100, 10)))
    anchor_inv = np.linalg.inv(graph.anchor())
    in_map = np.array([anchor_inv @ graph.optimized_poses()[k] for k in range(len(ODOM))])
    truth = np.array(TRUTH)
    before = ate(truth, np.array(ODOM)).stats.rmse
    after_unaligned = np.linalg.norm(in_map[:, :3, 3] - truth[:, :3, 3], axis=1)
    assert before > 1.0  # 2 mrad per step over 100 steps
    assert np.sqrt(np.mean(after_unaligned**2)) < 0.1 * before  # no alignment needed: map frame


def test_a_session_without_map_loops_has_no_anchor() -> None:
    graph, _ = _session([])
    assert graph.anchor() is None


def test_removing_every_map_loop_keeps_the_graph_solvable() -> None:
    graph, handles = _session([10, 40])
    for handle in handles.values():
        graph.remove_loop(handle)
    poses = graph.optimized_poses()
    assert np.allclose(poses[len(ODOM) - 1], ODOM[-1], atol=1e-6)  # back to odometry


def test_residuals_report_map_loops() -> None:
    graph, handles = _session([10, 40, 70])
    residuals = {r.handle: r for r in graph.loop_residuals()}
    assert set(residuals) == set(handles.values())
    assert all(r.whitened_norm < 1.0 for r in residuals.values())


def test_the_final_robust_pass_keeps_isam2s_estimate_with_prior_map_loops() -> None:
    """`optimize`'s solve holds one chain of keyframes: with map places in the graph the final
    pass says it does not run, and the robust kernel's iSAM2 estimate, which already discounts a
    wrong map loop, is the answer."""
    config = PoseGraphConfig.model_validate({"gnc": {"enabled": True}})
    graph, handles = _session(list(range(0, 100, 10)), wrong={50: 12}, config=config)
    isam2 = graph.optimized_poses()
    final = graph.finalize()
    assert graph.final_solve_refusal() == "a session with prior-map loops"
    assert [r.what for r in graph.recoveries] == [
        "the final robust pass does not run on a session with prior-map loops; iSAM2's estimate is kept"
    ]
    assert all(np.allclose(final[k], isam2[k]) for k in isam2) and set(graph.loop_handles) == set(handles.values())


def test_a_map_place_cannot_change_pose() -> None:
    graph = PoseGraph()
    graph.add_keyframe(0, np.eye(4))
    graph.add_keyframe(1, _pose(1.0, 0.0, 0.0))
    graph.add_map_loop(3, MAP[3], 0, np.eye(4))
    with pytest.raises(ValueError, match="map place 3 was added before with another pose"):
        graph.add_map_loop(3, MAP[4], 1, np.eye(4))
    with pytest.raises(ValueError, match="keyframe 7 has not been added"):
        graph.add_map_loop(3, MAP[3], 7, np.eye(4))
