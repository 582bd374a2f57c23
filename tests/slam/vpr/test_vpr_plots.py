"""The VPR plots write complete PNG files and leave no temporary files behind."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from loopclosure.metrics import precision_recall_curve
from ssmvpr_slam.vpr.plots import plot_pr_curves, plot_recall_at_n

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _assert_png(path: Path) -> None:
    data = path.read_bytes()
    assert data.startswith(PNG_MAGIC) and len(data) > 1000
    assert [p.name for p in path.parent.iterdir() if p.name.startswith(".")] == []


def test_pr_curves_png(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    scores = rng.random(50)
    curves = {
        f"±{tol}": precision_recall_curve(scores, rng.random(50) < 0.5 + 0.1 * tol, np.ones(50, bool))
        for tol in (1, 2, 3)
    }
    out = plot_pr_curves(curves, tmp_path / "sub" / "pr.png", title="Corridor")
    assert out == tmp_path / "sub" / "pr.png"
    _assert_png(out)
    plot_pr_curves(curves, out, title="again")  # overwrite in place
    _assert_png(out)


def test_recall_at_n_png(tmp_path: Path) -> None:
    by_stage = {
        "stage I": {1: 0.6, 5: 0.8, 10: 0.9, 50: 0.97},
        "stage II": np.array([[1, 5, 10, 50], [0.8, 0.9, 0.95, 0.97]]),
        "N=1..4": [0.5, 0.6, 0.7, 0.8],
    }
    _assert_png(plot_recall_at_n(by_stage, tmp_path / "recall.png"))


def test_empty_input_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="no curves"):
        plot_pr_curves({}, tmp_path / "x.png")
    with pytest.raises(ValueError, match="no recall values"):
        plot_recall_at_n({}, tmp_path / "x.png")
    assert list(tmp_path.iterdir()) == []
