"""Loop-closure detection measured as the literature does, and at the shipped decision.

Per stream frame, the detector's winner (a proposal, accepted or not) with its decision score:
the calibrated z, or the raw sequence score under `detector.decision: absolute`. A frame is a
true positive when its accepted loop is correct, a false positive when it is not (a frame
without any true revisit included); recall counts the frames that have a true revisit.
* precision / recall at the decision the detector made;
* the PR curve over the decision score, its AUC, and the maximum recall at 100 % precision
  (the best any threshold on that score could do, chosen afterwards);
* false accepts split by where they land: within a pass, or across passes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from loopclosure.detector import LoopProposal
from loopclosure.metrics import PRCurve, pr_auc, precision_recall_curve, recall_at_full_precision
from ssmvpr_slam.loop_eval.revisit_truth import LoopTruth


@dataclass(frozen=True)
class Judged:
    """Every stream frame's winner, judged: arrays of one entry per frame."""

    match: np.ndarray  # (N,) matched stream frame, -1 without a winner
    score: np.ndarray  # (N,) decision score, -inf without a winner
    accepted: np.ndarray  # (N,) bool
    correct: np.ndarray  # (N,) bool: the winner is a true revisit
    across: np.ndarray  # (N,) bool: the winner lies in another pass
    has_truth: np.ndarray  # (N,) bool


def decision_score(proposal: LoopProposal) -> float:
    """What the decision compared: the calibrated z, else the raw sequence score."""
    if proposal.decision_score is not None:
        return float(proposal.decision_score)
    return float(proposal.sequence_score if proposal.sequence_score is not None else proposal.score)


def judge(proposals: tuple[LoopProposal | None, ...], truth: LoopTruth) -> Judged:
    n = len(truth)
    match = np.full(n, -1, np.int64)
    score = np.full(n, -np.inf)
    accepted, correct, across = np.zeros(n, bool), np.zeros(n, bool), np.zeros(n, bool)
    has_truth = truth.has_truth
    for q, p in enumerate(proposals):
        if p is None:
            continue
        match[q], score[q], accepted[q] = p.match_id, decision_score(p), p.accepted
        correct[q] = has_truth[q] and truth.correct(q, p.match_id)
        across[q] = truth.passes[q] != truth.passes[p.match_id]
    return Judged(match, score, accepted, correct, across, has_truth)


def only_across(judged: Judged) -> Judged:
    """The same, with every winner inside its own pass left out (neither right nor wrong): for
    a set like Corridor, whose passes revisit places the ground truth does not list."""
    keep = judged.across | (judged.match < 0)
    return Judged(
        np.where(keep, judged.match, -1), np.where(keep, judged.score, -np.inf), judged.accepted & keep,
        judged.correct & keep, judged.across, judged.has_truth,
    )  # fmt: skip


def curve(judged: Judged) -> PRCurve | None:
    """The PR curve over the decision score (None when no frame has a true revisit)."""
    if not judged.has_truth.any():
        return None
    return precision_recall_curve(judged.score, judged.correct, judged.has_truth)


def loop_metrics(judged: Judged, passes: int) -> dict[str, Any]:
    """`metrics.json`'s `loops` block."""
    accepted = int(judged.accepted.sum())
    right = int((judged.accepted & judged.correct).sum())
    with_truth = int(judged.has_truth.sum())
    pr = curve(judged)
    wrong = judged.accepted & ~judged.correct
    out: dict[str, Any] = {
        "frames": len(judged.match),
        "with_truth": with_truth,
        "accepted": accepted,
        "correct": right,
        "precision": right / accepted if accepted else None,
        "recall": right / with_truth if with_truth else None,
        "max_recall_at_full_precision": recall_at_full_precision(pr) if pr is not None else None,
        "pr_auc": pr_auc(pr) if pr is not None else None,
        "false_accepts": int(wrong.sum()),
    }
    if passes > 1:
        out["false_accepts_by_place"] = {
            "within_pass": int((wrong & ~judged.across).sum()),
            "across_passes": int((wrong & judged.across).sum()),
        }
    return out
