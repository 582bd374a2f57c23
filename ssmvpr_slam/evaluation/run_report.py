"""Evaluation of a finished run against ground truth: `evaluate(result, config) -> RunReport`.

Logs often lose ground truth for a while (GNSS outage, a reference that ends early);
dropping the whole evaluation for that hides what can be measured. Keyframes without it are
left out: the trajectory errors use the covered ones, and loops count only when both ends are
covered (both re-indexed into the covered keyframes). `ground_truth_coverage` is covered / all
keyframes. The report is typed: plots take its aligned poses and loop evaluation from fields,
and `metrics()` gives the JSON for metrics.json.
"""

from __future__ import annotations

import copy
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np

from loopclosure.metrics import pr_auc, precision_recall_curve
from ssmvpr_slam.evaluation.config import EvaluationConfig, LoopMetricsConfig, TrajectoryMetricsConfig
from ssmvpr_slam.evaluation.loop_metrics import LoopEvaluation, evaluate_loops, find_revisits
from ssmvpr_slam.evaluation.metrics import (
    AteResult,
    DriftResult,
    KittiRelativeError,
    RpeResult,
    ate,
    drift_per_100m,
    kitti_relative_error,
    rpe,
)
from ssmvpr_slam.run_result import LoopRecord, RunResult

CAMERAS = ("front", "rear")


@dataclass(frozen=True)
class TrajectoryReport:
    """Odometry against optimised poses, both against ground truth (covered keyframes only)."""

    ate_odometry: AteResult
    ate_optimised: AteResult
    rpe_odometry: RpeResult
    rpe_optimised: RpeResult
    drift_odometry: DriftResult
    kitti_odometry: KittiRelativeError
    kitti_optimised: KittiRelativeError

    @property
    def ate_ratio(self) -> float | None:
        odom = self.ate_odometry.stats.rmse
        return self.ate_optimised.stats.rmse / odom if odom > 0 else None

    def to_dict(self) -> dict[str, Any]:
        return {
            "ate_odometry": self.ate_odometry.to_dict(),
            "ate_optimised": self.ate_optimised.to_dict(),
            "ate_ratio": self.ate_ratio,
            "rpe_odometry": self.rpe_odometry.to_dict(),
            "rpe_optimised": self.rpe_optimised.to_dict(),
            "drift_odometry": self.drift_odometry.to_dict(),
            # per keyframe pose; 100 m+ segments, so null on short runs
            "kitti_rel_error": {"odometry": self.kitti_odometry.to_dict(), "optimised": self.kitti_optimised.to_dict()},
        }


@dataclass(frozen=True)
class LoopReport:
    """Loop closures of the session (prior-map loops apart) against ground truth."""

    evaluation: LoopEvaluation
    proposed: int
    gate_accepted: int
    in_graph: int
    spaced: int  # gate-accepted, not registered: a loop in the graph a few keyframes back stands for each
    judged_in_graph: int | None  # loops in graph with both ends covered; None when all are
    in_graph_by_sequence_direction: dict[str, int]  # what the detector called each judged loop
    rear_camera_keyframes: int
    in_graph_by_camera: dict[str, int]
    in_graph_by_method: dict[str, int]  # how each loop in the graph was verified
    first_sight: dict[str, int]  # revisits, and those whose first loop entered the graph on its own registration

    def to_dict(self) -> dict[str, Any]:
        out = copy.deepcopy(self.evaluation.to_dict())  # its by_direction is extended below, not the evaluation's
        out.update(proposed=self.proposed, gate_accepted=self.gate_accepted, in_graph=self.in_graph)
        if self.spaced:  # precision and recall then judge the spaced loops beside those in the graph
            out["spaced"] = self.spaced
        by_direction: dict[str, dict[str, Any]] = out["by_direction"]  # type: ignore[assignment]  # to_dict's values are plain JSON
        for name, counts in by_direction.items():
            counts["loops_in_graph_by_sequence_direction"] = self.in_graph_by_sequence_direction.get(name, 0)
        out["rear_camera_keyframes"] = self.rear_camera_keyframes
        out["in_graph_by_camera"] = dict(self.in_graph_by_camera)
        out["in_graph_by_method"] = dict(self.in_graph_by_method)
        out["first_sight"] = dict(self.first_sight)
        if self.judged_in_graph is not None:
            out["judged_in_graph"] = self.judged_in_graph  # those precision/recall are computed on (with spaced ones)
        return out


@dataclass(frozen=True)
class PriorMapReport:
    """Loops against the prior map (`--map`), and the map as it was loaded."""

    places: int
    places_with_pose: int
    places_with_scan: int
    loops_proposed: int
    loops_gate_accepted: int
    loops_in_graph: int
    anchored: bool
    loops_correct: int | None = None  # judged: in graph, ground truth on both ends
    precision: float | None = None
    ate_rmse: float | None = None
    """ATE of the map's own poses against its ground truth: a session corrected onto the map
    carries the map's error, so the run's optimised ATE is read beside this."""

    def to_dict(self) -> dict[str, Any]:
        out = dict(self.__dict__)
        if self.loops_correct is None:
            del out["loops_correct"], out["precision"]
        if self.ate_rmse is None:
            del out["ate_rmse"]
        return out


@dataclass(frozen=True)
class RunReport:
    """The evaluation of one run (ground truth, trajectory errors, loops, prior-map loops).

    aligned_poses / translation_errors: odometry and optimised poses in the ground truth's
    frame and their per-keyframe errors, for plots; only when every keyframe has ground truth."""

    keyframes: int
    ground_truth_keyframes: int
    trajectory: TrajectoryReport | None = None
    loops: LoopReport | None = None
    stream_pr_auc: float | None = None
    stream_pr_auc_sequence: float | None = None
    prior_map: PriorMapReport | None = None
    aligned_poses: tuple[np.ndarray, np.ndarray] | None = None
    translation_errors: tuple[np.ndarray, np.ndarray] | None = None
    ground_truth_complete: np.ndarray | None = None  # (N, 4, 4) when every keyframe has it

    @property
    def ground_truth(self) -> bool:
        return self.ground_truth_keyframes > 0

    @property
    def ground_truth_coverage(self) -> float:
        return self.ground_truth_keyframes / self.keyframes if self.keyframes else 0.0

    def metrics(self) -> dict[str, Any]:
        """The evaluation's part of metrics.json (the prior map's goes under its own key)."""
        if not self.keyframes:
            return {"ground_truth": False}
        out: dict[str, Any] = {"ground_truth": self.ground_truth}
        if self.trajectory is not None:
            out.update(self.trajectory.to_dict())
        if self.loops is not None:
            out["loops"] = self.loops.to_dict()
        if self.stream_pr_auc is not None:
            out["stream_pr_auc"] = self.stream_pr_auc
            out["stream_pr_auc_sequence"] = self.stream_pr_auc_sequence
        out["ground_truth_coverage"] = self.ground_truth_coverage
        out["ground_truth_keyframes"] = self.ground_truth_keyframes
        return out


def evaluate(
    result: RunResult, config: EvaluationConfig, ground_truth: Sequence[np.ndarray | None] | None = None
) -> RunReport:
    """Evaluate `result` on the keyframes that have ground truth.

    ground_truth: one 4x4 pose (or None) per keyframe; default the poses the frames carried."""
    kfs = result.keyframes
    gt_list = [k.gt_pose for k in kfs] if ground_truth is None else list(ground_truth)
    if len(gt_list) != len(kfs):
        raise ValueError(f"ground_truth: {len(gt_list)} poses for {len(kfs)} keyframes")
    covered = np.array([g is not None and bool(np.isfinite(g).all()) for g in gt_list], bool)
    prior = (
        _prior_map_report(result, gt_list, config.loops, config.trajectory.alignment)
        if result.prior_map is not None
        else None
    )
    report = RunReport(len(kfs), int(covered.sum()), prior_map=prior)
    if not covered.any():
        return report
    keep = np.flatnonzero(covered)
    gt = np.array([gt_list[i] for i in keep])
    odom, optimised = result.odometry[keep], result.optimised[keep]
    trajectory = _trajectory_report(gt, odom, optimised, config.trajectory) if len(keep) >= 3 else None
    index = {int(old): new for new, old in enumerate(keep)}
    judged = [
        _reindexed(r, index)
        for r in result.session_loops
        if r.proposal.query_id in index and r.proposal.match_id in index
    ]
    loops = _loop_report(gt, judged, result, config.loops, partial=not covered.all())
    pr_auc_single, pr_auc_sequence = _stream_pr_auc(gt, judged, config.loops)
    complete = bool(covered.all()) and trajectory is not None
    aligned = errors = None
    if complete and trajectory is not None:
        aligned = (trajectory.ate_odometry.aligned_poses, trajectory.ate_optimised.aligned_poses)
        errors = (trajectory.ate_odometry.errors, trajectory.ate_optimised.errors)
    return RunReport(
        keyframes=len(kfs),
        ground_truth_keyframes=len(keep),
        trajectory=trajectory,
        loops=loops,
        stream_pr_auc=pr_auc_single,
        stream_pr_auc_sequence=pr_auc_sequence,
        prior_map=prior,
        # the aligned poses and per-pose errors of a partial ground truth cover only some
        # keyframes: the plots then show the full run unaligned
        aligned_poses=aligned,
        translation_errors=errors,
        ground_truth_complete=gt if covered.all() else None,
    )


def _reindexed(record: LoopRecord, index: dict[int, int]) -> LoopRecord:
    p = record.proposal
    return replace(record, proposal=replace(p, query_id=index[p.query_id], match_id=index[p.match_id]))


def _trajectory_report(
    gt: np.ndarray, odom: np.ndarray, optimised: np.ndarray, cfg: TrajectoryMetricsConfig
) -> TrajectoryReport:
    lengths, step = tuple(cfg.kitti_lengths_m), cfg.kitti_step_frames
    return TrajectoryReport(
        ate_odometry=ate(gt, odom, cfg.alignment),
        ate_optimised=ate(gt, optimised, cfg.alignment),
        rpe_odometry=rpe(gt, odom, cfg.rpe_delta, cfg.rpe_unit, cfg.rpe_all_pairs),
        rpe_optimised=rpe(gt, optimised, cfg.rpe_delta, cfg.rpe_unit, cfg.rpe_all_pairs),
        drift_odometry=drift_per_100m(gt, odom, cfg.drift_segment_m),
        kitti_odometry=kitti_relative_error(gt, odom, lengths=lengths, step_frames=step),
        kitti_optimised=kitti_relative_error(gt, optimised, lengths=lengths, step_frames=step),
    )


def _loop_report(
    gt: np.ndarray, judged: list[LoopRecord], result: RunResult, cfg: LoopMetricsConfig, partial: bool
) -> LoopReport:
    in_graph = [r for r in judged if r.in_graph]
    # a spaced loop is the recogniser's claim that a loop in the graph a few keyframes back
    # stands for: judged with them, so spacing loops out does not read as lost recall
    closed = [r for r in judged if r.closed]
    evaluation = evaluate_loops(gt, [(r.proposal.query_id, r.proposal.match_id) for r in closed], cfg,
                                rear_camera=result.rear_keyframes > 0)  # fmt: skip
    counted = list(result.session_loops) if partial else judged  # every proposal is still counted
    return LoopReport(
        evaluation=evaluation,
        proposed=len(counted),
        gate_accepted=sum(r.proposal.accepted for r in counted),
        in_graph=sum(r.in_graph for r in counted),
        spaced=sum(r.spaced for r in counted),
        judged_in_graph=len(in_graph) if partial else None,
        # evaluate_loops splits recall by direction and camera visibility; beside it, what the
        # detector itself called each loop in the graph (the direction of its winning sequence)
        in_graph_by_sequence_direction={
            d: sum(r.proposal.direction == d for r in in_graph) for d in ("forward", "reverse")
        },
        rear_camera_keyframes=result.rear_keyframes,
        in_graph_by_camera={c: sum(r.proposal.camera == c for r in in_graph) for c in CAMERAS},
        in_graph_by_method=dict(sorted(Counter(_verified_by(r) for r in counted if r.in_graph).items())),
        first_sight=_first_sight(counted, cfg.revisit_gap_keyframes),
    )


def _verified_by(record: LoopRecord) -> str:
    """What let a loop into the graph: its registration's method, or `earlier_loops` for a place
    prior that earlier loops of its revisit vouched for."""
    method = record.registration.method if record.registration is not None else "none"
    return "earlier_loops" if method == "yaw_prior" and "earlier loops of the revisit agree" in (
        record.registration.reason if record.registration is not None else ""
    ) else method  # fmt: skip


def _first_sight(records: list[LoopRecord], gap: int) -> dict[str, int]:
    """Revisits (runs of accepted loops, each query and match within `gap` keyframes of the run's
    last) and how many of them had their first loop in the graph on its own registration (ICP
    or two views), not waiting for earlier loops of the revisit to agree."""
    runs: list[list[LoopRecord]] = []
    for record in records:
        if not record.proposal.accepted or record.spaced or record.proposal.prior_map:
            continue
        q, m = record.proposal.query_id, record.proposal.match_id
        for run in reversed(runs[-4:]):  # a revisit's loops alternate with another's where streets repeat
            last = run[-1].proposal
            if 0 < q - last.query_id <= gap and abs(m - last.match_id) <= gap:
                run.append(record)
                break
        else:
            runs.append([record])
    first_in = sum(run[0].in_graph and _verified_by(run[0]) not in ("earlier_loops", "none") for run in runs)
    return {"revisits": len(runs), "first_loop_in_graph": first_in}


def _stream_pr_auc(
    gt: np.ndarray, session: list[LoopRecord], cfg: LoopMetricsConfig
) -> tuple[float | None, float | None]:
    """The paper's PR-AUC over the stream: each keyframe's best proposal and its score; and the
    same proposals ranked by their sequence score, the detector's decision score."""
    n = len(gt)
    revisits = set(find_revisits(gt, cfg.correct_radius, cfg.min_frame_gap).tolist())
    has_truth = np.array([i in revisits for i in range(n)])
    if not has_truth.any():
        return None, None
    scores = np.full(n, -np.inf)
    seq_scores = np.full(n, -np.inf)
    correct = np.zeros(n, bool)
    for r in session:
        q, m = r.proposal.query_id, r.proposal.match_id
        scores[q] = r.proposal.score
        correct[q] = q in revisits and np.linalg.norm(gt[q, :3, 3] - gt[m, :3, 3]) <= cfg.correct_radius
        if r.proposal.sequence_score is not None:
            seq_scores[q] = r.proposal.sequence_score
    return (pr_auc(precision_recall_curve(scores, correct, has_truth)),
            pr_auc(precision_recall_curve(seq_scores, correct, has_truth)))  # fmt: skip


def _prior_map_report(
    result: RunResult, gt: list[np.ndarray | None], cfg: LoopMetricsConfig, alignment: Literal["se3", "sim3", "none"]
) -> PriorMapReport:
    prior = result.prior_map
    assert prior is not None
    loops = [r for r in result.loops if r.proposal.prior_map]
    judged = [
        r
        for r in loops
        if r.in_graph and r.proposal.match_place in prior.gt_poses and gt[r.proposal.query_id] is not None
    ]
    correct = None
    if judged:
        distances = [np.linalg.norm(gt[r.proposal.query_id][:3, 3] - prior.gt_poses[r.proposal.match_place][:3, 3])  # type: ignore[index]
                     for r in judged]  # fmt: skip
        correct = int(sum(d <= cfg.correct_radius for d in distances))
    both = sorted(set(prior.poses) & set(prior.gt_poses))
    map_ate = None
    if len(both) >= 3:
        gt_poses, map_poses = (np.array([d[p] for p in both]) for d in (prior.gt_poses, prior.poses))
        try:
            map_ate = ate(gt_poses, map_poses, alignment).stats.rmse
        except (ValueError, np.linalg.LinAlgError):  # places that cannot be aligned (all at one spot): no figure
            map_ate = None
    return PriorMapReport(
        places=len(prior), places_with_pose=len(prior.poses), places_with_scan=len(prior.scans),
        loops_proposed=len(loops), loops_gate_accepted=sum(r.proposal.accepted for r in loops),
        loops_in_graph=sum(r.in_graph for r in loops), anchored=result.anchored,
        loops_correct=correct, precision=None if correct is None else correct / len(judged), ate_rmse=map_ate,
    )  # fmt: skip
