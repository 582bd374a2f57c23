"""Figures of a run: top view with loop edges, translation error along the traverse, loop P/R.

Figures render on their own Agg canvas (no pyplot, no global backend switch, no display)
and every PNG is written atomically. Trajectories are drawn as
given: align odometry / optimised poses to the ground truth first (e.g. `AteResult.aligned_poses`).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from ssmvpr_common.atomic import atomic_write
from ssmvpr_slam.evaluation.config import PlotConfig
from ssmvpr_slam.evaluation.loop_metrics import LoopEvaluation

COLOURS = {
    "gt": "black",
    "odometry": "tab:orange",
    "optimised": "tab:blue",
    "correct": "tab:green",
    "wrong": "tab:red",
}
LOOP_ALPHA = 0.6
LOOP_WIDTH = 0.8


def new_figure(config: PlotConfig, height_scale: float = 1.0) -> Figure:
    """A figure bound to its own Agg canvas."""
    fig = Figure(figsize=(config.width_in, config.height_in * height_scale))
    FigureCanvasAgg(fig)
    return fig


def save_figure(fig: Figure, path: str | os.PathLike[str], config: PlotConfig | None = None) -> Path:
    """Lay out `fig` and render it to PNG atomically (on an Agg canvas, no pyplot)."""
    if not isinstance(fig.canvas, FigureCanvasAgg):
        FigureCanvasAgg(fig)
    fig.tight_layout()
    dpi = (config or PlotConfig()).dpi
    return atomic_write(path, lambda handle: fig.savefig(handle, format="png", dpi=dpi))


def _positions(name: str, poses: np.ndarray | None) -> np.ndarray | None:
    if poses is None:
        return None
    arr = np.asarray(poses, dtype=np.float64)
    if arr.ndim == 3 and arr.shape[1:] == (4, 4):
        arr = arr[:, :3, 3]
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name}: expected (N, 4, 4) poses or (N, 3) positions, got {arr.shape}")
    return arr


def plot_trajectories(
    path: str | os.PathLike[str],
    gt: np.ndarray | None = None,
    odometry: np.ndarray | None = None,
    optimised: np.ndarray | None = None,
    loops: Sequence[tuple[int, int]] = (),
    loop_correct: Sequence[bool] | None = None,
    title: str = "Trajectories (top view)",
    config: PlotConfig | None = None,
) -> Path:
    """Top view (x, y) of the trajectories with loop edges (q, m), green if correct, red if
    wrong. Edges join the odometry positions when given (there they span the drift each loop
    corrects; on the ground truth a correct loop has no length), else ground truth, else
    optimised, with a dot at both ends."""
    cfg = config or PlotConfig()
    series = {
        "ground truth": (_positions("gt", gt), COLOURS["gt"]),
        "odometry": (_positions("odometry", odometry), COLOURS["odometry"]),
        "optimised": (_positions("optimised", optimised), COLOURS["optimised"]),
    }
    if all(pos is None for pos, _ in series.values()):
        raise ValueError("gt, odometry, optimised: give at least one trajectory")
    if loop_correct is not None and len(loop_correct) != len(loops):
        raise ValueError(f"loop_correct: {len(loop_correct)} flags for {len(loops)} loops")
    fig = new_figure(cfg)
    ax = fig.subplots()
    # odometry wide and dashed under the optimised line: where loops changed little, both stay visible
    styles: dict[str, dict[str, Any]] = {
        "ground truth": {"linewidth": 1.2}, "odometry": {"linewidth": 2.6, "linestyle": (0, (4, 2))},
        "optimised": {"linewidth": 1.2},
    }  # fmt: skip
    for label, (pos, colour) in series.items():
        if pos is not None:
            ax.plot(pos[:, 0], pos[:, 1], color=colour, label=label, **styles[label])
    if not loops:
        ax.text(0.5, 0.5, "no loops", transform=ax.transAxes, ha="center", va="center", color="0.4", fontsize=14)
    order = ("odometry", "ground truth", "optimised")
    anchor = next(pos for pos, _ in (series[name] for name in order) if pos is not None)
    drawn: set[str] = set()
    for k, (q, m) in enumerate(loops):
        if not (0 <= q < len(anchor) and 0 <= m < len(anchor)):
            raise ValueError(f"loops[{k}]: keyframe index outside 0..{len(anchor) - 1}")
        ok = True if loop_correct is None else bool(loop_correct[k])
        kind = "correct" if ok else "wrong"
        loop_label = f"{kind} loop" if kind not in drawn else None
        drawn.add(kind)
        ax.plot(
            [anchor[q, 0], anchor[m, 0]],
            [anchor[q, 1], anchor[m, 1]],
            color=COLOURS[kind],
            alpha=LOOP_ALPHA,
            linewidth=LOOP_WIDTH,
            marker=".",
            label=loop_label,
        )
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_title(title)
    ax.legend(loc="best")
    ax.grid(True, alpha=0.3)
    return save_figure(fig, path, cfg)


def plot_translation_error(
    path: str | os.PathLike[str],
    odometry_errors: np.ndarray | None,
    optimised_errors: np.ndarray | None,
    distance_m: np.ndarray | None = None,
    title: str = "Translation error along the traverse",
    config: PlotConfig | None = None,
) -> Path:
    """Per-keyframe translation error (e.g. `AteResult.errors`) of odometry vs optimised,
    against travelled distance when given, else keyframe index."""
    cfg = config or PlotConfig()
    curves = {
        "odometry": (odometry_errors, COLOURS["odometry"]),
        "optimised": (optimised_errors, COLOURS["optimised"]),
    }
    if all(err is None for err, _ in curves.values()):
        raise ValueError("odometry_errors, optimised_errors: give at least one")
    fig = new_figure(cfg, height_scale=0.5)
    ax = fig.subplots()
    for label, (err, colour) in curves.items():
        if err is None:
            continue
        err = np.asarray(err, dtype=np.float64).reshape(-1)
        if distance_m is not None and len(distance_m) != len(err):
            raise ValueError(f"distance_m: {len(distance_m)} values for {len(err)} errors")
        x = np.arange(len(err)) if distance_m is None else np.asarray(distance_m)
        ax.plot(x, err, color=colour, label=label)
    ax.set_xlabel("keyframe" if distance_m is None else "distance travelled [m]")
    ax.set_ylabel("translation error [m]")
    ax.set_title(title)
    ax.legend(loc="best")
    ax.grid(True, alpha=0.3)
    return save_figure(fig, path, cfg)


def plot_loop_summary(
    path: str | os.PathLike[str],
    evaluation: LoopEvaluation,
    title: str = "Loop closures",
    config: PlotConfig | None = None,
) -> Path:
    """Precision / recall bars and the counts behind them."""
    cfg = config or PlotConfig()
    fig = new_figure(cfg, height_scale=0.5)
    ax_ratio, ax_count = fig.subplots(1, 2)
    ratios = {"precision": evaluation.precision, "recall": evaluation.recall}
    names = list(ratios)
    values = [0.0 if v is None else v for v in ratios.values()]
    bars = ax_ratio.bar(names, values, color=[COLOURS["optimised"], COLOURS["correct"]])
    for bar, value in zip(bars, ratios.values()):
        text = "n/a" if value is None else f"{value:.2f}"
        centre = (bar.get_x() + bar.get_width() / 2, bar.get_height())
        ax_ratio.annotate(text, centre, ha="center", va="bottom")
    ax_ratio.set_ylim(0.0, 1.1)
    ax_ratio.set_title("per query keyframe")
    counts = {
        "revisits": evaluation.n_revisits,
        "recalled": evaluation.n_recalled_revisits,
        "TP queries": evaluation.n_true_positive_queries,
        "FP queries": evaluation.n_false_positive_queries,
    }
    colours = [COLOURS["gt"], COLOURS["correct"], COLOURS["correct"], COLOURS["wrong"]]
    ax_count.bar(list(counts), list(counts.values()), color=colours)
    ax_count.tick_params(axis="x", labelrotation=30)
    ax_count.set_title("counts")
    if evaluation.n_revisits == 0:  # empty bars would read as a failure: the route never comes back
        for ax in (ax_ratio, ax_count):
            ax.text(0.5, 0.5, "no revisits in the ground truth:\nno loops to find", transform=ax.transAxes,
                    ha="center", va="center", color="0.3")  # fmt: skip
    elif evaluation.n_loops == 0:
        ax_ratio.text(0.5, 0.5, "no loops", transform=ax_ratio.transAxes, ha="center", va="center", color="0.3")
    fig.suptitle(title)
    return save_figure(fig, path, cfg)
