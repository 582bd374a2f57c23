"""How an optimised pose graph is judged (`optimize`, `tools/bench_backend.py`): ATE after the
alignment its dimension allows, and how well the loops were sorted into true and false."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ssmvpr_slam.evaluation.metrics import AteResult, ate


def planar_alignment(est: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Est poses moved by the SE(2) transform (rotation about z, xy translation) that best
    aligns their positions onto ref's (2-D Umeyama without scale)."""
    a, b = est[:, :2, 3], ref[:, :2, 3]
    mu_a, mu_b = a.mean(axis=0), b.mean(axis=0)
    cov = (b - mu_b).T @ (a - mu_a)
    u, _, vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(u @ vt))
    rot2 = u @ np.diag([1.0, d]) @ vt
    transform = np.eye(4)
    transform[:2, :2] = rot2
    transform[:2, 3] = mu_b - rot2 @ mu_a
    return transform @ est


def trajectory_ate(gt: np.ndarray, est: np.ndarray, dim: int) -> AteResult:
    """ATE of `est` against `gt` after SE(2) alignment (2-D graphs) or SE(3) (3-D graphs)."""
    if dim == 2:
        result = ate(gt, planar_alignment(np.asarray(est), np.asarray(gt)), "none")
        return replace(result, alignment_kind="se2")
    return ate(gt, est, "se3")


def loop_classification_scores(
    predicted_outlier: np.ndarray, true_outlier: np.ndarray
) -> dict[str, float | int | None]:
    """Precision / recall of the outlier class (true positive = a false loop flagged outlier)."""
    pred = np.asarray(predicted_outlier, dtype=bool)
    truth = np.asarray(true_outlier, dtype=bool)
    tp = int(np.sum(pred & truth))
    fp = int(np.sum(pred & ~truth))
    fn = int(np.sum(~pred & truth))
    return {
        "loops": int(len(pred)),
        "true_outliers": int(truth.sum()),
        "flagged_outliers": int(pred.sum()),
        "true_positives": tp,
        "false_positives": fp,
        "false_negatives": fn,
        "outlier_precision": tp / (tp + fp) if tp + fp else None,
        "outlier_recall": tp / (tp + fn) if tp + fn else None,
    }
