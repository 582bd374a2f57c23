"""The printed run summary, read from the run's metrics: recall over what a camera could see
beside recall over all revisits, a prior map's loops and its own error, n/a where a ratio or a
recall has no meaning."""

from __future__ import annotations

import pytest
from pydantic import ValidationError
from rich.console import Console
from run_metrics_examples import example_ate, example_loops, example_metrics

from ssmvpr_slam.results.summary import summary_table


def _text(metrics) -> str:  # noqa: ANN001
    console = Console(record=True, width=200)
    console.print(summary_table(metrics))
    return console.export_text()


def test_summary_reports_camera_visible_and_directional_recall() -> None:
    loops = example_loops(proposed=40, gate_accepted=30, in_graph=30, precision=1.0, recall=0.6, recall_visible=0.9,
                          forward={"recall": 0.9}, reverse={"recall": None})  # fmt: skip
    text = _text(example_metrics(loops=loops))
    assert "1.000 / 0.600" in text
    assert "visible / forward / reverse revisits" in text and "0.900 / 0.900 / n/a" in text


def test_summary_reports_prior_map_loops_and_the_maps_own_error() -> None:
    """A `--map` run's loops go to the map: without these rows the summary read 0 / 0 / 0 loops and
    an optimised ATE above the odometry's with nothing to say the map itself was that far off."""
    parts = {
        "loops": example_loops(proposed=0, gate_accepted=0, in_graph=0, precision=None, recall=0.0),
        "prior_map_loops": {"places": 120, "places_with_pose": 120, "places_with_scan": 0, "loops_proposed": 113,
                            "loops_gate_accepted": 112, "loops_in_graph": 112, "anchored": True, "loops_correct": 112,
                            "precision": 1.0, "ate_rmse": 1.514},
        "ground_truth": True, "ground_truth_coverage": 1.0, "ground_truth_keyframes": 90,
        "ate_odometry": example_ate(0.74), "ate_optimised": example_ate(0.94), "ate_ratio": 1.27,
    }  # fmt: skip
    text = _text(example_metrics(**parts))
    assert "prior-map loops proposed / gate-accepted / in graph" in text and "113 / 112 / 112" in text
    assert "prior-map loop precision" in text and "1.000" in text
    assert "prior map's own ATE RMSE" in text and "1.51 m" in text
    assert "prior-map" not in _text(example_metrics(**{k: v for k, v in parts.items() if k != "prior_map_loops"}))


def test_summary_of_an_odometry_without_error() -> None:
    """Logged ground-truth poses as odometry have ATE 0, so no ratio: the summary must still print
    (it raised after the results were written, and the run exited 1)."""
    metrics = example_metrics(ground_truth=True, ground_truth_coverage=1.0, ground_truth_keyframes=12,
                              ate_odometry=example_ate(0.0), ate_optimised=example_ate(0.0), ate_ratio=None)  # fmt: skip
    text = _text(metrics)
    assert "optimised / odometry" in text and "n/a" in text


def test_the_summary_says_the_route_never_comes_back() -> None:
    never = example_loops(proposed=0, gate_accepted=0, in_graph=0, precision=None, recall=None, n_revisits=0)
    assert "none: no place is passed twice, no loop to find" in _text(example_metrics(loops=never))
    again = example_loops(proposed=0, gate_accepted=0, in_graph=0, precision=None, recall=None, n_revisits=12)
    assert "no place is passed twice" not in _text(example_metrics(loops=again))


@pytest.mark.parametrize("bad", [{"frames_sen": 3}, {"loops": example_loops(in_grph=3)}, {"keyframes": -1}])
def test_metrics_that_the_schema_does_not_declare_are_refused(bad: dict) -> None:
    with pytest.raises(ValidationError):
        example_metrics(**bad)
