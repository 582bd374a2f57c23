"""`ssmvpr-slam optimize`: a pose-graph file solved robustly, judged against ground truth when
given, written as a new results folder. The command line (`cli/evaluation.py`) only parses the
options."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.markup import escape

from ssmvpr_common.trajectory_io import write_tum
from ssmvpr_slam.backend import g2o_io
from ssmvpr_slam.backend.graph_optimizer import KERNEL_NAMES, OptimizerSettings, initial_poses, optimize_graph
from ssmvpr_slam.backend.gtsam_errors import gtsam_reason
from ssmvpr_slam.errors import OptionError
from ssmvpr_slam.evaluation.graph_metrics import loop_classification_scores, trajectory_ate
from ssmvpr_slam.results.run_folder import output_dir, staged_results_dir, write_json


def run_optimize(
    graph: Path,
    console: Console,
    *,
    gt: Path | None = None,
    gt_edges: Path | None = None,
    gt_radius: float | None = None,
    times: Path | None = None,
    kernel: str = "dcs",
    gnc: bool = True,
    check: bool = True,
    refine: bool = True,
    batch: bool | None = None,
    from_odometry: bool = False,
    out: Path | None = None,
) -> tuple[Path, dict[str, Any]]:
    """Solve, judge and write (the options are the CLI's, validated here); returns (the results
    folder, its metrics)."""
    if kernel not in KERNEL_NAMES:
        raise OptionError(f"--kernel: expected one of {', '.join(KERNEL_NAMES)}, got {kernel!r}")
    if gt_radius is not None:
        if not gt_radius > 0 or not np.isfinite(gt_radius):
            raise OptionError(f"--gt-radius: expected metres > 0, got {gt_radius}")
        if gt is None or gt_edges is not None:
            raise OptionError("--gt-radius: needs --gt, and replaces --gt-edges")
    base = out if out is not None else Path("results")
    with output_dir(base, "--out"):  # checked before the graph is read
        data = g2o_io.read_pose_graph(graph)
        if from_odometry:
            data = data.without_estimate()
        stamps = g2o_io.read_times(times, data) if times is not None else None
        gt_poses = g2o_io.read_ground_truth(gt, data, stamps) if gt is not None else None
        true_pairs: set[tuple[int, int]] | None = None
        if gt_edges is not None:  # checked before the solve: an odometry-only list would call every loop false
            true_pairs = g2o_io.read_edge_pairs(gt_edges)
            g2o_io.check_loop_truth(gt_edges, true_pairs, data)
        solver = "auto" if batch is None else "batch" if batch else "isam2"
        settings = OptimizerSettings(kernel=kernel, gnc=gnc, solver=solver, verify=check)
        if not refine:
            settings = replace(settings, refine_scales=())
        try:
            result = optimize_graph(data, settings)
        except RuntimeError as exc:  # GTSAM's: an indeterminate or ill-conditioned system
            raise g2o_io.PoseGraphFileError(
                f"{graph}: GTSAM could not optimise this graph in the robust solve ({gtsam_reason(exc)}); look for edges with extreme information "
                "or translations, and for vertices no edge connects to the first"
            ) from None
        loops = [data.edges[k] for k in result.loop_indices]
        metrics: dict[str, Any] = {
            "graph": str(graph), "dimension": data.dim, "vertices": len(data.ids), "edges": len(data.edges),
            "odometry_edges": len(data.edges) - len(loops), "loop_candidates": len(loops),
            "initialised_from_odometry": result.initialised_from_odometry,
            "solver": solver, "kernel_solve": result.solver,
            "start_tls": dict(result.start_tls), "kernel": kernel,
            "refine_scales": list(settings.refine_scales) if kernel != "none" else [], "gnc": gnc,
            "check": gnc and check and result.check_error is None, "check_error": result.check_error,
            "check_removed": result.check_removed, "check_readmitted": result.check_readmitted,
            "seconds": result.seconds,
            "loops_inlier": int(result.loop_inlier.sum()), "loops_outlier": result.n_outliers,
            "classification": result.classification,
            "outlier_loops": [[e.i, e.j] for e, ok in zip(loops, result.loop_inlier) if not ok],
        }  # fmt: skip
        if gt_poses is not None:
            metrics["ate"] = trajectory_ate(gt_poses, result.poses, data.dim).to_dict()
            metrics["ate_initial"] = trajectory_ate(gt_poses, initial_poses(data)[0], data.dim).to_dict()
        truth = None
        if true_pairs is not None:
            truth = np.array([(min(e.i, e.j), max(e.i, e.j)) not in true_pairs for e in loops], dtype=bool)
        elif gt_radius is not None and gt_poses is not None:
            ends = np.array([[data.index_of(e.i), data.index_of(e.j)] for e in loops], dtype=int).reshape(-1, 2)
            truth = np.linalg.norm(gt_poses[ends[:, 0], :3, 3] - gt_poses[ends[:, 1], :3, 3], axis=1) > gt_radius
        if truth is not None:
            metrics["loop_classification"] = loop_classification_scores(~result.loop_inlier, truth)
            metrics["loop_classification"]["truth"] = (str(gt_edges) if true_pairs is not None
                                                       else f"ground truth within {gt_radius} m")  # fmt: skip
            if gt_poses is not None:  # the bound: least squares over odometry and the true loops alone
                false = set(result.loop_indices[truth].tolist())
                true_graph = data.with_edges(e for n, e in enumerate(data.edges) if n not in false)
                oracle = optimize_graph(  # from odometry, not from a stored estimate false loops may have bent
                    true_graph.without_estimate(), OptimizerSettings(kernel="none", gnc=False, solver="batch")
                )
                bound = trajectory_ate(gt_poses, oracle.poses, data.dim)
                metrics["ate_oracle"] = bound.to_dict()
                metrics["ate_ratio_to_oracle"] = (
                    metrics["ate"]["rmse"] / bound.stats.rmse if bound.stats.rmse > 1e-12 else None
                )  # an exact graph has a bound of 0
        with staged_results_dir(base, "optimize") as staged:  # a new folder per call; latest-optimize moves last
            g2o_io.write_g2o(staged.path / "optimised.g2o", data, result.poses)
            if stamps is not None:
                write_tum(staged.path / "optimised.tum", stamps, result.poses)
            write_json(staged.path / "metrics.json", metrics)
    if result.check_error is not None:
        console.print(f"[yellow]warning:[/yellow] {escape(str(graph))}: {escape(result.check_error)}", highlight=False)
    summary = f"{len(data.ids)} vertices, {len(loops)} loop candidates, {result.n_outliers} rejected"
    if "ate" in metrics:
        summary += f", ATE {metrics['ate']['rmse']:.3f} m"
    if "ate_oracle" in metrics:
        summary += f" (true loops alone: {metrics['ate_oracle']['rmse']:.3f} m)"
    console.print(f"{summary}; wrote [bold]{escape(str(staged.final))}[/bold] ({result.seconds:.1f} s)")
    assert staged.final is not None
    return staged.final, metrics
