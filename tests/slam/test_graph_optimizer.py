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
