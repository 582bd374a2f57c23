"""The printed run summary states recall over what a camera could see beside recall over all revisits."""

from __future__ import annotations

from rich.console import Console

from ssmvpr_slam.runner import summary_table


def test_summary_reports_camera_visible_and_directional_recall() -> None:
    metrics = {
        "frames": 100, "keyframes": 90,
        "loops": {
            "proposed": 40, "gate_accepted": 30, "in_graph": 30, "precision": 1.0, "recall": 0.6,
            "recall_visible": 0.9,
            "by_direction": {"forward": {"recall": 0.9}, "reverse": {"recall": None}},
        },
    }  # fmt: skip
    console = Console(record=True, width=200)
    console.print(summary_table(metrics))
    text = console.export_text()
    assert "1.000 / 0.600" in text
    assert "visible / forward / reverse revisits" in text and "0.900 / 0.900 / n/a" in text


def test_summary_reports_prior_map_loops_and_the_maps_own_error() -> None:
    """A `--map` run's loops go to the map: without these rows the summary read 0 / 0 / 0 loops and
    an optimised ATE above the odometry's with nothing to say the map itself was that far off."""
    metrics = {
        "frames": 100, "keyframes": 90,
        "loops": {"proposed": 0, "gate_accepted": 0, "in_graph": 0, "precision": None, "recall": 0.0},
        "prior_map_loops": {"places": 120, "places_with_pose": 120, "loops_proposed": 113, "loops_gate_accepted": 112,
                            "loops_in_graph": 112, "anchored": True, "loops_correct": 112, "precision": 1.0,
                            "ate_rmse": 1.514},
        "ground_truth_coverage": 1.0, "ground_truth_keyframes": 90,
        "ate_odometry": {"rmse": 0.74}, "ate_optimised": {"rmse": 0.94}, "ate_ratio": 1.27,
    }  # fmt: skip
    console = Console(record=True, width=200)
    console.print(summary_table(metrics))
    text = console.export_text()
    assert "prior-map loops proposed / gate-accepted / in graph" in text and "113 / 112 / 112" in text
    assert "prior-map loop precision" in text and "1.000" in text
    assert "prior map's own ATE RMSE" in text and "1.51 m" in text
    without = Console(record=True, width=200)
    without.print(summary_table({k: v for k, v in metrics.items() if k != "prior_map_loops"}))
    assert "prior-map" not in without.export_text()


def test_summary_of_an_odometry_without_error() -> None:
    """Logged ground-truth poses as odometry have ATE 0, so no ratio: the summary must still print
    (it raised after the results were written, and the run exited 1)."""
    metrics = {
        "frames": 12, "keyframes": 12, "ground_truth_coverage": 1.0, "ground_truth_keyframes": 12,
        "ate_odometry": {"rmse": 0.0}, "ate_optimised": {"rmse": 0.0}, "ate_ratio": None,
    }  # fmt: skip
    console = Console(record=True, width=200)
    console.print(summary_table(metrics))
    text = console.export_text()
    assert "optimised / odometry" in text and "n/a" in text
