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
