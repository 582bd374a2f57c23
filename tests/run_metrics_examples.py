"""Complete `RunMetrics` for tests of what reads them: a plain run's parts, with the parts a test
is about given (every model forbids keys it does not declare, so an example cannot drift from
what a run writes)."""

from __future__ import annotations

from typing import Any

from ssmvpr_slam.results.metrics import RunInputs, RunMetrics


def example_inputs(**changes: Any) -> RunInputs:
    parts: dict[str, Any] = {"log": "drive.mcap", "source": "mcap", "source_stats": {}, "odometry_kind": "kiss_icp",
                             "prior_map": None, "resumed_from": None}  # fmt: skip
    return RunInputs.model_validate({**parts, **changes})


def example_loops(**changes: Any) -> dict[str, Any]:
    direction = {"revisits": 10, "recalled": 6, "recall": 0.6, "visible": 10, "recall_visible": 0.6,
                 "loops_in_graph_by_sequence_direction": 6}  # fmt: skip
    loops = {
        "precision": 1.0, "recall": 0.6, "n_revisits": 10, "n_query_keyframes": 6, "n_true_positive_queries": 6,
        "n_false_positive_queries": 0, "n_recalled_revisits": 6, "recall_visible": 0.6, "n_visible_revisits": 10,
        "n_recalled_visible": 6, "by_direction": {"forward": direction, "reverse": {**direction, "revisits": 0}},
        "n_loops": 6, "n_correct_loops": 6, "proposed": 8, "gate_accepted": 6, "in_graph": 6,
        "rear_camera_keyframes": 0, "in_graph_by_camera": {"front": 6, "rear": 0},
    }  # fmt: skip
    for key, value in changes.items():
        if key in ("forward", "reverse"):
            loops["by_direction"][key] = {**loops["by_direction"][key], **value}
        else:
            loops[key] = value
    return loops


def example_ate(rmse: float) -> dict[str, Any]:
    transform = {
        "rotation": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        "translation": [0.0] * 3,
        "scale": 1.0,
    }
    return {"alignment": "se3", "rmse": rmse, "mean": rmse, "median": rmse, "std": 0.0, "min": 0.0, "max": rmse,
            "n": 10, "transform": transform}  # fmt: skip


def example_metrics(**parts: Any) -> RunMetrics:
    """A run of 100 frames and 90 keyframes without ground truth, with `parts` given."""
    run: dict[str, Any] = {
        "frames": 100, "frames_skipped": {}, "keyframes": 90, "recognition_started": True, "interrupted": False,
        "source_error": None, "error": None, "seconds": 10.0, "frames_per_second": 10.0, "latency_per_keyframe": {},
        "odometry": {}, "pose_graph_recoveries": [], **example_inputs().model_dump(), "ground_truth": False,
    }  # fmt: skip
    return RunMetrics.model_validate({**run, **parts})
