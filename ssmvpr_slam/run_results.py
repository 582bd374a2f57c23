"""Everything a run leaves behind, and its evaluation against ground truth when there is one."""

from __future__ import annotations

import csv
import io
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from loopclosure.atomic import atomic_write_text
from loopclosure.metrics import pr_auc, precision_recall_curve
from ssmvpr_slam.backend.g2o_io import from_pose_graph, write_g2o
from ssmvpr_slam.config import SlamConfig, dump_config
from ssmvpr_slam.evaluation.loop_metrics import evaluate_loops, find_revisits
from ssmvpr_slam.evaluation.metrics import ate, drift_per_100m, kitti_relative_error, rpe
from ssmvpr_slam.evaluation.trajectory_io import write_kitti, write_tum
from ssmvpr_slam.pipeline import Keyframe, LoopRecord, SlamPipeline
from ssmvpr_slam.prior_map import save_map
from ssmvpr_slam.results import write_json

LOOP_COLUMNS = [
    "query_kf", "match_kf", "score", "stage1_score", "column_shift", "yaw_guess_rad", "gate_accepted",
    "gate_reason", "camera", "direction", "sequence_score", "sequence_terms", "registration", "registration_accepted",
    "registration_reason",
    "inlier_ratio", "rmse", "in_graph", "prior_map", "injected", "gt_distance_m",
]  # fmt: skip


def write_loop_csv(path: Path, loops: list[LoopRecord], gt_distance: list[float | None], final: set[int]) -> None:
    """One row per proposal; `in_graph` is whether its factor survived to the end (GNC may drop it)."""
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(LOOP_COLUMNS)
    for record, distance in zip(loops, gt_distance):
        p, reg = record.proposal, record.registration
        writer.writerow([
            p.query_id, p.match_id, f"{p.score:.4f}", f"{p.stage1_score:.4f}", p.column_shift, f"{p.yaw_guess:.4f}",
            int(p.accepted), p.reason, p.camera, p.direction or "",
            "" if p.sequence_score is None else f"{p.sequence_score:.4f}", p.sequence_terms,
            reg.method if reg else "", int(reg.accepted) if reg else "",
            reg.reason if reg else "", f"{reg.inlier_ratio:.3f}" if reg else "", f"{reg.rmse:.3f}" if reg else "",
            int(record.factor_handle in final), int(p.prior_map), int(record.injected),
            "" if distance is None else f"{distance:.2f}",
        ])  # fmt: skip
    atomic_write_text(path, buffer.getvalue())


def _gt_distance(pipeline: SlamPipeline, record: LoopRecord) -> float | None:
    kfs = pipeline.state.keyframes
    p = record.proposal
    if p.prior_map or p.match_id >= len(kfs):
        return None
    q, m = kfs[p.query_id].gt_pose, kfs[p.match_id].gt_pose
    distance = None if q is None or m is None else float(np.linalg.norm(q[:3, 3] - m[:3, 3]))
    return distance if distance is not None and np.isfinite(distance) else None  # NaN: no ground truth there


def _session_places(pipeline: SlamPipeline) -> dict[int, int]:
    """Keyframe id -> database place index of this session's places."""
    database = pipeline.detector.database
    first = pipeline.detector.prior_places
    return {database.places[i].frame_id: i for i in range(first, len(database))}


def map_frame_poses(pipeline: SlamPipeline, optimised: np.ndarray) -> np.ndarray | None:
    """The session's optimised poses in the map frame: its own frame without a prior map,
    the prior map's frame once a map loop anchored it, None if it never was."""
    if pipeline.prior_map is None:
        return optimised
    anchor = pipeline.graph.anchor()
    return None if anchor is None else np.linalg.inv(anchor) @ optimised


def _save_map(folder: Path, pipeline: SlamPipeline, optimised: np.ndarray, config: SlamConfig) -> None:
    kfs = pipeline.state.keyframes
    places = _session_places(pipeline)
    in_map = map_frame_poses(pipeline, optimised) if len(kfs) else None
    poses = {} if in_map is None else {places[k.id]: in_map[k.id] for k in kfs if k.id in places}
    scans = {places[k.id]: k.scan for k in kfs if k.id in places and k.scan is not None}
    gt = {places[k.id]: k.gt_pose for k in kfs if k.id in places and k.gt_pose is not None}
    if pipeline.prior_map is not None:  # carry the prior places' scans into the grown map
        scans.update(pipeline.prior_map.scans)
    save_map(folder, pipeline.detector.database, config.vpr, poses, scans, gt)


def _prior_map_metrics(pipeline: SlamPipeline, config: SlamConfig) -> dict[str, Any]:
    prior = pipeline.prior_map
    loops = [r for r in pipeline.state.loops if r.proposal.prior_map]
    out: dict[str, Any] = {
        "places": len(prior), "places_with_pose": len(prior.poses), "places_with_scan": len(prior.scans),
        "loops_proposed": len(loops), "loops_gate_accepted": sum(r.proposal.accepted for r in loops),
        "loops_in_graph": sum(r.in_graph for r in loops), "anchored": pipeline.graph.anchor() is not None,
    }  # fmt: skip
    kfs = pipeline.state.keyframes
    judged = [r for r in loops if r.in_graph and r.proposal.match_place in prior.gt_poses and kfs[r.proposal.query_id].gt_pose is not None]
    if judged:
        radius = config.evaluation.loops.correct_radius
        distances = [np.linalg.norm(kfs[r.proposal.query_id].gt_pose[:3, 3] - prior.gt_poses[r.proposal.match_place][:3, 3])
                     for r in judged]  # fmt: skip
        out["loops_correct"] = int(sum(d <= radius for d in distances))
        out["precision"] = out["loops_correct"] / len(judged)
    return out


def has_ground_truth(keyframes: list[Keyframe]) -> np.ndarray:
    """Which keyframes carry a usable ground-truth pose (not None, all finite)."""
    return np.array([k.gt_pose is not None and bool(np.isfinite(k.gt_pose).all()) for k in keyframes], bool)


def evaluate_run(pipeline: SlamPipeline, odom: np.ndarray, optimised: np.ndarray, config: SlamConfig) -> dict[str, Any]:
    """Evaluate on the keyframes that have ground truth and say how many those are.

    Logs often lose ground truth for a while (GNSS outage, a reference that ends early);
    dropping the whole evaluation for that hides what can be measured. Keyframes without it
    are left out: the trajectory errors use the covered ones, and loops count only when both
    ends are covered (both re-indexed into the covered keyframes). `ground_truth_coverage` is
    covered / all keyframes."""
    kfs = pipeline.state.keyframes
    covered = has_ground_truth(kfs)
    coverage = {"ground_truth_coverage": float(covered.mean()) if len(kfs) else 0.0,
                "ground_truth_keyframes": int(covered.sum())}  # fmt: skip
    if not covered.any():
        return {"ground_truth": False, **coverage}
    if covered.all():
        return {**_evaluate_covered(pipeline, odom, optimised, config), **coverage}
    keep = np.flatnonzero(covered)
    index = {int(old): new for new, old in enumerate(keep)}
    loops = []
    for r in pipeline.state.loops:
        p = r.proposal
        if p.prior_map or r.injected:  # not judged against the session's ground truth either way
            loops.append(r)
        elif p.query_id in index and p.match_id in index:
            loops.append(replace(r, proposal=replace(p, query_id=index[p.query_id], match_id=index[p.match_id])))
    view = SimpleNamespace(state=SimpleNamespace(keyframes=[kfs[i] for i in keep], loops=loops,
                                                 rear_keyframes=pipeline.state.rear_keyframes))
    out = _evaluate_covered(view, odom[keep], optimised[keep], config)  # type: ignore[arg-type]
    # the aligned poses and per-pose errors cover only some keyframes: the plots use the full run
    out.pop("_aligned", None)
    out.pop("_errors", None)
    session = [r for r in pipeline.state.loops if not r.proposal.prior_map and not r.injected]
    out["loops"]["judged_in_graph"] = out["loops"]["in_graph"]  # those precision/recall are computed on
    out["loops"]["proposed"] = len(session)
    out["loops"]["gate_accepted"] = sum(r.proposal.accepted for r in session)
    out["loops"]["in_graph"] = sum(r.in_graph for r in session)
    return {**out, **coverage}


def _evaluate_covered(pipeline: SlamPipeline, odom: np.ndarray, optimised: np.ndarray, config: SlamConfig) -> dict[str, Any]:
    """ATE/RPE/KITTI error of odometry vs optimised, loop precision/recall and the stream's PR-AUC."""
    kfs = pipeline.state.keyframes
    if not kfs or any(k.gt_pose is None for k in kfs):
        return {"ground_truth": False}
    gt = np.array([k.gt_pose for k in kfs])
    traj = config.evaluation.trajectory
    out: dict[str, Any] = {"ground_truth": True}
    if len(kfs) >= 3:
        a_odom, a_opt = ate(gt, odom, traj.alignment), ate(gt, optimised, traj.alignment)
        out["ate_odometry"] = a_odom.to_dict()
        out["ate_optimised"] = a_opt.to_dict()
        out["ate_ratio"] = a_opt.stats.rmse / a_odom.stats.rmse if a_odom.stats.rmse > 0 else None
        out["rpe_odometry"] = rpe(gt, odom, traj.rpe_delta, traj.rpe_unit).to_dict()
        out["rpe_optimised"] = rpe(gt, optimised, traj.rpe_delta, traj.rpe_unit).to_dict()
        out["drift_odometry"] = drift_per_100m(gt, odom, traj.drift_segment_m).to_dict()
        kitti = {"lengths": tuple(traj.kitti_lengths_m), "step_frames": traj.kitti_step_frames}
        out["kitti_rel_error"] = {  # per keyframe pose; 100 m+ segments, so null on short runs
            "odometry": kitti_relative_error(gt, odom, **kitti).to_dict(),
            "optimised": kitti_relative_error(gt, optimised, **kitti).to_dict(),
        }
        out["_errors"] = (a_odom.errors, a_opt.errors)
        out["_aligned"] = (a_odom.aligned_poses, a_opt.aligned_poses)  # in the ground truth's frame, for plots

    loops_cfg = config.evaluation.loops
    # injected wrong loops (a test option) are not proposals: counting them, or letting their
    # score 0 overwrite the real proposal of the same keyframe in the PR-AUC, skews the metrics
    session = [r for r in pipeline.state.loops if not r.proposal.prior_map and not r.injected]
    in_graph = [(r.proposal.query_id, r.proposal.match_id) for r in session if r.in_graph]
    evaluation = evaluate_loops(gt, in_graph, loops_cfg, rear_camera=pipeline.state.rear_keyframes > 0)
    out["loops"] = evaluation.to_dict()
    out["_loop_evaluation"] = evaluation
    out["loops"]["proposed"] = len(session)
    out["loops"]["gate_accepted"] = sum(r.proposal.accepted for r in session)
    out["loops"]["in_graph"] = len(in_graph)
    out["loops"]["injected"] = sum(r.injected for r in pipeline.state.loops)

    # the paper's PR-AUC over the stream: each keyframe's best proposal and its score
    revisits = set(find_revisits(gt, loops_cfg.correct_radius, loops_cfg.min_frame_gap).tolist())
    scores = np.full(len(kfs), -np.inf)
    correct = np.zeros(len(kfs), bool)
    for r in session:
        q, m = r.proposal.query_id, r.proposal.match_id
        scores[q] = r.proposal.score
        correct[q] = q in revisits and np.linalg.norm(gt[q, :3, 3] - gt[m, :3, 3]) <= loops_cfg.correct_radius
    has_truth = np.array([i in revisits for i in range(len(kfs))])
    if has_truth.any():
        out["stream_pr_auc"] = pr_auc(precision_recall_curve(scores, correct, has_truth))
        # the same proposals ranked by their sequence score, the detector's decision score
        seq_scores = np.full(len(kfs), -np.inf)
        for r in session:
            if r.proposal.sequence_score is not None:
                seq_scores[r.proposal.query_id] = r.proposal.sequence_score
        out["stream_pr_auc_sequence"] = pr_auc(precision_recall_curve(seq_scores, correct, has_truth))
    # evaluate_loops splits recall by direction and camera visibility; add what the detector
    # itself called each loop in the graph (the direction of its winning sequence)
    in_graph_records = [r for r in session if r.in_graph]
    for name, counts in out["loops"]["by_direction"].items():
        counts["loops_in_graph_by_sequence_direction"] = sum(r.proposal.direction == name for r in in_graph_records)
    out["loops"]["rear_camera_keyframes"] = pipeline.state.rear_keyframes
    out["loops"]["in_graph_by_camera"] = {c: sum(r.proposal.camera == c for r in in_graph_records) for c in ("front", "rear")}
    return out


def write_run_results(folder: Path, pipeline: SlamPipeline, config: SlamConfig, extra: dict[str, Any]) -> dict[str, Any]:
    """Trajectories (TUM + KITTI), pose_graph.g2o, loop_closures.csv, database, config, metrics.json, plots."""
    stamps, odom, optimised = pipeline.trajectories()
    final = set(pipeline.graph.loop_handles)  # a final GNC pass may have dropped loops
    for record in pipeline.state.loops:
        if record.factor_handle is not None and record.factor_handle not in final:
            record.factor_handle = None
    kfs = pipeline.state.keyframes
    if len(kfs):
        write_tum(folder / "odometry.tum", stamps, odom)
        write_kitti(folder / "odometry.kitti", odom)
        write_tum(folder / "optimised.tum", stamps, optimised)
        write_kitti(folder / "optimised.kitti", optimised)
        write_g2o(folder / "pose_graph.g2o", from_pose_graph(pipeline.graph, optimised))
        covered = has_ground_truth(kfs)
        if covered.any():  # TUM has stamps, so a partial ground truth is still one file evo reads
            write_tum(folder / "ground_truth.tum", stamps[covered], np.array([k.gt_pose for k, ok in zip(kfs, covered) if ok]))
        if covered.all():  # KITTI lines are matched by position: only a complete one
            write_kitti(folder / "ground_truth.kitti", np.array([k.gt_pose for k in kfs]))
    write_loop_csv(folder / "loop_closures.csv", pipeline.state.loops,
                   [_gt_distance(pipeline, r) for r in pipeline.state.loops], final)  # fmt: skip
    atomic_write_text(folder / "config.yaml", dump_config(config))
    if config.results.save_database and pipeline.detector.database is not None:
        _save_map(folder / "database", pipeline, optimised, config)

    evaluation = evaluate_run(pipeline, odom, optimised, config) if len(kfs) else {"ground_truth": False}
    errors = evaluation.pop("_errors", None)
    odom, optimised = evaluation.pop("_aligned", (odom, optimised))
    loop_eval = evaluation.pop("_loop_evaluation", None)
    state = pipeline.state
    metrics = {
        "frames": state.frames_seen,
        "frames_skipped": dict(state.frames_skipped),
        "keyframes": len(kfs),
        "interrupted": state.interrupted,
        "source_error": state.source_error,
        "error": None if state.step_error is None else f"{type(state.step_error).__name__}: {state.step_error}",
        "seconds": state.seconds,
        "frames_per_second": state.frames_seen / state.seconds if state.seconds else None,
        "latency_per_keyframe": state.times.summary(),
        "odometry": pipeline.odometry.stats.__dict__ if hasattr(pipeline.odometry, "stats") else {},
        **extra,
        **evaluation,
    }
    if pipeline.prior_map is not None:
        metrics["prior_map_loops"] = _prior_map_metrics(pipeline, config)
    write_json(folder / "metrics.json", metrics)
    if config.results.plots and len(kfs) >= 2:
        _plots(folder, kfs, odom, optimised, pipeline, errors, loop_eval, config)
    return metrics


def _plots(folder, kfs, odom, optimised, pipeline, errors, loop_eval, config) -> None:  # noqa: ANN001
    from ssmvpr_slam.evaluation.metrics import path_lengths
    from ssmvpr_slam.evaluation.plots import plot_loop_summary, plot_trajectories, plot_translation_error

    gt = np.array([k.gt_pose for k in kfs]) if has_ground_truth(kfs).all() else None
    graph_loops = [r for r in pipeline.state.loops if r.in_graph and not r.proposal.prior_map]
    edges = [(r.proposal.query_id, r.proposal.match_id) for r in graph_loops]
    correct = None
    if gt is not None:
        radius = config.evaluation.loops.correct_radius
        correct = [bool(np.linalg.norm(gt[q, :3, 3] - gt[m, :3, 3]) <= radius) for q, m in edges]
    plot_cfg = config.evaluation.plots
    title = "Top view: odometry vs optimised" + (" (aligned to ground truth)" if gt is not None else "")
    plot_trajectories(folder / "trajectory_top_view.png", gt, odom, optimised, edges, correct, title, plot_cfg)
    if errors is not None:
        plot_translation_error(folder / "translation_error.png", errors[0], errors[1], path_lengths(gt), config=plot_cfg)
    if loop_eval is not None:
        plot_loop_summary(folder / "loop_closures.png", loop_eval, config=plot_cfg)
