"""`vpr-eval`, `loop-eval` and `optimize`: the benchmarks, each measuring one part on its own
(recognition, loop-closure detection, the robust back end). Their work is in `vpr.evaluate`,
`loop_eval.runner` and `optimize`; a command here parses its options and calls it."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ssmvpr_slam.cli.common import (
    ConfigOpt,
    DeviceOpt,
    OutOpt,
    WeightsOpt,
    app,
    console,
    examples,
    make_config,
    out_option,
    validated_update,
)
from ssmvpr_slam.cli.errors import friendly_errors


@app.command(
    "vpr-eval",
    epilog=examples(
        "ssmvpr-slam vpr-eval ../shared/data/corridor/ref ../shared/data/corridor/query --weights $W",
        "ssmvpr-slam vpr-eval REF QUERY --gt gt.csv -L 3 -L 5 --direction forward",
    ),
)
@friendly_errors
def vpr_eval(
    ref: Annotated[Path, typer.Argument(help="Reference (database) image folder.")],
    query: Annotated[Path, typer.Argument(help="Query image folder.")],
    gt: Annotated[
        Path | None,
        typer.Option(
            help="Ground truth: VPR-Bench .npy or CSV (Reference/Live or Serial No,Query,Ref). "
            "Default: frame-aligned sorted filenames."
        ),
    ] = None,
    tolerance: Annotated[
        int | None,
        typer.Option(
            help="± frames around each true reference counted as correct (default 2; 0 for a --gt file that already "
            "lists windows, as VPR-Bench .npy files do)."
        ),
    ] = None,
    sequential: Annotated[
        bool | None,
        typer.Option(
            "--sequential/--no-sequential", help="Frame-correlation prior (RAS 2020); default: as configured."
        ),
    ] = None,
    num_candidates: Annotated[
        int | None, typer.Option("--num-candidates", "-n", help="N of the filtering stage.")
    ] = None,
    sequence: Annotated[
        list[int] | None,
        typer.Option(
            "--sequence", "-L", help="Also match sequences of L queries (repeat for several L; 1 = single frames)."
        ),
    ] = None,
    direction: Annotated[
        str | None,
        typer.Option(metavar="[forward|reverse|both]", help="Sequence direction (default forward)."),
    ] = None,
    pca: Annotated[Path | None, typer.Option(help="Codebooks from `fit-pca` (default: fit on the references).")] = None,
    config: ConfigOpt = None,
    weights: WeightsOpt = None,
    device: DeviceOpt = None,
    out: OutOpt = None,
) -> None:
    """Recognition on a VPR benchmark: PR curves, AUC, recall@N, timings (the paper's protocol)."""
    from ssmvpr_slam.results.run_folder import output_dir
    from ssmvpr_slam.vpr.evaluate import run_vpr_eval

    cfg = make_config(config, weights, device, out)
    if tolerance is not None:
        cfg.vpr_eval.tolerance = tolerance
    if sequence:
        cfg.vpr_eval.sequence_lengths = sorted(set(sequence))
    if direction is not None:
        cfg.vpr_eval.sequence = validated_update(cfg.vpr_eval.sequence, {"direction": direction})
    if num_candidates is not None:
        cfg.vpr.filtering.num_candidates = num_candidates
    if sequential is None:
        sequential = cfg.vpr.frame_correlation.enabled
    with output_dir(cfg.results.out_dir, out_option(out)):
        run_vpr_eval(ref, query, cfg, gt, sequential, pca, console)


@app.command(
    "loop-eval",
    epilog=examples(
        "ssmvpr-slam loop-eval ../shared/data/gardens_point_half/day_right ../shared/data/gardens_point_half/night_right "
        "--weights $W",
        "ssmvpr-slam loop-eval images/ --gt-poses poses.txt --radius 10",
        "ssmvpr-slam loop-eval kitti00/image_0 --gt-matrix kitti00_loops.mat",
        "ssmvpr-slam loop-eval drive.bag --radius 10 --weights $W",
        "ssmvpr-slam loop-eval ../shared/data/gardens_point_half/day_right ../shared/data/gardens_point_half/night_right "
        "--verify --weights $W",
    ),
)
@friendly_errors
def loop_eval(
    sequences: Annotated[
        list[Path],
        typer.Argument(
            help="FIRST SECOND: two passes of one route, streamed one after the other (every SECOND frame i "
            "revisits FIRST frame i); or one SEQUENCE with --gt-poses or --gt-matrix; or one LOG (MCAP, ROS bag, "
            "KITTI folder) judged by its own ground-truth poses, a keyframe per frontend.keyframes step.",
            show_default=False,
        ),
    ],
    gt: Annotated[
        Path | None,
        typer.Option(
            help="Two passes: a vpr-eval ground-truth file (.npy VPR-Bench, .csv) instead of frame-aligned names."
        ),
    ] = None,
    gt_poses: Annotated[
        Path | None,
        typer.Option(
            "--gt-poses",
            help="One sequence: ground-truth poses (TUM or KITTI, one per image); a revisit is "
            "an earlier frame within --radius outside the exclusion window.",
        ),
    ] = None,  # fmt: skip
    gt_matrix: Annotated[
        Path | None,
        typer.Option(
            "--gt-matrix",
            help="One sequence: a square 0/1 loop matrix (.npy, .csv or MATLAB .mat), as "
            "published for KITTI 00/05/06, City Centre, New College, Lip6, Malaga.",
        ),
    ] = None,  # fmt: skip
    gt_threshold: Annotated[
        float | None,
        typer.Option(
            "--gt-threshold",
            help="With --gt-matrix: a matrix of similarities, whose values >= this are loops (without it, "
            "values other than 0/1 are refused).",
        ),
    ] = None,  # fmt: skip
    tolerance: Annotated[int, typer.Option(help="± frames around a true place that count as correct.")] = 2,
    radius: Annotated[
        float, typer.Option(help="--gt-poses or a LOG: metres within which a frame revisits another.")
    ] = 10.0,
    spacing: Annotated[
        float, typer.Option(help="Metres per frame for the exclusion window, without --gt-poses.")
    ] = 1.0,
    rear: Annotated[
        list[Path] | None, typer.Option(help="A rear camera's image folder per sequence (repeat, in order).")
    ] = None,
    verify: Annotated[
        bool,
        typer.Option(
            "--verify",
            help="Check every accepted loop by two views on the backbone's own features (the verifier `run` uses, "
            "backend.registration.two_view.deep; a fundamental matrix, images carry no intrinsics); a loop the views "
            "refuse stands when 2 earlier verified loops of its revisit agree with it along the path, as a run's "
            "on_geometry_failure: consistent. Reports the loops with and without it.",
        ),
    ] = False,
    config: ConfigOpt = None,
    weights: WeightsOpt = None,
    device: DeviceOpt = None,
    out: OutOpt = None,
) -> None:
    """Loop-closure detection benchmark through the detector `run` builds: precision and recall at its
    decision, maximum recall at 100% precision, PR curve (metrics.json, loops.csv, pr.png)."""
    from ssmvpr_slam.loop_eval.runner import LoopEvalInputs, run_loop_eval
    from ssmvpr_slam.results.run_folder import output_dir

    cfg = make_config(config, weights, device, out)
    inputs = LoopEvalInputs(tuple(sequences), gt, gt_poses, gt_matrix, tolerance, radius, spacing, tuple(rear or ()),
                            gt_threshold=gt_threshold)  # fmt: skip
    with output_dir(cfg.results.out_dir, out_option(out)):
        run_loop_eval(inputs, cfg, console, verify=verify)


@app.command(
    "optimize",
    epilog=examples(
        "ssmvpr-slam optimize results/latest-run/pose_graph.g2o --gt results/latest-run/ground_truth.tum",
        "ssmvpr-slam optimize ../shared/data/posegraphs/<graph>.g2o --kernel cauchy --no-gnc",
    ),
)
@friendly_errors
def optimize(
    graph: Annotated[Path, typer.Argument(help="Pose graph: g2o (SE2 / SE3:QUAT) or TORO 2D.")],
    gt: Annotated[Path | None, typer.Option(help="Ground truth: g2o, TUM (.tum) or a per-vertex pose file.")] = None,
    gt_edges: Annotated[
        Path | None, typer.Option("--gt-edges", help="The true edges (i j ... per line): loops not listed are false.")
    ] = None,
    gt_radius: Annotated[
        float | None,
        typer.Option(
            "--gt-radius",
            help="With --gt and no --gt-edges: a loop is true when its two vertices are within this many "
            "metres in the ground truth (a place recogniser's loops against GPS).",
        ),
    ] = None,
    times: Annotated[
        Path | None, typer.Option(help="Vertex timestamps ('t' or 'id t' per line): also write TUM.")
    ] = None,
    kernel: Annotated[
        str, typer.Option(metavar="[cauchy|huber|dcs|gm|tukey|none]", help="Robust kernel on the loop edges.")
    ] = "dcs",
    gnc: Annotated[
        bool,
        typer.Option(
            "--gnc/--no-gnc",
            help="GNC (TLS, odometry as known inliers) after the kernel solve (default on; docs/backend_benchmarks.md).",
        ),
    ] = True,
    check: Annotated[
        bool,
        typer.Option("--check/--no-check", help="With GNC: leave-one-out check of the loops GNC keeps (default on)."),
    ] = True,
    refine: Annotated[
        bool, typer.Option("--refine/--no-refine", help="After the first kernel solve, one batch solve at scale 1.")
    ] = True,
    batch: Annotated[
        bool | None,
        typer.Option(
            "--batch/--isam2",
            help="Kernel solve: one batch solve, or iSAM2 in vertex order as a stream would. Default: batch from "
            "the graph's own vertex estimate; both, keeping the lower TLS objective, when the vertices are "
            "chained from odometry.",
            show_default=False,
        ),
    ] = None,
    from_odometry: Annotated[
        bool,
        typer.Option(
            "--from-odometry",
            help="Ignore the vertex estimate in the file and chain odometry (as for all-zero vertices).",
        ),
    ] = False,
    out: OutOpt = None,
) -> None:
    """Optimise a g2o / TORO pose graph robustly; write optimised.g2o, TUM and metrics.json into a new
    optimize_<stamp> folder (and latest-optimize)."""
    from ssmvpr_slam.app.optimize import run_optimize

    run_optimize(graph, console, gt=gt, gt_edges=gt_edges, gt_radius=gt_radius, times=times, kernel=kernel, gnc=gnc,
                 check=check, refine=refine, batch=batch, from_odometry=from_odometry, out=out)  # fmt: skip
