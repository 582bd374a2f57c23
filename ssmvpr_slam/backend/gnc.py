"""Batch outlier rejection of loop closures with GTSAM's graduated non-convexity (GNC).

Kept apart from `pose_graph` because it rebuilds the full graph from plain records: GNC needs
Gaussian factors (it supplies the robust loss itself) and the indices of the known inliers.
"""

from __future__ import annotations

from collections.abc import Callable

import gtsam
import numpy as np

from ssmvpr_slam.backend.config import GncConfig

Edge = tuple[int, int, np.ndarray, gtsam.noiseModel.Base]


def run_gnc(
    prior: tuple[int, np.ndarray, gtsam.noiseModel.Base],
    odom_edges: list[Edge],
    loops: dict[int, Edge],
    initial: gtsam.Values,
    key: Callable[[int], int],
    config: GncConfig,
):
    """Optimise prior + odometry + loops with GNC; return a `GncResult` keyed by loop handle."""
    from ssmvpr_slam.backend.pose_graph import GncResult

    graph = gtsam.NonlinearFactorGraph()
    kf0, pose0, prior_noise = prior
    graph.add(gtsam.PriorFactorPose3(key(kf0), gtsam.Pose3(pose0), prior_noise))
    for i, j, measured, gauss in odom_edges:
        graph.add(gtsam.BetweenFactorPose3(key(i), key(j), gtsam.Pose3(measured), gauss))
    known_inliers = list(range(graph.size()))
    slots: dict[int, int] = {}
    for handle, (i, j, measured, gauss) in loops.items():
        slots[handle] = graph.size()
        graph.add(gtsam.BetweenFactorPose3(key(i), key(j), gtsam.Pose3(measured), gauss))

    kf_ids = _kf_ids(prior, odom_edges)
    if not loops:
        # Nothing to classify; GNC would only re-run LM with every factor a known inlier.
        values = gtsam.LevenbergMarquardtOptimizer(graph, initial).optimize()
        return GncResult(_poses(values, kf_ids, key), [], [], {})

    lm_params = gtsam.LevenbergMarquardtParams()
    params = gtsam.GncLMParams(lm_params)
    params.setLossType(gtsam.GncLossType.TLS if config.loss == "tls" else gtsam.GncLossType.GM)
    if params.maxIterations != config.max_iterations:  # GTSAM prints a warning on every set
        params.setMaxIterations(config.max_iterations)
    params.setKnownInliers(known_inliers)
    optimizer = gtsam.GncLMOptimizer(graph, initial, params)
    optimizer.setInlierCostThresholdsAtProbability(config.inlier_probability)
    values = optimizer.optimize()
    weights_all = np.asarray(optimizer.getWeights())
    weights = {h: float(weights_all[s]) for h, s in slots.items()}
    inliers = [h for h, w in weights.items() if w >= config.weight_threshold]
    outliers = [h for h, w in weights.items() if w < config.weight_threshold]
    return GncResult(_poses(values, kf_ids, key), inliers, outliers, weights)


def _kf_ids(prior: tuple[int, np.ndarray, object], odom_edges: list[Edge]) -> list[int]:
    return [prior[0]] + [edge[1] for edge in odom_edges]


def _poses(
    values: gtsam.Values, kf_ids: list[int], key: Callable[[int], int]
) -> dict[int, np.ndarray]:
    return {kf: values.atPose3(key(kf)).matrix() for kf in kf_ids}
