"""PNG figures of VPR results: PR curves (per tolerance / per stage) and recall vs N.

Figures are drawn on matplotlib's Agg canvas directly (no pyplot), so plotting never touches
the global backend nor needs a display, and each PNG is written to a temporary file and moved
into place, so a crash never leaves a half-written image behind.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from loopclosure.metrics import PRCurve, pr_auc
from ssmvpr_slam.evaluation.plots import save_figure

__all__ = ["plot_pr_curves", "plot_recall_at_n"]


def plot_pr_curves(curves: Mapping[str, PRCurve], path: str | Path, title: str = "Precision-recall") -> Path:
    """All curves on one axes, each labelled with its AUC (trapezoid, see ``pr_auc``)."""
    if not curves:
        raise ValueError("plot_pr_curves: no curves given")
    fig = Figure(figsize=(6.0, 5.0))
    ax = fig.add_subplot()
    for label, curve in curves.items():
        ax.plot(curve.recall, curve.precision, linewidth=2, label=f"{label} (AUC {pr_auc(curve):.3f})")
    ax.set(xlim=(0.0, 1.02), ylim=(0.0, 1.02), xlabel="Recall", ylabel="Precision", title=title)
    ax.grid(True, linestyle=":")
    ax.legend(loc="lower left")
    return save_figure(fig, path)


def _n_and_recall(values: Mapping[int, float] | object) -> tuple[np.ndarray, np.ndarray]:
    """{n: recall}, a (2, k) array of (n, recall) rows, or recalls for n = 1..k."""
    if isinstance(values, Mapping):
        ns = np.array(sorted(values), dtype=float)
        return ns, np.array([values[int(n)] for n in ns], dtype=float)
    arr = np.asarray(values, dtype=float)
    if arr.ndim == 2 and arr.shape[0] == 2:
        return arr[0], arr[1]
    if arr.ndim == 1:
        return np.arange(1, arr.size + 1, dtype=float), arr
    raise ValueError(f"plot_recall_at_n: cannot read recall values of shape {arr.shape}")


def plot_recall_at_n(
    recall_by_stage: Mapping[str, Mapping[int, float] | object],
    path: str | Path,
    title: str = "Recall@N",
) -> Path:
    """Recall against the number of candidates N, one line per stage / method."""
    if not recall_by_stage:
        raise ValueError("plot_recall_at_n: no recall values given")
    fig = Figure(figsize=(6.0, 4.5))
    ax = fig.add_subplot()
    for label, values in recall_by_stage.items():
        ns, rec = _n_and_recall(values)
        ax.plot(ns, rec, marker="o", linewidth=2, label=label)
    ax.set(ylim=(0.0, 1.02), xlabel="N (candidates)", ylabel="Recall@N", title=title)
    ax.grid(True, linestyle=":")
    ax.legend(loc="lower right")
    return save_figure(fig, path)
