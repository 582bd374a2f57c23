"""The SSM-VPR paper's evaluation: PR curve over a match-score threshold, its AUC, recall@N.

Every query contributes exactly one match (its best-scoring reference) with that match's
score. Sweeping a threshold from high to low, a query is *accepted* when its score is at or
above the threshold. At each threshold::

    precision = correct accepted / accepted
    recall    = correct accepted / queries that have a true match

The recall denominator counts queries with truth, not correct matches: a wrong match that
is accepted costs precision and can never be recovered as recall, which is the usual VPR
reading (and what sklearn's curve would give only if every query's best match were correct).
numpy only, so the library evaluates itself without sklearn.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from loopclosure.benchmark_truth import GroundTruth, correct_mask
from loopclosure.errors import LoopClosureInputError

__all__ = [
    "PRCurve",
    "pr_auc",
    "precision_at_full_recall",
    "precision_recall_curve",
    "recall_at_full_precision",
    "recall_at_n",
    "summarize",
    "top1_accuracy",
]


@dataclass(frozen=True)
class PRCurve:
    """Points of a PR curve, ordered by decreasing threshold (recall non-decreasing).

    Point 0 is the conventional start (recall 0, precision 1, threshold +inf: nothing accepted).
    Point k >= 1 is "accept every query with score >= thresholds[k]"; thresholds are the
    distinct scores, so tied scores enter the curve together as one point. The integer counts
    are kept so that "precision is exactly 1" and "recall is exactly 1" need no float compare.
    """

    precision: np.ndarray
    recall: np.ndarray
    thresholds: np.ndarray
    true_positives: np.ndarray
    accepted: np.ndarray
    n_with_truth: int


def _vector(x: object, name: str, dtype: type, n: int | None = None) -> np.ndarray:
    arr = np.asarray(x)
    if arr.ndim != 1:
        raise LoopClosureInputError(f"{name}: expected a 1-D array, got shape {arr.shape}")
    if n is not None and arr.shape[0] != n:
        raise LoopClosureInputError(f"{name}: expected {n} entries (one per query), got {arr.shape[0]}")
    if dtype is bool and arr.dtype != bool:
        if arr.size and not np.all((arr == 0) | (arr == 1)):
            raise LoopClosureInputError(f"{name}: expected booleans")
    return arr.astype(dtype)


def precision_recall_curve(scores: object, correct: object, has_truth: object) -> PRCurve:
    """PR curve of one best match per query; see the module docstring for the definitions.

    scores: (n_query,) match scores, higher = more confident (±inf allowed, NaN refused).
    correct: (n_query,) whether that best match is right; has_truth: whether the query has
    any true reference. A correct match without truth is refused as contradictory.
    """
    s = _vector(scores, "scores", float)
    n = s.shape[0]
    c = _vector(correct, "correct", bool, n)
    t = _vector(has_truth, "has_truth", bool, n)
    if np.isnan(s).any():
        raise LoopClosureInputError(f"scores: {int(np.isnan(s).sum())} NaN score(s); use -inf for 'no match'")
    if np.any(c & ~t):
        q = int(np.flatnonzero(c & ~t)[0])
        raise LoopClosureInputError(f"correct: query {q} is marked correct but has no true match")
    n_truth = int(t.sum())
    if n_truth == 0:
        raise LoopClosureInputError("has_truth: no query has a true match, so recall is undefined")

    order = np.argsort(-s, kind="stable")
    s_sorted, c_sorted = s[order], c[order]
    tp_cum = np.cumsum(c_sorted, dtype=np.int64)
    # The last index of each run of equal scores: ties are accepted all at once.
    last = np.flatnonzero(np.r_[s_sorted[1:] != s_sorted[:-1], True])
    tp = np.r_[0, tp_cum[last]].astype(np.int64)
    acc = np.r_[0, last + 1].astype(np.int64)
    precision = np.where(acc > 0, tp / np.maximum(acc, 1), 1.0)
    return PRCurve(
        precision=precision,
        recall=tp / n_truth,
        thresholds=np.r_[np.inf, s_sorted[last]],
        true_positives=tp,
        accepted=acc,
        n_with_truth=n_truth,
    )


def pr_auc(curve: PRCurve) -> float:
    """Area under the PR curve by the trapezoid rule in recall, from the (0, 1) start point.

    This is the paper's "AUC of the PR curve". It differs from sklearn's average precision,
    a step sum. A curve that never reaches recall 1 has no area beyond its largest recall.
    """
    r, p = curve.recall, curve.precision
    return float(np.sum(np.diff(r) * (p[1:] + p[:-1]) / 2.0))


def precision_at_full_recall(curve: PRCurve) -> float:
    """Best precision among the points that reach 100% recall; 0.0 if none does.

    100% recall needs every query with truth accepted *and* correct, so this is 0 whenever
    some such query's best match is wrong -- a strict reading, reported as such.
    """
    full = curve.true_positives == curve.n_with_truth
    return float(curve.precision[full].max()) if full.any() else 0.0


def recall_at_full_precision(curve: PRCurve) -> float:
    """Largest recall at a point with no false positive (precision exactly 1.0); 0.0 if none."""
    perfect = curve.true_positives == curve.accepted
    return float(curve.recall[perfect].max())  # the start point (0 accepted) is always perfect


def _truth_denominator(gt: GroundTruth) -> tuple[np.ndarray, int]:
    has = gt.has_truth
    n = int(has.sum())
    if n == 0:
        raise LoopClosureInputError("ground truth: no query has a true match, so recall is undefined")
    return has, n


def recall_at_n(
    candidate_lists: object,
    gt: GroundTruth,
    tolerance: int,
    ns: Iterable[int] | None = None,
) -> dict[int, float]:
    """Fraction of queries with truth that have a correct reference among their top n.

    candidate_lists: (n_query, N) reference indices, best first; -1 pads short lists.
    ns defaults to (1, 5, 10, N) restricted to n <= N; an n above N is refused because the
    lists cannot say what lies beyond rank N.
    """
    cands = np.asarray(candidate_lists)
    if cands.ndim != 2 or cands.shape[0] != gt.n_query or cands.shape[1] == 0:
        raise LoopClosureInputError(f"candidate_lists: expected shape ({gt.n_query}, N) with N >= 1, got {cands.shape}")
    big_n = cands.shape[1]
    wanted = sorted({n for n in (1, 5, 10, big_n) if n <= big_n} if ns is None else set(ns))
    for n in wanted:
        if isinstance(n, bool) or int(n) != n or not 1 <= n <= big_n:
            raise LoopClosureInputError(f"ns: {n!r} must be an integer in 1..{big_n} (the list length)")
    has, n_truth = _truth_denominator(gt)
    # hit_rank[q] = first rank with a correct reference (big_n if none).
    ok = correct_mask(gt, cands, tolerance)
    hit_rank = np.where(ok.any(axis=1), ok.argmax(axis=1), big_n)[has]
    return {int(n): float(np.count_nonzero(hit_rank < n) / n_truth) for n in wanted}


def top1_accuracy(matches: object, gt: GroundTruth, tolerance: int) -> float:
    """Fraction of queries with truth whose single match is correct (= recall@1, no threshold)."""
    m = np.asarray(matches)
    if m.ndim != 1:
        raise LoopClosureInputError(f"matches: expected shape ({gt.n_query},), got {m.shape}")
    has, n_truth = _truth_denominator(gt)
    return float(np.count_nonzero(correct_mask(gt, m, tolerance)[has]) / n_truth)


def summarize(
    scores: object,
    matches: object,
    gt: GroundTruth,
    tolerance: int,
    candidate_lists: object | None = None,
    ns: Sequence[int] | None = None,
) -> dict[str, object]:
    """All headline numbers for one run as plain Python types, ready for ``json.dump``.

    recall@N keys are strings ("1", "5", ...) so the dict survives a JSON round trip unchanged.
    """
    m = np.asarray(matches)
    correct = correct_mask(gt, m, tolerance) if m.ndim == 1 else None
    if correct is None:
        raise LoopClosureInputError(f"matches: expected shape ({gt.n_query},), got {m.shape}")
    curve = precision_recall_curve(scores, correct, gt.has_truth)
    out: dict[str, object] = {
        "n_query": gt.n_query,
        "n_ref": gt.n_ref,
        "n_with_truth": curve.n_with_truth,
        "tolerance": int(tolerance),
        "top1_accuracy": top1_accuracy(m, gt, tolerance),
        "pr_auc": pr_auc(curve),
        "precision_at_full_recall": precision_at_full_recall(curve),
        "recall_at_full_precision": recall_at_full_precision(curve),
    }
    if candidate_lists is not None:
        rec = recall_at_n(candidate_lists, gt, tolerance, ns)
        out["recall_at_n"] = {str(n): v for n, v in rec.items()}
    return out
