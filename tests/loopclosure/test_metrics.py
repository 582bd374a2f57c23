"""PR curve, AUC and recall@N on cases small enough to compute by hand."""

from __future__ import annotations

import json

import numpy as np
import pytest
from sklearn import metrics as skm

from loopclosure.benchmark_truth import GroundTruth
from loopclosure.errors import LoopClosureInputError
from loopclosure.metrics import (
    pr_auc,
    precision_at_full_recall,
    precision_recall_curve,
    recall_at_full_precision,
    recall_at_n,
    summarize,
    top1_accuracy,
)

T, F = True, False


def test_perfect_ranking() -> None:
    c = precision_recall_curve([3.0, 2.0, 1.0], [T, T, T], [T, T, T])
    assert c.precision.tolist() == [1, 1, 1, 1]
    np.testing.assert_allclose(c.recall, [0, 1 / 3, 2 / 3, 1])
    assert c.thresholds.tolist() == [np.inf, 3, 2, 1]
    assert pr_auc(c) == pytest.approx(1.0)
    assert precision_at_full_recall(c) == 1.0
    assert recall_at_full_precision(c) == 1.0


def test_all_wrong() -> None:
    c = precision_recall_curve([3.0, 2.0, 1.0], [F, F, F], [T, T, T])
    assert c.precision.tolist() == [1, 0, 0, 0]
    assert c.recall.tolist() == [0, 0, 0, 0]
    assert pr_auc(c) == 0.0
    assert precision_at_full_recall(c) == 0.0
    assert recall_at_full_precision(c) == 0.0


def test_ties_enter_together_and_order_does_not_matter() -> None:
    scores = [0.9, 0.5, 0.5, 0.1]
    c = precision_recall_curve(scores, [T, T, F, T], [T, T, T, T])
    assert c.accepted.tolist() == [0, 1, 3, 4]
    assert c.true_positives.tolist() == [0, 1, 2, 3]
    np.testing.assert_allclose(c.precision, [1, 1, 2 / 3, 3 / 4])
    np.testing.assert_allclose(c.recall, [0, 0.25, 0.5, 0.75])
    auc = 0.25 * (1 + 1) / 2 + 0.25 * (1 + 2 / 3) / 2 + 0.25 * (2 / 3 + 3 / 4) / 2
    assert pr_auc(c) == pytest.approx(auc)
    # The wrong match tied with a right one is swapped in the input: same curve.
    c2 = precision_recall_curve([0.5, 0.1, 0.9, 0.5], [F, T, T, T], [T, T, T, T])
    np.testing.assert_array_equal(c.precision, c2.precision)
    np.testing.assert_array_equal(c.recall, c2.recall)
    assert precision_at_full_recall(c) == 0.0  # one query's best match is wrong
    assert recall_at_full_precision(c) == 0.25


def test_queries_without_truth() -> None:
    # Query 1 has no true match: accepting it is a false positive; it never adds recall.
    c = precision_recall_curve([0.9, 0.8, 0.7, 0.6], [T, F, T, F], [T, F, T, T])
    assert c.n_with_truth == 3
    np.testing.assert_allclose(c.precision, [1, 1, 1 / 2, 2 / 3, 1 / 2])
    np.testing.assert_allclose(c.recall, [0, 1 / 3, 1 / 3, 2 / 3, 2 / 3])
    assert pr_auc(c) == pytest.approx(1 / 3 + (1 / 3) * (1 / 2 + 2 / 3) / 2)
    assert recall_at_full_precision(c) == pytest.approx(1 / 3)
    assert precision_at_full_recall(c) == 0.0


def test_low_scored_query_without_truth_keeps_full_precision() -> None:
    c = precision_recall_curve([0.9, 0.8, 0.1], [T, T, F], [T, T, F])
    np.testing.assert_allclose(c.precision, [1, 1, 1, 2 / 3])
    np.testing.assert_allclose(c.recall, [0, 0.5, 1, 1])
    assert precision_at_full_recall(c) == 1.0
    assert recall_at_full_precision(c) == 1.0
    assert pr_auc(c) == pytest.approx(1.0)


def test_infinite_scores_are_thresholds_too() -> None:
    c = precision_recall_curve([np.inf, -np.inf], [T, F], [T, T])
    assert c.thresholds.tolist() == [np.inf, np.inf, -np.inf]
    assert c.accepted.tolist() == [0, 1, 2]


@pytest.mark.parametrize(
    ("scores", "correct", "truth", "pattern"),
    [
        ([1.0, np.nan], [T, F], [T, T], "NaN"),
        ([1.0, 2.0], [T, T], [T, F], "query 1 is marked correct but has no true match"),
        ([1.0, 2.0], [F, F], [F, F], "no query has a true match"),
        ([1.0, 2.0], [T], [T, T], "correct: expected 2 entries"),
        ([[1.0, 2.0]], [T], [T], "scores: expected a 1-D array"),
    ],
)
def test_curve_bad_input(scores: list, correct: list, truth: list, pattern: str) -> None:
    with pytest.raises(LoopClosureInputError, match=pattern):
        precision_recall_curve(scores, correct, truth)


def test_agrees_with_sklearn_when_every_query_has_truth() -> None:
    rng = np.random.default_rng(1)
    for _ in range(20):
        n = int(rng.integers(5, 60))
        scores = np.round(rng.random(n), 1)  # coarse scores: plenty of ties
        correct = rng.random(n) < 0.6
        correct[0] = True
        ours = precision_recall_curve(scores, correct, np.ones(n, bool))
        sk_p, sk_r, sk_t = skm.precision_recall_curve(correct, scores)
        # sklearn: increasing thresholds, plus a final (recall 0, precision 1) point.
        assert sorted(sk_t.tolist()) == sorted(ours.thresholds[1:].tolist())
        idx = {t: i for i, t in enumerate(ours.thresholds)}
        for p, r, t in zip(sk_p[:-1], sk_r[:-1], sk_t):
            i = idx[t]
            assert ours.precision[i] == pytest.approx(p)
            # sklearn's recall counts correct matches; ours counts queries with truth.
            assert ours.recall[i] == pytest.approx(r * correct.sum() / n)
        assert (sk_p[-1], sk_r[-1]) == (ours.precision[0], ours.recall[0]) == (1.0, 0.0)
        assert pr_auc(ours) == pytest.approx(skm.auc(ours.recall, ours.precision))


# --------------------------------------------------------------------------- recall@N


def _gt() -> GroundTruth:
    return GroundTruth.from_sets([[0], [1], [2], []], n_ref=10)


def test_recall_at_n_hand_case() -> None:
    cands = np.array([[5, 0, 1], [1, 7, 8], [9, 9, 2], [3, 3, 3]])
    assert recall_at_n(cands, _gt(), 0) == {1: pytest.approx(1 / 3), 3: 1.0}
    assert recall_at_n(cands, _gt(), 0, ns=[2, 1]) == {1: pytest.approx(1 / 3), 2: pytest.approx(2 / 3)}
    # ±5 makes 5 a correct first candidate for query 0 (true reference 0).
    assert recall_at_n(cands, _gt(), 5, ns=[1]) == {1: pytest.approx(2 / 3)}


def test_recall_at_n_default_ns_and_padding() -> None:
    cands = np.full((4, 12), -1)
    cands[0, 0], cands[1, 6], cands[2, 11] = 0, 1, 2
    assert recall_at_n(cands, _gt(), 0) == {
        1: pytest.approx(1 / 3),
        5: pytest.approx(1 / 3),
        10: pytest.approx(2 / 3),
        12: 1.0,
    }


def test_recall_at_n_bad_input() -> None:
    cands = np.zeros((4, 3), dtype=int)
    with pytest.raises(LoopClosureInputError, match=r"ns: 5 must be an integer in 1\.\.3"):
        recall_at_n(cands, _gt(), 0, ns=[5])
    with pytest.raises(LoopClosureInputError, match="candidate_lists: expected shape"):
        recall_at_n(cands[:2], _gt(), 0)
    with pytest.raises(LoopClosureInputError, match="no query has a true match"):
        recall_at_n(cands, GroundTruth.from_sets([[]] * 4, n_ref=10), 0)


def test_top1_accuracy() -> None:
    assert top1_accuracy(np.array([0, 3, 2, 5]), _gt(), 0) == pytest.approx(2 / 3)
    assert top1_accuracy(np.array([0, 3, 2, 5]), _gt(), 2) == 1.0


def test_summarize_is_json_ready() -> None:
    cands = np.array([[0, 1], [3, 1], [2, 0], [4, 4]])
    out = summarize([0.9, 0.5, 0.8, 0.7], cands[:, 0], _gt(), 0, candidate_lists=cands)
    assert json.loads(json.dumps(out)) == out
    assert out["n_with_truth"] == 3
    assert out["top1_accuracy"] == pytest.approx(2 / 3)
    assert out["recall_at_n"] == {"1": pytest.approx(2 / 3), "2": 1.0}
    # Sorted by score: q0 ok, q2 ok, q3 (no truth) wrong, q1 wrong.
    assert out["recall_at_full_precision"] == pytest.approx(2 / 3)
    assert out["pr_auc"] == pytest.approx(2 / 3)
