"""Evaluation of a run: trajectory I/O (TUM, KITTI), Umeyama alignment, ATE / RPE / drift /
KITTI relative error, loop-closure precision / recall, and plots. Plots (matplotlib) load only
when imported."""

from ssmvpr_common.trajectory_io import read_kitti, read_tum, write_kitti, write_tum
from ssmvpr_slam.evaluation.alignment import Alignment, align_trajectory, umeyama
from ssmvpr_slam.evaluation.config import (
    EvaluationConfig,
    LoopMetricsConfig,
    TrajectoryMetricsConfig,
)
from ssmvpr_slam.evaluation.loop_metrics import LoopEvaluation, evaluate_loops, find_revisits
from ssmvpr_slam.evaluation.metrics import (
    AteResult,
    DriftResult,
    ErrorStats,
    KittiLengthError,
    KittiRelativeError,
    RpeResult,
    associate,
    ate,
    drift_per_100m,
    kitti_relative_error,
    rpe,
)

__all__ = [
    "Alignment",
    "AteResult",
    "DriftResult",
    "ErrorStats",
    "EvaluationConfig",
    "KittiLengthError",
    "KittiRelativeError",
    "LoopEvaluation",
    "LoopMetricsConfig",
    "RpeResult",
    "TrajectoryMetricsConfig",
    "align_trajectory",
    "associate",
    "ate",
    "drift_per_100m",
    "evaluate_loops",
    "find_revisits",
    "kitti_relative_error",
    "read_kitti",
    "read_tum",
    "rpe",
    "umeyama",
    "write_kitti",
    "write_tum",
]
