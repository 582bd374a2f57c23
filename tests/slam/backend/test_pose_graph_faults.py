"""PoseGraph when an iSAM2 step fails: never left half-updated, the run's estimate never lost.

Before: one odometry step of 1e5 m made Cholesky report an indeterminate system, iSAM2 kept the
half-applied values, and the next update (the run's final one included) failed with "key already
exists", so no results were written."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from ssmvpr_slam.backend.config import GncConfig, PoseGraphConfig
from ssmvpr_slam.backend.g2o_io import from_pose_graph
from ssmvpr_slam.backend.pose_graph import PoseGraph, PoseGraphError
from ssmvpr_slam.errors import SlamError


def _pose(x: float, y: float = 0.0) -> np.ndarray:
    pose = np.eye(4)
    pose[:2, 3] = x, y
    return pose


def _track(graph: PoseGraph, xs: list[float], first: int = 0) -> None:
    for k, x in enumerate(xs, start=first):
        graph.add_keyframe(k, _pose(x))
        graph.update()


def _xs(graph: PoseGraph) -> list[float]:
    return [float(p[0, 3]) for p in graph.optimized_poses().values()]


@pytest.mark.parametrize("jump", [3e4, 1e5, 1e8])
def test_a_huge_odometry_step_is_re_solved_with_qr(jump: float) -> None:
    graph = PoseGraph()
    xs = [0.0, 1.0, 2.0, jump, jump + 1.0, 5.0, 6.0]
    _track(graph, xs)
    assert _xs(graph) == pytest.approx(xs, abs=1e-6 * jump)
    [recovery] = graph.recoveries  # QR is kept: the step back needs no second recovery
    assert recovery.keyframes == (3,)
    assert "indeterminate linear system" in recovery.what and "re-solved with QR" in recovery.what
    assert f"odometry step of {jump - 2.0:.1e} m" in recovery.what
    handle = graph.add_loop(0, 6, _pose(6.0))  # the rebuilt graph takes loops, removals and GNC alike
    graph.update()
    graph.remove_loop(handle)
    graph.update()
    assert graph.finalize().keys() == set(range(len(xs)))


def test_a_modest_step_still_uses_cholesky_without_recovery() -> None:
    graph = PoseGraph()
    _track(graph, [0.0, 1.0, 1e4, 2.0])
    assert graph.recoveries == [] and graph._factorization == "CHOLESKY"


class _RefusesLongEdges:
    """An iSAM2 that, in every factorisation, refuses a step holding an odometry edge over
    1 km (what Cholesky does at 3e4 m), so that the last fallback is exercised."""

    def __init__(self, isam: gtsam.ISAM2, refuse_all_from: int | None = None) -> None:
        self._isam = isam
        self._refuse_all_from = refuse_all_from

    def update(self, graph: gtsam.NonlinearFactorGraph | None = None, values: gtsam.Values | None = None,
               removals: list[int] | None = None):  # noqa: ANN201  # fmt: skip
        if graph is None:
            return self._isam.update()
        for i in range(graph.size()):
            factor = graph.at(i)
            keys = [gtsam.Symbol(k).index() for k in factor.keys()]
            long = (
                isinstance(factor, gtsam.BetweenFactorPose3) and np.linalg.norm(factor.measured().translation()) > 1e3
            )
            if long or (self._refuse_all_from is not None and max(keys) >= self._refuse_all_from):
                raise RuntimeError(f"\nIndeterminate linear system detected\n1 (Symbol: x{max(keys)}).\n")
        return self._isam.update(graph, values, removals or [])

    def calculateEstimate(self) -> gtsam.Values:  # noqa: N802
        return self._isam.calculateEstimate()


def _refusing_graph(monkeypatch: pytest.MonkeyPatch, config: PoseGraphConfig | None = None,
                    refuse_all_from: int | None = None) -> PoseGraph:  # fmt: skip
    new_isam = PoseGraph._new_isam
    monkeypatch.setattr(PoseGraph, "_new_isam", lambda self: _RefusesLongEdges(new_isam(self), refuse_all_from))
    return PoseGraph(config)


@pytest.mark.parametrize("gnc", [False, True])
def test_when_qr_fails_too_new_loops_go_first_then_the_keyframe_starts_a_segment(
    monkeypatch: pytest.MonkeyPatch, gnc: bool
) -> None:
    graph = _refusing_graph(monkeypatch, PoseGraphConfig(gnc=GncConfig(enabled=gnc)))
    _track(graph, [0.0, 1.0, 2.0])
    kept = graph.add_loop(0, 2, _pose(2.0))
    graph.update()
    graph.add_keyframe(3, _pose(5e3))
    graph.update()
    graph.add_keyframe(4, _pose(5e3 + 1.0))
    dropped = graph.add_loop(0, 4, _pose(5e3 + 1.0))
    graph.add_keyframe(5, _pose(6e3))  # queued in the same step; its 999 m edge is fine here
    graph.update()
    assert [r.keyframes for r in graph.recoveries] == [(3,), (4, 5)]
    assert "keyframe(s) 3 start a new graph segment (odometry edge cut)" in graph.recoveries[0].what
    # the long loop was the trouble: dropping it solved the step, so 4 and 5 keep their odometry
    assert graph.recoveries[1].what.endswith("1 new loop(s) dropped") and "segment" not in graph.recoveries[1].what
    assert graph.loop_handles == [kept] and dropped not in graph.loop_handles
    _track(graph, [6e3 + 1.0, 6e3 + 2.0], first=6)  # short steps after the segment join it as usual
    assert len(graph.recoveries) == 2
    final = graph.finalize()
    assert [float(p[0, 3]) for p in final.values()] == pytest.approx(
        [0.0, 1.0, 2.0, 5e3, 5e3 + 1.0, 6e3, 6e3 + 1.0, 6e3 + 2.0], abs=1e-3
    )
    # pose_graph.g2o lists what was solved: not the cut edge 2 -> 3, nor the dropped loop
    assert graph.segment_starts == [3]
    data = from_pose_graph(graph, np.stack(list(final.values())))
    assert [(e.i, e.j) for e in data.edges] == [(0, 1), (1, 2), (3, 4), (4, 5), (5, 6), (6, 7), (0, 2)]
    three_four = data.edges[2]
    assert three_four.measured[0, 3] == pytest.approx(1.0) and three_four.information.shape == (6, 6)


def test_when_nothing_helps_the_estimate_so_far_is_kept_and_the_error_is_clear(monkeypatch: pytest.MonkeyPatch) -> None:
    graph = _refusing_graph(monkeypatch, refuse_all_from=3)
    _track(graph, [0.0, 1.0, 2.0])
    graph.add_keyframe(3, _pose(3.0))
    with pytest.raises(PoseGraphError, match=r"keyframe\(s\) 3 \(indeterminate linear system near x3\)") as info:
        graph.update()
    assert isinstance(info.value, SlamError) and isinstance(info.value, RuntimeError)
    assert "\n" not in str(info.value)
    assert _xs(graph) == pytest.approx([0.0, 1.0, 2.0, 3.0])  # the new keyframe at its odometry guess
    graph.add_keyframe(4, _pose(4.0))
    with pytest.raises(PoseGraphError):  # no half-updated iSAM2 is ever used again
        graph.update()
    assert _xs(graph) == pytest.approx([0.0, 1.0, 2.0, 3.0, 4.0])  # reads go on, at the odometry guesses
    assert len(graph.finalize()) == 5
