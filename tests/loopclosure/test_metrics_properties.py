"""Properties of the PR curve that must hold for any scores and any correctness pattern."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from loopclosure.metrics import (
    pr_auc,
    precision_at_full_recall,
    precision_recall_curve,
    recall_at_full_precision,
)


@st.composite
def runs(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    n = draw(st.integers(1, 40))
    # Few distinct values so ties are common; sometimes continuous scores.
    value = st.integers(0, 4).map(float) if draw(st.booleans()) else st.floats(-1e3, 1e3)
    scores = np.array(draw(st.lists(value, min_size=n, max_size=n)))
    truth = np.array(draw(st.lists(st.booleans(), min_size=n, max_size=n)))
    truth[draw(st.integers(0, n - 1))] = True
    correct = np.array(draw(st.lists(st.booleans(), min_size=n, max_size=n))) & truth
    return scores, correct, truth


@settings(max_examples=200, deadline=None)
@given(runs())
def test_curve_invariants(run: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
    scores, correct, truth = run
    c = precision_recall_curve(scores, correct, truth)
    assert np.all((c.precision >= 0) & (c.precision <= 1))
    assert np.all((c.recall >= 0) & (c.recall <= 1))
    assert np.all(np.diff(c.recall) >= 0)  # threshold decreasing -> recall never drops
    assert np.all(np.diff(c.thresholds) < 0)  # one point per distinct score
    assert (c.precision[0], c.recall[0]) == (1.0, 0.0)
    assert c.accepted[-1] == scores.size
    assert c.recall[-1] == correct.sum() / truth.sum()
    assert 0.0 <= pr_auc(c) <= 1.0 + 1e-12
    assert 0.0 <= precision_at_full_recall(c) <= 1.0
    assert 0.0 <= recall_at_full_precision(c) <= c.recall[-1]


@settings(max_examples=100, deadline=None)
@given(runs(), st.randoms(use_true_random=False))
def test_curve_ignores_input_order(run: tuple[np.ndarray, ...], rnd: object) -> None:
    scores, correct, truth = run
    perm = np.arange(scores.size)
    rnd.shuffle(perm)  # type: ignore[attr-defined]
    a = precision_recall_curve(scores, correct, truth)
    b = precision_recall_curve(scores[perm], correct[perm], truth[perm])
    np.testing.assert_array_equal(a.precision, b.precision)
    np.testing.assert_array_equal(a.recall, b.recall)


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-10, 10), min_size=1, max_size=30))
def test_all_correct_gives_unit_auc(scores: list[float]) -> None:
    n = len(scores)
    c = precision_recall_curve(scores, np.ones(n, bool), np.ones(n, bool))
    assert abs(pr_auc(c) - 1.0) < 1e-12
    assert precision_at_full_recall(c) == recall_at_full_precision(c) == 1.0
