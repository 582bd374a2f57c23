"""`optimize_graph` on graphs with a known optimum, with false loops, and on a real graph."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ssmvpr_slam.backend.g2o_io import GraphEdge, PoseGraphData, planar_pose, read_ground_truth, read_pose_graph
from ssmvpr_slam.backend.graph_optimizer import OptimizerSettings, optimize_graph, trajectory_ate
from ssmvpr_slam.backend.se3 import make_pose, relative, rot_z


def _circle(n: int, dim: int, loops: list[tuple[int, int]], rng: np.random.Generator | None = None) -> tuple[PoseGraphData, np.ndarray]:
    """Poses on a circle (3-D: a helix); measurements exact (or noisy); vertices all zero."""
    gt = []
    for k in range(n):
        a = 2 * np.pi * k / n
        z = 0.0 if dim == 2 else 0.2 * k
        gt.append(make_pose(rot_z(a + np.pi / 2), (5 * np.cos(a), 5 * np.sin(a), z)))
    gt = np.array(gt)
    info = np.diag([100.0] * 3 + [25.0] * 3)
    edges = []
    for i, j in [(k, k + 1) for k in range(n - 1)] + loops:
        rel = relative(gt[i], gt[j])
        if rng is not None:
            noise = planar_pose(*rng.normal(0, [0.05, 0.05, 0.02])) if dim == 2 else make_pose(np.eye(3), rng.normal(0, 0.05, 3))
            rel = rel @ noise
        edges.append(GraphEdge(i, j, rel, info))
    return PoseGraphData(dim, tuple(range(n)), np.tile(np.eye(4), (n, 1, 1)), tuple(edges), "circle", False), gt


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("batch", [False, True])
def test_exact_graph_reaches_its_optimum(dim: int, batch: bool) -> None:
    graph, gt = _circle(30, dim, [(0, 29), (5, 25), (10, 20)])
    result = optimize_graph(graph, OptimizerSettings(batch=batch))
    assert result.initialised_from_odometry
    assert trajectory_ate(gt, result.poses, dim).stats.rmse < 1e-6
    assert result.loop_inlier.all() and result.n_loops == 3


def test_gnc_keeps_ate_with_false_loops() -> None:
    rng = np.random.default_rng(3)
    true_loops = [(0, 39), (3, 36), (6, 33), (10, 30), (12, 28), (15, 25)]
    graph, gt = _circle(40, 2, true_loops, rng)
    clean = optimize_graph(graph, OptimizerSettings(kernel="none", gnc=False, batch=True))
    clean_ate = trajectory_ate(gt, clean.poses, 2).stats.rmse
    info = graph.loops[0].information
    false = [GraphEdge(int(i), int(j), planar_pose(0.1, -0.1, 0.05), info)
             for i, j in ((2, 20), (8, 35), (1, 17), (22, 38), (4, 27), (11, 33))]  # fmt: skip
    noisy = graph.with_edges((*graph.edges, *false))
    plain = optimize_graph(noisy, OptimizerSettings(kernel="none", gnc=False, batch=True))
    assert trajectory_ate(gt, plain.poses, 2).stats.rmse > 3 * clean_ate  # the false loops hurt
    robust = optimize_graph(noisy, OptimizerSettings(kernel="cauchy", gnc=True))  # iSAM2, then GNC
    assert trajectory_ate(gt, robust.poses, 2).stats.rmse <= 1.1 * clean_ate
    flagged = robust.loop_indices[~robust.loop_inlier]
    assert set(flagged.tolist()) == set(range(len(graph.edges), len(noisy.edges)))  # exactly the false ones
    assert robust.before_gnc is not None and "GNC" in robust.classification


def test_ring_from_shared_data(shared_dir: Path) -> None:
    base = shared_dir / "data" / "posegraphs" / "ring"
    graph = read_pose_graph(base / "originalDataset" / "ring.g2o")
    gt = read_ground_truth(base / "groundTruth" / "ring.g2o", graph)
    odometry = trajectory_ate(gt, graph.poses, 2).stats.rmse
    result = optimize_graph(graph)
    assert result.n_outliers == 0
    assert trajectory_ate(gt, result.poses, 2).stats.rmse < 0.5 * odometry


def test_settings_refuse_unknown_kernel() -> None:
    with pytest.raises(ValueError, match="kernel"):
        OptimizerSettings(kernel="l2")


def _drifting_circle_with_false_loops(dim: int) -> tuple[PoseGraphData, PoseGraphData, np.ndarray]:
    """(outlier-free graph, the same with as many random false loops as true ones, ground truth):
    noisy odometry drifts far enough that the loops' whitened errors at the odometry start are
    large, as on ring / ringCity."""
    rng = np.random.default_rng(7)
    true_loops = [(0, 59), (5, 55), (10, 50), (15, 45), (20, 40), (2, 31), (28, 58), (12, 47)]
    graph, gt = _circle(60, dim, true_loops, rng)
    edges = list(graph.edges)
    for n, e in enumerate(edges[:59]):  # a steady heading bias on the odometry
        edges[n] = GraphEdge(e.i, e.j, e.measured @ make_pose(rot_z(0.01), (0.0, 0.0, 0.0)), e.information)
    graph = graph.with_edges(edges)
    info = graph.loops[0].information
    false = []
    while len(false) < len(true_loops):
        i, j = sorted(int(v) for v in rng.integers(0, 60, 2))
        if j - i > 1:
            motion = planar_pose(*rng.normal(0, [0.3, 0.3, np.radians(10)]))
            false.append(GraphEdge(i, j, motion, info))
    return graph, graph.with_edges((*graph.edges, *false)), gt


@pytest.mark.parametrize("dim", [2, 3])
def test_default_configuration_holds_with_half_false_loops(dim: int) -> None:
    """The default of `optimize` (iSAM2 with DCS 10, then batch DCS 1) stays within 10 % of the
    outlier-free optimum with 50 % random false loops, from a drifted odometry start."""
    clean, noisy, gt = _drifting_circle_with_false_loops(dim)
    optimum = trajectory_ate(gt, optimize_graph(clean, OptimizerSettings(kernel="none", batch=True)).poses, dim)
    plain = optimize_graph(noisy, OptimizerSettings(kernel="none", batch=True))
    assert trajectory_ate(gt, plain.poses, dim).stats.rmse > 1.5 * optimum.stats.rmse  # the false loops hurt
    result = optimize_graph(noisy)
    assert trajectory_ate(gt, result.poses, dim).stats.rmse <= 1.1 * optimum.stats.rmse
    false_indices = set(range(len(clean.edges), len(noisy.edges)))
    assert set(result.loop_indices[~result.loop_inlier].tolist()) == false_indices
