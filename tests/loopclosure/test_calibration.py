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


def test_the_model_warms_up_then_scores_in_its_spread() -> None:
    model = RunnerUpModel(CalibratedDecisionConfig(min_history=10, history=20, prior_runner_ups=20))
    for v in range(9):
        model.observe(float(v))
    assert not model.ready and model.score(100.0) is None
    model.observe(9.0)  # 0..9: median 4.5; interquartile range 4.5, twice the median deviation 5: the smaller
    assert model.ready and model.score(9.0) == pytest.approx((9.0 - 4.5) / 4.5)
    for v in range(10, 40):  # only the newest 20 are kept
        model.observe(float(v))
    assert len(model) == 20 and model.score(29.5) == pytest.approx(0.0)
    with pytest.raises(ValueError, match="finite"):
        model.observe(float("nan"))


def test_the_spread_holds_while_nearly_half_the_runner_ups_are_off() -> None:
    # a young model: 12 runner-ups of a train standing at a station (the same place again, as good
    # as the winner) among 16 ordinary ones; the interquartile range would take the stations' level
    model = RunnerUpModel(CalibratedDecisionConfig(min_history=5, prior_runner_ups=0))
    ordinary = np.linspace(0.0, 0.02, 16)
    for v in [*ordinary, *np.full(12, 0.15)]:
        model.observe(float(v))
    median, spread = model.level()  # type: ignore[misc]
    values = np.r_[ordinary, np.full(12, 0.15)]
    q1, q3 = np.percentile(values, [25.0, 75.0])
    assert spread < 0.25 * (q3 - q1)
    assert model.score(0.25) > 6.0  # a right match standing clear of the ordinary runner-ups
    assert (0.25 - median) / (q3 - q1) < 2.0  # which the interquartile range would not see


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
    decision = CalibratedDecision(CalibratedDecisionConfig(min_history=5, propose=-100, prior_runner_ups=0), accept=6.0)
    for v in (0.10, 0.12, 0.11, 0.09, 0.10, 0.13):
        decision.model.observe(v)
    third = match([120, 121, 20, 21, 60], [0.60, 0.55, 0.59, 0.50, 0.12], 120)
    field = np.linspace(0.0, 0.2, 30)  # a field of 30 places; without fields seen the prior is silent
    unlinked = decision.decide(third, field)
    linked = decision.decide(third, field, joined={20})
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


def test_the_prior_judges_the_first_keyframes_in_field_spreads_and_fades_as_runner_ups_arrive() -> None:
    config = CalibratedDecisionConfig(min_history=5, prior_median=0.8, prior_spread=1.0, prior_runner_ups=40)
    model = RunnerUpModel(config)
    assert not model.ready  # neither runner-ups nor a field yet
    model.observe_field(np.array([0.0, 0.1, 0.2, 0.3, 0.4]))  # interquartile range 0.2
    assert model.ready and model.score(0.16 + 6 * 0.2) == pytest.approx(6.0)  # median 0.8 * 0.2, spread 0.2
    for _ in range(40):  # up to prior_runner_ups runner-ups its bounds hold in full
        model.observe(0.0)
    assert model.level() == pytest.approx((0.16, 0.2))  # the stream's own are lower
    model.observe(0.0)
    for _ in range(39):  # twice as many: they weigh a half
        model.observe(0.0)
    assert model.level() == pytest.approx((0.08, 0.1))
    for v in np.linspace(0.5, 1.0, 220):  # a grown model: the prior weighs 40 / 300 and bounds nothing
        model.observe(float(v))
    values = np.r_[np.zeros(80), np.linspace(0.5, 1.0, 220)]
    median = np.median(values)
    own = (median, min(np.subtract(*np.percentile(values, [75.0, 25.0])), 2 * np.median(np.abs(values - median))))
    assert model.level() == pytest.approx(own)


def test_the_prior_bounds_a_noisy_young_model_from_below() -> None:
    # five runner-ups that happen to agree: alone they would call anything a loop
    config = CalibratedDecisionConfig(min_history=5, prior_median=0.8, prior_spread=1.0, prior_runner_ups=40)
    model = RunnerUpModel(config)
    model.observe_field(np.linspace(0.0, 0.4, 21))  # spread 0.2
    for v in (0.010, 0.011, 0.010, 0.012, 0.011):
        model.observe(v)
    median, spread = model.level()  # type: ignore[misc]
    assert spread == pytest.approx(0.2) and median == pytest.approx(0.8 * 0.2)  # the prior in full
    assert model.score(0.3) < 6.0  # a lead of 0.3 is not a loop against a field this wide


def test_a_keyframe_with_a_small_field_decides_nothing_but_its_runner_up_counts() -> None:
    decision = CalibratedDecision(CalibratedDecisionConfig(min_field=10, propose=-100), accept=6.0)
    winner = match([1, 2, 8], [0.9, 0.2, 0.1], 1)
    assert decision.decide(winner, np.linspace(0.0, 0.2, 3)) is None  # 3 places: no decision
    assert len(decision.model) == 1 and not decision.model.ready  # the runner-up joined, no field did
    verdict = decision.decide(winner, np.linspace(0.0, 0.2, 10))
    assert verdict is not None and verdict.accepted  # the prior alone: 0.9 is far above a field of 0.2


def test_a_state_saved_before_the_prior_resumes_with_the_runner_ups_alone() -> None:
    model = RunnerUpModel(CalibratedDecisionConfig())
    model.observe_field(np.linspace(0.0, 0.4, 21))
    model.observe(0.1)
    state = model.state_arrays("model_")
    assert set(state) == {"model_runner_ups", "model_field_spreads"}
    old = {"model_runner_ups": state["model_runner_ups"]}
    RunnerUpModel.check_state_arrays(old, "model_")
    resumed = RunnerUpModel(CalibratedDecisionConfig())
    resumed.load_state_arrays(old, "model_")
    assert len(resumed) == 1 and not resumed.ready
    again = RunnerUpModel(CalibratedDecisionConfig())
    again.load_state_arrays(state, "model_")
    assert again.level() == model.level()
    with pytest.raises(LoopClosureInputError, match="field_spreads"):
        RunnerUpModel.check_state_arrays({**state, "model_field_spreads": np.array([np.nan])}, "model_")
