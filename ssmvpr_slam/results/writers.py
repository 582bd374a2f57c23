"""Files of a run, each from the `RunResult` (and the `RunReport`): nothing here changes either.

One writer per output, each atomic (a temp file renamed into place), so any subset can be
written again (a checkpoint writes the trajectories and the loop log of a partial run with
the same functions as the final results):

- `write_trajectories`: odometry / optimised / ground truth in TUM and KITTI (evo reads them);
- `write_pose_graph`: pose_graph.g2o;
- `write_loop_csv`: loop_closures.csv, one row per proposal with its final in-graph status;
- `write_database`: the place database with map poses and scans or kept images (a prior map for `--map`);
- `write_metrics`: metrics.json;
- `write_plots`: top view, translation error, loop precision/recall;
- `write_trajectory_mcap`: trajectory.mcap for Foxglove (`ssmvpr_slam.results.mcap_output`).
"""

from __future__ import annotations

import csv
import io
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ssmvpr_common.atomic import atomic_write_text
from ssmvpr_common.trajectory_io import write_kitti, write_tum
from ssmvpr_slam.backend.g2o_io import write_g2o
from ssmvpr_slam.config.slam import SlamConfig, dump_config
from ssmvpr_slam.evaluation.run_report import RunReport
from ssmvpr_slam.prior_map import REAR_FOLDER, KeptImages, save_map
from ssmvpr_slam.results.metrics import RunInputs, RunMetrics
from ssmvpr_slam.results.run_folder import write_json
from ssmvpr_slam.run_result import Keyframe, LoopRecord, RunResult, has_ground_truth

LOOP_COLUMNS = [
    "query_kf", "match_kf", "score", "stage1_score", "column_shift", "yaw_guess_rad", "gate_accepted",
    "gate_reason", "camera", "direction", "sequence_score", "sequence_terms", "decision_score", "runner_up",
    "registration", "registration_accepted",
    "registration_reason",
    "inlier_ratio", "rmse", "in_graph", "prior_map", "gt_distance_m",
]  # fmt: skip


def write_results(
    folder: Path, result: RunResult, report: RunReport, config: SlamConfig, inputs: RunInputs
) -> RunMetrics:
    """Every output of a finished run into `folder`; returns what metrics.json holds."""
    write_trajectories(folder, result)
    write_pose_graph(folder, result)
    write_loop_csv(folder / "loop_closures.csv", result.keyframes, result.loops, prior_gt(result))
    write_config(folder, config)
    if config.results.save_database:
        write_database(folder / "database", result, config)
    metrics = write_metrics(folder, result, report, inputs)
    if config.results.plots:
        write_plots(folder, result, report, config)
    if config.results.mcap:
        from ssmvpr_slam.results.mcap_output import write_trajectory_mcap

        write_trajectory_mcap(folder / "trajectory.mcap", result)  # thumbnails were made per keyframe
    return metrics


def write_trajectories(folder: Path, result: RunResult) -> None:
    """TUM and KITTI files of the keyframes (none for a run without keyframes: no empty file)."""
    kfs = result.keyframes
    if not kfs:
        return
    write_tum(folder / "odometry.tum", result.stamps, result.odometry)
    write_kitti(folder / "odometry.kitti", result.odometry)
    write_tum(folder / "optimised.tum", result.stamps, result.optimised)
    write_kitti(folder / "optimised.kitti", result.optimised)
    covered = has_ground_truth(kfs)
    if covered.any():  # TUM has stamps, so a partial ground truth is still one file evo reads
        write_tum(
            folder / "ground_truth.tum",
            result.stamps[covered],
            np.array([k.gt_pose for k, ok in zip(kfs, covered) if ok]),
        )
    if covered.all():  # KITTI lines are matched by position: only a complete one
        write_kitti(folder / "ground_truth.kitti", np.array([k.gt_pose for k in kfs]))


def write_pose_graph(folder: Path, result: RunResult) -> None:
    if result.pose_graph is not None:
        write_g2o(folder / "pose_graph.g2o", result.pose_graph, result.optimised)


def write_config(folder: Path, config: SlamConfig) -> None:
    atomic_write_text(folder / "config.yaml", dump_config(config))


def prior_gt(result: RunResult) -> dict[int, np.ndarray]:
    """Ground truth of the prior map's places (by place index), where its sessions had it."""
    return {} if result.prior_map is None else result.prior_map.gt_poses


def write_loop_csv(
    path: Path,
    keyframes: tuple[Keyframe, ...] | list[Keyframe],
    loops: tuple[LoopRecord, ...] | list[LoopRecord],
    prior_gt: dict[int, np.ndarray] | None = None,
) -> None:
    """One row per proposal; `in_graph` is whether its factor is in the graph at the end (GNC may drop it).
    prior_gt: the prior map's ground truth by place, for the distance of loops to it."""
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(LOOP_COLUMNS)
    for record in loops:
        p, reg = record.proposal, record.registration
        distance = _gt_distance(keyframes, record, prior_gt or {})
        writer.writerow([
            p.query_id, p.match_id, f"{p.score:.4f}", f"{p.stage1_score:.4f}", p.column_shift, f"{p.yaw_guess:.4f}",
            int(p.accepted), p.reason, p.camera, p.direction or "",
            "" if p.sequence_score is None else f"{p.sequence_score:.4f}", p.sequence_terms,
            "" if p.decision_score is None else f"{p.decision_score:.3f}",
            "" if p.runner_up_score is None else f"{p.runner_up_score:.4f}",
            reg.method if reg else "", int(reg.accepted) if reg else "",
            reg.reason if reg else "", f"{reg.inlier_ratio:.3f}" if reg else "", f"{reg.rmse:.3f}" if reg else "",
            int(record.in_graph), int(p.prior_map),
            "" if distance is None else f"{distance:.2f}",
        ])  # fmt: skip
    atomic_write_text(path, buffer.getvalue())


def _gt_distance(
    keyframes: tuple[Keyframe, ...] | list[Keyframe], record: LoopRecord, prior_gt: dict[int, np.ndarray]
) -> float | None:
    p = record.proposal
    if p.prior_map:
        q, m = keyframes[p.query_id].gt_pose, prior_gt.get(p.match_place)
    elif p.match_id >= len(keyframes):
        return None
    else:
        q, m = keyframes[p.query_id].gt_pose, keyframes[p.match_id].gt_pose
    distance = None if q is None or m is None else float(np.linalg.norm(q[:3, 3] - m[:3, 3]))
    return distance if distance is not None and np.isfinite(distance) else None  # NaN: no ground truth there


def write_database(
    folder: Path, result: RunResult, config: SlamConfig, poses: np.ndarray | None = None, images: bool = True
) -> None:
    """The session's place database with each place's map-frame pose, ground truth and scan (or,
    without one, its kept images).

    poses: the keyframe poses to store (default the result's map-frame poses; a checkpoint
    passes iSAM2's current estimate). images: False leaves the kept images out (a checkpoint
    holds them in its own images/ folder)."""
    if result.database is None:
        return
    in_map = result.in_map_frame if poses is None else poses
    places = result.session_places
    kfs = result.keyframes
    map_poses = {} if in_map is None else {places[k.id]: in_map[k.id] for k in kfs if k.id in places}
    scans = {places[k.id]: k.scan.points.astype(np.float32) for k in kfs if k.id in places and k.scan is not None}
    gt = {places[k.id]: k.gt_pose for k in kfs if k.id in places and k.gt_pose is not None}
    kept = kept_images(kfs, places, config) if images else None
    if result.prior_map is not None:  # carry the prior places' scans and images into the grown map
        scans.update(result.prior_map.scans)
        if kept is not None:
            kept.update(result.prior_map.images)
    if result.rear_database is not None and len(result.rear_database):  # first: the manifest below is the last write
        result.rear_database.save(folder / REAR_FOLDER)
    save_map(folder, result.database, config.vpr, map_poses, scans, gt, kept)


def kept_images(keyframes: Sequence[Keyframe], places: Mapping[int, int], config: SlamConfig) -> KeptImages:
    """The grey images the keyframes without a scan kept, by place, with the run's two-view
    intrinsics: what verifies a loop to these places from another session (`map`, `run --map`)."""
    camera = KeptImages.camera_of(config.backend.registration.two_view)
    front = {places[k.id]: k.image for k in keyframes if k.id in places and k.image is not None}
    rear = {places[k.id]: k.rear_image for k in keyframes if k.id in places and k.rear_image is not None}
    return KeptImages(front, rear, dict.fromkeys(front.keys() | rear.keys(), camera))


def run_metrics(result: RunResult) -> dict[str, Any]:
    """The run's own counters for metrics.json (the evaluation adds its part)."""
    end = result.ending
    return {
        "frames": result.frames_seen,
        "frames_skipped": dict(result.frames_skipped),
        "keyframes": len(result.keyframes),
        # False when the run ended inside the PCA warm-up: nothing was matched and no database saved
        "recognition_started": result.database is not None,
        "keyframes_judged": result.keyframes_judged,
        "too_short_to_decide": result.too_short_to_decide,
        "interrupted": end.interrupted,
        "source_error": end.source_error,
        "error": end.error,
        "seconds": end.seconds,
        "frames_per_second": result.frames_seen / end.seconds if end.seconds else None,
        "latency_per_keyframe": result.latency(),
        "odometry": dict(result.odometry_stats),
        "pose_graph_recoveries": list(result.graph_recoveries),
        **({} if result.realtime is None else {"realtime": result.realtime.to_dict()}),
    }


def metrics_of(result: RunResult, report: RunReport, inputs: RunInputs) -> RunMetrics:
    """metrics.json's content: the run's counters, its inputs, the evaluation; validated against
    `RunMetrics` (a key that the model does not declare fails here, not in a reader)."""
    metrics = {**run_metrics(result), **inputs.model_dump(), **report.metrics()}
    if report.prior_map is not None:
        metrics["prior_map_loops"] = report.prior_map.to_dict()
    return RunMetrics.model_validate(metrics)


def write_metrics(folder: Path, result: RunResult, report: RunReport, inputs: RunInputs) -> RunMetrics:
    metrics = metrics_of(result, report, inputs)
    write_json(folder / "metrics.json", metrics.to_json_dict())
    return metrics


def write_plots(folder: Path, result: RunResult, report: RunReport, config: SlamConfig) -> None:
    """Top view with loop edges, translation error along the traverse, loop precision/recall."""
    if len(result.keyframes) < 2:
        return
    from ssmvpr_slam.evaluation.metrics import path_lengths
    from ssmvpr_slam.evaluation.plots import plot_loop_summary, plot_trajectories, plot_translation_error

    gt = report.ground_truth_complete
    odom, optimised = report.aligned_poses or (result.odometry, result.optimised)
    edges = [(r.proposal.query_id, r.proposal.match_id) for r in result.session_loops if r.in_graph]
    correct = None
    if gt is not None:
        radius = config.evaluation.loops.correct_radius
        correct = [bool(np.linalg.norm(gt[q, :3, 3] - gt[m, :3, 3]) <= radius) for q, m in edges]
    plot_cfg = config.evaluation.plots
    title = "Top view: odometry vs optimised" + (" (aligned to ground truth)" if gt is not None else "")
    plot_trajectories(folder / "trajectory_top_view.png", gt, odom, optimised, edges, correct, title, plot_cfg)
    if report.translation_errors is not None and gt is not None:
        errors = report.translation_errors
        plot_translation_error(
            folder / "translation_error.png", errors[0], errors[1], path_lengths(gt), config=plot_cfg
        )
    if report.loops is not None:
        plot_loop_summary(folder / "loop_closures.png", report.loops.evaluation, config=plot_cfg)
