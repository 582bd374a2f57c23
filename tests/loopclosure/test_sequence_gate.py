"""The sequence prior as a gate: query i -> place j passes only when the recognitions of
i-1 .. i-(L-1) lie within ±tol of j-1 .. j-(L-1) (forward) or j+1 .. j+(L-1) (reverse).

Everything is in place-index space: `observe(query, match)` records what keyframe `query`
recognised, `decide(query, match)` judges the next closure before it is observed.
"""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from loopclosure.config import SequenceGateConfig
from loopclosure.sequence_gate import SequenceGate


def gate(length: int = 3, tolerance: int = 2, allow_reverse: bool = True) -> SequenceGate:
    return SequenceGate(SequenceGateConfig(length=length, tolerance=tolerance, allow_reverse=allow_reverse))


def observed(g: SequenceGate, *pairs: tuple[int, int | None]) -> SequenceGate:
    for query, match in pairs:
        g.observe(query, match)
    return g


def test_forward_revisit_is_accepted() -> None:
    g = observed(gate(), (98, 48), (99, 49))
    decision = g.decide(100, 50)
    assert decision.accepted and decision.direction == "forward"
    assert "forward" in decision.reason


def test_forward_revisit_with_jitter_within_tolerance_is_accepted() -> None:
    # the predecessors recognised places 2 before / 1 after where a perfect match would be
    g = observed(gate(tolerance=2), (98, 46), (99, 50))
    assert g.decide(100, 50).accepted


def test_reverse_revisit_accepted_only_when_allowed() -> None:
    pairs = ((98, 52), (99, 51))  # driven the other way: i-k matched j+k
    allowed = observed(gate(tolerance=1, allow_reverse=True), *pairs).decide(100, 50)
    assert allowed.accepted and allowed.direction == "reverse"
    refused = observed(gate(tolerance=1, allow_reverse=False), *pairs).decide(100, 50)
    assert not refused.accepted and refused.direction is None
    assert refused.reason == "keyframe 99 matched 51, expected 49±1"
    assert " or " not in refused.reason  # no reverse alternative offered when it is off


def test_broken_sequence_rejected_naming_the_keyframe() -> None:
    # i-1 agrees, but i-2 matched a place far away: a lucky single-frame alias
    g = observed(gate(), (98, 300), (99, 49))
    decision = g.decide(100, 50)
    assert not decision.accepted and decision.direction is None
    assert "keyframe 98 matched 300" in decision.reason
    assert "48±2" in decision.reason and "52±2" in decision.reason  # forward and reverse expectations


def test_mixed_directions_rejected() -> None:
    # i-1 fits only forward (49), i-2 fits only reverse (52): neither direction as a whole
    decision = observed(gate(tolerance=1), (98, 52), (99, 49)).decide(100, 50)
    assert not decision.accepted
    assert "keyframe 98" in decision.reason


def test_predecessor_that_recognised_nothing_rejects() -> None:
    g = observed(gate(), (98, 48), (99, None))
    decision = g.decide(100, 50)
    assert not decision.accepted
    assert decision.reason == "keyframe 99 recognised nothing"


def test_predecessor_never_observed_rejects() -> None:
    g = observed(gate(), (99, 49))  # 98 was never observed
    decision = g.decide(100, 50)
    assert not decision.accepted
    assert decision.reason == "keyframe 98 not seen"


def test_empty_history_rejects_first_keyframe() -> None:
    decision = gate().decide(0, 0)
    assert not decision.accepted and "not seen" in decision.reason


def test_old_observations_fall_out_of_the_window() -> None:
    # a recognition at 97 is irrelevant to query 100 with L=3, and a gap at 98 is not papered over
    g = observed(gate(), (97, 47), (99, 49))
    assert g.decide(100, 50).reason == "keyframe 98 not seen"
    # the history only holds L-1 entries: a later query sees newer observations only
    g = observed(gate(), (98, 48), (99, 49), (100, 50), (101, 51))
    assert g.decide(102, 52).accepted
    assert g.decide(100, 50).reason == "keyframe 99 not seen"  # 98 and 99 dropped from the window


def test_place_zero_is_a_real_match_not_nothing() -> None:
    # match index 0 must not be mistaken for "recognised nothing"
    g = observed(gate(), (10, 0), (11, 1))
    assert g.decide(12, 2).accepted


@pytest.mark.parametrize("tolerance", [0, 1, 2, 3])
def test_tolerance_boundary(tolerance: int) -> None:
    expected_98, expected_99 = 48, 49
    for delta, accepted in ((tolerance, True), (-tolerance, True), (tolerance + 1, False), (-tolerance - 1, False)):
        g = observed(gate(tolerance=tolerance, allow_reverse=False), (98, expected_98 + delta), (99, expected_99))
        decision = g.decide(100, 50)
        assert decision.accepted is accepted, (tolerance, delta, decision.reason)
        if not accepted:
            assert f"keyframe 98 matched {expected_98 + delta}, expected 48±{tolerance}" == decision.reason


@pytest.mark.parametrize("allow_reverse", [True, False])
def test_length_one_always_accepts(allow_reverse: bool) -> None:
    g = gate(length=1, allow_reverse=allow_reverse)
    assert g.decide(5, 123).accepted
    g.observe(5, None)
    g.observe(6, 999)
    decision = g.decide(7, 3)
    assert decision.accepted and decision.direction == "forward"


def test_reset_forgets_history() -> None:
    g = observed(gate(), (98, 48), (99, 49))
    g.reset()
    assert not g.decide(100, 50).accepted


@settings(max_examples=200, deadline=None)
@given(
    length=st.integers(2, 6),
    tolerance=st.integers(0, 3),
    query=st.integers(10, 10_000),
    match=st.integers(0, 5_000),
    data=st.data(),
)
def test_consistent_forward_sequences_are_accepted(length, tolerance, query, match, data) -> None:  # noqa: ANN001
    g = gate(length=length, tolerance=tolerance)
    jitter = data.draw(st.lists(st.integers(-tolerance, tolerance), min_size=length - 1, max_size=length - 1))
    for k in range(length - 1, 0, -1):  # oldest first, as a stream arrives
        g.observe(query - k, match - k + jitter[k - 1])
    decision = g.decide(query, match)
    assert decision.accepted, decision.reason
    assert decision.direction == "forward"


@settings(max_examples=200, deadline=None)
@given(
    length=st.integers(2, 6),
    tolerance=st.integers(0, 3),
    match=st.integers(0, 5_000),
    data=st.data(),
)
def test_one_predecessor_beyond_tolerance_is_rejected(length, tolerance, match, data) -> None:  # noqa: ANN001
    g = gate(length=length, tolerance=tolerance, allow_reverse=False)
    query = 10_000
    bad_k = data.draw(st.integers(1, length - 1))
    off = data.draw(st.integers(tolerance + 1, tolerance + 50)) * data.draw(st.sampled_from([-1, 1]))
    for k in range(length - 1, 0, -1):
        g.observe(query - k, match - k + (off if k == bad_k else 0))
    decision = g.decide(query, match)
    assert not decision.accepted
    assert f"keyframe {query - bad_k} matched {match - bad_k + off}" in decision.reason
