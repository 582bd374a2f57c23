"""The calibrated loop decision on synthetic score streams: the same decisions whatever the
stream's level and scale of stage-II scores, which absolute thresholds cannot give; the runner-up
model, runner-ups away from the winner and from joined places, and place links."""

from __future__ import annotations

import numpy as np
import pytest

from loopclosure.calibration import CalibratedDecision, PlaceLinks, RunnerUpModel, decide_stream, runner_up
from loopclosure.config import CalibratedDecisionConfig, SequenceMatchConfig
from loopclosure.errors import LoopClosureInputError
from loopclosure.sequence_matcher import SequenceMatch

SEQUENCE = SequenceMatchConfig(length=8, direction="forward", sequence_candidates=20)
CALIBRATED = CalibratedDecisionConfig()


def world(seed: int = 0, n: int = 260) -> tuple[np.ndarray, list[np.ndarray], np.ndarray, dict[int, int]]:
    """A stream of n keyframes whose place database is its own past: background scores with a
    per-keyframe level (texture), queries 150.. revisiting places 30.. on a forward line, and a
    short alias (queries 90..92 look like places 40..42 as much as a revisit looks like its
    place in a single frame, but only for three keyframes). Stage I keeps each query's 50 best
    places before the exclusion window (30 keyframes)."""
    rng = np.random.default_rng(seed)
    level = rng.uniform(0.05, 0.2, n)[:, None]
    s = (level + rng.gamma(2.0, 0.03, (n, n))).astype(np.float32)
    truth = {}
    for k, q in enumerate(range(150, n)):
        s[q, 30 + k] += 0.25 + rng.normal(0.0, 0.04)
        truth[q] = 30 + k
    for k, q in enumerate(range(90, 93)):
        s[q, 40 + k] += 0.25
    limits = np.maximum(0, np.arange(n) - 30)
    candidates = [np.sort(np.argsort(-s[q, : limits[q]], kind="stable")[:50]) for q in range(n)]
    return s, candidates, limits, truth


def accepted(decisions: list[tuple[SequenceMatch, object]]) -> dict[int, int]:
    return {q: m.place for q, (m, v) in enumerate(decisions) if v is not None and v.accepted}  # type: ignore[attr-defined]


@pytest.mark.parametrize("scale, shift", [(0.3, 0.05), (2.5, -0.2), (1.0, 0.4)])
def test_a_shifted_and_scaled_stream_gets_the_same_decisions(scale: float, shift: float) -> None:
    s, candidates, limits, truth = world()
    base = decide_stream(s, candidates, limits, SEQUENCE, CALIBRATED)
    moved = decide_stream((scale * s + shift).astype(np.float32), candidates, limits, SEQUENCE, CALIBRATED)
    assert accepted(base) == accepted(moved)
    for (_, a), (_, b) in zip(base, moved):
        assert (a is None) == (b is None)
        if a is not None and b is not None:
            assert b.z == pytest.approx(a.z, rel=1e-4, abs=1e-4)
    # and the decisions are good ones: every accepted loop right, most of the revisit found
    loops = accepted(base)
    assert loops and all(abs(p - truth.get(q, -99)) <= 2 for q, p in loops.items())
    assert len(loops) >= 0.8 * len(truth)


def test_an_absolute_threshold_does_not_transfer_between_such_streams() -> None:
    # the same stream at a third of the scale: a raw sequence threshold that found the revisit
    # in one finds nothing in the other (the failure the calibrated decision removes)
    s, candidates, limits, truth = world()
    raw = SequenceMatchConfig(length=8, direction="forward", sequence_candidates=20)
    from loopclosure.sequence_matcher import match_sequences

    def found(scores: np.ndarray) -> int:
        return sum(m.place is not None and m.score >= 0.3 for m in match_sequences(scores, raw, candidates, limits))

    assert found(s) >= 0.8 * len(truth)
    assert found(s / 3) == 0


def test_nothing_is_accepted_in_a_stream_without_revisits() -> None:
    s, candidates, limits, _ = world(seed=3)
    rng = np.random.default_rng(5)
    s[150:] = (rng.uniform(0.05, 0.2, (len(s) - 150, 1)) + rng.gamma(2.0, 0.03, (len(s) - 150, len(s)))).astype(
        np.float32
    )
    assert accepted(decide_stream(s, candidates, limits, SEQUENCE, CALIBRATED)) == {}


def test_the_model_warms_up_then_scores_in_interquartile_ranges() -> None:
    model = RunnerUpModel(CalibratedDecisionConfig(min_history=10, history=20))
    for v in range(9):
        model.observe(float(v))
    assert not model.ready and model.score(100.0) is None
    model.observe(9.0)  # 0..9: median 4.5, quartiles 2.25 and 6.75
    assert model.ready and model.score(9.0) == pytest.approx((9.0 - 4.5) / 4.5)
    for v in range(10, 40):  # only the newest 20 are kept
        model.observe(float(v))
    assert len(model) == 20 and model.score(29.5) == pytest.approx(0.0)
    with pytest.raises(ValueError, match="finite"):
        model.observe(float("nan"))


def test_a_flat_stream_still_orders_winners_above_its_level() -> None:
    model = RunnerUpModel(CalibratedDecisionConfig(min_history=5))
    for _ in range(5):
        model.observe(0.2)
    assert model.score(0.3) > 1e3 and model.score(0.2) == 0.0 and model.score(0.1) < -1e3  # type: ignore[operator]


def match(places: list[int], scores: list[float], place: int) -> SequenceMatch:
    return SequenceMatch(place, max(scores), "forward", 1.0, max(scores), 8,
                         np.array(places), np.array(scores, np.float64))  # fmt: skip


def test_the_runner_up_is_neither_a_neighbour_of_the_winner_nor_a_place_joined_to_it() -> None:
    m = match([10, 11, 13, 14, 30, 31, 50], [0.9, 0.8, 0.7, 0.6, 0.5, 0.45, 0.2], 10)
    assert runner_up(m, window=3) == 0.6  # 14 is the first place more than 3 from 10
    assert runner_up(m, window=4) == 0.5
    assert runner_up(m, window=3, joined={14}) == 0.5  # 14 is the same place as 10 (an accepted loop)
    assert runner_up(m, window=3, joined={14, 31}) == 0.2
    assert runner_up(match([10, 11], [0.9, 0.8], 10), window=3) is None


def test_a_third_visit_is_judged_against_other_places_not_the_first_visit() -> None:
    # the winner (a place of the second visit) and the first visit score alike: without the
    # link the lead is nothing, with it the lead is over the other places
    decision = CalibratedDecision(CalibratedDecisionConfig(min_history=5, propose=-100), accept=6.0)
    for v in (0.10, 0.12, 0.11, 0.09, 0.10, 0.13):
        decision.model.observe(v)
    third = match([120, 121, 20, 21, 60], [0.60, 0.55, 0.59, 0.50, 0.12], 120)
    unlinked = decision.decide(third)
    linked = decision.decide(third, joined={20})
    assert unlinked is not None and linked is not None
    assert unlinked.runner_up == 0.59 and linked.runner_up == 0.12
    assert linked.accepted


def test_place_links_join_transitively_and_come_back_from_their_state() -> None:
    links = PlaceLinks()
    links.join(120, 20)
    links.join(220, 121)
    links.join(221, 120)
    assert links.joined(20) == {120, 221} and links.joined(121) == {220} and links.joined(5) == set()
    again = PlaceLinks()
    arrays = links.state_arrays()
    PlaceLinks.check_state_arrays(arrays, 300)
    again.load_state_arrays(arrays)
    assert again.joined(221) == {20, 120} and again.pairs == links.pairs
    with pytest.raises(LoopClosureInputError, match="place_links"):
        PlaceLinks.check_state_arrays(arrays, 200)
    with pytest.raises(LoopClosureInputError, match="place_links"):
        PlaceLinks.check_state_arrays({"place_links": np.zeros(3)}, 300)


def test_config_refuses_a_propose_level_above_accept() -> None:
    with pytest.raises(ValueError, match="propose"):
        CalibratedDecisionConfig(accept=2.0, propose=3.0)
