"""Batch outlier rejection of loop closures with GTSAM's graduated non-convexity (GNC).

Kept apart from `pose_graph` because it rebuilds the full graph from plain records: GNC needs
Gaussian factors (it supplies the robust loss itself) and the indices of the known inliers.
"""

from __future__ import annotations

from dataclasses import dataclass

import gtsam
import numpy as np

from ssmvpr_slam.backend.config import GncConfig


@dataclass(frozen=True)
class GncResult:
    """Outcome of the batch GNC pass; handles refer to `add_loop`'s return values."""

    poses: dict[int, np.ndarray]
    inliers: list[int]
    outliers: list[int]
    weights: dict[int, float]


def run_gnc(
    known: list[gtsam.NonlinearFactor],
    loops: dict[int, gtsam.NonlinearFactor],
    initial: gtsam.Values,
    pose_keys: dict[int, int],
    config: GncConfig,
) -> GncResult:
    """Optimise known-inlier factors plus Gaussian loop factors with GNC.

    Returns a `GncResult` with the poses of `pose_keys` (keyframe id -> variable key) and the
    loops classified by handle.
    """
    graph = gtsam.NonlinearFactorGraph()
    for factor in known:
        graph.add(factor)
    known_inliers = list(range(graph.size()))
    slots: dict[int, int] = {}
    for handle, factor in loops.items():
        slots[handle] = graph.size()
        graph.add(factor)

    if not loops:
        # Nothing to classify; GNC would only re-run LM with every factor a known inlier.
        values = gtsam.LevenbergMarquardtOptimizer(graph, initial).optimize()
        return GncResult(_poses(values, pose_keys), [], [], {})

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
    return GncResult(_poses(values, pose_keys), inliers, outliers, weights)


def _poses(values: gtsam.Values, pose_keys: dict[int, int]) -> dict[int, np.ndarray]:
    return {kf: values.atPose3(key).matrix() for kf, key in pose_keys.items()}
